"""The robot does not move blind at start-up: until the camera's first fresh frame, and until the first
estimate of each safety-critical stage, the wheels are held from the first cycle. The hold says what it
waits for; once camera.stale_after_s + 2 s (or safety.estimate_timeout_s + 2 s) have passed without it, the
stale hold takes over as before."""
from vbnav.control.controllers.manual import TeleopController
from vbnav.control.runtime.interfaces import Controller, Estimate, Twist, VisionStage
from vbnav.control.runtime.runtime import OperatorCommand
from runtime_helpers import PERIOD_NS, make_runtime

T0 = 1_000_000_000  # SimClock start
CAMERA_NS = int(1e9 / 15)   # TickCamera's period


def teleop_stream(r, ctx, twist, wheels):
    """An operator who sends 0.3 m/s at 10 Hz from the first cycle on."""
    if (ctx.now_ns - T0) % 100_000_000 == 0:
        r.submit(OperatorCommand("teleop", (0.3, 0.0), "test"))


def moving(drive):
    return [t for t, l, r, p in drive.log if p and (l != 0 or r != 0)]


def test_teleop_at_start_does_not_move_the_wheels_before_the_cameras_first_frame():
    first = T0 + 1_000_000_000
    rt, drive, clock = make_runtime(TeleopController(timeout_s=0.5),
                                    cam_kw={"stop_at_ns": T0, "resume_at_ns": first})
    rt.cycle_observers.append(teleop_stream)
    result = rt.run(duration_s=2.0)
    first_frame = T0 + CAMERA_NS * -(-1_000_000_000 // CAMERA_NS)    # the first due at or after 1 s
    assert min(moving(drive)) >= first_frame, (min(moving(drive)) - T0) / 1e6
    assert max(moving(drive)) > first_frame + 500_000_000      # it drives once the frame came
    hold = next(e for e in result.events if e.kind == "hold" and e.cause == "camera_waiting")
    assert hold.stamp_ns == T0 and "camera tick" in hold.message and "first frame" in hold.message, hold
    assert "stale" not in hold.message and "old" not in hold.message
    release = next(e for e in result.events if e.kind == "release" and e.cause == "camera_waiting")
    assert first_frame <= release.stamp_ns < first_frame + PERIOD_NS      # at the frame, no release_s debounce
    refused = [e for e in result.events if e.kind == "rejected" and e.cause == "teleop"]
    assert refused and "camera_waiting" in refused[0].message
    assert not result.count("hold", "camera_stale")


class LateObstacles(VisionStage):
    """A safety-critical stage whose first estimate comes only for frames from ``first_ns`` on."""
    kind = "obstacles"
    safety_critical = True

    def __init__(self, first_ns):
        self.first_ns = first_ns

    def process(self, frame, odom):
        if frame.stamp_ns < self.first_ns:
            return None
        return Estimate(frame.stamp_ns, self.kind, True, None, {"speed_scale": 1.0})


def test_teleop_at_start_does_not_move_the_wheels_before_the_obstacle_stages_first_estimate():
    first = T0 + 1_000_000_000
    rt, drive, clock = make_runtime(TeleopController(timeout_s=0.5), stages=[LateObstacles(first)])
    rt.cycle_observers.append(teleop_stream)
    result = rt.run(duration_s=2.0)
    assert min(moving(drive)) >= first, (min(moving(drive)) - T0) / 1e6
    assert max(moving(drive)) > first + 500_000_000
    hold = next(e for e in result.events if e.kind == "hold" and e.cause == "obstacles_waiting")
    assert hold.stamp_ns == T0 and "first obstacles estimate" in hold.message, hold
    assert not result.count("hold", "camera_waiting")     # the camera delivered in the first cycle: no hold
    assert not result.count("hold", "obstacles_stale")


class Cruise(Controller):
    """A controller that drives without vision."""

    def update(self, ctx):
        return Twist(0.3, 0.0)


def test_a_camera_that_never_delivers_holds_from_the_first_cycle_then_is_stale_as_before():
    rt, drive, clock = make_runtime(Cruise(), cam_kw={"stop_at_ns": T0})
    rt.pipeline.camera.error = "tick: no such device"
    result = rt.run(duration_s=4.0)
    assert not moving(drive)
    assert drive.physics.powered is False
    waiting = next(e for e in result.events if e.kind == "hold" and e.cause == "camera_waiting")
    assert waiting.stamp_ns == T0
    grace_ns = int((rt.cfg.camera.stale_after_s + 2.0) * 1e9)
    stale = next(e for e in result.events if e.kind == "hold" and e.cause == "camera_stale")
    assert T0 + grace_ns < stale.stamp_ns <= T0 + grace_ns + PERIOD_NS
    assert "old" in stale.message and stale.message.endswith(": tick: no such device"), stale.message
    # the waiting hold gave way to the stale one in the same cycle: the robot was held throughout
    release = next(e for e in result.events if e.kind == "release" and e.cause == "camera_waiting")
    assert release.stamp_ns == stale.stamp_ns
    assert "camera_stale" in rt.safety.holds and "camera_waiting" not in rt.safety.holds
