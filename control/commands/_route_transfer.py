"""``vbnav route pull|push|remote``: copy taught routes from and to robots over zenoh (comms/route_transfer.py).

Registered into ``vbnav route`` by control/commands/route.py (modules named ``_route_*``)."""
from __future__ import annotations

from pathlib import Path

from vbnav.control.commands._net import add_net_args, open_client
from vbnav.drivers.errors import InputError

_EPILOG = """\
A route is copied as one archive with its SHA-256; the receiver checks it, unpacks it beside the
destination, checks that it loads as a route and only then swaps it in (an old route of that name stays
intact until then). Pulling is allowed to whoever may read the robot's telemetry; pushing is a command:
only telemetry.operators on an authenticated robot, and signed (--secret-file) on a robot with
telemetry.shared_secret_file. Exit: 0 copied, 1 refused or failed, 2 bad input, 3 robot not reachable."""


def _local_routes_dir(args) -> Path:
    from vbnav.control.config import load_config
    from vbnav.control.route import routes_root
    cfg = load_config(args.config)
    return routes_root(cfg.controller.routes_dir, cfg.source)


def _drop_option(parser, option: str) -> None:
    for action in list(parser._actions):
        if option in action.option_strings:
            parser._remove_action(action)
            for group in parser._action_groups:
                if action in group._group_actions:
                    group._group_actions.remove(action)
            for opt in action.option_strings:
                parser._option_string_actions.pop(opt, None)


def register_route(cmds) -> None:
    import argparse
    for name, text in (("pull", "copy route NAME from robot ROBOT into this machine's routes directory"),
                       ("push", "copy this machine's route NAME to robot ROBOT"),
                       ("remote", "the routes robot ROBOT serves")):
        c = cmds.add_parser(name, help=text, description=text, epilog=_EPILOG,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
        add_net_args(c)
        _drop_option(c, "--robot")       # the robot is the ROBOT argument here
        c.add_argument("target", metavar="ROBOT", help="robot name (robot.name in its configuration)")
        if name != "remote":
            c.add_argument("name", metavar="NAME", help="route name (a plain name in a routes directory)")
            c.add_argument("--config", "-c", default=None, metavar="FILE",
                           help="this machine's configuration: its controller.routes_dir is where routes are "
                                "taken from / written to (default configs/sim.yaml)")
            c.add_argument("--dir", default=None, metavar="DIR", help="use DIR as the local routes directory")
        if name == "push":
            c.add_argument("--as", dest="as_name", default=None, metavar="NAME2", help="name on the robot")
            c.add_argument("--secret-file", default=None, metavar="FILE",
                           help="sign the chunks with the robot's shared secret (telemetry.shared_secret_file)")
        c.add_argument("--timeout", type=float, default=10.0, metavar="S", help="per answer (default 10)")
        c.set_defaults(func=_run, route_action=name)


def _run(args) -> int:
    import sys

    from vbnav.control.comms import route_transfer as rt
    from vbnav.control.route import RouteError, check_route_name, resolve_route
    robot = args.target
    try:
        check_route_name(robot)          # a robot name is a plain name too (part of a key expression)
        if args.route_action != "remote":
            check_route_name(args.name)
    except RouteError as exc:
        raise InputError(str(exc)) from None
    local = None
    if args.route_action != "remote":
        local = Path(args.dir).expanduser() if args.dir else _local_routes_dir(args)
    secret = None
    if args.route_action == "push" and args.secret_file:
        from vbnav.control.comms.command_auth import read_secret
        try:
            secret = read_secret(args.secret_file, check_owner=False)
        except ValueError as exc:
            raise InputError(str(exc)) from None
    session = None
    try:
        session = open_client(args)      # ConnectionError: exit 3, as when the robot does not answer
        if args.route_action == "remote":
            for r in rt.fetch_route_list(session, robot, args.timeout):
                state = "complete" if r["complete"] else "INCOMPLETE"
                print(f"{r['name']}  {r['keyframes']} keyframes  {state}")
            return 0
        if args.route_action == "pull":
            path, sha = rt.pull_route(session, robot, args.name, local, args.timeout)
            print(f"pulled route {args.name!r} from robot {robot} into {path} (sha256 {sha})")
            return 0
        source = resolve_route(local, args.name, must_exist=True)
        target = args.as_name or args.name
        sha = rt.push_route(session, robot, target, source, secret=secret, timeout_s=args.timeout)
        print(f"pushed route {args.name!r} to robot {robot} as {target!r} (sha256 {sha})")
        return 0
    except ConnectionError as exc:
        print(f"vbnav route {args.route_action}: {exc}", file=sys.stderr)
        return 3
    except RouteError as exc:
        print(f"vbnav route {args.route_action}: {exc}", file=sys.stderr)
        return 1
    finally:
        if session is not None:
            session.close()
