"""The ``goto`` controller: drive to a planar goal in the VSLAM's reference frame (section 11.3)."""
from __future__ import annotations

import math
import threading
from typing import Optional

from vbnav.control.config import RobotConfig
from vbnav.control.config.vslam import GotoConfig
from vbnav.control.controllers.fusion import PoseFusion
from vbnav.control.runtime.interfaces import (
    STOP,
    ControlContext,
    Controller,
    Estimate,
    Twist,
)
from vbnav.control.runtime.kinematics import keep_curvature, saturate
from vbnav.control.stages.vslam import VslamFix
from vbnav.vision.geometry import Pose2, wrap_angle


#: A route's waypoint counts as passed this near (m); the planner's ``Approach`` allows for it.
WAYPOINT_TOLERANCE_M = 0.15


# ---------------------------------------------------------------------------------- controller
def polar_coordinates(pose: Pose2, goal: Pose2) -> tuple[float, float, float]:
    """(rho, alpha, beta) of Astolfi's go-to-pose law, in this package's conventions.

    rho: distance to the goal; alpha: bearing of the goal seen from the robot
    (positive to the robot's right, like theta); beta: the angle the goal heading
    still needs beyond that bearing, so that theta_goal - theta = alpha + beta.
    The law v = k_rho rho, w = k_alpha alpha + k_beta beta (k_rho > 0, k_beta < 0,
    k_alpha > k_rho) is locally exponentially stable (Siegwart & Nourbakhsh,
    "Introduction to Autonomous Mobile Robots", 3.6.2); with theta growing to the
    right the signs of alpha, beta and w all flip together, so the gains keep theirs.
    """
    dx, dz = goal.x - pose.x, goal.z - pose.z
    rho = math.hypot(dx, dz)
    alpha = wrap_angle(math.atan2(dx, dz) - pose.theta)
    beta = wrap_angle(goal.theta - pose.theta - alpha)
    return rho, alpha, beta



