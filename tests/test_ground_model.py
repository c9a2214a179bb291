"""The piecewise ground (vision/ground_model.py) on analytic street scenes: a kerb, camber, ramps.

Street scale, as the KITTI test runs it: KITTI's rectified camera at half resolution
(613x185, fx 353.5 px, baseline 0.537 m), 1.65 m above the road, level. True disparity
plus Gaussian noise of 0.25 px, the robust sigma SGBM shows on KITTI 06's road (10-30 m,
docs/obstacles.md). Thresholds as there: 10 cm obstacle / negative, noise floor 3 sigma =
0.75 px, the mounting bounds of ObstaclesConfig (5 cm... see STREET_FIT).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

import disparity_scenes as ds  # same directory

from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.ground_model import GroundModelParams, fit_ground_model
from vbnav.vision.ground_plane import PlaneFitParams, expected_plane
from vbnav.vision.obstacles import ObstacleParams, PixelClass, detect_obstacles
from vbnav.vision.stereo import StereoRig

RIG = StereoRig(PinholeCamera(613, 185, 353.5456, 353.5456, 300.94, 91.56), 0.537)
H = 1.65
PRIOR = expected_plane(RIG, H, 0.0)
SIGMA = 0.25
PARAMS = ObstacleParams(obstacle_height=0.10, negative_depth=0.10, noise_px=3 * SIGMA, max_height=2.0,
                        report_range=40.0)
STREET_FIT = PlaneFitParams(step=2, inlier_height=0.05, max_height_change=0.15, max_pitch_change_deg=2.0,
                            max_roll_change_deg=2.0)
STREET = GroundModelParams(corridor_half_width=1.75)       # half a 3.5 m lane
RANGE = 30.0                                                # m, the road judged out to here


def _detect(scene, rng, ground=STREET):
    r = ds.render(scene, RIG)
    D = r.disparity + rng.normal(0.0, SIGMA, r.disparity.shape).astype(np.float32)
    return r, detect_obstacles(D, RIG, PRIOR, STREET_FIT, PARAMS, ground=ground)


def _road(r, half_width=5.25):
    """Road surface within RANGE and +-half_width of the camera (two 3.5 m lanes and a half)."""
    with np.errstate(invalid="ignore"):
        return ((r.surface == ds.FLOOR) & (r.points[..., 2] <= RANGE) & (np.abs(r.points[..., 0]) <= half_width))


def _share(labels, mask, cls):
    return float(np.mean(labels[mask] == cls))


def test_kerb_taller_than_the_threshold_is_an_obstacle(rng):
    """A 15 cm kerb and raised pavement 2 m to the right, along the whole street.

    Judged where 15 cm shows above the noise floor, D h / (H - h) >= 3 sigma, i.e. out to
    fB h / ((H - h) 3 sigma) = 25 m, the kerb's face 12.5 cm and more up (the threshold is 10 cm) and
    the pavement within 0.25 m of its edge: beyond the
    corridor (1.75 m) the camber allowance (6 cm per m) raises the threshold, so 15 cm is above
    it only up to (0.15 - 0.10) / 0.06 = 0.83 m past the corridor (docs/obstacles.md)."""
    h_kerb = 0.15
    pavement = ds.Box(2.0, 6.0, 0.0, 200.0, h_kerb, texel=0.02)
    r, s = _detect(ds.Scene(H, 0.0, boxes=(pavement,)), rng)
    z_max = RIG.fb * h_kerb / ((H - h_kerb) * PARAMS.noise_px)
    with np.errstate(invalid="ignore"):         # the face's lowest rows are below any threshold
        kerb = ((r.surface == ds.BOX0) & (r.points[..., 2] <= z_max) & (r.points[..., 0] <= 2.25)
                & (r.elevation >= 0.125))
    assert kerb.sum() > 300
    assert _share(s.labels, kerb, PixelClass.OBSTACLE) >= 0.9
    road = _road(r, 2.0)
    assert _share(s.labels, road, PixelClass.GROUND) >= 0.99
    fl = s.fit.floor                                 # the pavement does not tilt the fit
    # measured 0.0034 deg and 2.8 mm on 2026-12-04, bars about 2x
    assert abs(math.degrees(fl.roll)) < 0.008 and fl.height == pytest.approx(H, abs=0.006)


def test_camber_is_ground(rng):
    """A crowned road: the other lane, left of the crown 1.75 m to the left, falls away at 2.5 %
    while the camera's lane rises toward the crown at 2.5 %: 5 % relative, as the car sees it."""
    r, s = _detect(ds.Scene(H, 0.0, camber=(-1.75, 0.05)), rng)
    road = _road(r)
    assert _share(s.labels, road, PixelClass.GROUND) >= 0.97
    assert _share(s.labels, road, PixelClass.NEGATIVE) <= 0.01
    # the single plane (the peer) calls the far side of the crown negative
    _, one = _detect(ds.Scene(H, 0.0, camber=(-1.75, 0.05)), rng, ground=None)
    assert _share(one.labels, road, PixelClass.NEGATIVE) > 0.05


