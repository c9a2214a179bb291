"""The fleet view of ``vbnav monitor --all``: every robot seen on the network (a fleet behind a router).

Subscribes to ``vbnav/*/state`` and ``vbnav/*/events`` and asks every robot's event history
(``vbnav/*/events/recent``), so a robot shows up as soon as it publishes or answers, and keeps a line
per robot: mode, route and keyframe, safety, odometry pose, loop rate and how long ago it was last heard.
Live (refreshes in place) by default; ``--once`` prints the table once and exits, after ``--count N``
robots were seen or ``--timeout`` seconds passed (exit 1 if fewer than N were seen).
"""
from __future__ import annotations

import json
import sys
import threading
import time

STALE_S = 2.0     # a robot not heard from for longer is marked STALE (state comes at >= 1 Hz by default 20)


class FleetView:
    """The latest state (or event) of every robot seen, filled by zenoh callbacks."""

    def __init__(self, now_s=time.monotonic):
        self.lock = threading.Lock()
        self.now = now_s
        self.robots: dict[str, dict] = {}     # name -> {"state": dict|None, "event": dict|None, "rx": s}
        self.changed = threading.Event()

    def _note(self, robot: str, kind: str, msg: dict) -> None:
        with self.lock:
            row = self.robots.setdefault(robot, {"state": None, "event": None, "rx": 0.0})
            row[kind] = msg
            row["rx"] = self.now()
        self.changed.set()

    def on_sample(self, sample) -> None:   # zenoh thread: vbnav/<robot>/state or /events
        try:
            msg = json.loads(sample.payload.to_bytes())
            robot = str(sample.key_expr).split("/")[1]
        except (ValueError, IndexError):
            return
        if isinstance(msg, dict):
            self._note(robot, "state" if msg.get("schema") == "vbnav.state" else "event", msg)

    def load_history(self, session, timeout_s: float = 1.0) -> None:
        """Robots that answer for their event history (robots that are up but idle between states)."""
        try:
            for reply in session.get("vbnav/*/events/recent", timeout=timeout_s):
                if reply.ok is None:
                    continue
                robot = str(reply.ok.key_expr).split("/")[1]
                events = json.loads(reply.ok.payload.to_bytes()).get("events", [])
                with self.lock:
                    known = robot in self.robots
                if not known:
                    self._note(robot, "event", events[-1] if events else {})
        except Exception:
            pass   # a convenience: live state still arrives

    def rows(self) -> list[tuple[str, dict]]:
        with self.lock:
            return sorted((name, dict(row)) for name, row in self.robots.items())


def _pose(p) -> str:
    return "-" if not p else f"x {p['x']:+7.2f} z {p['z']:+7.2f} th {p['theta']:+5.2f}"


def robot_line(name: str, row: dict, now_s: float) -> str:
    """One robot: name, mode, route/keyframe, safety, odometry pose, loop rate, last heard."""
    age = now_s - row["rx"]
    heard = f"{age:5.1f} s ago" + ("  STALE" if age > STALE_S else "")
    s = row.get("state")
    if not s:
        e = row.get("event") or {}
        return f"{name:<16} {'(no state yet)':<52} last event {e.get('kind', '-')}  heard {heard}"
    where = s.get("route") or "-"
    if s.get("keyframe") is not None:
        where += f"#{s['keyframe']}"
    safety = s.get("safety", {})
    faults = ",".join(safety.get("faults", []))
    loop = s.get("loop", {})
    return (f"{name:<16} {str(s.get('mode')):<8} {where:<16} {str(safety.get('state')):<7} "
            f"{_pose(s.get('pose', {}).get('odom')):<34} {loop.get('rate_hz', 0):4.0f} Hz  heard {heard}"
            + (f"  faults {faults}" if faults else ""))


def render_fleet(rows, now_s: float) -> str:
    lines = [f"vbnav monitor --all  {len(rows)} robot(s)",
             f"{'ROBOT':<16} {'MODE':<8} {'ROUTE#KF':<16} {'SAFETY':<7} {'ODOMETRY (m, rad)':<34} LOOP     LAST"]
    lines += [robot_line(name, row, now_s) for name, row in rows] or ["  (no robot seen yet)"]
    return "\n".join(lines)


def run_all(args, session) -> int:
    """The fleet view on an open client session (monitor.py opens and closes it)."""
    view = FleetView()
    session.declare_subscriber("vbnav/*/state", view.on_sample)
    session.declare_subscriber("vbnav/*/events", view.on_sample)
    view.load_history(session)
    if args.once:
        want = args.count or 0
        deadline = time.monotonic() + args.timeout
        while time.monotonic() < deadline:
            if want and sum(1 for _, r in view.rows() if r.get("state")) >= want:
                break
            view.changed.wait(0.1)
            view.changed.clear()
        rows = view.rows()
        print(render_fleet(rows, view.now()))
        seen = sum(1 for _, r in rows if r.get("state"))
        if want and seen < want:
            print(f"vbnav monitor: {seen} robot(s) with state within {args.timeout:g} s, expected {want}",
                  file=sys.stderr)
            return 1
        return 0 if rows else 1
    period = 1.0 / args.refresh
    started = time.monotonic()
    while True:
        rows = view.rows()
        text = render_fleet(rows, view.now())
        if not any(r.get("state") for _, r in rows) and time.monotonic() - started > args.timeout:
            text += (f"\n  no robot has sent state in {args.timeout:g} s at {args.connect} (is `vbnav run` going, "
                     f"with telemetry enabled and its telemetry.listen reachable from here?)")
        sys.stdout.write("\x1b[H\x1b[2J" + text + "\n")
        sys.stdout.flush()
        time.sleep(period)
