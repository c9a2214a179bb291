"""Line segments in a rectified stereo pair and their 3D reconstruction (Marvin, section 11.2.1.1).

Marvin reconstructs the boundaries of man-made objects as 3D line segments.
Here that is three steps, all pure (arrays in, arrays out):

1. ``detect_segments``: OpenCV's LSD (``createLineSegmentDetector``: sub-pixel,
   parameter-free apart from a length floor, no edge thresholds to tune per
   scene) in each image, run on the half-size image for speed, each line then
   re-fitted to the full-resolution gradient (``refine_lines``), plus an
   appearance descriptor per segment: the mean grey level on either side of it,
   sampled a few pixels off the line.
2. ``match_stereo``: in a rectified pair a 3D line seen by both cameras lies on
   the same rows, so a left segment's partner is a right segment overlapping
   it in y (the epipolar constraint), with the same direction and contrast
   polarity (LSD orients segments by the gradient), a disparity in range and a
   similar grey level on at least one side (at an occluding boundary only the
   near side looks the same from both cameras). Score = row overlap x
   appearance. Every candidate within ``ambiguity_ratio`` of the best is kept as
   a hypothesis (Fig. 11.4), and an optional prediction (expected disparity per
   left segment, from the map) raises the score of the candidates it agrees with.
3. ``triangulate``: each endpoint's disparity is where the right segment's line
   crosses the endpoint's row; depth z = fx B / d (11.1). The covariance of each
   3D endpoint is propagated from the image: sigma_perp across the line,
   sigma_along along it (LSD endpoints are weak along the line), and the
   disparity's sigma sqrt(2) sigma_perp / |sin(angle to the rows)|, which grows
   without bound as a segment turns parallel to the epipolar lines; segments
   closer than ``min_epipolar_angle_deg`` to horizontal are not reconstructed
   (their disparity is undetermined by the line itself).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np


@dataclass(frozen=True)
class LineParams:
    """Detection, matching and uncertainty settings (pixels unless stated)."""

    min_length_px: float = 25.0         # shorter LSD segments are texture detail, not object boundaries
    # LSD runs on the image scaled by detect_scale (OpenCV's default 0.8 takes 2.7x as long at 640x480) with
    # a level-line angle tolerance of lsd_angle_deg (OpenCV's 22.5 merges more at the coarse scale: Middlebury
    # 83 % of endpoints within 2 px against 87 % at 15 deg); refine_lines restores the accuracy across the line.
    detect_scale: float = 0.5
    lsd_angle_deg: float = 15.0
    refine_radius_px: float = 3.0       # full-resolution line re-fit: the gradient peak is searched this far across
    refine_samples: int = 16            # points along the segment for the re-fit
    side_offset_px: float = 3.0         # where the side grey levels are sampled (beyond LSD's ~2 px support)
    side_samples: int = 9               # points along the segment for the side grey levels
    max_angle_diff_deg: float = 12.0    # left/right direction difference allowed (perspective changes it a little)
    min_epipolar_angle_deg: float = 20.0  # angle to the rows below which disparity is ill-conditioned
    min_overlap: float = 0.5            # shared rows / rows of the shorter segment
    min_disparity_px: float = 0.5
    max_disparity_px: float = 120.0
    appearance_sigma: float = 12.0      # grey levels: side means differing by this score exp(-1/2)
    ambiguity_ratio: float = 0.8        # candidates scoring >= this x the best are kept as hypotheses
    min_score: float = 0.25
    sigma_perp_px: float = 0.3          # LSD's line position accuracy across the line (measured in tests)
    sigma_along_px: float = 2.0         # endpoint accuracy along the line
    prior_bonus: float = 1.0            # score x (1 + bonus) for a candidate the prediction agrees with
    prior_gate_px: float = 1.5          # |d - d_predicted| allowed on top of 3 sigma of the prediction
    # Edge search for left segments LSD found no partner for (occluding boundaries, see ``match_edges``).
    edge_search: bool = True
    edge_samples: int = 16              # points along the left segment
    edge_strength: float = 0.5          # right-image edge along the line >= this x the left one's gradient
    band_px: tuple = (2.0, 4.0, 6.0)    # side band offsets (beyond LSD's ~2 px support, as the floor test's)
    band_max_diff: float = 12.0         # grey levels: mean |left - right| of a side band on one surface (noise ~2)
    edge_refit_px: float = 1.0          # the right line's re-fit may move it this far from the searched disparity
    # Vertical 3D lines along the pencil through the vertical vanishing point (``vision/line_vertical.py``;
    # used when ``reconstruct_pair`` is given the world's vertical in the camera frame).
    vertical_search: bool = True
    vertical_k_sigma: float = 3.0       # ridge of |gradient across| above this x the Sobel's noise sigma
    vertical_tol_px: float = 0.75       # a ridge supports the pencil lines (columns) within this of it
    vertical_gap_px: int = 4            # unsupported rows bridged in a run (a sign change: the Sobel's 3 rows and 1)


@dataclass
class Segments2D:
    """N image segments: ``xy`` (N, 4) = x0, y0, x1, y1 (px, LSD orientation), ``sides`` (N, 2) grey levels
    left / right of the direction of travel."""

    xy: np.ndarray
    sides: np.ndarray

    def __len__(self) -> int:
        return len(self.xy)

    @property
    def length(self) -> np.ndarray:
        return np.hypot(self.xy[:, 2] - self.xy[:, 0], self.xy[:, 3] - self.xy[:, 1])

    @property
    def direction(self) -> np.ndarray:
        """(N, 2) unit directions from endpoint 0 to endpoint 1."""
        d = self.xy[:, 2:4] - self.xy[:, 0:2]
        return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


@dataclass
class StereoMatches:
    """Candidate pairs (left index, right index), their scores and disparities at the left endpoints.

    ``group`` is the left index: several rows with the same group are rival
    hypotheses for one left segment; ``best`` marks the top-scoring one of each.
    """

    left: np.ndarray
    right: np.ndarray
    score: np.ndarray
    disparity: np.ndarray      # (K, 2) px at the left segment's endpoints
    best: np.ndarray           # bool (K,)
    predicted: np.ndarray      # bool (K,): the prediction agreed with this candidate

    def __len__(self) -> int:
        return len(self.left)

    def subset(self, keep: np.ndarray) -> "StereoMatches":
        return StereoMatches(self.left[keep], self.right[keep], self.score[keep], self.disparity[keep],
                             self.best[keep], self.predicted[keep])


# A floor line's stance (Segments3D.stance, LineMap.stance): what the stereo pair shows above it.
STANDING = 1      # a surface rises from it (a box's or a wall's foot)
FLAT = -1         # floor on both sides (a texture line, a marking)


@dataclass
class Segments3D:
    """K 3D segments in the left camera frame: ``P`` (K, 2, 3) m, ``cov`` (K, 2, 3, 3) m^2,
    with the image segments they came from (``left_xy``, ``right_xy`` (K, 4)), the match ``score`` and
    ``group`` / ``best`` from the matcher (rival hypotheses share a group). ``stance`` (K,) says what a
    floor line has above it (vision/line_floor.py): STANDING (a surface rises from it: a box's or a wall's
    foot), FLAT (floor on both sides: a texture line or a marking) or 0 (not known, or not a floor line)."""

    P: np.ndarray
    cov: np.ndarray
    left_xy: np.ndarray
    right_xy: np.ndarray
    score: np.ndarray
    group: np.ndarray
    best: np.ndarray
    extra: dict = field(default_factory=dict)
    stance: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        if self.stance is None:
            self.stance = np.zeros(len(self.P), np.int8)

    def __len__(self) -> int:
        return len(self.P)

    def subset(self, keep) -> "Segments3D":
        return Segments3D(self.P[keep], self.cov[keep], self.left_xy[keep], self.right_xy[keep],
                          self.score[keep], self.group[keep], self.best[keep],
                          {k: v[keep] for k, v in self.extra.items()}, self.stance[keep])

    @staticmethod
    def concat(parts: list) -> "Segments3D":
        """One Segments3D of several (``extra`` keeps the keys all parts have)."""
        parts = [p for p in parts if len(p)]
        if not parts:
            return Segments3D.empty()
        keys = set.intersection(*(set(p.extra) for p in parts))
        cat = np.concatenate
        return Segments3D(cat([p.P for p in parts]), cat([p.cov for p in parts]), cat([p.left_xy for p in parts]),
                          cat([p.right_xy for p in parts]), cat([p.score for p in parts]),
                          cat([p.group for p in parts]), cat([p.best for p in parts]),
                          {k: cat([p.extra[k] for p in parts]) for k in keys}, cat([p.stance for p in parts]))

    @staticmethod
    def empty() -> "Segments3D":
        z = np.zeros
        return Segments3D(z((0, 2, 3)), z((0, 2, 3, 3)), z((0, 4)), z((0, 4)), z(0), z(0, int), z(0, bool))


# ------------------------------------------------------------------------------------- detection
_LSD: dict = {}


def _detector(scale: float, angle_deg: float):
    key = (scale, angle_deg)
    if key not in _LSD:    # one detector per setting and process: creating it allocates its tables
        # OpenCV's defaults but for scale and the angle tolerance: sigma_scale 0.6, quant 2, log_eps 0,
        # density_th 0.7, n_bins 1024.
        _LSD[key] = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD, scale, 0.6, 2.0, angle_deg)
    return _LSD[key]


def grey(image: np.ndarray) -> np.ndarray:
    if image.ndim == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.dtype != np.uint8:
        return cv2.normalize(image, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return image


def detect_segments(image: np.ndarray, params: LineParams = LineParams(), grad: Optional[tuple] = None) -> Segments2D:
    """LSD segments at least ``min_length_px`` long, their lines re-fitted at full resolution, with their
    side grey levels.

    LSD's cost grows with the pixels it visits, so it runs on the image scaled by ``detect_scale``; that
    costs its across-line accuracy (Middlebury median 0.22 -> 0.36 px at 0.5), which ``refine_lines``
    restores from the full-resolution gradient. ``grad``: ``gradients(grey(image))``, if the caller has them.
    """
    g = grey(image)
    found = _detector(params.detect_scale, params.lsd_angle_deg).detect(g)[0]
    xy = np.zeros((0, 4)) if found is None else found.reshape(-1, 4).astype(np.float64)
    length = np.hypot(xy[:, 2] - xy[:, 0], xy[:, 3] - xy[:, 1])
    xy = xy[length >= params.min_length_px]
    if params.refine_radius_px > 0:
        xy = refine_lines(g, xy, params, grad)
    return Segments2D(xy, side_means(g, xy, params))


def refine_lines(image: np.ndarray, xy: np.ndarray, params: LineParams = LineParams(),
                 grad: Optional[tuple] = None) -> np.ndarray:
    """See ``refit_lines``: the refined segments (a segment without enough gradient peaks keeps LSD's line)."""
    return refit_lines(image, xy, params, grad=grad)[0]


def refit_lines(image: np.ndarray, xy: np.ndarray, params: LineParams = LineParams(), radius_px: float = None,
                either_polarity: bool = False, grad: Optional[tuple] = None,
                trim: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Each segment moved across itself onto the full-resolution edge (endpoints stay where they are along it).

    At ``refine_samples`` points spread along the segment the gradient across the line (3x3 Sobel,
    bilinear) is sampled at whole-pixel offsets up to ``refine_radius_px`` either side; its peak, with the
    segment's own polarity, is located to sub-pixel by a parabola. A line offset(t) = a + b t fitted to the
    peaks (weighted by their strength, peaks more than 0.5 px off the first fit dropped) moves the endpoints.
    ``trim``: an end whose samples include at least two peaks off the fitted line (more than 0.5 px), and
    none on it, is cut back to the last sample on it (half a sample spacing beyond): LSD's angle tolerance
    joins two edges meeting at a small image angle into one segment (a box's two feet at a corner, seen from
    low and far), whose straight part is one edge and whose end is the other.
    A segment with fewer than a quarter of its samples on a peak keeps LSD's line. ``either_polarity``:
    the gradient's magnitude across the line is fitted (an occluding boundary's contrast changes sign where
    the background changes). ``grad``: ``gradients(image)``, if the caller has them. Returns the segments
    and (N,) bool: re-fitted.
    """
    n_seg = len(xy)
    if n_seg == 0:
        return xy, np.zeros(0, bool)
    gx, gy = gradients(image) if grad is None else grad
    k = params.refine_samples
    r = int(round(params.refine_radius_px if radius_px is None else radius_px))
    t = (np.arange(k) + 0.5) / k                                       # (k,) along the segment
    off = np.arange(-r, r + 1, dtype=np.float64)                       # (m,) across it
    p0, p1 = xy[:, 0:2], xy[:, 2:4]
    d = p1 - p0
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    nrm = np.column_stack((d[:, 1], -d[:, 0]))                         # (N, 2)
    pts = (p0[:, None, None, :] + (p1 - p0)[:, None, None, :] * t[None, :, None, None]
           + off[None, None, :, None] * nrm[:, None, None, :]).astype(np.float32)     # (N, k, m, 2)
    mx, my = pts[..., 0].reshape(n_seg, -1), pts[..., 1].reshape(n_seg, -1)
    sx = cv2.remap(gx, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(n_seg, k, -1)
    sy = cv2.remap(gy, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(n_seg, k, -1)
    prof = sx * nrm[:, None, None, 0] + sy * nrm[:, None, None, 1]      # gradient across the line (N, k, m)
    if either_polarity:
        prof = np.abs(prof)
    else:
        prof = prof * np.sign(prof[:, :, r].sum(axis=1))[:, None, None]     # the segment's polarity: peaks positive
    j = prof.argmax(axis=2)                                            # (N, k)
    inner = (j > 0) & (j < 2 * r)
    jc = np.clip(j, 1, 2 * r - 1)
    take = lambda q: np.take_along_axis(prof, q[..., None], axis=2)[..., 0]    # noqa: E731
    ym, y0, yp = take(jc - 1), take(jc), take(jc + 1)
    curv = ym - 2.0 * y0 + yp
    peak = inner & (curv < 0) & (y0 > 0)
    o = off[jc] + np.where(peak, 0.5 * (ym - yp) / np.where(peak, curv, -1.0), 0.0)
    w = np.where(peak, y0, 0.0)
    a, b = _fit_offsets(t, o, w)
    res = np.abs(o - (a[:, None] + b[:, None] * t[None]))
    w = np.where(res <= 0.5, w, 0.0)
    a, b = _fit_offsets(t, o, w)
    ok = ((w > 0).sum(axis=1) >= max(3, k // 4)) & (np.abs(a) <= r) & (np.abs(a + b) <= r)
    out = xy.copy()
    out[ok, 0:2] += a[ok, None] * nrm[ok]
    out[ok, 2:4] += (a + b)[ok, None] * nrm[ok]
    if trim:
        on = peak & (np.abs(o - (a[:, None] + b[:, None] * t[None])) <= 0.5)
        off = peak & ~on
        first, last = on.argmax(axis=1), k - 1 - on[:, ::-1].argmax(axis=1)
        idx = np.arange(k)[None]
        lo = np.where(ok & ((off & (idx < first[:, None])).sum(axis=1) >= 2), t[first] - 0.5 / k, 0.0)
        hi = np.where(ok & ((off & (idx > last[:, None])).sum(axis=1) >= 2), t[last] + 0.5 / k, 1.0)
        q0, q1 = out[:, 0:2].copy(), out[:, 2:4].copy()
        out[:, 0:2] = q0 + lo[:, None] * (q1 - q0)
        out[:, 2:4] = q0 + hi[:, None] * (q1 - q0)
    return out, ok


def _fit_offsets(t: np.ndarray, o: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least squares o = a + b t per row (t (k,), o and w (N, k)); rows without weight give 0, 0."""
    sw = w.sum(axis=1)
    swt, swtt = w @ t, w @ (t * t)
    swo, swto = (w * o).sum(axis=1), (w * o * t[None]).sum(axis=1)
    det = sw * swtt - swt * swt
    good = det > 1e-9 * np.maximum(sw, 1e-12) ** 2
    det = np.where(good, det, 1.0)
    a = np.where(good, (swtt * swo - swt * swto) / det, 0.0)
    b = np.where(good, (sw * swto - swt * swo) / det, 0.0)
    return a, b


def side_means(image: np.ndarray, xy: np.ndarray, params: LineParams = LineParams()) -> np.ndarray:
    """(N, 2) mean grey level ``side_offset_px`` to the left / right of each segment (bilinear samples)."""
    if len(xy) == 0:
        return np.zeros((0, 2))
    k = params.side_samples
    t = (np.arange(k) + 0.5) / k
    p0, p1 = xy[:, None, 0:2], xy[:, None, 2:4]
    pts = p0 + (p1 - p0) * t[None, :, None]                        # (N, k, 2)
    d = (xy[:, 2:4] - xy[:, 0:2])
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    nrm = np.column_stack((d[:, 1], -d[:, 0]))[:, None, :]        # left of travel in image coords (y down)
    out, g = [], np.asarray(image, np.float32)
    for sign in (1.0, -1.0):
        q = (pts + sign * params.side_offset_px * nrm).astype(np.float32)
        vals = cv2.remap(g, q[..., 0], q[..., 1], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)
        out.append(vals.mean(axis=1))
    return np.column_stack(out).astype(np.float64)


# -------------------------------------------------------------------------------------- matching
def _x_at(xy: np.ndarray, y: np.ndarray) -> np.ndarray:
    """x where each segment's line crosses row y (broadcasting; segments must not be horizontal)."""
    x0, y0, x1, y1 = (xy[..., i] for i in range(4))
    return x0 + (y - y0) * (x1 - x0) / np.where(np.abs(y1 - y0) < 1e-9, 1e-9, y1 - y0)


def epipolar_angle(seg: Segments2D) -> np.ndarray:
    """Angle (rad, 0..pi/2) of each segment to the image rows."""
    d = seg.direction
    return np.arcsin(np.clip(np.abs(d[:, 1]), 0.0, 1.0))


def match_stereo(left: Segments2D, right: Segments2D, params: LineParams = LineParams(),
                 prior: Optional[np.ndarray] = None) -> StereoMatches:
    """Candidate matches of left to right segments under the epipolar constraint.

    prior: optional (N_left, 2) of (predicted disparity px at the segment's midpoint, its sigma px),
    NaN where nothing is predicted (guided matching: candidates within the gate get the bonus).
    """
    nl, nr = len(left), len(right)
    empty = StereoMatches(np.zeros(0, int), np.zeros(0, int), np.zeros(0), np.zeros((0, 2)),
                          np.zeros(0, bool), np.zeros(0, bool))
    if nl == 0 or nr == 0:
        return empty
    sin_min = math.sin(math.radians(params.min_epipolar_angle_deg))
    okl = np.abs(left.direction[:, 1]) >= sin_min
    okr = np.abs(right.direction[:, 1]) >= sin_min
    L, R = left.xy[okl], right.xy[okr]
    il, ir = np.nonzero(okl)[0], np.nonzero(okr)[0]
    if len(L) == 0 or len(R) == 0:
        return empty
    # Row overlap (epipolar constraint).
    lo_l, hi_l = np.minimum(L[:, 1], L[:, 3]), np.maximum(L[:, 1], L[:, 3])
    lo_r, hi_r = np.minimum(R[:, 1], R[:, 3]), np.maximum(R[:, 1], R[:, 3])
    lo = np.maximum(lo_l[:, None], lo_r[None, :])
    hi = np.minimum(hi_l[:, None], hi_r[None, :])
    shorter = np.minimum((hi_l - lo_l)[:, None], (hi_r - lo_r)[None, :])
    overlap = np.clip(hi - lo, 0.0, None) / np.maximum(shorter, 1e-9)
    # Same direction and polarity.
    dl, dr = left.direction[il], right.direction[ir]
    cos_ang = dl @ dr.T
    # Disparity at the left segment's middle row (the right line extended there), where a prediction is given.
    ym = (0.5 * (L[:, 1] + L[:, 3]))[:, None]
    disp = 0.5 * (L[:, 0] + L[:, 2])[:, None] - _x_at(R[None, :, :], ym)
    # Appearance: the better-matching side (an occluding edge keeps only its near side).
    sl, sr = left.sides[il], right.sides[ir]
    dside = np.abs(sl[:, None, :] - sr[None, :, :])                    # (nl, nr, 2)
    app = np.exp(-0.5 * (dside.min(axis=2) / params.appearance_sigma) ** 2)
    score = overlap * app
    valid = ((overlap >= params.min_overlap) & (cos_ang >= math.cos(math.radians(params.max_angle_diff_deg)))
             & (disp >= params.min_disparity_px) & (disp <= params.max_disparity_px))
    predicted = np.zeros_like(valid)
    if prior is not None:
        pd, ps = prior[il, 0], prior[il, 1]
        has = np.isfinite(pd)
        gate = 3.0 * np.where(has, ps, 0.0) + params.prior_gate_px
        predicted = has[:, None] & (np.abs(disp - np.where(has, pd, 0.0)[:, None]) <= gate[:, None]) & valid
        score = np.where(predicted, score * (1.0 + params.prior_bonus), score)
    score = np.where(valid & (score >= params.min_score), score, 0.0)
    best = score.max(axis=1)
    keep = (score > 0) & (score >= params.ambiguity_ratio * best[:, None])
    a, b = np.nonzero(keep)
    if len(a) == 0:
        return empty
    is_best = score[a, b] >= best[a]
    # Endpoint disparities: the right line's x at each left endpoint's row.
    Lk, Rk = L[a], R[b]
    d0 = Lk[:, 0] - _x_at(Rk, Lk[:, 1])
    d1 = Lk[:, 2] - _x_at(Rk, Lk[:, 3])
    # Best: the top candidate of its left segment that is also the top candidate of its right segment
    # (mutual best; one per left segment, ties to the first).
    best_r = score.max(axis=0)
    mutual = is_best & (score[a, b] >= best_r[b])
    first = np.zeros(len(a), bool)
    seen = set()
    for k in np.nonzero(mutual)[0]:
        if a[k] not in seen:
            seen.add(a[k])
            first[k] = True
    return StereoMatches(il[a], ir[b], score[a, b], np.column_stack((d0, d1)), first, predicted[a, b])


def _sample(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of a float32 image at (x, y) (any equal shapes; 0 outside the image)."""
    n = x.size
    pad = (-n) % 1024                        # remap takes maps under 32767 rows and columns: 1024 columns
    mx = np.concatenate((x.astype(np.float32).ravel(), np.zeros(pad, np.float32))).reshape(-1, 1024)
    my = np.concatenate((y.astype(np.float32).ravel(), np.zeros(pad, np.float32))).reshape(-1, 1024)
    out = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out.ravel()[:n].reshape(x.shape)


def gradients(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The image's gradient (3x3 Sobel / 8, float32) along x and y: computed once per image of a pair and
    given to the steps that read it (re-fit, edge search, vertical lines)."""
    g = np.asarray(image, np.float32)
    return (cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3, scale=0.125), cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3, scale=0.125))


