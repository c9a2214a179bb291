"""The loop thread's real-time settings stay its own: a thread started from it afterwards (a lazily
started writer, an executor) runs on the process's CPUs with normal scheduling, not on the loop's."""
from __future__ import annotations

import os
import threading

import pytest

from vbnav.control.config import Config
from vbnav.control.controllers.manual import IdleController
from vbnav.control.runtime.runtime import Runtime
from vbnav.drivers.clock import MonotonicClock
from runtime_helpers import RecordingDrive


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs to tell the sets apart")
def test_a_thread_started_from_the_loop_does_not_inherit_its_cpu_set():
    process_cpus = os.sched_getaffinity(0)
    loop_cpu = min(process_cpus)
    cfg = Config.model_validate({"loop": {"cpu_affinity": [loop_cpu], "rate_hz": 100,
                                          # the trip is checked in cycles: a loaded machine must not stop the run
                                          "max_missed_streak": 10 ** 6, "stall_periods": 1e6}})
    clock = MonotonicClock()
    rt = Runtime(cfg, RecordingDrive(clock), IdleController(), clock)
    seen = {}

    def start_a_thread_once(runtime, ctx, twist, wheels):
        if "loop" in seen:
            return
        seen["loop"] = os.sched_getaffinity(0)

        def child():
            seen["child"] = os.sched_getaffinity(0)
            seen["policy"] = os.sched_getscheduler(0)
        t = threading.Thread(target=child)
        t.start()
        t.join()
        runtime.request_stop()

    rt.cycle_observers.append(start_a_thread_once)
    runner = threading.Thread(target=rt.run, args=(10.0,))
    runner.start()
    runner.join(30)
    assert not runner.is_alive()
    assert seen["loop"] == {loop_cpu}                                  # the loop thread took its own CPU
    assert seen["child"] == process_cpus and seen["policy"] == os.SCHED_OTHER, seen
    assert os.sched_getaffinity(0) == process_cpus                     # nothing else was touched
