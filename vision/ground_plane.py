"""The ground plane in (u, v, disparity) space (chapter 11.2.2.2, equations 11.3-11.8).

Derivation (camera frame x right, y down, z forward; unit vector g pointing
down, i.e. toward the floor; camera optical centre H above the floor). Floor
points X satisfy g . X = H. With the normalised ray r = (x/z, y/z, 1) =
((u - cx)/fx, (v - cy)/fy, 1) a floor point is X = z r, so z = H / (g . r)
and its disparity D = fx B / z is

    D(u, v) = (fx B / H) g . r(u, v)                        (linear in u and v)
            = rho_1 u + rho_2 v + rho_3                     (11.7)

    rho_1 = w_x / fx,  rho_2 = w_y / fy,  rho_3 = w_z - rho_1 cx - rho_2 cy,
    w = (fx B / H) g.

Conversely a fitted plane gives w = (rho_1 fx, rho_2 fy, rho_3 + rho_1 cx + rho_2 cy),
the camera height H = fx B / |w| and the down direction g = w / |w|: the plane
in disparity space holds the camera's height, pitch and roll above the floor.

A camera mounted with pitch p (positive looking down) and roll 0 has
g = R_rc^T (0, 1, 0) = (0, cos p, sin p).

Height of any pixel's point above the floor (used for thresholds in metres):
with D_g the plane's disparity at that pixel (the disparity the floor would
have there), the point X = (fx B / D) r has g . X = H D_g / D, so

    e = H - g . X = H (D - D_g) / D.

A point h above the floor on the pixel's ray has D = D_g H / (H - h); h below
it (a step down of depth h) has D = D_g H / (H + h). Above the horizon D_g <= 0
and every point with D > 0 is above the floor, as it must be.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Optional

import numpy as np

from vbnav.vision.geometry import rot_x, rot_z
from vbnav.vision.stereo import StereoRig


@dataclass(frozen=True)
class FloorGeometry:
    """The floor seen from the camera: height H (m) and unit down vector g (camera frame)."""

    height: float
    down: tuple[float, float, float]

    @property
    def pitch(self) -> float:
        """rad, positive looking down (for a camera without roll)."""
        g = self.down
        return math.atan2(g[2], math.hypot(g[0], g[1]))

    @property
    def roll(self) -> float:
        """rad, rotation of the image about the optical axis (positive: floor tilts toward +x)."""
        g = self.down
        return math.atan2(g[0], g[1])

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Down g, forward f (optical axis projected on the floor) and lateral l = g x f (right)."""
        g = np.asarray(self.down, dtype=float)
        f = np.array([0.0, 0.0, 1.0]) - g[2] * g
        if np.linalg.norm(f) < 1e-9:         # camera looking straight down: forward is image up
            f = np.array([0.0, -1.0, 0.0]) - (-g[1]) * g
        f /= np.linalg.norm(f)
        return g, f, np.cross(g, f)


@dataclass(frozen=True)
class DisparityPlane:
    """D(u, v) = rho_1 u + rho_2 v + rho_3 (11.7)."""

    rho: tuple[float, float, float]

    def predict(self, u, v):
        r1, r2, r3 = self.rho
        return r1 * u + r2 * v + r3

    def image(self, height: int, width: int) -> np.ndarray:
        """The plane's disparity at every pixel, float32 HxW."""
        u, v = pixel_grid(height, width)
        r1, r2, r3 = (np.float32(x) for x in self.rho)
        return u * r1 + v * r2 + r3

    def floor(self, rig: StereoRig) -> FloorGeometry:
        """Camera height and down direction implied by this plane (module docstring)."""
        r1, r2, r3 = self.rho
        w = np.array([r1 * rig.fx, r2 * rig.fy, r3 + r1 * rig.cx + r2 * rig.cy])
        n = float(np.linalg.norm(w))
        if n < 1e-12:
            raise ValueError("degenerate disparity plane (all coefficients zero)")
        return FloorGeometry(rig.fb / n, tuple(float(x) for x in w / n))

    def horizon_v(self, u: float) -> float:
        """Image row where the plane's disparity reaches zero (the horizon) at column u."""
        r1, r2, r3 = self.rho
        return -(r1 * u + r3) / r2 if abs(r2) > 1e-12 else math.inf


