"""A simulated fleet through one zenoh router: three robot processes, monitor --all, route pull/push.

The router is a router-mode zenoh session in this process with the configuration docs/fleet.md gives
zenohd (user/password authentication and network.router_access_control). The robots are the real Runtime
on the wall clock (tests/telemetry_robot.py) connecting to it with telemetry.trust_router, each serving its
own routes folder. A route is taught on the simulated robot into robot r1's folder, pulled from r1,
checked, pushed to r2 by an operator and repeated from r2's folder on the simulated clock.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from test_telemetry_net import finish, free_port, start_robot
from vbnav.control.comms import route_transfer as rt
from vbnav.control.comms.network import client_session_config, open_session, router_session_config
from vbnav.control.route import load_route, stray_route_dirs

ROBOTS = ("r1", "r2", "r3")
USERS = {"router": "router-password", "op": "op-password", "viewer": "viewer-password",
         **{r: f"{r}-password" for r in ROBOTS}}


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fleet")
    users = tmp / "users.txt"
    users.write_text("".join(f"{u}:{p}\n" for u, p in USERS.items()))
    users.chmod(0o600)
    # The route is taught first (simulated robot, simulated clock) into r1's routes folder.
    from vbnav.control.config import load_config
    from vbnav.control.runtime.factory import make_robot
    from vbnav.control.session import Session, teach_driver
    cfg = load_config(None)
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    router = open_session(router_session_config([endpoint], "router", USERS["router"], str(users), list(ROBOTS),
                                                ["op"]))

    def start(r):
        return start_robot("--port", free_port(), "--controller", "idle", "--duration", 60, "--name", r,
                           "--connect", endpoint, "--router-auth", f"{r}:{USERS[r]}:{users}",
                           "--routes-dir", tmp / r, "--rate", 50, timeout_s=60)
    procs, sessions = [], []
    pool = ThreadPoolExecutor(len(ROBOTS))       # the robots start while the route is taught
    starting = [pool.submit(start, r) for r in ROBOTS]
    try:
        taught = Session(cfg, make_robot(cfg, with_camera=True)).teach(teach_driver(cfg), tmp / "r1" / "loop",
                                                                      duration_s=3.0)
        assert taught.keyframes >= 3
        for f in starting:
            procs.append(f.result())
        op = open_session(client_session_config([endpoint], "op", USERS["op"]))
        viewer = open_session(client_session_config([endpoint], "viewer", USERS["viewer"]))
        sessions += [op, viewer]
        yield {"tmp": tmp, "endpoint": endpoint, "op": op, "viewer": viewer}
    finally:
        for s in sessions:
            s.close()
        for f in starting:
            if f.exception() is None and f.result() not in procs:
                procs.append(f.result())
        pool.shutdown()
        for p in procs:
            finish(p, stop=True)
        router.close()


def _cli(*args, user: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    env = dict(os.environ, VBNAV_ZENOH_PASSWORD=USERS[user])
    return subprocess.run([sys.executable, "-m", "vbnav.control.cli", *map(str, args), "--user", user],
                          capture_output=True, text=True, env=env, timeout=timeout)


def test_monitor_all_sees_every_robot_through_the_router(fleet):
    mon = _cli("monitor", "--all", "--once", "--count", 3, "--timeout", 30, "--connect", fleet["endpoint"],
               user="viewer")
    assert mon.returncode == 0, mon.stderr
    lines = mon.stdout.splitlines()
    assert "3 robot(s)" in lines[0]
    rows = [ln for ln in lines[2:] if ln.split() and ln.split()[0] in ROBOTS]
    assert [ln.split()[0] for ln in rows] == list(ROBOTS) and all(" idle " in ln for ln in rows), mon.stdout


def test_a_route_taught_on_one_robot_is_pulled_checked_pushed_and_repeated_on_another(fleet, capsys, monkeypatch):
    from vbnav.control.cli import main
    tmp, endpoint = fleet["tmp"], fleet["endpoint"]
    assert [r["name"] for r in rt.list_remote(fleet["viewer"], "r1", timeout_s=20)] == ["loop"]
    assert rt.list_remote(fleet["viewer"], "r2", timeout_s=20) == []
    # The command line in this process (a client session of its own): reading is for anyone the router admits.
    monkeypatch.setenv("VBNAV_ZENOH_PASSWORD", USERS["viewer"])
    assert main(["route", "pull", "r1", "loop", "--to", str(tmp / "laptop"), "--connect", endpoint, "--timeout", "20",
                 "--user", "viewer"]) == 0, capsys.readouterr().err
    assert main(["route", "check", str(tmp / "laptop" / "loop")]) == 0
    assert "intact" in capsys.readouterr().out
    # Writing to a robot: refused to a viewer (the router drops the query), done for an operator.
    with pytest.raises(rt.NoAnswer, match="refuses writes"):
        rt.push(fleet["viewer"], "r2", tmp / "laptop" / "loop", timeout_s=3)
    assert not (tmp / "r2" / "loop").exists()
    monkeypatch.setenv("VBNAV_ZENOH_PASSWORD", USERS["op"])
    assert main(["route", "push", "r2", str(tmp / "laptop" / "loop"), "--connect", endpoint, "--timeout", "20",
                 "--user", "op"]) == 0, capsys.readouterr().err
    assert "pushed route loop to robot r2" in capsys.readouterr().out
    assert sorted(p.name for p in (tmp / "r2" / "loop").iterdir()) == \
        sorted(p.name for p in (tmp / "r1" / "loop").iterdir())
    assert not stray_route_dirs(tmp / "r2" / "loop")
    with pytest.raises(rt.TransferError, match="exists on this robot"):
        rt.push(fleet["op"], "r2", tmp / "laptop" / "loop", timeout_s=20)
    # Repeated from r2's folder on the simulated robot.
    from vbnav.control.config import load_config
    from vbnav.control.runtime.factory import make_robot
    from vbnav.control.session import Session
    cfg = load_config(None)
    route = load_route(tmp / "r2" / "loop")
    result = Session(cfg, make_robot(cfg, with_camera=True, run=1)).repeat(route, duration_s=15.0)
    assert result.keyframe_reached >= len(route) - 2, result


def test_a_damaged_push_is_refused_and_leaves_the_robot_untouched(fleet):
    op, tmp = fleet["op"], fleet["tmp"]
    src = tmp / "r1" / "loop"
    files = rt.route_files(src)
    base = "vbnav/r3/routes/push/broken/0123456789abcdef"

    def ask(key, payload):
        return json.loads(rt._ask(op, key, 20.0, payload=payload))
    assert ask(f"{base}/begin", json.dumps({"bytes": sum(f["size"] for f in files)}).encode())["ok"]
    manifest = (src / "manifest.json").read_bytes()
    ask(f"{base}/chunk/manifest.json/0", manifest[:-1] + b" ")       # one byte changed on the way
    with pytest.raises(rt.TransferError, match="arrived damaged"):
        ask(f"{base}/file/manifest.json", json.dumps({"size": files[0]["size"], "sha256": files[0]["sha256"]}).encode())
    with pytest.raises(rt.TransferError, match="no transfer"):      # the push is dropped with its files
        ask(f"{base}/commit", b"{}")
    assert not (tmp / "r3" / "broken").exists() and not stray_route_dirs(tmp / "r3" / "broken")


def test_commands_through_the_router_obey_the_operator_rule(fleet):
    import zenoh
    events = []
    sub = fleet["viewer"].declare_subscriber("vbnav/r3/events", lambda s: events.append(json.loads(s.payload.to_bytes())))
    time.sleep(0.5)
    opts = dict(congestion_control=zenoh.CongestionControl.BLOCK)
    fleet["viewer"].put("vbnav/r3/cmd/estop", json.dumps({"reason": "viewer", "ack": "fromviewer"}), **opts)
    fleet["op"].put("vbnav/r3/cmd/estop", json.dumps({"reason": "operator", "ack": "fromop"}), **opts)
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and not any(e.get("ack") == "fromop" for e in events):
        time.sleep(0.1)
    sub.undeclare()
    acks = {e.get("ack") for e in events if e.get("kind") in ("command", "command_rejected")}
    assert "fromop" in acks and "fromviewer" not in acks


def test_the_router_configuration_in_docs_fleet_is_the_one_tested():
    import zenoh

    from vbnav.control.comms.network import router_access_control
    from pathlib import Path
    text = (Path(__file__).resolve().parents[1] / "docs" / "fleet.md").read_text()
    acl = json.loads(zenoh.Config.from_json5(text.split("```json5\n")[1].split("```")[0]).get_json("access_control"))
    ref = router_access_control(["r1", "r2"], ["alice"])
    assert acl["rules"] == ref["rules"] and acl["policies"] == ref["policies"]
    assert [{k: v for k, v in s.items() if v is not None} for s in acl["subjects"]] == ref["subjects"]


def write_sim_route(path: Path, n: int = 3) -> None:
    """A route of ``n`` keyframes taught with the simulated robot's camera and mount (configs/sim.yaml): one
    that robot's repeat takes (a pushed route its repeat refuses is not installed)."""
    import dataclasses

    import numpy as np
    from test_route import make_kf
    from vbnav.control.config import load_config
    from vbnav.control.route import RouteWriter
    cfg = load_config("sim")
    rng = np.random.default_rng(0)
    with RouteWriter(path, "sim", cfg.camera.to_model(), cfg.camera.mount.to_mount()) as w:
        for i in range(n):
            kf = make_kf(rng, i)
            image = np.zeros((cfg.camera.height, cfg.camera.width), np.uint8)
            image[:kf.image.shape[0], :kf.image.shape[1]] = kf.image
            w.append(dataclasses.replace(kf, image=image))


