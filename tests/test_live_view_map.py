"""The line map in Foxglove: ``vbnav map view`` serves a saved map's segments and planning grid to a Foxglove
client; a run with the line-map stage publishes the map as it grows (only when it changed, at the scene rate)
and a recording ends with the map the run saved."""
import json
import struct
import subprocess
import sys
import time

import numpy as np
import pytest

from foxglove_client import FoxgloveClient, double, protobuf_fields
from vbnav.control.comms import foxglove_channels as fc
from vbnav.control.runtime.interfaces import StageOverlay, VisionStage
from vbnav.control.stages.line_map import MapScene

VBNAV = [sys.executable, "-m", "vbnav.control.cli"]

# A small known map (world metres: x right, y down, z forward, floor y = 0): a wall edge standing on the
# floor and a box's top edge (verified), a stereo candidate and an abstraction hypothesis (not verified).
SEGMENTS = [((1.0, 0.0, 2.0), (1.0, -1.0, 2.0), True, False),
            ((-0.5, -0.3, 3.0), (0.5, -0.3, 3.0), True, False),
            ((0.2, -0.1, 1.0), (0.4, -0.6, 1.5), False, False),
            ((-1.0, 0.0, 4.0), (-1.0, -0.5, 4.5), False, True)]


def _write_map(path):
    cov = (np.eye(3) * 1e-4).tolist()
    segs = [{"id": k, "p0": list(a), "p1": list(b), "cov0": cov, "cov1": cov, "support": 3 if v else 1,
             "misses": 0, "verified": v, "group": -1, "hypothesis": h, "views": []}
            for k, (a, b, v, h) in enumerate(SEGMENTS)]
    path.write_text(json.dumps({"format": "vbnav-line-map", "version": 1, "frames": 10, "params": {},
                                "meta": {}, "segments": segs}))


def _fg(p):
    """World point -> Foxglove odom axes (x forward, y left, z up)."""
    return (p[2], -p[0], -p[1])


def _vec(data: bytes, n: int = 3) -> tuple:
    f = protobuf_fields(data)
    return tuple(double(f[k][0]) if k in f else 0.0 for k in range(1, n + 1))


def decode_line_map(data: bytes) -> dict[str, np.ndarray]:
    """foxglove.SceneUpdate -> {kind: (N, 2, 3) endpoints in Foxglove axes}; kinds by LINE_MAP_RGBA."""
    entities = protobuf_fields(data)[2]                          # SceneUpdate.entities
    assert len(entities) == 1
    entity = protobuf_fields(entities[0])
    assert entity[2] == [b"odom"] and entity[3] == [fc.LINE_MAP_ENTITY.encode()]   # frame_id, id
    colours = {rgba: kind for kind, rgba in fc.LINE_MAP_RGBA.items()}
    out = {}
    for line in entity.get(11, []):                              # SceneEntity.lines
        f = protobuf_fields(line)
        assert f[1] == [2]                                       # LinePrimitive.type LINE_LIST
        kind = colours[_vec(f[6][0], 4)]                         # LinePrimitive.color (r, g, b, a)
        out[kind] = np.array([_vec(p) for p in f[5]]).reshape(-1, 2, 3)  # LinePrimitive.points
    return out


