"""An emulated ODrive (firmware 0.5.x ASCII protocol) behind a pseudo-terminal.

Commands served (one per line, optionally followed by ``*<xor of the bytes before *>``;
answers to a checksummed command carry a checksum too, as the firmware does):

- ``v <axis> <vel turns/s> [torque_ff]``: velocity setpoint (feeds the watchdog)
- ``f <axis>``: answers ``<pos turns> <vel turns/s>``
- ``u <axis>``: feeds the watchdog
- ``r <property>`` / ``w <property> <value>``: read / write a property
- ``sc``: clear errors on both axes (the axes stay idle until requested again)

Axis behaviour: the velocity loop runs only in CLOSED_LOOP_CONTROL (state 8)
with control_mode VELOCITY (2). An axis error drops the axis to IDLE (1). The
watchdog (``axisN.config.enable_watchdog``, ``axisN.config.watchdog_timeout``)
expires without feeds in closed loop: AXIS_ERROR_WATCHDOG_TIMER_EXPIRED (0x800).
Faults: ``no_answer`` (the whole device silent), ``corrupt`` (answers with a
wrong checksum or garbled text), ``axis(n).inject(motor=..., encoder=...)``,
``axis(n).ignores_commands`` (the axis takes no ``v``/``w``: lines lost on their way, a
hung axis; it still answers reads, so a host that reads back sees it did not stop);
``axis(n).idle_after_s`` (a requested IDLE is reached that long after the request).

Baud rate: the emulated port is the ODrive's USB CDC port, which ignores the
rate (as the real one does); the host may set any.

Logging (``vbnav.emulator.odrive``; ``vbnav emulate odrive -v``/``-vv``): INFO
for watchdog expiry, errors cleared, injected faults, plug events; DEBUG for
every line received.
"""
from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Optional

from vbnav.drivers.sim.dynamixel_emulator import WheelCoupling
from vbnav.drivers.sim.pty_device import LoggedFlag, PtyDevice

log = logging.getLogger("vbnav.emulator.odrive")

AXIS_STATE_IDLE = 1
AXIS_STATE_CLOSED_LOOP = 8
CONTROL_MODE_VELOCITY = 2
INPUT_MODE_VEL_RAMP = 2
AXIS_ERROR_INVALID_STATE = 0x1
AXIS_ERROR_MOTOR_FAILED = 0x40
AXIS_ERROR_ENCODER_FAILED = 0x100
AXIS_ERROR_WATCHDOG_EXPIRED = 0x800


def checksum(text: str) -> int:
    c = 0
    for b in text.encode("ascii"):
        c ^= b
    return c


