"""Teach and repeat, wired once: stages, controller, route files, runtime and telemetry of a run.

``Session(cfg, robot).teach(...)`` records a route while a controller drives;
``Session(cfg, robot).repeat(route)`` patrols it. ``vbnav teach``, ``vbnav repeat``
and the demo run through it; the operator's in-run mode switching
(controllers/operator.py) uses the same parts, ``Teaching`` and ``Repeating``,
inside one long run. The robot comes from ``runtime.factory.make_robot``, so a
simulated and a real robot run the same code.

This sits above the runtime (it composes runtime, stages, controllers, route
files and comms), so it lives beside ``route.py`` rather than in ``runtime/``,
which the plug-ins import.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence

from vbnav.control.comms.link import TelemetryLink
from vbnav.control.config import Config
from vbnav.control.controllers.manual import TeleopController
from vbnav.control.controllers.path import PathFollower, room_loop
from vbnav.control.controllers.repeat import RepeatController
from vbnav.control.route import Route, RouteWriter, check_route_config
from vbnav.control.runtime.factory import Robot
from vbnav.control.runtime.finishing import finishing
from vbnav.control.runtime.interfaces import Controller
from vbnav.control.runtime.runtime import ENDED_WELL, RunResult, Runtime
from vbnav.control.stages.repeat import RepeatStage
from vbnav.control.stages.teach import TeachStage

TEACH_LOOP_SPEED = 0.4   # m/s of the scripted teacher (controller.teach: room_loop)


MIN_ROUTE_KEYFRAMES = 2          # a repeat steers from one keyframe towards the next


class Teaching:
    """A route being taught: the TeachStage, and the RouteWriter that stores each keyframe as it comes."""

    vision_wait_s = 10.0     # how long close() waits for the vision thread still inside a frame of teach

    def __init__(self, cfg: Config, route_dir, overwrite: bool = False):
        model, mount = cfg.camera.to_model(), cfg.camera.mount.to_mount()
        self.stage = TeachStage(model, mount, cfg.vbc)
        self.writer = RouteWriter(Path(route_dir), cfg.robot.name, model, mount, overwrite=overwrite,
                                  calibration=cfg.camera.calibration_record())
        self.stamps: list[int] = []      # stamp_ns of each keyframe written, in order
        self.unwritten = ""              # why an interrupted teach's last keyframes were not written (close)

    def save(self, frame=None, results=None) -> None:
        """Write the keyframes the stage has emitted (a pipeline frame listener)."""
        for kf in self.stage.pop_keyframes():
            self.writer.append(kf)
            self.stamps.append(kf.stamp_ns)

    @property
    def note(self) -> Optional[str]:
        """Why the route ends before the last frame (TeachStage.end_note, ``unwritten``), or None."""
        return "; ".join(n for n in (self.stage.end_note, self.unwritten) if n) or None

    def close(self, complete: bool = True, vision=None) -> bool:
        """End of teaching: the stage's last keyframes, then the route marked complete (or not). A route
        of fewer than MIN_ROUTE_KEYFRAMES is never complete (a replacement would put an unusable route in
        the old one's place). True when the route was closed complete.

        An interrupted teach (a fault) keeps its last keyframes too, the one being pooled and the one at the
        last frame: dropped, up to vbc.keyframe_distance_m of the route taught was lost. Only when writing
        them fails again (the writer's own fault) is the route closed without them.

        vision: the run's VisionPipeline, once stopped (the run's end) or once the teach stage was taken out of
        its stages (a switch of mode). Its thread may still be inside a frame of the teach stage (a slow fsync
        of a keyframe): close() waits ``vision_wait_s`` for it (``wait_released``), and if it is still there,
        leaves the route as written (incomplete, loadable) rather than write it from two threads (two keyframes
        with one index)."""
        if vision is not None and not vision.wait_released(self.vision_wait_s):
            self.unwritten = (f"the vision thread was still inside a frame {self.vision_wait_s:g} s after teaching "
                              f"ended (a frame still being processed or written): the route was left as written, "
                              f"incomplete, with {len(self.stamps)} keyframes and without its last ones")
            return False
        try:
            self.stage.finish()
            self.save()
        except Exception as exc:
            if complete:
                raise
            self.unwritten = f"the last keyframes could not be written ({type(exc).__name__}: {exc})"
        complete = complete and len(self.stamps) >= MIN_ROUTE_KEYFRAMES
        self.writer.close(complete=complete)
        return complete


class Repeating:
    """The parts of a repeat of ``route``: the RepeatStage that localises, the RepeatController that steers."""

    def __init__(self, cfg: Config, route: Route):
        vcfg = cfg.vbc
        self.route = route
        check_route_config(route, cfg)
        self.stage = RepeatStage(route, vcfg, cfg.camera.to_model(), cfg.camera.mount.to_mount())
        self.controller = RepeatController(route, vcfg, cfg.robot.max_linear_speed, cfg.robot.max_angular_speed)


def teach_loop_speed(cfg: Config, speed: float = TEACH_LOOP_SPEED) -> float:
    """The scripted teacher's speed: ``speed``, or robot.max_linear_speed when that is lower (clipped by the
    limiter alone, the turn rate kept, it would drive a tighter arc than the one it chose)."""
    return min(speed, cfg.robot.max_linear_speed)


def teach_driver(cfg: Config) -> Controller:
    """Who drives while a route is taught (``controller.teach``): the operator by teleop, or on the
    simulated robot the scripted teacher once around the room's loop from ``sim.start_pose``."""
    if cfg.controller.teach == "room_loop":
        return PathFollower(room_loop(), teach_loop_speed(cfg), start=cfg.sim.start())
    return TeleopController(cfg.safety.command_timeout_s)


