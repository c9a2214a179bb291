"""Safety monitor: decides whether the wheels may move, and says why not.

Two kinds of stop:
- latched (``trip``): an exception in any stage, SIGINT/SIGTERM, a streak of
  missed deadlines, a faulted drive, a drive whose bus was lost (``drive_lost``,
  while it may still come back), a stall, an operator estop. The robot stays
  stopped until ``reset`` (operator resume); fatal causes also end the run.
  ``latched_at`` keeps when each latched stop last began (a second estop while one
  is latched begins it anew): a resume that names the newest stop its sender has
  seen (``latched_ns``) clears nothing that began after it (``latched_after``).
- held (``hold``): a condition that stops the robot while it lasts and releases
  by itself once it has been clear for ``release_s`` (debounce): a stale camera
  frame, a stale vision estimate, a silent command stream, an obstacle. The
  silent command stream and the obstacle (debounced by its stage) release at once
  (``RELEASE_AT_ONCE``), and so do the start-up holds that wait for the camera's
  first frame or a safety-critical stage's first estimate (``*_waiting``).

Every change is an event (time, kind, cause, message), told to the listeners
(telemetry, the console) as it happens and kept for the run report in an
``EventLog``: a run of months holds and releases the obstacle stop each time
someone walks past, so the log keeps the first ``EVENTS_FIRST`` and the last
``EVENTS_LAST`` events in full, a count of every (kind, cause) since the start,
and says how many it left out between them. The runtime commands zero and
disables the drive the same cycle a stop starts. One kind of hold is milder: a ``turn_only`` hold (an obstacle
seen in a stop zone, for a round robot with ``obstacles.turn_when_held``) stops the travel the same cycle but
lets a turn on the spot through (``may_turn``) while no other hold or latched stop is active.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Iterator

FATAL = ("exception", "signal", "deadline", "drive", "camera", "network")

#: Held causes that release the cycle they clear, without the ``release_s`` debounce. A silent command
#: stream (``command_timeout``) ends when a fresh command arrives: the command's own freshness (sent within
#: ``safety.command_timeout_s``) is the debounce, and waiting ``release_s`` (0.5 s, as long as the timeout)
#: would let no single teleop message ever move the robot, and cut every stream's first half second.
#: The obstacle stop is debounced by the obstacle stage itself (``obstacles.release_s``, after its k-of-n
#: persistence): a second debounce here would make the configured release time the sum of both.
RELEASE_AT_ONCE = ("command_timeout", "obstacle")
#: Held causes named ``<what>_waiting`` (``camera_waiting``, ``obstacles_waiting``) hold the robot at start-up until
#: the camera's first fresh frame, or a safety-critical stage's first estimate, comes. They release at once too: the
#: first frame is the news they wait for, not a stream that may flicker (which ``release_s`` debounces).
WAITING = "_waiting"


@dataclass
class SafetyEvent:
    stamp_ns: int
    kind: str        # "trip", "hold", "hold_changed", "release", "reset", "rejected", "warning", "drive_reconnected"
    cause: str
    message: str

    def as_dict(self) -> dict:
        return {"stamp_ns": self.stamp_ns, "kind": self.kind, "cause": self.cause, "message": self.message}


#: Events the run report keeps in full: the first ones (how the run started) and the last ones (how it went
#: lately, how it ended). Those in between are counted (``EventLog.counts``, ``EventLog.dropped``), not kept.
EVENTS_FIRST = 100
EVENTS_LAST = 1000


class EventLog:
    """The safety events of a run, bounded: the first ``first`` and the last ``last`` in full, in order; the
    number of every (kind, cause) over the whole run (``counts``); how many were left out (``dropped``).

    Iterating gives the kept events in order (the first ones, then the last ones); ``dropped_after`` is
    how many of them come before the gap (a report says there that events were left out)."""

    def __init__(self, first: int = EVENTS_FIRST, last: int = EVENTS_LAST):
        if first < 0 or last < 1:
            raise ValueError(f"EventLog keeps first >= 0 and last >= 1 events, got {first}, {last}")
        self.first = first
        self._head: list = []
        self._tail: deque = deque(maxlen=last)
        self.total = 0
        self.counts: dict[tuple[str, str], int] = {}     # (kind, cause) -> events over the whole run

    def append(self, ev: "SafetyEvent") -> None:
        self.total += 1
        key = (ev.kind, ev.cause)
        self.counts[key] = self.counts.get(key, 0) + 1
        if len(self._head) < self.first:
            self._head.append(ev)
        else:
            self._tail.append(ev)

    @property
    def dropped(self) -> int:
        """Events left out between the first and the last ones kept."""
        return self.total - len(self._head) - len(self._tail)

    @property
    def dropped_after(self) -> int:
        """How many kept events come before the ones left out."""
        return len(self._head)

    def __iter__(self) -> Iterator["SafetyEvent"]:
        yield from self._head
        yield from self._tail

    def __len__(self) -> int:
        return len(self._head) + len(self._tail)

    def __bool__(self) -> bool:
        return self.total > 0

    def __getitem__(self, i):
        return list(self)[i]

    def count(self, kind: str, cause: str | None = None) -> int:
        """Events of ``kind`` (and ``cause``) over the whole run, the ones left out included."""
        return sum(n for (k, c), n in self.counts.items() if k == kind and (cause is None or c == cause))

    def gap_line(self) -> str:
        """What the report says where events were left out ("" when none were)."""
        if not self.dropped:
            return ""
        counts = ", ".join(f"{k} {c} {n}" for (k, c), n in sorted(self.counts.items()))
        return (f"{self.dropped} safety events left out here (the report keeps the first {self.first} and the "
                f"last {self._tail.maxlen}); the whole run's events by kind and cause: {counts}")


@dataclass
class SafetyMonitor:
    release_s: float                                   # s a held cause must stay clear (safety.release_s)
    latched: dict = field(default_factory=dict)        # cause -> message
    latched_at: dict = field(default_factory=dict)     # cause -> ns it (last) began
    holds: dict = field(default_factory=dict)          # cause -> message (active)
    _clear_since: dict = field(default_factory=dict)   # cause -> ns when it went clear
    events: EventLog = field(default_factory=EventLog)   # bounded: first and last events, counts
    speed_scale: float = 1.0                           # from obstacle zones, in [0, 1]
    turn_only: set = field(default_factory=set)        # active held causes that let a turn on the spot through
    listeners: list = field(default_factory=list)      # callables(SafetyEvent)

    # -- inputs ------------------------------------------------------------
    def trip(self, now_ns: int, cause: str, message: str) -> None:
        if cause in self.latched:
            # begun anew (a second operator's estop): a resume sent before it did not know of it, and the
            # latch now stands for the newest stop's reason
            self.latched[cause] = message
            self.latched_at[cause] = now_ns
            return
        self.latched[cause] = message
        self.latched_at[cause] = now_ns
        self._emit(SafetyEvent(now_ns, "trip", cause, message))

    def hold(self, now_ns: int, cause: str, active: bool, message: str = "", turn_only: bool = False) -> None:
        """Report the state of a held condition every cycle. ``turn_only``: it holds the robot's travel but
        lets a turn on the spot through (``may_turn``), e.g. a round robot held by an obstacle ahead; a hold
        that changes between the two is a ``hold_changed`` event with the new message, not a new ``hold``
        (one stop, counted once: a repeat's stops on the way counted it twice)."""
        if active:
            self._clear_since.pop(cause, None)
            if cause not in self.holds or turn_only != (cause in self.turn_only):
                kind = "hold_changed" if cause in self.holds else "hold"
                self.holds[cause] = message
                (self.turn_only.add if turn_only else self.turn_only.discard)(cause)
                self._emit(SafetyEvent(now_ns, kind, cause, message))
            return
        if cause not in self.holds:
            return
        since = self._clear_since.setdefault(cause, now_ns)
        waiting = cause.endswith(WAITING)
        release_s = 0.0 if cause in RELEASE_AT_ONCE or waiting else self.release_s
        if now_ns - since >= release_s * 1e9:
            del self.holds[cause]
            del self._clear_since[cause]
            self.turn_only.discard(cause)
            # a wait ends with what it waited for, or with the stale hold that takes over (its own event)
            self._emit(SafetyEvent(now_ns, "release", cause, f"{cause} ended" if waiting
                                   else f"{cause} clear for {release_s:g} s"))

    def reset(self, now_ns: int, message: str = "operator resume") -> list[str]:
        """Clear the non-fatal latched stops (estop). Fatal ones need a restart."""
        cleared = [c for c in self.latched if c not in FATAL]
        for c in cleared:
            del self.latched[c]
            del self.latched_at[c]
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
    def latched_ns(self) -> int | None:
        """When the newest latched stop began (None when none is latched): what a resume names."""
        return max(self.latched_at.values(), default=None)

    def latched_after(self, seen_ns: int) -> list[str]:
        """The latched stops that began after ``seen_ns``, as 'cause (began at T: message)'."""
        return [f"{c} (began at {t}: {self.latched[c]})" for c, t in self.latched_at.items() if t > seen_ns]

    @property
    def may_move(self) -> bool:
        return not self.latched and not self.holds

    @property
    def may_turn(self) -> bool:
        """Held, but only by holds that let a turn on the spot through (forward speed 0): no latched stop, and
        every active hold ``turn_only``. False when ``may_move`` (nothing holds the robot at all)."""
        return not self.latched and bool(self.holds) and all(c in self.turn_only for c in self.holds)

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
