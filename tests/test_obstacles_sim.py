"""Obstacles in the simulated world (drivers/sim_world.py) seen by the simulated stereo camera.

The robot camera of configs/sim.yaml (640x480, fx 400, 0.25 m up, level, 0.10 m ahead
of the axle) with a 7.5 cm baseline. Truth comes from the world: which polygon each
pixel sees. Two disparity sources: the camera's true disparity (as an OAK delivers its
own, here exact) and OpenCV SGBM on the rendered pair.
"""
from __future__ import annotations

import numpy as np
import pytest

from vbnav.control.stages.obstacles import ObstacleStage

from vbnav.control.config.obstacles import ObstaclesConfig
from vbnav.drivers.clock import SimClock
from vbnav.drivers.sim.camera import SimCamera
from vbnav.drivers.sim.world import KINDS, World
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.geometry import CameraMount, Pose2, camera_pose
from vbnav.vision.ground_plane import expected_plane
from vbnav.vision.obstacles import ObstacleParams, PixelClass, detect_obstacles, nearest_in_corridor
from vbnav.vision.stereo import SgbmParams, StereoRig, sgbm_disparity

CAM = PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5)
MOUNT = CameraMount(0.25, 0.10, 0.0, 0.0)
B = 0.075
RIG = StereoRig(PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5), B)
PRIOR = expected_plane(RIG, MOUNT.height, 0.0)
FLOOR = KINDS.index("floor")


def _render(world: World, pose: Pose2 = Pose2()):
    cam = SimCamera(world, CAM, MOUNT, lambda: pose, SimClock(), 15.0, noise_std=2.0, seed=1, stereo_baseline=B)
    frame = cam.render_frame(pose, 0, 1)
    ids, _ = world.label_image(CAM, *camera_pose(pose, MOUNT))
    return frame, ids


def _mask(world, ids, name):
    return np.isin(ids, [q.pid for q in world.group(name)])


@pytest.fixture(scope="module")
def corridor():
    w = World.corridor(seed=3)
    w.add_box("box2cm", (0.0, 3.10 + 0.075), (0.3, 0.02, 0.15))      # front face 3.0 m from the camera
    w.add_box("box1cm", (0.7, 2.10 + 0.075), (0.3, 0.01, 0.15))
    w.add_box("box5cm", (-0.6, 2.10 + 0.075), (0.3, 0.05, 0.15))
    w.add_floor_sheet("sheet", (0.45, 1.4), (0.4, 0.5), thickness=0.001)
    frame, ids = _render(w)
    return w, frame, ids


def test_true_disparity_2cm_box_at_3m(corridor):
    w, frame, ids = corridor
    s = detect_obstacles(frame.disparity, RIG, PRIOR, params=ObstacleParams(obstacle_height=0.01))
    box = _mask(w, ids, "box2cm")
    assert box.sum() > 100
    assert np.mean(s.labels[box] == PixelClass.OBSTACLE) >= 0.95
    # measured 0.00099 on 2026-11-30
    assert np.mean(s.labels[(w.kind_image(ids) == FLOOR)] == PixelClass.OBSTACLE) <= 0.002
    assert np.mean(s.labels[_mask(w, ids, "sheet")] == PixelClass.OBSTACLE) == 0.0     # flat sheet: ground
    n = nearest_in_corridor(s.obstacle_points, half_width=0.2)
    assert n is not None and n.distance == pytest.approx(3.0, abs=0.03)


def test_true_disparity_1cm_box_with_5mm_threshold(corridor):
    w, frame, ids = corridor
    s = detect_obstacles(frame.disparity, RIG, PRIOR, params=ObstacleParams(obstacle_height=0.005))
    assert np.mean(s.labels[_mask(w, ids, "box1cm")] == PixelClass.OBSTACLE) >= 0.95
    # measured 0.0011 on 2026-11-30
    assert np.mean(s.labels[(w.kind_image(ids) == FLOOR)] == PixelClass.OBSTACLE) <= 0.0025
    assert np.mean(s.labels[_mask(w, ids, "sheet")] == PixelClass.OBSTACLE) <= 0.001  # measured 0 on 2026-11-30


def test_sgbm_on_the_rendered_pair(corridor):
    """SGBM on these textures has ~0.4 px median floor error (p90 1.4 px), so it needs a 2 cm
    threshold and a 0.6 px noise floor. Measured here (2026-11-30): 5 cm box at 2 m 100 %, 2 cm box
    at 3 m 50 %, floor 0.96 %, sheet 0 %: the 2 cm / 0.5 % targets hold for true disparity only."""
    w, frame, ids = corridor
    D = sgbm_disparity(frame.image, frame.right, SgbmParams(num_disparities=80, block_size=5))
    s = detect_obstacles(D, RIG, PRIOR, params=ObstacleParams(obstacle_height=0.02, noise_px=0.6,
                                                               min_blob_pixels=30, max_height=1.0))
    assert s.fit.ok and s.fit.floor.height == pytest.approx(0.25, abs=0.01)
    assert np.mean(s.labels[_mask(w, ids, "box5cm")] == PixelClass.OBSTACLE) >= 0.9
    assert np.mean(s.labels[_mask(w, ids, "box2cm")] == PixelClass.OBSTACLE) >= 0.4   # found, not whole
    assert np.mean(s.labels[(w.kind_image(ids) == FLOOR)] == PixelClass.OBSTACLE) <= 0.01
    assert np.mean(s.labels[_mask(w, ids, "sheet")] == PixelClass.OBSTACLE) <= 0.01


def test_step_down_is_negative_and_stops_the_robot():
    w = World.corridor_with_step(seed=4, step_at=1.5, step_depth=0.15)
    frame, ids = _render(w)
    kinds = w.kind_image(ids)
    s = detect_obstacles(frame.disparity, RIG, PRIOR, params=ObstacleParams())
    lower = (kinds == KINDS.index("step")) & (frame.disparity > RIG.fb / 10.0)   # lower floor within 10 m
    assert lower.sum() > 1000
    assert np.mean(s.labels[lower] == PixelClass.NEGATIVE) >= 0.95
    assert np.mean(s.labels[kinds == FLOOR] == PixelClass.NEGATIVE) <= 0.001  # measured 0 on 2026-11-30
    edge = nearest_in_corridor(s.negative_points, half_width=0.25)
    assert edge.distance == pytest.approx(1.5 - MOUNT.forward, abs=0.05)    # the edge, from the camera
    cfg = ObstaclesConfig(persist_k=1, persist_n=1,
                          zones=[{"name": "stop", "action": "stop", "distance": 1.6, "half_width": 0.25}])
    stage = ObstacleStage(RIG, MOUNT, cfg)
    e = stage.process(frame, Pose2())
    assert e.info["speed_scale"] == 0.0
    assert e.value.nearest_negative[0] == pytest.approx(1.5, abs=0.05)       # robot frame: from the axle
