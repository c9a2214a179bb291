"""The hand-over of operator commands to the loop: a safety lane, and one teleop slot per sender.

Any thread (the zenoh callback, a test, a console) calls ``post``; the loop calls ``drain``
once per cycle. Neither blocks for long: both hold one lock for a few dictionary operations.

- **Safety lane** (estop, resume, mode): every accepted command is kept until the loop takes
  it, in arrival order. Nothing evicts it. ``resume`` and ``mode`` are refused (the sender
  gets a reason) once ``SAFETY_LANE_LIMIT`` are waiting; ``estop`` is never refused.
- **Teleop slots**: a teleop replaces the one still waiting from the same sender (coalescing:
  only the newest value matters), so a flood costs one slot, not a queue. A sender is
  ``(source, session)``; at most ``MAX_SENDERS`` are tracked at once, and a new sender beyond
  that is refused. Senders silent for longer than the command timeout are forgotten.
- **Order**: ``drain`` returns the commands in arrival order across both lanes, so a teleop
  that arrived before an estop is never applied after it.

Teleop freshness (``stale_after_ns`` = ``safety.command_timeout_s``) is judged by the
sender's clock, not by when the loop gets to a message:

- ``seq`` (optional): a teleop whose seq is not above the last accepted one from its sender
  is refused as out of order. A new ``session`` id is a new sender (a restarted process);
  a sender silent for longer than the timeout starts its seq afresh.
- ``stamp_ns`` (optional): the sender's ``time.monotonic_ns()`` when it sent the message.
  The robot estimates, per sender, offset = min over messages of (arrival - stamp): the
  minimum-delay filter. The message's send time on the robot's clock is stamp + offset, and
  its age at time t is t - (stamp + offset), i.e. (arrival - stamp - offset), the transport
  backlog beyond the fastest message seen, plus (t - arrival), the wait for the loop.
  A teleop older than the timeout when it arrives or when the loop takes it is refused, and
  the teleop controller times out at send time + timeout, so the wheels stop within
  timeout + 2 loop periods of the last message *sent*, however long it queued on the way.

  Clock assumption: the sender's and the robot's monotonic clocks need not agree (any
  offset; another machine), but must run at the same rate, within ``DRIFT`` (100 ppm;
  crystal clocks are within about 50 ppm): the offset estimate may rise by at most 100 us
  per second between messages (at most ``DRIFT_CAP_NS`` in all), to follow a sender clock
  that runs slow. The estimate includes the smallest transport delay seen, so ages are
  measured relative to the fastest message (sub-millisecond on a LAN). A sender that moves
  to another machine must use a new ``session``.
- A teleop without ``stamp_ns`` is accepted, its send time taken as its arrival time: a
  transport backlog before arrival then goes unseen (``vbnav send`` always stamps).
- A stamp that cannot be a reading of the sender's clock is refused and does not move the offset
  estimate: past an int64 (a monotonic_ns never is), or ahead of the sender's clock as tracked
  (arrival - offset) by more than the staleness window. Taken, one such stamp (10**300) was fresh
  by construction, drove the robot, and set the offset so far back that every later teleop of its
  sender (or of the operator whose ``sender`` and ``session`` a peer copied: they are what the
  message says) was stale for good. A stamp up to the window ahead is still taken: it cannot be
  told from a first message that was that long on the way, and it costs the sender at most that
  much of each later teleop's freshness (a new ``session`` starts afresh).
- A first message sets the offset estimate alone: one stamped far ahead (a clock glitch, a peer copying the
  sender and session) made every later teleop of that session stale for good. One monotonic clock numbered
  in order (``vbnav send``, ``vbnav teleop``, the live view) never gives a higher ``seq`` a lower stamp: such
  a message restarts the estimate from itself, as a new session would (no looser than one: a new session's
  first message is taken as sent on arrival too). Without ``seq`` nothing tells that glitch from a steady
  transport backlog the robot must refuse (both show every later message late by the same amount), so such
  a sender stays stale until it starts a new ``session``. (Signed commands come from this machine and read its
  clock: comms/operator_commands.py refuses their stamps ahead of it before they reach the mailbox. Unsigned
  senders may be anywhere, any offset: no bound on a first stamp exists.)
- A first ``seq`` far ahead (10**12: a bug, a peer copying the sender and session) made every later teleop of that
  session out of order while it kept sending. A message numbered at or below the last one taken but stamped
  after it cannot be a reordered or repeated one: the numbering restarted, and it is taken (``renumbered``).
  Reordered messages (a lower seq and an earlier stamp) are still refused; without ``stamp_ns`` nothing tells a
  restarted numbering from a reordering, and such a sender needs a new ``session`` (or a silence longer than the
  timeout).

After a loop stall, an estop or a lost drive the runtime calls ``refuse_teleop_sent_before``:
teleop sent before the stop began is stale, even if younger than the timeout (``sent_before_stop``
says so of a teleop already drained).
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, replace
from typing import Callable, Optional

SAFETY_LANE_LIMIT = 256      # waiting resume/mode commands; estop is never refused
MAX_SENDERS = 16             # teleop senders tracked at once
DRIFT = 1e-4                 # clock-rate difference the offset estimate follows (100 ppm)
DRIFT_CAP_NS = 10_000_000    # ... by at most 10 ms between two messages of a sender
INT64 = (-2 ** 63, 2 ** 63 - 1)   # a clock's nanosecond reading fits in one


@dataclass(frozen=True)
class OperatorCommand:
    """A command from outside the loop (network, CLI, tests), applied at the loop's next cycle.

    kind: "estop" | "resume" | "teleop" (args: v, w) | "mode" (args: mode[, route]).
    seq, stamp_ns, session: the sender's sequence number, send time on its own clock and session id
    (teleop ordering and freshness, see the module docstring); all optional.
    ack: the sender's id for this command, repeated in the events that answer it ("" for none).
    arrival_ns, order: set by ``CommandMailbox.post``. sent_ns: the send time on the robot's clock,
    set by ``drain`` for teleop.
    """

    kind: str
    args: tuple = ()
    source: str = "local"
    seq: Optional[int] = None
    stamp_ns: Optional[int] = None
    session: str = ""
    ack: str = ""
    arrival_ns: Optional[int] = None
    order: int = 0
    sent_ns: Optional[int] = None


class RefusalThrottle:
    """Refusals nobody waits for (a teleop stream at 10-20 Hz; a flood of malformed or unsigned commands,
    thousands a second) reported at most once per ``every_ns`` per reason key, the first one with a count of
    those held back since the last report; with ``max_reports``, at most that many reports of all keys
    together per ``every_ns`` (a sender can make up keys: a field name of its own starts a reason). Any thread."""

    MAX_KEYS = 256          # distinct keys remembered; a new one past them forgets the stalest
    _NEVER = -(1 << 62)     # a key held back but not reported yet

    def __init__(self, every_ns: int = 1_000_000_000, max_reports: Optional[int] = None):
        self.every_ns = every_ns
        self.max_reports = max_reports
        self._lock = threading.Lock()
        self._last: dict[str, tuple[int, int]] = {}     # key -> (last report ns, held back since)
        self._window = (self._NEVER, 0)                 # (start ns, reports in it) for max_reports

    def report(self, key: str, reason: str, now_ns: int, held: str = "teleop refused for this reason") -> Optional[str]:
        """The reason to report now (with the count of those held back, ``held`` saying what they were), or None
        to hold this one back."""
        with self._lock:
            if key not in self._last and len(self._last) >= self.MAX_KEYS:
                del self._last[min(self._last, key=lambda k: self._last[k][0])]
            last, since = self._last.get(key, (self._NEVER, 0))
            hold = now_ns - last < self.every_ns
            if not hold and self.max_reports is not None:
                start, n = self._window
                if now_ns - start >= self.every_ns:
                    start, n = now_ns, 0
                hold = n >= self.max_reports
                self._window = (start, n + (not hold))
            if hold:
                self._last[key] = (last, since + 1)
                return None
            self._last[key] = (now_ns, 0)
        if since:
            reason += f" (and {since} more {held} since the last report)"
        return reason


class _Entry:
    """A posted command with its arrival order and time (the command itself stays as the sender made it)."""

    __slots__ = ("cmd", "order", "arrival_ns")

    def __init__(self, cmd: OperatorCommand, order: int, arrival_ns: int):
        self.cmd, self.order, self.arrival_ns = cmd, order, arrival_ns


class _Sender:
    """What the mailbox knows about one teleop sender: ordering, clock offset, the waiting command."""

    __slots__ = ("last_seq", "last_stamp", "offset_ns", "offset_at", "last_arrival", "pending")

    def __init__(self):
        self.last_seq: Optional[int] = None
        self.last_stamp: Optional[int] = None    # the stamp of the message that set last_seq
        self.offset_ns: Optional[int] = None     # robot clock - sender clock, min-delay estimate
        self.offset_at = 0
        self.last_arrival = 0
        self.pending: Optional[_Entry] = None

    def observe_clock(self, arrival_ns: int, stamp_ns: int) -> None:
        d = arrival_ns - stamp_ns
        if self.offset_ns is None:
            self.offset_ns = d
        else:
            rise = min(int((arrival_ns - self.offset_at) * DRIFT), DRIFT_CAP_NS)
            self.offset_ns = min(self.offset_ns + max(rise, 0), d)
        self.offset_at = arrival_ns

    def two_clocks(self, seq: Optional[int], stamp_ns: int) -> bool:
        """Whether a message numbered after the last one taken carries an earlier stamp: one monotonic clock
        never reads so, so the stamps that set the offset estimate were not all this sender's clock."""
        return seq is not None and self.last_seq is not None and self.last_stamp is not None and \
            seq > self.last_seq and stamp_ns < self.last_stamp

    def renumbered(self, stamp_ns: Optional[int]) -> bool:
        """Whether a message numbered at or below the last one taken carries a later stamp: a reordered or
        repeated message never does (one clock numbers and stamps in order), so the numbering restarted (the
        last seq was a glitch, or the sender counts anew): taken, its seq the new last."""
        return stamp_ns is not None and self.last_stamp is not None and stamp_ns > self.last_stamp

    def impossible_stamp(self, arrival_ns: int, stamp_ns: int, window_ns: int, source: str) -> Optional[str]:
        """Why ``stamp_ns`` cannot be a reading of this sender's clock, else None."""
        if not INT64[0] <= stamp_ns <= INT64[1]:
            return (f"stamp_ns cannot be a reading of {source}'s clock: a {stamp_ns.bit_length()}-bit number, not an "
                    f"int64 nanosecond count")
        if self.offset_ns is None:
            return None
        ahead = stamp_ns - (arrival_ns - self.offset_ns)
        if ahead > window_ns:
            return (f"stamp_ns cannot be a reading of {source}'s clock: {ahead * 1e-6:.0f} ms ahead of it as the robot "
                    f"tracks it, more than the {window_ns * 1e-6:.0f} ms staleness window "
                    f"(safety.command_timeout_s); a sender whose clock was reset needs a new session")
        return None

    def sent_ns(self, e: _Entry) -> int:
        if e.cmd.stamp_ns is None or self.offset_ns is None:
            return e.arrival_ns
        return e.cmd.stamp_ns + self.offset_ns


