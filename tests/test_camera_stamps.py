"""A camera that misbehaves stops the robot, on the vision thread (real clock) as in the loop's own read
(simulated clock), and the stop says why and which camera: frame stamps ahead of the robot's clock, stamps
that go backwards or repeat, frames without an image."""
import re
import threading

import numpy as np
import pytest

from runtime_helpers import PERIOD_NS, RecordingDrive, TickCamera
from vbnav.control.config import Config
from vbnav.control.runtime.interfaces import ControlContext, Controller, Twist, VisionStage
from vbnav.control.runtime.pipeline import VisionPipeline
from vbnav.control.runtime.runtime import Runtime
from vbnav.drivers.clock import SimClock

T0 = 1_000_000_000      # SimClock start
BAD_AT = T0 + 1_000_000_000
HOUR_NS = 3600 * 1_000_000_000


class Cruise(Controller):
    def __init__(self, hook=None):
        self.hook = hook

    def update(self, ctx: ControlContext) -> Twist:
        if self.hook:
            self.hook(ctx)
        return Twist(0.3, 0.0)


class BadCamera(TickCamera):
    """TickCamera whose frames due from ``BAD_AT`` on are rewritten by ``spoil(frame)``; it counts the frames
    it returned and when it was last read, so the loop can wait for the vision thread (lockstep)."""

    def __init__(self, clock, spoil, bad_at=BAD_AT):
        super().__init__(clock)
        self.spoil = spoil
        self.bad_at = bad_at
        self.returned = 0
        self.read_ns = -1

    def read(self, timeout_s=0.0):
        frame = super().read(timeout_s)
        if frame is not None and frame.stamp_ns >= self.bad_at:
            frame = self.spoil(frame)
        if frame is not None:
            self.returned += 1
        self.read_ns = self.clock.now_ns()
        return frame


class Seen(VisionStage):
    """Keeps the stamp and image of every frame it was given."""

    kind = "seen"

    def __init__(self):
        self.frames = []

    def process(self, frame, odom):
        self.frames.append((frame.stamp_ns, frame.image))
        return None


def run(spoil, inline, duration_s=3.0, stage=None, bad_at=BAD_AT):
    clock = SimClock()
    drive = RecordingDrive(clock)
    cam = BadCamera(clock, spoil, bad_at)
    pipeline = VisionPipeline(cam, [stage] if stage else [], clock, inline=inline)

    def lockstep(ctx):
        # the vision thread has read the camera at this cycle's time and handled every frame it got
        for _ in range(2000):
            if inline or pipeline.fault or (cam.read_ns >= ctx.now_ns and pipeline._frames_ended >= cam.returned):
                return
            threading.Event().wait(0.001)
        raise AssertionError("the vision thread did not keep up")

    rt = Runtime(Config(), drive, Cruise(lockstep), clock, pipeline)
    result = rt.run(duration_s=duration_s)
    return rt, result, drive


def assert_camera_stop(rt, result, drive, words):
    limit_ns = int(rt.cfg.camera.stale_after_s * 1e9)
    holds = [e for e in result.events if e.kind == "hold" and e.cause == "camera_stale"]
    assert holds, [e.as_dict() for e in result.events]
    hold = holds[0]
    # the last good frame came at most one camera period (15 Hz) before BAD_AT
    assert BAD_AT - int(1e9 / 15) + limit_ns < hold.stamp_ns <= BAD_AT + limit_ns + PERIOD_NS, hold
    assert "camera tick" in hold.message and all(w in hold.message for w in words), hold.message
    assert drive.last_motion_ns() > BAD_AT                              # it drove until then
    assert drive.stopped_since(hold.stamp_ns + 2 * PERIOD_NS)


