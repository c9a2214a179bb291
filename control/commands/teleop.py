"""``vbnav teleop``: drive a robot from the keyboard, streaming teleop at 20 Hz while a key is held.

A terminal reports key presses, never releases: a held key repeats (after the keyboard's repeat delay,
250-660 ms, then 25-30 times a second). So a key press drives for ``--hold`` seconds and each repeat
extends it; the stream stops, with one zero command, ``--hold`` after the last repeat. The robot's own
command timeout (safety.command_timeout_s) stops it if this program dies. The terminal goes to raw mode
for single key presses and is restored on every exit (q, Ctrl-C, SIGTERM, SIGHUP, the terminal gone, an
error); each of them, while a key drives, sends a zero command first. The robot's
refusals of teleop, estop and resume (its ``command_rejected`` events: a latched or held stop, speeds
beyond its limits, a repeat in progress) replace the 'driving' line, so the screen never says 'driving'
while the robot stands still.

``r`` resumes only the stops this program has seen: it names the ``safety.latched_ns`` of the robot's last
state (``resume_body``), so another operator's estop that came after it is not cleared (the robot refuses
the resume and says why); before any state has come, ``r`` sends nothing and says so.
"""
from __future__ import annotations

import json
import os
import queue
import select
import signal
import sys
import time
from typing import Callable

from vbnav.control.commands._common import positive
from vbnav.control.commands._net import (CommandPublisher, StateWatch, add_net_args, command_secret, open_robot,
                                         resume_body, robot_answers)
from vbnav.drivers.errors import InputError

#: key -> (forward, turn) direction; positive turn is to the right (vision/geometry.py)
MOVES = {"w": (1, 0), "s": (-1, 0), "a": (0, -1), "d": (0, 1),
         "\x1b[A": (1, 0), "\x1b[B": (-1, 0), "\x1b[D": (0, -1), "\x1b[C": (0, 1)}
QUIT = ("q", "\x03", "\x04")         # q, Ctrl-C, Ctrl-D
HELP = ("vbnav teleop: hold w/s or up/down to drive, a/d or left/right to turn; space stops; "
        "x estop, r resume; q or Ctrl-C quits")


def register(sub) -> None:
    p = sub.add_parser("teleop", help="drive a robot from the keyboard (teleop at 20 Hz while a key is held)",
                       description=HELP + ". Needs a run that takes teleop: `vbnav run -c CONFIG --controller "
                                          "teleop` (or operator).")
    add_net_args(p, signs=True)
    p.add_argument("--speed", type=positive, default=0.1, metavar="V", help="m/s while w/s is held (default 0.1)")
    p.add_argument("--turn", type=positive, default=0.5, metavar="W", help="rad/s while a/d is held (default 0.5)")
    p.add_argument("--rate", type=positive, default=20.0, metavar="HZ", help="send rate while driving (default 20)")
    p.add_argument("--hold", type=positive, default=0.7, metavar="S",
                   help="a key press drives this long, each repeat extends it (default 0.7: above the usual "
                        "keyboard repeat delay, so a held key drives without a gap)")
    p.add_argument("--secret-file", default=None, metavar="FILE",
                   help="sign the commands with the robot's shared secret (telemetry.shared_secret_file)")
    p.set_defaults(func=run)


def keys(data: str):
    """Split terminal input into keys: arrow escape sequences, or single characters."""
    i = 0
    while i < len(data):
        if data.startswith("\x1b[", i) and i + 2 < len(data):
            yield data[i:i + 3]
            i += 3
        else:
            yield data[i]
            i += 1


def _check_speeds(args) -> None:
    """With the robot's configuration (-c), --speed and --turn within its limits: the robot refuses every
    teleop beyond them, while this screen would say 'driving'."""
    if not args.config:
        return
    from vbnav.control.config import load_config
    cfg = load_config(args.config)
    for option, value, key, limit in (("--speed", args.speed, "max_linear_speed", cfg.robot.max_linear_speed),
                                      ("--turn", args.turn, "max_angular_speed", cfg.robot.max_angular_speed)):
        if value > limit + 1e-9:
            raise InputError(f"{option} {value:g}: above robot.{key} {limit:g} of {cfg.source}; the robot would "
                             "refuse every command")


