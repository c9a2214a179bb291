"""Operator session: teleop in idle, cmd/mode teach records a route, cmd/mode repeat patrols it."""
from vbnav.control.config import load_config
from vbnav.control.runtime.factory import make_robot
from vbnav.control.controllers.operator import OperatorController
from vbnav.control.route import load_route
from vbnav.control.runtime.runtime import OperatorCommand, Runtime


def test_idle_teach_idle_repeat(tmp_path):
    cfg = load_config(None, overrides={"sim": {"start_pose": [-3.5, -1.0, 0.0]},
                                       "controller": {"routes_dir": str(tmp_path)}})
    start = cfg.sim.start()
    robot = make_robot(cfg, with_camera=True)
    pipeline = robot.pipeline
    ctl = OperatorController(cfg, pipeline, cfg.safety.command_timeout_s)
    rt = Runtime(cfg, robot.drive, ctl, robot.clock, pipeline)
    ctl.attach(rt)
    route = tmp_path / "route"
    t0 = robot.clock.now_ns()
    script = []   # (time s, command)
    for k in range(0, 60):                       # 0-6 s: teleop at 10 Hz, straight ahead
        script.append((0.1 * k, OperatorCommand("teleop", (0.3, 0.0), "op")))
    script.insert(5, (0.45, OperatorCommand("mode", ("teach", route.name), "op")))
    script.append((6.5, OperatorCommand("mode", ("idle",), "op")))
    script.append((7.0, OperatorCommand("mode", ("repeat", "missing"), "op")))
    script.sort(key=lambda x: x[0])
    modes, taught_end = [], {}

    def feed(r, ctx, twist, wheels):
        t = (ctx.now_ns - t0) * 1e-9
        while script and script[0][0] <= t:
            r.submit(script.pop(0)[1])
        modes.append(ctl.name)
        if t >= 7.5 and "repeat_sent" not in taught_end:
            # The operator carries the robot back to where teaching started, then asks for a repeat.
            robot.drive.physics.pose = start
            r.submit(OperatorCommand("mode", ("repeat", route.name), "op"))
            taught_end["repeat_sent"] = t
        if ctl.mode == "repeat":
            taught_end["repeating"] = True
        if taught_end.get("repeating") and ctl.name == "idle":
            r.loop.stop()

    rt.cycle_observers.append(feed)
    result = rt.run(duration_s=90.0)
    ctl.close()
    assert result.reason in ("stopped", "duration"), result.message
    kfs = load_route(route).keyframes
    assert len(kfs) >= 3, "teach mode recorded keyframes"
    assert {"idle", "teach", "repeat"} <= set(modes), set(modes)
    rejected = [e for e in result.events if e.kind == "rejected" and e.cause == "mode"]
    assert any("missing" in e.message for e in rejected), [e.message for e in rejected]
    # The repeat ended at the route's end and went back to idle on its own.
    assert modes[-1] == "idle"
    end = robot.drive.physics.pose
    last = kfs[-1].odom
    # measured 3.0 cm / 3.7 mm on 2026-11-30
    assert abs(end.z - (start.z + last.z)) < 0.06 and abs(end.x - start.x) < 0.008


# ---- a mode command is answered once the switch took effect, and a refused one changes nothing ------------

import json                                                   # noqa: E402
import threading                                              # noqa: E402

from vbnav.control.comms.link import TelemetryLink            # noqa: E402
from vbnav.control.comms.telemetry import Sink                # noqa: E402
from vbnav.control.controllers import operator as operator_module   # noqa: E402
from vbnav.control.runtime.pipeline import VisionPipeline     # noqa: E402


class _Events(Sink):
    """A recorder stand-in that keeps the events the link publishes."""

    def __init__(self):
        self.events = []

    def new_segment(self, segment):
        pass

    def event(self, stamp_ns, payload, msg):
        self.events.append(json.loads(payload))

    def answers(self):
        """(kind, ack, reason) of the command and command_rejected events, in order."""
        return [(e["kind"], e.get("ack"), e.get("reason", "")) for e in self.events
                if e["kind"] in ("command", "command_rejected")]


