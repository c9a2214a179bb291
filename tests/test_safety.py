"""Every safety trigger stops both wheels within two loop periods and says why."""
import math
import os
import signal

import pytest

from vbnav.control.runtime.interfaces import ControlContext, Controller, Twist, VisionStage
from vbnav.control.controllers.manual import ScriptedController, TeleopController
from vbnav.control.runtime.runtime import OperatorCommand
from runtime_helpers import PERIOD_NS, make_runtime

T0 = 1_000_000_000  # SimClock start


class Cruise(Controller):
    """Drives forward and calls ``hook(ctx)`` every cycle (to inject a failure at a chosen time)."""

    def __init__(self, hook=None):
        self.hook = hook

    def update(self, ctx: ControlContext) -> Twist:
        if self.hook:
            self.hook(ctx)
        return Twist(0.3, 0.1)


def assert_stopped_within_two_periods(drive, trigger_ns):
    assert drive.last_motion_ns() < trigger_ns + 2 * PERIOD_NS, (drive.last_motion_ns() - trigger_ns) / 1e6
    assert drive.stopped_since(trigger_ns + 2 * PERIOD_NS)
    assert drive.log[-1][3] is False, "drive left powered"
    assert drive.last_motion_ns() > trigger_ns - 5 * PERIOD_NS, "robot was not moving before the trigger"


def test_stale_camera_stops_and_recovers():
    stop_at = T0 + 2_000_000_000
    resume_at = T0 + 4_000_000_000
    rt, drive, clock = make_runtime(ScriptedController([[0.3, 0.0, 6.0]]),
                                    cam_kw={"stop_at_ns": stop_at, "resume_at_ns": resume_at})
    result = rt.run()
    assert result.reason == "finished"
    holds = [e for e in result.events if e.kind == "hold" and e.cause == "camera_stale"]
    assert len(holds) == 1 and "old" in holds[0].message
    # Last frame before the gap was at most one camera period before stop_at.
    trigger = holds[0].stamp_ns
    assert stop_at < trigger <= stop_at + int(0.5e9) + PERIOD_NS
    moving_in_gap = [t for t, l, r, p in drive.log if p and l != 0 and trigger + 2 * PERIOD_NS <= t < resume_at]
    assert not moving_in_gap
    assert any(e.kind == "release" and e.cause == "camera_stale" for e in result.events)
    # It drives again after frames return.
    assert any(t > resume_at and p and l > 0 for t, l, r, p in drive.log)


def test_a_camera_whose_grabbing_thread_failed_stops_the_robot_and_the_hold_says_why():
    """A grabbing thread that raised ended silently: the stale-camera hold stopped the robot, but nothing
    said why. The driver keeps the failure in ``error`` and the hold names it."""
    import threading

    from vbnav.drivers.camera import GrabbingCamera

    class Broken(GrabbingCamera):
        class Options:
            @staticmethod
            def model_validate(d):
                return d

        def connect(self):
            self._start_grabbing("broken-grab")

        def disconnect(self):
            self._stop.set()
            self._join_grabbing(1.0)

        def _grab_loop(self):
            raise RuntimeError("VIDIOC_DQBUF: bad buffer")

    cam = Broken(options={})
    cam.connect()
    cam._thread.join(2.0)
    assert cam.error == "Broken: the grabbing thread failed: RuntimeError: VIDIOC_DQBUF: bad buffer"
    assert not any(t.name == "broken-grab" for t in threading.enumerate())

    rt, drive, clock = make_runtime(ScriptedController([[0.3, 0.0, 4.0]]), cam_kw={"stop_at_ns": T0 + 1_000_000_000})
    rt.pipeline.camera.error = cam.error          # the loop's camera, as a driver whose thread failed at 1 s
    result = rt.run()
    hold = next(e for e in result.events if e.kind == "hold" and e.cause == "camera_stale")
    assert hold.message.endswith(": " + cam.error), hold.message
    assert not [t for t, l, r, p in drive.log if p and l != 0 and t > hold.stamp_ns + 2 * PERIOD_NS]


def test_frozen_camera_stops_and_recovers():
    """Frames that keep coming on time with the image they froze on (a driver re-queuing its last buffer)
    stop the robot like no frames at all: held 'camera_stale' once the image has not changed for
    camera.stale_after_s while the wheels moved, released on the first new image."""
    freeze_at = T0 + 2_000_000_000
    thaw_at = T0 + 4_000_000_000
    rt, drive, clock = make_runtime(ScriptedController([[0.3, 0.0, 6.0]]),
                                    cam_kw={"freeze_at_ns": freeze_at, "thaw_at_ns": thaw_at})
    result = rt.run()
    assert result.reason == "finished"
    holds = [e for e in result.events if e.kind == "hold" and e.cause == "camera_stale"]
    assert len(holds) == 1 and "frozen" in holds[0].message, holds
    trigger = holds[0].stamp_ns
    # The last new image came at most one camera period before freeze_at. The same image counts as
    # fresh (a still scene) until the wheels have moved 2 cm since it: 67 ms at 0.3 m/s, then the next
    # frame; the stop comes camera.stale_after_s after the last fresh frame.
    limit_ns = int(rt.cfg.camera.stale_after_s * 1e9)
    camera_ns = int(1e9 / 15)
    travel_ns = int(0.02 / 0.3 * 1e9)
    assert freeze_at - camera_ns + limit_ns < trigger <= freeze_at + travel_ns + camera_ns + limit_ns + PERIOD_NS
    assert any(trigger - 5 * PERIOD_NS < t < trigger and p and l > 0 for t, l, r, p in drive.log)   # was moving
    assert not [t for t, l, r, p in drive.log if p and l != 0 and trigger + 2 * PERIOD_NS <= t < thaw_at]
    releases = [e for e in result.events if e.kind == "release" and e.cause == "camera_stale"]
    release_ns = int(rt.safety.release_s * 1e9)             # like the stale camera's: clear this long
    assert len(releases) == 1
    assert thaw_at + release_ns <= releases[0].stamp_ns <= thaw_at + camera_ns + release_ns + PERIOD_NS
    assert any(t > thaw_at and p and l > 0 for t, l, r, p in drive.log)


def test_a_still_scene_is_not_a_frozen_camera():
    """A noise-free camera in front of a still scene gives the same image while the robot stands still:
    no stop. Once the wheels turn, the same image is frozen."""
    rt, drive, clock = make_runtime(ScriptedController([[0.0, 0.0, 2.0], [0.0, 0.2, 1.0]]),
                                    cam_kw={"freeze_at_ns": T0})
    result = rt.run()
    holds = [e for e in result.events if e.kind == "hold" and e.cause == "camera_stale"]
    assert len(holds) == 1 and "frozen" in holds[0].message, holds
    # Turning at 0.2 rad/s from 2 s: 5 mrad after 25 ms, then camera.stale_after_s from the last new
    # image (the first frame, at T0).
    assert holds[0].stamp_ns > T0 + 2_000_000_000


