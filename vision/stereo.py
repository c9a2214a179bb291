"""A rectified stereo pair and its disparity (OpenCV semi-global matching).

Disparity D (pixels) and depth z (metres) are related by D = fx * B / z (11.1),
B the baseline. Everything downstream takes disparity images as float32 with
NaN where no disparity is known, so the source (SGBM here, the OAK's on-device
matcher, the simulated camera's true disparity) does not matter.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.features import orb_matches, to_grey


@dataclass(frozen=True)
class StereoRig:
    """The rectified left camera and the baseline (m) to the right one (right centre at +baseline along x)."""

    camera: PinholeCamera
    baseline: float

    def __post_init__(self):
        c = self.camera
        if not (c.width > 0 and c.height > 0):
            raise ValueError(f"StereoRig: image size must be positive, got {c.width}x{c.height}")
        if not (c.fx > 0 and c.fy > 0):
            raise ValueError(f"StereoRig: focal lengths must be positive, got fx={c.fx}, fy={c.fy}")
        if c.has_distortion:
            raise ValueError("StereoRig: the camera of a rectified pair has no distortion")
        if not self.baseline > 0:
            raise ValueError(f"StereoRig: baseline must be positive (metres), got {self.baseline}")

    # The left camera's numbers, read by the disparity formulas throughout vision/ground_plane.py,
    # vision/obstacles.py and their callers.
    width = property(lambda self: self.camera.width)
    height = property(lambda self: self.camera.height)
    fx = property(lambda self: self.camera.fx)
    fy = property(lambda self: self.camera.fy)
    cx = property(lambda self: self.camera.cx)
    cy = property(lambda self: self.camera.cy)

    @property
    def fb(self) -> float:
        """fx * baseline: disparity (px) times depth (m)."""
        return self.fx * self.baseline

    def depth(self, disparity):
        return self.fb / disparity

    def disparity_at(self, depth):
        return self.fb / depth

    def scaled(self, factor: float) -> "StereoRig":
        return StereoRig(self.camera.scaled(factor), self.baseline)


@dataclass(frozen=True)
class SgbmParams:
    """StereoSGBM settings. ``num_disparities`` must be a positive multiple of 16."""

    num_disparities: int = 64
    block_size: int = 5
    uniqueness_ratio: int = 10
    speckle_window: int = 100
    speckle_range: int = 2
    disp12_max_diff: int = 1
    mode: str = "sgbm_3way"   # "sgbm" (5 directions), "sgbm_3way" (faster), "hh" (8 directions)

    def __post_init__(self):
        if self.num_disparities <= 0 or self.num_disparities % 16:
            raise ValueError(f"SgbmParams.num_disparities must be a positive multiple of 16, "
                             f"got {self.num_disparities}")
        if self.block_size < 1 or self.block_size % 2 == 0:
            raise ValueError(f"SgbmParams.block_size must be odd and >= 1, got {self.block_size}")
        if self.mode not in _MODES:
            raise ValueError(f"SgbmParams.mode must be one of {sorted(_MODES)}, got {self.mode!r}")


_MODES = {"sgbm": cv2.STEREO_SGBM_MODE_SGBM, "sgbm_3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
          "hh": cv2.STEREO_SGBM_MODE_HH}

#: 640x480 robot camera (fx 400, B 7.5 cm): 80 disparities reach 0.375 m, nearer than the lowest
#: floor ray of a level camera 0.25 m up (0.42 m).
SGBM_640x480 = SgbmParams(num_disparities=80, block_size=5)
#: KITTI (1226x370, fx 707, B 0.54 m): 128 disparities reach 3 m.
SGBM_KITTI = SgbmParams(num_disparities=128, block_size=5)


#: The most disparities the stereo matchers here search (SGBM's time and memory grow with the count).
MAX_SGBM_DISPARITIES = 256


def sgbm_disparities_for(rig: StereoRig, min_depth: float) -> int:
    """How many disparities (a multiple of 16, at least 16) cover depths from ``min_depth`` to infinity."""
    return max(16, int(16 * math.ceil(rig.fb / min_depth / 16)))


def nearest_floor_m(rig: StereoRig, height_m: float, pitch_rad: float) -> float:
    """Distance ahead of the nearest floor point the bottom image row sees, for a camera ``height_m`` above a
    flat floor pitched down by ``pitch_rad``: the depth the obstacle stage's stereo matching must reach."""
    bottom = math.atan2(rig.height - 1 - rig.cy, rig.fy) + pitch_rad          # lowest ray below level
    return height_m / max(1e-3, math.tan(bottom))


