"""Teach and repeat by Vision-Based Control (chapter section 11.2.2.1): pure logic, no I/O, no threads.

- ``TeachStage`` (vision thread, while the robot is driven along the route): tracks
  features, estimates each landmark's inverse height from odometry, and emits
  ``Keyframe`` records chosen by travelled distance, rotation and feature overlap.
  A keyframe is emitted when the *next* one is started (or at ``finish()``), so its
  landmarks' heights already pool the motion after it. The runtime drains
  ``pop_keyframes()`` into a ``RouteWriter``.
- ``RepeatStage`` (vision thread, while repeating): localises each frame against the
  keyframe ahead (KLT tracks labelled with the taught track ids; ORB re-acquisition
  when too few remain, e.g. after an occlusion or a jump; guided association, i.e.
  KLT from the keyframe image started at the pixels the current fix predicts, after
  each keyframe switch), computes the VBC pose relative to that keyframe and
  advances when the robot passes it. Returns ``Estimate(kind="vbc", value=VBCFix)``.
- ``RepeatController`` (loop rate): dead-reckons from the latest fix with odometry,
  follows the taught keyframe path with pure pursuit (a nonholonomic base corrects
  lateral error through heading), slows and stops when too few landmarks agree,
  resumes when they do, and finishes at the last keyframe.

Frames: a fix's pose is the robot relative to keyframe k. The path the
controller follows is the polyline of the keyframes' taught odometry poses;
the robot's pose on it is ``kf[k].odom * pose``, so only the *local* taught
geometry around keyframe k matters, never the accumulated odometry drift.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from vbnav.control.controller import STOP, ControlContext, Controller, Estimate, Twist, VisionStage
from vbnav.control.route import Keyframe, Route
from vbnav.drivers.camera import Frame
from vbnav.vision.features import (FeatureTracker, describe, detect_and_describe, geometric_inliers,
                                   match_descriptors, to_grey)
from vbnav.vision.camera_model import rays_from_angles
from vbnav.vision.geometry import CameraMount, Pose2
from vbnav.vision.vbc import (InverseHeightEstimator, estimate_pose, inverse_range, levelled_bearings,
                              predict_bearings)


class VBCConfig(BaseModel):
    """The ``vbc:`` section of a robot configuration."""

    model_config = ConfigDict(extra="forbid")
    # tracking
    max_features: int = Field(200, ge=10, description="tracks kept alive while teaching")
    min_distance_px: float = Field(12.0, gt=0, description="minimum spacing of detected corners")
    fb_threshold_px: float = Field(1.0, gt=0, description="forward-backward KLT rejection threshold")
    klt_window_px: int = Field(11, ge=5, le=41, description="KLT window side; 11 halves the cost at 15 Hz")
    klt_levels: int = Field(3, ge=0, le=6, description="KLT pyramid levels")
    bearing_sigma_px: float = Field(1.0, gt=0, description="bearing noise, in pixels at the focal length")
    # keyframes
    keyframe_distance_m: float = Field(0.4, gt=0)
    keyframe_rotation_deg: float = Field(12.0, gt=0)
    keyframe_min_overlap: float = Field(0.6, ge=0, le=1, description="new keyframe when fewer of the last "
                                        "keyframe's landmarks are still tracked")
    keyframe_min_spacing_m: float = Field(0.05, ge=0, description="no overlap-triggered keyframe closer than this")
    min_keyframe_landmarks: int = Field(20, ge=4)
    denoise_baseline_m: float = Field(0.5, ge=0, description="a keyframe stores the bearings its tracks' fit "
                                      "predicts only for tracks first seen within this distance (odometry "
                                      "heading drifts ~1 deg/m), else the observed ones")
    # repeat
    min_landmarks: int = Field(12, ge=4, description="fewer agreeing landmarks: the fix is not trusted")
    slow_landmarks: int = Field(30, ge=4, description="fewer agreeing landmarks: drive slower")
    reacquire_below: int = Field(40, ge=0, description="re-match descriptors when fewer keyframe landmarks are tracked")
    reacquire_every: int = Field(3, ge=1, description="frames between re-acquisition attempts while short")
    guided_fraction: float = Field(0.6, ge=0, le=1, description="pull in keyframe landmarks by predicted KLT "
                                   "when fewer than this share are tracked")
    guided_radius_px: float = Field(25.0, gt=0, description="max distance of a guided match from its prediction")
    pass_margin_m: float = Field(0.0, description="keyframe k is passed when the robot is this far behind it (z)")
    cruise_speed: float = Field(0.25, gt=0, description="m/s")
    lookahead_m: float = Field(0.25, gt=0, description="pure-pursuit lookahead along the taught path")
    fix_gain: float = Field(0.5, gt=0, le=1, description="share of a new fix's correction applied at once")
    blind_distance_m: float = Field(0.3, ge=0, description="distance driven on odometry alone before stopping")
    blind_speed_factor: float = Field(0.4, gt=0, le=1)
    goal_tolerance_m: float = Field(0.03, gt=0)
    max_estimate_age_s: float = Field(0.5, gt=0)
    turn_in_place_deg: float = Field(60.0, gt=0, description="larger heading errors turn on the spot")


@dataclass
class VBCFix:
    """A repeat-stage result: the robot relative to keyframe ``keyframe`` at the frame's time."""

    keyframe: int
    pose: Pose2
    odom: Pose2
    n_agree: int
    quality: dict = field(default_factory=dict)
    finished: bool = False


