"""The robot factory: the simulated start pose from the configuration."""
from __future__ import annotations

import math

import pytest

from vbnav.control.config import ConfigError, load_config
from vbnav.control.runtime.factory import make_robot, noise_seed
from vbnav.drivers.clock import SimClock
from vbnav.vision.geometry import Pose2


def test_the_simulated_robot_starts_at_sim_start_pose():
    cfg = load_config(None, overrides={"sim": {"start_pose": [1.5, -2.0, 90.0], "seed": 3}})
    robot = make_robot(cfg, with_camera=False, run=2)
    assert isinstance(robot.clock, SimClock) and robot.camera is None and robot.world is None
    assert robot.start == Pose2(1.5, -2.0, math.radians(90.0))
    assert robot.drive.true_pose == robot.start
    assert robot.true_pose().as_array() == pytest.approx([0.0, 0.0, 0.0], abs=1e-12)   # in the odometry frame
    assert noise_seed(cfg, 2) == 3002


@pytest.mark.parametrize("bad", [[0.0, 0.0], [0.0, float("nan"), 0.0]])
def test_sim_start_pose_is_validated(bad):
    with pytest.raises(ConfigError, match="sim.start_pose"):
        load_config(None, overrides={"sim": {"start_pose": bad}})
