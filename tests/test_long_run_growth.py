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


# ---- operator mode switches: teach, idle, a refused repeat, many times in one run --------------------------

import gc                                                       # noqa: E402
import weakref                                                  # noqa: E402
from types import SimpleNamespace                               # noqa: E402

from vbnav.control.comms.link import TelemetryLink              # noqa: E402
from vbnav.control.comms.telemetry import Sink                  # noqa: E402
from vbnav.control.controllers import operator as operator_module   # noqa: E402
from vbnav.control.runtime.mailbox import OperatorCommand       # noqa: E402


class _KeyframeEveryFrame(VisionStage):
    """A teach stage that emits a keyframe on every frame (the real one needs a textured world)."""

    kind = "teach"
    n_keyframes = 0

    def process(self, frame, odom):
        self.n_keyframes += 1
        return Estimate(frame.stamp_ns, self.kind, True, SimpleNamespace(odom=odom))


class _Teaching:
    """session.Teaching without files: the operator's teach parts around ``_KeyframeEveryFrame``."""

    made: list = []

    def __init__(self, cfg, route_dir, overwrite=False):
        self.stage = _KeyframeEveryFrame()
        _Teaching.made.append(weakref.ref(self.stage))

    def save(self, frame=None, results=None):
        pass

    def close(self, complete=True):
        return True


class _Quiet(Sink):
    def new_segment(self, segment):
        pass


def test_many_teach_sessions_keep_only_the_latest_route_and_release_the_old_ones(tmp_path, monkeypatch):
    # Before: the link's taught poses (drawn as the route being taught, sent whole at the scene rate) kept every
    # keyframe of every teach of the run, and OperatorController.errors every refused switch (one a cycle here:
    # 60 teach sessions of 15 keyframes grew them to 900 poses and 60 errors).
    monkeypatch.setattr(operator_module, "Teaching", _Teaching)
    _Teaching.made = []
    cfg = Config()
    cfg.controller.routes_dir = str(tmp_path)
    cfg.telemetry.enabled = False
    rt, drive, clock = make_runtime(None, cfg=cfg)
    drive.log = _NoLog()
    pipeline = rt.pipeline
    ctl = operator_module.OperatorController(cfg, pipeline, cfg.safety.command_timeout_s)
    rt.controller = ctl
    ctl.attach(rt)
    link = TelemetryLink.attach(rt, cfg, recorder=_Quiet(), network=False)
    sessions, period = 60, 130                     # cycles: teach 1.0 s, idle 0.3 s
    seen = []

    def feed(r, ctx, twist, wheels):
        k, phase = divmod(ctx.cycle, period)
        if phase == 0 and k < sessions:
            r.submit(OperatorCommand("mode", ("teach", f"route{k}"), "op"))
        elif phase == 100:
            seen.append((ctl.status().get("keyframes"), len(link._taught)))
            r.submit(OperatorCommand("mode", ("idle",), "op"))
        elif phase == 110:
            r.submit(OperatorCommand("mode", ("repeat", "missing"), "op"))
        elif phase == 120:
            seen[-1] += (len(pipeline.stages), len(pipeline.frame_listeners))

    rt.cycle_observers.append(feed)
    result = rt.run(duration_s=sessions * period / cfg.loop.rate_hz)
    ctl.close()
    link.close(result)
    assert len(seen) == sessions and len(_Teaching.made) == sessions
    per_teach = max(kf for kf, *_ in seen)
    assert 10 <= per_teach <= 16                                       # 1 s at 15 frames/s
    # The taught route drawn is the latest teach's, never more than one teach's keyframes.
    assert all(taught <= kf + 1 for kf, taught, *_ in seen), seen
    assert len(link._taught) <= per_teach + 1
    assert len(ctl.errors) <= operator_module.ERRORS_KEPT < sessions
    assert "missing" in ctl.errors[-1]
    # Nothing else piles up per switch: the same stages and listeners, the old teach stages released.
    assert {s[2:] for s in seen} == {seen[0][2:]}
    gc.collect()
    assert sum(ref() is not None for ref in _Teaching.made) <= 1


# ---- live view: a Foxglove client reconnects under a new id after every network blip ----------------------

