"""Monocular VSLAM front end of section 11.3: one reference set of landmarks, pose against it.

Landmarks live in the frame of the current *reference frame* (a camera pose).
Every image: track the landmarks' pixels (KLT), turn them into rays (11.9),
recover the motion reference -> current camera from those rays and the
landmarks' reference coordinates (11.15-11.17, robust), never by chaining
frame-to-frame motions (11.3.3.2). New landmarks are reconstructed by the
spherical-disparity equation (11.11), either from the calibrated stereo pair
(known (R, T) between the cameras: metric scale for the whole run), from a
depth image, or from the camera's own motion once the parallax is large enough,
then transformed back into the reference frame: the reference set grows in
every direction the camera looks. When too few of the reference frame's own
landmarks remain visible, the current frame becomes the new reference frame
(hand-off); the chain of reference frames is kept.

Pure computation: images and arrays in, poses out.
"""
from __future__ import annotations

import itertools
from collections import deque
from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from vbnav.vision.bundle_adjust import bundle_adjust
from vbnav.vision.camera_model import FisheyeCamera, PinholeCamera
from vbnav.vision.features import KltTracker, describe, match_descriptors, orb_matches
from vbnav.vision.geometry import absolute_orientation, similarity_moved
from vbnav.vision.motion import MotionEstimate, recover_motion_robust
from vbnav.vision.spherical import spherical_disparity


# ORB corners are tied to the landmarks they sit on in the last image within this distance: about the
# localisation error of an ORB keypoint found on pyramid level 1-2 (scale 1.2-1.44, +-1 px there).
ORB_TIE_PX = 3.0
# A KLT pose whose consensus is under a quarter of the tracks is doubted: true tracks of a rigid scene agree
# far more (40-95 % per frame on the real sequences in ../shared/data), tracks dragged by a jump beyond the
# pyramid agree by chance. The ORB fallbacks are tried; the KLT pose stands only if they fail.
# Counted over the landmarks seen again since they were triangulated: one triangulated in the last frame has
# not been checked in a third view, and under large motion most are off by more than the inlier bound there
# (kitti06 left-only, every third frame: 24 % within 1 px at their first re-observation, 85-88 % of the
# older ones at stride 1), which says nothing about the tracks (docs/vslam.md).
MIN_INLIER_FRACTION = 0.25
#: Frame-to-frame motion estimates kept in ``Vslam.stats`` (the latest; ~3 kB each with their arrays).
STATS_KEPT = 32
# Essential-matrix inliers needed from those matches: 5 determine it; 15 give a margin over outliers.
ORB_MIN_MATCHES = 15
# A monocular landmark born at the parallax gate (min_parallax_px, 10 px) with 1 px of noise has a 10 %
# depth error (one sigma); the kept ones have been refined over their tracks since (5 % at 20 px of
# parallax), so 10 % of its distance is one to two sigmas.
SIM3_MAX_RELATIVE_ERROR = 0.10


class VslamConfig(BaseModel):
    """Settings of the VSLAM front end (the ``vslam:`` section of a robot configuration)."""

    model_config = ConfigDict(extra="forbid")

    max_landmarks: int = Field(400, gt=10, description="landmarks tracked at most")
    min_landmarks: int = Field(250, gt=3, description="below this many tracked, new landmarks are added")
    max_candidates: int = Field(1000, ge=0, description="monocular: features waiting for enough parallax")
    min_parallax_px: float = Field(10.0, gt=0, description="gate of the spherical disparity (monocular), in pixels "
                                                          "at the focal length: a two-view depth's relative "
                                                          "error is the ray noise over the parallax, so 10 px "
                                                          "starts a landmark within 10 % for 1 px of noise")
    inlier_threshold_px: float = Field(1.0, gt=0, description="ray angle, in pixels at the focal length")
    handoff_fraction: float = Field(0.4, ge=0, le=1,
                                    description="hand-off when fewer of the reference frame's own landmarks "
                                                "than this fraction remain")
    handoff_min: int = Field(40, ge=3, description="hand-off when fewer of its own landmarks remain visible")
    min_inliers: int = Field(8, ge=3, description="fewer inliers than this: frame lost")
    stereo_max_depth_baselines: float = Field(80.0, gt=0,
                                              description="stereo landmarks farther than this many baselines "
                                                          "are not used (too little disparity)")
    min_depth: float = Field(0.0, ge=0, description="landmarks nearer than this (m) are not created")
    reacquire_every: int = Field(0, ge=0, description="frames between searches for lost reference landmarks "
                                                       "(0: never; lost landmarks are then forgotten)")
    reacquire_radius_px: float = Field(12.0, gt=0, description="re-found corner within this of the prediction")
    max_dormant: int = Field(5000, ge=0, description="lost landmarks kept for re-acquisition")
    anchor_tracks: bool = Field(False, description="refine every track by KLT from the image where its feature "
                                                   "was detected (removes the random walk of frame-to-frame KLT)")
    anchor_max_shift_px: float = Field(2.0, gt=0, description="anchored position accepted within this of the "
                                                              "frame-to-frame track")
    refine_landmarks: bool = Field(True, description="monocular landmarks: least-squares position over all "
                                                     "views (11.11 generalised to N views), updated every frame")
    weight_by_uncertainty: bool = Field(True, description="monocular landmarks weigh in the pose by the "
                                                          "confidence of their N-view position")
    min_landmark_weight: float = Field(0.01, ge=0, le=1,
                                       description="floor of that weight: with only poorly known landmarks "
                                                   "(forward motion) the pose must not rest on a handful")
    klt_window: int = Field(21, ge=5, description="KLT window side, px")
    klt_levels: int = Field(3, ge=0, description="KLT pyramid levels")
    min_distance_px: float = Field(12.0, gt=0, description="minimum spacing of detected corners, px")
    detect_cells: int = Field(0, ge=0, description="new corners spread over about this many square image "
                                                   "cells, each ranked on its own (0: the whole image at once)")
    ba_window: int = Field(0, ge=0, description="monocular landmarks: bundle adjustment of the last this many "
                                                "frames' poses and the landmarks they see (0: off; see "
                                                "docs/vslam.md for why it is off)")
    ba_history: int = Field(2, ge=2, description="frames before the adjusted ones whose views of the same "
                                                 "landmarks take part with their poses fixed (they hold the "
                                                 "position and scale of the window)")
    ba_outlier_sigmas: float = Field(3.03, gt=0, description="after the adjustment, monocular landmarks with an "
                                                             "observation farther than this many inlier "
                                                             "thresholds are dropped (3.03: 99 % of 2-D "
                                                             "Gaussian noise)")