def _sigma(camera, cfg: VBCConfig) -> float:
    return cfg.bearing_sigma_px / float(camera.fx)


# --------------------------------------------------------------------------------------------- teach
class TeachStage(VisionStage):
    """Tracks features and emits keyframes while the robot is driven along the route."""

    kind = "teach"

    def __init__(self, camera, mount: CameraMount, cfg: VBCConfig | None = None):
        self.camera = camera
        self.mount = mount
        self.cfg = cfg or VBCConfig()
        self.tracker = FeatureTracker(self.cfg.max_features, self.cfg.min_distance_px,
                                      win_size=self.cfg.klt_window_px, levels=self.cfg.klt_levels,
                                      fb_threshold=self.cfg.fb_threshold_px)
        self.heights = InverseHeightEstimator(mount, _sigma(camera, self.cfg))
        self._pending: Optional[dict] = None
        self._ready: list[Keyframe] = []
        self._count = 0
        self._distance = 0.0
        self._last_odom: Optional[Pose2] = None
        self._last_frame: Optional[tuple] = None

    @property
    def n_keyframes(self) -> int:
        return self._count

    def process(self, frame: Frame, odom: Pose2) -> Estimate:
        image = to_grey(frame.image)
        t = self.tracker.track(image)
        return self.update(t.ids, t.pts, odom, frame.stamp_ns, image=image)

    def update(self, ids, pixels, odom: Pose2, stamp_ns: int = 0, image: np.ndarray | None = None,
               descriptors: np.ndarray | None = None) -> Estimate:
        """Feature-level step (also used directly by tests with synthetic landmarks).

        descriptors: per-point descriptors when no image is given (else ORB on ``image``).
        """
        ids = np.asarray(ids, np.int64)
        pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
        if self._last_odom is not None:
            self._distance += math.hypot(odom.x - self._last_odom.x, odom.z - self._last_odom.z)
        self._last_odom = odom
        alpha, beta = levelled_bearings(self.camera.rays(pixels), self.mount) if len(ids) else (np.zeros(0),) * 2
        self.heights.observe(ids, alpha, beta, odom)
        self._refresh_pending_heights()
        emitted = None
        self._last_frame = (ids, pixels, alpha, beta, odom, stamp_ns, image, descriptors)
        if self._keyframe_due(ids, odom) and len(ids) >= self.cfg.min_keyframe_landmarks:
            emitted = self._finalise_pending()
            self._pending = self._candidate(ids, pixels, alpha, beta, odom, stamp_ns, image, descriptors)
            self._last_frame = None
            # Its tracks already have heights: a keyframe taken at the last frame must not be left without.
            self._refresh_pending_heights()
        info = {"tracks": len(ids), "keyframes": self._count, "distance": self._distance}
        return Estimate(stamp_ns, self.kind, True, emitted, info)

    def finish(self) -> Optional[Keyframe]:
        """End of teaching: emit the pending keyframe and one at the last frame, where the route ends.

        Returns the final keyframe (all are queued for ``pop_keyframes``).
        """
        last = self._finalise_pending()
        if self._last_frame is not None and len(self._last_frame[0]) >= 4:
            self._pending = self._candidate(*self._last_frame)
            self._last_frame = None
            self._refresh_pending_heights()
            last = self._finalise_pending()
        return last

    def pop_keyframes(self) -> list[Keyframe]:
        """Keyframes emitted since the last call, in order (for the RouteWriter)."""
        out, self._ready = self._ready, []
        return out

    def _keyframe_due(self, ids: np.ndarray, odom: Pose2) -> bool:
        p = self._pending
        if p is None:
            return True
        rel = p["odom"].between(odom)
        dist = self._distance - p["distance"]
        if dist >= self.cfg.keyframe_distance_m or abs(rel.theta) >= math.radians(self.cfg.keyframe_rotation_deg):
            return True
        overlap = np.isin(p["track_ids"], ids).mean() if len(p["track_ids"]) else 0.0
        return overlap < self.cfg.keyframe_min_overlap and dist >= self.cfg.keyframe_min_spacing_m

    def _candidate(self, ids, pixels, alpha, beta, odom, stamp_ns, image, descriptors) -> dict:
        if image is not None and descriptors is None:
            desc, idx = describe(image, pixels)
        else:
            idx = np.arange(len(ids))
            desc = (np.asarray(descriptors, np.uint8).reshape(len(ids), -1) if descriptors is not None
                    else np.zeros((len(ids), 32), np.uint8))
        n = len(idx)
        return {"track_ids": ids[idx], "pixels": pixels[idx].astype(np.float32), "alpha": alpha[idx],
                "beta": beta[idx], "descriptors": desc, "odom": odom, "distance": self._distance,
                "stamp_ns": int(stamp_ns), "image": image if image is not None else np.zeros((1, 1), np.uint8),
                "w": np.full(n, np.nan), "var": np.full(n, np.inf)}

    def _refresh_pending_heights(self) -> None:
        """Keep the latest height estimate of each pending landmark (tracks may die before emission)."""
        p = self._pending
        if p is None:
            return
        _, w, var = self.heights.estimate(p["track_ids"])
        known = np.isfinite(w) & np.isfinite(var)
        p["w"][known] = w[known]
        p["var"][known] = var[known]
        # The keyframe's own observation carries one frame's noise, and every later fix against
        # this keyframe would inherit it as a bias: store the bearings that the whole track
        # predicts at the keyframe pose instead, once its range is well determined.
        alpha, beta, valid = self.heights.bearings_at(p["track_ids"], p["odom"], self.cfg.denoise_baseline_m)
        good = valid & known & (var < (0.3 * w) ** 2)
        p["alpha"][good] = alpha[good]
        p["beta"][good] = beta[good]

    def _finalise_pending(self) -> Optional[Keyframe]:
        p = self._pending
        if p is None:
            return None
        self._pending = None
        kf = Keyframe(self._count, p["image"], p["pixels"], p["alpha"], p["beta"], p["descriptors"], p["w"],
                      p["var"], p["track_ids"], p["odom"], p["distance"], p["stamp_ns"])
        self._count += 1
        self._ready.append(kf)
        return kf


