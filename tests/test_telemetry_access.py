"""Who can command the robot, and `vbnav send` telling the truth about it (issue 12, points 4 and 5).

In-process: the configuration rules (telemetry.* validation) and the signature check. Over zenoh loopback,
each scenario against a robot process (tests/telemetry_robot.py) on a free port: `vbnav send` against a
running robot, a wrong robot name, a refused command, a non-operator with authentication on a loopback
listener, and signed commands with a shared secret.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from types import SimpleNamespace

import pytest

from test_telemetry_net import Operator, finish, free_port, start_robot   # same directory
from vbnav.control.comms.command_auth import CommandVerifier, _mac, read_secret, sign
from vbnav.control.comms.network import robot_session_config
from vbnav.control.config import ConfigError, parse_config


def parse_telemetry_config(section: dict, source: str = "<config>"):
    """The telemetry section as a whole configuration validates it (errors name source and key path)."""
    return parse_config({"telemetry": section}, source).telemetry

CLI = [sys.executable, "-m", "vbnav.control.cli"]


def _users(tmp_path):
    d = tmp_path / "users.txt"
    d.write_text("robot:robot-secret\noperator:operator-pw\nviewer:viewer-pw1\n")
    return str(d)


def _usrpwd(tmp_path):
    return {"usrpwd": {"user": "robot", "password": "robot-secret", "dictionary_file": _users(tmp_path)}}


def _secret_file(tmp_path, name="secret", mode=0o600, text="0123456789abcdef0123456789abcdef"):
    p = tmp_path / name
    p.write_text(text + "\n")
    p.chmod(mode)
    return p


def _commanders(conf):
    return [p["subjects"] for p in conf["access_control"]["policies"] if "commands-in" in p["rules"]]


# ---- configuration -------------------------------------------------------------------------

def test_authentication_on_a_loopback_listener_enforces_the_operators(tmp_path):
    t = parse_telemetry_config({"listen": ["tcp/127.0.0.1:7447"], "auth": _usrpwd(tmp_path), "operators": ["op"]})
    conf = robot_session_config(t, "sim")
    assert _commanders(conf) == [["operators", "operators-tls"]]
    subjects = {s["id"]: s for s in conf["access_control"]["subjects"]}
    assert subjects["operators"]["usernames"] == ["op"]


def test_authentication_without_operators_is_refused_even_on_loopback(tmp_path):
    with pytest.raises(ConfigError, match=r"robot.yaml: telemetry: .*telemetry.operators: authentication is "
                                          r"configured.*nobody could"):
        parse_telemetry_config({"auth": _usrpwd(tmp_path)}, "robot.yaml")


def test_operators_without_authentication_are_refused():
    with pytest.raises(ConfigError, match=r"telemetry.operators: without telemetry.auth no peer is identified"):
        parse_telemetry_config({"operators": ["op"]})


@pytest.mark.parametrize("connect", ["tcp/127.0.0.1:7448", "tcp/10.0.0.2:7447"])
def test_a_connect_endpoint_is_remote_even_on_loopback_unless_the_router_is_trusted(connect):
    with pytest.raises(ConfigError, match=rf"remote access \(connect {connect}\).*authentication.*"
                                          r"telemetry.operators.*trust_router"):
        parse_telemetry_config({"connect": [connect]})
    t = parse_telemetry_config({"connect": [connect], "trust_router": True})
    assert not t.remote
    assert _commanders(robot_session_config(t, "sim")) == [["everyone"]]


@pytest.mark.parametrize("section,message", [
    ({"trust_router": True}, r"telemetry.trust_router: true trusts the routers in telemetry.connect, which is empty"),
    ({"trust_router": True, "connect": ["tcp/127.0.0.1:7448"], "listen": ["tcp/0.0.0.0:7447"]},
     r"telemetry.trust_router: .*found tcp/0.0.0.0:7447: listen on loopback only"),
    ({"trust_router": True, "connect": ["tcp/127.0.0.1:7448"], "operators": ["op"]},
     r"telemetry.operators cannot be enforced with telemetry.trust_router"),
])
def test_trust_router_is_refused_where_it_cannot_hold(section, message):
    with pytest.raises(ConfigError, match=message):
        parse_telemetry_config(section)


def test_a_trusted_router_with_authentication_lets_the_router_decide(tmp_path):
    t = parse_telemetry_config({"connect": ["tcp/10.0.0.2:7447"], "trust_router": True, "auth": _usrpwd(tmp_path)})
    assert _commanders(robot_session_config(t, "sim")) == [["everyone"]]


def test_shared_secret_file_is_checked_at_load(tmp_path):
    good = _secret_file(tmp_path)
    assert parse_telemetry_config({"shared_secret_file": str(good)}).shared_secret_file == str(good)
    loose = _secret_file(tmp_path, "loose", mode=0o644)
    with pytest.raises(ConfigError, match=r"robot.yaml: telemetry: .*telemetry.shared_secret_file: .*loose: mode "
                                          r"0644 lets other users read the secret; run `chmod 600"):
        parse_telemetry_config({"shared_secret_file": str(loose)}, "robot.yaml")
    short = _secret_file(tmp_path, "short", text="abc")
    with pytest.raises(ConfigError, match=r"telemetry.shared_secret_file: .*3 bytes, at least 16"):
        parse_telemetry_config({"shared_secret_file": str(short)})
    with pytest.raises(ConfigError, match=r"telemetry.shared_secret_file: .*cannot read"):
        parse_telemetry_config({"shared_secret_file": str(tmp_path / "missing")})
    with pytest.raises(ConfigError, match=r"telemetry.shared_secret_file: signed commands are for a robot reachable "
                                          r"from this machine only.*connect tcp/127.0.0.1:7448"):
        parse_telemetry_config({"shared_secret_file": str(good), "connect": ["tcp/127.0.0.1:7448"],
                                "trust_router": True})


# ---- the signature check (in-process, a fake clock) ----------------------------------------

def test_signed_commands_unsigned_wrong_stale_and_replayed_are_refused():
    secret, key, payload = b"0123456789abcdef-secret", "vbnav/sim/cmd/resume", b'{"seq": 1}'
    now = [10_000_000_000]
    v = CommandVerifier(secret, window_s=5.0, now_ns=lambda: now[0])
    att = sign(secret, key, payload, stamp_ns=now[0])
    assert v.verify(key, payload, att) is None
    assert v.verify(key, payload, att).startswith("replayed")
    assert v.verify(key, payload, None).startswith("unsigned")
    assert v.verify(key, payload, b"garbage").startswith("malformed")
    assert v.verify(key, payload, sign(b"another-secret-of-16", key, payload)).startswith("bad signature")
    assert v.verify(key, b'{"seq": 2}', att).startswith("bad signature")              # payload changed
    assert v.verify("vbnav/sim/cmd/estop", payload, att).startswith("bad signature")  # replayed on another command
    assert v.verify(key, payload, sign(secret, key, payload, stamp_ns=now[0] - 6_000_000_000)).startswith("stale")
    now[0] += 6_000_000_000     # the first one left the window: still refused, now as stale
    assert v.verify(key, payload, att).startswith("stale")
    # a stamp of 5000 digits under a valid MAC (a secret holder's): int() raised past Python's 4300-digit limit
    stamp, nonce = b"9" * 5000, b"0123456789abcdef"
    long_stamp = b" ".join((b"vbnav-hmac1", stamp, nonce, _mac(secret, key, stamp, nonce, payload).encode()))
    assert v.verify(key, payload, long_stamp).startswith("malformed")


class _SignedRobot:
    """A robot's command path with a shared secret, on a settable clock: the zenoh subscriber's callback, the
    inbox and the loop's mailbox, its refusals published as events into ``sink`` (``close`` flushes them)."""

    SECRET = b"0123456789abcdef-secret"

    def __init__(self):
        from test_telemetry_units import ListSink
        from vbnav.control.comms.link import TelemetryLink
        from vbnav.control.comms.operator_commands import CommandInbox, CommandSubscriber, TeleopLimits
        from vbnav.control.comms.telemetry import TelemetryPublisher
        from vbnav.control.runtime.mailbox import CommandMailbox

        self.now = [10_000_000_000]
        self.sink = ListSink()
        self.pub = TelemetryPublisher("sim", [self.sink], now_ns=lambda: self.now[0])
        link = SimpleNamespace(publisher=self.pub)
        self.inbox = CommandInbox(TeleopLimits(0.5, 1.5), deliver=CommandMailbox(lambda: self.now[0], 500_000_000).post,
                                  on_reject=lambda *a: TelemetryLink._on_reject(link, *a), now_ns=lambda: self.now[0])
        subscribed = []
        session = SimpleNamespace(declare_subscriber=lambda k, cb: subscribed.append(cb))
        CommandSubscriber(session, "sim", self.inbox,
                          verify=CommandVerifier(self.SECRET, now_ns=lambda: self.now[0]).verify)
        self._on_sample = subscribed[0]

    def put(self, kind: str, payload: bytes, attachment: bytes = None) -> None:
        self._on_sample(SimpleNamespace(key_expr=f"vbnav/sim/cmd/{kind}",
                                        payload=type("P", (), {"__len__": lambda s: len(payload),
                                                               "to_bytes": lambda s: payload})(),
                                        attachment=None if attachment is None else SimpleNamespace(
                                            to_bytes=lambda: attachment)))

    def signature(self, kind: str, payload: bytes) -> bytes:
        return sign(self.SECRET, f"vbnav/sim/cmd/{kind}", payload, stamp_ns=self.now[0])

    def refusals(self) -> list:
        self.pub.close()
        return [e for e in self.sink.events if e["kind"] == "command_rejected"]


