"""A frozen camera: the same image again and again, with fresh stamps.

A USB camera whose driver re-queues its last buffer, or a capture thread that hangs while the timestamps
come from the host, delivers frames on time that show a view the robot has left. The stale-camera stop
(``camera.stale_after_s``) never fires, VSLAM and repeat report poses that stop moving while the wheels
turn, and the obstacle stage judges a clear view that is no longer in front of the robot.

A live sensor never gives two byte-identical frames: shot and read noise change some pixel of every
frame. A still scene in a noise-free simulation does, so an unchanged image counts as frozen only once the
wheels have moved far enough since the image last changed that a live camera would have seen the change:

- travel: a point at the image's edge (x/z = 0.5) at 5 m shifts by f * 0.5 * d / 5 when the robot drives d
  towards it; ``TRAVEL_SHIFT_PX`` 1 px of it: d = 10 / f, 2 cm at f = 500 px (``MIN_TRAVEL_M``, a
  640-pixel-wide lens of ~65 deg); nearer points shift more.
- turn: every point shifts by f * a; ``TURN_SHIFT_PX`` 2.5 px of it: a = 2.5 / f, 5 mrad (0.29 deg) at
  f = 500 px (``MIN_TURN_RAD``).

The pipeline takes f from the configured camera (``camera.fx``): a wide lens needs more motion to show it.

A hung driver may re-queue the few buffers it holds rather than one, so the frames cycle A, B, C, D, A...:
each differs from the one before. An image equal to any of the last ``RECENT_IMAGES`` distinct images counts
as that image seen again, frozen once the wheels moved the distances above since it was first seen.
``RECENT_IMAGES`` 4 is the number of buffers OpenCV's V4L2 backend queues by default (``DEFAULT_V4L_BUFFERS``);
the driver sets ``CAP_PROP_BUFFERSIZE`` 1, which a device may round up to its own minimum, so 4 covers both.

A frozen frame is not *fresh*: it goes to no vision stage (an old image paired with new odometry would
pull teach's landmark heights towards far and start keyframes whose image is not at their pose), and
the runtime's stale-camera check counts from the last fresh frame, so the robot stops
``camera.stale_after_s`` after the image froze (plus the distance above) and drives again on the first
frame that differs. A covered lens that gives exactly black frames counts as frozen too while the robot
moves, which is the same answer: nothing can be seen.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from vbnav.vision.geometry import Pose2

TRAVEL_SHIFT_PX = 1.0      # at the image's edge (x/z = EDGE), DEPTH_M away
TURN_SHIFT_PX = 2.5
EDGE, DEPTH_M = 0.5, 5.0
RECENT_IMAGES = 4


def thresholds(focal_px: float) -> tuple[float, float]:
    """(travel m, turn rad) after which an unchanged image is frozen, for a camera of focal length ``focal_px``."""
    return TRAVEL_SHIFT_PX * DEPTH_M / (EDGE * focal_px), TURN_SHIFT_PX / focal_px


MIN_TRAVEL_M, MIN_TURN_RAD = thresholds(500.0)   # the default (a camera of f = 500 px): 2 cm, 5 mrad


class FrozenImageWatch:
    """Says whether each frame is fresh: a new image, or one of the last ``recent`` images while the robot
    stood still since that image was first seen."""

    def __init__(self, min_travel_m: float = MIN_TRAVEL_M, min_turn_rad: float = MIN_TURN_RAD,
                 recent: int = RECENT_IMAGES):
        self.min_travel_m = min_travel_m
        self.min_turn_rad = min_turn_rad
        # copies of the last ``recent`` distinct images, newest last, each with the pose it was first seen at
        self._recent: deque[tuple[np.ndarray, Pose2]] = deque(maxlen=recent)
        self.frozen = False

    @classmethod
    def for_focal(cls, focal_px: float) -> "FrozenImageWatch":
        """The watch for a camera of focal length ``focal_px`` (``thresholds``)."""
        return cls(*thresholds(focal_px))

    def fresh(self, image: np.ndarray, odom: Pose2) -> bool:
        seen = next((pose for old, pose in self._recent
                     if old.shape == image.shape and old.dtype == image.dtype and np.array_equal(old, image)),
                    None)
        if seen is None:
            self._remember(image, odom)
            return True
        moved = seen.between(odom)
        self.frozen = (math.hypot(moved.x, moved.z) >= self.min_travel_m
                       or abs(moved.theta) >= self.min_turn_rad)
        return not self.frozen

    def _remember(self, image: np.ndarray, odom: Pose2) -> None:
        # A copy: a driver may hand out the same buffer again, filled anew (comparing it with itself
        # would call every frame frozen). The oldest copy's memory is reused when it has the same format.
        spare = self._recent[0][0] if len(self._recent) == self._recent.maxlen else None
        copy = spare if spare is not None and spare.shape == image.shape and spare.dtype == image.dtype \
            else np.empty_like(image)
        np.copyto(copy, image)
        self._recent.append((copy, odom))
        self.frozen = False
