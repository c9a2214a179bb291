"""Camera calibration files -> PinholeCamera / FisheyeCamera.

Reads
- OpenCV FileStorage YAML/XML (``%YAML:1.0`` files written by calibrateCamera samples):
  ``camera_matrix`` (or ``K``) and ``distortion_coefficients`` (or ``D``, ``dist_coeffs``)
  as matrices, ``image_width``/``image_height`` (or ``width``/``height``), and optionally
  ``distortion_model`` (``fisheye``/``equidistant`` picks the fisheye model);
- ROS ``camera_info`` YAML (camera_calibration's output): ``image_width``,
  ``image_height``, ``camera_matrix.data`` (9 numbers), ``distortion_model``
  (plumb_bob, rational_polynomial -> pinhole; equidistant -> fisheye) and
  ``distortion_coefficients.data``.
Errors name the file and the field and say what was expected.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml

from vbnav.drivers.errors import InputError, yaml_problem
from vbnav.vision.camera_model import FisheyeCamera, PinholeCamera

_K_NAMES = ("camera_matrix", "K", "cameraMatrix")
_D_NAMES = ("distortion_coefficients", "D", "dist_coeffs", "distCoeffs")
_W_NAMES = ("image_width", "width")
_H_NAMES = ("image_height", "height")
_PINHOLE_MODELS = ("plumb_bob", "rational_polynomial", "pinhole", "radtan", "")
_FISHEYE_MODELS = ("equidistant", "fisheye", "kannala_brandt")


class CalibrationError(InputError):
    """A calibration file is missing, unreadable or lacks a field. The message names file and field."""


def check_intrinsics(source: str, fx: float, fy: float, cx: float, cy: float, width=None, height=None,
                     prefix: str = "") -> None:
    """Raise CalibrationError unless the intrinsics can be those of a camera: finite numbers, positive
    focal lengths, and (when the image size is known) the principal point inside the image.

    A NaN or zero focal length does not fail anywhere else: every frame is simply lost. ``prefix`` is
    the field's parent as the file names it (``"P0 "`` for a KITTI calib.txt).
    """
    for name, v in (("fx", fx), ("fy", fy), ("cx", cx), ("cy", cy)):
        if not np.isfinite(v):
            raise CalibrationError(f"{source}: {prefix}{name}: expected a finite number, got {v}")
    for name, v in (("fx", fx), ("fy", fy)):
        if v <= 0:
            raise CalibrationError(f"{source}: {prefix}{name}: the focal length must be > 0 px, got {v}")
    for name, v, size, side in (("cx", cx, width, "width"), ("cy", cy, height, "height")):
        if size is not None and not 0 <= v <= size:
            raise CalibrationError(f"{source}: {prefix}{name}: the principal point {v} is outside the image "
                                   f"(0..{size}, the image {side})")


def check_baseline(source: str, baseline, field: str = "baseline") -> None:
    """Raise CalibrationError unless the stereo baseline is a finite distance > 0 m (right camera at
    +baseline along the left camera's x): a zero baseline gives no depth at all."""
    if not np.isfinite(baseline) or baseline <= 0:
        raise CalibrationError(f"{source}: {field}: expected a finite stereo baseline > 0 m (the right camera "
                               f"at +baseline along the left camera's x), got {baseline}")


def load_calibration(path) -> PinholeCamera | FisheyeCamera:
    """Camera model from an OpenCV YAML/XML or ROS camera_info YAML calibration file."""
    p = Path(path)
    if not p.is_file():
        raise CalibrationError(f"{p}: calibration file does not exist")
    text = p.read_text(errors="replace")
    if p.suffix.lower() == ".xml" or text.lstrip().startswith(("%YAML", "<?xml", "<opencv_storage")):
        return _load_opencv(p)
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise CalibrationError(f"{p}: {yaml_problem(e)}") from None
    if not isinstance(doc, dict):
        raise CalibrationError(f"{p}: expected a mapping with camera_matrix and distortion_coefficients")
    km = doc.get("camera_matrix")
    if isinstance(km, dict) and "data" in km:
        return _from_ros(p, doc)
    return _from_plain_yaml(p, doc)


def _build(path: Path, model: str, K: np.ndarray, dist: np.ndarray, width, height):
    K = np.asarray(K, dtype=float)
    if K.size != 9:
        raise CalibrationError(f"{path}: camera_matrix: expected 3x3 (9 numbers), got {K.size}")
    K = K.reshape(3, 3)
    if not (K[0, 0] > 0 and K[1, 1] > 0 and np.isfinite(K).all()):
        raise CalibrationError(f"{path}: camera_matrix: focal lengths must be positive finite numbers")
    try:
        w, h = int(width), int(height)
    except (TypeError, ValueError):
        raise CalibrationError(f"{path}: image_width/image_height: expected integers, got {width!r}, {height!r}") \
            from None
    if w <= 0 or h <= 0:
        raise CalibrationError(f"{path}: image_width/image_height: must be positive, got {w}x{h}")
    check_intrinsics(str(path), K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h, prefix="camera_matrix ")
    d = tuple(float(x) for x in np.asarray(dist, dtype=float).ravel())
    model = (model or "").strip().lower()
    if model in _FISHEYE_MODELS:
        if len(d) not in (0, 4):
            raise CalibrationError(f"{path}: distortion_coefficients: fisheye ({model}) expects 4 numbers "
                                   f"k1..k4, got {len(d)}")
        return FisheyeCamera(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2], d or (0.0, 0.0, 0.0, 0.0))
    if model not in _PINHOLE_MODELS:
        raise CalibrationError(f"{path}: distortion_model: {model!r} is not supported "
                               f"(expected one of {_PINHOLE_MODELS[:2] + _FISHEYE_MODELS[:1]})")
    if len(d) not in (0, 4, 5, 8, 12, 14):
        raise CalibrationError(f"{path}: distortion_coefficients: expected 4, 5, 8, 12 or 14 numbers "
                               f"(OpenCV order k1 k2 p1 p2 [k3 [k4 k5 k6 ...]]), got {len(d)}")
    return PinholeCamera(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2], d)


