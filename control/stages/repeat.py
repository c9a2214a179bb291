"""The repeat stage of teach-and-repeat by Vision-Based Control (chapter section 11.2.2.1).

``RepeatStage`` (vision thread, while repeating): localises each frame against the
keyframe ahead (KLT tracks labelled with the taught track ids; ORB re-acquisition
when too few remain, e.g. after an occlusion or a jump; guided association, i.e.
KLT from the keyframe image started at the pixels the current fix predicts, after
each keyframe switch), computes the VBC pose relative to that keyframe and
advances when the robot passes it. Returns ``Estimate(kind="vbc", value=VBCFix)``.
A fix is trusted only where odometry since the frame before can explain it (``_accept``);
a keyframe that gives no fix is skipped when the next one gives one there.

Frames: a fix's pose is the robot relative to keyframe k. The path the
controller follows is the polyline of the keyframes' taught odometry poses;
the robot's pose on it is ``kf[k].odom * pose``, so only the *local* taught
geometry around keyframe k matters, never the accumulated odometry drift.
"""
from __future__ import annotations

import math
from dataclasses import replace
from typing import Optional

import cv2
import numpy as np
from vbnav.control.config.vbc import VBCConfig
from vbnav.control.route import Route
from vbnav.control.runtime.interfaces import Estimate, StageOverlay, VisionStage
from vbnav.control.stages.frame_input import odometry_problem, stage_image
from vbnav.control.stages.vbc_fix import VBCFix, bearing_sigma
from vbnav.drivers.camera import Frame
from vbnav.vision.camera_model import azimuth_elevation, rays_from_angles
from vbnav.vision.features import (
    FeatureTracker,
    detect_and_describe,
    geometric_inliers,
    match_descriptors,
    to_grey,
)
from vbnav.vision.geometry import CameraMount, Pose2
from vbnav.vision.vbc import (
    estimate_pose,
    inverse_range,
    levelled_bearings,
    predict_bearings,
    tilt_rotation,
)


def _pitch_roll_deg(tilt) -> tuple[float, float]:
    """The tilt of ``estimate_pose`` (rotations about the robot's x and z axes that take the current rays
    back) as the camera's change of mounting in CameraMount's terms: pitch positive looking further
    down, roll positive turned clockwise seen from behind; deg."""
    return -math.degrees(float(tilt[0])), math.degrees(float(tilt[1]))


