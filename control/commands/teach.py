"""vbnav teach: record a route while the robot is driven."""
from __future__ import annotations

from pathlib import Path

from vbnav.control.commands._common import add_config_arg


def register(sub) -> None:
    p = sub.add_parser(
        "teach", help="record a route (keyframes) while the robot is driven",
        description="Record a route for 'vbnav repeat'. On the simulated robot the route is driven by a scripted "
                    "driver along the demo loop (20 m, four turns); on a robot you drive it by teleoperation "
                    "('vbnav send teleop V W' from another terminal, or any zenoh publisher on "
                    "vbnav/<robot>/cmd/teleop) and stop with Ctrl-C or 'vbnav send estop'. Every keyframe is "
                    "on disk (atomically) as soon as it is taken, so an interruption loses nothing recorded.")
    add_config_arg(p)
    p.add_argument("--out", required=True, metavar="PATH", help="route directory to create")
    p.add_argument("--overwrite", action="store_true", help="replace an existing route directory")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--record", default=None, metavar="FILE.mcap", help="record telemetry and images (MCAP)")
    p.set_defaults(func=run)


def run(args) -> int:
    from vbnav.control.config import load_config
    from vbnav.control.demo import demo_route, make_sim_robot, start_pose, teach_route
    from vbnav.control.controllers.path import PathFollower
    from vbnav.control.runtime.progress import ProgressPrinter

    cfg = load_config(args.config)
    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not args.overwrite:
        print(f"vbnav teach: {out} exists and is not empty (use --overwrite to replace it)")
        return 2
    printer = ProgressPrinter()
    if cfg.camera.driver == "sim" and cfg.drive.driver == "sim":
        from vbnav.drivers.sim.world import World
        path = demo_route()
        start = start_pose(path)
        robot = make_sim_robot(cfg, World.by_name(cfg.sim.world, cfg.sim.seed), start)
        with _sim_recorder(cfg, args) as recorder:
            result = teach_route(cfg, robot, PathFollower(path, 0.4, start=start), out, printer, args.duration,
                                 recorder=recorder)
    else:
        result = _teach_on_robot(cfg, out, printer, args)
    printer.done()
    print(f"teach ended: {result.reason} ({result.message}); {result.keyframes} keyframes in {out}")
    return 0 if result.keyframes >= 2 and result.reason in ("finished", "duration", "signal", "stopped") else 1


def _teach_on_robot(cfg, out, printer, args):
    """Teleoperated teaching with the configured drivers (real time)."""
    from vbnav.control.demo import TeachResult, RunTrace
    from vbnav.control.runtime.factory import make_robot
    from vbnav.control.controllers.manual import TeleopController
    from vbnav.control.route import RouteWriter
    from vbnav.control.runtime.runtime import Runtime
    from vbnav.control.stages.teach import TeachStage
    import numpy as np

    model, mount = cfg.camera.to_model(), cfg.camera.mount.to_mount()
    stage = TeachStage(model, mount, cfg.vbc)
    clock, drive, pipeline = make_robot(cfg, [stage])
    with RouteWriter(out, cfg.robot.name, model, mount, overwrite=True) as writer:
        pipeline.frame_listeners.append(lambda f, r: [writer.append(kf) for kf in stage.pop_keyframes()])
        rt = Runtime(cfg, drive, TeleopController(cfg.safety.command_timeout_s), clock, pipeline)
        link = _attach_telemetry(cfg, rt, args)
        result = None
        try:
            result = rt.run(args.duration, lambda r: printer(f"teach: {stage.n_keyframes} keyframes, "
                                                             f"{r.odometry.distance:.1f} m"))
        finally:
            link.close(result)
        stage.finish()
        for kf in stage.pop_keyframes():
            writer.append(kf)
    return TeachResult(RunTrace(), stage.n_keyframes, np.zeros((0, 2)), result.reason, result.message,
                       result.timing)


def _attach_telemetry(cfg, rt, args):
    """Telemetry, network commands and --record for a run on the robot; close it with ``link.close(result)``."""
    from vbnav.control.comms.link import TelemetryLink
    return TelemetryLink.attach(rt, cfg, record=getattr(args, "record", None))


class _sim_recorder:
    """``with _sim_recorder(cfg, args) as rec``: an McapRecorder for --record on the simulated robot, or None.

    Simulated runs (faster than real time) record but do not open the network.
    """

    def __init__(self, cfg, args):
        self.cfg, self.path, self.rec = cfg, getattr(args, "record", None), None

    def __enter__(self):
        if self.path:
            from vbnav.control.comms.recording import McapRecorder
            self.rec = McapRecorder(self.path, self.cfg.robot.name, metadata={"config": self.cfg.source or ""})
        return self.rec

    def __exit__(self, *exc):
        if self.rec is not None:
            self.rec.close()