def test_stale_estimate_stops_and_recovers():
    """A controller's estimate (here 'vslam') that stops coming while frames still do: held '<kind>_stale'
    once it is older than safety.estimate_timeout_s, released when estimates return."""
    from vbnav.control.runtime.interfaces import Estimate
    gap = (T0 + 1_500_000_000, T0 + 4_000_000_000)

    class Fixes(VisionStage):
        kind = "vslam"

        def process(self, frame, odom):
            if gap[0] <= frame.stamp_ns < gap[1]:
                return None                          # tracking lost: no estimate, frames keep coming
            return Estimate(frame.stamp_ns, self.kind, True, None, {})

    class NeedsVslam(Cruise):
        requires = ("vslam",)

    rt, drive, clock = make_runtime(NeedsVslam(), stages=[Fixes()])
    result = rt.run(duration_s=6)
    limit = rt.cfg.safety.estimate_timeout_s
    holds = [e for e in result.events if e.kind == "hold" and e.cause == "vslam_stale"]
    assert len(holds) == 1 and "vslam" in holds[0].message
    trigger = holds[0].stamp_ns
    assert gap[0] + limit * 1e9 - 0.1e9 < trigger <= gap[0] + limit * 1e9 + PERIOD_NS    # last fix <= 1 frame before
    assert any(trigger - 5 * PERIOD_NS < t < trigger and p and l > 0 for t, l, r, p in drive.log)   # was moving
    assert not [t for t, l, r, p in drive.log if p and l != 0 and trigger + 2 * PERIOD_NS <= t < gap[1]]
    assert any(e.kind == "release" and e.cause == "vslam_stale" for e in result.events)
    assert any(t > gap[1] and p and l > 0 for t, l, r, p in drive.log)


def test_exception_in_vision_stage():
    class Exploding(VisionStage):
        kind = "boom"

        def process(self, frame, odom):
            if frame.stamp_ns >= T0 + 1_000_000_000:
                raise RuntimeError("tracker diverged")
            return None

    rt, drive, clock = make_runtime(ScriptedController([[0.3, 0.0, 5.0]]), stages=[Exploding()])
    result = rt.run()
    assert result.reason == "exception"
    assert "boom" in result.message and "tracker diverged" in result.message
    first_bad_frame = T0 + 1_000_000_000 + (-(1_000_000_000) % int(1e9 / 15))
    assert_stopped_within_two_periods(drive, first_bad_frame)


def test_exception_in_a_stage_running_in_its_own_thread():
    """BackgroundStage (the line map's fast loop during goto --map on a real clock): the stage fails in its
    thread; the next frame on the vision thread raises, naming it, and the robot stops within two loop
    periods of that frame, as for any stage."""
    import threading

    from vbnav.control.stages.background import BackgroundStage

    class Exploding(VisionStage):
        kind = "line_map"

        def process(self, frame, odom):
            if frame.stamp_ns >= T0 + 1_000_000_000:
                raise ValueError("map update diverged")
            return None

    raised_at = []

    class Watched(BackgroundStage):
        def process(self, frame, odom):
            try:
                return super().process(frame, odom)
            except RuntimeError:
                raised_at.append(frame.stamp_ns)
                raise

    bg = Watched(Exploding(), inline=False)

    def hook(ctx):   # a loaded machine may not run the worker for a while: hold simulated time until it failed
        if ctx.now_ns >= T0 + 1_200_000_000:
            for _ in range(1000):
                if bg._error is not None:
                    return
                threading.Event().wait(0.01)

    rt, drive, clock = make_runtime(Cruise(hook), stages=[bg])
    bg.start()
    try:
        result = rt.run(duration_s=5)
    finally:
        bg.stop()
    assert result.reason == "exception", result
    assert "line_map" in result.message and "own thread" in result.message and "diverged" in result.message
    assert raised_at and raised_at[0] > T0 + 1_000_000_000
    assert_stopped_within_two_periods(drive, raised_at[0])


def test_a_failed_line_map_abstraction_thread_fails_the_stage():
    """The line map's slow loop runs in its own thread (map build, goto --map): when it fails, the fast
    loop's next frame raises naming it, so the pipeline's fault stops the robot as for any stage (the
    thread died silently, and the robot mapped on without objects)."""
    import threading

    import numpy as np

    from vbnav.control.config import load_config
    from vbnav.control.stages.line_map import LineMapStage
    from vbnav.drivers.camera import Frame
    from vbnav.vision.geometry import Pose2

    stage = LineMapStage.from_config(load_config("sim_stereo"), abstraction_period_s=0.01)

    def snapshot():
        raise MemoryError("abstraction pass failed")
    stage.abstraction.snapshot = snapshot
    stage.start()
    try:
        for _ in range(500):
            if stage.abstraction.error is not None:
                break
            threading.Event().wait(0.01)
        img = np.zeros((480, 640), np.uint8)
        with pytest.raises(RuntimeError, match="line-map abstraction thread failed: MemoryError") as err:
            stage.process(Frame(img, T0, 1, right=img), Pose2())
        assert isinstance(err.value.__cause__, MemoryError)      # its traceback goes with the run's fault
    finally:
        stage.stop()


def test_exception_in_the_camera_thread():
    """On a real clock the camera is read in the vision thread: a driver that raises there (a USB camera
    gone mid-read) is the pipeline's fault, and the robot stops within two periods of the cycle that sees it."""
    import threading

    from runtime_helpers import RecordingDrive, TickCamera
    from vbnav.control.config import Config
    from vbnav.control.runtime.pipeline import VisionPipeline
    from vbnav.control.runtime.runtime import Runtime
    from vbnav.drivers.clock import SimClock

    unplugged = threading.Event()       # set by the loop at 1.5 s: the fault can only arise while it waits

    class Unplugged(TickCamera):
        def read(self, timeout_s=0.0):
            if unplugged.is_set():
                raise OSError(19, "No such device")
            threading.Event().wait(0.001)            # a driver's read takes a little time
            return super().read(timeout_s)

    clock = SimClock()
    drive = RecordingDrive(clock)
    pipeline = VisionPipeline(Unplugged(clock), [], clock, inline=False)
    seen = []

    def hook(ctx):   # hold simulated time once the camera is gone until the thread has met it
        if ctx.now_ns >= T0 + 1_500_000_000 and not seen:
            unplugged.set()
            for _ in range(1000):
                if pipeline.fault is not None:
                    seen.append(ctx.now_ns)
                    return
                threading.Event().wait(0.01)

    rt = Runtime(Config(camera={"stale_after_s": 5.0}), drive, Cruise(hook), clock, pipeline)
    result = rt.run(duration_s=5)
    assert result.reason == "exception" and "No such device" in result.message, result
    assert seen and drive.last_motion_ns() < seen[0] + 2 * PERIOD_NS
    assert drive.stopped_since(seen[0] + 2 * PERIOD_NS) and drive.log[-1][3] is False


@pytest.mark.parametrize("inline", [False, True], ids=["vision-thread", "loop-thread"])
def test_a_camera_that_fails_mid_run_ends_it_as_a_camera_fault_on_either_thread(inline):
    """A camera whose read raised CameraError (the device went away) ended the run as 'camera' (exit 3, a
    device's failure) only when it failed at start-up; mid-run, on the vision thread (real clock) or in the
    loop's own cycle (inline), it ended as 'exception' (exit 1, a bug). Every camera failure is now 'camera',
    and the robot stops as before."""
    import threading

    from runtime_helpers import RecordingDrive, TickCamera
    from vbnav.control.config import Config
    from vbnav.control.runtime.pipeline import VisionPipeline
    from vbnav.control.runtime.runtime import DEVICE_FAULTS, Runtime
    from vbnav.drivers.camera import CameraError
    from vbnav.drivers.clock import SimClock

    gone = threading.Event()

    class Gone(TickCamera):
        def read(self, timeout_s=0.0):
            if gone.is_set():
                raise CameraError("camera /dev/video0 went away (unplugged?)")
            if not inline:
                threading.Event().wait(0.001)
            return super().read(timeout_s)

    clock = SimClock()
    drive = RecordingDrive(clock)
    pipeline = VisionPipeline(Gone(clock), [], clock, inline=inline)
    seen = []

    def hook(ctx):
        if ctx.now_ns >= T0 + 1_500_000_000 and not seen:
            gone.set()
            seen.append(ctx.now_ns)
            for _ in range(1000):      # the vision thread: hold simulated time until it met the failure
                if inline or pipeline.fault is not None:
                    return
                threading.Event().wait(0.01)

    rt = Runtime(Config(camera={"stale_after_s": 5.0}), drive, Cruise(hook), clock, pipeline)
    result = rt.run(duration_s=5)
    assert result.reason == "camera" and result.reason in DEVICE_FAULTS, result
    assert "went away" in result.message and "camera" in result.message, result
    assert drive.stopped_since(seen[0] + 2 * PERIOD_NS) and drive.log[-1][3] is False


