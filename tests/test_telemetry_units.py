"""Telemetry, network commands, network configuration and recording: in-process, deterministic."""
from __future__ import annotations

import json
import re
import math

import pytest

from runtime_helpers import RecordingDrive
from vbnav.control.config import Config, ConfigError, parse_config
from vbnav.control.controllers.manual import IdleController, TeleopController
from vbnav.control.comms.operator_commands import CommandInbox, TeleopLimits, parse_command, CommandRejected
from vbnav.control.config.telemetry import DEFAULT_ENDPOINT, TelemetryConfig, is_loopback_endpoint
from vbnav.control.comms.network import robot_session_config
from vbnav.control.comms.recording import McapRecorder, format_summary, iter_recording, read_recording
from vbnav.control.runtime.runtime import Runtime
from vbnav.control.comms.telemetry import EVENT_RESERVE, QUEUE_LIMIT, Sink, StateSample, TelemetryPublisher, decode
from vbnav.control.comms.link import TelemetryLink
from vbnav.drivers.clock import SimClock

LIMITS = TeleopLimits(0.5, 1.5)


# ---- network configuration ----------------------------------------------------------------

def test_default_session_is_loopback_only_without_scouting():
    t = TelemetryConfig()
    conf = robot_session_config(t, "sim")
    assert conf["listen"]["endpoints"] == [DEFAULT_ENDPOINT] == ["tcp/127.0.0.1:7447"]
    assert conf["scouting"]["multicast"]["enabled"] is False
    assert conf["scouting"]["gossip"]["enabled"] is False
    assert conf["connect"]["endpoints"] == []
    assert not t.remote
    # Loopback without authentication: anyone local may command (docs/telemetry.md), but nobody may publish
    # on the robot's telemetry keys through its session.
    acl = conf["access_control"]
    assert acl["default_permission"] == "deny"
    assert [p["subjects"] for p in acl["policies"] if "commands-in" in p["rules"]] == [["everyone"]]
    assert not any(r["flows"] == ["ingress"] and "put" in r["messages"] and "vbnav/sim/state" in r["key_exprs"]
                   for r in acl["rules"])


@pytest.mark.parametrize("ep,loop", [("tcp/127.0.0.1:7447", True), ("tcp/127.3.0.1:1", True),
                                     ("tcp/[::1]:7447", True), ("udp/localhost:9", True),
                                     ("unixsock-stream//tmp/z.sock", True), ("tcp/0.0.0.0:7447", False),
                                     ("tcp/[::]:7447", False), ("tls/192.168.1.5:7447", False),
                                     ("tcp/robot.local:7447", False), ("tcp/127.0.0.1:7447#iface=lo", True)])
def test_loopback_classification(ep, loop):
    assert is_loopback_endpoint(ep) is loop


@pytest.mark.parametrize("section", [
    {"listen": ["tcp/0.0.0.0:7447"]},
    {"listen": ["tcp/127.0.0.1:7447"], "connect": ["tcp/10.0.0.2:7447"]},
    {"scouting": True},
    {"listen": ["tcp/0.0.0.0:7447"], "operators": ["op"]},                       # no authentication
])
def test_remote_access_without_auth_is_refused_with_a_clear_message(section, tmp_path):
    with pytest.raises(ConfigError) as e:
        parse_config({"telemetry": section}, "robot.yaml")
    msg = str(e.value)
    assert msg.startswith("robot.yaml: telemetry")
    assert "authentication" in msg and "127.0.0.1:7447" in msg


def test_remote_access_without_operators_is_refused(tmp_path):
    d = tmp_path / "users.txt"
    d.write_text("op:secretpass\n")
    with pytest.raises(ConfigError, match="telemetry.operators"):
        parse_config({"telemetry": {"listen": ["tcp/0.0.0.0:7447"],
                                    "auth": {"usrpwd": {"user": "r", "password": "robotpass",
                                                        "dictionary_file": str(d)}}}})


def test_remote_config_builds_auth_and_acl_limiting_commands_to_operators(tmp_path):
    d = tmp_path / "users.txt"
    d.write_text("op:secretpass\n")
    t = parse_config({"telemetry": {"listen": ["tcp/0.0.0.0:7447"], "operators": ["op"],
                                    "auth": {"usrpwd": {"user": "r", "password": "robotpass",
                                                        "dictionary_file": str(d)}}}}).telemetry
    conf = robot_session_config(t, "bot1")
    assert conf["transport"]["auth"]["usrpwd"]["dictionary_file"] == str(d.resolve())
    acl = conf["access_control"]
    assert acl["enabled"] and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    cmd_policies = [p for p in acl["policies"] if "commands-in" in p["rules"]]
    assert rules["commands-in"]["key_exprs"] == ["vbnav/bot1/cmd/**"]
    subjects = {s["id"]: s for s in acl["subjects"]}
    assert all(subjects[s].get("usernames", subjects[s].get("cert_common_names")) == ["op"]
               for p in cmd_policies for s in p["subjects"])
    assert "vbnav/bot1/cmd/**" not in rules["telemetry-out"]["key_exprs"]


