"""Dynamixel X-series wheels (Protocol 2.0, velocity mode) through the real dynamixel-sdk.

Per control cycle the bus carries one GroupSyncWrite of Goal Velocity (no
answer) and one GroupSyncRead of Present Velocity + Present Position (one
status packet per servo). The SDK's answer timeout is budgeted: its stock
``PortHandler`` waits ``2 x LATENCY_TIMER(16 ms) + 2 ms`` busy for every
missing status packet, which at 100 Hz would cost 3 periods per absent servo.
``BudgetedPort`` replaces that with the adapter's real latency (set the FTDI
latency timer of a U2D2 to 1 ms: ``echo 1 > /sys/bus/usb-serial/devices/ttyUSB0/latency_timer``)
plus a margin, so a silent servo costs a few milliseconds.

Safety: torque goes off on ``disable()``/``close()`` and on every failure
path that can still reach the bus; when the bus itself is gone, the servos'
Bus Watchdog (configured at bring-up) stops them on their own.
"""
from __future__ import annotations

import math
import os
import select
import time
from typing import Any, Literal, Optional

from pydantic import ConfigDict, Field, field_validator, model_validator
from vbnav.drivers.plain_values import PlainValues

from vbnav.drivers import discovery
from vbnav.drivers import dynamixel_table as reg
from vbnav.drivers.dynamixel_protocol import to_signed
from vbnav.drivers.dynamixel_table import (ACCEL_UNIT_RAD_S2, BAUD_VALUES, HW_ERROR_BITS, MODE_VELOCITY,
                                           MODEL_NUMBERS, TICKS_PER_REV, VELOCITY_UNIT_RAD_S, WATCHDOG_UNIT_S, Register,
                                           rate_problem)
from vbnav.drivers.serial_drive import SerialWheelDrive, require_two_wheels
from vbnav.drivers.wheels import DriveError, DriveFault, FaultKind, WheelState

try:  # imported lazily by the registry; a clear error if the SDK is missing
    import dynamixel_sdk as sdk
except ImportError as _exc:  # pragma: no cover - dependency is in pyproject
    sdk = None
    _SDK_ERROR = _exc

VELOCITY_LIMIT_MAX_RAD_S = round(1023 * VELOCITY_UNIT_RAD_S, 2)   # what Velocity Limit (44) holds: 0..1023 units
BRING_UP_EXTRA_MS = 30.0  # answer window added during bring-up: not time-critical, and must not flake
BRING_UP_ATTEMPTS = 3
# Present Velocity and Present Position are adjacent (tests check it): one sync read of (address, length)
_STATE_BLOCK = (reg.PRESENT_VELOCITY.address, reg.PRESENT_VELOCITY.size + reg.PRESENT_POSITION.size)


def decode_hardware_error(bits: int) -> str:
    names = [f"{name} (bit {b})" for b, name in HW_ERROR_BITS.items() if bits & (1 << b)]
    return ", ".join(names) or f"unknown bits 0x{bits:02x}"


def rad_s_to_units(rate: float) -> int:
    return int(round(rate / VELOCITY_UNIT_RAD_S))


def units_to_rad_s(units: int) -> float:
    return units * VELOCITY_UNIT_RAD_S


if sdk is not None:
    class BudgetedPort(sdk.PortHandler):
        """PortHandler whose answer timeout is the adapter latency, not the SDK's 16 ms constant."""

        def __init__(self, port_name: str, latency_ms: float, margin_ms: float):
            super().__init__(port_name)
            self.latency_ms = latency_ms
            self.margin_ms = margin_ms
            self.extra_ms = 0.0  # raised during bring-up, where time is not critical

        def relaxed(self, extra_ms: float):
            port = self

            class _Relaxed:
                def __enter__(self):
                    port.extra_ms = extra_ms

                def __exit__(self, *exc):
                    port.extra_ms = 0.0
            return _Relaxed()

        def setPacketTimeout(self, packet_length):  # noqa: N802 - SDK name
            self.packet_start_time = self.getCurrentTime()
            self.packet_timeout = self.tx_time_per_byte * packet_length + 2.0 * self.latency_ms + self.margin_ms + self.extra_ms

        def readPort(self, length):  # noqa: N802 - SDK name
            # The SDK polls readPort in a loop with a zero timeout: a busy-wait that burns a core and,
            # in Python, keeps other threads from the GIL. Block in select() until bytes come or the
            # answer window closes instead; the SDK's own timeout logic is unchanged.
            data = self.ser.read(length)
            if not data:
                remaining_ms = self.packet_timeout - self.getTimeSinceStart()
                if remaining_ms > 0:
                    select.select([self.ser.fd], [], [], min(remaining_ms, 5.0) * 1e-3)
                    data = self.ser.read(length)
            return data


