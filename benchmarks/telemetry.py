"""Telemetry cost on the loop thread, and delivery to a subscriber in another process.

Two ways to get a state message out of a fixed-rate loop, measured in the same run:

- ours: the loop builds a ``StateSample`` and calls ``TelemetryPublisher.offer_state`` (a queue hop);
  the publisher thread serialises it to JSON and puts it with an express, congestion-control-DROP
  zenoh publisher;
- bare: the loop serialises the same message and calls ``publisher.put`` itself (same zenoh options).

Every cycle publishes (state rate = loop rate, the worst case), at 100 Hz and 1 kHz. The subscriber is
a separate process (a zenoh client on loopback); latency is its receive time minus the sample's stamp,
both ``time.monotonic_ns`` (one clock for all processes on a machine).

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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=3.0, help="per run (default 3)")
    ap.add_argument("--port", type=int, default=0, help="loopback port (default: a free one)")
    ap.add_argument("--subscriber", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    port = a.port or free_port()
    if a.subscriber:
        subscriber(port, a.seconds)
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
