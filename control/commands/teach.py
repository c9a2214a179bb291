"""vbnav teach: record a route while the robot is driven."""
from __future__ import annotations

import sys
from pathlib import Path

from vbnav.control.commands._common import (add_config_arg, apart_from_config, output_file, positive, record_target_error,
                                             refuse_network_driver_without_network, refuse_unserved_live_view)
from vbnav.drivers.errors import InputError


def register(sub) -> None:
    p = sub.add_parser(
        "teach", help="record a route (keyframes) while the robot is driven",
        description="Record a route for 'vbnav repeat'. On the simulated robot (controller.teach: room_loop) the "
                    "route is driven by a scripted driver along the simulated room's loop (20 m, four turns) "
                    "from sim.start_pose; on a robot you drive it by teleoperation "
                    "('vbnav send teleop V W' from another terminal, or any zenoh publisher on "
                    "vbnav/<robot>/cmd/teleop) and end it with Ctrl-C (or --duration); 'vbnav send estop' stops the "
                    "wheels until 'vbnav send resume', the teach goes on. Every keyframe is on disk (atomically) "
                    "as soon as it is taken, so an interruption loses nothing recorded.")
    add_config_arg(p)
    p.add_argument("--out", required=True, metavar="PATH", help="route directory to create")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing route directory (and --record file): the new one is written "
                        "beside it and takes its place only when complete")
    p.add_argument("--duration", type=positive, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--record", default=None, metavar="FILE.mcap", help="record telemetry and images (MCAP)")
    p.set_defaults(func=run)


def run(args) -> int:
    from vbnav.control.config import load_config
    from vbnav.control.route import stray_route_dirs
    from vbnav.control.runtime.factory import make_robot
    from vbnav.control.runtime.progress import ProgressPrinter
    from vbnav.control.runtime.runtime import DEVICE_FAULTS
    from vbnav.control.session import Session, teach_driver

    cfg = load_config(args.config)
    refuse_unserved_live_view(cfg)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: is a file, expected a route directory (to create, or to replace with "
                         "--overwrite)")
    if not out.parent.is_dir():
        raise InputError(f"--out {out}: the folder {out.parent} "
                         f"{'is not a directory' if out.parent.exists() else 'does not exist'}")
    output_file(args.record, "--record")
    apart_from_config(cfg, {"--record": args.record})
    if out.exists() and any(out.iterdir()) and not args.overwrite:
        raise InputError(f"--out {out}: exists and is not empty (use --overwrite to replace it)")
    why = record_target_error(args)
    if why:
        raise InputError(why)
    if cfg.controller.teach == "teleop" and cfg.on_simulated_clock():   # on stdout: tests/test_factory_session.py
        print(f"vbnav teach: {cfg.source}: controller.teach 'teleop' on the simulated clock: nobody can drive a "
              "run faster than real time (set controller.teach: room_loop, or sim.realtime: true)")
        return 2
    if cfg.controller.teach == "teleop":
        refuse_network_driver_without_network(cfg, f"{cfg.source}: controller.teach teleop", False,
                                              "nobody could drive the route")
    for left in stray_route_dirs(out):
        print(f"vbnav teach: note: {left} was left by an interrupted replacement of {out.name} (kept: it holds "
              f"recorded keyframes; delete it when it is not needed)", file=sys.stderr)
    robot = make_robot(cfg, with_camera=True)
    printer = ProgressPrinter()
    session = Session(cfg, robot, record=args.record, progress=printer, record_overwrite=args.overwrite)
    result = session.teach(teach_driver(cfg), out, overwrite=args.overwrite, duration_s=args.duration)
    printer.done()
    if result.note:
        print(f"vbnav teach: note: {result.note}", file=sys.stderr)
    if result.complete:
        print(f"teach ended: {result.reason} ({result.message}); {result.keyframes} keyframes in {out}")
        return 0 if session.recording_error is None else 1     # a --record asked for and not made
    where = (f"the route at {out} is unchanged; the {result.keyframes} keyframes recorded are in "
             f"{result.directory}" if result.directory != out else
             f"{out} holds {result.keyframes} keyframes, marked incomplete (teach again with --overwrite to "
             "replace it)")
    print(f"teach ended: {result.reason} ({result.message}); not a complete route: {where}")
    return 3 if result.reason in DEVICE_FAULTS else 1
