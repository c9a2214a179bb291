"""A box's missing top and lower edges measured in the recent keyframes (section 11.2.1.1's hypotheses).

The slow loop (vision/line_abstraction.py) turns a box's verified corners into hypotheses of its missing
lines; a horizontal one (a top or a lower edge) comes when the corners were verified, often as the box
leaves the view, so it is first looked for in the frames already seen: the map's keyframes (``Keyframe``:
the left segments, the camera pose and the left image of frames a distinct viewpoint apart).

``sight_hypotheses`` runs on the slow loop's thread (control/stages/line_map.py, ``AbstractionThread``) on
a snapshot of the keyframes, and returns one ``HorizontalFix`` (or None) per hypothesis; the fast loop
inserts the hypotheses with their fixes (``LineMap.add_hypotheses``), which costs it nothing more than an
insertion. Looking for a box's eight edges in up to 40 keyframes' images costs 40-100 ms: on the fast loop's
thread that was one frame in 150 ms (issue 16's 15 Hz).

Pure: arrays in, estimates out. A keyframe's gradient is computed once, when a hypothesis is first looked
for in it, and kept with it (only this module's functions compute it).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Optional

import cv2
import numpy as np

from vbnav.vision.line_projection import project_segments
from vbnav.vision.line_segments import gradients
from vbnav.vision.line_vertical import SOBEL_NOISE_GAIN, noise_sigma

if TYPE_CHECKING:
    from vbnav.vision.line_map import MapParams

HYPOTHESIS_SIGMA_M = 0.05  # a hypothesis's sigma per axis: its corners' positions, the footprint's fit
RIDGE_SAMPLES = 64       # points of a hypothesis's line whose median gradient is its ridge response
CHI2_1_99 = 6.63         # 99 % quantile of chi-square with 1 degree of freedom (a height)
CHI2_2_99 = 9.21         # ... with 2 (an image line's position)


@dataclass(eq=False)
class Keyframe:
    """A frame the map remembers: its left segments ``xy`` (N, 4), camera pose (``R``: camera to world,
    ``t``: the camera centre) and its left grey image (None when the caller gave none)."""

    xy: np.ndarray
    R: np.ndarray
    t: np.ndarray
    image: Optional[np.ndarray] = None
    _gradient: Optional[tuple] = field(default=None, repr=False)

    def gradient(self) -> tuple:
        """((gx, gy), noise sigma) of the image, computed when first asked for."""
        if self._gradient is None:
            self._gradient = (gradients(self.image), noise_sigma(self.image))
        return self._gradient


@dataclass
class HorizontalFix:
    """A horizontal hypothesis measured in the keyframes: the height ``y`` (2,) of each end (world y, m),
    its variance ``var_y`` (2,) (1 / the summed weights of the sightings kept), the ``support`` (sightings
    kept) and the distinct viewpoints ``views`` they came from."""

    y: np.ndarray
    var_y: np.ndarray
    support: int
    views: list


def viewpoint(R_wc: np.ndarray, t_wc: np.ndarray) -> np.ndarray:
    """(x, y, z, heading) of a camera pose: the camera centre and the heading of its optical axis."""
    return np.array([t_wc[0], t_wc[1], t_wc[2], math.atan2(R_wc[0, 2], R_wc[2, 2])])


def same_viewpoint(a: np.ndarray, b: np.ndarray, params: "MapParams") -> bool:
    """Viewpoints (x, y, z, heading) nearer than ``view_baseline_m`` and ``view_angle_deg`` are one: the rule
    for a segment's views, the keyframes and a hypothesis's sightings."""
    d = a[:3] - b[:3]
    return (math.sqrt(d.dot(d)) < params.view_baseline_m
            and abs(math.remainder(a[3] - b[3], math.tau)) < math.radians(params.view_angle_deg))


def distinct_views(views: list, params: "MapParams") -> list:
    """The viewpoints of ``views`` apart (``same_viewpoint``) from every one kept before them."""
    distinct: list = []
    for v in views:
        if not any(same_viewpoint(v, w, params) for w in distinct):
            distinct.append(v)
    return distinct


def is_horizontal(A: np.ndarray) -> bool:
    """A hypothesis (2, 3) whose ends are at one height: a box's top or lower edge."""
    return abs(A[0, 1] - A[1, 1]) < 1e-9


