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
- ID (7) and Baud Rate (8) are EEPROM: written with torque off, the status
  packet still goes out under the old id and at the old rate, then the servo
  answers to the new ones (what ``vbnav servo set-id/set-baud`` relies on).

Baud rate: each servo listens at the rate of its Baud Rate register (the bus's
``baud`` at power-on, default 1 Mbps; a new XL430 ships at 57600). A pty
carries bytes whatever the rate, so the bus reads the rate the host set on its
side (``PtyDevice.host_baud``) for every chunk it receives: a servo set to
another rate hears only noise, so it neither acts on the packet nor answers,
exactly what a host at the wrong rate sees on a real bus (silence, then a
timeout). ``handle_bytes`` (no pty) has no rate: every servo hears it.

Faults are injected per servo: ``no_answer`` (silent, as if unplugged from the
bus), ``corrupt`` (answers with a broken CRC), ``garbled_rx`` (hears every packet
corrupted: answers a unicast one with CRC Error and applies nothing, ignores its share of a
sync packet), ``drops_stops`` (a count: that many of the next stop writes to the servo, a 0 to Goal
Velocity or Torque Enable, arrive corrupted: a unicast one answered with CRC Error, its share of a sync
write ignored; other packets are heard intact, so the reads keep feeding its bus watchdog),
``set_hardware_error(bits)``.
``unplug()``/``replug()`` simulate the USB adapter going away and coming back
(the stable device path is a symlink, as /dev/serial/by-id/... is).

Wheel motion: in Velocity mode the present velocity follows Goal Velocity at
the Profile Acceleration and the position integrates it; or, when a
``WheelCoupling`` is attached, the commanded rate goes to it (e.g. the
simulated base) and the present values come back from it.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Protocol

from vbnav.drivers import dynamixel_protocol as dp
from vbnav.drivers.dynamixel_table import (
    ACCEL_UNIT_RPM2, BAUD_RATE, BAUD_RATES, BAUD_VALUES, BUS_WATCHDOG, EEPROM_END, FIRMWARE_VERSION, GOAL_VELOCITY,
    HARDWARE_ERROR_STATUS, ID, MAX_ID, MODE_VELOCITY, MODEL_NUMBER, MODEL_NUMBERS, MOVING, OPERATING_MODE,
    OPERATING_MODES, PRESENT_INPUT_VOLTAGE, PRESENT_POSITION, PRESENT_TEMPERATURE, PRESENT_VELOCITY,
    PROFILE_ACCELERATION, REGISTERED_INSTRUCTION, REGISTERS, RETURN_DELAY_TIME, RETURN_DELAY_UNIT_S,
    STATUS_RETURN_LEVEL, TABLE_SIZE, TICKS_PER_REV, TORQUE_ENABLE, VELOCITY_LIMIT, VELOCITY_UNIT_RPM,
    WATCHDOG_UNIT_S, Register, rate_problem)
from vbnav.drivers.sim.pty_device import LoggedFlag, PtyDevice

log = logging.getLogger("vbnav.emulator.dynamixel")
INSTRUCTION_NAMES = {dp.INST_PING: "PING", dp.INST_READ: "READ", dp.INST_WRITE: "WRITE",
                     dp.INST_REG_WRITE: "REG_WRITE", dp.INST_ACTION: "ACTION", dp.INST_REBOOT: "REBOOT",
                     dp.INST_SYNC_READ: "SYNC_READ", dp.INST_SYNC_WRITE: "SYNC_WRITE",
                     dp.INST_BULK_READ: "BULK_READ", dp.INST_BULK_WRITE: "BULK_WRITE"}
ERROR_NAMES = {dp.ERR_RESULT_FAIL: "result fail", dp.ERR_INSTRUCTION: "instruction error", dp.ERR_CRC: "CRC error",
               dp.ERR_DATA_RANGE: "data range error", dp.ERR_DATA_LENGTH: "data length error",
               dp.ERR_DATA_LIMIT: "data limit error", dp.ERR_ACCESS: "access error"}


@dataclass(frozen=True)
class ServoModel:
    name: str
    number: int
    velocity_limit: int  # factory default, 0.229 rpm units
    voltage_dV: int  # reported input voltage, 0.1 V