# -------------------------------------------------------------------------------------------- repeat
class RepeatStage(VisionStage):
    """Localises each frame against the keyframe ahead and advances along the route."""

    kind = "vbc"

    def __init__(self, route: Route, cfg: VBCConfig | None = None, camera=None, mount: CameraMount | None = None):
        if not route.keyframes:
            raise ValueError(f"{route.path}: route has no keyframes")
        self.route = route
        self.kfs = route.keyframes
        self.camera = camera or route.camera
        self.mount = mount or route.mount
        self.cfg = cfg or VBCConfig()
        self.sigma = _sigma(self.camera, self.cfg)
        # Only keyframe landmarks are tracked (no detection): their ids are the taught track ids.
        self.tracker = FeatureTracker(max_features=10_000, win_size=self.cfg.klt_window_px,
                                      levels=self.cfg.klt_levels, fb_threshold=self.cfg.fb_threshold_px,
                                      redetect_fraction=0.0)
        self.index = 0
        self.finished = False
        self._pose: Optional[Pose2] = None      # last pose relative to kf[index]
        self._odom: Optional[Pose2] = None      # odometry at that pose
        self._since_reacquire = 10 ** 9
        self._started = False
        self._since_guided = 10 ** 9
        self.stats = {"reacquired": 0, "guided": 0, "switches": 0}

    # -- image path
    def process(self, frame: Frame, odom: Pose2) -> Estimate:
        image = to_grey(frame.image)
        if self._started:
            self.tracker.track(image)
        else:
            self.tracker.track_points(image, np.zeros((0, 2)), np.zeros(0, np.int64))
            self._started = True
        self._since_reacquire += 1
        self._since_guided += 1
        kf = self.kfs[self.index]
        tracked = int(np.isin(self.tracker.tracks.ids, kf.track_ids).sum())
        if tracked < self.cfg.reacquire_below and self._since_reacquire >= self.cfg.reacquire_every:
            self._reacquire(image)
        t = self.tracker.tracks
        index = self.index
        est = self.localise(t.ids, t.pts, odom, frame.stamp_ns)
        # With a trusted fix, pull in the keyframe's landmarks not tracked yet: after a keyframe
        # switch, and whenever fewer than guided_fraction of them are tracked.
        kf = self.kfs[self.index]
        tracked = int(np.isin(self.tracker.tracks.ids, kf.track_ids).sum())
        if est.ok and (self.index != index or (tracked < self.cfg.guided_fraction * len(kf)
                                               and self._since_guided >= self.cfg.reacquire_every)):
            self._guided(image, est.value.pose)
        self._prune()
        return est

    def _guided(self, image: np.ndarray, pose: Pose2) -> int:
        """KLT from the keyframe image to this one, started where the fix predicts each landmark.

        Bearings are predicted with the exact model (inverse range from the landmark's height,
        0 = far when unknown), turned back into camera rays and pixels. The keyframe image is
        scaled to this image's mean brightness first (KLT matches intensities, lighting changes).
        """
        self._since_guided = 0
        kf = self.kfs[self.index]
        if kf.image is None or kf.image.size <= 1:
            return 0
        missing = np.flatnonzero(~np.isin(kf.track_ids, self.tracker.tracks.ids))
        if len(missing) < 4:
            return 0
        rho = np.nan_to_num(inverse_range(kf.beta[missing], kf.inv_height[missing]), nan=0.0)
        a, b = predict_bearings(kf.alpha[missing], kf.beta[missing], rho, pose, self.mount.forward, self.mount.lateral)
        rays = rays_from_angles(a, b) @ self.mount.rotation()     # levelled -> camera frame
        px, front = self.camera.project(rays)
        inside = front & self.camera.in_image(px, margin=10)
        if inside.sum() < 4:
            return 0
        missing, px = missing[inside], px[inside].astype(np.float32)
        kimg = to_grey(kf.image)
        m_k, m_c = float(kimg.mean()), float(image.mean())
        if m_k > 1.0 and abs(m_c / m_k - 1.0) > 0.05:
            kimg = cv2.convertScaleAbs(kimg, alpha=m_c / m_k)
        p0 = kf.pixels[missing].astype(np.float32).reshape(-1, 1, 2)
        win = (self.cfg.klt_window_px + 4,) * 2
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(kimg, image, p0, px.reshape(-1, 1, 2).copy(), winSize=win,
                                              maxLevel=self.cfg.klt_levels, flags=flags)
        back, st2, _ = cv2.calcOpticalFlowPyrLK(image, kimg, p1, p0.copy(), winSize=win,
                                                maxLevel=self.cfg.klt_levels, flags=flags)
        p1 = p1.reshape(-1, 2)
        good = ((st1.ravel() == 1) & (st2.ravel() == 1)
                & (np.linalg.norm(back.reshape(-1, 2) - p0.reshape(-1, 2), axis=1) < self.cfg.fb_threshold_px)
                & (np.linalg.norm(p1 - px, axis=1) < self.cfg.guided_radius_px)
                & self.camera.in_image(p1, margin=8))
        self.tracker.add_points(p1[good], kf.track_ids[missing[good]])
        self.stats["guided"] += int(good.sum())
        return int(good.sum())

    def _prune(self) -> None:
        """Drop tracks that belong to neither the current nor the next keyframe (bounded cost)."""
        keep_ids = self.kfs[self.index].track_ids
        if self.index + 1 < len(self.kfs):
            keep_ids = np.concatenate([keep_ids, self.kfs[self.index + 1].track_ids])
        keep = np.isin(self.tracker.tracks.ids, keep_ids)
        if not keep.all():
            self.tracker.tracks = self.tracker.tracks.subset(keep)

    def _reacquire(self, image: np.ndarray) -> int:
        """Match ORB descriptors of fresh corners against the keyframe; seed tracks for the matches."""
        self._since_reacquire = 0
        kf = self.kfs[self.index]
        if len(kf) < 8:
            return 0
        pts, desc = detect_and_describe(image, 500)
        pairs = match_descriptors(desc, kf.descriptors)
        if len(pairs) < 8:
            return 0
        cur = pts[pairs[:, 0]]
        lm = pairs[:, 1]
        inl = geometric_inliers(self.camera.rays(kf.pixels[lm]), self.camera.rays(cur),
                                threshold=2.0 * self.sigma)
        keep = inl & ~np.isin(kf.track_ids[lm], self.tracker.tracks.ids)
        self.tracker.add_points(cur[keep], kf.track_ids[lm[keep]])
        self.stats["reacquired"] += int(keep.sum())
        return int(keep.sum())

    # -- feature path (tests feed this directly)
    def localise(self, ids, pixels, odom: Pose2, stamp_ns: int = 0) -> Estimate:
        ids = np.asarray(ids, np.int64)
        pixels = np.asarray(pixels, np.float64).reshape(-1, 2)
        predicted = None
        if self._pose is not None:
            predicted = self._pose.compose(self._odom.between(odom))
        res, n_agree = self._fix(self.index, ids, pixels, predicted)
        ok = res is not None and res.ok and n_agree >= self.cfg.min_landmarks
        pose = res.pose if ok else predicted
        if pose is not None:
            # Passing keyframe k (its z reached): continue against k+1 in k+1's frame.
            while self.index < len(self.kfs) - 1 and pose.z >= -self.cfg.pass_margin_m:
                step = self.kfs[self.index].odom.between(self.kfs[self.index + 1].odom)
                self.index += 1
                self.stats["switches"] += 1
                self._since_reacquire = 10 ** 9
                pose = step.inverse().compose(pose)
                res2, n2 = self._fix(self.index, ids, pixels, pose)
                if res2 is not None and res2.ok and n2 >= self.cfg.min_landmarks:
                    res, n_agree, pose, ok = res2, n2, res2.pose, True
                else:
                    ok = False
                    n_agree = n2
            if self.index == len(self.kfs) - 1 and pose.z >= -self.cfg.goal_tolerance_m:
                self.finished = True
            self._pose, self._odom = pose, odom
        quality = res.quality.as_dict() if res is not None else {}
        fix = VBCFix(self.index, pose if pose is not None else Pose2(), odom, n_agree, quality, self.finished)
        return Estimate(stamp_ns, self.kind, bool(ok), fix, {"keyframe": self.index, "n_agree": n_agree,
                                                              "tracked": len(ids)})

    def _fix(self, k: int, ids, pixels, initial: Optional[Pose2]):
        kf = self.kfs[k]
        _, i_kf, i_cur = np.intersect1d(kf.track_ids, ids, assume_unique=False, return_indices=True)
        if len(i_kf) < 4:
            return None, 0
        a, b = levelled_bearings(self.camera.rays(pixels[i_cur]), self.mount)
        res = estimate_pose(kf.alpha[i_kf], kf.beta[i_kf], kf.inv_height[i_kf], a, b, kf.inv_height_var[i_kf],
                            forward=self.mount.forward, lateral=self.mount.lateral, sigma=self.sigma,
                            initial=initial)
        return res, res.quality.n_inliers