def test_missing_dictionary_file_is_named(tmp_path):
    t = parse_config({"telemetry": {"listen": ["tcp/0.0.0.0:7447"], "operators": ["op"],
                                    "auth": {"usrpwd": {"user": "r", "password": "robotpass",
                                                        "dictionary_file": str(tmp_path / "nope.txt")}}}}).telemetry
    with pytest.raises(ConfigError, match="dictionary_file: file not found"):
        robot_session_config(t, "sim")


def test_unknown_telemetry_key_names_the_file_and_key(tmp_path):
    with pytest.raises(ConfigError, match=r"robot.yaml: telemetry.state_rate: unknown key"):
        parse_config({"telemetry": {"state_rate": 5}}, "robot.yaml")


# ---- command validation -------------------------------------------------------------------

@pytest.mark.parametrize("kind,payload", [
    ("teleop", '{"linear": 0.2, "angular": -0.5}'), ("estop", ""), ("estop", '{"reason": "door"}'),
    ("resume", "{}"), ("mode", '{"mode": "repeat", "route": "hall_2.v1"}'), ("mode", '{"mode": "idle"}'),
])
def test_valid_commands_parse(kind, payload):
    assert parse_command(kind, payload, LIMITS).kind == kind


@pytest.mark.parametrize("kind,payload,why", [
    ("teleop", '{"linear": 0.9, "angular": 0}', "outside"),
    ("teleop", '{"linear": 0.1, "angular": -2}', "outside"),
    ("teleop", '{"linear": NaN, "angular": 0}', "finite"),
    ("teleop", '{"linear": "fast", "angular": 0}', "linear"),
    # Types as JSON gives them, no coercion: a bool or a string where a number belongs is a sender's bug,
    # and true was taken as 1.0 m/s, "0.3" as 0.3 (silently).
    ("teleop", '{"linear": true, "angular": 0}', "linear"),
    ("teleop", '{"linear": "0.3", "angular": 0}', "linear"),
    ("teleop", '{"linear": 0.1, "angular": 0, "seq": true}', "seq"),
    ("teleop", '{"linear": 0.1, "angular": 0, "seq": 1.5}', "seq"),
    ("teleop", '{"linear": 0.1, "angular": 0, "stamp_ns": "12"}', "stamp_ns"),
    ("estop", '{"reason": 7}', "reason"),
    ("teleop", '{"linear": 0.1}', "angular"),
    ("teleop", '[0.1, 0]', "JSON object"),
    ("teleop", '{"linear": 0.1, "angular": 0, "turbo": 1}', "turbo"),
    ("teleop", '{"linear": 0.1,', "not JSON"),
    ("mode", '{"mode": "repeat"}', "needs a route"),
    ("mode", '{"mode": "teach"}', "needs a route"),
    ("mode", '{"mode": "idle", "route": "hall"}', "takes no route"),     # idle showed it in its state, unused
    ("mode", '{"mode": "dance"}', "mode"),
    ("mode", '{"mode": "teach", "route": "../../etc/x"}', "plain name"),      # routes are names, never paths
    ("mode", '{"mode": "teach", "route": "/etc/x"}', "plain name"),
    ("mode", '{"mode": "repeat", "route": "a/b"}', "plain name"),
    ("mode", '{"mode": "repeat", "route": ".."}', "plain name"),
    ("mode", '{"mode": "repeat", "route": ".hidden"}', "plain name"),
    # a key given twice: JSON readers keep the last one, so one of the two values was dropped unsaid
    ("teleop", '{"linear": 0.5, "angular": 0, "linear": 0.0}', "duplicate key 'linear'"),
    ("mode", '{"mode": "teach", "route": "hall", "route": "yard"}', "duplicate key 'route'"),
    ("launch", '{}', "unknown command"),
    ("estop", '{"reason": "' + "x" * 5000 + '"}', "exceeds"),
])
def test_bad_commands_are_rejected_with_a_reason(kind, payload, why):
    with pytest.raises(CommandRejected, match=why):
        parse_command(kind, payload, LIMITS)


