"""Pose fusion for the vision controllers: odometry between vision fixes, a share of each fix's correction.

A vision fix (a VBC pose relative to a keyframe, a VSLAM pose) says where the robot
was when its frame was exposed; by the time it reaches the loop the robot has moved
on. So the filter keeps its fused pose together with the odometry reading at which
that pose held (the anchor): between fixes the pose is carried forward by the
odometry motion since the anchor, and a fix is compared with the pose predicted at
*its frame's* odometry, not with the pose now. Only ``fix_gain`` of the difference
is applied at once (a complementary filter): odometry is smooth but drifts, fixes do
not drift but jitter from frame to frame.

``PoseFusion`` is shared by ``RepeatController`` and ``GotoController``; it holds
the pose, nothing else, and never looks at a clock.
"""
from __future__ import annotations

import math
from typing import Optional

from vbnav.vision.geometry import Pose2

#: m: blind travel is summed in straight steps of at least this (a bend is counted along it, to within a
#: fraction of a percent; a standing robot's encoder read noise, back and forth, never adds up)
BLIND_STEP_M = 0.01


class PoseFusion:
    """Planar pose fused from odometry and trusted vision fixes taken at their frames' odometry."""

    def __init__(self, fix_gain: float):
        if not 0.0 < fix_gain <= 1.0:
            raise ValueError(f"fix_gain must be in (0, 1], got {fix_gain}")
        self.fix_gain = fix_gain
        self._pose: Optional[Pose2] = None      # fused pose when odometry read self._anchor
        self._anchor: Optional[Pose2] = None
        self._trusted: Optional[Pose2] = None   # odometry at the last trusted fix
        self._counted: Optional[Pose2] = None   # odometry up to which the blind travel is summed
        self._driven = 0.0                      # blind travel summed up to it, m

    @property
    def initialised(self) -> bool:
        """True once a first fix has been applied."""
        return self._pose is not None

    def correct(self, measured: Pose2, odom_at_frame: Pose2) -> None:
        """Blend in a trusted fix ``measured``, taken when odometry read ``odom_at_frame``.

        The first fix is taken as it is; later ones move the pose predicted at the
        frame's odometry by ``fix_gain`` times the difference (in that pose's frame).
        """
        self._trusted = self._counted = odom_at_frame
        self._driven = 0.0
        if self._pose is None:
            self._pose, self._anchor = measured, odom_at_frame
            return
        pred = self.predict(odom_at_frame)
        d = pred.between(measured)
        g = self.fix_gain
        self._pose = pred.compose(Pose2(g * d.x, g * d.z, g * d.theta))
        self._anchor = odom_at_frame

    def predict(self, odom: Pose2) -> Pose2:
        """The fused pose when odometry reads ``odom`` (the last anchor carried forward by odometry)."""
        if self._pose is None:
            raise RuntimeError("PoseFusion.predict before the first fix")
        return self._pose.compose(self._anchor.between(odom))

    def blind_distance(self, odom: Pose2) -> float:
        """Distance, m, driven on odometry alone since the last trusted fix's frame: along the path (the
        readings given here, every cycle), in steps of BLIND_STEP_M. The straight line let a robot go round
        a bend blind, or a full circle, with less or nothing counted."""
        if self._trusted is None:
            raise RuntimeError("PoseFusion.blind_distance before the first fix")
        step = math.hypot(odom.x - self._counted.x, odom.z - self._counted.z)
        if step < BLIND_STEP_M:
            return self._driven + step
        self._driven += step
        self._counted = odom
        return self._driven
