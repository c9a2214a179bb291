"""``vbnav route list|info|plot|check|pull|push``: look after taught routes.

- ``list [DIR]``: the routes in a folder (default: the configuration's
  ``controller.routes_dir`` with ``-c``; a folder and ``-c`` together are
  refused), one line each: keyframes, length, camera, complete or not.
- ``info PATH``: one route in full: robot, creation time, camera and mount it was
  taught with, keyframes, length, landmarks per keyframe, extent.
- ``plot PATH [--out FILE.png]``: a top view of the taught path (odometry at the
  keyframes, headings, start and end); default file ``PATH.png`` beside the route.
- ``check PATH [-c CONFIG]``: every PNG chunk and ``.npz`` member against its
  CRC-32, every file decoded, the manifest compared with the files; with ``-c``,
  the route's camera (intrinsics, distortion, size) and mount compared with the
  configuration's as ``vbnav repeat -c CONFIG`` does. Exit 0 intact (complete or
  not: the verdict says which), 1 damaged or refused by ``vbnav repeat`` (no
  keyframes, or with ``-c`` another camera or mount), 2 not a route.
- ``pull ROBOT NAME``, ``push ROBOT PATH``: copy a route from or to a robot over
  zenoh, checksummed (comms/route_transfer.py, docs/fleet.md). Exit codes as
  ``vbnav send``: 0 copied, 1 refused or failed, 2 bad input, 3 cannot connect or
  no such robot.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from vbnav.control.commands._common import output_file, positive
from vbnav.control.commands._net import add_net_args, open_client
from vbnav.drivers.errors import InputError


def register(sub) -> None:
    p = sub.add_parser("route", help="list, describe, plot or check taught routes", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    act = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    ls = act.add_parser("list", help="the routes in a folder")
    ls.add_argument("dir", nargs="?", default=None, metavar="DIR",
                    help="folder of routes (default: controller.routes_dir of --config; one of the two is needed)")
    ls.add_argument("--config", "-c", default=None, metavar="FILE",
                    help="a robot configuration YAML whose controller.routes_dir is listed, instead of DIR (a bare "
                         "name like 'sim' is looked up in configs/)")
    ls.set_defaults(func=run_list)
    for name, fn, help_ in (("info", run_info, "one route in full"), ("plot", run_plot, "top view PNG"),
                            ("check", run_check, "verify checksums and manifest")):
        a = act.add_parser(name, help=help_)
        a.add_argument("path", metavar="PATH", help="the route directory")
        if name == "plot":
            a.add_argument("--out", default=None, metavar="FILE", help="PNG to write (default PATH.png)")
        if name == "check":
            a.add_argument("--config", "-c", default=None, metavar="FILE",
                           help="also refuse the route as 'vbnav repeat -c FILE' would: another camera (intrinsics, "
                                "distortion, image size) or camera mount than this robot configuration's")
        a.set_defaults(func=fn)
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
    elif args.config is not None:       # the folder given is listed: the configuration would not be read
        raise InputError(f"give a folder of routes ({args.dir}) or --config {args.config} for its "
                         "controller.routes_dir, not both")
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
            if key == "calibration" and isinstance(value, dict):
                value = _calibration_text(value)
            value = f"{value:.2f}" if key == "length_m" else ("yes" if value is True else "no" if value is False
                                                             else value)
            print(f"{key + ':':<12} {value}")
    if info["note"]:
        print(f"note:        {info['note']}")
    return 0


def _calibration_text(c: dict) -> str:
    """The manifest's calibration record in one line: where it came from, then the intrinsics."""
    src = (f"{c['file']} ({c.get('format', '?')}, sha256 {str(c.get('sha256'))[:12]})" if c.get("file")
           else "inline in the configuration")
    parts = [src]
    if all(k in c for k in ("width", "height")):
        parts.append(f"{c.get('model', '?')} {c['width']}x{c['height']}")
    if all(isinstance(c.get(k), (int, float)) for k in ("fx", "fy", "cx", "cy")):
        parts.append(f"fx {c['fx']:.2f} fy {c['fy']:.2f} cx {c['cx']:.2f} cy {c['cy']:.2f} px")
    dist = c.get("distortion")
    if dist:        # a hand-edited manifest may hold anything here: shown as written, not formatted
        parts.append("distortion [" + (", ".join(f"{d:.4g}" for d in dist) if isinstance(dist, list) and all(
            isinstance(d, (int, float)) for d in dist) else repr(dist)) + "]")
    if c.get("baseline"):
        b = c["baseline"]
        parts.append(f"baseline {b:.4f} m" if isinstance(b, (int, float)) else f"baseline {b!r}")
    return "; ".join(parts)


