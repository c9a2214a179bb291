"""Windowed bundle adjustment: camera poses and landmark positions that agree with every ray seen.

The front end (``vision/vslam.py``) solves each frame's pose against landmarks whose positions were
fixed by two or a few views; a monocular run's scale then drifts, because each new landmark inherits
the scale error of the poses that triangulated it. Adjusting the last few keyframes' poses and the
landmarks they see together, against all their observations, ties new landmarks to old ones and
removes most of that drift (the scale of the window is held by its oldest poses, which stay fixed).

Residual of observation ``o`` (landmark ``j`` seen in frame ``k`` along the unit ray ``n``): the
direction to the landmark, ``x = (R_k X_j + t_k) / |R_k X_j + t_k|``, projected onto two axes
orthogonal to ``n``, times the focal length: an angular error in pixels, valid for any camera model
(the front end works with rays, not pixels). Loss: Huber with its knee at 1.345 sigma (95 %
efficiency at Gaussian noise), sigma the tracking noise in pixels. Solved by Levenberg-Marquardt
with an analytic Jacobian and the points eliminated by the Schur complement (each residual depends
on one pose and one point). scipy.optimize.least_squares (trf, sparse Jacobian, lsmr) was tried
first: 250-600 ms per window of 5-7 poses and 200 points, and its robust-loss rescaling crept
from a drifted start; this solver takes a few ms.

Pure computation: arrays in, arrays out.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

HUBER_K = 1.345  # Huber's constant for 95 % asymptotic efficiency at Gaussian noise, in units of sigma


@dataclass
class BundleResult:
    poses_cw: np.ndarray  # (K, 4, 4) camera-from-world after adjustment
    points: np.ndarray  # (M, 3) world
    residual_px: np.ndarray  # (O,) angular residual of each observation, px at the focal length
    behind: np.ndarray  # (O,) observation whose landmark ends up behind the camera
    cost_before: float
    cost_after: float
    evaluations: int


def _so3_series(w: np.ndarray, a, b, small_angle: float) -> np.ndarray:
    """I + a(th) [w]x + b(th) [w]x^2 for rotation vectors ``w`` (..., 3); ``a``, ``b`` take
    (th, small) and give the exact coefficient, or its Taylor series where ``small``."""
    w = np.asarray(w, float)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = th < small_angle
    return np.eye(3) + a(np.where(small, 1.0, th), th, small) * K + b(np.where(small, 1.0, th), th, small) * (K @ K)


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrices of rotation vectors ``w`` (..., 3) (Rodrigues)."""
    return _so3_series(w, lambda t, th, sm: np.where(sm, 1.0 - th ** 2 / 6, np.sin(t) / t),
                       lambda t, th, sm: np.where(sm, 0.5 - th ** 2 / 24, (1 - np.cos(t)) / t ** 2), 1e-8)


