"""Telemetry and commands between two processes on loopback (the real Runtime in a robot process).

One robot process per scenario (tests/telemetry_robot.py); this process is the operator: a zenoh client
that subscribes to state and events and sends commands. Every test uses a free port, never 7447.
"""
from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from vbnav.control.comms.network import client_session_config, open_session

HERE = Path(__file__).resolve().parent
ROBOT = HERE / "telemetry_robot.py"
PERIOD_NS = 10_000_000        # robot loop at 100 Hz
STATE_PERIOD_NS = 50_000_000  # state at 20 Hz


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_robot(*args, timeout_s: float = 30.0) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, str(ROBOT), *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=str(HERE))
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if line.strip() == "READY":
            return proc
        if not line and proc.poll() is not None:
            raise RuntimeError(f"robot exited {proc.returncode}: {proc.stderr.read()}")
    proc.kill()
    raise RuntimeError("robot did not start")


class Operator:
    """A zenoh client in this process: collects state/events, sends commands."""

    def __init__(self, port: int, robot: str = "sim", user=None, password=None):
        self.session = open_session(client_session_config([f"tcp/127.0.0.1:{port}"], user, password))
        self.robot = robot
        self.lock = threading.Lock()
        self.states: list[tuple[float, dict]] = []
        self.events: list[dict] = []
        self.session.declare_subscriber(f"vbnav/{robot}/state", self._on_state)
        self.session.declare_subscriber(f"vbnav/{robot}/events", self._on_event)

    def _on_state(self, sample):
        msg = json.loads(sample.payload.to_bytes())
        with self.lock:
            self.states.append((time.monotonic(), msg))

    def _on_event(self, sample):
        with self.lock:
            self.events.append(json.loads(sample.payload.to_bytes()))

    def send(self, what: str, **body):
        import zenoh
        self.session.put(f"vbnav/{self.robot}/cmd/{what}", json.dumps(body),
                         congestion_control=zenoh.CongestionControl.BLOCK)

    def teleop_for(self, seconds: float, v: float, w: float, rate_hz: float = 20.0):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.send("teleop", linear=v, angular=w)
            time.sleep(1.0 / rate_hz)

    def close(self):
        self.session.close()


def finish(proc: subprocess.Popen, timeout_s: float = 20.0, stop: bool = False) -> None:
    """Wait for the robot (after SIGTERM if ``stop``: the runtime stops cleanly and writes its report)."""
    if stop and proc.poll() is None:
        proc.terminate()
    try:
        proc.wait(timeout_s)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, proc.stderr.read()


@pytest.fixture(scope="module")
def teleop_session(tmp_path_factory):
    """13 s robot run: teleop 2 s, silence 1.5 s, teleop 1 s, estop (teleop continues 1 s), then watch."""
    tmp = tmp_path_factory.mktemp("net")
    port = free_port()
    report = tmp / "report.json"
    proc = start_robot("--port", port, "--controller", "teleop", "--duration", 13, "--report", report)
    op = Operator(port)
    try:
        t0 = time.monotonic()
        time.sleep(0.5)
        op.teleop_for(2.0, 0.3, 0.2)
        time.sleep(1.5)
        op.teleop_for(1.0, 0.3, -0.2)
        op.send("estop", reason="test")
        op.teleop_for(1.0, 0.3, 0.0)   # must not move a latched robot
        time.sleep(max(0.0, t0 + 11.0 - time.monotonic()))
        with op.lock:
            states, events = list(op.states), list(op.events)
    finally:
        op.close()
    finish(proc)
    return {"states": states, "events": events, "report": json.loads(report.read_text())}