def test_exception_in_controller():
    def hook(ctx):
        if ctx.now_ns >= T0 + 1_500_000_000:
            raise ZeroDivisionError("bad gain")

    rt, drive, clock = make_runtime(Cruise(hook))
    result = rt.run(duration_s=5)
    assert result.reason == "exception" and "controller" in result.message and "bad gain" in result.message
    assert_stopped_within_two_periods(drive, T0 + 1_500_000_000)


@pytest.mark.parametrize("bad", [(float("nan"), 0.0), (0.0, float("nan")), (float("inf"), 0.0), (0.3, -math.inf)])
def test_non_finite_command_from_the_controller(bad):
    """A NaN or inf from a controller (a NaN pose upstream) stops the robot and ends the run, named; the
    speed limits would otherwise have turned it into full speed."""
    class Broken(Cruise):
        def update(self, ctx):
            return Twist(*bad) if ctx.now_ns >= T0 + 1_500_000_000 else Twist(0.3, 0.1)

    rt, drive, clock = make_runtime(Broken())
    result = rt.run(duration_s=5)
    assert result.reason == "exception" and "Broken commanded" in result.message, result.message
    assert_stopped_within_two_periods(drive, T0 + 1_500_000_000)


def test_missed_deadline_streak():
    def hook(ctx):
        if ctx.now_ns >= T0 + 1_000_000_000:
            rt.clock.advance(25_000_000)  # the cycle's work takes 25 ms at 100 Hz

    rt, drive, clock = make_runtime(Cruise(hook))
    result = rt.run(duration_s=5)
    assert result.reason == "deadline" and "consecutive missed deadlines" in result.message
    assert result.timing.overruns >= rt.cfg.loop.max_missed_streak
    # Every slow cycle overruns; the stop comes once the streak reaches the limit.
    streak_full = T0 + 1_000_000_000 + rt.cfg.loop.max_missed_streak * 30_000_000
    assert_stopped_within_two_periods(drive, streak_full)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT])
def test_signals(sig):
    def hook(ctx):
        if ctx.now_ns == T0 + 1_000_000_000:
            os.kill(os.getpid(), sig)

    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT)}
    rt, drive, clock = make_runtime(Cruise(hook))
    result = rt.run(duration_s=5)
    assert result.reason == "signal" and signal.Signals(sig).name in result.message
    assert_stopped_within_two_periods(drive, T0 + 1_000_000_000)
    # The handlers in force before the run (default, or SIG_IGN in a background job) are restored.
    assert {s: signal.getsignal(s) for s in before} == before


def test_lost_drive():
    rt, drive, clock = make_runtime(Cruise(), drive_kw={})
    drive.options = drive.Options(fail_after_s=1.0)
    result = rt.run(duration_s=5)
    assert result.reason == "drive" and "bus lost" in result.message
    assert drive.physics.powered is False
    assert drive.last_motion_ns() <= T0 + 1_000_000_000


def test_teleop_command_silence_stops_robot():
    teleop = TeleopController(timeout_s=0.5)

    def feed(r, ctx, twist, wheels):
        # An operator sends 10 Hz commands for 2 s, then goes silent.
        t = ctx.now_ns - T0
        if t < 2_000_000_000 and t % 100_000_000 == 0:
            r.submit(OperatorCommand("teleop", (0.3, 0.0), "test"))

    rt, drive, clock = make_runtime(teleop)
    rt.cycle_observers.append(feed)
    rt.run(duration_s=4)
    last_cmd = T0 + 1_900_000_000
    assert drive.last_motion_ns() < last_cmd + int(0.5e9) + 2 * PERIOD_NS
    assert drive.last_motion_ns() > T0 + 1_800_000_000
    assert teleop.timed_out


def test_estop_latches_until_resume():
    def feed(r, ctx, twist, wheels):
        t = ctx.now_ns - T0
        if t == 1_000_000_000:
            r.submit(OperatorCommand("estop", ("test button",), "test"))
        if t == 2_000_000_000:
            r.submit(OperatorCommand("resume", (), "test"))

    rt, drive, clock = make_runtime(Cruise())
    rt.cycle_observers.append(feed)
    result = rt.run(duration_s=3)
    trips = [e for e in result.events if e.kind == "trip" and e.cause == "estop"]
    assert trips and "test button" in trips[0].message
    moving = [t for t, l, r, p in drive.log if p and l != 0]
    assert not [t for t in moving if T0 + 1_000_000_000 + 2 * PERIOD_NS <= t < T0 + 2_000_000_000]
    assert any(t > T0 + 2_000_000_000 for t in moving)


def test_teleop_during_a_latched_stop_is_refused_and_never_drives_after_the_resume():
    """A teleop stream (10 Hz) through an estop (1 s) and a resume (2 s): teleop taken during the latch was
    answered 'applied' while the wheels stayed stopped, and the one held last (sent at 1.9 s, within the
    command timeout) drove the robot the moment the resume came. Now refused, saying why, and the robot
    moves again on the first teleop after the resume."""
    teleop = TeleopController(timeout_s=0.5)

    def feed(r, ctx, twist, wheels):
        t = ctx.now_ns - T0
        if t == 1_000_000_000:
            r.submit(OperatorCommand("estop", ("test button",), "test"))
        if t == 2_000_000_000:
            r.submit(OperatorCommand("resume", (), "test"))
        if t < 3_000_000_000 and t % 100_000_000 == 50_000_000:
            r.submit(OperatorCommand("teleop", (0.3, 0.0), "test"))

    rt, drive, clock = make_runtime(teleop)
    rt.cycle_observers.append(feed)
    applied = []
    rt.command_listeners.append(lambda r, cmd, outcome, now: applied.append((now, cmd.kind)))
    result = rt.run(duration_s=3.5)
    refused = [e for e in result.events if e.kind == "rejected" and e.cause == "teleop"]
    assert refused and "estop" in refused[0].message and "latched" in refused[0].message, refused
    in_latch = [t for t, k in applied if k == "teleop" and T0 + 1_000_000_000 < t < T0 + 2_000_000_000]
    assert not in_latch
    moving = [t for t, l, r, p in drive.log if p and l != 0]
    assert not [t for t in moving if T0 + 1_000_000_000 + 2 * PERIOD_NS <= t < T0 + 2_050_000_000]
    assert any(t > T0 + 2_050_000_000 for t in moving)