def _operator_session(tmp_path, pipeline=None):
    cfg = load_config(None, overrides={"sim": {"start_pose": [-3.5, -1.0, 0.0]}, "telemetry": {"enabled": False},
                                       "controller": {"routes_dir": str(tmp_path)}})
    robot = make_robot(cfg, with_camera=True)
    pipeline = pipeline(robot.clock) if pipeline is not None else robot.pipeline
    ctl = OperatorController(cfg, pipeline, cfg.safety.command_timeout_s)
    rt = Runtime(cfg, robot.drive, ctl, robot.clock, pipeline)
    ctl.attach(rt)
    sink = _Events()
    link = TelemetryLink.attach(rt, cfg, recorder=sink, network=False)
    return robot, ctl, rt, link, sink


def _at_cycles(rt, actions):
    """Run ``actions[cycle](runtime)`` in the cycle observer of that cycle."""
    def feed(r, ctx, twist, wheels):
        fn = actions.get(ctx.cycle)
        if fn is not None:
            fn(r)
    rt.cycle_observers.append(feed)


def test_a_refused_mode_command_is_never_acknowledged_and_the_teach_goes_on(tmp_path):
    robot, ctl, rt, link, sink = _operator_session(tmp_path)
    seen = {}

    def teleop(r):
        r.submit(OperatorCommand("teleop", (0.3, 0.0), "op"))

    # teleop from cycle 10: before the camera's first frame (the simulated vision latency) it is refused
    actions = {c: teleop for c in range(10, 400, 10)}
    actions[5] = lambda r: r.submit(OperatorCommand("mode", ("teach", "hall"), "op", ack="T1"))
    actions[150] = lambda r: (r.submit(OperatorCommand("mode", ("repeat", "missing"), "op", ack="R1")),
                              r.submit(OperatorCommand("mode", ("teach", "hall"), "op", ack="T2")))
    actions[152] = lambda r: seen.update(kf=ctl.status()["keyframes"], stages=[s.kind for s in
                                                                              robot.pipeline.stages])
    _at_cycles(rt, actions)
    result = rt.run(4.0)
    ctl.close()
    link.close(result)
    answers = sink.answers()
    assert answers[0][:2] == ("command", "T1")
    # Refused, with the sender's ack, and never called applied.
    assert ("command", "R1") not in [a[:2] for a in answers] and ("command", "T2") not in [a[:2] for a in answers]
    refused = {a[1]: a[2] for a in answers if a[0] == "command_rejected"}
    assert "no such route" in refused["R1"] and "not empty" in refused["T2"], answers
    # The refused switches left the teach as it was: its stage still runs and keyframes keep coming.
    assert ctl.mode == "teach" and ctl.teaching_route == "hall" and seen["stages"][0] == "teach"
    assert len(load_route(tmp_path / "hall").keyframes) > seen["kf"]


class _Gate:
    """Teaching whose construction waits for ``open`` (a slow disk): the switch is on its worker meanwhile."""

    def __init__(self):
        self.open = threading.Event()
        self.real = operator_module.Teaching

    def __call__(self, *a, **kw):
        assert self.open.wait(10.0)
        return self.real(*a, **kw)