def test_state_arrives_at_the_configured_rate_without_gaps_for_10s(teleop_session):
    states = teleop_session["states"]
    t_first = states[0][0]
    window = [(t, m) for t, m in states if t - t_first <= 10.0]
    seqs = [m["seq"] for _, m in window]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "missing or reordered state messages"
    assert len(window) >= 10.0 * 20 - 2
    stamps = [m["stamp_ns"] for _, m in window]
    gaps = [b - a for a, b in zip(stamps, stamps[1:])]
    # Stamps are loop wake-up times, 5 loop periods apart give or take the wake-up jitter. A gap off that
    # means the loop itself did not run on time (CPU starvation on a shared machine): allowed only as the
    # robot's own loop statistics explain it, each overrun giving at most two (a long gap, then the short
    # one of the catch-up). A fixed share of the gaps failed a run with 4 of 199 beside 15 overruns.
    rep = teleop_session["report"]
    late = [g for g in gaps if not STATE_PERIOD_NS - PERIOD_NS < g < 1.5 * STATE_PERIOD_NS]
    assert len(late) <= 2 * rep["overruns"], (late, rep["overruns"])
    assert stamps[-1] - stamps[0] < (len(stamps) - 1) * STATE_PERIOD_NS * 1.03   # the rate, over 10 s
    rx = [t for t, _ in window]
    assert max(b - a for a, b in zip(rx, rx[1:])) < 1.0   # and none was held back for long in transit
    assert all(m["schema"] == "vbnav.state" and m["version"] == 1 for _, m in window)


def test_teleop_silence_stops_the_robot_after_the_timeout(teleop_session):
    rep = teleop_session["report"]
    teleops = [c["t_ns"] for c in rep["received"] if c["kind"] == "teleop"]
    silence = [(a, b) for a, b in zip(teleops, teleops[1:]) if b - a > 1e9]
    assert len(silence) == 1
    last, resumed = silence[0]
    log = [(t, l, r, p) for t, l, r, p in rep["drive_log"]]
    moving = [t for t, l, r, p in log if p and (l or r) and last - 0.5e9 < t < resumed]
    assert moving and max(moving) > last                         # drove on until the timeout ...
    # ... and not longer: the last message takes effect at the next cycle, which may wake late on a
    # loaded machine by up to the loop's worst lateness.
    assert max(moving) <= last + 0.5e9 + 2 * PERIOD_NS + rep["max_lateness_ms"] * 1e6
    assert any(e["kind"] == "safety_hold" and e["cause"] == "command_timeout" for e in teleop_session["events"])


def test_estop_from_another_process_zeroes_both_wheels_within_two_periods(teleop_session):
    rep = teleop_session["report"]
    estop = next(c for c in rep["received"] if c["kind"] == "estop")
    t_e, c_e = estop["t_ns"], estop["cycle"]      # arrival time, and the loop cycle running at that moment
    log = rep["drive_log"]
    assert any(p and (l or r) for t, l, r, p in log if t_e - 0.2e9 < t < t_e), "robot was not moving at estop"
    # Within two loop periods counted in cycles: the cycle running when it arrived may still write its
    # command, the next one applies the estop. (In wall time that is two periods unless the loop is late.)
    after = [(l, r, p) for c, l, r, p in rep["cycle_log"] if c >= c_e + 2]
    assert after and all((not p) or (l == 0 and r == 0) for l, r, p in after)
    states = [m for _, m in teleop_session["states"] if m["stamp_ns"] >= t_e + 2 * PERIOD_NS]
    assert states
    for m in states:
        assert m["safety"]["state"] == "estop" and any(f.startswith("estop") for f in m["safety"]["faults"])
        assert m["wheels"]["cmd"] == {"left": 0.0, "right": 0.0}
    trips = [e for e in teleop_session["events"] if e["kind"] == "safety_trip"]
    assert trips and trips[0]["cause"] == "estop"


