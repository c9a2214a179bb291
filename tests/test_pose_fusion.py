"""The controllers' shared pose fusion (odometry between fixes, gain * innovation at the fix's frame) and
command saturation (angular limit keeping the arc; proportional command between a floor and a ceiling)."""
from __future__ import annotations

import math

import pytest

from vbnav.control.controllers.fusion import PoseFusion
from vbnav.control.runtime.interfaces import Twist
from vbnav.control.runtime.kinematics import keep_curvature, saturate
from vbnav.vision.geometry import Pose2


def close(a: Pose2, b: Pose2, tol=1e-12) -> bool:
    return abs(a.x - b.x) < tol and abs(a.z - b.z) < tol and abs(a.theta - b.theta) < tol


# ------------------------------------------------------------------------------------------- fusion
def test_first_fix_is_taken_whole_then_odometry_carries_it():
    f = PoseFusion(0.5)
    assert not f.initialised
    odom0 = Pose2(10.0, -3.0, 0.4)                 # odometry and fix frames are unrelated
    fix = Pose2(1.0, 2.0, math.pi / 2)
    f.correct(fix, odom0)
    assert f.initialised and close(f.predict(odom0), fix)
    # 1 m forward on odometry: in the fix frame, 1 m along the fused heading (pi/2: toward +x)
    moved = odom0.compose(Pose2(0.0, 1.0, 0.0))
    assert close(f.predict(moved), Pose2(2.0, 2.0, math.pi / 2))
    # a turn on the spot turns the fused pose by the same angle
    turned = moved.compose(Pose2(0.0, 0.0, -0.3))
    assert close(f.predict(turned), Pose2(2.0, 2.0, math.pi / 2 - 0.3))


@pytest.mark.parametrize("gain", [0.25, 0.5, 1.0])
def test_a_fix_moves_the_pose_at_its_frame_by_gain_times_the_innovation(gain):
    f = PoseFusion(gain)
    f.correct(Pose2(0.0, 0.0, 0.0), Pose2())
    frame_odom = Pose2(0.0, 1.0, 0.0)              # the frame was exposed here...
    now_odom = Pose2(0.5, 1.0, math.pi / 2)        # ...the fix arrives after a further turn and 0.5 m
    pred = f.predict(frame_odom)
    assert close(pred, Pose2(0.0, 1.0, 0.0))
    innovation = Pose2(0.04, -0.02, 0.01)          # the fix, in the predicted pose's frame (heading 0)
    f.correct(pred.compose(innovation), frame_odom)
    at_frame = f.predict(frame_odom)
    assert at_frame.x == pytest.approx(gain * 0.04, abs=1e-12)
    assert at_frame.z == pytest.approx(1.0 - gain * 0.02, abs=1e-12)
    assert at_frame.theta == pytest.approx(gain * 0.01, abs=1e-12)
    # now: the corrected frame pose carried forward by the odometry since the frame (not the fix applied now)
    assert close(f.predict(now_odom), at_frame.compose(frame_odom.between(now_odom)))


def test_gain_one_takes_each_fix_and_repeated_fixes_converge():
    f = PoseFusion(1.0)
    f.correct(Pose2(), Pose2())
    f.correct(Pose2(0.3, 0.2, 0.1), Pose2(0.0, 0.5, 0.0))
    assert close(f.predict(Pose2(0.0, 0.5, 0.0)), Pose2(0.3, 0.2, 0.1))
    half = PoseFusion(0.5)
    half.correct(Pose2(), Pose2())
    for _ in range(40):                            # the same fix again and again: the error halves each time
        half.correct(Pose2(0.3, 0.2, 0.1), Pose2())
    assert close(half.predict(Pose2()), Pose2(0.3, 0.2, 0.1), tol=1e-9)


