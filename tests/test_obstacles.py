"""Obstacle labels on analytic scenes (true disparity with noise, and SGBM on rendered textured pairs).

The simulated robot camera: 640x480, fx = fy = 400, 0.25 m above the floor,
level (configs/sim.yaml), stereo baseline 7.5 cm (an OAK-D's).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

import disparity_scenes as ds  # same directory

from vbnav.vision.ground_plane import expected_plane
from vbnav.vision.obstacles import (KOfN, ObstacleParams, PixelClass, classify, detect_obstacles,
                                    nearest_in_corridor)
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.stereo import SgbmParams, StereoRig, sgbm_disparity

RIG = StereoRig(PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5), 0.075)
H = 0.25
PRIOR = expected_plane(RIG, H, 0.0)

BOX_2CM_3M = ds.Box(-0.10, 0.10, 3.0, 3.15, 0.02)
BOX_1CM_2M = ds.Box(-0.75, -0.55, 2.0, 2.15, 0.01)
SHEET = ds.Box(0.3, 0.7, 1.5, 1.9, 0.002)           # a newspaper lying flat (chapter Fig. 11.9)
SCENE = ds.Scene(H, 0.0, boxes=(BOX_2CM_3M, SHEET, BOX_1CM_2M))
STEP = ds.Scene(H, 0.0, step_z=2.5, step_depth=0.17)


def _noisy(r, rng, sigma):
    return r.disparity + rng.normal(0.0, sigma, r.disparity.shape).astype(np.float32)


def _flagged(labels, mask, cls=PixelClass.OBSTACLE):
    return float(np.mean(labels[mask] == cls))


def test_stereo_rig_is_a_rectified_camera_and_a_baseline():
    half = RIG.scaled(0.5)
    assert half.camera == RIG.camera.scaled(0.5) and half.baseline == RIG.baseline
    assert (half.width, half.height, half.fx, half.cy) == (320, 240, 200.0, 119.5)
    assert half.fb == pytest.approx(200.0 * 0.075)
    with pytest.raises(ValueError, match="distortion"):
        StereoRig(PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5, (0.1, 0.0, 0.0, 0.0)), 0.075)
    with pytest.raises(ValueError, match="baseline"):
        StereoRig(RIG.camera, 0.0)


def test_2cm_box_at_3m_found_and_floor_clean(rng):
    r = ds.render(SCENE, RIG)
    D = _noisy(r, rng, 0.1)                         # about the OAK's subpixel noise
    s = detect_obstacles(D, RIG, PRIOR, params=ObstacleParams(obstacle_height=0.01, noise_px=0.3))
    box = r.surface == ds.BOX0
    assert box.sum() > 60                           # ~3 rows x 27 columns are visible
    assert _flagged(s.labels, box) >= 0.95
    assert _flagged(s.labels, r.surface == ds.FLOOR) <= 1e-4  # measured 4.0e-5 (6 px) on 2026-12-04, bar 2.5x
    assert _flagged(s.labels, r.surface == ds.BOX0 + 1) <= 0.01          # the flat sheet is ground
    assert _flagged(s.labels, r.surface == ds.BOX0 + 1, PixelClass.GROUND) >= 0.99


def test_1cm_box_with_a_5mm_threshold(rng):
    """The chapter's figure: 1 cm above the floor. It needs a threshold below 1 cm and low noise."""
    r = ds.render(SCENE, RIG)
    D = _noisy(r, rng, 0.03)
    s = detect_obstacles(D, RIG, PRIOR, params=ObstacleParams(obstacle_height=0.005, noise_px=0.1))
    assert _flagged(s.labels, r.surface == ds.BOX0 + 2) >= 0.95
    assert _flagged(s.labels, r.surface == ds.BOX0) >= 0.95
    assert _flagged(s.labels, r.surface == ds.FLOOR) <= 1e-4  # measured 4.6e-5 (7 px) on 2026-12-04, bar 2x


def test_step_down_is_a_negative_obstacle(rng):
    r = ds.render(STEP, RIG)
    D = _noisy(r, rng, 0.1)
    s = detect_obstacles(D, RIG, PRIOR, params=ObstacleParams(noise_px=0.3))
    near = RIG.fb / r.disparity > 0                 # all
    lower = (r.surface == ds.LOWER_FLOOR) & (r.disparity > RIG.fb / 15.0)   # lower floor within 15 m
    assert _flagged(s.labels, lower, PixelClass.NEGATIVE) >= 0.95
    assert _flagged(s.labels, (r.surface == ds.FLOOR) & near, PixelClass.NEGATIVE) <= 0.001  # measured 0 on 2026-11-30
    edge = nearest_in_corridor(s.negative_points, half_width=0.2)
    assert edge is not None and edge.distance == pytest.approx(2.5, abs=0.05)
    assert nearest_in_corridor(s.obstacle_points, half_width=0.2) is None


