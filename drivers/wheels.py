"""Differential wheel drive interface.

Lifecycle after ros2_control: ``connect()`` configures (device open and
readable, torque off), ``enable()`` activates (commands flow), ``disable()``
deactivates (wheels stopped, torque off), ``close()`` releases. Every failure
path ends in ``disable()``; implementations make it idempotent and best-effort
(it must not raise while the device is already gone).

Units are SI at this boundary: wheel angles in rad, wheel rates in rad/s.
Conversions to motor units happen inside each driver.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass, field


@dataclass
class WheelState:
    """Measured state of both wheels at ``stamp_ns``.

    position: (left, right) accumulated wheel angle, rad (unwrapped).
    velocity: (left, right) wheel rate, rad/s.
    faults: human-readable fault descriptions; empty when healthy.
    """

    stamp_ns: int
    position: tuple[float, float]
    velocity: tuple[float, float]
    faults: tuple[str, ...] = ()
    enabled: bool = False
    extra: dict = field(default_factory=dict)


class DriveError(RuntimeError):
    """The wheel drive failed: bus lost, device missing, hardware fault."""


class WheelDrive(abc.ABC):
    name: str = "drive"

    @abc.abstractmethod
    def connect(self) -> None:
        """Open and configure the device; wheels stay unpowered."""

    @abc.abstractmethod
    def enable(self) -> None:
        """Power the wheels; commands are accepted from now on."""

    @abc.abstractmethod
    def write(self, left: float, right: float) -> None:
        """Command wheel rates (rad/s). Raises DriveError if the bus is lost."""

    @abc.abstractmethod
    def read(self) -> WheelState:
        """Latest measured wheel state. Raises DriveError if the bus is lost."""

    @abc.abstractmethod
    def disable(self) -> None:
        """Command zero and remove power. Idempotent, never raises."""

    @abc.abstractmethod
    def close(self) -> None:
        """Disable and release the device. Idempotent, never raises."""

    def clear_faults(self) -> None:
        """Explicit operator action (e.g. Dynamixel REBOOT). Default: nothing to clear."""

    def __enter__(self) -> "WheelDrive":
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()
