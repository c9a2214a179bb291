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
efficiency at Gaussian noise), sigma the tracking noise in pixels. Solved by
``scipy.optimize.least_squares`` (trust region, sparse Jacobian by finite differences over the
known sparsity: each residual depends on one pose and one point).

Pure computation: arrays in, arrays out.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix

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


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rotation matrices of rotation vectors ``w`` (..., 3) (Rodrigues)."""
    w = np.asarray(w, float)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = np.zeros(w.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th ** 2 / 6, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th ** 2 / 24, (1 - np.cos(ths)) / ths ** 2)
    return np.eye(3) + a * K + b * (K @ K)


def left_jacobian_so3(w: np.ndarray) -> np.ndarray:
    """(..., 3, 3) left Jacobian of SO(3): d exp(w) / dw = [J_l(w) dw]x exp(w)."""
    w = np.asarray(w, float)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = np.zeros(w.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    a = np.where(small, 0.5 - th ** 2 / 24, (1 - np.cos(ths)) / ths ** 2)
    b = np.where(small, 1.0 / 6 - th ** 2 / 120, (ths - np.sin(ths)) / ths ** 3)
    return np.eye(3) + a * K + b * (K @ K)


def skew(v: np.ndarray) -> np.ndarray:
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
    point), the residual vector (2 per observation, px) and its sparse Jacobian."""

    x0: np.ndarray
    residuals: Callable[[np.ndarray], np.ndarray]
    jacobian: Callable[[np.ndarray, np.ndarray], csr_matrix]  # (x, row weights) -> weighted Jacobian
    unpack: Callable[[np.ndarray], tuple]  # x -> (R, t, X)
    camera_points: Callable[[np.ndarray], np.ndarray]


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
    point_obs = np.flatnonzero(jcol[obs_point] >= 0)

    def jacobian_blocks(x):
        """Per observation: d r / d (w, t) of its pose (2x6) and d r / d X of its point (2x3).
        r = f E d, d = Xc / |Xc|: dr/dXc = f E (I - d d^T) / |Xc|; dXc/dX = R, dXc/dt = I,
        dXc/dw = -[R X]x J_l(w) (R = exp(w) R0)."""
        R, t, X = unpack(x)
        Xc = np.einsum("oij,oj->oi", R[obs_frame], X[obs_point]) + t[obs_frame]
        nrm = np.maximum(np.linalg.norm(Xc, axis=1), 1e-12)
        d = Xc / nrm[:, None]
        Jc = focal_px * (E - np.einsum("oai,oi,oj->oaj", E, d, d)) / nrm[:, None, None]
        Jp = np.zeros((n_obs, 2, 6))
        if len(free_k):
            Jl = np.zeros((len(poses_cw), 3, 3))
            Jl[free_k] = left_jacobian_so3(x[:6 * len(free_k)].reshape(-1, 6)[:, :3])
            o = pose_obs
            RX = Xc[o] - t[obs_frame[o]]
            Jp[o, :, :3] = -np.einsum("oai,oij,ojk->oak", Jc[o], skew(RX), Jl[obs_frame[o]])
            Jp[o, :, 3:] = Jc[o]
        Jx = np.einsum("oai,oij->oaj", Jc, R[obs_frame])
        return Jp, Jx

    x0 = np.concatenate((np.hstack((np.zeros((len(free_k), 3)), t0[free_k])).ravel(), points[free_j].ravel()))
    n_obs = len(obs_frame)
    ri, ci = [], []
    for col, width in ((kcol[obs_frame], 6), (jcol[obs_point], 3)):
        o = np.flatnonzero(col >= 0)
        r = (2 * o[:, None] + np.arange(2)[None]).repeat(width, axis=1)  # (n, 2 * width): both rows
        c = np.tile(col[o][:, None] + np.arange(width)[None], (1, 2))
        ri.append(r.ravel())
        ci.append(c.ravel())
    ri, ci = np.concatenate(ri), np.concatenate(ci)
    shape = (2 * n_obs, len(x0))

    def jacobian(x, w):
        Jp, Jx = jacobian_blocks(x)
        data = np.concatenate((Jp[pose_obs].reshape(-1), Jx[point_obs].reshape(-1)))
        return csr_matrix((data * w[ri], (ri, ci)), shape=shape)

    return BundleProblem(x0, residuals, jacobian, unpack, camera_points)


def bundle_adjust(poses_cw: np.ndarray, fixed_pose: np.ndarray, points: np.ndarray, fixed_point: np.ndarray,
                  obs_frame: np.ndarray, obs_point: np.ndarray, obs_ray: np.ndarray, focal_px: float,
                  sigma_px: float = 1.0, max_nfev: int = 10, rounds: int = 2) -> BundleResult:
    """Adjust the poses not ``fixed_pose`` and the points not ``fixed_point`` to the observations
    (``obs_frame[o]`` sees ``obs_point[o]`` along ``obs_ray[o]``, unit rays in that camera).
    ``poses_cw`` are camera-from-world; the fixed ones set the gauge (two fixed poses fix a
    monocular window's position, orientation and scale)."""
    poses_cw = np.asarray(poses_cw, float)
    points = np.asarray(points, float)
    n_obs = len(obs_frame)
    prob = bundle_problem(poses_cw, fixed_pose, points, fixed_point, obs_frame, obs_point, obs_ray, focal_px)
    x0, residuals, jacobian, unpack, camera_points = prob.x0, prob.residuals, prob.jacobian, prob.unpack, \
        prob.camera_points
    if len(x0) == 0 or n_obs == 0:
        r = residuals(x0).reshape(-1, 2) if n_obs else np.zeros((0, 2))
        return BundleResult(poses_cw.copy(), points.copy(), np.linalg.norm(r, axis=1),
                            np.zeros(n_obs, bool), 0.0, 0.0, 0)
    # Huber by iteratively reweighted least squares: scipy's own robust loss (a rescaling of the
    # Gauss-Newton step) creeps when most residuals start beyond the knee, as after scale drift;
    # a few rounds of weighted least squares with the weights of the last solution do not.
    k = HUBER_K * sigma_px
    x, w = x0, np.ones(2 * n_obs)
    nfev = 0
    for _ in range(rounds):
        sol = least_squares(lambda z, w=w: w * residuals(z), x, jac=lambda z, w=w: jacobian(z, w), method="trf",
                            x_scale="jac", max_nfev=max_nfev, tr_solver="lsmr")
        x, nfev = sol.x, nfev + sol.nfev
        r = np.linalg.norm(residuals(x).reshape(-1, 2), axis=1)  # one weight per observation (both axes)
        w = np.repeat(np.sqrt(np.minimum(1.0, k / np.maximum(r, 1e-12))), 2)
    f_scale = k
    sol.x = x
    sol.fun = residuals(x)
    sol.nfev = nfev
    R, t, X = unpack(sol.x)
    out = np.repeat(np.eye(4)[None], len(poses_cw), 0)
    out[:, :3, :3], out[:, :3, 3] = R, t
    Xc = camera_points(sol.x)
    behind = np.einsum("oi,oi->o", Xc, obs_ray) <= 0
    cost0 = float(np.sum(_huber(residuals(x0), f_scale)))
    return BundleResult(out, X, np.linalg.norm(sol.fun.reshape(-1, 2), axis=1), behind, cost0,
                        float(np.sum(_huber(sol.fun, f_scale))), int(sol.nfev))


def _huber(r: np.ndarray, k: float) -> np.ndarray:
    a = np.abs(r)
    return np.where(a <= k, 0.5 * r ** 2, k * (a - 0.5 * k))
