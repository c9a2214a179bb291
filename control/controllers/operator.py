"""Operator mode switching inside one run: idle, teach and repeat, as `cmd/mode` asks.

This is the one place where a run switches modes. The runtime and the telemetry
link only forward `mode` commands to the controller's ``handle_command``
(runtime/interfaces.py); a controller that runs a single mode answers them with
the base class's default (the current mode is unchanged, any other needs a new run).

The robot's everyday session on hardware: ``vbnav run --controller operator``
starts idle (teleop commands drive it); ``mode teach ROUTE`` starts recording a
route while the operator drives; ``mode idle`` closes the route (every keyframe
is already on disk); ``mode repeat ROUTE`` patrols it and returns to idle at
its end. ROUTE is a name inside ``controller.routes_dir`` (route.resolve_route),
never a path: the command comes from the network.

Everything that touches files (opening a route writer, loading and checking a
route) runs on a worker thread, never on the loop's thread: while it works the
mode is ``switching`` and the robot holds still (teleop is refused), and the command is answered
(``command`` event, or ``command_rejected``) only once the switch is done
(``PENDING``, then ``Runtime.complete_command``). (Under the simulated clock the
switch is done in place, and answered at once: simulated time does not pass, and
runs stay deterministic.) A route that fails to load is a rejected command; the
robot stays in its mode, still teaching or repeating what it was (the target is
built before the current mode is closed). The one exception: ``repeat`` of the
route being taught closes the teach first (to read its last keyframes); if that
route then fails to load, the robot is idle and the refusal says so.

The teach and repeat parts (stage, route writer, controller) are the ones
``vbnav teach`` and ``vbnav repeat`` run with: ``session.Teaching`` and
``session.Repeating``.
"""
from __future__ import annotations

import threading
from collections import deque
from typing import TYPE_CHECKING, Optional

from vbnav.control.controllers.manual import TeleopController
from vbnav.control.route import describe_route_error, load_route, resolve_route, routes_root
from vbnav.control.runtime.interfaces import (APPLIED, PENDING, STOP, CommandOutcome, ControlContext, Controller,
                                              Twist)
from vbnav.control.runtime.mailbox import OperatorCommand
from vbnav.control.session import Repeating, Teaching

if TYPE_CHECKING:
    from vbnav.control.runtime.runtime import Runtime

MODES = ("idle", "teach", "repeat")
ERRORS_KEPT = 20                 # failed switches kept in OperatorController.errors