def sgbm_params_for(rig: StereoRig, min_depth: float = 0.4, block_size: int = 5) -> SgbmParams:
    """Settings that cover depths from ``min_depth`` to infinity on this rig, at most
    ``MAX_SGBM_DISPARITIES`` (then the nearest depth covered is fB / 256: callers that take a depth from the
    user check ``sgbm_disparities_for`` first and say so).

    For the 640x480 robot camera (fx 400, B 7.5 cm) this gives 80 disparities; for
    KITTI (fx 707, B 0.54 m) and min_depth 3 m it gives 128.
    """
    num = min(MAX_SGBM_DISPARITIES, sgbm_disparities_for(rig, min_depth))
    return SgbmParams(num_disparities=num, block_size=block_size)


@lru_cache(maxsize=8)
def _matcher(p: SgbmParams):
    channels = 1
    return cv2.StereoSGBM_create(
        minDisparity=0, numDisparities=p.num_disparities, blockSize=p.block_size,
        P1=8 * channels * p.block_size ** 2, P2=32 * channels * p.block_size ** 2,
        disp12MaxDiff=p.disp12_max_diff, uniquenessRatio=p.uniqueness_ratio,
        speckleWindowSize=p.speckle_window, speckleRange=p.speckle_range, mode=_MODES[p.mode])


def _grey(img: np.ndarray, name: str) -> np.ndarray:
    if img.ndim == 3 and img.shape[2] in (3, 4):     # BGR, or BGRA as some V4L2 cameras deliver
        return to_grey(img)
    if img.ndim == 3 and img.shape[2] == 1:
        return img[:, :, 0]
    if img.ndim != 2:
        raise ValueError(f"{name} image must be HxW grey or HxWx3 BGR (or BGRA), got shape {img.shape}")
    return img


def _to_8bit_together(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A non-8-bit pair (16-bit, float) as 8 bits, both by one range (the pair's lowest to highest finite
    value): stretched each on its own, a scene brighter in one view gave the two images different grey levels
    for the same surface, and SGBM matched two different exposures. NaN is taken as the lowest value."""
    both = np.concatenate([np.ravel(left), np.ravel(right)]).astype(np.float64)
    finite = both[np.isfinite(both)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 0.0)
    scale = 255.0 / (hi - lo) if hi > lo else 0.0

    def to8(im):
        x = np.nan_to_num(im.astype(np.float64), nan=lo, posinf=hi, neginf=lo)
        return np.clip(np.rint((x - lo) * scale), 0, 255).astype(np.uint8)
    return to8(left), to8(right)


def sgbm_disparity(left: np.ndarray, right: np.ndarray, params: SgbmParams | None = None) -> np.ndarray:
    """Disparity of the left image (float32 px, NaN where unmatched) from a rectified pair."""
    if left.shape[:2] != right.shape[:2]:
        raise ValueError(f"left and right images differ in size: {left.shape[:2]} vs {right.shape[:2]}")
    p = params or SgbmParams()
    l8, r8 = _grey(left, "left"), _grey(right, "right")
    if l8.dtype != np.uint8 or r8.dtype != np.uint8:
        l8, r8 = _to_8bit_together(l8, r8)
    raw = _matcher(p).compute(l8, r8)           # int16, 4 fractional bits, -16 where invalid
    disp = raw.astype(np.float32) * np.float32(1.0 / 16.0)
    disp[raw <= 0] = np.nan
    return disp


def as_disparity(disparity: np.ndarray, invalid_at_or_below: float = 0.0) -> np.ndarray:
    """A disparity image in the convention used here: float32, NaN where unknown.

    Accepts float images (NaN / <= 0 for unknown) and the OAK's or SGBM's fixed-point
    output once scaled by the caller.
    """
    d = np.asarray(disparity, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f"disparity must be a HxW image, got shape {d.shape}")
    out = d.copy()
    out[~(out > invalid_at_or_below)] = np.nan
    return out


#: A pair's order is judged from at least this many matches off zero disparity (fewer: a blank view, no verdict).
PAIR_ORDER_MIN_MATCHES = 20


def pair_disparity_signs(left: np.ndarray, right: np.ndarray, row_tol_px: float = 2.0,
                         min_px: float = 1.0) -> tuple[int, int]:
    """(positive, negative): ORB matches of a rectified pair on the same row (within ``row_tol_px``) whose
    disparity left-minus-right is above ``min_px`` and below ``-min_px``. A pair the right way round has
    nearly all positive (nothing is behind the camera); swapped images, nearly all negative."""
    pl, pr = orb_matches(left, right)
    same_row = np.abs(pl[:, 1] - pr[:, 1]) <= row_tol_px
    d = (pl[:, 0] - pr[:, 0])[same_row]
    return int(np.sum(d > min_px)), int(np.sum(d < -min_px))

