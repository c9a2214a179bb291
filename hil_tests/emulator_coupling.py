"""Couples a device emulator's motors to the simulated base, in real time.

The emulators (Dynamixel bus, ODrive) step their motors every millisecond; with
this coupling each step sends the motor's driven rate to ``DiffDrivePhysics``
(sim_base) and reads the wheel's angle and rate back from it. So the real driver,
through the real protocol, moves the simulated robot, whose true pose the
hardware-in-the-loop tests compare with the runtime's odometry.
"""
from __future__ import annotations

import threading

from vbnav.drivers.clock import MonotonicClock
from vbnav.drivers.sim.base import DiffDrivePhysics


class PhysicsCoupling:
    """``channels`` maps a motor id (servo id or axis number) to (wheel index 0=left/1=right, sign).

    The sign is how the motor is mounted: a mirrored right motor turns backwards
    for the robot to go forwards, and the driver's ``invert_right`` undoes it.
    """

    def __init__(self, physics: DiffDrivePhysics, channels: dict[int, tuple[int, int]], clock=None):
        self.physics = physics
        self.channels = dict(channels)
        self.clock = clock or MonotonicClock()
        self.lock = threading.Lock()
        physics.time_ns = self.clock.now_ns()
        physics.powered = True  # power is the motor's business: a motor without torque commands 0

    def command(self, motor_id: int, rate_rad_s: float) -> None:
        wheel, sign = self.channels[motor_id]
        with self.lock:
            self.physics.advance_to(self.clock.now_ns())
            self.physics.command[wheel] = sign * rate_rad_s

    def measure(self, motor_id: int) -> tuple[float, float]:
        wheel, sign = self.channels[motor_id]
        with self.lock:
            self.physics.advance_to(self.clock.now_ns())
            return sign * float(self.physics.angle[wheel]), sign * float(self.physics.rate[wheel])

    @property
    def true_pose(self):
        with self.lock:
            self.physics.advance_to(self.clock.now_ns())
            return self.physics.pose