def test_a_switch_on_the_worker_is_acknowledged_when_it_took_effect(tmp_path, monkeypatch):
    gate = _Gate()
    monkeypatch.setattr(operator_module, "Teaching", gate)
    robot, ctl, rt, link, sink = _operator_session(
        tmp_path, pipeline=lambda clock: VisionPipeline(None, [], clock, inline=False))   # the real-clock path
    modes = {}

    def join(r):
        worker = ctl._worker          # None when the loop already took its result
        if worker is not None:
            worker.join(10.0)

    def let_it_finish(r):
        gate.open.set()
        join(r)

    _at_cycles(rt, {10: lambda r: r.submit(OperatorCommand("mode", ("repeat", "missing"), "op", ack="R1")),
                    11: join,                                 # applied in cycle 11, its worker done
                    20: lambda r: r.submit(OperatorCommand("mode", ("teach", "hall"), "op", ack="T1")),
                    25: lambda r: r.submit(OperatorCommand("mode", ("idle",), "op", ack="I1")),
                    30: let_it_finish})
    rt.cycle_observers.append(lambda r, ctx, twist, wheels: modes.setdefault(ctl.mode, ctx.cycle))
    result = rt.run(1.0)
    ctl.close()
    link.close(result)
    assert result.reason == "duration", result.message
    events = [e for e in sink.events if e["kind"] in ("command", "command_rejected")]
    assert [(e["kind"], e.get("ack")) for e in events] == [
        ("command_rejected", "R1"), ("command_rejected", "I1"), ("command", "T1")], events
    assert "no such route" in events[0]["reason"] and "still in progress" in events[1]["reason"]
    # T1 was answered in the cycle the teach began, not when its worker started (cycle 21).
    assert events[2]["cycle"] == modes["teach"] == 31


def test_a_switch_the_run_ended_before_is_refused_and_its_route_closed(tmp_path, monkeypatch):
    gate = _Gate()
    monkeypatch.setattr(operator_module, "Teaching", gate)
    robot, ctl, rt, link, sink = _operator_session(
        tmp_path, pipeline=lambda clock: VisionPipeline(None, [], clock, inline=False))
    _at_cycles(rt, {10: lambda r: r.submit(OperatorCommand("mode", ("teach", "hall"), "op", ack="T1"))})
    result = rt.run(0.5)
    gate.open.set()
    ctl.close()
    link.close(result)
    assert sink.answers() == [("command_rejected", "T1", "mode teach: the run ended before the switch took effect")]
    assert (tmp_path / "hall" / "manifest.json").is_file()     # the route it opened is closed, not left open


def test_a_switch_still_on_its_worker_when_the_run_ends_is_answered_and_its_route_closed(tmp_path, monkeypatch):
    """A switch whose worker outlived the run's end (a route still loading from a slow disk) was never
    answered: the sender waited for its timeout. It is refused at the end, and the route the worker then
    opens is closed, not left open."""
    gate = _Gate()
    monkeypatch.setattr(operator_module, "Teaching", gate)
    monkeypatch.setattr(OperatorController, "close_wait_s", 0.2)
    robot, ctl, rt, link, sink = _operator_session(
        tmp_path, pipeline=lambda clock: VisionPipeline(None, [], clock, inline=False))
    _at_cycles(rt, {10: lambda r: r.submit(OperatorCommand("mode", ("teach", "hall"), "op", ack="T1"))})
    result = rt.run(0.5)
    worker = ctl._worker
    ctl.close()                                   # the gate is still shut: the worker is still at it
    assert worker.is_alive()
    gate.open.set()
    worker.join(10.0)
    link.close(result)
    assert sink.answers() == [("command_rejected", "T1", "mode teach: the run ended while the switch was still "
                                                         "under way (not done after 0.2 s)")]
    assert ctl._pending is None and ctl.mode == "idle"
    assert (tmp_path / "hall" / "manifest.json").is_file()     # what it opened was closed by the worker


def test_commands_the_run_ended_before_are_answered_and_later_ones_refused(tmp_path):
    """Commands posted in the run's last cycle (after the loop drained its mailbox) got no answer at all:
    'vbnav send' waited for its timeout. Each command gets exactly one answer."""
    robot, ctl, rt, link, sink = _operator_session(tmp_path)
    sent = []

    def post(r, ctx, twist, wheels):          # after this cycle's drain: the last cycle's are never taken
        if ctx.cycle >= 40:
            for kind, args in (("teleop", (0.1, 0.0)), ("mode", ("idle",)), ("estop", ())):
                ack = f"{kind}{ctx.cycle}"
                if r.submit(OperatorCommand(kind, args, "op", ack=ack)) is None:
                    sent.append(ack)

    rt.cycle_observers.append(post)
    result = rt.run(0.5)
    late = rt.submit(OperatorCommand("estop", (), "op", ack="late"))
    ctl.close()
    link.close(result)
    answers = sink.answers()
    assert sorted(a for _, a, _ in answers) == sorted(sent), answers
    final = max(int(a.lstrip("teleopmdsi")) for a in sent)      # the last cycle that posted
    ended = {a[1] for a in answers if a[0] == "command_rejected" and "the run ended (duration" in a[2]}
    assert ended == {f"teleop{final}", f"mode{final}"}, answers
    # an estop accepted is applied, however the run ends (latched, kept in a latch file: test_estop_latch.py)
    assert ("command", f"estop{final}", "") in answers, answers
    assert late is not None and "the run ended (duration" in late


