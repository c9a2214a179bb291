"""First set-up of Dynamixel X servos through the dynamixel-sdk: find them, give each its id and baud rate.

A new XL430/XM430 answers as id 1 at 57600 bit/s; a robot wants two distinct
ids (left and right wheel) and a fast bus (1 Mbps in the shipped configs).
``scan`` tries each baud rate with the SDK's broadcast ping (every servo at
that rate answers with its model number and firmware), ``set_id`` and
``set_baud`` write the EEPROM registers ID (7) and Baud Rate (8), which a servo
accepts only with torque off, and check the result by pinging the servo under
its new id or at its new rate.

Connect one new servo at a time when they all still have id 1: two servos with
one id answer together and garble each other.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Optional

from vbnav.drivers import dynamixel_table as reg
from vbnav.drivers.discovery import check_device
from vbnav.drivers.dynamixel_table import BAUD_VALUES, MAX_ID, MODEL_NUMBERS, rate_problem
from vbnav.drivers.errors import InputError
from vbnav.drivers.wheels import DriveError

try:
    import dynamixel_sdk as sdk
    from vbnav.drivers.dynamixel import BudgetedPort
except ImportError:  # pragma: no cover - dependency is in pyproject
    sdk = None

#: Rates a Dynamixel X bus is usually set to, most likely first (factory 57600, then the fast ones).
SCAN_BAUDS = (57_600, 1_000_000, 115_200, 2_000_000, 3_000_000, 4_000_000)
MODEL_NAMES = {number: name for name, number in MODEL_NUMBERS.items()}
ADAPTER_LATENCY_MS = 16.0     # an FTDI adapter's latency timer before it is set to 1 ms: wait for the worst


@dataclass
class FoundServo:
    dxl_id: int
    baud: int
    model_number: int
    firmware: int

    @property
    def model(self) -> str:
        return MODEL_NAMES.get(self.model_number, f"unknown model {self.model_number}")


class DynamixelBusTool:
    """One adapter, opened at one rate at a time; ``close()`` (or ``with``) releases it."""

    def __init__(self, port: str):
        if sdk is None:  # pragma: no cover
            raise DriveError("dynamixel-sdk is not installed")
        check_device(port, "the bus adapter's serial device", " (vbnav find lists the serial ports)")
        self.port_name = port
        self.port = BudgetedPort(port, ADAPTER_LATENCY_MS, 2.0)
        self.ph = sdk.PacketHandler(2.0)
        self.baud: Optional[int] = None

    def __enter__(self) -> "DynamixelBusTool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self.baud is not None:
            self.port.closePort()
            self.baud = None

    def at(self, baud: int) -> "DynamixelBusTool":
        """Talk at ``baud`` bit/s from now on."""
        if rate_problem(baud):
            raise InputError(f"--baud: {rate_problem(baud)}")
        if self.baud == baud:
            return self
        try:
            ok = (self.port.openPort() if self.baud is None else True) and self.port.setBaudRate(baud)
        except Exception as exc:  # serial.SerialException, OSError
            raise DriveError(f"cannot open {self.port_name}: {exc}") from exc
        if not ok:
            raise DriveError(f"cannot open {self.port_name} at {baud} bit/s")
        self.baud = baud
        return self

    # -- looking ---------------------------------------------------------------------------------
    def broadcast_ping(self) -> list[FoundServo]:
        """Every servo answering at the current rate."""
        found, _res = self.ph.broadcastPing(self.port)
        return [FoundServo(i, self.baud, model, fw) for i, (model, fw) in sorted(found.items())]

    def ping(self, dxl_id: int) -> Optional[FoundServo]:
        model, res, _err = self.ph.ping(self.port, dxl_id)
        if res != sdk.COMM_SUCCESS:
            return None
        fw, res, _err = self.ph.read1ByteTxRx(self.port, dxl_id, reg.FIRMWARE_VERSION.address)
        return FoundServo(dxl_id, self.baud, model, fw if res == sdk.COMM_SUCCESS else -1)

    def scan(self, bauds: Iterable[int] = SCAN_BAUDS, progress=None) -> list[FoundServo]:
        """Servos at each of ``bauds`` (broadcast ping at each rate)."""
        found = []
        for baud in bauds:
            self.at(baud)
            here = self.broadcast_ping()
            if progress is not None:
                progress(baud, here)
            found.extend(here)
        return found

    # -- changing ----------------------------------------------------------------------------------
    def _require(self, dxl_id: int) -> FoundServo:
        servo = self.ping(dxl_id)
        if servo is None:
            raise DriveError(f"no servo with id {dxl_id} answers on {self.port_name} at {self.baud} bit/s "
                             f"('vbnav find servos --port {self.port_name}' shows what is there)")
        return servo

    def _write_eeprom(self, dxl_id: int, register, value: int) -> None:
        """Torque off (EEPROM is locked while it is on), then the register; refused writes are errors."""
        for r, v in ((reg.TORQUE_ENABLE, 0), (register, value)):
            res, err = self.ph.write1ByteTxRx(self.port, dxl_id, r.address, v)
            if res != sdk.COMM_SUCCESS:
                raise DriveError(f"servo {dxl_id}: writing {r.name} = {v}: {self.ph.getTxRxResult(res)}")
            if err & 0x7F:
                raise DriveError(f"servo {dxl_id}: writing {r.name} = {v} refused: {self.ph.getRxPacketError(err)}")

    def set_id(self, dxl_id: int, new_id: int) -> FoundServo:
        """Give servo ``dxl_id`` the id ``new_id`` (which no servo on the bus may have)."""
        if not 0 <= new_id <= MAX_ID:
            raise InputError(f"--new-id {new_id}: a servo id is 0..{MAX_ID}")
        servo = self._require(dxl_id)
        if new_id == dxl_id:
            return servo
        other = self.ping(new_id)
        if other is not None:
            raise DriveError(f"id {new_id} is taken on {self.port_name} by a {other.model} servo: two servos with one "
                             f"id garble each other's answers; choose another id")
        self._write_eeprom(dxl_id, reg.ID, new_id)
        moved = self.ping(new_id)
        if moved is None:
            raise DriveError(f"servo {dxl_id} accepted id {new_id} but does not answer under it")
        return moved

    def set_baud(self, dxl_id: int, new_baud: int) -> FoundServo:
        """Switch servo ``dxl_id`` to ``new_baud`` bit/s, then find it there."""
        if rate_problem(new_baud):
            raise InputError(f"--new-baud: {rate_problem(new_baud)}")
        self._require(dxl_id)
        self._write_eeprom(dxl_id, reg.BAUD_RATE, BAUD_VALUES[new_baud])
        servo = self.at(new_baud).ping(dxl_id)
        if servo is None:
            raise DriveError(f"servo {dxl_id} accepted {new_baud} bit/s but does not answer at that rate")
        return servo