class GotoController(Controller):
    """Drive to a goal pose in the reference frame, localised by the VSLAM and odometry in between.

    Phases: "drive" (the polar law, forward only: a goal behind turns the robot on
    the spot first, so the camera looks where the robot goes), "turn" (on the spot
    to the goal heading once within the position tolerance), "settle" (stopped,
    within both tolerances, for ``settle_s``), then finished.
    """

    name = "goto"
    requires = ("vslam",)

    def __init__(self, goal: Pose2, cfg: GotoConfig | None = None, max_linear_speed: float | None = None,
                 max_angular_speed: float | None = None, waypoints: Optional[list] = None,
                 waypoint_tolerance_m: float = WAYPOINT_TOLERANCE_M, follow_route: bool = False):
        """``max_linear_speed``, ``max_angular_speed``: the robot's limits (default: the robot section's).

        waypoints: (x, z) points in the reference frame to pass on the way to ``goal`` (a path planned on the
        line map's grid, vision/nav_grid.py); each counts as passed within ``waypoint_tolerance_m``.
        follow_route: the route was planned around obstacles (``goto --map``): each leg is driven straight
        to its waypoint (turning on the spot toward it first when it lies off to the side) and the goal
        heading is taken by turning on the spot at the goal. The polar law's heading term would swing the
        robot off the planned leg to arrive along the waypoint's or the goal's heading, where the planner
        never checked the clearance: on seeds 5 and 7 of the room that swing turned the robot's nose to a
        box 0.55 m beyond the goal, inside the obstacle stop's 0.8 m zone, and the stop held it 0.3-0.6 m
        short until the time ran out (benchmarks/goto_replan.py --seed). And while the obstacle stop holds
        the travel (letting a turn on the spot through), the two terms can cancel with the robot facing the
        obstacle: seed 5 from (-0.9, -1.5), re-planned past box_a's corner with the next waypoint 49.5 deg to
        the robot's left and that waypoint's heading 178 deg from the robot's, w = 1.8 x 0.864 - 0.5 x 3.10
        rad/s ~ 0, and the robot stood still, held, for the rest of the run.
        """
        self.follow_route = bool(follow_route)
        self.final_goal = goal
        self.waypoints = [tuple(w) for w in (waypoints or [])]
        self.waypoint_tolerance_m = float(waypoint_tolerance_m)
        self.goal = self._next_target(goal)
        self.cfg = cfg or GotoConfig()
        limits = RobotConfig()
        self.v_max = min(self.cfg.cruise_speed,
                         limits.max_linear_speed if max_linear_speed is None else max_linear_speed)
        self.w_max = limits.max_angular_speed if max_angular_speed is None else max_angular_speed
        self._fusion = PoseFusion(self.cfg.fix_gain)   # robot pose in the reference frame
        self._last_stamp: Optional[int] = None
        self._phase = "waiting"
        self._creep_from: Optional[Pose2] = None  # odometry where a monocular VSLAM started initialising
        self._settled_ns: Optional[int] = None
        self._finished = False
        self._status: dict = {"state": "waiting"}
        self._new_route: Optional[list] = None  # posted by the re-planner's thread, taken by update()
        self._route_lock = threading.Lock()     # held for an assignment only: the loop never waits on planning
        self.route_changes = 0
        self._held: Optional[str] = None

    @property
    def finished(self) -> bool:
        return self._finished

    @property
    def pose(self) -> Optional[Pose2]:
        """The fused pose estimate at the last update (None before the first VSLAM pose)."""
        return self._status.get("_pose")

    def status(self) -> dict:
        return {k: v for k, v in self._status.items() if not k.startswith("_")}

    def route(self) -> list[tuple[float, float]]:
        """The waypoints still ahead and the goal, (x, z) in the reference frame (a re-planner's pending
        route if one was posted and not yet taken)."""
        with self._route_lock:
            pending = self._new_route
            if pending is None:
                return list(self.waypoints) + [(self.final_goal.x, self.final_goal.z)]
        route, goal = pending
        return list(route) + [goal if goal is not None else (self.final_goal.x, self.final_goal.z)]

    def replace_route(self, waypoints: list, goal_xz=None) -> None:
        """New waypoints (x, z) in the reference frame to the same goal, e.g. a path re-planned around what
        the map now holds; with ``goal_xz`` to that position instead (the goal heading kept: the re-planner's
        nearest free point to a goal the map's noise put in the planner's margin). Safe to call from another
        thread: the control loop takes them at its next update."""
        route = [tuple(map(float, w)) for w in waypoints]
        goal = None if goal_xz is None else tuple(map(float, goal_xz))
        with self._route_lock:
            self._new_route = (route, goal)

    def hold(self, reason: Optional[str]) -> None:
        """Stop and stay stopped while ``reason`` (e.g. "no path": the grown map closed the way to the goal);
        ``None`` drives on. Safe to call from another thread."""
        self._held = reason

    def _take_new_route(self) -> None:
        with self._route_lock:
            pending, self._new_route = self._new_route, None
        if pending is None:
            return
        self.waypoints, goal = pending
        moved = goal is not None and goal != (self.final_goal.x, self.final_goal.z)
        if moved:
            self.final_goal = Pose2(goal[0], goal[1], self.final_goal.theta)
        self.goal = self._next_target(self.final_goal)
        self.route_changes += 1
        if (self.waypoints or moved) and self._phase in ("turn", "settle"):
            self._phase, self._settled_ns = "drive", None

    def update(self, ctx: ControlContext) -> Twist:
        if self._new_route is not None:
            self._take_new_route()
        self._absorb(ctx.estimate("vslam", self.cfg.max_estimate_age_s), ctx.odom)
        if self._creep_from is not None and not self._finished:
            # A monocular VSLAM needs parallax before its first pose (at the start or after it was lost and
            # restarted): creep straight ahead, not farther than blind_distance_m.
            crept = math.hypot(ctx.odom.x - self._creep_from.x, ctx.odom.z - self._creep_from.z)
            self._status = {"state": "initialising", "crept_m": crept}
            return Twist(self.cfg.init_creep_speed, 0.0) if crept <= self.cfg.blind_distance_m else STOP
        if not self._fusion.initialised or self._finished:
            return STOP
        if self._held is not None:
            self._status = {**self._status, "state": "held", "held": self._held}
            return STOP
        P = self._fusion.predict(ctx.odom)
        blind = self._fusion.blind_distance(ctx.odom)
        if self.waypoints and math.hypot(P.x - self.goal.x, P.z - self.goal.z) <= self.waypoint_tolerance_m:
            self.waypoints.pop(0)                   # passed: head for the next one (or the goal)
            self.goal = self._next_target(self.final_goal)
        rho, alpha, beta = polar_coordinates(P, self.goal)
        dth = wrap_angle(self.goal.theta - P.theta)
        twist = self._law(ctx.now_ns, rho, alpha, beta, dth) if blind <= self.cfg.blind_distance_m else STOP
        self._status = {"state": self._phase if blind <= self.cfg.blind_distance_m else "blind",
                        "distance_m": rho, "heading_error_deg": math.degrees(dth), "blind_m": blind,
                        "x": P.x, "z": P.z, "theta_deg": math.degrees(P.theta), "_pose": P}
        return twist

    def _next_target(self, goal: Pose2) -> Pose2:
        """The next waypoint (heading: toward the one after it) or the goal itself."""
        if not self.waypoints:
            return goal
        x, z = self.waypoints[0]
        nx, nz = self.waypoints[1] if len(self.waypoints) > 1 else (goal.x, goal.z)
        return Pose2(x, z, math.atan2(nx - x, nz - z))

    def _law(self, now_ns: int, rho: float, alpha: float, beta: float, dth: float) -> Twist:
        c = self.cfg
        tol_th = math.radians(c.heading_tolerance_deg)
        if self.waypoints:                           # on the way: drive only, no final turn
            self._phase = "drive"
        elif self._phase in ("waiting", "drive") and rho <= c.position_tolerance_m:
            self._phase = "turn"
        elif self._phase in ("turn", "settle") and rho > c.redrive_factor * c.position_tolerance_m:
            self._phase, self._settled_ns = "drive", None   # pushed away (or a corrected estimate): drive again
        elif self._phase == "waiting":
            self._phase = "drive"
        if self._phase == "drive":
            # Speed proportional to the distance (slows near the goal), with a floor so the last
            # centimetres do not take forever; zero while the goal is off to the side.
            v = saturate(c.k_rho * rho, c.min_drive_speed, self.v_max) * max(math.cos(alpha), 0.0)
            fade = min(1.0, rho / c.approach_radius_m)      # beta is ill-defined at the goal itself
            if self.follow_route:
                fade = 0.0                                  # the planned legs, then the turn on the spot
            w = c.k_alpha * alpha + c.k_beta * beta * fade
            return keep_curvature(Twist(v, w), self.w_max)
        if abs(dth) > tol_th:
            self._phase, self._settled_ns = "turn", None
            return Twist(0.0, saturate(c.final_turn_gain * dth, c.final_turn_min_speed, c.final_turn_speed))
        if self._phase != "settle":
            self._phase, self._settled_ns = "settle", now_ns
        if (now_ns - self._settled_ns) * 1e-9 >= c.settle_s:
            self._finished = True
            self._phase = "finished"
        return STOP

    def _absorb(self, est: Optional[Estimate], odom: Pose2) -> None:
        if est is None or est.stamp_ns == self._last_stamp or not isinstance(est.value, VslamFix):
            return
        self._last_stamp = est.stamp_ns
        if not est.ok:
            if self._creep_from is None and est.value.quality.get("initialising"):
                self._creep_from = odom
            return
        self._creep_from = None
        fix: VslamFix = est.value
        self._fusion.correct(fix.pose, fix.odom)