def test_inbox_rejects_with_events_and_the_safety_lane_refuses_loudly_but_never_evicts():
    from vbnav.control.runtime.mailbox import SAFETY_LANE_LIMIT, CommandMailbox
    clock = SimClock()
    mailbox = CommandMailbox(clock.now_ns, 500_000_000)
    rejected = []
    inbox = CommandInbox(LIMITS, deliver=mailbox.post, on_reject=lambda k, r, p, v: rejected.append((k, r)),
                         now_ns=clock.now_ns)
    assert inbox.submit("teleop", b'{"linear": 5, "angular": 0}') is None
    clock.advance(1_000_000_000)             # a refusal nobody waits for (no ack): reported once a second per kind
    assert inbox.submit("teleop", b"\xff\xfe") is None
    assert [k for k, _ in rejected] == ["teleop", "teleop"] and mailbox.drain(clock.now_ns()) == ([], [])
    assert inbox.submit("estop", b'{"reason": "first"}') is not None
    for _ in range(SAFETY_LANE_LIMIT + 5):
        inbox.submit("resume", b"{}")
    assert inbox.submit("estop", b'{"reason": "last"}') is not None       # a full lane still takes an estop
    assert inbox.rejected == 2 + 6                                         # each refusal counted, one reported
    assert len(rejected) == 2 + 1 and rejected[-1][1].startswith("command lane full")
    clock.advance(1_000_000_000)
    inbox.submit("resume", b"{}")
    assert rejected[-1][1].startswith("command lane full") and \
        rejected[-1][1].endswith("(and 5 more resume commands refused for this reason since the last report)"), \
        rejected[-1]
    applied, refused = mailbox.drain(clock.now_ns())
    kinds = [c.kind for c in applied]
    assert not refused and len(kinds) == SAFETY_LANE_LIMIT + 1 and kinds[0] == kinds[-1] == "estop"
    assert applied[-1].args == ("last",) and applied[0].args == ("first",)    # the oldest was not evicted


# ---- the publisher ------------------------------------------------------------------------

class ListSink(Sink):
    def __init__(self):
        self.states, self.events, self.images = [], [], []

    def state(self, stamp_ns, payload, msg):
        self.states.append(decode(payload))

    def event(self, stamp_ns, payload, msg):
        self.events.append(decode(payload))

    def image(self, stamp_ns, payload, msg, jpeg):
        self.images.append((decode(payload), jpeg))


def _sample(t_ns, cycle, **kw):
    return StateSample(t_ns, cycle, "teleop", "ok", odom=(0.1, 0.2, 0.3), **kw)


def test_state_is_decimated_on_the_sample_clock_with_jitter_and_stalls():
    sink = ListSink()
    pub = TelemetryPublisher("sim", [sink], state_rate_hz=20, loop_rate_hz=100)
    period = 10_000_000
    jitter = [0, 300_000, 50_000, 2_000_000, 0]  # wake-up lateness pattern, < half a period
    for k in range(200):                          # 2 s at 100 Hz
        pub.offer_state(_sample(k * period + jitter[k % 5], k))
    for k in range(300, 400):                     # after a 1 s stall
        pub.offer_state(_sample(k * period, k))
    pub.close()
    cycles = [s["cycle"] for s in sink.states]
    assert cycles[:40] == list(range(0, 200, 5))
    assert cycles[40:] == list(range(300, 400, 5))
    assert [s["seq"] for s in sink.states] == list(range(1, len(cycles) + 1))


def test_state_message_fields():
    sink = ListSink()
    pub = TelemetryPublisher("bot", [sink], state_rate_hz=20, loop_rate_hz=100)
    pub.offer_state(StateSample(123, 7, "repeat", "estop", ("estop: from zenoh",), (1, 2, 0.5), None,
                                (1.1, 2.1, 0.4), 3, 1.0, -1.0, 0.9, -0.8, 0.1, 0.2, 150_000, 20_000, 2, "r.json",
                                latched_ns=100))
    pub.event("mode_change", stamp_ns=5, mode="repeat", previous="idle")
    pub.close()
    s = sink.states[0]
    assert (s["schema"], s["version"], s["robot"], s["mode"], s["route"]) == ("vbnav.state", 1, "bot", "repeat",
                                                                              "r.json")
    assert s["safety"] == {"state": "estop", "faults": ["estop: from zenoh"], "latched_ns": 100}
    assert s["pose"] == {"odom": {"x": 1.0, "z": 2.0, "theta": 0.5}, "vbc": None,
                         "vslam": {"x": 1.1, "z": 2.1, "theta": 0.4}}
    assert s["wheels"] == {"cmd": {"left": 1.0, "right": -1.0}, "meas": {"left": 0.9, "right": -0.8}}
    assert s["keyframe"] == 3 and s["loop"]["compute_ms"] == pytest.approx(0.15)
    e = sink.events[0]
    assert (e["schema"], e["kind"], e["mode"], e["previous"], e["stamp_ns"]) == ("vbnav.event", "mode_change",
                                                                                "repeat", "idle", 5)


def test_offer_never_blocks_and_drops_when_the_queue_is_full():
    pub = TelemetryPublisher("sim", [ListSink()], state_rate_hz=1000, loop_rate_hz=1000)  # thread not started
    queued = sum(pub.offer_state(_sample(k * 1_000_000, k)) for k in range(QUEUE_LIMIT + 50))
    assert queued == QUEUE_LIMIT and pub.dropped == 50
    pub.close()


