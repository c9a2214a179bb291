"""Commands from the network: validated off the loop thread, handed to the loop's command mailbox.

Keys (``<robot>`` is ``robot.name``), payloads JSON objects:

- ``vbnav/<robot>/cmd/estop``   ``{"reason": "..."}`` (optional): latching stop
- ``vbnav/<robot>/cmd/resume``  ``{"latched_ns": T}`` (optional): clears an estop latch; with
  ``latched_ns`` (the state's ``safety.latched_ns`` its sender saw) only if no stop began after T
- ``vbnav/<robot>/cmd/teleop``  ``{"linear": m/s, "angular": rad/s}``: drive; must keep coming
- ``vbnav/<robot>/cmd/mode``    ``{"mode": "idle"|"teach"|"repeat", "route": "NAME"}`` (teach and repeat
  only: a route name inside the robot's ``controller.routes_dir``, never a path: control/route.py ``resolve_route``)

Every payload may carry ``"sender"`` (str), ``"session"`` (str, one per sender process),
``"seq"`` (int, increasing per session) and ``"stamp_ns"`` (int, the sender's
``time.monotonic_ns()`` when sent). For teleop, seq and stamp decide order and freshness
(control/runtime/mailbox.py: out-of-order and stale teleop is refused; the clock assumption
is documented there and in docs/telemetry.md). ``"ack"`` (str) is an id the robot repeats in
the ``command`` event once the command took effect, or in the ``command_rejected`` event, so a
sender can wait for its own answer (``vbnav send``).

The zenoh callback thread checks the payload's size before copying it into Python, parses and
validates it (pydantic), and posts an ``OperatorCommand`` to ``Runtime.submit`` (the
``CommandMailbox``): estop, resume and mode wait in a lane nothing evicts; teleop keeps only the
newest message per sender. The loop drains the mailbox once per cycle, never blocking.
Malformed, unknown, out-of-range, oversized, unsigned (with ``telemetry.shared_secret_file``),
stale or out-of-order commands are refused with a ``command_rejected`` event (but an estop whose body
is malformed or oversized stops the robot all the same, its trip naming the fault and its answer carrying the
payload's ``ack`` when one is there: ``refuse_body``). A refusal nobody waits for is reported
at most once a second per reason, with the count held back: stale and out-of-order teleop without
an ``ack``; any other payload without an ``ack``, or one whose signature failed, per command kind and
reason, 10 a second in all (a flood of them filled the telemetry queue's event places:
``CommandInbox.refuse``). They
never raise into zenoh or the loop and never move the robot. Unauthorised peers are stopped
earlier, by zenoh's access control (see network.py): their messages never arrive.

Teleop silence is a stop condition of the runtime's ``TeleopController``
(control/controllers/manual.py, ``safety.command_timeout_s``), counted from the last message's
send time.
"""
from __future__ import annotations

import re
import time
from dataclasses import dataclass
from typing import Callable, Literal, Optional

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from vbnav.control.comms.command_auth import FUTURE_SLACK_NS
from vbnav.control.route import check_route_name
from vbnav.control.runtime.mailbox import OperatorCommand, RefusalThrottle
from vbnav.drivers.plain_values import load_json

MAX_PAYLOAD = 4096                 # bytes; larger command payloads are refused unread
REPORT_EVERY_NS = 1_000_000_000    # refusals nobody waits for are reported at most this often per reason
UNANSWERED_REPORTS = 10            # and at most this many of them in all per REPORT_EVERY_NS
ACK_PATTERN = r"^[A-Za-z0-9_\-]{1,64}$"
ROUTE_MODES = ("teach", "repeat")  # the modes that take a route; idle takes none


#: the ack of a payload that may not parse (a refusal repeats it; a malformed estop's answer too)
ACK_IN_PAYLOAD = re.compile(r'"ack"\s*:\s*"(' + ACK_PATTERN.strip("^$") + ')"')
CONTROL_CHARACTERS = re.compile(r"[\x00-\x1f\x7f-\x9f]")
REASON_MAX_CHARS = 200             # an estop's reason


def _printable(v: Optional[str]) -> Optional[str]:
    """Free text the robot prints (its console's event echo, the journal, vbnav monitor): a terminal escape or a
    line break there could clear the screen or forge a line ('safety reset: estop')."""
    if v is not None:
        m = CONTROL_CHARACTERS.search(v)
        if m:
            raise ValueError(f"control character {m.group()!r} at {m.start()}: printable text only")
    return v


