"""Arguments and session set-up shared by the network subcommands (monitor, send)."""
from __future__ import annotations

import argparse
import os

from vbnav.control.network import DEFAULT_ENDPOINT, client_session_config, open_session


def add_net_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", default="sim", metavar="NAME", help="robot name (robot.name in its config; default sim)")
    p.add_argument("--connect", default=DEFAULT_ENDPOINT, metavar="ENDPOINT",
                   help=f"zenoh endpoint of the robot or a router (default {DEFAULT_ENDPOINT})")
    p.add_argument("--user", default=None, help="zenoh user name, when the robot requires authentication")
    p.add_argument("--password-env", default="VBNAV_ZENOH_PASSWORD", metavar="VAR",
                   help="environment variable holding the password (default VBNAV_ZENOH_PASSWORD); "
                        "never pass passwords on the command line")


def open_client(args):
    """A zenoh client session from the parsed arguments; raises ConnectionError with a clear message."""
    password = os.environ.get(args.password_env) if args.user else None
    if args.user and password is None:
        raise ConnectionError(f"--user {args.user} given but ${args.password_env} is not set")
    try:
        return open_session(client_session_config([args.connect], args.user, password))
    except Exception as exc:
        raise ConnectionError(f"cannot connect to {args.connect}: {exc} (is `vbnav run` going, with its "
                              f"telemetry.listen on this endpoint?)") from None
