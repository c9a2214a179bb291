"""Reading images and writing result files atomically (temporary file in the same folder, then rename),
for the commands that read image pairs and write PNG / JSON results (``vbnav lines``, ``vbnav map``)."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from vbnav.drivers.atomic_file import write_atomic


def read_image(path: str, what: str) -> np.ndarray:
    """The image at ``path`` as OpenCV reads it; FileNotFoundError / ValueError name ``what`` and the path."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"{what} {path}: file not found")
    img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{what} {path}: not an image OpenCV can read")
    return img


def write_png(path: str, img: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise ValueError(f"{path}: could not encode PNG")
    write_atomic(path, buf.tobytes())


def write_json(path: str, data) -> None:
    write_atomic(path, json.dumps(data, indent=1))
