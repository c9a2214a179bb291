"""Wheel odometry by exact arc integration (``vision.geometry.arc_step``), and its stamped history.

Between two encoder readings the wheels are assumed to turn at constant rates,
so the robot moves on a circular arc whose chord is integrated exactly.
``OdometryHistory`` keeps the last poses with their readings' stamps, so a vision
stage gets the pose at its frame's exposure, not the newest one.
"""
from __future__ import annotations

import threading
from typing import Optional

import numpy as np

from vbnav.drivers.wheels import WheelState
from vbnav.vision.geometry import Pose2, arc_step, wrap_angle


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


class OdometryHistory:
    """The last ``capacity`` odometry poses with their stamps, and the pose at any stamp among them.

    A camera frame is exposed 30-100 ms before a vision stage gets to it; by then the
    robot has moved on, so the stage needs the odometry *of its frame*, not the newest.
    The loop records every cycle's pose at its wheel reading's stamp (``record``: no
    allocation, preallocated ring); the vision thread asks for the pose at a frame's
    stamp (``at``), interpolated between the two readings around it, or the motion
    between two frames' stamps (``motion``). A lock guards the ring: the loop's side
    holds it for four array writes.

    Out of range: a stamp older than the ring gets the oldest pose (the ring holds
    ``capacity`` loop periods, 2.56 s at 100 Hz by default, far more than any usable
    camera latency); a stamp newer than the last reading (a frame stamped after the
    loop's last cycle) is extrapolated at the last reading's rate, for at most
    ``max_extrapolate_ns``, then held.
    """

    def __init__(self, capacity: int = 256, max_extrapolate_ns: int = 50_000_000):
        if capacity < 2:
            raise ValueError(f"OdometryHistory capacity must be >= 2, got {capacity}")
        self.capacity = capacity
        self.max_extrapolate_ns = max_extrapolate_ns
        self._t = np.zeros(capacity, np.int64)
        self._p = np.zeros((capacity, 3))          # x, z, theta (theta unwrapped)
        self._n = 0                                 # readings recorded so far
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return min(self._n, self.capacity)

    def clear(self) -> None:
        with self._lock:
            self._n = 0

    def record(self, stamp_ns: int, pose: Pose2) -> None:
        """Add the pose read at ``stamp_ns`` (loop thread; stamps must not decrease)."""
        with self._lock:
            n, cap = self._n, self.capacity
            i = n % cap
            if n:
                j = (n - 1) % cap
                if stamp_ns <= self._t[j]:        # same reading again (a lost drive holds its stamp): replace
                    i, n = j, n - 1
                theta = self._p[j, 2] + wrap_angle(pose.theta - self._p[j, 2])   # unwrapped: interpolates
            else:
                theta = pose.theta
            self._t[i] = stamp_ns
            self._p[i, 0] = pose.x
            self._p[i, 1] = pose.z
            self._p[i, 2] = theta
            self._n = n + 1

    def at(self, stamp_ns: int) -> Optional[Pose2]:
        """The odometry pose at ``stamp_ns`` (None before the first reading)."""
        with self._lock:
            n, cap = self._n, self.capacity
            if n == 0:
                return None
            size = min(n, cap)
            first = n - size                        # logical index of the oldest reading

            def t(k: int) -> int:
                return int(self._t[k % cap])

            if stamp_ns <= t(first):
                return self._pose(first % cap)
            last = n - 1
            if stamp_ns >= t(last):
                if size < 2:
                    return self._pose(last % cap)
                a, b = (last - 1) % cap, last % cap
                ahead = min(stamp_ns - t(last), self.max_extrapolate_ns)
                return self._blend(a, b, 1.0 + ahead / max(1, t(last) - t(last - 1)))
            lo, hi = first, last                    # t(lo) < stamp <= t(hi)
            while hi - lo > 1:
                mid = (lo + hi) // 2
                if t(mid) < stamp_ns:
                    lo = mid
                else:
                    hi = mid
            return self._blend(lo % cap, hi % cap, (stamp_ns - t(lo)) / (t(hi) - t(lo)))

    def motion(self, from_ns: int, to_ns: int) -> Optional[Pose2]:
        """The odometry motion from stamp ``from_ns`` to ``to_ns``, in the robot's frame at ``from_ns``."""
        a, b = self.at(from_ns), self.at(to_ns)
        return None if a is None or b is None else a.between(b)

    def _pose(self, i: int) -> Pose2:
        x, z, th = self._p[i]
        return Pose2(float(x), float(z), wrap_angle(float(th)))

    def _blend(self, i: int, j: int, a: float) -> Pose2:
        p = self._p[i] + a * (self._p[j] - self._p[i])
        return Pose2(float(p[0]), float(p[1]), wrap_angle(float(p[2])))