def test_a_robot_with_a_shared_secret_takes_only_signed_pushes(tmp_path):
    from vbnav.control.comms.command_auth import read_secret
    secret_path = tmp_path / "secret"
    secret_path.write_text("0123456789abcdef0123456789abcdef\n")
    secret_path.chmod(0o600)
    write_sim_route(tmp_path / "local" / "loop")
    port = free_port()
    proc = start_robot("--port", port, "--controller", "idle", "--duration", 60, "--name", "solo",
                       "--secret-file", secret_path, "--routes-dir", tmp_path / "robot", timeout_s=60)
    session = open_session(client_session_config([f"tcp/127.0.0.1:{port}"]))
    try:
        with pytest.raises(rt.TransferError, match="push refused: unsigned"):
            rt.push(session, "solo", tmp_path / "local" / "loop", timeout_s=20)
        assert not (tmp_path / "robot" / "loop").exists()
        answer = rt.push(session, "solo", tmp_path / "local" / "loop", secret=read_secret(str(secret_path)),
                         timeout_s=20)
        assert answer["keyframes"] == 3 and load_route(tmp_path / "robot" / "loop").complete
        pulled = rt.pull(session, "solo", "loop", tmp_path / "back")        # reading needs no signature
        assert load_route(pulled).complete
    finally:
        session.close()
        finish(proc, stop=True)


