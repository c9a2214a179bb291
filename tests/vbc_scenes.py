"""Synthetic planar scenes with known truth for the VBC tests (no renderer)."""
from __future__ import annotations

import numpy as np

from vbnav.vision.camera_model import azimuth_elevation
from vbnav.vision.geometry import CameraMount, Pose2, camera_pose


def levelled_points(robot: Pose2, mount: CameraMount, points: np.ndarray) -> np.ndarray:
    """World points (N, 3) in the levelled frame: robot axes at the camera centre."""
    _, t_wc = camera_pose(robot, mount)
    return (np.asarray(points) - t_wc) @ robot.rotation3()


def bearings(robot: Pose2, mount: CameraMount, points: np.ndarray):
    return azimuth_elevation(levelled_points(robot, mount, points))


def room_points(rng, n: int, mount: CameraMount, *, min_range=1.5, max_range=6.0, fov=1.2,
                heights=(0.0, 2.0)) -> np.ndarray:
    """Landmarks in front of a robot at the origin: heights above the floor, world y = -height."""
    az = rng.uniform(-fov / 2, fov / 2, n)
    r = rng.uniform(min_range, max_range, n)
    h = rng.uniform(*heights, n)
    return np.column_stack((r * np.sin(az), -h, mount.forward + r * np.cos(az)))