def test_teleop_during_a_held_stop_is_refused_and_never_drives_when_it_clears():
    """A teleop stream (10 Hz) through an obstacle stop zone (1-2 s): teleop taken during the hold was
    answered 'applied' while the wheels stayed stopped. Now refused, naming the hold, and the robot moves
    again on teleop sent after the zone has cleared."""
    from vbnav.control.runtime.interfaces import Estimate

    class Zone(VisionStage):
        kind = "obstacles"

        def process(self, frame, odom):
            t = (frame.stamp_ns - T0) * 1e-9
            return Estimate(frame.stamp_ns, self.kind, True, None,
                            {"speed_scale": 0.0 if 1.0 <= t < 2.0 else 1.0, "reason": "box ahead"})

    teleop = TeleopController(timeout_s=0.5)

    def feed(r, ctx, twist, wheels):
        t = ctx.now_ns - T0
        if t < 3_000_000_000 and t % 100_000_000 == 50_000_000:
            r.submit(OperatorCommand("teleop", (0.3, 0.0), "test", ack=f"t{t}"))

    rt, drive, clock = make_runtime(teleop, stages=[Zone()])
    rt.cycle_observers.append(feed)
    applied = []
    rt.command_listeners.append(lambda r, cmd, outcome, now: applied.append(now))
    result = rt.run(duration_s=3.5)
    hold = next(e for e in result.events if e.kind == "hold" and e.cause == "obstacle")
    release = next(e for e in result.events if e.kind == "release" and e.cause == "obstacle")
    refused = [e for e in result.events if e.kind == "rejected" and e.cause == "teleop"]
    assert refused and all("obstacle" in e.message and "held" in e.message for e in refused), refused
    # every teleop while held is refused (each carries an ack, so none is throttled), none applied
    assert len(refused) >= (release.stamp_ns - hold.stamp_ns) // 100_000_000 - 1, len(refused)
    assert not [t for t in applied if hold.stamp_ns <= t < release.stamp_ns]
    moving = [t for t, l, r, p in drive.log if p and l != 0]
    assert not [t for t in moving if hold.stamp_ns + 2 * PERIOD_NS <= t < release.stamp_ns]
    assert any(t > release.stamp_ns for t in moving)


def test_a_teleop_held_from_before_a_hold_does_not_drive_when_it_clears():
    """One teleop at 0.8 s (command timeout 1 s), an obstacle stop zone at 1.0-1.2 s: the command, held
    through the stop, drove the robot again the moment the zone cleared (until 1.8 s), on an order given
    before anyone knew of the obstacle. The hold now drops it; a teleop sent after the zone drives."""
    from vbnav.control.runtime.interfaces import Estimate

    class Zone(VisionStage):
        kind = "obstacles"

        def process(self, frame, odom):
            t = (frame.stamp_ns - T0) * 1e-9
            return Estimate(frame.stamp_ns, self.kind, True, None,
                            {"speed_scale": 0.0 if 1.0 <= t < 1.2 else 1.0, "reason": "box ahead"})

    def feed(r, ctx, twist, wheels):
        if ctx.now_ns - T0 in (800_000_000, 2_000_000_000):
            r.submit(OperatorCommand("teleop", (0.3, 0.0), "test", ack=f"t{ctx.now_ns}"))

    rt, drive, clock = make_runtime(TeleopController(timeout_s=1.0), stages=[Zone()])
    rt.cycle_observers.append(feed)
    result = rt.run(duration_s=2.5)
    hold = next(e for e in result.events if e.kind == "hold" and e.cause == "obstacle")
    release = next(e for e in result.events if e.kind == "release" and e.cause == "obstacle")
    assert release.stamp_ns < T0 + 1_700_000_000, (release.stamp_ns - T0) / 1e9   # inside the old command's life
    moving = [t for t, l, r, p in drive.log if p and l != 0]
    assert any(t < hold.stamp_ns for t in moving)                                   # it drove before the zone
    assert not [t for t in moving if hold.stamp_ns + 2 * PERIOD_NS <= t < T0 + 2_000_000_000], \
        [(t - T0) / 1e9 for t in moving if t > hold.stamp_ns][:5]
    assert any(t > T0 + 2_000_000_000 for t in moving)                              # a fresh teleop drives


def test_a_command_that_raises_ends_the_run_and_it_and_the_rest_of_its_drain_are_answered():
    """A controller that raises on a command ends the run (motors stopped); that command and the estop
    drained behind it in the same cycle were never answered, so their senders waited for a timeout."""
    class Fragile(Cruise):
        def handle_command(self, cmd, now_ns):
            if cmd.kind == "mode":
                raise RuntimeError("mode switch broke")
            return super().handle_command(cmd, now_ns)

    rt, drive, clock = make_runtime(Fragile())
    seen = []
    rt.command_observers.append(lambda r, cmd, now: seen.append(cmd.ack))

    def post(r, ctx, twist, wheels):
        if ctx.cycle == 10:
            for kind, args in (("mode", ("idle",)), ("estop", ())):
                r.submit(OperatorCommand(kind, args, "op", ack=kind))

    rt.cycle_observers.append(post)
    result = rt.run(duration_s=2.0)
    assert result.reason == "exception" and "mode switch broke" in result.message
    rejected = [e for e in result.events if e.kind == "rejected"]
    assert [e.cause for e in rejected] == ["mode"], rejected
    assert all("the run ended (exception" in e.message for e in rejected), rejected
    # the estop was accepted, so it is applied (latched, kept in a latch file): test_estop_latch.py
    assert "estop" in rt.safety.latched
    assert seen[-2:] == ["mode", "estop"]           # each answer is told which command (ack) it is for
    assert drive.log[-1][1:3] == (0.0, 0.0)


def test_a_resume_says_what_it_did_not_clear():
    """A resume during an obstacle hold, or with nothing latched, was answered plainly 'applied', as if the
    robot were free to move. It is taken, with a note on what it left."""
    from vbnav.control.runtime.interfaces import Estimate

    class Zone(VisionStage):
        kind = "obstacles"

        def process(self, frame, odom):
            t = (frame.stamp_ns - T0) * 1e-9
            return Estimate(frame.stamp_ns, self.kind, True, None,
                            {"speed_scale": 0.0 if 1.0 <= t < 2.0 else 1.0, "reason": "box ahead"})

    rt, drive, clock = make_runtime(Cruise(), stages=[Zone()])
    answers = []
    rt.command_listeners.append(lambda r, cmd, outcome, now: answers.append((cmd.ack, outcome)))

    def post(r, ctx, twist, wheels):
        t = ctx.now_ns - T0
        for at, kind in ((500_000_000, "estop"), (700_000_000, "resume"), (800_000_000, "resume"),
                         (1_300_000_000, "estop"), (1_500_000_000, "resume"), (1_600_000_000, "resume")):
            if t == at:
                r.submit(OperatorCommand(kind, (), "op", ack=f"{kind}@{at // 100_000_000}"))

    rt.cycle_observers.append(post)
    rt.run(duration_s=2.5)
    notes = {ack: (o.applied, o.reason, o.unchanged) for ack, o in answers}
    assert notes["resume@7"] == (True, "", False)                       # cleared the estop, free to move
    assert notes["resume@8"] == (True, "nothing was latched", True)
    assert notes["resume@15"] == (True, "cleared estop; still held by obstacle until it clears", False)
    assert notes["resume@16"] == (True, "nothing was latched; still held by obstacle until it clears", True)


def test_obstacle_speed_scale_slows_and_stops():
    from vbnav.control.runtime.interfaces import Estimate

    class Zone(VisionStage):
        """Reports a slow-down zone between 1 and 2 s and a stop zone between 2 and 3 s."""
        kind = "obstacles"

        def process(self, frame, odom):
            t = (frame.stamp_ns - T0) * 1e-9
            scale = 0.5 if 1.0 <= t < 2.0 else (0.0 if 2.0 <= t < 3.0 else 1.0)
            return Estimate(frame.stamp_ns, self.kind, True, None, {"speed_scale": scale, "reason": "box ahead"})

    rt, drive, clock = make_runtime(ScriptedController([[0.3, 0.0, 5.0]]), stages=[Zone()])
    rt.run()
    cmd = {t: (l, p) for t, l, r, p in drive.log}
    full = 0.3 / 0.05
    at = lambda s: cmd[min(cmd, key=lambda t: abs(t - (T0 + int(s * 1e9))))]
    assert at(0.8)[0] == pytest.approx(full)
    assert at(1.7)[0] == pytest.approx(full / 2, rel=1e-6)
    assert at(2.5) == (0.0, False)
    assert at(4.5)[0] == pytest.approx(full, rel=1e-6)
    holds = [e for e in rt.safety.events if e.cause == "obstacle"]
    assert holds[0].kind == "hold" and holds[0].message == "box ahead" and holds[1].kind == "release"
    # the zone's own debounce (obstacles.release_s) is the release time: not safety.release_s on top of it
    assert 0 <= holds[1].stamp_ns - (T0 + 3_000_000_000) < 0.15e9, (holds[1].stamp_ns - T0) / 1e9
    assert at(3.25)[0] > 0.3 * full         # accelerating again (with the double debounce: still 0 until 3.5 s)