class _Query:
    """What the robot's route thread sees of a zenoh query, and what it answered."""

    def __init__(self, key: str, payload: bytes | None = None):
        self.key_expr, self.attachment, self.answer = key, None, None
        self.payload = None if payload is None else type("Payload", (), {"to_bytes": lambda self: payload})()

    def reply(self, key, payload):
        self.answer = ("ok", payload)

    def reply_err(self, payload):
        self.answer = ("err", json.loads(payload)["error"])


class _Session:
    def declare_queryable(self, key, callback):
        return type("Queryable", (), {"undeclare": lambda self: None})()


@pytest.mark.parametrize("key, reason", [
    ("files/nope", "route 'nope': no such route"),
    ("files/..", "plain name"),
    ("chunk/loop/..manifest.json/0", "route file name"),
    ("chunk/loop/manifest.json/x", "byte offset"),
    ("files/bad", "route 'bad': manifest.json: not a route manifest"),
    ("push/loop/short/begin", "transfer id"),
    ("push/loop/abcdefgh\n/begin", "transfer id"),            # '$' matched before a final newline
    ("chunk/loop/manifest.json\n/0", "route file name"),
    ("bogus", "unknown route query"),
])
def test_the_route_server_refuses_bad_queries_without_naming_its_folders(tmp_path, key, reason):
    root = tmp_path / "routes"
    (root / "bad").mkdir(parents=True)
    (root / "bad" / "manifest.json").write_text("{")
    server = rt.RouteServer(_Session(), "r", root)
    try:
        q = _Query(f"vbnav/r/routes/{key}")
        server._handle(q)
    finally:
        server.close()
    assert q.answer[0] == "err" and reason in q.answer[1] and str(tmp_path) not in q.answer[1], q.answer


