"""Each gain the controllers read from their configuration changes what they command (one cycle, no vision).

Repeat: a straight taught path of three keyframes along +z, the robot placed by one VBC fix.
Goto: one VSLAM fix near the goal. Safety: the held-stop release delay. Path follower: its keyword settings.
"""
from __future__ import annotations

import math
import re

import numpy as np
import pytest

from vbnav.control.config import Config, ConfigError, parse_config
from vbnav.control.config.vbc import VBCConfig
from vbnav.control.config.vslam import GotoConfig
from vbnav.control.controllers.goto import GotoController
from vbnav.control.controllers.manual import ScriptedController
from vbnav.control.controllers.path import PathFollower
from vbnav.control.controllers.repeat import RepeatController
from vbnav.control.route import Keyframe, Route
from vbnav.control.runtime.interfaces import ControlContext, Estimate, Twist
from vbnav.control.stages.vbc_fix import VBCFix
from vbnav.control.stages.vslam import VslamFix
from vbnav.drivers.wheels import WheelState
from vbnav.vision.geometry import CameraMount, Pose2
from runtime_helpers import make_runtime


def _ctx(odom: Pose2, kind: str, est, k: int = 0) -> ControlContext:
    return ControlContext(k * 10_000_000, 0.01, odom, WheelState(0, (0.0, 0.0), (0.0, 0.0)), {kind: est}, k)


# -------------------------------------------------------------------------------------------- repeat
def _straight_route() -> Route:
    empty = np.zeros(0)
    kfs = [Keyframe(i, np.zeros((1, 1), np.uint8), np.zeros((0, 2), np.float32), empty, empty,
                    np.zeros((0, 32), np.uint8), empty, empty, np.zeros(0, np.int64), Pose2(0.0, 0.5 * i, 0.0),
                    0.5 * i) for i in range(3)]
    return Route(None, "test", "now", None, CameraMount(), True, kfs)


def repeat_command(pose: Pose2, n_agree: int = 100, **settings):
    """The repeat controller's first command with the robot at ``pose`` (taught-odometry frame)."""
    ctl = RepeatController(_straight_route(), VBCConfig(**settings), max_linear_speed=0.5, max_angular_speed=1.5)
    est = Estimate(0, "vbc", True, VBCFix(0, pose, Pose2(), n_agree))
    return ctl.update(_ctx(Pose2(), "vbc", est))


def test_a_repeat_without_a_fix_stands_still_and_says_why():
    """Started away from the route, no keyframe matches: the robot waits, and the progress line says so."""
    from vbnav.control.session import repeat_status
    ctl = RepeatController(_straight_route(), VBCConfig(), max_linear_speed=0.5, max_angular_speed=1.5)
    failed = Estimate(0, "vbc", False, VBCFix(0, Pose2(), Pose2(), 2))       # the keyframe does not match
    assert ctl.update(_ctx(Pose2(), "vbc", failed)) == Twist(0.0, 0.0)
    text = repeat_status(ctl.status(), 0, 3)
    assert text.startswith("keyframe 1/3 (waiting for a first match with the route") and "facing along it" in text
    placed = Estimate(10_000_000, "vbc", True, VBCFix(0, Pose2(0.0, 0.2, 0.0), Pose2(), 100))
    ctl.update(_ctx(Pose2(), "vbc", placed, 1))
    assert repeat_status(ctl.status(), 0, 3) == "keyframe 1/3"                 # placed: no more waiting


def test_a_repeat_stopped_blind_says_why():
    """Fixes refused for longer than vbc.blind_distance_m: the robot stops, and the progress line says that
    it drove that far without a trusted fix and the last fix's reason (it read 'keyframe 1/3' alone)."""
    from vbnav.control.session import repeat_status
    cfg = VBCConfig()
    ctl = RepeatController(_straight_route(), cfg, max_linear_speed=0.5, max_angular_speed=1.5)
    ctl.update(_ctx(Pose2(), "vbc", Estimate(0, "vbc", True, VBCFix(0, Pose2(0.0, -0.4, 0.0), Pose2(), 100))))
    why = "repeat: fix 0.60 m / 1.0 deg from where odometry puts the robot (gate 0.15 m / 5.0 deg: vbc.fix_gate_m)"
    refused = Estimate(1, "vbc", False, VBCFix(0, Pose2(0.0, -0.05, 0.0), Pose2(0.0, 0.35, 0.0), 80),
                       {"reason": why})
    assert ctl.update(_ctx(Pose2(0.0, 0.35, 0.0), "vbc", refused, 1)) == Twist(0.0, 0.0)
    text = repeat_status(ctl.status(), 0, 3)
    assert ctl.status()["state"] == "blind", ctl.status()
    assert "0.35 m without a trusted camera fix (vbc.blind_distance_m 0.3)" in text and why in text, text

