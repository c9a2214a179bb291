"""Vision-Based Control (chapter section 11.2.2.1): planar pose from bearing errors.

Conventions (vision/geometry.py, DESIGN.md)
-------------------------------------------
Camera rays are first rotated into the *levelled* frame: the robot's axes
(x right, y down, z forward) placed at the camera's optical centre, so the
camera's pitch and yaw on its mount do not enter the planar model
(``levelled_bearings``). In that frame a landmark at (x, y, z) has azimuth
alpha = atan2(x, z) and elevation beta = atan2(y, r), r = sqrt(x^2 + z^2);
y is its height *below* the camera (y < 0 above it), constant while the robot
drives on the floor. We use w = 1/y (inverse height) and the in-plane inverse
range rho = 1/r = w tan(beta), which stays finite for landmarks far away or
near the horizon.

Derivation of the image Jacobian
--------------------------------
The robot moves by a small planar increment delta = (dx, dz, dtheta) in its
own frame (``Pose2.compose``: the new pose is p * delta). The camera sits at
(l, f) = (mount.lateral, mount.forward) in the robot frame, so it moves by
    dc = (dx + f dtheta, dz - l dtheta)
(the derivative of rot_y(theta) applied to (l, f) at theta = 0), and turns by
dtheta. A landmark at (x, z) in the levelled camera frame is then seen at
    x' = x - dc_x - z dtheta,   z' = z - dc_z + x dtheta      (first order)
because the frame turns right by dtheta (theta grows toward +x). With
d alpha = (z dx' - x dz') / r^2 and d beta = -y dr / R^2, dr = (x dx' + z dz') / r,
R^2 = r^2 + y^2:
    d alpha = (-z dc_x + x dc_z) / r^2 - dtheta
    d beta  = y (x dc_x + z dc_z) / (r R^2)
Substituting x = r sin(alpha), z = r cos(alpha), 1/r = rho = w tan(beta) and
y / R^2 = sin^2(beta) / y = w sin^2(beta):

    d alpha/dx     = -w tan(beta) cos(alpha)
    d alpha/dz     =  w tan(beta) sin(alpha)
    d alpha/dtheta = -1 - w tan(beta) (f cos(alpha) + l sin(alpha))
    d beta/dx      =  w sin^2(beta) sin(alpha)
    d beta/dz      =  w sin^2(beta) cos(alpha)
    d beta/dtheta  =  w sin^2(beta) (f sin(alpha) - l cos(alpha))

Every entry depends only on the observed (alpha, beta) and w. Compared with the
chapter's (11.2): its first row reads "z/r^2, -x/r^2 - 1" where "-x/r^2" and
"-1" are two separate columns; the signs of the translation columns are
opposite to ours because the chapter differentiates with respect to the
landmark's displacement, we with respect to the robot's; and the chapter's
camera turns about its own centre, while ours sits ``forward`` ahead of the
axle, which adds the rho f and w sin^2(beta) f terms to the theta column.
Landmarks at the camera's height (beta ~ 0) have ~0 translation columns: they
inform heading only. ``tests/test_vbc.py`` checks all six entries against
central finite differences of the exact model below.

Exact model (used for Gauss-Newton)
-----------------------------------
A landmark taught at (alpha0, beta0) with inverse range rho0 sits at
q = (sin alpha0, cos alpha0) / rho0 in the taught levelled frame. Seen from
the robot at planar pose p = (x, z, theta) relative to the taught pose, and
scaling by rho0 > 0 (which changes no angle):
    u = (sin alpha0, cos alpha0) + rho0 (m - p * m),   m = (l, f)
    v = rot(theta)^T u,     alpha = atan2(v_x, v_z),
    beta = atan2(tan(beta0), |v|)            (since y rho0 = tan(beta0))
Gauss-Newton linearises this at the current estimate with the Jacobian above
(evaluated at the *predicted* bearings) and composes the increment on the
right: p <- p * delta.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from vbnav.vision.camera_model import azimuth_elevation, rays_from_angles
from vbnav.vision.geometry import CameraMount, Pose2

#: tan(beta) is floored at this magnitude when converting between w and rho.
_MIN_TAN = 1e-6
#: Variance of rho (1/m^2) assumed for a landmark without a height estimate:
#: ranges from ~0.7 m to infinity are all plausible.
UNKNOWN_RHO_VAR = 1.5 ** 2


def known_range(beta: np.ndarray, inv_height: np.ndarray, inv_height_var: np.ndarray | None) -> np.ndarray:
    """Landmarks whose range is known: a finite inverse height whose inverse-range variance
    (var_w tan^2(beta), the variance the height estimator solves for) is below
    ``UNKNOWN_RHO_VAR``, the variance ``estimate_pose`` gives a landmark without a height;
    above it the estimate says less than no estimate. No variance given: every finite one."""
    w = np.asarray(inv_height, dtype=np.float64).ravel()
    known = np.isfinite(w)
    if inv_height_var is None:
        return known
    t = np.tan(np.asarray(beta, dtype=np.float64).ravel())
    with np.errstate(invalid="ignore"):
        var_rho = np.asarray(inv_height_var, dtype=np.float64).ravel() * t * t
    return known & np.isfinite(var_rho) & (var_rho < UNKNOWN_RHO_VAR)


def levelled_bearings(rays: np.ndarray, mount: CameraMount) -> tuple[np.ndarray, np.ndarray]:
    """(alpha, beta) of camera-frame rays expressed in the levelled (robot-axis) frame."""
    n = np.asarray(rays, dtype=np.float64).reshape(-1, 3) @ mount.rotation().T
    return azimuth_elevation(n)


def _safe_tan(beta: np.ndarray) -> np.ndarray:
    t = np.tan(beta)
    return np.where(np.abs(t) < _MIN_TAN, np.where(t < 0, -_MIN_TAN, _MIN_TAN), t)


def inverse_range(beta: np.ndarray, inv_height: np.ndarray) -> np.ndarray:
    """rho = 1/r = w tan(beta): in-plane inverse distance of a landmark."""
    return np.asarray(inv_height, dtype=np.float64) * np.tan(np.asarray(beta, dtype=np.float64))


def inverse_height_from_range(beta: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """w = rho / tan(beta) (tan floored away from zero)."""
    return np.asarray(rho, dtype=np.float64) / _safe_tan(np.asarray(beta, dtype=np.float64))


def jacobian(sin_alpha: np.ndarray, cos_alpha: np.ndarray, rho: np.ndarray, w_sin2_beta: np.ndarray, *,
             forward: float = 0.0, lateral: float = 0.0) -> np.ndarray:
    """Image Jacobian d(alpha, beta)/d(x, z, theta) of each landmark, shape (2, N, 3):
    ``[0]`` the azimuth rows, ``[1]`` the elevation rows (``reshape(2 * N, 3)`` stacks them).

    The landmarks are given by sin and cos of their levelled azimuth, their in-plane
    inverse range rho = w tan(beta) and w sin^2(beta) = rho sin(beta) cos(beta)
    (w = 1/y, 1/m): the forms the estimator has at hand at each predicted bearing,
    so it evaluates no trigonometry. forward/lateral: camera offset from the robot's
    rotation centre (m). The derivative is with respect to a small robot motion in
    the robot's own frame (see the module docstring).
    """
    sa, ca = sin_alpha, cos_alpha
    J = np.empty((2, len(sa), 3))
    J[0, :, 0] = -rho * ca
    J[0, :, 1] = rho * sa
    J[0, :, 2] = -1.0 - rho * (forward * ca + lateral * sa)
    J[1, :, 0] = w_sin2_beta * sa
    J[1, :, 1] = w_sin2_beta * ca
    J[1, :, 2] = w_sin2_beta * (forward * sa - lateral * ca)
    return J


def _transform_vectors(pose: Pose2, forward: float, lateral: float):
    """(rotation cos, sin, d) with d = m - p*m, the camera displacement reversed (taught frame)."""
    c, s = math.cos(pose.theta), math.sin(pose.theta)
    pm_x = pose.x + c * lateral + s * forward
    pm_z = pose.z - s * lateral + c * forward
    return c, s, np.array([lateral - pm_x, forward - pm_z])


def predict_bearings(taught_alpha, taught_beta, rho, pose: Pose2, forward: float = 0.0,
                     lateral: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Exact bearings of landmarks (taught bearings, inverse range rho) from ``pose`` relative to the taught pose."""
    a0 = np.asarray(taught_alpha, dtype=np.float64)
    t0 = np.tan(np.asarray(taught_beta, dtype=np.float64))
    c, s, d = _transform_vectors(pose, forward, lateral)
    ux = np.sin(a0) + rho * d[0]
    uz = np.cos(a0) + rho * d[1]
    vx = c * ux - s * uz
    vz = s * ux + c * uz
    return np.arctan2(vx, vz), np.arctan2(t0, np.hypot(vx, vz))


