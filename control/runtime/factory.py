"""The robot a configuration describes, built in one place: clock, drive, camera, vision pipeline.

Simulation and hardware differ only in the drivers the configuration names. With
the simulated drivers the factory also builds the simulated world (what the
camera renders) and places the robot at ``sim.start_pose``; the simulator's true
pose is then available to measure with (never to steer).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from vbnav.control.config import Config, ConfigError, validate_driver_options
from vbnav.control.runtime.pipeline import VisionPipeline
from vbnav.drivers import registry
from vbnav.drivers.clock import Clock, MonotonicClock, SimClock
from vbnav.vision.geometry import Pose2


@dataclass
class Robot:
    """What ``make_robot`` builds. ``world`` and ``start`` are set for the simulated drive only."""

    clock: Clock
    drive: object
    camera: Optional[object] = None
    pipeline: Optional[VisionPipeline] = None
    world: Optional[object] = None        # drivers.sim.world.World the simulated camera renders
    start: Optional[Pose2] = None         # the simulated robot's true start pose in the world

    def true_pose(self) -> Optional[Pose2]:
        """The simulator's pose relative to the start (the odometry's frame); None on hardware."""
        if self.start is None:
            return None
        return self.start.between(self.drive.true_pose)


def noise_seed(cfg: Config, run: int = 0) -> int:
    """Seed of the simulated motor and image noise of run ``run`` on seed ``sim.seed``: every run of a
    scenario (the demo's teach and each repeat) draws its own noise, and each is reproducible."""
    return cfg.sim.seed * 1000 + run


def make_clock(cfg: Config) -> Clock:
    if cfg.on_simulated_clock():
        return SimClock()
    return MonotonicClock(spin_ns=cfg.loop.spin_us * 1000)


def make_drive(cfg: Config, clock, options=None, run: int = 0):
    opts = options or validate_driver_options(cfg, cfg.source or "<config>")["drive"]
    cls = registry.load(registry.DRIVES, cfg.drive.driver)
    if cfg.drive.driver == "sim":
        return cls.from_config(cfg, clock, opts, seed=noise_seed(cfg, run), start=cfg.sim.start())
    return cls.from_config(cfg, clock, opts)


def make_world(cfg: Config):
    """The simulated world named by ``sim.world`` (its textures seeded by ``sim.seed``)."""
    from vbnav.drivers.sim.world import World
    return World.by_name(cfg.sim.world, cfg.sim.seed)


def make_camera(cfg: Config, clock, drive=None, options=None, world=None, run: int = 0):
    """The configured camera. The simulated camera renders ``world`` from the simulated drive's true pose."""
    opts = options or validate_driver_options(cfg, cfg.source or "<config>")["camera"]
    cls = registry.load(registry.CAMERAS, cfg.camera.driver)
    if cfg.camera.driver == "sim":
        from vbnav.drivers.sim.base import SimDiffDrive
        if not isinstance(drive, SimDiffDrive):
            raise ConfigError(f"{cfg.source or '<config>'}: camera.driver 'sim' needs drive.driver 'sim' (it renders "
                              f"the simulated room from the simulated robot's pose), drive.driver is "
                              f"{cfg.drive.driver!r}: set camera.driver to the robot's camera")
        return cls.from_config(cfg, clock, opts, pose_fn=lambda: drive.true_pose,
                               world=world if world is not None else make_world(cfg), seed=noise_seed(cfg, run))
    return cls.from_config(cfg, clock, opts)


def make_pipeline(cfg: Config, clock, camera, stages) -> VisionPipeline:
    """A pipeline with ``stages`` plus the safety stages the configuration enables (obstacle zones)."""
    from vbnav.control.stages.obstacles import make_obstacle_stage

    stages = list(stages)
    if not any(s.kind == "obstacles" for s in stages):
        obstacle_stage = make_obstacle_stage(cfg)
        if obstacle_stage is not None:
            stages.append(obstacle_stage)
    inline = clock.simulated
    return VisionPipeline(camera, stages, clock, inline=inline,
                          latency_s=cfg.sim.vision_latency_s if inline else 0.0, focal_px=cfg.camera.fx)


def check_wheel_speed_limit(cfg: Config, drive) -> None:
    """Raise ConfigError when the drive clips a wheel below robot.max_wheel_speed: the kinematics scale both
    wheels together within that limit (the curvature kept), a drive clipping the faster one alone bends the
    path."""
    own = drive.wheel_speed_limit
    if own is not None and cfg.robot.max_wheel_speed > own[0] * (1 + 1e-9):
        raise ConfigError(f"{cfg.source or '<config>'}: robot.max_wheel_speed {cfg.robot.max_wheel_speed:g} rad/s is "
                          f"above what the drive lets a wheel turn, {own[1]} ({own[0]:.3f} rad/s): it would clip the "
                          f"faster wheel alone and bend the robot's path; lower robot.max_wheel_speed (and "
                          f"max_linear_speed) or raise the drive's limit")


def check_drive_watchdog(cfg: Config, drive) -> None:
    """Raise ConfigError when the drive's own watchdog (it stops the wheels after that long without a packet) is
    shorter than two loop periods: the loop writes once a cycle, so it would expire between two cycles, or at
    the first late one, and hold the robot (drive_lost) for good."""
    own = drive.watchdog
    period = 1.0 / cfg.loop.rate_hz
    if own is not None and own[0] < 2 * period - 1e-9:
        raise ConfigError(f"{cfg.source or '<config>'}: {own[1]} {own[0]:g} s is below two loop periods, "
                          f"{2 * period:g} s (loop.rate_hz {cfg.loop.rate_hz:g} Hz): the loop writes once a cycle, "
                          f"and the drive would stop the wheels between two cycles or at the first late one (raise "
                          f"{own[1]}, or loop.rate_hz)")


def check_devices(cfg: Config) -> None:
    """Raise what ``make_robot`` raises of this configuration before any device opens: the drive and the camera
    built from it (not connected: nothing is opened or moved) refuse their settings, and the drive's own wheel
    speed limit is checked. What 'vbnav config check' calls "valid" is what a run takes."""
    clock = make_clock(cfg)
    opts = validate_driver_options(cfg, cfg.source or "<config>")
    drive = make_drive(cfg, clock, opts["drive"])
    make_camera(cfg, clock, drive, opts["camera"])
    check_wheel_speed_limit(cfg, drive)
    check_drive_watchdog(cfg, drive)


def make_robot(cfg: Config, stages=(), with_camera: Optional[bool] = None, run: int = 0) -> Robot:
    """The robot of a configuration, with a pipeline running ``stages`` (plus the enabled safety stages).

    with_camera: default, if stages or the obstacle stop need it. run: the index of this run in a scenario
    of several runs (simulated drivers only, see ``noise_seed``).
    """
    clock = make_clock(cfg)
    opts = validate_driver_options(cfg, cfg.source or "<config>")
    drive = make_drive(cfg, clock, opts["drive"], run)
    simulated = cfg.drive.driver == "sim"
    want_camera = (bool(stages) or cfg.obstacles.enabled) if with_camera is None else with_camera
    world = make_world(cfg) if want_camera and cfg.camera.driver == "sim" else None
    camera = make_camera(cfg, clock, drive, opts["camera"], world, run) if want_camera else None
    pipeline = make_pipeline(cfg, clock, camera, list(stages)) if camera is not None else None
    check_wheel_speed_limit(cfg, drive)
    check_drive_watchdog(cfg, drive)
    return Robot(clock, drive, camera, pipeline, world, cfg.sim.start() if simulated else None)
