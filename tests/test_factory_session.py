"""The robot factory and the teach/repeat session: start pose from the configuration, one run per robot."""
from __future__ import annotations

import re
import math

import pytest

from vbnav.control.config import ConfigError, load_config
from vbnav.control.controllers.manual import IdleController
from vbnav.control.runtime.factory import make_robot, noise_seed
from vbnav.control.session import Session, teach_driver
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


def test_the_scripted_teacher_never_drives_a_real_drive():
    with pytest.raises(ConfigError, match="controller.teach"):
        load_config("sentry-dynamixel", overrides={"controller": {"teach": "room_loop"}})
    assert type(teach_driver(load_config("sentry-dynamixel"))).__name__ == "TeleopController"
    assert type(teach_driver(load_config(None))).__name__ == "PathFollower"


@pytest.mark.parametrize("world", ["corridor", "corridor_step"])
def test_the_room_loop_is_driven_in_a_room_only(tmp_path, capsys, world):
    """controller.teach room_loop (and vbnav demo) drive the simulated room's 7 m x 4 m loop: with sim.world a
    3 m wide corridor it was accepted and the robot taught a loop through the corridor's walls. Both are refused,
    naming sim.world; the room without boxes has the same walls and is taken."""
    from vbnav.control.cli import main
    with pytest.raises(ConfigError, match=rf"controller.teach 'room_loop'.*sim.world {world!r}"):
        load_config(None, overrides={"controller": {"teach": "room_loop"}, "sim": {"world": world}})
    load_config(None, overrides={"controller": {"teach": "room_loop"}, "sim": {"world": "empty_room"}})
    cfg = tmp_path / "corridor.yaml"
    cfg.write_text(f"controller:\n  teach: teleop\nsim:\n  world: {world}\n")
    assert main(["demo", "-c", str(cfg), "--out", str(tmp_path / "demo")]) == 2
    assert f"sim.world {world!r}" in capsys.readouterr().err
    assert not (tmp_path / "demo").exists()


def test_teleop_teaching_on_the_simulated_clock_is_refused(tmp_path, capsys):
    from vbnav.control.cli import main
    cfg = tmp_path / "teleop.yaml"
    cfg.write_text("controller:\n  teach: teleop\n")
    assert main(["teach", "-c", str(cfg), "--out", str(tmp_path / "route")]) == 2
    assert "simulated clock" in capsys.readouterr().out
    assert not (tmp_path / "route").exists()


def test_a_session_runs_once_and_needs_the_camera(tmp_path):
    cfg = load_config(None)
    with pytest.raises(ValueError, match="camera"):
        Session(cfg, make_robot(cfg, with_camera=False))
    session = Session(cfg, make_robot(cfg, with_camera=True))
    result = session.teach(IdleController(), tmp_path / "route", duration_s=0.5)
    assert result.reason == "duration" and result.keyframes == len(result.keyframe_stamps)
    assert (tmp_path / "route" / "manifest.json").exists()
    # the robot stood still: no second keyframe at the same place (the route would not load with it)
    from vbnav.control.route import load_route
    assert len(load_route(tmp_path / "route").keyframes) == result.keyframes == 1
    with pytest.raises(RuntimeError, match="one run"):
        session.teach(IdleController(), tmp_path / "again")
    assert not (tmp_path / "again").exists()


def test_a_second_ctrl_c_while_the_taught_route_is_closed_does_not_cut_it_short(tmp_path, monkeypatch, capsys):
    """The run ends (the first Ctrl-C, here its duration); a second Ctrl-C while the route is closed (the last
    keyframes written, the manifest marked complete) raised KeyboardInterrupt there: the route stayed
    incomplete without its last keyframe. It is held, as while the recording is closed."""
    import os
    import signal
    from vbnav.control.route import load_route
    from vbnav.control.stages.teach import TeachStage
    finish = TeachStage.finish

    def interrupted(self):
        os.kill(os.getpid(), signal.SIGINT)
        return finish(self)
    monkeypatch.setattr(TeachStage, "finish", interrupted)
    cfg = load_config(None)
    result = Session(cfg, make_robot(cfg, with_camera=True)).teach(teach_driver(cfg), tmp_path / "route",
                                                                   duration_s=2.0)
    assert result.complete and result.keyframes >= 2, result
    assert "SIGINT: the robot is stopped" in capsys.readouterr().err
    route = load_route(tmp_path / "route")
    assert route.complete and len(route.keyframes) == result.keyframes

