"""The simulated world: geometry, textures, ground-truth labels, scene edits."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from vbnav.drivers.sim.render import Renderer
from vbnav.drivers.sim.world import KINDS, World, make_texture
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.geometry import CameraMount, Pose2, camera_pose

CAM = PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5)
MOUNT = CameraMount(height=0.25, forward=0.10)


@pytest.fixture(scope="module")
def room():
    return World.room(seed=0)


def test_room_layout_and_route_clearance(room):
    assert room.bounds == (-5.0, 5.0, -4.0, 4.0)
    kinds = {q.kind for q in room.polygons}
    assert kinds == {"floor", "ceiling", "wall", "box"}
    route = World.suggested_route()
    perim = sum(math.dist(route[i], route[(i + 1) % len(route)]) for i in range(len(route)))
    assert perim >= 20.0
    for i in range(len(route)):
        (x0, z0), (x1, z1) = route[i], route[(i + 1) % len(route)]
        for a in np.linspace(0, 1, 50):
            assert room.clearance(x0 + a * (x1 - x0), z0 + a * (z1 - z0)) >= 1.0


def test_quads_face_the_inside_of_the_room(room):
    # Every wall, floor and ceiling normal points toward the room centre (0, -1.25, 0).
    for q in room.polygons:
        if q.kind in ("wall", "floor", "ceiling"):
            assert q.normal @ (np.array([0.0, -1.25, 0.0]) - q.center) > 0, q.name
    for q in room.group("box_a"):        # box faces point out of the box
        box_center = np.array([-1.3, -0.45, 0.3])
        assert q.normal @ (q.center - box_center) > 0


def test_textures_are_deterministic_distinct_and_corner_rich():
    a = make_texture(123, 512, 256, 256.0).copy()
    make_texture.cache_clear()
    b = make_texture(123, 512, 256, 256.0)
    assert np.array_equal(a, b)
    c = make_texture(124, 512, 256, 256.0)
    assert np.mean(np.abs(a.astype(int) - c.astype(int))) > 20      # another seed, another texture
    assert a.std() > 40
    corners = cv2.goodFeaturesToTrack(a, 2000, 0.01, 5)
    assert len(corners) > 300                                          # 2 m x 1 m of texture
    room = World.room(seed=0)
    # Every surface has its own texture: no two walls' textures correlate.
    walls = [q.texture[:300, :1000].astype(np.float32) for q in room.polygons if q.kind == "wall"]
    for i in range(len(walls)):
        for j in range(i + 1, len(walls)):
            r = np.corrcoef(walls[i].ravel(), walls[j].ravel())[0, 1]
            assert abs(r) < 0.1


def test_room_generation_is_fast_enough():
    import time
    make_texture.cache_clear()
    t0 = time.perf_counter()
    World.room(seed=77)
    # Generous bound (the target is < 1 s on one core); catches an accidental 10x.
    assert time.perf_counter() - t0 < 5.0


def test_label_image_kinds_and_depth(room):
    R, t = camera_pose(Pose2(-3.5, -2.0, math.radians(60)), MOUNT)
    ids, depth = room.label_image(CAM, R, t)
    kinds = room.kind_image(ids)
    assert ids.dtype == np.int32 and depth.dtype == np.float32
    assert (ids > 0).all()                                   # closed room: a surface everywhere
    assert (kinds[-1] == KINDS.index("floor")).all()         # bottom row: floor
    assert (kinds[0] == KINDS.index("ceiling")).any()
    assert np.isfinite(depth).all() and depth.min() > 0.3 and depth.max() < 13.0


def test_move_and_remove_boxes_change_the_view():
    w = World.room(seed=1)
    pose = Pose2(-3.5, -2.0, math.atan2(2.2, 2.3))   # looking at box_a
    R, t = camera_pose(pose, MOUNT)
    ids0, _ = w.label_image(CAM, R, t)
    box_a = {q.pid for q in w.group("box_a")}
    n0 = np.isin(ids0, list(box_a)).sum()
    assert n0 > 5000
    tex_before = [q.texture for q in w.group("box_a")]
    w.move_box("box_a", (-2.0, 2.5))
    assert [q.texture for q in w.group("box_a")] == tex_before        # same box, moved
    assert {q.pid for q in w.group("box_a")} == box_a                 # same ids
    ids1, _ = w.label_image(CAM, R, t)
    assert np.isin(ids1, [q.pid for q in w.group("box_a")]).sum() != n0
    w.remove("box_a")
    with pytest.raises(KeyError, match="box_a"):
        w.group("box_a")
    ids2, _ = w.label_image(CAM, R, t)
    assert not np.isin(ids2, list(box_a)).any()
    with pytest.raises(KeyError, match="no box named"):
        w.move_box("nope", (0, 0))


def test_small_box_and_floor_sheet_on_the_floor():
    w = World.corridor(seed=2)
    w.add_box("cm1", (0.0, 3.0), (0.3, 0.01, 0.3))
    w.add_floor_sheet("sheet", (0.3, 1.5), (0.5, 0.4))
    R, t = camera_pose(Pose2(0.0, 0.0, 0.0), CameraMount(height=0.4, pitch=math.radians(15)))
    ids, depth = w.label_image(CAM, R, t)
    kinds = w.kind_image(ids)
    box = kinds == KINDS.index("box")
    assert box.sum() > 100                                      # a 1 cm box at 3 m is visible
    height = -w.surface_points(CAM, R, t)[..., 1]
    assert height[box].max() == pytest.approx(0.01, abs=1e-4) and height[box].min() > -1e-4
    assert np.median(np.abs(height[kinds == KINDS.index("floor")])) < 1e-5
    sheet = kinds == KINDS.index("sheet")
    assert sheet.sum() > 2000
    # The sheet lies 1 mm above the floor: its depth is the floor's depth to < 1 %.
    v = np.nonzero(sheet.any(axis=1))[0]
    row = int(np.median(v))
    cols = np.nonzero(sheet[row])[0]
    # Floor depth along a row for a pitched camera, from the ray-plane intersection.
    ray = np.linalg.inv(CAM.K) @ np.array([cols[len(cols) // 2], row, 1.0])
    ray_w = R @ ray
    z_floor = (0.0 - t[1]) / ray_w[1]
    assert depth[row, cols[len(cols) // 2]] == pytest.approx(z_floor, rel=0.01)


def test_corridor_step_down_is_labelled():
    w = World.corridor_with_step(seed=0, step_at=3.0, step_depth=0.15)
    R, t = camera_pose(Pose2(0.0, 0.0, 0.0), CameraMount(height=0.4, pitch=math.radians(10)))
    ids, depth = w.label_image(CAM, R, t)
    kinds = w.kind_image(ids)
    low = kinds == KINDS.index("step")
    assert low.sum() > 1000
    # Beyond the step the surface is 0.15 m lower than the floor plane predicts:
    # a pixel of the low floor is deeper than the floor at y = 0 along the same ray.
    r, cidx = np.argwhere(low)[len(np.argwhere(low)) // 2]
    ray_w = R @ (np.linalg.inv(CAM.K) @ np.array([cidx, r, 1.0]))
    z_floor0 = (0.0 - t[1]) / ray_w[1]
    z_low = (0.15 - t[1]) / ray_w[1]
    assert depth[r, cidx] == pytest.approx(z_low, rel=1e-3)
    assert depth[r, cidx] > z_floor0 * 1.1
    pts = w.surface_points(CAM, R, t)
    assert pts[r, cidx, 1] == pytest.approx(0.15, abs=1e-4)          # 15 cm below the floor
    floor = kinds == KINDS.index("floor")
    assert np.abs(pts[floor][:, 1]).max() < 1e-3


def test_by_name_and_bad_names():
    assert len(World.by_name("room", 0).group("floor")) == 1
    assert "box_a" not in World.by_name("empty_room", 0).names()
    with pytest.raises(ValueError, match="unknown simulated world 'moon'"):
        World.by_name("moon")
    w = World()
    with pytest.raises(ValueError, match="width and height"):
        w.add_floor(0, 0, 0, 1)
    w.add_box("b", (0, 0), (1, 1, 1))
    with pytest.raises(ValueError, match="already has"):
        w.add_box("b", (0, 0), (1, 1, 1))
    with pytest.raises(TypeError):
        Renderer(w, object())


def test_footprints_give_walls_and_box_outlines(room):
    fp = {name: (kind, pts) for name, kind, pts in room.footprints()}
    assert {"wall_south", "box_a", "box_e"} <= set(fp) and "floor" not in fp
    kind, pts = fp["box_e"]          # 1.2 m x 0.5 m box at (0.5, 3.55), no yaw
    assert kind == "box" and pts.shape == (4, 2)
    assert np.allclose(np.sort(pts[:, 0]), [-0.1, -0.1, 1.1, 1.1])
    assert np.allclose(np.sort(pts[:, 1]), [3.3, 3.3, 3.8, 3.8])
    assert fp["wall_south"][1].shape == (2, 2)