def test_blind_distance_is_the_odometry_travel_since_the_last_trusted_fix():
    f = PoseFusion(0.5)
    f.correct(Pose2(5.0, 5.0, 1.0), Pose2(1.0, 1.0, 0.0))
    assert f.blind_distance(Pose2(1.0, 1.0, 2.0)) == 0.0          # turning on the spot is not travel
    assert f.blind_distance(Pose2(1.3, 1.4, 0.0)) == pytest.approx(0.5)
    f.correct(Pose2(5.0, 5.5, 1.0), Pose2(1.3, 1.4, 0.0))
    assert f.blind_distance(Pose2(1.3, 1.4, 0.0)) == 0.0
    assert f.blind_distance(Pose2(1.3, 1.1, 0.0)) == pytest.approx(0.3)


def test_blind_distance_along_a_curve_is_the_path_driven_not_the_chord():
    """vbc/goto.blind_distance_m is the distance driven on odometry alone: the straight line from the last
    fix let a robot driving blind round a tight bend (a U-turn of 0.1 m radius, 0.31 m of path) go on with
    0.2 m counted, and round a full circle with none. Read noise of a standing robot (1 mm back and forth)
    is no travel."""
    f = PoseFusion(0.5)
    f.correct(Pose2(), Pose2())
    r = 0.1
    for k in range(1, 201):                       # a full circle in 200 steps, one per control cycle
        a = math.pi * k / 100
        d = f.blind_distance(Pose2(r * (1 - math.cos(a)), r * math.sin(a), -a))
        if k == 100:
            assert d == pytest.approx(math.pi * r, rel=0.02)          # the U-turn: 0.31 m, not the chord 0.2
    assert d == pytest.approx(2 * math.pi * r, rel=0.02)              # back where it started: 0.63 m, not 0
    f.correct(Pose2(), Pose2())
    for k in range(1000):
        d = f.blind_distance(Pose2(0.001 * (k % 2), 0.0, 0.0))
    assert d < 0.01

def test_fusion_rejects_bad_gains_and_use_before_a_fix():
    for g in (0.0, -0.1, 1.5):
        with pytest.raises(ValueError, match="fix_gain"):
            PoseFusion(g)
    f = PoseFusion(0.5)
    with pytest.raises(RuntimeError):
        f.predict(Pose2())
    with pytest.raises(RuntimeError):
        f.blind_distance(Pose2())


# --------------------------------------------------------------------------------------- saturation
@pytest.mark.parametrize("v,w", [(0.3, 2.0), (0.3, -2.0), (-0.2, 3.0), (-0.2, -3.0), (0.0, 5.0)])
def test_keep_curvature_limits_w_and_keeps_sign_and_arc(v, w):
    out = keep_curvature(Twist(v, w), 1.5)
    assert abs(out.w) == 1.5
    assert math.copysign(1.0, out.w) == math.copysign(1.0, w)
    assert out.v == 0.0 if v == 0.0 else math.copysign(1.0, out.v) == math.copysign(1.0, v)
    assert out.v * w == pytest.approx(v * out.w, abs=1e-15)     # same curvature v/w
    assert abs(out.v) <= abs(v)


def test_keep_curvature_leaves_commands_within_the_limit_alone():
    for tw in (Twist(0.3, 1.5), Twist(0.3, -1.2), Twist(-0.1, 0.0)):
        assert keep_curvature(tw, 1.5) is tw


def test_saturate_holds_the_magnitude_between_floor_and_ceiling_and_keeps_the_sign():
    assert saturate(0.2, 0.05, 0.4) == 0.2
    assert saturate(-0.2, 0.05, 0.4) == -0.2
    assert saturate(0.01, 0.05, 0.4) == 0.05
    assert saturate(-0.01, 0.05, 0.4) == -0.05
    assert saturate(3.0, 0.05, 0.4) == 0.4
    assert saturate(-3.0, 0.05, 0.4) == -0.4
    assert saturate(0.0, 0.05, 0.4) == 0.05
    assert saturate(0.01, 0.05, 0.03) == 0.03       # the ceiling (a speed limit) wins over the floor