def test_a_teach_ended_by_a_fault_keeps_the_keyframes_it_has_taken(tmp_path):
    """A teach that ends on a fault (a camera unplugged, a drive fault; here the driver's bug) closes its route
    incomplete. The keyframe being pooled (it is written when the next one starts) and the one at the last
    frame were dropped: up to vbc.keyframe_distance_m of the route taught was lost. They are written, the
    route stays marked incomplete."""
    from vbnav.control.route import load_route
    from vbnav.drivers.camera import CameraError
    cfg = load_config(None)
    driver = teach_driver(cfg)
    update = driver.update

    def failing(ctx):
        if ctx.odom.z > 1.0:
            raise CameraError("sim: unplugged")
        return update(ctx)
    driver.update = failing
    result = Session(cfg, make_robot(cfg, with_camera=True)).teach(driver, tmp_path / "route", duration_s=10.0)
    assert result.reason == "camera" and not result.complete, result
    route = load_route(tmp_path / "route")
    assert not route.complete and len(route.keyframes) == result.keyframes >= 3
    assert route.keyframes[-1].odom.z > 0.95, [kf.odom for kf in route.keyframes]   # where the fault came


def test_last_keyframes_that_cannot_be_written_after_a_fault_are_said(tmp_path):
    """Closing an interrupted teach writes its last keyframes; when that fails too, the route is closed
    incomplete all the same and the teach's note says what was not written (complete, it raises)."""
    import numpy as np
    from vbnav.control.route import Keyframe, RouteError
    from vbnav.control.session import Teaching
    from vbnav.vision.geometry import Pose2
    cfg = load_config(None)
    empty = np.zeros(0)
    bad = Keyframe(0, np.zeros((480, 640), np.uint8), np.zeros((0, 2), np.float32), empty, empty,
                   np.zeros((0, 32), np.uint8), empty, empty, np.zeros(0, np.int64), Pose2(), float("nan"))
    for complete in (False, True):
        teaching = Teaching(cfg, tmp_path / f"route{complete}")
        teaching.stage._ready.append(bad)
        if complete:
            with pytest.raises(RouteError, match="distance"):
                teaching.close(complete=True)
        else:
            assert teaching.close(complete=False) is False
            assert "the last keyframes could not be written (RouteError" in teaching.unwritten

def test_a_simulated_camera_on_a_real_drive_is_a_config_error_naming_the_file(tmp_path, capsys):
    """It renders from the simulated robot's pose: on a real drive it cannot work, and that is the
    configuration's fault (exit 2, the file named), not a traceback."""
    from vbnav.control.cli import main
    cfg = tmp_path / "real.yaml"
    cfg.write_text("drive:\n  driver: dynamixel\n  options: {port: /dev/ttyNOPE}\n")   # camera: the default, sim
    assert main(["teach", "-c", str(cfg), "--out", str(tmp_path / "r"), "--duration", "1"]) == 2
    err = capsys.readouterr().err
    assert str(cfg) in err and "camera.driver 'sim' needs drive.driver 'sim'" in err and "'dynamixel'" in err


@pytest.mark.parametrize("drive, says, fits", [
    ({"driver": "dynamixel", "options": {"port": "/dev/ttyNOPE", "velocity_limit_rad_s": 6.0}},
     r"drive.options.velocity_limit_rad_s \(6\.000 rad/s", {"velocity_limit_rad_s": 12.0}),
    ({"driver": "odrive", "options": {"port": "/dev/ttyNOPE", "vel_limit_turns_s": 2.0, "gear_ratio": 2.0}},
     r"drive.options.vel_limit_turns_s / gear_ratio \(6\.283 rad/s", {"gear_ratio": 1.0}),
])
def test_a_drive_limit_below_robot_max_wheel_speed_is_refused(drive, says, fits):
    """robot.max_wheel_speed is the limit the kinematics scale both wheels within (keeping the curvature); a
    serial drive clips each wheel on its own at its limit (Dynamixel Velocity Limit, ODrive vel_limit). With
    the drive's limit below it (the defaults: 20 rad/s, a Dynamixel's 6), the robot section's limit was
    accepted and the drive clipped the faster wheel, bending the path. make_robot refuses it, naming both."""
    from vbnav.control.runtime.factory import make_robot
    robot = {"max_wheel_speed": 10.0, "max_linear_speed": 0.3}
    teleop = {"teach": "teleop"}
    cfg = load_config(None, overrides={"robot": robot, "drive": drive, "controller": teleop})
    with pytest.raises(ConfigError, match=r"robot.max_wheel_speed 10 rad/s.*" + says):
        make_robot(cfg, with_camera=False)
    fitting = {**drive, "options": {**drive["options"], **fits}}
    built = make_robot(load_config(None, overrides={"robot": robot, "drive": fitting, "controller": teleop}),
                       with_camera=False)
    built.drive.close()


