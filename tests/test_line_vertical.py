"""Vertical lines along the pencil through the vertical vanishing point (vision/line_vertical.py, issue 16)."""
from __future__ import annotations

import cv2
import numpy as np

from vbnav.vision.line_segments import LineParams, reconstruct_pair
from vbnav.vision.line_vertical import pencil_map

F, B = 400.0, 0.1
D_BOX, D_WALL, EDGE_X = 40, 10, 300         # disparities (px) and the box corner's column in the left image


def _texture(seed: int, shape, amp: float, blur: float) -> np.ndarray:
    n = np.random.default_rng(seed).normal(0.0, 1.0, shape).astype(np.float32)
    n = cv2.GaussianBlur(n, (0, 0), blur)
    return amp * n / n.std()


def _corner_pair(seed: int = 0):
    """A box face (x < EDGE_X, disparity D_BOX, grey 128 + texture) in front of a wall of 30-row bands
    alternately darker and brighter than the face (disparity D_WALL): the corner's contrast changes sign
    every 30 rows, as box_b's far corner against the room's wall."""
    H, W = 480, 640
    face = 128.0 + _texture(seed, (H, W + D_BOX), 12.0, 2.0)
    bands = np.where((np.arange(H) // 30) % 2 == 0, 70.0, 190.0)[:, None]
    wall = bands + _texture(seed + 1, (H, W + D_WALL), 12.0, 2.0)
    x = np.arange(W)[None, :]
    left = np.where(x < EDGE_X, face[:, :W], wall[:, :W])
    right = np.where(x < EDGE_X - D_BOX, face[:, D_BOX:D_BOX + W], wall[:, D_WALL:D_WALL + W])
    rng = np.random.default_rng(seed + 2)
    noisy = [np.clip(im + rng.normal(0, 2.0, im.shape), 0, 255).astype(np.uint8) for im in (left, right)]
    return noisy[0], noisy[1]


def _corner_rows(res) -> float:
    """Rows of the longest 3D segment on the corner (left x within 1 px, disparity within 0.5 px)."""
    s = res.segments
    on = ((np.abs(s.left_xy[:, [0, 2]] - EDGE_X).max(axis=1) <= 1.0)
          & (np.abs(s.extra["disparity"] - D_BOX).max(axis=1) <= 0.5))
    return float(np.abs(s.left_xy[on, 3] - s.left_xy[on, 1]).max()) if on.any() else 0.0


def test_a_corner_whose_contrast_changes_sign_is_one_vertical_line():
    left, right = _corner_pair()
    up = np.array([0.0, 1.0, 0.0])                     # a level camera: the pencil is the columns
    with_lines = reconstruct_pair(left, right, F, F, 319.5, 239.5, B, LineParams(), vertical=up)
    without = reconstruct_pair(left, right, F, F, 319.5, 239.5, B, LineParams(vertical_search=False), vertical=up)
    assert _corner_rows(without) < 100                # LSD and the edge search: pieces between sign changes
    assert _corner_rows(with_lines) >= 400, _corner_rows(with_lines)
    # Nothing is matched off the corner: the wall's bands are horizontal, the face's texture is blobs.
    s = with_lines.segments
    vert = np.abs(s.left_xy[:, 0] - s.left_xy[:, 2]) < 1e-9
    assert (np.abs(s.left_xy[vert, 0] - EDGE_X) <= 1.0).all()


def test_without_an_orientation_nothing_is_added():
    left, right = _corner_pair()
    a = reconstruct_pair(left, right, F, F, 319.5, 239.5, B, LineParams())
    b = reconstruct_pair(left, right, F, F, 319.5, 239.5, B, LineParams(vertical_search=False))
    assert np.array_equal(a.segments.P, b.segments.P)


def test_a_pitched_camera_resamples_the_pencil_to_columns():
    # Pitched down 10 deg: the world's vertical in the camera frame leans toward +z; its vanishing point is
    # below the image, and each pencil line maps to one column of the resampled image.
    p = np.radians(10.0)
    v = np.array([0.0, np.cos(p), np.sin(p)])
    mx, my = pencil_map(v, F, F, 319.5, 239.5, 640, 480)
    vp = np.array([F * v[0] / v[2] + 319.5, F * v[1] / v[2] + 239.5])
    for c in (50, 319, 600):
        pts = np.column_stack((mx[:, c], my[:, c]))
        d = pts - vp                                   # collinear with the vanishing point
        cross = d[:, 0] * d[0, 1] - d[:, 1] * d[0, 0]
        assert np.abs(cross / np.linalg.norm(d, axis=1) / np.linalg.norm(d[0])).max() < 1e-4
    assert pencil_map(np.array([0.0, 1.0, 0.0]), F, F, 319.5, 239.5, 640, 480) is None
