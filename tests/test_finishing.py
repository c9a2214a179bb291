"""A second Ctrl-C while a run finishes (recording, route, summary) is held, not raised."""
from __future__ import annotations

import io
import os
import signal

from vbnav.control.runtime.finishing import finishing


def test_signals_while_finishing_are_held_told_once_and_handed_back():
    out = io.StringIO()
    done = []
    before = signal.getsignal(signal.SIGINT)
    with finishing("closing the recording", stream=out):
        os.kill(os.getpid(), signal.SIGINT)        # the impatient second Ctrl-C
        os.kill(os.getpid(), signal.SIGTERM)
        done.append("recording closed")            # the finishing goes on
    assert done == ["recording closed"]
    assert out.getvalue().strip() == "SIGINT: the robot is stopped; closing the recording, a moment ..."
    assert signal.getsignal(signal.SIGINT) is before