def match_edges(left_image: np.ndarray, right_image: np.ndarray, left: Segments2D, todo: np.ndarray,
                params: LineParams = LineParams(), grads: Optional[tuple] = None) -> tuple[np.ndarray, np.ndarray]:
    """Partners in the right image for the left segments ``todo`` (indices) that LSD found none for.

    At an occluding boundary the background differs between the two images, so the edge's contrast changes
    along it, differently in each image, and LSD breaks it into pieces at different rows (or misses it) in
    the right image. The edge itself is still there: along the epipolar lines, at the disparity of the
    nearer surface (which owns the boundary). For every integer disparity in range the right image's
    gradient across the segment (either sign) is averaged at the ``edge_samples`` points of the left
    segment shifted by it; local maxima at least ``edge_strength`` x the left segment's own gradient are
    candidates. A candidate needs one side band (``band_px`` off the line) to match between the images
    (mean |left - right| <= ``band_max_diff``: the near surface is the same in both; at a wrong disparity
    neither side is), and must be the only one (periodic texture gives several: no partner). The right
    line is then re-fitted to the gradient's magnitude (``refit_lines``, 2 px either side) and kept if it
    moved at most ``edge_refit_px`` from the searched disparity at both ends.

    ``grads``: ``gradients`` of both images' grey levels, if the caller has them. Returns the right
    segments' ``xy`` (K, 4) and the left index of each (K,).
    """
    todo = np.asarray(todo, int)
    none = np.zeros((0, 4)), np.zeros(0, int)
    if len(todo) == 0:
        return none
    L = grey(left_image).astype(np.float32)
    R = grey(right_image).astype(np.float32)
    xy = left.xy[todo]
    d_dir = left.direction[todo]
    nrm = np.column_stack((d_dir[:, 1], -d_dir[:, 0]))                          # (N, 2)
    k = params.edge_samples
    t = (np.arange(k) + 0.5) / k
    q = xy[:, None, 0:2] + (xy[:, None, 2:4] - xy[:, None, 0:2]) * t[None, :, None]      # (N, k, 2)
    (lgx, lgy), (rgx, rgy) = (gradients(L), gradients(R)) if grads is None else grads
    strength = np.abs(_sample(lgx, q[..., 0], q[..., 1]) * nrm[:, None, 0]
                      + _sample(lgy, q[..., 0], q[..., 1]) * nrm[:, None, 1]).mean(axis=1)   # (N,)
    D = np.arange(math.ceil(params.min_disparity_px), math.floor(params.max_disparity_px) + 1, dtype=np.float64)
    if len(D) == 0:                                  # no whole disparity in range: nothing to search
        return none
    xs = q[..., 0][..., None] - D                                                  # (N, k, nD)
    ys = np.broadcast_to(q[..., 1][..., None], xs.shape)
    E = np.abs(_sample(rgx, xs, ys) * nrm[:, None, None, 0]
               + _sample(rgy, xs, ys) * nrm[:, None, None, 1]).mean(axis=1)        # (N, nD)
    Ep = np.pad(E, ((0, 0), (1, 1)))
    peak = (E >= Ep[:, :-2]) & (E > Ep[:, 2:]) & (E >= params.edge_strength * strength[:, None])
    n_idx, d_idx = np.nonzero(peak)
    if len(n_idx) == 0:
        return none
    # Side bands at each candidate: either side matching is the near surface.
    off = np.asarray(params.band_px, float)
    cost = []
    for sign in (1.0, -1.0):
        bx = q[n_idx, :, None, 0] + sign * off[None, None, :] * nrm[n_idx, None, None, 0]     # (C, k, o)
        by = q[n_idx, :, None, 1] + sign * off[None, None, :] * nrm[n_idx, None, None, 1]
        cost.append(np.abs(_sample(L, bx, by) - _sample(R, bx - D[d_idx][:, None, None], by)).mean(axis=(1, 2)))
    good = np.minimum(*cost) <= params.band_max_diff
    n_idx, d_idx = n_idx[good], d_idx[good]
    count = np.bincount(n_idx, minlength=len(todo))
    one = count[n_idx] == 1
    n_idx, d_idx = n_idx[one], d_idx[one]
    if len(n_idx) == 0:
        return none
    shifted = xy[n_idx] - D[d_idx][:, None] * np.array([1.0, 0.0, 1.0, 0.0])
    fit, ok = refit_lines(R, shifted, params, radius_px=2.0, either_polarity=True, grad=(rgx, rgy))
    moved = np.abs(fit - shifted)[:, [0, 2]].max(axis=1)
    keep = ok & (moved <= params.edge_refit_px)
    return fit[keep], todo[n_idx[keep]]