class EmulatedAxis:
    def __init__(self, index: int):
        self.index = index
        self.current_state = AXIS_STATE_IDLE
        self.error = 0
        self.motor_error = 0
        self.encoder_error = 0
        self.controller_error = 0
        self.control_mode = 3  # position control at power-on
        self.input_mode = 1  # passthrough
        self.input_vel = 0.0
        self.vel_limit = 2.0  # turns/s
        self.vel_ramp_rate = 1.0  # turns/s^2
        self.vel_setpoint = 0.0   # what the velocity loop follows: input_vel, ramped in VEL_RAMP input mode
        self.watchdog_timeout = 0.0
        self.enable_watchdog = False
        self.pos = 0.0
        self.vel = 0.0
        self.last_feed = time.monotonic()
        self.time_constant_s = 0.02  # velocity loop response
        self.ignores_commands = False    # fault: v and w to this axis are dropped (reads are answered)
        self.idle_after_s = 0.0          # a requested IDLE is reached this long after the request
        self._idle_at: Optional[float] = None

    def properties(self) -> dict[str, tuple]:
        """name -> (getter, setter or None)."""
        def attr(name, kind=float):
            return (lambda: getattr(self, name),
                    lambda v: setattr(self, name, kind(v)))
        return {
            "current_state": (lambda: self.current_state, None),
            "requested_state": (lambda: 0, self.request_state),
            "error": attr("error", int),
            "motor.error": attr("motor_error", int),
            "encoder.error": attr("encoder_error", int),
            "controller.error": attr("controller_error", int),
            "controller.config.control_mode": attr("control_mode", int),
            "controller.config.input_mode": attr("input_mode", int),
            "controller.config.vel_limit": attr("vel_limit"),
            "controller.config.vel_ramp_rate": attr("vel_ramp_rate"),
            "controller.input_vel": attr("input_vel"),
            "config.watchdog_timeout": attr("watchdog_timeout"),
            "config.enable_watchdog": (lambda: int(self.enable_watchdog),
                                       lambda v: setattr(self, "enable_watchdog", bool(int(float(v))))),
            "encoder.pos_estimate": (lambda: self.pos, None),
            "encoder.vel_estimate": (lambda: self.vel, None),
        }

    def any_error(self) -> bool:
        return bool(self.error or self.motor_error or self.encoder_error or self.controller_error)

    def request_state(self, value) -> None:
        state = int(float(value))
        if state == AXIS_STATE_CLOSED_LOOP:
            if self.any_error():
                self.error |= AXIS_ERROR_INVALID_STATE
                return
            self.last_feed = time.monotonic()
            self.current_state = AXIS_STATE_CLOSED_LOOP
        elif state == AXIS_STATE_IDLE:
            if self.idle_after_s > 0:      # the state machine leaves closed loop at its own pace
                self._idle_at = time.monotonic() + self.idle_after_s
            else:
                self.current_state = AXIS_STATE_IDLE

    def inject(self, motor: int = 0, encoder: int = 0, controller: int = 0) -> None:
        """A hardware fault: the axis records it and disarms."""
        self.motor_error |= motor
        self.encoder_error |= encoder
        self.controller_error |= controller
        if motor:
            self.error |= AXIS_ERROR_MOTOR_FAILED
        if encoder:
            self.error |= AXIS_ERROR_ENCODER_FAILED
        self.current_state = AXIS_STATE_IDLE
        log.info("axis%d: fault injected (motor 0x%x, encoder 0x%x, controller 0x%x): disarmed", self.index,
                 motor, encoder, controller)

    def clear_errors(self) -> None:
        self.error = self.motor_error = self.encoder_error = self.controller_error = 0

    def feed(self) -> None:
        self.last_feed = time.monotonic()

    def check_watchdog(self, now: float) -> bool:
        if (self.enable_watchdog and self.watchdog_timeout > 0 and self.current_state == AXIS_STATE_CLOSED_LOOP
                and now - self.last_feed > self.watchdog_timeout):
            self.error |= AXIS_ERROR_WATCHDOG_EXPIRED
            self.current_state = AXIS_STATE_IDLE
            log.info("axis%d: watchdog expired (no feed for %.0f ms): WATCHDOG_TIMER_EXPIRED, disarmed",
                     self.index, self.watchdog_timeout * 1000)
            return True
        return False

    def target(self) -> float:
        if self.current_state != AXIS_STATE_CLOSED_LOOP or self.control_mode != CONTROL_MODE_VELOCITY:
            return 0.0
        return max(-self.vel_limit, min(self.vel_limit, self.vel_setpoint))

    def _ramp(self, dt: float) -> None:
        """input_vel -> vel_setpoint: at once in passthrough, at ``vel_ramp_rate`` in VEL_RAMP; from 0 when
        the axis (re)enters closed loop."""
        if self.current_state != AXIS_STATE_CLOSED_LOOP:
            self.vel_setpoint = 0.0
        elif self.input_mode == INPUT_MODE_VEL_RAMP:
            step = abs(self.vel_ramp_rate) * dt
            self.vel_setpoint += max(-step, min(step, self.input_vel - self.vel_setpoint))
        else:
            self.vel_setpoint = self.input_vel

    def step(self, dt: float, coupling: Optional[WheelCoupling] = None) -> None:
        if self._idle_at is not None and time.monotonic() >= self._idle_at:
            self.current_state, self._idle_at = AXIS_STATE_IDLE, None
        self._ramp(dt)
        target = self.target()
        if coupling is not None:
            coupling.command(self.index, target * 2 * math.pi)
            angle, rate = coupling.measure(self.index)
            self.pos, self.vel = angle / (2 * math.pi), rate / (2 * math.pi)
            return
        alpha = 1.0 - math.exp(-dt / self.time_constant_s) if self.time_constant_s > 0 else 1.0
        self.vel += (target - self.vel) * alpha
        self.pos += self.vel * dt


