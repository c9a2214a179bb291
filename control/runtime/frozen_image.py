"""A frozen camera: the same image again and again, with fresh stamps.

A USB camera whose driver re-queues its last buffer, or a capture thread that hangs while the timestamps
come from the host, delivers frames on time that show a view the robot has left. The stale-camera stop
(``camera.stale_after_s``) never fires, VSLAM and repeat report poses that stop moving while the wheels
turn, and the obstacle stage judges a clear view that is no longer in front of the robot.

A live sensor never gives two byte-identical frames: shot and read noise change some pixel of every
frame. A still scene in a noise-free simulation does, so an unchanged image counts as frozen only once the
wheels have moved far enough since the image last changed that a live camera would have seen the change:

- ``MIN_TRAVEL_M`` 2 cm: a point at the image's edge (x/z = 0.5) at 5 m shifts by f * 0.5 * 0.02 / 5 =
  1 px at f = 500 px (640-pixel-wide lens of ~65 deg) when the robot drives 2 cm towards it; nearer
  points shift more.
- ``MIN_TURN_RAD`` 5 mrad (0.29 deg): every point shifts by f * 0.005 = 2.5 px at f = 500 px.

A frozen frame is not *fresh*: it goes to no vision stage (an old image paired with new odometry would
pull teach's landmark heights towards far and start keyframes whose image is not at their pose), and
the runtime's stale-camera check counts from the last fresh frame, so the robot stops
``camera.stale_after_s`` after the image froze (plus the distance above) and drives again on the first
frame that differs. A covered lens that gives exactly black frames counts as frozen too while the robot
moves, which is the same answer: nothing can be seen.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from vbnav.vision.geometry import Pose2

MIN_TRAVEL_M = 0.02
MIN_TURN_RAD = 0.005


class FrozenImageWatch:
    """Says whether each frame is fresh: a new image, or the same one while the robot stood still."""

    def __init__(self, min_travel_m: float = MIN_TRAVEL_M, min_turn_rad: float = MIN_TURN_RAD):
        self.min_travel_m = min_travel_m
        self.min_turn_rad = min_turn_rad
        self._last: Optional[np.ndarray] = None      # a copy of the last image that changed
        self._pose_at_change: Optional[Pose2] = None
        self.frozen = False

    def fresh(self, image: np.ndarray, odom: Pose2) -> bool:
        last = self._last
        if last is None or last.shape != image.shape or last.dtype != image.dtype \
                or not np.array_equal(last, image):
            self._remember(image, odom)
            return True
        moved = self._pose_at_change.between(odom)
        self.frozen = (math.hypot(moved.x, moved.z) >= self.min_travel_m
                       or abs(moved.theta) >= self.min_turn_rad)
        return not self.frozen

    def _remember(self, image: np.ndarray, odom: Pose2) -> None:
        # A copy: a driver may hand out the same buffer again, filled anew (comparing it with itself
        # would call every frame frozen).
        if self._last is None or self._last.shape != image.shape or self._last.dtype != image.dtype:
            self._last = np.empty_like(image)
        np.copyto(self._last, image)
        self._pose_at_change = odom
        self.frozen = False