def test_repeat_approach_gain_and_floor():
    near = Pose2(0.0, 0.9, 0.0)                                   # 0.1 m before the last keyframe
    assert repeat_command(near).v == pytest.approx(1.5 * 0.1)
    assert repeat_command(near, approach_gain=1.0).v == pytest.approx(0.1)
    nearer = Pose2(0.0, 0.969, 0.0)                               # 3.1 cm left: 1.5/s asks for 4.65 cm/s
    assert repeat_command(nearer).v == pytest.approx(0.05)
    assert repeat_command(nearer, approach_min_speed=0.02).v == pytest.approx(1.5 * 0.031)


def test_repeat_turn_in_place_rate():
    sideways = Pose2(0.0, 0.2, math.radians(-90))                 # looking left, the path runs ahead (+z)
    tw = repeat_command(sideways)
    assert tw.v == 0.0 and tw.w == pytest.approx(0.6 * 1.5)       # turns right, on the spot
    assert repeat_command(sideways, turn_in_place_rate=0.8).w == pytest.approx(0.8 * 1.5)


def test_repeat_speed_factor_at_min_landmarks():
    start = Pose2(0.0, 0.1, 0.0)
    cfg = VBCConfig()
    assert repeat_command(start, n_agree=cfg.min_landmarks).v == pytest.approx(0.3 * cfg.cruise_speed)
    assert repeat_command(start, n_agree=cfg.min_landmarks,
                          min_landmarks_speed_factor=0.5).v == pytest.approx(0.5 * cfg.cruise_speed)
    mid = (cfg.min_landmarks + cfg.slow_landmarks) // 2               # linear up to 1 at slow_landmarks
    share = (mid - cfg.min_landmarks) / (cfg.slow_landmarks - cfg.min_landmarks)
    assert repeat_command(start, n_agree=mid).v == pytest.approx((0.3 + 0.7 * share) * cfg.cruise_speed)


def test_repeat_slows_to_the_blind_speed_once_the_last_fix_is_too_old():
    """A fix older than vbc.max_estimate_age_s is not used: the robot then drives on odometry alone, at
    blind_speed_factor, as with a failed fix. The old fix's landmark count kept it at full speed."""
    cfg = VBCConfig()
    ctl = RepeatController(_straight_route(), cfg, max_linear_speed=0.5, max_angular_speed=1.5)
    est = Estimate(0, "vbc", True, VBCFix(0, Pose2(0.0, 0.1, 0.0), Pose2(), 100))
    assert ctl.update(_ctx(Pose2(), "vbc", est)).v == pytest.approx(cfg.cruise_speed)      # fresh: full speed
    old = int(cfg.max_estimate_age_s * 100) + 1                                            # cycles of 10 ms
    v = ctl.update(_ctx(Pose2(0.0, 0.05, 0.0), "vbc", est, old)).v
    assert v == pytest.approx(cfg.blind_speed_factor * cfg.cruise_speed)
    assert ctl.status()["n_agree"] == 0

# ---------------------------------------------------------------------------------------------- goto
def goto_commands(fixes: list[Pose2], goal=Pose2(0.0, 3.0, 0.0), **settings):
    """One command per VSLAM fix (fix_gain 1: each fix is the pose), odometry standing still."""
    ctl = GotoController(goal, GotoConfig(**{"fix_gain": 1.0, **settings}), 0.5, 1.5)
    out = []
    for k, pose in enumerate(fixes):
        est = Estimate(k + 1, "vslam", True, VslamFix(pose, Pose2(), np.eye(4), 100, 0))
        out.append(ctl.update(_ctx(Pose2(), "vslam", est, k)))
    return out, ctl


def test_goto_min_drive_speed():
    near = Pose2(0.0, 2.95, 0.0)                                   # 5 cm short: k_rho asks for 3 cm/s
    assert goto_commands([near])[0][0].v == pytest.approx(0.04)
    assert goto_commands([near], min_drive_speed=0.02)[0][0].v == pytest.approx(0.6 * 0.05)


def test_goto_final_turn_gain_and_floor():
    off = Pose2(0.0, 3.0, math.radians(-10))                        # at the goal, 10 deg left of its heading
    tw = goto_commands([off])[0][0]
    assert tw.v == 0.0 and tw.w == pytest.approx(1.5 * math.radians(10))
    assert goto_commands([off], final_turn_gain=1.0)[0][0].w == pytest.approx(math.radians(10))
    slight = Pose2(0.0, 3.0, math.radians(1.5))                     # 1.5 deg right: turn left at the floor
    assert goto_commands([slight])[0][0].w == pytest.approx(-0.05)
    assert goto_commands([slight], final_turn_min_speed=0.01)[0][0].w == pytest.approx(-1.5 * math.radians(1.5))


