"""``vbnav monitor``: a live terminal view of a robot's state and events."""
from __future__ import annotations

import argparse
import collections
import json
import sys
import threading
import time
from typing import Optional

from vbnav.control.commands._common import positive
from vbnav.control.commands._net import add_net_args, open_client, open_robot, robots_seen

REFRESH_HZ = 5.0    # --refresh when not given (it defaults to None: with --once it is refused)


def _robots(text: str) -> int:
    """argparse type: a number of robots, >= 1."""
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a number of robots >= 1, got {text!r}")
    return n


def register(sub) -> None:
    p = sub.add_parser("monitor", help="live view of a robot's state and events over zenoh",
                       description="Subscribe to vbnav/<robot>/state and /events and show mode, pose, loop "
                                   "timing, faults and recent events (refreshes in place; Ctrl-C quits).")
    add_net_args(p)
    p.add_argument("--once", action="store_true", help="print the first state received and exit (for scripts)")
    p.add_argument("--json", action="store_true", help="with --once: print the raw JSON state message")
    p.add_argument("--timeout", type=positive, default=5.0, metavar="S",
                   help="with --once: give up after S seconds without state (exit 1); live: say which robots "
                        "answer after S seconds without state; default 5")
    p.add_argument("--refresh", type=positive, default=None, metavar="HZ",
                   help=f"live view: screens per second (default {REFRESH_HZ:g}; 0.2 redraws every 5 s)")
    p.add_argument("--all", action="store_true", help="every robot seen (a fleet behind a router), one line each")
    p.add_argument("--count", type=_robots, default=None, metavar="N",
                   help="with --all --once: print as soon as N robots sent state (exit 1 if fewer within --timeout)")
    p.set_defaults(func=_run)


class View:
    """Latest state and recent events, filled by zenoh callbacks."""

    def __init__(self, n_events: int = 10):
        self.lock = threading.Lock()
        self.state: dict | None = None
        self.events: collections.deque = collections.deque(maxlen=n_events)
        self.got_state = threading.Event()
        self.n_state = 0
        self.last_rx = 0.0

    def on_state(self, sample) -> None:
        try:
            msg = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        with self.lock:
            self.state, self.n_state, self.last_rx = msg, self.n_state + 1, time.monotonic()
        self.got_state.set()

    def load_history(self, session, key: str, timeout_s: float = 1.0) -> None:
        """Events that happened before this monitor started (the robot keeps the last 20)."""
        try:
            for reply in session.get(key, timeout=timeout_s):
                if reply.ok is None:
                    continue
                past = json.loads(reply.ok.payload.to_bytes()).get("events", [])
                with self.lock:
                    seen = {e.get("seq") for e in self.events}
                    merged = [e for e in past if e.get("seq") not in seen] + list(self.events)
                    self.events.clear()
                    self.events.extend(merged)
        except Exception:
            pass  # history is a convenience: live events still arrive

    def on_event(self, sample) -> None:
        try:
            msg = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        with self.lock:
            self.events.append(msg)


def _pose(p) -> str:
    if not p:
        return "-"
    return f"x {p['x']:+.3f} m  z {p['z']:+.3f} m  theta {p['theta']:+.3f} rad"


def _event_line(e: dict) -> str:
    extra = " ".join(f"{k}={v}" for k, v in e.items()
                     if k not in ("schema", "version", "robot", "seq", "stamp_ns", "kind"))
    return f"#{e.get('seq', '?'):<5} {e.get('kind', '?'):<18} {extra}"[:160]


def _rate(x) -> str:
    """A wheel rate, or n/a when not measured (null: the drive was unreachable)."""
    return "  n/a" if x is None else f"{x:+.2f}"