@dataclass(frozen=True)
class VBCQuality:
    """How far to trust a VBC pose.

    n_landmarks: landmarks used; n_inliers: those whose error the pose explains
    (robust normalised residual < 3); n_known: those inliers whose range is known
    (``known_range``), the only ones that fix the translation: a landmark without
    one is taken as far away and informs the heading; rms_residual: rad, over inliers;
    condition: condition number of the (unit-scaled) normal matrix, large when
    the geometry does not constrain the pose; iterations, converged: Gauss-Newton.
    """

    n_landmarks: int
    n_inliers: int
    rms_residual: float
    condition: float
    iterations: int
    converged: bool
    n_known: int = 0

    def as_dict(self) -> dict:
        return {"n_landmarks": self.n_landmarks, "n_inliers": self.n_inliers, "n_known": self.n_known,
                "rms_residual": self.rms_residual, "condition": self.condition,
                "iterations": self.iterations, "converged": self.converged}


@dataclass(frozen=True)
class VBCResult:
    """Robot pose relative to the taught (keyframe) pose, its covariance and quality."""

    pose: Pose2
    covariance: np.ndarray
    inliers: np.ndarray
    quality: VBCQuality
    ok: bool = True
    info: dict = field(default_factory=dict)


def _robust_weights(d2: np.ndarray, loss: str, k: float) -> np.ndarray:
    """IRLS weights from squared normalised residuals."""
    if loss == "huber":
        d = np.sqrt(d2)
        return np.where(d <= k, 1.0, k / np.maximum(d, 1e-12))
    if loss == "cauchy":
        return 1.0 / (1.0 + d2 / (k * k))
    raise ValueError(f"unknown robust loss {loss!r} (expected 'huber' or 'cauchy')")


