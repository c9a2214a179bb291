"""Progress lines for long runs: one updating line on a terminal, plain lines in logs; never written on the
caller's thread (the control loop's), so a console that blocks cannot hold the loop."""
from __future__ import annotations

import queue
import sys
import threading
import time
from collections import deque
from typing import Optional, TextIO


class ProgressPrinter:
    """Progress lines, written by a thread of its own.

    The runtime calls progress on the loop's thread: a terminal paused with Ctrl-S or a pipe nobody reads
    blocks a write, and must never hold the control loop. ``__call__`` only leaves the newest line for the
    writer (a line not yet written is replaced by a newer one); ``say`` (and ``force``) queues a line that
    stays (news and milestones between the progress lines, in order, never replaced); ``done`` waits for the writer (briefly) and then writes on the
    caller's thread (how many lines of ``say`` a slow console made it drop, then ``text``), so it is for the
    end of a run, never for the loop's thread."""

    #: how long ``done`` waits for a line still being written (a blocked console) before it goes on
    DONE_WAIT_S = 2.0
    #: lines of ``say`` waiting for a console that blocks; more are counted in ``dropped``, not kept
    SAY_LIMIT = 100

    def __init__(self, stream: Optional[TextIO] = None, min_interval_s: float = 0.5):
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.min_interval_s = min_interval_s if self.tty else 5.0
        self._last = 0.0
        self._width = 0
        self._cv = threading.Condition()
        self._line: Optional[str] = None     # the newest line not yet taken by the writer
        self._said: deque = deque()           # (stream, text) of ``say``, in order
        self.dropped = 0                      # lines of ``say`` left out: the console did not keep up
        self._writing = False
        self._thread = threading.Thread(target=self._write, name="vbnav-progress", daemon=True)
        self._thread.start()

    def __call__(self, text: str, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._last < self.min_interval_s:
            return
        self._last = now
        if force:             # a milestone: written in order, never replaced by the next line
            self.say(text)
            return
        with self._cv:
            self._line = text
            self._cv.notify()

    def say(self, text: str, stream: Optional[TextIO] = None) -> None:
        """A line that stays (on ``stream``, by default the progress stream), written before the next
        progress line; never blocks."""
        with self._cv:
            if len(self._said) >= self.SAY_LIMIT:
                self.dropped += 1
                return
            self._said.append((stream or self.stream, text))
            self._line = None     # an older progress line not yet written: the news supersedes it
            self._cv.notify()

    def done(self, text: str = "") -> None:
        with self._cv:
            self._cv.wait_for(lambda: self._line is None and not self._said and not self._writing,
                              timeout=self.DONE_WAIT_S)
        if self.tty and self._width:
            self.stream.write("\r" + " " * self._width + "\r")
        if self.dropped:
            self.stream.write(f"{self.dropped} progress lines dropped (slow terminal)\n")
        if text:
            self.stream.write(text + "\n")
        self.stream.flush()
        self._width = 0

    def _write(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._line is not None or self._said)
                said, self._said = list(self._said), deque()
                text, self._line = self._line, None
                self._writing = True
            try:
                for stream, news in said:
                    if self.tty and self._width:       # off the progress line first
                        self.stream.write("\r" + " " * self._width + "\r")
                        self.stream.flush()
                        self._width = 0
                    stream.write(news + "\n")
                    stream.flush()
                if text is None:
                    pass
                elif self.tty:
                    pad = max(0, self._width - len(text))
                    self.stream.write("\r" + text + " " * pad)
                    self._width = len(text)
                else:
                    self.stream.write(text + "\n")
                self.stream.flush()
            except (OSError, ValueError):   # a closed pipe (`vbnav run 2>&1 | head`): progress is a courtesy
                pass
            finally:
                with self._cv:
                    self._writing = False
                    self._cv.notify_all()


class EventEcho:
    """Safety events on the console as they happen (the run's summary lists them again at the end).

    The loop only queues an event (``__call__`` is a safety listener): a terminal or pipe that blocks
    must never stall the loop, so a thread of its own does the writing. A closed stream silences it.
    """

    #: events waiting for a console that blocks (a paused terminal, a full pipe); more are counted, not kept
    QUEUE_LIMIT = 1000

    def __init__(self, stream: Optional[TextIO] = None):
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self._queue: queue.Queue = queue.Queue(maxsize=self.QUEUE_LIMIT)
        self._lock = threading.Lock()
        self.dropped = 0          # events not echoed because the console did not keep up (not yet said)
        self._thread = threading.Thread(target=self._write, name="vbnav-event-echo", daemon=True)
        self._thread.start()

    def attach(self, rt) -> "EventEcho":
        """Echo the safety events of runtime ``rt``, which then prints none of them itself."""
        rt.safety.listeners.append(self)
        rt.safety_on_console = True
        return self

    def __call__(self, event) -> None:
        try:
            self._queue.put_nowait(event)
        except queue.Full:        # a blocked console must not grow the process for months
            with self._lock:
                self.dropped += 1

    def close(self) -> None:
        """Write what is queued, then stop."""
        try:
            self._queue.put(None, timeout=2.0)
        except queue.Full:
            return
        self._thread.join(timeout=2.0)

    def _write(self) -> None:
        while True:
            e = self._queue.get()
            with self._lock:
                dropped, self.dropped = self.dropped, 0
            clear = "\r\x1b[K" if self.tty else ""     # over a progress line in place
            stamp = time.strftime('%H:%M:%S')
            lines = [f"{clear}{stamp} {dropped} safety events not echoed: the console did not keep up "
                     f"(the run summary counts them)\n"] if dropped else []
            if e is not None:
                lines.append(f"{clear}{stamp} safety {e.kind}: {e.cause}: {e.message}\n")
            try:
                self.stream.write("".join(lines))
                self.stream.flush()
            except (OSError, ValueError):              # closed pipe or stream: nobody is reading
                return
            if e is None:
                return
