"""A piecewise ground for real streets and floors: near/far bands hinged at their edges.

One plane (vision/ground_plane.py) is the whole floor only when the floor is flat. A street
has kerbs and raised pavements beside the lane, a crowned cross-section (camber) and grade
changes (ramps); a single RANSAC plane then tilts to catch pavement and road together, and
everything it does not fit turns into obstacles or negative obstacles. This model:

1. **Near band, mounting prior.** The band nearest the camera (prior-plane disparity from
   its largest value in view down to 1/``near_ratio`` of it) is fitted with three degrees of
   freedom, only on samples inside the corridor ahead (|lateral| <= ``corridor_half_width``
   on the prior's floor), and the fit must agree with the mounting within the bounds of
   PlaneFitParams (camera height in metres, pitch and roll in degrees). A fit beyond them
   is rejected (best hypothesis inside them, else the prior itself).
2. **Farther bands, hinged.** Band k covers disparities [b_k / band_ratio, b_k) of the band
   before it, b_k = b_{k-1} / band_ratio (equal depth ratios: each band is the same share of
   its distance). Its plane contains the line where the previous band's plane reaches
   disparity b_k (the ground is continuous: a kerb is a step, not ground), so it has one
   degree of freedom: the grade change theta about that line, bounded by
   atan(``max_grade_change``). In (u, v, D) the pencil of planes through that line is
   D = (1 + t) P_prev(u, v) - t b_k; theta is scored on a grid and refined in t by least
   squares on the inliers. A band with too little ground, or with a stretch (one of
   ``continuity_parts``) where under ``min_continuity`` of the samples lie on the plane (a
   plane folded onto the lower floor beyond a step meets it along a line only), continues the
   previous band's plane (t = 0); so does a band whose best bend gains under ``min_bend_gain``
   times the inliers of no bend. When a band cannot reach the ground within the bound (a ramp
   began late in the band before, which stayed flat), the band before is refitted at each grade
   and the pair with the most inliers kept (``_bend_the_band_before``).
3. **Camber beyond the corridor.** Outside the fitted corridor the ground may bend away
   laterally by ``cross_slope_allowance`` (rise over run) per metre: the obstacle and negative
   thresholds grow by allowance * (|lateral| - corridor_half_width) there
   (``GroundModel.tolerance``).

docs/obstacles.md derives the defaults (bounds, band ratio, grade and cross-slope allowances).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np

from vbnav.vision.ground_plane import (DisparityPlane, FloorGeometry, PlaneFit, PlaneFitParams,
                                       fit_ground_plane, pixel_grid)
from vbnav.vision.stereo import StereoRig


@dataclass(frozen=True)
class GroundModelParams:
    band_ratio: float = math.sqrt(2.0)     # far / near depth of a band
    near_ratio: float = math.sqrt(2.0)     # far / near depth of the near band
    max_bands: int = 10
    min_band_disparity: float = 1.0        # px; no band starts beyond this disparity
    corridor_half_width: float = 1.0       # m either side of the camera's line ahead
    max_grade_change: float = 0.08         # rise over run, between adjacent bands (1:12 ramps)
    cross_slope_allowance: float = 0.06    # rise over run per metre beyond the corridor (camber)
    grade_steps: int = 17                  # grade-change candidates scored per band
    min_band_inliers: int = 30
    continuity_parts: int = 4              # the band is checked in this many stretches...
    min_continuity: float = 0.5            # ...each with at least this share of its samples on the plane
    min_bend_gain: float = 1.1             # a bend must hold this many times the inliers of no bend
    score_points: int = 1500
    min_height_fraction: float = 0.25      # camera height above a band's plane vs the band before


@dataclass(frozen=True)
class GroundBand:
    plane: DisparityPlane
    floor: FloorGeometry
    near_disparity: float       # the band holds pixels where the previous band's plane is below this
    grade_change: float         # rad about the hinge, positive uphill (0 for the near band)
    inliers: int
    pool: int
    fitted: bool
    reason: str = ""


@dataclass
class GroundModel:
    bands: list[GroundBand]
    near: PlaneFit                          # the near band's fit (camera height, pitch, roll)
    params: GroundModelParams = field(default_factory=GroundModelParams)
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def images(self, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        """Per pixel: the ground's disparity D_g and the camera height above that band's plane
        (float32 HxW both, cached: read-only)."""
        key = (height, width)
        if key not in self._cache:
            self._cache[key] = self._images(height, width)
        return self._cache[key]

    def _images(self, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        Dg = self.bands[0].plane.image(height, width).copy()
        H = np.full((height, width), np.float32(self.bands[0].floor.height))
        u, v = pixel_grid(height, width)

        def row_where(plane: DisparityPlane, d: float) -> float:
            """The lowest row at which the plane still reads d at either image edge (D grows downward)."""
            r1, r2, r3 = plane.rho
            return max((d - r3 - r1 * x) / r2 for x in (0.0, width - 1.0)) if r2 > 0 else float(height)

        bands = self.bands
        for k in range(1, len(bands)):
            b, prev = bands[k], bands[k - 1].plane
            # Rows below where the previous plane reaches b are nearer bands; rows above where this
            # band's plane reaches the next band's edge are farther bands (they overwrite them next).
            v_end = int(min(height, max(0.0, math.ceil(row_where(prev, b.near_disparity)) + 1)))
            v_top = 0
            if k + 1 < len(bands) and b.plane.rho[1] > 0:
                v_top = int(min(v_end, max(0.0, math.floor(min(
                    (bands[k + 1].near_disparity - b.plane.rho[2] - b.plane.rho[0] * x) / b.plane.rho[1]
                    for x in (0.0, width - 1.0))) - 1)))
            rows = slice(v_top, v_end)
            # band k holds the pixels where the previous band's plane is below b_k (the pencil keeps
            # that nested: such pixels are in every nearer band's far part too)
            p1, p2, p3 = (np.float32(x) for x in prev.rho)
            m = (u[rows] * p1 + v[rows] * p2 + p3) < np.float32(b.near_disparity)
            q1, q2, q3 = (np.float32(x) for x in b.plane.rho)
            Dg[rows][m] = (u[rows] * q1 + v[rows] * q2 + q3)[m]
            H[rows][m] = b.floor.height
        Dg.flags.writeable = False
        H.flags.writeable = False
        return Dg, H

    def tolerance(self, Dg: np.ndarray, rig: StereoRig) -> np.ndarray:
        """Extra height allowance per pixel, m: cross_slope_allowance per metre beyond the corridor."""
        lat = lateral_on_floor(Dg, rig, self.near.floor)
        excess = np.maximum(np.abs(lat) - np.float32(self.params.corridor_half_width), 0)
        return np.where(Dg > 0, excess * np.float32(self.params.cross_slope_allowance), 0).astype(np.float32)


def lateral_on_floor(Dg: np.ndarray, rig: StereoRig, floor: FloorGeometry, u=None, v=None) -> np.ndarray:
    """Lateral offset (m, right positive) of where each pixel's ray meets a floor of disparity Dg
    (pixels (u, v); default the whole image)."""
    if u is None:
        u, v = pixel_grid(*Dg.shape)
    _, _, l = floor.axes()
    lr = (u - np.float32(rig.cx)) * np.float32(l[0] / rig.fx) + (v - np.float32(rig.cy)) * np.float32(l[1] / rig.fy) \
        + np.float32(l[2])
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(Dg > 0, np.float32(rig.fb) / Dg * lr, np.float32(np.inf)).astype(np.float32)


BEYOND = "grade change"
CONTINUED = "the band before, continued, fits"


def _w(rho, rig: StereoRig) -> np.ndarray:
    r1, r2, r3 = rho
    return np.array([r1 * rig.fx, r2 * rig.fy, r3 + r1 * rig.cx + r2 * rig.cy])


def _pencil_t(rho, b: float, thetas: np.ndarray, rig: StereoRig) -> np.ndarray:
    """t of the planes D = (1 + t) P - t b through the hinge line whose floor normals are the
    previous one turned by thetas (rad, positive uphill). In w = (fx B / H) g terms the pencil is
    w_t = (1 + t) w - t b e_z, and turning g about the hinge axis (g x e_z) keeps it in span(w, e_z):
    solve (w - b e_z) t - lambda n = -w for (t, lambda), per theta (normal equations, 2x2)."""
    w = _w(rho, rig)
    g = w / np.linalg.norm(w)
    f = np.array([0.0, 0.0, 1.0]) - g[2] * g
    f /= np.linalg.norm(f)
    # uphill: the floor's up normal tips backwards, so its down vector g tips forwards
    n = np.cos(thetas)[:, None] * g[None] + np.sin(thetas)[:, None] * f[None]
    a = w - b * np.array([0.0, 0.0, 1.0])
    an, nn, aw, nw = n @ a, (n * n).sum(axis=1), a @ w, n @ w
    det = (a @ a) * nn - an * an
    return (-aw * nn + an * nw) / det


def _grade_of(rho_prev, rho, rig: StereoRig) -> float:
    """Signed angle between two floor normals, positive when the second rises ahead."""
    w0, w1 = _w(rho_prev, rig), _w(rho, rig)
    g0, g1 = w0 / np.linalg.norm(w0), w1 / np.linalg.norm(w1)
    f = np.array([0.0, 0.0, 1.0]) - g0[2] * g0
    ang = math.acos(float(np.clip(g0 @ g1, -1.0, 1.0)))
    return ang if g1 @ f > 0 else -ang      # the down vector tips forwards on an uphill


def _samples(disparity: np.ndarray, step: int):
    s = step
    h, w = disparity.shape
    vs = np.arange(s // 2, h, s, dtype=np.float32)
    us = np.arange(s // 2, w, s, dtype=np.float32)
    V, U = np.meshgrid(vs, us, indexing="ij")
    return U, V, disparity[s // 2::s, s // 2::s]


def _fit_hinge(U, V, d, prev: GroundBand, b: float, b_far: float, rig: StereoRig, fit: PlaneFitParams,
               p: GroundModelParams, rng, fixed_grade: Optional[float] = None) -> GroundBand:
    """Band k's hinge (module docstring, 2). ``fixed_grade`` (rad): take that bend as it is."""
    P = prev.plane.predict(U, V)
    with np.errstate(invalid="ignore"):
        pool = (d > 0) & (P < b) & (P >= b_far)
        Ub, Vb, Pb = U[pool], V[pool], P[pool]
        inside = np.abs(lateral_on_floor(Pb, rig, prev.floor, Ub, Vb)) <= p.corridor_half_width
    Us, Vs = Ub[inside], Vb[inside]
    Pp, dp = Pb[inside].astype(np.float64), d[pool][inside].astype(np.float64)
    n = len(dp)

    def same(reason: str, inl: int = 0) -> GroundBand:
        return GroundBand(prev.plane, prev.floor, b, 0.0, inl, n, False, reason)

    if n < p.min_band_inliers:
        return same(f"{n} samples in the corridor (need {p.min_band_inliers}): continues the band before")
    if n > p.score_points:
        idx = rng.choice(n, p.score_points, replace=False)
        Pp, dp, Us, Vs = Pp[idx], dp[idx], Us[idx], Vs[idx]
    H = prev.floor.height
    # Continuity along the band: a ramp fits every part of it, a plane folded onto the lower floor
    # beyond a step (or over an obstacle ahead) misses a stretch. Each of continuity_parts
    # stretches that holds samples must have most of them within twice the inlier band.
    stretch = (np.clip((b - Pp) / max(b - b_far, 1e-9), 0.0, 0.999) * p.continuity_parts).astype(int)
    counts = np.bincount(stretch, minlength=p.continuity_parts)
    filled = counts >= 5

    def worst_stretch(t: float) -> float:
        pr = Pp + t * (Pp - b)
        near = np.abs(dp - pr) < 2.0 * np.maximum(fit.inlier_min_px, pr * (fit.inlier_height / H))
        hits = np.bincount(stretch, weights=near, minlength=p.continuity_parts)
        return float((hits[filled] / counts[filled]).min()) if filled.any() else 0.0

    theta_max = math.atan(p.max_grade_change)
    thetas = np.linspace(-theta_max, theta_max, p.grade_steps) if fixed_grade is None else np.array([fixed_grade])
    r = np.asarray(prev.plane.rho)
    ts = _pencil_t(r, b, thetas, rig)
    ez = np.array([0.0, 0.0, 1.0])
    rhos = (1 + ts)[:, None] * r[None] - (ts * b)[:, None] * ez[None]
    # the thresholds need the camera above the band's plane (a far uphill can pass above it)
    wn = np.linalg.norm(np.array([_w(x, rig) for x in rhos]), axis=1)
    keep = (rig.fb / wn >= p.min_height_fraction * prev.floor.height) & (1 + ts > 0)
    thetas, ts, rhos = thetas[keep], ts[keep], rhos[keep]
    if len(thetas) == 0:
        return same("no grade within the bound keeps the camera above this band's plane: continues the band before")
    pred = rhos[:, 0:1] * Us[None] + rhos[:, 1:2] * Vs[None] + rhos[:, 2:3]
    band = np.maximum(fit.inlier_min_px, pred * (fit.inlier_height / H))
    scores = (np.abs(dp[None] - pred) < band).sum(axis=1)
    # ties go to the smallest grade change (the ground continues unless the data says otherwise)
    best = max(range(len(thetas)), key=lambda i: (scores[i], -abs(thetas[i])))
    # The data must ask for a bend: on a flat floor the noise moves the best grade about while
    # its inlier count stays within a few per cent of the band before, continued.
    on = int((np.abs(dp - Pp) < np.maximum(fit.inlier_min_px, Pp * (fit.inlier_height / H))).sum())
    if fixed_grade is None and scores[best] < p.min_bend_gain * on and worst_stretch(0.0) >= p.min_continuity:
        return GroundBand(prev.plane, prev.floor, b, 0.0, on, len(dp), True, CONTINUED)
    t = float(ts[best])
    for _ in range(2 if fixed_grade is None else 0):     # refine t in D = P + t (P - b) on the inliers
        pr = Pp + t * (Pp - b)
        inl = np.abs(dp - pr) < np.maximum(fit.inlier_min_px, pr * (fit.inlier_height / H))
        if inl.sum() < p.min_band_inliers:
            return same(f"{int(inl.sum())} ground samples (need {p.min_band_inliers}): continues the band before")
        x = Pp[inl] - b
        t = float(((dp[inl] - Pp[inl]) * x).sum() / (x * x).sum())
    pr = Pp + t * (Pp - b)
    inl = np.abs(dp - pr) < np.maximum(fit.inlier_min_px, pr * (fit.inlier_height / H))
    worst = worst_stretch(t)
    if worst < p.min_continuity:
        return same(f"a stretch of the band fits only {worst:.0%} (need {p.min_continuity:.0%}): "
                    "continues the band before", int(inl.sum()))
    plane = DisparityPlane(tuple(float(x) for x in (1 + t) * r - t * b * np.array([0.0, 0.0, 1.0])))
    grade = _grade_of(r, plane.rho, rig)
    if abs(grade) > theta_max + 1e-9 or plane.floor(rig).height < p.min_height_fraction * prev.floor.height:
        return same(f"{BEYOND} {math.degrees(grade):.1f} deg beyond the bound "
                    f"{math.degrees(theta_max):.1f} deg: continues the band before", int(inl.sum()))
    return GroundBand(plane, plane.floor(rig), b, grade, int(inl.sum()), n, True)


