"""vbnav run: the loop with the configured drivers and controller."""
from __future__ import annotations

import json
import sys

from vbnav.control.commands._common import (add_config_arg, apart_from_config, apply_realtime, duration_within_script,
                                           enable_live_view, output_file, positive,
                                           record_target_error, refuse_network_driver_without_network,
                                           refuse_unserved_live_view)
from vbnav.drivers.errors import InputError
from vbnav.control.commands._net import add_telemetry_args, attach_telemetry


def register(sub) -> None:
    p = sub.add_parser("run", help="run the control loop with the configured drivers and controller",
                       description="Run the fixed-rate control loop with the drivers and controller named in the "
                                   "configuration (controller.kind: scripted, teleop, operator, idle). 'operator' is the "
                                   "robot's everyday session: teleop driving plus cmd/mode idle, teach ROUTE and "
                                   "repeat ROUTE from the network (vbnav send mode ...). Prints progress and a "
                                   "timing summary; safety events print on stderr as they happen. Stops on "
                                   "SIGINT/SIGTERM with the wheels at zero. The camera opens only when the run "
                                   "uses it (controller operator, or obstacles.enabled; --camera to watch it "
                                   "anyway): a robot without a camera runs teleop, scripted and idle.")
    add_config_arg(p)
    p.add_argument("--duration", type=positive, default=None, metavar="S",
                   help="stop after S seconds (simulated seconds on the simulated clock)")
    p.add_argument("--controller", choices=["scripted", "teleop", "operator", "idle"], default=None,
                   help="override controller.kind from the configuration")
    cam = p.add_mutually_exclusive_group()
    cam.add_argument("--no-camera", action="store_true",
                     help="do not open the camera even when the run would use it (an operator session that "
                          "only takes teleop)")
    cam.add_argument("--camera", action="store_true",
                     help="open the camera even when the run does not use it, so a stale camera stops the robot")
    p.add_argument("--realtime", action="store_true",
                   help="simulated robot: run on the wall clock (sim.realtime: true) so telemetry opens and "
                        "'vbnav monitor', 'vbnav send' and the Foxglove live view work; without it the "
                        "simulated robot runs faster than real time and only records (refused with a real drive or camera: "
                        "always on the wall clock)")
    p.add_argument("--live-view", action="store_true",
                   help="serve the live view to the Foxglove app (telemetry.live_view.enabled: true; "
                        "ws://127.0.0.1:8765 by default, docs/telemetry.md)")
    p.add_argument("--json", action="store_true", help="print the run summary as JSON on stdout")
    add_telemetry_args(p)
    p.set_defaults(func=run)


def build_controller(cfg, kind: str):
    from vbnav.control.controllers.manual import IdleController, ScriptedController, TeleopController
    if kind == "scripted":
        return ScriptedController(cfg.controller.script)
    if kind == "teleop":
        return TeleopController(cfg.safety.command_timeout_s)
    if kind == "idle":
        return IdleController()
    raise ValueError(f"controller.kind {kind!r} is not available in 'vbnav run'")


def camera_wanted(cfg, kind: str, args) -> bool:
    """Whether this run opens the camera: when something uses it (the operator's teach and repeat, the
    obstacle stop, the live view's image), or when asked; never with --no-camera."""
    if args.no_camera:
        return False
    return args.camera or kind == "operator" or cfg.obstacles.enabled or cfg.telemetry.live_view.enabled


