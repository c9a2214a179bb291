"""Safety monitor: decides whether the wheels may move, and says why not.

Two kinds of stop:
- latched (``trip``): an exception in any stage, SIGINT/SIGTERM, a streak of
  missed deadlines, a faulted drive, a drive whose bus was lost (``drive_lost``,
  while it may still come back), a stall, an operator estop. The robot stays
  stopped until ``reset`` (operator resume); fatal causes also end the run.
- held (``hold``): a condition that stops the robot while it lasts and releases
  by itself once it has been clear for ``release_s`` (debounce): a stale camera
  frame, a stale vision estimate, a silent command stream, an obstacle. The
  silent command stream and the obstacle (debounced by its stage) release at once
  (``RELEASE_AT_ONCE``).

Every change is an event (time, kind, cause, message) kept for telemetry and
the run report. The runtime commands zero and disables the drive the same cycle
a stop starts.
"""
from __future__ import annotations

from dataclasses import dataclass, field

FATAL = ("exception", "signal", "deadline", "drive", "camera")

#: Held causes that release the cycle they clear, without the ``release_s`` debounce. A silent command
#: stream (``command_timeout``) ends when a fresh command arrives: the command's own freshness (sent within
#: ``safety.command_timeout_s``) is the debounce, and waiting ``release_s`` (0.5 s, as long as the timeout)
#: would let no single teleop message ever move the robot, and cut every stream's first half second.
#: The obstacle stop is debounced by the obstacle stage itself (``obstacles.release_s``, after its k-of-n
#: persistence): a second debounce here would make the configured release time the sum of both.
RELEASE_AT_ONCE = ("command_timeout", "obstacle")


@dataclass
class SafetyEvent:
    stamp_ns: int
    kind: str        # "trip", "hold", "release", "reset", "rejected", "warning", "drive_reconnected"
    cause: str
    message: str

    def as_dict(self) -> dict:
        return {"stamp_ns": self.stamp_ns, "kind": self.kind, "cause": self.cause, "message": self.message}


@dataclass
class SafetyMonitor:
    release_s: float                                   # s a held cause must stay clear (safety.release_s)
    latched: dict = field(default_factory=dict)        # cause -> message
    holds: dict = field(default_factory=dict)          # cause -> message (active)
    _clear_since: dict = field(default_factory=dict)   # cause -> ns when it went clear
    events: list = field(default_factory=list)
    speed_scale: float = 1.0                           # from obstacle zones, in [0, 1]
    listeners: list = field(default_factory=list)      # callables(SafetyEvent)

    # -- inputs ------------------------------------------------------------
    def trip(self, now_ns: int, cause: str, message: str) -> None:
        if cause in self.latched:
            return
        self.latched[cause] = message
        self._emit(SafetyEvent(now_ns, "trip", cause, message))

    def hold(self, now_ns: int, cause: str, active: bool, message: str = "") -> None:
        """Report the state of a held condition every cycle."""
        if active:
            self._clear_since.pop(cause, None)
            if cause not in self.holds:
                self.holds[cause] = message
                self._emit(SafetyEvent(now_ns, "hold", cause, message))
            return
        if cause not in self.holds:
            return
        since = self._clear_since.setdefault(cause, now_ns)
        release_s = 0.0 if cause in RELEASE_AT_ONCE else self.release_s
        if now_ns - since >= release_s * 1e9:
            del self.holds[cause]
            del self._clear_since[cause]
            self._emit(SafetyEvent(now_ns, "release", cause, f"{cause} clear for {release_s:g} s"))

    def reset(self, now_ns: int, message: str = "operator resume") -> list[str]:
        """Clear the non-fatal latched stops (estop). Fatal ones need a restart."""
        cleared = [c for c in self.latched if c not in FATAL]
        for c in cleared:
            del self.latched[c]
        if cleared:
            self._emit(SafetyEvent(now_ns, "reset", ",".join(cleared), message))
        return cleared

    def reject(self, now_ns: int, command: str, message: str) -> None:
        """A refused operator command: an event for the log and listeners, no change to the stop state."""
        self._emit(SafetyEvent(now_ns, "rejected", command, message))

    def note(self, now_ns: int, kind: str, cause: str, message: str) -> None:
        """News that changes no stop (``drive_reconnected``): an event for the log and listeners."""
        self._emit(SafetyEvent(now_ns, kind, cause, message))

    # -- outputs -----------------------------------------------------------
    @property
    def may_move(self) -> bool:
        return not self.latched and not self.holds

    @property
    def fatal(self) -> str | None:
        for c in FATAL:
            if c in self.latched:
                return c
        return None

    def reasons(self) -> list[str]:
        return [f"{c}: {m}" for c, m in {**self.latched, **self.holds}.items()]

    def state(self) -> dict:
        return {"may_move": self.may_move, "latched": dict(self.latched), "holds": dict(self.holds),
                "speed_scale": self.speed_scale}

    def _emit(self, ev: SafetyEvent) -> None:
        self.events.append(ev)
        for fn in self.listeners:
            try:
                fn(ev)
            except Exception:  # a listener must never break the safety path
                pass