# ---------------------------------------------------------------------------------- triangulation
def triangulate(left: Segments2D, right: Segments2D, matches: StereoMatches, fx: float, fy: float,
                cx: float, cy: float, baseline: float, params: LineParams = LineParams(),
                doffs: float = 0.0) -> Segments3D:
    """3D segments (left camera frame) with endpoint covariances for the given matches.

    The left segment is clipped to the rows it shares with the right one, so
    neither image's over-long endpoint extends the 3D segment. ``doffs``: the
    right principal point minus the left one (px; 0 for pairs rectified to a
    common principal point, Middlebury gives it).
    """
    if len(matches) == 0:
        return Segments3D.empty()
    L, R = left.xy[matches.left], right.xy[matches.right]
    lo = np.maximum(np.minimum(L[:, 1], L[:, 3]), np.minimum(R[:, 1], R[:, 3]))
    hi = np.minimum(np.maximum(L[:, 1], L[:, 3]), np.maximum(R[:, 1], R[:, 3]))
    y0 = np.clip(L[:, 1], lo, hi)
    y1 = np.clip(L[:, 3], lo, hi)
    x0, x1 = _x_at(L, y0), _x_at(L, y1)
    d0 = x0 - _x_at(R, y0) + doffs
    d1 = x1 - _x_at(R, y1) + doffs
    uv = np.stack((np.column_stack((x0, y0)), np.column_stack((x1, y1))), axis=1)   # (K, 2, 2)
    d = np.column_stack((d0, d1))
    # Both ends at least the smallest disparity matched (the match tests the middle's; an end can be below it):
    # on a pair of identical images ends at 0.02 px were points kilometres away.
    ok = (d >= params.min_disparity_px).all(axis=1)
    uv, d, L, R = uv[ok], d[ok], L[ok], R[ok]
    Z = fx * baseline / d
    X = (uv[..., 0] - cx) * Z / fx
    Y = (uv[..., 1] - cy) * Z / fy
    P = np.stack((X, Y, Z), axis=-1)
    # Image covariance of an endpoint: anisotropic (across / along the line), plus the disparity's.
    t = uv[:, 1] - uv[:, 0]
    t = t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    n = np.column_stack((-t[:, 1], t[:, 0]))
    S_uv = (params.sigma_perp_px ** 2 * n[:, :, None] * n[:, None, :]
            + params.sigma_along_px ** 2 * t[:, :, None] * t[:, None, :])          # (K, 2, 2)
    sin_a = np.maximum(np.abs(t[:, 1]), 1e-3)
    var_d = 2.0 * (params.sigma_perp_px / sin_a) ** 2                               # (K,)
    cov = np.zeros(P.shape[:2] + (3, 3))
    for e in range(2):
        J = np.zeros((len(P), 3, 3))         # d(X, Y, Z) / d(u, v, d)
        z, dd = Z[:, e], d[:, e]
        J[:, 0, 0] = z / fx
        J[:, 1, 1] = z / fy
        J[:, 0, 2] = -X[:, e] / dd
        J[:, 1, 2] = -Y[:, e] / dd
        J[:, 2, 2] = -z / dd
        S = np.zeros((len(P), 3, 3))
        S[:, :2, :2] = S_uv
        S[:, 2, 2] = var_d
        cov[:, e] = J @ S @ J.transpose(0, 2, 1)
    left_xy = np.column_stack((uv[:, 0], uv[:, 1]))
    right_xy = np.column_stack((uv[:, 0, 0] - d[:, 0] + doffs, uv[:, 0, 1], uv[:, 1, 0] - d[:, 1] + doffs,
                                uv[:, 1, 1]))
    return Segments3D(P, cov, left_xy, right_xy, matches.score[ok], matches.left[ok], matches.best[ok],
                      {"right_index": matches.right[ok], "predicted": matches.predicted[ok],
                       "disparity": d})


