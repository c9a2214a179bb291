"""Controllers that need no vision: a scripted drive and teleoperation."""
from __future__ import annotations

from typing import Optional

from vbnav.control.runtime.interfaces import APPLIED, STOP, CommandOutcome, ControlContext, Controller, Twist
from vbnav.control.runtime.mailbox import OperatorCommand


class ScriptedController(Controller):
    """Plays [v m/s, w rad/s, seconds] segments, then finishes (simulation, bring-up tests)."""

    name = "scripted"

    def __init__(self, segments: list[list[float]] | list[tuple[float, float, float]], repeat: bool = False):
        if not segments:
            raise ValueError("scripted controller: the script has no segments")
        for i, seg in enumerate(segments):
            if len(seg) != 3 or seg[2] <= 0:
                raise ValueError(f"scripted controller: segment {i} must be [v, w, seconds > 0], got {seg}")
        self.segments = [tuple(float(x) for x in s) for s in segments]
        self.repeat = repeat
        self._t0: Optional[int] = None
        self._done = False
        self._index = 0
        self.total_s = sum(s[2] for s in self.segments)

    def start(self, ctx: ControlContext) -> None:
        self._t0 = ctx.now_ns

    def update(self, ctx: ControlContext) -> Twist:
        if self._t0 is None:
            self._t0 = ctx.now_ns
        t = (ctx.now_ns - self._t0) * 1e-9
        if self.repeat:
            t %= self.total_s
        for i, (v, w, dur) in enumerate(self.segments):
            if t < dur:
                self._index = i
                return Twist(v, w)
            t -= dur
        self._done = True
        return STOP

    @property
    def finished(self) -> bool:
        return self._done

    def status(self) -> dict:
        return {"segment": self._index, "of": len(self.segments)}


class TeleopController(Controller):
    """Follows the latest operator command; stops when commands stop arriving.

    The command stream's silence for ``timeout_s`` is a stop condition: a lost
    network or a crashed operator console must never leave the robot driving.
    The timeout runs from when a command was sent (its sender's stamp mapped to
    the loop's clock by the command mailbox), not from when the loop applied it.
    """

    name = "teleop"

    def __init__(self, timeout_s: float):
        """``timeout_s``: command silence that stops the robot (safety.command_timeout_s)."""
        self.timeout_ns = int(timeout_s * 1e9)
        self._cmd = STOP
        self._stamp: Optional[int] = None
        self.timed_out = True

    def set_command(self, v: float, w: float, sent_ns: int) -> None:
        """The newest command, sent at ``sent_ns`` on the loop's clock: it holds until sent_ns + timeout."""
        self._cmd = Twist(v, w)
        self._stamp = sent_ns

    def forget_command(self) -> None:
        """Drop the held command (after a loop stall): only a fresh one moves the robot again."""
        self._cmd = STOP
        self._stamp = None

    def handle_command(self, cmd: OperatorCommand, now_ns: int) -> CommandOutcome:
        """``teleop`` (v, w) sets the command; freshness runs from when it was sent (mapped to the
        loop's clock by the mailbox), not from now. Other commands: as every controller."""
        if cmd.kind == "teleop":
            self.set_command(float(cmd.args[0]), float(cmd.args[1]), cmd.sent_ns)
            return APPLIED
        return super().handle_command(cmd, now_ns)

    def update(self, ctx: ControlContext) -> Twist:
        self.timed_out = self._stamp is None or ctx.now_ns - self._stamp > self.timeout_ns
        return STOP if self.timed_out else self._cmd

    def status(self) -> dict:
        return {"timed_out": self.timed_out, "v": self._cmd.v, "w": self._cmd.w}

    def safety_conditions(self) -> dict[str, tuple[bool, str]]:
        return {"command_timeout": (self.timed_out,
                                    f"no teleop command for more than {self.timeout_ns * 1e-9:g} s")}


class IdleController(Controller):
    name = "idle"

    def update(self, ctx: ControlContext) -> Twist:
        return STOP
