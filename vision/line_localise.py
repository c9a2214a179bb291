"""Localisation against the line map: the robot's planar pose from 2D-3D line correspondences.

A robot started in a mapped room knows roughly where it is (odometry, the last
pose, a start pose within ``search_m`` / ``search_deg``). The pose is found in
two steps:

1. coarse search: on a grid of poses around the guess, predict the verified map
   segments (vision/line_map.py) and count those that some detected left-image
   segment lies along (direction and distance gates); the best count wins;
2. refinement: Gauss-Newton (Huber-weighted) on (x, z, heading) minimising the
   distances of the projected 3D endpoints of each matched map segment to the
   infinite line of its detected 2D segment, re-associating with a shrinking
   gate. The pose is planar (the camera mount is fixed), so three unknowns.

The result carries the number of correspondences and the residual RMS (px):
``ok`` needs at least ``min_matches`` of them, so a view of blank walls is
reported, not guessed, and at least ``min_explained`` of the map segments the
pose predicts in view, so a pose that lines up a few parallel lines by chance is
reported too.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vbnav.vision.geometry import CameraMount, Pose2, camera_pose
from vbnav.vision.line_map import LineMap
from vbnav.vision.line_segments import Segments2D


@dataclass(frozen=True)
class LocaliseParams:
    search_m: float = 0.3
    search_step_m: float = 0.1
    search_deg: float = 12.0
    search_step_deg: float = 3.0
    gate_px: tuple = (6.0, 3.0, 1.5)      # association gates of the refinement rounds
    iterations: int = 6
    huber_px: float = 1.0
    min_matches: int = 8
    # A true pose sees most of what the map predicts in view (occlusions and missed detections take some:
    # 53-82 % over 16 random poses in the rendered room); a wrong one lines up a few parallel lines by
    # chance (8-30 % there). Half separates them.
    min_explained: float = 0.5


@dataclass
class Localisation:
    pose: Pose2
    matches: int
    rms_px: float
    ok: bool
    predicted: int = 0      # map segments the pose predicts in view (``matches`` of them were found)


@dataclass(frozen=True)
class View:
    """The left camera: intrinsics, image size, stereo baseline (for the predicted disparity), mount."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    baseline: float
    mount: CameraMount

    def predict(self, lmap: LineMap, pose: Pose2):
        R, t = camera_pose(pose, self.mount)
        return lmap.predict(R, t, self.fx, self.fy, self.cx, self.cy, self.baseline, self.width, self.height)


def _count(lmap: LineMap, segs: Segments2D, view: View, pose: Pose2, gate_px: float) -> int:
    pred = view.predict(lmap, pose)
    if len(pred) == 0:
        return 0
    ok, dist, _ = lmap._support_matrix(segs, pred)
    return int((ok & (dist <= gate_px)).any(axis=0).sum())


def localise(lmap: LineMap, segs: Segments2D, view: View, guess: Pose2,
             params: LocaliseParams = LocaliseParams()) -> Localisation:
    """The robot pose seen by ``segs`` (left image) in the map's frame, searched around ``guess``."""
    best, best_n = guess, -1
    steps_xy = np.arange(-params.search_m, params.search_m + 1e-9, params.search_step_m)
    steps_th = np.radians(np.arange(-params.search_deg, params.search_deg + 1e-9, params.search_step_deg))
    for dth in steps_th:
        for dx in steps_xy:
            for dz in steps_xy:
                pose = Pose2(guess.x + dx, guess.z + dz, guess.theta + dth)
                n = _count(lmap, segs, view, pose, params.gate_px[0])
                if n > best_n:
                    best, best_n = pose, n
    pose = best
    n, rms = 0, math.inf
    for gate in params.gate_px:
        for _ in range(params.iterations):
            pose, n, rms, step = _gauss_newton_step(lmap, segs, view, pose, gate, params.huber_px)
            if step < 1e-5:
                break
    predicted = len(view.predict(lmap, pose))
    ok = n >= params.min_matches and n >= params.min_explained * predicted
    return Localisation(pose, n, rms, ok, predicted)


def _residuals(lmap: LineMap, view: View, pose: Pose2, idx: np.ndarray, lines: np.ndarray) -> np.ndarray:
    """Signed distances (px) of the projected endpoints of map segments ``idx`` to image lines
    (a, b, c) with a^2 + b^2 = 1: shape (2K,)."""
    R, t = camera_pose(pose, view.mount)
    Pc = (lmap.P[idx] - t) @ R                                      # (K, 2, 3)
    z = np.maximum(Pc[..., 2], 1e-3)
    u = view.fx * Pc[..., 0] / z + view.cx
    v = view.fy * Pc[..., 1] / z + view.cy
    return (lines[:, None, 0] * u + lines[:, None, 1] * v + lines[:, None, 2]).ravel()


def _gauss_newton_step(lmap: LineMap, segs: Segments2D, view: View, pose: Pose2, gate: float, huber: float):
    pred = view.predict(lmap, pose)
    if len(pred) == 0 or len(segs) == 0:
        return pose, 0, math.inf, 0.0
    ok, dist, _ = lmap._support_matrix(segs, pred)
    ok &= dist <= gate
    # Each predicted segment takes its nearest detected segment.
    cost = np.where(ok, dist, np.inf)
    det = cost.argmin(axis=0)
    has = np.isfinite(cost[det, np.arange(len(pred))])
    if has.sum() < 3:
        return pose, int(has.sum()), math.inf, 0.0
    idx = pred.index[has]
    xy = segs.xy[det[has]]
    d = xy[:, 2:4] - xy[:, 0:2]
    nrm = np.column_stack((-d[:, 1], d[:, 0])) / np.linalg.norm(d, axis=1, keepdims=True)
    lines = np.column_stack((nrm, -(nrm * xy[:, 0:2]).sum(axis=1)))
    r0 = _residuals(lmap, view, pose, idx, lines)
    eps = (1e-4, 1e-4, 1e-5)
    J = np.empty((len(r0), 3))
    for k in range(3):
        dp = np.zeros(3)
        dp[k] = eps[k]
        p2 = Pose2(pose.x + dp[0], pose.z + dp[1], pose.theta + dp[2])
        J[:, k] = (_residuals(lmap, view, p2, idx, lines) - r0) / eps[k]
    w = np.where(np.abs(r0) <= huber, 1.0, huber / np.maximum(np.abs(r0), 1e-12))
    H = J.T @ (w[:, None] * J) + 1e-6 * np.eye(3)
    delta = -np.linalg.solve(H, J.T @ (w * r0))
    new = Pose2(pose.x + delta[0], pose.z + delta[1], pose.theta + delta[2])
    rms = float(np.sqrt(np.mean(r0 ** 2)))
    return new, int(has.sum()), rms, float(np.abs(delta[:2]).max() + abs(delta[2]))
