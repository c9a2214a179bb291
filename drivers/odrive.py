"""ODrive wheels over the ASCII protocol (pyserial), closed-loop velocity control of two axes.

Per cycle: ``v <axis> <turns/s>`` for both axes (it feeds the axis watchdog in
the firmware; ``u`` feeds it where no command is due) and ``f <axis>`` for
position and velocity. Every ``error_poll_every`` cycles the axis error words
are read; any error (or an axis that left closed loop) is a fault: both axes go
to IDLE and ``DriveError`` names the decoded bits. ``clear_faults()`` sends
``sc``. Optional ``*<xor>`` checksums on every line (answers are checked too).

Units: wheel rad/s <-> motor turns/s through ``gear_ratio`` (motor turns per wheel turn).
"""
from __future__ import annotations

import math
import os
import select
import termios
import time
from typing import Any, Optional

from pydantic import ConfigDict, Field, model_validator
from vbnav.drivers.plain_values import PlainValues

from vbnav.drivers.serial_drive import SerialWheelDrive, require_two_wheels
from vbnav.drivers.wheels import DriveError, DriveFault, DriveState, FaultKind, WheelState

try:
    import serial
except ImportError:  # pragma: no cover - pyserial is a dependency
    serial = None

AXIS_STATE_IDLE = 1
AXIS_STATE_CLOSED_LOOP = 8
CONTROL_MODE_VELOCITY = 2
INPUT_MODE_PASSTHROUGH = 1
INPUT_MODE_VEL_RAMP = 2

# firmware 0.5.x error bits (a subset named; others print as hex)
AXIS_ERRORS = {0x1: "INVALID_STATE", 0x40: "MOTOR_FAILED", 0x100: "ENCODER_FAILED", 0x200: "CONTROLLER_FAILED",
               0x800: "WATCHDOG_TIMER_EXPIRED", 0x2000: "MAX_ENDSTOP_PRESSED", 0x4000: "ESTOP_REQUESTED",
               0x20000: "HOMING_WITHOUT_ENDSTOP", 0x40000: "OVER_TEMP", 0x80000: "UNKNOWN_POSITION"}
MOTOR_ERRORS = {0x1: "PHASE_RESISTANCE_OUT_OF_RANGE", 0x2: "PHASE_INDUCTANCE_OUT_OF_RANGE", 0x8: "DRV_FAULT",
                0x10: "CONTROL_DEADLINE_MISSED", 0x80: "MODULATION_MAGNITUDE", 0x400: "CURRENT_SENSE_SATURATION",
                0x1000: "CURRENT_LIMIT_VIOLATION", 0x10000: "MODULATION_IS_NAN", 0x20000: "MOTOR_THERMISTOR_OVER_TEMP",
                0x40000: "FET_THERMISTOR_OVER_TEMP"}
ENCODER_ERRORS = {0x1: "UNSTABLE_GAIN", 0x2: "CPR_POLEPAIRS_MISMATCH", 0x4: "NO_RESPONSE",
                  0x8: "UNSUPPORTED_ENCODER_MODE", 0x10: "ILLEGAL_HALL_STATE", 0x20: "INDEX_NOT_FOUND_YET",
                  0x40: "ABS_SPI_TIMEOUT", 0x80: "ABS_SPI_COM_FAIL", 0x100: "ABS_SPI_NOT_READY"}
AXIS_ERROR_WATCHDOG_EXPIRED = 0x800
CONTROLLER_ERRORS = {0x1: "OVERSPEED", 0x2: "INVALID_INPUT_MODE", 0x4: "UNSTABLE_GAIN", 0x8: "INVALID_MIRROR_AXIS",
                     0x10: "INVALID_LOAD_ENCODER", 0x20: "INVALID_ESTIMATE", 0x40: "INVALID_CIRCULAR_RANGE",
                     0x80: "SPINOUT_DETECTED"}

ERROR_WORDS = (("error", AXIS_ERRORS), ("motor.error", MOTOR_ERRORS), ("encoder.error", ENCODER_ERRORS),
               ("controller.error", CONTROLLER_ERRORS))


