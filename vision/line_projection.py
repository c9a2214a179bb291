"""3D line segments seen from a camera pose: projected into the left image, clipped in depth and to the image.

Shared by the DLM's prediction (``LineMap.predict``: what the current view should contain) and the slow
loop's sightings of hypotheses in the keyframes (vision/line_sighting.py). Pure: arrays in, arrays out.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

NEAR_M = 0.1      # segments are clipped to depth >= this in front of the camera before projection


@dataclass
class Projection:
    """Of K segments: ``keep`` (K,) the ones in view (in front of the camera, in the image, nearer than the
    range, long enough in the image); for those, ``xy`` (k, 4) their clipped image segments and
    ``inv_depth`` (k, 2) the inverse depth at the clipped ends (affine along the image of a 3D line)."""

    keep: np.ndarray
    xy: np.ndarray
    inv_depth: np.ndarray


def project_segments(P: np.ndarray, R_wc: np.ndarray, t_wc: np.ndarray, fx: float, fy: float, cx: float,
                     cy: float, width: int, height: int, max_range_m: float, min_length_px: float) -> Projection:
    """Segments P (K, 2, 3) (world frame) seen from camera pose (R_wc: camera to world, t_wc: its centre):
    clipped in 3D to depth >= ``NEAR_M``, projected, clipped to [0, W-1] x [0, H-1]; in view when some of
    it is left, its nearer clipped end lies within ``max_range_m`` in depth and it is at least
    ``min_length_px`` long in the image."""
    Pc = (P - t_wc) @ R_wc                     # camera frame (K, 2, 3)
    z = Pc[..., 2]
    n = len(P)
    t0, t1 = np.zeros(n), np.ones(n)
    dz = z[:, 1] - z[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        tz = (NEAR_M - z[:, 0]) / dz
    t0 = np.where((z[:, 0] < NEAR_M) & (dz > 0), np.maximum(t0, tz), t0)
    t1 = np.where((z[:, 1] < NEAR_M) & (dz < 0), np.minimum(t1, tz), t1)
    alive = (t1 > t0) & ((z[:, 0] >= NEAR_M) | (z[:, 1] >= NEAR_M))
    A = Pc[:, 0] + (Pc[:, 1] - Pc[:, 0]) * t0[:, None]
    B = Pc[:, 0] + (Pc[:, 1] - Pc[:, 0]) * t1[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        ua = np.column_stack((fx * A[:, 0] / A[:, 2] + cx, fy * A[:, 1] / A[:, 2] + cy))
        ub = np.column_stack((fx * B[:, 0] / B[:, 2] + cx, fy * B[:, 1] / B[:, 2] + cy))
        wa, wb = 1.0 / A[:, 2], 1.0 / B[:, 2]
    s0, s1 = clip_to_rect(ua, ub, width, height)
    alive &= s1 > s0
    pa = ua + (ub - ua) * s0[:, None]
    pb = ua + (ub - ua) * s1[:, None]
    w0 = wa + (wb - wa) * s0
    w1 = wa + (wb - wa) * s1
    with np.errstate(invalid="ignore"):
        in_range = np.minimum(w0, w1) >= 1.0 / max_range_m
        long_enough = np.hypot(*(pb - pa).T) >= min_length_px
    keep = alive & in_range & long_enough
    return Projection(keep, np.column_stack((pa, pb))[keep], np.column_stack((w0, w1))[keep])


def in_view_reach(fx: float, fy: float, cx: float, cy: float, width: int, height: int, max_range_m: float) -> float:
    """How far from the camera centre a point in the image and within ``max_range_m`` in depth can be:
    ``max_range_m`` sqrt(1 + a^2 + b^2), a, b the image's half-extents over the focal lengths."""
    a, b = max(cx, width - 1.0 - cx) / fx, max(cy, height - 1.0 - cy) / fy
    return max_range_m * math.sqrt(1.0 + a * a + b * b) + 1e-6


def clip_to_rect(a: np.ndarray, b: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Liang-Barsky: parameter range [s0, s1] of segments a->b inside [0, W-1] x [0, H-1] (s1 < s0: outside)."""
    d = b - a
    s0, s1 = np.zeros(len(a)), np.ones(len(a))
    for axis, lim in ((0, width - 1.0), (1, height - 1.0)):
        for p, q in ((-d[:, axis], a[:, axis]), (d[:, axis], lim - a[:, axis])):
            with np.errstate(divide="ignore", invalid="ignore"):
                r = q / p
            par = np.abs(p) < 1e-12
            s0 = np.where(~par & (p < 0), np.maximum(s0, r), s0)
            s1 = np.where(~par & (p > 0), np.minimum(s1, r), s1)
            s1 = np.where(par & (q < 0), -1.0, s1)
    return s0, s1
