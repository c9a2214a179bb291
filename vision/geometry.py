"""Poses and frames shared by every module.

Conventions (DESIGN.md): camera frame is OpenCV's (x right, y down, z forward).
The world frame uses the same axes, with the floor at y = 0 (so points above the
floor have y < 0). A planar robot pose (x, z, theta) has its heading direction
(sin theta, cos theta) in the (x, z) plane: theta grows when the robot turns
toward +x (right, clockwise seen from above). Angular rates follow theta.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def wrap_angle(a: float) -> float:
    """Wrap to (-pi, pi]."""
    return math.atan2(math.sin(a), math.cos(a))


@dataclass(frozen=True)
class Pose2:
    """Planar pose on the floor: position (x, z) in m, heading theta in rad."""

    x: float = 0.0
    z: float = 0.0
    theta: float = 0.0

    def compose(self, other: "Pose2") -> "Pose2":
        """self * other: ``other`` expressed in self's frame, mapped to self's parent."""
        c, s = math.cos(self.theta), math.sin(self.theta)
        # Robot-frame (x right, z forward) to parent: rot_y(theta) on (x, z).
        return Pose2(self.x + c * other.x + s * other.z,
                     self.z - s * other.x + c * other.z,
                     wrap_angle(self.theta + other.theta))

    def inverse(self) -> "Pose2":
        c, s = math.cos(self.theta), math.sin(self.theta)
        return Pose2(-(c * self.x - s * self.z), -(s * self.x + c * self.z), wrap_angle(-self.theta))

    def between(self, other: "Pose2") -> "Pose2":
        """``other`` expressed in this pose's frame (self^-1 * other)."""
        return self.inverse().compose(other)

    def as_array(self) -> np.ndarray:
        return np.array([self.x, self.z, self.theta])

    def rotation3(self) -> np.ndarray:
        return rot_y(self.theta)

    def translation3(self) -> np.ndarray:
        return np.array([self.x, 0.0, self.z])


@dataclass(frozen=True)
class CameraMount:
    """Where the camera sits on the robot.

    height: optical centre above the floor, m. forward/lateral: offset from the
    wheel-axle centre along the robot's z (forward) and x (right), m.
    pitch: rad, positive looking down. yaw: rad, positive looking right. roll: rad about the
    optical axis, positive turned clockwise seen from behind (the camera's x axis, image right,
    tilts down).
    """

    height: float = 0.25
    forward: float = 0.0
    lateral: float = 0.0
    pitch: float = 0.0
    yaw: float = 0.0
    roll: float = 0.0

    def rotation(self) -> np.ndarray:
        """R_robot_camera: camera axes expressed in the robot frame."""
        return rot_y(self.yaw) @ rot_x(-self.pitch) @ rot_z(self.roll)

    def translation(self) -> np.ndarray:
        return np.array([self.lateral, -self.height, self.forward])


def camera_pose(robot: Pose2, mount: CameraMount) -> tuple[np.ndarray, np.ndarray]:
    """World-from-camera (R_wc, t_wc) for a robot pose and a camera mount."""
    R_wr = robot.rotation3()
    R_wc = R_wr @ mount.rotation()
    t_wc = R_wr @ mount.translation() + robot.translation3()
    return R_wc, t_wc


def arc_step(pose: Pose2, ds: float, dth: float) -> Pose2:
    """Pose after moving ``ds`` metres along a circular arc that turns by ``dth`` rad.

    Exact for constant wheel rates between two samples (the chord of the arc),
    unlike the Euler step ``x += ds sin(theta)`` which drifts on tight turns.
    """
    th0 = pose.theta
    if abs(dth) < 1e-9:
        thm = th0 + 0.5 * dth  # second-order limit: chord at the mid heading
        return Pose2(pose.x + ds * math.sin(thm), pose.z + ds * math.cos(thm), wrap_angle(th0 + dth))
    radius = ds / dth
    th1 = th0 + dth
    return Pose2(pose.x + radius * (math.cos(th0) - math.cos(th1)),
                 pose.z + radius * (math.sin(th1) - math.sin(th0)),
                 wrap_angle(th1))


def absolute_orientation(P: np.ndarray, Q: np.ndarray, weights: np.ndarray | None = None,
                         with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float | np.ndarray]:
    """(R, t, s) minimising sum_i w_i |s R P_i + t - Q_i|^2, R in SO(3) (Umeyama 1991).

    ``P``, ``Q``: (N, 3) corresponding points, or (..., N, 3) for independent problems solved at
    once (the motion solver's 3-point hypotheses). ``weights`` (..., N), uniform if None. The
    scale s > 0 is fitted only ``with_scale`` (Sim(3), e.g. aligning a monocular trajectory),
    else s = 1 (SE(3)); it is a float for one problem, an array for a batch.

    With Sigma = sum_i w_i (Q_i - mu_Q)(P_i - mu_P)^T / sum_i w_i = U S V^T:
    R = U D V^T, D = diag(1, 1, det(U) det(V)) (the reflection guard: when the best orthogonal
    map is a mirror image, the axis of the smallest singular value is flipped instead),
    s = trace(S D) / var(P), t = mu_Q - s R mu_P.

    The motion alternation (vision/motion.py) runs only the rotation step of this on a
    cross-covariance it updates linearly (``motion._rotation_from_cross_covariance``), and
    vision/motion_kernel.py compiles that step (its own 3x3 SVD, no allocation) for the
    real-time solver; tests/test_motion_kernel.py checks the compiled twin against the numpy one.
    """
    P = np.asarray(P, float)
    Q = np.asarray(Q, float)
    if weights is None:
        mu_p, mu_q = P.mean(-2), Q.mean(-2)
        a, b = P - mu_p[..., None, :], Q - mu_q[..., None, :]
        sigma = np.swapaxes(b, -1, -2) @ a / P.shape[-2]
        var_p = (a ** 2).sum(-1).mean(-1)
    else:
        w = np.asarray(weights, float)
        w = w / w.sum(-1, keepdims=True)
        mu_p, mu_q = (w[..., None] * P).sum(-2), (w[..., None] * Q).sum(-2)
        a, b = P - mu_p[..., None, :], Q - mu_q[..., None, :]
        sigma = np.swapaxes(b, -1, -2) @ (w[..., None] * a)
        var_p = (w * (a ** 2).sum(-1)).sum(-1)
    U, S, Vt = np.linalg.svd(sigma)
    D = np.ones(S.shape)
    D[..., 2] = np.where(np.linalg.det(U) * np.linalg.det(Vt) < 0, -1.0, 1.0)
    R = (U * D[..., None, :]) @ Vt
    s = (S * D).sum(-1) / var_p if with_scale else np.ones(S.shape[:-1])
    t = mu_q - ((s[..., None, None] * R) @ mu_p[..., None])[..., 0]
    return R, t, (float(s) if s.ndim == 0 else s)


def similarity_moved(W: np.ndarray, s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """A 4x4 world-from-camera pose after the world moves by X' = s R X + t (the camera keeps its scale)."""
    out = np.array(W, float, copy=True)
    out[:3, :3] = R @ out[:3, :3]
    out[:3, 3] = s * R @ out[:3, 3] + t
    return out


def rotation_angle(R: np.ndarray) -> float:
    """Angle of a rotation matrix, rad (robust near 0 and pi)."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(math.acos(max(-1.0, min(1.0, c))))


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """(qx, qy, qz, qw) with qw >= 0, from a rotation matrix."""
    m = np.asarray(R, dtype=float)
    t = np.trace(m)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def matrix_from_quat(q) -> np.ndarray:
    x, y, z, w = (float(v) for v in q)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
