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


def test_a_hangup_or_quit_while_finishing_is_held_too():
    """The run ends on SIGHUP (the ssh session gone) and SIGQUIT, but finishing held only SIGINT and SIGTERM:
    the second SIGHUP of a hang-up (the kernel's, then the shell's to its jobs) killed the process while it
    closed the recording and the route being taught. Run in a child: unheld, the signal kills it."""
    import subprocess
    import sys

    code = ("import os, signal\n"
            "from vbnav.control.runtime.finishing import finishing\n"
            "with finishing('closing the recording'):\n"
            "    os.kill(os.getpid(), signal.SIGHUP)\n"
            "    os.kill(os.getpid(), signal.SIGQUIT)\n"
            "    print('recording closed', flush=True)\n"
            "assert signal.getsignal(signal.SIGHUP) is signal.SIG_DFL\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                       env={**os.environ, "PYTHONFAULTHANDLER": ""})
    assert r.returncode == 0 and "recording closed" in r.stdout, (r.returncode, r.stderr)
    assert "SIGHUP: the robot is stopped; closing the recording, a moment ..." in r.stderr