def test_a_blocked_sink_never_drops_a_command_answer_for_routine_telemetry_and_says_what_it_dropped():
    """Found by an audit: with the publisher thread stuck in a sink, states filled the 256 places of the queue and
    the answer of an applied command (and a safety trip) was dropped with them, unsaid: its sender waited for
    nothing. Events now have places of their own beyond the routine ones, and events dropped beyond those are
    counted and announced (an events_dropped event) once the publisher runs again."""
    sink = ListSink()
    pub = TelemetryPublisher("sim", [sink], state_rate_hz=1000, loop_rate_hz=1000)  # thread not started: stuck
    assert sum(pub.offer_state(_sample(k * 1_000_000, k)) for k in range(QUEUE_LIMIT + 10)) == QUEUE_LIMIT
    assert pub.event("command", stamp_ns=1, command="resume", ack="a1")
    assert pub.event("safety_trip", stamp_ns=2, cause="estop", message="estop from test")
    flood = sum(pub.event("command_rejected", stamp_ns=3, command="mode", reason="bad") for _ in range(EVENT_RESERVE))
    assert flood == EVENT_RESERVE - 2
    assert not pub.event("command", stamp_ns=4, command="estop", ack="a2")
    pub.close()
    kinds = [e["kind"] for e in sink.events if e["kind"] != "events_dropped"]
    assert kinds[:2] == ["command", "safety_trip"] and len(kinds) == EVENT_RESERVE, kinds[:3]
    assert [e["ack"] for e in sink.events if e["kind"] == "command"] == ["a1"]
    said = [e for e in sink.events if e["kind"] == "events_dropped"]
    assert len(said) == 1 and said[0]["count"] == 3 and said[0]["kinds"] == {"command_rejected": 2, "command": 1}
    assert "command" in said[0]["message"] and "3 events" in said[0]["message"], said[0]


def test_vbnav_send_without_an_answer_says_the_robot_dropped_events_rather_than_blaming_the_operators(capsys):
    import argparse

    from vbnav.control.commands.send import REFUSED, _report
    dropped = {"kind": "events_dropped", "count": 3, "message": "3 events were not published (command x3): ..."}
    args = argparse.Namespace(wait=2.0, user=None, tls_cert=None)
    assert _report(args, "r1", "resume", None, 1, dropped=dropped) == REFUSED
    err = capsys.readouterr().err
    assert "3 events were not published" in err and "vbnav monitor" in err and "telemetry.operators" not in err, err


def test_vbnav_send_hears_an_events_dropped_that_carries_no_ack():
    """vbnav send read the robot's events_dropped only after its filter on its own ack, which that event never
    carries: an answer lost with it was still called 'the robot may refuse commands from ...'."""
    from vbnav.control.commands.send import _Heard
    heard = _Heard("A1", signed=False)
    for msg in ({"kind": "events_dropped", "count": 3, "message": "3 events were not published"},
                {"kind": "command", "ack": "B2"}, {"kind": "command_pending", "ack": "A1"}):
        heard.take(msg)
    assert [m["count"] for m in heard.dropped] == [3] and heard.answers.empty() and len(heard.pending) == 1
    heard.take({"kind": "command_rejected", "ack": "A1", "reason": "x"})
    assert heard.answers.get_nowait()["reason"] == "x"


def test_vbnav_send_finds_an_answer_the_network_dropped_in_the_robots_event_history():
    """The robot publishes its events with congestion control DROP: an answer zenoh dropped on the way left vbnav
    send saying 'no acknowledgement: the robot may refuse commands from ...', untrue, though the robot's event
    history (events/recent) held it. vbnav send asks the history before it says no answer came."""
    from types import SimpleNamespace

    from vbnav.control.commands.send import _Heard
    history = {"schema": "vbnav.events.recent", "events": [{"kind": "command", "ack": "B2", "cycle": 3},
                                                           {"kind": "command", "ack": "A1", "cycle": 7}]}
    reply = SimpleNamespace(ok=SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: json.dumps(history).encode())))
    asked = []
    session = SimpleNamespace(get=lambda key, timeout: asked.append(key) or [reply])
    heard = _Heard("A1", signed=False)
    heard.recall(session, "r1")
    assert asked == ["vbnav/r1/events/recent"] and heard.answers.get_nowait()["cycle"] == 7
    heard.recall(SimpleNamespace(get=lambda key, timeout: [SimpleNamespace(ok=None)]), "r1")     # no history
    assert heard.answers.empty()


def test_a_failing_sink_does_not_stop_the_others():
    class Broken(Sink):
        def state(self, *a):
            raise OSError("disk full")
    good = ListSink()
    pub = TelemetryPublisher("sim", [Broken(), good], state_rate_hz=20).start()
    for k in range(10):
        pub.offer_state(_sample(k * 50_000_000, k))
    pub.close()
    assert len(good.states) == 10 and pub.sink_errors == 10


# ---- commands into the real runtime, on the simulated clock ---------------------------------

def _runtime(controller, clock):
    cfg = Config.model_validate({"telemetry": {"enabled": False}, "safety": {"command_timeout_s": 0.5}})
    drive = RecordingDrive(clock)
    rt = Runtime(cfg, drive, controller, clock)
    return cfg, drive, rt