class _Cmd(BaseModel):
    # strict: types as JSON gives them (an int is a number too), never coerced: "linear": true was taken as
    # 1.0 m/s and "0.3" as 0.3, a sender's bug driving the robot instead of a refusal
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)
    seq: Optional[int] = Field(None, description="increasing per session: teleop at or below the last is refused")
    sender: Optional[str] = Field(None, max_length=64)
    session: Optional[str] = Field(None, max_length=64, description="one id per sender process; a new one "
                                   "restarts seq and clock tracking")
    stamp_ns: Optional[int] = Field(None, ge=0, description="sender's monotonic clock when sent, ns")
    ack: Optional[str] = Field(None, pattern=ACK_PATTERN, description="echoed in the command / command_rejected "
                               "event of this command")

    _printable_text = field_validator("sender", "session")(_printable)


class EstopCmd(_Cmd):
    reason: str = Field("", max_length=REASON_MAX_CHARS)

    _printable_reason = field_validator("reason")(_printable)


class ResumeCmd(_Cmd):
    latched_ns: Optional[int] = Field(None, description="the newest latched stop the sender has seen (the state's "
                                      "safety.latched_ns): a stop that began after it is not cleared, the resume is "
                                      "refused. Without it, every stop a resume may clear is cleared")


class TeleopCmd(_Cmd):
    linear: float = Field(..., allow_inf_nan=False, description="m/s, forward positive")
    angular: float = Field(..., allow_inf_nan=False, description="rad/s, positive turns right")


class ModeCmd(_Cmd):
    mode: Literal["idle", "teach", "repeat"]
    route: Optional[str] = Field(None, min_length=1, max_length=128,
                                 description="a route name in the robot's controller.routes_dir, never a path")

    @field_validator("route")
    @classmethod
    def _plain_name(cls, v):
        if v is not None:
            check_route_name(v)      # RouteError is a ValueError: pydantic reports it
        return v

    @model_validator(mode="after")
    def _route_as_the_mode_takes_it(self):
        if self.mode in ROUTE_MODES and not self.route:
            raise ValueError(f"mode {self.mode!r} needs a route (\"route\": \"NAME\")")
        if self.mode not in ROUTE_MODES and self.route is not None:
            # idle would show the route in its state while ignoring it
            raise ValueError(f"mode {self.mode!r} takes no route")
        return self


COMMAND_MODELS: dict[str, type[_Cmd]] = {"estop": EstopCmd, "resume": ResumeCmd, "teleop": TeleopCmd,
                                         "mode": ModeCmd}


@dataclass(frozen=True)
class NetCommand:
    kind: str           # estop | resume | teleop | mode
    body: _Cmd


@dataclass(frozen=True)
class TeleopLimits:
    max_linear: float   # m/s
    max_angular: float  # rad/s


class CommandRejected(ValueError):
    pass