class CommandMailbox:
    def __init__(self, now_ns: Callable[[], int], stale_after_ns: int):
        self._now = now_ns
        self.stale_after_ns = int(stale_after_ns)
        self._lock = threading.Lock()
        self._lane: list[_Entry] = []
        self._senders: dict[tuple[str, str], _Sender] = {}
        self._order = 0
        self._fresh_after_ns: Optional[int] = None
        self._fresh_why = ""      # what began then: "the loop stalled", "the estop", ...
        self.coalesced = 0        # teleops replaced by a newer one from the same sender before the loop took them
        self._closed = ""         # why the loop takes no more commands (the run ended)

    # -- any thread ------------------------------------------------------------
    def post(self, cmd: OperatorCommand) -> Optional[str]:
        """Accept ``cmd`` (returns None) or refuse it (returns the reason, for the sender)."""
        now = self._now()
        with self._lock:
            if self._closed:
                return self._closed
            self._order += 1
            e = _Entry(cmd, self._order, now if cmd.arrival_ns is None else cmd.arrival_ns)
            if cmd.kind != "teleop":
                if cmd.kind != "estop" and len(self._lane) >= SAFETY_LANE_LIMIT:
                    return (f"command lane full ({SAFETY_LANE_LIMIT} waiting): the loop is not taking commands; "
                            f"estop is still accepted")
                self._lane.append(e)
                return None
            return self._post_teleop(e)

    def _post_teleop(self, e: _Entry) -> Optional[str]:
        cmd, arrival = e.cmd, e.arrival_ns
        key = (cmd.source, cmd.session)
        s = self._senders.get(key)
        if s is None:
            self._forget_silent(arrival)
            if len(self._senders) >= MAX_SENDERS:
                return f"too many teleop senders ({MAX_SENDERS} active); this one is not tracked"
            s = self._senders[key] = _Sender()
        elif arrival - s.last_arrival > self.stale_after_ns:
            s.last_seq = None          # silent for longer than the timeout: a restarted sender may count anew
        if cmd.seq is not None and s.last_seq is not None and cmd.seq <= s.last_seq and \
                not s.renumbered(cmd.stamp_ns):
            return f"out of order: seq {cmd.seq} after {s.last_seq} from {cmd.source}"
        if cmd.stamp_ns is not None:
            if s.two_clocks(cmd.seq, cmd.stamp_ns):
                s.offset_ns = None     # tracked afresh from this message, as a new session would be
            impossible = s.impossible_stamp(arrival, cmd.stamp_ns, self.stale_after_ns, cmd.source)
            if impossible:
                return impossible
            s.observe_clock(arrival, cmd.stamp_ns)
        reason = self._stale(s, e, arrival)
        if reason:
            return reason
        if cmd.seq is not None:
            s.last_seq, s.last_stamp = cmd.seq, cmd.stamp_ns
        s.last_arrival = arrival
        if s.pending is not None:
            self.coalesced += 1
        s.pending = e
        return None

    def _stale(self, s: _Sender, e: _Entry, now: int) -> Optional[str]:
        sent = s.sent_ns(e)
        reason = self._sent_before_stop(sent)
        if reason:
            return reason
        age = now - sent
        if age > self.stale_after_ns:
            return (f"stale: sent {age * 1e-6:.0f} ms ago by the sender's clock "
                    f"(limit {self.stale_after_ns * 1e-6:.0f} ms, safety.command_timeout_s)")
        return None

    def _forget_silent(self, now: int) -> None:
        for key in [k for k, s in self._senders.items()
                    if s.pending is None and now - s.last_arrival > self.stale_after_ns]:
            del self._senders[key]

    # -- loop thread -------------------------------------------------------------
    def drain(self, now_ns: int) -> tuple[list[OperatorCommand], list[tuple[OperatorCommand, str]]]:
        """(commands to apply in arrival order, teleops refused as stale now). Never blocks for long."""
        refused: list[tuple[OperatorCommand, str]] = []
        with self._lock:
            if not self._lane and not any(s.pending is not None for s in self._senders.values()):
                return [], refused
            taken, self._lane = self._lane, []
            sent: dict[int, int] = {}
            for s in self._senders.values():
                e, s.pending = s.pending, None
                if e is None:
                    continue
                reason = self._stale(s, e, now_ns)
                if reason:
                    refused.append((e.cmd, reason + " when the loop took it"))
                else:
                    taken.append(e)
                    sent[e.order] = s.sent_ns(e)
        taken.sort(key=lambda e: e.order)
        return [replace(e.cmd, arrival_ns=e.arrival_ns, order=e.order, sent_ns=sent.get(e.order)) for e in taken], refused

    def close(self, why: str) -> list[OperatorCommand]:
        """The run ended: the commands still waiting (each needs its refusal), and every later post is
        refused with ``why``. Any thread."""
        with self._lock:
            self._closed = why
            waiting = [e.cmd for e in self._lane]
            waiting += [s.pending.cmd for s in self._senders.values() if s.pending is not None]
            self._lane = []
            for s in self._senders.values():
                s.pending = None
        return waiting

    def reopen(self) -> None:
        """A new run of the same loop takes commands again."""
        with self._lock:
            self._closed = ""

    def refuse_teleop_sent_before(self, t_ns: int, why: str = "the loop stalled") -> None:
        """After a stop (a stall, an estop): teleop sent before ``t_ns`` (robot clock) is stale from now on.
        why: what began at ``t_ns``, for the refusal."""
        with self._lock:
            if self._fresh_after_ns is None or t_ns >= self._fresh_after_ns:
                self._fresh_after_ns, self._fresh_why = t_ns, why

    def sent_before_stop(self, cmd: OperatorCommand) -> Optional[str]:
        """Loop thread: the refusal of a drained teleop sent before the last stop began, else None (a teleop
        that arrived behind an estop in the same drain, sent before it)."""
        if cmd.kind != "teleop" or cmd.sent_ns is None:
            return None
        with self._lock:
            return self._sent_before_stop(cmd.sent_ns)

    def _sent_before_stop(self, sent: int) -> Optional[str]:
        if self._fresh_after_ns is not None and sent < self._fresh_after_ns:
            return f"stale: sent {(self._fresh_after_ns - sent) * 1e-6:.0f} ms before {self._fresh_why}"
        return None

    @property
    def waiting(self) -> int:
        with self._lock:
            return len(self._lane) + sum(s.pending is not None for s in self._senders.values())