def test_a_turn_only_obstacle_hold_stops_the_travel_at_once_and_lets_the_turn_through():
    """An obstacle hold that lets a turn on the spot through (``turn_ok``, obstacles.turn_when_held): the forward
    speed is zero from the first cycle of the hold (no deceleration ramp), the turn keeps going with the drive
    powered; a second zero scale without ``turn_ok`` (a blind stage) stops both and powers the drive down."""
    from vbnav.control.runtime.interfaces import Estimate

    class Zone(VisionStage):
        """kind ``obstacles``: held, turn allowed, from 1 to 3 s; kind ``blind``: held, no turn, 2 to 2.5 s."""

        def __init__(self, kind, start, end, turn_ok):
            self.kind, self.start, self.end, self.turn_ok = kind, start, end, turn_ok

        def process(self, frame, odom):
            t = (frame.stamp_ns - T0) * 1e-9
            held = self.start <= t < self.end
            info = {"speed_scale": 0.0 if held else 1.0, "reason": f"{self.kind} ahead"}
            if self.turn_ok:
                info["turn_ok"] = held
            return Estimate(frame.stamp_ns, self.kind, True, None, info)

    rt, drive, clock = make_runtime(ScriptedController([[0.3, 0.5, 5.0]]),
                                    stages=[Zone("obstacles", 1.0, 3.0, True), Zone("blind", 2.0, 2.5, False)])
    rt.run()
    log = [(t, l, r, p) for t, l, r, p in drive.log]
    at = lambda s: [e for e in log if e[0] <= T0 + int(s * 1e9)][-1]      # the drive's state at s
    wheel_v = lambda e: (e[1] + e[2]) / 2          # forward speed in wheel rad/s
    assert wheel_v(at(0.9)) > 0.29 / 0.05 * 0.99                         # driving before the hold
    began = next(e.stamp_ns for e in rt.safety.events if e.cause == "obstacle" and e.kind == "hold")
    first_held = next(e for e in log if e[0] >= began)
    assert wheel_v(first_held) == pytest.approx(0.0, abs=1e-9) and first_held[3]     # the cycle the hold began
    for s in (1.5, 1.9, 2.7):
        e = at(s)
        assert e[3] and e[1] == pytest.approx(-e[2]) and abs(e[1]) > 1.0, (s, e)   # turning on the spot, powered
    assert at(2.25)[1:] == (0.0, 0.0, False)                             # blind too: everything stops
    assert wheel_v(at(4.5)) > 0.29 / 0.05 * 0.99                         # released: driving again
    holds = [(e.kind, e.message) for e in rt.safety.events if e.cause == "obstacle"]
    assert holds[0] == ("hold", "obstacles ahead; turning on the spot allowed (obstacles.turn_when_held, a round robot)")
    assert ("hold_changed", "blind ahead") in holds                       # the hold changed to a full stop, and said so
    assert holds[-1][0] == "release"


def test_one_obstacle_hold_whose_turn_only_flag_flips_is_counted_once():
    """A turn-only obstacle hold (obstacles.turn_when_held) that became a full stop while the stage was blind,
    and turn-only again, re-emitted a ``hold`` at each change: a repeat's stops on the way (``holds_on_the_way``)
    counted one continuous stop three times. The changes are ``hold_changed`` events, with their messages."""
    from vbnav.control.runtime.interfaces import Estimate

    class Zone(VisionStage):
        """Held from 1 to 3 s; the turn allowed but from 2 to 2.5 s (the stage went blind)."""
        kind = "obstacles"

        def process(self, frame, odom):
            t = (frame.stamp_ns - T0) * 1e-9
            held = 1.0 <= t < 3.0
            reason = "blind" if 2.0 <= t < 2.5 else "box ahead"
            return Estimate(frame.stamp_ns, self.kind, True, None,
                            {"speed_scale": 0.0 if held else 1.0, "reason": reason,
                             "turn_ok": held and reason != "blind"})

    result = make_runtime(ScriptedController([[0.3, 0.5, 5.0]]), stages=[Zone()])[0].run()
    kinds = [(e.kind, e.message.split(";")[0]) for e in result.events if e.cause == "obstacle"]
    assert kinds == [("hold", "box ahead"), ("hold_changed", "blind"), ("hold_changed", "box ahead"),
                     ("release", "obstacle clear for 0 s")], kinds
    assert result.holds_on_the_way() == 1 and result.count("hold", "obstacle") == 1


def test_a_teleop_that_only_turns_is_taken_under_a_turn_only_hold():
    """A round robot held by an obstacle ahead may turn on the spot (obstacles.turn_when_held), but every teleop
    was refused while the hold lasted: an operator could not turn the robot away from what held it. A teleop
    with linear 0 is taken and turns the robot; one that also drives forward is refused, saying what is taken;
    under a full hold (the stage blind) every teleop is refused, as before."""
    from vbnav.control.runtime.interfaces import Estimate

    class Zone(VisionStage):
        """Held from 1 s on; the turn allowed but from 2 to 2.5 s (the stage went blind)."""
        kind = "obstacles"

        def process(self, frame, odom):
            t = (frame.stamp_ns - T0) * 1e-9
            blind = 2.0 <= t < 2.5
            return Estimate(frame.stamp_ns, self.kind, True, None,
                            {"speed_scale": 0.0 if t >= 1.0 else 1.0, "reason": "blind" if blind else "box ahead",
                             "turn_ok": t >= 1.0 and not blind})

    def feed(r, ctx, twist, wheels):       # forward and turning before 1.5 s, then a turn on the spot
        t = (ctx.now_ns - T0) * 1e-9
        linear = 0.2 if t < 1.5 or 2.8 <= t < 2.9 else 0.0
        r.submit(OperatorCommand("teleop", (linear, 0.5), "test", ack=f"t{ctx.cycle}"))

    rt, drive, clock = make_runtime(TeleopController(timeout_s=0.5), stages=[Zone()])
    rt.cycle_observers.append(feed)
    applied, refused = [], []
    rt.command_listeners.append(lambda r, cmd, outcome, now: applied.append(((now - T0) * 1e-9, cmd.args[0])))
    rt.safety.listeners.append(lambda ev: refused.append(((ev.stamp_ns - T0) * 1e-9, ev.message))
                               if ev.kind == "rejected" else None)
    rt.run(duration_s=3.0)
    at = lambda s: [e for e in drive.log if e[0] <= T0 + int(s * 1e9)][-1]      # the drive's state at s
    for s in (1.8, 1.95, 2.7):
        e = at(s)
        assert e[3] and e[1] == pytest.approx(-e[2]) and abs(e[1]) > 1.0, (s, e)   # turning on the spot, powered
    assert at(2.25)[1:] == (0.0, 0.0, False)                                  # blind: everything stops
    within = lambda events, lo, hi: [e for e in events if lo <= e[0] < hi]
    assert len(within(applied, 1.6, 2.0)) >= 30 and len(within(applied, 2.55, 2.8)) >= 20   # the turns taken
    assert not within(refused, 1.6, 2.0) and not within(refused, 2.55, 2.8)
    assert not within(applied, 2.1, 2.45)                                   # blind from the frame after 2 s
    assert not [e for e in applied if e[0] >= 1.1 and e[1] != 0.0]          # held: nothing forward taken
    assert "does not move the robot" in within(refused, 2.1, 2.45)[0][1]              # blind: refused
    forward = within(refused, 2.8, 2.9)
    assert forward and "only a turn on the spot (linear 0) is taken" in forward[0][1], forward