def sight_hypotheses(P: np.ndarray, keyframes: list, camera: tuple, params: "MapParams",
                     sigma_m: float = HYPOTHESIS_SIGMA_M, pinned: Optional[np.ndarray] = None) -> list:
    """Per hypothesis of P (K, 2, 3): its ``HorizontalFix`` in the keyframes (``measure_horizontal``), or None
    (not horizontal, not seen from enough viewpoints, or sightings that disagree). camera: (fx, fy, cx, cy,
    baseline, width, height) of the left image. pinned (K, 2) bool: the ends that are seen corners (the
    others, footprint corners, are checked to reach the edge: ``ridge_sighting``); None: all."""
    if params.sight_sigma_px <= 0:
        return [None] * len(P)
    P = np.asarray(P, float).reshape(-1, 2, 3)
    pinned = np.ones((len(P), 2), bool) if pinned is None else np.asarray(pinned, bool).reshape(-1, 2)
    return [measure_horizontal(A, keyframes, camera, params, sigma_m, tuple(pin)) if is_horizontal(A) else None
            for A, pin in zip(P, pinned)]


def measure_horizontal(A: np.ndarray, keyframes: list, camera: tuple, params: "MapParams",
                       sigma_m: float = HYPOTHESIS_SIGMA_M, pinned: tuple = (True, True)) -> Optional[HorizontalFix]:
    """A horizontal hypothesis A (2, 3) (a box's top or lower edge) in the keyframes: each sighting's plane
    (``sightings``) meets the vertical lines of the edge's two corners (their x, z: verified vertical edges)
    at the edge's ends' heights, each with the sigma s z / (fx |n_y|) and ``assoc_extra_m``. A horizontal line
    seen while driving spans one plane with every camera centre (the camera's height is fixed), so its height
    cannot be triangulated; its corners' lines fix where it is. Measured when seen from ``verify_views``
    distinct viewpoints and every frame's heights lie within the chi-square gate (1 dof, 99 %) of their
    weighted mean: the mean is its height. A keyframe with several ridges (none 1.5 x the others) counts with
    the one within the gate of the height the keyframes with one ridge give, when exactly one is (at 0.6 m
    the gate's 4 mm of pose is 7 px: two ridges 3 px apart can both be within it). A lower edge lies on the
    floor; measuring its height all the same is the check that the lines found agree."""
    p = params
    fx = camera[0]
    cand = []                                       # per frame: heights (C, 2), weights (C, 2), viewpoint
    for ns, R, t in sightings(A, keyframes, camera, params, sigma_m, pinned):
        ns = [n for n in ns if abs(n[1]) >= 1e-6]
        if not ns:
            continue
        ze = np.maximum((A - t) @ R[:, 2], 0.1)
        y = np.array([[(n @ t - n[0] * A[e, 0] - n[2] * A[e, 2]) / n[1] for e in range(2)] for n in ns])
        w = np.array([1.0 / ((p.sight_sigma_px * ze / (fx * abs(n[1]))) ** 2 + p.assoc_extra_m ** 2) for n in ns])
        cand.append((y, w, viewpoint(R, t)))
    # The frames with one ridge decide; a frame with several (``ridge_sighting``: none 1.5 x the others)
    # adds the one within the gate of their height, when exactly one is (another viewpoint decides, as
    # for rival stereo matches: a ridge of the background moves with the viewpoint, the edge stays put).
    one = [c for c in cand if len(c[0]) == 1]
    ys, ws, views = [c[0][0] for c in one], [c[1][0] for c in one], [c[2] for c in one]
    fix = _agreeing(np.reshape(ys, (-1, 2)), np.reshape(ws, (-1, 2)), views, 1)
    if fix is None:
        return None
    for y, w, v in (c for c in cand if len(c[0]) > 1):
        inside = (w * (y - fix[0]) ** 2).max(axis=1) <= CHI2_1_99
        if inside.sum() == 1:
            k = int(np.argmax(inside))
            ys.append(y[k])
            ws.append(w[k])
            views.append(v)
    out = _agreeing(np.array(ys), np.array(ws), views, p.verify_views)
    if out is None:
        return None
    y, var_y, support, kept = out
    distinct = distinct_views(kept, params)
    if len(distinct) < p.verify_views:
        return None
    return HorizontalFix(y, var_y, support, distinct)