def test_unauthorised_peer_is_refused_commands_but_receives_telemetry(tmp_path):
    users = tmp_path / "users.txt"
    users.write_text("robot:robot-secret\noperator:operator-pw\nviewer:viewer-pw1\n")
    port = free_port()
    report = tmp_path / "report.json"
    proc = start_robot("--port", port, "--controller", "idle", "--duration", 60, "--report", report,
                       "--remote", users, "--operators", "operator")
    try:
        with pytest.raises(Exception):          # wrong password: no session at all
            open_session(client_session_config([f"tcp/127.0.0.1:{port}"], "viewer", "wrong-password"))
        viewer = Operator(port, user="viewer", password="viewer-pw1")
        time.sleep(0.7)
        for _ in range(5):
            viewer.send("estop", reason="viewer")
            time.sleep(0.1)
        time.sleep(1.0)
        operator = Operator(port, user="operator", password="operator-pw")
        time.sleep(0.7)
        operator.send("estop", reason="operator")
        time.sleep(1.0)
        with viewer.lock:
            viewer_states = [m for _, m in viewer.states]
        history = [json.loads(r.ok.payload.to_bytes()) for r in viewer.session.get("vbnav/sim/events/recent",
                                                                                   timeout=2.0) if r.ok]
        viewer.close()
        operator.close()
    finally:
        finish(proc, stop=True)
    rep = json.loads(report.read_text())
    estops = [c["args"] for c in rep["received"] if c["kind"] == "estop"]
    assert estops == [["operator"]]                     # the viewer's five never reached the runtime
    assert len(viewer_states) >= 40                     # ~3 s of 20 Hz state reached the viewer meanwhile
    assert viewer_states[-1]["safety"]["state"] == "estop"   # and it saw the operator's estop take effect
    kinds = [e["kind"] for e in history[0]["events"]]         # the ACL lets readers query the event history
    assert kinds[0] == "run_start" and "safety_trip" in kinds


def test_non_loopback_listener_without_authentication_is_refused_at_start_up():
    port = free_port()
    r = subprocess.run([sys.executable, str(ROBOT), "--port", str(port), "--listen", f"tcp/0.0.0.0:{port}"],
                       capture_output=True, text=True, timeout=60, cwd=str(HERE))
    assert r.returncode == 2 and "READY" not in r.stdout
    assert "remote access (tcp/0.0.0.0" in r.stderr and "authentication" in r.stderr
    with pytest.raises(Exception):  # and nothing is listening
        socket.create_connection(("127.0.0.1", port), timeout=0.5).close()


def test_vbnav_run_and_config_check_refuse_a_public_listener(tmp_path):
    from vbnav.control.cli import main
    cfg = tmp_path / "robot.yaml"
    cfg.write_text("telemetry:\n  listen: ['tcp/0.0.0.0:7447']\n")
    from vbnav.control.config import ConfigError, load_config
    with pytest.raises(ConfigError, match=r"robot.yaml: telemetry: .*remote access \(tcp/0.0.0.0:7447\)"):
        load_config(cfg)       # refused at load, before any device or network opens
    assert main(["run", "--config", str(cfg), "--duration", "1"]) == 2
    assert main(["config", "check", "--config", str(cfg)]) == 2


def _wait_for_recorded_states(part, n: int, timeout_s: float) -> None:
    """Until the recording being written has flushed ``n`` state messages (it flushes a chunk every second)."""
    from vbnav.control.comms.recording import read_recording
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        time.sleep(0.5)
        try:
            ch = read_recording(part).channels.get("/vbnav/state") if part.exists() else None
        except Exception:      # a chunk being written: read again on the next poll
            ch = None
        if ch is not None and ch.count >= n:
            return
    pytest.fail(f"{part}: fewer than {n} state messages recorded within {timeout_s} s")


def test_sigkilled_recording_is_readable_up_to_its_last_chunk(tmp_path):
    from vbnav.control.comms.recording import read_recording
    port = free_port()
    path = tmp_path / "crash.mcap"
    proc = start_robot("--port", port, "--controller", "scripted", "--duration", 60, "--record", path)
    _wait_for_recorded_states(tmp_path / "crash.mcap.part", 40, timeout_s=45)   # not a fixed sleep: start-up
    proc.kill()                                                                # is slower on a loaded machine
    proc.wait(10)
    assert not path.exists() and (tmp_path / "crash.mcap.part").exists()
    s = read_recording(path)
    assert not s.complete
    state = s.channels["/vbnav/state"]
    # flushed every second: at least the first ~2 s of 20 Hz state, contiguous from the start
    assert state.count >= 35 and state.rate_hz == pytest.approx(20.0, rel=0.05)
    assert s.channels["/vbnav/events"].count >= 2          # run_start, mode_change