def test_exception_in_the_progress_callback_stops_the_robot_and_says_where():
    rt, drive, clock = make_runtime(Cruise())

    def progress(r):
        if r.clock.now_ns() >= T0 + 1_000_000_000:
            raise RuntimeError("console gone")
    result = rt.run(duration_s=5, progress=progress, progress_every_s=0.5)
    assert result.reason == "exception" and "outside the cycle" in result.message and "console gone" in result.message
    assert "start-up" not in result.message
    assert_stopped_within_two_periods(drive, T0 + 1_000_000_000)


def test_a_teleop_taken_in_the_cycle_an_estimate_hold_begins_is_refused_not_applied():
    """Estimates were checked after the commands: a teleop taken in the cycle a stale-estimate hold began was
    answered 'applied', then dropped by that same hold the same cycle. Now the hold is known first and the
    teleop refused, naming it."""
    from vbnav.control.runtime.interfaces import Estimate
    gap_ns = T0 + 1_000_000_000

    class Fixes(VisionStage):
        kind = "vslam"

        def process(self, frame, odom):
            return None if frame.stamp_ns >= gap_ns else Estimate(frame.stamp_ns, self.kind, True, None, {})

    class NeedsVslam(TeleopController):
        requires = ("vslam",)

    def feed(r, ctx, twist, wheels):       # one teleop a cycle, each asking for its answer
        r.submit(OperatorCommand("teleop", (0.3, 0.0), "test", ack=f"t{ctx.cycle}"))

    rt, drive, clock = make_runtime(NeedsVslam(timeout_s=0.5), stages=[Fixes()])
    rt.cycle_observers.append(feed)
    applied, refused = [], []
    rt.command_listeners.append(lambda r, cmd, outcome, now: applied.append(now))
    rt.safety.listeners.append(lambda ev: refused.append((ev.stamp_ns, ev.message)) if ev.kind == "rejected" else None)
    result = rt.run(duration_s=2.0)
    hold = next(e for e in result.events if e.kind == "hold" and e.cause == "vslam_stale")
    assert applied and max(applied) < hold.stamp_ns, [(t - hold.stamp_ns) / 1e6 for t in applied[-3:]]
    assert refused[0][0] == hold.stamp_ns and "vslam_stale" in refused[0][1], refused[:2]


def test_an_exception_in_the_vision_thread_outside_the_stages_ends_the_run_and_says_why():
    """On a real clock the vision thread does more than the stages: the frozen-image check, the odometry at
    the frame's stamp. An exception there ended the thread with a line on stderr only: no fault, the
    estimates and frames stopped, and the robot was left to the stale-camera hold, with no word of why."""
    import threading

    from runtime_helpers import RecordingDrive, TickCamera
    from vbnav.control.config import Config
    from vbnav.control.runtime.pipeline import VisionPipeline
    from vbnav.control.runtime.runtime import Runtime
    from vbnav.drivers.clock import SimClock

    broken = threading.Event()          # set by the loop at 1.5 s

    class BrokenWatch:
        frozen = False

        def fresh(self, image, odom):
            if broken.is_set():
                raise ValueError("watch broke")
            threading.Event().wait(0.001)
            return True

    clock = SimClock()
    drive = RecordingDrive(clock)
    pipeline = VisionPipeline(TickCamera(clock), [], clock, inline=False)
    pipeline.frozen = BrokenWatch()
    seen = []

    hook = break_at_1_5_s(broken, pipeline, seen)
    rt = Runtime(Config(camera={"stale_after_s": 5.0}), drive, Cruise(hook), clock, pipeline)
    result = rt.run(duration_s=5)
    assert seen
    assert result.reason == "exception" and "vision thread" in result.message and "watch broke" in result.message, \
        result.message
    assert rt.fault_traceback and "ValueError" in rt.fault_traceback
    assert drive.last_motion_ns() < seen[0] + 2 * PERIOD_NS
    assert drive.stopped_since(seen[0] + 2 * PERIOD_NS) and drive.log[-1][3] is False


def break_at_1_5_s(broken, pipeline, seen: list, ready=lambda: True):
    """A loop hook that sets ``broken`` at 1.5 s (or at the first cycle after it when ``ready()``) and holds
    simulated time there until the vision thread has met it (a fault, or the thread ended), appending that
    cycle's time to ``seen``."""
    import threading

    def hook(ctx):
        if ctx.now_ns >= T0 + 1_500_000_000 and not seen and ready():
            broken.set()
            for _ in range(300):
                if pipeline.fault is not None or not pipeline._thread.is_alive():
                    seen.append(ctx.now_ns)
                    return
                threading.Event().wait(0.01)
    return hook


@pytest.mark.parametrize("where", ["stage", "camera"])
def test_a_system_exit_on_the_vision_thread_ends_the_run_and_says_why(where):
    """A library's sys.exit() on the vision thread (in a stage, or in the camera's read) is a SystemExit, which
    ends a thread without a word: the pipeline had no fault, the run went on to 'duration reached', and the robot
    drove on until the stale-camera hold (camera.stale_after_s later) stopped it, saying only that the frames
    were old. It is the pipeline's fault now, as any exception there."""
    import sys
    import threading

    from runtime_helpers import RecordingDrive, TickCamera
    from vbnav.control.config import Config
    from vbnav.control.runtime.pipeline import VisionPipeline
    from vbnav.control.runtime.runtime import Runtime
    from vbnav.drivers.clock import SimClock

    broken = threading.Event()          # set by the loop at 1.5 s

    class Exiting(VisionStage):
        kind = "probe"

        def process(self, frame, odom):
            if broken.is_set() and where == "stage":
                sys.exit("a library gave up")
            threading.Event().wait(0.001)
            return None

    class ExitingCamera(TickCamera):
        def read(self, timeout_s=0.0):
            if broken.is_set() and where == "camera":
                sys.exit("a library gave up")
            return super().read(timeout_s)

    clock = SimClock()
    drive = RecordingDrive(clock)
    pipeline = VisionPipeline(ExitingCamera(clock), [Exiting()], clock, inline=False)
    seen = []

    # on a loaded machine the vision thread may lag the simulated clock: the start waits for its first frame
    hook = break_at_1_5_s(broken, pipeline, seen, ready=lambda: drive.last_motion_ns() > 0)
    rt = Runtime(Config(camera={"stale_after_s": 5.0}), drive, Cruise(hook), clock, pipeline)
    result = rt.run(duration_s=5)
    assert seen
    assert result.reason == "exception" and "SystemExit" in result.message and "gave up" in result.message, \
        result.message
    assert_stopped_within_two_periods(drive, seen[0])


