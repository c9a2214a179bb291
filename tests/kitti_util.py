"""KITTI odometry (sequence 06 subset) for the VBC real-data check: calib, poses, stereo heights.

The calibration comes from the one KITTI reader, ``drivers/stereo_calib.read_kitti_calib``.
"""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from vbnav.drivers.stereo_calib import StereoCalibration, read_kitti_calib
from vbnav.vision.features import FeatureTracker
from vbnav.vision.geometry import CameraMount, Pose2
from vbnav.vision.vbc import estimate_pose, levelled_bearings


read_calib = read_kitti_calib  # the name benchmarks/vbc_frame.py imports


def read_poses(path: Path) -> np.ndarray:
    """(N, 4, 4) camera-to-world matrices."""
    m = np.loadtxt(path).reshape(-1, 3, 4)
    out = np.tile(np.eye(4), (len(m), 1, 1))
    out[:, :3, :] = m
    return out


def planar_motion(T_a: np.ndarray, T_b: np.ndarray) -> Pose2:
    """Camera b relative to camera a as a planar pose (x, z, heading about the camera's y)."""
    T = np.linalg.inv(T_a) @ T_b
    return Pose2(T[0, 3], T[2, 3], math.atan2(T[0, 2], T[2, 2]))


def stereo_points(left: np.ndarray, right: np.ndarray, pts: np.ndarray, calib: StereoCalibration,
                  sigma_d: float = 0.5):
    """Inverse height w = 1/Y and its variance of left-image points, from the rectified right image.

    Disparity by KLT along the row (forward-backward checked, |dv| < 1 px). Returns
    (valid mask, w, var_w). Y = (v - cy) b / d is the height below the camera.
    """
    p0 = pts.reshape(-1, 1, 2).astype(np.float32)
    win, lev = (21, 21), 4
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(left, right, p0, None, winSize=win, maxLevel=lev)
    p0r, st2, _ = cv2.calcOpticalFlowPyrLK(right, left, p1, None, winSize=win, maxLevel=lev)
    p0, p1, p0r = p0.reshape(-1, 2), p1.reshape(-1, 2), p0r.reshape(-1, 2)
    d = p0[:, 0] - p1[:, 0]
    ok = ((st1.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(p0r - p0, axis=1) < 0.5)
          & (np.abs(p1[:, 1] - p0[:, 1]) < 1.0) & (d > 1.0))
    dv = pts[:, 1] - calib.cy
    dv = np.where(np.abs(dv) < 0.05, np.copysign(0.05, dv), dv)
    w = d / (dv * calib.baseline)
    var_w = (sigma_d / (dv * calib.baseline)) ** 2 + (0.5 * d / (dv * dv * calib.baseline)) ** 2
    return ok, w, var_w


def vbc_frame_pair_errors(root: Path, n_pairs: int | None = None):
    """Run VBC between consecutive KITTI frames; per pair (translation error / distance, heading error deg, n)."""
    root = Path(root)
    calib = read_kitti_calib(root / "calib.txt")
    poses = read_poses(root / "poses.txt")
    files = sorted((root / "image_l").iterdir())
    n = len(files) - 1 if n_pairs is None else min(n_pairs, len(files) - 1)
    tracker = FeatureTracker(max_features=800, min_distance=10, win_size=21, levels=4, redetect_fraction=1.0)
    mount = CameraMount(height=1.65)
    out = []
    left = cv2.imread(str(files[0]), cv2.IMREAD_GRAYSCALE)
    cam = calib.camera(left.shape[1], left.shape[0])
    tracks0 = tracker.track(left)
    for i in range(n):
        right = cv2.imread(str(root / "image_r" / files[i].name), cv2.IMREAD_GRAYSCALE)
        ok, w, var_w = stereo_points(left, right, tracks0.pts, calib)
        ids0, pts0 = tracks0.ids[ok], tracks0.pts[ok]
        w, var_w = w[ok], var_w[ok]
        nxt = cv2.imread(str(files[i + 1]), cv2.IMREAD_GRAYSCALE)
        tracks1 = tracker.track(nxt)
        common, i0, i1 = np.intersect1d(ids0, tracks1.ids, return_indices=True)
        a0, b0 = levelled_bearings(cam.rays(pts0[i0]), mount)
        a1, b1 = levelled_bearings(cam.rays(tracks1.pts[i1]), mount)
        res = estimate_pose(a0, b0, w[i0], a1, b1, var_w[i0], sigma=0.5 / calib.fx)
        truth = planar_motion(poses[i], poses[i + 1])
        dist = math.hypot(truth.x, truth.z)
        terr = math.hypot(res.pose.x - truth.x, res.pose.z - truth.z) / max(dist, 1e-9)
        herr = abs(math.degrees(res.pose.theta - truth.theta))
        out.append((terr, herr, len(common), res.quality.n_inliers))
        left, tracks0 = nxt, tracks1
    return np.array(out)