@dataclass
class StereoLines:
    """Everything one stereo pair gave: both images' segments, the candidate matches and the 3D segments."""

    left: Segments2D
    right: Segments2D
    matches: StereoMatches
    segments: Segments3D


def reconstruct_pair(left_image: np.ndarray, right_image: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                     baseline: float, params: LineParams = LineParams(), prior_fn=None,
                     doffs: float = 0.0, vertical: Optional[np.ndarray] = None) -> StereoLines:
    """Detect, match and triangulate one rectified pair.

    prior_fn(left_segments) -> (N, 2) prediction for guided matching (see ``match_stereo``), or None.
    vertical: the world's vertical (3,) in the left camera frame, when the camera's orientation is known;
    with ``params.vertical_search`` the vertical lines of ``vision/line_vertical.py`` are added.
    """
    grads = gradients(grey(left_image)), gradients(grey(right_image))     # each step reads the same ones
    ls, rs = detect_segments(left_image, params, grads[0]), detect_segments(right_image, params, grads[1])
    prior = prior_fn(ls) if prior_fn is not None else None
    m = match_stereo(ls, rs, params, prior)
    if params.edge_search:
        rs, m = _add_edge_matches(left_image, right_image, ls, rs, m, params, grads)
    if vertical is not None and params.vertical_search:
        from vbnav.vision.line_vertical import add_vertical_matches
        ls, rs, m = add_vertical_matches(left_image, right_image, ls, rs, m, vertical, fx, fy, cx, cy, params,
                                         grads)
    return StereoLines(ls, rs, m, triangulate(ls, rs, m, fx, fy, cx, cy, baseline, params, doffs))


