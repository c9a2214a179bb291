"""What the network carries per robot at the default telemetry rates (docs/fleet.md quotes the figure).

The simulated robot runs in real time (``sim.realtime: true``) teaching its room loop with the default
``telemetry:`` section (state 20 Hz, JPEG 2 Hz at 320 px, quality 70) on a loopback port; a zenoh client
in this process subscribes to ``vbnav/<robot>/**`` and counts the payload bytes of every key for the
run. Payload bytes only: zenoh's framing adds a few bytes per message, TCP/IP about 50 more.

Usage: python benchmarks/fleet_bandwidth.py [--seconds 20]
"""
from __future__ import annotations

import argparse
import collections
import socket
import tempfile
import threading
import time
from pathlib import Path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=20.0)
    a = ap.parse_args()
    from vbnav.control.comms.network import client_session_config, open_session
    from vbnav.control.config import load_config
    from vbnav.control.runtime.factory import make_robot
    from vbnav.control.session import Session, teach_driver

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cfg = load_config(None, overrides={"sim": {"realtime": True}, "telemetry": {"listen": [endpoint]}})
    t = cfg.telemetry
    counts: dict = collections.defaultdict(lambda: [0, 0])      # key -> [messages, payload bytes]
    lock = threading.Lock()
    window = {"start": None}

    def on_sample(sample) -> None:
        if window["start"] is None:
            return
        with lock:
            c = counts[str(sample.key_expr)]
            c[0] += 1
            c[1] += len(sample.payload)

    robot = make_robot(cfg, with_camera=True)
    session_box = {}

    def subscribe_when_up() -> None:       # the robot's session opens inside teach(): connect once it listens
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            try:
                s = open_session(client_session_config([endpoint]))
                s.declare_subscriber(f"vbnav/{cfg.robot.name}/**", on_sample)
                session_box["s"] = s
                time.sleep(2.0)              # let the run settle, then count
                window["start"] = time.monotonic()
                return
            except Exception:
                time.sleep(0.2)

    th = threading.Thread(target=subscribe_when_up, daemon=True)
    th.start()
    with tempfile.TemporaryDirectory() as tmp:
        Session(cfg, robot).teach(teach_driver(cfg), Path(tmp) / "loop", duration_s=a.seconds + 4.0)
    span = time.monotonic() - window["start"] if window["start"] else 0.0
    if "s" in session_box:
        session_box["s"].close()
    print(f"robot {cfg.robot.name}: state {t.state_rate_hz:g} Hz, image {t.image_rate_hz:g} Hz at {t.image_width} px "
          f"q{t.jpeg_quality}, counted for {span:.1f} s (teaching the room loop in real time)")
    total = 0
    for key, (n, size) in sorted(counts.items()):
        total += size
        print(f"  {key:<28} {n / span:6.1f} msg/s  {size / max(n, 1):8.0f} B/msg  {size / span / 1000:7.1f} kB/s")
    print(f"  total payload                {total / span / 1000:7.1f} kB/s  ({total * 8 / span / 1e6:.2f} Mbit/s)")


if __name__ == "__main__":
    main()
