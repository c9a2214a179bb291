"""Calibration of a rectified stereo pair: KITTI ``calib.txt`` or a vbnav stereo YAML.

KITTI (odometry benchmark): lines ``P0: <12 numbers>`` and ``P1: <12 numbers>``, the
3x4 projection matrices of the rectified left and right grey cameras, row-major.
Files without the ``Pn:`` labels (two bare lines of 12 numbers, as in some
published subsets) are accepted too; ``#`` lines are comments. The left camera's
K = P0[:, :3]. Each rectified camera is Pi = K [I | t_i] with Pi[0,3] = fx t_i,x, so
the baseline (right camera centre at +B along the left camera's x) is
B = -(P1[0,3] - P0[0,3]) / P1[0,0]. The image size is not in the file; it comes
from the images. ``read_kitti_calib`` is the one reader of this format (the
dataset reader and the tests use it too).

vbnav stereo YAML (``*.yaml`` / ``*.yml``), documented in docs/obstacles.md::

    width: 640            # px, rectified images
    height: 480
    fx: 400.0             # px, rectified left camera
    fy: 400.0
    cx: 319.5
    cy: 239.5
    baseline: 0.075       # m, right camera centre at +baseline along the left camera's x
    mount:                # optional: camera pose above the floor, seeds the ground-plane fit
      height: 0.25        # m, optical centre above the floor
      pitch_deg: 0.0      # positive looking down
      roll_deg: 0.0
    disparity_scale: 1.0  # optional: disparity px per unit of a stored integer disparity image
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from vbnav.drivers.calibration import CalibrationError, check_intrinsics
from vbnav.drivers.errors import yaml_problem
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.stereo import StereoRig


class _Mount(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    height: float = Field(gt=0, description="m")
    pitch_deg: float = Field(0.0, ge=-90, le=90)
    roll_deg: float = Field(0.0, ge=-45, le=45)


class _StereoYaml(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    baseline: float = Field(gt=0, description="m")
    mount: Optional[_Mount] = None
    disparity_scale: Optional[float] = Field(None, gt=0)


@dataclass(frozen=True, eq=False)
class StereoCalibration:
    """A rectified stereo pair as a calibration file gives it.

    ``K`` is the rectified left camera's 3x3 intrinsic matrix. A KITTI file has no
    image size (``size`` None: it comes from the images) and may lack the right
    camera (``baseline`` None: a monocular sequence).
    """

    K: np.ndarray
    baseline: Optional[float]  # m, right camera centre at +baseline along the left camera's x
    size: Optional[tuple[int, int]] = None  # (width, height) of the rectified images
    mount_height: Optional[float] = None
    mount_pitch_deg: float = 0.0
    mount_roll_deg: float = 0.0
    disparity_scale: Optional[float] = None
    source: str = "<calibration>"

    # the left camera's intrinsics by name
    fx = property(lambda self: float(self.K[0, 0]))
    fy = property(lambda self: float(self.K[1, 1]))
    cx = property(lambda self: float(self.K[0, 2]))
    cy = property(lambda self: float(self.K[1, 2]))

    def camera(self, width: Optional[int] = None, height: Optional[int] = None) -> PinholeCamera:
        """The left camera for images of the given size (checked against the file's size if it has one)."""
        size = (width, height) if width is not None and height is not None else self.size
        if size is None:
            raise CalibrationError(f"{self.source}: the image size is not in the file; give the images")
        if self.size is not None and tuple(size) != tuple(self.size):
            raise CalibrationError(f"{self.source}: width/height: calibration is for {self.size[0]}x{self.size[1]} "
                                   f"images, got {size[0]}x{size[1]}")
        check_intrinsics(self.source, self.fx, self.fy, self.cx, self.cy, size[0], size[1],
                         prefix="" if self.size is not None else "P0 ")
        return PinholeCamera(int(size[0]), int(size[1]), self.fx, self.fy, self.cx, self.cy)

    def rig(self, width: Optional[int] = None, height: Optional[int] = None) -> StereoRig:
        """The StereoRig for images of the given size."""
        if self.baseline is None:
            raise CalibrationError(f"{self.source}: no right camera (P1) in the file")
        return StereoRig(self.camera(width, height), self.baseline)


def load_stereo_calibration(path: str | Path) -> StereoCalibration:
    """KITTI calib.txt or vbnav stereo YAML, chosen by the file suffix."""
    p = Path(path)
    if not p.is_file():
        raise CalibrationError(f"{p}: calibration file not found")
    if p.suffix.lower() in (".yaml", ".yml"):
        return _load_yaml(p)
    return read_kitti_calib(p)


def _load_yaml(p: Path) -> StereoCalibration:
    try:
        data = yaml.safe_load(p.read_text())
    except yaml.YAMLError as exc:
        raise CalibrationError(f"{p}: {yaml_problem(exc)}") from None
    if not isinstance(data, dict):
        raise CalibrationError(f"{p}: expected a mapping with width, height, fx, fy, cx, cy, baseline")
    try:
        m = _StereoYaml.model_validate(data)
    except ValidationError as exc:
        lines = []
        for err in exc.errors():
            loc = ".".join(str(x) for x in err["loc"])
            msg = "unknown key" if err["type"] == "extra_forbidden" else err["msg"]
            lines.append(f"{p}: {loc}: {msg}")
        raise CalibrationError("\n".join(lines)) from None
    check_intrinsics(str(p), m.fx, m.fy, m.cx, m.cy, m.width, m.height)
    mount = m.mount
    K = np.array([[m.fx, 0.0, m.cx], [0.0, m.fy, m.cy], [0.0, 0.0, 1.0]])
    return StereoCalibration(K, m.baseline, (m.width, m.height),
                             mount.height if mount else None, mount.pitch_deg if mount else 0.0,
                             mount.roll_deg if mount else 0.0, m.disparity_scale, str(p))


_LABEL = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*:(.*)$")


def read_kitti_calib(path: str | Path, need_right: bool = True) -> StereoCalibration:
    """The left intrinsics and the baseline from a KITTI ``calib.txt`` (P0 and P1, labelled or bare).

    With ``need_right=False`` a file with P0 alone is a monocular calibration (baseline None).
    """
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise CalibrationError(f"{p}: cannot read: {exc}") from None
    mats: dict[str, tuple[int, np.ndarray]] = {}
    bare: list[tuple[int, np.ndarray]] = []
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        m = _LABEL.match(line)
        label, rest = (m.group(1), m.group(2)) if m else (None, line)
        try:
            vals = np.array([float(x) for x in rest.split()])
        except ValueError:
            raise CalibrationError(f"{p}: line {n}: expected numbers, got {rest.strip()[:40]!r}") from None
        if label is None:
            bare.append((n, vals))
        else:
            mats[label] = (n, vals)
    if "P0" not in mats:
        mats.update(zip(("P0", "P1"), bare))
    for key in ("P0", "P1"):
        if key not in mats:
            if key == "P1" and not need_right:
                continue
            raise CalibrationError(f"{p}: {key}: missing (expected lines 'P0: <12 numbers>' and 'P1: <12 numbers>')")
        n, vals = mats[key]
        if vals.size != 12:
            raise CalibrationError(f"{p}: {key} (line {n}): expected 12 numbers (3x4 matrix), got {vals.size}")
        if not np.isfinite(vals).all():
            raise CalibrationError(f"{p}: {key} (line {n}): expected finite numbers, got {vals[~np.isfinite(vals)][0]}")
    P0 = mats["P0"][1].reshape(3, 4)
    K = P0[:, :3]
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(f"{p}: P0: focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
    check_intrinsics(str(p), K[0, 0], K[1, 1], K[0, 2], K[1, 2], prefix="P0 ")
    if "P1" not in mats:
        return StereoCalibration(K, None, source=str(p))
    P1 = mats["P1"][1].reshape(3, 4)
    if not np.allclose(K, P1[:, :3], rtol=1e-6, atol=1e-6):
        raise CalibrationError(f"{p}: P1: left part differs from P0's; the pair is not rectified to one K")
    baseline = float(-(P1[0, 3] - P0[0, 3]) / P1[0, 0])
    if baseline <= 0:
        raise CalibrationError(f"{p}: P1: baseline -(P1[0,3] - P0[0,3]) / P1[0,0] = {baseline:.4f} m, expected > 0 "
                               f"(is P1 the right camera?)")
    return StereoCalibration(K, baseline, source=str(p))