@dataclass
class ReferenceFrame:
    """A reference frame of the chain: its world-from-camera pose and when it was created."""

    index: int  # frame counter at creation
    pose_wc: np.ndarray  # 4x4 world-from-reference-camera
    landmarks: int  # landmarks it owned at creation


@dataclass
class FrameResult:
    ok: bool
    pose_wc: np.ndarray  # 4x4 world-from-camera (last good pose if not ok)
    tracked: int
    inliers: int
    iterations: int
    residual_px: float
    handoff: bool = False
    added: int = 0
    reference: int = 0  # index of the reference frame the pose was computed against


@dataclass
class _Landmarks:
    P: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # in the reference frame
    px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # pixel in the last image
    own: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # created with the reference frame
    desc: np.ndarray = field(default_factory=lambda: np.zeros((0, 32), np.uint8))  # ORB at creation
    described: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    anchor: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # frame where the feature was detected
    apx: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # its pixel there
    # Monocular landmarks: normal equations of the N-view least squares, sum_k w_k Q_k (X - C_k) = 0 with
    # Q_k = I - m_k m_k^T (m_k the ray, C_k the camera centre of view k, both in the reference frame).
    A: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    b: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    refine: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    uid: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # identity across frames (observations)
    free: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # position from own motion: adjustable

    _ROWS = ("P", "px", "own", "desc", "described", "anchor", "apx", "A", "b", "refine", "uid", "free")

    def keep(self, m: np.ndarray) -> "_Landmarks":
        """Keep the rows in ``m``; return the others (for the dormant set)."""
        gone = _Landmarks(**{k: getattr(self, k)[~m] for k in self._ROWS})
        for k in self._ROWS:
            setattr(self, k, getattr(self, k)[m])
        return gone

    def transform(self, R: np.ndarray, T: np.ndarray) -> None:
        """Re-express in a new reference frame, X' = R X + T (normal equations included: A' = R A R^T,
        b' = R b + A' T keep A' X' = b' equivalent to A X = b)."""
        self.P = self.P @ R.T + T
        self.A = np.einsum("ij,njk,lk->nil", R, self.A, R)
        self.b = self.b @ R.T + np.einsum("nij,j->ni", self.A, T)

    def add(self, P: np.ndarray, px: np.ndarray, own: bool, image: np.ndarray | None = None,
            desc: np.ndarray | None = None, described: np.ndarray | None = None, anchor=None, apx=None,
            A=None, b=None, refine=None, uid=None, free=None) -> None:
        n = len(P)
        self.uid = np.concatenate((self.uid, _new_uids(n) if uid is None else uid))
        refine_rows = np.zeros(n, bool) if refine is None else np.broadcast_to(refine, n)
        self.free = np.concatenate((self.free, refine_rows if free is None else np.broadcast_to(free, n)))
        self.anchor = np.concatenate((self.anchor, np.broadcast_to(np.asarray(-1 if anchor is None else anchor), n)))
        self.apx = np.vstack((self.apx, px if apx is None else apx))
        self.A = np.concatenate((self.A, np.zeros((n, 3, 3)) if A is None else A))
        self.b = np.vstack((self.b, np.zeros((n, 3)) if b is None else b))
        self.refine = np.concatenate((self.refine, np.zeros(n, bool) if refine is None else refine))
        if desc is None:
            desc = np.zeros((n, 32), np.uint8)
            described = np.zeros(n, bool)
            if image is not None and n:
                d, idx = describe(image, px)
                desc[idx], described[idx] = d, True
        self.P = np.vstack((self.P, P))
        self.px = np.vstack((self.px, px))
        self.own = np.concatenate((self.own, np.full(n, own)))
        self.desc = np.vstack((self.desc, desc))
        self.described = np.concatenate((self.described, described))

    def extend(self, other: "_Landmarks", own: bool = False) -> None:
        self.add(other.P, other.px, own, desc=other.desc, described=other.described, anchor=other.anchor,
                 apx=other.apx, A=other.A, b=other.b, refine=other.refine, uid=other.uid, free=other.free)


@dataclass
class _Candidates:
    """Monocular: features waiting for parallax; first ray and pose (ref -> camera) at first sight."""

    px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    ray0: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    R0: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    T0: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    anchor: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    apx: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    uid: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # kept by the landmark it becomes

    def keep(self, m: np.ndarray) -> None:
        self.px, self.ray0, self.R0, self.T0 = self.px[m], self.ray0[m], self.R0[m], self.T0[m]
        self.anchor, self.apx, self.uid = self.anchor[m], self.apx[m], self.uid[m]


_UIDS = itertools.count()


def _new_uids(n: int) -> np.ndarray:
    return np.fromiter(itertools.islice(_UIDS, n), int, n)


@dataclass
class _View:
    """What one frame of the adjustment window saw: its pose and the rays of the features it tracked."""

    image_id: int
    pose_wc: np.ndarray
    uid: np.ndarray
    rays: np.ndarray


def _to_h_batch(R: np.ndarray, T: np.ndarray) -> np.ndarray:
    M = np.repeat(np.eye(4)[None], len(R), 0)
    M[:, :3, :3], M[:, :3, 3] = R, T
    return M


def _to_h(R: np.ndarray, T: np.ndarray) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, T
    return M