def test_monitor_and_send_command_line_tools(tmp_path):
    port = free_port()
    report = tmp_path / "report.json"
    proc = start_robot("--port", port, "--controller", "idle", "--duration", 60, "--report", report)
    ep = ["--connect", f"tcp/127.0.0.1:{port}"]
    cli = [sys.executable, "-m", "vbnav.control.cli"]
    try:
        mon = subprocess.run(cli + ["monitor", "--once", "--json", *ep], capture_output=True, text=True, timeout=30)
        assert mon.returncode == 0, mon.stderr
        state = json.loads(mon.stdout)
        assert state["schema"] == "vbnav.state" and state["mode"] == "idle" and state["safety"]["state"] == "ok"
        sent = subprocess.run(cli + ["send", "estop", "--reason", "cli", *ep], capture_output=True, text=True,
                              timeout=30)
        assert sent.returncode == 0, sent.stderr
        bad = subprocess.run(cli + ["send", "mode", "repeat", *ep], capture_output=True, text=True, timeout=30)
        assert bad.returncode == 2 and "needs a route" in bad.stderr      # refused locally, nothing sent
        time.sleep(0.3)
        mon = subprocess.run(cli + ["monitor", "--once", *ep], capture_output=True, text=True, timeout=30)
        assert mon.returncode == 0 and "safety  estop" in mon.stdout and "estop from zenoh" in mon.stdout
        assert "safety_trip" in mon.stdout and "run_start" in mon.stdout   # events from before it started
    finally:
        finish(proc, stop=True)
    rep = json.loads(report.read_text())
    assert [c["args"] for c in rep["received"]] == [["cli"]]
    nobody = subprocess.run(cli + ["monitor", "--once", "--connect", f"tcp/127.0.0.1:{free_port()}"],
                            capture_output=True, text=True, timeout=30)
    assert nobody.returncode == 3 and "cannot connect" in nobody.stderr


def _make_pki(d: Path) -> None:
    """A test CA and certificates for robot, operator and viewer (CN = name; SAN localhost, 127.0.0.1)."""
    def ssl(*args):
        subprocess.run(["openssl", *args], check=True, capture_output=True, cwd=d)
    ssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "1",
        "-subj", "/CN=vbnav-test-ca")
    (d / "ext.cnf").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    for name in ("robot", "operator", "viewer"):
        ssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{name}.key", "-out", f"{name}.csr",
            "-subj", f"/CN={name}")
        ssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
            "-out", f"{name}.pem", "-days", "1", "-extfile", "ext.cnf")


def test_mutual_tls_operator_commands_viewer_refused_via_the_cli(tmp_path):
    import shutil
    if shutil.which("openssl") is None:
        from conftest import unavailable
        unavailable("the openssl command is needed to make test certificates")
    _make_pki(tmp_path)
    port = free_port()
    report = tmp_path / "report.json"
    proc = start_robot("--port", port, "--controller", "idle", "--duration", 60, "--report", report,
                       "--tls", tmp_path, "--operators", "operator")
    cli = [sys.executable, "-m", "vbnav.control.cli"]

    def as_(name):
        return ["--connect", f"tls/localhost:{port}", "--tls-ca", str(tmp_path / "ca.pem"),
                "--tls-cert", str(tmp_path / f"{name}.pem"), "--tls-key", str(tmp_path / f"{name}.key")]
    try:
        r = subprocess.run(cli + ["send", "estop", "--reason", "viewer", "--wait", "1", *as_("viewer")],
                           capture_output=True, text=True, timeout=30)
        # Connected and sent (every peer sees the robot's command subscriber); the robot's ACL dropped it without
        # an answer (the robot's report below proves it never reached the loop).
        assert r.returncode == 1 and "no acknowledgement within 1 s" in r.stderr, r.stderr
        r = subprocess.run(cli + ["monitor", "--once", "--json", *as_("viewer")], capture_output=True, text=True,
                           timeout=30)
        assert r.returncode == 0 and json.loads(r.stdout)["safety"]["state"] == "ok"   # telemetry flows
        with pytest.raises(Exception):            # no client certificate: the robot refuses the session
            open_session(client_session_config([f"tls/localhost:{port}"],
                                               tls={"root_ca_certificate": str(tmp_path / "ca.pem")}))
        r = subprocess.run(cli + ["send", "estop", "--reason", "operator", *as_("operator")],
                           capture_output=True, text=True, timeout=30)
        assert r.returncode == 0, r.stderr
    finally:
        finish(proc, stop=True)
    rep = json.loads(report.read_text())
    assert [c["args"] for c in rep["received"] if c["kind"] == "estop"] == [["operator"]]


