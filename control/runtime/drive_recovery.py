"""Waiting for a drive that lost its bus to come back, within a window, without blocking the loop.

While a drive is in ERROR with a lost bus (every fault ``reconnectable``), its
``reconnect()`` is tried again and again: each attempt that the driver deems
due repeats the safe bring-up (torque off, operating mode, limits, watchdog),
which on a real bus takes tens of milliseconds, and longer when the adapter is
back but a motor does not answer. On the real clock the attempts therefore run
on their own thread and the loop only polls the outcome; on the simulated clock
they run inline, once per cycle, so a simulated run stays deterministic. The
loop does not touch the drive meanwhile.

Outcomes: ``BACK`` (the drive is INACTIVE again), ``FAILED`` (the device is back
but faulted, or an attempt raised something other than a DriveError: waiting longer
will not help), ``EXPIRED`` (the window passed).
"""
from __future__ import annotations

import enum
import threading
import traceback
from typing import Optional

from vbnav.drivers.wheels import DriveError, WheelDrive

ATTEMPT_EVERY_S = 0.01   # how often the thread asks the drive; the driver spaces real attempts itself


class Outcome(enum.Enum):
    BACK = "back"
    FAILED = "failed"
    EXPIRED = "expired"


class DriveRecovery:
    def __init__(self, drive: WheelDrive, cause: str, since_ns: int, window_s: float, threaded: bool):
        self.drive = drive
        self.cause = cause                 # what was lost, as the drive said it
        self.since_ns = since_ns
        self.window_s = window_s
        self.deadline_ns = since_ns + int(window_s * 1e9)
        self.error: Optional[str] = None   # why it FAILED
        self.traceback: Optional[str] = None   # when it FAILED because an attempt raised (not a DriveError)
        self._outcome: Optional[Outcome] = None
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        if threaded:
            self._thread = threading.Thread(target=self._run, name="drive-reconnect", daemon=True)
            self._thread.start()

    def poll(self, now_ns: int) -> Optional[Outcome]:
        """The outcome so far (None: still waiting). Called by the loop once per cycle."""
        if self._thread is None and self._outcome is None:
            self._attempt()
        if self._outcome is None and now_ns >= self.deadline_ns:
            self.stop()                    # an attempt in progress may still bring it back: it counts
            if self._outcome is None:
                self._outcome = Outcome.EXPIRED
        return self._outcome

    def stop(self) -> None:
        """End the attempts (the run ends); waits for one in progress."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)

    def _attempt(self) -> None:
        try:
            if self.drive.reconnect():
                self._outcome = Outcome.BACK
        except DriveError as exc:
            self.error = str(exc)
            self._outcome = Outcome.FAILED
        except Exception as exc:
            # Not a device answer but a failure of the attempt itself: on the thread it would end the attempts
            # unseen, and the run would wait out its window and then call the drive "not back".
            self.error = f"the reconnect attempt raised {exc!r}"
            self.traceback = traceback.format_exc()
            self._outcome = Outcome.FAILED

    def _run(self) -> None:
        while self._outcome is None and not self._stop.is_set():
            self._attempt()
            self._stop.wait(ATTEMPT_EVERY_S)
