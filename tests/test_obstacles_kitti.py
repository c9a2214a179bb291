"""Real data: KITTI odometry sequence 06 (shared_data/kitti06_stereo), SGBM + ground-plane suppression.

Road region: a trapezoid on the lane ahead of the car, rows 215-365, 320 px wide
at the bottom (x 470-790) narrowing to x 575-660 at row 215 (about 9 m to 45 m
ahead). It was drawn on the images (frames 0-50) to stay on the asphalt, clear of
the curbs and of parked cars. Obstacle boxes were picked on the images by eye:
the parked car on the right in frame 0 and frame 25, the car ahead in frame 10.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from vbnav.drivers.stereo_calib import load_stereo_calibration
from vbnav.vision.ground_plane import expected_plane
from vbnav.vision.obstacles import ObstacleParams, PixelClass, detect_obstacles, nearest_in_corridor
from vbnav.vision.stereo import SGBM_KITTI, sgbm_disparity

pytestmark = pytest.mark.realdata

ROAD = np.array([[470, 365], [790, 365], [660, 215], [575, 215]], np.int32)
CARS = {0: (725, 180, 835, 240), 10: (665, 178, 720, 210), 25: (820, 195, 1110, 330)}   # x0, y0, x1, y1
FRAMES = (0, 10, 25, 32, 40, 50)
# 10 cm (a curb) above or below the road; things more than 2 m up (branches, mismatches in the
# sky at the image top) are overhangs a car passes under.
PARAMS = ObstacleParams(obstacle_height=0.10, negative_depth=0.10, noise_px=0.4, max_height=2.0, report_range=40.0)


@pytest.fixture(scope="module")
def kitti(shared_data):
    root = shared_data / "kitti06_stereo"
    calib = load_stereo_calibration(root / "calib.txt")
    rig = calib.rig(1226, 370)
    prior = expected_plane(rig, 1.65, 0.0)        # KITTI's camera is ~1.65 m above the road, level
    road = np.zeros((370, 1226), np.uint8)
    cv2.fillPoly(road, [ROAD], 1)
    out = {}
    for f in FRAMES:
        left = cv2.imread(str(root / "image_l" / f"{f:06d}.png"), cv2.IMREAD_GRAYSCALE)
        right = cv2.imread(str(root / "image_r" / f"{f:06d}.png"), cv2.IMREAD_GRAYSCALE)
        disp = sgbm_disparity(left, right, SGBM_KITTI)
        out[f] = detect_obstacles(disp, rig, prior, params=PARAMS)
    return out, road.astype(bool)


def test_calibration_matches_the_readme(shared_data):
    c = load_stereo_calibration(shared_data / "kitti06_stereo" / "calib.txt")
    assert c.fx == pytest.approx(707.0912) and c.cx == pytest.approx(601.8873) and c.cy == pytest.approx(183.1104)
    assert c.baseline == pytest.approx(379.8145 / 707.0912)


@pytest.mark.parametrize("frame", FRAMES)
def test_fitted_plane_matches_the_road(kitti, frame):
    scenes, road = kitti
    s = scenes[frame]
    assert s.fit.ok and not s.fit.used_prior
    fl = s.fit.floor
    assert fl.height == pytest.approx(1.65, abs=0.07)
    assert abs(math.degrees(fl.pitch)) < 2.0 and abs(math.degrees(fl.roll)) < 2.0
    ground = float(np.mean(s.labels[road] == PixelClass.GROUND))
    assert ground >= 0.95, f"frame {frame}: {ground:.3f} of the road region is ground"
    # nothing blocks the lane straight ahead within 8 m (the left curb is ~1 m to the left)
    n = nearest_in_corridor(s.obstacle_points, half_width=0.6, max_range=40.0)
    assert n is None or n.distance > 8.0


@pytest.mark.parametrize("frame", sorted(CARS))
def test_parked_cars_are_obstacles(kitti, frame):
    scenes, _ = kitti
    x0, y0, x1, y1 = CARS[frame]
    box = scenes[frame].labels[y0:y1, x0:x1]
    known = box != PixelClass.UNKNOWN
    assert known.mean() > 0.8
    assert np.mean(box[known] == PixelClass.OBSTACLE) >= 0.9