def test_teleop_silence_stops_the_robot_after_the_timeout_on_the_sim_clock():
    clock = SimClock()
    cfg, drive, rt = _runtime(TeleopController(0.5), clock)
    inbox = CommandInbox(LIMITS, deliver=rt.submit, now_ns=clock.now_ns)
    sent = []

    def operator(r, ctx, twist, wheels):  # teleop at 10 Hz for 2 s of loop time, then silence
        if ctx.cycle % 10 == 0 and ctx.now_ns - r._start_ns < 2e9:
            inbox.submit("teleop", json.dumps({"linear": 0.3, "angular": 0.2}))
            sent.append(ctx.now_ns)

    rt.cycle_observers.append(operator)
    rt.run(4.0)
    last = sent[-1]
    period = rt.loop.period_ns
    assert drive.last_motion_ns() > last                              # kept moving after the last message ...
    assert drive.last_motion_ns() <= last + 0.5e9 + 2 * period        # ... until the timeout, and no longer
    assert drive.stopped_since(last + int(0.5e9) + 2 * period)
    assert any(e.cause == "command_timeout" and e.kind == "hold" and e.stamp_ns > last for e in rt.safety.events)


def test_garbage_commands_never_move_an_idle_robot():
    clock = SimClock()
    cfg, drive, rt = _runtime(IdleController(), clock)
    rejected = []
    inbox = CommandInbox(LIMITS, deliver=rt.submit, on_reject=lambda *a: rejected.append(a), now_ns=clock.now_ns)
    junk = [("teleop", b'{"linear": 99, "angular": 0}'), ("teleop", b"{{{{"), ("teleop", b'{"linear": 1e309}'),
            ("mode", b'{"mode": "repeat"}'), ("rm -rf", b"{}"), ("teleop", bytes(range(256)))]

    def attacker(r, ctx, twist, wheels):
        if ctx.cycle < 100:
            inbox.submit(*junk[ctx.cycle % len(junk)])

    rt.cycle_observers.append(attacker)
    result = rt.run(1.5)
    # every one refused; reported once a second per kind and reason (no ack: nobody waits for the answers)
    assert result.ok and inbox.rejected == 100 and inbox.accepted == 0
    keys = [(k, r.split()[0]) for k, r, *_ in rejected]
    assert len(rejected) == len(set(keys)) == 4, rejected     # teleop: 'linear' and 'not' (JSON); mode; unknown
    assert drive.last_motion_ns() == -1


def test_a_sender_making_up_reasons_still_gets_ten_refusals_reported_a_second():
    # A field name of the sender's own starts its refusal's reason: one key each, so 1000 of them a second
    # would each be a first report. At most UNANSWERED_REPORTS a second are, in all; the rest are counted.
    from vbnav.control.comms.operator_commands import UNANSWERED_REPORTS
    clock = SimClock()
    rejected = []
    inbox = CommandInbox(LIMITS, deliver=lambda c: None, on_reject=lambda *a: rejected.append(a), now_ns=clock.now_ns)
    for n in range(1000):
        inbox.submit("mode", json.dumps({f"f{n}": 1, "mode": "idle"}).encode())
        clock.advance(500_000)                      # 1000 in 0.5 s
    assert inbox.rejected == 1000 and len(rejected) == UNANSWERED_REPORTS == 10
    assert [r[1].split(":")[0] for r in rejected] == [f"f{n}" for n in range(10)]
    clock.advance(1_000_000_000)
    inbox.submit("mode", b'{"f999": 1, "mode": "idle"}')  # a second on: a key held back is said with its count
    assert len(rejected) == 11 and rejected[-1][1].endswith("(and 1 more mode commands refused for this reason "
                                                            "since the last report)"), rejected[-1]


# ---- recording ----------------------------------------------------------------------------

def test_recording_of_a_sim_run_has_every_channel_at_its_rate(tmp_path):
    from vbnav.control.controllers.manual import ScriptedController
    clock = SimClock()
    cfg, drive, rt = _runtime(ScriptedController([[0.3, 0.0, 3.0], [0.3, 0.4, 4.0], [0.0, 0.0, 3.0]]), clock)
    path = tmp_path / "run.mcap"
    link = TelemetryLink.attach(rt, cfg, record=str(path))
    result = rt.run()
    link.close(result)
    assert not (tmp_path / "run.mcap.part").exists()
    s = read_recording(path)
    assert s.complete and s.truncated_reason == ""
    assert set(s.channels) == {"/vbnav/state", "/vbnav/events", "/vbnav/log", "/vbnav/pose/odom", "/vbnav/odometry"}
    state = s.channels["/vbnav/state"]
    assert state.schema == "vbnav.state" and s.channels["/vbnav/pose/odom"].schema == "foxglove.PoseInFrame"
    assert abs(state.count - 10.0 * 20) <= 1 and state.rate_hz == pytest.approx(20.0, rel=1e-6)
    assert s.channels["/vbnav/pose/odom"].count == state.count
    kinds = [json.loads(d)["kind"] for t, _, _, d in iter_recording(path) if t == "/vbnav/events"]
    assert kinds[0] == "run_start" and "mode_change" in kinds and kinds[-1] == "run_end"
    from foxglove_client import double, protobuf_fields
    poses = [protobuf_fields(d) for t, _, _, d in iter_recording(path) if t == "/vbnav/pose/odom"]
    assert poses[-1][2] == [b"odom"]                              # foxglove.PoseInFrame: frame_id, pose
    position = protobuf_fields(protobuf_fields(poses[-1][3][0])[1][0])
    x, y = (double(position[k][0]) if k in position else 0.0 for k in (1, 2))
    assert math.hypot(x, y) > 1.0                                 # the scripted drive went somewhere
    assert "vbnav.state" in format_summary(s)


