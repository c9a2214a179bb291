"""Differential wheel drive interface: lifecycle states, fault kinds, the measured state.

Lifecycle after ros2_control's hardware components, enforced here and only here
(``WheelDrive``'s public methods; a driver implements the ``_``-hooks)::

    UNCONFIGURED --connect()--> INACTIVE --enable()--> ACTIVE
                                INACTIVE <--disable()-- ACTIVE
    any fault ------------------------------------------> ERROR
    ERROR --reconnect() (after a lost bus)---------------> INACTIVE
    ERROR --clear_faults() (operator action)-------------> INACTIVE
    any --close()----------------------------------------> FINALIZED (terminal)

- UNCONFIGURED: built, device not opened.
- INACTIVE: device open and configured (the safe bring-up ran), wheels unpowered.
- ACTIVE: wheels powered; ``write()`` is accepted only here.
- ERROR: a fault (``faults`` says which): the drive stopped every wheel it could
  still reach; where it cannot (bus gone), the device's own watchdog does.
- FINALIZED: released.

``disable()`` and ``close()`` never raise (every failure path ends in them,
also when the device is already gone).

Units are SI at this boundary: wheel angles in rad, wheel rates in rad/s.
Conversions to motor units happen inside each driver.
"""
from __future__ import annotations

import abc
import enum
import math
import threading
from dataclasses import dataclass, field
from typing import Optional


class DriveState(enum.Enum):
    UNCONFIGURED = "unconfigured"
    INACTIVE = "inactive"
    ACTIVE = "active"
    FINALIZED = "finalized"
    ERROR = "error"


class FaultKind(enum.Enum):
    """What a driver detected. The device and the details are in the ``DriveFault``."""

    BUS_LOST = "bus_lost"              # the adapter / device path went away (USB unplugged, device reset)
    NO_REPLY = "no_reply"              # the device is there but a motor does not answer
    CORRUPT_REPLY = "corrupt_reply"    # answers with a bad CRC / checksum, truncated or unparsable
    SEND_FAILED = "send_failed"        # a command packet could not be sent on the bus
    HARDWARE_ERROR = "hardware_error"  # the device reports an error: Dynamixel Hardware Error Status bits
    #                                    (input voltage, overheating, encoder, electrical shock, overload),
    #                                    ODrive axis/motor/encoder/controller error words
    WATCHDOG = "watchdog"              # the device's command watchdog expired: the host was silent too long
    SETUP = "setup"                    # the device refused the bring-up (a register write, closed loop)

    @property
    def reconnectable(self) -> bool:
        """A reconnect (the safe bring-up again) is the remedy: nothing is wrong with the device itself. The
        device went away (``BUS_LOST``), stopped answering for longer than its missed-read allowance
        (``NO_REPLY``: a servo's power or cable), or stopped its wheels because the host was silent for its
        watchdog time (``WATCHDOG``: a frozen process); the bring-up re-arms it, unpowered, and the robot
        waits for an operator's resume."""
        return self in (FaultKind.BUS_LOST, FaultKind.NO_REPLY, FaultKind.WATCHDOG)


@dataclass(frozen=True)
class DriveFault:
    """One fault: its kind, the part that has it ("servo 2 (right)", "axis1 (right)", "adapter
    /dev/ttyUSB0"), and the full sentence for people (it names the device too, and what stops the wheels
    or what clears the fault)."""

    kind: FaultKind
    device: str
    message: str

    def __str__(self) -> str:
        return self.message

    def as_dict(self) -> dict:
        return {"kind": self.kind.value, "device": self.device, "message": self.message}


@dataclass
class WheelState:
    """Measured state of both wheels at ``stamp_ns``.

    position: (left, right) accumulated wheel angle, rad (unwrapped).
    velocity: (left, right) wheel rate, rad/s; NaN when not measured (the drive is unreachable).
    faults: the drive's active faults; empty when healthy.
    drive_state: the drive's lifecycle state when this was measured.
    """

    stamp_ns: int
    position: tuple[float, float]
    velocity: tuple[float, float]
    faults: tuple[DriveFault, ...] = ()
    drive_state: DriveState = DriveState.INACTIVE
    extra: dict = field(default_factory=dict)

    @property
    def enabled(self) -> bool:
        return self.drive_state is DriveState.ACTIVE


