"""``vbnav route list|info|plot|check|pull|push``: look after taught routes.

- ``list [DIR]``: the routes in a folder (default: the configuration's
  ``controller.routes_dir`` with ``-c``), one line each: keyframes, length,
  camera, complete or not.
- ``info PATH``: one route in full: robot, creation time, camera and mount it was
  taught with, keyframes, length, landmarks per keyframe, extent.
- ``plot PATH [--out FILE.png]``: a top view of the taught path (odometry at the
  keyframes, headings, start and end); default file ``PATH.png`` beside the route.
- ``check PATH``: every PNG chunk and ``.npz`` member against its CRC-32, every
  file decoded, the manifest compared with the files. Exit 0 intact (complete or
  not: the verdict says which), 1 damaged, 2 not a route.
- ``pull ROBOT NAME``, ``push ROBOT PATH``: copy a route from or to a robot over
  zenoh, checksummed (commands/_route_transfer.py, docs/fleet.md).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from vbnav.control.commands._common import add_config_arg, output_file
from vbnav.drivers.errors import InputError


def register(sub) -> None:
    p = sub.add_parser("route", help="list, describe, plot or check taught routes", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    act = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    ls = act.add_parser("list", help="the routes in a folder")
    ls.add_argument("dir", nargs="?", default=None, metavar="DIR",
                    help="folder of routes (default: controller.routes_dir of --config)")
    add_config_arg(ls)
    ls.set_defaults(func=run_list)
    for name, fn, help_ in (("info", run_info, "one route in full"), ("plot", run_plot, "top view PNG"),
                            ("check", run_check, "verify checksums and manifest")):
        a = act.add_parser(name, help=help_)
        a.add_argument("path", metavar="PATH", help="the route directory")
        if name == "plot":
            a.add_argument("--out", default=None, metavar="FILE", help="PNG to write (default PATH.png)")
        a.set_defaults(func=fn)
    from vbnav.control.commands._route_transfer import add_transfer_actions
    add_transfer_actions(act)       # pull, push: over zenoh


def run_list(args) -> int:
    from vbnav.control.route_tools import list_routes
    if args.dir is None:
        if args.config is None:
            raise InputError("give a folder of routes, or --config FILE for its controller.routes_dir")
        from vbnav.control.config import load_config
        from vbnav.control.route import routes_root
        cfg = load_config(args.config)
        folder = routes_root(cfg.controller.routes_dir, cfg.source)
    else:
        folder = Path(args.dir)
    routes = list_routes(folder)
    print(f"{folder}: {len(routes)} route(s)")
    if routes:
        print(f"  {'NAME':<24} {'KEYFRAMES':>9} {'LENGTH':>9}  {'COMPLETE':<8}  {'CAMERA':<28} CREATED")
    for r in routes:
        if r.error:
            print(f"  {r.name:<24} {r.error}")
            continue
        print(f"  {r.name:<24} {r.keyframes:>9} {r.length_m:>7.2f} m  {'yes' if r.complete else 'NO':<8}  "
              f"{r.camera:<28} {r.created}")
    return 0


def run_info(args) -> int:
    from vbnav.control.route_tools import describe
    info = describe(args.path)
    for key in ("path", "robot", "created", "complete", "keyframes", "length_m", "camera", "mount", "calibration",
                "landmarks", "extent"):
        if key in info:
            value = info[key]
            value = f"{value:.2f}" if key == "length_m" else ("yes" if value is True else "no" if value is False
                                                             else value)
            print(f"{key + ':':<12} {value}")
    if info["note"]:
        print(f"note:        {info['note']}")
    return 0


def run_plot(args) -> int:
    from vbnav.control.route_tools import plot
    out = Path(args.out) if args.out else Path(args.path.rstrip("/") + ".png")
    output_file(out, "--out")
    print(f"wrote {plot(args.path, out)}")
    return 0


def run_check(args) -> int:
    from vbnav.control.route_tools import check
    report = check(args.path)
    for p in report.problems:
        print(f"  damaged: {p}")
    for n in report.notes:
        print(f"  note: {n}")
    if not report.intact:
        print(f"{report.path}: DAMAGED ({len(report.problems)} problem(s)); a repeat would refuse or misread it: "
              f"teach it again (vbnav teach -c CONFIG --out {report.path} --overwrite)")
        return 1
    print(f"{report.path}: intact, {report.keyframes} keyframes, "
          f"{'complete' if report.complete else 'incomplete (teaching was interrupted)'}")
    return 0