def test_a_non_finite_wheel_position_ends_the_run_and_never_reaches_the_odometry():
    """A drive that reads NaN for a wheel angle (an ODrive answering 'nan' for a failed encoder) made the
    pose NaN for the rest of the run: telemetry, the vision stages' odometry and a teleop run drove on
    without a position. It is a drive fault: the run ends with reason 'drive' the cycle it comes, the wheels
    stop and the pose stays the last finite one."""
    import dataclasses

    rt, drive, clock = make_runtime(Cruise(), camera=False)
    read = drive.read

    def glitchy_read():
        s = read()
        if clock.now_ns() >= T0 + 1_000_000_000:
            s = dataclasses.replace(s, position=(math.nan, s.position[1]))
        return s
    drive.read = glitchy_read
    result = rt.run(duration_s=3)
    assert result.reason == "drive" and "non-finite" in result.message, result.message
    pose = rt.odometry.pose
    assert math.isfinite(pose.x) and math.isfinite(pose.z) and math.isfinite(pose.theta)
    assert_stopped_within_two_periods(drive, T0 + 1_000_000_000)


def test_an_exception_in_the_first_progress_call_is_not_called_a_start_up_failure():
    """The progress callback runs in the first cycle too: its exception there was reported as 'start-up:',
    as if the drive or the camera had not come up, after a cycle had driven."""
    rt, drive, clock = make_runtime(Cruise())

    def progress(r):
        raise RuntimeError("console gone")
    result = rt.run(duration_s=5, progress=progress)
    assert result.reason == "exception" and "console gone" in result.message
    assert "start-up" not in result.message and "outside the cycle" in result.message, result.message
    assert drive.log[-1][3] is False


def test_ctrl_z_stops_the_robot_and_ends_the_run():
    """SIGTSTP (Ctrl-Z) was left at its default: the process stopped where it was with the wheels at their
    last command, stopped only by the device's watchdog, and the loop found a stall when it was continued.
    It now ends the run like SIGINT: the wheels to zero and the drive disabled at the next cycle. In a child
    process: unhandled, the signal stops it."""
    import subprocess
    import sys

    code = '''
import os, signal, sys
sys.path.insert(0, "tests")
from runtime_helpers import make_runtime, PERIOD_NS
from test_safety import Cruise, T0, assert_stopped_within_two_periods
def hook(ctx):
    if ctx.now_ns == T0 + 1_000_000_000:
        os.kill(os.getpid(), signal.SIGTSTP)
rt, drive, clock = make_runtime(Cruise(hook))
result = rt.run(duration_s=5)
assert result.reason == "signal" and "SIGTSTP" in result.message, result
assert_stopped_within_two_periods(drive, T0 + 1_000_000_000)
assert signal.getsignal(signal.SIGTSTP) is signal.SIG_DFL
print("ok", flush=True)
'''
    try:
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=20,
                           cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    except subprocess.TimeoutExpired:
        pytest.fail("the run stopped itself on SIGTSTP, wheels as they were")
    assert r.returncode == 0 and "ok" in r.stdout, r.stderr


def test_with_catch_up_a_stall_is_the_latched_stall_stop_not_a_fatal_deadline():
    """With loop.overrun_policy catch_up, the ticks a 2 s stall left behind run back to back; each of them
    ended after its (long past) deadline, so five of them made a 'deadline' streak: the run ended, saying
    '5 consecutive missed deadlines ... last compute 0.0 ms', for a stall the loop recovers from (a latched,
    non-fatal stop). A catch-up tick that gains ground is no overrun of the loop's work."""
    from vbnav.control.config import Config

    cfg = Config()
    cfg.loop.overrun_policy = "catch_up"

    def hook(ctx):
        if ctx.now_ns == T0 + 1_000_000_000:
            rt.clock.advance(2_000_000_000)            # the process froze for 2 s in this cycle

    rt, drive, clock = make_runtime(Cruise(hook), camera=False, cfg=cfg)
    result = rt.run(duration_s=5)
    assert result.reason == "duration", result.message
    assert result.count("trip", "stall") == 1 and result.count("trip", "deadline") == 0
    assert drive.stopped_since(T0 + 3_010_000_000)        # latched: no resume came


def test_with_catch_up_a_loop_that_cannot_keep_up_still_ends_on_the_deadline_streak():
    from vbnav.control.config import Config

    cfg = Config()
    cfg.loop.overrun_policy = "catch_up"

    def hook(ctx):
        if ctx.now_ns >= T0 + 1_000_000_000:
            rt.clock.advance(25_000_000)  # the cycle's work takes 25 ms at 100 Hz

    rt, drive, clock = make_runtime(Cruise(hook), camera=False, cfg=cfg)
    result = rt.run(duration_s=5)
    assert result.reason == "deadline" and "consecutive missed deadlines" in result.message
    assert_stopped_within_two_periods(drive, T0 + 1_000_000_000 + cfg.loop.max_missed_streak * 25_000_000)


_BACKGROUND_RUN = '''
import os, signal, subprocess, sys, termios
tty = sys.argv[1]
if sys.argv[2] == "leader":
    # the session's foreground job: the run goes to a background process group of its own
    p = subprocess.Popen([sys.executable, "-c", sys.argv[3], tty, "run"], process_group=0)
    pid, status = os.waitpid(p.pid, os.WUNTRACED)
    if os.WIFSTOPPED(status):
        os.kill(p.pid, signal.SIGKILL)
        os.waitpid(p.pid, 0)
        print("stopped by", signal.Signals(os.WSTOPSIG(status)).name, file=sys.stderr, flush=True)
        sys.exit(2)
    sys.exit(os.waitstatus_to_exitcode(status))
sys.path.insert(0, "tests")
from runtime_helpers import make_runtime
from test_safety import Cruise
assert os.getpgrp() != os.tcgetpgrp(0), "not in the background"
out = open(tty, "w")
rt, drive, clock = make_runtime(Cruise())
read = []
def progress(r):                         # a background job's output to its terminal (stty tostop)
    print("cycle", r.cycle, file=out, flush=True)
    if not read:
        try:
            os.read(0, 1)                # a background job's read of its terminal
        except OSError as exc:
            read.append(exc)
result = rt.run(duration_s=3, progress=progress)
assert result.reason == "duration", result
assert read and read[0].errno == 5, read          # EIO: the read fails, it does not stop the process
assert drive.log[-1][3] is False
print("ok", file=sys.stderr, flush=True)
'''


