"""vbnav repeat: patrol a taught route."""
from __future__ import annotations

import sys

from vbnav.control.commands._common import (add_config_arg, add_record_overwrite_arg, apart_from_config, output_file, positive,
                                           record_target_error, refuse_unserved_live_view)
from vbnav.drivers.errors import InputError


def register(sub) -> None:
    p = sub.add_parser(
        "repeat", help="patrol a taught route by vision-based control",
        description="Repeat a route recorded by 'vbnav teach'. The route is checked completely (manifest, every "
                    "keyframe file) before the motors are enabled. The robot localises against the keyframe "
                    "ahead, slows and stops when too few landmarks agree, resumes when they do, and stops at "
                    "the end of the route.")
    add_config_arg(p)
    p.add_argument("--path", required=True, metavar="PATH", help="route directory from 'vbnav teach'")
    p.add_argument("--duration", type=positive, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--record", default=None, metavar="FILE.mcap", help="record telemetry and images (MCAP)")
    add_record_overwrite_arg(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from vbnav.control.config import load_config
    from vbnav.control.route import load_route
    from vbnav.control.runtime.factory import make_robot
    from vbnav.control.runtime.progress import ProgressPrinter
    from vbnav.control.runtime.runtime import DEVICE_FAULTS
    from vbnav.control.session import Session

    cfg = load_config(args.config)
    refuse_unserved_live_view(cfg)
    output_file(args.record, "--record")
    apart_from_config(cfg, {"--record": args.record})
    why = record_target_error(args, overwrite_is_record_only=True)
    if why:
        raise InputError(why)
    route = load_route(args.path)          # before any device is opened; a RouteError is exit 2
    if route.repeat_refusal():
        raise InputError(f"{args.path}: {route.repeat_refusal()}")
    if not route.complete:
        print(f"vbnav repeat: warning: {args.path}: {route.incomplete_note()}", file=sys.stderr)
    printer = ProgressPrinter()
    session = Session(cfg, make_robot(cfg, with_camera=True), record=args.record, progress=printer,
                      record_overwrite=args.overwrite)
    result = session.repeat(route, args.duration)
    printer.done()
    print(f"repeat ended: {result.reason} ({result.message}); {result.progress_text()}")
    print("timing: " + result.timing.line())
    if result.reason == "signal":
        return 130
    if result.reason in DEVICE_FAULTS:     # the hardware failed, not the patrol (vbnav's exit codes)
        return 3
    return 0 if result.reason == "finished" and session.recording_error is None else 1   # a --record not made