def test_a_push_never_replaces_the_route_being_taught(tmp_path):
    server = rt.RouteServer(_Session(), "r", tmp_path, busy=lambda name: f"route {name!r} is being taught"
                            if name == "loop" else None)
    try:
        q = _Query("vbnav/r/routes/push/loop/0123456789abcdef/begin", b'{"bytes": 10, "overwrite": true}')
        server._handle(q)
        other = _Query("vbnav/r/routes/push/other/0123456789abcdef/begin", b'{"bytes": 10}')
        server._handle(other)
    finally:
        server.close()
    assert q.answer == ("err", "route 'loop' is being taught") and other.answer[0] == "ok"


def test_a_pushed_route_is_on_disk_before_it_is_installed(tmp_path, monkeypatch):
    """Chunks are appended to the staging files; the commit renames the staging folder into the routes. A
    power cut after the rename must not find empty files: each file is fsynced once verified."""
    from pathlib import Path

    import numpy as np
    from test_route import write_route
    write_route(tmp_path / "local" / "loop", np.random.default_rng(0), 3)
    synced: list[str] = []
    real_fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(os.readlink(f"/proc/self/fd/{fd}")), real_fsync(fd)))
    server = rt.RouteServer(_Session(), "r", tmp_path / "robot")
    base = "vbnav/r/routes/push/loop/0123456789abcdef"
    files = rt.route_files(tmp_path / "local" / "loop")
    try:
        for key, payload in [(f"{base}/begin", json.dumps({"bytes": sum(f["size"] for f in files)}).encode()),
                             *[q for f in files for q in (
                                 (f"{base}/chunk/{f['name']}/0", (tmp_path / "local" / "loop" / f["name"]).read_bytes()),
                                 (f"{base}/file/{f['name']}",
                                  json.dumps({"size": f["size"], "sha256": f["sha256"]}).encode()))]]:
            q = _Query(key, payload)
            server._handle(q)
            assert q.answer[0] == "ok", (key, q.answer)
        staged = {Path(p).name for p in synced if "/robot/" in p}
        assert staged == {f["name"] for f in files}                 # every file, before the commit
        q = _Query(f"{base}/commit", b"{}")
        server._handle(q)
    finally:
        server.close()
    assert q.answer[0] == "ok" and load_route(tmp_path / "robot" / "loop").complete


