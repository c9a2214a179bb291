"""Motion recovery from rays to known landmarks (section 11.3.2, equations 11.14-11.17).

Landmarks P_i are known in a reference frame; the current camera sees them
along unit rays n'_i. We want (R, T) with D'_i n'_i = R P_i + T (11.14).
The alternation of the chapter:

    1. depth guesses D'_i (D_init, the previous depths, or a prior pose)   (11.15)
    2. P'_i = D'_i n'_i                                                     (11.16)
    3. (R, T) = argmin sum w_i |R P_i + T - P'_i|^2 by SVD, det R = +1      (11.17)
    4. D'_i = n'_i . (R P_i + T), repeat until the depths stop changing.

Steps 2-4 are block-coordinate descent on the object-space error
sum w_i |(I - n'_i n'_i^T)(R P_i + T)|^2, the objective of Lu, Hager and
Mjolsness (PAMI 2000, the chapter's reference [15]) and of SQPnP. As in their
method, after the SVD rotation we take the translation that is optimal for that
rotation in the object-space error (a closed form with a 3x3 matrix fixed per
solve) instead of the centroid difference: same fixed point, far fewer
iterations when the motion is along the rays.

Weights: uniform weights minimise the object-space error (what SQPnP does);
``angular=True`` weights each point by 1/D_i^2 so the error becomes the
squared ray angle, the right metric for pixel noise on deep scenes (KITTI).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from vbnav.vision import motion_kernel
from vbnav.vision.geometry import absolute_orientation


@dataclass
class MotionEstimate:
    """Pose of the reference frame in the current camera frame: X_cur = R X_ref + T."""

    R: np.ndarray
    T: np.ndarray
    depths: np.ndarray  # D'_i along the current rays
    iterations: int  # alternation steps of the final solve (sum over refinement rounds if robust)
    residual: float  # rms angle between rays and predicted directions, rad (inliers, unweighted)
    inliers: np.ndarray  # bool mask
    converged: bool
    hypotheses: int = 0  # minimal-set hypotheses tried (robust solve only)
    info: dict = field(default_factory=dict)


def angular_residuals(P: np.ndarray, rays: np.ndarray, R: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Angle (rad) between each ray and the direction to R P_i + T; pi for points at the centre."""
    X = P @ R.T + T
    norm = np.linalg.norm(X, axis=1)
    u = X / np.where(norm > 0, norm, 1.0)[:, None]
    chord = np.linalg.norm(u - rays, axis=1)
    return 2.0 * np.arcsin(np.clip(chord / 2.0, 0.0, 1.0))


def _det3(m: np.ndarray) -> float:
    a, b, c, d, e, f, g, h, i = m.ravel().tolist()
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


try:  # the bare gufunc behind np.linalg.svd: half the per-call overhead on 3x3 matrices
    from numpy.linalg import _umath_linalg as _ul

    _ul.svd_f(np.eye(3), signature="d->ddd")

    def _svd3(H: np.ndarray):
        return _ul.svd_f(H, signature="d->ddd")
except Exception:  # pragma: no cover - other numpy versions
    def _svd3(H: np.ndarray):
        return np.linalg.svd(H)


def _rotation_from_cross_covariance(H: np.ndarray) -> np.ndarray:
    """R = V U^T for H = U S V^T, with det R = +1 (reflection guard): the rotation step of
    ``geometry.absolute_orientation`` for an H the alternation updates linearly, in the form
    motion_kernel.rotation_from_cross_covariance compiles (3x3 SVD without numpy's overhead, the
    sign from det H unless H is singular)."""
    U, _, Vt = _svd3(H)
    dH = _det3(H)
    scale = float(np.abs(H).max()) ** 3
    sign = (1.0 if dH > 0 else -1.0) if abs(dH) > 1e-12 * scale else np.sign(_det3(U) * _det3(Vt))
    if sign < 0:
        Vt = Vt.copy()
        Vt[2] = -Vt[2]
    return Vt.T @ U.T