def test_a_refusal_of_a_command_whose_signature_failed_never_answers_the_ack_it_carries():
    """Found by an audit: the robot echoed the ack of every refused payload in its command_rejected event, also of
    a payload whose signature failed. Any local user who saw an operator's signed resume on cmd/** could replay
    it (or send it unsigned) at once: the refusal ('replayed', 'unsigned') went out on the zenoh thread before
    the loop applied the genuine one, and `vbnav send`, which takes the first answer carrying its ack, said
    'robot refused resume' of a resume that was applied. The ack of an unverified payload is now reported as
    unverified_ack, which no sender takes for its answer."""
    robot = _SignedRobot()
    payload = json.dumps({"ack": "R1", "sender": "op", "latched_ns": 5}).encode()
    att = robot.signature("resume", payload)
    for args in ((payload, att), (payload, att), (payload, None)):     # the genuine one, a replay, unsigned
        robot.put("resume", *args)
    refusals = robot.refusals()
    assert robot.inbox.accepted == 1 and robot.inbox.rejected == 2
    assert len(refusals) == 2 and [e.get("ack") for e in refusals] == [None, None], refusals
    assert [e.get("unverified_ack") for e in refusals] == ["R1", "R1"], refusals


def test_a_flood_of_refused_commands_makes_a_few_events_and_a_senders_answer_still_goes_out():
    """A refusal was one command_rejected event each: 10,000 malformed, unsigned or unknown commands a second
    filled the events' 1024 places in the telemetry queue, and the events behind them (a command's answer, a
    safety change) were dropped (4866 of them here). A refusal that answers nobody is now reported once a
    second per kind and reason, with the count held back; one a sender waits for (signed, with an ack) goes
    out every time."""
    from vbnav.control.comms.telemetry import EVENT_RESERVE
    robot = _SignedRobot()

    def send(kind: str, body: dict, signed: bool = True):
        payload = json.dumps(body).encode()
        robot.put(kind, payload, robot.signature(kind, payload) if signed else None)

    flood = 2 * EVENT_RESERVE
    for n in range(flood):
        send("mode", {"mode": "fly", "seq": n})                       # signed, malformed, no ack
        send("resume", {"ack": f"x{n}"}, signed=False)                # unsigned, with an ack anyone may copy
        send(f"junk{n}", {})                                          # a kind of the sender's choosing
        if n == flood // 2:
            send("mode", {"mode": "teach", "ack": "OP1"})             # an operator's, refused: its answer
    robot.now[0] += 1_000_000_000                                     # a second on: the count is said
    send("mode", {"mode": "fly"})
    refusals = robot.refusals()
    assert robot.inbox.rejected == 3 * flood + 2 and robot.inbox.accepted == 0
    assert sorted(e["command"] for e in refusals) == ["junk0", "mode", "mode", "mode", "resume"], refusals
    answer = [e for e in refusals if e.get("ack") == "OP1"]
    assert len(answer) == 1 and "needs a route" in answer[0]["reason"], refusals
    assert not [e for e in robot.sink.events if e["kind"] == "events_dropped"] and robot.pub.dropped == 0
    assert refusals[-1]["reason"].endswith(f"(and {flood - 1} more mode commands refused for this reason since "
                                           f"the last report)"), refusals[-1]


