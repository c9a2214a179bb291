"""Dynamixel bus time per control cycle, over a pseudo-terminal to the emulator in its own process.

1. One cycle of our driver (one GroupSyncWrite of Goal Velocity + one sync read of Present
   Velocity/Position for 2 servos) beside the naive cycle (per servo: write4ByteTxRx of Goal
   Velocity, read4ByteTxRx of Present Velocity and of Present Position), same bus, same run:
   median and p99 of each and the ratio.
2. A 100 Hz loop on absolute deadlines with servo 2 missing from the bus: achieved rate and
   overruns, with our budgeted answer window against the stock SDK PortHandler (whose wait for
   a missing answer is 2 x LATENCY_TIMER 16 ms + 2 ms).

The emulator answers faster than a real 1 Mbps bus (a pty has no baud rate and no USB latency),
so absolute numbers are host overheads; the ratio and the missing-servo behaviour carry over.
Usage: python benchmarks/motor_bus.py [--cycles 500] [--seconds 2]
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time

import numpy as np
import dynamixel_sdk as sdk

from vbnav.drivers.dynamixel import BudgetedPort, DynamixelDrive
from vbnav.drivers.dynamixel_table import GOAL_VELOCITY, PRESENT_POSITION, PRESENT_VELOCITY, RETURN_DELAY_TIME, TORQUE_ENABLE


def start_emulator(ids: str):
    proc = subprocess.Popen([sys.executable, "-m", "vbnav.control.cli", "emulate", "dynamixel", "--ids", ids],
                            stdout=subprocess.PIPE, text=True)
    return proc, proc.stdout.readline().strip()


def stats(ns: list[int]) -> str:
    a = np.asarray(ns) / 1e6
    return f"median {np.median(a):6.3f} ms  p99 {np.percentile(a, 99):6.3f} ms  max {a.max():6.3f} ms"


def bench_cycles(path: str, cycles: int) -> tuple[list[int], list[int]]:
    drive = DynamixelDrive(options=DynamixelDrive.Options(port=path, margin_ms=3.0, max_missed_reads=10**6))
    drive.connect()
    drive.enable()
    ours = []
    for k in range(cycles):
        v = 2.0 * np.sin(k * 0.05)
        t0 = time.perf_counter_ns()
        drive.write(v, v)
        drive.read()
        ours.append(time.perf_counter_ns() - t0)
    drive.close()
    # the naive peer as the SDK's examples write it: stock PortHandler, one transaction per register
    port, ph = sdk.PortHandler(path), sdk.PacketHandler(2.0)
    port.openPort()
    naive = []
    for k in range(cycles):
        u = int(80 * np.sin(k * 0.05)) & 0xFFFFFFFF
        t0 = time.perf_counter_ns()
        for i in (1, 2):
            ph.write4ByteTxRx(port, i, GOAL_VELOCITY.address, u)
            ph.read4ByteTxRx(port, i, PRESENT_VELOCITY.address)
            ph.read4ByteTxRx(port, i, PRESENT_POSITION.address)
        naive.append(time.perf_counter_ns() - t0)
    for i in (1, 2):
        ph.write1ByteTxRx(port, i, TORQUE_ENABLE.address, 0)
    port.closePort()
    return ours, naive


def loop_with_missing_servo(port, seconds: float, rate_hz: float = 100.0) -> dict:
    """Sync write + sync read of ids 1 and 2 at ``rate_hz`` where id 2 never answers."""
    ph = sdk.PacketHandler(2.0)
    port.openPort()
    ph.write1ByteTxRx(port, 1, RETURN_DELAY_TIME.address, 0)
    sw = sdk.GroupSyncWrite(port, ph, GOAL_VELOCITY.address, GOAL_VELOCITY.size)
    sr = sdk.GroupSyncRead(port, ph, PRESENT_VELOCITY.address, PRESENT_VELOCITY.size + PRESENT_POSITION.size)
    for i in (1, 2):
        sw.addParam(i, [0, 0, 0, 0])
        sr.addParam(i)
    period = int(1e9 / rate_hz)
    start = time.monotonic_ns()
    deadline = start
    cycles = overruns = 0
    busy = []
    while time.monotonic_ns() - start < seconds * 1e9:
        t0 = time.monotonic_ns()
        sw.txPacket()
        sr.txRxPacket()  # fails on id 2 after the answer window
        busy.append(time.monotonic_ns() - t0)
        cycles += 1
        deadline += period
        now = time.monotonic_ns()
        if now > deadline:
            overruns += 1
            deadline = now  # skip policy: re-align
        else:
            time.sleep((deadline - now) / 1e9)
    elapsed = (time.monotonic_ns() - start) / 1e9
    port.closePort()
    return {"rate": cycles / elapsed, "overruns": overruns, "cycles": cycles, "busy": busy}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cycles", type=int, default=500)
    ap.add_argument("--seconds", type=float, default=2.0)
    args = ap.parse_args(argv)

    proc, path = start_emulator("1,2")
    try:
        ours, naive = bench_cycles(path, args.cycles)
    finally:
        proc.terminate()
        proc.wait()
    print(f"bus cycle over a pty, 2 servos, {args.cycles} cycles each (emulator in its own process)")
    print(f"  sync write + sync read (DynamixelDrive): {stats(ours)}")
    print(f"  naive per-servo write4ByteTxRx + 2 x read4ByteTxRx: {stats(naive)}")
    print(f"  ratio naive/ours: median {np.median(naive) / np.median(ours):.2f}x  "
          f"p99 {np.percentile(naive, 99) / np.percentile(ours, 99):.2f}x")

    proc, path = start_emulator("1")  # servo 2 is missing from the bus
    try:
        d = DynamixelDrive.Options()  # the driver's defaults
        budgeted = loop_with_missing_servo(BudgetedPort(path, d.latency_ms, d.margin_ms), args.seconds)
        stock = loop_with_missing_servo(sdk.PortHandler(path), args.seconds)
    finally:
        proc.terminate()
        proc.wait()
    print(f"100 Hz loop, servo 2 missing, {args.seconds:g} s each")
    label = f"budgeted window (2 x {d.latency_ms:g} + {d.margin_ms:g} ms)"
    for name, r in ((label, budgeted), ("stock SDK PortHandler", stock)):
        print(f"  {name:38s}: {r['rate']:6.1f} Hz, overruns {r['overruns']}/{r['cycles']}, "
              f"bus time per cycle {stats(r['busy'])}")
    print(f"  rate ratio budgeted/stock: {budgeted['rate'] / stock['rate']:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