def run_plot(args) -> int:
    from vbnav.control.route_tools import plot
    out = Path(args.out) if args.out else Path(args.path.rstrip("/") + ".png")
    output_file(out, "--out")
    print(f"wrote {plot(args.path, out)}")
    return 0


def run_check(args) -> int:
    from vbnav.control.route_tools import check
    cfg = None
    if args.config is not None:
        from vbnav.control.config import load_config
        cfg = load_config(args.config)
    report = check(args.path, cfg)
    for p in report.problems:
        print(f"  damaged: {p}")
    for n in report.notes:
        print(f"  note: {n}")
    if not report.intact:
        print(f"{report.path}: DAMAGED ({len(report.problems)} problem(s)); a repeat would refuse or misread it: "
              f"teach it again (vbnav teach -c {args.config or 'CONFIG'} --out {report.path} --overwrite)")
        return 1
    if report.repeat_refusal:
        repeat = f"vbnav repeat -c {args.config}" if args.config else "vbnav repeat"
        print(f"{report.path}: its files are whole, but {repeat} refuses it: {report.repeat_refusal}")
        return 1
    print(f"{report.path}: intact, {report.keyframes} keyframes, "
          f"{'complete' if report.complete else 'incomplete (teaching was interrupted)'}")
    return 0


# ---- pull and push over zenoh (the logic: control/comms/route_transfer.py) ----------------------------
OK, REFUSED, BAD_INPUT, UNREACHABLE = 0, 1, 2, 3

_EPILOG = """\
Pulling reads the robot's routes: anyone the robot (or its router) admits may. Pushing writes to
the robot: only telemetry.operators may (a robot with telemetry.shared_secret_file needs the push
signed: --secret-file, or -c with that configuration). Every file is checked against its SHA-256
and the route is put in place only when complete (docs/fleet.md).
exit 0 copied, 1 refused or failed, 2 bad input, 3 cannot connect or no such robot.
"""