class _ObjectSpaceIteration:
    """One solve's precomputed linear maps, so each alternation step costs O(1), not O(N).

    With Q_i = V_i (R P_i + T) (the depth update folded into the new points,
    V_i = n_i n_i^T) the weighted cross-covariance of step 3 is linear in (R, T):
        H_ab = sum_i w_i p~_ia n_ib (n_i . (R P_i + T)),  p~ = P - weighted centroid,
    i.e. vec(H) = A vec(R) + B T. The translation optimal for R in the
    object-space error (LHM eq. 20) is linear in R too: T = C vec(R). So a step
    is H = (A + B C) vec(R), an SVD, and R. Depths are only formed at the end.
    """

    def __init__(self, P: np.ndarray, n: np.ndarray, w: np.ndarray | None):
        N = len(P)
        w = np.full(N, 1.0 / N) if w is None else w / w.sum()
        cP = w @ P
        wp = (P - cP) * w[:, None]
        K = (wp[:, :, None] * n[:, None, :]).reshape(N, 9)  # w p~_a n_b
        L = (n[:, :, None] * P[:, None, :]).reshape(N, 9)  # n_c P_d
        A = K.T @ L
        B = K.T @ n
        # T(R) = -Ainv g, g = R (sum w P) - sum w n (n . R P)
        Ainv = np.linalg.inv(np.eye(3) - (n * w[:, None]).T @ n)
        G = -(n * w[:, None]).T @ L
        G[0, 0:3] += cP
        G[1, 3:6] += cP
        G[2, 6:9] += cP
        self.C = -Ainv @ G
        self.M = A + B @ self.C
        # Object-space error as a quadratic form in vec(R): e_i = (I - V_i)(A_i + C) vec(R), A_i vec(R) = R P_i.
        Ai = np.zeros((N, 3, 9))
        for a in range(3):
            Ai[:, a, 3 * a:3 * a + 3] = P
        Ai += self.C
        proj = Ai - n[:, :, None] * np.einsum("ni,nij->nj", n, Ai)[:, None, :]
        self.E = np.einsum("nij,nik->jk", Ai * w[:, None, None], proj)

    def step(self, R: np.ndarray) -> np.ndarray:
        return _rotation_from_cross_covariance((self.M @ R.ravel()).reshape(3, 3))

    def error(self, R: np.ndarray) -> float:
        r = R.ravel()
        return float(r @ self.E @ r)

    def translation(self, R: np.ndarray) -> np.ndarray:
        return self.C @ R.ravel()


def recover_motion(points: np.ndarray, rays: np.ndarray, depths: np.ndarray | float | None = None, *,
                   prior: tuple[np.ndarray, np.ndarray] | None = None, weights: np.ndarray | None = None,
                   angular: bool = False, max_iter: int = 200, tol: float = 1e-5,
                   overrelax: float = 2.0) -> MotionEstimate:
    """The alternation 11.15-11.17 for n >= 3 landmarks.

    points (N, 3): landmarks in the reference frame; rays (N, 3): unit rays in
    the current frame. Initial depths, by priority: ``prior`` (R, T) (depths
    n' . (R P + T)), ``depths`` (array or scalar D_init), else the median
    distance of the landmarks from the reference origin. Converged when no
    depth can change by more than ``tol`` times the mean depth (bounded by
    |dR| max|P| + |dT| so the depths need not be formed each step).
    ``overrelax`` > 1 extrapolates each rotation step along its geodesic by that
    factor when this lowers the object-space error (safeguarded over-relaxation:
    same fixed point, about 40 % fewer iterations); 1 is the plain alternation.
    """
    P = np.asarray(points, float).reshape(-1, 3)
    n = np.asarray(rays, float).reshape(-1, 3)
    N = len(P)
    if N < 3 or len(n) != N:
        raise ValueError(f"motion recovery needs >= 3 landmarks with one ray each, got {N} and {len(n)}")
    if prior is not None:
        D = None  # n' . (R P + T), formed by whichever path runs
    elif depths is None:
        D = np.full(N, float(np.median(np.linalg.norm(P, axis=1))))
    else:
        D = np.broadcast_to(np.asarray(depths, float), (N,)).copy()
    w = None if weights is None else np.asarray(weights, float).reshape(N)
    if motion_kernel.AVAILABLE:
        R0, T0 = (_EYE, _ZERO) if prior is None else prior
        # Contiguous float64 in, always: another memory layout would compile another kernel, mid-run.
        R, T, D, it, res, converged = motion_kernel.solve_from(
            np.ascontiguousarray(P), np.ascontiguousarray(n), np.ascontiguousarray(R0, dtype=float).reshape(3, 3),
            np.ascontiguousarray(T0, dtype=float).reshape(3),
            _EMPTY if D is None else D, _EMPTY if w is None else np.ascontiguousarray(w), bool(angular),
            int(max_iter), float(tol), float(overrelax))
        return MotionEstimate(R, T, D, it, res, np.ones(N, bool), converged)
    if D is None:
        D = np.einsum("ij,ij->i", P @ prior[0].T + prior[1], n)
    if angular:
        inv2 = 1.0 / np.maximum(np.abs(D), 1e-12) ** 2
        w = inv2 if w is None else w * inv2
    return _recover_motion_numpy(P, n, D, w, max_iter, tol, overrelax)


