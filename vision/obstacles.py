"""Obstacles by ground-plane suppression in disparity space (chapter 11.2.2.2).

Every pixel with a disparity is compared with the disparity D_g the fitted
ground plane predicts there (vision/ground_plane.py). Thresholds are heights in
metres, converted per pixel: a point h above the floor on a pixel's ray has
disparity D_g H / (H - h), one h below it D_g H / (H + h), H the camera height
implied by the plane. So

    obstacle  D - D_g >  max(D_g h_obs / (H - h_obs), noise_px)
    negative  D_g - D >  max(D_g h_neg / (H + h_neg), noise_px), where ground is expected
    ground    everything in between, where ground is expected (D_g > 0)
    unknown   no disparity, beyond max_range, or higher than max_height (overhangs)

Two refinements make the labels usable:
- Vertical growth: the lowest rows of a box's front face are closer to the floor
  than any threshold. A vertical surface keeps its disparity down a column while
  the floor's changes by rho_2 per row, so a pixel just below an obstacle pixel
  joins it when its disparity is nearer the obstacle's than the plane's, or when
  it is above a weak threshold (hysteresis: weak_fraction of the height).
- Blobs smaller than ``min_blob_pixels`` are matching noise, not obstacles, and
  become unknown.
Missing disparity in a column run that borders a negative obstacle (the band
occluded beyond a step's edge) is negative too.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Optional

import cv2
import numpy as np

from vbnav.vision.ground_model import GroundModel, GroundModelParams, fit_ground_model
from vbnav.vision.ground_plane import (DisparityPlane, FloorGeometry, PlaneFit, PlaneFitParams,
                                       fit_ground_plane)
from vbnav.vision.stereo import StereoRig


class PixelClass(IntEnum):
    GROUND = 0
    OBSTACLE = 1
    NEGATIVE = 2
    UNKNOWN = 255


@dataclass(frozen=True)
class ObstacleParams:
    obstacle_height: float = 0.01      # m above the floor: lower things are ground
    negative_depth: float = 0.03       # m below the floor: deeper is a negative obstacle
    noise_px: float = 0.0              # disparity noise floor, px (about 0.5 for SGBM, 0 for true disparity)
    grow_rows: int = 3                 # rows a vertical surface may grow down toward its foot
    weak_fraction: float = 0.25        # growth also takes pixels above weak_fraction * obstacle_height
    min_blob_pixels: int = 12          # smaller connected obstacle regions are noise
    max_height: Optional[float] = None  # m; higher points (table tops the robot passes under) are unknown
    max_range: Optional[float] = None  # m; farther points are unknown
    min_ground_disparity: float = 0.5  # px; ground is expected where the plane predicts more
    missing_negative_rows: int = 63    # missing runs up to this long next to a negative become negative
    smooth_columns: int = 5            # horizontal mean over this many pixels before thresholding (1: off)
    report_range: float = 10.0         # m; obstacle points beyond are not listed for the zones


@dataclass
class ObstacleScene:
    """Labels and floor points of one disparity image.

    Floor points are in the camera's floor frame: origin below the optical centre,
    forward along the optical axis projected on the floor, lateral to the right (m).
    """

    labels: np.ndarray                 # uint8 HxW PixelClass values
    fit: PlaneFit
    obstacle_points: np.ndarray        # (N, 2) float32 (lateral, forward) of obstacle pixels
    negative_points: np.ndarray        # (M, 2) float32, where the ray meets the ground plane
    fractions: dict = field(default_factory=dict)
    ground: Optional[GroundModel] = None   # the piecewise ground, when it was used (fit: its near band)

    @property
    def plane(self) -> DisparityPlane:
        return self.fit.plane


def classify(disparity: np.ndarray, plane: DisparityPlane, floor: FloorGeometry, rig: StereoRig,
             params: ObstacleParams = ObstacleParams(), ground: Optional[GroundModel] = None) -> np.ndarray:
    """Per-pixel PixelClass labels (uint8) of a float32 disparity image (NaN unknown).

    With ``ground`` (vision/ground_model.py) the floor is its bands (each with its own camera
    height) instead of ``plane``, and the heights grow by its camber allowance beyond its corridor.
    """
    p = params
    h, w = disparity.shape
    if ground is None:
        Dg = plane.image(h, w)
        H = np.float32(floor.height)
        h_obs, h_neg = np.float32(p.obstacle_height), np.float32(p.negative_depth)
    else:
        Dg, H = ground.images(h, w)
        extra = ground.tolerance(Dg, rig)
        # capped below the camera height: a threshold at the camera's own height is no threshold
        h_obs = np.minimum(np.float32(p.obstacle_height) + extra, np.float32(0.9) * H)
        h_neg = np.float32(p.negative_depth) + extra
    with np.errstate(invalid="ignore"):
        valid = disparity > 0
        # A short horizontal mean cuts the matcher's noise while keeping every row (a low
        # obstacle is only a few rows tall); holes are filled with the plane for the mean only.
        D = disparity
        if p.smooth_columns > 1:
            D = cv2.blur(np.where(valid, disparity, Dg), (p.smooth_columns, 1))
        resid = D - Dg
        ground_expected = Dg > p.min_ground_disparity
        obs = valid & (resid > np.maximum(Dg * (h_obs / (H - h_obs)), np.float32(p.noise_px)))
        neg = valid & ground_expected & (-resid > np.maximum(Dg * (h_neg / (H + h_neg)), np.float32(p.noise_px)))
        out_of_scope = np.zeros_like(valid)
        if p.max_height is not None:           # e = H (D - D_g) / D > max_height
            out_of_scope |= valid & (H * resid > np.float32(p.max_height) * D)
        if p.max_range is not None:           # depth z = fB / D beyond max_range
            out_of_scope |= valid & (D < np.float32(rig.fb / p.max_range))
    obs &= ~out_of_scope
    box = _bbox(obs) if p.grow_rows > 0 else None
    if box is not None:            # only the obstacles' rows and the few below them can change
        rs = slice(box[0].start, min(h, box[0].stop + p.grow_rows))
        h_weak = np.float32(p.weak_fraction) * h_obs
        Hr, hw = (H[rs] if np.ndim(H) else H), (h_weak[rs] if np.ndim(h_weak) else h_weak)
        weak = resid[rs] > np.maximum(Dg[rs] * (hw / (Hr - hw)), np.float32(p.noise_px))
        obs[rs] = _grow_down(D[rs], resid[rs], (valid & ~neg & ~out_of_scope)[rs], obs[rs], p.grow_rows, weak)
    if p.min_blob_pixels > 1:
        # one labelling pass for both kinds (a blob touching both counts all its pixels)
        keep = _drop_small_blobs(obs | neg, p.min_blob_pixels)
        obs &= keep
        neg &= keep
    if neg.any():
        neg |= _missing_next_to(neg, ~valid & ground_expected, p.missing_negative_rows)
    ground = valid & ground_expected & ~out_of_scope
    u8 = np.uint8
    return np.where(obs, u8(PixelClass.OBSTACLE), np.where(neg, u8(PixelClass.NEGATIVE),
                    np.where(ground, u8(PixelClass.GROUND), u8(PixelClass.UNKNOWN))))


def _grow_down(D, resid, allowed, obs, rows: int, weak) -> np.ndarray:
    """Grow obstacle pixels down their column while the disparity stays that of the surface above
    (nearer it than the plane's), or while the pixel is above the weak (hysteresis) threshold."""
    obs = obs.copy()
    seed = np.where(obs, D, np.nan).astype(np.float32)
    abs_resid = np.abs(resid)
    for _ in range(rows):
        above = seed[:-1]
        with np.errstate(invalid="ignore"):
            cand = allowed[1:] & ~obs[1:] & ~np.isnan(above) & ((np.abs(D[1:] - above) < abs_resid[1:]) | weak[1:])
        if not cand.any():
            break
        obs[1:] |= cand
        seed[1:][cand] = D[1:][cand]
    return obs


def _bbox(mask: np.ndarray) -> Optional[tuple[slice, slice]]:
    rows = np.flatnonzero(mask.any(axis=1))
    if len(rows) == 0:
        return None
    cols = np.flatnonzero(mask[rows[0]:rows[-1] + 1].any(axis=0))
    return slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)


