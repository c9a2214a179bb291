"""Near-horizontal segments on the floor, reconstructed from one stereo frame and the known floor plane.

A segment nearly parallel to the image rows has no disparity of its own (vision/line_segments.py leaves
those within ``min_epipolar_angle_deg`` out), and from a robot driving past an edge the motion baseline
is degenerate too (moving along a line does not change the plane it spans with the camera centre). But
the robot knows its floor: the camera's height and tilt come from the mount, and the floor is y = 0 in
the world frame. The lower edges of boxes and the lines where walls meet the floor lie in that plane, so
each is the intersection of its back-projected plane with the floor.

Whether a segment is on the floor is tested in the same stereo pair: the floor just below it (a band
``band_px`` under the line, on the floor for a box's or a wall's foot) is warped into the right image
with the floor's disparity at each row; on the floor it matches (mean absolute grey difference within
``max_diff`` and ``contrast`` x better than at the floor disparity +-``shift_px``, so the band has texture
enough to tell), while texture on a box face or a wall below the camera does not: it stands in front of
the floor and its disparity is larger. The DLM then verifies the 3D segment from three viewpoints like
any stereo segment.

What stands on the line is tested the same way, above it (``stance``). The band ``above_px`` over the line
is warped twice: with the floor's disparity (the floor goes on beyond the line: a texture line or a marking,
FLAT) and with the disparity of the vertical plane through the 3D line (a face rises from it: a box's or a
wall's foot, STANDING). On a level camera the floor's disparity falls by baseline / height px per row above
the line while a face keeps the line's own (0.3 px per row for the simulated robot's 0.075 m baseline at
0.25 m), so 12 rows part the two hypotheses by 3.6 px, past the floor test's ``shift_px``. The better one
must match (``max_diff``) and be ``contrast`` x better than the other; else the stance is unknown (0). The
map keeps a foot and a texture line apart by it (vision/line_map.py): on the rooms of World.room seeds 2
and 5 (60 frames) 73-82 % of the feet's observations stood and none was flat, 77-79 % of the texture
lines' were flat and 0-1 % stood.

Covariance: each image endpoint moved by ``sigma_perp_px`` across the line (and ``sigma_along_px``
along it) and the camera's height over the floor by ``floor_sigma_m`` (mount calibration, floor
flatness), propagated through the ray-floor intersection by finite differences.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from vbnav.vision.line_segments import FLAT, STANDING, Segments2D, Segments3D, grey, refit_lines


@dataclass(frozen=True)
class FloorParams:
    max_angle_deg: float = 20.0      # the segments stereo leaves out (below this to the rows)
    min_length_px: float = 25.0
    band_px: tuple = (3.0, 6.0, 9.0)  # rows of the floor band under the line (beyond LSD's ~2 px support)
    above_px: tuple = (3.0, 6.0, 9.0, 12.0)   # rows of the band over it, for its stance (module docstring)
    samples: int = 16                # points along the segment per band row
    shift_px: float = 3.0            # the alternative disparities the floor's must beat
    contrast: float = 2.0            # ... by this factor (an untextured band proves nothing)
    max_diff: float = 12.0           # grey levels: mean |left - right| at the floor disparity (noise ~2)
    max_range_m: float = 3.0
    sigma_perp_px: float = 0.3
    sigma_along_px: float = 2.0
    floor_sigma_m: float = 0.003


def _floor_hit(uv: np.ndarray, K_inv: np.ndarray, R_wc: np.ndarray, t_wc: np.ndarray) -> np.ndarray:
    """World points (N, 3) where the rays of pixels uv (N, 2) meet the floor y = 0 (NaN: above the horizon)."""
    rays = np.column_stack((uv, np.ones(len(uv)))) @ K_inv.T @ R_wc.T          # world directions
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -t_wc[1] / rays[:, 1]
    s = np.where(s > 0, s, np.nan)
    return t_wc + s[:, None] * rays


def floor_segments(left: Segments2D, left_image: np.ndarray, right_image: np.ndarray, K: np.ndarray,
                   baseline: float, R_wc: np.ndarray, t_wc: np.ndarray,
                   params: FloorParams = FloorParams(), first_group: int = 2 * 10 ** 6) -> Segments3D:
    """3D segments (left camera frame) of the near-horizontal left segments that lie on the floor."""
    if len(left) == 0:
        return Segments3D.empty()
    sel = (np.abs(left.direction[:, 1]) < math.sin(math.radians(params.max_angle_deg))) \
        & (left.length >= params.min_length_px)
    idx = np.nonzero(sel)[0]
    if len(idx) == 0:
        return Segments3D.empty()
    K_inv = np.linalg.inv(K)
    L, R = grey(left_image).astype(np.float32), grey(right_image).astype(np.float32)
    xy = left.xy[idx]
    ok = _floor_points(xy, K_inv, R_wc, t_wc, params)[1]
    idx, xy = idx[ok], xy[ok]
    if len(idx) == 0:
        return Segments3D.empty()
    on = _floor_band_matches(xy, L, R, K, K_inv, baseline, R_wc, t_wc, params)
    # An end running on into another edge is cut back (refit_lines' trim): the floor would back-project the
    # other edge's part as this line's continuation.
    xy = refit_lines(L, xy[on], trim=True)[0]
    idx = idx[on]
    Pc, ok = _floor_points(xy, K_inv, R_wc, t_wc, params)
    ok &= np.linalg.norm(xy[:, 2:4] - xy[:, 0:2], axis=1) >= params.min_length_px
    idx, xy, Pc = idx[ok], xy[ok], Pc[ok]
    if len(idx) == 0:
        return Segments3D.empty()
    cov = _covariance(xy, Pc, K_inv, R_wc, t_wc, params)
    stance = _stance(xy, Pc, L, R, K, K_inv, baseline, R_wc, t_wc, params)
    n = len(idx)
    return Segments3D(Pc, cov, xy.copy(), np.full((n, 4), np.nan), np.ones(n), first_group + idx,
                      np.ones(n, bool), stance=stance)


def _floor_points(xy: np.ndarray, K_inv: np.ndarray, R_wc: np.ndarray, t_wc: np.ndarray,
                  params: FloorParams) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2, 3) the floor points of the image lines' ends xy (N, 4), camera frame, and (N,) bool: both in
    front of the camera, within range."""
    Pc = (_floor_hit(xy.reshape(-1, 2), K_inv, R_wc, t_wc).reshape(-1, 2, 3) - t_wc) @ R_wc
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(Pc).all(axis=(1, 2)) & (Pc[..., 2] > 0.1).all(axis=1) \
            & (Pc[..., 2] <= params.max_range_m).all(axis=1)
    return Pc, ok