@lru_cache(maxsize=8)
def pixel_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Column and row index images (float32, read-only), cached per size."""
    u = np.broadcast_to(np.arange(width, dtype=np.float32)[None, :], (height, width))
    v = np.broadcast_to(np.arange(height, dtype=np.float32)[:, None], (height, width))
    return u, v


def plane_from_floor(rig: StereoRig, height: float, down) -> DisparityPlane:
    """The disparity plane of a floor ``height`` m below the camera along unit vector ``down``."""
    if not height > 0:
        raise ValueError(f"camera height above the floor must be positive, got {height}")
    g = np.asarray(down, dtype=float)
    g = g / np.linalg.norm(g)
    w = rig.fb / height * g
    r1, r2 = w[0] / rig.fx, w[1] / rig.fy
    return DisparityPlane((float(r1), float(r2), float(w[2] - r1 * rig.cx - r2 * rig.cy)))


def expected_plane(rig: StereoRig, height: float, pitch: float = 0.0, roll: float = 0.0) -> DisparityPlane:
    """The plane predicted by the camera mounting: ``height`` m, ``pitch`` rad down, ``roll`` rad."""
    R_rc = rot_x(-pitch) @ rot_z(roll)          # camera axes in the robot frame (yaw does not matter)
    return plane_from_floor(rig, height, R_rc.T @ np.array([0.0, 1.0, 0.0]))


@dataclass(frozen=True)
class PlaneFitParams:
    """Robust ground-plane fit settings.

    The inlier band is a height above/below the floor (``inlier_height`` m) converted to
    disparity per point, widened to ``inlier_min_px`` for the matcher's noise.
    """

    step: int = 4                       # sample every step-th row and column
    min_disparity: float = 0.5          # ground is only sought where the prior predicts more, px
    prior_tolerance_rel: float = 0.35   # seed pool: |D - D_prior| < rel * D_prior + px
    prior_tolerance_px: float = 2.0
    inlier_height: float = 0.02         # m
    inlier_min_px: float = 0.35         # px
    hypotheses: int = 64
    score_points: int = 2000            # hypotheses are scored on at most this many pool points
    refine_iterations: int = 3
    min_inliers: int = 60
    max_tilt_change_deg: float = 8.0    # fitted floor normal vs prior
    max_height_ratio: float = 1.5       # fitted height within [1/r, r] of the prior
    # Tighter bounds from a known mounting (None: only the two above). A fit outside them is
    # rejected: the camera cannot be that far off its mount (docs/obstacles.md derives them).
    max_height_change: Optional[float] = None      # m, |fitted camera height - prior|
    max_pitch_change_deg: Optional[float] = None   # |fitted pitch - prior pitch|
    max_roll_change_deg: Optional[float] = None    # |fitted roll - prior roll|
    seed: int = 0


@dataclass(frozen=True)
class PlaneFit:
    plane: DisparityPlane
    floor: FloorGeometry
    ok: bool                  # a plane was fitted and passed the plausibility checks
    used_prior: bool          # the prior was returned (too little ground, or implausible fit)
    inliers: int
    pool: int
    reason: str = ""

    @property
    def inlier_fraction(self) -> float:
        return self.inliers / self.pool if self.pool else 0.0


def _band(pred: np.ndarray, w_norm: np.ndarray, rig: StereoRig, p: PlaneFitParams) -> np.ndarray:
    # Height h of the plane's floor point moved to disparity: D_g * h / H, with H = fB / |w|.
    return np.maximum(p.inlier_min_px, pred * (p.inlier_height * w_norm / rig.fb))


def _w(rho: np.ndarray, rig: StereoRig) -> np.ndarray:
    """Rows of rho (..., 3) -> (fx B / H) g, see the module docstring."""
    return np.stack([rho[..., 0] * rig.fx, rho[..., 1] * rig.fy,
                     rho[..., 2] + rho[..., 0] * rig.cx + rho[..., 1] * rig.cy], axis=-1)


def _plausible(rho: np.ndarray, rig: StereoRig, prior: Optional[FloorGeometry], p: PlaneFitParams) -> np.ndarray:
    w = _w(rho, rig)
    n = np.linalg.norm(w, axis=-1)
    ok = n > 1e-9
    if prior is None:
        return ok & (w[..., 1] > 0)             # floor below the optical axis's horizon line
    g = w / np.where(ok, n, 1.0)[..., None]
    pd = prior.down
    cos_tilt = g[..., 0] * pd[0] + g[..., 1] * pd[1] + g[..., 2] * pd[2]
    height = rig.fb / np.where(ok, n, 1.0)
    ratio = height / prior.height
    ok = (ok & (cos_tilt > math.cos(math.radians(p.max_tilt_change_deg)))
          & (ratio < p.max_height_ratio) & (ratio > 1.0 / p.max_height_ratio))
    if p.max_height_change is not None:
        ok &= np.abs(height - prior.height) <= p.max_height_change
    if p.max_pitch_change_deg is not None:        # pitch and roll as FloorGeometry defines them
        pitch = np.arctan2(g[..., 2], np.hypot(g[..., 0], g[..., 1]))
        ok &= np.abs(np.degrees(pitch - prior.pitch)) <= p.max_pitch_change_deg
    if p.max_roll_change_deg is not None:
        roll = np.arctan2(g[..., 0], g[..., 1])
        ok &= np.abs(np.degrees(roll - prior.roll)) <= p.max_roll_change_deg
    return ok


def _least_squares(A: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Normal equations of D = rho . (u, v, 1), summed elementwise: numpy's BLAS matrix products
    spawn threads, which costs milliseconds on a busy 2-core machine for these small sizes."""
    u, v, dd = (x.astype(np.float64) for x in (A[:, 0], A[:, 1], d))
    n = float(len(dd))
    su, sv, suu, svv, suv = u.sum(), v.sum(), (u * u).sum(), (v * v).sum(), (u * v).sum()
    M = np.array([[suu, suv, su], [suv, svv, sv], [su, sv, n]])
    b = np.array([(u * dd).sum(), (v * dd).sum(), dd.sum()])
    return np.linalg.solve(M, b)


