"""Reading images and writing result files atomically (temporary file in the same folder, then rename),
for the commands that read image pairs and write PNG / JSON results (``vbnav lines``, ``vbnav map``)."""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np

from vbnav.drivers.atomic_file import write_atomic
from vbnav.drivers.datasets import JPEG_CUT_SHORT, jpeg_cut_short


def read_image(path: str, what: str) -> np.ndarray:
    """The image at ``path`` as OpenCV reads it; FileNotFoundError / ValueError name ``what`` and the path."""
    if Path(path).is_dir():
        raise ValueError(f"{what} {path}: is a directory, expected an image file")
    if not Path(path).is_file():
        raise FileNotFoundError(f"{what} {path}: file not found")
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise ValueError(f"{what} {path}: cannot read: {exc.strerror or exc}") from None
    if jpeg_cut_short(data):
        raise ValueError(f"{what} {path}: {JPEG_CUT_SHORT}")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    if img is None:
        raise ValueError(f"{what} {path}: not an image OpenCV can read")
    return img


def pair_problem(left: np.ndarray, right: np.ndarray, left_path, right_path) -> str:
    """"" when the two images of a stereo pair can be matched, else why not: another size, or another bit depth
    (an 8-bit image put on a 16-bit one's range comes out black, and matches nothing, silently)."""
    if left.shape[:2] != right.shape[:2]:
        return (f"left {left_path} is {left.shape[1]}x{left.shape[0]} but right {right_path} is "
                f"{right.shape[1]}x{right.shape[0]}")
    if left.dtype != right.dtype:
        return (f"left {left_path} is {left.dtype} but right {right_path} is {right.dtype}: expected one bit depth "
                f"for both images of a pair")
    return ""


def same_pair_problem(left_path, right_path, left=None, right=None) -> str:
    """"" unless --left and --right are one file or, given the images, hold one image: a stereo pair is two
    cameras' images (one image twice has no disparity: ``vbnav lines`` reconstructed segments kilometres away,
    ``vbnav obstacles`` failed late with "ground plane fit failed")."""
    if Path(left_path).resolve() == Path(right_path).resolve():
        return f"--left and --right are the same file, {left_path}: a stereo pair is two cameras' images"
    if left is not None and left.shape == right.shape and np.array_equal(left, right):
        return f"left {left_path} and right {right_path} are the same image: a stereo pair is two cameras' images"
    return ""


def png_name_problem(path, option: str) -> str:
    """"" when ``path`` (or None) names a PNG file, else why not: the result images are PNG, and PNG bytes
    under a .jpg name are a file other programs refuse or misread."""
    if path is None or Path(path).suffix.lower() == ".png":
        return ""
    return f"{option} {path}: expected a file name ending in .png (the image is written as PNG)"


def png_bytes(path, img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise ValueError(f"{path}: could not encode PNG")
    return buf.tobytes()


def write_png(path: str, img: np.ndarray) -> None:
    write_atomic(path, png_bytes(path, img))


def json_text(data, indent: int = 1) -> str:
    """``data`` as strict JSON: a NaN or infinity (a value not measured) is written as null (JSON has no
    word for them: Python's NaN made files that jq and most readers refuse whole)."""
    return json.dumps(_finite_or_null(data), indent=indent, allow_nan=False)


def write_json(path: str, data, indent: int = 1) -> None:
    write_atomic(path, json_text(data, indent))


def display_bgr(img: np.ndarray) -> np.ndarray:
    """An image as 8-bit BGR for drawing on: grey to BGR, BGRA without its alpha (lines drawn with alpha 0
    were invisible), 16-bit or float stretched from its lowest to its highest finite value (drawn on the
    8-bit scale, 16-bit colours came out black)."""
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.dtype != np.uint8:
        x = img.astype(np.float64)
        finite = x[np.isfinite(x)]
        lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 0.0)
        x = np.nan_to_num(x, nan=lo, posinf=hi, neginf=lo)
        img = np.clip(np.rint((x - lo) * (255.0 / (hi - lo) if hi > lo else 0.0)), 0, 255).astype(np.uint8)
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return img.copy()


def _finite_or_null(x):
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite_or_null(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite_or_null(v) for v in x]
    return x
