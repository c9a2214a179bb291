"""EventEcho: safety events on the console, never holding the loop, never growing without bound."""
import io
import re
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
    out.go.set()
    echo.close()
    text = out.getvalue()
    # Every event is either echoed or counted in a 'not echoed' line (the writer may take some of the count
    # before it blocks, so it can come in more than one line).
    echoed = text.count("safety hold")
    not_echoed = sum(int(m) for m in re.findall(r"(\d+) safety events not echoed", text))
    assert echoed + not_echoed == n, (echoed, not_echoed)
    assert not_echoed >= 499 and echoed <= EventEcho.QUEUE_LIMIT + 1 and "box 0" in text


def test_a_blocked_console_never_holds_the_progress_caller():
    """ProgressPrinter wrote on the caller's thread, and the runtime calls progress on the loop's: a terminal
    paused with Ctrl-S (or a pipe nobody reads) froze the control loop in the write, estops unread."""
    import time

    from runtime_helpers import make_runtime

    from vbnav.control.controllers.manual import IdleController
    from vbnav.control.runtime.progress import ProgressPrinter

    out = BlockedConsole()
    printer = ProgressPrinter(out)
    rt, drive, clock = make_runtime(IdleController(), camera=False)
    t0 = time.monotonic()
    result = rt.run(duration_s=3, progress=lambda r: printer(f"cycle {r.cycle}", force=True))
    elapsed = time.monotonic() - t0
    assert result.reason == "duration"
    assert elapsed < 5.0, f"the loop waited {elapsed:.1f} s on the console"
    out.go.set()
    printer.done("the end")
    text = out.getvalue()
    assert "cycle 0" in text and text.endswith("the end\n"), text


def test_news_lines_between_progress_lines_never_hold_the_caller_and_keep_their_order():
    """vbnav goto printed the re-planner's news from the progress callback (the loop's thread) with print()
    after ``done()``: a blocked console held the loop there. ``say`` queues the line for the writer."""
    import time

    from vbnav.control.runtime.progress import ProgressPrinter

    out = BlockedConsole()
    news = BlockedConsole()
    printer = ProgressPrinter(out)
    t0 = time.monotonic()
    printer("goto: drive 1", force=True)
    for k in range(3):
        printer.say(f"goto: re-planned {k}", stream=news)
    printer("goto: drive 2", force=True)
    assert time.monotonic() - t0 < 1.0
    out.go.set()
    news.go.set()
    printer.done()
    assert news.getvalue() == "goto: re-planned 0\ngoto: re-planned 1\ngoto: re-planned 2\n"
    assert out.getvalue().endswith("goto: drive 2\n")


def test_a_forced_progress_line_is_never_replaced_by_the_next_one():
    """Forced lines are milestones (the demo's 'taught ...', 'repeat 1: ...'): handed to the writer while it
    was blocked, the next line replaced them and they were never written."""
    from vbnav.control.runtime.progress import ProgressPrinter

    out = BlockedConsole()
    printer = ProgressPrinter(out)
    printer("start", force=True)          # the writer takes it and blocks on the console
    printer("taught 12 keyframes", force=True)
    printer("repeat: keyframe 1/12", force=True)
    out.go.set()
    printer.done()
    assert out.getvalue() == "start\ntaught 12 keyframes\nrepeat: keyframe 1/12\n"


def test_progress_lines_dropped_for_a_slow_console_are_reported_at_the_end():
    """ProgressPrinter counted the lines of ``say`` it left out for a console that did not keep up (``dropped``)
    but never said so: the run's output just lacked them. ``done`` reports the count."""
    from vbnav.control.runtime.progress import ProgressPrinter

    out = BlockedConsole()
    printer = ProgressPrinter(out)
    n = ProgressPrinter.SAY_LIMIT + 50
    for k in range(n):
        printer.say(f"news {k}")
    out.go.set()
    printer.done("the end")
    text = out.getvalue()
    written = len(re.findall(r"^news \d+$", text, re.M))
    assert printer.dropped >= 49 and written + printer.dropped == n, (written, printer.dropped)
    assert text.endswith(f"{printer.dropped} progress lines dropped (slow terminal)\nthe end\n"), text[-200:]


def test_no_dropped_line_no_report():
    from vbnav.control.runtime.progress import ProgressPrinter

    out = io.StringIO()
    printer = ProgressPrinter(out)
    printer.say("news")
    printer.done("the end")
    assert "dropped" not in out.getvalue()