def test_live_view_clients_that_come_and_go_leave_bounded_state(tmp_path):
    # Before: the ids of every client that ever gave the operator token, and a seq counter per client that ever
    # sent teleop, were kept for the life of the process (measured with real WebSocket clients: 20 connections,
    # 20 operators and 20 counters left after all of them went; the SDK unadvertises their teleop channels).
    import json
    import os

    import foxglove

    from vbnav.control.comms import live_view as lv_module

    token = tmp_path / "token"
    token.write_text("operator-token-0123456789\n")
    os.chmod(token, 0o600)
    cfg = Config()
    cfg.telemetry.live_view.enabled = True
    cfg.telemetry.live_view.port = 0
    cfg.telemetry.live_view.operator_token_file = str(token)
    sent = []
    lv = lv_module.LiveView(cfg.telemetry, "r", submit_teleop=lambda k, p: sent.append(json.loads(p)),
                            refuse=lambda k, r, p: sent.append(r), to_wall_ns=lambda t: t)
    try:
        twist = json.dumps({"linear": {"x": 0.1, "y": 0, "z": 0}, "angular": {"x": 0, "y": 0, "z": 0}}).encode()
        n = 3 * lv_module.OPERATORS_KEPT
        for i in range(n):                           # connect, authenticate, drive, go away (as the SDK tells it)
            client, channel = SimpleNamespace(id=i + 1), SimpleNamespace(id=7, topic=lv_module.TELEOP_TOPIC)
            lv.on_set_parameters(client, [foxglove.Parameter(lv_module.TOKEN_PARAMETER,
                                                             value="operator-token-0123456789")])
            lv.on_client_advertise(client, channel)
            lv.on_message_data(client, 7, twist)
            lv.on_message_data(client, 7, twist)
            lv.on_client_unadvertise(client, 7)
        assert len(lv._operators) <= lv_module.OPERATORS_KEPT and not lv._teleop_channels
        assert isinstance(lv._seq, int)
        assert lv.is_operator(n) and not lv.is_operator(1)      # the latest stay operators, the oldest went
        # each client: its two twists, then the stop sent in its name when it went away while driving
        assert all(isinstance(m, dict) for m in sent) and len(sent) == 3 * n
        assert all(m["linear"] == 0 and m["angular"] == 0 for m in sent[2::3]), sent[2::3][:3]
        per_sender = {}
        for m in sent:                               # each sender's seq still increases
            per_sender.setdefault(m["session"], []).append(m["seq"])
        assert all(a < b for seqs in per_sender.values() for a, b in zip(seqs, seqs[1:]))
    finally:
        lv.close()


# ---- VSLAM: what grows per frame, not per place ----------------------------------------------------------

def test_vslam_keeps_the_latest_motion_estimates_not_one_per_frame():
    # Before: Vslam.stats kept the motion estimate of every frame tracked (~3 kB each with its depth and inlier
    # arrays; measured 300 for 300 frames): 160 MB an hour at 15 frames/s, and nothing reads them.
    import math

    from vbnav.drivers.clock import SimClock
    from vbnav.drivers.sim.camera import SimCamera
    from vbnav.drivers.sim.world import World
    from vbnav.vision import vslam as vslam_module
    from vbnav.vision.camera_model import PinholeCamera
    from vbnav.vision.geometry import CameraMount, Pose2

    cam_model = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
    cam = SimCamera(World.room(seed=0), cam_model, CameraMount(height=0.5, forward=0.1), lambda: Pose2(), SimClock(),
                    10, noise_std=2.0, stereo_baseline=0.12)
    out = [Pose2(0.0, -1.5 + 0.03 * k, math.radians(3.0 * k)) for k in range(12)]
    frames = [cam.render_frame(p, seq=k) for k, p in enumerate(out + out[-2::-1])]
    slam = vslam_module.Vslam(cam_model, vslam_module.VslamConfig(), stereo_baseline=0.12)
    slam.initialise_stereo(frames[0].image, frames[0].right)
    tracked = 0
    while tracked < 2 * vslam_module.STATS_KEPT:           # back and forth over the same ground
        for f in frames[1:]:
            tracked += slam.process(f.image, f.right).ok
        frames.reverse()
    assert len(slam.stats) <= vslam_module.STATS_KEPT < tracked