def test_vbnav_run_record_is_read_back_with_every_channel_at_its_rate(tmp_path):
    from vbnav.control.cli import main
    from vbnav.control.comms.recording import iter_recording, read_recording
    cfg = tmp_path / "robot.yaml"
    cfg.write_text("telemetry:\n  state_rate_hz: 20\n"    # simulated clock: records, opens no network
                   "controller:\n  kind: scripted\n  script: [[0.3, 0.0, 3.0], [0.3, 0.4, 3.0]]\n")
    path = tmp_path / "run.mcap"
    assert main(["run", "--config", str(cfg), "--no-camera", "--record", str(path)]) == 0
    s = read_recording(path)
    assert s.complete
    assert {"/vbnav/state", "/vbnav/events", "/vbnav/log", "/vbnav/pose/odom"} <= set(s.channels)
    assert abs(s.channels["/vbnav/state"].count - 6.0 * 20) <= 1
    assert s.channels["/vbnav/pose/odom"].count == s.channels["/vbnav/state"].count
    kinds = [json.loads(d)["kind"] for t, _, _, d in iter_recording(path) if t == "/vbnav/events"]
    assert kinds[0] == "run_start" and kinds[-1] == "run_end"


def test_a_run_that_never_starts_keeps_the_earlier_recording(tmp_path):
    """--overwrite promises the new recording takes the old one's place only when complete. A run whose
    telemetry session could not open (a second robot on the port) closed its recorder, which renamed an empty
    recording over the earlier one: the earlier recording is kept now, and no PATH.part is left."""
    from runtime_helpers import RecordingDrive
    from vbnav.control.config import Config
    from vbnav.control.controllers.manual import IdleController
    from vbnav.control.runtime.runtime import Runtime
    from vbnav.control.comms.link import TelemetryLink
    from vbnav.drivers.clock import SimClock
    cfg = Config.model_validate({"telemetry": {"listen": [f"tcp/127.0.0.1:{free_port()}"]}})
    clock = SimClock()
    path = tmp_path / "run.mcap"
    path.write_bytes(b"the earlier run's recording")
    first = TelemetryLink.attach(Runtime(cfg, RecordingDrive(clock), IdleController(), clock), cfg)
    try:
        with pytest.raises(ConnectionError, match="cannot open the zenoh session"):
            TelemetryLink.attach(Runtime(cfg, RecordingDrive(clock), IdleController(), clock), cfg,
                                 record=str(path), record_overwrite=True)
    finally:
        first.close()
    assert path.read_bytes() == b"the earlier run's recording"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]


def test_a_second_robot_on_the_same_port_gets_a_clear_error():
    from runtime_helpers import RecordingDrive
    from vbnav.control.config import Config
    from vbnav.control.controllers.manual import IdleController
    from vbnav.control.runtime.runtime import Runtime
    from vbnav.control.comms.link import TelemetryLink
    from vbnav.drivers.clock import SimClock
    cfg = Config.model_validate({"telemetry": {"listen": [f"tcp/127.0.0.1:{free_port()}"]}})
    clock = SimClock()
    first = TelemetryLink.attach(Runtime(cfg, RecordingDrive(clock), IdleController(), clock), cfg)
    try:
        with pytest.raises(ConnectionError, match="cannot open the zenoh session listening on tcp/127.0.0.1"):
            TelemetryLink.attach(Runtime(cfg, RecordingDrive(clock), IdleController(), clock), cfg)
    finally:
        first.close()