_EYE, _ZERO, _EMPTY = np.eye(3), np.zeros(3), np.zeros(0)


def _recover_motion_numpy(P: np.ndarray, n: np.ndarray, D: np.ndarray, w: np.ndarray | None, max_iter: int,
                          tol: float, overrelax: float) -> MotionEstimate:
    """The reference implementation of the alternation; motion_kernel.solve compiles the same steps."""
    N = len(P)
    solver = _ObjectSpaceIteration(P, n, w)
    ws = np.full(N, 1.0 / N) if w is None else w / w.sum()
    Pc = P - ws @ P
    # first step from the guessed depths (11.15, 11.16), then the folded steps
    R = _rotation_from_cross_covariance((Pc * ws[:, None]).T @ (D[:, None] * n))
    T = solver.translation(R)
    bound = tol * max(float(np.mean(np.abs(D))), 1e-300)
    pmax = float(np.sqrt(np.max(np.einsum("ij,ij->i", P, P))))
    converged = False
    it = 1
    while it < max_iter:
        it += 1
        R_new = solver.step(R)
        if overrelax > 1.0:
            # Linear convergence along a slow direction: extrapolate along the rotation step
            # (geodesic over-relaxation), kept only if it lowers the object-space error.
            # cv2.Rodrigues returns zero under 1e-5 rad, so such steps are not extrapolated.
            v = cv2.Rodrigues(R.T @ R_new)[0]
            R_acc = R @ cv2.Rodrigues(v * overrelax)[0]
            if solver.error(R_acc) < solver.error(R_new):
                R_new = R_acc
        T_new = solver.translation(R_new)
        dR = (R_new - R).ravel()
        dT = T_new - T
        change = math.sqrt(float(dR @ dR)) * pmax + math.sqrt(float(dT @ dT))
        R, T = R_new, T_new
        if change <= bound:
            converged = True
            break
    X = P @ R.T + T
    D = np.einsum("ij,ij->i", X, n)
    ang = angular_residuals(P, n, R, T)
    return MotionEstimate(R, T, D, it, float(np.sqrt(np.mean(ang ** 2))), np.ones(N, bool), converged)


def _three_distinct(rng: np.random.Generator, N: int, h: int) -> np.ndarray:
    """h random triples of distinct indices in [0, N), vectorised."""
    a = rng.integers(0, N, h)
    b = (a + rng.integers(1, N, h)) % N
    c = rng.integers(0, N - 2, h)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    c = c + (c >= lo)
    c = c + (c >= hi)
    return np.column_stack((a, b, c))


