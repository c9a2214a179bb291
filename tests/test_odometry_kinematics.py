"""Kinematics, limits and odometry against the simulated base's ground truth."""
import math

import numpy as np
import pytest

from vbnav.control.config import Config
from vbnav.control.runtime.interfaces import Twist
from vbnav.control.runtime.kinematics import DiffDriveKinematics, TwistLimiter
from vbnav.control.runtime.odometry import Odometry
from vbnav.drivers.clock import SimClock
from vbnav.drivers.sim.base import BaseParams, SimDiffDrive
from vbnav.vision.geometry import Pose2, arc_step


def test_kinematics_round_trip_and_turn_direction():
    k = DiffDriveKinematics(0.05, 0.3)
    left, right = k.wheels(Twist(0.4, 0.8))
    assert left > right  # positive w turns right (toward +x): the left wheel runs faster
    t = k.twist(left, right)
    assert t.v == pytest.approx(0.4) and t.w == pytest.approx(0.8)


def test_arc_step_matches_fine_euler_integration():
    pose = Pose2(0.3, -0.2, 0.7)
    ds, dth = 0.5, 1.1
    exact = arc_step(pose, ds, dth)
    x, z, th = pose.x, pose.z, pose.theta
    n = 200000
    for _ in range(n):
        x += ds / n * math.sin(th + 0.5 * dth / n)
        z += ds / n * math.cos(th + 0.5 * dth / n)
        th += dth / n
    assert exact.x == pytest.approx(x, abs=1e-9) and exact.z == pytest.approx(z, abs=1e-9)
    # Moving forward with heading 0 goes along +z; turning right (dth > 0) bends toward +x.
    p = arc_step(Pose2(), 1.0, 0.5)
    assert p.z > 0 and p.x > 0


def test_limits_hold():
    cfg = Config()
    lim = TwistLimiter.from_config(cfg.robot)
    r = cfg.robot
    dt = 0.01
    prev = Twist()
    rng = np.random.default_rng(3)
    for _ in range(2000):
        want = Twist(*rng.uniform(-3, 3, 2))
        got = lim.apply(want, dt)
        assert abs(got.v) <= r.max_linear_speed + 1e-12
        assert abs(got.w) <= r.max_angular_speed + 1e-12
        assert abs(got.v - prev.v) <= r.max_linear_accel * dt + 1e-12
        assert abs(got.w - prev.w) <= r.max_angular_accel * dt + 1e-12
        left, right = lim.kinematics.wheels(got)
        assert max(abs(left), abs(right)) <= r.max_wheel_speed + 1e-9
        prev = got
    # Wheel saturation keeps the curvature.
    lim2 = TwistLimiter(DiffDriveKinematics(0.05, 0.3), 10, 10, 1e9, 1e9, 5.0)
    out = lim2.apply(Twist(1.0, 2.0), 0.01)
    assert out.w / out.v == pytest.approx(2.0)
    # A non-finite command is no command: not the limit a clip would map it to (lim2 allows any acceleration).
    for bad in (Twist(float("nan"), 0.0), Twist(0.0, float("nan")), Twist(float("inf"), 0.0), Twist(0.2, -math.inf)):
        assert lim2.apply(bad, 0.01) == Twist(0.0, 0.0), bad


def _drive_figure_eight(slip_std: float, seed: int):
    params = BaseParams(slip_std=slip_std)
    clock = SimClock()
    drive = SimDiffDrive(params, clock, seed=seed)
    k = DiffDriveKinematics(params.wheel_radius, params.wheel_separation)
    odo = Odometry(params.wheel_radius, params.wheel_separation)
    drive.connect()
    drive.enable()
    period = 10_000_000
    v, w = 0.3, 0.6  # radius 0.5 m circles; a full circle takes 2*pi/0.6 s
    t_circle = 2 * math.pi / w
    n = int(2 * t_circle / 0.01)
    for i in range(n):
        ww = w if i * 0.01 < t_circle else -w
        odo.update(drive.read())
        drive.write(*k.wheels(Twist(v, ww)))
        clock.advance(period)
    drive.write(0, 0)
    for _ in range(50):
        clock.advance(period)
        odo.update(drive.read())
    return odo.pose, drive.true_pose, odo.distance


def test_odometry_matches_ground_truth_without_slip():
    est, true, dist = _drive_figure_eight(0.0, 1)
    assert dist > 5.0
    # Only encoder quantisation remains (4096 ticks/rev): sub-millimetre over 6 m.
    assert math.hypot(est.x - true.x, est.z - true.z) < 1e-3
    assert abs(est.theta - true.theta) < 1e-3
    # A figure-eight ends where it started.
    assert math.hypot(true.x, true.z) < 0.003  # measured 1.3 mm on 2026-11-30, bar 2x


def test_odometry_error_within_slip_noise():
    """Over many seeds the odometry error matches what the slip random walk predicts."""
    slip = 0.002
    errs = []
    for seed in range(8):
        est, true, dist = _drive_figure_eight(slip, seed)
        errs.append(math.hypot(est.x - true.x, est.z - true.z))
    # Per wheel: std slip*sqrt(d) ~ 5 mm over 6 m; heading std ~ sqrt(2)*that/L ~ 0.023 rad, whose
    # effect over the path is a few cm. Bound with margin, and check the noise is really there.
    assert max(errs) < 0.04  # measured 0.018 on 2026-11-30, bar 2x
    assert np.median(errs) > 0.006  # measured 0.012 on 2026-11-30: the noise is there, bar 1/2


def test_physics_starts_when_the_clock_does():
    """A drive built on a clock that reads hours of uptime must not integrate those hours first."""
    clock = SimClock(start_ns=10 ** 16)          # ~4 months of uptime in 1 ms physics steps if it did
    drive = SimDiffDrive(BaseParams(), clock)
    assert drive.true_pose == Pose2()
    assert drive.physics.time_ns == clock.now_ns()
