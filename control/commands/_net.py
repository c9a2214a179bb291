"""Network arguments shared by subcommands.

- Clients (monitor, send): ``add_net_args`` and ``open_client``.
- Robot runs (run, map build, goto; teach/repeat/demo through the session): ``add_telemetry_args`` (--record,
  --no-telemetry) and ``attach_telemetry(runtime, cfg, args)`` which connects telemetry, network commands and
  the recording.
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


def add_net_args(p: argparse.ArgumentParser, signs: bool = False) -> None:
    """The options that reach a robot; ``signs``: the command sends commands, signed with -c's secret."""
    p.add_argument("--robot", default=None, metavar="NAME",
                   help="robot name (robot.name in its config); default: from --config, else the only robot "
                        "answering on the network")
    p.add_argument("--config", "-c", default=None, metavar="FILE",
                   help="the robot's configuration: its robot.name names the robot" + (
                       " (and the commands are signed with its telemetry.shared_secret_file)" if signs else ""))
    p.add_argument("--connect", default=DEFAULT_ENDPOINT, metavar="ENDPOINT", type=endpoint,
                   help=f"zenoh endpoint of the robot or a router (default {DEFAULT_ENDPOINT})")
    p.add_argument("--user", default=None, help="zenoh user name, when the robot requires authentication")
    p.add_argument("--password-env", default="VBNAV_ZENOH_PASSWORD", metavar="VAR",
                   help="environment variable holding the password (default VBNAV_ZENOH_PASSWORD); "
                        "never pass passwords on the command line")
    p.add_argument("--tls-ca", default=None, metavar="PEM", help="CA certificate, for a robot listening on tls/")
    p.add_argument("--tls-cert", default=None, metavar="PEM", help="this client's certificate (mutual TLS)")
    p.add_argument("--tls-key", default=None, metavar="PEM", help="this client's private key (mutual TLS)")


TLS_PROTOCOLS = ("tls", "quic")      # the zenoh links that use transport.link.tls


def open_client(args):
    """A zenoh client session from the parsed arguments; raises ConnectionError with a clear message when
    the endpoint cannot be reached, InputError (nothing tried) for options that cannot work: --user without
    its password, part of the TLS options, a TLS file that is not there, TLS options for a link without TLS."""
    from vbnav.drivers.errors import InputError
    password = os.environ.get(args.password_env) if args.user else None
    if args.user and password is None:
        raise InputError(f"--user {args.user} given but ${args.password_env} is not set (the password is read "
                         f"from it, --password-env)")
    tls = None
    if args.tls_ca or args.tls_cert or args.tls_key:
        if not (args.tls_ca and args.tls_cert and args.tls_key):
            raise InputError("mutual TLS needs all of --tls-ca, --tls-cert and --tls-key")
        if args.connect.split("/", 1)[0] not in TLS_PROTOCOLS:
            raise InputError(f"--tls-ca, --tls-cert, --tls-key: --connect {args.connect} is not a TLS link, which "
                             f"would not use them (connect to tls/HOST:PORT)")
        for option, path in (("--tls-ca", args.tls_ca), ("--tls-cert", args.tls_cert), ("--tls-key", args.tls_key)):
            if not os.path.isfile(path):
                raise InputError(f"{option} {path}: " + ("is a directory, expected a PEM file" if os.path.isdir(path)
                                                         else "no such file"))
        tls = {"root_ca_certificate": args.tls_ca, "connect_certificate": args.tls_cert,
               "connect_private_key": args.tls_key, "enable_mtls": True}
    try:
        return open_session(client_session_config([args.connect], args.user, password, tls))
    except Exception as exc:
        raise ConnectionError(f"cannot connect to {args.connect}: {exc} (is `vbnav run` going, with its "
                              f"telemetry.listen on this endpoint?)") from None


def robots_seen(session, timeout_s: float = 3.0) -> list[str]:
    """Names of the robots answering on this network: every robot's event history is readable by all
    (``vbnav/<robot>/events/recent``). The query ends when every robot answered, at once when none is
    there; the timeout only bounds a robot slow to answer (a loaded machine)."""
    names = set()
    try:
        for reply in session.get("vbnav/*/events/recent", timeout=timeout_s):
            if reply.ok is not None:
                parts = str(reply.ok.key_expr).split("/")
                if len(parts) == 4:
                    names.add(parts[1])
    except Exception:
        pass
    return sorted(names)


def robot_answers(session, robot: str, timeout_s: float) -> bool:
    """Whether a robot of that name is there: its event-history queryable answers (every robot has one,
    readable by everyone); with no such robot the query ends at once."""
    try:
        return any(r.ok is not None for r in session.get(f"vbnav/{robot}/events/recent", timeout=timeout_s))
    except Exception:
        return False