def render(robot: str, state: dict | None, events, rx_age_s: float | None = None) -> str:
    lines = [f"vbnav monitor  robot {robot}"]
    if state is None:
        lines.append("  (no state received yet)")
    else:
        s = state
        safety = s.get("safety", {})
        faults = ", ".join(safety.get("faults", [])) or "none"
        drive = s.get("drive", {})
        drive_faults = ", ".join(f"{f.get('kind')} ({f.get('device')})" for f in drive.get("faults", [])) or "none"
        loop = s.get("loop", {})
        wh = s.get("wheels", {})
        cmd, meas = wh.get("cmd", {}), wh.get("meas", {})
        lines += [
            f"  mode    {s.get('mode')}" + (f"  route {s['route']}" if s.get("route") else "")
            + (f"  keyframe {s['keyframe']}" if s.get("keyframe") is not None else ""),
            f"  safety  {safety.get('state')}   faults: {faults}",
            f"  odom    {_pose(s.get('pose', {}).get('odom'))}",
            f"  vbc     {_pose(s.get('pose', {}).get('vbc'))}",
            f"  vslam   {_pose(s.get('pose', {}).get('vslam'))}",
            f"  wheels  cmd L {_rate(cmd.get('left'))} R {_rate(cmd.get('right'))} rad/s   "
            f"meas L {_rate(meas.get('left'))} R {_rate(meas.get('right'))} rad/s",
            f"  drive   {drive.get('state')}   faults: {drive_faults}",
            f"  twist   v {s.get('twist', {}).get('linear', 0):+.3f} m/s  w {s.get('twist', {}).get('angular', 0):+.3f} rad/s",
            f"  loop    {loop.get('rate_hz', 0):.0f} Hz  cycle {s.get('cycle')}  compute {loop.get('compute_ms', 0):.2f} ms"
            f"  lateness {loop.get('lateness_ms', 0):.2f} ms  overruns {loop.get('overruns', 0)}",
        ]
        if rx_age_s is not None:
            lines.append(f"  last state received {rx_age_s:.1f} s ago" + ("  (STALE)" if rx_age_s > 1.0 else ""))
    lines.append("  recent events:")
    lines += [f"    {_event_line(e)}" for e in events] or ["    (none)"]
    return "\n".join(lines)


def _seen_hint(session, robot: str, args) -> str:
    """What the network does have, when the robot asked for is silent."""
    seen = robots_seen(session)
    if not seen:
        return (f"no robot answers at {args.connect} (is `vbnav run` going, with its telemetry.listen on this "
                f"endpoint and telemetry enabled?)")
    if robot in seen:
        return (f"robot {robot} answers but publishes no state (telemetry.state_rate_hz, or its "
                f"telemetry.operators refuse this client)")
    return f"robots seen at {args.connect}: {', '.join(seen)} (pick one with --robot NAME or -c CONFIG)"


def _not_applied(args) -> Optional[str]:
    """Why an option given would not be used with the others, or None."""
    if args.count is not None and not (args.all and args.once):
        return "--count goes with --all --once"
    if args.json and not args.once:
        return "--json prints one state with --once; the live view is not JSON"
    if args.all and args.json:
        return "--json prints a single robot's state; --all shows every robot (one line each)"
    if args.all and (args.robot or args.config):
        named = "--robot" if args.robot else "--config"
        return f"--all shows every robot; {named} names one robot (give one or the other)"
    if args.once and args.refresh is not None:
        return "--refresh is the live view's rate; --once prints once and exits"
    return None


def _run(args) -> int:
    view = View()
    why = _not_applied(args)
    if why:
        print(f"vbnav monitor: {why}", file=sys.stderr)
        return 2
    if args.refresh is None:
        args.refresh = REFRESH_HZ
    if args.all:        # every robot: no name to resolve
        from vbnav.control.comms.fleet_view import run_all
        try:
            session = open_client(args)
        except ConnectionError as exc:
            print(f"vbnav monitor: {exc}", file=sys.stderr)
            return 3
        try:
            return run_all(args, session)
        except KeyboardInterrupt:
            return 0
        finally:
            session.close()
    try:
        session, robot = open_robot(args, "vbnav monitor")
    except ConnectionError as exc:
        print(f"vbnav monitor: {exc}", file=sys.stderr)
        return 3
    except LookupError as exc:
        print(f"vbnav monitor: {exc}", file=sys.stderr)
        return 1
    try:
        session.declare_subscriber(f"vbnav/{robot}/state", view.on_state)
        session.declare_subscriber(f"vbnav/{robot}/events", view.on_event)
        view.load_history(session, f"vbnav/{robot}/events/recent")
        if args.once:
            if not view.got_state.wait(args.timeout):
                print(f"vbnav monitor: no state on vbnav/{robot}/state within {args.timeout:g} s; "
                      f"{_seen_hint(session, robot, args)}", file=sys.stderr)
                return 1
            with view.lock:
                state, events = view.state, list(view.events)
            print(json.dumps(state) if args.json else render(robot, state, events))
            return 0
        period = 1.0 / args.refresh
        started, hint = time.monotonic(), None
        while True:
            with view.lock:
                state, events, last = view.state, list(view.events), view.last_rx
            age = time.monotonic() - last if state is not None else None
            text = render(robot, state, events, age)
            if state is None and time.monotonic() - started > args.timeout:
                if hint is None:
                    hint = _seen_hint(session, robot, args)
                text += f"\n  no state from {robot} after {args.timeout:g} s: {hint}"
            sys.stdout.write("\x1b[H\x1b[2J" + text + "\n")
            sys.stdout.flush()
            time.sleep(period)
    except KeyboardInterrupt:
        return 0
    finally:
        session.close()
