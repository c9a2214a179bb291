"""Ground plane in (u, v, D): the analytic plane from the mounting, its inverse, the fit."""
from __future__ import annotations

import math

import numpy as np
import pytest

import disparity_scenes as ds  # same directory

from vbnav.vision.geometry import CameraMount, Pose2, camera_pose
from vbnav.vision.ground_plane import (DisparityPlane, expected_plane, fit_ground_plane,
                                       plane_from_floor)
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.stereo import StereoRig

RIG = StereoRig(PinholeCamera(640, 480, 400.0, 410.0, 322.0, 236.0), 0.075)


@pytest.mark.parametrize("height,pitch_deg", [(0.25, 0.0), (0.25, 12.0), (0.6, -3.0), (1.65, 1.0)])
def test_expected_plane_predicts_rendered_floor_disparity(height, pitch_deg):
    scene = ds.Scene(height, math.radians(pitch_deg))
    r = ds.render(scene, RIG)
    plane = expected_plane(RIG, height, math.radians(pitch_deg))
    floor = r.surface == ds.FLOOR
    assert floor.sum() > 10000
    h, w = r.disparity.shape
    err = plane.image(h, w)[floor] - r.disparity[floor]
    assert np.max(np.abs(err)) < 1e-3 * np.max(r.disparity[floor])


def test_expected_plane_agrees_with_camera_mount_convention():
    """Project floor points through vision.geometry's camera_pose and compare disparities."""
    mount = CameraMount(height=0.3, forward=0.1, pitch=math.radians(8))
    R_wc, t_wc = camera_pose(Pose2(0.4, -1.0, 0.3), mount)
    plane = expected_plane(RIG, 0.3, math.radians(8))
    rng = np.random.default_rng(3)
    # floor points in front of the camera: world y = 0
    fwd = R_wc[:, 2] * np.array([1, 0, 1])
    fwd /= np.linalg.norm(fwd)
    side = np.cross([0, 1.0, 0], fwd)
    pts = t_wc * np.array([1, 0, 1]) + np.outer(rng.uniform(0.8, 6, 50), fwd) + np.outer(rng.uniform(-1, 1, 50), side)
    Pc = (pts - t_wc) @ R_wc                      # camera frame: R_wc^T (p - t)
    u = RIG.fx * Pc[:, 0] / Pc[:, 2] + RIG.cx
    v = RIG.fy * Pc[:, 1] / Pc[:, 2] + RIG.cy
    np.testing.assert_allclose(plane.predict(u, v), RIG.fb / Pc[:, 2], rtol=1e-9)


@pytest.mark.parametrize("height,pitch,roll", [(0.25, 0.1, 0.0), (1.65, -0.02, 0.03), (0.4, 0.5, -0.1)])
def test_plane_gives_back_height_pitch_roll(height, pitch, roll):
    fl = expected_plane(RIG, height, pitch, roll).floor(RIG)
    assert fl.height == pytest.approx(height, rel=1e-9)
    assert fl.pitch == pytest.approx(pitch, abs=1e-9)
    assert fl.roll == pytest.approx(roll, abs=1e-9)
    assert plane_from_floor(RIG, fl.height, fl.down).rho == pytest.approx(expected_plane(RIG, height, pitch, roll).rho)


def test_height_threshold_in_disparity():
    """A point h above the floor on a pixel's ray has disparity D_g H / (H - h) (module docstring)."""
    H, pitch, h = 0.25, math.radians(6), 0.02
    plane = expected_plane(RIG, H, pitch)
    fl = plane.floor(RIG)
    g = np.asarray(fl.down)
    for u, v in [(100.0, 300.0), (320.0, 400.0), (600.0, 250.0)]:
        r = np.array([(u - RIG.cx) / RIG.fx, (v - RIG.cy) / RIG.fy, 1.0])
        z = (H - h) / (g @ r)                     # g . X = H - h on the ray X = z r
        D = RIG.fb / z
        Dg = plane.predict(u, v)
        assert D == pytest.approx(Dg * H / (H - h), rel=1e-12)
        assert H * (D - Dg) / D == pytest.approx(h, rel=1e-9)   # the inverse: height from disparity


def _scene_with_clutter():
    boxes = (ds.Box(-0.8, -0.3, 1.0, 1.4, 0.5), ds.Box(0.2, 1.5, 2.0, 2.5, 1.0), ds.Box(-3, 3, 6.0, 6.2, 2.0),
             ds.Box(-0.2, 0.3, 0.8, 1.0, 0.08))
    return ds.Scene(0.25, math.radians(7), boxes=boxes)


@pytest.mark.parametrize("prior_error", [(0.0, 0.0), (0.05, 3.0), (-0.04, -4.0)])
def test_fit_recovers_floor_despite_clutter_and_a_wrong_prior(rng, prior_error):
    scene = _scene_with_clutter()
    r = ds.render(scene, RIG)
    D = r.disparity + rng.normal(0, 0.15, r.disparity.shape).astype(np.float32)
    D[rng.random(D.shape) < 0.1] = np.nan                       # unmatched pixels
    dh, dpitch = prior_error
    prior = expected_plane(RIG, 0.25 + dh, scene.pitch + math.radians(dpitch))
    fit = fit_ground_plane(D, RIG, prior)
    assert fit.ok and not fit.used_prior
    assert fit.floor.height == pytest.approx(0.25, abs=0.003)
    assert math.degrees(fit.floor.pitch) == pytest.approx(7.0, abs=0.1)
    assert abs(math.degrees(fit.floor.roll)) < 0.025  # measured 0.009-0.012 deg on 2026-11-30, bar 2x
    non_floor = np.isin(r.surface[2::4, 2::4], [ds.BOX0, ds.BOX0 + 1, ds.BOX0 + 2])
    assert non_floor.mean() > 0.2                              # the clutter is substantial


def test_fit_without_prior(rng):
    scene = _scene_with_clutter()
    r = ds.render(scene, RIG)
    D = r.disparity + rng.normal(0, 0.15, r.disparity.shape).astype(np.float32)
    fit = fit_ground_plane(D, RIG, None)
    assert fit.ok
    assert fit.floor.height == pytest.approx(0.25, abs=0.003)


def test_fit_falls_back_to_prior_when_no_floor_is_visible():
    wall = ds.Scene(0.25, 0.0, boxes=(ds.Box(-5, 5, 0.3, 0.4, 3.0),))   # nearer than the lowest floor ray
    r = ds.render(wall, RIG)
    prior = expected_plane(RIG, 0.25, 0.0)
    fit = fit_ground_plane(r.disparity, RIG, prior)
    assert not fit.ok and fit.used_prior and fit.plane == prior
    assert "floor" in fit.reason or "hypothesis" in fit.reason or "inliers" in fit.reason


def test_fit_is_deterministic(rng):
    r = ds.render(_scene_with_clutter(), RIG)
    D = r.disparity + rng.normal(0, 0.2, r.disparity.shape).astype(np.float32)
    prior = expected_plane(RIG, 0.25, math.radians(7))
    assert fit_ground_plane(D, RIG, prior).plane == fit_ground_plane(D, RIG, prior).plane


def test_fit_rejects_wrong_image_size():
    with pytest.raises(ValueError, match="640x480"):
        fit_ground_plane(np.zeros((10, 10), np.float32), RIG, None)


def test_degenerate_plane_is_an_error():
    with pytest.raises(ValueError, match="degenerate"):
        DisparityPlane((0.0, 0.0, 0.0)).floor(RIG)
    with pytest.raises(ValueError, match="positive"):
        plane_from_floor(RIG, 0.0, (0, 1, 0))