def robot_name(args, session, who: str) -> str:
    """The robot to talk to: --robot, else --config's robot.name, else the only robot on the network.

    Raises InputError for an unreadable --config, LookupError (with what was seen) when the network has
    no robot or several."""
    if args.robot:
        return args.robot
    if args.config:
        from vbnav.control.config import ConfigError, load_config
        from vbnav.drivers.errors import InputError
        try:
            return load_config(args.config).robot.name
        except ConfigError as exc:
            raise InputError(str(exc)) from None
    seen = robots_seen(session)
    if len(seen) == 1:
        return seen[0]
    if not seen:
        raise LookupError(f"no robot answers at {args.connect} (is `vbnav run` going, with telemetry on?); "
                          f"name it with --robot NAME or -c CONFIG")
    raise LookupError(f"several robots answer at {args.connect}: {', '.join(seen)}; pick one with --robot NAME "
                      f"or -c CONFIG ({who})")


def open_robot(args, who: str):
    """A client session and the name of the robot to talk to (``robot_name``). Raises ConnectionError
    when the endpoint cannot be reached, LookupError when no robot can be named (the session closed)."""
    session = open_client(args)
    try:
        return session, robot_name(args, session, who)
    except BaseException:
        session.close()
        raise


class StateWatch:
    """The robot's newest state message (``vbnav/<robot>/state``), kept by a subscriber: what a resume
    names (``resume_body``). ``state`` is None until one came."""

    def __init__(self, session, robot: str):
        import threading
        self.key = f"vbnav/{robot}/state"
        self.state: dict | None = None
        self._came = threading.Event()
        session.declare_subscriber(self.key, self._on_state)

    def _on_state(self, sample) -> None:     # zenoh thread
        import json
        try:
            msg = json.loads(sample.payload.to_bytes())
            latched = msg["safety"].get("latched_ns")
            if isinstance(msg["stamp_ns"], int) and (latched is None or isinstance(latched, int)):
                self.state = msg
                self._came.set()
        except (ValueError, KeyError, TypeError, AttributeError):
            pass

    def wait(self, timeout_s: float) -> dict | None:
        """The newest state, waiting up to ``timeout_s`` for the first; None if none came."""
        self._came.wait(max(0.0, timeout_s))
        return self.state


def resume_body(state: dict | None) -> dict | None:
    """The resume that clears only what the robot's last ``state`` showed: its ``safety.latched_ns``, or, with
    nothing latched then, the state's own ``stamp_ns`` (a stop that began after it was not seen). None before
    any state: the sender cannot know which stop a resume would clear."""
    if state is None:
        return None
    latched = state["safety"].get("latched_ns")
    return {"latched_ns": state["stamp_ns"] if latched is None else latched}


def command_secret(args) -> bytes | None:
    """The shared secret to sign commands with (--secret-file, else --config's
    telemetry.shared_secret_file), or None; raises ValueError naming the file."""
    from vbnav.control.comms.command_auth import read_secret
    path = args.secret_file
    if path is None and args.config:
        from vbnav.control.config import ConfigError, load_config
        try:
            path = load_config(args.config).telemetry.shared_secret_file
        except ConfigError as exc:
            raise ValueError(str(exc)) from None
    return None if path is None else read_secret(path, check_owner=False)


class CommandPublisher:
    """Operator commands to one robot, as ``vbnav send`` and ``vbnav teleop`` put them on the network.

    Each message carries this sender's session id, an increasing ``seq`` and the send time on this
    machine's monotonic clock (the robot refuses teleop that is out of order or older than its command
    timeout, docs/telemetry.md "Commands"), and a signature when the robot has a shared secret.
    """

    def __init__(self, session, robot: str, sender: str, secret: bytes | None = None):
        import uuid
        self.session, self.robot, self.secret = session, robot, secret
        self.base = {"sender": sender, "session": uuid.uuid4().hex[:16]}
        self.seq = 0
        self._publishers: dict = {}

    def publisher(self, what: str):
        """The reliable publisher of ``vbnav/<robot>/cmd/<what>`` (its matching_status says if the robot is there)."""
        if what not in self._publishers:
            import zenoh
            self._publishers[what] = self.session.declare_publisher(
                self.key(what), congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE)
        return self._publishers[what]

    def key(self, what: str) -> str:
        return f"vbnav/{self.robot}/cmd/{what}"

    def put(self, what: str, body: dict) -> None:
        import json
        import time
        stamp_ns = time.monotonic_ns()
        # body first: an ``ack`` leads, so the robot can echo it even for a payload it refuses unparsed
        payload = json.dumps({**body, **self.base, "seq": self.seq, "stamp_ns": stamp_ns}).encode()
        self.seq += 1
        if self.secret is None:
            self.publisher(what).put(payload)
        else:   # the signature covers the payload bytes: seq, stamp_ns, session and ack cannot be altered
            from vbnav.control.comms.command_auth import sign
            self.publisher(what).put(payload, attachment=sign(self.secret, self.key(what), payload,
                                                              stamp_ns=stamp_ns))


def add_telemetry_args(p: argparse.ArgumentParser, overwrite_help: str = "") -> None:
    """``overwrite_help``: what else the command's --overwrite replaces (its own output), if anything."""
    p.add_argument("--record", default=None, metavar="PATH",
                   help="record state, events and images to an MCAP file (opens in Foxglove; see "
                        "docs/telemetry.md); written as PATH.part and renamed when the run ends")
    add_record_overwrite_arg(p, overwrite_help)
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
