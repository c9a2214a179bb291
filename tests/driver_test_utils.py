"""Scaffolding the wheel-driver tests share: polling, driving for some cycles, a controller process
killed with SIGKILL, and ``vbnav emulate`` run as a subprocess. The assertions about each device
stay in its own test file."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from contextlib import contextmanager
from typing import Callable, Iterator


def wait_until(pred, timeout=2.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.005)
    return pred()


def drive_for(drive, left, right, cycles=10):
    for _ in range(cycles):
        drive.write(left, right)
        state = drive.read()
        time.sleep(0.005)
    return state


def controller_script(module: str, drive_class: str, watchdog_option: str) -> str:
    """A controlling process: ``<drive_class>`` on port argv[1] with its watchdog at argv[2] s, says
    "running" once enabled, then drives both wheels at 3 rad/s until killed."""
    return textwrap.dedent(f"""
        import sys, time
        from vbnav.drivers.{module} import {drive_class}
        d = {drive_class}(options={drive_class}.Options(port=sys.argv[1], {watchdog_option}=float(sys.argv[2])))
        d.connect(); d.enable()
        print("running", flush=True)
        while True:
            d.write(3.0, 3.0); d.read(); time.sleep(0.01)
    """)


def kill_controller_while_driving(script: str, path: str, watchdog_s: float,
                                  moving: Callable[[], bool], stopped: Callable[[], bool]) -> None:
    """Run ``script`` against the device at ``path``; once the wheels move, SIGKILL the process
    (no disable, no close) and check that the device stops the wheels by itself."""
    proc = subprocess.Popen([sys.executable, "-c", script, path, str(watchdog_s)],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "running"
        assert wait_until(moving, timeout=3.0)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=5)
        assert wait_until(stopped, timeout=2.0)
    finally:
        if proc.poll() is None:
            proc.kill()


@contextmanager
def emulate_cli(*args: str) -> Iterator[str]:
    """``vbnav emulate <args>`` as a process; yields the device path it prints first and checks it
    exits cleanly on SIGTERM."""
    proc = subprocess.Popen([sys.executable, "-m", "vbnav.control.cli", "emulate", *args],
                            stdout=subprocess.PIPE, text=True)
    try:
        yield proc.stdout.readline().strip()
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=5) == 0