class ODriveEmulator(PtyDevice):
    """A two-axis ODrive on a pty. ``start()`` returns the device path."""

    thread_name = "odrive-emulator"
    logger_name = log.name

    def __init__(self, link: str | Path | None = None, coupling: Optional[WheelCoupling] = None,
                 step_s: float = 0.001):
        self.axes = [EmulatedAxis(0), EmulatedAxis(1)]
        super().__init__(link, step_s)
        self.coupling = coupling
        self.vbus_voltage = 24.0
        self.log: list[tuple[float, str]] = []
        self._buf = b""
        self._t0 = time.monotonic()
        # Answers held back (a slow or loaded device, fault injected with ``reply_delay_s``): (due, bytes).
        self.reply_delay_s = 0.0
        self._due: list[tuple[float, bytes]] = []

    def axis(self, n: int) -> EmulatedAxis:
        return self.axes[n]

    # -- injected faults (logged) --------------------------------------------------------
    no_answer = LoggedFlag("silent (fault injected)", "answers again")
    corrupt = LoggedFlag("garbles its answers (fault injected)", "answers intact again")

    def _log_event(self, text: str) -> None:
        log.info("%s", text)

    # -- serving (the pty lifecycle is PtyDevice's, shared with the Dynamixel bus) ------------
    def _reset_input(self) -> None:
        self._buf = b""
        self._due.clear()       # answers held back belong to the old byte stream, lost with it

    def _serve_bytes(self, data: bytes) -> None:
        out = self.handle_bytes(data)
        if out and self.reply_delay_s > 0:
            self._due.append((time.monotonic() + self.reply_delay_s, out))
        elif out:
            self._write(out)

    def _step(self, now: float, dt: float) -> None:
        while self._due and self._due[0][0] <= now:
            self._write(self._due.pop(0)[1])
        for ax in self.axes:
            if ax.check_watchdog(now):
                self._log(f"watchdog_expired {ax.index}")
            ax.step(dt, self.coupling)

    def _log(self, text: str) -> None:
        self.log.append((time.monotonic() - self._t0, text))
        if len(self.log) > 20000:
            del self.log[:10000]

    # -- protocol ----------------------------------------------------------------------
    def handle_bytes(self, data: bytes) -> bytes:
        """Feed raw bytes; return the answer bytes (used by the pty thread and by tests)."""
        with self.lock:
            self._buf += data
            out = []
            while b"\n" in self._buf:
                line, _, self._buf = self._buf.partition(b"\n")
                text = line.decode("ascii", "replace").strip("\r ")
                if not text:
                    continue
                answer = self._line(text)
                if answer is not None and not self.no_answer:
                    out.append(answer)
            return "".join(out).encode("ascii")

    def _line(self, text: str) -> Optional[str]:
        use_checksum = False
        if "*" in text:
            body, _, given = text.rpartition("*")
            try:
                ok = int(given) == checksum(body)
            except ValueError:
                ok = False
            if not ok:
                log.info("line with a bad checksum dropped: %r", text)
                return None  # the firmware silently drops a line with a bad checksum
            text, use_checksum = body.strip(), True
        self._log(text)
        reply = self._command(text.split())
        log.debug("%r -> %r", text, reply)
        if reply is None:
            return None
        if use_checksum:
            reply = f"{reply}*{checksum(reply) ^ (0xFF if self.corrupt else 0)}"
        elif self.corrupt:
            reply = reply.replace(" ", "#")
        return reply + "\r\n"

    def _command(self, tok: list[str]) -> Optional[str]:
        cmd = tok[0]
        try:
            if cmd == "v":
                ax = self.axes[int(tok[1])]
                if ax.ignores_commands:
                    return None
                ax.input_vel = float(tok[2])
                ax.feed()
                return None
            if cmd == "f":
                ax = self.axes[int(tok[1])]
                return f"{ax.pos:.6f} {ax.vel:.6f}"
            if cmd == "u":
                self.axes[int(tok[1])].feed()
                return None
            if cmd == "sc":
                if any(ax.any_error() for ax in self.axes):
                    log.info("sc: errors cleared (%s)", ", ".join(
                        f"axis{ax.index} error 0x{ax.error:x}" for ax in self.axes if ax.any_error()))
                for ax in self.axes:
                    ax.clear_errors()
                return None
            if cmd == "r":
                getter, _ = self._property(tok[1])
                if getter is None:
                    return "invalid property"
                value = getter()
                return f"{value:.6f}" if isinstance(value, float) else str(value)
            if cmd == "w":
                _, setter = self._property(tok[1])
                if setter is None:
                    return "invalid property"
                setter(tok[2])
                return None
        except (IndexError, ValueError):
            return "invalid command format"
        return "unknown command"

    def _property(self, name: str):
        if name == "vbus_voltage":
            return (lambda: self.vbus_voltage), None
        if name == "fw_version_minor":
            return (lambda: 5), None
        if name.startswith("axis") and "." in name:
            head, _, rest = name.partition(".")
            try:
                ax = self.axes[int(head[4:])]
            except (ValueError, IndexError):
                return None, None
            getter, setter = ax.properties().get(rest, (None, None))
            if setter is not None and ax.ignores_commands:
                return getter, _dropped
            return getter, setter
        return None, None


def _dropped(value) -> None:
    """The setter of an axis that ignores commands: the write is lost."""