@pytest.mark.parametrize("inline", [False, True], ids=["vision-thread", "loop-thread"])
def test_frames_stamped_ahead_of_the_robots_clock_are_refused_and_stop_the_robot(inline):
    """A camera whose stamps ran ahead of the loop's clock was never stale on the vision thread (the age,
    now - stamp, was negative for an hour): the robot drove on whatever it saw. A frame stamped more than
    ``FUTURE_STAMP_TOLERANCE_S`` after the robot's clock at its reception is refused, and the stale-camera
    check counts from when the last good frame was received on the robot's own clock too."""
    def ahead(frame):
        frame.stamp_ns += HOUR_NS
        return frame

    rt, result, drive = run(ahead, inline)
    assert result.reason == "duration", result
    assert_camera_stop(rt, result, drive, ["in the future"])


def repeat_stamp(frame):
    frame.stamp_ns = BAD_AT - 1       # after the last good frame's (BAD_AT - 10 ns), then again and again
    return frame


def backwards(frame):
    frame.stamp_ns = 2 * BAD_AT - frame.stamp_ns
    return frame


def nan_stamp(frame):
    frame.stamp_ns = float("nan")     # a driver that turned a missing device stamp into a float
    return frame


def no_image(frame):
    frame.image = None
    return frame


def empty_image(frame):
    frame.image = np.zeros((0, 0), np.uint8)
    return frame


@pytest.mark.parametrize("inline", [False, True], ids=["vision-thread", "loop-thread"])
@pytest.mark.parametrize("spoil,words", [(repeat_stamp, ["not after the last frame's"]),
                                         (backwards, ["not after the last frame's"]),
                                         (nan_stamp, ["not integer nanoseconds"]),
                                         (no_image, ["no image"]), (empty_image, ["no image"])],
                         ids=["repeated-stamps", "stamps-going-back", "nan-stamp", "none-image", "empty-image"])
def test_frames_whose_stamps_do_not_increase_or_without_an_image_go_to_no_stage_and_stop_the_robot(
        spoil, words, inline):
    """Frames whose stamps repeat or go backwards went to the stages (odometry from the past paired with a
    new image, a time step of zero), and the stop that followed, if any, said the last frame was old while
    frames kept coming; a NaN stamp made the camera's age NaN, never above the limit: never stale on the
    vision thread; a frame without an image ended the run as a bug in the frozen-image check. Each is
    refused before any check or stage, the robot stops as for a stale camera, and the hold says why."""
    stage = Seen()
    rt, result, drive = run(spoil, inline, stage=stage)
    assert result.reason == "duration", result
    assert_camera_stop(rt, result, drive, words)
    stamps = [t for t, _ in stage.frames]
    assert stamps == sorted(set(stamps)), "a stage got a frame whose stamp did not increase"
    assert all(img is not None and img.size for _, img in stage.frames)


def test_a_camera_read_that_blocks_for_ever_stops_the_robot_within_the_stated_time():
    """A driver whose read never returns (a hung USB transfer) holds the vision thread, not the loop: no
    frame is received after it, and the stale-camera hold stops the wheels camera.stale_after_s + P after
    the last frame, naming the camera; the run still ends (the blocked thread is left behind)."""
    release = threading.Event()
    blocked = threading.Event()

    class Hung(BadCamera):
        def read(self, timeout_s=0.0):
            if self.clock.now_ns() >= BAD_AT:
                blocked.set()
                release.wait()              # for ever, until the test lets it go
                return None
            return super().read(timeout_s)

    clock = SimClock()
    drive = RecordingDrive(clock)
    cam = Hung(clock, lambda f: f)
    pipeline = VisionPipeline(cam, [], clock, inline=False)

    def lockstep(ctx):
        for _ in range(2000):
            if blocked.is_set() or (cam.read_ns >= ctx.now_ns and pipeline._frames_ended >= cam.returned):
                return
            threading.Event().wait(0.001)
        raise AssertionError("the vision thread did not keep up")

    rt = Runtime(Config(), drive, Cruise(lockstep), clock, pipeline)
    try:
        result = rt.run(duration_s=3.0)
    finally:
        release.set()
    assert blocked.is_set() and result.reason == "duration", result
    assert_camera_stop(rt, result, drive, ["old"])