def test_a_route_repeat_refuses_is_not_pushed_nor_installed(tmp_path):
    """A whole route of 0 keyframes passed the push's check and the robot's commit, and with overwrite replaced
    the robot's working route by one its repeat refuses. The sender refuses it, and so does the robot."""
    import numpy as np
    from test_route import write_route
    write_route(tmp_path / "local" / "loop", np.random.default_rng(0), 0)
    with pytest.raises(rt.RouteError, match="vbnav repeat refuses it: the route has no keyframes.*not pushing"):
        rt.push(None, "r", tmp_path / "local" / "loop")           # refused before any network use
    write_route(tmp_path / "robot" / "loop", np.random.default_rng(1), 3)
    before = (tmp_path / "robot" / "loop" / "manifest.json").read_bytes()
    server = rt.RouteServer(_Session(), "r", tmp_path / "robot")
    base = "vbnav/r/routes/push/loop/0123456789abcdef"
    files = rt.route_files(tmp_path / "local" / "loop")
    try:
        for key, payload in [(f"{base}/begin", json.dumps({"bytes": sum(f["size"] for f in files),
                                                            "overwrite": True}).encode()),
                             *[q for f in files for q in (
                                 (f"{base}/chunk/{f['name']}/0", (tmp_path / "local" / "loop" / f["name"]).read_bytes()),
                                 (f"{base}/file/{f['name']}",
                                  json.dumps({"size": f["size"], "sha256": f["sha256"]}).encode()))]]:
            q = _Query(key, payload)
            server._handle(q)
            assert q.answer[0] == "ok", (key, q.answer)
        q = _Query(f"{base}/commit", b"{}")
        server._handle(q)
    finally:
        server.close()
    assert q.answer[0] == "err" and "the route has no keyframes" in q.answer[1], q.answer
    assert (tmp_path / "robot" / "loop" / "manifest.json").read_bytes() == before
    assert len(load_route(tmp_path / "robot" / "loop")) == 3 and not stray_route_dirs(tmp_path / "robot" / "loop")


def _push(server, src: Path, name: str = "loop", robot: str = "r") -> tuple:
    """Push the route folder ``src`` to ``server`` (of ``robot``) as ``name``, query by query; the commit's
    answer."""
    base = f"vbnav/{robot}/routes/push/{name}/0123456789abcdef"
    files = rt.route_files(src)
    for key, payload in [(f"{base}/begin", json.dumps({"bytes": sum(f["size"] for f in files)}).encode()),
                         *[q for f in files for q in (
                             (f"{base}/chunk/{f['name']}/0", (src / f["name"]).read_bytes()),
                             (f"{base}/file/{f['name']}", json.dumps({"size": f["size"],
                                                                       "sha256": f["sha256"]}).encode()))]]:
        q = _Query(key, payload)
        server._handle(q)
        assert q.answer[0] == "ok", (key, q.answer)
    q = _Query(f"{base}/commit", b"{}")
    server._handle(q)
    return q.answer


def test_a_pushed_route_this_robots_repeat_refuses_for_its_camera_is_not_installed(tmp_path):
    """The robot's commit checked only what a repeat refuses whatever the configuration (no keyframes): a route
    taught with another camera or mount was installed, and the robot's `mode repeat` refused it afterwards.
    The commit now refuses what this robot's repeat refuses (check_route_config with its configuration)."""
    import math

    import numpy as np
    from test_route import CAM, MOUNT, write_route
    from vbnav.control.comms.link import _route_server
    from vbnav.control.config import load_config
    write_route(tmp_path / "local" / "loop", np.random.default_rng(0), 3)
    runtime = type("Runtime", (), {"controller": type("Controller", (), {"teaching_route": None})()})()
    same = {"width": CAM.width, "height": CAM.height, "fx": CAM.fx, "fy": CAM.fy, "cx": CAM.cx, "cy": CAM.cy,
            "distortion": list(CAM.dist), "mount": {"height": MOUNT.height, "forward": MOUNT.forward,
                                                    "lateral": MOUNT.lateral,
                                                    "pitch_deg": math.degrees(MOUNT.pitch)}}
    for name, camera, routes in (("other", {}, tmp_path / "robot1"), ("same", same, tmp_path / "robot2")):
        cfg = load_config("sim", overrides={"controller": {"routes_dir": str(routes)}, "camera": camera})
        routes.mkdir()
        server = _route_server(_Session(), cfg, None, runtime)
        try:
            answer = _push(server, tmp_path / "local" / "loop", robot=cfg.robot.name)
        finally:
            server.close()
        if name == "other":
            assert answer[0] == "err" and "this robot's repeat refuses it" in answer[1], answer
            assert "another image size" in answer[1] and str(routes) not in answer[1], answer
            assert not (routes / "loop").exists()
        else:
            assert answer[0] == "ok", answer
            assert len(load_route(routes / "loop")) == 3