def _agreeing(ys: np.ndarray, ws: np.ndarray, views: list, least: int) -> Optional[tuple]:
    """The frames' heights ys (F, 2) (weights ws) within the chi-square gate (1 dof, 99 %) of their weighted
    mean, dropping the farthest first (another line near the prediction in that frame) while at least
    ``least`` are left: (mean (2,), its variance (2,), how many kept, their viewpoints), or None."""
    keep = np.ones(len(ys), bool)
    while keep.sum() >= max(least, 1):
        y = (ws[keep] * ys[keep]).sum(axis=0) / ws[keep].sum(axis=0)
        chi = np.where(keep, (ws * (ys - y) ** 2).max(axis=1), -1.0)
        if chi.max() <= CHI2_1_99:
            return y, 1.0 / ws[keep].sum(axis=0), int(keep.sum()), [v for v, k in zip(views, keep) if k]
        keep[int(chi.argmax())] = False
    return None


def sightings(A: np.ndarray, keyframes: list, camera: tuple, params: "MapParams",
              sigma_m: float = HYPOTHESIS_SIGMA_M, pinned: tuple = (True, True)) -> list:
    """Hypothesis A (2, 3) in the keyframes: in a keyframe that kept its image, a horizontal hypothesis is
    looked for in the image's gradient (``ridge_sighting``); in the others, where it is predicted in view,
    the nearest left segment along its prediction (direction ``predict_angle_deg``, midpoint within the
    prediction and within sqrt(chi2_2,99 %) sqrt(s^2 + (fx sigma_m / z)^2) px of it, s =
    ``sight_sigma_px``). Returns a list of (normals, R, t): the unit normals (world frame) of the planes the
    line spans with the camera centre t, one per ridge or segment found there (several: the ridges of an
    ambiguous image, ``ridge_sighting``)."""
    p = params
    fx, fy, cx, cy, _, width, height = camera
    Kinv = np.linalg.inv(np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]))
    out = []
    for kf in keyframes:
        R, t, xy = kf.R, kf.t, kf.xy
        if kf.image is not None and is_horizontal(A):
            ns = ridge_sighting(A, kf, camera, params, sigma_m, pinned)
            if ns:
                out.append((ns, R, t))
            continue
        pr = project_segments(A[None], R, t, fx, fy, cx, cy, width, height, p.max_range_m,
                              p.predict_min_length_px)
        if not pr.keep[0] or len(xy) == 0:
            continue
        a, b = pr.xy[0, :2], pr.xy[0, 2:]
        L = float(np.linalg.norm(b - a))
        u = (b - a) / L
        mid = 0.5 * (xy[:, :2] + xy[:, 2:])
        along = (mid - a) @ u / L
        dist = np.abs((mid - a) @ np.array([u[1], -u[0]]))
        d = xy[:, 2:] - xy[:, :2]
        cos = np.abs(d @ u) / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-12)
        z = float((A.mean(axis=0) - t) @ R[:, 2])
        gate = math.sqrt(CHI2_2_99) * math.hypot(p.sight_sigma_px, fx * sigma_m / max(z, 0.1))
        ok = (dist <= gate) & (along >= 0) & (along <= 1) & (cos >= math.cos(math.radians(p.predict_angle_deg)))
        if not ok.any():
            continue
        j = np.nonzero(ok)[0][np.argmin(dist[ok])]
        n = np.cross(R @ (Kinv @ np.r_[xy[j, :2], 1.0]), R @ (Kinv @ np.r_[xy[j, 2:], 1.0]))
        n /= max(float(np.linalg.norm(n)), 1e-12)
        out.append(([n], R, t))
    return out


