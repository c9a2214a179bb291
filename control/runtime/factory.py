"""Builds clocks, drivers and pipelines from a validated configuration."""
from __future__ import annotations

from typing import Optional

from vbnav.control.config import Config, validate_driver_options
from vbnav.control.runtime.pipeline import VisionPipeline
from vbnav.drivers import registry
from vbnav.drivers.clock import MonotonicClock, SimClock


def uses_sim_clock(cfg: Config) -> bool:
    """The simulated clock runs when everything is simulated and real time is not asked for."""
    return cfg.drive.driver == "sim" and cfg.camera.driver == "sim" and not cfg.sim.realtime


def make_clock(cfg: Config):
    if uses_sim_clock(cfg):
        return SimClock()
    return MonotonicClock(spin_ns=cfg.loop.spin_us * 1000)


def make_drive(cfg: Config, clock, options=None):
    opts = options or validate_driver_options(cfg, cfg.source or "<config>")["drive"]
    cls = registry.load(registry.DRIVES, cfg.drive.driver)
    return cls.from_config(cfg, clock, opts)


def make_camera(cfg: Config, clock, drive=None, options=None, world=None):
    """The configured camera. The simulated camera needs the simulated base (its true pose)."""
    opts = options or validate_driver_options(cfg, cfg.source or "<config>")["camera"]
    cls = registry.load(registry.CAMERAS, cfg.camera.driver)
    if cfg.camera.driver == "sim":
        from vbnav.drivers.sim.base import SimDiffDrive
        if not isinstance(drive, SimDiffDrive):
            raise ValueError("camera.driver 'sim' needs drive.driver 'sim' (it renders from the simulated pose)")
        return cls.from_config(cfg, clock, opts, pose_fn=lambda: drive.true_pose, world=world)
    return cls.from_config(cfg, clock, opts)


def make_pipeline(cfg: Config, clock, camera, stages) -> VisionPipeline:
    """A pipeline with ``stages`` plus the safety stages the configuration enables (obstacle zones)."""
    from vbnav.control.stages.obstacles import make_obstacle_stage

    stages = list(stages)
    if not any(s.kind == "obstacles" for s in stages):
        obstacle_stage = make_obstacle_stage(cfg)
        if obstacle_stage is not None:
            stages.append(obstacle_stage)
    inline = getattr(clock, "simulated", False)
    return VisionPipeline(camera, stages, clock, inline=inline,
                          latency_s=cfg.sim.vision_latency_s if inline else 0.0)


def make_robot(cfg: Config, stages=(), with_camera: Optional[bool] = None, world=None):
    """(clock, drive, pipeline) for a configuration. ``with_camera`` defaults to: if stages need it."""
    clock = make_clock(cfg)
    opts = validate_driver_options(cfg, cfg.source or "<config>")
    drive = make_drive(cfg, clock, opts["drive"])
    want_camera = (bool(stages) or cfg.obstacles.enabled) if with_camera is None else with_camera
    camera = make_camera(cfg, clock, drive, opts["camera"], world=world) if want_camera else None
    pipeline = make_pipeline(cfg, clock, camera, list(stages)) if camera is not None else None
    return clock, drive, pipeline
