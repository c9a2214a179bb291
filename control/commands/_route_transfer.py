"""``vbnav route pull ROBOT NAME`` and ``vbnav route push ROBOT PATH``: copy a route over zenoh.

The logic is in control/comms/route_transfer.py; this module only adds the two actions to ``vbnav route``.
Exit codes as ``vbnav send``: 0 copied, 1 refused or failed (the reason is printed), 2 bad input,
3 cannot connect or no such robot.
"""
from __future__ import annotations

import sys
from pathlib import Path

from vbnav.control.commands._common import add_config_arg, positive
from vbnav.control.commands._net import add_net_args, open_client

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
    import argparse
    pl = act.add_parser("pull", help="copy a route from a robot over zenoh", epilog=_EPILOG,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    pl.add_argument("target", metavar="ROBOT", help="the robot's name (robot.name)")
    pl.add_argument("name", metavar="NAME", help="the route's name in the robot's controller.routes_dir")
    pl.add_argument("--to", default=None, metavar="DIR",
                    help="folder to put the route in (default: controller.routes_dir of --config, else the "
                         "current folder); the route lands in DIR/NAME")
    pl.add_argument("--overwrite", action="store_true", help="replace an existing DIR/NAME (swapped when complete)")
    add_config_arg(pl)
    pl.set_defaults(func=run_pull)
    ps = act.add_parser("push", help="copy a local route to a robot over zenoh (operators only)", epilog=_EPILOG,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    ps.add_argument("target", metavar="ROBOT", help="the robot's name (robot.name)")
    ps.add_argument("path", metavar="PATH", help="the local route directory")
    ps.add_argument("--name", default=None, metavar="NAME", help="its name on the robot (default: PATH's folder name)")
    ps.add_argument("--overwrite", action="store_true", help="replace the robot's route of that name")
    ps.add_argument("--secret-file", default=None, metavar="FILE",
                    help="sign the push with the robot's shared secret (telemetry.shared_secret_file)")
    add_config_arg(ps)
    ps.set_defaults(func=run_push)
    for sp in (pl, ps):
        add_net_args(sp)
        for a in sp._actions:          # ROBOT is positional here: hide the shared --robot option
            if a.dest == "robot":
                a.help = argparse.SUPPRESS
        sp.add_argument("--timeout", type=positive, default=5.0, metavar="S",
                        help="wait up to S seconds for each answer of the robot (default 5)")


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
    """The shared secret to sign with (--secret-file, else --config's telemetry.shared_secret_file), or None:
    the same rule as ``vbnav send``."""
    from vbnav.control.commands.send import _secret as send_secret
    from vbnav.drivers.errors import InputError
    try:
        return send_secret(args)
    except ValueError as exc:
        raise InputError(str(exc)) from None


def _transfer(args, what: str, fn) -> int:
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
        print(f"vbnav route {what}: robot {args.target}: {exc}", file=sys.stderr)
        return REFUSED
    finally:
        session.close()


def run_pull(args) -> int:
    from vbnav.control.comms.route_transfer import pull
    root = _dest_root(args)

    def go(session) -> int:
        dest = pull(session, args.target, args.name, root, overwrite=args.overwrite, timeout_s=args.timeout)
        print(f"pulled route {args.name} from robot {args.target} to {dest} (checksums verified)")
        return OK
    return _transfer(args, "pull", go)


def run_push(args) -> int:
    from vbnav.control.comms.route_transfer import push
    secret = _secret(args)

    def go(session) -> int:
        answer = push(session, args.target, args.path, name=args.name, overwrite=args.overwrite, secret=secret,
                      timeout_s=args.timeout)
        name = args.name or Path(args.path).name
        print(f"pushed route {name} to robot {args.target}: {answer.get('keyframes')} keyframes "
              f"(checksums verified by the robot)")
        return OK
    return _transfer(args, "push", go)
