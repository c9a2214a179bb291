"""What the wheel drives behind a USB serial device (Dynamixel, ODrive) share.

Options from the ``drive`` section, wheel signs, fault bookkeeping, and the
policy when the device goes away: a lost device marks the drive disconnected
and faulted (the device's own watchdog stops the wheels), ``read()`` looks for
it again every ``reconnect_interval_s`` once its path is back, and repeated
missed reads become a fault. The protocol, bring-up and per-cycle I/O stay in
each driver.
"""
from __future__ import annotations

import abc
import os
import threading
from typing import Any, Optional

from pydantic import BaseModel

from vbnav.drivers.clock import MonotonicClock
from vbnav.drivers.wheels import DriveError, WheelDrive, WheelState


class SerialWheelDrive(WheelDrive):
    """Base of the serial wheel drives. ``Options`` must have ``port``, ``max_missed_reads`` and
    ``reconnect_interval_s``."""

    Options: type[BaseModel]
    drive_name = "drive"  # the drive in messages: "<drive_name> faulted: ..."
    device_name = "device"  # the device in messages: "<device_name> <port> lost ..."

    def __init__(self, cfg: Any = None, clock=None, *, options: Optional[BaseModel] = None,
                 invert_left: Optional[bool] = None, invert_right: Optional[bool] = None):
        drive_cfg = getattr(cfg, "drive", None)
        if options is None:
            options = self.Options.model_validate(drive_cfg.options if drive_cfg is not None else {})
        self.opt = options
        self.clock = clock or MonotonicClock()
        inv_l = invert_left if invert_left is not None else bool(getattr(drive_cfg, "invert_left", False))
        inv_r = invert_right if invert_right is not None else bool(getattr(drive_cfg, "invert_right", False))
        self.signs = (-1 if inv_l else 1, -1 if inv_r else 1)
        self.faults: list[str] = []
        self._connected = False
        self._enabled = False
        self._lock = threading.RLock()
        self._missed_reads = 0
        self._next_reconnect_ns = 0
        self._state = WheelState(self.clock.now_ns(), (0.0, 0.0), (0.0, 0.0))

    @classmethod
    def from_config(cls, cfg, clock, options=None):
        """As the runtime's factory builds drives: the robot config, its clock, the validated options."""
        return cls(cfg, clock, options=options)

    @property
    def is_connected(self) -> bool:
        return self._connected

    def disable(self) -> None:
        with self._lock:
            self._enabled = False
            self._stop_wheels()

    def close(self) -> None:
        with self._lock:
            self.disable()
            self._close_device()
            self._connected = False

    # -- what each device does -------------------------------------------------------------
    @abc.abstractmethod
    def _stop_wheels(self) -> None:
        """Command zero and remove power on whatever is still reachable; never raises."""

    @abc.abstractmethod
    def _close_device(self) -> None:
        """Release the serial device; never raises."""

    @abc.abstractmethod
    def _watchdog_note(self) -> str:
        """What stops the wheels while the host cannot reach them (said when the device is lost)."""

    def _reconnect_failed(self, exc: DriveError) -> None:
        """A reconnect attempt failed with ``exc`` (the drive stays disconnected)."""

    # -- checks before commands ------------------------------------------------------------
    def _check_can_enable(self) -> None:
        if not self._connected:
            raise DriveError(f"{self.drive_name} on {self.opt.port} is not connected")
        if self.faults:
            raise DriveError(f"{self.drive_name} has faults, clear them first (clear_faults): "
                             f"{'; '.join(self.faults)}")

    def _check_can_write(self) -> None:
        if self.faults:
            raise DriveError(f"{self.drive_name} faulted: {'; '.join(self.faults)}")
        if not self._enabled:
            raise DriveError(f"{self.drive_name} is not enabled")

    def _ensure_connected(self) -> None:
        """Before a read: reconnect when it is time, else say why the device cannot be read."""
        if not self._connected:
            self._try_reconnect()
        if not self._connected:
            if self._port_present() and self.faults:
                raise DriveError(f"{self.device_name} {self.opt.port} is back but not usable: "
                                 f"{'; '.join(self.faults)}")
            raise DriveError(f"{self.device_name} {self.opt.port} is gone; waiting for it to come back")

    # -- failure handling --------------------------------------------------------------------
    def _port_present(self) -> bool:
        return os.path.exists(self.opt.port)

    def _missed_read(self, why: str) -> None:
        """One read got no usable answer; the state is held until ``max_missed_reads`` in a row."""
        self._missed_reads += 1
        if self._missed_reads >= self.opt.max_missed_reads:
            self._fault(why)

    def _lost(self, exc: BaseException):
        """The device went away: disconnected and faulted until it is back; raises DriveError."""
        self._enabled = False
        self._connected = False
        self._close_device()
        self._next_reconnect_ns = self.clock.now_ns() + int(self.opt.reconnect_interval_s * 1e9)
        msg = (f"{self.device_name} {self.opt.port} lost ({type(exc).__name__}: {exc}); "
               f"{self._watchdog_note()}; reconnecting when the device is back")
        self.faults = [msg]
        raise DriveError(msg) from exc

    def _fault(self, cause: str):
        """Record, stop everything reachable, raise. A fault already reported is not raised again:
        read() then keeps returning states that list it, so the operator sees it until cleared."""
        if cause in self.faults:
            return
        self.faults.append(cause)
        self._enabled = False
        self._stop_wheels()
        raise DriveError(f"{self.drive_name} fault: {cause}")

    def _try_reconnect(self) -> None:
        now = self.clock.now_ns()
        if now < self._next_reconnect_ns or not self._port_present():
            return
        self._next_reconnect_ns = now + int(self.opt.reconnect_interval_s * 1e9)
        try:
            self.faults = []
            self.connect()
        except DriveError as exc:
            self._connected = False
            self._reconnect_failed(exc)