# ---------------------------------------------------------------------------------------- controller
class RepeatController(Controller):
    """Pure pursuit along the taught keyframe path, localised by VBC fixes and odometry in between."""

    name = "repeat"
    requires = ("vbc",)

    def __init__(self, route: Route, cfg: VBCConfig | None = None, max_linear_speed: float = 0.5,
                 max_angular_speed: float = 1.5):
        if not route.keyframes:
            raise ValueError(f"{route.path}: route has no keyframes")
        self.cfg = cfg or VBCConfig()
        self.kfs = route.keyframes
        self.path = np.array([[kf.odom.x, kf.odom.z] for kf in self.kfs])
        self.v_max = min(self.cfg.cruise_speed, max_linear_speed)
        self.w_max = max_angular_speed
        self._k = 0
        self._P: Optional[Pose2] = None          # robot pose in the taught-odometry frame
        self._P_odom: Optional[Pose2] = None     # odometry when _P was set
        self._last_stamp: Optional[int] = None
        self._n_agree = 0
        self._good_odom: Optional[Pose2] = None  # odometry at the last trusted fix
        self._blind = 0.0
        self._finished = False
        self._status: dict = {}

    @property
    def finished(self) -> bool:
        return self._finished

    def status(self) -> dict:
        return dict(self._status)

    def update(self, ctx: ControlContext) -> Twist:
        self._absorb(ctx.estimate("vbc", self.cfg.max_estimate_age_s))
        if self._P is None or self._finished:
            self._status = {"state": "finished" if self._finished else "waiting", "keyframe": self._k}
            return STOP
        P = self._P.compose(self._P_odom.between(ctx.odom))
        if self._good_odom is not None:
            self._blind = math.hypot(ctx.odom.x - self._good_odom.x, ctx.odom.z - self._good_odom.z)
        return self._pursue(P)

    def _absorb(self, est: Optional[Estimate]) -> None:
        if est is None or est.stamp_ns == self._last_stamp or not isinstance(est.value, VBCFix):
            return
        self._last_stamp = est.stamp_ns
        fix: VBCFix = est.value
        self._k = fix.keyframe
        self._n_agree = fix.n_agree if est.ok else 0
        if fix.finished:
            self._finished = True
        if not est.ok:
            return
        measured = self.kfs[fix.keyframe].odom.compose(fix.pose)
        self._good_odom = fix.odom
        if self._P is None:
            self._P, self._P_odom = measured, fix.odom
            return
        # Complementary filter: blend the dead-reckoned pose at the frame time toward the fix.
        pred = self._P.compose(self._P_odom.between(fix.odom))
        d = pred.between(measured)
        g = self.cfg.fix_gain
        self._P = pred.compose(Pose2(g * d.x, g * d.z, g * d.theta))
        self._P_odom = fix.odom

    def _pursue(self, P: Pose2) -> Twist:
        seg, s, lateral, remaining = self._project(P)
        target = self._point_ahead(seg, s, self.cfg.lookahead_m)
        rel = P.between(Pose2(target[0], target[1], 0.0))
        heading_err = math.atan2(rel.x, rel.z)
        v = self.v_max * self._confidence()
        if remaining < self.cfg.goal_tolerance_m and seg == len(self.path) - 2:
            self._finished = True
            self._status = {"state": "finished", "keyframe": self._k}
            return STOP
        v = min(v, max(0.05, 1.5 * remaining)) if v > 0 else 0.0
        if abs(heading_err) > math.radians(self.cfg.turn_in_place_deg) and v > 0:
            w = math.copysign(0.6 * self.w_max, heading_err)
            v = 0.0
        else:
            L2 = rel.x * rel.x + rel.z * rel.z
            kappa = 2.0 * rel.x / max(L2, 1e-6)
            w = v * kappa
            if abs(w) > self.w_max:                     # keep the curvature, lower the speed
                v *= self.w_max / abs(w)
                w = math.copysign(self.w_max, w)
        self._status = {"state": "driving" if v > 0 or w != 0 else "stopped", "keyframe": self._k,
                        "lateral_m": lateral, "heading_err_deg": math.degrees(heading_err),
                        "n_agree": self._n_agree, "blind_m": self._blind, "remaining_m": remaining}
        return Twist(v, w)

    def _confidence(self) -> float:
        """Speed factor from the number of agreeing landmarks and the distance driven blind."""
        c = self.cfg
        if self._n_agree >= c.slow_landmarks:
            return 1.0
        if self._n_agree >= c.min_landmarks:
            return 0.3 + 0.7 * (self._n_agree - c.min_landmarks) / max(c.slow_landmarks - c.min_landmarks, 1)
        return c.blind_speed_factor if self._blind < c.blind_distance_m else 0.0

    def _project(self, P: Pose2):
        """Closest segment near the current keyframe: (segment, arclength on it, signed lateral, remaining)."""
        n = len(self.path)
        if n == 1:
            d = float(np.hypot(*(self.path[0] - [P.x, P.z])))
            return 0, 0.0, 0.0, d
        lo, hi = max(self._k - 2, 0), min(self._k + 1, n - 2)
        best = None
        for i in range(lo, hi + 1):
            a, b = self.path[i], self.path[i + 1]
            ab = b - a
            L = float(np.hypot(*ab)) or 1e-9
            t = float(np.clip(np.dot([P.x - a[0], P.z - a[1]], ab) / (L * L), 0.0, 1.0))
            q = a + t * ab
            d = float(np.hypot(P.x - q[0], P.z - q[1]))
            if best is None or d < best[0] - 1e-9:
                # lateral sign: positive when the robot is right of the path direction (toward +x of it)
                side = (ab[1] * (P.x - a[0]) - ab[0] * (P.z - a[1])) / L
                best = (d, i, t * L, side)
        _, seg, s, side = best
        seg_len = np.hypot(*np.diff(self.path, axis=0).T)
        remaining = float(seg_len[seg] - s + seg_len[seg + 1:].sum())
        return seg, s, side, remaining

    def _point_ahead(self, seg: int, s: float, dist: float) -> np.ndarray:
        n = len(self.path)
        if n == 1:
            return self.path[0]
        while True:
            a, b = self.path[seg], self.path[seg + 1]
            L = float(np.hypot(*(b - a)))
            if s + dist <= L or seg == n - 2:
                t = min((s + dist) / max(L, 1e-9), 1.0)
                return a + t * (b - a)
            dist -= L - s
            s = 0.0
            seg += 1


def teach_repeat_config(section: dict | None, source: str = "<config>") -> VBCConfig:
    """Validate the free ``vbc:`` configuration section; errors name the file and key path."""
    from pydantic import ValidationError

    from vbnav.control.config import ConfigError, _format_errors
    try:
        return VBCConfig.model_validate(section or {})
    except ValidationError as exc:
        raise ConfigError(_format_errors(source, exc, prefix="vbc")) from None