class OperatorController(Controller):
    requires: tuple[str, ...] = ()
    close_wait_s = 5.0      # how long the run's end waits for a switch still on its worker

    def __init__(self, cfg, pipeline, teleop_timeout_s: float):
        self.cfg = cfg
        self.pipeline = pipeline
        self.teleop = TeleopController(teleop_timeout_s)
        self.mode = "idle"
        self.active: Optional[Controller] = None        # the repeat controller in repeat mode
        self.route_path: Optional[str] = None
        self._base_stages = list(pipeline.stages) if pipeline is not None else []
        self._teaching = None                          # session.Teaching: the route being taught
        self._pending: Optional[tuple] = None          # (mode, route, stages, controller, teaching, error, cmd, note)
        self._worker_cmd: Optional[OperatorCommand] = None  # the command the worker's switch answers
        self._switch_lock = threading.Lock()           # _pending posted vs. the run ending without it
        self._abandoned = False                        # the run ended while the worker was still at it
        self._previous: Optional[tuple] = None         # (stages, controller) detached by the switch in progress
        self._worker: Optional[threading.Thread] = None
        # the latest failed switches (each is also a rejected safety event): a run of months keeps a few
        self.errors: deque[str] = deque(maxlen=ERRORS_KEPT)
        self._runtime: Optional["Runtime"] = None       # hears a switch that fails after it was accepted

    # -- Controller ----------------------------------------------------------
    @property
    def name(self) -> str:
        return "switching" if self._worker is not None else self.mode

    @property
    def teaching_route(self) -> Optional[str]:
        return self.route_path if self.mode == "teach" else None

    def update(self, ctx: ControlContext) -> Twist:
        if self._pending is not None:
            self._apply_pending(ctx.now_ns)
        if self._worker is not None:
            return STOP
        if self.mode == "repeat" and self.active is not None:
            twist = self.active.update(ctx)
            if self.active.finished:
                self._start_switch("idle", None, ctx.now_ns)
            return twist
        return self.teleop.update(ctx)   # idle and teach: the operator drives (STOP when silent)

    def forget_command(self) -> None:
        self.teleop.forget_command()

    def safety_conditions(self) -> dict[str, tuple[bool, str]]:
        # A silent teleop stream only matters while the operator drives (idle, teach).
        if self.mode == "repeat":
            return {"command_timeout": (False, "")}
        return self.teleop.safety_conditions()

    @property
    def followed_route(self) -> Optional[str]:
        return self.route_path if self.mode in ("teach", "repeat") else None

    def status(self) -> dict:
        s = {"mode": self.name, "route": self.route_path}
        if self.active is not None:
            s.update(self.active.status())
        if self._teaching is not None:
            s["keyframes"] = self._teaching.stage.n_keyframes
        return s

    # -- commands ------------------------------------------------------------
    def attach(self, runtime: "Runtime") -> "OperatorController":
        """Let a switch that fails on the worker (a route that does not load) be refused in the runtime's
        events; without it the failure is only kept in ``errors``."""
        self._runtime = runtime
        return self

    def handle_command(self, cmd: OperatorCommand, now_ns: int) -> CommandOutcome:
        """``teleop`` drives in idle and teach (refused while repeating or switching: it would not move the robot,
        and held until the repeat or the switch ends it would drive the robot then); ``mode`` switches."""
        if cmd.kind == "teleop":
            if self._worker is not None:
                # The robot holds still until the switch is done: 'applied' would be untrue, a switch to repeat
                # drops it, and held through the switch it would drive the robot when the new mode begins.
                return CommandOutcome.refused(f"a switch to {self._worker.name} is in progress: the robot holds "
                                              f"still until it is done; teleop again then")
            if self.mode == "repeat":
                return CommandOutcome.refused(f"mode repeat: the robot follows route {self.route_path!r}; teleop "
                                              f"drives in idle and teach (send mode idle first)")
            return self.teleop.handle_command(cmd, now_ns)
        if cmd.kind != "mode":
            return super().handle_command(cmd, now_ns)
        target = cmd.args[0] if cmd.args else None
        route = cmd.args[1] if len(cmd.args) > 1 else None
        if target not in MODES:
            return CommandOutcome.refused(f"unknown mode {target!r}; expected one of {', '.join(MODES)}")
        if self._worker is not None:
            return CommandOutcome.refused(f"a switch to {self._worker.name} is still in progress")
        if target == "idle" and self.mode == "idle":     # nothing to switch: no worker, no pause of the teleop
            return CommandOutcome(True, unchanged=True)
        if target in ("teach", "repeat") and not route:
            return CommandOutcome.refused(f"mode {target!r} needs a route path")
        if target in ("teach", "repeat") and self.pipeline is None:   # repeat: no VBC fix would ever come
            return CommandOutcome.refused(f"mode {target!r} needs a camera (this run has none)")
        return self._start_switch(target, route, now_ns, cmd)

    # -- switching (worker thread) --------------------------------------------
    def _start_switch(self, target: str, route: Optional[str], now_ns: int,
                      cmd: Optional[OperatorCommand] = None) -> CommandOutcome:
        """On the loop thread: detach the current mode's stages, then let a worker do the file work.

        cmd: the operator's command (None for the switch to idle at a repeat's end). Returns its answer:
        at once under the simulated clock, else ``PENDING`` (answered when the worker is done)."""
        self._previous = (list(self.pipeline.stages) if self.pipeline is not None else None, self.active)
        if self.pipeline is not None:
            if self._drain_keyframes in self.pipeline.frame_listeners:
                self.pipeline.frame_listeners.remove(self._drain_keyframes)
            self.pipeline.stages = list(self._base_stages)   # the teach stage's last frame: Teaching.close waits
        self.active = None
        if self.pipeline is None or self.pipeline.inline:
            # Simulated clock: switch synchronously, so runs stay deterministic (time does not pass meanwhile).
            self._prepare(target, route, cmd)
            return self._apply_pending(now_ns, deferred=False)
        self._worker_cmd = cmd
        self._worker = threading.Thread(target=self._prepare, args=(target, route, cmd),
                                        name=target, daemon=True)
        self._worker.start()
        return PENDING

    def _prepare(self, target: str, route: Optional[str], cmd: Optional[OperatorCommand] = None) -> None:
        """The switch (``_prepare_switch``), always answered: an error it did not expect (closing the new
        route failed too, on a full disk) would end the worker unseen, the command unanswered and every later
        switch refused as still in progress. Then the robot goes idle, saying why."""
        try:
            self._prepare_switch(target, route, cmd)
        except Exception as exc:
            old, self._teaching = self._teaching, None
            if old is not None:
                try:
                    old.close(complete=False)
                except Exception:
                    pass
            self._post(("idle", None, list(self._base_stages), None, None,
                        f"mode {target}: the switch failed ({exc!r}); the robot is idle", cmd))

    def _prepare_switch(self, target: str, route: Optional[str], cmd: Optional[OperatorCommand] = None) -> None:
        """Build what the target needs, then close what the current mode opened (off the loop thread).

        The target first: a switch that fails leaves the current mode as it was (``_apply_pending`` puts
        its stages back), a route being taught included."""
        where = None     # the route's directory, once resolved
        closed = ""      # what the failed switch closed anyway
        ended = ""       # why the route taught until now ends before its last frame (Teaching.note)
        try:
            if target in ("teach", "repeat"):   # a name inside controller.routes_dir, never a path
                where = resolve_route(routes_root(self.cfg.controller.routes_dir, self.cfg.source), route,
                                      must_exist=target == "repeat")
            if target == "repeat" and self.mode == "teach" and route == self.route_path:
                # Repeat what is being taught: its last keyframes are written when the teach closes.
                ended = self._close_teach()
                closed = f"; teaching {route!r} was closed, the robot is idle" + (f" ({ended})" if ended else "")
            stages, controller, teaching, note = list(self._base_stages), None, None, ""
            if target == "teach":
                teaching = Teaching(self.cfg, where, overwrite=False)
                stages = [teaching.stage] + stages
            elif target == "repeat":
                loaded = load_route(where)
                repeating = Repeating(self.cfg, loaded)
                stages = [repeating.stage] + stages
                if not loaded.complete:     # applied, with what vbnav repeat warns of
                    note = f"mode repeat: route {route!r}: {loaded.incomplete_note()}"
                controller = repeating.controller
        except Exception as exc:  # the mode stays as it was; the operator sees why (never a path outside)
            why = describe_route_error(exc, where, route) if where is not None else str(exc)
            if closed:
                self._post(("idle", None, list(self._base_stages), None, None, f"mode {target}: {why}{closed}",
                            cmd))
            else:
                self._post((self.mode, self.route_path, None, None, None, f"mode {target}: {why}", cmd))
            return
        try:
            ended = self._close_teach() or ended
        except Exception as exc:   # the route being taught could not be closed (a full disk)
            self._teaching = None
            if teaching is not None:
                teaching.close(complete=False)
            why = describe_route_error(exc, where, route) if where is not None else str(exc)
            self._post(("idle", None, list(self._base_stages), None, None,
                             f"mode {target}: closing the route being taught failed: {why}; the robot is idle", cmd))
            return
        if ended:      # applied, with what vbnav teach prints of the route it closed
            note = "; ".join(n for n in (f"mode {target}: {ended}", note) if n)
        self._post((target, route, stages, controller, teaching, None, cmd), note)

    def _post(self, pending: tuple, note: str = "") -> None:
        """Worker: hand the prepared switch to the loop, unless the run ended without waiting for it
        (``close``): then what it opened is closed here, and its command was answered already."""
        with self._switch_lock:
            if not self._abandoned:
                self._pending = (*pending, note)
                return
        teaching = pending[4]
        if teaching is not None:
            teaching.close()
        self._close_teach()     # the route being taught when the run ended: close() left it to this thread

    def _close_teach(self, complete: bool = True) -> str:
        """Close the route being taught (``complete``: marked complete, as a run that ended well; a fault
        leaves it incomplete, as ``vbnav teach`` does); what ``vbnav teach`` would print of why it ends before
        the last frame (Teaching.note, naming the route), else ''."""
        teaching = self._teaching
        if teaching is None:
            return ""
        teaching.close(complete=complete, vision=self.pipeline)   # after the vision thread's frame, if any
        self._teaching = None
        return f"route {self.route_path!r} taught: {teaching.note}" if teaching.note else ""

    def _apply_pending(self, now_ns: Optional[int] = None, deferred: bool = True) -> CommandOutcome:
        """On the loop thread: take the result of the switch, and answer the command that asked for it.

        deferred: the command was answered ``PENDING`` (worker thread): its answer goes to the runtime now.
        Otherwise it is returned (to ``handle_command``). A switch nobody asked for that fails is refused
        in the runtime's events."""
        mode, route, stages, controller, teaching, error, cmd, note = self._pending
        self._pending = None
        self._worker = None
        self._worker_cmd = None
        previous, self._previous = self._previous, None
        rt = self._runtime
        if now_ns is None:
            now_ns = rt.clock.now_ns() if rt is not None else 0
        outcome = CommandOutcome.refused(error) if error else CommandOutcome(True, note) if note else APPLIED
        if error:
            self.errors.append(error)
        if stages is None:   # failed, nothing closed: the mode stays, and what the switch detached goes back
            self._restore(previous)
        else:
            self.mode, self.route_path, self.active = mode, route, controller
            self.requires = ("vbc",) if mode == "repeat" else ()
            if mode == "repeat":
                self.teleop.forget_command()    # what the operator drove with before must not outlast the repeat
            self._teaching = teaching
            if self.pipeline is not None:
                if teaching is not None:
                    self.pipeline.frame_listeners.append(self._drain_keyframes)
                self.pipeline.latest.pop("vbc", None)
                self.pipeline.stages = stages    # one reference swap: the vision thread sees old or new list
        if rt is not None and cmd is None and error:
            rt.safety.reject(now_ns, "mode", error)
        elif rt is not None and cmd is not None and deferred:
            rt.complete_command(cmd, outcome, now_ns)
        return outcome

    def _restore(self, previous: Optional[tuple]) -> None:
        """A switch failed before anything was closed: the current mode's stages and controller go back."""
        if previous is None:
            return
        stages, self.active = previous
        if self.pipeline is not None and stages is not None:
            if self._teaching is not None and self._drain_keyframes not in self.pipeline.frame_listeners:
                self.pipeline.frame_listeners.append(self._drain_keyframes)
            self.pipeline.stages = stages

    def _drain_keyframes(self, frame, results) -> None:
        teaching = self._teaching
        if teaching is not None:
            teaching.save()

    def close(self, complete: bool = True) -> None:
        """End of the run: a route being taught is closed with every keyframe so far, marked complete when the
        run ended well (``complete``); a run a fault ended leaves it incomplete, as ``vbnav teach`` does."""
        if self._worker is not None:
            self._worker.join(timeout=self.close_wait_s)
        with self._switch_lock:
            gone = self._worker is not None and self._worker.is_alive() and self._pending is None
            self._abandoned = gone
        rt = self._runtime
        if gone and self._worker_cmd is not None and rt is not None:
            # Still loading or opening its route: answered now, not never; the worker closes what it opens.
            cmd = self._worker_cmd
            rt.complete_command(cmd, CommandOutcome.refused(
                f"mode {cmd.args[0]}: the run ended while the switch was still under way (not done after "
                f"{self.close_wait_s:g} s)"), rt.clock.now_ns())
        if not gone:
            pending, self._pending = self._pending, None
            if pending is not None:
                # The run ended before the loop took the switch: the route it opened is closed too, and
                # the command that asked for it is refused (it never took effect).
                mode, route, stages, controller, teaching, error, cmd, _ = pending
                self._worker = None
                if teaching is not None:
                    teaching.close()
                rt = self._runtime
                if cmd is not None and rt is not None:
                    rt.complete_command(cmd, CommandOutcome.refused(
                        f"mode {cmd.args[0]}: the run ended before the switch took effect"), rt.clock.now_ns())
        if not gone:      # else the worker closes the route being taught: one thread, never two at once
            ended = self._close_teach(complete)
            if ended and rt is not None:     # no command to answer: the run's events say it
                rt.safety.note(rt.clock.now_ns(), "warning", "teach", ended)