def _minimal_hypotheses(P: np.ndarray, n: np.ndarray, D0: np.ndarray, samples: np.ndarray, iters: int
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Run the alternation on many 3-point sets at once (centroid translation), (H, 3, 3), (H, 3)."""
    Ps, ns = P[samples], n[samples]
    D = D0[samples]
    R = T = None
    for _ in range(iters):
        R, T, _ = absolute_orientation(Ps, D[..., None] * ns)
        D = np.einsum("hkj,hkj->hk", np.einsum("hij,hkj->hki", R, Ps) + T[:, None], ns)
        D = np.maximum(D, 1e-9 * (np.abs(D).max(axis=1, keepdims=True) + 1e-300))
    return R, T


def _scored_hypotheses(P: np.ndarray, n: np.ndarray, D0: np.ndarray, samples: np.ndarray, iters: int,
                       gate: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """_minimal_hypotheses and, for each, the number of rays within the angle whose cosine is ``gate``."""
    if motion_kernel.AVAILABLE:
        return motion_kernel.minimal_hypotheses(P, n, D0, samples, int(iters), float(gate))
    Rs, Ts = _minimal_hypotheses(P, n, D0, samples, iters)
    X = np.einsum("hij,kj->hki", Rs, P) + Ts[:, None]
    X /= np.linalg.norm(X, axis=2, keepdims=True)
    return Rs, Ts, np.sum(np.einsum("hki,ki->hk", X, n) > gate, axis=1)


def recover_motion_robust(points: np.ndarray, rays: np.ndarray, depths: np.ndarray | float | None = None, *,
                          prior: tuple[np.ndarray, np.ndarray] | None = None, threshold: float = 0.004,
                          angular: bool = False, confidence: float = 0.999, max_hypotheses: int = 200,
                          batch: int = 16, minimal_iters: int = 8, refine_rounds: int = 3, score_factor: float = 3.0,
                          rng: np.random.Generator | None = None, tol: float = 1e-5,
                          weights: np.ndarray | None = None, local_optimisation: bool = False) -> MotionEstimate:
    """Outlier-robust motion: 3-point hypotheses (the chapter's minimal set), then robust reweighting.

    Hypotheses run the alternation on 3 landmarks from the same initial depths
    (batched); each is scored by the number of rays within ``threshold`` rad.
    The prior pose, when given, is one more hypothesis. The best consensus set
    is refined by the full alternation with Cauchy weights on the ray angles,
    ``refine_rounds`` times, the inlier set recomputed each round. ``weights``
    (N,), if given, multiply the Cauchy weights (confidence in each landmark).
    ``local_optimisation``: each new best hypothesis is refitted to its consensus set (LO-RANSAC;
    docs/vslam.md).
    """
    P = np.ascontiguousarray(np.asarray(points, float).reshape(-1, 3))
    n = np.ascontiguousarray(np.asarray(rays, float).reshape(-1, 3))
    N = len(P)
    if N < 3:
        raise ValueError(f"motion recovery needs >= 3 landmarks, got {N}")
    rng = rng if rng is not None else np.random.default_rng(0)
    if prior is not None:
        D0 = np.einsum("ij,ij->i", P @ prior[0].T + prior[1], n)
        D0 = np.where(D0 > 0, D0, np.median(np.abs(D0)))
    elif depths is None:
        D0 = np.full(N, float(np.median(np.linalg.norm(P, axis=1))))
    else:
        D0 = np.broadcast_to(np.asarray(depths, float), (N,)).copy()

    # Hypotheses are scored with a looser gate than the final inlier test: a 3-point pose (or a
    # predicted one) is itself noisy, and a tight gate would pick a biased consensus set.
    gate = np.cos(score_factor * threshold)
    best_count, best = -1, None
    if prior is not None:
        best_count = int(np.sum(angular_residuals(P, n, *prior) < score_factor * threshold))
        best = prior
    tried = 0

    def hypotheses_needed(count: int) -> float:  # RANSAC's bound for the inlier fraction seen so far
        eps = count / N
        return np.log(1 - confidence) / np.log(max(1 - eps ** 3, 1e-12)) if eps < 1 else 0

    given_w = None if weights is None else np.asarray(weights, float).reshape(N)

    def local_optimum(R, T, count):
        """LO-RANSAC (Chum, Matas and Kittler 2003): the pose fitted to a hypothesis' consensus set
        replaces it when it gathers more rays; a 3-point pose is noisy, and on few landmarks two
        noisy hypotheses can tie with different consensus sets."""
        inl = angular_residuals(P, n, R, T) < score_factor * threshold
        if inl.sum() <= 3:
            return (R, T), count
        w = None if given_w is None else given_w[inl]
        est = recover_motion(P[inl], n[inl], D0[inl], prior=(R, T), weights=w, angular=angular, tol=1e-4,
                             max_iter=50)
        c = int(np.sum(angular_residuals(P, n, est.R, est.T) < score_factor * threshold))
        return ((est.R, est.T), c) if c > count else ((R, T), count)

    if local_optimisation and best is not None:
        best, best_count = local_optimum(*best, best_count)
    if N > 3 and best_count < N:
        needed = hypotheses_needed(best_count) if best_count > 0 else max_hypotheses
        while tried < min(needed, max_hypotheses):
            h = min(batch, max_hypotheses - tried)
            samples = _three_distinct(rng, N, h)
            Rs, Ts, counts = _scored_hypotheses(P, n, D0, samples, minimal_iters, gate)
            k = int(np.argmax(counts))
            tried += h
            if counts[k] > best_count:
                best_count, best = int(counts[k]), (Rs[k], Ts[k])
                if local_optimisation:
                    best, best_count = local_optimum(*best, best_count)
                needed = hypotheses_needed(best_count)
    if best is None:  # N == 3: the minimal set is all we have
        best = (None, None)
    inl = (np.ones(N, bool) if best[0] is None
           else angular_residuals(P, n, *best) < score_factor * threshold)
    if inl.sum() < 3:
        inl = np.ones(N, bool)
    est_prior = None if best[0] is None else best
    total_iters = 0
    prior_w = np.ones(N) if given_w is None else given_w
    weights = prior_w.copy()
    est = None
    for _ in range(max(1, refine_rounds)):
        idx = np.flatnonzero(inl)
        est = recover_motion(P[idx], n[idx], D0[idx], prior=est_prior, weights=weights[idx],
                             angular=angular, tol=tol)
        total_iters += est.iterations
        r = angular_residuals(P, n, est.R, est.T)
        est_prior = (est.R, est.T)
        new_inl = r < threshold
        if new_inl.sum() < 3:
            break
        sigma = max(threshold / 3.0, float(np.median(r[new_inl])) * 1.4826)
        weights = prior_w / (1.0 + (r / sigma) ** 2)  # Cauchy
        if np.array_equal(new_inl, inl) and _ > 0:
            inl = new_inl
            break
        inl = new_inl
    r = angular_residuals(P, n, est.R, est.T)
    D = np.einsum("ij,ij->i", P @ est.R.T + est.T, n)
    res = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else float("nan")
    return MotionEstimate(est.R, est.T, D, total_iters, res, inl, est.converged, hypotheses=tried)


def warm_up() -> None:
    """Compile the numba kernels, or load them from numba's disk cache, before a real-time loop needs
    them: with a cold cache (a fresh install) the first solve would take seconds. Runs the public
    solvers on a small synthetic scene, so the compiled signatures are exactly the ones they use."""
    if not motion_kernel.AVAILABLE:
        return
    rng = np.random.default_rng(0)
    P = np.column_stack((rng.uniform(-1, 1, 12), rng.uniform(-1, 1, 12), rng.uniform(3, 6, 12)))
    rays = P / np.linalg.norm(P, axis=1, keepdims=True)
    prior = (np.eye(3), np.zeros(3))
    recover_motion(P, rays, prior=prior, angular=True)
    recover_motion(P, rays, depths=4.0)
    recover_motion_robust(P, rays, prior=prior, angular=True, weights=np.ones(len(P)), rng=rng)
    recover_motion_robust(P, rays, angular=True, rng=rng)  # no prior: the 3-point hypotheses run