class DriveError(RuntimeError):
    """The wheel drive failed or refused: bus lost, device missing, hardware fault, a call its state forbids.
    When it is a fault, the drive is in ERROR and ``drive.faults`` says which."""


class WheelDrive(abc.ABC):
    """A differential wheel drive. The lifecycle is this class's; a driver implements the hooks."""

    name: str = "drive"              # the registry name
    drive_name: str = "wheel drive"  # the drive in messages: "<drive_name> faulted: ..."
    # Whether ``reconnect`` can ever succeed: a serial drive looks for its device again; a drive that
    # cannot come back leaves a lost bus to end the run at once.
    can_reconnect: bool = False

    def __init__(self) -> None:
        self._state = DriveState.UNCONFIGURED
        self._faults: list[DriveFault] = []
        self._lock = threading.RLock()   # lifecycle and I/O; a reconnect may run on another thread
        self.reconnect_note = ""         # why the last reconnect attempt failed ("" when none failed)
        # what the last disable() or close() could not stop (a motor that did not answer), None when it stopped
        # all (or an enable armed the motors since): they never raise, so this is where the caller learns that
        # only the device's watchdog is left
        self.stop_failure: Optional[str] = None
        # errors the bring-up at start-up found and cleared on its own (an ODrive's expired axis watchdog with
        # drive.options.clear_watchdog_error_at_start), one sentence each naming the device, the error and the
        # setting that allowed it: a run says each in an event
        self.watchdogs_cleared_at_start: list[str] = []

    # -- what a drive is in --------------------------------------------------------------
    @property
    def state(self) -> DriveState:
        return self._state

    @property
    def faults(self) -> tuple[DriveFault, ...]:
        return tuple(self._faults)

    @property
    def serial_port(self) -> Optional[str]:
        """The serial device the drive talks through (``vbnav doctor`` checks its access), or None."""
        return None

    @property
    def serial_latency_ms(self) -> Optional[float]:
        """The adapter latency timer the driver's timeouts assume, ms, or None when they assume none."""
        return None

    @property
    def watchdog(self) -> Optional[tuple[float, str]]:
        """(s, the setting that gives it): how long the device runs without a packet before it stops the wheels
        on its own, or None when it has no such watchdog. The loop feeds it once a cycle."""
        return None

    @property
    def wheel_speed_limit(self) -> Optional[tuple[float, str]]:
        """(rad/s, the setting that gives it): the speed at which the drive clips each wheel's command on its
        own, or None when it clips none (the runtime's kinematics keep within robot.max_wheel_speed)."""
        return None

    # -- the lifecycle (the only place that changes ``state``) -----------------------------
    def connect(self) -> None:
        """UNCONFIGURED -> INACTIVE: open the device and run the safe bring-up; wheels stay unpowered.
        A device that reports a fault at bring-up leaves the drive in ERROR (``clear_faults`` may help)."""
        with self._lock:
            self._require("connect", DriveState.UNCONFIGURED)
            self._bring_up_or_fail(self._configure)

    def enable(self) -> None:
        """INACTIVE -> ACTIVE: power the wheels at zero; commands are accepted from now on."""
        with self._lock:
            if self._state is DriveState.ACTIVE:
                return
            if self._state is DriveState.ERROR:
                raise DriveError(f"{self.drive_name} has faults, clear them first (clear_faults): {self._fault_text()}")
            self._require("enable", DriveState.INACTIVE)
            try:
                self._activate()
            except BaseException:
                # Whatever stopped the bring-up (a DriveError, or a driver's own bug), what it armed stops.
                self._stop_wheels()
                raise
            self._state = DriveState.ACTIVE
            self.stop_failure = None     # armed again: a stop not taken before is moot

    def disable(self) -> None:
        """ACTIVE -> INACTIVE: command zero and remove power. In any other state it only stops what it can
        reach. Idempotent, never raises."""
        with self._lock:
            if self._state in (DriveState.UNCONFIGURED, DriveState.FINALIZED):
                return
            # Released (a lost bus, a reconnect that met a device fault), the stop reaches nothing: its silence is
            # no confirmation of a stop not taken before, which stays said (a close reported it taken: "the drive
            # reported every motor stopped").
            if self._reachable():
                if self._state is not DriveState.ACTIVE and self.stop_failure:
                    self.stop_failure = self._stop_again()      # the runtime's resend of a stop not taken
                else:
                    self.stop_failure = self._stop_wheels()
            if self._state is DriveState.ACTIVE:
                self._state = DriveState.INACTIVE

    def close(self) -> None:
        """Any state -> FINALIZED: stop, then release the device. Idempotent, never raises."""
        with self._lock:
            if self._state is DriveState.FINALIZED:
                return
            if self._state is not DriveState.UNCONFIGURED:
                pending = self.stop_failure
                self.stop_failure = self._stop_wheels()
                if self.stop_failure is None and pending and not self._reachable():
                    # Released already (a reconnect that met a device fault): the stop reached nothing, and
                    # its silence is no confirmation of the stop not taken before.
                    self.stop_failure = f"{pending}; the device was already released, so the stop sent as the " \
                                        f"drive closed reached nothing"
            self._release()
            self._state = DriveState.FINALIZED

    def write(self, left: float, right: float) -> None:
        """Command wheel rates (rad/s); only while ACTIVE. A fault raises DriveError (state ERROR)."""
        with self._lock:
            if self._state is DriveState.ERROR:
                raise DriveError(f"{self.drive_name} faulted: {self._fault_text()}")
            if self._state is not DriveState.ACTIVE:
                raise DriveError(f"{self.drive_name} is not enabled (state {self._state.value})")
            if not (math.isfinite(left) and math.isfinite(right)):
                raise DriveError(f"{self.drive_name}: non-finite wheel command ({left}, {right})")
            self._write(left, right)

    def read(self) -> WheelState:
        """Latest measured wheel state (INACTIVE, ACTIVE, and ERROR where the device still answers).
        A fault raises DriveError once (state ERROR); later reads list it in ``faults``."""
        with self._lock:
            if self._state in (DriveState.UNCONFIGURED, DriveState.FINALIZED):
                raise DriveError(f"{self.drive_name} is not connected (state {self._state.value})")
            return self._read()

    def reconnect(self) -> bool:
        """ERROR -> INACTIVE after a lost bus (every fault ``reconnectable``): one attempt, when the driver
        deems it due, at the same safe bring-up as ``connect``. True once INACTIVE; False while the device
        is not back. Raises DriveError when the device is back but faulted (the faults say why: waiting
        longer will not help) or when the faults are not a lost bus."""
        with self._lock:
            if self._state is DriveState.INACTIVE:
                return True
            if self._state is not DriveState.ERROR:
                raise DriveError(f"{self.drive_name}: nothing to reconnect (state {self._state.value})")
            if not all(f.kind.reconnectable for f in self._faults):
                raise DriveError(f"{self.drive_name}: not a lost bus, needs clear_faults: {self._fault_text()}")
            try:
                back = self._reconnect()
            except DriveError as exc:
                self.reconnect_note = str(exc)
                device_faults = [f for f in self._faults if not f.kind.reconnectable]
                if device_faults:        # the bus is back, the device is not well: that is the fault now
                    self._faults = device_faults
                    raise
                return False             # not back yet (or lost again during the attempt)
            if back:
                self.reconnect_note = ""
                self._faults.clear()
                self._state = DriveState.INACTIVE
            return back

    def clear_faults(self) -> None:
        """Explicit operator action (Dynamixel REBOOT, ODrive ``sc``), then the bring-up again: ERROR (or a
        drive whose connect failed on a device fault) -> INACTIVE. Nothing to do while ACTIVE."""
        with self._lock:
            if self._state is DriveState.ACTIVE:
                return
            self._require("clear_faults", DriveState.ERROR, DriveState.INACTIVE, DriveState.UNCONFIGURED)
            self._bring_up_or_fail(self._clear_faults)

    def __enter__(self) -> "WheelDrive":
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- what a driver implements -----------------------------------------------------------
    @abc.abstractmethod
    def _configure(self) -> None:
        """Open the device and run the safe bring-up (torque off, mode, limits, watchdog). Raises DriveError;
        a fault the device reports is recorded with ``_record_fault`` before raising."""

    @abc.abstractmethod
    def _activate(self) -> None:
        """Zero the goals, arm the watchdog, power the wheels. Raises DriveError."""

    @abc.abstractmethod
    def _write(self, left: float, right: float) -> None:
        """Send finite wheel rates (rad/s). A fault goes through ``_fault``."""

    @abc.abstractmethod
    def _read(self) -> WheelState:
        """Measure the wheels. A fault goes through ``_fault``."""

    @abc.abstractmethod
    def _stop_wheels(self) -> Optional[str]:
        """Command zero and remove power on whatever is still reachable; never raises. Returns what it could
        not stop, as a message naming the motor (None when every one took the stop)."""

    def _stop_again(self) -> Optional[str]:
        """A stop some motor did not take (``stop_failure`` set), sent again from the control loop: as
        ``_stop_wheels``. A driver whose read-back waits (the ODrive's) reads back the stop sent before instead
        and sends this one without waiting for it, so the loop's cycle is not made late."""
        return self._stop_wheels()

    def _reachable(self) -> bool:
        """Whether a stop sent now can reach the motors (the device is open). Default: always."""
        return True

    @abc.abstractmethod
    def _release(self) -> None:
        """Release the device; never raises."""

    def _reconnect(self) -> bool:
        """One reconnect attempt when due (see ``reconnect``). Default: this drive cannot come back."""
        return False

    def _clear_faults(self) -> None:
        """The operator's clearing action plus the bring-up. Default: the bring-up again."""
        if self._state is DriveState.ERROR:
            self._release()
        self._configure()

    # -- for drivers: recording faults ----------------------------------------------------------
    def _record_fault(self, fault: DriveFault) -> bool:
        """Note a fault (state ERROR). False if it was already noted."""
        if fault in self._faults:
            return False
        self._faults.append(fault)
        self._state = DriveState.ERROR
        return True

    def _fault(self, *faults: DriveFault, text: str = "") -> None:
        """Record, stop everything reachable, raise DriveError naming them. Faults already reported are not
        raised again: ``read()`` then keeps returning states that list them, so the operator sees them until
        cleared."""
        new = [f for f in faults if self._record_fault(f)]
        if not new:
            return
        self._stop_wheels()
        raise DriveError(text or f"{self.drive_name} fault: {'; '.join(str(f) for f in new)}")

    def _fault_text(self) -> str:
        return "; ".join(str(f) for f in self._faults) or "none recorded"

    # -- the transitions' plumbing ----------------------------------------------------------------
    def _require(self, action: str, *allowed: DriveState) -> None:
        if self._state not in allowed:
            raise DriveError(f"{self.drive_name}: cannot {action} in state {self._state.value} "
                             f"(allowed: {', '.join(s.value for s in allowed)})")

    def _bring_up_or_fail(self, bring_up) -> None:
        """Run a bring-up: INACTIVE with no faults when it completes; on DriveError ERROR if the device
        reported a fault, else back to UNCONFIGURED (the device is released)."""
        self._faults.clear()
        try:
            bring_up()
        except DriveError:
            self._stop_wheels()
            if not self._faults:
                self._release()
                self._state = DriveState.UNCONFIGURED
            else:
                self._state = DriveState.ERROR
            raise
        self._state = DriveState.INACTIVE
