"""The ``vslam:`` section: the VSLAM on the robot and the ``goto`` controller."""
from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator
from vbnav.control.config.base import Strict, written
from vbnav.vision.vslam import VslamConfig


class GotoConfig(Strict):
    """``vslam.goto``: the go-to controller's gains and tolerances."""

    cruise_speed: float = Field(0.3, gt=0, description="top speed, m/s, at most robot.max_linear_speed (the "
                                "default is cut to it; a value written above it is refused)")
    k_rho: float = Field(0.6, gt=0, description="1/s, speed per metre to the goal")
    k_alpha: float = Field(1.8, gt=0, description="1/s, turn rate per rad of bearing to the goal")
    k_beta: float = Field(-0.5, lt=0, description="1/s, turn rate per rad of final-heading error; goto --map "
                          "drives its planned legs straight and turns to the heading on the spot at the goal, "
                          "without it")
    position_tolerance_m: float = Field(0.01, gt=0, description="goal reached within this distance (estimate)")
    heading_tolerance_deg: float = Field(0.7, gt=0, description="final heading within this (estimate)")
    approach_radius_m: float = Field(0.25, gt=0, description="inside it the heading term (beta) fades out; "
                                     "goto --map drives its planned legs without it")
    final_turn_speed: float = Field(0.4, gt=0, description="rad/s at most for the final turn on the spot, at "
                                    "most robot.max_angular_speed (the default is cut to it; a value written "
                                    "above it is refused)")
    settle_s: float = Field(0.3, ge=0, description="stopped this long within tolerance before finishing")
    fix_gain: float = Field(0.5, gt=0, le=1, description="share of a new VSLAM pose's correction applied at once")
    max_estimate_age_s: float = Field(0.5, gt=0, description="older VSLAM poses are not used by the controller")
    blind_distance_m: float = Field(0.3, ge=0, description="distance driven on odometry alone before stopping")
    init_creep_speed: float = Field(0.1, ge=0, description="m/s straight ahead while a monocular VSLAM waits for "
                                                           "the parallax to initialise (at most blind_distance_m), "
                                                           "at most robot.max_linear_speed (the default is cut "
                                                           "to it; a value written above it is refused)")
    min_drive_speed: float = Field(0.04, gt=0, description="m/s: floor of the drive speed k_rho * distance, so "
                                   "the last centimetres do not take forever (0.6/s reaches it at 6.7 cm)")
    redrive_factor: float = Field(2.0, ge=1, description="turning or settling, the robot drives again when "
                                  "farther than this times position_tolerance_m from the goal: hysteresis, so "
                                  "estimate jitter at the tolerance does not flip between drive and turn")
    final_turn_gain: float = Field(1.5, gt=0, description="1/s: final turn rate per rad of heading error, up to "
                                   "final_turn_speed (with 0.4 rad/s: proportional within 15 deg of the goal "
                                   "heading)")
    final_turn_min_speed: float = Field(0.05, gt=0, description="rad/s: floor of the final turn rate, so the last "
                                        "degree does not take forever (1.5/s reaches it at 1.9 deg)")



#: Front-end settings read only for landmarks a single camera triangulates from its own motion (Vslam
#: _add_from_motion, _refine_landmarks, _confidence): a stereo VSLAM (metric_scale stereo) creates none.
MONOCULAR_LANDMARK_KEYS = ("max_candidates", "min_parallax_px", "refine_landmarks", "weight_by_uncertainty",
                           "min_landmark_weight")