def test_a_push_signed_with_another_robots_configuration_says_whose(tmp_path, monkeypatch, capsys):
    """route push -c CONFIG ROBOT signed with CONFIG's secret whatever robot.name CONFIG named: a push to r2
    signed with r1's configuration said nothing of r1, on success or refusal. A fleet may share one secret, so
    it is not refused: both the success line and the refusal name the configuration's robot."""
    import yaml

    from vbnav.control.cli import main
    from vbnav.control.commands import route as route_cmd
    secret = tmp_path / "secret"
    secret.write_text("0123456789abcdef0123456789abcdef\n")
    secret.chmod(0o600)
    cfg = tmp_path / "r1.yaml"
    cfg.write_text(yaml.safe_dump({"robot": {"name": "r1"}, "telemetry": {"shared_secret_file": str(secret)}}))
    write_sim_route(tmp_path / "local" / "loop")
    session = type("Session", (), {"close": lambda self: None})()
    monkeypatch.setattr(route_cmd, "open_client", lambda args: session)     # the transfer itself is not under test
    answers = iter([{"keyframes": 3}, rt.TransferError("push refused: bad signature")])

    def push(session, robot, path, secret=None, **kw):
        assert secret is not None        # signed with r1's secret
        answer = next(answers)
        if isinstance(answer, Exception):
            raise answer
        return answer
    monkeypatch.setattr(rt, "push", push)
    whose = f"signed with the secret of robot r1's configuration {cfg} (-c), not r2's"
    assert main(["route", "push", "r2", str(tmp_path / "local" / "loop"), "-c", str(cfg)]) == 0
    assert whose in capsys.readouterr().out
    assert main(["route", "push", "r2", str(tmp_path / "local" / "loop"), "-c", str(cfg)]) == 1
    err = capsys.readouterr().err
    assert "push refused: bad signature" in err and whose in err, err
    # the configuration of the robot pushed to: no note
    cfg.write_text(yaml.safe_dump({"robot": {"name": "r2"}, "telemetry": {"shared_secret_file": str(secret)}}))
    answers = iter([{"keyframes": 3}])
    assert main(["route", "push", "r2", str(tmp_path / "local" / "loop"), "-c", str(cfg)]) == 0
    assert "signed with the secret of" not in capsys.readouterr().out


def test_a_command_signed_with_another_robots_configuration_says_whose(tmp_path, monkeypatch, capsys):
    """vbnav send --robot r2 -c r1.yaml signed with r1's secret and said nothing of it (as route push did)."""
    import yaml

    from vbnav.control.cli import main
    from vbnav.control.commands import send as send_cmd
    secret = tmp_path / "secret"
    secret.write_text("0123456789abcdef0123456789abcdef\n")
    secret.chmod(0o600)
    cfg = tmp_path / "r1.yaml"
    cfg.write_text(yaml.safe_dump({"robot": {"name": "r1"}, "telemetry": {"shared_secret_file": str(secret)}}))

    def unreachable(args):                  # the network is not under test: what is said before it is
        raise ConnectionError("cannot connect (test)")
    monkeypatch.setattr(send_cmd, "open_client", unreachable)
    main(["send", "estop", "--robot", "r2", "-c", str(cfg)])
    assert f"signed with the secret of robot r1's configuration {cfg} (-c), not r2's" in capsys.readouterr().err
    main(["send", "estop", "--robot", "r1", "-c", str(cfg)])
    assert "signed with the secret of robot" not in capsys.readouterr().err