MODELS = {name: ServoModel(name, MODEL_NUMBERS[name], velocity_limit, 120)
          for name, velocity_limit in (("XL430-W250", 265), ("XM430-W350", 200))}


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

    def __init__(self, dxl_id: int, model: ServoModel, baud: int = 1_000_000):
        if rate_problem(baud):
            raise ValueError(rate_problem(baud))
        self.dxl_id = dxl_id
        self.model = model
        self._factory_baud = baud
        self.table = bytearray(TABLE_SIZE)
        self._position = 0.0  # ticks, float
        self._velocity = 0.0  # 0.229 rpm units, float
        self._pending: Optional[tuple[int, bytes]] = None
        self.last_comm = time.monotonic()
        self.drops_stops = 0    # fault: this many of the next stop writes arrive corrupted (the rest intact)
        self.power_on()

    # -- injected faults (logged: what a test or an operator did to the bus) ---------------
    no_answer = LoggedFlag("silent (fault injected)", "answers again")
    corrupt = LoggedFlag("answers with a broken CRC (fault injected)", "answers intact again")
    garbled_rx = LoggedFlag("hears every packet corrupted: answers CRC Error, applies nothing (fault injected)",
                            "hears intact packets again")

    def _log_event(self, text: str) -> None:
        log.info("servo %d: %s", self.dxl_id, text)

    # -- control table -----------------------------------------------------------
    def get(self, register: Register, signed: bool | None = None) -> int:
        """The register's value (signed as the control table says unless ``signed`` is given)."""
        return register.decode(self.table[register.address:register.end], signed)

    def put(self, register: Register, value: int) -> None:
        """Set a register directly (no access check: the servo's own doing, or a test's)."""
        self.table[register.address:register.end] = register.encode(value)

    def power_on(self) -> None:
        """Factory defaults of the RAM area (EEPROM is kept across reboots)."""
        if self.get(MODEL_NUMBER) == 0:
            self.put(MODEL_NUMBER, self.model.number)
            self.put(FIRMWARE_VERSION, 46)
            self.put(ID, self.dxl_id)
            self.put(BAUD_RATE, BAUD_VALUES[self._factory_baud])
            self.put(RETURN_DELAY_TIME, 250)  # 500 us
            self.put(OPERATING_MODE, 3)  # position control
            self.put(VELOCITY_LIMIT, self.model.velocity_limit)
        self.table[EEPROM_END:] = bytes(TABLE_SIZE - EEPROM_END)
        self.put(STATUS_RETURN_LEVEL, 2)
        self.put(PRESENT_INPUT_VOLTAGE, self.model.voltage_dV)
        self.put(PRESENT_TEMPERATURE, 36)
        # after power-on the position is reported within one turn
        self._position = float(int(self._position) % TICKS_PER_REV)
        self._velocity = 0.0
        self._pending = None
        self._sync_present()

    @property
    def baud(self) -> int:
        """The rate this servo listens and answers at, bit/s (its Baud Rate register)."""
        return BAUD_RATES.get(self.get(BAUD_RATE), 0)

    @property
    def torque_on(self) -> bool:
        return self.get(TORQUE_ENABLE) == 1

    @property
    def hardware_error(self) -> int:
        return self.get(HARDWARE_ERROR_STATUS)

    def alert(self) -> int:
        return dp.ERR_ALERT if self.hardware_error else 0

    def set_hardware_error(self, bits: int) -> None:
        """Latch hardware error bits: torque goes off, only REBOOT clears them."""
        self.put(HARDWARE_ERROR_STATUS, self.hardware_error | bits)
        self.put(TORQUE_ENABLE, 0)
        log.info("servo %d: hardware error 0x%02x, torque off until REBOOT", self.dxl_id, self.hardware_error)

    def read(self, addr: int, size: int) -> tuple[int, bytes]:
        if size <= 0 or addr < 0 or addr + size > TABLE_SIZE:
            return dp.ERR_ACCESS, b""
        return 0, bytes(self.table[addr:addr + size])

    def write(self, addr: int, data: bytes) -> int:
        """Apply a write; returns the status error number (0 = accepted)."""
        end = addr + len(data)
        if not data or addr < 0 or end > TABLE_SIZE:
            return dp.ERR_ACCESS
        touches = lambda r: addr < r.end and end > r.address  # noqa: E731
        if any(touches(r) and not r.writable for r in REGISTERS.values()):
            return dp.ERR_ACCESS
        if addr < EEPROM_END and self.torque_on:
            return dp.ERR_ACCESS
        new = bytearray(self.table)
        new[addr:end] = data
        val = lambda r: r.decode(new[r.address:r.end])  # noqa: E731
        if touches(OPERATING_MODE) and val(OPERATING_MODE) not in OPERATING_MODES:
            return dp.ERR_DATA_RANGE
        if touches(TORQUE_ENABLE):
            if val(TORQUE_ENABLE) > 1:
                return dp.ERR_DATA_RANGE
            if val(TORQUE_ENABLE) == 1 and self.hardware_error:
                return dp.ERR_RESULT_FAIL
        if touches(BUS_WATCHDOG) and not 0 <= val(BUS_WATCHDOG) <= 127:
            return dp.ERR_DATA_RANGE
        if touches(GOAL_VELOCITY):
            if self.get(BUS_WATCHDOG) == -1:
                return dp.ERR_RESULT_FAIL  # bus watchdog error: goals locked until it is cleared
            if abs(val(GOAL_VELOCITY)) > self.get(VELOCITY_LIMIT):
                return dp.ERR_DATA_LIMIT
        if touches(VELOCITY_LIMIT) and not 0 <= val(VELOCITY_LIMIT) <= 1023:
            return dp.ERR_DATA_RANGE
        if touches(ID) and not 0 <= val(ID) <= MAX_ID:
            return dp.ERR_DATA_RANGE
        if touches(BAUD_RATE) and val(BAUD_RATE) not in BAUD_RATES:
            return dp.ERR_DATA_RANGE
        self.table[:] = new
        return 0

    # -- motion --------------------------------------------------------------------
    def target_velocity(self) -> float:
        """Velocity the servo drives toward, 0.229 rpm units."""
        if not self.torque_on or self.get(OPERATING_MODE) != MODE_VELOCITY:
            return 0.0
        return float(self.get(GOAL_VELOCITY))

    def check_watchdog(self, now: float) -> bool:
        """True when the bus watchdog has just expired."""
        wd = self.get(BUS_WATCHDOG)
        if 1 <= wd <= 127 and self.torque_on and now - self.last_comm > wd * WATCHDOG_UNIT_S:
            self.put(GOAL_VELOCITY, 0)
            self.put(BUS_WATCHDOG, -1)
            return True
        return False

    def step(self, dt: float, coupling: Optional[WheelCoupling] = None) -> None:
        target = self.target_velocity()
        if coupling is not None:
            coupling.command(self.dxl_id, units_to_rad_s(target))
            angle, rate = coupling.measure(self.dxl_id)
            self._position = angle / (2 * math.pi) * TICKS_PER_REV
            self._velocity = rate / (2 * math.pi) * 60.0 / VELOCITY_UNIT_RPM
        else:
            accel = self.get(PROFILE_ACCELERATION) * ACCEL_UNIT_RPM2 / 60.0 / VELOCITY_UNIT_RPM
            dv = target - self._velocity
            if accel > 0:
                dv = max(-accel * dt, min(accel * dt, dv))
            self._velocity += dv
            self._position += self._velocity * VELOCITY_UNIT_RPM / 60.0 * TICKS_PER_REV * dt
        self._sync_present()

    def _sync_present(self) -> None:
        self.put(PRESENT_VELOCITY, int(round(self._velocity)))
        self.put(PRESENT_POSITION, int(round(self._position)))
        self.put(MOVING, 1 if abs(self._velocity) >= 0.5 else 0)