def test_teleop_is_refused_while_repeating_and_never_drives_after_the_repeat_ends():
    from runtime_helpers import make_runtime
    from vbnav.control.config import Config
    from vbnav.control.controllers.manual import ScriptedController
    cfg = Config.model_validate({"safety": {"command_timeout_s": 0.5}})
    ctl = OperatorController(cfg, None, cfg.safety.command_timeout_s)
    rt, drive, clock = make_runtime(ctl, camera=False, cfg=cfg)
    ctl.attach(rt)
    # A repeat that drives straight for 1 s, then ends (the route's end): the operator controller goes idle.
    ctl.mode, ctl.route_path, ctl.active = "repeat", "hall", ScriptedController([[0.2, 0.0, 1.0]])
    answers, modes = [], {}
    rt.command_listeners.append(lambda r, cmd, outcome, now: answers.append(("applied", cmd.ack)))
    rt.safety.listeners.append(lambda ev: answers.append((ev.kind, ev.message)) if ev.kind == "rejected" else None)
    t0 = clock.now_ns()

    def operator(r, ctx, twist, wheels):
        modes.setdefault(ctl.name, ctx.now_ns)
        k = (ctx.now_ns - t0) // 10_000_000
        if 50 <= k < 95 and k % 5 == 0:         # a 20 Hz stream, no ack, turning hard, until 0.95 s
            r.submit(OperatorCommand("teleop", (0.0, 1.0), "stick", seq=int(k), stamp_ns=ctx.now_ns))
        if k == 95:
            r.submit(OperatorCommand("teleop", (0.0, 1.0), "op", ack="T1", stamp_ns=ctx.now_ns))

    rt.cycle_observers.append(operator)
    rt.run(2.0)
    assert modes["idle"] - t0 <= 1_020_000_000, "the repeat ended at 1 s"
    turning = [t for t, left, right, p in drive.log if p and abs(left - right) > 1e-9]
    assert not turning, "a teleop given while repeating turned the robot"
    rejected = [a for a in answers if a[0] == "rejected"]
    assert ("applied", "T1") not in answers and rejected[-1][1].startswith("mode repeat: the robot follows route")
    # the stream without ack: one report a second, not one per message
    assert len(rejected) == 2, rejected


def test_teleop_during_a_switch_is_refused_not_answered_applied(tmp_path, monkeypatch):
    """While a switch runs on its worker the robot holds still: a teleop then was answered 'applied', and a
    switch to repeat dropped it without a word. It is refused, saying the switch is in progress."""
    gate = _Gate()
    monkeypatch.setattr(operator_module, "Teaching", gate)
    robot, ctl, rt, link, sink = _operator_session(
        tmp_path, pipeline=lambda clock: VisionPipeline(None, [], clock, inline=False))   # the real-clock path
    start = robot.drive.physics.pose

    def let_it_finish(r):
        gate.open.set()
        if ctl._worker is not None:
            ctl._worker.join(10.0)

    _at_cycles(rt, {10: lambda r: r.submit(OperatorCommand("mode", ("teach", "hall"), "op", ack="T1")),
                    15: lambda r: r.submit(OperatorCommand("teleop", (0.3, 0.0), "op", ack="V1",
                                                           stamp_ns=r.clock.now_ns())),
                    40: let_it_finish})
    result = rt.run(1.0)
    ctl.close()
    link.close(result)
    answers = sink.answers()
    assert [a[:2] for a in answers] == [("command_rejected", "V1"), ("command", "T1")], answers
    assert "a switch to teach is in progress" in answers[0][2]
    end = robot.drive.physics.pose
    assert abs(end.x - start.x) < 1e-6 and abs(end.z - start.z) < 1e-6, "the refused teleop drove after the switch"


