"""vbnav repeat: patrol a taught route."""
from __future__ import annotations

import contextlib

from vbnav.control.commands._common import add_config_arg


def register(sub) -> None:
    p = sub.add_parser(
        "repeat", help="patrol a taught route by vision-based control",
        description="Repeat a route recorded by 'vbnav teach'. The route is checked completely (manifest, every "
                    "keyframe file) before the motors are enabled. The robot localises against the keyframe "
                    "ahead, slows and stops when too few landmarks agree, resumes when they do, and stops at "
                    "the end of the route.")
    add_config_arg(p)
    p.add_argument("--path", required=True, metavar="PATH", help="route directory from 'vbnav teach'")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--record", default=None, metavar="FILE.mcap", help="record telemetry and images (MCAP)")
    p.set_defaults(func=run)


def run(args) -> int:
    from vbnav.control.commands.teach import _sim_recorder
    from vbnav.control.config import load_config
    from vbnav.control.runtime.progress import ProgressPrinter
    from vbnav.control.route import RouteError, load_route
    from vbnav.control.runtime.runtime import Runtime
    from vbnav.control.controllers.repeat import RepeatController
    from vbnav.control.stages.repeat import RepeatStage

    cfg = load_config(args.config)
    try:
        route = load_route(args.path)          # before any device is opened
    except (RouteError, FileNotFoundError) as exc:
        print(f"vbnav repeat: {exc}")
        return 2
    if not route.keyframes:
        print(f"vbnav repeat: {args.path}: the route has no keyframes")
        return 2
    vcfg = cfg.vbc
    stage = RepeatStage(route, vcfg, cfg.camera.to_model(), cfg.camera.mount.to_mount())
    controller = RepeatController(route, vcfg, cfg.robot.max_linear_speed, cfg.robot.max_angular_speed)
    printer = ProgressPrinter()
    if cfg.camera.driver == "sim" and cfg.drive.driver == "sim":
        from vbnav.control.demo import demo_route, make_sim_robot, start_pose
        from vbnav.control.runtime.factory import make_pipeline
        from vbnav.drivers.sim.world import World
        robot = make_sim_robot(cfg, World.by_name(cfg.sim.world, cfg.sim.seed), start_pose(demo_route()))
        clock, drive = robot.clock, robot.drive
        pipeline = make_pipeline(cfg, clock, robot.camera, [stage])
    else:
        from vbnav.control.runtime.factory import make_robot
        clock, drive, pipeline = make_robot(cfg, [stage])
    rt = Runtime(cfg, drive, controller, clock, pipeline)
    simulated = cfg.camera.driver == "sim" and cfg.drive.driver == "sim"
    with (_sim_recorder(cfg, args) if simulated else contextlib.nullcontext()) as recorder:
        from vbnav.control.comms.link import TelemetryLink
        # The simulated robot records only; a real robot also publishes and takes network commands.
        link = TelemetryLink.attach(rt, cfg, record=None if simulated else args.record, recorder=recorder,
                                    network=not simulated, segment="repeat")
        result = None
        try:
            result = rt.run(args.duration, lambda r: printer(
                f"repeat: keyframe {stage.index + 1}/{len(route.keyframes)}  {r.odometry.distance:.1f} m  "
                f"{'ok' if r.safety.may_move else 'STOP ' + ', '.join(r.safety.reasons())}"))
        finally:
            link.close(result)
    printer.done()
    print(f"repeat ended: {result.reason} ({result.message}); reached keyframe {stage.index + 1} of "
          f"{len(route.keyframes)}")
    print("timing: " + result.timing.line())
    if result.reason == "signal":
        return 130
    return 0 if result.reason == "finished" else 1