def test_vbnav_send_unanswered_names_a_refusal_of_its_ack_whose_signature_failed(capsys):
    import argparse

    from vbnav.control.commands.send import REFUSED, _report
    refusal = {"kind": "command_rejected", "unverified_ack": "R1", "reason": "unsigned: this robot accepts only ..."}
    assert _report(argparse.Namespace(wait=2.0, user=None, tls_cert=None), "r1", "resume", None, 1,
                   unverified=refusal) == REFUSED
    err = capsys.readouterr().err
    assert "signature failed (unsigned: " in err and "--secret-file" in err, err


def test_an_estop_is_verified_even_when_a_flood_filled_the_replay_cache(monkeypatch):
    """The replay cache is bounded: once full, new signed commands were refused, an estop too. An estop is
    never dropped whatever floods the inbox; it is still checked (signature, age, replay)."""
    from vbnav.control.comms import command_auth
    monkeypatch.setattr(command_auth, "REPLAY_CACHE_LIMIT", 3)
    secret, now = b"0123456789abcdef-secret", [10_000_000_000]
    v = CommandVerifier(secret, window_s=5.0, now_ns=lambda: now[0])
    teleop, estop = "vbnav/sim/cmd/teleop", "vbnav/sim/cmd/estop"
    for i in range(3):
        p = b'{"seq": %d}' % i
        assert v.verify(teleop, p, sign(secret, teleop, p, stamp_ns=now[0])) is None
    p = b'{"seq": 9}'
    assert v.verify(teleop, p, sign(secret, teleop, p, stamp_ns=now[0])).startswith("more than 3 signed")
    att = sign(secret, estop, b"{}", stamp_ns=now[0])
    assert v.verify(estop, b"{}", att) is None
    assert v.verify(estop, b"{}", att).startswith("replayed")      # still replay-checked
    assert v.verify(estop, b"{}", sign(secret, estop, b"{}", stamp_ns=now[0] - 6_000_000_000)).startswith("stale")


