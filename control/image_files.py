"""Reading images and writing result files atomically (temporary file in the same folder, then rename),
for the commands that read image pairs and write PNG / JSON results (``vbnav lines``, ``vbnav map``)."""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import cv2
import numpy as np


def read_image(path: str, what: str) -> np.ndarray:
    """The image at ``path`` as OpenCV reads it; FileNotFoundError / ValueError name ``what`` and the path."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"{what} {path}: file not found")
    img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{what} {path}: not an image OpenCV can read")
    return img


def _atomic_write(path: str, suffix: str, write) -> None:
    d = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=suffix, dir=d)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_png(path: str, img: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise ValueError(f"{path}: could not encode PNG")
    _atomic_write(path, ".png", lambda f: f.write(buf.tobytes()))


def write_json(path: str, data) -> None:
    _atomic_write(path, ".json", lambda f: f.write(json.dumps(data, indent=1).encode()))
