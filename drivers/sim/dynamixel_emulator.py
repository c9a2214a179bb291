"""An emulated Dynamixel X-series bus behind a pseudo-terminal.

The real dynamixel-sdk opens the pty's slave side as if it were a U2D2
adapter; this module answers on the master side with Protocol 2.0 status
packets from a stateful control table per servo. It is what the driver tests,
the hardware-in-the-loop tests and ``vbnav emulate dynamixel`` run against.

Behaviour follows the e-Manual of the XL430-W250 / XM430-W350:

- EEPROM area (addresses < 64, e.g. Operating Mode 11, Velocity Limit 44)
  is writable only with torque off (else Access Error).
- Goal Velocity above Velocity Limit is a Data Limit Error.
- Hardware Error Status (70) bits switch torque off and set the Alert bit
  (0x80) in every status packet until a REBOOT.
- Bus Watchdog (98, units of 20 ms): with torque on, a silence longer than the
  set time stops the wheel (Goal Velocity 0) and the register reads 0xFF
  (-1). Goal writes then fail until 0 is written to it.
- Return Delay Time (9, units of 2 us) delays every answer.
- Reg Write stores a write until ACTION; Sync/Bulk Read answers come in the
  order of the requested ids.

Faults are injected per servo: ``no_answer`` (silent, as if unplugged from the
bus), ``corrupt`` (answers with a broken CRC), ``set_hardware_error(bits)``.
``unplug()``/``replug()`` simulate the USB adapter going away and coming back
(the stable device path is a symlink, as /dev/serial/by-id/... is).

Wheel motion: in Velocity mode the present velocity follows Goal Velocity at
the Profile Acceleration and the position integrates it; or, when a
``WheelCoupling`` is attached, the commanded rate goes to it (e.g. the
simulated base) and the present values come back from it.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Protocol

from vbnav.drivers import dynamixel_protocol as dp
from vbnav.drivers.sim.pty_device import PtyDevice

# Control table addresses (X-series, Protocol 2.0).
ADDR_MODEL_NUMBER = 0
ADDR_FIRMWARE = 6
ADDR_ID = 7
ADDR_BAUD = 8
ADDR_RETURN_DELAY = 9
ADDR_OPERATING_MODE = 11
ADDR_VELOCITY_LIMIT = 44
ADDR_TORQUE_ENABLE = 64
ADDR_LED = 65
ADDR_STATUS_RETURN_LEVEL = 68
ADDR_REGISTERED = 69
ADDR_HW_ERROR = 70
ADDR_BUS_WATCHDOG = 98
ADDR_GOAL_PWM = 100
ADDR_GOAL_VELOCITY = 104
ADDR_PROFILE_ACCEL = 108
ADDR_PROFILE_VELOCITY = 112
ADDR_GOAL_POSITION = 116
ADDR_MOVING = 122
ADDR_PRESENT_VELOCITY = 128
ADDR_PRESENT_POSITION = 132
ADDR_PRESENT_VOLTAGE = 144
ADDR_PRESENT_TEMPERATURE = 146
TABLE_SIZE = 147
EEPROM_END = 64

# Read-only ranges (start, end exclusive): model info, hardware error, present values.
READ_ONLY = [(0, 7), (ADDR_REGISTERED, ADDR_HW_ERROR + 1), (120, TABLE_SIZE)]

VELOCITY_UNIT_RPM = 0.229
PROFILE_ACCEL_UNIT_RPM2 = 214.577
TICKS_PER_REV = 4096
WATCHDOG_UNIT_S = 0.020


@dataclass(frozen=True)
class ServoModel:
    name: str
    number: int
    velocity_limit: int  # factory default, 0.229 rpm units
    voltage_dV: int  # reported input voltage, 0.1 V


MODELS = {
    "XL430-W250": ServoModel("XL430-W250", 1060, 265, 120),
    "XM430-W350": ServoModel("XM430-W350", 1020, 200, 120),
}


def model_by_name(name: str) -> ServoModel:
    key = name.upper()
    if key not in MODELS:
        raise ValueError(f"unknown Dynamixel model {name!r}; emulated models: {', '.join(MODELS)}")
    return MODELS[key]


class WheelCoupling(Protocol):
    """Where emulated wheels get their motion from when not integrated internally.

    ``command`` receives the rate the servo is driving at (rad/s, servo sign),
    ``measure`` returns (angle rad, rate rad/s) of that servo's wheel.
    """

    def command(self, dxl_id: int, rate_rad_s: float) -> None: ...

    def measure(self, dxl_id: int) -> tuple[float, float]: ...


@dataclass
class LogEntry:
    t: float
    dxl_id: int
    op: str  # "ping", "write", "read", "reboot", "action", "watchdog_expired", ...
    addr: int = -1
    value: int = 0


class EmulatedServo:
    """One servo: control table, motion and faults."""

    def __init__(self, dxl_id: int, model: ServoModel):
        self.dxl_id = dxl_id
        self.model = model
        self.no_answer = False
        self.corrupt = False
        self.table = bytearray(TABLE_SIZE)
        self._position = 0.0  # ticks, float
        self._velocity = 0.0  # 0.229 rpm units, float
        self._pending: Optional[tuple[int, bytes]] = None
        self.last_comm = time.monotonic()
        self.power_on()

    # -- control table -----------------------------------------------------------
    def get(self, addr: int, size: int, signed: bool = False) -> int:
        return int.from_bytes(self.table[addr:addr + size], "little", signed=signed)

    def put(self, addr: int, size: int, value: int) -> None:
        self.table[addr:addr + size] = (value & ((1 << (8 * size)) - 1)).to_bytes(size, "little")

    def power_on(self) -> None:
        """Factory defaults of the RAM area (EEPROM is kept across reboots)."""
        if self.get(ADDR_MODEL_NUMBER, 2) == 0:
            self.put(ADDR_MODEL_NUMBER, 2, self.model.number)
            self.put(ADDR_FIRMWARE, 1, 46)
            self.put(ADDR_ID, 1, self.dxl_id)
            self.put(ADDR_BAUD, 1, 3)  # 1 Mbps
            self.put(ADDR_RETURN_DELAY, 1, 250)  # 500 us
            self.put(ADDR_OPERATING_MODE, 1, 3)  # position control
            self.put(ADDR_VELOCITY_LIMIT, 4, self.model.velocity_limit)
        self.table[EEPROM_END:] = bytes(TABLE_SIZE - EEPROM_END)
        self.put(ADDR_STATUS_RETURN_LEVEL, 1, 2)
        self.put(ADDR_PRESENT_VOLTAGE, 2, self.model.voltage_dV)
        self.put(ADDR_PRESENT_TEMPERATURE, 1, 36)
        # after power-on the position is reported within one turn
        self._position = float(int(self._position) % TICKS_PER_REV)
        self._velocity = 0.0
        self._pending = None
        self._sync_present()

    @property
    def torque_on(self) -> bool:
        return self.table[ADDR_TORQUE_ENABLE] == 1

    @property
    def hardware_error(self) -> int:
        return self.table[ADDR_HW_ERROR]

    def alert(self) -> int:
        return dp.ERR_ALERT if self.hardware_error else 0

    def set_hardware_error(self, bits: int) -> None:
        """Latch hardware error bits: torque goes off, only REBOOT clears them."""
        self.table[ADDR_HW_ERROR] |= bits & 0xFF
        self.table[ADDR_TORQUE_ENABLE] = 0

    def read(self, addr: int, size: int) -> tuple[int, bytes]:
        if size <= 0 or addr < 0 or addr + size > TABLE_SIZE:
            return dp.ERR_ACCESS, b""
        return 0, bytes(self.table[addr:addr + size])

    def write(self, addr: int, data: bytes) -> int:
        """Apply a write; returns the status error number (0 = accepted)."""
        end = addr + len(data)
        if not data or addr < 0 or end > TABLE_SIZE:
            return dp.ERR_ACCESS
        if any(addr < hi and end > lo for lo, hi in READ_ONLY):
            return dp.ERR_ACCESS
        if addr < EEPROM_END and self.torque_on:
            return dp.ERR_ACCESS
        touches = lambda a, n: addr < a + n and end > a  # noqa: E731
        new = bytearray(self.table)
        new[addr:end] = data
        val = lambda a, n, s=False: int.from_bytes(new[a:a + n], "little", signed=s)  # noqa: E731
        if touches(ADDR_OPERATING_MODE, 1) and val(ADDR_OPERATING_MODE, 1) not in (0, 1, 3, 4, 5, 16):
            return dp.ERR_DATA_RANGE
        if touches(ADDR_TORQUE_ENABLE, 1):
            if val(ADDR_TORQUE_ENABLE, 1) > 1:
                return dp.ERR_DATA_RANGE
            if val(ADDR_TORQUE_ENABLE, 1) == 1 and self.hardware_error:
                return dp.ERR_RESULT_FAIL
        if touches(ADDR_BUS_WATCHDOG, 1) and val(ADDR_BUS_WATCHDOG, 1) > 127:
            return dp.ERR_DATA_RANGE
        if touches(ADDR_GOAL_VELOCITY, 4):
            if self.table[ADDR_BUS_WATCHDOG] == 0xFF:
                return dp.ERR_RESULT_FAIL  # bus watchdog error: goals locked until it is cleared
            if abs(val(ADDR_GOAL_VELOCITY, 4, True)) > self.get(ADDR_VELOCITY_LIMIT, 4):
                return dp.ERR_DATA_LIMIT
        if touches(ADDR_VELOCITY_LIMIT, 4) and not 0 <= val(ADDR_VELOCITY_LIMIT, 4, True) <= 1023:
            return dp.ERR_DATA_RANGE
        self.table[:] = new
        return 0

    # -- motion --------------------------------------------------------------------
    def target_velocity(self) -> float:
        """Velocity the servo drives toward, 0.229 rpm units."""
        if not self.torque_on or self.table[ADDR_OPERATING_MODE] != 1:
            return 0.0
        return float(self.get(ADDR_GOAL_VELOCITY, 4, signed=True))

    def check_watchdog(self, now: float) -> bool:
        """True when the bus watchdog has just expired."""
        wd = self.table[ADDR_BUS_WATCHDOG]
        if 1 <= wd <= 127 and self.torque_on and now - self.last_comm > wd * WATCHDOG_UNIT_S:
            self.put(ADDR_GOAL_VELOCITY, 4, 0)
            self.table[ADDR_BUS_WATCHDOG] = 0xFF
            return True
        return False

    def step(self, dt: float, coupling: Optional[WheelCoupling] = None) -> None:
        target = self.target_velocity()
        if coupling is not None:
            coupling.command(self.dxl_id, units_to_rad_s(target))
            angle, rate = coupling.measure(self.dxl_id)
            self._position = angle / (2 * 3.141592653589793) * TICKS_PER_REV
            self._velocity = rate / (2 * 3.141592653589793) * 60.0 / VELOCITY_UNIT_RPM
        else:
            accel = self.get(ADDR_PROFILE_ACCEL, 4) * PROFILE_ACCEL_UNIT_RPM2 / 60.0 / VELOCITY_UNIT_RPM
            dv = target - self._velocity
            if accel > 0:
                dv = max(-accel * dt, min(accel * dt, dv))
            self._velocity += dv
            self._position += self._velocity * VELOCITY_UNIT_RPM / 60.0 * TICKS_PER_REV * dt
        self._sync_present()

    def _sync_present(self) -> None:
        self.put(ADDR_PRESENT_VELOCITY, 4, int(round(self._velocity)))
        self.put(ADDR_PRESENT_POSITION, 4, int(round(self._position)))
        self.table[ADDR_MOVING] = 1 if abs(self._velocity) >= 0.5 else 0


def units_to_rad_s(units: float) -> float:
    return units * VELOCITY_UNIT_RPM * 2 * 3.141592653589793 / 60.0




class DynamixelBus(PtyDevice):
    """Servos on one emulated bus, served from a thread over a pty.

    ``start()`` returns the device path to open (the symlink ``link`` when
    given, else the pty slave). ``stop()`` ends it. Thread-safe fault injection
    via ``servo(id)`` under ``lock``.
    """

    thread_name = "dxl-emulator"

    def __init__(self, ids=(1, 2), model: str | ServoModel = "XL430-W250", link: str | Path | None = None,
                 coupling: Optional[WheelCoupling] = None, step_s: float = 0.001):
        self.model = model if isinstance(model, ServoModel) else model_by_name(model)
        self.servos = {i: EmulatedServo(i, self.model) for i in ids}
        super().__init__(link, step_s)
        self.coupling = coupling
        self.log: list[LogEntry] = []
        self.packets_seen = 0
        self._parser = dp.PacketParser()
        self._t0 = time.monotonic()

    def _reset_input(self) -> None:
        self._parser = dp.PacketParser()

    # -- helpers for tests --------------------------------------------------------------
    def servo(self, dxl_id: int) -> EmulatedServo:
        return self.servos[dxl_id]

    def writes(self, dxl_id: Optional[int] = None) -> list[LogEntry]:
        with self.lock:
            return [e for e in self.log if e.op == "write" and (dxl_id is None or e.dxl_id == dxl_id)]

    def _log(self, dxl_id: int, op: str, addr: int = -1, value: int = 0) -> None:
        self.log.append(LogEntry(time.monotonic() - self._t0, dxl_id, op, addr, value))
        if len(self.log) > 20000:
            del self.log[:10000]

    # -- serving ---------------------------------------------------------------------------
    def _serve_bytes(self, data: bytes) -> None:
        for pkt in self._parser.feed(data):
            self._handle(pkt)

    def _step(self, now: float, dt: float) -> None:
        for s in self.servos.values():
            if s.check_watchdog(now):
                self._log(s.dxl_id, "watchdog_expired")
            s.step(dt, self.coupling)

    def handle_bytes(self, data: bytes) -> bytes:
        """Process raw instruction bytes and return the raw answer (no pty; for protocol tests)."""
        out = bytearray()
        with self.lock:
            for pkt in self._parser.feed(data):
                out += b"".join(self._answers(pkt))
        return bytes(out)

    def _handle(self, pkt: dp.Packet) -> None:
        for reply in self._answers(pkt):
            self._write(reply)

    def _targets(self, pkt: dp.Packet) -> list[EmulatedServo]:
        if pkt.dxl_id == dp.BROADCAST_ID:
            return list(self.servos.values())
        s = self.servos.get(pkt.dxl_id)
        return [s] if s else []

    def _status(self, servo: EmulatedServo, error: int, data: bytes = b"") -> bytes:
        """A status packet after the servo's Return Delay Time; empty if it is silent."""
        if servo.no_answer:
            return b""
        delay = servo.table[ADDR_RETURN_DELAY] * 2e-6
        if delay > 0 and self._master >= 0:
            time.sleep(delay)
        raw = dp.encode_status(servo.dxl_id, error | servo.alert(), data)
        if servo.corrupt:
            raw = raw[:-1] + bytes([raw[-1] ^ 0x5A])
        return raw

    def _answers(self, pkt: dp.Packet) -> list[bytes]:
        self.packets_seen += 1
        now = time.monotonic()
        targets = self._targets(pkt)
        live = [s for s in targets if not s.no_answer]
        if not pkt.crc_ok:
            # a servo answers a unicast packet with a broken CRC with CRC Error
            if pkt.dxl_id != dp.BROADCAST_ID and live:
                return [self._status(live[0], dp.ERR_CRC)]
            return []
        inst, p = pkt.inst, pkt.params
        for s in live:
            s.last_comm = now
        unicast = pkt.dxl_id != dp.BROADCAST_ID
        if inst == dp.INST_PING:
            out = []
            for s in live:
                self._log(s.dxl_id, "ping")
                out.append(self._status(s, 0, s.table[0:2] + s.table[ADDR_FIRMWARE:ADDR_FIRMWARE + 1]))
            return out
        if inst in (dp.INST_READ, dp.INST_WRITE, dp.INST_REG_WRITE, dp.INST_REBOOT, dp.INST_ACTION):
            out = []
            for s in live:
                err, data = self._single(s, inst, p)
                if unicast or inst == dp.INST_PING:
                    out.append(self._status(s, err, data))
            return out if unicast and inst != dp.INST_ACTION else []
        if inst in (dp.INST_SYNC_READ, dp.INST_SYNC_WRITE):
            if len(p) < 4:
                return []
            addr = p[0] | p[1] << 8
            size = p[2] | p[3] << 8
            body = p[4:]
            if inst == dp.INST_SYNC_READ:
                out = []
                for dxl_id in body:
                    s = self.servos.get(dxl_id)
                    if s is None or s.no_answer:
                        continue
                    s.last_comm = now
                    err, data = s.read(addr, size)
                    out.append(self._status(s, err, data))
                return out
            for k in range(0, len(body) - size, size + 1):
                s = self.servos.get(body[k])
                if s is None or s.no_answer:
                    continue
                s.last_comm = now
                value = bytes(body[k + 1:k + 1 + size])
                err = s.write(addr, value)
                self._log(s.dxl_id, "write" if not err else f"write_error_{err}", addr,
                          int.from_bytes(value, "little", signed=True))
            return []
        if inst in (dp.INST_BULK_READ, dp.INST_BULK_WRITE):
            out = []
            k = 0
            while k + 5 <= len(p):
                dxl_id, addr, size = p[k], p[k + 1] | p[k + 2] << 8, p[k + 3] | p[k + 4] << 8
                s = self.servos.get(dxl_id)
                if inst == dp.INST_BULK_READ:
                    k += 5
                    if s is not None and not s.no_answer:
                        s.last_comm = now
                        err, data = s.read(addr, size)
                        out.append(self._status(s, err, data))
                else:
                    value = bytes(p[k + 5:k + 5 + size])
                    k += 5 + size
                    if s is not None and not s.no_answer:
                        s.last_comm = now
                        err = s.write(addr, value)
                        self._log(s.dxl_id, "write" if not err else f"write_error_{err}", addr,
                                  int.from_bytes(value, "little", signed=True))
            return out
        # unknown instruction
        return [self._status(s, dp.ERR_INSTRUCTION) for s in live] if unicast else []

    def _single(self, s: EmulatedServo, inst: int, p: bytes) -> tuple[int, bytes]:
        if inst == dp.INST_READ:
            if len(p) != 4:
                return dp.ERR_DATA_LENGTH, b""
            addr, size = p[0] | p[1] << 8, p[2] | p[3] << 8
            self._log(s.dxl_id, "read", addr, size)
            return s.read(addr, size)
        if inst in (dp.INST_WRITE, dp.INST_REG_WRITE):
            if len(p) < 3:
                return dp.ERR_DATA_LENGTH, b""
            addr, value = p[0] | p[1] << 8, bytes(p[2:])
            if inst == dp.INST_REG_WRITE:
                s._pending = (addr, value)
                s.table[ADDR_REGISTERED] = 1
                self._log(s.dxl_id, "reg_write", addr, int.from_bytes(value, "little", signed=True))
                return 0, b""
            err = s.write(addr, value)
            self._log(s.dxl_id, "write" if not err else f"write_error_{err}", addr,
                      int.from_bytes(value, "little", signed=True))
            return err, b""
        if inst == dp.INST_ACTION:
            if s._pending is None:
                return dp.ERR_RESULT_FAIL, b""
            addr, value = s._pending
            s._pending = None
            s.table[ADDR_REGISTERED] = 0
            err = s.write(addr, value)
            self._log(s.dxl_id, "action", addr, int.from_bytes(value, "little", signed=True))
            return err, b""
        if inst == dp.INST_REBOOT:
            self._log(s.dxl_id, "reboot")
            s.power_on()  # the answer goes out before the reboot, with the error state cleared after
            return 0, b""
        return dp.ERR_INSTRUCTION, b""