@pytest.mark.parametrize("start,grade", [(8.0, 0.05), (15.0, 0.05), (12.0, -0.05)])
def test_ramp_is_ground(rng, start, grade):
    r, s = _detect(ds.Scene(H, 0.0, ramp=(start, grade)), rng)
    road = _road(r, 1.75)
    assert _share(s.labels, road, PixelClass.GROUND) >= 0.97
    assert _share(s.labels, road, PixelClass.NEGATIVE) <= 0.01
    assert _share(s.labels, road, PixelClass.OBSTACLE) <= 0.01
    bends = [b.grade_change for b in s.ground.bands[1:] if b.grade_change != 0.0]
    assert bends and math.copysign(1.0, bends[0]) == math.copysign(1.0, grade)    # the first bend's sense


def test_box_on_the_road_is_still_an_obstacle(rng):
    """The hinged bands do not bend over a real obstacle: a 30 cm box 20 m ahead."""
    box = ds.Box(-0.5, 0.5, 20.0, 20.5, 0.3, texel=0.02)
    r, s = _detect(ds.Scene(H, 0.0, boxes=(box,)), rng)
    assert _share(s.labels, r.surface == ds.BOX0, PixelClass.OBSTACLE) >= 0.9


def test_step_down_is_still_negative(rng):
    """A 30 cm drop 14 m ahead: the hinge cannot fold onto the lower road (coverage check)."""
    r, s = _detect(ds.Scene(H, 0.0, step_z=14.0, step_depth=0.3), rng)
    with np.errstate(invalid="ignore"):         # in the corridor: beyond it the camber allowance grows
        lower = (r.surface == ds.LOWER_FLOOR) & (r.points[..., 2] <= RANGE) & (np.abs(r.points[..., 0]) <= 1.75)
    assert _share(s.labels, lower, PixelClass.NEGATIVE) >= 0.9
    assert _share(s.labels, _road(r, 1.75), PixelClass.NEGATIVE) <= 0.01


def test_fit_outside_the_mounting_bounds_is_rejected(rng):
    """A prior 4 degrees off in roll: no plane within 2 degrees of it fits, so the fit says so."""
    r = ds.render(ds.Scene(H, 0.0), RIG)
    D = r.disparity + rng.normal(0.0, SIGMA, r.disparity.shape).astype(np.float32)
    wrong = expected_plane(RIG, H, 0.0, math.radians(4.0))
    m = fit_ground_model(D, RIG, wrong, STREET_FIT, STREET)
    fl = m.near.floor
    assert abs(math.degrees(fl.roll) - 4.0) <= 2.0 + 1e-6      # never beyond the bound
    assert not m.near.ok or abs(math.degrees(fl.roll) - 4.0) <= 2.0


def test_hinge_grades_round_trip():
    """The pencil D = (1 + t) P - t b holds the planes through the hinge line; t for a grade change
    theta gives back theta (positive: the ground rises ahead), and the line stays put."""
    from vbnav.vision.ground_model import _grade_of, _pencil_t
    plane = expected_plane(RIG, H, math.radians(0.6), math.radians(0.3))
    r, b = np.asarray(plane.rho), 12.0
    thetas = np.radians([-4.5, -1.0, 0.0, 2.0, 4.5])
    for t, th in zip(_pencil_t(r, b, thetas, RIG), thetas):
        rho = (1 + t) * r - t * b * np.array([0.0, 0.0, 1.0])
        assert math.degrees(_grade_of(r, rho, RIG)) == pytest.approx(math.degrees(th), abs=1e-6)
        u = np.array([0.0, 300.0, 612.0])
        v = (b - r[0] * u - r[2]) / r[1]              # on the hinge line: the old plane reads b
        np.testing.assert_allclose(rho[0] * u + rho[1] * v + rho[2], b, rtol=1e-9)
        if th > 0:                                     # uphill: farther ground has more disparity
            assert rho[1] * 10.0 + rho[2] > r[1] * 10.0 + r[2]


def test_ground_images_follow_the_band_cascade(rng):
    """GroundModel.images (row-limited per band) equals the plain cascade: band k's plane wherever
    band k-1's plane reads below b_k, on a ramp where the bands bend."""
    r = ds.render(ds.Scene(H, 0.0, ramp=(15.0, 0.05)), RIG)
    D = r.disparity + rng.normal(0.0, SIGMA, r.disparity.shape).astype(np.float32)
    m = fit_ground_model(D, RIG, PRIOR, STREET_FIT, STREET)
    assert any(b.grade_change != 0.0 for b in m.bands)
    h, w = D.shape
    ref = m.bands[0].plane.image(h, w).copy()
    ref_h = np.full_like(ref, m.bands[0].floor.height)
    for k in range(1, len(m.bands)):
        inside = m.bands[k - 1].plane.image(h, w) < m.bands[k].near_disparity
        ref[inside] = m.bands[k].plane.image(h, w)[inside]
        ref_h[inside] = m.bands[k].floor.height
    Dg, Hk = m.images(h, w)
    np.testing.assert_array_equal(Dg, ref)
    np.testing.assert_array_equal(Hk, ref_h)
