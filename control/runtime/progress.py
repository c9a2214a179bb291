"""Progress lines for long runs: one updating line on a terminal, plain lines in logs."""
from __future__ import annotations

import queue
import sys
import threading
import time
from typing import Optional, TextIO


class ProgressPrinter:
    def __init__(self, stream: Optional[TextIO] = None, min_interval_s: float = 0.5):
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.min_interval_s = min_interval_s if self.tty else 5.0
        self._last = 0.0
        self._width = 0

    def __call__(self, text: str, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._last < self.min_interval_s:
            return
        self._last = now
        try:
            if self.tty:
                pad = max(0, self._width - len(text))
                self.stream.write("\r" + text + " " * pad)
                self._width = len(text)
            else:
                self.stream.write(text + "\n")
            self.stream.flush()
        except (OSError, ValueError):   # a closed pipe (`vbnav run 2>&1 | head`): progress is a courtesy
            pass

    def done(self, text: str = "") -> None:
        if self.tty and self._width:
            self.stream.write("\r" + " " * self._width + "\r")
        if text:
            self.stream.write(text + "\n")
        self.stream.flush()
        self._width = 0


class EventEcho:
    """Safety events on the console as they happen (the run's summary lists them again at the end).

    The loop only queues an event (``__call__`` is a safety listener): a terminal or pipe that blocks
    must never stall the loop, so a thread of its own does the writing. A closed stream silences it.
    """

    def __init__(self, stream: Optional[TextIO] = None):
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._write, name="vbnav-event-echo", daemon=True)
        self._thread.start()

    def __call__(self, event) -> None:
        self._queue.put(event)

    def close(self) -> None:
        """Write what is queued, then stop."""
        self._queue.put(None)
        self._thread.join(timeout=2.0)

    def _write(self) -> None:
        while True:
            e = self._queue.get()
            if e is None:
                return
            clear = "\r\x1b[K" if self.tty else ""     # over a progress line in place
            try:
                self.stream.write(f"{clear}{time.strftime('%H:%M:%S')} safety {e.kind}: {e.cause}: {e.message}\n")
                self.stream.flush()
            except (OSError, ValueError):              # closed pipe or stream: nobody is reading
                return