def units_to_rad_s(units: float) -> float:
    return units * VELOCITY_UNIT_RPM * 2 * math.pi / 60.0


class DynamixelBus(PtyDevice):
    """Servos on one emulated bus, served from a thread over a pty.

    ``start()`` returns the device path to open (the symlink ``link`` when
    given, else the pty slave). ``stop()`` ends it. Thread-safe fault injection
    via ``servo(id)`` under ``lock``.
    """

    thread_name = "dxl-emulator"

    logger_name = log.name

    def __init__(self, ids=(1, 2), model: str | ServoModel = "XL430-W250", link: str | Path | None = None,
                 coupling: Optional[WheelCoupling] = None, step_s: float = 0.001, baud: int = 1_000_000):
        self.model = model if isinstance(model, ServoModel) else model_by_name(model)
        self.servos = {i: EmulatedServo(i, self.model, baud) for i in ids}
        super().__init__(link, step_s)
        self._host_baud: Optional[int] = None     # the host's rate while a chunk is served (None: any)
        self._mismatch_baud: Optional[int] = None
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
        host = self._host_baud = self.host_baud()
        if not any(self._hears(s) for s in self.servos.values()):
            # Nobody on the bus runs at the host's rate: to every servo this is noise. Nothing is parsed,
            # nothing answers (the parser starts afresh, as a servo's UART resynchronises).
            if host != self._mismatch_baud:
                rates = sorted({s.baud for s in self.servos.values()})
                log.info("host sends at %s bit/s, the servos listen at %s bit/s: they hear noise and stay silent",
                         host, ", ".join(map(str, rates)))
            self._mismatch_baud = host
            log.debug("%d bytes at %s bit/s dropped (no servo at that rate)", len(data), host)
            self._parser = dp.PacketParser()
            return
        self._mismatch_baud = None
        try:
            for pkt in self._parser.feed(data):
                self._handle(pkt)
        finally:
            self._host_baud = None

    def _hears(self, s: EmulatedServo) -> bool:
        """The servo runs at the host's rate (checked per packet: a servo switched mid-chunk stops hearing)."""
        return self._host_baud is None or s.baud == self._host_baud

    def _listener(self, dxl_id: int) -> Optional[EmulatedServo]:
        """Servo ``dxl_id`` if it is on the bus and hears the host's rate."""
        s = self.servos.get(dxl_id)
        return s if s is not None and self._hears(s) else None

    def _step(self, now: float, dt: float) -> None:
        for s in self.servos.values():
            limit_ms = s.get(BUS_WATCHDOG) * WATCHDOG_UNIT_S * 1000
            if s.check_watchdog(now):
                self._log(s.dxl_id, "watchdog_expired")
                log.info("servo %d: bus watchdog expired (no packet for %.0f ms): Goal Velocity 0, goals locked "
                         "until 0 is written to Bus Watchdog", s.dxl_id, limit_ms)
            s.step(dt, self.coupling)

    def handle_bytes(self, data: bytes) -> bytes:
        """Process raw instruction bytes and return the raw answer (no pty; for protocol tests)."""
        out = bytearray()
        with self.lock:
            for pkt in self._parser.feed(data):
                out += b"".join(self._answers(pkt))
        return bytes(out)

    def _handle(self, pkt: dp.Packet) -> None:
        replies = self._answers(pkt)
        if log.isEnabledFor(logging.DEBUG):
            log.debug("%s to id %s (%d parameter bytes%s) -> %d status packet(s)",
                      INSTRUCTION_NAMES.get(pkt.inst, f"instruction 0x{pkt.inst:02x}"),
                      "broadcast" if pkt.dxl_id == dp.BROADCAST_ID else pkt.dxl_id, len(pkt.params),
                      "" if pkt.crc_ok else ", bad CRC", sum(1 for r in replies if r))
        for reply in replies:
            self._write(reply)
        self._apply_identity_changes()

    def _apply_identity_changes(self) -> None:
        """A servo whose ID register was written answers to its new id from now on (its status packet
        went out under the old one)."""
        for old, s in list(self.servos.items()):
            new = s.get(ID)
            if new == old:
                continue
            del self.servos[old]
            if new in self.servos:
                log.warning("servo %d took id %d, which servo %d already has: the two collide on the bus; "
                            "the emulator keeps only the newer one", old, new, new)
            s.dxl_id = new
            self.servos[new] = s
            log.info("servo %d: ID is now %d", old, new)

    def _servo_event(self, s: EmulatedServo, op: str, addr: int, value: bytes, err: int) -> None:
        """Log a write (list and logger): refused writes, ID and baud changes at INFO."""
        number = int.from_bytes(value, "little", signed=True)
        self._log(s.dxl_id, op if not err else f"write_error_{err}", addr, number)
        if err:
            name = next((r.name for r in REGISTERS.values() if r.address == addr), f"address {addr}")
            log.info("servo %d: write of %s = %d refused: %s", s.dxl_id, name, number, ERROR_NAMES.get(err, err))
        elif addr == BAUD_RATE.address:
            log.info("servo %d: Baud Rate is now %d bit/s (from the next packet)", s.dxl_id, s.baud)

    def _targets(self, pkt: dp.Packet) -> list[EmulatedServo]:
        if pkt.dxl_id == dp.BROADCAST_ID:
            return [s for s in self.servos.values() if self._hears(s)]
        s = self._listener(pkt.dxl_id)
        return [s] if s else []

    def _status(self, servo: EmulatedServo, error: int, data: bytes = b"") -> bytes:
        """A status packet after the servo's Return Delay Time; empty if it is silent."""
        if servo.no_answer:
            return b""
        delay = servo.get(RETURN_DELAY_TIME) * RETURN_DELAY_UNIT_S
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
        if not pkt.crc_ok or (pkt.dxl_id != dp.BROADCAST_ID and live and live[0].garbled_rx):
            # a servo answers a unicast packet with a broken CRC with CRC Error
            if pkt.dxl_id != dp.BROADCAST_ID and live:
                return [self._status(live[0], dp.ERR_CRC)]
            return []
        inst, p = pkt.inst, pkt.params
        if inst in (dp.INST_WRITE, dp.INST_REG_WRITE) and pkt.dxl_id != dp.BROADCAST_ID and live \
                and len(p) > 2 and self._drops_stop(live[0], p[0] | p[1] << 8, p[2:]):
            return [self._status(live[0], dp.ERR_CRC)]
        for s in live:
            s.last_comm = now
        unicast = pkt.dxl_id != dp.BROADCAST_ID
        if inst == dp.INST_PING:
            out = []
            for s in live:
                self._log(s.dxl_id, "ping")
                model = s.table[MODEL_NUMBER.address:MODEL_NUMBER.end]
                out.append(self._status(s, 0, model + s.table[FIRMWARE_VERSION.address:FIRMWARE_VERSION.end]))
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
                    s = self._listener(dxl_id)
                    if s is None or s.no_answer or s.garbled_rx:
                        continue
                    s.last_comm = now
                    err, data = s.read(addr, size)
                    out.append(self._status(s, err, data))
                return out
            for k in range(0, len(body) - size, size + 1):
                s = self._listener(body[k])
                if s is None or s.no_answer or s.garbled_rx or self._drops_stop(s, addr, body[k + 1:k + 1 + size]):
                    continue
                s.last_comm = now
                value = bytes(body[k + 1:k + 1 + size])
                self._servo_event(s, "write", addr, value, s.write(addr, value))
            return []
        if inst in (dp.INST_BULK_READ, dp.INST_BULK_WRITE):
            out = []
            k = 0
            while k + 5 <= len(p):
                dxl_id, addr, size = p[k], p[k + 1] | p[k + 2] << 8, p[k + 3] | p[k + 4] << 8
                s = self._listener(dxl_id)
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
                        self._servo_event(s, "write", addr, value, s.write(addr, value))
            return out
        # unknown instruction
        return [self._status(s, dp.ERR_INSTRUCTION) for s in live] if unicast else []

    def _drops_stop(self, s: EmulatedServo, addr: int, value: bytes) -> bool:
        """The ``drops_stops`` fault: True (and one fewer left) when this write is a stop (0 to Goal Velocity or
        Torque Enable) that reaches the servo corrupted."""
        if s.drops_stops <= 0 or addr not in (GOAL_VELOCITY.address, TORQUE_ENABLE.address) or any(value):
            return False
        s.drops_stops -= 1
        log.info("servo %d: a stop arrived corrupted (fault injected; %d more to come)", s.dxl_id, s.drops_stops)
        return True

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
                s.put(REGISTERED_INSTRUCTION, 1)
                self._log(s.dxl_id, "reg_write", addr, int.from_bytes(value, "little", signed=True))
                return 0, b""
            err = s.write(addr, value)
            self._servo_event(s, "write", addr, value, err)
            return err, b""
        if inst == dp.INST_ACTION:
            if s._pending is None:
                return dp.ERR_RESULT_FAIL, b""
            addr, value = s._pending
            s._pending = None
            s.put(REGISTERED_INSTRUCTION, 0)
            err = s.write(addr, value)
            self._log(s.dxl_id, "action", addr, int.from_bytes(value, "little", signed=True))
            return err, b""
        if inst == dp.INST_REBOOT:
            self._log(s.dxl_id, "reboot")
            log.info("servo %d: REBOOT (hardware errors cleared, RAM area to defaults)", s.dxl_id)
            s.power_on()  # the answer goes out before the reboot, with the error state cleared after
            return 0, b""
        return dp.ERR_INSTRUCTION, b""
