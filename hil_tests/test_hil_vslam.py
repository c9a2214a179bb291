"""The VSLAM in the real runtime on the simulated robot (issue 4, "Simulation" acceptance).

Simulated base and stereo camera on the simulated clock, the real loop, safety
monitor and vision pipeline. Ground truth comes from the simulator and is used
only to measure. Camera at 10 Hz and 320 x 240 (same field of view as
configs/sim_stereo.yaml) in the loop test to keep it short; goto runs the
shipped configuration unchanged.
"""
import math

import pytest

from vslam_eval import run_vslam_loop  # tests/vslam_eval.py

from vbnav.control.config import load_config
from vbnav.control.runtime.factory import make_robot
from vbnav.control.runtime.runtime import Runtime
from vbnav.control.controllers.goto import GotoController
from vbnav.control.stages.vslam import make_vslam_stage
from vbnav.vision.geometry import Pose2, wrap_angle


def test_loop_return_against_reference_set_beats_chaining_fivefold():
    r = run_vslam_loop()
    # The return: the last frame whose pose was computed against the first reference set (anchor 0).
    i = r.return_frame(0)
    e = r.errors_at(i)
    print(f"\n10 m loop ({r.distance_m:.1f} m driven, {len(r.stamps)} frames, {r.wall_s:.1f} s wall): "
          f"error at the return: VSLAM {e['vslam_m'] * 100:.2f} cm / {e['vslam_deg']:.2f} deg "
          f"(frame {e['frame']}, against anchor {e['anchor']}), chained frame-to-frame {e['chained_m'] * 100:.2f} cm / "
          f"{e['chained_deg']:.2f} deg, ratio {e['ratio']:.3f}; largest VSLAM error on the way "
          f"{r.max_vslam_error_m() * 100:.1f} cm; {r.stats}")
    assert r.reason == "finished"
    assert r.distance_m >= 9.5
    # measured 8.8 cm on 2026-11-30, bar 2x
    assert math.hypot(*r.truth[-1, :2]) < 0.18, "the robot did not come back to its start"
    assert r.vslam_ok.all() and r.stats["lost"] == 0 and r.chained_lost == 0
    assert r.stats["handoffs"] >= 4, "a loop that turns 360 degrees must hand off the reference frame"
    # Back at the start the pose is computed against the first reference set, not through the chain,
    # up to the end of the run.
    assert i >= len(r.stamps) - 3, (i, len(r.stamps))
    # measured 0.077 cm against chained 6.97 cm (ratio 0.011; the issue asked for 0.2) and 0.031 deg
    # on 2026-11-30, bars 2x; since the robot waits for the camera's first frame (30 ms of simulated vision
    # latency), 0.14 cm against 5.17 cm (ratio 0.027) and 0.066 deg: the frames sample the lap 30 ms later,
    # and millimetre errors move that much with it. Ratio bar 2x of that.
    assert e["vslam_m"] <= 0.055 * e["chained_m"], e
    assert e["vslam_deg"] <= 0.07


def _goto(goal: Pose2, cfg=None, covered=None):
    """Run goto on the shipped stereo configuration; ``covered`` = (from s, to s) covers the lens."""
    cfg = cfg or load_config("sim_stereo", overrides={"loop": {"max_missed_streak": 10 ** 6,
                                                                   "stall_periods": 10 ** 6}})
    stage = make_vslam_stage(cfg)
    robot = make_robot(cfg, [stage])        # at the configuration's sim.start_pose
    ctrl = GotoController(goal, cfg.vslam.goto, cfg.robot.max_linear_speed, cfg.robot.max_angular_speed)
    rt = Runtime(cfg, robot.drive, ctrl, robot.clock, robot.pipeline)
    if covered is not None:
        def cover(r, ctx, twist, wheels):
            robot.camera.occluded = covered[0] <= ctx.now_ns * 1e-9 < covered[1]
        rt.cycle_observers.append(cover)
    result = rt.run(60.0)
    true = robot.true_pose()
    return result, true, ctrl, stage