def add_transfer_actions(act) -> None:
    """The ``pull`` and ``push`` actions of ``vbnav route`` (``act``: its sub-parsers)."""
    pl = act.add_parser("pull", help="copy a route from a robot over zenoh", epilog=_EPILOG,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    pl.add_argument("target", metavar="ROBOT", help="the robot's name (robot.name)")
    pl.add_argument("name", metavar="NAME", help="the route's name in the robot's controller.routes_dir")
    pl.add_argument("--to", default=None, metavar="DIR",
                    help="folder to put the route in (default: controller.routes_dir of --config, else the "
                         "current folder); the route lands in DIR/NAME")
    pl.add_argument("--overwrite", action="store_true", help="replace an existing DIR/NAME (swapped when complete)")
    pl.set_defaults(func=run_pull)
    ps = act.add_parser("push", help="copy a local route to a robot over zenoh (operators only)", epilog=_EPILOG,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    ps.add_argument("target", metavar="ROBOT", help="the robot's name (robot.name)")
    ps.add_argument("path", metavar="PATH", help="the local route directory")
    ps.add_argument("--name", default=None, metavar="NAME", help="its name on the robot (default: PATH's folder name)")
    ps.add_argument("--overwrite", action="store_true", help="replace the robot's route of that name")
    ps.add_argument("--secret-file", default=None, metavar="FILE",
                    help="sign the push with the robot's shared secret (telemetry.shared_secret_file)")
    ps.set_defaults(func=run_push)
    for sp in (pl, ps):
        add_net_args(sp)
        for a in sp._actions:          # ROBOT is positional here: hide the shared --robot option
            if a.dest == "robot":
                a.help = argparse.SUPPRESS
            elif a.dest == "config":       # -c: where routes are taken from / put, and the push's secret
                a.help = ("a configuration: its controller.routes_dir is the local routes folder (pull), its "
                          "telemetry.shared_secret_file signs a push (one without it is refused)")
        sp.add_argument("--timeout", type=positive, default=5.0, metavar="S",
                        help="wait up to S seconds for each answer of the robot (default 5)")


def _refuse_unused(args) -> str:
    """The shared network options the transfer actions do not take: --robot (ROBOT is the positional
    argument here), for a pull -c with --to (-c only says where the route goes), for a push -c with
    --secret-file or without a telemetry.shared_secret_file (-c only gives the secret). Returns, for a push
    -c whose robot.name is not ROBOT, whose secret signs it (a fleet may share one secret: not refused, said)."""
    if args.robot is not None:
        raise InputError(f"--robot {args.robot}: route {args.action} names the robot as its first argument "
                         f"({args.target})")
    if args.action == "pull" and args.to is not None and args.config is not None:
        raise InputError(f"--config {args.config}: with --to {args.to} a pull reads nothing from it (it only gives "
                         f"the routes folder); give one or the other")
    if args.action == "push" and args.config is not None:
        # -c gives a push the secret it signs with, nothing else (ROBOT names the robot)
        if args.secret_file is not None:
            raise InputError(f"--config {args.config}: with --secret-file {args.secret_file} a push reads nothing "
                             f"from it (it only gives the secret); give one or the other")
        from vbnav.control.config import ConfigError, load_config
        try:
            cfg = load_config(args.config)
        except ConfigError as exc:
            raise InputError(str(exc)) from None
        if cfg.telemetry.shared_secret_file is None:
            raise InputError(f"--config {args.config}: {cfg.source} sets no telemetry.shared_secret_file, the one "
                             f"thing a push reads from it: the push would go unsigned (leave -c out to push "
                             f"unsigned to a robot without a secret)")
        if cfg.robot.name != args.target:
            return (f"signed with the secret of robot {cfg.robot.name}'s configuration {args.config} (-c), not "
                    f"{args.target}'s: {args.target} takes it only if it shares that secret")
    return ""


def _dest_root(args) -> Path:
    if args.to is not None:
        return Path(args.to)
    if args.config is not None:
        from vbnav.control.config import load_config
        from vbnav.control.route import routes_root
        cfg = load_config(args.config)
        return routes_root(cfg.controller.routes_dir, cfg.source)
    return Path.cwd()


def _secret(args) -> bytes | None:
    """The shared secret to sign with (--secret-file, else --config's telemetry.shared_secret_file), or None."""
    from vbnav.control.comms.command_auth import signing_secret
    try:
        return signing_secret(args.secret_file, args.config)
    except ValueError as exc:
        raise InputError(str(exc)) from None


def _transfer(args, what: str, fn, note: str = "") -> int:
    from vbnav.control.comms.route_transfer import NoAnswer, NoRobot, TransferError
    try:
        session = open_client(args)
    except ConnectionError as exc:
        print(f"vbnav route {what}: {exc}", file=sys.stderr)
        return UNREACHABLE
    try:
        return fn(session)
    except NoAnswer as exc:
        print(f"vbnav route {what}: {exc}", file=sys.stderr)
        return UNREACHABLE if isinstance(exc, NoRobot) else REFUSED
    except TransferError as exc:
        print(f"vbnav route {what}: robot {args.target}: {exc}" + (f" ({note})" if note else ""), file=sys.stderr)
        return REFUSED
    finally:
        session.close()


def run_pull(args) -> int:
    from vbnav.control.comms.route_transfer import pull
    _refuse_unused(args)
    root = _dest_root(args)

    def go(session) -> int:
        dest = pull(session, args.target, args.name, root, overwrite=args.overwrite, timeout_s=args.timeout)
        print(f"pulled route {args.name} from robot {args.target} to {dest} (checksums verified)")
        return OK
    return _transfer(args, "pull", go)


def run_push(args) -> int:
    from vbnav.control.comms.route_transfer import push
    whose = _refuse_unused(args)
    secret = _secret(args)

    def go(session) -> int:
        answer = push(session, args.target, args.path, name=args.name, overwrite=args.overwrite, secret=secret,
                      timeout_s=args.timeout)
        name = args.name or Path(args.path).name
        print(f"pushed route {name} to robot {args.target}: {answer.get('keyframes')} keyframes "
              f"(checksums verified by the robot" + (f"; {whose})" if whose else ")"))
        return OK
    return _transfer(args, "push", go, whose)