def ridge_sighting(A: np.ndarray, kf: Keyframe, camera: tuple, params: "MapParams",
                   sigma_m: float = HYPOTHESIS_SIGMA_M, pinned: tuple = (True, True)) -> list:
    """A horizontal hypothesis A (2, 3) (a box's top or lower edge between its corners' vertical lines) in
    one keyframe's image: the height at which the line between the corners, projected, runs along a ridge of
    the gradient across it, in MAGNITUDE (either sign: a box's top against a textured wall changes contrast
    sign every few tens of pixels, and LSD keeps pieces too short to be found or none). Heights from
    ``sight_up_m`` above the hypothesis (a top; its corners' LSD pieces end early) to 3 sigma_m below it
    (3 sigma_m either way for a lower edge), in steps moving the line 1 px (the peak refined by a parabola);
    the response at a height is the median of |gradient . normal| (3x3 Sobel / 8) over ``RIDGE_SAMPLES``
    points of the line, at least half of them in the image. A sighting when the best response is above
    ``ridge_k_sigma`` (3) sigma of the Sobel's noise and 1.5 x the best one more than 3 px from it (a unique
    ridge; both chosen, not derived: docs/line_map.md), and for a lower edge within 3 ``assoc_extra_m`` of
    the floor; an end that is not a seen corner (``pinned``) must be reached by the edge (below). Returns the
    unit normal of the plane through the camera centre and the line at that height, in a list; when the best
    ridge is not unique, the normals of every ridge within 1.5 x of it that passes the same tests (the
    peaks of the response more than 3 px from a stronger one kept), the best first, for the other
    keyframes to decide between (``measure_horizontal``); an empty list when the best fails a test."""
    p = params
    fx, fy, cx, cy, _, width, height = camera
    R, t = kf.R, kf.t
    y0 = float(A[0, 1])
    lower = abs(y0) < 1e-9
    T = RIDGE_SAMPLES
    s_ = (np.arange(T) + 0.5) / T
    base = A[0] + (A[1] - A[0]) * s_[:, None]                                   # (T, 3) at the hypothesis height
    zc = (base - t) @ R[:, 2]
    if (zc > 0.1).sum() < T // 2:
        return []
    step = max(float(zc[zc > 0.1].min()), 0.1) / fy           # 1 px at the nearest point (the peak: a parabola)
    lo, hi = y0 - (3.0 * sigma_m if lower else p.sight_up_m), y0 + 3.0 * sigma_m
    # Cull: the face between the corners' lines over the searched heights is a convex quadrilateral; when
    # its four corners lie in front of the camera and beyond one side of the image, so does all of it.
    quad = np.array([[A[e, 0], y, A[e, 2]] for e in range(2) for y in (lo, hi)])
    qc = (quad - t) @ R
    if (qc[:, 2] > 0.1).all():
        qu, qv = fx * qc[:, 0] / qc[:, 2] + cx, fy * qc[:, 1] / qc[:, 2] + cy
        if (qu < 1).all() or (qu > width - 2).all() or (qv < 1).all() or (qv > height - 2).all():
            return []
    ys = np.arange(lo, hi + 0.5 * step, step)
    (gx, gy), noise = kf.gradient()
    pts = np.broadcast_to(base, (len(ys), T, 3)).copy()
    pts[..., 1] = ys[:, None]
    pc = (pts - t) @ R                                                            # (Y, T, 3) camera frame
    z = pc[..., 2]
    ok = z > 0.1
    zs = np.where(ok, z, 1.0)
    u = fx * pc[..., 0] / zs + cx
    v = fy * pc[..., 1] / zs + cy
    ok &= (u >= 1) & (u <= width - 2) & (v >= 1) & (v <= height - 2)
    # The image line's normal at each height, from its first and last points in the image (the line is
    # straight; an end behind the camera has no projection).
    rows = np.arange(len(ys))
    first, last = np.argmax(ok, axis=1), T - 1 - np.argmax(ok[:, ::-1], axis=1)
    du, dv = u[rows, last] - u[rows, first], v[rows, last] - v[rows, first]
    ln = np.maximum(np.hypot(du, dv), 1e-9)
    nx, ny = -dv / ln, du / ln
    mx, my = u.astype(np.float32), v.astype(np.float32)
    sx = cv2.remap(gx, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    sy = cv2.remap(gy, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    mag = np.abs(sx * nx[:, None] + sy * ny[:, None])
    enough = ok.sum(axis=1) >= T // 2
    if not enough.any():
        return []
    # Each height's median over its points in the image (the others sorted first as -1).
    srt = np.sort(np.where(ok, mag, -1.0), axis=1)
    nv = ok.sum(axis=1)
    med = srt[rows, T - nv + (nv - 1) // 2]
    resp = np.where(enough, med, -1.0)
    best = int(np.argmax(resp))
    floor_resp = p.ridge_k_sigma * SOBEL_NOISE_GAIN * noise
    if resp[best] < floor_resp:
        return []
    # An end that is a footprint corner, not a seen corner, is where the rectangle says the box ends: the
    # edge must reach it (the median of that end quarter's points, when half of them are in the image, above
    # the noise too). The median over the whole line finds an edge the hypothesis overshoots by a third, and
    # a lower edge 0.2 m past box_a's corner was verified that way (room seed 2, 120 frames, from a footprint
    # a floor line had stretched). A seen corner's end is where the corner's line is: not checked (near a
    # corner the foot's contrast often fades, room seed 3).
    q = T // 4
    mid = T // 2

    def passes(k: int) -> bool:
        for end, part in zip(pinned, (slice(0, q), slice(T - q, T))):
            inside = ok[k, part]
            if not end and inside.sum() >= q // 2 and np.median(mag[k, part][inside]) < floor_resp:
                return False
        # A lower edge is on the floor: a ridge found higher is a line on the face (its search range is the
        # hypothesis's, only to test that the floor's ridge is the unique one).
        return not (lower and abs(float(ys[k])) > 3.0 * p.assoc_extra_m)

    def offset(k: int) -> np.ndarray:
        """Each height's line from height k's, across it, at the middle point (px)."""
        return np.abs((u[:, mid] - u[k, mid]) * nx[k] + (v[:, mid] - v[k, mid]) * ny[k])

    if not passes(best):
        return []
    ridges, offsets = [best], [offset(best)]
    far = enough & (offsets[0] > 3.0)
    if far.any() and resp[best] < 1.5 * resp[far].max():
        # Not unique: the peaks of the response within 1.5 x of the best, strongest first, each more than
        # 3 px from every stronger one kept, and passing the same tests.
        inner = resp[1:-1]
        peak = np.zeros(len(ys), bool)
        peak[1:-1] = far[1:-1] & (inner >= resp[:-2]) & (inner >= resp[2:]) & (1.5 * inner >= resp[best])
        for k in np.nonzero(peak)[0][np.argsort(-resp[peak], kind="stable")].tolist():
            if all(off[k] > 3.0 for off in offsets) and passes(k):
                ridges.append(k)
                offsets.append(offset(k))
    return [_plane(A, t, _refined(ys, resp, k, step)) for k in ridges]


def _refined(ys: np.ndarray, resp: np.ndarray, k: int, step: float) -> float:
    """Height k of the response's ridge, refined by the parabola through it and its two neighbours."""
    y = float(ys[k])
    if 0 < k < len(ys) - 1 and resp[k - 1] >= 0 and resp[k + 1] >= 0:
        a_, b_, c_ = resp[k - 1], resp[k], resp[k + 1]
        curv = a_ - 2.0 * b_ + c_
        if curv < 0:
            y += step * 0.5 * (a_ - c_) / curv
    return y


def _plane(A: np.ndarray, t: np.ndarray, y: float) -> np.ndarray:
    """The unit normal of the plane through the camera centre t and hypothesis A's line at height y."""
    P0 = np.r_[A[0, 0], y, A[0, 2]]
    P1 = np.r_[A[1, 0], y, A[1, 2]]
    n = np.cross(P0 - t, P1 - t)
    return n / max(float(np.linalg.norm(n)), 1e-12)
