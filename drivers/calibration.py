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

``load_camera_calibration`` is the one entry of a configuration's ``camera.calibration_file``: it
also takes the stereo formats of stereo_calib.py (vbnav stereo YAML, KITTI calib.txt) and returns a
:class:`CameraCalibration` (camera, baseline, file, SHA-256). ``calibration_problems`` lists legal but
implausible values (for ``vbnav doctor``); ``opencv_yaml_text``/``ros_camera_info_text`` format what ``vbnav calibrate`` computes
(written with ``drivers.atomic_file.write_atomic``).
"""
from __future__ import annotations

import hashlib
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import yaml

from vbnav.drivers.errors import InputError, yaml_problem
from vbnav.drivers.plain_values import load_yaml
from vbnav.vision.camera_model import FisheyeCamera, PinholeCamera, check_distortion

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


def check_baseline(source: str, baseline, field: str = "baseline") -> float:
    """The stereo baseline as a float; CalibrationError unless it is a number (not text, not true/false) that is
    a finite distance > 0 m (right camera at +baseline along the left camera's x): a zero baseline gives no
    depth at all. The one check of a baseline: calibration files, dataset camera YAML, a frame's
    meta['baseline_m'] (control/stages/frame_input.frame_baseline)."""
    try:
        b = math.nan if isinstance(baseline, (str, bytes, bool, np.bool_)) else float(baseline)
    except (TypeError, ValueError):
        b = math.nan
    if not math.isfinite(b) or b <= 0:
        raise CalibrationError(f"{source}: {field}: expected a finite stereo baseline > 0 m (the right camera "
                               f"at +baseline along the left camera's x), got {baseline!r}")
    lo, hi = BASELINE_RANGE_M
    if not lo <= b <= hi:      # 5e9 m or 5e-12 m was taken: every depth wrong by as many orders of magnitude
        raise CalibrationError(f"{source}: {field}: {b:g} m is no stereo camera's baseline, expected between "
                               f"{lo:g} and {hi:g} m (a length in another unit than metres?)")
    return b


#: A stereo camera's baseline, m: from a phone's 1 cm pair down to 1 mm, up to a car's 0.54 m (KITTI) and a
#: truck's few metres, 10 m at most. Outside it the file holds another unit, not a rig.
BASELINE_RANGE_M = (1e-3, 10.0)


def load_calibration(path) -> PinholeCamera | FisheyeCamera:
    """Camera model from an OpenCV YAML/XML or ROS camera_info YAML calibration file."""
    p = Path(path)
    if not p.is_file():
        raise CalibrationError(f"{p}: calibration file does not exist")
    text = p.read_text(errors="replace")
    if p.suffix.lower() == ".xml" or text.lstrip().startswith(("%YAML", "<?xml", "<opencv_storage")):
        return _load_opencv(p)
    try:
        doc = load_yaml(text)
    except yaml.YAMLError as e:
        raise CalibrationError(f"{p}: {yaml_problem(e)}") from None
    if not isinstance(doc, dict):
        raise CalibrationError(f"{p}: expected a mapping with camera_matrix and distortion_coefficients")
    km = doc.get("camera_matrix")
    if isinstance(km, dict) and "data" in km:
        return _from_ros(p, doc)
    return _from_plain_yaml(p, doc)


def _plain_numbers(path: Path, field: str, value) -> None:
    """Refuse text and true/false where numbers belong: numpy would read "400" and true as numbers."""
    if isinstance(value, (list, tuple)):
        for v in value:
            _plain_numbers(path, field, v)
    elif isinstance(value, (bool, str)):
        raise CalibrationError(f"{path}: {field}: expected numbers, got {value!r}")


def _build(path: Path, model: str, K: np.ndarray, dist: np.ndarray, width, height):
    for field, value in (("camera_matrix", K), ("distortion_coefficients", dist)):
        _plain_numbers(path, field, value)
    for value in (width, height):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise CalibrationError(f"{path}: image_width/image_height: expected whole numbers of pixels, got "
                                   f"{width!r}, {height!r}")
    K = np.asarray(K, dtype=float)
    if K.size != 9:
        raise CalibrationError(f"{path}: camera_matrix: expected 3x3 (9 numbers), got {K.size}")
    K = K.reshape(3, 3)
    if not (K[0, 0] > 0 and K[1, 1] > 0 and np.isfinite(K).all()):
        raise CalibrationError(f"{path}: camera_matrix: focal lengths must be positive finite numbers")
    if abs(K[0, 1]) > 1e-6 * K[0, 0] or K[1, 0] != 0 or not np.allclose(K[2], (0.0, 0.0, 1.0), rtol=0, atol=1e-9):
        raise CalibrationError(f"{path}: camera_matrix: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew: "
                               f"the camera models have fx, fy, cx, cy only), got {K.tolist()}")
    try:
        w, h = int(width), int(height)
    except (TypeError, ValueError):
        raise CalibrationError(f"{path}: image_width/image_height: expected integers, got {width!r}, {height!r}") \
            from None
    if w <= 0 or h <= 0:
        raise CalibrationError(f"{path}: image_width/image_height: must be positive, got {w}x{h}")
    check_intrinsics(str(path), K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h, prefix="camera_matrix ")
    model = (model or "").strip().lower()
    if model not in _PINHOLE_MODELS + _FISHEYE_MODELS:
        raise CalibrationError(f"{path}: distortion_model: {model!r} is not supported "
                               f"(expected one of {_PINHOLE_MODELS[:2] + _FISHEYE_MODELS[:1]})")
    fisheye = model in _FISHEYE_MODELS
    try:
        d = check_distortion("fisheye" if fisheye else "pinhole", dist)
    except ValueError as exc:
        order = "k1 k2 k3 k4" if fisheye else "k1 k2 p1 p2 [k3 [k4 k5 k6 ...]]"
        raise CalibrationError(f"{path}: distortion_coefficients: {exc} ({model}, OpenCV order {order})") from None
    if fisheye:
        return FisheyeCamera(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2], d or (0.0, 0.0, 0.0, 0.0))
    return PinholeCamera(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2], d)


def _from_ros(path: Path, doc: dict):
    def data(field: str, required: bool = True):
        node = doc.get(field)
        if node is None and not required:
            return np.zeros(0)
        if not isinstance(node, dict) or "data" not in node:
            raise CalibrationError(f"{path}: {field}: expected a mapping with 'data' (ROS camera_info)")
        _plain_numbers(path, f"{field}.data", node["data"])
        try:
            values = np.asarray(node["data"], dtype=float)
        except (TypeError, ValueError):
            raise CalibrationError(f"{path}: {field}.data: expected a list of numbers") from None
        rows, cols = node.get("rows"), node.get("cols")
        if rows is not None or cols is not None:    # the shape the data claims: a number lost in an edit shows
            if not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in (rows, cols)):
                raise CalibrationError(f"{path}: {field}: rows and cols must be whole numbers, got {rows!r}, "
                                       f"{cols!r}")
            if rows * cols != values.size:
                raise CalibrationError(f"{path}: {field}: rows x cols is {rows}x{cols} = {rows * cols} numbers, "
                                       f"data has {values.size}")
        return values

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
        return _build(path, str(doc.get("distortion_model", "")), K, D if D is not None else [], w, h)
    except (TypeError, ValueError) as e:
        if isinstance(e, CalibrationError):
            raise
        raise CalibrationError(f"{path}: camera_matrix/distortion_coefficients: expected numbers ({e})") from None


def _first(doc: dict, names):
    for n in names:
        if n in doc:
            return doc[n]
    return None


def open_filestorage(path) -> "cv2.FileStorage":
    """An OpenCV YAML/XML file opened for reading; CalibrationError naming it when it cannot be parsed."""
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:    # a parse error surfaces as SystemError from the constructor
        why = str(exc.__cause__ or exc).strip().splitlines()[-1]
        raise CalibrationError(f"{path}: not a readable OpenCV YAML/XML file ({why})") from None
    if not fs.isOpened():
        raise CalibrationError(f"{path}: not a readable OpenCV YAML/XML file")
    return fs


def _load_opencv(path: Path):
    fs = open_filestorage(path)
    try:
        K = _fs_mat(path, fs, _K_NAMES)
        if K is None:
            raise CalibrationError(f"{path}: camera_matrix: missing (looked for {', '.join(_K_NAMES)})")
        D = _fs_mat(path, fs, _D_NAMES)
        w, h = _fs_int(path, fs, _W_NAMES), _fs_int(path, fs, _H_NAMES)
        if w is None or h is None:
            raise CalibrationError(f"{path}: image_width/image_height: missing")
        model_node = fs.getNode("distortion_model")
        model = model_node.string() if not model_node.empty() else ""
        return _build(path, model, K, D if D is not None else np.zeros(0), w, h)
    finally:
        fs.release()


def _fs_mat(path: Path, fs, names):
    """The first of ``names`` present, as a matrix (an ``!!opencv-matrix`` or a list of numbers); None when none
    is. Anything else there is a CalibrationError naming the field: OpenCV's own assertion (data that does not
    fill rows x cols, text or a mapping where the matrix belongs) would otherwise escape as a cv2.error."""
    for n in names:
        node = fs.getNode(n)
        if node.empty():
            continue
        try:
            m = node.mat()
        except cv2.error:
            m = None
        if m is None and node.isSeq() and all(node.at(i).isReal() or node.at(i).isInt() for i in range(node.size())):
            m = np.array([node.at(i).real() for i in range(node.size())])
        if m is None:
            raise CalibrationError(f"{path}: {n}: expected a matrix (!!opencv-matrix with rows x cols numbers in "
                                   f"data, or a list of numbers)")
        return m
    return None


def _fs_int(path: Path, fs, names):
    """The first of ``names`` present as a whole number; None when none is (``FileNode.real()`` reads text as
    1.8e308 and would cut 640.7 to 640)."""
    for n in names:
        node = fs.getNode(n)
        if node.empty():
            continue
        if not node.isInt():
            raise CalibrationError(f"{path}: {n}: expected a whole number of pixels, got "
                                   f"{node.string() if node.isString() else node.real() if node.isReal() else 'no number'}")
        return int(node.real())
    return None


# -- the calibration a configuration uses ---------------------------------------------------------

@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """What ``camera.calibration_file`` gives: the camera model, the stereo baseline (m, None for a
    single camera), the file and its SHA-256 (recorded in a taught route's manifest), its format."""

    camera: PinholeCamera | FisheyeCamera
    baseline: Optional[float]
    file: str
    sha256: str
    format: str          # opencv, ros, yaml, kitti, vbnav-stereo
    # a vbnav stereo YAML's mount block: height m, pitch_deg, roll_deg (None: the file has none)
    mount: Optional[tuple[float, float, float]] = None
    disparity_scale: Optional[float] = None   # a vbnav stereo YAML's: px per unit of a stored disparity image


def file_sha256(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def load_camera_calibration(path, width: Optional[int] = None, height: Optional[int] = None) -> CameraCalibration:
    """Any calibration file vbnav reads, by its content: OpenCV YAML/XML, ROS camera_info, the vbnav
    stereo YAML (a ``baseline`` key) or a KITTI ``calib.txt`` (``P0:`` lines; it has no image size, so
    ``width``/``height`` give it). Errors name the file."""
    from vbnav.drivers.stereo_calib import load_stereo_calibration, read_kitti_calib
    p = Path(path)
    if not p.is_file():
        raise CalibrationError(f"{p}: calibration file does not exist" + (" (it is a directory)" if p.is_dir() else ""))
    text = p.read_text(errors="replace")
    head = text.lstrip()
    if p.suffix.lower() == ".txt" or re.match(r"(#.*\n\s*)*P0\s*:", head):
        st = read_kitti_calib(p, need_right=False)
        if width is None or height is None:
            raise CalibrationError(f"{p}: a KITTI calib.txt has no image size; set camera.width/height")
        return CameraCalibration(st.camera(width, height), st.baseline, str(p), file_sha256(p), "kitti")
    if not head.startswith(("%YAML", "<?xml", "<opencv_storage")) and p.suffix.lower() != ".xml":
        try:
            doc = load_yaml(text)
        except yaml.YAMLError as e:
            raise CalibrationError(f"{p}: {yaml_problem(e)}") from None
        if isinstance(doc, dict) and "baseline" in doc:
            st = load_stereo_calibration(p)
            mount = None if st.mount_height is None else (st.mount_height, st.mount_pitch_deg, st.mount_roll_deg)
            return CameraCalibration(st.camera(), st.baseline, str(p), file_sha256(p), "vbnav-stereo", mount,
                                     st.disparity_scale)
        fmt = "ros" if isinstance(doc, dict) and isinstance(doc.get("camera_matrix"), dict) else "yaml"
    else:
        fmt = "opencv"
    return CameraCalibration(load_calibration(p), None, str(p), file_sha256(p), fmt)


# Plausible lens: a horizontal field of view between these (deg). Narrower is a telephoto lens or fx in
# the wrong unit (mm, or for a larger image); wider than 170 deg is a fisheye that needs the fisheye model.
PLAUSIBLE_HFOV_DEG = (15.0, 170.0)
# fx/fy outside this band: pixels far from square, usually a calibration for another resolution in one axis.
PLAUSIBLE_ASPECT = (0.8, 1.25)
# principal point farther from the image centre than this share of the size: a calibration for a crop.
PLAUSIBLE_CENTRE_OFFSET = 0.2


def calibration_problems(cal: CameraCalibration) -> list[str]:
    """Sanity checks of a loaded calibration (for 'vbnav doctor'): one line per implausible value, empty if
    all is plausible. A loaded file is already valid; this catches values that are legal but unlikely."""
    c, out = cal.camera, []
    if isinstance(c, PinholeCamera):
        hfov = 2 * math.degrees(math.atan2(c.width / 2, c.fx))
        if not PLAUSIBLE_HFOV_DEG[0] <= hfov <= PLAUSIBLE_HFOV_DEG[1]:
            out.append(f"{cal.file}: fx {c.fx:.1f} px gives a {hfov:.0f} deg horizontal field of view on "
                       f"{c.width} px (plausible {PLAUSIBLE_HFOV_DEG[0]:g}-{PLAUSIBLE_HFOV_DEG[1]:g})")
    if not PLAUSIBLE_ASPECT[0] <= c.fx / c.fy <= PLAUSIBLE_ASPECT[1]:
        out.append(f"{cal.file}: fx/fy = {c.fx / c.fy:.2f}, expected near 1 (square pixels)")
    for name, v, size in (("cx", c.cx, c.width), ("cy", c.cy, c.height)):
        if abs(v - (size - 1) / 2) > PLAUSIBLE_CENTRE_OFFSET * size:
            out.append(f"{cal.file}: {name} {v:.1f} px is more than {PLAUSIBLE_CENTRE_OFFSET:.0%} of the image "
                       f"from its centre {(size - 1) / 2:.1f}")
    return out


# -- writing calibration files ----------------------------------------------------------------------

def opencv_yaml_text(K, dist, size: tuple[int, int], model: str = "plumb_bob", extra: Optional[dict] = None) -> str:
    """An OpenCV FileStorage YAML (``%YAML:1.0``) with camera_matrix, distortion_coefficients, the image
    size and ``extra`` (numbers or matrices: the reprojection errors), as cv2.FileStorage writes it."""
    fs = cv2.FileStorage(".yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fs.write("image_width", int(size[0]))
    fs.write("image_height", int(size[1]))
    fs.write("distortion_model", model)
    fs.write("camera_matrix", np.asarray(K, float).reshape(3, 3))
    fs.write("distortion_coefficients", np.asarray(dist, float).reshape(1, -1))
    for k, v in (extra or {}).items():
        fs.write(k, np.asarray(v, float) if isinstance(v, (list, tuple, np.ndarray)) else v)
    return fs.releaseAndGetString()


def ros_camera_info_text(K, dist, size: tuple[int, int], name: str = "camera", model: str = "plumb_bob",
                         comments: tuple[str, ...] = ()) -> str:
    """A ROS camera_info YAML (camera_calibration's format); ``comments`` go on top as ``#`` lines (ROS
    readers do not know extra keys, so the reprojection errors are comments there)."""
    K = np.asarray(K, float).reshape(3, 3)
    P = np.hstack([K, np.zeros((3, 1))])
    doc = {"image_width": int(size[0]), "image_height": int(size[1]), "camera_name": name,
           "camera_matrix": {"rows": 3, "cols": 3, "data": [float(x) for x in K.ravel()]},
           "distortion_model": model,
           "distortion_coefficients": {"rows": 1, "cols": int(np.size(dist)),
                                       "data": [float(x) for x in np.ravel(dist)]},
           "rectification_matrix": {"rows": 3, "cols": 3, "data": [float(x) for x in np.eye(3).ravel()]},
           "projection_matrix": {"rows": 3, "cols": 4, "data": [float(x) for x in P.ravel()]}}
    head = "".join(f"# {c}\n" for c in comments)
    return head + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)
