"""Wheel odometry by exact arc integration (``vision.geometry.arc_step``).

Between two encoder readings the wheels are assumed to turn at constant rates,
so the robot moves on a circular arc whose chord is integrated exactly.
"""
from __future__ import annotations

from vbnav.drivers.wheels import WheelState
from vbnav.vision.geometry import Pose2, arc_step


class Odometry:
    """Integrates wheel encoder positions into a planar pose."""

    def __init__(self, wheel_radius: float, wheel_separation: float, start: Pose2 = Pose2()):
        self.r = wheel_radius
        self.L = wheel_separation
        self.pose = start
        self.distance = 0.0          # total path length, m
        self._last: tuple[float, float] | None = None

    def reset(self, pose: Pose2 = Pose2()) -> None:
        self.pose = pose
        self.distance = 0.0
        self._last = None

    def rebase(self) -> None:
        """Take the next reading as the new reference, keeping the pose: the encoders may count from
        elsewhere after a drive came back (a device that restarted). Motion in between is not counted."""
        self._last = None

    def update(self, state: WheelState) -> Pose2:
        left, right = state.position
        if self._last is None:
            self._last = (left, right)
            return self.pose
        dl = (left - self._last[0]) * self.r
        dr = (right - self._last[1]) * self.r
        self._last = (left, right)
        ds = 0.5 * (dl + dr)
        self.pose = arc_step(self.pose, ds, (dl - dr) / self.L)
        self.distance += abs(ds)
        return self.pose
