"""State of a months-long run stays bounded: what grows per event, per sender, per mode switch is capped.

Each test runs many more events (or senders, or switches) than the structure keeps, on the simulated clock, and
asserts its size against the bound the code states, not against a measurement."""
from __future__ import annotations

from runtime_helpers import make_runtime

from vbnav.control.config import Config
from vbnav.control.controllers.manual import IdleController
from vbnav.control.runtime.interfaces import Estimate, VisionStage
from vbnav.control.runtime.safety import EVENTS_FIRST, EVENTS_LAST


class _Passers(VisionStage):
    """Someone walks through the stop zone on every other frame: an obstacle hold and release per pass."""

    kind = "obstacles"
    safety_critical = True

    def __init__(self):
        self.passes = 0
        self._n = 0

    def process(self, frame, odom):
        self._n += 1
        blocked = self._n % 2 == 0
        self.passes += blocked
        return Estimate(frame.stamp_ns, self.kind, True, None,
                        {"speed_scale": 0.0 if blocked else 1.0, "reason": f"person ahead (pass {self.passes})"})


def test_safety_events_keep_the_first_and_last_and_count_the_rest():
    # Before: SafetyMonitor.events kept every event of the run: 120 an hour with one passer-by a minute (235 B
    # each; 3600 an hour from a joystick held during a repeat), all listed again by the run's report.
    cfg = Config()
    cfg.loop.rate_hz = 20.0               # a coarse loop and camera: thousands of passes in a few seconds
    stage = _Passers()
    rt, drive, clock = make_runtime(IdleController(), stages=[stage], cfg=cfg, cam_kw=dict(rate_hz=5.0))
    drive.log = _NoLog()
    kept = EVENTS_FIRST + EVENTS_LAST
    passes = kept                           # two events a pass: twice as many as the report keeps
    result = rt.run(duration_s=passes * 2 / 5.0 + 1.0)
    assert stage.passes >= passes
    log = rt.safety.events
    assert len(log) == kept and len(result.events) == kept
    holds = result.count("hold", "obstacle")
    assert holds == stage.passes, (holds, stage.passes)          # every pass is counted, kept or not
    assert result.count("release", "obstacle") in (holds, holds - 1)
    assert result.events_dropped == log.total - kept > 0
    # The first events are the run's first ones, the last the run's last ones, in order.
    assert "pass 1)" in result.events[0].message
    assert f"pass {stage.passes})" in [e for e in result.events if e.kind == "hold"][-1].message
    stamps = [e.stamp_ns for e in result.events]
    assert stamps == sorted(stamps)
    # The report says where and how many were left out, with the whole run's counts.
    report = result.event_report()
    gap = report[EVENTS_FIRST]
    assert isinstance(gap, str) and f"{result.events_dropped} safety events left out" in gap
    assert f"hold obstacle {holds}" in gap
    assert not any(isinstance(e, str) for e in report[:EVENTS_FIRST] + report[EVENTS_FIRST + 1:])


class _NoLog(list):
    """The test drive's own command log is the test's, not the robot's: not kept here."""

    def append(self, item):
        pass