def _add_edge_matches(left_image: np.ndarray, right_image: np.ndarray, ls: Segments2D, rs: Segments2D,
                      m: StereoMatches, params: LineParams, grads: Optional[tuple] = None) -> tuple[Segments2D, StereoMatches]:
    """The right segments and matches with ``match_edges``' partners of the steep left segments LSD left
    unmatched appended (each its left segment's only, best candidate; score: its appearance as in
    ``match_stereo``)."""
    steep = np.abs(ls.direction[:, 1]) >= math.sin(math.radians(params.min_epipolar_angle_deg))
    todo = np.nonzero(steep & ~np.isin(np.arange(len(ls)), m.left))[0]
    rxy, li = match_edges(left_image, right_image, ls, todo, params, grads)
    if len(li) == 0:
        return rs, m
    sides = side_means(grey(right_image), rxy, params)
    app = np.exp(-0.5 * (np.abs(ls.sides[li] - sides).min(axis=1) / params.appearance_sigma) ** 2)
    ri = len(rs) + np.arange(len(li))
    L = ls.xy[li]
    disp = np.column_stack((L[:, 0] - _x_at(rxy, L[:, 1]), L[:, 2] - _x_at(rxy, L[:, 3])))
    rs = Segments2D(np.concatenate((rs.xy, rxy)), np.concatenate((rs.sides, sides)))
    cat = np.concatenate
    m = StereoMatches(cat((m.left, li)), cat((m.right, ri)), cat((m.score, app)), cat((m.disparity, disp)),
                      cat((m.best, np.ones(len(li), bool))), cat((m.predicted, np.zeros(len(li), bool))))
    return rs, m