def run(args) -> int:
    import termios
    import tty

    _check_speeds(args)
    fd = sys.stdin.fileno()
    if not os.isatty(fd):
        raise InputError("needs a terminal (stdin is not a tty); in scripts use `vbnav send teleop V W --for S`")
    try:
        secret = command_secret(args)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    try:
        session, robot = open_robot(args, "vbnav teleop")
    except (ConnectionError, LookupError) as exc:
        print(f"vbnav teleop: {exc}", file=sys.stderr)
        return 3
    try:
        if not robot_answers(session, robot, 2.0):
            print(f"vbnav teleop: no robot named {robot} answers at {args.connect}", file=sys.stderr)
            return 3
        out = CommandPublisher(session, robot, "vbnav-teleop", secret)
        refusals: queue.SimpleQueue = queue.SimpleQueue()

        def on_event(sample) -> None:
            try:
                msg = json.loads(sample.payload.to_bytes())
            except ValueError:
                return
            if isinstance(msg, dict) and msg.get("kind") == "command_rejected" and \
                    msg.get("command") in ("teleop", "estop", "resume"):
                refusals.put(f"robot {robot} refused {msg['command']}: {msg.get('reason', '?')}")

        session.declare_subscriber(f"vbnav/{robot}/events", on_event)
        watch = StateWatch(session, robot)      # the robot's last state (its safety.latched_ns: what r resumes)
        saved = termios.tcgetattr(fd)
        # SIGTERM, and SIGHUP (the terminal or ssh session gone): the stream ends with a stop, the terminal restored
        old_handlers = {sig: signal.signal(sig, lambda *_: sys.exit(130)) for sig in (signal.SIGTERM, signal.SIGHUP)}
        try:
            tty.setraw(fd)
            return _drive(fd, out, args, robot, refusals, lambda: watch.state)
        finally:
            termios.tcsetattr(fd, termios.TCSADRAIN, saved)
            for sig, handler in old_handlers.items():
                signal.signal(sig, handler)
            print()
    finally:
        session.close()


def _drive(fd: int, out: CommandPublisher, args, robot: str, refusals: queue.SimpleQueue,
           last_state: Callable[[], dict | None]) -> int:
    def say(text: str) -> None:        # raw mode: no newline translation
        sys.stdout.write("\r\x1b[K" + text)
        sys.stdout.flush()

    streaming = [False]
    try:
        return _keys_to_teleop(fd, out, args, robot, refusals, last_state, say, streaming)
    finally:
        # However it ends (q, the terminal gone, SIGTERM or SIGHUP, an error) while a key drove: stop now, not
        # at the robot's command timeout
        if streaming[0]:
            try:
                out.put("teleop", {"linear": 0.0, "angular": 0.0})
            except Exception:
                pass


def _keys_to_teleop(fd: int, out: CommandPublisher, args, robot: str, refusals: queue.SimpleQueue,
                    last_state: Callable[[], dict | None], say, streaming_flag: list) -> int:
    """The key loop; ``streaming_flag[0]``: whether the last teleop sent drove the robot (the caller stops it);
    ``last_state()``: the robot's last state message, or None."""
    sys.stdout.write(HELP + f" (robot {robot})\r\n")
    period = 1.0 / args.rate
    twist, held_until, shown = (0.0, 0.0), 0.0, None
    next_send = time.monotonic()
    while True:
        now = time.monotonic()
        ready, _, _ = select.select([fd], [], [], max(0.0, next_send - now))
        if ready:
            raw = os.read(fd, 64)
            if not raw:            # end of input: the terminal went away (a hang-up, with SIGHUP ignored)
                return 0
            data = raw.decode(errors="replace")
            for key in keys(data):
                if key in QUIT:
                    return 0
                if key in MOVES:
                    fwd, turn = MOVES[key]
                    twist = (fwd * args.speed, turn * args.turn)
                    held_until = time.monotonic() + args.hold
                elif key == " ":
                    held_until = 0.0
                elif key == "x":
                    held_until = 0.0
                    out.put("estop", {"reason": "vbnav teleop"})
                    say("estop sent (r resumes)")
                elif key == "r":
                    body = resume_body(last_state())
                    if body is None:
                        say(f"resume not sent: no state from robot {robot} yet, so this screen cannot know "
                            "which stop it would clear; press r again once it has")
                    else:
                        out.put("resume", body)
                        say("resume sent")
        refused = None
        while not refusals.empty():
            refused = refusals.get_nowait()
        if refused is not None:
            say(refused)       # stays until the twist changes: the robot is not doing what the keys ask
        now = time.monotonic()
        if now < next_send:
            continue
        next_send = max(next_send + period, now)       # 20 Hz without drift, no burst after a pause
        if now < held_until:
            streaming_flag[0] = True     # from this put on: it may have reached the robot
            out.put("teleop", {"linear": twist[0], "angular": twist[1]})
            if twist != shown:
                say(f"driving v {twist[0]:+.2f} m/s  w {twist[1]:+.2f} rad/s")
            shown = twist
        elif streaming_flag[0]:
            out.put("teleop", {"linear": 0.0, "angular": 0.0})   # released: stop now, not at the timeout
            streaming_flag[0], shown = False, None
            say("stopped")