def test_goto_redrive_factor():
    # Reached (turn/settle), then the estimate moves 1.5 tolerances away: within the default hysteresis
    # it stays put; with a factor of 1.2 it drives again.
    fixes = [Pose2(0.0, 2.995, 0.0), Pose2(0.0, 2.985, 0.0)]
    cmds, ctl = goto_commands(fixes)
    assert cmds[1].v == 0.0 and ctl.status()["state"] == "settle"
    cmds, ctl = goto_commands(fixes, redrive_factor=1.2)
    assert cmds[1].v > 0.0 and ctl.status()["state"] == "drive"


# -------------------------------------------------------------------------------------------- safety
def _release_after_resume(release_s: float) -> float:
    resume_at = 1_000_000_000 + 3_000_000_000
    cfg = Config(safety={"release_s": release_s})
    rt, drive, clock = make_runtime(ScriptedController([[0.3, 0.0, 6.0]]), cfg=cfg,
                                    cam_kw={"stop_at_ns": 1_000_000_000 + 1_000_000_000, "resume_at_ns": resume_at})
    result = rt.run()
    release = [e for e in result.events if e.kind == "release" and e.cause == "camera_stale"]
    assert len(release) == 1 and f"{release_s:g} s" in release[0].message
    return (release[0].stamp_ns - resume_at) * 1e-9


def test_safety_release_s_is_the_held_stop_debounce():
    assert _release_after_resume(1.0) - _release_after_resume(0.2) == pytest.approx(0.8, abs=0.011)


# --------------------------------------------------------------------------------------- path follower
def test_path_follower_settings():
    corner = np.array([[0.0, 0.0], [0.0, 0.05], [0.5, 0.05], [1.0, 0.05]])   # target well to the right

    def first_v(**kw):
        pf = PathFollower(corner, speed=0.4, lookahead=0.3, closed=False, **kw)
        return pf.update(_ctx(Pose2(), "none", None)).v

    assert first_v() == pytest.approx(0.4 * 0.3)
    assert first_v(min_speed_factor=0.5) == pytest.approx(0.4 * 0.5)
    line = np.array([[0.0, 0.0], [0.0, 0.5], [0.0, 1.0]])
    pf = PathFollower(line, speed=0.4, closed=False, finish_margin_m=0.6)
    pf.update(_ctx(Pose2(), "none", None))
    pf.update(_ctx(Pose2(0.0, 0.45, 0.0), "none", None))
    assert pf.finished                                              # 0.45 m of 1 m, less the 0.6 m margin
    with pytest.raises(ValueError, match="min_speed_factor"):
        PathFollower(line, min_speed_factor=0.0)


# ------------------------------------------------------------------------------------------ validation
@pytest.mark.parametrize("section,key,bad", [
    ("vbc", "turn_in_place_rate", 1.5), ("vbc", "approach_gain", 0.0), ("vbc", "approach_min_speed", -0.1),
    ("vbc", "min_landmarks_speed_factor", 0.0), ("vslam", "min_drive_speed", 0.0),
    ("vslam", "redrive_factor", 0.5), ("vslam", "final_turn_gain", 0.0), ("vslam", "final_turn_min_speed", 0.0),
    ("safety", "release_s", -1.0)])
def test_out_of_range_gains_are_configuration_errors(section, key, bad):
    data = {section: {"goto": {key: bad}} if section == "vslam" else {key: bad}}
    with pytest.raises(ConfigError, match=key):
        parse_config(data, "test.yaml")


@pytest.mark.parametrize("section, key", [({"vbc": {"cruise_speed": 0.25}}, "vbc.cruise_speed"),
                                          ({"vslam": {"goto": {"cruise_speed": 0.3}}}, "vslam.goto.cruise_speed")])
def test_a_cruise_speed_set_above_the_robots_limit_is_refused(section, key):
    """vbc.cruise_speed (the repeat) and vslam.goto.cruise_speed (goto) set above robot.max_linear_speed were
    accepted and cut to the limit without a word: the speed written was never driven. Refused, naming both;
    the defaults (not written) stay at most the robot's limit, as documented."""
    with pytest.raises(ConfigError, match=rf"{re.escape(key)} 0\.\d+ m/s is above robot\.max_linear_speed 0\.18"):
        parse_config({"robot": {"max_linear_speed": 0.18}, **section})
    cfg = parse_config({"robot": {"max_linear_speed": 0.18}})
    # the defaults are cut to 0.18 in the configuration itself: 'vbnav config show' prints the speed driven
    assert cfg.vbc.cruise_speed == 0.18 and cfg.vslam.goto.cruise_speed == 0.18


def test_slow_landmarks_below_min_landmarks_is_refused():
    """vbc.slow_landmarks below vbc.min_landmarks was accepted: the repeat then never slowed for a weak fix (full
    speed from slow_landmarks agreeing, min_landmarks_speed_factor never applied). Refused, naming both."""
    with pytest.raises(ConfigError, match=r"vbc: slow_landmarks 10 is below min_landmarks 12"):
        parse_config({"vbc": {"slow_landmarks": 10}})
    assert parse_config({"vbc": {"slow_landmarks": 12}}).vbc.slow_landmarks == 12