# -------------------------------------------------------------------------------------------- repeat
class RepeatStage(VisionStage):
    """Localises each frame against the keyframe ahead and advances along the route."""

    kind = "vbc"

    def __init__(self, route: Route, cfg: VBCConfig | None = None, camera=None, mount: CameraMount | None = None):
        if route.repeat_refusal():
            raise ValueError(f"{route.path}: {route.repeat_refusal()}")
        self.route = route
        self.kfs = route.keyframes
        self.camera = camera or route.camera
        self.mount = mount or route.mount
        self.cfg = cfg or VBCConfig()
        self.sigma = bearing_sigma(self.camera, self.cfg)
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
        self._trusted_odom: Optional[Pose2] = None   # odometry at the last trusted fix
        self._frame_start: Optional[tuple] = None        # the state before this frame (``_state``)
        self._last_ok = True
        self._confirmed = False                  # a fix has passed the gate against an earlier one
        self._view: Optional[tuple] = None       # (ids, pixels) of the last localise (``_new_view``)
        self._fresh_view = True                  # this frame's tracks differ from the last's
        # The camera's tilt (pitch, roll) on its mount since teaching (``_observe_tilt``): measured with
        # each fix, smoothed, and applied to the rays once it passes vbc.tilt_threshold_pitch_deg or _roll_deg.
        s0 = math.radians(self.cfg.tilt_sigma_deg)
        self._tilt_info = np.eye(2) / (s0 * s0) if s0 > 0 else None    # None: tilt not measured
        self._tilt_mean: Optional[np.ndarray] = None   # smoothed measurement, rad
        self._tilt_seen: Optional[np.ndarray] = None   # this frame's measurement
        self.tilt = np.zeros(2)                        # applied, rad
        self._tilt_R = np.eye(3)                       # its rotation (fixes, guided matching's predictions)
        self.stats = {"reacquired": 0, "guided": 0, "switches": 0, "skipped": 0, "gated": 0,
                      "largest_jump_m": 0.0, "largest_tilt_deg": 0.0}

    def overlay(self, estimate: Optional[Estimate]) -> StageOverlay:
        """The tracked features, the matched keyframe's features tracked now (at their keyframe
        pixels) and the route being followed."""
        tracks = self.tracker.tracks
        kf = self.kfs[min(self.index, len(self.kfs) - 1)]
        seen = np.isin(kf.track_ids, tracks.ids)
        return StageOverlay(tracked=tracks.pts, matched=np.asarray(kf.pixels, float)[seen],
                            route=(self.route.path.name or "route", [k.odom for k in self.kfs]))

    # -- image path
    def process(self, frame: Frame, odom: Pose2) -> Estimate:
        image, why = stage_image(frame.image, self.camera)
        why = why or odometry_problem(odom)
        if why:
            return self._unusable(frame, odom, f"repeat: {why}")
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
            if not self._last_ok and self.index + 1 < len(self.kfs):
                # No fix from this keyframe: its landmarks may be unfindable (a keyframe taught from a
                # blurred frame); the next one's let localise skip it.
                self._reacquire(image, self.index + 1)
        t = self.tracker.tracks
        index = self.index
        # A frame may be fixed again after more matches (``_relocalise``): every fix of it is gated
        # against the prediction from the frame before, not against a weaker fix of the same frame.
        self._frame_start = self._state()
        est = self.localise(t.ids, t.pts, odom, frame.stamp_ns)
        if est.ok and self.index != index:
            est = self._after_switch(image, est, odom, frame.stamp_ns)
        # With a trusted fix, pull in the keyframe's landmarks not tracked yet: whenever fewer
        # than guided_fraction of them are tracked.
        kf = self.kfs[self.index]
        tracked = int(np.isin(self.tracker.tracks.ids, kf.track_ids).sum())
        if est.ok and tracked < self.cfg.guided_fraction * len(kf) and self._since_guided >= self.cfg.reacquire_every:
            self._guided(image, est.value.pose)
        self._prune()
        self._last_ok = est.ok
        self._frame_start = None
        return est

    def _unusable(self, frame: Frame, odom: Pose2, why: str) -> Estimate:
        """A frame the stage cannot use (another size or dtype, odometry that is not finite): not ok, no
        landmarks agree, at the pose the last fix carried by odometry predicts (the last fix's pose itself
        when odometry is not finite); tracks and keyframe stay those of the last good frame."""
        if self._pose is None:
            pose = Pose2()
        elif odometry_problem(odom):
            pose = self._pose
        else:
            pose = self._pose.compose(self._odom.between(odom))
        fix = VBCFix(self.index, pose, odom, 0, {}, self.finished)
        return Estimate(frame.stamp_ns, self.kind, False, fix, {"keyframe": self.index, "n_agree": 0,
                                                                 "tracked": 0, "reason": why})

    def _after_switch(self, image: np.ndarray, est: Estimate, odom: Pose2, stamp_ns: int) -> Estimate:
        """This frame's fix against the keyframe just switched to, from that keyframe's own landmarks.

        The first fix after a switch rests on the landmarks the two keyframes share: few, and mostly
        the long-lived far ones, which fix heading but hardly the lateral offset (KITTI 06, a jump
        over two keyframes at the start: 34 shared landmarks). The new keyframe's landmarks are
        pulled in by guided KLT from that fix; when fewer than ``reacquire_below`` of them were
        tracked, also by descriptors first (no prediction involved), and the frame is fixed again
        after each, so the weak shared-landmark fix is not the frame's answer. With enough shared
        tracks (close keyframes) the fix stands and the new landmarks count from the next frame.
        """
        kf = self.kfs[self.index]
        short = np.isin(self.tracker.tracks.ids, kf.track_ids).sum() < self.cfg.reacquire_below
        if short and self._reacquire(image):
            est = self._relocalise(est, odom, stamp_ns)
        if self._guided(image, est.value.pose) and short:
            est = self._relocalise(est, odom, stamp_ns)
        return est

    def _relocalise(self, est: Estimate, odom: Pose2, stamp_ns: int) -> Estimate:
        """Localise the current frame again after adding matches, starting from its fix ``est``;
        ``est`` if that fails (the state then holds ``est``'s pose again: localise fell back to it)."""
        t = self.tracker.tracks
        again = self.localise(t.ids, t.pts, odom, stamp_ns)
        return again if again.ok else est

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
        # levelled -> camera frame, through the camera's tilt since teaching (R^T n, row vectors)
        rays = rays_from_angles(a, b) @ self._tilt_R @ self.mount.rotation()
        px, front = self.camera.project(rays)
        inside = front & self.camera.in_image(px, margin=10)
        if inside.sum() < 4:
            return 0
        missing, px = missing[inside], px[inside].astype(np.float32)
        kimg = to_grey(kf.image)
        m_k, m_c = float(kimg.mean()), float(image.mean())
        if m_k > 1.0 and abs(m_c / m_k - 1.0) > self.cfg.guided_exposure_tolerance:
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

    def _reacquire(self, image: np.ndarray, k: Optional[int] = None) -> int:
        """Match ORB descriptors of fresh corners against keyframe ``k`` (the current one); seed tracks
        for the matches."""
        self._since_reacquire = 0
        kf = self.kfs[self.index if k is None else k]
        if len(kf) < 8:
            return 0
        pts, desc = detect_and_describe(image, self.cfg.reacquire_features)
        pairs = match_descriptors(desc, kf.descriptors)
        if len(pairs) < 8:
            return 0
        cur = pts[pairs[:, 0]]
        lm = pairs[:, 1]
        inl = geometric_inliers(self.camera.rays(kf.pixels[lm]), self.camera.rays(cur),
                                threshold=self.cfg.reacquire_inlier_sigmas * self.sigma)
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
        start = self._frame_start or self._state()
        self._fresh_view = self._new_view(ids, pixels)
        res, n_agree = self._fix(self.index, ids, pixels, predicted)
        ok, why = self._accept(res, self.index, odom, start)
        first = self._pose is None          # no fix yet: the robot is where the route starts, at keyframe 0
        if not ok and (first or self._trusted_odom is not None) and self.index + 1 < len(self.kfs):
            # Skip a keyframe that gives no fix when the next one does where odometry expects it (or, before
            # any fix, where it was taught after the first: a route whose first keyframe was taught from a
            # blurred frame never started, the robot waiting for a first match where none could come).
            step = self.kfs[self.index].odom.between(self.kfs[self.index + 1].odom)
            ahead = step.inverse().compose(Pose2() if first else predicted)
            res2, n2 = self._fix(self.index + 1, ids, pixels, ahead)
            if self._accept(res2, self.index + 1, odom, start)[0]:
                self.index += 1
                self.stats["skipped"] += 1
                self._since_reacquire = 10 ** 9
                res, n_agree, ok, why, predicted = res2, n2, True, "", ahead
        # Until one fix has been confirmed by the gate, the reference is a single fix no prediction
        # checked (the first): a camera knocked on that frame made it wrong, and every right fix after
        # it was refused for good (the robot stood 3.4 m from the end). While unconfirmed, a fix the
        # gate refuses replaces the reference instead (not ok, the controller is not given it); the
        # next fix that agrees with it confirms it.
        replace = not ok and not self._confirmed and start[0] is not None and self._trusted(res)
        if replace:
            why += "; no fix confirmed yet: this one replaces the first as the reference"
        pose = res.pose if ok or replace else predicted
        if pose is not None:
            # Passing keyframe k (its z reached): continue against k+1 in k+1's frame. Not on a fix that
            # only replaced an unconfirmed reference: a wrong one must not carry the index past keyframes.
            while not replace and self.index < len(self.kfs) - 1 and pose.z >= -self.cfg.pass_margin_m:
                step = self.kfs[self.index].odom.between(self.kfs[self.index + 1].odom)
                self.index += 1
                self.stats["switches"] += 1
                self._since_reacquire = 10 ** 9
                pose = step.inverse().compose(pose)
                res2, n2 = self._fix(self.index, ids, pixels, pose)
                ok2, why2 = self._accept(res2, self.index, odom, start)
                if ok2:
                    res, n_agree, pose, ok, why = res2, n2, res2.pose, True, ""
                else:
                    ok, why = False, why2
                    n_agree = n2
            if self.index == len(self.kfs) - 1 and pose.z >= -self.cfg.goal_tolerance_m:
                self.finished = True
            self._pose, self._odom = pose, odom
            if ok or replace:
                self._trusted_odom = odom
        self._observe_tilt()
        quality = res.quality.as_dict() if res is not None else {}
        fix = VBCFix(self.index, pose if pose is not None else Pose2(), odom, n_agree, quality, self.finished)
        info = {"keyframe": self.index, "n_agree": n_agree, "tracked": len(ids),
                "camera_tilt_deg": [round(v, 3) for v in _pitch_roll_deg(self.tilt)]}   # applied
        if why:
            info["reason"] = why
        return Estimate(stamp_ns, self.kind, bool(ok), fix, info)

    def _new_view(self, ids: np.ndarray, pixels: np.ndarray) -> bool:
        """Whether these tracks are not those of the last localise: some landmark seen in both moved at all.
        KLT on an image identical to the last gives every track its pixel again to the bit, where a
        camera's read noise moves them; a frame delivered twice (a driver re-queuing its buffer while
        the robot stands, which the frozen-camera check lets through) is no second view."""
        before, self._view = self._view, (ids, pixels)
        if before is None:
            return True
        _, i0, i1 = np.intersect1d(before[0], ids, return_indices=True)
        return len(i0) == 0 or not np.array_equal(before[1][i0], pixels[i1])

    def _state(self) -> tuple:
        """(pose, its keyframe, odometry at it, odometry at the last trusted fix)."""
        return self._pose, self.index, self._odom, self._trusted_odom

    def _accept(self, res, k: int, odom: Pose2, start: tuple) -> tuple[bool, str]:
        """Whether to trust fix ``res`` (``_trusted``) against keyframe ``k``, and why not: odometry
        carries the pose before this frame (``start``: ``_state()`` then) to ``predicted`` (in ``k``'s
        frame).

        A fix is compared with that prediction (an innovation gate): it may differ by what the fix's
        own noise and the odometry since the last trusted fix can explain, ``fix_gate_m`` plus
        ``fix_gate_fraction`` of the distance driven since (``fix_gate_deg`` plus that share of the
        turn). A fix outside the gate is not trusted, however many landmarks agree: a keyframe with
        few findable landmarks can converge far away with all of them called inliers (the robust
        scale grows with the residuals), the same wrong pose frame after frame, and the keyframe
        switches that followed such a jump left the robot 21 m off on a keyframe it never reached.
        Only the first fix has no prediction. Until a fix passes the gate (``_confirmed``), one that
        fails it replaces the reference (``localise``): a first fix from a knocked frame is dropped
        by the next two that agree. Once confirmed, fixes outside the gate are refused and the
        controller stops after ``blind_distance_m``, saying why: a stop, where taking fixes that
        disagree with odometry could drive the robot anywhere.
        """
        if not self._trusted(res):
            return False, (res.info.get("reason", "") if res is not None else "")
        pose, at, pose_odom, trusted_odom = start
        if pose is None or trusted_odom is None:
            return True, ""
        step = self.kfs[at].odom.between(self.kfs[k].odom)
        predicted = step.inverse().compose(pose.compose(pose_odom.between(odom)))
        gap = predicted.between(res.pose)
        jump, turn = math.hypot(gap.x, gap.z), abs(gap.theta)
        moved = trusted_odom.between(odom)
        share = self.cfg.fix_gate_fraction
        gate_m = self.cfg.fix_gate_m + share * math.hypot(moved.x, moved.z)
        gate_rad = math.radians(self.cfg.fix_gate_deg) + share * abs(moved.theta)
        if jump <= gate_m and turn <= gate_rad:
            self.stats["largest_jump_m"] = max(self.stats["largest_jump_m"], jump)
            # The same view again (a frame delivered twice, or fixed again) agrees with itself: no confirmation.
            self._confirmed = self._confirmed or self._fresh_view
            return True, ""
        self.stats["gated"] += 1
        return False, (f"repeat: fix {jump:.2f} m / {math.degrees(turn):.1f} deg from where odometry puts "
                       f"the robot (gate {gate_m:.2f} m / {math.degrees(gate_rad):.1f} deg: vbc.fix_gate_m, "
                       f"fix_gate_fraction, fix_gate_deg)")

    def _observe_tilt(self) -> None:
        """Smooth this frame's tilt measurement (``vbc.tilt_smoothing``) and decide what the fixes apply.

        The camera's pitch and roll on its mount change rarely (a knock, a load, tyre pressure) and then
        stay, so the tilt is applied only once its smoothed pitch or roll exceeds its threshold
        (``tilt_threshold_pitch_deg``, ``tilt_threshold_roll_deg``), and dropped below half of both. Solved freely with every fix, it also took up what the taught
        landmark heights get wrong: on the untilted simulated repeats each fix's roll wandered by up to
        0.4 deg and the lateral error grew by up to half. A change of the applied tilt moves every fix at
        once, so the gate's reference is then taken afresh (``_confirmed``)."""
        seen, self._tilt_seen = self._tilt_seen, None
        if seen is None:
            return
        a = self.cfg.tilt_smoothing
        self._tilt_mean = seen.copy() if self._tilt_mean is None else self._tilt_mean + a * (seen - self._tilt_mean)
        big = math.degrees(float(np.max(np.abs(self._tilt_mean))))
        self.stats["largest_tilt_deg"] = max(self.stats["largest_tilt_deg"], big)
        # how far over its threshold the larger axis is (1 = at it)
        over = float(np.max(np.degrees(np.abs(self._tilt_mean))
                            / [self.cfg.tilt_threshold_pitch_deg, self.cfg.tilt_threshold_roll_deg]))
        applied = bool(self.tilt.any())
        if over > 1.0 or (applied and over > 0.5):
            tilt = self._tilt_mean.copy()
        else:
            tilt = np.zeros(2)
        if bool(tilt.any()) != applied:
            self._confirmed = False
        self.tilt = tilt
        self._tilt_R = tilt_rotation(tilt)

    def _trusted(self, res) -> bool:
        """A fix is ok when it converged with ``min_landmarks`` agreeing landmarks, of which at least
        ``min_known_landmarks`` have a known height: landmarks without one fix the heading but not
        the translation, and a fix that rests on them (a keyframe taught from a blurred frame, whose
        tracks died before their heights were known) can be metres off while all of them agree.
        A fix that is not ok leaves the robot on odometry, under the controller's blind-distance rule."""
        return (res is not None and res.ok and res.quality.n_inliers >= self.cfg.min_landmarks
                and res.quality.n_known >= self.cfg.min_known_landmarks)

    def _fix(self, k: int, ids, pixels, initial: Optional[Pose2]):
        kf = self.kfs[k]
        _, i_kf, i_cur = np.intersect1d(kf.track_ids, ids, assume_unique=False, return_indices=True)
        if len(i_kf) < 4:
            return None, 0
        a, b = levelled_bearings(self.camera.rays(pixels[i_cur]), self.mount)
        kw = dict(forward=self.mount.forward, lateral=self.mount.lateral, sigma=self.sigma, initial=initial)
        taught = (kf.alpha[i_kf], kf.beta[i_kf], kf.inv_height[i_kf])
        # The tilt, solved with the pose (a loose prior): once a frame, by the first fix that gives a
        # trusted one (the current keyframe's, as a rule). The camera's tilt is the same against every
        # keyframe, so the look-ahead and switch fixes of the frame reuse it instead of solving again.
        if self._tilt_info is not None and self._tilt_seen is None:
            mean = np.zeros(2) if self._tilt_mean is None else self._tilt_mean
            m = estimate_pose(*taught, a, b, kf.inv_height_var[i_kf], tilt_prior=(mean, self._tilt_info), **kw)
            if self._trusted(m):
                self._tilt_seen = np.asarray(m.info["tilt"], dtype=np.float64)
        measured = self._tilt_seen
        if self.tilt.any():
            a, b = azimuth_elevation(rays_from_angles(a, b) @ self._tilt_R.T)
        res = estimate_pose(*taught, a, b, kf.inv_height_var[i_kf], **kw)
        if res.ok and measured is not None:
            tilt_deg = math.degrees(float(np.max(np.abs(measured))))
            if tilt_deg > self.cfg.max_tilt_deg:
                pitch, roll = _pitch_roll_deg(measured)
                res = replace(res, ok=False, info={**res.info, "reason": (
                    f"repeat: the camera is tilted {pitch:+.1f} deg (pitch) / {roll:+.1f} deg (roll) from its "
                    f"mounting when the route was taught (limit vbc.max_tilt_deg {self.cfg.max_tilt_deg:g}): "
                    f"check the camera mount")})
        return res, res.quality.n_inliers
