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
mode is ``switching`` and the robot holds still. (Under the simulated clock the
switch is done in place: simulated time does not pass, and runs stay
deterministic.) A route that fails to load is
a rejected command; the robot stays in its mode.

The teach and repeat parts (stage, route writer, controller) are the ones
``vbnav teach`` and ``vbnav repeat`` run with: ``session.Teaching`` and
``session.Repeating``.
"""
from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING, Optional

from vbnav.control.controllers.manual import TeleopController
from vbnav.control.route import describe_route_error, load_route, resolve_route, routes_root
from vbnav.control.runtime.interfaces import APPLIED, STOP, CommandOutcome, ControlContext, Controller, Twist
from vbnav.control.runtime.mailbox import OperatorCommand
from vbnav.control.session import Repeating, Teaching

if TYPE_CHECKING:
    from vbnav.control.runtime.runtime import Runtime

MODES = ("idle", "teach", "repeat")


class OperatorController(Controller):
    requires: tuple[str, ...] = ()

    def __init__(self, cfg, pipeline, teleop_timeout_s: float):
        self.cfg = cfg
        self.pipeline = pipeline
        self.teleop = TeleopController(teleop_timeout_s)
        self.mode = "idle"
        self.active: Optional[Controller] = None        # the repeat controller in repeat mode
        self.route_path: Optional[str] = None
        self._base_stages = list(pipeline.stages) if pipeline is not None else []
        self._teaching = None                          # session.Teaching: the route being taught
        self._pending: Optional[tuple] = None          # (mode, route, stages, controller, teaching, error)
        self._worker: Optional[threading.Thread] = None
        self.errors: list[str] = []
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
            self._apply_pending()
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
        """``teleop`` drives (in every mode; it only moves the robot in idle and teach); ``mode`` switches."""
        if cmd.kind == "teleop":
            return self.teleop.handle_command(cmd, now_ns)
        if cmd.kind != "mode":
            return super().handle_command(cmd, now_ns)
        target = cmd.args[0] if cmd.args else None
        route = cmd.args[1] if len(cmd.args) > 1 else None
        if target not in MODES:
            return CommandOutcome.refused(f"unknown mode {target!r}; expected one of {', '.join(MODES)}")
        if self._worker is not None:
            return CommandOutcome.refused(f"a switch to {self._worker.name} is still in progress")
        if target in ("teach", "repeat") and not route:
            return CommandOutcome.refused(f"mode {target!r} needs a route path")
        if target == "teach" and self.pipeline is None:
            return CommandOutcome.refused("mode 'teach' needs a camera (this run has none)")
        self._start_switch(target, route, now_ns)
        return APPLIED

    # -- switching (worker thread) --------------------------------------------
    def _start_switch(self, target: str, route: Optional[str], now_ns: int) -> None:
        """On the loop thread: detach the current mode's stages, then let a worker do the file work."""
        frames_at_swap = 0
        if self.pipeline is not None:
            if self._drain_keyframes in self.pipeline.frame_listeners:
                self.pipeline.frame_listeners.remove(self._drain_keyframes)
            self.pipeline.stages = list(self._base_stages)
            frames_at_swap = self.pipeline.frames
        self.active = None
        if self.pipeline is None or self.pipeline.inline:
            # Simulated clock: switch synchronously, so runs stay deterministic (time does not pass meanwhile).
            self._prepare(target, route, frames_at_swap)
            return
        self._worker = threading.Thread(target=self._prepare, args=(target, route, frames_at_swap), name=target,
                                        daemon=True)
        self._worker.start()

    def _prepare(self, target: str, route: Optional[str], frames_at_swap: int = 0) -> None:
        """Close what the current mode opened, then build what the target needs (off the loop thread)."""
        where = None     # the route's directory, once resolved
        try:
            if self._teaching is not None and self.pipeline is not None and not self.pipeline.inline:
                # The vision thread may still be inside the teach stage with the last frame before the swap.
                deadline = time.monotonic() + 1.0
                while self.pipeline.frames <= frames_at_swap + 1 and time.monotonic() < deadline:
                    time.sleep(0.01)
            self._close_teach()
            stages, controller, teaching = list(self._base_stages), None, None
            if target in ("teach", "repeat"):   # a name inside controller.routes_dir, never a path
                where = resolve_route(routes_root(self.cfg.controller.routes_dir, self.cfg.source), route,
                                      must_exist=target == "repeat")
            if target == "teach":
                teaching = Teaching(self.cfg, where, overwrite=False)
                stages = [teaching.stage] + stages
            elif target == "repeat":
                repeating = Repeating(self.cfg, load_route(where))
                stages = [repeating.stage] + stages
                controller = repeating.controller
            self._pending = (target, route, stages, controller, teaching, None)
        except Exception as exc:  # the mode stays as it was; the operator sees why (never a path outside)
            why = describe_route_error(exc, where, route) if where is not None else str(exc)
            self._pending = (self.mode, self.route_path, None, None, None, f"mode {target}: {why}")

    def _close_teach(self) -> None:
        if self._teaching is not None:
            self._teaching.close()
        self._teaching = None

    def _apply_pending(self) -> None:
        mode, route, stages, controller, teaching, error = self._pending
        self._pending = None
        self._worker = None
        if error:
            self.errors.append(error)
            rt = self._runtime
            if rt is not None:
                rt.safety.reject(rt.clock.now_ns(), "mode", error)
            return
        self.mode, self.route_path, self.active = mode, route, controller
        self.requires = ("vbc",) if mode == "repeat" else ()
        self._teaching = teaching
        if self.pipeline is not None:
            if teaching is not None:
                self.pipeline.frame_listeners.append(self._drain_keyframes)
            self.pipeline.latest.pop("vbc", None)
            self.pipeline.stages = stages    # one reference swap: the vision thread sees old or new list

    def _drain_keyframes(self, frame, results) -> None:
        teaching = self._teaching
        if teaching is not None:
            teaching.save()

    def close(self) -> None:
        """End of the run: a route being taught is closed with every keyframe so far."""
        if self._worker is not None:
            self._worker.join(timeout=5.0)
        self._close_teach()
