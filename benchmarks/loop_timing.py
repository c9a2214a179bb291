"""Loop timing: our absolute-deadline loop vs a naive time.sleep(period) loop.

Both run the same work per cycle (a real Runtime cycle: simulated drive read,
odometry, scripted controller, limits, safety, write) at 100 Hz and 500 Hz,
once on an idle machine and once with an image-processing thread (OpenCV blur +
corner detection on 640x480, one OpenCV thread) in the same process.

Wake-up lateness is measured against each loop's ideal grid start + k * period,
so the naive loop's drift shows up as growing lateness; its period error is
printed too. Usage: python benchmarks/loop_timing.py [--seconds 30]
"""
from __future__ import annotations

import argparse
import threading
import time

import cv2
import numpy as np

from vbnav.control.config import Config
from vbnav.control.controllers.manual import ScriptedController
from vbnav.control.runtime.runtime import Runtime
from vbnav.drivers.clock import MonotonicClock
from vbnav.drivers.sim.base import BaseParams, SimDiffDrive


def make_runtime(rate_hz: float, rt_sched: bool = False) -> Runtime:
    loop = {"rate_hz": rate_hz, "max_missed_streak": 10**9, "stall_periods": 10**9}
    if rt_sched:
        loop.update(realtime_priority=50)
    cfg = Config.model_validate({"loop": loop})
    clock = MonotonicClock()
    drive = SimDiffDrive(BaseParams(), clock)
    rt = Runtime(cfg, drive, ScriptedController([[0.2, 0.3, 1e6]]), clock)
    drive.connect()
    drive.enable()
    rt._start_ns = clock.now_ns()
    return rt


def ours(rate_hz: float, seconds: float, rt_sched: bool = False) -> dict:
    """Our loop. Without rt_sched: Python's default scheduling and switch interval (5 ms);
    with it: the runtime's real-time settings (SCHED_FIFO 50, GIL switch interval 0.2 ms)."""
    rt = make_runtime(rate_hz, rt_sched)
    n = int(seconds * rate_hz)
    restore = rt._apply_scheduling() if rt_sched else (lambda: None)
    try:
        summary = rt.loop.run(lambda c, now: rt._cycle(c, now) or True, max_cycles=n)
    finally:
        restore()
    if rt.safety.events:
        print("  note:", "; ".join(e.message for e in rt.safety.events))
    L = summary.lateness_ms
    return {"p50": L["p50"], "p99": L["p99"], "max": L["max"], "overruns": summary.overruns,
            "period_err_p99": abs(summary.period_ms["p99"] - 1e3 / rate_hz), "drift_pct": 0.0}


def naive(rate_hz: float, seconds: float) -> dict:
    rt = make_runtime(rate_hz)
    period = 1.0 / rate_hz
    period_ns = int(1e9 / rate_hz)
    n = int(seconds * rate_hz)
    late = np.zeros(n, dtype=np.int64)
    wakes = np.zeros(n, dtype=np.int64)
    start = time.monotonic_ns()
    overruns = 0
    for k in range(n):
        wake = time.monotonic_ns()
        wakes[k] = wake
        late[k] = wake - (start + k * period_ns)
        rt._cycle(k, wake)
        if time.monotonic_ns() - wake > period_ns:
            overruns += 1
        time.sleep(period)
    per = np.diff(wakes)
    elapsed = (wakes[-1] - wakes[0]) * 1e-9
    return {"p50": float(np.percentile(late, 50)) * 1e-6, "p99": float(np.percentile(late, 99)) * 1e-6,
            "max": float(late.max()) * 1e-6, "overruns": overruns,
            "period_err_p99": float(np.percentile(np.abs(per - period_ns), 99)) * 1e-6,
            "drift_pct": 100.0 * (elapsed / ((n - 1) * period) - 1.0)}


class ImageLoad:
    """A vision-like load on the other core: blur + GFTT + KLT on 640x480 frames."""

    def __init__(self):
        self.stop = threading.Event()
        self.frames = 0
        rng = np.random.default_rng(0)
        self.img = cv2.GaussianBlur((rng.random((480, 640)) * 255).astype(np.uint8), (5, 5), 1.5)
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        prev = self.img
        while not self.stop.is_set():
            cur = np.roll(prev, 1, axis=1)
            pts = cv2.goodFeaturesToTrack(cur, 300, 0.01, 7)
            if pts is not None:
                cv2.calcOpticalFlowPyrLK(prev, cur, pts, None)
            cv2.GaussianBlur(cur, (7, 7), 2.0)
            prev = cur
            self.frames += 1

    def __enter__(self):
        cv2.setNumThreads(1)
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join()


def row(name, r, ref=None):
    ratio = f"  ratio naive/ours+rt p99 {r['p99'] / ref['p99']:.1f}x" if ref else ""
    return (f"  {name:7s} lateness p50 {r['p50']:8.3f}  p99 {r['p99']:8.3f}  max {r['max']:8.3f} ms  "
            f"overruns {r['overruns']:4d}  period err p99 {r['period_err_p99']:.3f} ms  "
            f"drift {r['drift_pct']:+.2f} %{ratio}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=30.0, help="duration of each run (default 30)")
    args = ap.parse_args()
    print(f"loop timing, {args.seconds:g} s per run, lateness against the ideal grid")
    for load in (False, True):
        for rate in (100.0, 500.0):
            L = ImageLoad() if load else None
            if L:
                L.__enter__()
            try:
                o = ours(rate, args.seconds)
                ort = ours(rate, args.seconds, rt_sched=True)
                nv = naive(rate, args.seconds)
            finally:
                if L:
                    L.__exit__()
            extra = f" (load: {L.frames / (3 * args.seconds):.0f} frames/s)" if L else ""
            print(f"{rate:g} Hz, {'with image load' if load else 'idle'}{extra}")
            print(row("ours", o))
            print(row("ours+rt", ort))
            print(row("naive", nv, ort))
            if rate == 100.0 and load:
                verdict = "PASS" if ort["p99"] <= 0.5 and ort["overruns"] == 0 else "MISS"
                print(f"  target (100 Hz under load: p99 <= 0.5 ms, no overruns), ours+rt: {verdict}")


if __name__ == "__main__":
    main()
