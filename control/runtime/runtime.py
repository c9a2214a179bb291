"""The runtime: one fixed-rate loop owning the order read -> update -> write.

Per cycle: read the wheels, integrate odometry, pick up the latest vision
estimates (inline pipeline: run them), apply operator commands, run the
controller, apply limits and the safety monitor, write the wheels, notify
observers (telemetry). Any exception, signal, deadline streak or drive loss
commands zero, disables the drive in the same cycle, and is reported.

A stall is a fault: a cycle that starts more than ``loop.stall_periods`` periods
after the tick it follows (a frozen process, a 2 s garbage collection, a blocked
callback) trips the latched, non-fatal ``stall`` stop in that cycle: the wheels
go to zero and the drive is disabled until an operator ``resume``; teleop sent
before the stall is refused and the teleop command is forgotten, so moving again
needs fresh commands; a resume that arrived during the stall (before it was detected) is refused. During the stall itself the drive keeps its last command:
only the drive's own watchdog can act inside it.

A lost drive bus is not the end at once: the drive goes to ERROR (its own
watchdog stops the wheels), the loop zeroes its command and trips the latched,
non-fatal ``drive_lost`` stop, and keeps cycling without touching the drive
while ``DriveRecovery`` (drive_recovery.py) lets it reconnect, for up to
``drive.reconnect_window_s``. Back in time: it re-ran its safe bring-up, a
``drive_reconnected`` event says so, and the robot stays stopped until an
operator ``resume`` (refused while the drive is still away). Not back in time,
or back with a fault of its own: the run ends with reason ``drive`` and the
cause. Any other drive fault ends the run at once.

Started by systemd (``vbnav service install``), the loop is the service's
heartbeat (systemd_notify.py): READY=1 after its first cycle, a WATCHDOG=1 ping
from completed cycles (throttled, non-blocking), STOPPING=1 when it ends; a
stalled loop stops the pings and systemd restarts the process. An operator's estop
outlives that restart: it is kept in ``safety.latch_file`` (estop_latch.py, written
off the loop thread), and a run that finds the file starts latched, the drive never
enabled until a resume.

Operator commands reach the loop through a ``CommandMailbox`` (mailbox.py):
``submit`` from any thread, drained once per cycle. The runtime applies
``estop`` and ``resume`` itself and forwards every other command to the
controller's ``handle_command`` (interfaces.py), which applies it or refuses it
with a reason (or, for work it does off the loop thread, answers ``PENDING`` and
later ``complete_command``); a refusal is a ``rejected`` safety event.
``command_observers`` hear each command before it is applied (and a pending one
again before its answer), ``command_listeners`` after it took effect.
"""
from __future__ import annotations

import faulthandler
import math
import os
import signal
import sys
import threading
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

from vbnav.control.runtime.finishing import STOP_SIGNALS as _FINISHING_STOP_SIGNALS
from vbnav.control.runtime.drive_recovery import DriveRecovery, Outcome
from vbnav.control.runtime.estop_latch import (LatchHold, LatchWriter, folder_problem, latch_path, latch_record,
                                              read_latch)
from vbnav.drivers.atomic_file import write_atomic
from vbnav.control.runtime.interfaces import APPLIED, STOP, CommandOutcome, ControlContext, Controller, Twist
from vbnav.control.runtime.kinematics import TwistLimiter
from vbnav.control.runtime.loop import FixedRateLoop, TimingSummary
from vbnav.control.runtime.mailbox import CommandMailbox, OperatorCommand, RefusalThrottle
from vbnav.control.runtime.odometry import Odometry, OdometryHistory
from vbnav.control.runtime.pipeline import VisionPipeline
from vbnav.control.runtime.safety import WAITING, SafetyMonitor
from vbnav.control.runtime.systemd_notify import SystemdNotifier
from vbnav.drivers.camera import CameraError
from vbnav.drivers.clock import Clock
from vbnav.drivers.wheels import DriveError, DriveState, WheelDrive, WheelState


def _nothing_to_undo() -> None:
    pass


def _new_threads_leave_the_loop_scheduling():
    """Linux threads inherit the scheduling policy and CPU set of the thread that creates them, so a thread
    started from the loop thread after ``_apply_scheduling`` (a lazily started writer, an executor) would
    run SCHED_FIFO on the loop's CPUs and could starve it. Every thread started through ``threading`` from
    now on first puts itself back to normal scheduling on the process's CPUs (the profile hook runs once,
    in the new thread, before its target). Returns the undo."""
    cpus = os.sched_getaffinity(0)      # the process's set: called before the loop thread takes its own

    earlier = threading.getprofile()   # a profiler's hook, if one is set: handed back to the new thread

    def back_to_normal(frame, event, arg):
        sys.setprofile(earlier)
        try:
            if os.sched_getscheduler(0) != os.SCHED_OTHER:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            os.sched_setaffinity(0, cpus)
        except OSError:
            pass

    threading.setprofile(back_to_normal)
    return lambda: threading.setprofile(earlier)


def _set_process_affinity(cpus: set[int]) -> Callable[[], None]:
    """Every thread of this process (sched_setaffinity takes a thread id) onto ``cpus``; returns the undo.
    Under systemd the unit's CPUAffinity= did this at start; a run started by hand does it here."""
    old = {}
    try:
        for tid in map(int, os.listdir("/proc/self/task")):
            try:
                before = os.sched_getaffinity(tid)
                os.sched_setaffinity(tid, cpus)
                old[tid] = before
            except ProcessLookupError:    # a thread that ended meanwhile
                continue
    except OSError:
        _restore_affinity(old)
        raise

    return lambda: _restore_affinity(old)


def _restore_affinity(old: dict) -> None:
    for tid, cpus in old.items():
        try:
            os.sched_setaffinity(tid, cpus)
        except OSError:
            pass


