"""The ``vbc:`` section: teach-and-repeat by Vision-Based Control (tracking, keyframes, repeat)."""
from __future__ import annotations

from pydantic import Field, model_validator
from vbnav.control.config.base import Strict, written

#: What reads the tilt measurement (control/stages/repeat.py _fix, _observe_tilt), unread with tilt_sigma_deg 0.
TILT_KEYS = ("tilt_smoothing", "tilt_threshold_pitch_deg", "tilt_threshold_roll_deg", "max_tilt_deg")


class VBCConfig(Strict):
    """The ``vbc:`` section of a robot configuration."""

    # tracking
    max_features: int = Field(200, ge=10, description="tracks kept alive while teaching")
    min_distance_px: float = Field(12.0, gt=0, description="minimum spacing of detected corners, px")
    fb_threshold_px: float = Field(1.0, gt=0, description="forward-backward KLT rejection threshold, px")
    klt_window_px: int = Field(11, ge=5, le=41, description="KLT window side, px; 11 halves the cost at 15 Hz")
    klt_levels: int = Field(3, ge=0, le=6, description="KLT pyramid levels")
    bearing_sigma_px: float = Field(1.0, gt=0, description="bearing noise, in pixels at the focal length")
    # keyframes
    keyframe_distance_m: float = Field(0.4, gt=0, description="a new keyframe after driving this far")
    keyframe_rotation_deg: float = Field(12.0, gt=0, description="... or after turning this much")
    keyframe_min_overlap: float = Field(0.6, ge=0, le=1, description="new keyframe when fewer of the last "
                                        "keyframe's landmarks are still tracked")
    keyframe_min_spacing_m: float = Field(0.05, ge=0, description="no overlap-triggered keyframe closer than this")
    min_keyframe_landmarks: int = Field(20, ge=4, description="no keyframe from a frame with fewer tracks")
    denoise_baseline_m: float = Field(0.5, ge=0, description="a keyframe stores the bearings its tracks' fit "
                                      "predicts only for tracks first seen within this distance (odometry "
                                      "heading drifts ~1 deg/m), else the observed ones")
    # repeat
    min_landmarks: int = Field(12, ge=4, description="fewer agreeing landmarks: the fix is not trusted")
    min_known_landmarks: int = Field(12, ge=2, description="fewer agreeing landmarks with a known height (finite "
                                     "inverse height, its inverse-range variance below that of an unknown one): "
                                     "the fix is not trusted. Only these fix the translation (one without a "
                                     "height is taken as far away and informs the heading), so the count "
                                     "min_landmarks asks of a fix is asked of them too; a keyframe taught from "
                                     "a blurred frame has almost none")
    slow_landmarks: int = Field(30, ge=4, description="fewer agreeing landmarks: drive slower")
    reacquire_below: int = Field(40, ge=0, description="re-match descriptors when fewer keyframe landmarks are tracked")
    reacquire_every: int = Field(3, ge=1, description="frames between re-acquisition attempts while short, and "
                                                       "between guided matching passes (guided_fraction)")
    guided_fraction: float = Field(0.6, ge=0, le=1, description="pull in keyframe landmarks by predicted KLT "
                                   "when fewer than this share are tracked")
    guided_radius_px: float = Field(25.0, gt=0, description="max distance of a guided match from its prediction")
    fix_gate_m: float = Field(0.15, gt=0, description="a fix farther than this (plus fix_gate_fraction of the "
                              "distance driven since the last trusted fix) from where odometry carries the "
                              "pose of the frame before is not trusted, m (RepeatStage._accept): 5x the "
                              "largest such jump of a trusted fix measured on the simulated repeats, 3.2 cm")
    fix_gate_deg: float = Field(3.0, gt=0, description="... or turned more than this (plus fix_gate_fraction of "
                                "the turn since the last trusted fix) from it, deg: 12x the largest measured "
                                "(0.24 deg, kitti06 real-image repeat)")
    fix_gate_fraction: float = Field(0.25, ge=0, description="share of the distance and turn on odometry since "
                                     "the last trusted fix added to the gates: 2x the largest measured (13 %: "
                                     "kitti06, 1.2 m a frame), and above wheel odometry's error (scale and "
                                     "heading a few per cent)")
    tilt_sigma_deg: float = Field(2.0, ge=0, description="prior standard deviation of the camera's tilt "
                                  "(pitch, roll) on its mount since the route was taught, deg: the prior of "
                                  "the tilt repeat measures once a frame (vision/vbc.py, estimate_pose; docs/teach_repeat.md). "
                                  "1 deg of pitch or roll moves bearings by up to 7 px at the image corner, "
                                  "which a planar fix took for up to 13 cm of lateral offset; 1 deg of "
                                  "pitch or 2 of roll stopped the repeat 1.7-2.1 m short. 0: not measured "
                                  "(tilt_smoothing, the tilt thresholds and max_tilt_deg then refused)")
    tilt_smoothing: float = Field(0.1, gt=0, le=1, description="share of each fix's tilt measurement taken "
                                  "into the smoothed tilt (an exponential mean over about 10 fixes, 0.7 s at "
                                  "15 Hz): a knock is followed within a second")
    tilt_threshold_pitch_deg: float = Field(0.4, gt=0, description="the smoothed tilt is applied to the fixes "
                                            "once its pitch exceeds this, deg (and until both fall under half "
                                            "their thresholds): 2x the largest smoothed pitch measured on the "
                                            "untilted simulated repeats (0.19 deg, 5 seeds x 2 repeats)")
    tilt_threshold_roll_deg: float = Field(0.75, gt=0, description="... or its roll exceeds this, deg: roll "
                                           "and lateral offset move bearings alike, and the untilted repeats' "
                                           "smoothed roll reached 0.57-0.66 deg where boxes had been moved. "
                                           "Below the thresholds nothing is applied: solving the tilt freely "
                                           "with every fix cost up to half more lateral error on a camera "
                                           "that did not move (RepeatStage._observe_tilt)")
    max_tilt_deg: float = Field(5.0, gt=0, description="a fix whose camera tilt since teaching is larger is "
                                "not trusted, and the reason names the camera mount, deg: beyond a few "
                                "degrees the mount itself has moved and needs fixing")
    pass_margin_m: float = Field(0.0, description="keyframe k is passed when the robot is this far behind it (z)")
    cruise_speed: float = Field(0.25, gt=0, description="repeat speed, m/s, at most robot.max_linear_speed (the "
                                "default is cut to it; a value written above it is refused)")
    lookahead_m: float = Field(0.25, gt=0, description="pure-pursuit lookahead along the taught path")
    fix_gain: float = Field(0.5, gt=0, le=1, description="share of a new fix's correction applied at once")
    blind_distance_m: float = Field(0.3, ge=0, description="distance driven on odometry alone (no fix, or only "
                                                            "failed ones) before stopping, m")
    blind_speed_factor: float = Field(0.4, gt=0, le=1, description="speed factor while driving on odometry "
                                                                  "alone")
    goal_tolerance_m: float = Field(0.03, gt=0, description="finished within this of the last keyframe")
    max_estimate_age_s: float = Field(0.5, gt=0, description="older fixes are not used by the controller")
    turn_in_place_deg: float = Field(60.0, gt=0, description="larger heading errors turn on the spot")
    turn_in_place_rate: float = Field(0.6, gt=0, le=1, description="turn on the spot at this share of "
                                      "robot.max_angular_speed: brisk, with headroom below the limit")
    approach_gain: float = Field(1.5, gt=0, description="1/s: on the last segment the speed is at most this "
                                 "times the distance left, so the robot slows into the end (from 0.25 m/s "
                                 "cruise, over the last 0.17 m)")
    approach_min_speed: float = Field(0.05, gt=0, description="m/s: floor of that approach speed, so the last "
                                      "centimetres do not take forever (1.5/s reaches it at 3.3 cm, about "
                                      "goal_tolerance_m)")
    min_landmarks_speed_factor: float = Field(0.3, gt=0, le=1, description="speed factor with min_landmarks "
                                              "agreeing, rising linearly to 1 at slow_landmarks: a weak fix "
                                              "slows the robot instead of stopping it")
    denoise_max_rel_std: float = Field(0.3, gt=0, description="a keyframe stores a track's fitted bearings only "
                                       "when its inverse height's standard deviation is below this share of "
                                       "it (its range known to about 30 %)")
    guided_exposure_tolerance: float = Field(0.05, ge=0, description="guided association rescales the keyframe "
                                             "image to this image's mean brightness when they differ by more "
                                             "than this share (KLT matches intensities)")
    reacquire_features: int = Field(500, ge=8, description="ORB corners detected for re-acquisition: 2.5 times "
                                    "the tracks kept while teaching (max_features), so most have a candidate")
    reacquire_inlier_sigmas: float = Field(2.0, gt=0, description="a re-acquired match must fit the epipolar "
                                           "geometry of the others within this many bearing_sigma_px")

    @model_validator(mode="after")
    def _slowing_between_min_and_slow_landmarks(self):
        if self.slow_landmarks < self.min_landmarks:
            raise ValueError(f"slow_landmarks {self.slow_landmarks} is below min_landmarks {self.min_landmarks}: the "
                             f"repeat would never slow for a weak fix (min_landmarks_speed_factor never applied); "
                             f"set slow_landmarks >= min_landmarks")
        return self

    @model_validator(mode="after")
    def _tilt_settings_only_with_the_tilt_measured(self):
        # tilt_sigma_deg 0: RepeatStage never solves the tilt, so nothing is smoothed, compared with its
        # thresholds or with max_tilt_deg
        unused = [k for k in TILT_KEYS if written(self, k)]
        if self.tilt_sigma_deg == 0 and unused:
            raise ValueError(f"{' and '.join(unused)}: {'act' if len(unused) > 1 else 'acts'} on the camera's tilt "
                             f"that the repeat measures, and tilt_sigma_deg 0 switches that measurement off (remove "
                             f"{' and '.join(unused)}, or set tilt_sigma_deg > 0 to measure the tilt)")
        return self