def _drop_small_blobs(mask: np.ndarray, min_pixels: int) -> np.ndarray:
    box = _bbox(mask)
    if box is None:
        return mask
    sub = np.ascontiguousarray(mask[box])
    n, lab, stats, _ = cv2.connectedComponentsWithStats(sub.view(np.uint8), connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_pixels
    keep[0] = False
    out = np.zeros_like(mask)
    out[box] = keep[lab]
    return out


def _missing_next_to(neg: np.ndarray, missing: np.ndarray, max_rows: int) -> np.ndarray:
    """Missing pixels joined to a negative pixel by an unbroken vertical run of missing pixels
    (at most ``max_rows`` long), above or below it. Path doubling: log2(max_rows) slice steps."""
    out = np.zeros_like(neg)
    for flip in (False, True):
        R = (neg[::-1] if flip else neg).copy()      # reached: negative, or missing joined to one
        C = (missing[::-1] if flip else missing).copy()   # C[v]: rows v-s+1..v all missing
        s = 1
        while s <= max_rows:
            R[s:] |= R[:-s] & C[s:]
            C[s:] &= C[:-s]
            s *= 2
        out |= R[::-1] if flip else R
    return out & missing


def floor_coordinates(u: np.ndarray, v: np.ndarray, d: np.ndarray, rig: StereoRig,
                      floor: FloorGeometry) -> tuple[np.ndarray, np.ndarray]:
    """(lateral, forward) on the floor, m, of pixels (u, v) with disparity d."""
    g, f, l = (a.astype(np.float32) for a in floor.axes())
    z = np.float32(rig.fb) / d
    x = (u.astype(np.float32) - np.float32(rig.cx)) * (z / np.float32(rig.fx))
    y = (v.astype(np.float32) - np.float32(rig.cy)) * (z / np.float32(rig.fy))
    return x * l[0] + y * l[1] + z * l[2], x * f[0] + y * f[1] + z * f[2]


def _points(mask: np.ndarray, disp: np.ndarray, rig: StereoRig, floor: FloorGeometry,
            min_disp: float) -> np.ndarray:
    box = _bbox(mask)
    if box is None:
        return np.zeros((0, 2), np.float32)
    with np.errstate(invalid="ignore"):
        sel = mask[box] & (disp[box] > min_disp)
    v, u = np.nonzero(sel)
    if len(u) == 0:
        return np.zeros((0, 2), np.float32)
    d = disp[box][v, u]
    v, u = v + box[0].start, u + box[1].start
    lat, fwd = floor_coordinates(u, v, d, rig, floor)
    return np.column_stack([lat, fwd]).astype(np.float32)


def class_fractions(labels: np.ndarray) -> dict:
    n = labels.size
    out = {c.name.lower(): np.count_nonzero(labels == c) / n for c in PixelClass if c != PixelClass.UNKNOWN}
    out["unknown"] = 1.0 - sum(out.values())
    return out


def detect_obstacles(disparity: np.ndarray, rig: StereoRig, prior: Optional[DisparityPlane] = None,
                     fit_params: PlaneFitParams = PlaneFitParams(),
                     params: ObstacleParams = ObstacleParams(),
                     ground: Optional[GroundModelParams] = None) -> ObstacleScene:
    """Fit the ground, label every pixel and list obstacle points on the floor.

    The ground is one plane, or with ``ground`` (and a mounting ``prior``) the piecewise model
    of vision/ground_model.py; ``scene.fit`` is then its near band's fit. An infinite disparity (a depth
    of 0 turned into disparity) is unknown, like NaN."""
    inf = np.isinf(disparity)
    if inf.any():
        disparity = np.where(inf, np.float32(np.nan), disparity)
    model = None
    if ground is not None and prior is not None:
        model = fit_ground_model(disparity, rig, prior, fit_params, ground)
        fit = model.near
        Dg = model.images(*disparity.shape)[0]
    else:
        fit = fit_ground_plane(disparity, rig, prior, fit_params)
        Dg = fit.plane.image(*disparity.shape)
    labels = classify(disparity, fit.plane, fit.floor, rig, params, model)
    min_disp = rig.fb / params.report_range
    obstacle_pts = _points(labels == PixelClass.OBSTACLE, disparity, rig, fit.floor, min_disp)
    # A negative obstacle's edge is no nearer than where its ray meets the ground.
    negative_pts = _points(labels == PixelClass.NEGATIVE, Dg, rig, fit.floor, min_disp)
    return ObstacleScene(labels, fit, obstacle_pts, negative_pts, class_fractions(labels), model)


@dataclass(frozen=True)
class NearestObstacle:
    distance: float     # m along the floor, forward
    bearing: float      # rad, positive to the right (theta convention of vision/geometry.py)
    lateral: float      # m, positive right


def nearest_in_corridor(points: np.ndarray, half_width: float, max_range: float = math.inf,
                        min_points: int = 5) -> Optional[NearestObstacle]:
    """The nearest obstacle in a straight corridor ahead: the ``min_points``-th nearest point
    with |lateral| <= half_width and 0 < forward <= max_range (robust to a few stray points)."""
    if len(points) == 0:
        return None
    lat, fwd = points[:, 0], points[:, 1]
    inside = (np.abs(lat) <= half_width) & (fwd > 0) & (fwd <= max_range)
    if np.count_nonzero(inside) < min_points:
        return None
    fl, ll = fwd[inside], lat[inside]
    k = min_points - 1
    i = np.argpartition(fl, k)[k]
    return NearestObstacle(float(fl[i]), float(math.atan2(ll[i], fl[i])), float(ll[i]))


class KOfN:
    """Temporal filter: true when the condition held in at least k of the last n updates."""

    def __init__(self, k: int, n: int):
        if not 1 <= k <= n:
            raise ValueError(f"need 1 <= k <= n, got k={k}, n={n}")
        self.k, self.n = k, n
        self._hist: list[bool] = []

    def update(self, flag: bool) -> bool:
        self._hist.append(bool(flag))
        if len(self._hist) > self.n:
            self._hist.pop(0)
        return self.state

    @property
    def state(self) -> bool:
        return sum(self._hist) >= self.k

    def reset(self) -> None:
        self._hist.clear()