def test_a_vision_thread_still_inside_a_frame_never_writes_the_route_beside_the_close(tmp_path):
    """A frame that takes longer than the pipeline's stop waits (a slow fsync on an SD card): the teach's close
    waits for the vision thread, and while it still runs leaves the route as written (incomplete) instead of
    finishing it from a second thread; once the thread has ended, the close finishes the route."""
    import threading
    import json
    from vbnav.control.route import MANIFEST
    from vbnav.control.runtime.pipeline import VisionPipeline
    from vbnav.control.session import Teaching
    from tests.runtime_helpers import TickCamera
    entered, release = threading.Event(), threading.Event()

    class Slow:      # a stage whose frame lasts until the test releases it
        kind = "slow"

        def process(self, frame, odom):
            entered.set()
            release.wait(60)

    clock = SimClock()
    pipeline = VisionPipeline(TickCamera(clock), [Slow()], clock, inline=False)
    teaching = Teaching(load_config(None), tmp_path / "route")
    teaching.vision_wait_s = 0.01
    finished = []
    teaching.stage.finish = lambda: finished.append(True)
    pipeline.start()
    try:
        assert entered.wait(60)
        assert pipeline.stop(timeout_s=0.01) is False and pipeline.still_running
        assert teaching.close(complete=True, vision=pipeline) is False
        assert finished == [] and "the vision thread was still inside a frame" in teaching.note
        assert json.loads((tmp_path / "route" / MANIFEST).read_text())["complete"] is False
    finally:
        release.set()
    assert pipeline.wait_stopped(60) and not pipeline.still_running
    teaching.unwritten = ""
    teaching.close(complete=True, vision=pipeline)
    assert finished == [True]


@pytest.mark.parametrize("drive, says", [
    ({"driver": "dynamixel", "options": {"port": "/dev/ttyNOPE", "bus_watchdog_s": 0.1}},
     "drive.options.bus_watchdog_s 0.1 s is below two loop periods, 0.4 s (loop.rate_hz 5 Hz)"),
    ({"driver": "odrive", "options": {"port": "/dev/ttyNOPE", "watchdog_s": 0.1}},
     "drive.options.watchdog_s 0.1 s is below two loop periods, 0.4 s (loop.rate_hz 5 Hz)"),
])
def test_a_drive_watchdog_the_loop_cannot_feed_is_refused(drive, says):
    """The serial drives' own watchdog (Dynamixel Bus Watchdog, ODrive axis watchdog) stops the wheels after
    that long without a packet; the loop writes once a cycle. With it at or below a loop period (a 5 Hz loop, the
    100 ms default: on the emulated bus the first cycle tripped it, drive_lost, held until resume) the robot
    could never drive. make_robot (and config check) refuse it, naming both, with room for one late cycle."""
    from vbnav.control.runtime.factory import make_robot
    robot = {"max_wheel_speed": 6.0, "max_linear_speed": 0.3}
    over = {"robot": robot, "drive": drive, "controller": {"teach": "teleop"},
            "loop": {"rate_hz": 5.0}, "telemetry": {"state_rate_hz": 5.0}}
    with pytest.raises(ConfigError, match=re.escape(says)):
        make_robot(load_config(None, overrides=over), with_camera=False)
    over["loop"]["rate_hz"] = 20.0          # 2 x 50 ms = 0.1 s: fed in time, with a late cycle to spare
    make_robot(load_config(None, overrides=over), with_camera=False).drive.close()


def test_the_scripted_teacher_drives_within_the_robots_speed_limit():
    """controller.teach room_loop was said to drive at 0.4 m/s, and with a lower robot.max_linear_speed its
    0.4 m/s was clipped by the limiter alone, the turn rate kept: a tighter arc than the one the teacher chose
    (and not the speed said). The teacher now drives at the robot's limit when that is lower (the reference
    says so): what it commands is what the limiter lets through."""
    from vbnav.control.runtime.interfaces import ControlContext
    from vbnav.control.runtime.kinematics import TwistLimiter
    from vbnav.drivers.wheels import WheelState
    cfg = load_config(None, overrides={"controller": {"teach": "room_loop"},
                                       "robot": {"max_linear_speed": 0.25}})
    still = ControlContext(0, 0.01, Pose2(), WheelState(0, (0.0, 0.0), (0.0, 0.0)), {})     # at the start
    twist = teach_driver(cfg).update(still)
    assert twist.v == pytest.approx(0.25)
    assert TwistLimiter.from_config(cfg.robot).apply(twist, 10.0) == twist       # driven as commanded
    fast = teach_driver(load_config(None, overrides={"controller": {"teach": "room_loop"}}))
    assert fast.update(still).v == pytest.approx(0.4)


def test_the_state_names_the_route_being_taught(tmp_path):
    """docs/telemetry.md documents the state's ``route`` as the route file of teach/repeat; the link never
    filled it in (vbnav monitor showed none; found by the messages audit)."""
    import json

    from vbnav.control.comms.recording import iter_recording
    cfg = load_config(None)
    session = Session(cfg, make_robot(cfg, with_camera=True), record=str(tmp_path / "teach.mcap"))
    session.teach(IdleController(), tmp_path / "route", duration_s=0.5)
    routes = {json.loads(d)["route"] for t, _, _, d in iter_recording(tmp_path / "teach.mcap") if t == "/vbnav/state"}
    assert routes == {str(tmp_path / "route")}, routes