class _Linearisation:
    """Residuals, Jacobian rows and rho-sensitivities of all landmarks at one pose (no trig but atan2).

    At the predicted direction v (module docstring): sin(alpha) = v_x/|v|, cos(alpha) = v_z/|v|,
    the current inverse range is rho0/|v|, and w sin^2(beta) = rho sin(beta) cos(beta) with
    tan(beta) = tan(beta0)/|v|, so ``jacobian`` needs no further trigonometry. ``J`` stacks
    the azimuth rows over the elevation rows, as the residuals are stacked.
    """

    __slots__ = ("ra", "rb", "J", "da", "db")

    def __init__(self, s0, c0, t0, rho, a1, b1, pose: Pose2, forward: float, lateral: float,
                 with_sensitivity: bool):
        c, s, d = _transform_vectors(pose, forward, lateral)
        ux = s0 + rho * d[0]
        uz = c0 + rho * d[1]
        vx = c * ux - s * uz
        vz = s * ux + c * uz
        n2 = vx * vx + vz * vz
        n = np.sqrt(n2)
        self.ra = (a1 - np.arctan2(vx, vz) + math.pi) % (2 * math.pi) - math.pi
        self.rb = b1 - np.arctan2(t0, n)
        sa, ca = vx / n, vz / n
        rc = rho / n
        ws2 = rc * t0 * n / (n2 + t0 * t0)
        self.J = jacobian(sa, ca, rc, ws2, forward=forward, lateral=lateral).reshape(2 * len(a1), 3)
        if with_sensitivity:
            hx, hz = c * d[0] - s * d[1], s * d[0] + c * d[1]
            self.da = (vz * hx - vx * hz) / n2
            self.db = -t0 / (t0 * t0 + n2) * (vx * hx + vz * hz) / n
        else:
            self.da = self.db = None