@pytest.mark.parametrize("goal", [(1.8, 2.4, 30.0), (-2.4, 1.8, -120.0)], ids=["ahead-right", "left-back"])
def test_goto_reaches_a_goal_3m_away(goal):
    g = Pose2(goal[0], goal[1], math.radians(goal[2]))
    assert math.hypot(g.x, g.z) == pytest.approx(3.0)
    result, true, ctrl, stage = _goto(g)
    pos_err = math.hypot(true.x - g.x, true.z - g.z)
    head_err = abs(math.degrees(wrap_angle(true.theta - g.theta)))
    print(f"\ngoto {goal}: {result.reason} after {result.cycles / 100:.1f} s; true error {pos_err * 100:.2f} cm, "
          f"{head_err:.2f} deg; {stage.stats}")
    assert result.reason == "finished", result.message
    assert pos_err <= 0.021     # measured 0.37-1.03 cm on 2026-11-30, bar 2x
    assert head_err <= 1.25     # measured 0.61-0.62 deg on 2026-11-30, bar 2x


def test_goto_rides_out_a_covered_lens():
    """1.5 s of black frames mid-way: the obstacle stage is blind and stops the robot at once; the black
    frames, identical while the wheels still move, are a frozen camera (camera_stale, and no stage takes
    them); the VSLAM, lost on the first ones, restarts from the stereo pair once the lens is clear; the
    goal is still reached."""
    g = Pose2(1.8, 2.4, 0.0)
    result, true, ctrl, stage = _goto(g, covered=(4.0, 5.5))
    pos_err = math.hypot(true.x - g.x, true.z - g.z)
    head_err = abs(math.degrees(wrap_angle(true.theta - g.theta)))
    print(f"\ngoto with a covered lens: {result.reason}; true error {pos_err * 100:.2f} cm, {head_err:.2f} deg; "
          f"{stage.stats}")
    assert stage.stats["lost"] >= 1 and stage.stats["restarts"] >= 1      # measured 3 and 1
    holds = {e.cause: e.message for e in result.events if e.kind == "hold"}
    assert "blind" in holds["obstacle"] and "frozen" in holds["camera_stale"], holds
    assert result.reason == "finished", result.message
    assert pos_err <= 0.0065 and head_err <= 1.0  # measured 0.45 cm / 0.55 deg on 2026-12-01 (0.32 / 0.47 on 11-30)


@pytest.mark.parametrize("goal", [(1.8, 2.4, 30.0), (-2.4, 1.8, -120.0)], ids=["ahead-right", "left-back"])
def test_goto_with_a_single_camera_scaled_by_the_wheels(goal):
    """vslam.metric_scale odometry: the robot creeps ahead until the two-view initialisation has 0.2 m of
    wheel-measured baseline, then drives to the goal on the monocular VSLAM, its scale pulled toward the
    wheels' at every hand-off. The position bar stays 5 cm: the wheel-scaled run ends 2.3-3.5 cm off."""
    g = Pose2(goal[0], goal[1], math.radians(goal[2]))
    cfg = load_config("sim_stereo", overrides={"loop": {"max_missed_streak": 10 ** 6, "stall_periods": 10 ** 6},
                                               "vslam": {"metric_scale": "odometry"}})
    result, true, ctrl, stage = _goto(g, cfg)
    pos_err = math.hypot(true.x - g.x, true.z - g.z)
    head_err = abs(math.degrees(wrap_angle(true.theta - g.theta)))
    print(f"\nmonocular goto {goal}: {result.reason}; true error {pos_err * 100:.2f} cm, {head_err:.2f} deg; "
          f"{stage.stats}")
    assert result.reason == "finished", result.message
    assert stage.baseline is None and stage.slam.baseline is None, "the stereo pair must not have been used"
    assert stage.stats["rescaled"] >= 2
    assert pos_err <= 0.05 and head_err <= 1.25  # measured 2.3-3.0 cm / 0.28-0.65 deg on 2026-12-01