def test_mode_repeat_without_a_camera_is_refused_like_teach(tmp_path, monkeypatch):
    """A run without a camera (--no-camera) answered 'mode repeat' as applied, then sat in repeat for good: no
    VBC fix ever comes, the stale estimate holds the robot, and teleop is refused while repeating."""
    from types import SimpleNamespace
    from runtime_helpers import make_runtime
    from test_controller_settings import _straight_route
    from vbnav.control.config import Config
    from vbnav.control.controllers.repeat import RepeatController
    cfg = Config.model_validate({"controller": {"routes_dir": str(tmp_path)}})
    (tmp_path / "hall").mkdir()
    monkeypatch.setattr(operator_module, "load_route", lambda where: _straight_route())
    monkeypatch.setattr(operator_module, "Repeating",
                        lambda cfg, route: SimpleNamespace(stage=None, controller=RepeatController(route)))
    ctl = OperatorController(cfg, None, cfg.safety.command_timeout_s)
    rt, drive, clock = make_runtime(ctl, camera=False, cfg=cfg)
    ctl.attach(rt)
    out = ctl.handle_command(OperatorCommand("mode", ("repeat", "hall"), "op"), clock.now_ns())
    assert not out.applied and out.reason == "mode 'repeat' needs a camera (this run has none)", out
    assert ctl.mode == "idle"


def test_a_stale_vbc_hold_of_a_repeat_ends_with_the_repeat(tmp_path, monkeypatch):
    """A repeat that got no VBC fix for safety.estimate_timeout_s holds the robot ('vbc_stale'). After 'mode
    idle' nothing required vbc any more, so nothing released the hold: the robot stayed stopped for good and
    every teleop was refused naming it. A hold on an estimate nobody requires any more is released."""
    from types import SimpleNamespace
    from runtime_helpers import make_runtime
    from test_controller_settings import _straight_route
    from vbnav.control.config import Config
    from vbnav.control.controllers.repeat import RepeatController
    from vbnav.control.runtime.interfaces import VisionStage

    class Lost(VisionStage):             # the repeat's stage, never localised
        kind = "vbc"

        def process(self, frame, odom):
            return None

    cfg = Config.model_validate({"controller": {"routes_dir": str(tmp_path)}})
    (tmp_path / "hall").mkdir()
    monkeypatch.setattr(operator_module, "load_route", lambda where: _straight_route())
    monkeypatch.setattr(operator_module, "Repeating",
                        lambda cfg, route: SimpleNamespace(stage=Lost(), controller=RepeatController(route)))
    rt, drive, clock = make_runtime(None, cfg=cfg)
    ctl = OperatorController(cfg, rt.pipeline, cfg.safety.command_timeout_s)
    rt.controller = ctl
    ctl.attach(rt)
    t0 = clock.now_ns()
    refused = []
    rt.safety.listeners.append(lambda ev: refused.append(ev.message) if ev.kind == "rejected" else None)

    def operator(r, ctx, twist, wheels):
        k = (ctx.now_ns - t0) // 10_000_000
        if k == 5:
            r.submit(OperatorCommand("mode", ("repeat", "hall"), "op", ack="R1"))
        if k == 400:
            r.submit(OperatorCommand("mode", ("idle",), "op", ack="I1"))
        if 460 <= k < 540 and k % 10 == 0:     # once the hold had safety.release_s to clear
            r.submit(OperatorCommand("teleop", (0.3, 0.0), "op", ack=f"t{k}", stamp_ns=ctx.now_ns))

    rt.cycle_observers.append(operator)
    result = rt.run(5.5)
    hold = next(e for e in result.events if e.kind == "hold" and e.cause == "vbc_stale")
    assert hold.stamp_ns < t0 + 4_000_000_000
    assert ctl.mode == "idle" and not refused, refused[:2]
    assert any(e.kind == "release" and e.cause == "vbc_stale" for e in result.events)
    assert any(t > t0 + 4_600_000_000 and p and left > 0 for t, left, right, p in drive.log), "teleop never drove"


