"""BackgroundStage (control/stages/background.py): a slow vision stage in its own thread with a one-frame
mailbox, so the stages on the vision thread (the VSLAM) keep the camera's rate; inline on a simulated clock."""
from __future__ import annotations

import threading

import numpy as np
import pytest

from vbnav.control.runtime.interfaces import Estimate, VisionStage
from vbnav.control.stages.background import BackgroundStage
from vbnav.drivers.camera import Frame
from vbnav.vision.geometry import Pose2


class Gated(VisionStage):
    """Finishes a frame only when the test lets it (no timing in the test)."""

    kind = "slow"

    def __init__(self, fail_on: int = -1):
        self.go = threading.Semaphore(0)
        self.started = threading.Semaphore(0)
        self.seen: list[int] = []
        self.fail_on = fail_on

    def process(self, frame, odom):
        self.started.release()
        assert self.go.acquire(timeout=10)
        if frame.seq == self.fail_on:
            raise ValueError("broken frame")
        self.seen.append(frame.seq)
        return Estimate(frame.stamp_ns, self.kind, True, frame.seq)


def _frame(k: int) -> Frame:
    return Frame(np.zeros((4, 4), np.uint8), k, k)


def test_inline_runs_the_stage_in_place():
    st = Gated()
    bg = BackgroundStage(st, inline=True)
    st.go.release()
    assert bg.process(_frame(1), Pose2()).value == 1 and st.seen == [1]


def test_threaded_returns_at_once_and_the_worker_takes_the_newest_frame():
    st = Gated()
    bg = BackgroundStage(st, inline=False)
    bg.start()
    try:
        assert bg.process(_frame(1), Pose2()) is None           # nothing finished yet, and no wait
        assert st.started.acquire(timeout=10)                    # the worker is busy with frame 1
        for k in (2, 3, 4):                                      # frames arriving meanwhile
            bg.process(_frame(k), Pose2())
        assert bg.replaced == 2                                  # 2 and 3 were replaced by 4
        st.go.release()
        assert st.started.acquire(timeout=10)                    # ... which the worker takes next
        st.go.release()
        for _ in range(1000):
            if bg.done == 2:
                break
            threading.Event().wait(0.01)
        assert st.seen == [1, 4]
        assert bg.process(_frame(5), Pose2()).value == 4         # the latest finished estimate
    finally:
        st.go.release()
        bg.stop()


def test_a_failure_in_the_thread_fails_the_next_call_naming_the_stage():
    st = Gated(fail_on=1)
    bg = BackgroundStage(st, inline=False)
    bg.start()
    try:
        bg.process(_frame(1), Pose2())
        st.go.release()
        for _ in range(1000):
            if bg._error is not None:
                break
            threading.Event().wait(0.01)
        with pytest.raises(RuntimeError, match="stage 'slow' failed in its own thread: ValueError"):
            bg.process(_frame(2), Pose2())
    finally:
        bg.stop()


def test_a_safety_critical_stage_is_refused():
    st = Gated()
    st.safety_critical = True
    with pytest.raises(ValueError, match="safety critical"):
        BackgroundStage(st, inline=False)