@dataclass
class TeachResult:
    keyframes: int
    keyframe_stamps: list        # stamp_ns of each keyframe, in order
    reason: str
    message: str
    timing: object
    complete: bool = True        # closed complete: ended well with MIN_ROUTE_KEYFRAMES or more
    directory: Optional[Path] = None   # where the keyframes are (beside the route when a replacement failed)
    note: Optional[str] = None   # why the route ends before the last frame (TeachStage.end_note, Teaching.unwritten)


@dataclass
class RepeatResult:
    completed: bool
    reason: str
    message: str
    keyframe_reached: int        # index of the keyframe the robot was heading for at the end
    keyframes: int

    @property
    def keyframes_passed(self) -> int:
        """How many keyframes the robot reached: all of them when it completed the route, else the ones before
        the keyframe it was heading for ('reached keyframe index + 1' said one more than it had)."""
        return self.keyframes if self.completed else self.keyframe_reached

    def progress_text(self) -> str:
        if self.completed:
            return f"reached keyframe {self.keyframes} of {self.keyframes}"
        return (f"passed {self.keyframes_passed} of {self.keyframes} keyframes (heading for keyframe "
                f"{self.keyframe_reached + 1})")
    events: list                 # safety events as dicts
    timing: object
    stops: int                   # safety holds on the way (not the start-up waits for a first frame)


Observer = Callable[..., None]       # (runtime, ctx, twist, wheel_command), every cycle


def repeat_status(status: dict, index: int, n: int) -> str:
    """The repeat's progress text; while no camera fix has placed the robot on the route, says so and why
    (a robot started away from the route's start otherwise stands still without a word), and so when it
    stopped after vbc.blind_distance_m without a trusted fix."""
    text = f"keyframe {index + 1}/{n}"
    if status.get("state") == "waiting":
        text += " (waiting for a first match with the route: start at its beginning, facing along it)"
    elif status.get("state") == "blind":
        text += f" ({status['reason']})"
    return text


