"""The teach stage of teach-and-repeat by Vision-Based Control (chapter section 11.2.2.1).

``TeachStage`` (vision thread, while the robot is driven along the route): tracks
features, estimates each landmark's inverse height from odometry, and emits
``Keyframe`` records chosen by travelled distance, rotation and feature overlap.
A keyframe is emitted when the *next* one is started (or at ``finish()``), so its
landmarks' heights already pool the motion after it. The runtime drains
``pop_keyframes()`` into a ``RouteWriter``.

A frame that loses most tracks at once after a healthy one (motion blur, a flash, a
corrupt frame) is set aside (``_suspect``): no keyframe starts on it, and the tracker
goes back to the frame before, so the next frame is tracked from there. A keyframe
started on a blurred frame had tracks that died at the next sharp frame, before their
heights were known, and a repeat localised against it metres off. When the next frame
loses them too, the scene did change, and that frame is taken as usual (a keyframe
one frame later than without the check).
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np
from vbnav.control.config.vbc import VBCConfig
from vbnav.control.route import Keyframe, is_step
from vbnav.control.runtime.interfaces import Estimate, StageOverlay, VisionStage
from vbnav.control.stages.frame_input import odometry_problem, stage_image
from vbnav.control.stages.vbc_fix import bearing_sigma
from vbnav.drivers.camera import Frame
from vbnav.vision.features import FeatureTracker, describe
from vbnav.vision.geometry import CameraMount, Pose2
from vbnav.vision.vbc import InverseHeightEstimator, levelled_bearings


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
        self.heights = InverseHeightEstimator(mount, bearing_sigma(camera, self.cfg))
        self._pending: Optional[dict] = None
        self._ready: list[Keyframe] = []
        self._count = 0
        self._last_kf: Optional[Keyframe] = None   # the last keyframe emitted
        self._distance = 0.0
        self._last_odom: Optional[Pose2] = None
        self._last_frame: Optional[tuple] = None
        self._prev_ids: Optional[np.ndarray] = None     # tracks of the last frame taken
        self._prev_suspect = False                      # the last frame was set aside
        self.suspect_frames = 0
        self.end_note: Optional[str] = None             # why finish() took no keyframe at the last frame

    @property
    def n_keyframes(self) -> int:
        return self._count

    def overlay(self, estimate: Optional[Estimate]) -> StageOverlay:
        """The features tracked in this frame."""
        return StageOverlay(tracked=self.tracker.tracks.pts)

    def process(self, frame: Frame, odom: Pose2) -> Estimate:
        image, why = stage_image(frame.image, self.camera)
        why = why or odometry_problem(odom)
        if why:
            # Another size or dtype, or no odometry to place it: not ok, the tracks wait for the next
            # usable frame.
            return Estimate(frame.stamp_ns, self.kind, False, None,
                            {"tracks": len(self.tracker.tracks), "keyframes": self._count,
                             "distance": self._distance, "reason": f"teach: {why}"})
        before = self.tracker.snapshot()
        t = self.tracker.track(image)
        est = self.update(t.ids, t.pts, odom, frame.stamp_ns, image=image)
        if est.info.get("suspect"):
            # Track the next frame from the last good one: if this was a blurred frame, most tracks
            # (and their height fits) go on; if they are lost again, the scene changed.
            self.tracker.restore(before)
        return est

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
        if self._suspect(ids):
            # Not observed either: the heights estimator would forget every track missing here.
            self._prev_suspect = True
            self.suspect_frames += 1
            info = {"tracks": len(ids), "keyframes": self._count, "distance": self._distance, "suspect": True}
            return Estimate(stamp_ns, self.kind, True, None, info)
        self._prev_ids, self._prev_suspect = ids, False
        alpha, beta = levelled_bearings(self.camera.rays(pixels), self.mount) if len(ids) else (np.zeros(0),) * 2
        self.heights.observe(ids, alpha, beta, odom)
        self._refresh_pending_heights()
        emitted = None
        # with its distance: a last frame set aside (``_suspect``) after it must not lengthen the route's end
        self._last_frame = (ids, pixels, alpha, beta, odom, stamp_ns, image, descriptors, self._distance)
        if self._keyframe_due(ids, odom) and len(ids) >= self.cfg.min_keyframe_landmarks:
            emitted = self._finalise_pending()
            self._pending = self._candidate(ids, pixels, alpha, beta, odom, stamp_ns, image, descriptors,
                                            self._distance)
            self._last_frame = None
            # Its tracks already have heights: a keyframe taken at the last frame must not be left without.
            self._refresh_pending_heights()
        info = {"tracks": len(ids), "keyframes": self._count, "distance": self._distance}
        return Estimate(stamp_ns, self.kind, True, emitted, info)

    def finish(self) -> Optional[Keyframe]:
        """End of teaching: emit the pending keyframe and one at the last frame, where the route ends
        (when that frame keeps ``min_keyframe_landmarks`` tracks, as every keyframe; else ``end_note``
        says why the route ends at the keyframe before).

        Returns the final keyframe (all are queued for ``pop_keyframes``).
        """
        last = self._finalise_pending()
        tracks = len(self._last_frame[0]) if self._last_frame is not None else 0
        if self._last_frame is not None and tracks < self.cfg.min_keyframe_landmarks:
            # As every keyframe: a repeat could not localise on so few landmarks at the route's end.
            self._last_frame = None
            self.end_note = (f"no keyframe at the last frame: it kept {tracks} tracks, below "
                             f"vbc.min_keyframe_landmarks {self.cfg.min_keyframe_landmarks}")
            if self._last_kf is not None:
                self.end_note += (f"; the route ends at the keyframe before, "
                                  f"{self._distance - self._last_kf.distance:.2f} m short of where the teach stopped")
        if self._last_frame is not None:
            self._pending = self._candidate(*self._last_frame)
            self._last_frame = None
            if self._last_kf is not None and not is_step(self._last_kf.distance, self._last_kf.odom.theta,
                                                        self._pending["distance"], self._pending["odom"].theta):
                # A robot that has not moved since that keyframe: the same place again is no step along
                # the route (the route refuses it, and would be unloadable with it).
                self._pending = None
                return self._last_kf
            self._refresh_pending_heights()
            last = self._finalise_pending()
        return last

    def pop_keyframes(self) -> list[Keyframe]:
        """Keyframes emitted since the last call, in order (for the RouteWriter)."""
        out, self._ready = self._ready, []
        return out

    def _suspect(self, ids: np.ndarray) -> bool:
        """This frame kept fewer than ``keyframe_min_overlap`` of the last frame's tracks, and that
        frame was taken with at least ``min_keyframe_landmarks`` tracks.

        That share is what the overlap trigger lets a keyframe lose over its whole span, where
        tracks leave the view gradually (1-3 % a frame on the rendered routes); one frame that loses
        it alone is an image event (blur, a flash, a corrupt frame) until the next frame confirms
        it. Only one frame in a row is set aside (the one after it is always taken), so the
        distance and rotation triggers are late by one frame at most.
        """
        prev = self._prev_ids
        if prev is None or self._prev_suspect or len(prev) < self.cfg.min_keyframe_landmarks:
            return False
        return float(np.isin(prev, ids).mean()) < self.cfg.keyframe_min_overlap

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

    def _candidate(self, ids, pixels, alpha, beta, odom, stamp_ns, image, descriptors, distance: float) -> dict:
        if image is not None and descriptors is None:
            desc, idx = describe(image, pixels)
        else:
            idx = np.arange(len(ids))
            desc = (np.asarray(descriptors, np.uint8).reshape(len(ids), -1) if descriptors is not None
                    else np.zeros((len(ids), 32), np.uint8))
        n = len(idx)
        return {"track_ids": ids[idx], "pixels": pixels[idx].astype(np.float32), "alpha": alpha[idx],
                "beta": beta[idx], "descriptors": desc, "odom": odom, "distance": distance,
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
        good = valid & known & (var < (self.cfg.denoise_max_rel_std * w) ** 2)
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
        self._last_kf = kf
        return kf