def tilt_rotation(tilt) -> np.ndarray:
    """The rotation exp([w]x), w = (tilt[0], 0, tilt[1]): the camera's tilt since teaching, about the
    levelled x axis (pitch) and z axis (roll), that takes the current levelled rays back to the taught
    mounting (``estimate_pose``)."""
    w = np.array([tilt[0], 0.0, tilt[1]], dtype=np.float64)
    a = float(np.linalg.norm(w))
    if a < 1e-15:
        return np.eye(3)
    k = w / a
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(a) * K + (1.0 - math.cos(a)) * (K @ K)


def _tilted_bearings(n1: np.ndarray, R: np.ndarray):
    """Bearings of the rays ``n1`` (N, 3) turned by ``R`` and their derivatives with respect to a small
    further turn d = (d_x, 0, d_z) on the left (dn = d x n): for a unit n = (x, y, z), r = |(x, z)|,
        d alpha / d_x = -x y / r^2,   d alpha / d_z = -z y / r^2,
        d beta  / d_x = -z / r,       d beta  / d_z =  x / r.
    Returns (alpha, beta, Jm) with Jm (2N, 2) stacked like the residuals (azimuths over elevations)."""
    n = n1 @ R.T
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    r2 = np.maximum(x * x + z * z, 1e-12)
    r = np.sqrt(r2)
    Jm = np.empty((2 * len(n), 2))
    Jm[:len(n), 0] = -x * y / r2
    Jm[:len(n), 1] = -z * y / r2
    Jm[len(n):, 0] = -z / r
    Jm[len(n):, 1] = x / r
    return np.arctan2(x, z), np.arctan2(y, r), Jm


def _tilt_of(R: np.ndarray) -> np.ndarray:
    """(pitch, roll) of a tilt rotation (the log map's x and z components)."""
    a = math.acos(max(-1.0, min(1.0, (np.trace(R) - 1.0) / 2.0)))
    f = 0.5 if a < 1e-9 else a / (2.0 * math.sin(a))
    return np.array([f * (R[2, 1] - R[1, 2]), f * (R[1, 0] - R[0, 1])])


