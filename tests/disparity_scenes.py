"""Analytic stereo scenes with known truth: a floor, boxes, flat sheets, a step down, camber and a ramp.

Ray casting in closed form (no rendering library): each pixel's ray is met with
the floor (y = 0, world frame of vision/geometry.py, y down), the lower floor
beyond a step (y = depth), and axis-aligned boxes. The result is the true
disparity, which surface each pixel sees and its height above the floor; with
``textured_pair`` also a procedurally textured left/right image pair for SGBM.
Used by the tests (it lives with them: no product code needs it).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np

from vbnav.vision.geometry import rot_x
from vbnav.vision.stereo import StereoRig

FLOOR, LOWER_FLOOR, BOX0 = 0, 1, 2   # surface ids; box i is BOX0 + i; -1 is sky (no hit)


@dataclass(frozen=True)
class Box:
    """Axis-aligned box standing on the floor: x (right) and z (forward) extents in m, height in m."""

    x0: float
    x1: float
    z0: float
    z1: float
    height: float
    texel: float = 0.004    # texture scale, m; far surfaces need coarser texture to stay matchable


@dataclass(frozen=True)
class Scene:
    camera_height: float = 0.25
    pitch: float = 0.0                      # rad, positive looking down
    boxes: tuple[Box, ...] = ()
    step_z: Optional[float] = None          # the floor drops at this forward distance...
    step_depth: float = 0.0                 # ...by this much (m)
    # Street shapes (both FLOOR, i.e. ground): camber = (x_crown, s): left of x_crown the
    # road falls away at s (rise over run) from the camera's lane; ramp = (z_start, grade):
    # beyond z_start the floor rises at grade (negative: falls).
    camber: Optional[tuple[float, float]] = None
    ramp: Optional[tuple[float, float]] = None
    texture_seed: int = 7
    extra: dict = field(default_factory=dict)


@dataclass
class Rendered:
    disparity: np.ndarray        # float32 HxW, NaN where the ray hits nothing
    surface: np.ndarray          # int16 HxW surface id
    elevation: np.ndarray        # float32 HxW height above the (upper) floor, m (negative below)
    points: np.ndarray           # float32 HxWx3 world points
    normal_axis: np.ndarray      # int8 HxW world axis of the hit face's normal (0 x, 1 y, 2 z)


def _cast(scene: Scene, rig: StereoRig, cam_x: float) -> Rendered:
    h, w = rig.height, rig.width
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    r = np.stack([(u - rig.cx) / rig.fx, (v - rig.cy) / rig.fy, np.ones_like(u)], axis=-1)
    R_wc = rot_x(-scene.pitch)
    rw = r @ R_wc.T                                      # ray directions in the world frame
    C = np.array([cam_x, -scene.camera_height, 0.0])
    t = np.full((h, w), np.inf)
    surf = np.full((h, w), -1, np.int16)
    axis = np.full((h, w), 1, np.int8)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = np.where(rw[..., 1] > 1e-12, scene.camera_height / rw[..., 1], np.inf)
        if scene.step_z is not None:
            z_hit = C[2] + t_floor * rw[..., 2]
            beyond = np.isfinite(t_floor) & (z_hit > scene.step_z)
            t_low = (scene.camera_height + scene.step_depth) / rw[..., 1]
            surf_floor = np.where(beyond, LOWER_FLOOR, FLOOR)
            t_floor = np.where(beyond, t_low, t_floor)
        else:
            surf_floor = np.full((h, w), FLOOR)
        for bent in _bent_floor(scene, C, rw):        # camber / ramp pieces replace the flat floor there
            beyond, t_b = bent
            t_floor = np.where(beyond, t_b, np.where(_off_piece(scene, C, rw, t_floor), np.inf, t_floor))
        take = t_floor < t
        t[take], surf[take] = t_floor[take], surf_floor[take]
        for i, b in enumerate(scene.boxes):
            lo = np.array([b.x0, -b.height, b.z0])
            hi = np.array([b.x1, 0.0, b.z1])
            t1 = (lo - C) / rw
            t2 = (hi - C) / rw
            near = np.minimum(t1, t2)
            tmin = np.nanmax(near, axis=-1)
            tmax = np.nanmin(np.maximum(t1, t2), axis=-1)
            hit = (tmax >= tmin) & (tmin > 0) & (tmin < t)
            t[hit], surf[hit] = tmin[hit], BOX0 + i
            axis[hit] = np.nanargmax(near, axis=-1)[hit]
    with np.errstate(invalid="ignore"):
        P = C + t[..., None] * rw
    z_cam = t                                            # the camera-frame ray has z = 1
    disp = np.where(np.isfinite(t), rig.fb / z_cam, np.nan).astype(np.float32)
    elev = np.where(np.isfinite(t), -P[..., 1], np.nan).astype(np.float32)
    return Rendered(disp, surf, elev, P.astype(np.float32), axis)


def _bent_floor(scene: Scene, C, rw):
    """(hit mask, t) of the sloped pieces: a plane n . P = c met by the ray, valid on its side."""
    out = []
    if scene.camber is not None:            # x < xc: y = s (xc - x), i.e. (s, 1, 0) . P = s xc
        xc, s = scene.camber
        n, c = np.array([s, 1.0, 0.0]), s * xc
        t_b = (c - n @ C) / (rw @ n)
        x = C[0] + t_b * rw[..., 0]
        out.append(((t_b > 0) & (x < xc), t_b))
    if scene.ramp is not None:              # z > z0: y = -g (z - z0), i.e. (0, 1, g) . P = g z0
        z0, g = scene.ramp
        n, c = np.array([0.0, 1.0, g]), g * z0
        t_b = (c - n @ C) / (rw @ n)
        z = C[2] + t_b * rw[..., 2]
        out.append(((t_b > 0) & (z > z0), t_b))
    return out


def _off_piece(scene: Scene, C, rw, t_floor):
    """Flat-floor hits that lie where a sloped piece is the floor instead."""
    P = C + t_floor[..., None] * rw
    off = np.zeros(t_floor.shape, bool)
    if scene.camber is not None:
        off |= P[..., 0] < scene.camber[0]
    if scene.ramp is not None:
        off |= P[..., 2] > scene.ramp[0]
    return off


def render(scene: Scene, rig: StereoRig) -> Rendered:
    """True disparity and truth of the left camera."""
    return _cast(scene, rig, 0.0)


def _texture_tile(seed: int, size: int = 512) -> np.ndarray:
    rng = np.random.default_rng(seed)
    tile = rng.random((size, size)).astype(np.float32)
    tile = cv2.GaussianBlur(tile, (0, 0), 1.2)
    tile = (tile - tile.min()) / (tile.max() - tile.min())
    return tile


def _shade(rendered: Rendered, tile: np.ndarray, texel: np.ndarray) -> np.ndarray:
    """Grey image: the tile sampled at 2 world coordinates chosen by the surface's orientation."""
    P = rendered.points
    s = rendered.surface
    ax = rendered.normal_axis
    # Faces with normal z (fronts) use (x, y); normal x (sides) use (z, y); normal y (floors, tops) (x, z).
    a = np.where(ax == 0, P[..., 2], P[..., 0])
    b = np.where(ax == 1, P[..., 2], P[..., 1])
    offset = (s.astype(np.float32) * 97.0)
    n = tile.shape[0]
    a, b = np.nan_to_num(a), np.nan_to_num(b)
    mapx = np.mod(a / texel + offset, n - 1).astype(np.float32)
    mapy = np.mod(b / texel + offset * 0.5, n - 1).astype(np.float32)
    img = cv2.remap(tile, mapx, mapy, cv2.INTER_LINEAR)
    img = np.where(s < 0, 0.8, 0.15 + 0.7 * img)
    return img


def textured_pair(scene: Scene, rig: StereoRig, noise_std: float = 1.0,
                  rng: Optional[np.random.Generator] = None) -> tuple[np.ndarray, np.ndarray, Rendered]:
    """Rectified grey uint8 left/right images of the scene (right camera at +baseline in x)."""
    tile = _texture_tile(scene.texture_seed)
    texel = np.array([0.004, 0.004] + [b.texel for b in scene.boxes], np.float32)   # per surface id
    left = _cast(scene, rig, 0.0)
    right = _cast(scene, rig, rig.baseline)
    rng = rng or np.random.default_rng(0)
    out = []
    for r in (left, right):
        img = _shade(r, tile, texel[np.clip(r.surface, 0, None)]) * 255.0 + rng.normal(0.0, noise_std, r.disparity.shape)
        out.append(np.clip(img, 0, 255).astype(np.uint8))
    return out[0], out[1], left