class VslamNavConfig(VslamConfig, Strict):
    """The ``vslam:`` section: the front end's settings (vision's ``VslamConfig``, which stays free of
    control/) plus the robot-side ones, as strict as every other section."""

    relocalise_radius_m: float = Field(1.0, ge=0, description="try an older anchor when the robot is this close "
                                                              "to where it was set (0: never)")
    relocalise_heading_deg: float = Field(35.0, gt=0, description="... and heading within this of it")
    relocalise_min_travel_m: float = Field(3.0, ge=0, description="only anchors set at least this far back "
                                                                    "along the robot's path (a loop closed)")
    relocalise_every: int = Field(1, ge=1, description="frames between relocalisation attempts")
    relocalise_min_inliers: int = Field(20, ge=6, description="landmarks that must agree with an anchor")
    relocalise_search_px: float = Field(20.0, gt=0, description="guided matching: search radius around the "
                                                               "landmark's predicted pixel")
    relocalise_max_correction_m: float = Field(0.5, gt=0, description="larger corrections are rejected as "
                                                                      "wrong matches")
    anchor_min_landmarks: int = Field(60, ge=6, description="reference frames with fewer are not kept as anchors")
    restart_after_lost: int = Field(3, ge=1, description="frames lost in a row before the front end restarts "
                                                         "from the current stereo pair at the odometry pose")
    max_planar_residual_m: float = Field(0.15, gt=0, description="camera height off its mount height by more "
                                                                 "than this: the pose is not trusted")
    metric_scale: Literal["stereo", "odometry"] = Field(
        "stereo", description="stereo: from the calibrated pair (or the device's disparity); odometry: a single "
                              "camera, initialised from two views scaled by the distance the wheels measured")
    odometry_init_baseline_m: float = Field(0.2, gt=0, description="metric_scale odometry: camera travel between "
                                                                  "the two initialisation views")
    odometry_init_max_frames: int = Field(100, ge=2, description="metric_scale odometry: frames to wait for that "
                                                                 "travel before starting over from a new first view")
    odometry_scale_gain: float = Field(0.5, ge=0, le=1, description="metric_scale odometry: at each hand-off, the "
                                       "share (in log scale) of the wheels' correction of the scale applied; 0: "
                                       "scale from the initialisation only")
    odometry_scale_min_travel_m: float = Field(0.3, gt=0, description="metric_scale odometry: camera travel the "
                                               "wheels and the VSLAM are compared over")
    goto: GotoConfig = Field(default_factory=GotoConfig, description="the goto controller (vbnav goto)")
    odometry_scale_min_ratio: float = Field(0.7, gt=0, le=1, description="metric_scale odometry: the ratio of the "
                                            "wheels' travel to the VSLAM's is clipped to at least this before a "
                                            "rescale, so one slipping or stalled comparison cannot wreck the map")
    odometry_scale_max_ratio: float = Field(1.4, ge=1, description="metric_scale odometry: ... and to at most "
                                            "this (a monocular scale drifts by a few % between hand-offs)")
    relocalise_max_hamming: int = Field(64, ge=0, le=256, description="relocalisation: a guided ORB match "
                                        "differs in at most this many of the 256 descriptor bits (a quarter, "
                                        "as for re-acquisition matches)")

    @model_validator(mode="after")
    def _bundle_adjustment_only_with_monocular_landmarks(self):
        # the window moves landmarks placed by the camera's own motion; a stereo VSLAM measures every one
        if self.ba_window > 0 and self.metric_scale == "stereo":
            raise ValueError(f"ba_window {self.ba_window}: the bundle adjustment moves landmarks placed by the "
                             f"camera's own motion; with metric_scale stereo the pair measures every landmark, so "
                             f"it would change nothing (ba_window 0, or metric_scale odometry for one camera)")
        return self

    @model_validator(mode="after")
    def _settings_that_apply(self):
        # written where they do not apply, these were accepted and never read
        given = [k for k in self.model_fields_set if written(self, k)]
        unused = [(k, "a single camera's scale (metric_scale odometry)") for k in sorted(given)
                  if k.startswith("odometry_") and self.metric_scale == "stereo"]
        if "stereo_max_depth_baselines" in given and self.metric_scale == "odometry":
            unused.append(("stereo_max_depth_baselines", "a stereo pair's landmarks (metric_scale stereo)"))
        # a single camera's bundle adjustment switched off (ba_window 0) keeps them, as a section switched off
        # does (docs/configuration.md); a stereo VSLAM has none to switch on
        unused += [(k, "a single camera's bundle adjustment (metric_scale odometry, ba_window > 0)")
                   for k in ("ba_history", "ba_outlier_sigmas") if k in given and self.metric_scale == "stereo"]
        # vision/vslam.py: candidates wait for parallax and become landmarks with an N-view refinement (refine set)
        # in _add_from_motion only; a stereo pair places every landmark from its own disparity (_add_from_stereo,
        # _add_from_depth), so no landmark is refined and every weight in the pose is 1 (_confidence)
        unused += [(k, "a single camera's landmarks placed by its own motion (metric_scale odometry)")
                   for k in MONOCULAR_LANDMARK_KEYS if k in given and self.metric_scale == "stereo"]
        if written(self.goto, "init_creep_speed") and self.metric_scale == "stereo":
            unused.append(("goto.init_creep_speed", "the drive while a single camera initialises (metric_scale "
                                                    "odometry)"))
        if unused:
            k, what = unused[0]
            raise ValueError(f"{k}: it sets {what}, which this configuration does not run (metric_scale "
                             f"{self.metric_scale}, ba_window {self.ba_window}): remove it, or configure what it "
                             f"applies to")
        return self
