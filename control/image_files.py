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


def write_png(path: str, img: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise ValueError(f"{path}: could not encode PNG")
    write_atomic(path, buf.tobytes())


def write_json(path: str, data, indent: int = 1) -> None:
    """``data`` as strict JSON: a NaN or infinity (a value not measured) is written as null (JSON has no
    word for them: Python's NaN made files that jq and most readers refuse whole)."""
    write_atomic(path, json.dumps(_finite_or_null(data), indent=indent, allow_nan=False))


def _finite_or_null(x):
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite_or_null(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite_or_null(v) for v in x]
    return x