def test_map_view_serves_a_saved_map_as_a_scene_and_its_planning_grid(tmp_path):
    path = tmp_path / "room.map.json"
    _write_map(path)
    proc = subprocess.Popen(VBNAV + ["map", "view", str(path), "--port", "0", "--duration", "60"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stderr.readline()
        assert "ws://127.0.0.1:" in line, line + proc.stderr.read()
        assert "2 verified segments, 2 candidates" in line
        port = int(line.split("ws://127.0.0.1:")[1].split()[0])
        c = FoxgloveClient("127.0.0.1", port)
        try:
            chans = c.wait_for_channels(["/vbnav/map/lines", "/vbnav/map/grid"])
            assert chans["/vbnav/map/lines"]["schemaName"] == "foxglove.SceneUpdate"
            assert chans["/vbnav/map/grid"]["schemaName"] == "foxglove.Grid"
            # Published before this client connected: it arrives because the server repeats it on subscribe.
            c.subscribe({1: chans["/vbnav/map/lines"]["id"], 2: chans["/vbnav/map/grid"]["id"]})
            got = {}
            end = time.monotonic() + 10
            while len(got) < 2 and time.monotonic() < end:
                m = c.poll(1.0)
                if m is not None:
                    got[m[0]] = m[2]
        finally:
            c.close()
    finally:
        proc.terminate()
        proc.communicate(timeout=30)
    assert proc.returncode == 0
    assert set(got) == {1, 2}
    lines = decode_line_map(got[1])
    assert {k: len(v) for k, v in lines.items()} == {"verified": 2, "candidate": 1, "hypothesis": 1}
    for kind, sel in (("verified", slice(0, 2)), ("candidate", slice(2, 3)), ("hypothesis", slice(3, 4))):
        want = np.array([[_fg(a), _fg(b)] for a, b, _, _ in SEGMENTS[sel]])
        np.testing.assert_allclose(lines[kind], want, atol=1e-9)
    # The grid: columns along the map's x (Foxglove -y), rows along z (Foxglove x); the standing wall edge
    # at x = 1, z = 2 is a mapped obstacle (100), 0.15 m from it is within the 0.2 m robot radius (50),
    # and 1 m from everything is free (0).
    g = protobuf_fields(got[2])
    assert g[2] == [b"odom"]
    pose = protobuf_fields(g[3][0])
    ox, oy, _ = _vec(pose[1][0])
    qx, qy, qz, qw = _vec(pose[2][0], 4)
    assert (qx, qy) == (0.0, 0.0) and qz == pytest.approx(-np.sqrt(0.5)) and qw == pytest.approx(np.sqrt(0.5))
    cols, res = struct.unpack("<I", g[4][0])[0], _vec(g[5][0], 2)[0]     # column_count is fixed32
    cells = np.frombuffer(g[9][0], np.uint8).reshape(-1, cols)
    x0, z0 = -oy, ox

    def cell(x, z):
        return cells[int(np.floor((z - z0) / res)), int(np.floor((x - x0) / res))]    # as NavGrid.cell
    assert cell(1.0, 2.0) == 100 and cell(1.15, 2.0) == 50 and cell(1.0, 3.0) == 0


def test_map_view_refuses_a_bad_map_file_naming_it(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "something else"}')
    r = subprocess.run(VBNAV + ["map", "view", str(bad), "--port", "0"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and f"{bad}: not a vbnav line map" in r.stderr


class _GrowingMap(VisionStage):
    """A vision stage whose map gains one segment in each of its first ``grow`` frames, then stays put."""

    kind = "growing_map"

    def __init__(self, grow: int):
        self.grow, self.frames = grow, 0
        self.scene = MapScene(0, np.zeros((0, 2, 3)), np.zeros(0, bool), np.zeros(0, bool))

    def process(self, frame, odom):
        self.frames += 1
        if self.frames <= self.grow:
            n = self.frames
            P = np.array([[[k, -0.5, 2.0], [k, 0.0, 2.0]] for k in range(n)], float)
            self.scene = MapScene(n, P, np.arange(n) % 2 == 0, np.zeros(n, bool))
        return None

    def overlay(self, estimate):
        return StageOverlay(line_map=self.scene)


def test_a_run_publishes_the_line_map_only_when_it_changed_at_the_scene_rate(tmp_path):
    from runtime_helpers import make_runtime
    from vbnav.control.comms.link import TelemetryLink
    from vbnav.control.comms.recording import iter_recording
    from vbnav.control.config import Config
    from vbnav.control.controllers.manual import IdleController
    cfg = Config.model_validate({"telemetry": {"enabled": False}})      # scene_rate_hz 1
    stage = _GrowingMap(grow=15)                                         # 1.5 s of frames at 10 Hz
    rt, _, _ = make_runtime(IdleController(), stages=[stage], cfg=cfg, cam_kw={"rate_hz": 10})
    path = tmp_path / "run.mcap"
    link = TelemetryLink.attach(rt, cfg, record=str(path))
    link.close(rt.run(4.5))
    scenes = [(t, decode_line_map(d)) for topic, _, t, d in iter_recording(path) if topic == "/vbnav/map/lines"]
    counts = [sum(len(v) for v in s.values()) for _, s in scenes]
    times = [t for t, _ in scenes]
    # At t = 0, 1 and 2 s (the map changed before each); at 3 and 4 s it had not: nothing more.
    assert len(scenes) == 3 and counts[0] >= 1 and counts[-1] == 15 and counts == sorted(set(counts))
    assert all(b - a >= 0.99e9 for a, b in zip(times, times[1:])) and times[-1] - times[0] < 2.5e9
    last = scenes[-1][1]
    assert len(last["verified"]) == 8 and len(last["candidate"]) == 7 and "hypothesis" not in last
    np.testing.assert_allclose(last["verified"][1], [_fg((2, -0.5, 2.0)), _fg((2, 0.0, 2.0))])


def test_a_map_build_recording_ends_with_the_map_it_saved(tmp_path):
    from vbnav.control.comms.recording import iter_recording
    from vbnav.control.line_map_file import load_map
    out, rec = tmp_path / "m.json", tmp_path / "build.mcap"
    r = subprocess.run(VBNAV + ["map", "build", "-c", "sim_stereo", "--duration", "1.5", "--out", str(out),
                                "--record", str(rec)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    scenes = [(t, decode_line_map(d)) for topic, _, t, d in iter_recording(rec) if topic == "/vbnav/map/lines"]
    times = [t for t, _ in scenes]
    # Frames at 15 Hz for 1.5 s: scenes at about 0 and 1 s (the map changes every frame while the robot
    # drives), and the final map when the run closed.
    assert len(scenes) == 3
    assert all(b - a >= 0.99e9 for a, b in zip(times[:-2], times[1:-1]))
    lmap, _ = load_map(out)
    last = scenes[-1][1]
    for kind, sel in (("verified", lmap.verified), ("candidate", ~lmap.verified & ~lmap.hypothesis),
                      ("hypothesis", ~lmap.verified & lmap.hypothesis)):
        want = lmap.P[sel][..., [2, 0, 1]] * [1, -1, -1]
        got = last.get(kind, np.zeros((0, 2, 3)))
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, atol=2e-6)         # the file keeps 6 decimals
    assert len(lmap) > 20


def test_the_live_view_repeats_the_last_map_to_a_client_that_subscribes_later():
    from vbnav.control.comms.live_view import LiveView
    from vbnav.control.config import Config
    tcfg = Config.model_validate({"telemetry": {"live_view": {"enabled": True, "port": 0}}}).telemetry
    lv = LiveView(tcfg, "sim", submit_teleop=lambda k, p: None, refuse=lambda k, r, p: None,
                  to_wall_ns=lambda t: t + 1_000_000_000)
    P = np.array([[a, b] for a, b, _, _ in SEGMENTS])
    verified, hypothesis = np.array([s[2] for s in SEGMENTS]), np.array([s[3] for s in SEGMENTS])
    try:
        for n in (2, 4):           # the map grows before anyone watches: the client gets the last one
            lv.foxglove(5_000 + n, "/vbnav/map/lines",
                        lambda t, n=n: fc.line_map_message(t, P[:n], verified[:n], hypothesis[:n]))
        c = FoxgloveClient("127.0.0.1", lv.port)
        try:
            chans = c.wait_for_channels(["/vbnav/map/lines"])
            c.subscribe({3: chans["/vbnav/map/lines"]["id"]})
            m = c.poll(10.0)
        finally:
            c.close()
    finally:
        lv.close()
    assert m is not None and m[0] == 3 and m[1] == 1_000_005_004       # wall time of the last map
    lines = decode_line_map(m[2])
    assert {k: len(v) for k, v in lines.items()} == {"verified": 2, "candidate": 1, "hypothesis": 1}