def estimate_pose(taught_alpha, taught_beta, inv_heights, current_alpha, current_beta,
                  inv_height_var=None, *, forward: float = 0.0, lateral: float = 0.0,
                  sigma: float = 1.5e-3, initial: Pose2 | None = None, max_iter: int = 40,
                  tol: float = 1e-5, huber_iters: int = 2, min_landmarks: int = 4,
                  tilt_prior: tuple | None = None) -> VBCResult:
    """Planar pose of the robot relative to the taught pose from matched bearings.

    taught_alpha/beta: levelled bearings stored with the keyframe; inv_heights:
    w = 1/y per landmark (NaN = unknown: the landmark then counts for heading,
    its range treated as uncertain); current_alpha/beta: the same landmarks now.
    inv_height_var: variance of w (1/m^2), propagated into each landmark's
    bearing noise. sigma: bearing noise (rad), e.g. 1 px / focal length.
    forward/lateral: camera offset from the rotation centre. initial: a pose
    guess (e.g. the last fix moved by odometry); default: a robust heading guess.

    Gauss-Newton on the exact bearing model with robust IRLS: at least
    ``huber_iters`` Huber iterations (with a MAD scale estimate, floored at
    sigma) until the steps are small, then Cauchy with that scale frozen, which
    down-weights gross outliers to ~0, until the step is below ``tol`` (m, rad).

    tilt_prior: (mean (2,), information (2, 2)) of the camera's tilt since teaching, (pitch, roll) in
    rad about the levelled x and z axes. Given, the tilt is solved with the pose (five unknowns, the
    prior as a Gaussian term) and ``info['tilt']`` / ``info['tilt_cov']`` hold its estimate: the current
    rays are turned by it before they are compared with the taught ones. A camera pitched or rolled by
    1 deg on its mount since teaching (a knock, a load, tyre pressure) moves every bearing by up to
    7 px, which a planar pose explains as 10-20 cm of lateral offset. Yaw is the heading's.
    """
    a0 = np.asarray(taught_alpha, dtype=np.float64).ravel()
    b0 = np.asarray(taught_beta, dtype=np.float64).ravel()
    a1 = np.asarray(current_alpha, dtype=np.float64).ravel()
    b1 = np.asarray(current_beta, dtype=np.float64).ravel()
    w = np.asarray(inv_heights, dtype=np.float64).ravel()
    n = len(a0)
    if not (len(b0) == len(a1) == len(b1) == len(w) == n):
        raise ValueError("estimate_pose: all landmark arrays must have the same length")
    t0 = np.tan(b0)
    known = np.isfinite(w)
    rho = np.where(known, w * t0, 0.0)
    if inv_height_var is None:
        var_rho = np.zeros(n)
    else:
        var_rho = np.asarray(inv_height_var, dtype=np.float64).ravel() * t0 * t0
    var_rho = np.where(known & np.isfinite(var_rho), var_rho, UNKNOWN_RHO_VAR)
    if n < min_landmarks:
        return _failed(n, initial, "too few landmarks")
    s0, c0 = np.sin(a0), np.cos(a0)

    if initial is None:
        # Turning shifts every azimuth by -dtheta: the median azimuth change is a robust heading guess.
        initial = Pose2(0.0, 0.0, -float(np.median((a1 - a0 + math.pi) % (2 * math.pi) - math.pi)))
    pose = initial
    tilted = tilt_prior is not None
    if tilted:
        tilt0 = np.asarray(tilt_prior[0], dtype=np.float64).reshape(2)
        info0 = np.asarray(tilt_prior[1], dtype=np.float64).reshape(2, 2)
        n1 = rays_from_angles(a1, b1)
        R_tilt = tilt_rotation(tilt0)
        a1, b1, Jm = _tilted_bearings(n1, R_tilt)
    scale = sigma
    converged = False
    phase = "huber"          # Huber with a re-estimated scale until the steps are small, then Cauchy
    huber_done = 0
    it = 0
    var = None
    for it in range(1, max_iter + 1):
        lin = _Linearisation(s0, c0, t0, rho, a1, b1, pose, forward, lateral, phase == "huber")
        r = np.concatenate((lin.ra, lin.rb))
        if phase == "huber":
            # Height uncertainty inflates each landmark's noise by how much its predicted bearing
            # moves with rho at this pose; frozen in the Cauchy phase, as pose-dependent weights
            # would let Gauss-Newton cycle.
            infl = np.concatenate((lin.da * lin.da * var_rho, lin.db * lin.db * var_rho))
            # Robust scale: the median of sqrt(d2/2) is 0.8326 for Gaussian residuals of unit
            # scale (Rayleigh median / sqrt 2); never below the stated noise nor wildly above it.
            d2 = _pair_sum(r * r / (scale * scale + infl))
            scale = max(sigma, min(float(np.median(np.sqrt(d2 / 2.0))) / 0.8326 * scale, 50 * sigma))
            var = scale * scale + infl
        d2 = _pair_sum(r * r / var)
        wts = _robust_weights(d2, "huber", 2.0) if phase == "huber" else _robust_weights(d2, "cauchy", 2.5)
        W = np.concatenate((wts, wts)) / var
        J = np.hstack((lin.J, -Jm)) if tilted else lin.J
        JW = J.T * W
        H, g = JW @ J + 1e-12 * np.eye(J.shape[1]), JW @ r
        if tilted:
            H[3:, 3:] += info0
            g[3:] += info0 @ (tilt0 - _tilt_of(R_tilt))
        try:
            delta = np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            return _failed(n, pose, "singular normal matrix")
        pose = pose.compose(Pose2(*delta[:3]))
        if tilted:
            R_tilt = tilt_rotation(delta[3:]) @ R_tilt
            a1, b1, Jm = _tilted_bearings(n1, R_tilt)
        step = float(np.max(np.abs(delta)))
        if phase == "huber":
            huber_done += 1
            if huber_done >= huber_iters and (step < 1e-3 or huber_done >= 4 * huber_iters):
                phase = "cauchy"
        elif step < tol:
            converged = True
            break

    lin = _Linearisation(s0, c0, t0, rho, a1, b1, pose, forward, lateral, False)
    r = np.concatenate((lin.ra, lin.rb))
    d2 = _pair_sum(r * r / var)
    inliers = d2 < 9.0 * 2
    W = np.concatenate((inliers, inliers)) / var
    J = np.hstack((lin.J, -Jm)) if tilted else lin.J
    H = (J.T * W) @ J
    if tilted:
        H[3:, 3:] += info0
    cond = _condition(H)
    try:
        cov_all = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        cov_all = np.full(H.shape, np.inf)
    cov = cov_all[:3, :3]
    extra = {"tilt": _tilt_of(R_tilt), "tilt_cov": cov_all[3:, 3:]} if tilted else {}
    n_in = int(inliers.sum())
    rms = float(np.sqrt(np.mean(np.concatenate([lin.ra[inliers], lin.rb[inliers]]) ** 2))) if n_in else math.inf
    n_known = int((inliers & known_range(b0, w, inv_height_var)).sum())
    q = VBCQuality(n, n_in, rms, cond, it, converged, n_known)
    ok = converged and n_in >= min_landmarks and cond < 1e9
    return VBCResult(pose, cov, inliers, q, ok, extra)


