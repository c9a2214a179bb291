"""Finishing a run without being cut short.

Once the runtime has stopped the wheels and handed the signals back, a second Ctrl-C (or a SIGTERM
from a service manager that is not patient) would raise KeyboardInterrupt in the middle of closing
the recording, the telemetry link or a route being taught, and lose the run's summary. While a run
finishes, ``finishing()`` holds SIGINT, SIGTERM, SIGHUP (a terminal that hangs up sends it twice),
SIGQUIT and SIGTSTP, the signals the runtime stops on: the first says once what is being waited for, and the
finishing goes on; the handlers are restored afterwards. The motors are already stopped at this
point (the runtime disables the drive before it returns), so nothing waits on a moving robot.
"""
from __future__ import annotations

import signal
import sys
import threading
from contextlib import contextmanager
from typing import Iterator, TextIO


#: The signals the runtime turns into a stop: while a run finishes, each of them is held. SIGHUP comes twice
#: when a terminal hangs up (the kernel's, then the shell's to its jobs), and its default kills.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGTSTP)
HELD = STOP_SIGNALS


@contextmanager
def finishing(what: str = "saving the recording and the summary", stream: TextIO | None = None) -> Iterator[None]:
    if threading.current_thread() is not threading.main_thread():
        yield                                       # signals are only delivered to the main thread
        return
    out = stream or sys.stderr
    told = []

    def hold(signum, frame):
        if not told:
            told.append(signum)
            print(f"\n{signal.Signals(signum).name}: the robot is stopped; {what}, a moment ...", file=out,
                  flush=True)

    old = {sig: signal.signal(sig, hold) for sig in HELD}
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
