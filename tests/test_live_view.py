"""The live view in Foxglove: a client speaking the Foxglove WebSocket protocol sees the advertised channels
and decodes image, pose and state from a real-time simulated run; teleop from a client drives the robot
through the same command path and operator rules as `vbnav send`."""
import json
import os
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest

from foxglove_client import SUBPROTOCOLS, FoxgloveClient, double, protobuf_fields
from test_telemetry_net import free_port

VBNAV = [sys.executable, "-m", "vbnav.control.cli"]


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    d = tmp_path_factory.mktemp("live")
    token = d / "token"
    token.write_text("operator-token-0123456789\n")
    os.chmod(token, 0o600)
    cfg = d / "sim.yaml"
    # A loaded test machine must not trip the deadline, stall or stale-camera stops: not what is tested here.
    cfg.write_text(f"""camera: {{width: 160, height: 120, fx: 100.0, fy: 100.0, cx: 79.5, cy: 59.5, rate_hz: 10,
         stale_after_s: 5.0}}
loop: {{max_missed_streak: 1000000, stall_periods: 1000000}}
sim: {{world: room, start_pose: [-3.5, 0.0, 0.0]}}
telemetry:
  listen: ['tcp/127.0.0.1:{free_port()}']
  image_rate_hz: 2
  live_view: {{enabled: true, port: 0, operator_token_file: '{token}'}}
""")
    proc = subprocess.Popen(VBNAV + ["run", "--realtime", "--controller", "teleop", "-c", str(cfg), "--duration",
                                     "120", "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    port = None
    for line in proc.stderr:                 # "vbnav: live view on ws://127.0.0.1:PORT ..."
        if "live view on ws://" in line:
            port = int(line.split("ws://127.0.0.1:")[1].split()[0])
            break
    assert port, "the robot did not announce its live view"
    yield port, token.read_text().strip()
    proc.terminate()
    proc.communicate(timeout=60)


def _collect(client, subs, want, deadline_s=30.0):
    got: dict[str, bytes] = {}
    end = time.monotonic() + deadline_s
    while time.monotonic() < end and not want <= set(got):
        m = client.poll(1.0)
        if m is not None:
            got.setdefault(subs[m[0]], m[2])
    return got


def test_a_foxglove_client_lists_channels_and_decodes_image_pose_and_state(robot):
    port, _ = robot
    c = FoxgloveClient("127.0.0.1", port)
    try:
        assert c.protocol in SUBPROTOCOLS
        chans = c.wait_for_channels(["/vbnav/image", "/vbnav/pose/odom", "/vbnav/state", "/vbnav/log",
                                     "/vbnav/odometry", "/vbnav/image/annotations", "/vbnav/route"])
        assert "clientPublish" in c.server_info["capabilities"]
        assert chans["/vbnav/image"]["schemaName"] == "foxglove.CompressedImage"
        assert chans["/vbnav/image"]["encoding"] == "protobuf"
        assert chans["/vbnav/state"]["encoding"] == "json"
        want = {"/vbnav/image", "/vbnav/pose/odom", "/vbnav/state"}
        subs = {i: t for i, t in enumerate(sorted(want), start=1)}
        c.subscribe({i: chans[t]["id"] for i, t in subs.items()})
        got = _collect(c, subs, want)
        assert want <= set(got), sorted(got)
        img = protobuf_fields(got["/vbnav/image"])
        assert img[3] == [b"jpeg"] and img[4] == [b"camera"]
        frame = cv2.imdecode(np.frombuffer(img[2][0], np.uint8), cv2.IMREAD_UNCHANGED)
        assert frame.shape[:2] == (120, 160)
        pose = protobuf_fields(got["/vbnav/pose/odom"])
        assert pose[2] == [b"odom"]
        orientation = protobuf_fields(protobuf_fields(pose[3][0])[2][0])
        w = double(orientation[4][0]) if 4 in orientation else 0.0
        assert abs(w) == pytest.approx(1.0, abs=1e-3)         # standing still, heading 0
        state = json.loads(got["/vbnav/state"])
        assert state["schema"] == "vbnav.state" and state["mode"] == "teleop"
    finally:
        c.close()


def _odom_z(client, sub_id, events=None, seconds=1.0) -> float:
    """The odometry z of the newest state: reads what arrives for ``seconds`` (older states wait in the socket)."""
    z = None
    end = time.monotonic() + seconds
    while time.monotonic() < end or z is None:
        m = client.poll(10.0)
        assert m is not None, "no state"
        if m[0] == sub_id:
            z = json.loads(m[2])["pose"]["odom"]["z"]
        elif events is not None:
            events.append(json.loads(m[2]))
    return z


TWIST = json.dumps({"linear": {"x": 0.3, "y": 0, "z": 0}, "angular": {"x": 0, "y": 0, "z": 0}}).encode()


def _drive(client, channel, seconds, events):
    """Publish TWIST at 10 Hz (the layout's Teleop panel rate) for ``seconds``; events (subscription 2) that
    arrive meanwhile are added to ``events``."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        client.publish(channel, TWIST)
        stop = time.monotonic() + 0.1
        while time.monotonic() < stop:
            m = client.poll(0.1)
            if m is not None and m[0] == 2:
                events.append(json.loads(m[2]))


def _wait_for_event(client, events, match, deadline_s=10.0):
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        found = [e for e in events if match(e)]
        if found:
            return found[0]
        m = client.poll(0.5)
        if m is not None and m[0] == 2:
            events.append(json.loads(m[2]))
    return None


def _drive_until_moved(client, channel, sub_id, z0, metres, deadline_s=30.0) -> float:
    """Publish TWIST at 10 Hz until the state shows ``metres`` of travel (or the deadline): the distance."""
    end = time.monotonic() + deadline_s
    z = z0
    while time.monotonic() < end and z - z0 <= metres:
        client.publish(channel, TWIST)
        stop = time.monotonic() + 0.1
        while time.monotonic() < stop:
            m = client.poll(0.1)
            if m is not None and m[0] == sub_id:
                z = json.loads(m[2])["pose"]["odom"]["z"]
    return z - z0


def test_teleop_from_a_client_moves_the_robot_only_once_it_is_an_operator(robot):
    port, token = robot
    c = FoxgloveClient("127.0.0.1", port, timeout_s=0.5)
    try:
        chans = c.wait_for_channels(["/vbnav/state", "/vbnav/events"])
        c.subscribe({1: chans["/vbnav/state"]["id"], 2: chans["/vbnav/events"]["id"]})
        c.advertise(7, "/vbnav/teleop")
        z0 = _odom_z(c, 1)
        events = []
        _drive(c, 7, 1.5, events)                     # not an operator yet: refused
        refused = _wait_for_event(c, events, lambda e: e["kind"] == "command_rejected"
                                  and "not an operator" in e["reason"])
        assert refused, "no command_rejected event for a client that is not an operator"
        assert abs(_odom_z(c, 1) - z0) < 0.02
        c.set_parameter("vbnav.operator_token", "wrong-token-0123456789")
        _drive(c, 7, 1.0, events)
        assert abs(_odom_z(c, 1) - z0) < 0.02
        c.set_parameter("vbnav.operator_token", token)
        # An operator now: 0.3 m/s teleop drives it 0.2 m in under a second of streaming (30 s allowed on a
        # loaded machine); the refusals above left it where it was.
        assert _drive_until_moved(c, 7, 1, z0, 0.2) > 0.2
        events.clear()
        c.publish(7, json.dumps({"linear": {"x": 9.0, "y": 0, "z": 0}, "angular": {"x": 0, "y": 0, "z": 0}}).encode())
        # beyond robot.max_linear_speed: refused like vbnav send teleop 9 0
        over = _wait_for_event(c, events, lambda e: e["kind"] == "command_rejected" and "outside" in e["reason"])
        assert over and "robot.max_linear_speed" in over["reason"]
    finally:
        c.close()


def test_the_shipped_layout_shows_only_channels_the_robot_publishes():
    from pathlib import Path

    from vbnav.control.comms.foxglove_channels import TOPICS
    from vbnav.control.comms.live_view import TELEOP_TOPIC
    layout = json.loads((Path(__file__).parents[1] / "docs" / "foxglove-layout.json").read_text())
    text = json.dumps(layout["configById"])
    used = {t for t in TOPICS if f'"{t}' in text}
    assert {"/vbnav/image", "/vbnav/image/annotations", "/vbnav/pose/odom", "/vbnav/route", "/vbnav/landmarks",
            "/vbnav/log", "/vbnav/state"} <= used
    assert layout["configById"]["Teleop!vbnav"]["topic"] == TELEOP_TOPIC
    assert layout["configById"]["Teleop!vbnav"]["publishRate"] >= 10    # faster than command_timeout_s stops it


def test_a_live_view_beyond_loopback_needs_remote_access_tls_and_an_operator_token():
    from vbnav.control.config import Config
    with pytest.raises(Exception, match="live_view.host '0.0.0.0' makes the live view reachable"):
        Config.model_validate({"telemetry": {"live_view": {"enabled": True, "host": "0.0.0.0"}}})
    Config.model_validate({"telemetry": {"live_view": {"enabled": True, "host": "127.0.0.1"}}})


def test_who_may_teleoperate_through_the_live_view(tmp_path):
    from vbnav.control.comms.live_view import operator_rule
    from vbnav.control.config import Config
    loopback = Config.model_validate({}).telemetry
    assert operator_rule(loopback) == (None, True, "")                 # as any local user may `vbnav send`
    secret = tmp_path / "secret"
    secret.write_text("s" * 32)
    os.chmod(secret, 0o600)
    signed = Config.model_validate({"telemetry": {"shared_secret_file": str(secret)}}).telemetry
    token, everyone, why = operator_rule(signed)
    assert token is None and not everyone and "operator_token_file" in why
    with_token = Config.model_validate({"telemetry": {"live_view": {"operator_token_file": str(secret)}}}).telemetry
    assert operator_rule(with_token) == (b"s" * 32, False, "")


def test_route_landmarks_and_overlays_encode_to_what_they_say():
    from vbnav.control.comms import foxglove_channels as fc
    from vbnav.control.stages.obstacles import stop_zone_outline
    from vbnav.vision.geometry import CameraMount, Pose2
    route = protobuf_fields(fc.encode(fc.route_message(5, "tour", [Pose2(0, 0, 0), Pose2(0.5, 1, 0), (1.0, 2.0, 0)])))
    entity = protobuf_fields(route[2][0])                      # SceneUpdate.entities
    assert entity[2] == [b"odom"] and entity[3] == [b"route/tour"]
    spheres, lines = entity.get(9, []), entity.get(11, [])     # SceneEntity.spheres, .lines
    assert len(spheres) == 3 and len(lines) == 1 and len(protobuf_fields(lines[0])[5]) == 3
    cloud = protobuf_fields(fc.encode(fc.landmarks_message(5, np.array([[1.0, 2.0, 3.0], [0.0, 0.0, 4.0]]))))
    data = cloud[6][0]
    assert len(data) == 2 * 12 and np.frombuffer(data[:12], "<f4").tolist() == [3.0, -1.0, -2.0]   # (z, -x, -y)
    ov = fc.Overlay(tracked=np.array([[10.0, 20.0], [30.0, 40.0]]), zone=np.array([[0, 0], [5, 0], [5, 5]]))
    ann = protobuf_fields(fc.encode(fc.annotations_message(5, ov.scaled(0.5))))
    kinds = [protobuf_fields(p) for p in ann[2]]                # ImageAnnotations.points
    assert [len(k[3]) for k in kinds] == [2, 3]                 # the tracked points, the zone outline
    first = protobuf_fields(kinds[0][3][0])
    assert (double(first[1][0]), double(first[2][0])) == (5.0, 10.0)    # scaled to the published image

    class Cam:
        fx = fy = 400.0
        cx, cy = 319.5, 239.5
    zone = stop_zone_outline(Cam(), CameraMount(height=0.25, forward=0.1), 0.25, 2.0)
    # The floor in front of a level camera 0.25 m up is below the horizon (v > cy), left and right of centre.
    assert len(zone) == 16 and (zone[:, 1] > Cam.cy).all()
    assert zone[:, 0].min() < Cam.cx < zone[:, 0].max()


def test_foxglove_teleop_takes_numbers_only():
    """The Foxglove path coerced with float(): a Twist whose linear.x was true drove at 1 m/s and "0.3" at
    0.3 m/s, where the zenoh path refuses both (a sender's bug must not drive the robot). Refused too."""
    import threading
    from types import SimpleNamespace
    from vbnav.control.comms.live_view import LiveView
    submitted, refused = [], []
    view = SimpleNamespace(_lock=threading.Lock(), _teleop_channels={(1, 7)}, is_operator=lambda cid: True,
                           _refuse=lambda k, why, p: refused.append(why), _submit=lambda k, p: submitted.append(p),
                           _seq=0, _session="s", _driving=set())
    view._submit_twist = lambda *a: LiveView._submit_twist(view, *a)
    client = SimpleNamespace(id=1)
    for x in (True, "0.3", None):
        LiveView.on_message_data(view, client, 7, json.dumps({"linear": {"x": x}, "angular": {"z": 0}}).encode())
    assert not submitted and len(refused) == 3, (submitted, refused)
    LiveView.on_message_data(view, client, 7, json.dumps({"linear": {"x": 0.3}, "angular": {"z": 1}}).encode())
    assert len(submitted) == 1 and json.loads(submitted[0])["angular"] == -1.0
    # a key given twice (the zenoh path refuses it): JSON readers kept the last, 0.5 m/s or 0 unsaid
    LiveView.on_message_data(view, client, 7, b'{"linear": {"x": 0.5, "x": 0.0}, "angular": {"z": 0}}')
    assert len(submitted) == 1 and "duplicate key 'x'" in refused[-1], (submitted, refused)
    # an integer beyond a float (JSON has no bound): float() raised OverflowError into the Foxglove server's
    # callback, the twist neither refused nor said; refused now, as a number out of range
    LiveView.on_message_data(view, client, 7, b'{"linear": {"x": 1' + b"0" * 400 + b'}, "angular": {"z": 0}}')
    assert len(submitted) == 1 and "too large" in refused[-1], (submitted, refused)


@pytest.mark.parametrize("data, says", [(b"[" * 4000, "nested too deep"),
                                         (b'{"linear": {"x": 0.3}, "angular": {"z": 0}, "pad": "' + b"x" * 5000 + b'"}',
                                          "exceeds 4096")])
def test_a_foxglove_teleop_nested_too_deep_or_too_large_is_refused_and_said(data, says):
    """Found by an audit: a Twist nested 4,000 deep raised RecursionError out of the Foxglove server's callback:
    the message was neither applied nor refused, unsaid; and a Twist of any size was parsed on the server's
    thread where the zenoh path refuses one beyond MAX_PAYLOAD unread. Both are refused with a command_rejected."""
    import threading
    from types import SimpleNamespace
    from vbnav.control.comms.live_view import LiveView
    submitted, refused = [], []
    view = SimpleNamespace(_lock=threading.Lock(), _teleop_channels={(1, 7)}, is_operator=lambda cid: True,
                           _refuse=lambda k, why, p: refused.append(why), _submit=lambda k, p: submitted.append(p),
                           _seq=0, _session="s", _driving=set())
    view._submit_twist = lambda *a: LiveView._submit_twist(view, *a)
    LiveView.on_message_data(view, SimpleNamespace(id=1), 7, data)
    assert not submitted and len(refused) == 1 and says in refused[0], (submitted, refused)


@pytest.mark.parametrize("how", ["close", "drop"])
def test_a_foxglove_client_that_goes_while_driving_stops_the_robot_at_once(how):
    """A Foxglove teleop client that disconnected while driving sent no stop: the robot drove on its last twist
    until safety.command_timeout_s. The SDK unadvertises a departing client's channels (after a close frame,
    or a connection just dropped), and the live view then sends a zero twist in its name, as vbnav teleop does
    when it ends; a client that stopped driving first gets no second stop."""
    from vbnav.control.comms.live_view import LiveView
    from vbnav.control.config import Config
    submitted = []
    view = LiveView(Config.model_validate({"telemetry": {"live_view": {"port": 0}}}).telemetry, "r1",
                    submit_teleop=lambda k, p: submitted.append(json.loads(p)), refuse=lambda *a: None,
                    to_wall_ns=lambda t: t)
    try:
        clients = [FoxgloveClient("127.0.0.1", view.port, timeout_s=0.5) for _ in range(2)]
        for c, twist in zip(clients, (TWIST, json.dumps({"linear": {"x": 0}, "angular": {"z": 0}}).encode())):
            c.poll(0.2)
            c.advertise(7, "/vbnav/teleop")
            _wait(lambda: len(view._teleop_channels) == clients.index(c) + 1)
            c.publish(7, twist)
            _wait(lambda: len(submitted) == clients.index(c) + 1)
        driver, idle = (m["sender"] for m in submitted)
        for c in clients:
            if how == "close":
                c.close()
            else:
                c.sock.close()          # no close frame: the connection just drops
        _wait(lambda: not view._teleop_channels)
        _wait(lambda: len(submitted) >= 3)
    finally:
        view.close()
    assert [(m["sender"], m["linear"], m["angular"]) for m in submitted] == \
        [(driver, 0.3, -0.0), (idle, 0.0, -0.0), (driver, 0.0, 0.0)], submitted
    assert submitted[2]["seq"] > submitted[0]["seq"] and submitted[2]["session"] == submitted[0]["session"]


def _wait(cond, deadline_s=10.0):
    end = time.monotonic() + deadline_s
    while not cond():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.01)


def test_a_safety_warning_is_a_warning_in_the_foxglove_log():
    """A safety_warning (a motor that did not take a stop, a drive lost again) was logged at Info level in
    Foxglove's log panel, beside routine lines; it is a Warning, as a hold and a refused command are."""
    from vbnav.control.comms.foxglove_channels import LogLevel, log_message

    def level(m) -> str:                     # the Log message shows its fields only in its repr
        return repr(log_message(1, m)).split("level=")[1].split(",")[0]
    msg = {"kind": "safety_warning", "robot": "r1", "cause": "stop_unconfirmed",
           "message": "dynamixel drive did not take the stop: servo 2 (right)"}
    assert level(msg) == str(int(LogLevel.Warning))
    assert level({**msg, "kind": "safety_stop_confirmed"}) == str(int(LogLevel.Info))