def test_missing_disparity_beyond_a_step_is_negative(rng):
    """A matcher often finds nothing just beyond an edge: missing where ground is expected."""
    r = ds.render(STEP, RIG)
    D = _noisy(r, rng, 0.1)
    lower = r.surface == ds.LOWER_FLOOR
    band = lower & (r.disparity > RIG.fb / 5.5)      # the lower floor from where it shows (4.2 m) to 5.5 m
    assert band.sum() > 1000
    D[band] = np.nan
    labels = classify(D, PRIOR, PRIOR.floor(RIG), RIG, ObstacleParams(noise_px=0.3))
    assert _flagged(labels, band, PixelClass.NEGATIVE) >= 0.95
    # missing disparity on plain floor stays unknown
    D2 = _noisy(ds.render(ds.Scene(H, 0.0), RIG), rng, 0.1)
    D2[300:320, 100:200] = np.nan
    labels2 = classify(D2, PRIOR, PRIOR.floor(RIG), RIG, ObstacleParams(noise_px=0.3))
    assert np.all(labels2[300:320, 100:200] == PixelClass.UNKNOWN)


def test_nearest_obstacle_distance_and_bearing(rng):
    box = ds.Box(0.25, 0.45, 1.8, 2.0, 0.1)          # 1.8 m ahead, 0.25-0.45 m to the right
    far_left = ds.Box(-0.75, -0.55, 1.0, 1.2, 0.3)   # nearer, but outside a 1 m wide corridor, to the left
    r = ds.render(ds.Scene(H, 0.0, boxes=(box, far_left)), RIG)
    s = detect_obstacles(_noisy(r, rng, 0.1), RIG, PRIOR, params=ObstacleParams(noise_px=0.3))
    n = nearest_in_corridor(s.obstacle_points, half_width=0.5)
    assert n is not None
    assert n.distance == pytest.approx(1.8, abs=0.04)
    assert 0.25 <= n.lateral <= 0.5 and n.bearing > 0          # to the right: positive bearing
    assert n.bearing == pytest.approx(math.atan2(n.lateral, n.distance))
    wide = nearest_in_corridor(s.obstacle_points, half_width=2.0)
    assert wide.distance == pytest.approx(1.0, abs=0.02) and wide.bearing < 0  # measured 0.990 m on 2026-11-30
    assert nearest_in_corridor(s.obstacle_points, half_width=0.5, max_range=1.5) is None


def test_overhangs_and_far_points_are_out_of_scope():
    table = ds.Box(-0.5, 0.5, 1.0, 1.6, 0.6)          # seen as a block here; its top is 0.6 m up
    r = ds.render(ds.Scene(H, 0.0, boxes=(table,)), RIG)
    labels = classify(r.disparity, PRIOR, PRIOR.floor(RIG), RIG, ObstacleParams(max_height=0.4))
    elev = r.elevation
    tbl = r.surface == ds.BOX0
    assert np.all(labels[tbl & (elev > 0.41)] == PixelClass.UNKNOWN)
    assert np.mean(labels[tbl & (elev < 0.39) & (elev > 0.02)] == PixelClass.OBSTACLE) > 0.97
    far = classify(r.disparity, PRIOR, PRIOR.floor(RIG), RIG, ObstacleParams(max_range=0.95))
    assert np.all(far[tbl] == PixelClass.UNKNOWN)   # the box is 1.0-1.6 m away, 0.95 m is the limit
    assert np.all(far[(r.surface == ds.FLOOR) & (r.disparity > RIG.fb / 0.9)] == PixelClass.GROUND)


def test_isolated_noise_pixels_are_not_obstacles(rng):
    r = ds.render(ds.Scene(H, 0.0), RIG)
    D = r.disparity.copy()
    spikes = rng.random(D.shape) < 0.002
    D[spikes] += 5.0                                  # single-pixel mismatches
    labels = classify(D, PRIOR, PRIOR.floor(RIG), RIG, ObstacleParams())
    assert np.count_nonzero(labels == PixelClass.OBSTACLE) == 0


def test_k_of_n_filter():
    f = KOfN(2, 3)
    assert [f.update(x) for x in (True, False, False, True, True, False, False)] == \
        [False, False, False, False, True, True, False]
    with pytest.raises(ValueError):
        KOfN(4, 3)


# --- SGBM on a rendered textured pair -----------------------------------------------------------

SGBM_SCENE = ds.Scene(H, 0.0, boxes=(ds.Box(-0.12, 0.12, 2.0, 2.15, 0.05), ds.Box(0.6, 0.84, 3.0, 3.15, 0.05),
                                     ds.Box(-0.9, -0.66, 3.0, 3.15, 0.03), SHEET,
                                     ds.Box(-30, 30, 12.0, 12.5, 8.0, texel=0.05)),   # a textured far wall, no sky
                      step_z=5.0, step_depth=0.17)