def _predict(rho: np.ndarray, A: np.ndarray) -> np.ndarray:
    """rho (3,) or (k, 3) applied to points A (n, 3) = (u, v, 1): (n,) or (k, n), without BLAS."""
    r = np.asarray(rho, dtype=np.float32)
    if r.ndim == 1:
        return A[:, 0] * r[0] + A[:, 1] * r[1] + r[2]
    return A[None, :, 0] * r[:, 0:1] + A[None, :, 1] * r[:, 1:2] + r[:, 2:3]


def fit_ground_plane(disparity: np.ndarray, rig: StereoRig, prior: Optional[DisparityPlane] = None,
                     params: PlaneFitParams = PlaneFitParams(), region: Optional[np.ndarray] = None) -> PlaneFit:
    """Robust fit of (11.7) to a disparity image (float32, NaN unknown).

    RANSAC on a subsampled grid: the pool is the points near the prior plane (the
    mounting's prediction; without a prior, the lower image half), 3-point hypotheses
    plus the prior itself are scored by inliers in a band of +-inlier_height metres,
    hypotheses whose floor tilts or lies far from the prior are rejected, and the best
    is refined by least squares on its inliers. Deterministic (seeded). ``region`` (bool HxW)
    restricts the samples further (vision/ground_model.py: the near band ahead). When the
    refined plane leaves the bounds, the best hypothesis inside them is kept unrefined.
    """
    p = params
    h, w = disparity.shape
    if (h, w) != (rig.height, rig.width):
        raise ValueError(f"disparity is {w}x{h} but the stereo rig is {rig.width}x{rig.height}")
    prior_floor = prior.floor(rig) if prior is not None else None
    s = p.step
    vs = np.arange(s // 2, h, s, dtype=np.float32)
    us = np.arange(s // 2, w, s, dtype=np.float32)
    d = disparity[s // 2::s, s // 2::s]
    V, U = np.meshgrid(vs, us, indexing="ij")
    valid = d > 0
    if region is not None:
        valid = valid & region[s // 2::s, s // 2::s]
    if prior is not None:
        dp = prior.predict(U, V)
        pool = valid & (dp > p.min_disparity) & (np.abs(d - dp) < p.prior_tolerance_rel * dp + p.prior_tolerance_px)
    else:
        pool = valid & (V > rig.cy)
    A = np.stack([U[pool], V[pool], np.ones(int(pool.sum()), np.float32)], axis=1)
    dd = d[pool]
    n = len(dd)

    def fallback(reason: str) -> PlaneFit:
        if prior is None:
            raise ValueError(f"ground plane fit failed and no prior plane was given: {reason}")
        return PlaneFit(prior, prior_floor, False, True, 0, n, reason)

    if n < p.min_inliers:
        return fallback(f"only {n} disparity samples where the floor is expected (need {p.min_inliers})")

    rng = np.random.default_rng(p.seed)
    idx = rng.integers(0, n, size=(p.hypotheses, 3))
    M = A[idx].astype(np.float64)                         # (hyp, 3, 3)
    det = np.linalg.det(M)
    good = np.abs(det) > 1e-6 * (rig.width * rig.height)
    rhos = np.linalg.solve(M[good], dd[idx][good].astype(np.float64)[..., None])[..., 0]
    if prior is not None:
        rhos = np.vstack([rhos, np.asarray(prior.rho)[None, :]])
    rhos = rhos[_plausible(rhos, rig, prior_floor, p)]
    if len(rhos) == 0:
        return fallback("no plausible plane hypothesis")

    sub = rng.choice(n, size=min(n, p.score_points), replace=False) if n > p.score_points else slice(None)
    As, ds = A[sub], dd[sub]
    pred = _predict(rhos, As)                                # (hyp, pts)
    wn = np.linalg.norm(_w(rhos, rig), axis=1).astype(np.float32)[:, None]
    scores = (np.abs(ds[None, :] - pred) < _band(pred, wn, rig, p)).sum(axis=1)
    rho = best = rhos[int(np.argmax(scores))]

    def inliers_of(r):
        pr = _predict(r, A)
        return np.abs(dd - pr) < _band(pr, np.float32(np.linalg.norm(_w(r, rig))), rig, p)

    inl = np.zeros(n, bool)
    for _ in range(p.refine_iterations):
        inl = inliers_of(rho)
        if inl.sum() < p.min_inliers:
            return fallback(f"only {int(inl.sum())} inliers after refinement")
        rho = _least_squares(A[inl], dd[inl])
    if not _plausible(rho[None, :], rig, prior_floor, p)[0]:
        # the least-squares step left the mounting's bounds: keep the best hypothesis inside them
        rho, inl = best, inliers_of(best)
        if inl.sum() < p.min_inliers:
            return fallback("refined plane is implausible for the camera mounting")
    plane = DisparityPlane(tuple(float(x) for x in rho))
    return PlaneFit(plane, plane.floor(rig), True, False, int(inl.sum()), n)
