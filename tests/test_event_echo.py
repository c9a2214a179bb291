"""EventEcho: safety events on the console, never holding the loop, never growing without bound."""
import io
import threading

from vbnav.control.runtime.progress import EventEcho
from vbnav.control.runtime.safety import SafetyEvent


class BlockedConsole(io.StringIO):
    """A terminal paused with Ctrl-S, or a pipe nobody reads: write blocks until ``go`` is set."""

    def __init__(self):
        super().__init__()
        self.go = threading.Event()

    def write(self, s):
        self.go.wait(10.0)
        return super().write(s)


def test_a_blocked_console_keeps_a_bounded_queue_and_says_what_it_did_not_echo():
    """The queue was unbounded: a console that blocks for a day of a patrol's events grew the process."""
    out = BlockedConsole()
    echo = EventEcho(out)
    n = EventEcho.QUEUE_LIMIT + 500
    for k in range(n):
        echo(SafetyEvent(k, "hold", "obstacle", f"box {k}"))
    assert echo._queue.qsize() <= EventEcho.QUEUE_LIMIT
    assert echo.dropped >= 499                     # the writer may hold one event, blocked in write()
    out.go.set()
    echo.close()
    text = out.getvalue()
    assert "safety events not echoed" in text and "box 0" in text
    assert text.count("safety hold") == n - int(text.split(" safety events not echoed")[0].split()[-1])
