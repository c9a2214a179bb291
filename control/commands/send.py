"""``vbnav send estop|resume|teleop V W|mode MODE``: command a robot over zenoh, for scripts."""
from __future__ import annotations

import json
import sys
import time
import uuid

from vbnav.control.commands._net import add_net_args, open_client

# Generous local bounds: the robot checks against its own configured limits and rejects with an event.
_LOCAL_LIMIT = 1e3


def register(sub) -> None:
    p = sub.add_parser("send", help="send a command to a robot (estop, resume, teleop, mode)",
                       description="Send one command on vbnav/<robot>/cmd/<command> (reliable delivery). "
                                   "The robot validates it and publishes a command_rejected event if it refuses.")
    cmds = p.add_subparsers(dest="what", metavar="COMMAND", required=True)
    e = cmds.add_parser("estop", help="latching stop: wheels to zero until `resume`")
    e.add_argument("--reason", default="", help="free text recorded in the event")
    r = cmds.add_parser("resume", help="clear an estop latch")
    t = cmds.add_parser("teleop", help="drive with V m/s and W rad/s (positive turns right)",
                        description="Teleop must keep arriving: the robot stops when it is silent for "
                                    "safety.command_timeout_s (and only a run with controller teleop follows it). Without --duration one message is sent.")
    t.add_argument("v", type=float, metavar="V", help="linear velocity, m/s")
    t.add_argument("w", type=float, metavar="W", help="angular velocity, rad/s")
    t.add_argument("--duration", type=float, default=0.0, metavar="S", help="keep sending for S seconds")
    t.add_argument("--rate", type=float, default=10.0, metavar="HZ", help="send rate with --duration (10)")
    m = cmds.add_parser("mode", help="switch mode: idle, teach, repeat --route PATH")
    m.add_argument("mode", choices=["idle", "teach", "repeat"])
    m.add_argument("--route", default=None, metavar="PATH", help="route file to repeat (or to teach into)")
    for sp in (e, r, t, m):
        add_net_args(sp)
        sp.add_argument("--wait", type=float, default=3.0, metavar="S",
                        help="wait up to S seconds for the robot's command subscriber (default 3)")
    p.set_defaults(func=_run)


def build_payload(args) -> tuple[str, dict]:
    """The command name and JSON body; validated locally with the robot's own models."""
    from vbnav.control.comms.operator_commands import CommandRejected, TeleopLimits, parse_command
    # One session id per invocation: the robot tracks seq and the clock offset per (sender, session).
    body: dict = {"sender": "vbnav-send", "session": uuid.uuid4().hex[:16]}
    if args.what == "estop" and args.reason:
        body["reason"] = args.reason
    elif args.what == "teleop":
        body.update(linear=args.v, angular=args.w)
    elif args.what == "mode":
        body["mode"] = args.mode
        if args.route:
            body["route"] = args.route
    try:
        parse_command(args.what, json.dumps(body), TeleopLimits(_LOCAL_LIMIT, _LOCAL_LIMIT))
    except CommandRejected as exc:
        raise ValueError(f"{args.what}: {exc}") from None
    return args.what, body


def _run(args) -> int:
    import zenoh
    try:
        what, body = build_payload(args)
    except ValueError as exc:
        print(f"vbnav send: {exc}", file=sys.stderr)
        return 2
    try:
        session = open_client(args)
    except ConnectionError as exc:
        print(f"vbnav send: {exc}", file=sys.stderr)
        return 3
    key = f"vbnav/{args.robot}/cmd/{what}"
    opts = dict(congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)
    try:
        pub = session.declare_publisher(key, **opts)
        # Wait for the robot's subscriber declaration to reach this fresh session (it never comes when the
        # robot is not running; it may or may not come when the robot's access control refuses this user).
        deadline = time.monotonic() + args.wait
        while not pub.matching_status and time.monotonic() < deadline:
            time.sleep(0.02)
        matched = pub.matching_status
        n = max(1, int(args.duration * args.rate)) if what == "teleop" and args.duration > 0 else 1
        for i in range(n):
            # seq and the send time on this machine's monotonic clock: the robot refuses teleop that is
            # out of order or older than its command timeout (docs/telemetry.md, "Commands").
            body["seq"] = i
            body["stamp_ns"] = time.monotonic_ns()
            pub.put(json.dumps(body))
            if n > 1:
                time.sleep(1.0 / args.rate)
        time.sleep(0.1)  # flush before closing
    finally:
        session.close()
    if not matched:
        print(f"vbnav send: sent {what} to {key}, but no robot subscribed to it within {args.wait:g} s: is the robot "
              f"running under that name, and is this user one of its operators?", file=sys.stderr)
        return 1
    print(f"sent {what} to {key}" + (f" ({n} messages)" if n > 1 else ""))
    return 0
