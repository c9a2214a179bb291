"""``vbnav send estop|resume|teleop V W|mode MODE``: command a robot over zenoh and wait for its answer."""
from __future__ import annotations

import json
import queue
import signal
import sys
import time
import uuid

from vbnav.control.commands._common import finite, non_negative, positive
from vbnav.control.commands._net import (CommandPublisher, StateWatch, add_net_args, command_secret, open_client,
                                         resume_body, robot_answers, robot_name)

# Generous local bounds: the robot checks against its own configured limits and rejects with an event.
_LOCAL_LIMIT = 1e3
RATE_HZ = 20.0      # teleop --for stream rate when --rate is not given (it defaults to None: without --for it
                    # is refused, one message has no rate)
CHECK_EVERY_S = 1.0  # a teleop --for stream asks the robot for an answer again this often after its first one

OK, REFUSED, BAD_INPUT, UNREACHABLE = 0, 1, 2, 3

_EPILOG = """\
The command carries an id ("ack"); vbnav send subscribes to the robot's events before
sending and waits for the robot's answer to that id:

exit 0  the robot applied the command: prints the loop cycle it took effect in
exit 1  the robot refused it: prints its reason (command_rejected event), or no answer came
        within --wait: the robot's access control drops commands from peers that are not
        in telemetry.operators without a word, or (mode) the robot took the switch and had
        not finished it (command_pending event: it says so); or (resume) no state came
        within --wait to learn the newest stop from: nothing sent
exit 2  bad arguments, refused locally (nothing sent), or an unusable --secret-file
exit 3  cannot connect to the endpoint, or no robot with that name is listening there

A robot with telemetry.shared_secret_file accepts only signed commands: pass the same
file with --secret-file (or --config with the robot's configuration).
See docs/telemetry.md ("Who can command the robot").
"""


