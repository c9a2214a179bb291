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

vbnav stereo YAML (``*.yaml`` / ``*.yml``; ``*.json`` with the same fields), documented in docs/obstacles.md::

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

OpenCV stereo rectification (``%YAML`` FileStorage, ``.yaml``/``.yml``/``.xml``), the result of
``cv2.stereoRectify`` for a pair of RAW (distorted, unrectified) cameras, e.g.
``indoor_stereo/euroc_v101/stereo_rectify.yaml``: ``image_width``, ``image_height``, per camera
``K0``/``D0`` (left) and ``K1``/``D1`` (right: 3x3 intrinsics, plumb_bob/radtan distortion), the
rectifying rotations ``R1`` (left) and ``R2`` (right) and the rectified projections ``P1``/``P2``
(OpenCV's names: 1 = left, 2 = right). The rectified left camera is K = P1[:, :3] and the baseline
B = -P2[0, 3] / P2[0, 0]. Only a caller that rectifies the images it reads accepts this form
(``raw_images=True``: ``StereoCalibration.rectify`` remaps a raw pair); the others reject it by name.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import yaml
from pydantic import ConfigDict, Field, ValidationError
from vbnav.drivers.plain_values import PlainValues, load_yaml

from vbnav.drivers.calibration import (CalibrationError, _fs_int, _fs_mat, check_baseline, check_intrinsics,
                                      open_filestorage)
from vbnav.drivers.errors import yaml_problem
from vbnav.vision.camera_model import PinholeCamera, check_distortion
from vbnav.vision.stereo import StereoRig


class _Mount(PlainValues):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    height: float = Field(gt=0, description="m")
    pitch_deg: float = Field(0.0, ge=-90, le=90)
    roll_deg: float = Field(0.0, ge=-45, le=45)


class _StereoYaml(PlainValues):
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
class Rectification:
    """How a raw (distorted, unrectified) pair becomes the rectified one: per camera (left, right) its
    intrinsics ``K``, distortion ``D``, rectifying rotation ``R`` and rectified projection ``P``, as
    cv2.stereoRectify gives them, for raw images of ``size`` (width, height)."""

    K: tuple
    D: tuple
    R: tuple
    P: tuple
    size: tuple[int, int]
    _maps: list = field(default_factory=list, repr=False)

    def apply(self, left: np.ndarray, right: np.ndarray, source: str) -> tuple[np.ndarray, np.ndarray]:
        """The rectified pair (bilinear remap; the maps are made once)."""
        for name, img in (("left", left), ("right", right)):
            if (img.shape[1], img.shape[0]) != tuple(self.size):
                raise CalibrationError(f"{source}: image_width/image_height: the rectification is for "
                                       f"{self.size[0]}x{self.size[1]} raw images, the {name} image is "
                                       f"{img.shape[1]}x{img.shape[0]}")
        if not self._maps:
            self._maps.extend(cv2.initUndistortRectifyMap(self.K[i], self.D[i], self.R[i], self.P[i],
                                                          tuple(self.size), cv2.CV_32FC1) for i in range(2))
        return tuple(cv2.remap(img, *self._maps[i], cv2.INTER_LINEAR) for i, img in enumerate((left, right)))


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
    rectification: Optional[Rectification] = None  # set when the file describes the raw cameras

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

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The rectified pair: raw images remapped if the file describes raw cameras, else as given."""
        if self.rectification is None:
            return left, right
        return self.rectification.apply(left, right, self.source)


def load_stereo_calibration(path: str | Path, raw_images: bool = False) -> StereoCalibration:
    """KITTI calib.txt, vbnav stereo YAML or (``raw_images``: the caller rectifies with
    ``StereoCalibration.rectify``) an OpenCV stereo rectification, chosen by suffix and first line."""
    p = Path(path)
    if p.is_dir():
        raise CalibrationError(f"{p}: is a directory, expected a calibration file")
    if not p.is_file():
        raise CalibrationError(f"{p}: calibration file not found")
    if p.suffix.lower() in (".yaml", ".yml", ".xml"):
        if p.read_text(errors="replace").lstrip().startswith(("%YAML", "<?xml", "<opencv_storage")):
            if not raw_images:
                raise CalibrationError(f"{p}: an OpenCV stereo rectification (K0, D0, R1, P1, ...) describes raw "
                                       f"cameras; this command takes rectified images and their calibration "
                                       f"(vbnav stereo YAML or KITTI calib.txt)")
            return read_opencv_rectification(p)
        return _load_yaml(p)
    if p.suffix.lower() == ".json":     # JSON is YAML: the same fields, checked the same way
        return _load_yaml(p)
    return read_kitti_calib(p)


_RECT_SHAPES = {"K0": (3, 3), "K1": (3, 3), "R1": (3, 3), "R2": (3, 3), "P1": (3, 4), "P2": (3, 4)}


def read_opencv_rectification(path: str | Path) -> StereoCalibration:
    """The rectified pair and the maps to it from an OpenCV FileStorage file with cv2.stereoRectify's result
    (module docstring). Errors name the file and the field."""
    p = Path(path)
    fs = open_filestorage(p)
    try:
        m = {k: _fs_mat(p, fs, (k,)) for k in ("K0", "D0", "K1", "D1", "R1", "R2", "P1", "P2")}
        w, h = _fs_int(p, fs, ("image_width",)), _fs_int(p, fs, ("image_height",))
    finally:
        fs.release()
    for k, v in m.items():
        want = _RECT_SHAPES.get(k)
        if v is None:
            raise CalibrationError(f"{p}: {k}: missing (an OpenCV stereo rectification needs K0, D0, K1, D1, "
                                   f"R1, R2, P1, P2, image_width, image_height)")
        v = np.asarray(v, float)
        if want is None:            # D0, D1: a pinhole's distortion coefficients
            try:
                m[k] = np.asarray(check_distortion("pinhole", v), float)
            except ValueError as exc:
                raise CalibrationError(f"{p}: {k}: {exc}") from None
            continue
        if v.shape != want:
            raise CalibrationError(f"{p}: {k}: expected a {want[0]}x{want[1]} matrix, got shape {v.shape}")
        if not np.isfinite(v).all():
            raise CalibrationError(f"{p}: {k}: expected finite numbers")
        m[k] = v
    if w is None or h is None or w <= 0 or h <= 0:
        raise CalibrationError(f"{p}: image_width/image_height: expected the raw image size in pixels > 0")
    for k in ("R1", "R2"):
        if not np.allclose(m[k] @ m[k].T, np.eye(3), atol=1e-6):
            raise CalibrationError(f"{p}: {k}: expected a rotation matrix (orthonormal)")
    P1, P2 = m["P1"], m["P2"]
    if not np.allclose(P1[:, :3], P2[:, :3], rtol=1e-6, atol=1e-6) or np.any(P1[:, 3] != 0):
        raise CalibrationError(f"{p}: P1/P2: expected one rectified K for both cameras and P1 = K [I | 0]")
    if P2[1, 3] != 0 or P2[2, 3] != 0:
        raise CalibrationError(f"{p}: P2: expected a horizontal pair (P2[1,3] = P2[2,3] = 0), got a vertical "
                               f"or skewed rectification")
    baseline = float(-P2[0, 3] / P2[0, 0])
    check_baseline(str(p), baseline, "P2 (baseline -P2[0,3]/P2[0,0])")
    K = P1[:, :3].copy()
    check_intrinsics(str(p), K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h, prefix="P1 ")
    for k in ("K0", "K1"):
        check_intrinsics(str(p), m[k][0, 0], m[k][1, 1], m[k][0, 2], m[k][1, 2], w, h, prefix=f"{k} ")
    rect = Rectification((m["K0"], m["K1"]), (m["D0"], m["D1"]), (m["R1"], m["R2"]), (P1, P2), (w, h))
    return StereoCalibration(K, baseline, (w, h), source=str(p), rectification=rect)


def _load_yaml(p: Path) -> StereoCalibration:
    try:
        data = load_yaml(p.read_text())
    except yaml.YAMLError as exc:
        raise CalibrationError(f"{p}: {yaml_problem(exc)}") from None
    if not isinstance(data, dict):
        raise CalibrationError(f"{p}: expected a mapping with width, height, fx, fy, cx, cy, baseline")
    if "baseline" not in data and any(k in data for k in ("camera_matrix", "K", "cameraMatrix")):
        raise CalibrationError(f"{p}: a single-camera calibration (camera_matrix, no baseline); expected a stereo "
                               f"calibration: vbnav stereo YAML (width, height, fx, fy, cx, cy, baseline) or KITTI "
                               f"calib.txt")
    try:
        m = _StereoYaml.model_validate(data)
    except ValidationError as exc:      # one line (vbnav's errors are), naming the file once
        parts = []
        for err in exc.errors():
            loc = ".".join(str(x) for x in err["loc"])
            msg = "unknown key" if err["type"] == "extra_forbidden" else err["msg"].removeprefix("Value error, ")
            parts.append(f"{loc}: {msg}")
        raise CalibrationError(f"{p}: " + "; ".join(parts)) from None
    check_intrinsics(str(p), m.fx, m.fy, m.cx, m.cy, m.width, m.height)
    check_baseline(str(p), m.baseline)
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
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise CalibrationError(f"{p}: cannot read: {exc}") from None
    except UnicodeDecodeError as exc:
        raise CalibrationError(f"{p}: not UTF-8 text (byte {exc.start}: {exc.reason}), expected P0 and P1 lines "
                               f"as plain text (saved as UTF-16?)") from None
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
            if re.match(r"\s*cam0\s*=\s*\[", line):       # Middlebury's calib.txt (cam0=[f 0 cx; ...], doffs=)
                raise CalibrationError(f"{p}: a Middlebury calib.txt (cam0=[...], doffs, baseline in mm), which vbnav "
                                       f"does not read; expected a KITTI calib.txt (P0 and P1 rows), a vbnav "
                                       f"stereo YAML or an OpenCV stereo rectification") from None
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
    check_baseline(str(p), baseline, "P1 (baseline -(P1[0,3] - P0[0,3]) / P1[0,0])")
    return StereoCalibration(K, baseline, source=str(p))
