"""Telemetry cost on the loop thread, and delivery to a subscriber in another process.

Two ways to get a state message out of a fixed-rate loop, measured in the same run:

- ours: the loop builds a ``StateSample`` and calls ``TelemetryPublisher.offer_state`` (a queue hop);
  the publisher thread serialises it to JSON and puts it with an express, congestion-control-DROP
  zenoh publisher;
- bare: the loop serialises the same message and calls ``publisher.put`` itself (same zenoh options).

Every cycle publishes (state rate = loop rate, the worst case), at 100 Hz and 1 kHz. The subscriber is
a separate process (a zenoh client on loopback); latency is its receive time minus the sample's stamp,
both ``time.monotonic_ns`` (one clock for all processes on a machine).

The live view (comms/live_view.py) at the default rates: a 100 Hz loop with 20 Hz state and 2 Hz camera
images (640x480, JPEG at 320 px), published to zenoh only, then to zenoh and the Foxglove WebSocket server
with a Foxglove client (another process) subscribed to every channel: the loop-thread cost of each, and the
bytes per second the client receives per channel and the zenoh payload bytes per second.

Usage: python benchmarks/telemetry.py [--seconds 3] [--port 0]
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import time

import numpy as np

KEY = "vbnav/bench/state"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ---- subscriber process ---------------------------------------------------------------------

def subscriber(port: int, seconds: float) -> None:
    from vbnav.control.comms.network import client_session_config, open_session
    recv: list[tuple[int, int, int]] = []   # (run, seq, latency ns)

    def on(sample):
        now = time.monotonic_ns()
        m = json.loads(sample.payload.to_bytes())
        recv.append((m["run"], m["seq"], now - m["stamp_ns"]))

    s = open_session(client_session_config([f"tcp/127.0.0.1:{port}"]))
    s.declare_subscriber(KEY, on)
    print("READY", flush=True)
    for line in sys.stdin:               # the parent says "DONE" when all runs are over
        if line.strip() == "DONE":
            break
    time.sleep(0.5)
    s.close()
    json.dump(recv, sys.stdout)


# ---- publisher side -------------------------------------------------------------------------

from vbnav.control.comms.telemetry import StateSample  # noqa: E402
from vbnav.vision.geometry import Pose2  # noqa: E402


def sample_for(stamp_ns: int, cycle: int):
    return StateSample(stamp_ns, cycle, "repeat", "ok", (), Pose2(1.234, 5.678, 0.321), None, None, 12,
                       3.1, 3.3, 3.05, 3.28, 0.16, 0.05, 180_000, 60_000, 0, "routes/corridor.json")


def run_loop(rate_hz: float, seconds: float, publish_one) -> np.ndarray:
    """Fixed-rate loop on absolute deadlines; returns the loop-thread cost of publish_one per cycle (ns)."""
    from vbnav.drivers.clock import MonotonicClock
    clock = MonotonicClock()
    period = int(1e9 / rate_hz)
    n = int(seconds * rate_hz)
    cost = np.zeros(n, dtype=np.int64)
    deadline = clock.now_ns()
    for k in range(n):
        clock.sleep_until(deadline)
        t0 = time.perf_counter_ns()
        publish_one(k, time.monotonic_ns())
        cost[k] = time.perf_counter_ns() - t0
        deadline += period
    return cost


class RunTaggingSink:
    """Our ZenohSink behaviour (express, DROP) with the run id added, so one subscriber can tell runs apart."""

    def __init__(self, publisher, run_id: int):
        self.pub, self.run = publisher, run_id

    def state(self, stamp_ns, payload, msg):
        msg["run"] = self.run
        self.pub.put(json.dumps(msg, separators=(",", ":")).encode())

    def event(self, *a): ...
    def image(self, *a): ...
    def close(self): ...


# ---- live view (Foxglove WebSocket) -----------------------------------------------------------

def foxglove_client(port: int, seconds: float) -> None:
    """Another process: subscribe to every channel and count the bytes received per topic."""
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))
    from foxglove_client import FoxgloveClient
    c = FoxgloveClient("127.0.0.1", port)
    chans = c.wait_for_channels(["/vbnav/state", "/vbnav/image"])
    subs = {i: ch for i, ch in enumerate(chans.values(), start=1)}
    c.subscribe({i: ch["id"] for i, ch in subs.items()})
    print("READY", flush=True)
    got: dict[str, int] = {}
    for line in sys.stdin:
        if line.strip() == "GO":
            break
    t0, end = time.monotonic(), time.monotonic() + seconds
    while time.monotonic() < end:
        m = c.poll(0.2)
        if m is not None:
            topic = subs[m[0]]["topic"]
            got[topic] = got.get(topic, 0) + len(m[2])
    c.close()
    json.dump({"seconds": time.monotonic() - t0, "bytes": got}, sys.stdout)


class ZenohBytes:
    """A sink that counts the zenoh payload bytes (what ZenohSink would put), per key."""

    def __init__(self):
        self.bytes = {"state": 0, "events": 0, "image": 0}

    def state(self, stamp_ns, payload, msg):
        self.bytes["state"] += len(payload)

    def event(self, stamp_ns, payload, msg):
        self.bytes["events"] += len(payload)

    def image(self, stamp_ns, payload, msg, jpeg):
        self.bytes["image"] += len(payload)

    def annotations(self, *a): ...
    def foxglove(self, *a): ...
    def close(self): ...


def live_view_runs(seconds: float) -> None:
    from vbnav.control.comms.live_view import LiveView
    from vbnav.control.comms.telemetry import TelemetryPublisher
    from vbnav.control.config.telemetry import TelemetryConfig
    from vbnav.control.comms.foxglove_channels import Overlay
    from vbnav.control.config import load_config
    from vbnav.control.runtime.factory import make_world
    from vbnav.drivers.sim.render import Renderer
    from vbnav.vision.camera_model import PinholeCamera
    from vbnav.vision.geometry import camera_pose
    cfg = load_config(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "configs", "sim.yaml"))
    c = cfg.camera        # the simulated room's view from the start pose: a camera image of realistic texture
    R, t = camera_pose(cfg.sim.start(), c.mount.to_mount())
    image = Renderer(make_world(cfg), PinholeCamera(c.width, c.height, c.fx, c.fy, c.cx, c.cy)).render(R, t).image
    rng = np.random.default_rng(0)
    overlay = Overlay(tracked=rng.uniform(0, 480, (200, 2)))   # 200 tracked features (vbc.max_features)

    def loop(pub):
        def one(k, now):
            if pub.state_due(now):
                pub.offer_state(sample_for(now, k))
            if pub.image_due(now):           # on a robot the vision thread offers it; a queue put either way
                pub.offer_image(image, now, k, overlay)
        return run_loop(100.0, seconds, one)

    results = []
    zb = ZenohBytes()
    pub = TelemetryPublisher("bench", [zb], state_rate_hz=20.0, loop_rate_hz=100.0, image_rate_hz=2.0).start()
    cost = loop(pub)
    pub.close()
    results.append(("zenoh payloads only", cost))
    tcfg = TelemetryConfig(live_view={"enabled": True, "port": 0})
    lv = LiveView(tcfg, "bench", lambda k, p: None, lambda k, r, p: None, lambda t: t)
    cl = subprocess.Popen([sys.executable, os.path.abspath(__file__), "--foxglove-client", str(lv.port),
                           "--seconds", str(seconds)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert cl.stdout.readline().strip() == "READY", "Foxglove client did not start"
    time.sleep(0.5)
    cl.stdin.write("GO\n")
    cl.stdin.flush()
    pub = TelemetryPublisher("bench", [ZenohBytes(), lv], state_rate_hz=20.0, loop_rate_hz=100.0,
                             image_rate_hz=2.0).start()
    cost = loop(pub)
    rx = json.loads(cl.stdout.read())      # the client counts for as long as the loop ran, then reports
    cl.wait(10)
    pub.close()
    results.append(("zenoh + live view, 1 client", cost))
    print()
    print(f"live view at the default rates: 100 Hz loop, 20 Hz state, 2 Hz 640x480 simulated camera images "
          f"(JPEG at 320 px), "
          f"{seconds:g} s per run")
    print(f"  {'publishing to':<30} {'loop cost us p50':>16} {'p99':>7}")
    for name, c in results:
        c50, c99 = np.percentile(c, [50, 99]) * 1e-3
        print(f"  {name:<30} {c50:>16.1f} {c99:>7.1f}")
    base, with_lv = (np.percentile(c, 50) for _, c in results)
    print(f"  loop-thread cost with the live view / without (median): {with_lv / base:.2f}x")
    per_s = {k: v / seconds for k, v in zb.bytes.items()}
    print(f"  zenoh payload bytes/s per robot: state {per_s['state']:.0f}, image {per_s['image']:.0f}, "
          f"total {sum(per_s.values()):.0f}")
    total = sum(rx["bytes"].values()) / rx["seconds"]
    print(f"  Foxglove client receives {total:.0f} B/s (message payloads):")
    for topic, n in sorted(rx["bytes"].items()):
        print(f"    {topic:<28} {n / rx['seconds']:>9.0f} B/s")
    lv.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=3.0, help="per run (default 3)")
    ap.add_argument("--port", type=int, default=0, help="loopback port (default: a free one)")
    ap.add_argument("--subscriber", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--foxglove-client", type=int, default=0, help=argparse.SUPPRESS)
    a = ap.parse_args()
    port = a.port or free_port()
    if a.subscriber:
        subscriber(port, a.seconds)
        return 0
    if a.foxglove_client:
        foxglove_client(a.foxglove_client, a.seconds)
        return 0

    import zenoh

    from vbnav.control.config.telemetry import TelemetryConfig

    from vbnav.control.comms.network import open_session, robot_session_config
    from vbnav.control.comms.telemetry import TelemetryPublisher, state_message

    session = open_session(robot_session_config(TelemetryConfig(listen=[f"tcp/127.0.0.1:{port}"]), "bench"))
    zpub = session.declare_publisher(KEY, express=True, congestion_control=zenoh.CongestionControl.DROP)
    sub = subprocess.Popen([sys.executable, os.path.abspath(__file__), "--subscriber", "--port", str(port)],
                           stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert sub.stdout.readline().strip() == "READY", "subscriber did not start"
    time.sleep(0.5)  # let the subscription reach this session

    runs = []  # (run id, name, rate, sent, cost array)
    run_id = 0
    for rate in (100.0, 1000.0):
        # floor: an empty call, same loop (a core waking from sleep has cold caches)
        run_id += 1
        cost = run_loop(rate, a.seconds, lambda k, now: None)
        runs.append((run_id, "floor: empty call", rate, 0, cost))
        # ours: the loop only offers a sample
        run_id += 1
        pub = TelemetryPublisher("bench", [RunTaggingSink(zpub, run_id)], state_rate_hz=rate, loop_rate_hz=rate)
        pub.start()
        cost = run_loop(rate, a.seconds, lambda k, now: pub.offer_state(sample_for(now, k)))
        pub.close()
        runs.append((run_id, "ours: offer_state (queue hop)", rate, len(cost) - pub.dropped, cost))
        time.sleep(0.3)
        # bare: serialise and put on the loop thread
        run_id += 1
        rid = run_id

        def bare(k, now, rid=rid, rate=rate):
            msg = state_message("bench", k + 1, sample_for(now, k), rate)
            msg["run"] = rid
            zpub.put(json.dumps(msg, separators=(",", ":")).encode())

        cost = run_loop(rate, a.seconds, bare)
        runs.append((run_id, "bare: json + zenoh put on loop", rate, len(cost), cost))
        time.sleep(0.3)

    # as the runtime uses it: 100 Hz loop, state at 20 Hz (state_due on every cycle, a sample every 5th)
    run_id += 1
    pub = TelemetryPublisher("bench", [RunTaggingSink(zpub, run_id)], state_rate_hz=20.0, loop_rate_hz=100.0)
    pub.start()
    cost = run_loop(100.0, a.seconds,
                    lambda k, now: pub.offer_state(sample_for(now, k)) if pub.state_due(now) else None)
    pub.close()
    runs.append((run_id, "ours: 20 Hz state, per loop cycle", 100.0, len(cost) // 5, cost))
    time.sleep(0.3)

    sub.stdin.write("DONE\n")
    sub.stdin.flush()
    recv = json.loads(sub.stdout.read())
    sub.wait(10)
    session.close()
    payload = len(json.dumps(state_message("bench", 1, sample_for(0, 0), 100.0)))
    print(f"state payload {payload} B, {a.seconds:g} s per run, subscriber in another process (zenoh client, "
          f"tcp loopback), every cycle publishes")
    print(f"{'rate':>6}  {'method':<32} {'loop cost us p50':>16} {'p99':>7} {'delivered':>9} "
          f"{'latency ms p50':>14} {'p99':>7}")
    by_run: dict[int, list[int]] = {}
    for r, _, lat in recv:
        by_run.setdefault(r, []).append(lat)
    table = {}
    for rid, name, rate, sent, cost in runs:
        c50, c99 = np.percentile(cost, [50, 99]) * 1e-3
        table.setdefault((rate, name[:4]), c50)
        if name.startswith("floor"):
            print(f"{rate:>6.0f}  {name:<32} {c50:>16.1f} {c99:>7.1f} {'-':>9} {'-':>14} {'-':>7}")
            continue
        lat = np.array(by_run.get(rid, [0]), dtype=np.float64) * 1e-6
        delivered = len(by_run.get(rid, [])) / (sent if name.startswith("ours: 20") else len(cost))
        l50, l99 = np.percentile(lat, [50, 99])
        print(f"{rate:>6.0f}  {name:<32} {c50:>16.1f} {c99:>7.1f} {delivered:>9.3f} {l50:>14.3f} {l99:>7.3f}")
    for rid, name, rate, sent, cost in runs:
        if name.startswith("ours: offer"):
            print(f"{rate:.0f} Hz ours: {len(cost) - sent} of {len(cost)} samples dropped at the queue (publisher "
                  f"thread behind; the loop never waits)")
    for rate in (100.0, 1000.0):
        print(f"loop-thread cost at {rate:.0f} Hz, bare put / ours (median): "
              f"{table[(rate, 'bare')] / table[(rate, 'ours')]:.1f}x")
    live_view_runs(a.seconds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
