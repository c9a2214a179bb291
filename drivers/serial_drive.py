"""What the wheel drives behind a USB serial device (Dynamixel, ODrive) share.

Options from the ``drive`` section, wheel signs, and the policy when the device
goes away: a lost device is closed and the drive goes to ERROR with a
``BUS_LOST`` fault (the device's own watchdog stops the wheels); ``reconnect()``
(and ``read()``, for a caller that only reads) looks for it again every
``reconnect_interval_s`` once its path is back and repeats the safe bring-up;
repeated missed reads become a fault. The protocol, bring-up and per-cycle I/O
stay in each driver.
"""
from __future__ import annotations

import abc
import os
from typing import Any, Optional

from pydantic import BaseModel

from vbnav.drivers.clock import MonotonicClock
from vbnav.drivers.wheels import DriveError, DriveFault, DriveState, FaultKind, WheelDrive, WheelState


def require_two_wheels(options: BaseModel, left: str, right: str, advice: str) -> BaseModel:
    """An ``Options`` validator's check that the two wheels are two devices: the same servo id (or ODrive
    axis) for both would fail only later, as one of them "not answering". Names both fields."""
    if getattr(options, left) == getattr(options, right):
        raise ValueError(f"{left} and {right} are both {getattr(options, left)}: {advice}")
    return options


class SerialWheelDrive(WheelDrive):
    """Base of the serial wheel drives. ``Options`` must have ``port``, ``max_missed_reads`` and
    ``reconnect_interval_s``."""

    Options: type[BaseModel]
    device_name = "device"  # the device in messages: "<device_name> <port> lost ..."
    can_reconnect = True

    def __init__(self, cfg: Any = None, clock=None, *, options: Optional[BaseModel] = None,
                 invert_left: Optional[bool] = None, invert_right: Optional[bool] = None):
        super().__init__()
        drive_cfg = getattr(cfg, "drive", None)
        # the configuration file the drive was built from (control.config.Config.source), for the commands a
        # message tells the user to run; None when built from options alone
        self.config_source: Optional[str] = getattr(cfg, "source", None)
        if options is None:
            options = self.Options.model_validate(drive_cfg.options if drive_cfg is not None else {})
        self.opt = options
        self.clock = clock or MonotonicClock()
        inv_l = invert_left if invert_left is not None else bool(getattr(drive_cfg, "invert_left", False))
        inv_r = invert_right if invert_right is not None else bool(getattr(drive_cfg, "invert_right", False))
        self.signs = (-1 if inv_l else 1, -1 if inv_r else 1)
        self._missed_reads = 0
        self._next_reconnect_ns = 0
        self._measured = WheelState(self.clock.now_ns(), (0.0, 0.0), (0.0, 0.0))

    @property
    def serial_port(self) -> Optional[str]:
        return self.opt.port

    @classmethod
    def from_config(cls, cfg, clock, options=None):
        """As the runtime's factory builds drives: the robot config, its clock, the validated options."""
        return cls(cfg, clock, options=options)

    # -- what each device does -------------------------------------------------------------
    @abc.abstractmethod
    def _device_open(self) -> bool:
        """The serial device is open (it is closed when lost)."""

    def _reachable(self) -> bool:
        return self._device_open()

    @abc.abstractmethod
    def _watchdog_note(self) -> str:
        """What stops the wheels while the host cannot reach them (said when the device is lost)."""

    # -- reading and reconnecting ------------------------------------------------------------
    def _check_device(self) -> None:
        """Before a read: a lost device is looked for again (``reconnect``); DriveError while it is not back."""
        if self._device_open():
            return
        lost = self.state is DriveState.ERROR and all(f.kind.reconnectable for f in self.faults)
        if not lost:
            raise DriveError(f"{self.drive_name} on {self.opt.port} is not usable: {self._fault_text()}")
        if self.reconnect():
            return
        if self._port_present() and self.reconnect_note:
            raise DriveError(f"{self.device_name} {self.opt.port} is back but its bring-up failed: "
                             f"{self.reconnect_note}; trying again every {self.opt.reconnect_interval_s:g} s")
        raise DriveError(f"{self.device_name} {self.opt.port} is gone; read() and reconnect() look for it "
                         f"every {self.opt.reconnect_interval_s:g} s")

    def _reconnect(self) -> bool:
        now = self.clock.now_ns()
        if now < self._next_reconnect_ns or not self._port_present():
            return False
        self._next_reconnect_ns = now + int(self.opt.reconnect_interval_s * 1e9)
        self._missed_reads = 0
        self._release()        # a silent motor or an expired watchdog leaves the port open: start afresh
        try:
            self._configure()
        except DriveError:
            self._stop_wheels()
            self._release()
            raise
        return True

    # -- failure handling --------------------------------------------------------------------
    def _port_present(self) -> bool:
        return os.path.exists(self.opt.port)

    def _missed_read(self, fault: DriveFault) -> None:
        """One read got no usable answer; the state is held until ``max_missed_reads`` in a row."""
        self._missed_reads += 1
        if self._missed_reads >= self.opt.max_missed_reads:
            self._fault(fault)

    def _lost(self, exc: BaseException):
        """The device went away: closed, ERROR with a BUS_LOST fault until it is back; raises DriveError."""
        self._release()
        self._next_reconnect_ns = self.clock.now_ns() + int(self.opt.reconnect_interval_s * 1e9)
        fault = DriveFault(FaultKind.BUS_LOST, f"{self.device_name} {self.opt.port}",
                           f"{self.device_name} {self.opt.port} lost ({type(exc).__name__}: {exc}); "
                           f"{self._watchdog_note()}")
        self._faults.clear()
        self._record_fault(fault)
        raise DriveError(fault.message) from exc