def register(sub) -> None:
    import argparse
    p = sub.add_parser("send", help="send a command to a robot (estop, resume, teleop, mode) and wait for its answer",
                       description="Send one command on vbnav/<robot>/cmd/<command> (reliable delivery) and wait "
                                   "for the robot to apply or refuse it.",
                       epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    cmds = p.add_subparsers(dest="what", metavar="COMMAND", required=True)
    e = cmds.add_parser("estop", help="latching stop: wheels to zero until `resume`")
    e.add_argument("--reason", default="", help="free text recorded in the event (printable, at most 200 characters: "
                                                "longer is cut and control characters escaped, saying so; the "
                                                "estop goes out regardless)")
    r = cmds.add_parser("resume", help="clear the latched stops the robot's state shows (--latched-ns: the ones "
                                       "you saw; --clear-all: every one)",
                        description="Clear the latched stops (estop, stall, lost drive once back) that began up to "
                                    "the newest one the robot's state shows: vbnav send reads vbnav/<robot>/state "
                                    "(within --wait) and names its safety.latched_ns, so another operator's estop "
                                    "that began after it is not cleared (the robot refuses the resume and says "
                                    "why). With no state within --wait nothing is sent (exit 1).")
    seen = r.add_mutually_exclusive_group()
    seen.add_argument("--latched-ns", type=int, default=None, metavar="T",
                      help="name the newest stop you have seen yourself (the robot's state: safety.latched_ns, or "
                           "its trip event's stamp_ns) instead of reading the state: a stop that began after it is "
                           "not cleared and the robot refuses the resume (docs/telemetry.md)")
    seen.add_argument("--clear-all", action="store_true",
                      help="clear every latch, also stops you have not seen (another operator's estop a moment "
                           "ago): no state is read")
    t = cmds.add_parser("teleop", help="drive with V m/s and W rad/s (positive turns right)",
                        description="Teleop must keep arriving: the robot stops when it is silent for "
                                    "safety.command_timeout_s (and only a run with controller teleop or operator follows "
                                    "it). Without --for one message is sent (the robot drives up to the timeout); "
                                    "`vbnav send teleop 0.1 0 --for 3` drives 3 s, then sends a stop (V and W 0). The "
                                    "exit code is the robot's answer to the first message it applies or refuses, "
                                    "and to one message a second after it (an estop or a hold meanwhile); a "
                                    "refusal stops the stream.")
    t.add_argument("v", type=finite, metavar="V", help="linear velocity, m/s")
    t.add_argument("w", type=finite, metavar="W", help="angular velocity, rad/s")
    t.add_argument("--for", "--duration", dest="duration", type=non_negative, default=0.0, metavar="S",
                   help="keep sending for S seconds, so the robot drives that long (one message drives it for "
                        "at most safety.command_timeout_s)")
    t.add_argument("--rate", type=positive, default=None, metavar="HZ",
                   help=f"send rate with --for (default {RATE_HZ:g})")
    m = cmds.add_parser("mode", help="switch mode: idle, teach, repeat --route NAME")
    m.add_argument("mode", choices=["idle", "teach", "repeat"],
                   help="idle; teach (record a route while teleop drives) or repeat (patrol a route): both need "
                        "--route")
    m.add_argument("--route", default=None, metavar="NAME",
                   help="route to repeat (or to teach into): a name in the robot's controller.routes_dir; "
                        "mode idle takes none")
    for sp in (e, r, t, m):
        sp.epilog, sp.formatter_class = _EPILOG, argparse.RawDescriptionHelpFormatter
        add_net_args(sp, signs=True)
        sp.add_argument("--wait", type=positive, default=3.0, metavar="S",
                        help="wait up to S seconds for the robot, then for its answer (default 3)")
        sp.add_argument("--secret-file", default=None, metavar="FILE",
                        help="sign the command with the robot's shared secret (telemetry.shared_secret_file)")
    p.set_defaults(func=_run)


def build_payload(args) -> tuple[str, dict]:
    """The command name and JSON body; validated locally with the robot's own models.

    ``ack`` comes first, so the robot can echo it even for a payload it refuses unparsed.
    """
    from vbnav.control.comms.operator_commands import ROUTE_MODES, CommandRejected, TeleopLimits, parse_command
    from vbnav.control.route import RouteError, check_route_name
    # One session id per invocation: the robot tracks seq and the clock offset per (sender, session).
    body: dict = {"ack": uuid.uuid4().hex, "sender": "vbnav-send", "session": uuid.uuid4().hex[:16]}
    if args.what == "estop" and args.reason:
        body["reason"] = _estop_reason(args.reason)
    elif args.what == "resume" and args.latched_ns is not None:
        body["latched_ns"] = args.latched_ns
    elif args.what == "teleop":
        if args.rate is not None and not args.duration > 0:     # one message: there is no rate to send it at
            raise ValueError("--rate is the rate of a --for S stream; without --for one message is sent")
        body.update(linear=args.v, angular=args.w)
    elif args.what == "mode":
        if args.route is not None and args.mode not in ROUTE_MODES:     # the robot would ignore it
            raise ValueError(f"--route: mode {args.mode} takes no route (only {' and '.join(ROUTE_MODES)} do)")
        if args.route is None and args.mode in ROUTE_MODES:
            raise ValueError(f"--route: mode {args.mode} needs a route (--route NAME, a route in the robot's "
                             f"controller.routes_dir)")
        if args.route is not None:
            try:
                check_route_name(args.route)
            except RouteError as exc:
                raise ValueError(f"--route: {exc}") from None
        body["mode"] = args.mode
        if args.route is not None:
            body["route"] = args.route
    try:
        parse_command(args.what, json.dumps(body), TeleopLimits(_LOCAL_LIMIT, _LOCAL_LIMIT))
    except CommandRejected as exc:
        raise ValueError(f"{args.what}: {exc}") from None
    return args.what, body


def _estop_reason(text: str) -> str:
    """The --reason as the robot takes it: control characters escaped, at most REASON_MAX_CHARS. An estop is
    never refused for its reason (a note pasted in an emergency); what was changed is said."""
    from vbnav.control.comms.operator_commands import CONTROL_CHARACTERS, REASON_MAX_CHARS
    fixed = CONTROL_CHARACTERS.sub(lambda m: repr(m.group())[1:-1], text)
    if len(fixed) > REASON_MAX_CHARS:
        fixed = fixed[:REASON_MAX_CHARS - 3] + "..."
    if fixed != text:
        print(f"vbnav send: --reason sent as {fixed!r} (the robot takes printable text of at most "
              f"{REASON_MAX_CHARS} characters); that does not hold the estop back", file=sys.stderr)
    return fixed


def _who(args) -> str:
    if args.user:
        return f"user {args.user}"
    if args.tls_cert:
        return f"the holder of certificate {args.tls_cert}"
    return "unauthenticated clients"


def _run(args) -> int:
    try:
        what, body = build_payload(args)
        secret = command_secret(args)
    except ValueError as exc:
        print(f"vbnav send: {exc}", file=sys.stderr)
        return BAD_INPUT
    if secret is not None and args.config and args.robot and args.secret_file is None:
        # A fleet may share one secret, so not refused; but the sender should know whose secret signs it.
        from vbnav.control.config import load_config
        named = load_config(args.config).robot.name
        if named != args.robot:
            print(f"vbnav send: signed with the secret of robot {named}'s configuration {args.config} (-c), not "
                  f"{args.robot}'s: {args.robot} takes it only if it shares that secret", file=sys.stderr)
    try:
        session = open_client(args)
    except ConnectionError as exc:
        print(f"vbnav send: {exc}", file=sys.stderr)
        return UNREACHABLE
    # SIGTERM and SIGHUP (the terminal gone) end a teleop stream as Ctrl-C does: with its stop
    old_handlers = {sig: signal.signal(sig, lambda *_: sys.exit(130)) for sig in (signal.SIGTERM, signal.SIGHUP)}
    try:
        return _exchange(session, args, what, body, secret)
    finally:
        for sig, handler in old_handlers.items():
            signal.signal(sig, handler)
        session.close()


def _exchange(session, args, what: str, body: dict, secret: bytes | None) -> int:
    try:
        robot = robot_name(args, session, "vbnav send")
    except LookupError as exc:
        print(f"vbnav send: {exc}", file=sys.stderr)
        return UNREACHABLE
    heard = _Heard(body["ack"], signed=secret is not None)

    def on_event(sample) -> None:   # zenoh thread
        try:
            msg = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        if isinstance(msg, dict):
            heard.take(msg)

    # Subscribe first: the answer may come before put() returns.
    session.declare_subscriber(f"vbnav/{robot}/events", on_event)
    learn = what == "resume" and args.latched_ns is None and not args.clear_all
    watch = StateWatch(session, robot) if learn else None
    out = CommandPublisher(session, robot, body["sender"], secret)
    key, pub = out.key(what), out.publisher(what)
    deadline = time.monotonic() + args.wait

    def matched() -> bool:
        while not pub.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        return pub.matching_status.matching

    if what == "estop" and matched():
        pass    # a stop goes out once the robot's command subscriber is there, however slow its event history is
    elif not robot_answers(session, robot, max(0.1, args.wait)):
        print(f"vbnav send: no robot named {robot} is listening on {key} at {args.connect} (is `vbnav run` going "
              f"with robot.name {robot}?)", file=sys.stderr)
        return UNREACHABLE
    if not matched():
        print(f"vbnav send: robot {robot} is running but does not offer {key} to {_who(args)}: the robot may refuse "
              f"commands from {_who(args)} (telemetry.operators)", file=sys.stderr)
        return REFUSED

    if watch is not None:     # a resume clears only the stops the robot's newest state shows
        state = watch.wait(deadline - time.monotonic())
        seen = resume_body(state)
        if seen is None:
            print(f"vbnav send: no state from robot {robot} on {watch.key} within {args.wait:g} s, so this "
                  f"resume cannot know which stop it would clear (another operator's estop a moment ago?); "
                  f"nothing sent. Give --latched-ns T (the safety.latched_ns you saw), --clear-all to clear every "
                  f"latch, or a longer --wait (telemetry.state_rate_hz of the robot)", file=sys.stderr)
            return REFUSED
        body.update(seen)
        # Say what it clears: another operator's stop that landed before that state is cleared with it.
        faults = "; ".join(map(str, state["safety"].get("faults") or [])) or "no fault"
        print(f"vbnav send: this resume clears what robot {robot}'s newest state shows: safety "
              f"{state['safety'].get('state')} ({faults}), latched_ns {seen['latched_ns']}", file=sys.stderr)

    def put(seq: int, with_ack: bool) -> None:
        out.put(what, body if with_ack else {k: v for k, v in body.items() if k != "ack"})

    stream = what == "teleop" and args.duration > 0
    rate = (args.rate or RATE_HZ) if stream else None
    n = max(1, int(args.duration * rate)) if stream else 1
    answer, sent = None, 0
    check_every = max(1, round((rate or RATE_HZ) * CHECK_EVERY_S))
    first = time.monotonic()
    try:
        for i in range(n):
            if answer is None:      # ack until answered: a coalesced or lost one cannot hide the answer
                put(i, with_ack=True)
            elif i % check_every == 0:
                # Once applied, the stream's later messages carried no ack, and the robot summarises refusals of
                # a stream without one: an estop or a hold meanwhile refused the rest unheard, and this printed
                # 'applied'. One message a second asks again, under an ack of its own.
                out.put(what, {**body, "ack": heard.check()})
            else:
                put(i, with_ack=False)
            sent += 1
            if answer is None:
                answer = _poll(heard.answers)
            if answer is not None and answer["kind"] == "command_rejected" or heard.later_refusal():
                break
            if answer is None and time.monotonic() - first > args.wait:
                break
            if stream:      # after the last one too: it drives for its period, then the stop
                time.sleep(1.0 / rate)
    finally:
        # however the stream ends (its time up, Ctrl-C, SIGTERM or SIGHUP, an error): the robot would drive on
        # with the last command until its command timeout (also after a later message was refused: the ones before
        # it drove)
        stopped = stream and sent > 0 and not (answer is not None and answer["kind"] == "command_rejected")
        if stopped:
            out.put(what, {"linear": 0.0, "angular": 0.0})
    if answer is None:
        answer = _poll(heard.answers, max(0.0, first + args.wait - time.monotonic()))
    if answer is None:      # an answer the network dropped (congestion control DROP) is in the robot's history
        heard.recall(session, robot)
        answer = _poll(heard.answers)
    later = heard.later_refusal()
    if answer is not None and answer["kind"] == "command" and later is not None:
        print(f"vbnav send: robot {robot} applied {what} at cycle {answer.get('cycle', '?')}, then refused a later "
              f"message of the stream: {later.get('reason', '?')} ({sent} messages sent"
              f"{', then a stop' if stopped else ''})", file=sys.stderr)
        return REFUSED
    return _report(args, robot, what, answer, sent, stopped, heard.pending[0] if heard.pending else None,
                   heard.dropped[-1] if heard.dropped else None, heard.unverified[0] if heard.unverified else None)


class _Heard:
    """What the robot's events say of one command (its ``ack``): the zenoh thread ``take``s each event."""

    def __init__(self, ack: str, signed: bool):
        self.ack, self.signed = ack, signed
        self.answers: queue.SimpleQueue = queue.SimpleQueue()   # command / command_rejected with its ack
        self.pending: list = []      # command_pending: the robot took the command and finishes it later
        self.dropped: list = []      # events_dropped: the robot's telemetry queue was full, an answer may be lost
        self.unverified: list = []   # refusals of a payload with this ack whose signature failed (a copy's?)
        self._checks: set = set()    # the acks of a stream's later messages (``check``)
        self.later: list = []        # command_rejected answering one of them

    def check(self) -> str:
        """A new ack for a stream's later message: a refusal of it is ``later_refusal``."""
        ack = uuid.uuid4().hex
        self._checks.add(ack)
        return ack

    def later_refusal(self):
        """The robot's first refusal of a stream's later message (``check``), else None."""
        return self.later[0] if self.later else None

    def take(self, msg: dict) -> None:
        kind = msg.get("kind")
        if kind == "events_dropped":             # carries no ack: any command's answer may be among them
            self.dropped.append(msg)
        elif msg.get("ack") in self._checks:
            if kind == "command_rejected":
                self.later.append(msg)
        elif msg.get("unverified_ack") == self.ack:
            # unsigned, this command is refused whoever else sent it too: the answer; signed, it may be a copy's
            if self.signed:
                self.unverified.append(msg)
            else:
                self.answers.put(msg)
        elif msg.get("ack") != self.ack:
            return
        elif kind in ("command", "command_rejected"):
            self.answers.put(msg)
        elif kind == "command_pending":
            self.pending.append(msg)

    def recall(self, session, robot: str, timeout_s: float = 1.0) -> None:
        """``take`` the robot's recent events (``vbnav/<robot>/events/recent``, the last 20 its telemetry sent):
        an answer zenoh dropped on the way (its events go with congestion control DROP) is among them."""
        try:
            for reply in session.get(f"vbnav/{robot}/events/recent", timeout=timeout_s):
                if reply.ok is None:
                    continue
                events = json.loads(reply.ok.payload.to_bytes()).get("events", [])
                for msg in events if isinstance(events, list) else []:
                    if isinstance(msg, dict):
                        self.take(msg)
        except Exception:       # no history: the report says no answer came
            pass


def _poll(answers: queue.SimpleQueue, timeout_s: float = 0.0):
    try:
        return answers.get(timeout=timeout_s) if timeout_s > 0 else answers.get_nowait()
    except queue.Empty:
        return None


def _report(args, robot: str, what: str, answer, sent: int, stopped: bool = False, pending=None,
            dropped=None, unverified=None) -> int:
    if answer is None and pending is not None:
        print(f"vbnav send: robot {robot} took {what} at cycle {pending.get('cycle', '?')} and had not finished it "
              f"within {args.wait:g} s (a mode switch loads its route first): `vbnav monitor` shows the mode once "
              f"it is done, a longer --wait waits for it", file=sys.stderr)
        return REFUSED
    if answer is None and unverified is not None:
        print(f"vbnav send: no acknowledgement within {args.wait:g} s; robot {robot} refused a {what} carrying this "
              f"command's ack whose signature failed ({unverified.get('reason', '?')}): if it was this one, sign "
              f"it (--secret-file, or -c CONFIG with telemetry.shared_secret_file)", file=sys.stderr)
        return REFUSED
    if answer is None and dropped is not None:
        print(f"vbnav send: no acknowledgement within {args.wait:g} s, and robot {robot} said "
              f"{dropped.get('message', 'it dropped events')!r}: the answer may be among them; `vbnav monitor` "
              f"shows whether the {what} took effect", file=sys.stderr)
        return REFUSED
    if answer is None:
        print(f"vbnav send: no acknowledgement within {args.wait:g} s: the robot may refuse commands from "
              f"{_who(args)} (telemetry.operators)", file=sys.stderr)
        return REFUSED
    if answer["kind"] == "command_rejected":
        print(f"vbnav send: robot {robot} refused {what}: {answer.get('reason', '?')}", file=sys.stderr)
        return REFUSED
    stream = f" ({sent} messages sent{', then a stop' if stopped else ''})" if sent > 1 or stopped else ""
    note = f": {answer['note']}" if answer.get("note") else ""
    print(f"{what} applied by robot {robot} at cycle {answer.get('cycle', '?')}{stream}{note}")
    return OK
