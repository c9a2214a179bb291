"""Network arguments shared by subcommands.

- Clients (monitor, send): ``add_net_args`` and ``open_client``.
- Robot runs (run, and teach/repeat/demo): ``add_telemetry_args`` (--record, --no-telemetry) and
  ``attach_telemetry(runtime, cfg, args)`` which connects telemetry, network commands and the recording.
"""
from __future__ import annotations

import argparse
import os
import re

from vbnav.control.commands._common import add_record_overwrite_arg
from vbnav.control.config.telemetry import DEFAULT_ENDPOINT

from vbnav.control.comms.network import client_session_config, open_session


def endpoint(text: str) -> str:
    """argparse type: a zenoh endpoint, <protocol>/<address> (tcp/127.0.0.1:7447, tls/robot.local:7447)."""
    if not re.fullmatch(r"[a-z0-9-]+/\S+", text):
        raise argparse.ArgumentTypeError(f"expected a zenoh endpoint <protocol>/<address> like {DEFAULT_ENDPOINT}, "
                                         f"got {text!r}")
    return text


def add_net_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", default="sim", metavar="NAME", help="robot name (robot.name in its config; default sim)")
    p.add_argument("--connect", default=DEFAULT_ENDPOINT, metavar="ENDPOINT", type=endpoint,
                   help=f"zenoh endpoint of the robot or a router (default {DEFAULT_ENDPOINT})")
    p.add_argument("--user", default=None, help="zenoh user name, when the robot requires authentication")
    p.add_argument("--password-env", default="VBNAV_ZENOH_PASSWORD", metavar="VAR",
                   help="environment variable holding the password (default VBNAV_ZENOH_PASSWORD); "
                        "never pass passwords on the command line")
    p.add_argument("--tls-ca", default=None, metavar="PEM", help="CA certificate, for a robot listening on tls/")
    p.add_argument("--tls-cert", default=None, metavar="PEM", help="this client's certificate (mutual TLS)")
    p.add_argument("--tls-key", default=None, metavar="PEM", help="this client's private key (mutual TLS)")


def open_client(args):
    """A zenoh client session from the parsed arguments; raises ConnectionError with a clear message."""
    password = os.environ.get(args.password_env) if args.user else None
    if args.user and password is None:
        raise ConnectionError(f"--user {args.user} given but ${args.password_env} is not set")
    tls = None
    if args.tls_ca or args.tls_cert or args.tls_key:
        if not (args.tls_ca and args.tls_cert and args.tls_key):
            raise ConnectionError("mutual TLS needs all of --tls-ca, --tls-cert and --tls-key")
        tls = {"root_ca_certificate": args.tls_ca, "connect_certificate": args.tls_cert,
               "connect_private_key": args.tls_key, "enable_mtls": True}
    try:
        return open_session(client_session_config([args.connect], args.user, password, tls))
    except Exception as exc:
        raise ConnectionError(f"cannot connect to {args.connect}: {exc} (is `vbnav run` going, with its "
                              f"telemetry.listen on this endpoint?)") from None


def add_telemetry_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--record", default=None, metavar="PATH",
                   help="record state, events and images to an MCAP file (opens in Foxglove; see "
                        "docs/telemetry.md); written as PATH.part and renamed when the run ends")
    add_record_overwrite_arg(p)
    p.add_argument("--no-telemetry", action="store_true",
                   help="do not open the zenoh session (no telemetry, no network commands); runs on the "
                        "simulated clock never open it")


def attach_telemetry(rt, cfg, args):
    """TelemetryLink for a runtime, or None (after a message on stderr) if the zenoh session cannot open.

    Call after building the Runtime and before ``rt.run``; call ``link.close(result)`` after it.
    The network opens only when the loop runs in real time: a run on the simulated clock is an offline
    computation (it finishes faster than anyone could watch or command it), so it only records.
    """
    import sys

    from vbnav.control.comms.link import TelemetryLink
    network = not args.no_telemetry and not rt.clock.simulated
    try:
        link = TelemetryLink.attach(rt, cfg, record=args.record, network=network, record_overwrite=args.overwrite)
    except ConnectionError as exc:
        print(f"vbnav: {exc}", file=sys.stderr)
        return None
    if link.live_view is not None:
        lv = cfg.telemetry.live_view
        scheme = "wss" if lv.tls_certificate else "ws"
        print(f"vbnav: live view on {scheme}://{lv.host}:{link.live_view.port} (Foxglove: Open connection, "
              f"Foxglove WebSocket; layout docs/foxglove-layout.json)", file=sys.stderr, flush=True)
    return link