def test_mode_repeat_of_an_incomplete_route_says_so_when_applied(tmp_path, monkeypatch):
    """vbnav repeat warns that an incomplete route (its teach was interrupted) ends at its last keyframe;
    'mode repeat' of it was answered applied without a word, and the repeat's 'finished' read as the whole
    route patrolled. The answer now carries the note, naming the route (never its path)."""
    from types import SimpleNamespace
    from dataclasses import replace
    from runtime_helpers import make_runtime
    from test_controller_settings import _straight_route
    from vbnav.control.config import Config
    from vbnav.control.controllers.repeat import RepeatController

    cfg = Config.model_validate({"controller": {"routes_dir": str(tmp_path)}})
    (tmp_path / "hall").mkdir()
    answers = {}
    for complete in (True, False):
        route = replace(_straight_route(), complete=complete)
        monkeypatch.setattr(operator_module, "load_route", lambda where: route)
        monkeypatch.setattr(operator_module, "Repeating",
                            lambda cfg, route: SimpleNamespace(stage=None, controller=RepeatController(route)))
        rt, drive, clock = make_runtime(None, cfg=cfg)
        ctl = OperatorController(cfg, rt.pipeline, cfg.safety.command_timeout_s)
        rt.controller = ctl
        ctl.attach(rt)
        out = ctl.handle_command(OperatorCommand("mode", ("repeat", "hall"), "op"), clock.now_ns())
        if out.pending:
            ctl._worker.join(10.0)
            out = ctl._apply_pending(clock.now_ns(), deferred=False)
        answers[complete] = out
    assert answers[True].applied and answers[True].reason == ""
    note = answers[False].reason
    assert answers[False].applied and note.startswith("mode repeat: route 'hall': the route is incomplete"), note
    assert "3 keyframes over 1.00 m exist; a repeat ends at the last of them" in note and str(tmp_path) not in note

def test_mode_idle_while_idle_is_acknowledged_as_unchanged(tmp_path):
    """'mode idle' in idle ran a whole switch (on the real clock: a worker, the robot held still meanwhile,
    teleop refused) and was answered as a switch; it is the mode already running: 'mode_unchanged'."""
    robot, ctl, rt, link, sink = _operator_session(tmp_path)
    _at_cycles(rt, {5: lambda r: r.submit(OperatorCommand("mode", ("idle",), "op", ack="I1"))})
    result = rt.run(0.2)
    ctl.close()
    link.close(result)
    kinds = [e["kind"] for e in sink.events if e["kind"] in ("mode_unchanged", "command", "command_rejected")]
    assert kinds == ["mode_unchanged", "command"], kinds
    assert ctl.mode == "idle"


def test_a_switch_whose_worker_fails_unexpectedly_is_answered_and_the_robot_is_idle(tmp_path, monkeypatch):
    """A full disk: closing the route being taught fails, and so does closing the new one the switch opened.
    The second failure ended the worker thread with a line on stderr only: the command was never answered,
    every later mode command was refused as 'still in progress' and the robot stood for the rest of the run
    without a word of why. The switch is now refused with the error, and the robot is idle."""
    robot, ctl, rt, link, sink = _operator_session(
        tmp_path, pipeline=lambda clock: VisionPipeline(None, [], clock, inline=False))   # the real-clock path
    full = threading.Event()
    real_close = operator_module.Teaching.close

    def close(self, complete=True):
        if full.is_set():
            raise OSError(28, "No space left on device")
        return real_close(self, complete)
    monkeypatch.setattr(operator_module.Teaching, "close", close)

    def join(r):
        if ctl._worker is not None:
            ctl._worker.join(10.0)

    _at_cycles(rt, {5: lambda r: r.submit(OperatorCommand("mode", ("teach", "a"), "op", ack="A")),
                    6: join,
                    20: lambda r: (full.set(), r.submit(OperatorCommand("mode", ("teach", "b"), "op", ack="B"))),
                    21: join,
                    30: lambda r: r.submit(OperatorCommand("mode", ("idle",), "op", ack="I"))})
    result = rt.run(0.5)
    full.clear()
    ctl.close()
    link.close(result)
    answers = sink.answers()
    acks = [(kind, ack) for kind, ack, _ in answers]
    assert ("command", "A") in acks and ("command_rejected", "B") in acks, answers
    reason_b = next(r for kind, ack, r in answers if ack == "B")
    assert "No space left on device" in reason_b and "idle" in reason_b, reason_b
    assert ("command", "I") in acks, answers          # not 'a switch ... is still in progress'
    assert ctl.mode == "idle"