def test_vbnav_run_in_real_time_publishes_and_obeys_an_estop(tmp_path):
    port = free_port()
    cfg = tmp_path / "rt.yaml"
    cfg.write_text(f"sim:\n  realtime: true\ntelemetry:\n  listen: ['tcp/127.0.0.1:{port}']\n"
                   "controller:\n  kind: scripted\n  script: [[0.2, 0.0, 60.0]]\n")
    cli = [sys.executable, "-m", "vbnav.control.cli"]
    robot = subprocess.Popen(cli + ["run", "--no-camera", "-c", str(cfg), "--duration", "30", "--json"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ep = ["--connect", f"tcp/127.0.0.1:{port}"]
    try:
        for _ in range(50):          # wait for the robot's listener
            mon = subprocess.run(cli + ["monitor", "--once", "--json", *ep], capture_output=True, text=True,
                                 timeout=30)
            if mon.returncode == 0:
                break
            time.sleep(0.2)
        state = json.loads(mon.stdout)
        assert state["mode"] == "scripted" and state["wheels"]["cmd"]["left"] > 0
        sent = subprocess.run(cli + ["send", "estop", *ep], capture_output=True, text=True, timeout=30)
        assert sent.returncode == 0, sent.stderr
        time.sleep(0.3)
        state = json.loads(subprocess.run(cli + ["monitor", "--once", "--json", *ep], capture_output=True,
                                          text=True, timeout=30).stdout)
        assert state["safety"]["state"] == "estop" and state["wheels"]["cmd"] == {"left": 0.0, "right": 0.0}
    finally:
        robot.terminate()
        out, err = robot.communicate(timeout=30)
    summary = json.loads(out)
    assert any(e["cause"] == "estop" and e["kind"] == "trip" for e in summary["events"]), summary["events"]


def test_a_robot_whose_zenoh_session_dies_stops_and_ends_the_run(tmp_path):
    """The robot's zenoh session dying mid-run (closed under it: every put raises 'session closed') was only
    counted in the publisher's sink errors: a repeat or a goto drove on with no network command (an estop)
    able to reach it, and nothing said so. The run now ends with the wheels stopped, cause 'network', naming
    the error (not a success: a service restarts it, with a new session)."""
    from runtime_helpers import RecordingDrive
    from test_safety import Cruise
    from vbnav.control.comms.link import TelemetryLink
    from vbnav.control.config import Config
    from vbnav.control.runtime.runtime import Runtime
    from vbnav.drivers.clock import MonotonicClock

    port = free_port()
    cfg = Config.model_validate({"telemetry": {"listen": [f"tcp/127.0.0.1:{port}"]},
                                 "loop": {"stall_periods": 10 ** 6, "max_missed_streak": 10 ** 6}})
    clock = MonotonicClock()
    drive = RecordingDrive(clock)
    rt = Runtime(cfg, drive, Cruise(), clock)
    link = TelemetryLink.attach(rt, cfg, network=True)
    died = []

    def kill_the_session(r, ctx, twist, wheels):
        if not died and ctx.now_ns - r._start_ns >= 300_000_000:
            died.append(ctx.now_ns)
            link.session.close()

    rt.cycle_observers.append(kill_the_session)
    result = rt.run(duration_s=10.0)
    link.close(result)
    assert died and result.reason == "network", (result.reason, result.message)
    assert "session closed" in result.message and "estop" in result.message, result.message
    assert not result.ok
    assert drive.last_motion_ns() > rt._start_ns and drive.stopped_since(drive.last_motion_ns() + 1)
    assert not drive.physics.powered