def _pair_sum(x: np.ndarray) -> np.ndarray:
    """Per-landmark sum of the azimuth and elevation halves of a stacked vector."""
    m = len(x) // 2
    return x[:m] + x[m:]


def _condition(H: np.ndarray) -> float:
    """Condition number of the normal matrix after scaling it to unit diagonal (units differ per axis)."""
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    Hs = H / np.outer(d, d)
    try:
        return float(np.linalg.cond(Hs))
    except np.linalg.LinAlgError:
        return math.inf


def _failed(n: int, pose: Pose2 | None, why: str) -> VBCResult:
    q = VBCQuality(n, 0, math.inf, math.inf, 0, False)
    return VBCResult(pose or Pose2(), np.full((3, 3), np.inf), np.zeros(n, bool), q, False, {"reason": why})


class InverseHeightEstimator:
    """Per-track inverse height w = 1/y from known planar motion (odometry) during teaching.

    Each track is anchored at its first observation (bearings alpha0, beta0 at
    odometry pose P0). At a later observation (alpha_k, beta_k) with the robot
    at p = P0^-1 Pk, the exact model (module docstring) gives
    v = rot(theta)^T (g0 + rho0 d) with g0 = (sin alpha0, cos alpha0), which must
    point along s = (sin alpha_k, cos alpha_k) with length tan(beta0)/tan(beta_k):
        s x v = 0                           (azimuth: lateral parallax)
        tan(beta_k) (s . v) = tan(beta0)    (elevation: forward motion)
    Both are *linear* in rho0 = w tan(beta0), each with residual ~ one bearing
    error. The anchor's own bearing error would enter every row alike and not
    average out, so it is estimated too: the unknowns are (rho0, d alpha0,
    d tan beta0), linear to first order, with the anchor observation as a prior
    row for each correction. Pooling all frames of a track is then a 3x3 least
    squares kept as running sums. The variance comes from the bearing noise,
    inflated by the fit's own chi^2 when that is larger (bad tracks).
    ``bearings_at`` gives the de-noised bearings of tracks at any pose, which is
    what a keyframe should store (its own single observation is noisier).
    """

    def __init__(self, mount: CameraMount = CameraMount(), sigma: float = 1.5e-3):
        self.forward = mount.forward
        self.lateral = mount.lateral
        self.sigma = sigma
        self._ids = np.zeros(0, dtype=np.int64)
        self._a0 = np.zeros(0)
        self._t0 = np.zeros(0)
        self._pose0 = np.zeros((0, 3))
        self._A = np.zeros((0, 3, 3))     # normal matrix of (rho0, d alpha0, d tan beta0)
        self._r = np.zeros((0, 3))        # right-hand side
        self._bb = np.zeros(0)            # sum of squared right-hand sides (for chi^2)
        self._n = np.zeros(0, dtype=np.int64)

    _FIELDS = ("_ids", "_a0", "_t0", "_pose0", "_A", "_r", "_bb", "_n")

    def __len__(self) -> int:
        return len(self._ids)

    def observe(self, track_ids, alpha, beta, odom: Pose2) -> None:
        """Add one frame: levelled bearings of tracked landmarks at odometry pose ``odom``.

        Tracks not seen before are anchored here; tracks missing from ``track_ids`` are forgotten.
        """
        ids = np.asarray(track_ids, dtype=np.int64).ravel()
        alpha = np.asarray(alpha, dtype=np.float64).ravel()
        beta = np.asarray(beta, dtype=np.float64).ravel()
        self._select(np.isin(self._ids, ids))
        seen, pos = self._find(ids)
        if seen.any():
            self._accumulate(pos[seen], alpha[seen], beta[seen], odom)
        if (~seen).any():
            self._append(ids[~seen], alpha[~seen], beta[~seen], odom)

    def _find(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if not len(self._ids):
            return np.zeros(len(ids), bool), np.zeros(len(ids), np.int64)
        pos = np.minimum(np.searchsorted(self._ids, ids), len(self._ids) - 1)
        return self._ids[pos] == ids, pos

    def _select(self, keep: np.ndarray) -> None:
        for name in self._FIELDS:
            setattr(self, name, getattr(self, name)[keep])

    def _append(self, ids, alpha, beta, odom: Pose2) -> None:
        m = len(ids)
        A = np.zeros((m, 3, 3))
        A[:, 1, 1] = 1.0                              # prior row: d alpha0 = 0 +- sigma
        A[:, 2, 2] = np.cos(beta) ** 4                # prior row: cos^2(beta0) d tan beta0 = 0 +- sigma
        new = {"_ids": ids, "_a0": alpha, "_t0": np.tan(beta), "_pose0": np.tile(odom.as_array(), (m, 1)),
               "_A": A, "_r": np.zeros((m, 3)), "_bb": np.zeros(m), "_n": np.zeros(m, dtype=np.int64)}
        for name in self._FIELDS:
            setattr(self, name, np.concatenate([getattr(self, name), new[name]]))
        self._select(np.argsort(self._ids, kind="stable"))

    def _relative(self, pos, odom: Pose2):
        """p = P0^-1 Pk per anchor (vectorised Pose2.between): (px, pz, theta)."""
        p0 = self._pose0[pos]
        c0, s0 = np.cos(p0[:, 2]), np.sin(p0[:, 2])
        dxw, dzw = odom.x - p0[:, 0], odom.z - p0[:, 1]
        return c0 * dxw - s0 * dzw, s0 * dxw + c0 * dzw, odom.theta - p0[:, 2]

    def _accumulate(self, pos, alpha, beta, odom: Pose2) -> None:
        px, pz, th = self._relative(pos, odom)
        c, s = np.cos(th), np.sin(th)
        f, l = self.forward, self.lateral
        dx = l - (px + c * l + s * f)       # d = m - p*m, in the anchor frame
        dz = f - (pz - s * l + c * f)
        a0 = self._a0[pos]
        sa0, ca0 = np.sin(a0), np.cos(a0)
        gx, gz = c * sa0 - s * ca0, s * sa0 + c * ca0          # R^T g0
        gpx, gpz = c * ca0 + s * sa0, s * ca0 - c * sa0        # R^T dg0/dalpha0
        hx, hz = c * dx - s * dz, s * dx + c * dz              # R^T d
        sx, sz = np.sin(alpha), np.cos(alpha)
        tk = np.tan(beta)
        cb2 = np.cos(beta) ** 2      # d/dbeta_k of tan(beta_k)(s.v) ~ 1/cos^2: rescale rows to ~ rad
        row1 = np.column_stack((sx * hz - sz * hx, sx * gpz - sz * gpx, np.zeros(len(pos))))
        b1 = -(sx * gz - sz * gx)
        row2 = np.column_stack((cb2 * tk * (sx * hx + sz * hz), cb2 * tk * (sx * gpx + sz * gpz), -cb2))
        b2 = cb2 * (self._t0[pos] - tk * (sx * gx + sz * gz))
        self._A[pos] += row1[:, :, None] * row1[:, None, :] + row2[:, :, None] * row2[:, None, :]
        self._r[pos] += row1 * b1[:, None] + row2 * b2[:, None]
        self._bb[pos] += b1 * b1 + b2 * b2
        self._n[pos] += 1

    def _solve(self, p):
        """(rho0, d alpha0, d tan beta0), var(rho0), informative mask for stored rows ``p``."""
        A, r = self._A[p], self._r[p]
        x = np.linalg.solve(A + 1e-15 * np.eye(3), r[:, :, None])[:, :, 0]
        Ainv = np.linalg.inv(A + 1e-15 * np.eye(3))
        chi2 = np.maximum(self._bb[p] - np.einsum("ni,ni->n", x, r), 0.0)
        dof = np.maximum(2 * self._n[p] - 3, 1)
        s2 = np.maximum(self.sigma ** 2, chi2 / dof)
        var_rho = s2 * Ainv[:, 0, 0]
        informative = (self._n[p] >= 2) & (Ainv[:, 0, 0] < 1e12)
        return x, var_rho, informative

    def estimate(self, track_ids=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids, w, var_w) for ``track_ids`` (all tracks if None); unknown tracks get NaN and inf."""
        if track_ids is None:
            ids, found, pos = self._ids.copy(), np.ones(len(self._ids), bool), np.arange(len(self._ids))
        else:
            ids = np.asarray(track_ids, dtype=np.int64).ravel()
            found, pos = self._find(ids)
        w = np.full(len(ids), np.nan)
        var = np.full(len(ids), np.inf)
        if not found.any():
            return ids, w, var
        p = pos[found]
        x, var_rho, ok = self._solve(p)
        t0 = self._t0[p] + x[:, 2]
        t0 = np.where(np.abs(t0) < _MIN_TAN, np.copysign(_MIN_TAN, t0), t0)
        w[found] = np.where(ok, x[:, 0] / t0, np.nan)
        var[found] = np.where(ok, var_rho / (t0 * t0), np.inf)
        return ids, w, var

    def bearings_at(self, track_ids, odom: Pose2, max_baseline: float = math.inf
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """De-noised levelled bearings of tracks seen from ``odom``: (alpha, beta, valid).

        Predicted by the exact model from the track's corrected anchor bearings and
        rho0; invalid (NaN) for unknown tracks or tracks without parallax yet, and for
        tracks anchored farther than ``max_baseline`` (m) from ``odom``: the prediction
        carries the odometry's heading error between the anchor and ``odom`` (wheel slip
        turns it by ~1 deg per metre), which would bias every fix against a keyframe that
        stores it, while the observation's own noise averages out over many landmarks.
        """
        ids = np.asarray(track_ids, dtype=np.int64).ravel()
        found, pos = self._find(ids)
        alpha = np.full(len(ids), np.nan)
        beta = np.full(len(ids), np.nan)
        if not found.any():
            return alpha, beta, found
        p = pos[found]
        x, _, ok = self._solve(p)
        a0 = self._a0[p] + x[:, 1]
        b0 = np.arctan(self._t0[p] + x[:, 2])
        rho = np.where(ok, x[:, 0], 0.0)
        px, pz, th = self._relative(p, odom)
        c, s = np.cos(th), np.sin(th)
        f, l = self.forward, self.lateral
        dx = l - (px + c * l + s * f)
        dz = f - (pz - s * l + c * f)
        ux, uz = np.sin(a0) + rho * dx, np.cos(a0) + rho * dz
        vx, vz = c * ux - s * uz, s * ux + c * uz
        alpha[found] = np.arctan2(vx, vz)
        beta[found] = np.arctan2(np.tan(b0), np.hypot(vx, vz))
        valid = np.zeros(len(ids), bool)
        valid[found] = ok & (np.hypot(px, pz) <= max_baseline)
        return alpha, beta, valid

    def anchor_bearings(self, track_ids) -> tuple[np.ndarray, np.ndarray]:
        """Anchor (first-seen) bearings of tracks, for diagnostics."""
        ids = np.asarray(track_ids, dtype=np.int64).ravel()
        pos = np.searchsorted(self._ids, ids)
        return self._a0[pos], np.arctan(self._t0[pos])
