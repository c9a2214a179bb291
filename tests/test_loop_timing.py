"""The control loop's timing summary (control/runtime/loop.py LoopTiming)."""
from __future__ import annotations

from vbnav.control.runtime.loop import LoopTiming

PERIOD = 10_000_000          # 100 Hz, ns


def _cycles(timing: LoopTiming, n: int, slow_at: int, slow_ns: int) -> None:
    t = 0
    for k in range(n):
        work = slow_ns if k == slow_at else 100_000
        timing.record(t, t, t + work)
        t += max(PERIOD, work)


def test_the_max_is_the_whole_runs_beyond_the_ring_buffers():
    """Found by the messages audit: the summary's max came from the ring buffers (the last 65,536 cycles, 11
    minutes at 100 Hz), so a 300 ms cycle earlier in a long run was 'compute max 0.100 ms' beside 'overruns 1'.
    The max is the whole run's, and the line says the percentiles are over the last N cycles."""
    timing = LoopTiming(capacity=1000)
    _cycles(timing, 3000, slow_at=100, slow_ns=300_000_000)
    s = timing.summary(100.0)
    assert abs(s.compute_ms["max"] - 300.0) < 1e-6 and s.compute_ms["p99"] < 1.0
    assert s.period_ms["max"] >= 300.0
    assert "(p50 and p99 over the last 1000)" in s.line()
    short = LoopTiming(capacity=1000)
    _cycles(short, 500, slow_at=100, slow_ns=300_000_000)
    assert abs(short.summary(100.0).compute_ms["max"] - 300.0) < 1e-6 and "over the last" not in short.summary(100.0).line()