class Session:
    """A teach or a repeat run on one robot from ``make_robot`` (one run: it closes the robot's drive).

    Telemetry: a run on the simulated clock (faster than real time) only records, into ``record`` (a
    path) or ``recorder`` (an McapRecorder shared by several runs, one segment each); a run in real
    time also publishes and takes network commands. An existing recording is refused unless
    ``record_overwrite``. ``progress`` gets a status line about once a second.
    """

    def __init__(self, cfg: Config, robot: Robot, record: Optional[str] = None, recorder=None,
                 progress: Optional[Callable[[str], None]] = None, record_overwrite: bool = False):
        if robot.pipeline is None:
            raise ValueError("teach and repeat need the camera: build the robot with_camera=True")
        self.cfg = cfg
        self.robot = robot
        self.record = record
        self.record_overwrite = record_overwrite     # replace an existing recording at ``record``
        self.recorder = recorder
        self.progress = progress
        self._spent = False
        self.recording_error: Optional[str] = None     # the recording asked for failed (said on stderr)

    def teach(self, controller: Controller, route_dir, overwrite: bool = False, duration_s: Optional[float] = None,
              observers: Sequence[Observer] = ()) -> TeachResult:
        """Drive with ``controller`` while a TeachStage records keyframes into ``route_dir``."""
        self._claim()
        teaching = Teaching(self.cfg, route_dir, overwrite)
        try:
            result = self._run(controller, teaching.stage, teaching.save, "teach", duration_s, observers,
                               lambda: f"{teaching.stage.n_keyframes} keyframes", route=str(route_dir))
        except BaseException:
            with finishing("closing the route"):
                teaching.close(complete=False, vision=self.robot.pipeline)
            raise
        # A second Ctrl-C must not cut the route short: its last keyframes, complete, the replacement swapped in.
        with finishing("writing the route's last keyframes"):
            complete = teaching.close(complete=result.reason in ENDED_WELL,   # a fault: interrupted
                                      vision=self.robot.pipeline)
        return TeachResult(len(teaching.stamps), list(teaching.stamps), result.reason, result.message,
                           result.timing, complete, teaching.writer.directory, teaching.note)

    def repeat(self, route: Route, duration_s: Optional[float] = None, observers: Sequence[Observer] = (),
               segment: str = "repeat") -> RepeatResult:
        """Patrol ``route``; ``observers`` run every cycle (a scenario's events, a ground-truth trace)."""
        self._claim()
        rep = Repeating(self.cfg, route)
        n = len(route.keyframes)
        result = self._run(rep.controller, rep.stage, None, segment, duration_s, observers,
                           lambda: repeat_status(rep.controller.status(), rep.stage.index, n),
                           route=str(route.path))
        stops = result.holds_on_the_way()
        return RepeatResult(result.reason == "finished", result.reason, result.message, rep.stage.index, n,
                            [e.as_dict() for e in result.events], result.timing, stops)

    # -- one run -------------------------------------------------------------
    def _run(self, controller, stage, frame_listener, segment: str, duration_s, observers,
             status: Callable[[], str], route: Optional[str] = None) -> RunResult:
        robot, pipeline = self.robot, self.robot.pipeline
        pipeline.stages = [stage, *pipeline.stages]     # the run's stage first, then the safety stages
        if frame_listener is not None:
            pipeline.frame_listeners.append(frame_listener)
        rt = Runtime(self.cfg, robot.drive, controller, robot.clock, pipeline)
        rt.cycle_observers.extend(observers)
        link = self._attach_telemetry(rt, segment)
        if link is not None:
            link.route = route          # the state's route (vbnav monitor shows it)
        echo = None
        if not robot.clock.simulated and self.progress is not None:   # a console run in real time
            from vbnav.control.runtime.progress import EventEcho
            echo = EventEcho().attach(rt)
        result = None
        try:
            result = rt.run(duration_s, self._progress_fn(segment.split()[0], status))
        finally:
            with finishing():       # a second Ctrl-C must not cut the recording short
                if link is not None:
                    link.close(result)
                    self.recording_error = link.recording_error
                if echo is not None:
                    echo.close()
        return result

    def _claim(self) -> None:
        if self._spent:
            raise RuntimeError("a robot serves one run (the run closes its drive): build another with make_robot")
        self._spent = True

    def _attach_telemetry(self, rt: Runtime, segment: str):
        """Record (and in real time publish); None when there is nothing to record or publish."""
        network = not self.robot.clock.simulated
        if self.recorder is None and not self.record and not network:
            return None
        return TelemetryLink.attach(rt, self.cfg, record=self.record, recorder=self.recorder, network=network,
                                    segment=segment, record_overwrite=self.record_overwrite)

    def _progress_fn(self, label: str, status: Callable[[], str]):
        say = self.progress
        if say is None:
            return None

        def fn(rt: Runtime) -> None:
            t = (rt.clock.now_ns() - rt._start_ns) * 1e-9
            safety = "ok" if rt.safety.may_move else "STOP " + ",".join(rt.safety.reasons())
            say(f"{label}: t={t:5.1f}s  travelled {rt.odometry.distance:5.1f} m  {status()}  "
                f"v={rt.last_twist.v:+.2f} w={rt.last_twist.w:+.2f}  {safety}")
        return fn