def run(args) -> int:
    from vbnav.control.config import load_config
    from vbnav.control.runtime.factory import make_robot
    from vbnav.control.runtime.finishing import finishing
    from vbnav.control.runtime.progress import EventEcho, ProgressPrinter
    from vbnav.control.runtime.runtime import DEVICE_FAULTS, ENDED_WELL, Runtime

    cfg = load_config(args.config)  # refuses unsafe network settings before any device opens
    output_file(args.record, "--record")
    apart_from_config(cfg, {"--record": args.record})
    why = record_target_error(args, overwrite_is_record_only=True)
    if why:
        raise InputError(why)
    apply_realtime(cfg, args.realtime)
    if args.live_view:
        enable_live_view(cfg, args.no_telemetry)
    refuse_unserved_live_view(cfg, args.no_telemetry, "add --realtime")
    kind = args.controller or cfg.controller.kind
    if kind in ("teleop", "operator"):
        who = f"--controller {kind}" if args.controller else f"{cfg.source}: controller.kind {kind}"
        refuse_network_driver_without_network(cfg, who, args.no_telemetry, "the robot would stand still until the end")
        if cfg.on_simulated_clock():        # as teach refuses it: the network is not opened on that clock
            raise InputError(f"{who} on the simulated clock (faster than real time): the network is not opened "
                             f"and nobody could drive it, the robot would stand still until the end; add --realtime "
                             f"(or sim.realtime: true)")
    if kind == "scripted":
        duration_within_script(cfg.controller.script, args.duration, f"{cfg.source}: controller.script")
    from vbnav.control.commands._common import refuse_no_camera_with_obstacle_stop
    refuse_no_camera_with_obstacle_stop(cfg, args.no_camera)
    robot = make_robot(cfg, with_camera=camera_wanted(cfg, kind, args))
    if robot.camera is None and not args.no_camera:
        print(f"camera: not opened (controller {kind} does not use it" +
              (")" if cfg.obstacles.enabled else ", obstacles are off); --camera opens it anyway"), file=sys.stderr)
    clock, drive, pipeline = robot.clock, robot.drive, robot.pipeline
    if kind == "operator":
        from vbnav.control.controllers.operator import OperatorController
        controller = OperatorController(cfg, pipeline, cfg.safety.command_timeout_s)
    else:
        controller = build_controller(cfg, kind)
    rt = Runtime(cfg, drive, controller, clock, pipeline)
    if kind == "operator":
        controller.attach(rt)
    link = attach_telemetry(rt, cfg, args)
    if link is None:
        return 3
    if clock.simulated and cfg.telemetry.enabled and not args.no_telemetry:
        print("vbnav run: simulated clock (faster than real time): telemetry, network commands and the live "
              "view are not opened; add --realtime to watch and command the simulated robot", file=sys.stderr)
    printer = ProgressPrinter()
    echo = None if clock.simulated else EventEcho().attach(rt)   # a simulated run is over before anyone could read them

    def progress(r: Runtime) -> None:
        t = (r.clock.now_ns() - r._start_ns) * 1e-9
        p = r.odometry.pose
        printer(f"t={t:6.1f}s  pose x={p.x:+.2f} z={p.z:+.2f} th={p.theta:+.2f}  "
                f"cmd v={r.last_twist.v:+.2f} w={r.last_twist.w:+.2f}  "
                f"safety={'ok' if r.safety.may_move else ','.join(r.safety.reasons())}")

    duration = args.duration
    if duration is None and kind != "scripted" and clock.simulated:
        duration = 10.0  # a simulated teleop/idle run has nobody to stop it
    result = None
    try:
        result = rt.run(duration, progress)      # under systemd the runtime itself notifies (systemd_notify.py)
    finally:
        with finishing():           # a second Ctrl-C must not cut the recording or the route short
            try:                    # a route being taught keeps every keyframe so far; complete if the run ended well
                if kind == "operator":
                    controller.close(complete=result is not None and result.reason in ENDED_WELL)
                else:
                    controller.close()
            finally:                # a route that could not be saved does not cut the recording short
                link.close(result)
                if echo is not None:
                    echo.close()
    with finishing("printing the summary"):
        printer.done()
        summary = {"reason": result.reason, "message": result.message, "cycles": result.cycles,
                   "timing": result.timing.as_dict(), "events": [e.as_dict() for e in result.events],
                   # a long run keeps its first and last events: how many were left out, and every kind's count
                   "events_dropped": result.events_dropped,
                   "event_counts": [{"kind": k, "cause": c, "count": n}
                                    for (k, c), n in sorted(result.event_counts.items())],
                   "final_odometry": rt.odometry.pose.as_array().tolist(),
                   # telemetry lost to errors (a sink that raised, an overlay not built): said on stderr too
                   "telemetry_errors": link.telemetry_errors}
        if args.json:
            print(json.dumps(summary, indent=2))
        else:
            print(f"run ended: {result.reason} ({result.message})")
            print("timing: " + result.timing.line())
            for e in result.event_report():
                print(f"safety: {e}" if isinstance(e, str) else f"safety {e.kind}: {e.cause}: {e.message}")
    if result.reason == "signal":
        return 130
    if result.reason in DEVICE_FAULTS:     # a device failed or is not there
        return 3
    return 0 if result.ok and link.recording_error is None else 1     # a --record asked for and not made