class DynamixelDrive(SerialWheelDrive):
    """Two Dynamixel X servos in velocity mode as the left and right wheel."""

    name = "dynamixel"
    drive_name = "dynamixel drive"
    device_name = "dynamixel adapter"

    class Options(PlainValues):
        model_config = ConfigDict(extra="forbid")
        port: str = Field("/dev/ttyUSB0", description="serial device of the U2D2 (prefer /dev/serial/by-id/...)")
        baudrate: int = Field(1_000_000, description="bus rate, bit/s: one a Dynamixel X servo runs at "
                                                     f"({', '.join(map(str, BAUD_VALUES))})")
        left_id: int = Field(1, ge=0, le=252, description="bus ID of the left wheel servo")
        right_id: int = Field(2, ge=0, le=252, description="bus ID of the right wheel servo")
        model: Optional[Literal[tuple(MODEL_NUMBERS)]] = Field(  # type: ignore[valid-type]
            None, description="expected servo model; None accepts any known X-series model")
        velocity_limit_rad_s: float = Field(6.0, gt=0, le=VELOCITY_LIMIT_MAX_RAD_S,
                                            description="written to Velocity Limit (44), at most its 1023 units "
                                                        f"({VELOCITY_LIMIT_MAX_RAD_S:g} rad/s); commands clamp")
        profile_acceleration_rad_s2: float = Field(0.0, ge=0, description="Profile Acceleration (108), in its "
                                                   f"{ACCEL_UNIT_RAD_S2:.4f} rad/s^2 units (a smaller positive value "
                                                   "is one unit); 0 = none")
        bus_watchdog_s: float = Field(0.1, ge=0.02, le=2.54, description="servo stops after this bus silence; at least "
                                      "two loop periods (the loop writes once a cycle; refused below)")
        latency_ms: float = Field(1.0, gt=0, le=16, description="adapter latency timer (FTDI), ms")
        margin_ms: float = Field(3.0, ge=0, le=20, description="extra wait for an answer, ms: the answer window "
                                 "2 x latency_ms + margin_ms stays within half of a 100 Hz period (docs/safety.md, "
                                 "'Drive timing')")
        max_missed_reads: int = Field(8, ge=1, description="consecutive failed reads that make a fault (the "
                                      "state is held meanwhile; the writes still feed the servos' watchdog): 8 at "
                                      "100 Hz tolerates 80 ms of misses, within the 100 ms bus watchdog")
        reconnect_interval_s: float = Field(0.5, gt=0, description="how often a lost adapter is looked for")

        @field_validator("baudrate")
        @classmethod
        def _x_series_rate(cls, v: int) -> int:
            why = rate_problem(v)
            if why:
                raise ValueError(why)
            return v

        @model_validator(mode="after")
        def _distinct_ids(self):
            return require_two_wheels(self, "left_id", "right_id", "each servo needs its own bus id "
                                                                   "('vbnav servo set-id' changes one)")

    def __init__(self, cfg: Any = None, clock=None, *, options: Optional["DynamixelDrive.Options"] = None,
                 invert_left: Optional[bool] = None, invert_right: Optional[bool] = None):
        if sdk is None:  # pragma: no cover
            raise DriveError(f"dynamixel-sdk is not installed: {_SDK_ERROR}")
        super().__init__(cfg, clock, options=options, invert_left=invert_left, invert_right=invert_right)
        options = self.opt
        self.ids = (options.left_id, options.right_id)
        self.sides = {options.left_id: "left", options.right_id: "right"}
        self.port = None
        self.ph = None
        self.models: dict[int, int] = {}   # id -> model number, read at bring-up
        self._last_raw: dict[int, Optional[int]] = {i: None for i in self.ids}
        self._ticks = {i: 0 for i in self.ids}
        self._last_write_ns: Optional[int] = None
        self._was_up = False        # brought up once by this process (a later bring-up is a reconnect)
        self._limit_units = min(rad_s_to_units(options.velocity_limit_rad_s), 1023)
        self._watchdog_units = max(1, min(127, int(round(options.bus_watchdog_s / WATCHDOG_UNIT_S))))

    @property
    def watchdog(self) -> Optional[tuple[float, str]]:
        return self._watchdog_units * WATCHDOG_UNIT_S, "drive.options.bus_watchdog_s"

    @property
    def wheel_speed_limit(self) -> Optional[tuple[float, str]]:
        return self.opt.velocity_limit_rad_s, "drive.options.velocity_limit_rad_s"

    @property
    def serial_latency_ms(self) -> Optional[float]:
        return self.opt.latency_ms

    # -- lifecycle hooks (WheelDrive owns the states) ---------------------------------------
    def _configure(self) -> None:
        """Open the adapter and bring the servos up in the safe order; torque stays off."""
        self._open_port()
        with self.port.relaxed(BRING_UP_EXTRA_MS):
            self._bring_up()

    def _activate(self) -> None:
        with self.port.relaxed(BRING_UP_EXTRA_MS):
            self._arm()
        self._last_write_ns = self.clock.now_ns()

    def _arm(self) -> None:
        """Zero goals, re-arm the watchdog, torque on."""
        for i in self.ids:
            # a watchdog that expired while we were away reads 0xFF and locks the goals: clear, re-arm
            self._write_register(i, reg.BUS_WATCHDOG, 0)
            self._write_register(i, reg.GOAL_VELOCITY, 0)
            self._write_register(i, reg.BUS_WATCHDOG, self._watchdog_units)
        for i in self.ids:
            self._write_register(i, reg.TORQUE_ENABLE, 1)

    def _write(self, left: float, right: float) -> None:
        now = self.clock.now_ns()
        if self._last_write_ns is not None and (now - self._last_write_ns) * 1e-9 > self._watchdog_units * WATCHDOG_UNIT_S:
            self._guard_io(lambda: self._check_watchdog(now))
        units = [self._to_units(self.signs[k] * v) for k, v in enumerate((left, right))]
        ok, why = self._guard_io(lambda: self._sync_write_velocity(units))
        if not ok:
            if not self._port_present():
                self._lost(OSError(why))
            self._fault(DriveFault(FaultKind.SEND_FAILED, f"dynamixel adapter {self.opt.port}",
                                   f"sync write of Goal Velocity: {why}"))
        self._last_write_ns = now

    def _read(self) -> WheelState:
        self._check_device()
        fault = self._guard_io(self._sync_read_state)
        if fault is None:
            self._missed_reads = 0
        else:
            if not self._port_present():
                self._lost(OSError(fault.message))
            self._missed_read(fault)
        return self._measured

    def _clear_faults(self) -> None:
        """REBOOT servos that report a hardware error (only a reboot clears it), then bring them up again.

        Works also when connect() itself failed on a hardware error."""
        if self.port is None:
            self._open_port()
        with self.port.relaxed(BRING_UP_EXTRA_MS):
            for i in self.ids:
                bits, res, _ = self._guard_io(lambda: self.ph.read1ByteTxRx(self.port, i, reg.HARDWARE_ERROR_STATUS.address))
                if res == sdk.COMM_SUCCESS and bits == 0:
                    continue
                res, _ = self._guard_io(lambda: self.ph.reboot(self.port, i))
                if res != sdk.COMM_SUCCESS:
                    raise DriveError(f"servo {i} ({self.sides[i]}): REBOOT failed: "
                                     f"{self.ph.getTxRxResult(res)}")
                time.sleep(0.05)  # the servo restarts before it answers again
                self._last_raw[i] = None  # position restarts within one turn; keep accumulating
            self._missed_reads = 0
            self._bring_up()

    # -- bring-up -----------------------------------------------------------------------------
    def _open_port(self) -> None:
        if not os.path.exists(self.opt.port):
            raise DriveError(f"dynamixel adapter {self.opt.port} not found (is the U2D2 plugged in? "
                             f"see /dev/serial/by-id/)")
        timer = discovery.read_latency_timer(self.opt.port)     # None: not an FTDI adapter
        if timer is not None and timer > self.opt.latency_ms:
            raise DriveError(f"dynamixel adapter {self.opt.port}: its latency timer is {timer} ms, and the answer "
                             f"window assumes drive.options.latency_ms {self.opt.latency_ms:g} ms: every answer "
                             f"would come too late (echo 1 | sudo tee {discovery.latency_timer_path(self.opt.port)}"
                             f"; a udev rule makes it permanent, docs/hardware.md)")
        self.port = BudgetedPort(self.opt.port, self.opt.latency_ms, self.opt.margin_ms)
        self.ph = sdk.PacketHandler(2.0)
        try:
            ok = self.port.openPort() and self.port.setBaudRate(self.opt.baudrate)
        except Exception as exc:  # serial.SerialException, OSError
            raise DriveError(f"cannot open dynamixel adapter {self.opt.port}: {exc}") from exc
        if not ok:
            raise DriveError(f"cannot open dynamixel adapter {self.opt.port} at {self.opt.baudrate} bit/s")
        self._sync_write = sdk.GroupSyncWrite(self.port, self.ph, reg.GOAL_VELOCITY.address, reg.GOAL_VELOCITY.size)
        self._sync_read = sdk.GroupSyncRead(self.port, self.ph, *_STATE_BLOCK)
        for i in self.ids:
            self._sync_read.addParam(i)

    def _device_open(self) -> bool:
        return self.port is not None

    def _release(self) -> None:
        if self.port is not None:
            try:
                self.port.closePort()
            except Exception:
                pass
        self.port = None

    def _bring_up(self) -> None:
        accepted = {MODEL_NUMBERS[self.opt.model]} if self.opt.model else set(MODEL_NUMBERS.values())
        for i in self.ids:
            for _attempt in range(BRING_UP_ATTEMPTS):  # a servo just powered may miss the first packet
                model, res, err = self._guard_io(lambda: self.ph.ping(self.port, i))
                if res == sdk.COMM_SUCCESS:
                    break
            if res != sdk.COMM_SUCCESS:
                raise DriveError(f"servo {i} ({self.sides[i]}) on {self.opt.port} did not answer ping at "
                                 f"{self.opt.baudrate} bit/s: {self.ph.getTxRxResult(res)} (a wrong id or baud "
                                 f"rate? 'vbnav find servos --port {self.opt.port}' shows what answers)")
            if model not in accepted:
                names = {v: k for k, v in MODEL_NUMBERS.items()}
                raise DriveError(f"servo {i} ({self.sides[i]}) is model number {model} "
                                 f"({names.get(model, 'unknown')}); expected {self.opt.model or 'an X-series model'} "
                                 f"({', '.join(str(a) for a in sorted(accepted))})")
            self.models[i] = model
        for i in self.ids:
            bits, res, err = self._guard_io(lambda: self.ph.read1ByteTxRx(self.port, i, reg.HARDWARE_ERROR_STATUS.address))
            if res == sdk.COMM_SUCCESS and bits:
                fault = self._hardware_fault(i, decode_hardware_error(bits))
                self._record_fault(fault)
                raise DriveError(fault.message)
        if not self._was_up:    # an expired watchdog found at start-up: the last run died driving, say so
            self.watchdogs_cleared_at_start = [
                f"servo {i} ({self.sides[i]}) on {self.opt.port}: Bus Watchdog expired (0xFF) found at start-up "
                f"(the host went silent before: a crash?) and cleared" for i in self.ids if self._watchdog_expired(i)]
        accel_units = int(round(self.opt.profile_acceleration_rad_s2 / ACCEL_UNIT_RAD_S2))
        if self.opt.profile_acceleration_rad_s2 > 0:
            accel_units = max(1, accel_units)   # 0 is "no limit": a gentle setting is the gentlest limit
        steps = [(reg.TORQUE_ENABLE, 0),
                 (reg.OPERATING_MODE, MODE_VELOCITY),
                 (reg.VELOCITY_LIMIT, self._limit_units),
                 (reg.PROFILE_ACCELERATION, accel_units),
                 (reg.RETURN_DELAY_TIME, 0),
                 (reg.BUS_WATCHDOG, 0),  # clears a latched watchdog error (0xFF)
                 (reg.BUS_WATCHDOG, self._watchdog_units)]
        for register, value in steps:
            for i in self.ids:
                self._write_register(i, register, value)
        self._last_raw = {i: None for i in self.ids}
        self._measured = WheelState(self.clock.now_ns(), self._positions(), (0.0, 0.0))
        self._was_up = True

    def _watchdog_expired(self, i: int) -> bool:
        v, res, _ = self._guard_io(lambda: self.ph.read1ByteTxRx(self.port, i, reg.BUS_WATCHDOG.address))
        return res == sdk.COMM_SUCCESS and v == 0xFF

    def _hardware_fault(self, i: int, detail: str) -> DriveFault:
        return DriveFault(FaultKind.HARDWARE_ERROR, f"servo {i} ({self.sides[i]})",
                          f"servo {i} ({self.sides[i]}) hardware error: {detail}; only a REBOOT clears it "
                          f"(clear_faults)")

    def _write_register(self, i: int, register: Register, value: int) -> None:
        """A confirmed register write (bring-up, enable): retried, since none of them is time-critical."""
        fn = {1: self.ph.write1ByteTxRx, 2: self.ph.write2ByteTxRx, 4: self.ph.write4ByteTxRx}[register.size]
        addr, what = register.address, register.name
        for _attempt in range(BRING_UP_ATTEMPTS):
            res, err = self._guard_io(lambda: fn(self.port, i, addr, value & ((1 << (8 * register.size)) - 1)))
            if res == sdk.COMM_SUCCESS:
                break
        if res != sdk.COMM_SUCCESS:
            raise DriveError(f"servo {i} ({self.sides[i]}): writing {what} ({addr}) = {value} got no answer: "
                             f"{self.ph.getTxRxResult(res)}")
        if err & 0x7F:
            fault = DriveFault(FaultKind.SETUP, f"servo {i} ({self.sides[i]})",
                               f"servo {i} ({self.sides[i]}): writing {what} ({addr}) = {value} refused: "
                               f"{self.ph.getRxPacketError(err)}")
            self._record_fault(fault)
            raise DriveError(fault.message)

    # -- per-cycle I/O ---------------------------------------------------------------------------
    def _to_units(self, rate: float) -> int:
        return max(-self._limit_units, min(self._limit_units, rad_s_to_units(rate)))

    def _sync_write_velocity(self, units: list[int]) -> tuple[bool, str]:
        self._sync_write.clearParam()
        for i, u in zip(self.ids, units):
            self._sync_write.addParam(i, list(reg.GOAL_VELOCITY.encode(u)))
        res = self._sync_write.txPacket()
        if res != sdk.COMM_SUCCESS:
            return False, f"sync write failed: {self.ph.getTxRxResult(res)}"
        return True, ""

    def _sync_read_state(self) -> Optional[DriveFault]:
        """One sync read; each servo's status is received with its error byte (GroupSyncRead's own
        rxPacket drops it, and with it the hardware-alert bit). None when it worked, else what went wrong."""
        res = self._sync_read.txPacket()
        if res != sdk.COMM_SUCCESS:
            return DriveFault(FaultKind.SEND_FAILED, f"dynamixel adapter {self.opt.port}",
                              f"sync read could not be sent: {self.ph.getTxRxResult(res)}")
        values = {}
        alerts = []
        for i in self.ids:
            data, res, err = self.ph.readRx(self.port, i, _STATE_BLOCK[1])
            if res != sdk.COMM_SUCCESS:
                kind, why = (FaultKind.NO_REPLY, "no status packet (servo not answering)") \
                    if res == sdk.COMM_RX_TIMEOUT else \
                    (FaultKind.CORRUPT_REPLY, "corrupted status packet (bad CRC or truncated)") \
                    if res == sdk.COMM_RX_CORRUPT else (FaultKind.NO_REPLY, self.ph.getTxRxResult(res))
                device = f"servo {i} ({self.sides[i]})"
                return DriveFault(kind, device, f"{device}: {why}")
            if err & 0x80:
                alerts.append(i)
            # velocity signed; the position kept unsigned, as the unwrapping below expects
            values[i] = (reg.PRESENT_VELOCITY.decode(data[0:4]), reg.PRESENT_POSITION.decode(data[4:8], signed=False))
        now = self.clock.now_ns()
        for i, (vel, raw_pos) in values.items():
            last = self._last_raw[i]
            # Present Position is a 32-bit multi-turn count; unwrap across its overflow and reboots
            self._ticks[i] += 0 if last is None else to_signed(raw_pos - last, 4)
            self._last_raw[i] = raw_pos
        vel = tuple(self.signs[k] * units_to_rad_s(values[i][0]) for k, i in enumerate(self.ids))
        self._measured = WheelState(now, self._positions(), vel, self.faults, self.state,
                                    {"raw_velocity": [values[i][0] for i in self.ids]})
        if alerts:
            faults = []
            for i in alerts:
                bits, res, _ = self.ph.read1ByteTxRx(self.port, i, reg.HARDWARE_ERROR_STATUS.address)
                faults.append(self._hardware_fault(
                    i, decode_hardware_error(bits) if res == sdk.COMM_SUCCESS else "unreadable"))
            self._fault(*faults)
        return None

    def _positions(self) -> tuple[float, float]:
        return tuple(self.signs[k] * self._ticks[i] * 2 * math.pi / TICKS_PER_REV for k, i in enumerate(self.ids))

    def _check_watchdog(self, now: int) -> None:
        for i in self.ids:
            if self._watchdog_expired(i):
                gap = (now - self._last_write_ns) * 1e-9
                self._fault(DriveFault(
                    FaultKind.WATCHDOG, f"servo {i} ({self.sides[i]})",
                    f"servo {i} ({self.sides[i]}): bus watchdog expired after {gap * 1000:.0f} ms without "
                    f"commands (limit {self._watchdog_units * 20} ms); wheels stopped, the bring-up re-arms it"))

    # -- failure handling ---------------------------------------------------------------------------
    def _guard_io(self, fn):
        """Run one SDK call; a vanished adapter becomes DriveError (a BUS_LOST fault, the port closed)."""
        try:
            return fn()
        except DriveError:
            raise
        except Exception as exc:  # serial.SerialException, OSError, TypeError from a closed port
            self._lost(exc)

    def _watchdog_note(self) -> str:
        return f"the servos' bus watchdog ({self._watchdog_units * 20} ms) stops the wheels"

    def _stop_wheels(self) -> Optional[str]:
        """Goal Velocity 0 and torque off on every servo still answering; the servos whose torque-off was not
        acknowledged, or answered with an error (a CRC error: the packet arrived corrupted and was not
        applied), named (their bus watchdog is what stops them)."""
        if self.port is None or self.ph is None:
            return None
        missed = []
        for i in self.ids:
            try:
                self.port.is_using = False  # an exception mid-transfer leaves the SDK's flag set
                self.ph.write4ByteTxRx(self.port, i, reg.GOAL_VELOCITY.address, 0)
                res, err = self.ph.write1ByteTxRx(self.port, i, reg.TORQUE_ENABLE.address, 0)
                why = (f"not acknowledged ({self.ph.getTxRxResult(res)})" if res != sdk.COMM_SUCCESS else
                       f"refused ({self.ph.getRxPacketError(err)})" if err & 0x7F else None)
            except Exception as exc:
                why = f"not acknowledged ({exc!r})"
            if why is not None:
                missed.append(f"servo {i} ({self.sides[i]}): torque off {why}")
        return "; ".join(missed) or None