def test_a_background_run_that_writes_or_reads_its_terminal_is_not_stopped_with_the_wheels_live():
    """A run started in the background (``vbnav run ... &``) with ``stty tostop`` got SIGTTOU at its first
    progress line, and SIGTTIN at a read of its terminal: left at their defaults they stop the process where
    it is, the wheels at their last command. The run ignores both while the wheels are live: the line is
    written, the read fails (EIO), and the run goes on. A real background job: a session of its own on a
    pseudo-terminal with tostop set, its leader in the foreground, the run in a background process group."""
    import fcntl
    import subprocess
    import sys
    import termios

    master, slave = os.openpty()
    attrs = termios.tcgetattr(slave)
    attrs[3] |= termios.TOSTOP
    termios.tcsetattr(slave, termios.TCSANOW, attrs)
    name = os.ttyname(slave)

    def take_the_terminal():
        fcntl.ioctl(0, termios.TIOCSCTTY, 0)

    try:
        r = subprocess.run([sys.executable, "-c", _BACKGROUND_RUN, name, "leader", _BACKGROUND_RUN],
                           stdin=slave, stdout=slave, stderr=subprocess.PIPE, text=True, timeout=60,
                           start_new_session=True, preexec_fn=take_the_terminal,
                           cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    finally:
        os.close(slave)
    try:
        written = os.read(master, 65536).decode()
    except OSError:
        written = ""
    os.close(master)
    assert r.returncode == 0 and "ok" in r.stderr, r.stderr
    assert "cycle" in written, written


def test_a_stop_signal_during_start_up_never_powers_the_wheels():
    """Ctrl-C (or a service manager's SIGTERM) while the camera was still coming up (an OAK's discovery
    takes seconds) was seen at the first cycle only: start-up went on and powered the drive first. The run
    now ends before the drive is enabled."""
    rt, drive, clock = make_runtime(Cruise())
    connect = rt.pipeline.camera.connect
    enabled = []

    def slow_connect():
        os.kill(os.getpid(), signal.SIGINT)         # the operator gives up waiting for the camera
        connect()

    def enable():
        enabled.append(clock.now_ns())
        type(drive).enable(drive)

    rt.pipeline.camera.connect = slow_connect
    drive.enable = enable
    result = rt.run(duration_s=2)
    assert result.reason == "signal" and "SIGINT" in result.message, result
    assert enabled == [] and not [p for t, l, r, p in drive.log if p], drive.log


def test_a_stop_the_drive_did_not_take_is_reported_not_swallowed():
    """When the run ends (here SIGTERM) the runtime disables the drive; a drive that could not stop a motor
    (a servo that stopped answering just then) passed over it in silence (its disable never raises), and
    the run ended as if its wheels had stopped. The drive now says what it could not stop
    (``stop_failure``) and the run reports it as a warning: only the device's own watchdog stops that motor."""
    from runtime_helpers import RecordingDrive
    from vbnav.control.config import Config
    from vbnav.control.runtime.runtime import Runtime
    from vbnav.drivers.clock import SimClock

    class Unconfirmed(RecordingDrive):
        def _stop_wheels(self):
            super()._stop_wheels()
            return "servo 2 (right): torque off not acknowledged (no answer)" if self.fail else None

    def after_the_write(r, ctx, twist, wheels):
        if ctx.now_ns == T0 + 1_000_000_000:
            drive.fail = True
            rt.request_stop(signal.SIGTERM)

    clock = SimClock()
    drive = Unconfirmed(clock)
    drive.fail = False
    rt = Runtime(Config(), drive, Cruise(), clock)
    rt.cycle_observers.append(after_the_write)
    result = rt.run(duration_s=3)
    assert result.reason == "signal", result
    warnings = [e for e in result.events if e.kind == "warning" and e.cause == "stop_unconfirmed"]
    assert len(warnings) == 1, result.events
    msg = warnings[0].message
    assert drive.drive_name in msg and "servo 2 (right): torque off not acknowledged" in msg and "watchdog" in msg


def test_a_start_up_failure_before_the_drive_was_enabled_reports_no_unconfirmed_stop():
    rt, drive, clock = make_runtime(Cruise())

    def no_bus():
        from vbnav.drivers.wheels import DriveError
        raise DriveError("no bus")
    drive.connect = no_bus
    result = rt.run(duration_s=1)
    assert result.reason == "drive" and not [e for e in result.events if e.cause == "stop_unconfirmed"], result


def test_an_estop_a_motor_did_not_take_is_reported():
    """The loop's own stop (an estop, a hold) disables the drive too: a motor that did not take it went
    unsaid there as well, the state saying 'estop' as if the wheels had stopped."""
    from runtime_helpers import RecordingDrive
    from vbnav.control.config import Config
    from vbnav.control.runtime.runtime import Runtime
    from vbnav.drivers.clock import SimClock

    class Unconfirmed(RecordingDrive):
        stops = 0

        def _stop_wheels(self):
            super()._stop_wheels()
            self.stops += 1
            return "servo 1 (left): torque off not acknowledged (no answer)"

    def operator(r, ctx, twist, wheels):
        if ctx.now_ns == T0 + 1_000_000_000:
            r.submit(OperatorCommand("estop", (), "op"))

    clock = SimClock()
    drive = Unconfirmed(clock)
    rt = Runtime(Config(), drive, Cruise(), clock)
    rt.cycle_observers.append(operator)
    result = rt.run(duration_s=2)
    warnings = [e for e in result.events if e.kind == "warning" and e.cause == "stop_unconfirmed"]
    assert len(warnings) == 2, result.events          # the estop's, and the end's: still not taken
    assert warnings[0].stamp_ns == T0 + 1_000_000_000 + PERIOD_NS and "servo 1 (left)" in warnings[0].message
    assert "sending it again every 10 cycles" in warnings[0].message, warnings[0]
    assert "still did not take the stop when the run ended" in warnings[1].message, warnings[1]
    # the estop's stop, then one every 10 cycles in the second that followed, then the end's disable and close
    assert drive.stops == 1 + 10 + 2, drive.stops


def test_a_drive_fault_whose_stop_another_motor_did_not_take_is_reported():
    """When the drive itself failed (a fault of one servo), the run did not report what the stop could not
    reach ('its own stop says so'), but the fault names only the servo that failed: the other servo, whose
    torque-off went unacknowledged, was passed over and the run ended as if both wheels had stopped."""
    from runtime_helpers import RecordingDrive
    from vbnav.control.config import Config
    from vbnav.control.runtime.runtime import Runtime
    from vbnav.drivers.clock import SimClock
    from vbnav.drivers.wheels import DriveFault, FaultKind

    class Overload(RecordingDrive):
        def _read(self):
            if self.clock.now_ns() >= T0 + 1_000_000_000:
                self._fault(DriveFault(FaultKind.HARDWARE_ERROR, "servo 2 (right)", "servo 2 (right): overload"))
            return super()._read()

        def _stop_wheels(self):
            super()._stop_wheels()
            return "servo 1 (left): torque off not acknowledged (no answer)"

    clock = SimClock()
    drive = Overload(clock)
    result = Runtime(Config(), drive, Cruise(), clock).run(duration_s=2)
    assert result.reason == "drive" and "overload" in result.message, result
    warnings = [e for e in result.events if e.kind == "warning" and e.cause == "stop_unconfirmed"]
    assert len(warnings) == 1 and "servo 1 (left): torque off not acknowledged" in warnings[0].message, \
        result.events


@pytest.mark.parametrize("at", ["start-up", "after an estop"])
def test_an_enable_that_failed_part_way_and_whose_stop_was_not_taken_is_reported(at):
    """An enable() that armed one motor and then failed (the other did not enter closed loop) stops what it
    armed; the run reported that stop only for a drive it had seen enabled, so a motor armed by the failed
    enable that did not take the stop went unsaid."""
    from runtime_helpers import RecordingDrive
    from vbnav.control.config import Config
    from vbnav.control.runtime.runtime import Runtime
    from vbnav.drivers.clock import SimClock
    from vbnav.drivers.wheels import DriveError

    class HalfArmed(RecordingDrive):
        enables, armed_left = 0, False

        def _activate(self):
            super()._activate()
            self.enables += 1
            if self.enables == (1 if at == "start-up" else 2):
                self.armed_left = True
                raise DriveError("axis1 (right) did not enter closed loop")

        def _stop_wheels(self):
            super()._stop_wheels()
            return "axis0 (left): did not take the stop: current_state 8" if self.armed_left else None

    def operator(r, ctx, twist, wheels):
        if ctx.now_ns == T0 + 500_000_000:
            r.submit(OperatorCommand("estop", (), "op"))
        elif ctx.now_ns == T0 + 800_000_000:
            r.submit(OperatorCommand("resume", (), "op"))

    clock = SimClock()
    drive = HalfArmed(clock)
    rt = Runtime(Config(), drive, Cruise(), clock)
    rt.cycle_observers.append(operator)
    result = rt.run(duration_s=2)
    assert result.reason == "drive" and "closed loop" in result.message, result
    warnings = [e for e in result.events if e.kind == "warning" and e.cause == "stop_unconfirmed"]
    assert len(warnings) == 1 and "axis0 (left): did not take the stop" in warnings[0].message, result.events