def parse_command(kind: str, payload: bytes | str, limits: TeleopLimits) -> NetCommand:
    """Validate one command; raises CommandRejected with a reason a human can act on."""
    model = COMMAND_MODELS.get(kind)
    if model is None:
        raise CommandRejected(f"unknown command {kind!r}; expected one of {', '.join(COMMAND_MODELS)}")
    if len(payload) > MAX_PAYLOAD:
        raise CommandRejected(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    try:
        # a key given twice would keep its last value only, the other dropped unsaid: refused
        data = load_json(payload) if payload and str(payload).strip() else {}
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise CommandRejected(f"not JSON: {exc}") from None
    if not isinstance(data, dict):
        raise CommandRejected(f"expected a JSON object, got {type(data).__name__}")
    try:
        body = model.model_validate(data)
    except ValidationError as exc:
        errs = "; ".join(f"{'.'.join(map(str, e['loc'])) or kind}: {e['msg']}" for e in exc.errors())
        raise CommandRejected(errs) from None
    if isinstance(body, TeleopCmd):
        if abs(body.linear) > limits.max_linear + 1e-9:
            raise CommandRejected(f"linear {body.linear} m/s outside +-{limits.max_linear} (robot.max_linear_speed)")
        if abs(body.angular) > limits.max_angular + 1e-9:
            raise CommandRejected(f"angular {body.angular} rad/s outside +-{limits.max_angular} "
                                  f"(robot.max_angular_speed)")
    return NetCommand(kind, body)


def operator_command(cmd: NetCommand) -> OperatorCommand:
    """The runtime's ``OperatorCommand`` for a validated network command."""
    b = cmd.body
    if cmd.kind == "estop":
        args = (b.reason,) if b.reason else ()
    elif cmd.kind == "teleop":
        args = (b.linear, b.angular)
    elif cmd.kind == "mode":
        args = (b.mode, b.route) if b.route else (b.mode,)
    elif cmd.kind == "resume":
        args = () if b.latched_ns is None else (b.latched_ns,)
    else:
        args = ()
    return OperatorCommand(cmd.kind, args, source=f"zenoh:{b.sender}" if b.sender else "zenoh", seq=b.seq,
                           stamp_ns=b.stamp_ns, session=b.session or "", ack=b.ack or "")


# (command kind, reason, payload excerpt, verified: False when the payload failed its signature check, so the ack
# it carries may be anyone's and is no answer to its sender)
RejectFn = Callable[[str, str, str, bool], None]


class CommandInbox:
    """Validates commands from any thread and delivers them; reports every refusal.

    ``submit`` parses a payload, turns it into an ``OperatorCommand`` and passes it to
    ``deliver`` (``Runtime.submit``: the loop's mailbox), which returns None when it took the
    command or the reason it refused it. Refusals go to ``on_reject``; those nobody waits for (a
    flood would flood the events) at most once per second, telling how many were refused since the
    last report: teleop without an ``ack`` that the mailbox refused per reason, any other without an
    ``ack`` or with a failed signature per command kind and reason, 10 a second in all (``refuse``).
    """

    def __init__(self, limits: TeleopLimits, deliver: Callable[[OperatorCommand], Optional[str]],
                 on_reject: Optional[RejectFn] = None, now_ns: Callable[[], int] = time.monotonic_ns,
                 shared_clock: Optional[Callable[[], int]] = None):
        self.limits = limits
        # the monotonic clock senders stamp by when it is this machine's (signed commands: command_auth.py); a
        # stamp_ns ahead of it by more than FUTURE_SLACK_NS is no reading of it
        self._shared_clock = shared_clock
        self._deliver = deliver
        self._on_reject = on_reject
        self._now = now_ns
        self._reports = RefusalThrottle(REPORT_EVERY_NS)   # stream refusals: once a second per reason
        # refusals nobody waits for: once a second per kind and reason, UNANSWERED_REPORTS a second in all
        self._unanswered = RefusalThrottle(REPORT_EVERY_NS, UNANSWERED_REPORTS)
        self.accepted = 0
        self.rejected = 0

    def submit(self, kind: str, payload: bytes | str) -> Optional[NetCommand]:
        """The command if the loop's mailbox took it, else None (and a refusal report)."""
        try:
            cmd = parse_command(kind, payload, self.limits)
            self._check_shared_clock(cmd)
            reason = self._deliver(operator_command(cmd))
        except CommandRejected as exc:
            self.refuse_body(kind, str(exc), payload)
            return None
        except Exception as exc:  # never let a command crash the zenoh callback thread
            self.refuse_body(kind, f"internal error: {exc!r}", payload)
            return None
        if reason:
            # A teleop that asks for an answer (ack: vbnav send) gets one; a stream without acks is summarised.
            self.refuse(kind, reason, payload, stream=kind == "teleop" and not cmd.body.ack)
            return None
        self.accepted += 1
        return cmd

    def _check_shared_clock(self, cmd: NetCommand) -> None:
        """CommandRejected when the sender shares this machine's clock and its stamp_ns lies ahead of it: taken, a
        first teleop so stamped set its sender's clock offset, and every later teleop of the session was stale."""
        stamp = cmd.body.stamp_ns
        if self._shared_clock is None or stamp is None:
            return
        ahead = stamp - self._shared_clock()
        if ahead > FUTURE_SLACK_NS:
            raise CommandRejected(f"stamp_ns is {ahead * 1e-6:.0f} ms ahead of this machine's monotonic clock, which "
                                  f"a sender of signed commands shares (telemetry.shared_secret_file): more than "
                                  f"{FUTURE_SLACK_NS * 1e-6:.0f} ms, no reading of it")

    def refuse_body(self, kind: str, reason: str, payload) -> None:
        """A payload that is not a valid command (``reason``): refused, except an estop's. A stop asked for on
        cmd/estop by a peer allowed to command is taken whatever else its body says (a reason too long or
        null, an unknown key, not JSON, too large to read): refused, the robot drove on. Its trip names what
        was wrong with the body."""
        if kind != "estop":
            self.refuse(kind, reason, payload)
            return
        why = f"its payload was refused ({reason[:300]}), stopped all the same"
        text = payload[:MAX_PAYLOAD] if isinstance(payload, str) else bytes(payload[:MAX_PAYLOAD]).decode("utf-8",
                                                                                                     "replace")
        m = ACK_IN_PAYLOAD.search(text)          # its answer goes to the sender waiting for it
        refused = self._deliver(OperatorCommand("estop", (why,), source="zenoh", ack=m.group(1) if m else ""))
        # the mailbox never refuses an estop but when the run ended
        if refused:
            self.refuse(kind, refused, payload)
        else:
            self.accepted += 1

    def refuse(self, kind: str, reason: str, payload, stream: bool = False, verified: bool = True) -> None:
        """Count a refusal and report it (``payload``: the bytes, or b"" when it was not read).

        verified: False for a payload whose signature failed (unsigned, replayed, changed): anyone may have sent
        it, a copy of an operator's command among them, so its ack is reported as not its sender's answer.

        stream: a teleop the mailbox refused (stale, out of order, too many senders), which a flood
        repeats thousands of times: reported at most once a second per reason.

        A refusal that answers nobody (its payload carries no ack, or failed its signature) is reported at most
        once a second per command kind and reason (its first word), with the count held back, and at most
        UNANSWERED_REPORTS of them a second in all (a field name of the sender's own starts a reason): a flood of
        malformed or unsigned commands made one ``command_rejected`` event each, which filled the events' places
        in the telemetry queue ahead of the answers and safety events behind them. A refusal a sender waits for
        (a verified payload with an ack: ``vbnav send``) is always reported."""
        self.rejected += 1
        if self._on_reject is None:
            return
        excerpt = payload[:200] if isinstance(payload, str) else bytes(payload[:200]).decode("utf-8", "replace")
        words = reason.split(maxsplit=1)
        word = words[0].rstrip(":") if words else ""
        if stream:
            reason = self._reports.report(word, reason, self._now())
        elif not (verified and ACK_IN_PAYLOAD.search(excerpt)):
            known = kind if kind in COMMAND_MODELS else "unknown"      # any key under cmd/ arrives: not one each
            how = "" if verified else " unverified"
            reason = self._unanswered.report(f"{known}{how}:{word}", reason, self._now(),
                                             held=f"{known}{how} commands refused for this reason")
        if reason is None:
            return
        try:
            self._on_reject(kind, reason, excerpt, verified)
        except Exception:
            pass


VerifyFn = Callable[[str, bytes, Optional[bytes]], Optional[str]]   # (key, payload, attachment) -> refusal


class CommandSubscriber:
    """Subscribes ``vbnav/<robot>/cmd/**`` on a zenoh session and feeds an inbox (reliable delivery).

    verify: checks each sample before it is parsed (the shared-secret signature, comms/command_auth.py);
    a refused sample becomes a ``command_rejected`` report and never reaches the inbox.
    """

    def __init__(self, session, robot: str, inbox: CommandInbox, verify: Optional[VerifyFn] = None):
        self._prefix = f"vbnav/{robot}/cmd/"
        self._inbox = inbox
        self._verify = verify
        self._sub = session.declare_subscriber(f"vbnav/{robot}/cmd/**", self._on_sample)

    def _on_sample(self, sample) -> None:
        kind = "?"
        try:
            key = str(sample.key_expr)
            kind = key[len(self._prefix):] if key.startswith(self._prefix) else key
            size = len(sample.payload)       # zenoh's buffer: nothing is copied into Python yet
            if size > MAX_PAYLOAD:
                self._inbox.refuse_body(kind, f"payload of {size} bytes exceeds {MAX_PAYLOAD}; not read", b"")
                return
            payload = sample.payload.to_bytes()
            if self._verify is not None:
                attachment = sample.attachment
                refused = self._verify(key, payload, None if attachment is None else attachment.to_bytes())
                if refused:
                    self._inbox.refuse(kind, refused, payload, verified=False)
                    return
            self._inbox.submit(kind, payload)
        except Exception as exc:  # pragma: no cover - submit already never raises
            self._inbox.refuse(kind, f"internal error: {exc!r}", b"")

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except Exception:
            pass


def limits_from_config(cfg) -> TeleopLimits:
    return TeleopLimits(cfg.robot.max_linear_speed, cfg.robot.max_angular_speed)