def test_read_secret_checks_the_owner_for_the_robot_only(tmp_path):
    p = _secret_file(tmp_path)
    assert read_secret(str(p)) == b"0123456789abcdef0123456789abcdef"
    if os.geteuid() == 0:
        os.chown(p, 12345, -1)
        with pytest.raises(ValueError, match="not by the robot's user"):
            read_secret(str(p))
        assert read_secret(str(p), check_owner=False)


# ---- vbnav send against a robot process ----------------------------------------------------

def _send(port, *args, env=None, timeout=30):
    return subprocess.run(CLI + ["send", *map(str, args), "--connect", f"tcp/127.0.0.1:{port}"],
                          capture_output=True, text=True, timeout=timeout, env=env)


def test_send_waits_for_the_robots_answer(tmp_path):
    port = free_port()
    report = tmp_path / "report.json"
    proc = start_robot("--port", port, "--controller", "teleop", "--duration", 60, "--report", report)
    watcher = Operator(port)
    try:
        r = _send(port, "estop", "--reason", "truth")
        assert r.returncode == 0, r.stderr
        assert r.stdout.startswith("estop applied by robot sim at cycle ")
        cycle = int(r.stdout.split("at cycle ")[1].split()[0])
        r = _send(port, "resume")
        assert r.returncode == 0 and "resume applied" in r.stdout and ": " not in r.stdout, r.stderr
        r = _send(port, "resume")           # nothing to clear: taken, and the answer says so
        assert r.returncode == 0 and r.stdout.rstrip().endswith(": nothing was latched"), r.stdout
        r = _send(port, "teleop", 0.2, 0.0, "--duration", 1.0)      # a stream answers on its first message
        assert r.returncode == 0 and "teleop applied" in r.stdout and "messages sent" in r.stdout, r.stderr

        t0 = time.monotonic()
        r = _send(port, "estop", "--robot", "nosuch")
        assert r.returncode == 3 and time.monotonic() - t0 < 10
        assert f"no robot named nosuch is listening on vbnav/nosuch/cmd/estop at tcp/127.0.0.1:{port}" in r.stderr

        r = _send(port, "mode", "repeat", "--route", "no_such_route")     # this run cannot switch modes
        assert r.returncode == 1
        assert "refused mode: this run is 'teleop'; switching to 'repeat' needs a new run" in r.stderr
        r = _send(port, "teleop", 5.0, 0.0)                                  # refused before parsing
        assert r.returncode == 1 and "refused teleop: linear 5.0 m/s outside +-0.5" in r.stderr

        # Nobody can publish a fake state through the robot's session.
        import zenoh
        faker = Operator(port)
        for _ in range(10):
            faker.session.put("vbnav/sim/state", json.dumps({"schema": "vbnav.state", "fake": True}),
                              congestion_control=zenoh.CongestionControl.BLOCK)
            time.sleep(0.05)
        time.sleep(0.3)
        faker.close()
        with watcher.lock:
            states, events = [m for _, m in watcher.states], list(watcher.events)
    finally:
        watcher.close()
        finish(proc, stop=True)
    rep = json.loads(report.read_text())
    received = [c["kind"] for c in rep["received"]]
    assert received[:2] == ["estop", "resume"] and "teleop" in received and "mode" in received
    assert states and not any(m.get("fake") for m in states)
    acked = [e for e in events if e.get("ack")]
    applied = next(e for e in acked if e["kind"] == "command" and e["command"] == "estop")
    assert applied["cycle"] == cycle
    # the command event follows the trip it caused: published once the command took effect
    trip = next(e for e in events if e["kind"] == "safety_trip")
    assert trip["seq"] < applied["seq"]
    assert sum(e["kind"] == "command_rejected" for e in acked) == 2


