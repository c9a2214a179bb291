"""Commands from the network: validated off the loop thread, handed over through a queue.

Keys (``<robot>`` is ``robot.name``), payloads JSON objects:

- ``vbnav/<robot>/cmd/estop``   ``{"reason": "..."}`` (optional): latching stop
- ``vbnav/<robot>/cmd/resume``  ``{}``: clears an estop latch
- ``vbnav/<robot>/cmd/teleop``  ``{"linear": m/s, "angular": rad/s}``: drive; must keep coming
- ``vbnav/<robot>/cmd/mode``    ``{"mode": "idle"|"teach"|"repeat", "route": "PATH"}``

Every payload may carry ``"seq"`` (int) and ``"sender"`` (str) for the audit trail, and
``"ack"`` (str): an id the robot repeats in the ``command`` event once the command took effect,
or in the ``command_rejected`` event, so a sender can wait for its own answer (``vbnav send``).

The zenoh callback thread parses and validates (pydantic) and puts a
``NetCommand`` into a bounded queue; the loop calls ``CommandInbox.drain()``
once per cycle, which never blocks. Malformed, unknown, out-of-range commands
or a full queue are rejected with a ``command_rejected`` event: they never raise
into zenoh or the loop and never move the robot. Unauthorised peers are stopped
earlier, by zenoh's access control (see network.py): their messages never
arrive.

Teleop silence is a stop condition of the runtime's ``TeleopController``
(control/manual.py, ``safety.command_timeout_s``), driven by the loop's clock.
"""
from __future__ import annotations

import json
import queue
from dataclasses import dataclass
from typing import Callable, Literal, Optional

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

INBOX_LIMIT = 64
MAX_PAYLOAD = 4096
ACK_PATTERN = r"^[A-Za-z0-9_\-]{1,64}$"


class _Cmd(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)
    seq: Optional[int] = None
    sender: Optional[str] = Field(None, max_length=64)
    ack: Optional[str] = Field(None, pattern=ACK_PATTERN, description="echoed in the command / command_rejected "
                               "event of this command")


class EstopCmd(_Cmd):
    reason: str = Field("", max_length=200)


class ResumeCmd(_Cmd):
    pass


class TeleopCmd(_Cmd):
    linear: float = Field(..., allow_inf_nan=False, description="m/s, forward positive")
    angular: float = Field(..., allow_inf_nan=False, description="rad/s, positive turns right")


class ModeCmd(_Cmd):
    mode: Literal["idle", "teach", "repeat"]
    route: Optional[str] = Field(None, min_length=1, max_length=1024)

    @field_validator("route")
    @classmethod
    def _plain_path(cls, v):
        if v is not None and any(ord(c) < 32 for c in v):
            raise ValueError("route path contains control characters")
        return v

    @model_validator(mode="after")
    def _repeat_needs_route(self):
        if self.mode == "repeat" and not self.route:
            raise ValueError("mode 'repeat' needs a route (\"route\": \"PATH\")")
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
        data = json.loads(payload) if payload and str(payload).strip() else {}
    except (ValueError, UnicodeDecodeError) as exc:
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


RejectFn = Callable[[str, str, str], None]   # (command kind, reason, payload excerpt)


class CommandInbox:
    """Thread-safe hand-over from network callbacks to the loop.

    ``submit`` (any thread) validates, then either passes the command to ``deliver`` (e.g.
    ``Runtime.submit``, itself a thread-safe queue the loop drains) or, without ``deliver``, queues it
    for ``drain`` (loop thread, never blocks). Invalid commands go to ``on_reject``.
    """

    def __init__(self, limits: TeleopLimits, on_reject: Optional[RejectFn] = None,
                 deliver: Optional[Callable[[NetCommand], None]] = None):
        self.limits = limits
        self._on_reject = on_reject
        self._deliver = deliver
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self.accepted = 0
        self.rejected = 0

    def submit(self, kind: str, payload: bytes | str) -> Optional[NetCommand]:
        try:
            cmd = parse_command(kind, payload, self.limits)
            if self._q.qsize() >= INBOX_LIMIT:
                raise CommandRejected(f"command queue full ({INBOX_LIMIT}); the loop is not draining")
        except CommandRejected as exc:
            self._reject(kind, str(exc), payload)
            return None
        except Exception as exc:  # never let a command crash the zenoh callback thread
            self._reject(kind, f"internal error: {exc!r}", payload)
            return None
        if self._deliver is not None:
            self._deliver(cmd)
        else:
            self._q.put(cmd)
        self.accepted += 1
        return cmd

    def drain(self, limit: int = INBOX_LIMIT) -> list[NetCommand]:
        """All queued commands, oldest first (empty list on most cycles)."""
        if self._q.qsize() == 0:
            return []
        out = []
        for _ in range(limit):
            try:
                out.append(self._q.get_nowait())
            except queue.Empty:
                break
        return out

    def _reject(self, kind: str, reason: str, payload) -> None:
        self.rejected += 1
        if self._on_reject is not None:
            excerpt = payload[:200] if isinstance(payload, str) else bytes(payload[:200]).decode("utf-8", "replace")
            try:
                self._on_reject(kind, reason, excerpt)
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
        try:
            key = str(sample.key_expr)
            kind = key[len(self._prefix):] if key.startswith(self._prefix) else key
            payload = sample.payload.to_bytes()
            if self._verify is not None:
                attachment = sample.attachment
                refused = self._verify(key, payload, None if attachment is None else attachment.to_bytes())
                if refused:
                    self._inbox._reject(kind, refused, payload)
                    return
            self._inbox.submit(kind, payload)
        except Exception as exc:  # pragma: no cover - submit already never raises
            self._inbox._reject("?", f"internal error: {exc!r}", b"")

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except Exception:
            pass


def limits_from_config(cfg) -> TeleopLimits:
    return TeleopLimits(cfg.robot.max_linear_speed, cfg.robot.max_angular_speed)
