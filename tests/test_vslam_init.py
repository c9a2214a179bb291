"""Initialisation (11.3.3.1): two views with the planarity switch, and a known tag grid."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.geometry import rot_x, rot_y, rotation_angle
from vbnav.vision.vslam_init import TagGrid, init_from_tags, init_two_view, linear_essential

CAM = PinholeCamera(640, 480, 500.0, 500.0, 320.0, 240.0)


def unit(X):
    return X / np.linalg.norm(X, axis=1, keepdims=True)


def views(rng, P, scale, noise_px=0.3):
    R = rot_y(0.08) @ rot_x(-0.03)
    T = np.array([1.0, 0.1, 0.2]) * scale
    X2 = P @ R.T + T
    px1 = CAM.project(P)[0] + rng.normal(0, noise_px, (len(P), 2))
    px2 = CAM.project(X2)[0] + rng.normal(0, noise_px, (len(P), 2))
    return CAM.rays(px1), CAM.rays(px2), R, T


@pytest.mark.parametrize("scale", [1.0, 1e-3])
def test_general_scene_takes_the_essential_path(rng, scale):
    P = np.column_stack((rng.uniform(-2, 2, 80), rng.uniform(-1.5, 1.5, 80), rng.uniform(4, 9, 80))) * scale
    r1, r2, R, T = views(rng, P, scale)
    out = init_two_view(r1, r2, scale=np.linalg.norm(T))
    assert out.model == "essential"
    assert out.planar_ratio < 1.5
    # 0.3 px noise, 30 degree field of view: rotation and translation direction trade off (bas-relief)
    # (OpenCV's findEssentialMat + recoverPose on the same rays is no better)
    u1, u2 = r1[:, :2] / r1[:, 2:], r2[:, :2] / r2[:, 2:]
    E, _ = cv2.findEssentialMat(u1, u2, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=1e-3)
    _, R_cv, _, _ = cv2.recoverPose(E, u1, u2, np.eye(3))
    assert rotation_angle(out.R.T @ R) <= 1.1 * rotation_angle(R_cv.T @ R) + 1e-4
    assert rotation_angle(out.R.T @ R) < np.deg2rad(0.5)
    assert np.degrees(np.arccos(out.T @ T / np.linalg.norm(T) ** 2)) < 0.8  # measured 0.39 deg on 2026-11-30, bar 2x
    err = np.abs(out.depths1[out.valid] - np.linalg.norm(P, axis=1)[out.valid]) / np.linalg.norm(P, axis=1)[out.valid]
    assert out.valid.sum() > 60 and np.median(err) < 0.05


@pytest.mark.parametrize("scale", [1.0, 1e-3])
def test_planar_scene_takes_the_homography_path(rng, scale):
    # points on a tilted plane (the floor seen by a flying or endoscope camera)
    xy = np.column_stack((rng.uniform(-2, 2, 80), rng.uniform(-1.5, 1.5, 80)))
    P = (np.column_stack((xy, np.zeros(80))) @ rot_x(0.4).T + [0, 0, 6.0]) * scale
    r1, r2, R, T = views(rng, P, scale)
    out = init_two_view(r1, r2, scale=np.linalg.norm(T))
    assert out.model == "homography", out.singular_values
    assert rotation_angle(out.R.T @ R) < np.deg2rad(0.5)  # measured 0.23 deg on 2026-11-30, bar 2x
    err = np.abs(out.depths1[out.valid] - np.linalg.norm(P, axis=1)[out.valid]) / np.linalg.norm(P, axis=1)[out.valid]
    assert out.valid.sum() > 60 and np.median(err) < 0.02  # measured 0.0105 on 2026-11-30, bar 2x
    # noise-free: exact, through the homography path too
    r1, r2, R, T = views(rng, P, scale, noise_px=0.0)
    out = init_two_view(r1, r2, scale=np.linalg.norm(T))
    assert out.model == "homography" and rotation_angle(out.R.T @ R) < 1e-6


def test_linear_essential_spectrum_is_the_planarity_signal(rng):
    P = np.column_stack((rng.uniform(-2, 2, 40), rng.uniform(-1.5, 1.5, 40), rng.uniform(4, 9, 40)))
    r1, r2, _, _ = views(rng, P, 1.0, noise_px=0.0)
    s = np.linalg.svd(linear_essential(r1, r2), compute_uv=False)
    np.testing.assert_allclose(s / s[0], [1, 1, 0], atol=1e-6)


def render_tag_grid(R, T, size=0.08, spacing=0.1, rows=2, cols=3):
    """An image of a tag grid in the z = 0 plane of the grid frame, seen from X_cam = R X + T."""
    res = 2000  # pixels per metre on the board texture
    margin = 0.05
    w = int((cols * spacing + 2 * margin) * res)
    h = int((rows * spacing + 2 * margin) * res)
    board = np.full((h, w), 255, np.uint8)
    dic = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    for r in range(rows):
        for c in range(cols):
            side = int(size * res)
            tag = cv2.aruco.generateImageMarker(dic, r * cols + c, side)
            x0 = int((margin + c * spacing - size / 2) * res + spacing / 2 * res)
            y0 = int((margin + r * spacing - size / 2) * res + spacing / 2 * res)
            board[y0:y0 + side, x0:x0 + side] = tag
    # board pixel (i, j) -> grid point ((i + 0.5)/res - margin - spacing/2, ...)
    S = np.array([[1 / res, 0, 0.5 / res - margin - spacing / 2], [0, 1 / res, 0.5 / res - margin - spacing / 2],
                  [0, 0, 1]])
    H = CAM.K @ np.column_stack((R[:, 0], R[:, 1], T)) @ S
    return cv2.warpPerspective(board, H, (CAM.width, CAM.height), flags=cv2.INTER_AREA, borderValue=128)


def test_tag_grid_gives_the_camera_pose(rng):
    R = rot_x(0.35) @ rot_y(-0.2)
    T = np.array([-0.1, -0.05, 0.6])
    img = render_tag_grid(R, T)
    grid = TagGrid.from_spec({"family": "36h11", "tag_size": 0.08, "rows": 2, "cols": 3, "spacing": 0.1})
    extra = CAM.project(np.array([[0.05, 0.05, 0.0], [0.15, 0.02, 0.0]]) @ R.T + T)[0]
    out = init_from_tags(img, CAM, grid, extra_pixels=extra)
    assert out.info["tags"] == [0, 1, 2, 3, 4, 5]
    R_cw = out.pose_wc[:3, :3].T
    assert rotation_angle(R_cw.T @ R) < np.deg2rad(0.13)  # measured 0.063 deg on 2026-11-30, bar 2x
    assert np.linalg.norm(-R_cw @ out.pose_wc[:3, 3] - T) < 0.0013  # measured 0.62 mm on 2026-11-30, bar 2x
    # the two extra pixels got their depth from the grid plane (measured 0.61 mm off on 2026-12-04, bar 2x)
    np.testing.assert_allclose(out.points_cam[-2:], np.array([[0.05, 0.05, 0.0], [0.15, 0.02, 0.0]]) @ R.T + T,
                               atol=0.0013)