def test_why_a_route_taught_in_operator_mode_ends_early_is_said(tmp_path):
    """vbnav teach prints why the route ends before the last frame (TeachResult.note); the operator's teach
    closed it without a word. The mode command that closes it now says it in its answer, and the run's end
    in a warning event, naming the route."""
    from runtime_helpers import make_runtime
    from vbnav.control.config import Config

    cfg = Config.model_validate({"controller": {"routes_dir": str(tmp_path)}})
    why = "no keyframe at the last frame: it kept 3 tracks"
    outs = []
    for ending in ("mode", "run end"):
        rt, drive, clock = make_runtime(None, cfg=cfg)
        ctl = OperatorController(cfg, rt.pipeline, cfg.safety.command_timeout_s)
        rt.controller = ctl
        ctl.attach(rt)
        name = f"hall{len(outs)}"
        assert ctl.handle_command(OperatorCommand("mode", ("teach", name), "op"), clock.now_ns()).applied
        ctl._teaching.stage.finish = lambda stage=ctl._teaching.stage: setattr(stage, "end_note", why)
        if ending == "mode":
            out = ctl.handle_command(OperatorCommand("mode", ("idle",), "op"), clock.now_ns())
            assert out.applied and ctl.mode == "idle"
            outs.append(out.reason)
        else:
            ctl.close()
            outs.append(" ".join(e.message for e in rt.safety.events if e.kind == "warning" and e.cause == "teach"))
    assert outs[0] == f"mode idle: route 'hall0' taught: {why}", outs
    assert outs[1] == f"route 'hall1' taught: {why}", outs


def test_a_switch_still_under_way_is_said_and_vbnav_send_does_not_blame_access_control(tmp_path, monkeypatch,
                                                                                       capsys):
    """A mode switch that loads its route on the worker is answered when it took effect, which may be after
    vbnav send's --wait (a large route on a slow disk): vbnav send then said 'the robot may refuse commands
    from unauthenticated clients (telemetry.operators)', untrue, the robot had taken it. The robot now says
    it took the command and is finishing it (a command_pending event with its ack), and vbnav send says so."""
    import argparse

    from vbnav.control.commands.send import REFUSED, _report
    gate = _Gate()
    monkeypatch.setattr(operator_module, "Teaching", gate)
    robot, ctl, rt, link, sink = _operator_session(
        tmp_path, pipeline=lambda clock: VisionPipeline(None, [], clock, inline=False))   # the real-clock path

    def let_it_finish(r):
        gate.open.set()
        if ctl._worker is not None:
            ctl._worker.join(10.0)

    _at_cycles(rt, {10: lambda r: r.submit(OperatorCommand("mode", ("teach", "hall"), "op", ack="T1")),
                    30: let_it_finish})
    result = rt.run(0.5)
    ctl.close()
    link.close(result)
    events = [e for e in sink.events if e.get("ack") == "T1"]
    assert [(e["kind"], e["cycle"]) for e in events] == [("command_pending", 11), ("command", 31)], events
    assert events[0]["command"] == "mode" and events[0]["args"] == ["teach", "hall"]

    args = argparse.Namespace(wait=3.0, user=None, tls_cert=None)
    assert _report(args, "r1", "mode", None, 1, pending=events[0]) == REFUSED
    err = capsys.readouterr().err
    assert "robot r1 took mode at cycle 11 and had not finished it within 3 s" in err, err
    assert "telemetry.operators" not in err