def test_record_info_cli(tmp_path, capsys):
    from vbnav.control.cli import main
    path = tmp_path / "r.mcap"
    rec = McapRecorder(path, "sim")
    pub = TelemetryPublisher("sim", [rec], state_rate_hz=20)
    for k in range(100):
        pub.offer_state(_sample(1_000_000_000 + k * 10_000_000, k))
    pub.close()
    assert main(["record-info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "/vbnav/state" in out and " 20 " in out and "complete" in out
    assert main(["record-info", str(tmp_path / "missing.mcap")]) == 2
    (tmp_path / "bad.mcap").write_text("hello")
    assert main(["record-info", str(tmp_path / "bad.mcap")]) == 2


def test_images_and_rejected_mode_commands_reach_the_recording(tmp_path):
    import cv2
    import numpy as np

    from runtime_helpers import make_runtime
    from vbnav.control.controllers.manual import ScriptedController
    cfg = Config.model_validate({"telemetry": {"enabled": False, "image_rate_hz": 5, "image_width": 32}})
    rt, drive, clock = make_runtime(ScriptedController([[0.2, 0.0, 4.0]]), cfg=cfg, cam_kw={"rate_hz": 15})
    path = tmp_path / "img.mcap"
    link = TelemetryLink.attach(rt, cfg, record=str(path))

    def operator(r, ctx, twist, wheels):
        if ctx.cycle == 100:
            link.inbox.submit("mode", '{"mode": "teach", "route": "r.json"}')   # valid, but this run has no modes
            link.inbox.submit("teleop", '{"linear": 9, "angular": 0}')          # out of range

    rt.cycle_observers.append(operator)
    link.close(rt.run())
    s = read_recording(path)
    assert abs(s.channels["/vbnav/image"].count - 4 * 5) <= 1
    assert s.channels["/vbnav/image"].schema == "foxglove.CompressedImage"
    from foxglove_client import protobuf_fields
    img = next(protobuf_fields(d) for t, _, _, d in iter_recording(path) if t == "/vbnav/image")
    assert img[3] == [b"jpeg"] and img[4] == [b"camera"] and 1 in img     # foxglove.CompressedImage, protobuf
    decoded = cv2.imdecode(np.frombuffer(img[2][0], np.uint8), cv2.IMREAD_UNCHANGED)
    assert decoded.shape == (24, 32)                           # 48x64 test frames scaled to width 32
    events = [json.loads(d) for t, _, _, d in iter_recording(path) if t == "/vbnav/events"]
    rejected = {e["command"]: e["reason"] for e in events if e["kind"] == "command_rejected"}
    assert "switching to 'teach' needs a new run" in rejected["mode"] and "outside" in rejected["teleop"]
    logs = [protobuf_fields(d) for t, _, _, d in iter_recording(path) if t == "/vbnav/log"]
    # foxglove.Log: level (2) WARNING = 3, message (3)
    assert any(entry.get(2) == [3] and b"command_rejected" in entry[3][0] for entry in logs)


def test_non_finite_numbers_are_sent_as_null():
    sink = ListSink()
    pub = TelemetryPublisher("sim", [sink], state_rate_hz=20)
    pub.offer_state(StateSample(1, 0, "idle", "ok", (), (float("nan"), 0, 0), meas_left=float("inf")))
    pub.close()
    assert sink.states[0]["pose"]["odom"] is None and sink.states[0]["wheels"]["meas"]["left"] is None


def test_record_into_a_missing_directory_fails_before_opening_the_network(tmp_path):
    clock = SimClock()
    cfg = Config.model_validate({"telemetry": {"listen": ["tcp/127.0.0.1:1"]}})  # would fail to open anyway
    rt = Runtime(cfg, RecordingDrive(clock), IdleController(), clock)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        TelemetryLink.attach(rt, cfg, record=str(tmp_path / "no" / "such" / "dir" / "r.mcap"))


def test_vbc_pose_and_keyframe_come_from_the_repeat_estimate():
    from vbnav.control.runtime.interfaces import Estimate
    from vbnav.control.stages.vbc_fix import VBCFix
    from vbnav.control.comms.link import _estimate_pose
    from vbnav.vision.geometry import Pose2
    fix = VBCFix(7, Pose2(0.05, -0.4, 0.02), Pose2(1.0, 2.0, 0.1), 12)
    assert _estimate_pose(Estimate(1, "vbc", True, fix, {"keyframe": 7})) == Pose2(0.05, -0.4, 0.02)
    assert _estimate_pose(Estimate(1, "vbc", False, fix, {"keyframe": 7})) is None     # not trusted
    assert _estimate_pose(Estimate(1, "vslam", True, Pose2(3, 4, 5))) == Pose2(3, 4, 5)
    assert _estimate_pose(Estimate(1, "obstacles", True, {"zones": []})) is None


# ---- vbnav monitor's live view ------------------------------------------------------------------

class _Silent:
    """A zenoh session with nobody on it."""

    def declare_subscriber(self, key, callback):
        return None

    def get(self, key, timeout=None):
        return []

    def close(self):
        pass


@pytest.mark.parametrize("argv", [["monitor", "--robot", "sim"], ["monitor", "--all"]])
def test_monitor_refresh_below_half_a_hertz_is_the_rate_used(monkeypatch, argv):
    """--refresh 0.2 was raised to 0.5 Hz without a word: the live view now redraws every 5 s as asked."""
    from vbnav.control import cli
    from vbnav.control.commands import monitor
    monkeypatch.setattr(monitor, "open_robot", lambda args, who: (_Silent(), "sim"))
    monkeypatch.setattr(monitor, "open_client", lambda args: _Silent())
    periods = []

    def sleep(s):
        periods.append(s)
        raise KeyboardInterrupt     # one screen is enough
    monkeypatch.setattr("time.sleep", sleep)
    assert cli.main([*argv, "--refresh", "0.2"]) == 0
    assert periods == [pytest.approx(5.0)]


def test_monitor_all_live_says_when_no_robot_sends_state_after_the_timeout(monkeypatch, capsys):
    """--timeout in the live view of every robot: after S s with no state it says so, as for one robot."""
    import time as _time

    from vbnav.control import cli
    from vbnav.control.commands import monitor
    monkeypatch.setattr(monitor, "open_client", lambda args: _Silent())
    real_sleep, screens = _time.sleep, []

    def sleep(s):
        screens.append(capsys.readouterr().out)
        if len(screens) == 2:
            raise KeyboardInterrupt
        real_sleep(0.3)                                  # past the 0.2 s timeout before the second screen
    monkeypatch.setattr("time.sleep", sleep)
    assert cli.main(["monitor", "--all", "--timeout", "0.2"]) == 0
    assert "no robot has sent state in 0.2 s" not in screens[0]
    assert "no robot has sent state in 0.2 s" in screens[1]


# ---- vbnav send teleop --for ---------------------------------------------------------------------

class _Robot:
    """A zenoh session with one robot on it that applies every command (answers the first ack)."""

    def __init__(self):
        self.sent, self.events = [], None

    def declare_subscriber(self, key, callback):
        self.events = callback

    def declare_publisher(self, key, **kw):
        robot = self

        class Pub:
            matching_status = type("M", (), {"matching": True})()

            def put(self, payload, attachment=None):
                msg = json.loads(payload)
                robot.sent.append(msg)
                if "ack" in msg:
                    answer = json.dumps(robot.answer(msg)).encode()
                    robot.events(type("S", (), {"payload": type("P", (), {"to_bytes": lambda s: answer})()})())
        return Pub()

    def answer(self, msg: dict) -> dict:
        """The robot's answer to a message with an ack: applied."""
        return {"ack": msg["ack"], "kind": "command", "cycle": 7}

    def get(self, key, timeout=None):
        return [type("R", (), {"ok": object()})()]

    def close(self):
        pass


def test_send_teleop_for_ends_its_stream_with_a_stop(monkeypatch, capsys):
    """send teleop V W --for S promises the robot drives S seconds, but the stream just ended: the robot drove
    on with the last command until its safety.command_timeout_s (0.5 s more in configs/sim.yaml; a 0.01 s
    --for drove 0.5 s). The stream now ends with a zero command, as the keyboard teleop's does."""
    from vbnav.control import cli
    from vbnav.control.commands import send
    robot = _Robot()
    monkeypatch.setattr(send, "open_client", lambda args: robot)
    assert cli.main(["send", "teleop", "0.2", "0.1", "--for", "0.2", "--rate", "20", "--robot", "sim"]) == 0
    moving = [m for m in robot.sent if (m["linear"], m["angular"]) == (0.2, 0.1)]
    assert len(moving) == 4 and robot.sent[:4] == moving
    assert [(m["linear"], m["angular"]) for m in robot.sent[4:]] == [(0.0, 0.0)]
    assert "teleop applied by robot sim at cycle 7 (4 messages sent, then a stop)" in capsys.readouterr().out
    robot.sent.clear()
    assert cli.main(["send", "teleop", "0.2", "0", "--robot", "sim"]) == 0     # one message: no stream to end
    assert [(m["linear"], m["angular"]) for m in robot.sent] == [(0.2, 0.0)]


@pytest.mark.parametrize("argv, why", [
    (["--speed", "0.8"], "--speed 0.8: above robot.max_linear_speed 0.5"),
    (["--turn", "2"], "--turn 2: above robot.max_angular_speed 1.5"),
])
def test_keyboard_teleop_refuses_speeds_the_configured_robot_refuses(argv, why, capsys):
    """vbnav teleop -c sim --speed 0.8 said 'driving v +0.80 m/s' while the robot refused every message
    (robot.max_linear_speed 0.5): with the robot's configuration given, the speeds are checked first."""
    from vbnav.control import cli
    assert cli.main(["teleop", "-c", "sim", *argv]) == 2
    assert f"vbnav teleop: {why} of " in capsys.readouterr().err


@pytest.mark.parametrize("kind, payload", [
    ("estop", '{"reason": "\\u001b[2J\\u001b[H12:00:00 safety reset: estop"}'),
    ("teleop", '{"linear": 0.1, "angular": 0, "sender": "op\\u001b[2K"}'),
    ("resume", '{"session": "s\\r\\n12:00:00 safety reset"}'),
    ("mode", '{"mode": "idle", "sender": "op\\u009b2J"}'),
])
def test_control_characters_in_free_text_command_fields_are_refused(kind, payload):
    """An estop reason, a sender or a session is printed on the robot's console (the event echo), in the
    journal and in vbnav monitor: one carrying terminal escapes or line breaks could clear the screen or
    forge a line ('safety reset: estop') there. Control characters are refused, naming the field."""
    with pytest.raises(CommandRejected, match="control character"):
        parse_command(kind, payload, LIMITS)


def test_a_state_rate_above_the_loop_rate_is_refused_at_load():
    """telemetry.state_rate_hz above loop.rate_hz was accepted and the state came once a cycle, at the loop's
    rate (a state is published from a cycle): 200 Hz asked, 100 Hz sent. Refused at load naming both; the
    default is cut to the loop's rate (what is sent), as config show prints it."""
    with pytest.raises(ConfigError, match=r"robot.yaml: .*telemetry.state_rate_hz 200 Hz is above loop.rate_hz 100"):
        parse_config({"telemetry": {"state_rate_hz": 200}}, "robot.yaml")
    assert parse_config({"telemetry": {"state_rate_hz": 100}}).telemetry.state_rate_hz == 100
    slow = parse_config({"loop": {"rate_hz": 10}})
    assert slow.telemetry.state_rate_hz == 10
    assert parse_config(slow.model_dump(mode="json")).telemetry.state_rate_hz == 10     # loads back


@pytest.mark.parametrize("camera, rate, field", [
    ({"driver": "sim", "rate_hz": 15.0}, 15, "camera.rate_hz"),
    ({"driver": "oak", "options": {"replay_file": "rec.mp4", "replay_fps": 10.0}}, 10, "camera.options.replay_fps"),
    ({"driver": "v4l2", "rate_hz": 20.0, "options": {"device": "/dev/video0", "source": "device"}}, 20,
     "camera.rate_hz"),
])
def test_an_image_rate_above_the_cameras_frame_rate_is_refused_at_load(camera, rate, field):
    """telemetry.image_rate_hz above the camera's frame rate was accepted and an image went out once a frame (the
    simulated camera at 15 Hz with image_rate_hz 30: 15 images a second recorded). Refused at load naming both
    where the configuration gives the frame rate; the default is cut to it; a replayed recording (its own rate)
    is not known at load."""
    with pytest.raises(ConfigError, match=rf"robot.yaml: telemetry.image_rate_hz 30 Hz is above {re.escape(field)} "
                                          rf"{rate} Hz"):
        parse_config({"camera": camera, "telemetry": {"image_rate_hz": 30}}, "robot.yaml")
    assert parse_config({"camera": camera, "telemetry": {"image_rate_hz": rate}}).telemetry.image_rate_hz == rate
    slow = parse_config({"camera": {"driver": "sim", "rate_hz": 1.0, "stale_after_s": 2.0},
                         "safety": {"estimate_timeout_s": 2.0}})
    assert slow.telemetry.image_rate_hz == 1.0
    assert parse_config(slow.model_dump(mode="json")).telemetry.image_rate_hz == 1.0     # loads back
    parse_config({"camera": {"driver": "replay", "options": {"path": "rec"}}, "telemetry": {"image_rate_hz": 30}})


def test_an_image_width_above_the_cameras_is_refused_at_load():
    """telemetry.image_width is the width JPEG frames are scaled down to; above the camera's width the frames
    were sent at the camera's width (never scaled up) while the configuration said otherwise. Refused at load
    naming both; the default is cut to a narrower camera's width."""
    import numpy as np

    from vbnav.control.comms.telemetry import encode_jpeg
    assert encode_jpeg(np.zeros((480, 640), np.uint8), 1280, 70)[1:] == (640, 480)     # never scaled up
    with pytest.raises(ConfigError, match=r"robot.yaml: telemetry.image_width 1280 px is above camera.width 640 px"):
        parse_config({"telemetry": {"image_width": 1280}}, "robot.yaml")
    assert parse_config({"telemetry": {"image_width": 640}}).telemetry.image_width == 640
    small = parse_config({"camera": {"width": 160, "height": 120, "cx": 79.5, "cy": 59.5}})
    assert small.telemetry.image_width == 160
    assert parse_config(small.model_dump(mode="json")).telemetry.image_width == 160     # loads back