#: How a run may end and what it made (a route, a map) still be whole: its plan done, its time up, or
#: stopped by the operator (a stop command, Ctrl-C).
ENDED_WELL = ("finished", "duration", "stopped", "signal")
#: The signals that end a run (fatal ``signal``), the wheels to zero and the drive disabled at the next cycle:
#: finishing.STOP_SIGNALS, which the close-down holds too (one tuple, so the two never differ).
STOP_SIGNALS = _FINISHING_STOP_SIGNALS
#: Job-control signals the process gets from its own terminal I/O: SIGTTOU when a background run writes to its
#: terminal under ``stty tostop``, SIGTTIN when it reads it. Their default stops the process where it is, the
#: wheels at their last command; they are no operator's request to stop (that is SIGTSTP, Ctrl-Z), and a handler
#: would not do either: the kernel sends the signal again each time the interrupted write is retried, so the loop
#: thread would never get past its progress line. While the loop runs they are ignored: the line is written, a
#: read of the terminal fails (EIO), and the run goes on.
IGNORED_SIGNALS = (signal.SIGTTOU, signal.SIGTTIN)
#: Ends that are a device's failure, not the job's (the commands' exit code 3).
DEVICE_FAULTS = ("drive", "camera")
#: A stop a motor did not take is sent again this often while the loop runs (the loop keeps reading the
#: motors, and a Dynamixel bus watchdog counts every packet: fed by the reads it never trips). Once a tenth of a
#: second, the devices' own watchdog time (100 ms by default), so a motor that hears again stops about when its
#: watchdog would have. A resend to motors that answer costs a few short packets, well inside a cycle beside the
#: read (its answer window is half a period); one to a motor that does not answer costs an answer window per
#: packet and may make that cycle late, but only one cycle in ten: never a missed-deadline streak.
RESTOP_EVERY_S = 0.1
#: Frames the pipeline refuses (no image, a stamp ahead of the clock or not after the last one) are said in a
#: ``warning`` ``camera_frames_refused``: at the first, then at most this often with how many since (a camera
#: refusing every other frame would otherwise say so 7 times a second). Refused on, they stop the robot as a
#: stale camera, whose hold says why.
REFUSED_WARN_EVERY_S = 5.0


def _failure_reason(exc: Exception) -> str:
    """The run's end for an exception other than a DriveError: a camera that failed (CameraError: not there,
    gone, wrong format) is a device's failure wherever it raised (start-up, the loop's read); anything else is
    a bug. The vision thread's camera read follows the same rule (``VisionPipeline.fault_reason``)."""
    return "camera" if isinstance(exc, CameraError) else "exception"


class _StoppedDuringStartUp(Exception):
    """A stop signal came while the devices came up: the run ends before the drive is enabled."""


@dataclass
class RunResult:
    reason: str                       # "finished", "duration", "stopped", or a fatal cause
    message: str
    timing: TimingSummary
    events: list = field(default_factory=list)   # the first and the last safety events (safety.EventLog)
    events_dropped: int = 0           # events left out of ``events`` between the first and the last ones
    events_dropped_after: int = 0     # how many of ``events`` come before the ones left out
    event_counts: dict = field(default_factory=dict)   # (kind, cause) -> events over the whole run
    events_gap: str = ""              # what a report says where events were left out ("" when none were)

    @property
    def ok(self) -> bool:
        return self.reason in ("finished", "duration", "stopped")

    @property
    def cycles(self) -> int:
        """The cycles the loop ran, the last one (which ended the run) included: ``timing.cycles``, one count."""
        return self.timing.cycles

    def count(self, kind: str, cause: Optional[str] = None) -> int:
        """Safety events of ``kind`` (and ``cause``) over the whole run, those left out of ``events`` included."""
        if not self.event_counts:
            return sum(1 for e in self.events if e.kind == kind and (cause is None or e.cause == cause))
        return sum(n for (k, c), n in self.event_counts.items() if k == kind and (cause is None or c == cause))

    def holds_on_the_way(self) -> int:
        """Safety holds over the whole run but the start-up waits for a first frame or estimate (causes
        ``<what>_waiting``): every run has those, and a repeat counted them as stops on the way."""
        if not self.event_counts:
            return sum(1 for e in self.events if e.kind == "hold" and not str(e.cause).endswith(WAITING))
        return sum(n for (k, c), n in self.event_counts.items() if k == "hold" and not str(c).endswith(WAITING))

    def event_report(self) -> list:
        """The kept events in order, with ``events_gap`` (a str) where events were left out."""
        out: list = list(self.events)
        if self.events_dropped:
            out.insert(self.events_dropped_after, self.events_gap)
        return out