class Vslam:
    """The front end. ``initialise`` once with metric landmarks, then ``process`` every image."""

    def __init__(self, camera: PinholeCamera | FisheyeCamera, config: VslamConfig | None = None,
                 stereo_baseline: Optional[float] = None, seed: int = 0):
        self.camera = camera
        self.cfg = config or VslamConfig()
        self.baseline = stereo_baseline
        self.tracker = KltTracker(window=self.cfg.klt_window, levels=self.cfg.klt_levels,
                                  min_distance=self.cfg.min_distance_px)
        self.lm = _Landmarks()
        self.dormant = _Landmarks()  # reference landmarks whose tracks were lost
        self.reacquired = 0  # landmarks found again, in total
        self.descriptor_poses = 0  # frames posed by the ORB fallback
        self.cand = _Candidates()
        self.R = np.eye(3)  # reference -> current camera
        self.T = np.zeros(3)
        self.references: list[ReferenceFrame] = []
        self.prev: Optional[np.ndarray] = None
        self.frame = 0
        self.rng = np.random.default_rng(seed)  # RANSAC draws
        self.stats: deque[MotionEstimate] = deque(maxlen=STATS_KEPT)   # the latest frames' solves
        self._history: list[np.ndarray] = []  # last two good world-from-camera poses
        self._img_id = 0  # frame counter of the image being processed
        self._anchors: dict[int, np.ndarray] = {}  # images where live features were detected
        self._window: list[_View] = []  # the frames the bundle adjustment works on, oldest first
        self.adjusted: dict[int, np.ndarray] = {}  # image id -> world-from-camera after the last adjustment
        self.ba_runs = 0
        self._newborn = np.zeros(0, int)  # uids of the monocular landmarks triangulated in the last frame
        self.ba_dropped = 0  # landmarks dropped by the adjustment's outlier test, in total

    # ------------------------------------------------------------------ set-up
    @property
    def initialised(self) -> bool:
        return self.prev is not None

    @property
    def image_id(self) -> int:
        """Id of the last image given to ``initialise`` or ``process`` (the keys of ``adjusted``)."""
        return self._img_id

    @property
    def pose_wc(self) -> np.ndarray:
        return self.references[-1].pose_wc @ np.linalg.inv(_to_h(self.R, self.T))

    def initialise(self, image: np.ndarray, pixels: np.ndarray, points_cam: np.ndarray,
                   pose_wc: np.ndarray | None = None, right: np.ndarray | None = None,
                   depth: np.ndarray | None = None, estimated: bool = False) -> int:
        """Start with landmarks of known metric position in this camera's frame (from stereo, a depth
        image or a known reference structure); this camera becomes the first reference frame.
        ``estimated``: the positions come from this camera's own motion (a two-view start), so the
        bundle adjustment may move them."""
        self._img_id = self.frame
        self._anchors = {self._img_id: image}
        self.lm = _Landmarks()
        self.lm.add(np.asarray(points_cam, float).reshape(-1, 3), np.asarray(pixels, float).reshape(-1, 2), True,
                    image=image, anchor=self._img_id, free=estimated)
        self.dormant = _Landmarks()
        self.cand = _Candidates()  # a restart: candidates' first poses belong to the old reference
        self.R, self.T = np.eye(3), np.zeros(3)
        self.references = [ReferenceFrame(self.frame, np.eye(4) if pose_wc is None else np.asarray(pose_wc, float),
                                          len(self.lm.P))]
        self._history = [self.references[0].pose_wc]
        self.prev = image
        self._add_landmarks(image, right, depth, own=True)
        self.references[-1].landmarks = len(self.lm.P)
        self._window, self.adjusted = [], {}
        self._record_view()
        self.frame += 1
        return len(self.lm.P)

    def initialise_stereo(self, left: np.ndarray, right: np.ndarray, pose_wc: np.ndarray | None = None) -> int:
        if self.baseline is None:
            raise ValueError("stereo initialisation needs the stereo baseline")
        return self.initialise(left, np.zeros((0, 2)), np.zeros((0, 3)), pose_wc, right=right)

    def initialise_depth(self, image: np.ndarray, depth: np.ndarray, pose_wc: np.ndarray | None = None) -> int:
        return self.initialise(image, np.zeros((0, 2)), np.zeros((0, 3)), pose_wc, depth=depth)

    # ------------------------------------------------------------------ per frame
    def process(self, image: np.ndarray, right: np.ndarray | None = None, depth: np.ndarray | None = None
                ) -> FrameResult:
        if not self.initialised:
            raise RuntimeError("Vslam.process before initialise")
        cfg = self.cfg
        n_lm = len(self.lm.P)
        before = _Landmarks(**{k: getattr(self.lm, k) for k in _Landmarks._ROWS})  # for the ORB fallback
        pts = np.vstack((self.lm.px, self.cand.px))
        last_image = self.prev
        new_px, ok = self.tracker.track(self.prev, image, pts, guess=self._predicted_pixels())
        self.lm.px, self.cand.px = new_px[:n_lm], new_px[n_lm:]
        self.cand.keep(ok[n_lm:])
        self._make_dormant(self.lm.keep(ok[:n_lm]))
        tracked = len(self.lm.P)
        self.prev = image
        self.frame += 1
        self._img_id = self.frame - 1
        self._anchors[self._img_id] = image
        if cfg.anchor_tracks:
            self._refine_from_anchors(image)
        f = float(getattr(self.camera, "fx", 500.0))
        est = None
        if tracked >= max(cfg.min_inliers, 3):
            est = recover_motion_robust(self.lm.P, self.camera.rays(self.lm.px), prior=self._predicted_motion(),
                                        threshold=cfg.inlier_threshold_px / f, angular=True, rng=self.rng,
                                        weights=self._confidence(f) if cfg.weight_by_uncertainty else None,
                                        local_optimisation=True)
        agree = 0 if est is None else int((est.inliers & (est.depths > 0)).sum())
        checked = ~np.isin(self.lm.uid, self._newborn)  # seen again since they were triangulated
        self._newborn = np.zeros(0, int)
        agree_checked = 0 if est is None else int((est.inliers & (est.depths > 0) & checked).sum())
        if agree < cfg.min_inliers or agree_checked < MIN_INLIER_FRACTION * int(checked.sum()):
            # KLT kept too few, or mostly wrong ones (a jump, blur, an exposure change): match ORB
            # descriptors of the landmarks against fresh corners of this image, pose from those; then
            # oriented ORB between the last image and this one. A weak KLT pose stands only if both fail.
            fallback = self._descriptor_pose(image, before, f)
            if fallback is None:
                fallback = self._orb_tie_pose(last_image, image, before, f)
            if fallback is not None:
                est = fallback
            elif agree < cfg.min_inliers:
                return FrameResult(False, self.pose_wc, tracked, 0, 0, float("nan"),
                                   reference=len(self.references) - 1)
        self.stats.append(est)
        inl = est.inliers & (est.depths > 0)
        self.R, self.T = est.R, est.T
        self._history = [self._history[-1], self.pose_wc] if self._history else [self.pose_wc]
        self.lm.keep(inl)
        if cfg.refine_landmarks:
            self._refine_landmarks(self.camera.rays(self.lm.px))
        handoff = self._maybe_handoff()
        added = 0
        if cfg.reacquire_every and self.frame % cfg.reacquire_every == 0:
            self._reacquire(image)
        if len(self.lm.P) < cfg.min_landmarks or (self.baseline is None and depth is None):
            added = self._add_landmarks(image, right, depth, own=False)
        self._forget_anchors()
        self._record_view()
        self._adjust_window(f)
        return FrameResult(True, self.pose_wc, tracked, int(inl.sum()), est.iterations, est.residual * f,
                           handoff, added, len(self.references) - 1)

    def _descriptor_pose(self, image: np.ndarray, before: _Landmarks, f: float) -> Optional[MotionEstimate]:
        """Pose from ORB matches of the landmarks held before this frame's KLT (their descriptors from
        creation) to fresh corners; on success the matched landmarks become the tracked set."""
        d = before
        d.keep(d.described)  # keeps those rows in place (and returns the others)
        if len(d.P) < self.cfg.min_inliers:
            return None
        # The same corners (GFTT) and descriptors as the landmarks were given at creation (``describe``):
        # ORB's own FAST corners sit a pixel or two off and their descriptors then disagree.
        pts = self.tracker.detect(image, 2 * self.cfg.max_landmarks)
        desc, idx = describe(image, pts)
        pts = pts[idx]
        pairs = match_descriptors(d.desc, desc)
        if len(pairs) < self.cfg.min_inliers:
            return None
        li, ci = pairs[:, 0], pairs[:, 1]
        est = recover_motion_robust(d.P[li], self.camera.rays(pts[ci].astype(float)),
                                    prior=self._predicted_motion(), threshold=2 * self.cfg.inlier_threshold_px / f,
                                    angular=True, rng=self.rng, local_optimisation=True)
        if (est.inliers & (est.depths > 0)).sum() < self.cfg.min_inliers:
            return None
        order = np.argsort(li)
        self._adopt(d, li, pts[ci[order]].astype(float))
        est.inliers, est.depths = est.inliers[order], est.depths[order]
        return est

    def _adopt(self, d: _Landmarks, rows: np.ndarray, px: np.ndarray) -> None:
        """An ORB fallback's outcome: landmarks ``rows`` of ``d`` (in index order) become the tracked set at
        ``px``, anchored in this image (their old patches may be far from this view)."""
        m = np.zeros(len(d.P), bool)
        m[rows] = True
        d.keep(m)
        d.px = px
        d.anchor[:], d.apx = self._img_id, d.px.copy()
        self.lm = d
        self.descriptor_poses += 1

    def _orb_tie_pose(self, last_image: np.ndarray, image: np.ndarray, before: _Landmarks, f: float
                      ) -> Optional[MotionEstimate]:
        """Second fallback, for jumps that also defeat the landmarks' own upright descriptors (25 degrees
        and 0.4 m between hand-held frames). Oriented multi-scale ORB matched between the last image and
        this one gives the rotation and the direction of travel (essential matrix: many matches, no
        landmark needed). The length of the step comes from the landmarks that an ORB corner sits on in
        the last image (within ``ORB_TIE_PX``): each gives the length that puts it on its ray here; their
        median is taken, and those within the inlier bound become the tracked set."""
        d = before
        if len(d.P) < 3:
            return None
        pa, pb = orb_matches(last_image, image)
        if len(pa) < ORB_MIN_MATCHES:
            return None
        ra, rb = self.camera.rays(pa), self.camera.rays(pb)
        ua, ub = ra[:, :2] / ra[:, 2:], rb[:, :2] / rb[:, 2:]
        E, mask = cv2.findEssentialMat(ua, ub, np.eye(3), method=cv2.USAC_ACCURATE, prob=0.999,
                                       threshold=self.cfg.inlier_threshold_px / f)
        if E is None or E.shape != (3, 3):
            return None
        good, R_rel, t, mask = cv2.recoverPose(E, ua, ub, np.eye(3), mask=mask)
        if good < ORB_MIN_MATCHES:
            return None
        t = t.ravel()
        dist = np.linalg.norm(d.px[:, None, :] - pa[None, :, :], axis=2)  # landmarks x matches
        near = np.argmin(dist, axis=1)
        li = np.flatnonzero((dist[np.arange(len(d.P)), near] < ORB_TIE_PX) & (mask.ravel()[near] > 0))
        if len(li) < 3:
            return None
        n = rb[near[li]]
        X = (d.P[li] @ self.R.T + self.T) @ R_rel.T  # the landmarks rotated into this camera, before the step
        nt, nX = np.cross(n, t), np.cross(n, X)
        s = -np.einsum("ij,ij->i", nt, nX) / np.maximum(np.einsum("ij,ij->i", nt, nt), 1e-12)
        step = float(np.median(s))
        Xc = X + step * t
        ang = np.arccos(np.clip(np.einsum("ij,ij->i", Xc / np.linalg.norm(Xc, axis=1)[:, None], n), -1, 1))
        # A tied corner may sit up to ORB_TIE_PX from its landmark, here as in the last image.
        inl = (ang < (ORB_TIE_PX + self.cfg.inlier_threshold_px) / f) & (Xc[:, 2] > 0)
        if inl.sum() < 3:
            return None
        li = li[inl]
        R, T = R_rel @ self.R, R_rel @ self.T + step * t
        proj, _ = self.camera.project(Xc[inl])  # where the landmark is, not where its ORB corner was found
        self._adopt(d, li, np.asarray(proj, float).reshape(-1, 2))  # li is sorted: rows stay in order
        k = len(li)
        return MotionEstimate(R, T, np.linalg.norm(Xc[inl], axis=1), 0, float(np.sqrt(np.mean(ang[inl] ** 2))),
                              np.ones(k, bool), True)

    # ------------------------------------------------------------------ relocalisation after a restart
    def world_landmarks(self) -> tuple[np.ndarray, np.ndarray]:
        """The described landmarks (tracked and dormant) in world coordinates and their ORB
        descriptors: what a restarted front end can relocalise against."""
        W = self.references[-1].pose_wc
        P = np.vstack((self.lm.P[self.lm.described], self.dormant.P[self.dormant.described]))
        desc = np.vstack((self.lm.desc[self.lm.described], self.dormant.desc[self.dormant.described]))
        return P @ W[:3, :3].T + W[:3, 3], desc

    def relocalise(self, image: np.ndarray, points_w: np.ndarray, desc: np.ndarray,
                   min_inliers: int) -> Optional[np.ndarray]:
        """World-from-camera pose of ``image`` from ORB matches to kept world landmarks, or None when
        fewer than ``min_inliers`` agree (within the pose inlier threshold)."""
        if len(points_w) < min_inliers:
            return None
        pts = self.tracker.detect(image, 2 * self.cfg.max_landmarks)
        d, idx = describe(image, pts)
        pairs = match_descriptors(desc, d)
        if len(pairs) < min_inliers:
            return None
        W = self.pose_wc  # the current estimate: landmarks centred on it keep the solve well conditioned
        X = (points_w[pairs[:, 0]] - W[:3, 3]) @ W[:3, :3]  # in the current camera's axes
        f = float(getattr(self.camera, "fx", 500.0))
        est = recover_motion_robust(X, self.camera.rays(pts[idx][pairs[:, 1]]), prior=(np.eye(3), np.zeros(3)),
                                    threshold=self.cfg.inlier_threshold_px / f, angular=True, rng=self.rng)
        if (est.inliers & (est.depths > 0)).sum() < min_inliers:
            return None
        return W @ np.linalg.inv(_to_h(est.R, est.T))

    def similarity_to(self, points_w: np.ndarray, desc: np.ndarray, min_inliers: int,
                      max_relative_error: float = SIM3_MAX_RELATIVE_ERROR, rounds: int = 200
                      ) -> Optional[tuple[float, np.ndarray, np.ndarray, int]]:
        """Monocular relocalisation with scale: (s, R, t, inliers) such that s R X + t maps this run's
        world onto the world of the kept landmarks ``points_w``, from ORB matches of the kept
        descriptors to this run's tracked landmarks (3-D to 3-D, Umeyama with scale inside RANSAC).
        A pair agrees when the mapped point lies within ``max_relative_error`` of its distance from
        the (mapped) camera of the kept point: monocular depth errors grow with distance, angles do not.
        None when fewer than ``min_inliers`` agree."""
        L = self.lm
        own = np.flatnonzero(L.described)
        if len(own) < min_inliers or len(points_w) < min_inliers:
            return None
        pairs = match_descriptors(desc, L.desc[own])
        if len(pairs) < min_inliers:
            return None
        W = self.references[-1].pose_wc
        X_new = L.P[own[pairs[:, 1]]] @ W[:3, :3].T + W[:3, 3]
        X_old = np.asarray(points_w, float)[pairs[:, 0]]
        c_new = self.pose_wc[:3, 3]
        n = len(pairs)
        idx = np.array([self.rng.choice(n, 3, replace=False) for _ in range(rounds)])
        with np.errstate(invalid="ignore", divide="ignore"):  # collinear draws: no hypothesis (NaN)
            Rs, ts, ss = absolute_orientation(X_new[idx], X_old[idx], with_scale=True)
            mapped = ss[:, None, None] * np.einsum("hij,nj->hni", Rs, X_new) + ts[:, None, :]
            cam = ss[:, None] * np.einsum("hij,j->hi", Rs, c_new) + ts
            dist = np.linalg.norm(X_old[None] - cam[:, None, :], axis=2)
            agree = np.linalg.norm(mapped - X_old[None], axis=2) < max_relative_error * dist
        best = int(np.argmax(agree.sum(axis=1)))
        inl = agree[best]
        for _ in range(3):  # refit on the consensus set, then take its consensus again
            if inl.sum() < max(min_inliers, 3):
                return None
            R, t, sc = absolute_orientation(X_new[inl], X_old[inl], with_scale=True)
            c = sc * R @ c_new + t
            inl = np.linalg.norm(sc * X_new @ R.T + t - X_old, axis=1) \
                < max_relative_error * np.linalg.norm(X_old - c, axis=1)
        if inl.sum() < min_inliers:
            return None
        return float(sc), R, t, int(inl.sum())

    def correct_world_similarity(self, s: float, R: np.ndarray, t: np.ndarray) -> None:
        """Apply a similarity X' = s R X + t to this run's world: the structure of the current
        reference frame is rescaled by ``s`` and every reference frame, recent pose and window pose is
        moved with it (a monocular run relocalised against landmarks of known scale)."""
        self.rescale(s)

        def move(Wc: np.ndarray) -> np.ndarray:
            return similarity_moved(Wc, s, R, t)

        for ref in self.references:
            ref.pose_wc = move(ref.pose_wc)
        self._history = [move(Wc) for Wc in self._history]
        for v in self._window:
            v.pose_wc = move(v.pose_wc)
        self.adjusted = {k: move(Wc) for k, Wc in self.adjusted.items()}

    def correct_world(self, C: np.ndarray) -> None:
        """Apply a rigid world correction ``C`` (new world-from-old world) to the reference frames and
        the recent poses: what a relocalisation found wrong in the restart's placement."""
        self.correct_world_similarity(1.0, C[:3, :3], C[:3, 3])

    # ------------------------------------------------------------------ tracks and landmark positions
    def _refine_from_anchors(self, image: np.ndarray) -> None:
        """Frame-to-frame KLT drifts by a random walk; the feature's own patch in the image where it was
        detected does not. Track again from there, started at the frame-to-frame position; keep the
        result when it agrees with it (large viewpoint changes make the old patch useless)."""
        lim = self.cfg.anchor_max_shift_px
        params = dict(winSize=(self.cfg.klt_window, self.cfg.klt_window), maxLevel=1,
                      criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
        for S in (self.lm, self.cand):
            for a in np.unique(S.anchor):
                src = self._anchors.get(int(a))
                if src is None or int(a) == self._img_id:
                    continue
                idx = np.flatnonzero(S.anchor == a)
                guess = S.px[idx].astype(np.float32).reshape(-1, 1, 2).copy()
                out, st, _ = cv2.calcOpticalFlowPyrLK(src, image, S.apx[idx].astype(np.float32).reshape(-1, 1, 2),
                                                      guess, flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **params)
                out = out.reshape(-1, 2).astype(np.float64)
                good = (st.ravel() == 1) & (np.linalg.norm(out - S.px[idx], axis=1) < lim)
                S.px[idx[good]] = out[good]

    def _confidence(self, f: float) -> np.ndarray:
        """Weight of each landmark in the pose: 1 for landmarks of known position (structure, stereo,
        depth image); for monocular ones sigma^2 / (sigma^2 + sigma_lm^2), sigma the ray noise (one pixel
        at the focal length) and sigma_lm^2 = sigma^2 lambda_max(A^-1) / D^2 the angle its position
        uncertainty subtends from here (A: its N-view normal equations, weighted by 1/D^2 per view).
        sigma cancels: w = 1 / (1 + 1 / (lambda_min(A) D^2)), no noise level to tune."""
        L = self.lm
        w = np.ones(len(L.P))
        r = np.flatnonzero(L.refine)
        if len(r):
            ev = np.linalg.eigvalsh(L.A[r])[:, 0]
            D2 = np.sum((L.P[r] + self.R.T @ self.T) ** 2, axis=1)
            w[r] = np.maximum(1.0 / (1.0 + 1.0 / np.maximum(ev * D2, 1e-12)), self.cfg.min_landmark_weight)
        return w

    def _forget_anchors(self) -> None:
        used = set(np.unique(self.lm.anchor).tolist()) | set(np.unique(self.cand.anchor).tolist())
        for k in [k for k in self._anchors if k not in used and k != self._img_id]:
            del self._anchors[k]

    def _refine_landmarks(self, rays: np.ndarray) -> None:
        """Monocular landmarks: add this view to each one's N-view least squares (rays weighted by 1/D^2,
        i.e. angular error) and move it to the solution when the system is well conditioned."""
        L = self.lm
        r = np.flatnonzero(L.refine)
        if len(r) == 0:
            return
        C = -self.R.T @ self.T  # camera centre in the reference frame
        m = rays[r] @ self.R  # R^T n: rays in the reference frame
        D2 = np.sum((L.P[r] - C) ** 2, axis=1)
        w = 1.0 / np.maximum(D2, 1e-12)
        Q = np.eye(3)[None] - m[:, :, None] * m[:, None, :]
        L.A[r] += w[:, None, None] * Q
        L.b[r] += w[:, None] * np.einsum("nij,j->ni", Q, C)
        ev = np.linalg.eigvalsh(L.A[r])
        good = ev[:, 0] > self._min_conditioning * ev.sum(axis=1)
        if good.any():
            g = r[good]
            P = np.linalg.solve(L.A[g], L.b[g][:, :, None])[:, :, 0]
            front = (P @ self.R.T + self.T)[:, 2] > 0
            L.P[g[front]] = P[front]

    @property
    def _min_conditioning(self) -> float:
        # two views at the parallax gate theta: eigenvalues ~ (2, 2 - theta^2/2, theta^2/2) / (D^2): ratio theta^2/8
        return self._min_parallax ** 2 / 8.0

    @property
    def _min_parallax(self) -> float:
        """The parallax gate in radians: ``min_parallax_px`` at the focal length."""
        return self.cfg.min_parallax_px / float(getattr(self.camera, "fx", 500.0))

    def _predicted_pixels(self) -> np.ndarray:
        """Where the landmarks and candidates should appear in the next image at constant velocity: the
        KLT starts there, so it only has to find the deviation from the motion model (a turn of
        3 degrees per frame is 40 px of flow at f = 720 px, a few px of deviation). Landmarks are
        projected with the predicted motion; candidates (no depth yet) are rotated only, as if far.
        Points the prediction puts behind the camera or outside the image start where they are."""
        Rp, Tp = self._predicted_motion()
        cur = np.vstack((self.lm.px, self.cand.px))
        if len(cur) == 0 or len(self._history) < 2:
            return cur
        pred_lm, front_lm = self.camera.project(self.lm.P @ Rp.T + Tp)
        rays = self.camera.rays(self.cand.px) @ (Rp @ self.R.T).T  # current camera -> predicted camera
        pred_c, front_c = self.camera.project(rays)
        pred = np.vstack((np.asarray(pred_lm).reshape(-1, 2), np.asarray(pred_c).reshape(-1, 2)))
        ok = np.concatenate((front_lm, front_c)) & self.camera.in_image(pred, margin=0) & np.isfinite(pred).all(1)
        return np.where(ok[:, None], pred, cur)

    def _predicted_motion(self) -> tuple[np.ndarray, np.ndarray]:
        """Reference -> camera motion predicted at constant velocity from the last two poses."""
        if len(self._history) < 2:
            return self.R, self.T
        W1, W2 = self._history
        W = W2 @ np.linalg.inv(W1) @ W2  # W_k = W_{k-1} (W_{k-2}^-1 W_{k-1})
        M = np.linalg.inv(W) @ self.references[-1].pose_wc  # reference -> predicted camera
        return M[:3, :3], M[:3, 3]

    # ------------------------------------------------------------------ windowed bundle adjustment
    def _record_view(self) -> None:
        """Keep this frame's pose and the rays of its landmarks and candidates for the adjustment."""
        if self.cfg.ba_window < 1:
            return
        px = np.vstack((self.lm.px, self.cand.px))
        self._window.append(_View(self._img_id, self.pose_wc, np.concatenate((self.lm.uid, self.cand.uid)),
                                  self.camera.rays(px) if len(px) else np.zeros((0, 3))))
        del self._window[:-(self.cfg.ba_window + self.cfg.ba_history)]

    def _adjust_window(self, f: float) -> None:
        """Bundle adjustment of the window's poses and the monocular landmarks they see (landmarks of
        known position take part as fixed points); the oldest two poses stay fixed (gauge and scale).
        The current pose, the reference frame (when in the window), the landmarks and the candidates'
        first views take the adjusted values; landmarks left with an outlying observation are dropped."""
        win = self._window
        if self.cfg.ba_window < 1 or len(win) < 3 or not self.lm.free.any():
            return
        L = self.lm
        order = np.argsort(L.uid)
        obs_f, obs_p, obs_r = [], [], []
        for k, v in enumerate(win):
            pos = np.searchsorted(L.uid, v.uid, sorter=order)
            pos = np.minimum(pos, len(order) - 1)
            hit = L.uid[order[pos]] == v.uid
            obs_f.append(np.full(int(hit.sum()), k))
            obs_p.append(order[pos[hit]])
            obs_r.append(v.rays[hit])
        obs_f, obs_p, obs_r = np.concatenate(obs_f), np.concatenate(obs_p), np.concatenate(obs_r)
        views = np.bincount(obs_p, minlength=len(L.P))
        fixed_point = ~L.free | (views < 2)
        if fixed_point.all():
            return
        W_ref = self.references[-1].pose_wc
        X = L.P @ W_ref[:3, :3].T + W_ref[:3, 3]
        poses_cw = np.array([np.linalg.inv(v.pose_wc) for v in win])
        fixed_pose = np.arange(len(win)) < max(2, len(win) - self.cfg.ba_window)
        res = bundle_adjust(poses_cw, fixed_pose, X, fixed_point, obs_f, obs_p, obs_r, f,
                            sigma_px=self.cfg.inlier_threshold_px)
        self.ba_runs += 1
        new_wc = {v.image_id: np.linalg.inv(M) for v, M in zip(win, res.poses_cw)}
        for v in win:
            v.pose_wc = new_wc[v.image_id]
        self.adjusted = new_wc
        ref = self.references[-1]
        W_ref_new = new_wc.get(ref.index, W_ref)
        ref.pose_wc = W_ref_new
        # Landmarks in the (possibly moved) reference frame: fixed ones keep their world position,
        # adjusted ones take theirs; their normal equations keep their information (A) and are
        # re-centred on the adjusted position (b = A P) so the N-view refinement continues from it.
        D = np.linalg.inv(W_ref_new) @ W_ref
        L.transform(D[:3, :3], D[:3, 3])
        self.dormant.transform(D[:3, :3], D[:3, 3])
        moved = ~fixed_point
        inv = np.linalg.inv(W_ref_new)
        L.P[moved] = res.points[moved] @ inv[:3, :3].T + inv[:3, 3]
        L.b[moved] = np.einsum("nij,nj->ni", L.A[moved], L.P[moved])
        # Candidates' first views (reference -> camera at first sight).
        if len(self.cand.px):
            first_wc = W_ref @ np.linalg.inv(_to_h_batch(self.cand.R0, self.cand.T0))
            for a in np.unique(self.cand.anchor):
                if int(a) in new_wc:
                    first_wc[self.cand.anchor == a] = new_wc[int(a)]
            M0 = np.linalg.inv(W_ref_new) @ first_wc  # ... reference -> first camera is its inverse
            M0 = np.linalg.inv(M0)
            self.cand.R0, self.cand.T0 = M0[:, :3, :3], M0[:, :3, 3]
        cur = np.linalg.inv(new_wc[self._img_id]) @ W_ref_new  # reference -> current camera
        self.R, self.T = cur[:3, :3], cur[:3, 3]
        self._history = [new_wc.get(self._img_id - 1, self._history[0]), new_wc[self._img_id]] \
            if len(self._history) == 2 else [new_wc[self._img_id]]
        # Landmarks with an observation beyond the outlier bound, or behind a camera.
        bad = (res.residual_px > self.cfg.ba_outlier_sigmas * self.cfg.inlier_threshold_px) | res.behind
        drop = np.zeros(len(L.P), bool)
        drop[obs_p[bad]] = True
        drop &= L.free
        if drop.any():
            self.ba_dropped += int(drop.sum())
            L.keep(~drop)

    # ------------------------------------------------------------------ reference set
    def _maybe_handoff(self) -> bool:
        own = int(self.lm.own.sum())
        ref = self.references[-1]
        if own >= max(self.cfg.handoff_min, self.cfg.handoff_fraction * ref.landmarks):
            return False
        # Re-express the surviving landmarks in the current camera, which becomes the reference frame.
        self.lm.transform(self.R, self.T)
        self.dormant.transform(self.R, self.T)
        self.lm.own[:] = True
        Rc, Tc = self.cand.R0, self.cand.T0
        if len(Rc):  # candidates' first poses: ref_old -> cam0 becomes ref_new -> cam0
            Rinv = self.R.T
            self.cand.R0 = Rc @ Rinv
            self.cand.T0 = Tc - np.einsum("hij,j->hi", self.cand.R0, self.T)
        self.references.append(ReferenceFrame(self.frame - 1, self.pose_wc, len(self.lm.P)))
        self.R, self.T = np.eye(3), np.zeros(3)
        return True

    def rescale(self, s: float) -> None:
        """Multiply the metric scale of the current reference frame's structure by ``s`` (landmarks,
        dormant landmarks, candidates' first poses and the current motion, about the reference origin).
        For a monocular front end whose scale an outside sensor (wheel odometry) corrects."""
        if not s > 0:
            raise ValueError(f"rescale factor must be positive, got {s}")
        for lm in (self.lm, self.dormant):
            lm.P = lm.P * s
            lm.b = lm.b * s  # A X = b: A holds directions only
        self.cand.T0 = self.cand.T0 * s
        self.T = self.T * s

    def move_reference(self, position_w: np.ndarray) -> None:
        """Put the current reference frame at world position ``position_w`` (an outside correction); the
        recent poses the motion prediction uses move with it."""
        ref = self.references[-1]
        shift = np.asarray(position_w, float) - ref.pose_wc[:3, 3]
        ref.pose_wc = ref.pose_wc.copy()
        ref.pose_wc[:3, 3] += shift
        for k, W in enumerate(self._history):
            self._history[k] = W.copy()
            self._history[k][:3, 3] += shift

    def _add_landmarks(self, image, right, depth, own: bool) -> int:
        if self.baseline is not None and right is not None:
            n = self._add_from_stereo(image, right, own)
        elif depth is not None:
            n = self._add_from_depth(image, depth, own)
        else:
            n = self._add_from_motion(image, own)
        if own:
            self.references[-1].landmarks = len(self.lm.P)
        return n

    def _make_dormant(self, lost: _Landmarks) -> None:
        """Landmarks whose track was lost stay in the reference set, to be found again later."""
        if not self.cfg.reacquire_every or len(lost.P) == 0:
            return
        lost.keep(lost.described)
        self.dormant.extend(lost)
        extra = len(self.dormant.P) - self.cfg.max_dormant
        if extra > 0:  # forget the oldest
            m = np.ones(len(self.dormant.P), bool)
            m[:extra] = False
            self.dormant.keep(m)

    def _reacquire(self, image: np.ndarray) -> int:
        """Find dormant reference landmarks again: project them with the current pose, match ORB
        descriptors of fresh corners near the prediction. A re-found landmark keeps its reference
        coordinates, so coming back to a place ties the pose to the landmarks first seen there."""
        d = self.dormant
        if len(d.P) == 0:
            return 0
        X = d.P @ self.R.T + self.T
        pred, front = self.camera.project(X)
        vis = front & self.camera.in_image(pred, margin=16)
        if vis.sum() < 3:
            return 0
        corners = self.tracker.detect(image, 2 * self.cfg.max_landmarks, self.lm.px)
        if len(corners) < 2:
            return 0
        desc, idx = describe(image, corners)
        corners = corners[idx]
        vis_idx = np.flatnonzero(vis)
        pairs = match_descriptors(d.desc[vis_idx], desc)
        if len(pairs) == 0:
            return 0
        li, ci = vis_idx[pairs[:, 0]], pairs[:, 1]
        near = np.linalg.norm(corners[ci] - pred[li], axis=1) < self.cfg.reacquire_radius_px
        li, ci = li[near], ci[near]
        if len(li) == 0:
            return 0
        back = np.zeros(len(d.P), bool)
        back[li] = True
        found = d.keep(~back)  # d keeps the rest; ``found`` holds the re-found rows in index order
        order = np.argsort(li)
        found.px = corners[ci[order]]
        found.anchor[:], found.apx = self._img_id, found.px.copy()  # its old patch may be long gone
        self.lm.extend(found)
        self.reacquired += len(li)
        return len(li)

    def _two_view_normal_equations(self, P, ray0, R0, T0, rays):
        """Normal equations of the first view and the current one (reference-frame rays and centres)."""
        m0 = np.einsum("hji,hj->hi", R0, ray0)  # R0^T n0
        C0 = -np.einsum("hji,hj->hi", R0, T0)
        m1 = rays @ self.R
        C1 = np.broadcast_to(-self.R.T @ self.T, P.shape)
        A, b = np.zeros((len(P), 3, 3)), np.zeros((len(P), 3))
        for m, C in ((m0, C0), (m1, C1)):
            w = 1.0 / np.maximum(np.sum((P - C) ** 2, axis=1), 1e-12)
            Q = np.eye(3)[None] - m[:, :, None] * m[:, None, :]
            A += w[:, None, None] * Q
            b += w[:, None] * np.einsum("nij,nj->ni", Q, C)
        return A, b

    def _to_reference(self, X_cam: np.ndarray) -> np.ndarray:
        return (X_cam - self.T) @ self.R  # R^T (X - T)

    def _new_corners(self, image, budget: int) -> np.ndarray:
        existing = np.vstack((self.lm.px, self.cand.px))
        return self.tracker.detect(image, budget, existing, cells=self.cfg.detect_cells)

    def _add_from_stereo(self, left, right, own: bool) -> int:
        """Spherical disparity (11.11) with the known stereo motion: X_right = X_left - (b, 0, 0)."""
        px = self._new_corners(left, self.cfg.max_landmarks - len(self.lm.P))
        if len(px) == 0:
            return 0
        px_r, ok = self.tracker.track(left, right, px, levels=4)
        dx = px[:, 0] - px_r[:, 0]
        ok &= (np.abs(px_r[:, 1] - px[:, 1]) < 1.0) & (dx > 0.3)
        if not ok.any():
            return 0
        px, px_r = px[ok], px_r[ok]
        T = np.array([-self.baseline, 0.0, 0.0])
        n_l, n_r = self.camera.rays(px), self.camera.rays(px_r)
        rec = spherical_disparity(n_l, n_r, np.eye(3), T, min_parallax=0.0, max_residual_ratio=0.2)
        good = rec.valid & (rec.depth_ref < self.cfg.stereo_max_depth_baselines * self.baseline) \
            & (rec.depth_ref > self.cfg.min_depth)
        X = rec.depth_ref[good, None] * n_l[good]
        self.lm.add(self._to_reference(X), px[good], own, image=left, anchor=self._img_id)
        return int(good.sum())

    def _add_from_depth(self, image, depth, own: bool) -> int:
        px = self._new_corners(image, self.cfg.max_landmarks - len(self.lm.P))
        if len(px) == 0:
            return 0
        ij = np.round(px).astype(int)
        z = depth[np.clip(ij[:, 1], 0, depth.shape[0] - 1), np.clip(ij[:, 0], 0, depth.shape[1] - 1)]
        good = np.isfinite(z) & (z > max(self.cfg.min_depth, 1e-6))
        if self.baseline is not None:    # depth from a stereo disparity (an OAK's): as far as stereo landmarks go
            good &= z < self.cfg.stereo_max_depth_baselines * self.baseline
        n = self.camera.rays(px[good])
        X = n * (z[good] / n[:, 2])[:, None]  # depth images hold z, not the radial distance
        self.lm.add(self._to_reference(X), px[good], own, image=image, anchor=self._img_id)
        return int(good.sum())

    def _add_from_motion(self, image, own: bool) -> int:
        """Monocular: triangulate waiting candidates by spherical disparity between their first view
        and now, once the parallax passes the gate; then top up the candidates."""
        added = 0
        c = self.cand
        if len(c.px):
            rays = self.camera.rays(c.px)
            # first view -> now: X_now = R X_ref + T, X_0 = R0 X_ref + T0  =>  R_rel = R R0^T, T_rel = T - R_rel T0
            R_rel = np.einsum("ij,hkj->hik", self.R, c.R0)
            T_rel = self.T - np.einsum("hij,hj->hi", R_rel, c.T0)
            rec = spherical_disparity(c.ray0, rays, R_rel, T_rel, min_parallax=self._min_parallax,
                                      max_residual_ratio=0.05)
            d0 = rec.depth_ref
            ok = rec.valid & (d0 > self.cfg.min_depth)
            if ok.any():
                X0 = d0[ok, None] * c.ray0[ok]
                P = np.einsum("hji,hj->hi", c.R0[ok], X0 - c.T0[ok])  # R0^T (X0 - T0)
                A, b = self._two_view_normal_equations(P, c.ray0[ok], c.R0[ok], c.T0[ok], rays[ok])
                self.lm.add(P, c.px[ok], own, image=image, anchor=c.anchor[ok], apx=c.apx[ok], A=A, b=b,
                            refine=np.full(int(ok.sum()), self.cfg.refine_landmarks), uid=c.uid[ok], free=True)
                added = int(ok.sum())
                self._newborn = c.uid[ok].copy()
                c.keep(~ok)
        budget = self.cfg.max_candidates - len(c.px)
        if budget > 0 and len(self.lm.P) < self.cfg.max_landmarks:
            px = self._new_corners(image, budget)
            if len(px):
                m = len(px)
                c.px = np.vstack((c.px, px))
                c.ray0 = np.vstack((c.ray0, self.camera.rays(px)))
                c.R0 = np.concatenate((c.R0, np.repeat(self.R[None], m, 0)))
                c.T0 = np.vstack((c.T0, np.repeat(self.T[None], m, 0)))
                c.anchor = np.concatenate((c.anchor, np.full(m, self._img_id)))
                c.apx = np.vstack((c.apx, px))
                c.uid = np.concatenate((c.uid, _new_uids(m)))
        return added
