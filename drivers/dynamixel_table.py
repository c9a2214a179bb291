"""The Dynamixel X-series control table (Protocol 2.0), written once.

The driver (``drivers/dynamixel.py``) writes and reads these registers through
the dynamixel-sdk; the bus emulator (``drivers/sim/dynamixel_emulator.py``)
holds them per servo and refuses what a real servo refuses. Both take address,
size, signedness and access from here, so they cannot disagree.

Source: ROBOTIS e-Manual, control tables of the XL430-W250 and XM430-W350
(the other X-series models listed in ``MODEL_NUMBERS`` share this layout for
every register below). Listed are the registers vbnav uses and every
read-only one (the emulator answers a write to those with Access Error).
Addresses below ``EEPROM_END`` are EEPROM: writable only with torque off.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

EEPROM_END = 64


@dataclass(frozen=True)
class Register:
    """One control-table entry: ``size`` little-endian bytes at ``address``."""

    name: str
    address: int
    size: int
    signed: bool = False
    writable: bool = True

    @property
    def end(self) -> int:
        return self.address + self.size

    @property
    def eeprom(self) -> bool:
        return self.address < EEPROM_END

    def encode(self, value: int) -> bytes:
        """The register's bytes for ``value`` (two's complement for a negative one)."""
        return (value & ((1 << (8 * self.size)) - 1)).to_bytes(self.size, "little")

    def decode(self, data: bytes, signed: bool | None = None) -> int:
        """The value of the register's bytes; ``signed`` overrides the table's signedness."""
        return int.from_bytes(bytes(data[:self.size]), "little", signed=self.signed if signed is None else signed)


# EEPROM area
MODEL_NUMBER = Register("Model Number", 0, 2, writable=False)
MODEL_INFORMATION = Register("Model Information", 2, 4, writable=False)
FIRMWARE_VERSION = Register("Firmware Version", 6, 1, writable=False)
ID = Register("ID", 7, 1)
BAUD_RATE = Register("Baud Rate", 8, 1)
RETURN_DELAY_TIME = Register("Return Delay Time", 9, 1)  # units of 2 us
OPERATING_MODE = Register("Operating Mode", 11, 1)
VELOCITY_LIMIT = Register("Velocity Limit", 44, 4)  # 0..1023 velocity units
# RAM area
TORQUE_ENABLE = Register("Torque Enable", 64, 1)
LED = Register("LED", 65, 1)
STATUS_RETURN_LEVEL = Register("Status Return Level", 68, 1)
REGISTERED_INSTRUCTION = Register("Registered Instruction", 69, 1, writable=False)
HARDWARE_ERROR_STATUS = Register("Hardware Error Status", 70, 1, writable=False)
BUS_WATCHDOG = Register("Bus Watchdog", 98, 1, signed=True)  # units of WATCHDOG_UNIT_S; -1 once expired
GOAL_PWM = Register("Goal PWM", 100, 2, signed=True)
GOAL_VELOCITY = Register("Goal Velocity", 104, 4, signed=True)
PROFILE_ACCELERATION = Register("Profile Acceleration", 108, 4)
PROFILE_VELOCITY = Register("Profile Velocity", 112, 4)
GOAL_POSITION = Register("Goal Position", 116, 4, signed=True)
REALTIME_TICK = Register("Realtime Tick", 120, 2, writable=False)
MOVING = Register("Moving", 122, 1, writable=False)
MOVING_STATUS = Register("Moving Status", 123, 1, writable=False)
PRESENT_PWM = Register("Present PWM", 124, 2, signed=True, writable=False)
PRESENT_LOAD = Register("Present Load", 126, 2, signed=True, writable=False)
PRESENT_VELOCITY = Register("Present Velocity", 128, 4, signed=True, writable=False)
PRESENT_POSITION = Register("Present Position", 132, 4, signed=True, writable=False)
VELOCITY_TRAJECTORY = Register("Velocity Trajectory", 136, 4, signed=True, writable=False)
POSITION_TRAJECTORY = Register("Position Trajectory", 140, 4, signed=True, writable=False)
PRESENT_INPUT_VOLTAGE = Register("Present Input Voltage", 144, 2, writable=False)  # 0.1 V
PRESENT_TEMPERATURE = Register("Present Temperature", 146, 1, writable=False)  # deg C

REGISTERS: dict[str, Register] = {r.name: r for r in (
    MODEL_NUMBER, MODEL_INFORMATION, FIRMWARE_VERSION, ID, BAUD_RATE, RETURN_DELAY_TIME, OPERATING_MODE,
    VELOCITY_LIMIT, TORQUE_ENABLE, LED, STATUS_RETURN_LEVEL, REGISTERED_INSTRUCTION, HARDWARE_ERROR_STATUS,
    BUS_WATCHDOG, GOAL_PWM, GOAL_VELOCITY, PROFILE_ACCELERATION, PROFILE_VELOCITY, GOAL_POSITION, REALTIME_TICK,
    MOVING, MOVING_STATUS, PRESENT_PWM, PRESENT_LOAD, PRESENT_VELOCITY, PRESENT_POSITION, VELOCITY_TRAJECTORY,
    POSITION_TRAJECTORY, PRESENT_INPUT_VOLTAGE, PRESENT_TEMPERATURE)}
TABLE_SIZE = max(r.end for r in REGISTERS.values())

# Operating Mode values; vbnav drives wheels in velocity mode.
OPERATING_MODES = {0: "current", 1: "velocity", 3: "position", 4: "extended position",
                   5: "current-based position", 16: "PWM"}
MODE_VELOCITY = 1

# Baud Rate (8) values -> bit/s (X-series e-Manual). An XL430/XM430 leaves the factory at 57600 (value 1).
BAUD_RATES = {0: 9600, 1: 57_600, 2: 115_200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000, 6: 4_000_000,
              7: 4_500_000}
BAUD_VALUES = {bps: value for value, bps in BAUD_RATES.items()}
FACTORY_BAUD = 57_600


def rate_problem(baud) -> str:
    """"" when ``baud`` (bit/s) is a rate a Dynamixel X servo runs at, else why not, naming those rates."""
    if baud in BAUD_VALUES:
        return ""
    return f"{baud} is not a Dynamixel X rate; one of {', '.join(map(str, BAUD_VALUES))} bit/s"

MAX_ID = 252  # 253 and 254 (broadcast) are reserved

# Hardware Error Status bits (only a REBOOT clears them).
HW_ERROR_BITS = {0: "input voltage error", 2: "overheating", 3: "motor encoder error",
                 4: "electrical shock", 5: "overload"}

# Model Number (what a ping answers) of the X-series servos the driver accepts.
MODEL_NUMBERS = {"XL430-W250": 1060, "XM430-W350": 1020, "XM430-W210": 1030, "XM540-W270": 1120,
                 "XL330-M288": 1200}

# Units
VELOCITY_UNIT_RPM = 0.229  # one Goal/Present Velocity unit
VELOCITY_UNIT_RAD_S = VELOCITY_UNIT_RPM * 2.0 * math.pi / 60.0
ACCEL_UNIT_RPM2 = 214.577  # one Profile Acceleration unit, rev/min^2
ACCEL_UNIT_RAD_S2 = ACCEL_UNIT_RPM2 * 2.0 * math.pi / 3600.0
TICKS_PER_REV = 4096  # Present Position
WATCHDOG_UNIT_S = 0.020  # Bus Watchdog
RETURN_DELAY_UNIT_S = 2e-6  # Return Delay Time