def test_a_switch_out_of_teach_waits_for_a_slow_vision_thread_before_closing_the_route(tmp_path):
    """Leaving teach waited for the vision thread by a frame count with a 1 s deadline: a teach frame slower
    than that (a slow fsync of a keyframe) was still inside the teach stage when the switch finished the route
    from the worker thread (two writers of one route). The switch now waits for the thread as the run's end
    does (Teaching.close, VisionPipeline.wait_released): the route is finished after the frame, never beside
    it."""
    from runtime_helpers import TickCamera
    from vbnav.control.runtime.interfaces import PENDING
    from vbnav.drivers.clock import MonotonicClock

    cfg = load_config(None, overrides={"telemetry": {"enabled": False}, "controller": {"routes_dir": str(tmp_path)}})
    clock = MonotonicClock()
    pipeline = VisionPipeline(TickCamera(clock, rate_hz=50.0), [], clock, inline=False)
    ctl = OperatorController(cfg, pipeline, cfg.safety.command_timeout_s)
    order, gate, entered, release = [], threading.Event(), threading.Event(), threading.Event()

    def switch(*args):
        assert ctl.handle_command(OperatorCommand("mode", args, "op"), 0) is PENDING
        ctl._worker.join(30.0)
        assert not ctl._worker.is_alive()
        ctl._apply_pending()

    pipeline.start()
    try:
        switch("teach", "hall")
        teaching = ctl._teaching

        def slow_frame(frame, odom):        # a teach frame that lasts until the test releases it
            if gate.is_set():
                entered.set()
                release.wait(30.0)
                order.append("frame done")

        teaching.stage.process = slow_frame
        teaching.stage.finish = lambda: order.append("route finished")
        gate.set()
        assert entered.wait(30.0)
        releaser = threading.Timer(1.5, release.set)     # longer than the old 1 s frame-count deadline
        releaser.start()
        switch("idle")
        releaser.join()
    finally:
        release.set()
        pipeline.stop()
    assert ctl.mode == "idle" and order == ["frame done", "route finished"], order
    assert load_route(tmp_path / "hall") is not None


def test_the_operator_sessions_teleop_stream_going_silent_stops_the_wheels_within_the_timeout():
    """Every failure path stops the motors: in the operator session (idle and teach: the operator drives) a teleop
    stream that goes silent (a lost network) stops the wheels within safety.command_timeout_s + 2 periods of the
    last message sent, and they stay stopped. (The teleop controller's own test is test_safety's; the operator
    session wraps it.)"""
    from runtime_helpers import PERIOD_NS, make_runtime
    from vbnav.control.config import Config
    cfg = Config.model_validate({"safety": {"command_timeout_s": 0.5}})
    ctl = OperatorController(cfg, None, cfg.safety.command_timeout_s)
    rt, drive, clock = make_runtime(ctl, camera=False, cfg=cfg)
    ctl.attach(rt)
    t0 = clock.now_ns()
    last = []

    def operator(r, ctx, twist, wheels):
        k = (ctx.now_ns - t0) // PERIOD_NS
        if 10 <= k <= 60 and k % 5 == 0:         # a 20 Hz stream until 0.6 s, then the network is gone
            r.submit(OperatorCommand("teleop", (0.2, 0.0), "op", seq=int(k), stamp_ns=ctx.now_ns))
            last[:] = [ctx.now_ns]

    rt.cycle_observers.append(operator)
    result = rt.run(2.0)
    assert ctl.name == "idle" and result.reason == "duration"
    assert drive.last_motion_ns() > t0 + 500_000_000, "the stream never drove"
    assert drive.stopped_since(last[0] + 500_000_000 + 2 * PERIOD_NS), "the wheels drove on after the timeout"
    assert "command_timeout" in rt.safety.holds