class Runtime:
    def __init__(self, cfg, drive: WheelDrive, controller: Controller, clock: Clock,
                 pipeline: Optional[VisionPipeline] = None):
        self.cfg = cfg
        self.drive = drive
        self.controller = controller
        self.clock = clock
        self.pipeline = pipeline
        self.loop = FixedRateLoop(cfg.loop.rate_hz, clock, cfg.loop.overrun_policy)
        self.limiter = TwistLimiter.from_config(cfg.robot)
        self.kin = self.limiter.kinematics
        self.odometry = Odometry(cfg.robot.wheel_radius, cfg.robot.wheel_separation)
        self.odometry_history = OdometryHistory()   # stamped poses: stages get the pose of their frame
        if pipeline is not None:
            pipeline.history = self.odometry_history
        self.safety = SafetyMonitor(release_s=cfg.safety.release_s)
        self.mailbox = CommandMailbox(clock.now_ns, int(cfg.safety.command_timeout_s * 1e9))
        self.cycle_observers: list[Callable[["Runtime", ControlContext, Twist, tuple], None]] = []
        # called before each drained command is applied, and before the answer of one that was pending:
        # (runtime, command, now_ns)
        self.command_observers: list[Callable[["Runtime", OperatorCommand, int], None]] = []
        # called after a command took effect (not for refused ones): (runtime, command, outcome, now_ns)
        self.command_listeners: list[Callable[["Runtime", OperatorCommand, CommandOutcome, int], None]] = []
        # called when the controller took a command to finish later (PENDING: a mode switch loading its route),
        # before its answer: (runtime, command, now_ns)
        self.pending_listeners: list[Callable[["Runtime", OperatorCommand, int], None]] = []
        # a listener prints safety events on the console as they happen (progress.EventEcho.attach): what the
        # start-up says as a safety event is not printed a second time
        self.safety_on_console = False
        self.wheel_command = (0.0, 0.0)
        self.last_twist = STOP
        self.wheels: Optional[WheelState] = None
        self.ctx: Optional[ControlContext] = None
        self.cycle = 0
        self._signal: Optional[int] = None
        self._end_asked: Optional[tuple[str, str]] = None    # end_run's (reason, message)
        self._enabled = False
        self._unstopped: Optional[str] = None    # what the last stop did not reach, until a resend is taken
        self._unstopped_told_end = False         # its warning said the run ends with it (no resend follows)
        self._restop_every = max(1, round(RESTOP_EVERY_S * cfg.loop.rate_hz))   # cycles between resends
        self._restop_cycle = 0
        self._end: Optional[tuple[str, str]] = None
        self._last_now = 0
        self._start_ns = 0
        self._deadline_ns: Optional[int] = None
        self._recovery: Optional[DriveRecovery] = None   # while the drive's bus is lost
        self._teleop_reports = RefusalThrottle()          # refused teleop without ack: once a second per reason
        self._in_hand: list[OperatorCommand] = []          # drained commands not yet answered
        self._holds_seen: set[str] = set()               # holds other than the controller's, last cycle
        self._refused_told = 0                           # the pipeline's refused frames said in a warning
        self._refused_told_ns: Optional[int] = None      # when the last camera_frames_refused warning was
        self._controller_holds: set[str] = set()         # causes of the controller's safety_conditions
        self._estimate_kinds: set[str] = set()           # estimate kinds checked for freshness, or still held
        # (time, what): a resume that arrived before this time (a stall detected, the lost drive back) was sent
        # before anyone could know of it, and does not clear it
        self._resume_after: Optional[tuple[int, str]] = None
        # the estop taken in the drain being applied (_apply_commands): a resume behind it in that drain is refused
        self._estop_in_drain: Optional[str] = None
        self.fault_traceback: Optional[str] = None
        # sd_notify when started by systemd ($NOTIFY_SOCKET): READY, watchdog pings per cycle, STOPPING
        self.notifier: Optional[SystemdNotifier] = SystemdNotifier.from_environ()
        # an operator's estop kept across restarts (estop_latch.py): the file, and its writer while a run runs
        self.latch_file: Optional[Path] = latch_path(cfg)
        self._latch_writer: Optional[LatchWriter] = None
        self._latch_hold: Optional[LatchHold] = None    # while a run runs: `vbnav estop clear` refuses
        self._latch_lock = threading.Lock()    # the writer's end against an estop kept after the run ended

    # -- thread-safe inputs -------------------------------------------------
    def submit(self, cmd: OperatorCommand) -> Optional[str]:
        """Hand an operator command to the loop from any thread: None if accepted, else the refusal reason."""
        refused = self.mailbox.post(cmd)
        if refused and cmd.kind == "estop" and self.latch_file is not None:   # the mailbox refuses an estop only
            refused += self._keep_late_estop(cmd)                             # once the run ended
        return refused

    def _keep_late_estop(self, cmd: OperatorCommand) -> str:
        """Any thread, after the run ended (the process still closing, a restart to come): the estop is kept in
        the latch file, through the run's writer while it still writes (the newest post wins), else at once.
        Returns what the refusal adds."""
        path = self.latch_file
        record = latch_record(f"estop from {cmd.source}" + (f": {cmd.args[0]}" if cmd.args else "") +
                              " (after the run ended)", self.clock.now_ns())
        with self._latch_lock:
            try:
                # Through the run's writer, waited for: the answer below says the estop is kept, and it was
                # sent while the write was only posted (and said 'kept' of a folder that could not be written).
                why = self._latch_writer.write_and_wait(record) if self._latch_writer is not None else None
                if self._latch_writer is None:
                    write_atomic(path, record)
            except OSError as exc:
                why = str(exc.strerror or exc)
        if why:
            return f"; it could not be kept in {path} ({why}): the next run does not start latched"
        return f"; the estop is kept in {path}: the next run starts latched until a resume"

    def request_stop(self, signum: int = signal.SIGTERM) -> None:
        self._signal = signum

    def end_run(self, reason: str, message: str) -> None:
        """Any thread: a fatal ``reason`` (a FATAL cause) ends the run at the next cycle, the wheels stopped."""
        self._end_asked = (reason, message)

    # -- main --------------------------------------------------------------
    def run(self, duration_s: Optional[float] = None,
            progress: Optional[Callable[["Runtime"], None]] = None, progress_every_s: float = 1.0) -> RunResult:
        handlers = self._install_signal_handlers()
        restore_scheduling = _nothing_to_undo
        notifier = self.notifier
        if notifier is not None and notifier.watchdog_period_ns and not faulthandler.is_enabled():
            faulthandler.enable()    # systemd's watchdog kills with SIGABRT: the journal then shows where it hung
        next_progress = [0]
        looping = False      # the loop started: a failure from now on is no start-up failure
        self.mailbox.reopen()
        self._open_latch()        # before the devices: under a kept estop the wheels are never powered
        try:
            self.drive.connect()
            for cleared in self.drive.watchdogs_cleared_at_start:    # the last run died driving: say so
                self.safety.note(self.clock.now_ns(), "warning", "drive_watchdog_cleared", cleared)
            if self.pipeline is not None:
                self.pipeline.start()
            # after the pipeline's threads started: threads inherit their creator's CPU set and policy, and
            # the vision threads must not run SCHED_FIFO on the loop's CPUs
            restore_scheduling = self._apply_scheduling()
            if self._signal is not None:
                # a stop asked for while the devices came up (a camera's slow discovery): never powered
                raise _StoppedDuringStartUp(signal.Signals(self._signal).name)
            if not self.safety.latched:    # a kept estop (latch file): enabled by the cycle after the resume
                self._enabled = True      # before enable(): what a failed enable armed is stopped and reported too
                self._unstopped = None
                self.drive.enable()
            self._start_ns = self.clock.now_ns()
            self._deadline_ns = None if duration_s is None else self._start_ns + int(duration_s * 1e9)
            next_progress[0] = self._start_ns

            def step(cycle: int, now_ns: int) -> bool:
                keep = self._cycle(cycle, now_ns)
                if notifier is not None:     # the loop's heartbeat: a stalled loop stops systemd's pings
                    if cycle == 0:
                        notifier.ready(f"loop running at {self.loop.rate_hz:g} Hz")
                    notifier.beat()
                if progress is not None and now_ns >= next_progress[0]:
                    next_progress[0] = now_ns + int(progress_every_s * 1e9)
                    progress(self)
                return keep

            looping = True
            timing = self.loop.run(step)
        except _StoppedDuringStartUp as stop:
            self._finish(self.clock.now_ns(), "signal", f"received {stop} during start-up, before the drive "
                                                        f"was enabled")
            timing = self.loop.timing.summary(self.loop.rate_hz)
        except KeyboardInterrupt:  # pragma: no cover - handlers normally catch it first
            self._make_safe()
            self._end = ("signal", "SIGINT")
            timing = self.loop.timing.summary(self.loop.rate_hz)
        except Exception as exc:
            # Failure before or outside a cycle (connect, enable): still leave the wheels safe.
            self.fault_traceback = traceback.format_exc()
            self._make_safe()
            # a device that is not there is no bug: the commands report "drive" and "camera" as device errors
            reason = "drive" if isinstance(exc, DriveError) else _failure_reason(exc)
            where = "start-up" if not looping else f"outside the cycle (after cycle {self.cycle}, e.g. progress)"
            self.safety.trip(self.clock.now_ns(), reason, f"{where}: {exc}")
            self._end = (reason, f"{where}: {exc}")
            timing = self.loop.timing.summary(self.loop.rate_hz)
        finally:
            if notifier is not None:
                end = self._end or ("stopped", "loop stopped")
                notifier.stopping(f"{end[0]}: {end[1]}")
                notifier.close()
            self._end_recovery()
            self._make_safe()
            self._refuse_waiting_commands()
            try:
                lost = self._bus_lost()
                self.drive.close()
                self._closed(lost)
            except Exception:
                pass
            self._close_latch()      # the estop or resume of the last cycles on disk before the process ends
            if self.pipeline is not None:
                self.pipeline.stop()
            self._restore_signal_handlers(handlers)
            restore_scheduling()
        reason, message = self._end or ("stopped", "loop stopped")
        log = self.safety.events
        return RunResult(reason, message, timing, list(log), log.dropped, log.dropped_after,
                         dict(log.counts), log.gap_line())

    # -- one cycle -----------------------------------------------------------
    def _cycle(self, cycle: int, now: int) -> bool:
        self.cycle = cycle
        dt = (now - self._last_now) * 1e-9 if self._last_now else 1.0 / self.loop.rate_hz
        self._last_now = now
        stage = "read"
        try:
            if self._signal is not None:
                name = signal.Signals(self._signal).name
                return self._finish(now, "signal", f"received {name}")
            if self._end_asked is not None:
                return self._finish(now, *self._end_asked)
            if self._latch_writer is not None:
                self._latch_warnings(now)
            if self.loop.timing.streak >= self.cfg.loop.max_missed_streak:
                return self._finish(now, "deadline",
                                    f"{self.loop.timing.streak} consecutive missed deadlines "
                                    f"(period {1e3 / self.loop.rate_hz:.1f} ms, last compute "
                                    f"{self.loop.timing.last_compute_ns() * 1e-6:.1f} ms)")
            self._check_stall(now)
            wheels = self._read_wheels(now)
            if wheels is None:
                return False
            if not all(map(math.isfinite, wheels.position)):
                # A NaN or inf wheel angle (a failed encoder, a corrupted answer) would make the pose NaN for
                # the rest of the run: the drive's fault, before the odometry takes it.
                return self._finish(now, "drive", f"{self.drive.drive_name} read a non-finite wheel position "
                                                  f"{wheels.position}: the odometry cannot go on")
            self.wheels = wheels
            if wheels.drive_state is DriveState.ERROR and self._recovery is None:
                return self._finish(now, "drive", "drive fault: " + "; ".join(map(str, wheels.faults)))
            stage = "odometry"
            odom = self.odometry.update(wheels)
            self.odometry_history.record(wheels.stamp_ns or now, odom)
            stage = "vision"
            estimates = {}
            if self.pipeline is not None:
                self.pipeline.poll(now, odom)
                if self.pipeline.fault:
                    self.fault_traceback = self.pipeline.fault_traceback
                    return self._finish(now, self.pipeline.fault_reason, self.pipeline.fault)
                estimates = dict(self.pipeline.latest)
                self._check_camera(now)
                self._apply_speed_scales(now, estimates)
            ctx = ControlContext(now, dt, odom, wheels, estimates, cycle)
            self.ctx = ctx
            # before the commands, as the camera and obstacle holds: a teleop taken in the cycle a stale-estimate
            # hold begins is refused, not answered 'applied' and then dropped by the hold
            self._check_estimates(ctx)
            stage = "commands"
            self._apply_commands(now)
            stage = "controller"
            if cycle == 0:
                self.controller.start(ctx)
            twist = self.controller.update(ctx)
            if not (math.isfinite(twist.v) and math.isfinite(twist.w)):
                # A NaN or inf is a bug upstream (a NaN pose, a division by zero): the limiter's clip would
                # turn it into full speed, so it ends the run like an exception.
                raise FloatingPointError(f"{type(self.controller).__name__} commanded v={twist.v} w={twist.w}")
            for cause, (active, message) in self.controller.safety_conditions().items():
                self._controller_holds.add(cause)
                self.safety.hold(now, cause, active, message)
            self._forget_teleop_on_new_hold(now)
            stage = "safety"
            if self.safety.may_move or self.safety.may_turn:
                if self.safety.may_move:
                    s = self.safety.speed_scale
                    twist = self.limiter.apply(Twist(twist.v * s, twist.w * s), dt)
                else:                         # held by an obstacle ahead, a round robot: only the turn
                    twist = self.limiter.turn_only(twist.w, dt)
                if not self._enabled:
                    self._enabled = True      # before enable(): a failed enable's stop is reported by _make_safe
                    self._unstopped = None    # driven again: the stop that was not taken is moot
                    self.drive.enable()
            else:
                twist = self.limiter.stop()
                if self._enabled:
                    self.drive.write(0.0, 0.0)
                    self.drive.disable()
                    self._enabled = False
                    self._unconfirmed_stop(now, self.drive.stop_failure, ending=False)
                elif self._unstopped and self._recovery is None and cycle >= self._restop_cycle:
                    self._resend_stop(now)
            stage = "write"
            left, right = self.kin.wheels(twist)
            if self._enabled:
                self.drive.write(left, right)
            self.wheel_command = (left, right) if self._enabled else (0.0, 0.0)
            self.last_twist = twist
            stage = "observers"
            for fn in self.cycle_observers:
                fn(self, ctx, twist, self.wheel_command)
            if self.controller.finished:
                return self._finish(now, "finished", "controller finished")
            if self._deadline_ns is not None and now >= self._deadline_ns:
                return self._finish(now, "duration", "duration reached")
            return True
        except DriveError as exc:
            return self._drive_failed(now, stage, exc)
        except Exception as exc:
            self.fault_traceback = traceback.format_exc()
            return self._finish(now, _failure_reason(exc), f"exception in {stage}: {exc!r}")

    # -- the estop kept across restarts ---------------------------------------
    def _open_latch(self) -> None:
        """Start-up: a latch file that is there (or cannot be read) latches the run; its writer starts."""
        path = self.latch_file
        if path is None:
            return
        now = self.clock.now_ns()
        self._latch_hold = LatchHold(path)     # before reading: a clear by hand is done, or waits for the run's end
        kept = read_latch(path)
        if kept is not None:
            if not self.safety_on_console:      # else its trip, just below, is the console's line
                print(f"vbnav: {kept}", file=sys.stderr, flush=True)
            self.safety.trip(now, "estop", kept)
        problem = folder_problem(path)
        if problem:
            self.safety.note(now, "warning", "latch_file", f"latch file {path} cannot be written: {problem}; an "
                                                           f"estop will hold only until this process ends")
        self._latch_writer = LatchWriter(path)

    def _latch_warnings(self, now: int) -> None:
        for message in self._latch_writer.errors():
            self.safety.note(now, "warning", "latch_file", message)

    def _close_latch(self) -> None:
        if self._latch_writer is None:
            return
        writer = self._latch_writer
        with self._latch_lock:      # an estop kept after the run ended posts before this or writes after it
            writer.close()
            self._latch_writer = None
        now = self.clock.now_ns()
        for message in writer.errors():
            self.safety.note(now, "warning", "latch_file", message)
        self._latch_hold.release()
        self._latch_hold = None

    # -- a lost drive ---------------------------------------------------------
    def _read_wheels(self, now: int) -> Optional[WheelState]:
        """The drive's reading; while its bus is lost, the last position held (velocity unknown) and the
        reconnect polled. None when the run ended."""
        if self._recovery is None:
            return self.drive.read()
        outcome = self._recovery.poll(now)
        if outcome is None:
            last = self.wheels
            position = last.position if last is not None else (0.0, 0.0)
            return WheelState(now, position, (math.nan, math.nan), self.drive.faults, self.drive.state)
        recovery, self._recovery = self._recovery, None
        lost_s = (now - recovery.since_ns) * 1e-9
        if outcome is Outcome.BACK:
            self._restop_cycle = self.cycle      # a stop not taken before the loss: sent again at once
            self.odometry.rebase()   # a device that restarted counts from elsewhere: no jump in the pose
            self._resume_after = (now, "the drive came back")
            self.safety.note(now, "drive_reconnected", "drive_lost",
                             f"{self.drive.drive_name} is back after {lost_s:.2f} s and ran its safe bring-up "
                             f"(wheels unpowered); stopped until resume")
            return self.drive.read()
        cause = recovery.cause
        if outcome is Outcome.FAILED and recovery.traceback is not None:
            self.fault_traceback = recovery.traceback
            self._finish(now, "drive", f"{cause}; reconnecting failed after {lost_s:.2f} s: {recovery.error}")
        elif outcome is Outcome.FAILED:
            self._finish(now, "drive", f"{cause}; it came back after {lost_s:.2f} s but is not usable: "
                                       f"{recovery.error}")
        else:
            note = self.drive.reconnect_note
            self._finish(now, "drive", f"{cause}; not back within {recovery.window_s:g} s "
                                       f"(drive.reconnect_window_s)" + (f"; last attempt: {note}" if note else ""))
        return None

    def _drive_failed(self, now: int, stage: str, exc: DriveError) -> bool:
        """A DriveError in this cycle: a lost bus starts the wait for the drive; anything else ends the run."""
        window = self.cfg.drive.reconnect_window_s
        lost = self._bus_lost()
        if not lost or window <= 0 or not self.drive.can_reconnect or self._recovery is not None:
            return self._finish(now, "drive", f"{stage}: {exc}")
        self._make_safe(ending=False)
        cause = f"{stage}: {exc}"
        message = (f"{cause}; waiting up to {window:g} s (drive.reconnect_window_s) for it to come back, then "
                   f"stopped until resume")
        if "drive_lost" in self.safety.latched:   # lost again before a resume: the stop holds, say so anyway
            self.safety.note(now, "warning", "drive_lost", message)
        else:
            self.safety.trip(now, "drive_lost", message)
        self._forget_teleop(now, "the drive was lost")
        self._recovery = DriveRecovery(self.drive, cause, now, window,
                                       threaded=not self.clock.simulated)
        return True

    def _bus_lost(self) -> bool:
        """The drive faulted on a lost bus only (a device gone or silent: what a reconnect may bring back)."""
        faults = self.drive.faults
        return bool(self.drive.state is DriveState.ERROR and faults and all(f.kind.reconnectable for f in faults))

    def _end_recovery(self) -> None:
        if self._recovery is not None:
            self._recovery.stop()
            self._recovery = None

    def _check_stall(self, now: int) -> None:
        """A cycle that starts too long after the tick it follows: latched stop, old teleop forgotten."""
        late, period = self.loop.late_ns, self.loop.period_ns
        limit = self.cfg.loop.stall_periods
        if late <= limit * period:
            return
        self.safety.trip(now, "stall", f"loop stalled {late * 1e-6:.0f} ms ({late / period:.1f} periods, limit "
                                       f"{limit:g}, loop.stall_periods); the wheels kept their last command "
                                       f"meanwhile; resume to drive again")
        self._resume_after = (now, "the stall was detected")
        self._forget_teleop(now - late, "the loop stalled")

    def _forget_teleop(self, since: int, why: str) -> None:
        """A latched stop began at ``since``: the held teleop command is dropped and teleop sent before it is
        refused, so after ``resume`` only a fresh command moves the robot."""
        self.mailbox.refuse_teleop_sent_before(since, why)
        self.controller.forget_command()

    def _forget_teleop_on_new_hold(self, now: int) -> None:
        """A hold that begins (obstacle, stale or frozen camera, stale estimate) drops the held teleop
        command, as a latched stop does: held through the stop, it drove the robot again for the rest of
        its command_timeout the moment the hold cleared, on a command sent before anyone knew of it."""
        held = {c for c in self.safety.holds if c not in self._controller_holds}
        began = held - self._holds_seen
        self._holds_seen = held
        if began:
            self._forget_teleop(now, f"the {', '.join(sorted(began))} hold")

    def _check_camera(self, now: int) -> None:
        cam = self.pipeline.camera
        if cam is None:
            return
        limit = self.cfg.camera.stale_after_s
        # From the last fresh frame (a frozen camera's frames come on time with the image it froze on), by
        # its stamp or its reception on this clock, whichever is earlier (a stamp ahead of the clock).
        since = self.pipeline.last_fresh_ns
        if since is None:  # no frame yet: held from the first cycle, said stale once the camera had time to start
            age = (now - self._start_ns) * 1e-9
            stale = self._started_too_long_ago(now, limit)
            self.safety.hold(now, "camera_waiting", not stale, f"camera {cam.name}: waiting for its first frame "
                                                               f"(the wheels are held until it comes)")
        else:
            age = (now - since) * 1e-9
            stale = age > limit
            self.safety.hold(now, "camera_waiting", False)
        if self.pipeline.frozen.frozen:
            why = (f"camera {cam.name} frozen: the same image for {age:.2f} s while the wheels moved "
                   f"(limit {limit:g} s, camera.stale_after_s)")
        else:
            why = f"camera {cam.name}: last frame {age:.2f} s old (limit {limit:g} s)"
        received = self.pipeline.last_fresh_received_ns
        if stale and received is not None and (now - received) * 1e-9 <= limit:
            # frames arrive, but stamped too long before: a latency above the limit, or another clock
            why += (f"; it was received {(now - received) * 1e-9:.2f} s ago, stamped {(received - since) * 1e-9:.2f} "
                    f"s behind the robot's clock (a camera latency above the limit, or a camera on another clock)")
        if stale and self.pipeline.refused:     # frames came, and were refused
            why += f"; {self.pipeline.refused} ({self.pipeline.refused_frames} refused in all)"
        if stale and cam.error:                 # what the driver knows of why (unplugged, its thread failed)
            why += f": {cam.error}"
        self.safety.hold(now, "camera_stale", stale, why)
        self._warn_refused(now, cam.name)

    def _started_too_long_ago(self, now: int, limit_s: float) -> bool:
        """No frame (or estimate) since the start and ``limit_s`` + 2 s have passed: what waited for it (the
        ``*_waiting`` hold, from the first cycle) is now said as stale. The 2 s are the device's start-up."""
        return now - self._start_ns > (limit_s + 2.0) * 1e9

    def _warn_refused(self, now: int, camera: str) -> None:
        """A ``warning`` for frames the pipeline refused since the last one, at most every REFUSED_WARN_EVERY_S."""
        n = self.pipeline.refused_frames - self._refused_told
        told = self._refused_told_ns
        if n <= 0 or (told is not None and now - told < REFUSED_WARN_EVERY_S * 1e9):
            return
        since = "since the start" if told is None else f"in the last {(now - told) * 1e-9:.1f} s"
        self.safety.note(now, "warning", "camera_frames_refused",
                         f"camera {camera}: {n} frame{'s' if n > 1 else ''} refused {since}; the last: "
                         f"{self.pipeline.last_refusal}")
        self._refused_told += n
        self._refused_told_ns = now

    def _apply_speed_scales(self, now: int, estimates: dict) -> None:
        """Estimates may carry ``info['speed_scale']`` in [0, 1] (obstacle zones): the smallest applies,
        and 0 is a held stop until the zone has been clear for the release time."""
        scale = 1.0
        why = ""
        turn_ok = True      # every held stop says it lets a turn on the spot through (obstacles.turn_when_held)
        for e in estimates.values():
            s = e.info.get("speed_scale") if e is not None else None
            if s is not None and s <= 0.0 and turn_ok and e.info.get("turn_ok") is not True:
                turn_ok, why = False, e.info.get("reason", e.kind)      # the stop that holds the turn too
                scale = float(s)
            if s is not None and s < scale:
                scale, why = float(s), e.info.get("reason", e.kind)
        self.safety.speed_scale = max(0.0, scale)
        held = scale <= 0.0
        why = why or "obstacle in the stop zone"
        if held and turn_ok:
            why += "; turning on the spot allowed (obstacles.turn_when_held, a round robot)"
        self.safety.hold(now, "obstacle", held, why, turn_only=held and turn_ok)

    def _check_estimates(self, ctx: ControlContext) -> None:
        """Stages the controller needs, and safety-critical stages (obstacles), must stay fresh."""
        limit = self.cfg.safety.estimate_timeout_s
        critical = [s.kind for s in self.pipeline.stages if s.safety_critical] if self.pipeline is not None else []
        kinds = list(self.controller.requires) + critical
        for kind in kinds:
            e = ctx.estimates.get(kind)
            stale = e is None and self._started_too_long_ago(ctx.now_ns, limit) \
                or (e is not None and e.age_s(ctx.now_ns) > limit)
            self.safety.hold(ctx.now_ns, f"{kind}_stale", stale, f"no {kind} estimate newer than {limit:g} s")
            if kind in critical:    # the robot does not move before a safety-critical stage's first estimate
                self.safety.hold(ctx.now_ns, f"{kind}_waiting", e is None and not stale,
                                 f"waiting for the first {kind} estimate (stage {kind}; the wheels are held "
                                 f"until it comes)")
        # A kind no longer needed (the operator left repeat, which needs vbc): its hold is cleared, not kept
        # for good with nothing left to release it.
        gone = self._estimate_kinds - set(kinds)
        for kind in list(gone):
            self.safety.hold(ctx.now_ns, f"{kind}_stale", False)
            self.safety.hold(ctx.now_ns, f"{kind}_waiting", False)
            if f"{kind}_stale" not in self.safety.holds:
                gone.discard(kind)
        self._estimate_kinds = set(kinds) | gone

    def _apply_commands(self, now: int) -> None:
        commands, refused = self.mailbox.drain(now)
        for cmd, reason in refused:     # answered like the loop's own refusals: with the ack, a stream summarised
            for fn in self.command_observers:
                fn(self, cmd, now)
            self._answer(cmd, CommandOutcome.refused(reason), now)
        # Held until answered: a command that raises ends the run, and it and the rest of the drain (an
        # estop among them) are then answered by _refuse_waiting_commands, not left to time out.
        self._in_hand = commands
        self._estop_in_drain = None
        while self._in_hand:
            cmd = self._in_hand[0]
            for fn in self.command_observers:
                fn(self, cmd, now)
            outcome = self._apply_command(cmd, now)
            self._in_hand = self._in_hand[1:]
            if not outcome.pending:
                self._answer(cmd, outcome, now)
            else:
                for fn in self.pending_listeners:
                    fn(self, cmd, now)

    def complete_command(self, cmd: OperatorCommand, outcome: CommandOutcome, now: int) -> None:
        """A command the controller answered ``PENDING`` is done (loop thread): applied, or refused with
        its reason. ``command_observers`` hear it again first, so the answer carries the sender's ack."""
        for fn in self.command_observers:
            fn(self, cmd, now)
        self._answer(cmd, outcome, now)

    def _answer(self, cmd: OperatorCommand, outcome: CommandOutcome, now: int) -> None:
        if not outcome.applied:
            reason = outcome.reason
            if cmd.kind == "teleop" and not cmd.ack:   # a stream: like the inbox's refusals of stale teleop
                reason = self._teleop_reports.report(reason.split(":", 1)[0], reason, now)
                if reason is None:
                    return
            self.safety.reject(now, cmd.kind, reason)
            return
        for fn in self.command_listeners:
            fn(self, cmd, outcome, now)

    def _apply_command(self, cmd: OperatorCommand, now: int) -> CommandOutcome:
        """estop and resume are the runtime's; the controller answers every other command."""
        if cmd.kind == "estop":
            self.safety.trip(now, "estop", f"estop from {cmd.source}" + (f": {cmd.args[0]}" if cmd.args else ""))
            self._forget_teleop(now if cmd.arrival_ns is None else cmd.arrival_ns, "the estop")
            # a resume drained with it arrived before anyone could see it (the state showing it goes out after
            # this cycle): taken, it cleared the estop in the cycle it was applied, and the wheels drove on. By the
            # drain, not by the cycle's time: on the real clock commands also arrive between the tick and the drain
            # (a serial read takes milliseconds), later than `now` and still in this drain
            self._estop_in_drain = f"the estop from {cmd.source}"
            if self._latch_writer is not None:     # kept across a restart; written off the loop thread
                self._latch_writer.write(latch_record(self.safety.latched["estop"], now))
            return APPLIED
        stale = self.mailbox.sent_before_stop(cmd)   # a teleop drained behind the estop, sent before it
        if stale:
            return CommandOutcome.refused(stale)
        if cmd.kind == "resume" and self._recovery is not None:
            return CommandOutcome.refused(f"the drive is still lost: {self.drive.drive_name} has not come back yet; "
                                          f"resume once a drive_reconnected event says so")
        if cmd.kind == "resume" and self._estop_in_drain is not None:
            return CommandOutcome.refused(f"stale: this resume was taken in the cycle {self._estop_in_drain} took "
                                          f"effect, behind it, before any state could show that estop, so it was "
                                          f"not meant to clear it; resume again")
        if cmd.kind == "resume" and self._resume_after is not None and cmd.arrival_ns is not None \
                and cmd.arrival_ns < self._resume_after[0]:
            t, what = self._resume_after
            return CommandOutcome.refused(f"stale: this resume arrived {(t - cmd.arrival_ns) * 1e-6:.0f} ms before "
                                          f"{what}, so it was not meant to clear it; resume again")
        if cmd.kind == "resume" and cmd.args and cmd.args[0] > now:
            # it would clear every stop, though this robot never showed such a time: each robot's clock counts
            # from its own start, so another robot's state names times this one has not reached
            return CommandOutcome.refused(f"this resume names latched_ns {cmd.args[0]}, "
                                          f"{(cmd.args[0] - now) * 1e-9:.3f} s ahead of this robot's clock: no "
                                          f"stop it showed began then (another robot's state?); resume again "
                                          f"naming latched_ns {self.safety.latched_ns} (this robot's state)")
        if cmd.kind == "resume" and cmd.args:
            unseen = self.safety.latched_after(cmd.args[0])
            if unseen:
                return CommandOutcome.refused(f"stale: this resume names latched_ns {cmd.args[0]}, the newest stop "
                                              f"its sender had seen; {'; '.join(unseen)} came after it and is not "
                                              f"cleared; resume again naming latched_ns {self.safety.latched_ns}")
        if cmd.kind == "resume":
            cleared = self.safety.reset(now, f"resume from {cmd.source}")
            if "estop" in cleared and self._latch_writer is not None:
                self._latch_writer.remove()
            held = [c for c in self.safety.holds if c not in self._controller_holds]
            if cleared and not held:
                return APPLIED
            # Taken, but 'applied' alone would promise a robot free to move: say what it did not change.
            note = "cleared " + ", ".join(cleared) if cleared else "nothing was latched"
            if held:
                note += f"; still held by {', '.join(held)} until it clears"
            return CommandOutcome(True, note, unchanged=not cleared)
        if cmd.kind == "teleop" and self.safety.latched:
            # Taken, it would be 'applied' while the wheels stay stopped, and held it would drive the robot
            # the moment a resume comes.
            return CommandOutcome.refused(f"stopped by {', '.join(self.safety.latched)} (latched): teleop does "
                                          f"not move the robot until a resume")
        holds = [c for c in self.safety.holds if c not in self._controller_holds]
        if cmd.kind == "teleop" and holds:
            return self._teleop_while_held(cmd, holds, now)
        return self.controller.handle_command(cmd, now)

    def _teleop_while_held(self, cmd: OperatorCommand, holds: list, now: int) -> CommandOutcome:
        """A hold (obstacle, stale camera or estimate) keeps the wheels stopped while it lasts: 'applied' would
        be untrue, and a teleop held through it would drive the robot the moment it clears. The controller's own
        holds (command_timeout) are what a teleop clears. Holds that all let a turn on the spot through (a round
        robot held by an obstacle ahead) take a teleop that only turns (linear 0): the loop drives it as such,
        and it is how an operator turns the robot away from what holds it."""
        turn_only = all(c in self.safety.turn_only for c in holds)
        if turn_only and cmd.args and float(cmd.args[0]) == 0.0:
            return self.controller.handle_command(cmd, now)
        if turn_only:
            return CommandOutcome.refused(f"stopped by {', '.join(holds)} (held while it lasts): only a turn on "
                                          f"the spot (linear 0) is taken until it clears")
        return CommandOutcome.refused(f"stopped by {', '.join(holds)} (held while it lasts): teleop does not move "
                                      f"the robot until it clears")

    def _refuse_waiting_commands(self) -> None:
        """Commands that arrived in the last cycle or after it are answered, not left unanswered; later
        ones are refused by the mailbox with the same reason. An estop among them was accepted, so it is
        applied: latched and kept in the latch file (its writer is still open), or a service restarted after
        this fault would drive off with the operator's estop forgotten."""
        reason, message = self._end or ("stopped", "loop stopped")
        why = f"the run ended ({reason}: {message}) before the loop took this command"
        now = self.clock.now_ns()
        in_hand, self._in_hand = self._in_hand, []     # taken from the mailbox, never applied
        taken = f"the run ended ({reason}: {message}) before this command took effect"
        for cmd, because in [(c, taken) for c in in_hand] + [(c, why) for c in self.mailbox.close(why)]:
            for fn in self.command_observers:      # they tell the answer which command (and ack) it is for
                fn(self, cmd, now)
            outcome = self._apply_command(cmd, now) if cmd.kind == "estop" else CommandOutcome.refused(because)
            self._answer(cmd, outcome, now)

    def _finish(self, now: int, reason: str, message: str) -> bool:
        if reason not in ("finished", "duration"):
            self.safety.trip(now, reason, message)
        self._end_recovery()
        self._make_safe()
        self._end = (reason, message)
        return False

    def _make_safe(self, ending: bool = True) -> None:
        """Zero and disable the drive. What an enabled drive could not stop (``stop_failure``: a motor that did
        not answer) is a warning, also when the drive itself is what failed (its fault names the motor that
        failed, not the others its stop did not reach; a device gone entirely reports no stop_failure, its
        fault says its watchdog stops it). ``ending``: the run ends, the drive's close sends the stop once more
        (``_closed``); else the drive is lost and waited for, and the stop is sent again once it is back."""
        self.wheel_command = (0.0, 0.0)
        self.limiter.stop()
        try:
            self.drive.write(0.0, 0.0)
        except Exception:
            pass                  # disabled already, or faulted: the disable below is the stop that counts
        try:
            self.drive.disable()
            failed = self.drive.stop_failure
        except Exception as exc:  # a drive that breaks its never-raises contract
            failed = f"disable() raised {exc!r}"
        if self._enabled:
            self._unconfirmed_stop(self.clock.now_ns(), failed, ending)
        self._enabled = False

    def _unconfirmed_stop(self, now: int, failed: Optional[str], ending: bool) -> None:
        """A stop the drive could not fully carry out (``stop_failure``) is a warning, not silence. While the
        loop runs it is sent again every ``_restop_every`` cycles until it is taken (``_resend_stop``)."""
        if not failed:
            return
        self._unstopped = failed
        self._restop_cycle = self.cycle + self._restop_every
        self._unstopped_told_end = ending
        again = (f"sending it again every {self._restop_every} cycles ({RESTOP_EVERY_S * 1e3:.0f} ms) until it is "
                 f"taken (the loop's reads may keep the device's bus watchdog from stopping it)")
        if ending:
            then = ("the run ends: it is sent once more as the drive closes; if that is not taken either, only the "
                    "device's own watchdog stops it")
        elif self.drive.state is DriveState.ERROR:
            then = f"the drive is waited for: once it is back, {again}; until then only the device's own watchdog " \
                   f"stops it"
        else:
            then = again
        self.safety.note(now, "warning", "stop_unconfirmed", f"{self.drive.drive_name} did not take the stop: "
                                                              f"{failed}; {then}")

    def _resend_stop(self, now: int) -> None:
        """The stop a motor did not take, sent again (``disable`` stops what it reaches in any state)."""
        self._restop_cycle = self.cycle + self._restop_every
        try:
            self.drive.disable()
            failed = self.drive.stop_failure
        except Exception as exc:  # a drive that breaks its never-raises contract
            failed = f"disable() raised {exc!r}"
        if not failed:
            self._stop_confirmed(now, "sent again, the drive reports every motor stopped")
        else:
            self._unstopped = failed

    def _stop_confirmed(self, now: int, how: str) -> None:
        self.safety.note(now, "stop_confirmed", "stop_unconfirmed",
                         f"{self.drive.drive_name}: the stop it had not taken ({self._unstopped}) is confirmed now: "
                         f"{how}")
        self._unstopped = None

    def _closed(self, lost: bool) -> None:
        """After the drive's close, which sent the stop once more: a stop taken then is said; one still not
        taken too, unless the warning already said the run ends with it. ``lost``: the bus was lost before the
        close, so it reached nothing, and its silence confirms nothing."""
        if not self._unstopped:
            return
        now = self.clock.now_ns()
        failed = self.drive.stop_failure or ("the device is lost, the stop sent as the drive closed reached nothing"
                                             if lost else None)
        if not failed:
            self._stop_confirmed(now, "sent again as the drive closed, the drive reported every motor stopped")
            return
        if not self._unstopped_told_end:
            self.safety.note(now, "warning", "stop_unconfirmed",
                             f"{self.drive.drive_name} still did not take the stop when the run ended: {failed}; the "
                             f"drive is closed, only the device's own watchdog stops it now")
        self._unstopped = None

    # -- scheduling ----------------------------------------------------------
    def _apply_scheduling(self):
        """Real-time settings (real clock only): the process's CPU set (loop.process_cpu_affinity), then the
        loop thread's own CPU set and SCHED_FIFO priority. Called once the pipeline's threads run, so they
        do not inherit the loop's settings. Returns an undo function."""
        if self.clock.simulated:
            return _nothing_to_undo
        lc = self.cfg.loop
        old_interval = sys.getswitchinterval()
        sys.setswitchinterval(lc.gil_switch_interval_us * 1e-6)
        undo = [lambda: sys.setswitchinterval(old_interval)]
        now = self.clock.now_ns()
        if lc.process_cpu_affinity:
            try:
                undo.append(_set_process_affinity(set(lc.process_cpu_affinity)))
            except OSError as exc:
                self.safety.note(now, "warning", "scheduling", f"process_cpu_affinity: {exc}")
        if lc.cpu_affinity or lc.realtime_priority:
            undo.append(_new_threads_leave_the_loop_scheduling())
        if lc.cpu_affinity:
            try:
                old_aff = os.sched_getaffinity(0)
                os.sched_setaffinity(0, set(lc.cpu_affinity))
                undo.append(lambda: os.sched_setaffinity(0, old_aff))
            except (OSError, AttributeError) as exc:
                self.safety.note(now, "warning", "scheduling", f"cpu_affinity: {exc}")
        if lc.realtime_priority:
            try:
                old_policy, old_param = os.sched_getscheduler(0), os.sched_getparam(0)
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(lc.realtime_priority))
                undo.append(lambda: os.sched_setscheduler(0, old_policy, old_param))
            except (OSError, AttributeError) as exc:
                self.safety.note(now, "warning", "scheduling", f"SCHED_FIFO priority {lc.realtime_priority} "
                                 f"refused ({exc}); running with normal scheduling")

        def restore():
            for fn in reversed(undo):
                try:
                    fn()
                except OSError:
                    pass
        return restore

    # -- signals -------------------------------------------------------------
    def _install_signal_handlers(self):
        if threading.current_thread() is not threading.main_thread():
            return None
        old = {}
        # SIGHUP: the terminal or ssh session went away; SIGQUIT: Ctrl-\. Left at their defaults they kill
        # the process with the wheels last commanded, stopped only by the device's watchdog (and an
        # ODrive's then refuses the next start), with the recording and the route left unclosed. SIGTSTP
        # (Ctrl-Z) would stop the process where it is, the wheels as last commanded: it ends the run too.
        for sig in STOP_SIGNALS:
            old[sig] = signal.getsignal(sig)
            signal.signal(sig, lambda signum, frame: self.request_stop(signum))
        for sig in IGNORED_SIGNALS:      # a background run's terminal output or input: see IGNORED_SIGNALS
            old[sig] = signal.signal(sig, signal.SIG_IGN)
        return old

    @staticmethod
    def _restore_signal_handlers(old) -> None:
        if not old:
            return
        for sig, handler in old.items():
            signal.signal(sig, handler)
