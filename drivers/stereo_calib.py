"""Calibration of a rectified stereo pair: KITTI ``calib.txt`` or a vbnav stereo YAML.

KITTI (odometry benchmark): lines ``P0: <12 numbers>`` and ``P1: <12 numbers>``, the
3x4 projection matrices of the rectified left and right grey cameras, row-major.
Files without the ``Pn:`` labels (two bare lines of 12 numbers, as in some
published subsets) are accepted too. fx = P0[0,0], fy = P0[1,1], cx = P0[0,2],
cy = P0[1,2]; the baseline is B = -P1[0,3] / P1[0,0] (P1 = K [I | -B e_x]).
The image size is not in the file; it comes from the images.

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

from vbnav.vision.stereo import StereoRig


class CalibrationError(ValueError):
    """A calibration file is missing or malformed. The message names the file and field."""


class _Mount(BaseModel):
    model_config = ConfigDict(extra="forbid")
    height: float = Field(gt=0, description="m")
    pitch_deg: float = Field(0.0, ge=-90, le=90)
    roll_deg: float = Field(0.0, ge=-45, le=45)


class _StereoYaml(BaseModel):
    model_config = ConfigDict(extra="forbid")
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    baseline: float = Field(gt=0, description="m")
    mount: Optional[_Mount] = None
    disparity_scale: Optional[float] = Field(None, gt=0)


@dataclass(frozen=True)
class StereoCalibration:
    fx: float
    fy: float
    cx: float
    cy: float
    baseline: float
    width: Optional[int] = None          # None: take it from the images (KITTI)
    height: Optional[int] = None
    mount_height: Optional[float] = None
    mount_pitch_deg: float = 0.0
    mount_roll_deg: float = 0.0
    disparity_scale: Optional[float] = None
    source: str = "<calibration>"

    def rig(self, width: Optional[int] = None, height: Optional[int] = None) -> StereoRig:
        """The StereoRig for images of the given size (checked against the file's size if it has one)."""
        w = width if width is not None else self.width
        h = height if height is not None else self.height
        if w is None or h is None:
            raise CalibrationError(f"{self.source}: the image size is not in the file; give the images")
        if self.width is not None and (w, h) != (self.width, self.height):
            raise CalibrationError(f"{self.source}: width/height: calibration is for {self.width}x{self.height} "
                                   f"images, got {w}x{h}")
        return StereoRig(w, h, self.fx, self.fy, self.cx, self.cy, self.baseline)


def load_stereo_calibration(path: str | Path) -> StereoCalibration:
    """KITTI calib.txt or vbnav stereo YAML, chosen by the file suffix."""
    p = Path(path)
    if not p.is_file():
        raise CalibrationError(f"{p}: calibration file not found")
    if p.suffix.lower() in (".yaml", ".yml"):
        return _load_yaml(p)
    return _load_kitti(p)


def _load_yaml(p: Path) -> StereoCalibration:
    try:
        data = yaml.safe_load(p.read_text())
    except yaml.YAMLError as exc:
        raise CalibrationError(f"{p}: not valid YAML: {exc}") from None
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
    mount = m.mount
    return StereoCalibration(m.fx, m.fy, m.cx, m.cy, m.baseline, m.width, m.height,
                             mount.height if mount else None, mount.pitch_deg if mount else 0.0,
                             mount.roll_deg if mount else 0.0, m.disparity_scale, str(p))


_LABEL = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*:(.*)$")


def _load_kitti(p: Path) -> StereoCalibration:
    mats: dict[str, np.ndarray] = {}
    bare: list[np.ndarray] = []
    for n, line in enumerate(p.read_text().splitlines(), 1):
        if not line.strip():
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
    if "P0" not in mats and len(bare) >= 2:
        mats["P0"], mats["P1"] = bare[0], bare[1]
    for key in ("P0", "P1"):
        if key not in mats:
            raise CalibrationError(f"{p}: {key}: missing (expected lines 'P0: <12 numbers>' and 'P1: <12 numbers>')")
        n, vals = mats[key]
        if vals.size != 12:
            raise CalibrationError(f"{p}: {key} (line {n}): expected 12 numbers (3x4 matrix), got {vals.size}")
    P0 = mats["P0"][1].reshape(3, 4)
    P1 = mats["P1"][1].reshape(3, 4)
    fx, fy, cx, cy = P0[0, 0], P0[1, 1], P0[0, 2], P0[1, 2]
    if fx <= 0 or fy <= 0:
        raise CalibrationError(f"{p}: P0: focal lengths must be positive, got fx={fx}, fy={fy}")
    if not np.allclose(P0[:, :3], P1[:, :3], rtol=1e-6, atol=1e-6):
        raise CalibrationError(f"{p}: P1: left part differs from P0's; the pair is not rectified to one K")
    baseline = -P1[0, 3] / P1[0, 0]
    if baseline <= 0:
        raise CalibrationError(f"{p}: P1: baseline -P1[0,3]/P1[0,0] = {baseline:.4f} m, expected > 0 "
                               f"(is P1 the right camera?)")
    return StereoCalibration(float(fx), float(fy), float(cx), float(cy), float(baseline), source=str(p))