def _from_ros(path: Path, doc: dict):
    def data(field: str, required: bool = True):
        node = doc.get(field)
        if node is None and not required:
            return np.zeros(0)
        if not isinstance(node, dict) or "data" not in node:
            raise CalibrationError(f"{path}: {field}: expected a mapping with 'data' (ROS camera_info)")
        try:
            return np.asarray(node["data"], dtype=float)
        except (TypeError, ValueError):
            raise CalibrationError(f"{path}: {field}.data: expected a list of numbers") from None

    for key in ("image_width", "image_height"):
        if key not in doc:
            raise CalibrationError(f"{path}: {key}: missing (ROS camera_info needs it)")
    return _build(path, str(doc.get("distortion_model", "plumb_bob")), data("camera_matrix"),
                  data("distortion_coefficients", required=False), doc["image_width"], doc["image_height"])


def _from_plain_yaml(path: Path, doc: dict):
    """YAML without the OpenCV header but with the OpenCV key names (K as 9 numbers or nested lists)."""
    K = _first(doc, _K_NAMES)
    if K is None:
        raise CalibrationError(f"{path}: camera_matrix: missing (looked for {', '.join(_K_NAMES)})")
    if isinstance(K, dict) and "data" in K:
        K = K["data"]
    D = _first(doc, _D_NAMES)
    if isinstance(D, dict) and "data" in D:
        D = D["data"]
    w, h = _first(doc, _W_NAMES), _first(doc, _H_NAMES)
    if w is None or h is None:
        raise CalibrationError(f"{path}: image_width/image_height: missing")
    try:
        return _build(path, str(doc.get("distortion_model", "")), np.asarray(K, float),
                      np.asarray(D if D is not None else [], float), w, h)
    except (TypeError, ValueError) as e:
        if isinstance(e, CalibrationError):
            raise
        raise CalibrationError(f"{path}: camera_matrix/distortion_coefficients: expected numbers ({e})") from None


def _first(doc: dict, names):
    for n in names:
        if n in doc:
            return doc[n]
    return None


def _load_opencv(path: Path):
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as e:
        raise CalibrationError(f"{path}: not a readable OpenCV YAML/XML file ({str(e).strip()})") from None
    if not fs.isOpened():
        raise CalibrationError(f"{path}: not a readable OpenCV YAML/XML file")
    try:
        K = _fs_mat(fs, _K_NAMES)
        if K is None:
            raise CalibrationError(f"{path}: camera_matrix: missing (looked for {', '.join(_K_NAMES)})")
        D = _fs_mat(fs, _D_NAMES)
        w, h = _fs_int(fs, _W_NAMES), _fs_int(fs, _H_NAMES)
        if w is None or h is None:
            raise CalibrationError(f"{path}: image_width/image_height: missing")
        model_node = fs.getNode("distortion_model")
        model = model_node.string() if not model_node.empty() else ""
        return _build(path, model, K, D if D is not None else np.zeros(0), w, h)
    finally:
        fs.release()


def _fs_mat(fs, names):
    for n in names:
        node = fs.getNode(n)
        if node.empty():
            continue
        m = node.mat()
        if m is None and node.isSeq():
            m = np.array([node.at(i).real() for i in range(node.size())])
        if m is not None:
            return m
    return None


def _fs_int(fs, names):
    for n in names:
        node = fs.getNode(n)
        if not node.empty():
            return int(node.real())
    return None