@pytest.fixture(scope="module")
def sgbm_scene():
    left, right, truth = ds.textured_pair(SGBM_SCENE, RIG, noise_std=1.0, rng=np.random.default_rng(5))
    D = sgbm_disparity(left, right, SgbmParams(num_disparities=80, block_size=3))
    # max_height: the textureless sky gives SGBM some false matches high above the robot
    s = detect_obstacles(D, RIG, PRIOR, params=ObstacleParams(obstacle_height=0.01, noise_px=0.4, max_height=0.5))
    return D, truth, s


def test_sgbm_disparity_is_accurate_on_the_floor(sgbm_scene):
    D, truth, _ = sgbm_scene
    floor = (truth.surface == ds.FLOOR) & np.isfinite(D)
    assert floor.sum() > 0.3 * D.size
    assert np.median(np.abs(D[floor] - truth.disparity[floor])) < 0.3


def test_sgbm_boxes_sheet_and_step(sgbm_scene):
    D, truth, s = sgbm_scene
    assert s.fit.ok and s.fit.floor.height == pytest.approx(H, abs=0.005)
    assert _flagged(s.labels, truth.surface == ds.BOX0) >= 0.9       # 5 cm at 2 m
    assert _flagged(s.labels, truth.surface == ds.BOX0 + 1) >= 0.9   # 5 cm at 3 m
    assert _flagged(s.labels, truth.surface == ds.BOX0 + 2) >= 0.95  # 3 cm at 3 m (measured 0.977 on 2026-11-30)
    assert _flagged(s.labels, truth.surface == ds.BOX0 + 3) <= 0.005  # the sheet (measured 0 on 2026-11-30)
    assert _flagged(s.labels, truth.surface == ds.FLOOR) <= 0.005
    lower = (truth.surface == ds.LOWER_FLOOR) & (truth.disparity > RIG.fb / 15.0)
    # measured 0.86 on 2026-11-30: bar at twice the 14 % missed
    assert _flagged(s.labels, lower, PixelClass.NEGATIVE) >= 0.72
    n = nearest_in_corridor(s.obstacle_points, half_width=0.3)
    assert n is not None and n.distance == pytest.approx(2.0, abs=0.1)


@pytest.mark.parametrize("piecewise", [False, True], ids=["plane", "piecewise"])
def test_infinite_disparity_is_unknown_not_ground(piecewise):
    """An infinite disparity (a depth of 0 turned into disparity, fB / 0) counted as a disparity: a patch of it on
    a clear floor came out mostly ground (seen clear) with a rim of obstacle pixels at 0 m. It is unknown now,
    like NaN: the labels and points are those of the same image with NaN there."""
    from vbnav.vision.ground_model import GroundModelParams
    D = ds.render(ds.Scene(H, 0.0), RIG).disparity
    D[380:460, 250:390] = np.inf
    ground = GroundModelParams() if piecewise else None
    s = detect_obstacles(D, RIG, PRIOR, ground=ground)
    assert (s.labels[380:460, 250:390] == PixelClass.UNKNOWN).all()
    nan = D.copy()
    nan[380:460, 250:390] = np.nan
    ref = detect_obstacles(nan, RIG, PRIOR, ground=ground)
    np.testing.assert_array_equal(s.labels, ref.labels)
    assert len(s.obstacle_points) == len(ref.obstacle_points) == 0


def test_a_16_bit_pair_is_matched_as_its_8_bit_original_by_one_grey_scale():
    """sgbm_disparity stretched each image of a non-8-bit pair (vbnav obstacles --left/--right 16-bit PNGs) to
    8 bits on its own: something bright that only the right camera sees darkened the whole right image, and
    SGBM matched two different exposures. Both images now share one range: a 16-bit pair (an 8-bit one times
    257) gives the 8-bit pair's very disparity, and its texture matches everywhere at the true shift."""
    import cv2
    rng = np.random.default_rng(3)
    h, w, shift = 120, 200, 8
    tex = cv2.GaussianBlur(rng.random((h, w + shift)), (0, 0), 3.0)
    tex = np.rint(200 * (tex - tex.min()) / (tex.max() - tex.min())).astype(np.uint8)   # grey 0..200
    tex[0, 100] = 0                     # a black speck both cameras see: the pair's range is 0..255
    left8, right8 = tex[:, :w].copy(), tex[:, shift:].copy()     # a fronto-parallel wall 8 px away
    right8[:, -20:] = 255               # a lamp at the right border, seen by the right camera only
    d8 = sgbm_disparity(left8, right8)
    d16 = sgbm_disparity(left8.astype(np.uint16) * 257, right8.astype(np.uint16) * 257)
    assert np.array_equal(d16, d8, equal_nan=True)
    wall = d16[10:-10, 80:-30]          # away from the borders and the lamp
    assert np.mean(np.abs(wall - shift) < 0.5) > 0.99
