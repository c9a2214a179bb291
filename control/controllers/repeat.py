"""The repeat controller of teach-and-repeat by Vision-Based Control (chapter section 11.2.2.1).

``RepeatController`` (loop rate): dead-reckons from the latest fix with odometry,
follows the taught keyframe path with pure pursuit (a nonholonomic base corrects
lateral error through heading), slows and stops when too few landmarks agree,
resumes when they do, and finishes at the last keyframe.

Frames: a fix's pose is the robot relative to keyframe k. The path the
controller follows is the polyline of the keyframes' taught odometry poses;
the robot's pose on it is ``kf[k].odom * pose``, so only the *local* taught
geometry around keyframe k matters, never the accumulated odometry drift.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np
from vbnav.control.config import RobotConfig
from vbnav.control.config.vbc import VBCConfig
from vbnav.control.controllers.fusion import PoseFusion
from vbnav.control.route import Route
from vbnav.control.runtime.interfaces import (
    STOP,
    CommandOutcome,
    ControlContext,
    Controller,
    Estimate,
    Twist,
)
from vbnav.control.runtime.kinematics import keep_curvature, saturate
from vbnav.control.runtime.mailbox import OperatorCommand
from vbnav.control.stages.vbc_fix import VBCFix
from vbnav.vision.geometry import Pose2


# ---------------------------------------------------------------------------------------- controller
class RepeatController(Controller):
    """Pure pursuit along the taught keyframe path, localised by VBC fixes and odometry in between."""

    name = "repeat"
    requires = ("vbc",)

    def __init__(self, route: Route, cfg: VBCConfig | None = None, max_linear_speed: float | None = None,
                 max_angular_speed: float | None = None):
        """``max_linear_speed``, ``max_angular_speed``: the robot's limits (default: the robot section's)."""
        if route.repeat_refusal():
            raise ValueError(f"{route.path}: {route.repeat_refusal()}")
        self.cfg = cfg or VBCConfig()
        limits = RobotConfig()
        self.kfs = route.keyframes
        self.route_name = route.path.name if route.path is not None else None   # what `mode repeat` names
        self.path = np.array([[kf.odom.x, kf.odom.z] for kf in self.kfs])
        self.v_max = min(self.cfg.cruise_speed,
                         limits.max_linear_speed if max_linear_speed is None else max_linear_speed)
        self.w_max = limits.max_angular_speed if max_angular_speed is None else max_angular_speed
        self._k = 0
        self._fusion = PoseFusion(self.cfg.fix_gain)   # robot pose in the taught-odometry frame
        self._last_stamp: Optional[int] = None
        self._n_agree = 0
        self._blind = 0.0
        self._why = ""          # why the last estimate gave no trusted fix (the stage's reason)
        self._finished = False
        self._status: dict = {}

    @property
    def finished(self) -> bool:
        return self._finished

    def handle_command(self, cmd: OperatorCommand, now_ns: int) -> CommandOutcome:
        """``mode repeat`` naming another route is no 'unchanged': this run repeats its own route only."""
        name = self.route_name
        if cmd.kind == "mode" and len(cmd.args) > 1 and cmd.args[0] == self.name and name != cmd.args[1]:
            return CommandOutcome.refused(f"this run repeats route {name!r}; repeating {cmd.args[1]!r} needs a new "
                                          f"run (vbnav repeat --path ROUTE)")
        return super().handle_command(cmd, now_ns)

    def status(self) -> dict:
        return dict(self._status)

    def update(self, ctx: ControlContext) -> Twist:
        self._absorb(ctx.estimate("vbc", self.cfg.max_estimate_age_s))
        if not self._fusion.initialised or self._finished:
            self._status = {"state": "finished" if self._finished else "waiting", "keyframe": self._k}
            return STOP
        self._blind = self._fusion.blind_distance(ctx.odom)
        return self._pursue(self._fusion.predict(ctx.odom))

    def _absorb(self, est: Optional[Estimate]) -> None:
        if est is None:
            # None younger than vbc.max_estimate_age_s: on odometry alone, at the blind speed, as after a
            # failed fix (the old fix's landmark count kept the robot at full speed).
            self._n_agree = 0
            self._why = f"no camera fix newer than vbc.max_estimate_age_s {self.cfg.max_estimate_age_s:g} s"
            return
        if est.stamp_ns == self._last_stamp or not isinstance(est.value, VBCFix):
            return
        self._last_stamp = est.stamp_ns
        fix: VBCFix = est.value
        self._k = fix.keyframe
        self._n_agree = fix.n_agree if est.ok else 0
        if fix.finished:
            self._finished = True
        if not est.ok:
            self._why = est.info.get("reason", "") or "the camera fix was not trusted"
            return
        self._why = ""
        self._fusion.correct(self.kfs[fix.keyframe].odom.compose(fix.pose), fix.odom)

    def _pursue(self, P: Pose2) -> Twist:
        seg, s, lateral, remaining = self._project(P)
        target = self._point_ahead(seg, s, self.cfg.lookahead_m)
        rel = P.between(Pose2(target[0], target[1], 0.0))
        heading_err = math.atan2(rel.x, rel.z)
        c = self.cfg
        v = self.v_max * self._confidence()
        if remaining < c.goal_tolerance_m and seg == len(self.path) - 2:
            self._finished = True
            self._status = {"state": "finished", "keyframe": self._k}
            return STOP
        v = saturate(c.approach_gain * remaining, c.approach_min_speed, v) if v > 0 else 0.0
        if abs(heading_err) > math.radians(c.turn_in_place_deg) and v > 0:
            v, w = 0.0, math.copysign(c.turn_in_place_rate * self.w_max, heading_err)
        else:
            L2 = rel.x * rel.x + rel.z * rel.z
            kappa = 2.0 * rel.x / max(L2, 1e-6)        # pure pursuit: the arc through the target point
            arc = keep_curvature(Twist(v, v * kappa), self.w_max)
            v, w = arc.v, arc.w
        blind = self._blind >= c.blind_distance_m
        self._status = {"state": "blind" if blind else "driving" if v > 0 or w != 0 else "stopped",
                        "keyframe": self._k, "lateral_m": lateral, "heading_err_deg": math.degrees(heading_err),
                        "n_agree": self._n_agree, "blind_m": self._blind, "remaining_m": remaining}
        if blind:
            self._status["reason"] = (f"stopped: {self._blind:.2f} m without a trusted camera fix "
                                      f"(vbc.blind_distance_m {c.blind_distance_m:g}): {self._why}")
        return Twist(v, w)

    def _confidence(self) -> float:
        """Speed factor from the number of agreeing landmarks and the distance driven blind."""
        c = self.cfg
        if self._blind >= c.blind_distance_m:    # however good the last fix was: none came for this long
            return 0.0
        if self._n_agree >= c.slow_landmarks:
            return 1.0
        if self._n_agree >= c.min_landmarks:
            f = c.min_landmarks_speed_factor
            return f + (1.0 - f) * (self._n_agree - c.min_landmarks) / max(c.slow_landmarks - c.min_landmarks, 1)
        return c.blind_speed_factor

    def _project(self, P: Pose2):
        """Closest segment near the current keyframe: (segment, arclength on it, signed lateral, remaining)."""
        n = len(self.path)
        if n == 1:
            d = float(np.hypot(*(self.path[0] - [P.x, P.z])))
            return 0, 0.0, 0.0, d
        lo, hi = max(self._k - 2, 0), min(self._k + 1, n - 2)
        best = None
        for i in range(lo, hi + 1):
            a, b = self.path[i], self.path[i + 1]
            ab = b - a
            L = float(np.hypot(*ab)) or 1e-9
            t = float(np.clip(np.dot([P.x - a[0], P.z - a[1]], ab) / (L * L), 0.0, 1.0))
            q = a + t * ab
            d = float(np.hypot(P.x - q[0], P.z - q[1]))
            if best is None or d < best[0] - 1e-9:
                # lateral sign: positive when the robot is right of the path direction (toward +x of it)
                side = (ab[1] * (P.x - a[0]) - ab[0] * (P.z - a[1])) / L
                best = (d, i, t * L, side)
        _, seg, s, side = best
        seg_len = np.hypot(*np.diff(self.path, axis=0).T)
        remaining = float(seg_len[seg] - s + seg_len[seg + 1:].sum())
        return seg, s, side, remaining

    def _point_ahead(self, seg: int, s: float, dist: float) -> np.ndarray:
        n = len(self.path)
        if n == 1:
            return self.path[0]
        while True:
            a, b = self.path[seg], self.path[seg + 1]
            L = float(np.hypot(*(b - a)))
            if s + dist <= L or seg == n - 2:
                t = min((s + dist) / max(L, 1e-9), 1.0)
                return a + t * (b - a)
            dist -= L - s
            s = 0.0
            seg += 1