def test_send_from_a_non_operator_is_refused_on_an_authenticated_loopback_listener(tmp_path):
    users = _users(tmp_path)
    port = free_port()
    report = tmp_path / "report.json"
    proc = start_robot("--port", port, "--controller", "idle", "--duration", 60, "--report", report,
                       "--remote", users, "--operators", "operator", "--loopback")
    env = dict(os.environ)
    try:
        env["VBNAV_ZENOH_PASSWORD"] = "viewer-pw1"
        r = _send(port, "estop", "--reason", "viewer", "--user", "viewer", "--wait", 1.5, env=env)
        assert r.returncode == 1
        assert "no acknowledgement within 1.5 s: the robot may refuse commands from user viewer " \
               "(telemetry.operators)" in r.stderr
        env["VBNAV_ZENOH_PASSWORD"] = "operator-pw"
        r = _send(port, "estop", "--reason", "operator", "--user", "operator", env=env)
        assert r.returncode == 0 and "estop applied" in r.stdout, r.stderr
        r = _send(port, "resume")                              # no credentials: no session at all
        assert r.returncode == 3 and "cannot connect" in r.stderr
    finally:
        finish(proc, stop=True)
    rep = json.loads(report.read_text())
    assert [c["args"] for c in rep["received"]] == [["operator"]]      # the viewer's estop never reached the loop


