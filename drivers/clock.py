"""Clocks: the real monotonic clock and a simulated one.

Everything that schedules or stamps takes a clock, so that tests run the real
loop code faster than real time and deterministically. Times are integer
nanoseconds (``time.monotonic_ns`` semantics).
"""
from __future__ import annotations

import time
from typing import Protocol


class Clock(Protocol):
    """What the loop, the mailbox and the drivers need of a clock.

    simulated: True when time advances only as the loop sleeps (SimClock). Runs on a
    simulated clock are deterministic offline computations: vision runs inline, the
    network stays closed, and no real-time scheduling is applied.
    """

    simulated: bool

    def now_ns(self) -> int: ...

    def sleep_until(self, deadline_ns: int) -> None: ...


class MonotonicClock:
    """Real time. ``sleep_until`` sleeps to an absolute deadline.

    Sleeping to absolute deadlines (rather than ``sleep(period)``) keeps the
    long-run rate exact: lateness in one cycle does not shift the next.
    ``spin_ns`` busy-waits the last stretch; on these shared 2-core machines it
    helps only when no other thread wants the GIL, so it defaults to 0.
    """

    simulated = False

    def __init__(self, spin_ns: int = 0):
        self.spin_ns = int(spin_ns)

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def sleep_until(self, deadline_ns: int) -> None:
        remaining = deadline_ns - time.monotonic_ns()
        coarse = remaining - self.spin_ns
        if coarse > 0:
            time.sleep(coarse * 1e-9)
        if self.spin_ns:
            while time.monotonic_ns() < deadline_ns:
                pass


class SimClock:
    """Simulated time that advances only when someone sleeps.

    ``sleep_until`` jumps to the deadline, so a loop runs as fast as its
    computation allows, with the exact same schedule every run.
    """

    simulated = True

    def __init__(self, start_ns: int = 1_000_000_000):
        self._now = int(start_ns)

    def now_ns(self) -> int:
        return self._now

    def sleep_until(self, deadline_ns: int) -> None:
        if deadline_ns > self._now:
            self._now = int(deadline_ns)

    def advance(self, dt_ns: int) -> None:
        self._now += int(dt_ns)