def left_jacobian_so3(w: np.ndarray) -> np.ndarray:
    """(..., 3, 3) left Jacobian of SO(3): d exp(w) / dw = [J_l(w) dw]x exp(w)."""
    return _so3_series(w, lambda t, th, sm: np.where(sm, 0.5 - th ** 2 / 24, (1 - np.cos(t)) / t ** 2),
                       lambda t, th, sm: np.where(sm, 1.0 / 6 - th ** 2 / 120, (t - np.sin(t)) / t ** 3), 1e-6)


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3, 3) cross-product matrices [v]x."""
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    return K - np.swapaxes(K, -1, -2)


def tangent_axes(rays: np.ndarray) -> np.ndarray:
    """(O, 2, 3): two unit axes orthogonal to each unit ray (and to each other)."""
    n = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    helper = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(n, e1)
    return np.stack((e1, e2), axis=1)


@dataclass
class BundleProblem:
    """Parameters ``x`` (rotation-vector update and translation of each free pose, then each free
    point), the residual vector (2 per observation, px) and its Jacobian in blocks."""

    x0: np.ndarray
    residuals: Callable[[np.ndarray], np.ndarray]
    blocks: Callable[[np.ndarray], tuple]  # x -> (O, 2, 6) d r / d pose, (O, 2, 3) d r / d point
    unpack: Callable[[np.ndarray], tuple]  # x -> (R, t, X)
    camera_points: Callable[[np.ndarray], np.ndarray]
    pose_col: np.ndarray  # (O,) first column of the observation's pose in x, -1 if fixed
    point_col: np.ndarray  # (O,) first column of its point, -1 if fixed

    def jacobian_dense(self, x: np.ndarray) -> np.ndarray:
        """The whole Jacobian as a dense matrix (for checks on small problems)."""
        Jp, Jx = self.blocks(x)
        J = np.zeros((2 * len(Jp), len(self.x0)))
        for o in range(len(Jp)):
            if self.pose_col[o] >= 0:
                J[2 * o:2 * o + 2, self.pose_col[o]:self.pose_col[o] + 6] = Jp[o]
            if self.point_col[o] >= 0:
                J[2 * o:2 * o + 2, self.point_col[o]:self.point_col[o] + 3] = Jx[o]
        return J


def bundle_problem(poses_cw: np.ndarray, fixed_pose: np.ndarray, points: np.ndarray, fixed_point: np.ndarray,
                   obs_frame: np.ndarray, obs_point: np.ndarray, obs_ray: np.ndarray,
                   focal_px: float) -> BundleProblem:
    """The least-squares problem of ``bundle_adjust`` (arguments as there)."""
    poses_cw = np.asarray(poses_cw, float)
    points = np.asarray(points, float)
    obs_frame, obs_point = np.asarray(obs_frame, int), np.asarray(obs_point, int)
    free_k = np.flatnonzero(~np.asarray(fixed_pose, bool))
    free_j = np.flatnonzero(~np.asarray(fixed_point, bool))
    kcol = np.full(len(poses_cw), -1)
    kcol[free_k] = np.arange(len(free_k)) * 6
    jcol = np.full(len(points), -1)
    jcol[free_j] = 6 * len(free_k) + np.arange(len(free_j)) * 3
    R0, t0 = poses_cw[:, :3, :3], poses_cw[:, :3, 3]
    E = tangent_axes(obs_ray)

    def unpack(x):
        R, t, X = R0.copy(), t0.copy(), points.copy()
        p = x[:6 * len(free_k)].reshape(-1, 6)
        R[free_k] = exp_so3(p[:, :3]) @ R0[free_k]
        t[free_k] = p[:, 3:]
        X[free_j] = x[6 * len(free_k):].reshape(-1, 3)
        return R, t, X

    def camera_points(x):
        R, t, X = unpack(x)
        return np.einsum("oij,oj->oi", R[obs_frame], X[obs_point]) + t[obs_frame]

    def residuals(x):
        Xc = camera_points(x)
        d = Xc / np.maximum(np.linalg.norm(Xc, axis=1, keepdims=True), 1e-12)
        return (focal_px * np.einsum("oai,oi->oa", E, d)).ravel()

    pose_obs = np.flatnonzero(kcol[obs_frame] >= 0)

    def jacobian_blocks(x):
        """Per observation: d r / d (w, t) of its pose (2x6) and d r / d X of its point (2x3).
        r = f E d, d = Xc / |Xc|: dr/dXc = f E (I - d d^T) / |Xc|; dXc/dX = R, dXc/dt = I,
        dXc/dw = -[R X]x J_l(w) (R = exp(w) R0)."""
        R, t, X = unpack(x)
        Xc = np.einsum("oij,oj->oi", R[obs_frame], X[obs_point]) + t[obs_frame]
        nrm = np.maximum(np.linalg.norm(Xc, axis=1), 1e-12)
        d = Xc / nrm[:, None]
        Ed = (E @ d[:, :, None])[:, :, 0]
        Jc = focal_px * (E - Ed[:, :, None] * d[:, None, :]) / nrm[:, None, None]
        Jp = np.zeros((n_obs, 2, 6))
        if len(free_k):
            Jl = np.zeros((len(poses_cw), 3, 3))
            Jl[free_k] = left_jacobian_so3(x[:6 * len(free_k)].reshape(-1, 6)[:, :3])
            o = pose_obs
            RX = Xc[o] - t[obs_frame[o]]
            Jp[o, :, :3] = -(Jc[o] @ skew(RX)) @ Jl[obs_frame[o]]
            Jp[o, :, 3:] = Jc[o]
        Jx = Jc @ R[obs_frame]
        return Jp, Jx

    x0 = np.concatenate((np.hstack((np.zeros((len(free_k), 3)), t0[free_k])).ravel(), points[free_j].ravel()))
    n_obs = len(obs_frame)
    return BundleProblem(x0, residuals, jacobian_blocks, unpack, camera_points, kcol[obs_frame], jcol[obs_point])


def bundle_adjust(poses_cw: np.ndarray, fixed_pose: np.ndarray, points: np.ndarray, fixed_point: np.ndarray,
                  obs_frame: np.ndarray, obs_point: np.ndarray, obs_ray: np.ndarray, focal_px: float,
                  sigma_px: float = 1.0, max_iterations: int = 10) -> BundleResult:
    """Adjust the poses not ``fixed_pose`` and the points not ``fixed_point`` to the observations
    (``obs_frame[o]`` sees ``obs_point[o]`` along ``obs_ray[o]``, unit rays in that camera).
    ``poses_cw`` are camera-from-world; the fixed ones set the gauge (two fixed poses fix a
    monocular window's position, orientation and scale).

    Levenberg-Marquardt with the points eliminated (Schur complement: one 3x3 block per point, a
    dense system of 6 per free pose), Huber by reweighting each iteration (weight min(1, k/|r|)
    per observation)."""
    poses_cw = np.asarray(poses_cw, float)
    points = np.asarray(points, float)
    obs_frame, obs_point = np.asarray(obs_frame, int), np.asarray(obs_point, int)
    n_obs = len(obs_frame)
    prob = bundle_problem(poses_cw, fixed_pose, points, fixed_point, obs_frame, obs_point, obs_ray, focal_px)
    k = HUBER_K * sigma_px

    def cost(x):
        r = np.linalg.norm(prob.residuals(x).reshape(-1, 2), axis=1)
        return float(np.sum(_huber(r, k))), r

    x = prob.x0
    c, r = cost(x) if n_obs else (0.0, np.zeros(0))
    cost0, it = c, 0
    n_p = 6 * int(np.sum(~np.asarray(fixed_pose, bool)))
    free_j = np.flatnonzero(~np.asarray(fixed_point, bool))
    M = len(free_j)
    if len(x) and n_obs:
        po, pc = np.flatnonzero(prob.pose_col >= 0), prob.pose_col
        lo = np.flatnonzero(prob.point_col >= 0)
        lj = (prob.point_col[lo] - n_p) // 3  # free-point index of those observations
        both = np.flatnonzero((prob.pose_col >= 0) & (prob.point_col >= 0))
        bk, bj = prob.pose_col[both] // 6, (prob.point_col[both] - n_p) // 3
        lam = 1e-3
        for it in range(1, max_iterations + 1):
            Jp, Jx = prob.blocks(x)
            res = prob.residuals(x).reshape(-1, 2)
            w = np.minimum(1.0, k / np.maximum(r, 1e-12))  # Huber IRLS weight per observation
            K6 = n_p // 6
            Hpp = np.zeros((K6, 6, 6))
            gp = np.zeros((K6, 6))
            np.add.at(Hpp, pc[po] // 6, w[po, None, None] * (_t(Jp[po]) @ Jp[po]))
            np.add.at(gp, pc[po] // 6, w[po, None] * np.einsum("oai,oa->oi", Jp[po], res[po]))
            Hll = np.zeros((M, 3, 3))
            gl = np.zeros((M, 3))
            np.add.at(Hll, lj, w[lo, None, None] * (_t(Jx[lo]) @ Jx[lo]))
            np.add.at(gl, lj, w[lo, None] * np.einsum("oai,oa->oi", Jx[lo], res[lo]))
            Hpl = np.zeros((K6, M, 6, 3))
            np.add.at(Hpl, (bk, bj), w[both, None, None] * (_t(Jp[both]) @ Jx[both]))
            Hpl2 = Hpl.transpose(0, 2, 1, 3).reshape(n_p, 3 * M)
            while True:
                A = Hpp + lam * (Hpp * np.eye(6)) + 1e-9 * np.eye(6)
                B = Hll + lam * (Hll * np.eye(3)) + 1e-9 * np.eye(3)
                Binv = np.linalg.inv(B)
                HB = (Hpl @ Binv).transpose(0, 2, 1, 3).reshape(n_p, 3 * M)  # Hpl Hll^-1
                # einsum, not @: a threaded BLAS call on matrices this small costs more (4x on 2
                # busy cores) than the arithmetic
                S = -np.einsum("ij,kj->ik", HB, Hpl2)
                for kk in range(K6):
                    S[6 * kk:6 * kk + 6, 6 * kk:6 * kk + 6] += A[kk]
                rhs = -gp.reshape(-1) + np.einsum("ij,j->i", HB, gl.reshape(-1))
                dp = np.linalg.solve(S, rhs).reshape(K6, 6) if n_p else np.zeros((0, 6))
                dl = np.einsum("jab,jb->ja", Binv, -gl - np.einsum("ij,i->j", Hpl2, dp.reshape(-1)).reshape(M, 3))
                x_new = x + np.concatenate((dp.ravel(), dl.ravel()))
                c_new, r_new = cost(x_new)
                if c_new < c:
                    break
                lam *= 10.0
                if lam > 1e8:
                    break
            if c_new >= c:
                break
            done = c - c_new < 1e-4 * c  # a further 0.01 % of the cost moves nothing that matters
            x, c, r = x_new, c_new, r_new
            lam = max(lam / 10.0, 1e-7)
            if done:
                break
    R, t, X = prob.unpack(x)
    out = np.repeat(np.eye(4)[None], len(poses_cw), 0)
    out[:, :3, :3], out[:, :3, 3] = R, t
    behind = np.einsum("oi,oi->o", prob.camera_points(x), obs_ray) <= 0 if n_obs else np.zeros(0, bool)
    return BundleResult(out, X, r, behind, cost0, c, it)


def _t(J: np.ndarray) -> np.ndarray:
    return np.swapaxes(J, -1, -2)


def _huber(r: np.ndarray, k: float) -> np.ndarray:
    """Huber's loss of residual norms ``r`` (quadratic below ``k``, linear above)."""
    a = np.abs(r)
    return np.where(a <= k, 0.5 * r ** 2, k * (a - 0.5 * k))