@pytest.mark.parametrize("inline", [False, True], ids=["vision-thread", "loop-thread"])
def test_frames_refused_now_and_then_are_said_not_dropped_silently(inline):
    """Every other frame without an image: the frames between keep the camera fresh (no stop is due), but
    the refused ones were dropped without a word. A warning names the camera, how many and why, at most
    every REFUSED_WARN_EVERY_S."""
    from vbnav.control.runtime.runtime import REFUSED_WARN_EVERY_S

    def every_other(frame):
        return no_image(frame) if frame.seq % 2 else frame

    rt, result, drive = run(every_other, inline, duration_s=3.0 + REFUSED_WARN_EVERY_S)
    assert result.reason == "duration", result
    # the vision thread's first frame may reach the loop a cycle or two after the start: held until then (the
    # robot does not move before the camera's first frame), and released at it
    assert not [e for e in result.events if e.kind == "hold" and e.cause != "camera_waiting"], \
        "a camera at half its rate is not stale"
    assert all(e.stamp_ns < BAD_AT for e in result.events if e.cause == "camera_waiting")
    warnings = [e for e in result.events if e.kind == "warning" and e.cause == "camera_frames_refused"]
    assert len(warnings) == 2, [e.as_dict() for e in result.events]
    first, second = warnings
    assert BAD_AT <= first.stamp_ns <= BAD_AT + 2 * int(1e9 / 15) + PERIOD_NS
    assert second.stamp_ns - first.stamp_ns >= REFUSED_WARN_EVERY_S * 1e9
    assert all("camera tick" in w.message and "no image" in w.message for w in warnings), warnings
    assert "1 frame refused" in first.message and "frames refused" in second.message, warnings


@pytest.mark.parametrize("inline", [False, True], ids=["vision-thread", "loop-thread"])
def test_a_camera_read_that_raises_ends_the_run_naming_the_camera_with_its_traceback(inline):
    """A read that raised something other than CameraError (a driver's bug, an OSError) ended the run as
    'exception in vision: OSError(...)' in the loop's own read, naming no camera, and on the vision thread
    without the traceback the run result keeps for an exception. Both paths now say the same: the camera,
    what was raised, and its traceback."""
    def unplugged(frame):
        raise OSError(19, "No such device")

    rt, result, drive = run(unplugged, inline)
    assert result.reason == "exception", result
    assert result.message.startswith("camera tick: ") and "No such device" in result.message, result.message
    assert rt.fault_traceback and "OSError" in rt.fault_traceback
    assert drive.last_motion_ns() > BAD_AT - 5 * PERIOD_NS
    assert drive.stopped_since(BAD_AT + int(1e9 / 15) + 2 * PERIOD_NS) and drive.log[-1][3] is False


@pytest.mark.parametrize("lag_s", [0.6, 3600.0], ids=["latency-above-the-limit", "an-hour-behind"])
def test_frames_that_keep_coming_with_old_stamps_are_stale_and_the_hold_says_they_arrive(lag_s):
    """Frames delivered later than camera.stale_after_s after their exposure, or stamped an hour behind the
    robot's clock (a device clock not synced to the host's): the camera is stale by their stamps and the
    robot stops at once, but the hold said only 'last frame 0.60 s old', as if no frame had come. It now says
    that the frames arrive, and how far behind the robot's clock their stamps are."""
    def behind(frame):
        frame.stamp_ns -= int(lag_s * 1e9)
        return frame

    rt, result, drive = run(behind, inline=False, bad_at=0)
    assert result.reason == "duration", result
    hold = next(e for e in result.events if e.kind == "hold" and e.cause == "camera_stale")
    assert hold.stamp_ns <= T0 + 2 * PERIOD_NS, hold     # the first frame is already too old
    assert "camera tick" in hold.message and re.search(rf"received 0\.0\d s ago, stamped {lag_s:.2f} s behind the "
                                                       r"robot's clock", hold.message), hold.message
    assert drive.stopped_since(hold.stamp_ns + 2 * PERIOD_NS)
