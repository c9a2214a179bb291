"""Using the line map: localisation from 2D-3D line correspondences, the abstraction to objects, the
traversability grid and planner, and the map file. One map of the simulated room, built once per module
(30 frames of the 6 m loop, true poses)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from line_scenes import BASELINE, CAM, MOUNT, build_map, loop_poses, render_drive, stereo_camera
from vbnav.control.line_map_file import MapFileError, load_map, save_map
from vbnav.drivers.sim.world import World
from vbnav.vision.geometry import Pose2
from vbnav.vision.line_abstraction import box_polygons, missing_lines, vertical_edges
from vbnav.vision.line_localise import View, localise
from vbnav.vision.line_segments import detect_segments
from vbnav.vision.nav_grid import GridParams, build_grid, plan
from vbnav.vision.line_map import LineMap


@pytest.fixture(scope="module")
def room_map():
    world = World.room(0)
    drive = render_drive(world, loop_poses(30))
    lmap, _ = build_map(drive)
    return world, lmap


VIEW = View(CAM.fx, CAM.fy, CAM.cx, CAM.cy, CAM.width, CAM.height, BASELINE, MOUNT)


@pytest.mark.parametrize("true", [Pose2(-0.3, -1.5, 2.5), Pose2(0.0, -1.3, -2.5)])
def test_localisation_from_a_new_start_pose(room_map, true):
    world, lmap = room_map
    f = stereo_camera(world, seed=7).render_frame(true, seq=99)
    guess = Pose2(true.x + 0.2, true.z - 0.15, true.theta + math.radians(8))    # 25 cm, 8 deg off
    r = localise(lmap, detect_segments(f.image), VIEW, guess)
    err = math.hypot(r.pose.x - true.x, r.pose.z - true.z)
    dth = math.degrees(abs(math.remainder(r.pose.theta - true.theta, math.tau)))
    # Acceptance: 3 cm and 1 degree (measured 0.2-2.5 cm, 0.03-0.6 deg).
    assert err < 0.03 and dth < 1.0, (err, dth, r)
    assert r.matches >= 3


def test_localisation_reports_a_blank_view():
    lmap = LineMap()
    from vbnav.vision.line_segments import Segments2D
    r = localise(lmap, Segments2D(np.zeros((0, 4)), np.zeros((0, 2))), VIEW, Pose2())
    assert not r.ok and r.matches == 0


def test_abstraction_finds_box_corners_and_hypotheses():
    # A 0.8 x 0.6 x 0.9 m box seen at three vertical corners.
    corners = np.array([[0.0, 0.0], [0.8, 0.0], [0.8, 0.6]])
    P = np.array([[[x, 0.0, z], [x, -0.9, z]] for x, z in corners])
    edges = vertical_edges(P)
    assert len(edges) == 3 and np.allclose(edges[:, 2], 0.9)
    polys = box_polygons(edges)
    assert len(polys) == 1 and polys[0].corners == 3
    hyp = missing_lines(polys[0])
    assert np.allclose(hyp[0], [[0.0, 0.0, 0.6], [0.0, -0.9, 0.6]])     # the fourth corner
    lmap = LineMap()
    ids = lmap.add_hypotheses(hyp)
    assert len(ids) == len(hyp) and lmap.hypothesis.all() and not lmap.verified.any()


def test_planner_goes_around_a_mapped_box():
    # A box footprint between start and goal: the path keeps the robot radius from it.
    poly = np.array([[-0.4, -0.3], [0.4, -0.3], [0.4, 0.3], [-0.4, 0.3]])
    grid = build_grid(np.zeros((0, 2, 3)), GridParams(), extra_points=np.array([[0, -2], [0, 2]]), polygons=[poly])
    path = plan(grid, (0.0, -1.5), (0.0, 1.5))
    assert path is not None and len(path) >= 3
    pts = np.concatenate([np.linspace(a, b, 50) for a, b in zip(path, path[1:])])
    outside = np.maximum(np.abs(pts[:, 0]) - 0.4, np.abs(pts[:, 1]) - 0.3)
    assert outside.min() >= 0.2
    assert plan(grid, (0.0, -1.5), (0.0, 0.0)) is None                    # goal inside the box


@pytest.mark.xfail(strict=True, reason="acceptance not met: the loop map holds box_a's east corners only (LSD pieces "
                   "of its textured west edges are not verified), so the plan cuts through the box's west half")
def test_room_map_grid_plans_behind_box_a(room_map):
    world, lmap = room_map
    V = lmap.P[lmap.verified]
    polys = [p.footprint for p in box_polygons(vertical_edges(V))]
    goal = (-1.3, 1.2)                        # north of box_a: seen from the loop, never visited
    grid = build_grid(V, GridParams(), extra_points=np.array([goal, (0.0, -2.3)]), polygons=polys)
    for start in [(0.0, -2.25), (0.8, -1.0), (-0.9, -1.5)]:
        path = plan(grid, start, goal)
        assert path is not None, start
        pts = np.concatenate([np.linspace(a, b, 40) for a, b in zip(path, path[1:])])
        clear = min(world.clearance(x, z) for x, z in pts)
        assert clear > GridParams().robot_radius_m, (start, clear, path)   # never touches box or wall


def test_map_file_round_trip_and_errors(room_map, tmp_path):
    _, lmap = room_map
    p = tmp_path / "room.json"
    save_map(lmap, p, {"world": "room"})
    back, meta = load_map(p)
    assert meta == {"world": "room"} and len(back) == len(lmap)
    assert np.allclose(back.P, lmap.P, atol=1e-5) and (back.verified == lmap.verified).all()
    assert [len(v) for v in back.views] == [len(v) for v in lmap.views]
    data = json.loads(p.read_text())
    data["version"] = 99
    p.write_text(json.dumps(data))
    with pytest.raises(MapFileError, match="newer"):
        load_map(p)
    p.write_text("{}")
    with pytest.raises(MapFileError, match="not a vbnav line map"):
        load_map(p)


def test_map_build_info_plot_commands(tmp_path, capsys):
    from vbnav.control.cli import main
    out, png = tmp_path / "m.json", tmp_path / "m.png"
    assert main(["map", "build", "-c", "sim_stereo", "--out", str(out), "--duration", "0.4"]) == 0
    assert "verified segments" in capsys.readouterr().out
    assert main(["map", "info", str(out)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frames"] >= 4 and info["segments"] > 0
    assert main(["map", "plot", str(out), "--out", str(png), "--all"]) == 0
    assert png.stat().st_size > 1000
    assert main(["map", "info", str(tmp_path / "missing.json")]) == 2
    assert "map file not found" in capsys.readouterr().err


def test_abstraction_thread_posts_hypotheses_the_sensor_loop_inserts():
    import time

    from vbnav.control.stages.line_map import LineMapStage
    lmap = LineMap()
    corners = np.array([[0.0, 2.0], [0.8, 2.0], [0.8, 2.6]])
    P = np.array([[[x, 0.0, z], [x, -0.9, z]] for x, z in corners])
    lmap._insert(P, np.broadcast_to(1e-4 * np.eye(3), (3, 2, 3, 3)).copy(), np.full(3, -1), np.zeros(4))
    lmap.verified[:] = True
    stage = LineMapStage(CAM.fx, CAM.fy, CAM.cx, CAM.cy, CAM.width, CAM.height, BASELINE, MOUNT, lmap=lmap,
                         abstraction_period_s=0.01)
    stage.start()                                     # the slow loop in its own thread
    try:
        deadline = time.monotonic() + 5.0
        while stage.abstraction.runs < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        stage.stop()
    assert stage.abstraction.runs >= 2 and len(stage.abstraction.polygons) == 1
    assert stage.abstraction.hypotheses.qsize() == 1           # one object's hypotheses, posted once
    stage._drain_hypotheses()                                  # what process() does before each frame
    assert stage.stats["hypotheses_in"] == 5 and lmap.hypothesis.sum() == 5
    # Hypotheses are predicted (to be verified in view) and pruned by misses like any candidate.
    from vbnav.vision.geometry import camera_pose
    R, t = camera_pose(Pose2(0.4, 0.0, -math.radians(70.0)), MOUNT)     # the head (yaw 70 deg) looks along +z
    pred = lmap.predict(R, t, CAM.fx, CAM.fy, CAM.cx, CAM.cy, BASELINE, CAM.width, CAM.height)
    assert np.isin(np.nonzero(lmap.hypothesis)[0], pred.index).any()


def test_goto_map_refuses_unreachable_goal_and_start_without_map(tmp_path, capsys):
    from vbnav.control.cli import main
    # A closed square of 1 m high walls around (0, 3): a goal inside cannot be reached.
    sq = [(-0.5, 2.5), (0.5, 2.5), (0.5, 3.5), (-0.5, 3.5)]
    P = np.array([[[a[0], -0.5, a[1]], [b[0], -0.5, b[1]]] for a, b in zip(sq, sq[1:] + sq[:1])])
    lmap = LineMap()
    lmap._insert(P, np.broadcast_to(1e-4 * np.eye(3), (4, 2, 3, 3)).copy(), np.full(4, -1), np.zeros(4))
    lmap.verified[:] = True
    path = tmp_path / "box.json"
    save_map(lmap, path)
    assert main(["goto", "--map", str(path), "--goal", "0", "3", "0"]) == 1
    assert "no path" in capsys.readouterr().err
    assert main(["goto", "--start", "0", "0", "0", "--goal", "0", "3", "0"]) == 2
    assert "--start needs --map" in capsys.readouterr().err
