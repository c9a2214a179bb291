"""Planar paths: following a polyline (the teaching driver) and measuring lateral error."""
from __future__ import annotations

import math

import numpy as np
from vbnav.control.runtime.interfaces import ControlContext, Controller, Twist
from vbnav.vision.geometry import Pose2, wrap_angle


def rounded_rectangle(center_xz: tuple[float, float], size_xz: tuple[float, float], radius: float,
                      step: float = 0.05) -> np.ndarray:
    """Closed loop (N, 2) of (x, z) points, clockwise seen from above (right turns), starting mid bottom edge
    heading +z... it starts on the left edge heading forward (+z) so a robot at theta = 0 can follow it."""
    cx, cz = center_xz
    w, h = size_xz
    r = radius
    x0, x1, z0, z1 = cx - w / 2, cx + w / 2, cz - h / 2, cz + h / 2
    pts = []

    def line(a, b):
        n = max(2, int(math.hypot(b[0] - a[0], b[1] - a[1]) / step))
        for t in np.linspace(0, 1, n, endpoint=False):
            pts.append((a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])))

    def arc(c, a0, a1):
        n = max(4, int(abs(a1 - a0) * r / step))
        for t in np.linspace(a0, a1, n, endpoint=False):
            pts.append((c[0] + r * math.cos(t), c[1] + r * math.sin(t)))

    # Left edge going +z, then top-left corner turning right toward +x, and so on (clockwise from above
    # in x-right / z-forward coordinates means: +z, then +x, then -z, then -x).
    line((x0, cz), (x0, z1 - r))
    arc((x0 + r, z1 - r), math.pi, math.pi / 2)
    line((x0 + r, z1), (x1 - r, z1))
    arc((x1 - r, z1 - r), math.pi / 2, 0.0)
    line((x1, z1 - r), (x1, z0 + r))
    arc((x1 - r, z0 + r), 0.0, -math.pi / 2)
    line((x1 - r, z0), (x0 + r, z0))
    arc((x0 + r, z0 + r), -math.pi / 2, -math.pi)
    line((x0, z0 + r), (x0, cz))
    return np.array(pts)


def room_loop() -> np.ndarray:
    """A 20.6 m closed loop with four right turns, 1 m from the boxes and walls of the simulated room
    (World.room()): what the scripted teacher drives (controller.teach: room_loop) and the demo's route.
    It starts at (-3.5, 0) heading +z, the sim.start_pose of configs/sim.yaml."""
    return rounded_rectangle((0.0, 0.0), (7.0, 4.0), 0.8)


def path_length(path: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)))


def lateral_errors(points: np.ndarray, path: np.ndarray, closed: bool = False) -> np.ndarray:
    """Distance of each (x, z) point to the nearest segment of a polyline."""
    P = np.asarray(path, dtype=float)
    if closed:
        P = np.vstack([P, P[:1]])
    a, b = P[:-1], P[1:]
    ab = b - a
    L2 = np.maximum(np.sum(ab * ab, axis=1), 1e-12)
    out = np.empty(len(points))
    for i, p in enumerate(np.asarray(points, dtype=float)):
        t = np.clip(np.sum((p - a) * ab, axis=1) / L2, 0.0, 1.0)
        d = a + t[:, None] * ab - p
        out[i] = math.sqrt(float(np.min(np.sum(d * d, axis=1))))
    return out


class PathFollower(Controller):
    """Pure pursuit on a polyline with the odometry pose: the scripted 'driver' when teaching in simulation.

    On a robot the teacher drives by teleoperation instead; this stands in for that person.

    Settings (keyword arguments, checked here; a test scenario's, not a robot configuration's):
    speed: m/s on a straight path; lookahead: m to the point the robot steers to;
    min_speed_factor: the speed shrinks with the cosine of the bearing to that point, but not below
    this share, so a sharp corner is driven slowly rather than turned on the spot;
    finish_margin_m: done this far before the end of the path, so a closed loop does not
    chase its own start; search_points: how many path points from the current one the nearest is
    searched among.
    """

    name = "path_follower"

    def __init__(self, path: np.ndarray, speed: float = 0.4, lookahead: float = 0.5, closed: bool = True,
                 start: Pose2 = Pose2(), min_speed_factor: float = 0.3, finish_margin_m: float = 0.1,
                 search_points: int = 60):
        if not (speed > 0 and lookahead > 0 and 0 < min_speed_factor <= 1 and finish_margin_m >= 0
                and search_points >= 1):
            raise ValueError(f"path follower: need speed > 0, lookahead > 0, 0 < min_speed_factor <= 1, "
                             f"finish_margin_m >= 0, search_points >= 1 (got {speed}, {lookahead}, "
                             f"{min_speed_factor}, {finish_margin_m}, {search_points})")
        self.path = np.asarray(path, dtype=float)
        self.speed = speed
        self.lookahead = lookahead
        self.min_speed_factor = min_speed_factor
        self.finish_margin_m = finish_margin_m
        self.search_points = search_points
        self.closed = closed
        self.start_pose = start   # where the path's frame sits in the odometry frame
        self._index = 0
        self._travel = 0.0
        self.total = path_length(self.path) + (float(np.linalg.norm(self.path[-1] - self.path[0])) if closed else 0)
        self._done = False
        self._last_xz = None

    def update(self, ctx: ControlContext) -> Twist:
        pose = self.start_pose.compose(ctx.odom) if self.start_pose != Pose2() else ctx.odom
        xz = np.array([pose.x, pose.z])
        if self._last_xz is not None:
            self._travel += float(np.linalg.norm(xz - self._last_xz))
        self._last_xz = xz
        n = len(self.path)
        # Advance the index along the path (monotone, so a closed loop's end does not snap back to its start).
        window = [(self._index + k) % n for k in range(min(self.search_points, n))]
        d = np.linalg.norm(self.path[window] - xz, axis=1)
        self._index = window[int(np.argmin(d))]
        if self._travel > self.total - self.finish_margin_m:
            self._done = True
            return Twist()
        target = self._index
        for k in range(n):
            j = (self._index + k) % n
            if np.linalg.norm(self.path[j] - xz) >= self.lookahead:
                target = j
                break
        dx, dz = self.path[target] - xz
        # Bearing of the target in the robot frame (alpha convention: atan2(x, z) turned by -theta).
        alpha = wrap_angle(math.atan2(dx, dz) - pose.theta)
        curvature = 2.0 * math.sin(alpha) / max(self.lookahead, 1e-6)
        v = self.speed * max(self.min_speed_factor, math.cos(alpha))
        return Twist(v, v * curvature)

    @property
    def finished(self) -> bool:
        return self._done

    def status(self) -> dict:
        return {"travelled_m": round(self._travel, 2), "of_m": round(self.total, 2)}
