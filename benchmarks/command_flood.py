"""Loop timing and estop latency under a 10 k/s teleop flood, beside a baseline in the same run.

The robot is this process: the real Runtime at 100 Hz on the real clock, the simulated drive, the
teleop controller, and TelemetryLink with its zenoh session on a loopback port (commands reach the
loop through the zenoh callback thread, CommandInbox and the command mailbox). The operator is
another process, a zenoh client on the same host, one session for everything it sends:

- baseline: teleop at 20 Hz, as a console sends it;
- flood: teleop at 10,000 messages/s (reliable, congestion control BLOCK: a slow robot slows the
  sender instead of losing messages);

- flood-rt: the same flood, with estop and resume put at zenoh's REAL_TIME priority (the teleop at
  the default DATA priority), so that the transport sends them ahead of queued teleop;

and in every phase an estop every second (queued behind the teleop already sent, unless its
priority is higher), a resume half a second later. Both processes stamp with
``time.monotonic_ns`` (one clock on one host), so:

- lateness: each cycle's wake-up after its tick (``FixedRateLoop.late_ns``);
- arrival -> zero: from the estop reaching the mailbox to the end of the cycle that wrote zero wheels;
- send -> zero: from the operator's put to the same moment (includes the transport backlog).

``>5 per`` counts cycles that started more than 5 periods late (the default stall bound, which this
benchmark disables so that it measures instead of stopping). Usage:
python benchmarks/command_flood.py [--seconds 10] [--port 0]   (about 3 x seconds + 10 s)
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

FLOOD_RATE = 10_000.0
BASELINE_RATE = 20.0
PHASES = (("baseline", BASELINE_RATE, "DATA"), ("flood", FLOOD_RATE, "DATA"), ("flood-rt", FLOOD_RATE, "REAL_TIME"))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ---- the operator (another process) ----------------------------------------------------------------

def operator(port: int, start_ns: int, seconds: float) -> None:
    import zenoh

    from vbnav.control.comms.network import client_session_config, open_session
    s = open_session(client_session_config([f"tcp/127.0.0.1:{port}"]))
    block = dict(congestion_control=zenoh.CongestionControl.BLOCK)
    teleop = s.declare_publisher("vbnav/sim/cmd/teleop", **block)
    safety = {(k, prio): s.declare_publisher(f"vbnav/sim/cmd/{k}", priority=getattr(zenoh.Priority, prio), **block)
              for k in ("estop", "resume") for prio in ("DATA", "REAL_TIME")}
    ident = {"sender": "bench", "session": f"{os.getpid()}"}
    seq = 0
    sent = {phase: 0 for phase, _, _ in PHASES}
    estops = []                                   # (name, phase, send ns)
    for i, (phase, rate, prio) in enumerate(PHASES):
        t0 = start_ns + i * int(seconds * 1e9)
        end = t0 + int(seconds * 1e9)
        # estops at spread phases of the robot's 10 ms loop period (k * 3.7 ms modulo 10 ms)
        marks = [(t0 + int((k + 0.75) * 1e9) + (k * 3_700_000) % 10_000_000, "estop", k)
                 for k in range(int(seconds) - 1)]
        marks += [(t0 + int((k + 1.25) * 1e9), "resume", k) for k in range(int(seconds) - 1)]
        marks.sort()
        while time.monotonic_ns() < t0:
            time.sleep(0.001)
        k = 0
        period = int(1e9 / rate)
        while True:
            now = time.monotonic_ns()
            if now >= end:
                break
            while marks and marks[0][0] <= now:
                _, what, i = marks.pop(0)
                name = f"{phase} {i}"
                if what == "estop":
                    estops.append((name, phase, time.monotonic_ns()))
                    safety["estop", prio].put(json.dumps({"reason": name, **ident}))
                else:
                    safety["resume", prio].put(json.dumps(ident))
            due = t0 + k * period
            if due > now:
                time.sleep(min(due - now, 1_000_000) * 1e-9)
                continue
            # Send every message that is due (bursts of up to a millisecond's worth at 10 k/s).
            while due <= now and k * period < end - t0:
                seq += 1
                teleop.put(json.dumps({"linear": 0.2, "angular": 0.0, "seq": seq,
                                              "stamp_ns": time.monotonic_ns(), **ident}))
                sent[phase] += 1
                k += 1
                due = t0 + k * period
    time.sleep(0.5)
    s.close()
    print(json.dumps({"estops": estops, "sent": sent}), flush=True)


# ---- the robot (this process) ----------------------------------------------------------------------

def robot(port: int, seconds: float) -> dict:
    from vbnav.control.comms.link import TelemetryLink
    from vbnav.control.config import Config
    from vbnav.control.controllers.manual import TeleopController
    from vbnav.control.runtime.runtime import Runtime
    from vbnav.drivers.clock import MonotonicClock
    from vbnav.drivers.sim.base import BaseParams, SimDiffDrive

    cfg = Config.model_validate({"telemetry": {"listen": [f"tcp/127.0.0.1:{port}"]},
                                 "safety": {"command_timeout_s": 0.5},
                                 # measure, do not stop: a loaded machine must not end the run
                                 "loop": {"max_missed_streak": 10 ** 6, "stall_periods": 10 ** 6}})
    clock = MonotonicClock()
    drive = SimDiffDrive(BaseParams(), clock)
    rt = Runtime(cfg, drive, TeleopController(cfg.safety.command_timeout_s), clock)
    link = TelemetryLink.attach(rt, cfg)
    n = int((len(PHASES) * seconds + 6) * cfg.loop.rate_hz)
    wake = np.zeros(n, dtype=np.int64)
    late = np.zeros(n, dtype=np.int64)
    applied = {}                                   # estop name -> (arrival ns, wheels zero ns)
    just_applied = []

    def on_command(r, cmd, outcome, now):
        if cmd.kind == "estop":
            just_applied.append((cmd.args[0] if cmd.args else "?", cmd.arrival_ns))

    def on_cycle(r, ctx, twist, wheels):          # runs after this cycle wrote the wheels
        c = ctx.cycle
        if c < n:
            wake[c], late[c] = ctx.now_ns, r.loop.late_ns
        while just_applied:
            name, arrival = just_applied.pop()
            applied[name] = (arrival, clock.now_ns())

    rt.command_listeners.append(on_command)
    rt.cycle_observers.append(on_cycle)
    start_ns = time.monotonic_ns() + 3_000_000_000      # the operator's session and the loop settle first
    op = subprocess.Popen([sys.executable, os.path.abspath(__file__), "--operator", "--port", str(port),
                           "--start-ns", str(start_ns), "--seconds", str(seconds)],
                          stdout=subprocess.PIPE, text=True)
    result = None
    try:
        result = rt.run(duration_s=(start_ns - time.monotonic_ns()) * 1e-9 + len(PHASES) * seconds + 1.0)
    finally:
        link.close(result)
    out, _ = op.communicate(timeout=60)
    report = json.loads(out.strip().splitlines()[-1])
    cycles = min(rt.cycle + 1, n)
    return {"start_ns": start_ns, "wake": wake[:cycles], "late": late[:cycles], "applied": applied,
            "estops": report["estops"], "sent": report["sent"], "inbox": link.inbox,
            "coalesced": rt.mailbox.coalesced, "result": result, "period_ns": rt.loop.period_ns}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=10.0, help="length of each phase (default 10)")
    ap.add_argument("--port", type=int, default=0, help="loopback port (default: a free one)")
    ap.add_argument("--operator", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--start-ns", type=int, default=0, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.operator:
        operator(a.port, a.start_ns, a.seconds)
        return 0
    port = a.port or free_port()
    r = robot(port, a.seconds)
    S = int(a.seconds * 1e9)
    rows = {}
    for i, (phase, _, _) in enumerate(PHASES):
        t0 = r["start_ns"] + i * S
        sel = (r["wake"] >= t0) & (r["wake"] < t0 + S)
        L = r["late"][sel] * 1e-6
        arr, snd = [], []
        lost = []
        for name, ph, sent_ns in r["estops"]:
            if ph != phase:
                continue
            if name not in r["applied"]:
                lost.append(name)
                continue
            arrival, zero = r["applied"][name]
            arr.append((zero - arrival) * 1e-6)
            snd.append((zero - sent_ns) * 1e-6)
        rows[phase] = {"cycles": int(sel.sum()), "late": np.percentile(L, [50, 99]).tolist() + [float(L.max())],
                       "arr": arr, "snd": snd, "lost": lost, "rate": r["sent"][phase] / a.seconds,
                       "stalls": int((r["late"][sel] > 5 * r["period_ns"]).sum())}
    print(f"command flood: 100 Hz loop on the real clock, simulated drive, teleop controller; operator in another "
          f"process on zenoh loopback, one session; {a.seconds:g} s per phase, an estop every second")
    print(f"{'phase':<9} {'teleop/s':>9} {'cycles':>6} | {'lateness ms p50':>15} {'p99':>7} {'max':>7} {'>5 per':>6} | "
          f"{'estops':>6} {'arrival->zero ms p50':>20} {'max':>7} | {'send->zero ms p50':>17} {'max':>8}")

    def pct(v, q):
        return float(np.percentile(v, q)) if v else float("nan")

    for phase, x in rows.items():
        n_est = len(x["arr"])
        print(f"{phase:<9} {x['rate']:>9.0f} {x['cycles']:>6} | {x['late'][0]:>15.3f} {x['late'][1]:>7.3f} "
              f"{x['late'][2]:>7.3f} {x['stalls']:>6} | {n_est:>3}/{n_est + len(x['lost']):<2} {pct(x['arr'], 50):>20.2f} "
              f"{max(x['arr'], default=float('nan')):>7.2f} | {pct(x['snd'], 50):>17.2f} "
              f"{max(x['snd'], default=float('nan')):>8.2f}")
    b = rows["baseline"]

    def ratio(u, v):
        return u / v if v > 0 else float("nan")

    for phase in ("flood", "flood-rt"):
        f = rows[phase]
        print(f"{phase + '/baseline':<26} | {ratio(f['late'][0], b['late'][0]):>15.1f} "
              f"{ratio(f['late'][1], b['late'][1]):>7.1f} {ratio(f['late'][2], b['late'][2]):>7.1f} {'':>6} | {'':>6} "
              f"{ratio(pct(f['arr'], 50), pct(b['arr'], 50)):>20.1f} "
              f"{ratio(max(f['arr'], default=0), max(b['arr'], default=1)):>7.1f} | "
              f"{ratio(pct(f['snd'], 50), pct(b['snd'], 50)):>17.1f} "
              f"{ratio(max(f['snd'], default=0), max(b['snd'], default=1)):>8.1f}")
    inbox = r["inbox"]
    print(f"teleop through the inbox: {inbox.accepted} accepted, {inbox.rejected} refused (stale or out of order), "
          f"{r['coalesced']} coalesced in the mailbox; estops lost: {sum(len(x['lost']) for x in rows.values())}; "
          f"run ended: {r['result'].reason}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