def _band(xy: np.ndarray, offsets: tuple, samples: int, down: bool) -> np.ndarray:
    """(N, B, 2) image points of a band along each segment xy (N, 4): ``samples`` points along it on each of
    the rows ``offsets`` px off it, towards larger rows (``down``) or smaller."""
    t = (np.arange(samples) + 0.5) / samples
    pts = xy[:, None, 0:2] + (xy[:, None, 2:4] - xy[:, None, 0:2]) * t[None, :, None]      # (N, S, 2)
    d = xy[:, 2:4] - xy[:, 0:2]
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    off = np.column_stack((-d[:, 1], d[:, 0]))
    off = np.where((off[:, 1:2] < 0) == down, -off, off)
    return np.concatenate([pts + o * off[:, None, :] for o in offsets], axis=1)


def _sample(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return cv2.remap(img, u.astype(np.float32), v.astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)


def _mean_diff(lv: np.ndarray, R: np.ndarray, band: np.ndarray, disp: np.ndarray) -> np.ndarray:
    """(N,) mean |left - right| over each band (left samples lv (N, B)), the right image sampled at the band
    shifted by disparities disp (N, B); NaN when fewer than half the samples fall in both images."""
    rv = _sample(R, band[..., 0] - disp, band[..., 1])
    with np.errstate(invalid="ignore"):
        dev = np.abs(lv - rv)
        n_ok = np.isfinite(dev).sum(axis=1)
        return np.where(n_ok >= dev.shape[1] // 2, np.nansum(dev, axis=1) / np.maximum(n_ok, 1), np.nan)


def _floor_disparity(band: np.ndarray, fx: float, baseline: float, K_inv: np.ndarray, R_wc: np.ndarray,
                     t_wc: np.ndarray) -> np.ndarray:
    """(N, B) the floor's disparity at band points (N, B, 2) (NaN above the horizon)."""
    hit = _floor_hit(band.reshape(-1, 2), K_inv, R_wc, t_wc)
    z = ((hit - t_wc) @ R_wc)[:, 2]
    return (fx * baseline / z).reshape(band.shape[:2])


def _floor_band_matches(xy: np.ndarray, L: np.ndarray, R: np.ndarray, K: np.ndarray, K_inv: np.ndarray,
                        baseline: float, R_wc: np.ndarray, t_wc: np.ndarray, params: FloorParams) -> np.ndarray:
    """(N,) bool: the band under each segment matches the right image (float32 images L, R) at the floor's
    disparity."""
    band = _band(xy, params.band_px, params.samples, down=True)
    disp = _floor_disparity(band, K[0, 0], baseline, K_inv, R_wc, t_wc)
    lv = _sample(L, band[..., 0], band[..., 1])
    at, lo, hi = (_mean_diff(lv, R, band, disp + shift) for shift in (0.0, -params.shift_px, params.shift_px))
    with np.errstate(invalid="ignore"):
        return np.isfinite(disp).all(axis=1) & (at <= params.max_diff) & (params.contrast * at <= np.minimum(lo, hi))


def _stance(xy: np.ndarray, Pc: np.ndarray, L: np.ndarray, R: np.ndarray, K: np.ndarray, K_inv: np.ndarray,
            baseline: float, R_wc: np.ndarray, t_wc: np.ndarray, params: FloorParams) -> np.ndarray:
    """(N,) int8 STANDING, FLAT or 0 for floor lines xy (N, 4) at Pc (N, 2, 3) (camera frame) in the float32
    images L, R: whether the band over each matches the right image better with the disparity of a face
    standing on the line (the vertical plane through it) or with the floor's, going on beyond it (module
    docstring)."""
    band = _band(xy, params.above_px, params.samples, down=False)
    floor = _floor_disparity(band, K[0, 0], baseline, K_inv, R_wc, t_wc)
    vertical = R_wc.T @ np.array([0.0, 1.0, 0.0])                       # the world's vertical, camera frame
    n = np.cross(Pc[:, 1] - Pc[:, 0], vertical)
    rays = np.concatenate((band, np.ones(band.shape[:2] + (1,))), axis=2) @ K_inv.T  # (N, B, 3), z = 1
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.einsum("ni,ni->n", n, Pc[:, 0])[:, None] / np.einsum("ni,nbi->nb", n, rays)
        face = np.where(z > 0.1, K[0, 0] * baseline / z, np.nan)
    lv = _sample(L, band[..., 0], band[..., 1])
    at_floor, at_face = _mean_diff(lv, R, band, floor), _mean_diff(lv, R, band, face)
    c, m = params.contrast, params.max_diff
    with np.errstate(invalid="ignore"):
        standing = (at_face <= m) & (c * at_face <= at_floor)
        flat = (at_floor <= m) & (c * at_floor <= at_face)
    return np.where(standing, STANDING, np.where(flat, FLAT, 0)).astype(np.int8)


def _covariance(xy: np.ndarray, Pc: np.ndarray, K_inv: np.ndarray, R_wc: np.ndarray, t_wc: np.ndarray,
                params: FloorParams) -> np.ndarray:
    """(N, 2, 3, 3) endpoint covariances in the camera frame (finite differences through the floor hit)."""
    d = xy[:, 2:4] - xy[:, 0:2]
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    n = np.column_stack((-d[:, 1], d[:, 0]))
    cov = np.zeros(Pc.shape[:2] + (3, 3))
    dh = np.array([0.0, 0.5 * params.floor_sigma_m, 0.0])   # the camera's height over the floor
    up = R_wc.T @ np.array([0.0, 1.0, 0.0])                 # the floor's normal in the camera frame
    for e in range(2):
        uv = xy[:, 2 * e:2 * e + 2]
        for vec, sig in ((n, params.sigma_perp_px), (d, params.sigma_along_px)):
            moved = _floor_hit(uv + 0.5 * sig * vec, K_inv, R_wc, t_wc)
            back = _floor_hit(uv - 0.5 * sig * vec, K_inv, R_wc, t_wc)
            J = (moved - back) @ R_wc                       # camera frame, per sigma
            cov[:, e] += np.einsum("ki,kj->kij", J, J)
        J = (_floor_hit(uv, K_inv, R_wc, t_wc + dh) - _floor_hit(uv, K_inv, R_wc, t_wc - dh)) @ R_wc
        cov[:, e] += np.einsum("ki,kj->kij", J, J)
        cov[:, e] += params.floor_sigma_m ** 2 * np.outer(up, up)       # the floor's own unevenness
    return cov
