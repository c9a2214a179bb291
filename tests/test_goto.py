"""Go-to on the simulated robot: rendered stereo camera, VSLAM pose, odometry with errors, 100 Hz control."""
from __future__ import annotations

import math

import numpy as np
import pytest

from vbnav.control.controller import ControlContext
from vbnav.control.goto import GotoConfig, GotoController, VslamStage, robot_pose_from_camera
from vbnav.drivers.clock import SimClock
from vbnav.drivers.sim_camera import SimCamera
from vbnav.drivers.sim_world import World
from vbnav.drivers.wheels import WheelState
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.geometry import CameraMount, Pose2, camera_pose, wrap_angle

CAM = PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5)
MOUNT = CameraMount(height=0.5, forward=0.1, pitch=math.radians(5))
DT = 0.01
FRAME_EVERY = 20  # 5 Hz camera


def test_robot_pose_from_camera_inverts_camera_pose():
    p = Pose2(1.2, -0.7, 0.9)
    R, t = camera_pose(p, MOUNT)
    W = np.eye(4)
    W[:3, :3], W[:3, 3] = R, t
    q = robot_pose_from_camera(W, MOUNT)
    assert (q.x, q.z, q.theta) == pytest.approx((p.x, p.z, p.theta), abs=1e-12)


def drive(pose, v, w, dt):
    return pose.compose(Pose2(0.0, v * dt, w * dt))


def test_goto_reaches_a_goal_3m_away():
    start = Pose2(-1.0, -2.0, 0.0)
    goal_rel = (1.2, 2.75, math.radians(40))  # |(1.2, 2.75)| = 3.0 m, in the start frame
    cam = SimCamera(World.room(seed=0), CAM, MOUNT, lambda: Pose2(), SimClock(), 5, noise_std=2.0,
                    stereo_baseline=0.12)
    stage = VslamStage(CAM, MOUNT, stereo_baseline=0.12)
    ctl = GotoController(GotoConfig(goal=goal_rel, max_linear_speed=0.4))
    true, odom = start, Pose2()
    est = None
    for step in range(int(40 / DT)):
        if step % FRAME_EVERY == 0:
            est = stage.process(cam.render_frame(true, stamp_ns=step, seq=step), odom)
        ctx = ControlContext(step, DT, odom, WheelState(step, (0.0, 0.0), (0.0, 0.0)), {"vslam": est}, step)
        cmd = ctl.update(ctx)
        if ctl.finished:
            break
        true = drive(true, cmd.v, cmd.w, DT)
        odom = drive(odom, cmd.v * 1.03, cmd.w * 0.97, DT)  # 3 % odometry errors
    assert ctl.finished
    reached = start.between(true)  # true pose in the start frame
    assert math.hypot(reached.x - goal_rel[0], reached.z - goal_rel[1]) < 0.05
    assert abs(math.degrees(wrap_angle(reached.theta - goal_rel[2]))) < 2.0
    # odometry alone would have missed: the VSLAM pose is what got it there
    odom_err = math.hypot(odom.x - reached.x, odom.z - reached.z)
    assert odom_err > 0.05


def test_vslam_section_is_validated_with_key_paths():
    from vbnav.control.config import ConfigError
    from vbnav.control.goto import vslam_config

    assert vslam_config({"min_landmarks": 100}).min_landmarks == 100
    with pytest.raises(ConfigError, match=r"robot.yaml.*vslam.min_landmark"):
        vslam_config({"min_landmark": 100}, "robot.yaml")