def clear_errors_command(config_source: Optional[str]) -> str:
    """The command that clears the ODrive's latched errors, for the configuration the drive was built from
    (``CONFIG`` where that is not known)."""
    return f"vbnav odrive clear-errors -c {config_source or 'CONFIG'}"


def decode_bits(value: int, table: dict[int, str]) -> list[str]:
    names = [name for bit, name in table.items() if value & bit]
    rest = value & ~sum(b for b in table if value & b)
    if rest:
        names.append(f"0x{rest:x}")
    return names


def xor_checksum(text: str) -> int:
    c = 0
    for b in text.encode("ascii"):
        c ^= b
    return c


class ODriveDrive(SerialWheelDrive):
    name = "odrive"
    drive_name = "ODrive"
    device_name = "ODrive"

    class Options(PlainValues):
        model_config = ConfigDict(extra="forbid")
        port: str = Field("/dev/ttyACM0", description="ODrive USB CDC or UART device")
        baudrate: int = Field(115200, description="UART rate (ignored by USB CDC)")
        left_axis: int = Field(0, ge=0, le=1, description="axis of the left wheel motor")
        right_axis: int = Field(1, ge=0, le=1, description="axis of the right wheel motor")
        gear_ratio: float = Field(1.0, gt=0, description="motor turns per wheel turn")
        vel_limit_turns_s: float = Field(2.0, gt=0, description="axisN.controller.config.vel_limit")
        vel_ramp_rate: float = Field(0.0, ge=0, description="turns/s^2 (input_mode VEL_RAMP); 0 = passthrough")
        watchdog_s: float = Field(0.1, gt=0, description="axis watchdog: the axis disarms after this silence; "
                                  "at least two loop periods (the loop writes once a cycle; refused below)")
        checksum: bool = Field(False, description="append *<xor> to every line and check answers")
        reply_timeout_s: float = Field(0.005, gt=0, le=0.5, description="wait for one answer line in the loop")
        setup_timeout_s: float = Field(0.1, gt=0, le=2.0, description="wait for an answer during setup")
        error_poll_every: int = Field(10, ge=1, description="read the error words every N cycles")
        max_missed_reads: int = Field(8, ge=1, description="consecutive failed reads that make a fault (the "
                                      "state is held meanwhile; the writes still feed the axis watchdog): 8 at "
                                      "100 Hz tolerates 80 ms of misses, within the 100 ms axis watchdog")
        reconnect_interval_s: float = Field(0.5, gt=0, description="how often a lost adapter is looked for")
        clear_watchdog_error_at_start: bool = Field(
            False, description="an axis found at start-up with only WATCHDOG_TIMER_EXPIRED set (the host went "
                               "silent: a crash or a killed process) is cleared and brought up. Off: the run "
                               "refuses to start and names 'vbnav odrive clear-errors -c CONFIG'. A lost bus that "
                               "comes back during a run is always cleared: this process went silent itself")

        @model_validator(mode="after")
        def _two_axes(self):
            return require_two_wheels(self, "left_axis", "right_axis", "each wheel needs its own axis (0 and 1)")

    def __init__(self, cfg: Any = None, clock=None, *, options: Optional["ODriveDrive.Options"] = None,
                 invert_left: Optional[bool] = None, invert_right: Optional[bool] = None):
        super().__init__(cfg, clock, options=options, invert_left=invert_left, invert_right=invert_right)
        self.axes = (self.opt.left_axis, self.opt.right_axis)
        self.sides = {self.opt.left_axis: "left", self.opt.right_axis: "right"}
        self.ser = None
        self.vbus_voltage: Optional[float] = None   # bus voltage, V, read at bring-up
        self._owed_s = 0.0       # a question timed out this long: its answer may still come (_settle)
        self._cycle = 0
        self._rx = b""
        self._was_up = False        # brought up once by this process (a later bring-up is a reconnect)
        self.cleared_watchdogs: list[DriveFault] = []   # expired axis watchdogs the last bring-up cleared

    @property
    def watchdog(self) -> Optional[tuple[float, str]]:
        return self.opt.watchdog_s, "drive.options.watchdog_s"

    @property
    def wheel_speed_limit(self) -> Optional[tuple[float, str]]:
        return self.opt.vel_limit_turns_s * 2 * math.pi / self.opt.gear_ratio, \
            "drive.options.vel_limit_turns_s / gear_ratio"

    # -- lifecycle hooks (WheelDrive owns the states) ------------------------------------
    def _configure(self) -> None:
        self._connect(clear_errors=False)

    def _connect(self, clear_errors: bool) -> None:
        self.cleared_watchdogs = []
        if not os.path.exists(self.opt.port):
            raise DriveError(f"ODrive {self.opt.port} not found (is it plugged in? see /dev/serial/by-id/)")
        try:
            self.ser = serial.Serial(self.opt.port, self.opt.baudrate, timeout=0)
            # answers still queued from before (late replies that made a reconnect necessary) would be
            # taken for the answers to the bring-up's questions
            self.ser.reset_input_buffer()
            self._owed_s = 0.0
        except (serial.SerialException, OSError, termios.error) as exc:
            raise DriveError(f"cannot open ODrive {self.opt.port}: {exc}") from exc
        try:
            t = self.opt.setup_timeout_s
            vbus = self._query("r vbus_voltage", t)
            if vbus is None:
                raise DriveError(f"ODrive on {self.opt.port} does not answer 'r vbus_voltage'")
            try:
                self.vbus_voltage = float(vbus)
            except ValueError:
                raise DriveError(f"ODrive on {self.opt.port} answers 'r vbus_voltage' with {vbus!r}") from None
            if clear_errors:
                self._send("sc")
            for ax in self.axes:
                self._send(f"w axis{ax}.requested_state {AXIS_STATE_IDLE}")
            words = self._error_words(t)
            if self._only_expired_watchdogs(words) and (self._was_up or self.opt.clear_watchdog_error_at_start):
                # The axes stopped because the host went silent (a lost bus, a killed controller), not for
                # a fault of their own. During a run this process went silent itself: the bring-up clears
                # it, as the Dynamixel bring-up clears a latched Bus Watchdog. At start-up only when the
                # configuration says so; any other error stays for clear_faults.
                self.cleared_watchdogs = self._faults_in(words)
                if not self._was_up:
                    self.watchdogs_cleared_at_start = [
                        f"ODrive {self.opt.port} {f} found at start-up (the host went silent before: a crash?) and "
                        f"cleared (drive.options.clear_watchdog_error_at_start)" for f in self.cleared_watchdogs]
                self._send("sc")
                words = self._error_words(t)
            faults = self._faults_in(words)
            if faults:
                for f in faults:
                    self._record_fault(f)
                watchdog_only = all(f.kind is FaultKind.WATCHDOG for f in faults)
                clear = f"'{clear_errors_command(self.config_source)}'"
                hint = (f"the host went silent before (a crash?): clear with {clear}, "
                        "or set drive.options.clear_watchdog_error_at_start: true" if watchdog_only else
                        f"find the cause, then clear with {clear}")
                raise DriveError("ODrive reports errors: " + "; ".join(map(str, faults)) + f" ({hint})")
            mode = INPUT_MODE_VEL_RAMP if self.opt.vel_ramp_rate > 0 else INPUT_MODE_PASSTHROUGH
            for ax in self.axes:
                self._send(f"w axis{ax}.controller.config.control_mode {CONTROL_MODE_VELOCITY}")
                self._send(f"w axis{ax}.controller.config.input_mode {mode}")
                self._send(f"w axis{ax}.controller.config.vel_limit {self.opt.vel_limit_turns_s:.4f}")
                if self.opt.vel_ramp_rate > 0:
                    self._send(f"w axis{ax}.controller.config.vel_ramp_rate {self.opt.vel_ramp_rate:.4f}")
                self._send(f"w axis{ax}.controller.input_vel 0")
                self._send(f"w axis{ax}.config.watchdog_timeout {self.opt.watchdog_s:.4f}")
                self._send(f"w axis{ax}.config.enable_watchdog 1")
                self._check_setup_took(ax, t)
            self._was_up = True
        except (serial.SerialException, OSError, termios.error) as exc:
            # termios.error (not an OSError): the flush before a question, on a device gone mid-setup
            raise DriveError(f"ODrive {self.opt.port} failed during setup: {exc}") from exc
        except _Corrupt as exc:
            raise DriveError(f"ODrive {self.opt.port} during setup: {exc}") from exc

    def _activate(self) -> None:
        try:
            self._io(self._arm)
        except _Corrupt as exc:   # a garbled answer to current_state: not known to be armed, so not enabled
            self._record_fault(DriveFault(FaultKind.CORRUPT_REPLY, self.opt.port, f"while arming: {exc}"))
            raise DriveError(f"ODrive {self.opt.port} while arming: {exc}") from exc

    def _arm(self) -> None:
        for ax in self.axes:
            self._send(f"v {ax} 0")
            self._send(f"u {ax}")
            self._send(f"w axis{ax}.requested_state {AXIS_STATE_CLOSED_LOOP}")
        for ax in self.axes:
            state = self._query(f"r axis{ax}.current_state", self.opt.setup_timeout_s)
            if _integer(state) != AXIS_STATE_CLOSED_LOOP:
                faults = self._read_errors(self.opt.setup_timeout_s)
                for f in faults or [DriveFault(FaultKind.SETUP, self._axis(ax),
                                               f"ODrive {self._axis(ax)} did not enter closed loop (state {state})")]:
                    self._record_fault(f)
                raise DriveError(f"ODrive {self._axis(ax)} did not enter closed loop "
                                 f"(state {state}); errors: {'; '.join(map(str, faults)) or 'none'}")

    def _write(self, left: float, right: float) -> None:
        rates = (left, right)
        for k, ax in enumerate(self.axes):
            turns = self.signs[k] * rates[k] / (2 * math.pi) * self.opt.gear_ratio
            turns = max(-self.opt.vel_limit_turns_s, min(self.opt.vel_limit_turns_s, turns))
            self._io(lambda: self._send(f"v {ax} {turns:.4f}"))

    def _read(self) -> WheelState:
        self._check_device()
        self._cycle += 1
        values, fault = self._io(self._feedback)
        if values is None:
            self._missed_read(fault)
            return self._measured
        self._missed_reads = 0
        pos = tuple(self.signs[k] * values[k][0] * 2 * math.pi / self.opt.gear_ratio for k in range(2))
        vel = tuple(self.signs[k] * values[k][1] * 2 * math.pi / self.opt.gear_ratio for k in range(2))
        self._measured = WheelState(self.clock.now_ns(), pos, vel, self.faults, self.state)
        if self.state is DriveState.ACTIVE and self._cycle % self.opt.error_poll_every == 0:
            faults = self._io(lambda: self._read_errors(self.opt.reply_timeout_s * 4))
            if faults:
                self._fault(*faults)
        return self._measured

    def _clear_faults(self) -> None:
        """``sc`` clears the error words of both axes, within the full setup again; enable() re-arms."""
        self._release()
        self._connect(clear_errors=True)
        self._missed_reads = 0

    def _axis(self, ax: int) -> str:
        return f"axis{ax} ({self.sides[ax]})"

    # -- protocol --------------------------------------------------------------------------
    def _frame(self, text: str) -> bytes:
        if self.opt.checksum:
            text = f"{text}*{xor_checksum(text)}"
        return (text + "\n").encode("ascii")

    def _send(self, text: str) -> None:
        self.ser.write(self._frame(text))

    def _readline(self, timeout_s: float) -> Optional[str]:
        end = time.monotonic() + timeout_s
        while b"\n" not in self._rx:
            remaining = end - time.monotonic()
            if remaining <= 0:
                return None
            # select() instead of changing ser.timeout: pyserial reconfigures the tty on every change
            ready, _, _ = select.select([self.ser.fd], [], [], remaining)
            chunk = self.ser.read(self.ser.in_waiting or 1) if ready else b""
            if chunk:
                self._rx += chunk
            elif not os.path.exists(self.opt.port):
                raise OSError(f"{self.opt.port} disappeared")
        line, _, self._rx = self._rx.partition(b"\n")
        return line.decode("ascii", "replace").strip()

    def _check_setup_took(self, ax: int, t: float) -> None:
        """Read back what the bring-up wrote to axis ``ax`` that the wheels' safety rests on (the ASCII protocol
        acknowledges no write): DriveError, with a setup fault noted, for what did not take."""
        got = self._query(f"r axis{ax}.controller.config.control_mode", t)
        if _integer(got) != CONTROL_MODE_VELOCITY:
            self._record_fault(DriveFault(FaultKind.SETUP, self._axis(ax),
                                          f"ODrive {self._axis(ax)}: control_mode did not take ({got!r})"))
            raise DriveError(f"ODrive axis{ax}: control_mode did not take ({got!r})")
        # The axis watchdog is what stops the wheels when the host cannot (a lost bus, a killed process),
        # and the ASCII protocol acknowledges no write: a line lost on its way (a noisy UART) left it off,
        # and the wheels ran on after the host went silent. Read back, as the control mode.
        on = self._query(f"r axis{ax}.config.enable_watchdog", t)
        timeout = self._query(f"r axis{ax}.config.watchdog_timeout", t)
        if _integer(on) != 1 or not _close_to(timeout, self.opt.watchdog_s):
            why = (f"ODrive {self._axis(ax)}: the axis watchdog did not take (enable_watchdog {on!r}, "
                   f"watchdog_timeout {timeout!r}, expected 1 and {self.opt.watchdog_s:g} s): nothing would "
                   f"stop this wheel if the host went silent")
            raise self._setup_refused(ax, why)
        # The bring-up leaves the wheels unpowered (a reconnect's drive_reconnected says so): an axis that
        # did not take the IDLE request (its line lost, a hung axis) drove on at its last velocity.
        # Read after the questions above: its state machine has had its time to leave closed loop.
        state = self._query(f"r axis{ax}.current_state", t)
        if state is None:
            raise DriveError(f"ODrive on {self.opt.port} does not answer 'r axis{ax}.current_state'")
        if _integer(state) != AXIS_STATE_IDLE:
            why = (f"ODrive {self._axis(ax)}: did not take the stop: current_state {state} (not IDLE "
                   f"{AXIS_STATE_IDLE}) after the bring-up's IDLE request; only its axis watchdog stops it")
            raise self._setup_refused(ax, why)

    def _setup_refused(self, ax: int, why: str) -> DriveError:
        """A setup fault of axis ``ax`` noted, and the DriveError that ends the bring-up with it."""
        self._record_fault(DriveFault(FaultKind.SETUP, self._axis(ax), why))
        return DriveError(why)

    def _settle(self) -> None:
        """After a question went unanswered within its timeout, its answer may still come, and the ASCII
        protocol carries nothing that tells it from the next question's answer: a late current_state (8) was
        read as the error word that followed it (axis0 error=0x8, a fault the axis never had; a loaded CI
        machine, 2026-12-03). Wait until the line has been quiet for that timeout, discarding what arrives
        (at most a few lines: a babbling device does not hold the driver here). An answer later than that
        can still be misread. Then the input is flushed, as before every question."""
        quiet, self._owed_s = self._owed_s, 0.0
        if quiet > 0:
            self._rx = b""
            for _ in range(4):
                if self._readline(quiet) is None:
                    break
        self._rx = b""
        self.ser.reset_input_buffer()

    def _query(self, text: str, timeout_s: float) -> Optional[str]:
        """Send a line and return its answer (checksum verified), None on timeout."""
        self._settle()
        self._send(text)
        line = self._readline(timeout_s)
        if line is None:
            self._owed_s = timeout_s
            return None
        if self.opt.checksum:
            body, star, given = line.rpartition("*")
            if not star or not given.isdigit() or int(given) != xor_checksum(body):
                raise _Corrupt(f"answer to {text!r} has a bad checksum: {line!r}")
            line = body
        return line

    def _feedback(self) -> tuple[Optional[list], Optional[DriveFault]]:
        """``f`` for both axes in one write, then both answer lines: one round trip per cycle, not two."""
        self._settle()
        self.ser.write(b"".join(self._frame(f"f {ax}") for ax in self.axes))
        end = time.monotonic() + self.opt.reply_timeout_s
        out = []
        for ax in self.axes:
            line = self._readline(max(0.0, end - time.monotonic()))
            dev = self._axis(ax)
            if line is None:
                self._owed_s = self.opt.reply_timeout_s
                return None, DriveFault(FaultKind.NO_REPLY, dev, f"{dev}: no answer to 'f {ax}' within "
                                                                 f"{self.opt.reply_timeout_s * 1000:.0f} ms")
            if self.opt.checksum:
                body, star, given = line.rpartition("*")
                if not star or not given.isdigit() or int(given) != xor_checksum(body):
                    return None, DriveFault(FaultKind.CORRUPT_REPLY, dev,
                                            f"{dev}: corrupted answer (bad checksum): {line!r}")
                line = body
            try:
                pos, vel = (float(x) for x in line.split())
            except ValueError:
                return None, DriveFault(FaultKind.CORRUPT_REPLY, dev, f"{dev}: corrupted answer to 'f {ax}': {line!r}")
            out.append((pos, vel))
        return out, None

    def _error_words(self, timeout_s: float) -> dict[int, dict[str, Optional[int]]]:
        """axis -> its four error words (None where unreadable)."""
        found = {}
        for ax in self.axes:
            words = found[ax] = {}
            for name, _table in ERROR_WORDS:
                try:
                    got = self._query(f"r axis{ax}.{name}", timeout_s)
                    words[name] = int(float(got)) if got is not None else None
                except (_Corrupt, ValueError):
                    words[name] = None
        return found

    @staticmethod
    def _only_expired_watchdogs(words: dict[int, dict[str, Optional[int]]]) -> bool:
        """Some axis reports an expired watchdog and nothing else is set on any axis."""
        expired = [w["error"] == AXIS_ERROR_WATCHDOG_EXPIRED and not any(w[n] for n, _ in ERROR_WORDS[1:])
                   for w in words.values()]
        clean = [not any(w.values()) and w["error"] is not None for w in words.values()]
        return any(expired) and all(e or c for e, c in zip(expired, clean))

    def _faults_in(self, words: dict[int, dict[str, Optional[int]]]) -> list[DriveFault]:
        """The error words as faults: an expired watchdog alone is WATCHDOG, any other bit HARDWARE_ERROR."""
        found = []
        for ax, w in words.items():
            dev = self._axis(ax)
            if w["error"] is None:
                found.append(DriveFault(FaultKind.NO_REPLY, dev, f"{dev}: error word unreadable"))
                continue
            parts = [f"{name}={'|'.join(decode_bits(w[name], table))}" for name, table in ERROR_WORDS if w[name]]
            if parts:
                watchdog_only = w["error"] == AXIS_ERROR_WATCHDOG_EXPIRED and len(parts) == 1
                kind = FaultKind.WATCHDOG if watchdog_only else FaultKind.HARDWARE_ERROR
                found.append(DriveFault(kind, dev, f"{dev}: " + ", ".join(parts)))
        return found

    def _read_errors(self, timeout_s: float) -> list[DriveFault]:
        return self._faults_in(self._error_words(timeout_s))

    # -- failure handling -----------------------------------------------------------------------
    def _io(self, fn):
        try:
            return fn()
        except (DriveError, _Corrupt):
            raise
        except Exception as exc:  # SerialException, OSError from a vanished device
            self._lost(exc)

    def _watchdog_note(self) -> str:
        return f"its axis watchdog ({self.opt.watchdog_s * 1000:.0f} ms) disarms the motors"

    def _stop_wheels(self) -> Optional[str]:
        """Velocity 0 and IDLE on both axes (disarmed); the axes that did not take it, named. The ASCII protocol
        acknowledges neither command, so each axis's ``current_state`` is read back (``_stop_not_taken``)."""
        if self.ser is None:
            return None
        missed = {}
        for ax in self.axes:
            try:
                self._send(f"v {ax} 0")
                self._send(f"w axis{ax}.requested_state {AXIS_STATE_IDLE}")
            except Exception as exc:
                missed[ax] = f"the stop could not be sent ({exc!r})"
        silent = False       # a device that did not answer one axis's read-back answers no other: not waited for
        for ax in self.axes:
            if ax not in missed:
                missed[ax] = "no answer to the stop's read-back" if silent else self._stop_not_taken(ax)
                silent = silent or (missed[ax] or "").startswith("no answer")
        return "; ".join(f"{self._axis(ax)}: {m}" for ax, m in missed.items() if m) or None

    def _stop_again(self) -> Optional[str]:
        """The stop sent again from the loop (every 0.1 s while an axis has not taken it): the stop sent before
        is read back first, one question per axis (it had the time to idle since), then this one is sent; its
        own read-back would ask until 4 x reply_timeout_s had passed, a late cycle in every resend. A stop
        taken is confirmed by the resend after it."""
        if self.ser is None:
            return None
        t = self.opt.reply_timeout_s
        missed, silent = {}, False   # a device that did not answer one axis answers no other: not waited for
        for ax in self.axes:
            if silent:
                missed[ax] = "no answer to the stop's read-back"
                continue
            try:
                state = self._query(f"r axis{ax}.current_state", t)
            except Exception as exc:     # a device gone or a garbled answer: not known to have stopped
                missed[ax], silent = f"the stop's read-back failed ({exc!r})", True
                continue
            if state is None:
                missed[ax], silent = (f"no answer to 'r axis{ax}.current_state' within {t * 1000:.0f} ms: the "
                                      "stop is unconfirmed"), True
            elif _integer(state) != AXIS_STATE_IDLE:
                missed[ax] = (f"did not take the stop sent before: current_state {state} (not IDLE "
                              f"{AXIS_STATE_IDLE}); sent again")
        for ax in self.axes:
            try:
                self._send(f"v {ax} 0")
                self._send(f"w axis{ax}.requested_state {AXIS_STATE_IDLE}")
            except Exception as exc:
                missed[ax] = f"the stop could not be sent ({exc!r})"
        return "; ".join(f"{self._axis(ax)}: {m}" for ax, m in sorted(missed.items()) if m) or None

    def _stop_not_taken(self, ax: int) -> Optional[str]:
        """Why axis ``ax`` is not known to have taken the stop (read back: IDLE), None when it has. The axis
        leaves closed loop within a control period or so: its state is read again until ``t`` has passed."""
        t = self.opt.reply_timeout_s * 4
        end = time.monotonic() + t
        try:
            while True:
                state = self._query(f"r axis{ax}.current_state", t)
                if state is None:
                    return (f"no answer to 'r axis{ax}.current_state' within {t * 1000:.0f} ms: the stop is "
                            "unconfirmed")
                if _integer(state) == AXIS_STATE_IDLE:
                    return None
                if time.monotonic() >= end:
                    break
                time.sleep(0.001)
            vel = self._query(f"r axis{ax}.controller.input_vel", t)
        except Exception as exc:     # a device gone or a garbled answer: not known to have stopped
            return f"the stop's read-back failed ({exc!r})"
        return (f"did not take the stop: current_state {state} (not IDLE {AXIS_STATE_IDLE}), "
                f"controller.input_vel {vel} turns/s")

    def _device_open(self) -> bool:
        return self.ser is not None

    def _release(self) -> None:
        if self.ser is not None:
            try:
                self.ser.close()
            except Exception:
                pass
        self.ser = None


def _integer(answer: Optional[str]) -> Optional[int]:
    """An answer read as an integer (the ODrive prints enums as numbers), None when missing or not a number:
    a late answer to an earlier question (two numbers, say) is no answer, not a lost device."""
    try:
        return None if answer is None else int(float(answer))
    except ValueError:
        return None


def _close_to(answer: Optional[str], value: float) -> bool:
    """An answer that reads as ``value`` (written with 4 decimals, printed back with 6)."""
    try:
        return answer is not None and abs(float(answer) - value) < 1e-4
    except ValueError:
        return False


class _Corrupt(Exception):
    """An answer whose checksum does not match."""
