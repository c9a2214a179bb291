"""Differential-drive kinematics and command limits.

v = r (w_l + w_r) / 2,   w = r (w_l - w_r) / L
(w > 0 turns right, toward +x; see vision/geometry.py). Wheel rates in rad/s.

Two places limit commands. ``TwistLimiter`` (the runtime, every cycle, any
controller) clips v and w to the robot's limits, bounds their change, and scales
both when a wheel would saturate. The controllers shape their own commands
first with ``keep_curvature`` (an angular-rate limit that keeps the arc) and
``saturate`` (a proportional command held between a floor and a ceiling), so
that the limiter's independent clipping of v and w never bends their path.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from vbnav.control.runtime.interfaces import Twist


@dataclass(frozen=True)
class DiffDriveKinematics:
    wheel_radius: float
    wheel_separation: float

    def wheels(self, twist: Twist) -> tuple[float, float]:
        """(left, right) wheel rates, rad/s, for a body twist."""
        half = 0.5 * self.wheel_separation * twist.w
        return (twist.v + half) / self.wheel_radius, (twist.v - half) / self.wheel_radius

    def twist(self, left: float, right: float) -> Twist:
        r = self.wheel_radius
        return Twist(0.5 * r * (left + right), r * (left - right) / self.wheel_separation)


@dataclass
class TwistLimiter:
    """Velocity, acceleration and wheel-speed limits on commanded twists.

    Wheel saturation scales v and w together, so the path's curvature is kept
    (a turn stays the same turn, only slower). ``stop()`` bypasses the
    acceleration limit: a safety stop commands zero at once and leaves the
    deceleration to the motors' own limits.
    """

    kinematics: DiffDriveKinematics
    max_v: float
    max_w: float
    max_dv: float        # m/s^2
    max_dw: float        # rad/s^2
    max_wheel: float     # rad/s
    last: Twist = Twist()

    @classmethod
    def from_config(cls, robot) -> "TwistLimiter":
        return cls(DiffDriveKinematics(robot.wheel_radius, robot.wheel_separation), robot.max_linear_speed,
                   robot.max_angular_speed, robot.max_linear_accel, robot.max_angular_accel,
                   robot.max_wheel_speed)

    def apply(self, twist: Twist, dt: float) -> Twist:
        if not (math.isfinite(twist.v) and math.isfinite(twist.w)):    # before the clip, which maps NaN to a limit
            twist = Twist(0.0, 0.0)
        v = _clip(twist.v, self.max_v)
        w = _clip(twist.w, self.max_w)
        v = self.last.v + _clip(v - self.last.v, self.max_dv * dt)
        w = self.last.w + _clip(w - self.last.w, self.max_dw * dt)
        left, right = self.kinematics.wheels(Twist(v, w))
        peak = max(abs(left), abs(right))
        if peak > self.max_wheel:
            s = self.max_wheel / peak
            v, w = v * s, w * s
        self.last = Twist(v, w)
        return self.last

    def stop(self) -> Twist:
        self.last = Twist(0.0, 0.0)
        return self.last

    def turn_only(self, w: float, dt: float) -> Twist:
        """A stop of the travel that lets a turn on the spot through: v is zero at once, as ``stop()`` makes
        it, and w keeps the speed, acceleration and wheel limits."""
        self.last = Twist(0.0, self.last.w)
        return self.apply(Twist(0.0, w), dt)


def keep_curvature(twist: Twist, max_w: float) -> Twist:
    """Limit |w| to ``max_w`` by scaling v and w together: the same arc (v / w), driven slower."""
    if abs(twist.w) <= max_w:
        return twist
    return Twist(twist.v * (max_w / abs(twist.w)), math.copysign(max_w, twist.w))


def saturate(value: float, floor: float, ceiling: float) -> float:
    """``value`` with its magnitude held in [floor, ceiling] and its sign kept.

    For proportional commands (speed from a distance, turn rate from an angle): the
    floor keeps the last bit of the error from taking forever, the ceiling is the
    speed limit and wins when the two cross.
    """
    return math.copysign(min(ceiling, max(abs(value), floor)), value)


def _clip(x: float, limit: float) -> float:
    return max(-limit, min(limit, x))
