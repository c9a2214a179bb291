"""Go to a goal pose given in the VSLAM reference frame (the chapter's VBC for large displacements).

``VslamStage`` runs the VSLAM front end on the vision thread and publishes the
robot's planar pose in the frame of the robot at initialisation (the first
reference frame), together with the odometry pose at the frame's time.
``GotoController`` runs at the loop rate: it carries the last VSLAM pose
forward with the odometry accumulated since that frame, drives towards the
goal position (heading on the bearing, speed shrinking with distance and with
heading error), then turns in place to the goal heading, and finishes inside
the tolerances.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from vbnav.control.config import ConfigError, _format_errors
from vbnav.control.controller import ControlContext, Controller, Estimate, Twist, VisionStage
from vbnav.drivers.camera import Frame
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.geometry import CameraMount, Pose2, camera_pose, wrap_angle
from vbnav.vision.vslam import Vslam, VslamConfig


class GotoConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    goal: tuple[float, float, float] = Field(..., description="goal (x, z, theta) in m, m, rad, in the frame of "
                                                              "the robot when the VSLAM started")
    position_tolerance: float = Field(0.05, gt=0, description="m")
    heading_tolerance_deg: float = Field(2.0, gt=0)
    max_linear_speed: float = Field(0.3, gt=0, description="m/s")
    max_angular_speed: float = Field(1.0, gt=0, description="rad/s")
    k_distance: float = Field(0.8, gt=0, description="1/s: forward speed per metre to go")
    k_bearing: float = Field(2.0, gt=0, description="1/s: turn rate per radian of bearing error")
    k_heading: float = Field(1.5, gt=0, description="1/s: turn rate per radian of final heading error")
    estimate_max_age_s: float = Field(1.0, gt=0, description="older VSLAM poses stop the robot")


def vslam_config(section: dict | None, source: str = "<config>") -> VslamConfig:
    """Validate the free ``vslam:`` configuration section; errors name the file and key path."""
    try:
        return VslamConfig.model_validate(section or {})
    except ValidationError as exc:
        raise ConfigError(_format_errors(source, exc, prefix="vslam")) from None


@dataclass
class VslamFix:
    """The robot's pose from the VSLAM at a frame, and the odometry pose at the same time."""

    pose: Pose2
    odom: Pose2
    pose_wc: np.ndarray  # camera-to-world (world: robot frame at initialisation)


def robot_pose_from_camera(W: np.ndarray, mount: CameraMount) -> Pose2:
    """Planar robot pose from a world-from-camera matrix (inverse of ``camera_pose``)."""
    R_wr = W[:3, :3] @ mount.rotation().T
    t = W[:3, 3] - R_wr @ mount.translation()
    fwd = R_wr[:, 2]
    return Pose2(float(t[0]), float(t[2]), math.atan2(fwd[0], fwd[2]))


class VslamStage(VisionStage):
    """VSLAM on the vision thread: stereo frames (``Frame.right``) or depth (``meta['depth']``) start it."""

    kind = "vslam"

    def __init__(self, camera: PinholeCamera, mount: CameraMount, config: Optional[VslamConfig] = None,
                 stereo_baseline: Optional[float] = None):
        self.camera = camera
        self.mount = mount
        self.slam = Vslam(camera, config, stereo_baseline)
        R, t = camera_pose(Pose2(), mount)
        self.W0 = np.eye(4)
        self.W0[:3, :3], self.W0[:3, 3] = R, t  # world = robot frame at initialisation

    def process(self, frame: Frame, odom: Pose2) -> Optional[Estimate]:
        depth = frame.meta.get("depth") if frame.meta else None
        if not self.slam.initialised:
            if frame.right is not None and self.slam.baseline is not None:
                self.slam.initialise_stereo(frame.image, frame.right)
            elif depth is not None:
                self.slam.initialise_depth(frame.image, depth)
            else:
                return Estimate(frame.stamp_ns, self.kind, False, None, {"reason": "needs stereo or depth to start"})
            self.odom0 = odom
            W = self.W0 @ self.slam.pose_wc
            return Estimate(frame.stamp_ns, self.kind, True, VslamFix(robot_pose_from_camera(W, self.mount),
                                                                      odom, W), {"initialised": True})
        r = self.slam.process(frame.image, frame.right, depth)
        W = self.W0 @ r.pose_wc
        info = {"tracked": r.tracked, "inliers": r.inliers, "iterations": r.iterations,
                "residual_px": r.residual_px, "reference": r.reference}
        return Estimate(frame.stamp_ns, self.kind, r.ok, VslamFix(robot_pose_from_camera(W, self.mount), odom, W)
                        if r.ok else None, info)


class GotoController(Controller):
    name = "goto"
    requires = ("vslam",)

    def __init__(self, config: GotoConfig):
        self.cfg = config
        self.goal = Pose2(*config.goal)
        self._done = False
        self._turning = False
        self.pose: Optional[Pose2] = None

    @property
    def finished(self) -> bool:
        return self._done

    def current_pose(self, ctx: ControlContext) -> Optional[Pose2]:
        est = ctx.estimate("vslam", self.cfg.estimate_max_age_s)
        if est is None or not est.ok or est.value is None:
            return None
        fix: VslamFix = est.value
        return fix.pose.compose(fix.odom.between(ctx.odom))  # carried forward by odometry since the frame

    def update(self, ctx: ControlContext) -> Twist:
        pose = self.current_pose(ctx)
        self.pose = pose
        if pose is None or self._done:
            return Twist(0.0, 0.0)
        c = self.cfg
        dx, dz = self.goal.x - pose.x, self.goal.z - pose.z
        rho = math.hypot(dx, dz)
        heading_err = wrap_angle(self.goal.theta - pose.theta)
        if rho < c.position_tolerance * 0.6:
            self._turning = True
        elif rho > c.position_tolerance:
            self._turning = False
        if self._turning:
            if abs(heading_err) < math.radians(c.heading_tolerance_deg) * 0.5:
                self._done = True
                return Twist(0.0, 0.0)
            w = float(np.clip(c.k_heading * heading_err, -c.max_angular_speed, c.max_angular_speed))
            # minimum turn rate so the last fraction of a degree does not take forever
            if abs(w) < 0.05:
                w = math.copysign(0.05, heading_err)
            return Twist(0.0, w)
        bearing = wrap_angle(math.atan2(dx, dz) - pose.theta)
        v = min(c.max_linear_speed, c.k_distance * rho) * max(0.0, math.cos(bearing)) ** 2
        w = float(np.clip(c.k_bearing * bearing, -c.max_angular_speed, c.max_angular_speed))
        return Twist(v, w)

    def status(self) -> dict:
        p = self.pose
        return {"goal": list(self.cfg.goal), "pose": None if p is None else [p.x, p.z, p.theta],
                "turning": self._turning, "done": self._done}
