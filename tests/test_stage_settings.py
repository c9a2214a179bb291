"""The vision stages' thresholds that are settings reach the computation they steer.

Each test runs one stage step with a setting at its default and changed, and looks at what the step
handed to the vision routine (a spy in place of the routine) or what it produced.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

import vbnav.control.stages.repeat as repeat_stage
import vbnav.control.stages.vslam as vslam_stage
from vbnav.control.config.obstacles import ObstaclesConfig
from vbnav.control.config.vbc import VBCConfig
from vbnav.control.config.vslam import VslamNavConfig
from vbnav.control.route import Keyframe, Route
from vbnav.control.stages.obstacles import ObstacleStage
from vbnav.control.stages.repeat import RepeatStage
from vbnav.control.stages.teach import TeachStage
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.geometry import CameraMount, Pose2
from vbnav.vision.stereo import StereoRig
from vbnav.vision.vbc import levelled_bearings

CAM = PinholeCamera(320, 240, 200.0, 200.0, 159.5, 119.5)
MOUNT = CameraMount(0.25, 0.1)


def _texture(mean: float, seed: int = 0) -> np.ndarray:
    img = np.random.default_rng(seed).normal(mean, 30.0, (240, 320))
    return np.clip(img, 0, 255).astype(np.uint8)


def _one_keyframe_route(n: int = 12) -> Route:
    rng = np.random.default_rng(1)
    px = np.column_stack((rng.uniform(40, 280, n), rng.uniform(40, 200, n))).astype(np.float32)
    alpha, beta = levelled_bearings(CAM.rays(px), MOUNT)
    kf = Keyframe(0, _texture(100.0), px, alpha, beta, rng.integers(0, 256, (n, 32), dtype=np.uint8),
                  np.full(n, np.nan), np.full(n, np.inf), np.arange(n, dtype=np.int64), Pose2(), 0.0)
    return Route(None, "test", "now", CAM, MOUNT, True, [kf])


# ------------------------------------------------------------------------------------------- repeat
@pytest.mark.parametrize("features,sigmas", [(500, 2.0), (120, 3.5)])
def test_reacquisition_uses_its_feature_count_and_inlier_threshold(monkeypatch, features, sigmas):
    seen = {}

    def detect(image, n):
        seen["n"] = n
        return np.zeros((10, 2), np.float32), np.zeros((10, 32), np.uint8)

    def inliers(a, b, threshold):
        seen["threshold"] = threshold
        return np.zeros(len(a), bool)

    monkeypatch.setattr(repeat_stage, "detect_and_describe", detect)
    monkeypatch.setattr(repeat_stage, "match_descriptors", lambda q, t: np.column_stack((np.arange(10),) * 2))
    monkeypatch.setattr(repeat_stage, "geometric_inliers", inliers)
    stage = RepeatStage(_one_keyframe_route(), VBCConfig(reacquire_features=features,
                                                          reacquire_inlier_sigmas=sigmas))
    stage._reacquire(_texture(100.0))
    assert seen["n"] == features
    assert seen["threshold"] == pytest.approx(sigmas * stage.sigma)


@pytest.mark.parametrize("tolerance,rescaled", [(0.05, False), (0.02, True)])
def test_guided_association_matches_exposure_beyond_its_tolerance(monkeypatch, tolerance, rescaled):
    import cv2
    calls = []
    real = cv2.convertScaleAbs
    monkeypatch.setattr(cv2, "convertScaleAbs", lambda img, alpha: calls.append(alpha) or real(img, alpha=alpha))
    stage = RepeatStage(_one_keyframe_route(), VBCConfig(guided_exposure_tolerance=tolerance))
    image = _texture(104.0)                          # 4 % brighter than the keyframe image
    stage.tracker.track_points(image, np.zeros((0, 2)), np.zeros(0, np.int64))
    stage._guided(image, Pose2())
    assert bool(calls) == rescaled


# -------------------------------------------------------------------------------------------- teach
class _Heights:
    """Inverse heights 1 with relative standard deviations 0.1, 0.2, 0.4; fitted bearings all valid."""

    def estimate(self, ids):
        return None, np.ones(3), np.array([0.1, 0.2, 0.4]) ** 2

    def bearings_at(self, ids, odom, baseline):
        return np.ones(3), np.ones(3), np.ones(3, bool)


@pytest.mark.parametrize("rel_std,replaced", [(0.3, [True, True, False]), (0.5, [True, True, True])])
def test_keyframe_bearings_are_denoised_only_for_well_determined_ranges(rel_std, replaced):
    stage = TeachStage(CAM, MOUNT, VBCConfig(denoise_max_rel_std=rel_std))
    stage.heights = _Heights()
    stage._pending = {"track_ids": np.arange(3), "odom": Pose2(), "alpha": np.zeros(3), "beta": np.zeros(3),
                      "w": np.full(3, np.nan), "var": np.full(3, np.inf)}
    stage._refresh_pending_heights()
    assert list(stage._pending["alpha"] == 1.0) == replaced


# -------------------------------------------------------------------------------------------- vslam
class _Slam:
    """What the monocular scale correction touches of the front end."""

    def __init__(self, position):
        self.pose_wc = np.eye(4)
        self.pose_wc[:3, 3] = position
        self.references = [self]
        self.scales = []

    def move_reference(self, p):
        self.pose_wc[:3, 3] = p

    def rescale(self, s):
        self.scales.append(s)


@pytest.mark.parametrize("settings,ratio", [({}, 1.4), ({"odometry_scale_max_ratio": 1.2}, 1.2),
                                            ({"odometry_scale_min_ratio": 0.9}, 0.9)])
def test_monocular_scale_correction_is_clipped_by_its_ratio_settings(settings, ratio):
    cfg = VslamNavConfig.model_validate({"metric_scale": "odometry", "odometry_scale_gain": 1.0, **settings})
    stage = vslam_stage.VslamStage(CAM, MOUNT, None, cfg)
    base = vslam_stage.robot_to_camera_matrix(Pose2(), MOUNT)[:3, 3]
    long = ratio > 1.0                              # the wheels measured twice (or half) the VSLAM's travel
    stage.slam = _Slam(base + np.array([0.0, 0.0, 0.5 if long else 2.0]))
    stage._scale_base = (base, base)
    stage._correct_scale(Pose2(0.0, 1.0, 0.0))
    assert stage.slam.scales == [pytest.approx(ratio)]


def test_relocalisation_matches_with_its_hamming_limit(monkeypatch):
    seen = {}

    def matches(pred, desc_a, corners, desc_c, radius, max_distance):
        seen["max_distance"] = max_distance
        return np.zeros(0, int), np.zeros(0, int)

    monkeypatch.setattr(vslam_stage, "guided_matches", matches)
    cfg = VslamNavConfig.model_validate({"relocalise_max_hamming": 40, "relocalise_min_inliers": 6})
    stage = vslam_stage.VslamStage(CAM, MOUNT, 0.12, cfg)
    rng = np.random.default_rng(2)
    pw = np.column_stack((rng.uniform(-1, 1, 30), rng.uniform(-1.0, 0.0, 30), rng.uniform(2, 4, 30)))
    anchor = vslam_stage.Anchor(0, np.eye(4), Pose2(), pw, rng.integers(0, 256, (30, 32), dtype=np.uint8))
    assert stage._pose_against(anchor, _texture(100.0), np.eye(4)) is None
    assert seen["max_distance"] == 40


# ---------------------------------------------------------------------------------------- obstacles
def test_disparity_search_reaches_the_near_margin():
    rig = StereoRig(PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5), 0.075)
    mount = CameraMount(0.25, 0.1, 0.0, math.radians(10.0))
    wide = ObstacleStage(rig, mount, ObstaclesConfig()).sgbm.num_disparities
    narrow = ObstacleStage(rig, mount, ObstaclesConfig(sgbm_near_margin=1.0)).sgbm.num_disparities
    closer = ObstacleStage(rig, mount, ObstaclesConfig(sgbm_near_margin=0.3)).sgbm.num_disparities
    assert narrow <= wide < closer
