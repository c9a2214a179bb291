"""A fleet of three simulated robots through one zenoh router (a router-mode session, as zenohd would be):
`vbnav monitor --all` sees all three; a route on one robot is pulled (checksummed, swapped in), pushed to
another, and loads there keyframe for keyframe; a damaged push is refused and leaves the old route."""
import json
import subprocess
import sys
import time

import numpy as np
import pytest

from test_route import write_route
from test_telemetry_net import free_port

VBNAV = [sys.executable, "-m", "vbnav.control.cli"]
ROBOTS = ("r1", "r2", "r3")


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    import zenoh
    d = tmp_path_factory.mktemp("fleet")
    rport = free_port()
    router = zenoh.open(zenoh.Config.from_json5(json.dumps({
        "mode": "router", "listen": {"endpoints": [f"tcp/127.0.0.1:{rport}"]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}})))
    rng = np.random.default_rng(5)
    original = write_route(d / "routes_r1" / "tour", rng, n=6)
    procs = []
    for name in ROBOTS:
        cfg = d / f"{name}.yaml"
        cfg.write_text(f"""robot: {{name: {name}}}
loop: {{max_missed_streak: 1000000, stall_periods: 1000000}}
controller: {{routes_dir: routes_{name}}}
telemetry:
  listen: ['tcp/127.0.0.1:{free_port()}']
  connect: ['tcp/127.0.0.1:{rport}']
  trust_router: true
""")
        procs.append(subprocess.Popen(VBNAV + ["run", "--realtime", "--no-camera", "--controller", "idle", "-c",
                                               str(cfg), "--duration", "300"],
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    yield d, ["--connect", f"tcp/127.0.0.1:{rport}"], original
    for p in procs:
        p.terminate()
    for p in procs:
        p.communicate(timeout=60)
    router.close()


def _vbnav(capsys, *argv):
    """The command line in this process (the robots are processes; the clients need not be)."""
    from vbnav.control.cli import main
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_monitor_all_shows_every_robot_one_line_each(fleet, capsys):
    _, ep, _ = fleet
    seen = {}
    for _ in range(30):             # robots connect to the router at their own pace
        code, out, _ = _vbnav(capsys, "monitor", "--all", "--once", "--json", "--timeout", "1", *ep)
        seen = json.loads(out) if code == 0 else {}
        if set(seen) == set(ROBOTS):
            break
    assert set(seen) == set(ROBOTS), seen
    assert all(s["mode"] == "idle" for s in seen.values())
    code, out, _ = _vbnav(capsys, "monitor", "--all", "--once", "--timeout", "1", *ep)
    text = out.splitlines()
    assert text[0].endswith("3 robot(s)") and [ln.split()[0] for ln in text[1:]] == list(ROBOTS)


def test_a_route_is_pulled_from_one_robot_and_pushed_to_another(fleet, capsys):
    from vbnav.control.comms.route_transfer import pack_route
    from vbnav.control.route import load_route
    d, ep, original = fleet
    local = d / "laptop"
    for _ in range(30):
        code, out, err = _vbnav(capsys, "route", "pull", "r1", "tour", "--dir", str(local), *ep)
        if code != 3:
            break
        time.sleep(1)
    assert code == 0, err
    import hashlib
    sha = hashlib.sha256(pack_route(d / "routes_r1" / "tour")).hexdigest()
    assert f"sha256 {sha}" in out
    code, out, err = _vbnav(capsys, "route", "push", "r3", "tour", "--dir", str(local), *ep)
    assert code == 0, err
    copied = load_route(d / "routes_r3" / "tour")
    assert copied.complete and len(copied) == len(original)
    for a, b in zip(original, copied.keyframes):
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.track_ids, b.track_ids)
    code, out, _ = _vbnav(capsys, "route", "remote", "r3", *ep)
    assert code == 0 and "tour  6 keyframes  complete" in out
    code, _, err = _vbnav(capsys, "route", "pull", "r2", "tour", "--dir", str(local / "x"), *ep)
    assert code == 1 and "no such route" in err


def test_a_push_whose_checksum_does_not_match_is_refused_and_the_old_route_stays(fleet):
    import base64
    import zenoh
    from vbnav.control.comms.network import client_session_config
    from vbnav.control.comms.route_transfer import pack_route
    from vbnav.control.route import load_route
    d, ep, original = fleet
    data = pack_route(d / "routes_r1" / "tour")
    body = {"transfer": "abc123", "chunk": 0, "chunks": 1, "sha256": "0" * 64, "size": len(data),
            "sender": "test", "data": base64.b64encode(data[:30000]).decode()}
    body["size"] = 30000
    s = zenoh.open(zenoh.Config.from_json5(json.dumps(client_session_config([ep[1]]))))
    try:
        answers = [json.loads(r.ok.payload.to_bytes()) for r in
                   s.get("vbnav/r1/cmd/route/tour", payload=json.dumps(body).encode(), timeout=10) if r.ok]
    finally:
        s.close()
    assert answers and not answers[0]["ok"]
    assert "checksum mismatch" in answers[0]["reason"] or "not a usable route" in answers[0]["reason"]
    assert len(load_route(d / "routes_r1" / "tour")) == len(original)
    assert not [p for p in (d / "routes_r1").iterdir() if p.name.startswith(".")]    # nothing left beside


def test_pushing_a_route_is_a_command_only_operators_may_give(tmp_path):
    """An authenticated robot: a viewer may list (read) but its push never reaches the robot (zenoh's access
    control drops the query); an operator's push is taken."""
    from test_telemetry_net import finish, start_robot
    from vbnav.control.comms.network import client_session_config, open_session
    from vbnav.control.comms.route_transfer import fetch_route_list, push_route
    from vbnav.control.route import load_route
    users = tmp_path / "users.txt"
    users.write_text("robot:robot-secret\noperator:operator-pw\nviewer:viewer-pw1\n")
    routes, src = tmp_path / "routes", tmp_path / "src" / "tour"
    write_route(src, np.random.default_rng(1), n=3)
    port = free_port()
    proc = start_robot("--port", port, "--controller", "idle", "--duration", 60, "--remote", users,
                       "--operators", "operator", "--routes-dir", routes)
    ep = [f"tcp/127.0.0.1:{port}"]
    try:
        viewer = open_session(client_session_config(ep, "viewer", "viewer-pw1"))
        try:
            assert fetch_route_list(viewer, "sim") == []
            with pytest.raises(ConnectionError, match="no answer"):
                push_route(viewer, "sim", "tour", src, timeout_s=2.0)
        finally:
            viewer.close()
        assert not (routes / "tour").exists()
        operator = open_session(client_session_config(ep, "operator", "operator-pw"))
        try:
            push_route(operator, "sim", "tour", src)
            assert [r["name"] for r in fetch_route_list(operator, "sim")] == ["tour"]
        finally:
            operator.close()
    finally:
        finish(proc, stop=True)
    assert len(load_route(routes / "tour")) == 3