def _bend_the_band_before(U, V, d, bands: list, b: float, b_far: float, rig: StereoRig, fit: PlaneFitParams,
                          p: GroundModelParams, rng) -> Optional[GroundBand]:
    """A ramp that starts late in the band before left it flat or bent too little (the bend
    gained too few inliers there) and this band cannot catch up within the bound: try each bend
    of the band before and keep the pair of bands with the most inliers. Replaces bands[-1];
    None when no pair fits."""
    theta_max = math.atan(p.max_grade_change)
    best = None
    for th in np.linspace(-theta_max, theta_max, p.grade_steps):
        redo = _fit_hinge(U, V, d, bands[-2], bands[-1].near_disparity, b, rig, fit, p, rng, float(th))
        if not redo.fitted:
            continue
        again = _fit_hinge(U, V, d, redo, b, b_far, rig, fit, p, rng)
        if again.fitted and (best is None or redo.inliers + again.inliers > best[0]):
            best = (redo.inliers + again.inliers, redo, again)
    if best is None:
        return None
    bands[-1] = best[1]
    return best[2]


def fit_ground_model(disparity: np.ndarray, rig: StereoRig, prior: DisparityPlane,
                     fit: PlaneFitParams = PlaneFitParams(),
                     params: GroundModelParams = GroundModelParams()) -> GroundModel:
    """The near band fitted under the mounting prior, then hinged bands out to the horizon."""
    p = params
    h, w = disparity.shape
    if (h, w) != (rig.height, rig.width):
        raise ValueError(f"disparity is {w}x{h} but the stereo rig is {rig.width}x{rig.height}")
    d_max = float(max(prior.predict(0.0, h - 1.0), prior.predict(w - 1.0, h - 1.0)))   # nearest floor in view
    if not d_max > 0:
        raise ValueError("the mounting prior puts no floor in view (the bottom row is above its horizon)")
    b1 = d_max / p.near_ratio
    U, V, d = _samples(disparity, fit.step)
    Dps = prior.predict(U, V)
    with np.errstate(invalid="ignore"):      # only the samples the fit reads
        near_samples = (Dps >= b1) & (np.abs(lateral_on_floor(Dps, rig, prior.floor(rig), U, V))
                                      <= p.corridor_half_width)
    near_region = np.zeros((h, w), bool)
    near_region[fit.step // 2::fit.step, fit.step // 2::fit.step] = near_samples
    near = fit_ground_plane(disparity, rig, prior, fit, region=near_region)
    bands = [GroundBand(near.plane, near.floor, math.inf, 0.0, near.inliers, near.pool, near.ok, near.reason)]
    rng = np.random.default_rng(fit.seed)
    b = float(max(near.plane.predict(0.0, h - 1.0), near.plane.predict(w - 1.0, h - 1.0))) / p.near_ratio
    while len(bands) < p.max_bands and b > p.min_band_disparity:
        b_far = b / p.band_ratio if len(bands) < p.max_bands - 1 and b / p.band_ratio > p.min_band_disparity else 0.0
        band = _fit_hinge(U, V, d, bands[-1], b, b_far, rig, fit, p, rng)
        if band.reason.startswith(BEYOND) and len(bands) >= 2 and bands[-1].fitted:
            band = _bend_the_band_before(U, V, d, bands, b, b_far, rig, fit, p, rng) or band
        bands.append(band)
        b = b_far
        if b_far == 0.0:
            break
    return GroundModel(bands, near, p)


def corridor_mask(rig: StereoRig, height: float, centre: float, half_width: float, near: float,
                  far: float) -> np.ndarray:
    """Pixels of a level floor ``height`` m below a level camera that lie within ``half_width`` m of
    the line ``centre`` m to its right, from ``near`` to ``far`` m ahead (bool HxW): a region fixed
    by the geometry alone, for judging the ground ahead the same way on every frame."""
    pts = []
    for z, sides in ((near, (-1, 1)), (far, (1, -1))):
        for side in sides:
            x = centre + side * half_width
            pts.append((rig.cx + rig.fx * x / z, rig.cy + rig.fy * height / z))
    mask = np.zeros((rig.height, rig.width), np.uint8)
    cv2.fillPoly(mask, [np.round(np.array(pts)).astype(np.int32)], 1)
    return mask.astype(bool)
