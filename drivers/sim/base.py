"""Simulated differential-drive base.

``DiffDrivePhysics`` is the robot: two motors with first-order lag and an
acceleration (torque) limit, wheel slip noise on the ground contact, encoders
quantised to ticks, and the true pose. It is stepped in fixed small substeps,
so results do not depend on how often it is read.

``SimDiffDrive`` is the WheelDrive driver for it, on a clock: reading or
writing first advances the physics to the clock's time. With a ``SimClock`` it
runs faster than real time and is deterministic for a seed; with the
``MonotonicClock`` it runs in real time. Device emulators (Dynamixel, ODrive)
couple to the same ``DiffDrivePhysics``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
from pydantic import ConfigDict, Field, model_validator
from vbnav.drivers.plain_values import PlainValues

from vbnav.drivers.wheels import DriveError, DriveFault, DriveState, FaultKind, WheelDrive, WheelState
from vbnav.vision.geometry import Pose2, arc_step

SUBSTEP_NS = 1_000_000  # 1 ms physics step


@dataclass
class BaseParams:
    wheel_radius: float = 0.05
    wheel_separation: float = 0.30
    motor_time_constant_s: float = 0.05
    wheel_accel_limit: float = 40.0       # rad/s^2
    max_wheel_speed: float = 25.0         # rad/s, motor saturation
    encoder_ticks_per_rev: int = 4096
    slip_std: float = 0.002               # m per sqrt(m) of wheel travel (random walk)

    @classmethod
    def from_config(cls, cfg) -> "BaseParams":
        s, r = cfg.sim, cfg.robot
        return cls(r.wheel_radius, r.wheel_separation, s.motor_time_constant_s, s.wheel_accel_limit,
                   r.max_wheel_speed * 1.25, s.encoder_ticks_per_rev, s.slip_std)


class DiffDrivePhysics:
    """Ground-truth dynamics of a differential-drive robot. Not thread-safe by itself."""

    def __init__(self, params: BaseParams, seed: int = 0, pose: Pose2 = Pose2()):
        self.p = params
        self.rng = np.random.default_rng(seed)
        self.pose = pose
        self.command = [0.0, 0.0]         # commanded wheel rates, rad/s
        self.rate = [0.0, 0.0]            # actual motor rates, rad/s
        self.angle = [0.0, 0.0]           # true motor shaft angles, rad
        self._noise_buf: list[float] = []
        self.powered = False
        self.time_ns: int | None = None   # set by the first advance_to: physics starts when time does

    def step(self, dt: float) -> None:
        # Scalar math: two wheels are too few for numpy to pay off (this runs 1000 times per simulated second).
        p = self.p
        tau = max(p.motor_time_constant_s, dt)
        amax = p.wheel_accel_limit
        vmax = p.max_wheel_speed
        travel = [0.0, 0.0]
        for i in (0, 1):
            target = max(-vmax, min(vmax, self.command[i])) if self.powered else 0.0
            rate = self.rate[i]
            accel = max(-amax, min(amax, (target - rate) / tau))
            new_rate = rate + accel * dt
            dphi = 0.5 * (rate + new_rate) * dt
            self.rate[i] = new_rate
            self.angle[i] += dphi
            t = dphi * p.wheel_radius
            if p.slip_std > 0:
                # Slip noise whose std per step scales with sqrt(travel): the error is a random walk in
                # distance (slip_std metres per sqrt(metre) of travel), independent of the step size.
                t += self._noise() * p.slip_std * math.sqrt(abs(t))
            travel[i] = t
        self.pose = arc_step(self.pose, 0.5 * (travel[0] + travel[1]),
                             (travel[0] - travel[1]) / p.wheel_separation)

    def _noise(self) -> float:
        if not self._noise_buf:
            self._noise_buf = self.rng.normal(0.0, 1.0, 4096).tolist()
        return self._noise_buf.pop()

    def advance_to(self, t_ns: int) -> None:
        if self.time_ns is None:
            self.time_ns = int(t_ns)
            return
        while self.time_ns + SUBSTEP_NS <= t_ns:
            self.step(SUBSTEP_NS * 1e-9)
            self.time_ns += SUBSTEP_NS
        if t_ns > self.time_ns:
            self.step((t_ns - self.time_ns) * 1e-9)
            self.time_ns = t_ns

    def encoder_angles(self) -> tuple[float, float]:
        q = 2 * math.pi / self.p.encoder_ticks_per_rev
        return tuple(float(math.floor(a / q) * q) for a in self.angle)


class SimDiffDrive(WheelDrive):
    """WheelDrive on DiffDrivePhysics and a clock.

    Power follows the lifecycle: the motors are powered only while ACTIVE. A bus loss can be injected
    for tests (``options.fail_after_s``, and ``lost_for_s`` for it to come back): the motors lose power
    at once, as a device watchdog would stop them.
    """

    name = "sim"
    drive_name = "sim drive"

    class Options(PlainValues):
        model_config = ConfigDict(extra="forbid")
        fail_after_s: Optional[float] = Field(None, gt=0, description="testing: lose the bus after this time")
        lost_for_s: Optional[float] = Field(None, gt=0, description="testing: with fail_after_s, the bus comes "
                                            "back after this long (None: never)")

        @model_validator(mode="after")
        def _a_return_needs_a_loss(self):
            if self.lost_for_s is not None and self.fail_after_s is None:
                raise ValueError(f"lost_for_s: {self.lost_for_s:g} (the bus comes back) takes effect only with "
                                 f"fail_after_s (the bus is lost): set fail_after_s, or remove lost_for_s")
            return self

    def __init__(self, params: BaseParams, clock, seed: int = 0, start: Pose2 = Pose2(),
                 options: Optional["SimDiffDrive.Options"] = None):
        super().__init__()
        self.physics = DiffDrivePhysics(params, seed, start)
        self.physics.time_ns = clock.now_ns()
        self.clock = clock
        self.options = options or SimDiffDrive.Options()
        self._t0: Optional[int] = None
        self._lost_at: Optional[int] = None   # when the injected bus loss happened
        self.writes = 0

    @classmethod
    def from_config(cls, cfg, clock, options=None, seed: Optional[int] = None,
                    start: Optional[Pose2] = None) -> "SimDiffDrive":
        """seed: of the slip noise (default ``cfg.sim.seed``); start: the true start pose (default the origin)."""
        return cls(BaseParams.from_config(cfg), clock, seed=cfg.sim.seed if seed is None else seed,
                   start=start or Pose2(), options=options)

    @property
    def can_reconnect(self) -> bool:
        return self.options.lost_for_s is not None

    # -- lifecycle hooks (WheelDrive owns the states) ------------------------
    def _configure(self) -> None:
        self._t0 = self.clock.now_ns()
        self.physics.time_ns = self._t0

    def _activate(self) -> None:
        self._check_bus()
        self._advance()
        self.physics.command = [0.0, 0.0]
        self.physics.powered = True

    def _write(self, left: float, right: float) -> None:
        self._check_bus()
        self._advance()
        if self.physics.powered:
            self.physics.command = [float(left), float(right)]
        self.writes += 1

    def _read(self) -> WheelState:
        self._check_bus()
        self._advance()
        ph = self.physics
        return WheelState(ph.time_ns, ph.encoder_angles(), (float(ph.rate[0]), float(ph.rate[1])),
                          self.faults, self.state)

    def _stop_wheels(self) -> Optional[str]:
        if self._t0 is not None:
            self._advance()
        self.physics.command = [0.0, 0.0]
        self.physics.powered = False
        return None

    def _release(self) -> None:
        pass

    def _reconnect(self) -> bool:
        """The injected loss is over after ``lost_for_s``: the base is configured again (unpowered); the
        physics kept running meanwhile."""
        back_at = self._lost_at + int(self.options.lost_for_s * 1e9) if self.can_reconnect else None
        if back_at is None or self.clock.now_ns() < back_at:
            return False
        self._advance()
        return True

    # -- simulation access -------------------------------------------------
    @property
    def true_pose(self) -> Pose2:
        with self._lock:
            self._advance()
            return self.physics.pose

    def pose_at_now(self) -> Pose2:
        return self.true_pose

    @property
    def commanded(self) -> tuple[float, float]:
        return float(self.physics.command[0]), float(self.physics.command[1])

    def _advance(self) -> None:
        self.physics.advance_to(self.clock.now_ns())

    def _check_bus(self) -> None:
        """The injected bus loss (once): unpowered at once, state ERROR, DriveError."""
        if self._lost_at is not None:
            if self.state is DriveState.ERROR:
                raise DriveError("sim drive: the bus is lost (injected); not back yet")
            return
        fail_after = self.options.fail_after_s
        if fail_after is None or self._t0 is None:
            return
        now = self.clock.now_ns()
        if now - self._t0 > fail_after * 1e9:
            self._lost_at = now
            self._advance()
            self.physics.powered = False
            fault = DriveFault(FaultKind.BUS_LOST, "sim bus", "sim drive: bus lost (injected by "
                               "options.fail_after_s); the motors lost power")
            self._fault(fault, text=fault.message)
