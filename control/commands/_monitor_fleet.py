"""``vbnav monitor --all``: every robot seen through a router (or on one endpoint), one line each, live.

Subscribes to ``vbnav/*/state`` and ``vbnav/*/events``; a robot appears with its first message and
stays listed (marked STALE after a second of silence, so a robot that dropped off shows as such)."""
from __future__ import annotations

import json
import sys
import threading
import time


class FleetView:
    """Latest state and last event of every robot, filled by zenoh callbacks."""

    def __init__(self):
        self.lock = threading.Lock()
        self.robots: dict[str, dict] = {}      # name -> {"state", "rx", "event", "n"}

    def _entry(self, robot: str) -> dict:
        return self.robots.setdefault(robot, {"state": None, "rx": 0.0, "event": None, "n": 0})

    @staticmethod
    def _parse(sample):
        """(robot, message) of a telemetry sample, or None for anything that is not one."""
        try:
            msg = json.loads(sample.payload.to_bytes())
            return str(msg["robot"]), msg
        except (ValueError, KeyError, TypeError):
            return None

    def on_state(self, sample) -> None:
        got = self._parse(sample)
        if got is not None:
            with self.lock:
                e = self._entry(got[0])
                e["state"], e["rx"], e["n"] = got[1], time.monotonic(), e["n"] + 1

    def on_event(self, sample) -> None:
        got = self._parse(sample)
        if got is not None:
            with self.lock:
                self._entry(got[0])["event"] = got[1]

    def snapshot(self) -> dict[str, dict]:
        with self.lock:
            return {k: dict(v) for k, v in self.robots.items()}


def robot_line(name: str, e: dict, now: float) -> str:
    s = e["state"]
    if s is None:
        head = f"{name:<16} (events only)"
    else:
        odom = (s.get("pose") or {}).get("odom") or {}
        safety = s.get("safety") or {}
        faults = ",".join(f.split(":")[0] for f in safety.get("faults", []))
        tw = s.get("twist") or {}
        age = now - e["rx"]
        head = (f"{name:<16} {s.get('mode', '?'):<9} {safety.get('state', '?'):<7} "
                f"x {odom.get('x', 0.0):+7.2f} z {odom.get('z', 0.0):+7.2f} th {odom.get('theta', 0.0):+5.2f}  "
                f"v {tw.get('linear') or 0.0:+.2f} w {tw.get('angular') or 0.0:+.2f}  "
                f"{'STALE ' + format(age, '.1f') + ' s' if age > 1.0 else 'live'}"
                + (f"  [{faults}]" if faults else ""))
    ev = e["event"]
    if ev is not None:
        head += f"  last event: {ev.get('kind')}"
    return head[:200]


def render(view: FleetView) -> str:
    robots = view.snapshot()
    now = time.monotonic()
    lines = [f"vbnav monitor --all  {len(robots)} robot(s)"]
    lines += [robot_line(n, robots[n], now) for n in sorted(robots)] or ["  (no robot seen yet)"]
    return "\n".join(lines)


def run_fleet(args, session) -> int:
    view = FleetView()
    session.declare_subscriber("vbnav/*/state", view.on_state)
    session.declare_subscriber("vbnav/*/events", view.on_event)
    if args.once:
        # --once --all: wait --timeout seconds, then print every robot seen (one line each)
        time.sleep(args.timeout)
        robots = view.snapshot()
        if args.json:
            print(json.dumps({n: r["state"] for n, r in sorted(robots.items())}))
        else:
            print(render(view))
        return 0 if robots else 1
    period = 1.0 / max(0.5, args.refresh)
    while True:
        sys.stdout.write("\x1b[H\x1b[2J" + render(view) + "\n")
        sys.stdout.flush()
        time.sleep(period)