def test_shared_secret_signed_commands_only(tmp_path):
    secret_path = _secret_file(tmp_path)
    secret = read_secret(str(secret_path))
    port = free_port()
    report = tmp_path / "report.json"
    proc = start_robot("--port", port, "--controller", "idle", "--duration", 60, "--report", report,
                       "--secret-file", secret_path)
    op = Operator(port)
    import zenoh
    key = "vbnav/sim/cmd/estop"

    def put(payload: bytes, attachment=None):
        op.session.put(key, payload, attachment=attachment, congestion_control=zenoh.CongestionControl.BLOCK)
        time.sleep(0.3)

    try:
        time.sleep(0.5)
        put(b'{"reason": "unsigned"}')
        put(b'{"reason": "wrong"}', sign(b"not-the-robots-secret!", key, b'{"reason": "wrong"}'))
        good = b'{"reason": "signed"}'
        att = sign(secret, key, good)
        put(good, att)
        put(good, att)                                                   # the same message again
        r = _send(port, "resume")
        assert r.returncode == 1 and "refused resume: unsigned" in r.stderr
        r = _send(port, "resume", "--secret-file", secret_path)
        assert r.returncode == 0 and "resume applied" in r.stdout, r.stderr
        with op.lock:
            events = list(op.events)
    finally:
        op.close()
        finish(proc, stop=True)
    rep = json.loads(report.read_text())
    assert [c["kind"] for c in rep["received"]] == ["estop", "resume"] and rep["received"][0]["args"] == ["signed"]
    assert len(rep["received"][1]["args"]) == 1         # the latched_ns of the robot's state
    reasons = [e["reason"].split(":")[0] for e in events if e["kind"] == "command_rejected"]
    assert reasons == ["unsigned", "bad signature", "replayed", "unsigned"]


def test_send_resume_names_the_newest_stop_in_the_robots_state(tmp_path):
    """vbnav send resume without --latched-ns cleared every latch, another operator's estop this sender never
    saw among them. It now reads the robot's state and names its safety.latched_ns (as teleop's r does); a
    stop that began after it is not cleared."""
    port = free_port()
    report = tmp_path / "report.json"
    proc = start_robot("--port", port, "--controller", "idle", "--duration", 60, "--report", report)
    watcher = Operator(port)
    try:
        r = _send(port, "estop", "--reason", "first")
        assert r.returncode == 0, r.stderr
        r = _send(port, "resume")
        assert r.returncode == 0 and "resume applied" in r.stdout, r.stderr
        # It says what it clears (the stop's reason, from the state), so an operator sees another's stop in it.
        assert "this resume clears what robot sim's newest state shows: safety estop" in r.stderr, r.stderr
        assert "first" in r.stderr.split("this resume clears")[1], r.stderr
        with watcher.lock:
            states = list(watcher.states)
    finally:
        watcher.close()
        finish(proc, stop=True)
    rep = json.loads(report.read_text())
    (resume,) = [c for c in rep["received"] if c["kind"] == "resume"]
    latched = {s["safety"]["latched_ns"] for _, s in states if s["safety"]["state"] == "estop"}
    assert len(resume["args"]) == 1 and resume["args"][0] in latched, (resume, latched)


def test_send_resume_without_a_state_is_refused_unless_told_to_clear_every_latch(tmp_path):
    """With no state from the robot within --wait (here its one state went out before vbnav send
    subscribed: telemetry.state_rate_hz 0.001), vbnav send resume cannot know which stop it would clear: it
    sends nothing and says so, naming the robot's state topic and the options; --clear-all clears every
    latch knowingly."""
    port = free_port()
    report = tmp_path / "report.json"
    proc = start_robot("--port", port, "--controller", "idle", "--duration", 60, "--report", report,
                       "--state-rate", 0.001)
    try:
        assert _send(port, "estop").returncode == 0
        r = _send(port, "resume", "--wait", 1)
        assert r.returncode == 1, (r.stdout, r.stderr)
        assert "no state from robot sim on vbnav/sim/state within 1 s" in r.stderr, r.stderr
        assert "--latched-ns" in r.stderr and "--clear-all" in r.stderr, r.stderr
        r = _send(port, "resume", "--clear-all", "--latched-ns", 5)
        assert r.returncode == 2 and "not allowed with argument" in r.stderr, r.stderr
        r = _send(port, "resume", "--clear-all")
        assert r.returncode == 0 and "resume applied" in r.stdout, r.stderr
    finally:
        finish(proc, stop=True)
    rep = json.loads(report.read_text())
    assert [(c["kind"], c["args"]) for c in rep["received"]] == [("estop", []), ("resume", [])]
