"""Shared setup of the hardware-in-the-loop tests: a real driver, over a pty, to a device emulator
whose motors drive the simulated base."""
from __future__ import annotations

from emulator_coupling import PhysicsCoupling  # same directory

from vbnav.control.config import CONFIG_DIR, load_config
from vbnav.control.controllers.manual import ScriptedController
from vbnav.control.runtime.runtime import Runtime
from vbnav.drivers.clock import MonotonicClock
from vbnav.drivers.sim.base import BaseParams, DiffDrivePhysics


def physics_for(cfg) -> DiffDrivePhysics:
    """The simulated base with the robot's geometry; no slip, so odometry can match it closely."""
    r = cfg.robot
    return DiffDrivePhysics(BaseParams(wheel_radius=r.wheel_radius, wheel_separation=r.wheel_separation,
                                       motor_time_constant_s=0.03, wheel_accel_limit=40.0,
                                       max_wheel_speed=r.max_wheel_speed * 1.2, slip_std=0.0), seed=1)


def run_route(config_name: str, make_emulator, drive_options: dict, script, channels):
    """Run ``script`` with the runtime on the real clock. Returns (result, runtime, coupling)."""
    clock = MonotonicClock()
    base_cfg = load_config(CONFIG_DIR / config_name)
    coupling = PhysicsCoupling(physics_for(base_cfg), channels, clock)
    emulator = make_emulator(coupling)
    path = emulator.start()
    try:
        cfg = load_config(CONFIG_DIR / config_name,
                          overrides={"drive": {"options": {"port": path, **drive_options}},
                                     "controller": {"kind": "scripted", "script": script},
                                     # these tests check odometry against the simulator, not timing: a
                                     # loaded CI machine must not trip the missed-deadline stop
                                     "loop": {"max_missed_streak": 1000, "stall_periods": 1000}})
        from vbnav.control.runtime.factory import make_drive
        drive = make_drive(cfg, clock)
        rt = Runtime(cfg, drive, ScriptedController(cfg.controller.script), clock)
        result = rt.run(duration_s=sum(s[2] for s in script) + 2.0)
    finally:
        emulator.stop()
    return result, rt, coupling
