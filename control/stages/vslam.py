"""The VSLAM on the robot (chapter section 11.3), as a vision stage; ``controllers/goto.py`` drives on it.

``VslamStage`` (vision thread, kind "vslam"): runs ``vision.vslam.Vslam`` on the
robot's frames. Metric scale comes from the calibrated stereo pair (the right
image of the frame, section 11.3.1.1), on cameras that deliver only a
disparity image (OAK) from the depth that disparity gives, or, with a single
camera (``metric_scale: odometry``), from the wheels: a two-view initialisation
(essential matrix or homography) between the first frame and the first one the
wheels put ``odometry_init_baseline_m`` away, scaled by that distance; new
landmarks then come from motion (11.11) in that scale. The world frame is
the robot's odometry frame at the first frame (the robot's start pose), so a
goal "in the reference frame" is a pose relative to where the robot started.
Each reference frame of the VSLAM's chain is kept as an *anchor*: its
landmarks (world coordinates) with ORB descriptors, unless an older anchor lies
within half the relocalisation radius and heading (the anchors grow with the
area seen, not with the distance driven). When the robot comes back
near an older anchor, the frame is matched against that anchor's landmarks and
the pose is computed against them (11.15-11.17), not through the chain of
hand-offs: returning to the start gives the pose against the first reference
set. Anchors cost ~7 kB each (about 3 per metre of new ground). After a few lost
frames in a row (a covered lens) the front end restarts from the current
stereo pair at the pose odometry carried since the last good frame; the
anchors survive, so a later loop still closes. The stage reports the robot's
planar pose (camera pose through the mount).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
from vbnav.control.config.vslam import VslamNavConfig
from vbnav.control.runtime.interfaces import Estimate, PoseFix, StageOverlay, VisionStage
from vbnav.control.stages.frame_input import disparity_problem, frame_baseline, odometry_problem, stage_image
from vbnav.drivers.camera import Frame
from vbnav.vision.features import describe
from vbnav.vision.geometry import CameraMount, Pose2, camera_pose, rot_y
from vbnav.vision.motion import recover_motion_robust
from vbnav.vision.motion import warm_up as warm_up_motion_kernels
from vbnav.vision.vslam import Vslam
from vbnav.vision.vslam_init import init_two_view


# ------------------------------------------------------------------------------------- poses
def to_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, t
    return M



def robot_to_camera_matrix(pose: Pose2, mount: CameraMount) -> np.ndarray:
    """4x4 world-from-camera of the camera on a robot at ``pose``."""
    return to_matrix(*camera_pose(pose, mount))



def camera_to_robot(pose_wc: np.ndarray, mount: CameraMount) -> tuple[Pose2, float, float]:
    """Planar robot pose from a 6-DoF world-from-camera pose and the mount.

    Returns (pose, height error m, tilt error rad): how far the camera is from
    where a robot on the floor would hold it (a check of the estimate, since the
    VSLAM does not know the robot stays on the floor).
    """
    R_wr = pose_wc[:3, :3] @ mount.rotation().T        # R_wc = R_wr R_rc
    theta = math.atan2(R_wr[0, 2], R_wr[2, 2])          # rot_y(theta): [0,2] = sin, [2,2] = cos
    R_planar = rot_y(theta)
    p = pose_wc[:3, 3] - R_planar @ mount.translation()
    tilt = math.acos(max(-1.0, min(1.0, float(R_wr[1, 1]))))
    return Pose2(float(p[0]), float(p[2]), theta), float(p[1]), tilt



# ------------------------------------------------------------------------------------- stage
@dataclass
class VslamFix(PoseFix):
    """A VSLAM result: the robot pose in the reference (world) frame at the frame's time."""

    pose: Pose2
    odom: Pose2                  # odometry at the frame
    pose_wc: np.ndarray          # 4x4 world-from-camera
    inliers: int
    reference: int               # index of the reference frame of the chain the tracker uses
    anchor: Optional[int] = None  # anchor the pose was computed against directly (relocalisation), if any
    quality: dict = field(default_factory=dict)



@dataclass
class Anchor:
    """A reference frame kept for relocalisation: its landmarks in world coordinates with descriptors."""

    index: int
    pose_wc: np.ndarray
    robot: Pose2
    points_w: np.ndarray         # (N, 3)
    descriptors: np.ndarray      # (N, 32) uint8
    travelled: float = 0.0       # odometry path length when it was set, m



@dataclass
class _MonocularStart:
    """A monocular initialisation under way: corners of the first view tracked until the wheels say the
    camera has moved far enough for a metric two-view initialisation."""

    px0: np.ndarray              # corners in the first view
    px: np.ndarray               # where they are now
    keep: np.ndarray             # still tracked
    prev: np.ndarray             # last image
    odom0: Pose2                 # odometry at the first view
    pose0_wc: np.ndarray         # world-from-camera of the first view
    frames: int = 0



class VslamStage(VisionStage):
    """Runs the VSLAM on every frame; the estimate is the robot's pose in the reference frame."""

    kind = "vslam"

    def __init__(self, camera, mount: CameraMount, stereo_baseline: Optional[float],
                 cfg: VslamNavConfig | None = None, baseline_from_frames: bool = False):
        """stereo_baseline: metres. With ``baseline_from_frames`` it may be None: the first frame's
        ``meta['baseline_m']`` gives it (the OAK driver reads it from the device's calibration); a frame
        before it without a usable one is an unusable frame (not ok, ``info['reason']`` says why)."""
        self.cfg = cfg or VslamNavConfig()
        self.monocular = self.cfg.metric_scale == "odometry"
        if not self.monocular and (stereo_baseline is None or stereo_baseline <= 0) and not baseline_from_frames:
            raise ValueError("the VSLAM stage needs a stereo camera for metric scale: set the stereo baseline "
                             "(camera.options.stereo_baseline for the simulated camera), or vslam.metric_scale: "
                             "odometry for a single camera scaled by the wheels")
        self.camera = camera
        self.mount = mount
        self.baseline = None if self.monocular or not stereo_baseline else float(stereo_baseline)
        self.slam = Vslam(camera, self.cfg, stereo_baseline=self.baseline)
        warm_up_motion_kernels()  # compile now, not in the vision thread's first frame
        self._mono: Optional[_MonocularStart] = None
        # Monocular scale: (camera position by the VSLAM in chain coordinates, by odometry) where the
        # distance the two are compared over starts.
        self._scale_base: Optional[tuple[np.ndarray, np.ndarray]] = None
        self.anchors: list[Anchor] = []
        self.correction = np.eye(4)  # world-from-chain: aligns the hand-off chain with the last relocalisation
        self._frames = 0
        self._last_anchor_ref = -1
        self._travelled = 0.0
        self._last_odom: Optional[Pose2] = None
        self._ref_base = 0           # reference frames of earlier runs of the front end (before a restart)
        self._lost_streak = 0
        self._good: Optional[tuple[Pose2, Pose2]] = None   # (robot pose, odometry) at the last good frame
        self.stats = {"frames": 0, "lost": 0, "handoffs": 0, "relocalised": 0, "restarts": 0, "unusable": 0,
                      "anchors_skipped": 0}
        if self.monocular:
            self.stats.update(rescaled=0, last_scale=1.0)

    @property
    def reference_index(self) -> int:
        """Index of the current reference frame in the whole chain (across restarts)."""
        return self._ref_base + len(self.slam.references) - 1

    def overlay(self, estimate: Optional[Estimate]) -> StageOverlay:
        """The landmarks, in the VSLAM's world frame."""
        return StageOverlay(landmarks=self.slam.lm.P)

    def pose_at(self, odom: Pose2) -> Optional[Pose2]:
        """The robot pose in the reference frame when odometry reads ``odom``: the last good VSLAM pose
        carried forward by the odometry since its frame (None before the first). A stage after this one
        in the pipeline gets this frame's own pose."""
        good = self._good
        return None if good is None else good[0].compose(good[1].between(odom))

    # -- per frame
    def process(self, frame: Frame, odom: Pose2) -> Estimate:
        image, why = stage_image(frame.image, self.camera)
        odom_why = odometry_problem(odom)
        why = why or odom_why
        if self.baseline is None and not self.monocular:
            # From the first frame that carries a usable one; until then each frame is unusable (as any bad
            # frame: not ok, the go-to controller has no pose and stays stopped), saying why.
            b, b_why = frame_baseline(frame)
            if b is None:
                why = why or (f"{b_why}: the stereo VSLAM needs the stereo baseline for metric scale (set "
                              "camera.options.stereo_baseline)")
            else:
                self.baseline = b
                self.slam = Vslam(self.camera, self.cfg, stereo_baseline=self.baseline)
        right, depth = None, None
        if why:
            why = f"vslam: {why}"
        elif not self.monocular:
            right, depth, why = self._metric_input(frame)
        self._frames += 1
        self.stats["frames"] += 1
        if not odom_why:
            if self._last_odom is not None:
                self._travelled += math.hypot(odom.x - self._last_odom.x, odom.z - self._last_odom.z)
            self._last_odom = odom
        if why:
            return self._unusable(frame, odom, why)
        if not self.slam.initialised:
            # The first start at the odometry pose (the world frame is the odometry frame); a start retried
            # after a restart found too few landmarks at the last good pose carried by odometry.
            pose0_wc = robot_to_camera_matrix(self.pose_at(odom) or odom, self.mount)
            if self.monocular:
                return self._start_monocular(frame, image, odom, pose0_wc)
            return self._start(frame, image, right, depth, odom, pose0_wc)
        res = self.slam.process(image, right, depth)
        if self.monocular and res.handoff:
            res.pose_wc = self._correct_scale(odom)
        self.stats["lost"] += int(not res.ok)
        self.stats["handoffs"] += int(res.handoff)
        self._lost_streak = 0 if res.ok else self._lost_streak + 1
        if self._lost_streak >= self.cfg.restart_after_lost and self._good is not None:
            # Lost (covered lens, motion blur, a blank wall): start a new chain from this stereo pair at the
            # pose odometry gives since the last good frame. Anchors are kept, so the loop still closes.
            guess = self._good[0].compose(self._good[1].between(odom))
            if self.monocular:
                self._new_chain()
                return self._start_monocular(frame, image, odom, robot_to_camera_matrix(guess, self.mount))
            return self._start(frame, image, right, depth, odom, robot_to_camera_matrix(guess, self.mount),
                               restart=True)
        pose_wc = self.correction @ res.pose_wc
        anchor = None
        if res.ok:
            self._maybe_add_anchor(image)
            reloc = self._relocalise(image, pose_wc)
            if reloc is not None:
                anchor, pose_wc = reloc
                self.correction = pose_wc @ np.linalg.inv(res.pose_wc)
                self.stats["relocalised"] += 1
        est = self._estimate(frame, odom, res.ok, pose_wc, res.inliers, anchor,
                             {"iterations": res.iterations, "residual_px": res.residual_px,
                              "tracked": res.tracked, "handoff": res.handoff})
        if est.ok:
            self._good = (est.value.pose, odom)
        return est

    def _start(self, frame: Frame, image, right, depth, odom: Pose2, pose_wc: np.ndarray,
               restart: bool = False) -> Estimate:
        """(Re)initialise the front end from this frame's stereo pair (or depth) at world pose ``pose_wc``.

        With fewer landmarks than ``min_inliers`` (a dark or uniform view: lens cap, exposure not settled)
        nothing could be tracked against them: the front end stays uninitialised, the estimate is not ok
        and the next frame tries again (it was initialised with none and lost for good when no good pose
        came before)."""
        if restart:
            self._new_chain()
        if right is not None:
            n = self.slam.initialise_stereo(image, right, pose_wc)
        else:
            n = self.slam.initialise_depth(image, depth, pose_wc)
        self._lost_streak = 0
        if n < self.cfg.min_inliers:
            self.stats["lost"] += 1
            self.slam = Vslam(self.camera, self.cfg, stereo_baseline=self.baseline)
            est = self._estimate(frame, odom, False, pose_wc, n, None, {"restart": restart, "landmarks": n})
            est.info["reason"] = (f"vslam: {n} landmarks in this frame, fewer than vslam.min_inliers "
                                  f"({self.cfg.min_inliers}) to start on; the next frame is tried")
            return est
        self._maybe_add_anchor(image)
        est = self._estimate(frame, odom, n >= self.cfg.min_inliers, self.slam.pose_wc, n, None,
                             {"restart": restart})
        if est.ok:
            self._good = (est.value.pose, odom)
        return est

    def _new_chain(self) -> None:
        """A fresh front end after it was lost; the anchors of the old chain stay for relocalisation."""
        self._ref_base = self.reference_index + 1
        self.slam = Vslam(self.camera, self.cfg, stereo_baseline=self.baseline)
        self.correction = np.eye(4)
        self.stats["restarts"] += 1
        self._mono = None
        self._scale_base = None

    def _start_monocular(self, frame: Frame, image, odom: Pose2, pose0_wc: np.ndarray) -> Estimate:
        """Single camera: track the first view's corners until the wheels have moved the camera
        ``odometry_init_baseline_m``, then the two-view initialisation (vision/vslam_init.py) with that
        distance as the length of T. Until then the estimate is not ok and says "initialising", with the
        pose odometry gives (the go-to controller creeps ahead for the parallax)."""
        cfg, m = self.cfg, self._mono
        if m is None:
            px0 = self.slam.tracker.detect(image, cfg.max_landmarks, cells=cfg.detect_cells)
            self._mono = _MonocularStart(px0, px0.copy(), np.ones(len(px0), bool), image, odom, pose0_wc)
            return self._estimate(frame, odom, False, pose0_wc, 0, None, {"initialising": "monocular"})
        idx = np.flatnonzero(m.keep)
        nxt, ok = self.slam.tracker.track(m.prev, image, m.px[idx])
        m.keep[idx[~ok]] = False
        m.px[idx[ok]] = nxt[ok]
        m.prev, m.frames = image, m.frames + 1
        # Camera motion between the views from the wheels: X_now = R X_first + T.
        cam_odom = robot_to_camera_matrix(odom, self.mount)
        rel = np.linalg.inv(cam_odom) @ robot_to_camera_matrix(m.odom0, self.mount)
        pose_wc = m.pose0_wc @ np.linalg.inv(rel)   # where odometry puts the camera now
        baseline = float(np.linalg.norm(rel[:3, 3]))
        quality = {"initialising": "monocular", "baseline_m": baseline, "tracked": int(m.keep.sum())}
        if m.keep.sum() < max(8, cfg.min_inliers) or m.frames > cfg.odometry_init_max_frames:
            self._mono = None                        # start over from this view
            return self._start_monocular(frame, image, odom, pose_wc)
        if baseline < cfg.odometry_init_baseline_m:
            return self._estimate(frame, odom, False, pose_wc, 0, None, quality)
        px, rays0 = m.px[m.keep], self.camera.rays(m.px0[m.keep])
        tv = init_two_view(rays0, self.camera.rays(px), scale=baseline, translation_hint=rel[:3, 3])
        v = tv.valid
        if v.sum() < max(8, cfg.min_inliers):
            self._mono = None
            return self._start_monocular(frame, image, odom, pose_wc)
        X_first = tv.depths1[v, None] * rays0[v]
        pose_wc = m.pose0_wc @ np.linalg.inv(to_matrix(tv.R, tv.T))
        n = self.slam.initialise(image, px[v], X_first @ tv.R.T + tv.T, pose_wc)
        self._mono = None
        self._scale_base = (self.slam.references[-1].pose_wc[:3, 3].copy(), cam_odom[:3, 3])
        self._lost_streak = 0
        self._maybe_add_anchor(image)
        est = self._estimate(frame, odom, n >= cfg.min_inliers, self.slam.pose_wc, n, None,
                             {"initialised": tv.model, "baseline_m": baseline})
        if est.ok:
            self._good = (est.value.pose, odom)
        return est

    def _correct_scale(self, odom: Pose2) -> np.ndarray:
        """At a hand-off of the monocular front end: compare the camera travel since the scale base by the
        VSLAM and by the wheels, move the new reference frame's position along that travel and rescale its
        structure by the ratio (to the power ``odometry_scale_gain``). Direction stays the VSLAM's; only the
        length, which a single camera cannot observe, follows the wheels. Returns the corrected pose."""
        ref = self.slam.references[-1]
        p_vslam, p_odom = ref.pose_wc[:3, 3].copy(), robot_to_camera_matrix(odom, self.mount)[:3, 3]
        if self._scale_base is None:
            self._scale_base = (p_vslam, p_odom)
            return self.slam.pose_wc
        b_vslam, b_odom = self._scale_base
        d_vslam, d_odom = np.linalg.norm(p_vslam - b_vslam), np.linalg.norm(p_odom - b_odom)
        if d_odom < self.cfg.odometry_scale_min_travel_m or d_vslam <= 1e-9:
            return self.slam.pose_wc
        ratio = np.clip(d_odom / d_vslam, self.cfg.odometry_scale_min_ratio, self.cfg.odometry_scale_max_ratio)
        s = float(ratio) ** self.cfg.odometry_scale_gain
        self.slam.move_reference(b_vslam + s * (p_vslam - b_vslam))
        self.slam.rescale(s)
        self.stats["rescaled"] += 1
        self.stats["last_scale"] = round(s, 4)
        self._scale_base = (ref.pose_wc[:3, 3].copy(), p_odom)
        return self.slam.pose_wc

    def _metric_input(self, frame: Frame) -> tuple[Optional[np.ndarray], Optional[np.ndarray], str]:
        """(right image, depth, "") for the frame's metric scale, or (None, None, why) when the frame has
        neither a right image nor a disparity image. Not an error: an OAK publishes a frame without
        disparity whenever that disparity arrives late (drivers/oak_camera.py), the first frame too; the
        frame is then not ok and the next one is tried."""
        if frame.right is not None:
            right, why = stage_image(frame.right, self.camera, "right image")
            return right, None, f"vslam: {why}" if why else ""
        if frame.disparity is not None:
            why = disparity_problem(frame.disparity, self.camera)
            if why:
                return None, None, f"vslam: {why}"
            d = np.asarray(frame.disparity).astype(np.float32, copy=False)
            with np.errstate(divide="ignore", invalid="ignore"):
                depth = np.where(d > 0, float(self.camera.fx) * self.baseline / d, np.nan)
            return None, depth, ""
        return None, None, ("vslam: the frame has neither a right image nor a disparity image (the stereo "
                            "VSLAM needs one for metric scale; camera.options.stereo_baseline for the "
                            "simulated camera)")

    def _unusable(self, frame: Frame, odom: Pose2, why: str) -> Estimate:
        """The estimate for a frame the VSLAM cannot use (``why``): not ok, at the last good pose carried
        by odometry (odometry before the first; the last good pose itself when odometry is not finite). The
        front end's state stays that of the last good frame, so the next usable frame continues from there
        (or restarts once it is lost)."""
        self.stats["unusable"] += 1
        if odometry_problem(odom):
            guess = self._good[0] if self._good is not None else Pose2()
        else:
            guess = self.pose_at(odom) or odom
        est = self._estimate(frame, odom, False, robot_to_camera_matrix(guess, self.mount), 0, None,
                             {"unusable": why})
        est.info["reason"] = why
        return est

    def _estimate(self, frame: Frame, odom: Pose2, ok: bool, pose_wc: np.ndarray, inliers: int,
                  anchor: Optional[int], quality: Optional[dict] = None) -> Estimate:
        pose, dh, tilt = camera_to_robot(pose_wc, self.mount)
        ok = ok and abs(dh) <= self.cfg.max_planar_residual_m
        fix = VslamFix(pose, odom, pose_wc, inliers, self.reference_index, anchor,
                       {**(quality or {}), "height_error_m": dh, "tilt_deg": math.degrees(tilt)})
        return Estimate(frame.stamp_ns, self.kind, bool(ok), fix,
                        {"inliers": inliers, "reference": fix.reference, "anchor": anchor})

    # -- anchors (the chain's reference frames, kept for relocalisation)
    def _maybe_add_anchor(self, image: np.ndarray) -> None:
        ref_index = self.reference_index
        if ref_index == self._last_anchor_ref:
            return
        self._last_anchor_ref = ref_index
        lm = self.slam.lm
        if len(lm.P) < self.cfg.anchor_min_landmarks:
            return
        # Landmarks are in the reference frame; the current camera is the reference frame (just handed off,
        # or just initialised), so their pixels in this image describe them.
        ref_wc = self.correction @ self.slam.references[-1].pose_wc
        cur_wc = self.correction @ self.slam.pose_wc
        desc, idx = describe(image, lm.px)
        if len(idx) < self.cfg.anchor_min_landmarks:
            return
        robot = camera_to_robot(cur_wc, self.mount)[0]
        if self._anchored_near(robot):
            self.stats["anchors_skipped"] += 1
            return
        Pw = lm.P[idx] @ ref_wc[:3, :3].T + ref_wc[:3, 3]
        self.anchors.append(Anchor(ref_index, cur_wc, robot, Pw, desc, self._travelled))

    def _anchored_near(self, robot: Pose2) -> bool:
        """Whether a kept anchor lies within half the relocalisation radius and heading of ``robot``.

        Every pose within half the radius of such a place is within the whole radius of the kept anchor,
        and relocalisation tries the oldest near anchor first, so a new one there adds little and the list
        grew with the distance driven (16 anchors a lap of a 6 m loop, lap after lap: a patrol's memory and
        search time without bound). Kept this way, it grows with the area seen, not the distance."""
        r = 0.5 * self.cfg.relocalise_radius_m
        h = math.radians(0.5 * self.cfg.relocalise_heading_deg)
        for a in self.anchors:
            rel = a.robot.between(robot)
            if math.hypot(rel.x, rel.z) <= r and abs(rel.theta) <= h:
                return True
        return False

    def _relocalise(self, image: np.ndarray, pose_wc: np.ndarray) -> Optional[tuple[int, np.ndarray]]:
        """Pose against the oldest anchor near the current pose, or None."""
        cfg = self.cfg
        if cfg.relocalise_radius_m <= 0 or self._frames % cfg.relocalise_every:
            return None
        robot = camera_to_robot(pose_wc, self.mount)[0]
        current_ref = self.reference_index
        for a in self.anchors:
            if a.index >= current_ref - 1 or self._travelled - a.travelled < cfg.relocalise_min_travel_m:
                break                             # the tracker still measures against these (or nearly)
            rel = a.robot.between(robot)
            if math.hypot(rel.x, rel.z) > cfg.relocalise_radius_m or \
                    abs(rel.theta) > math.radians(cfg.relocalise_heading_deg):
                continue
            found = self._pose_against(a, image, pose_wc)
            if found is not None:
                return a.index, found
        return None

    def _pose_against(self, a: Anchor, image: np.ndarray, pose_wc: np.ndarray) -> Optional[np.ndarray]:
        """Match the anchor's landmarks in this image near where the current pose puts them (guided ORB
        matching), then the motion recovery (11.15-11.17) against their stored positions."""
        cfg = self.cfg
        cw = np.linalg.inv(pose_wc)
        P = a.points_w @ cw[:3, :3].T + cw[:3, 3]          # landmarks in the predicted camera frame
        pred, front = self.camera.project(P)
        vis = np.flatnonzero(front & self.camera.in_image(pred, margin=8))
        if len(vis) < cfg.relocalise_min_inliers:
            return None
        corners = self.slam.tracker.detect(image, 2 * cfg.max_landmarks)
        desc, idx = describe(image, corners)
        if len(idx) < cfg.relocalise_min_inliers:
            return None
        corners = corners[idx]
        lm, cn = guided_matches(pred[vis], a.descriptors[vis], corners, desc, cfg.relocalise_search_px,
                                cfg.relocalise_max_hamming)
        if len(lm) < cfg.relocalise_min_inliers:
            return None
        rays = self.camera.rays(corners[cn])
        f = float(self.camera.fx)
        est = recover_motion_robust(P[vis[lm]], rays, prior=(np.eye(3), np.zeros(3)),
                                    threshold=cfg.inlier_threshold_px / f, angular=True,
                                    rng=np.random.default_rng(self._frames))
        n_in = int((est.inliers & (est.depths > 0)).sum())
        if n_in < cfg.relocalise_min_inliers:
            return None
        # A correction larger than the chain can have drifted is a wrong match, not a loop closure.
        if np.linalg.norm(est.T) > cfg.relocalise_max_correction_m:
            return None
        # X_cur = R X_pred + T  =>  world-from-current = world-from-pred @ inv([R, T])
        return pose_wc @ np.linalg.inv(to_matrix(est.R, est.T))



def guided_matches(pred: np.ndarray, desc_a: np.ndarray, corners: np.ndarray, desc_c: np.ndarray,
                   radius: float, max_distance: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (landmark index, corner index): for each predicted pixel the corner within ``radius`` px with
    the nearest ORB descriptor (Hamming <= max_distance), each corner used once (nearest descriptor wins)."""
    if len(pred) == 0 or len(corners) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    near = np.linalg.norm(pred[:, None, :] - corners[None, :, :], axis=2) <= radius
    ham = np.unpackbits(desc_a[:, None, :] ^ desc_c[None, :, :], axis=2).sum(axis=2)
    ham = np.where(near, ham, 10 ** 6)
    best = np.argmin(ham, axis=1)
    dist = ham[np.arange(len(pred)), best]
    ok = dist <= max_distance
    lm, cn, dist = np.flatnonzero(ok), best[ok], dist[ok]
    order = np.argsort(dist, kind="stable")
    _, first = np.unique(cn[order], return_index=True)
    keep = np.sort(order[first])
    return lm[keep], cn[keep]



def stereo_baseline_of(cfg) -> Optional[float]:
    """The stereo baseline the configured camera gives, if any (its calibration file, else its
    ``options.stereo_baseline``; OAK: from the device, in the frames)."""
    return cfg.camera.stereo_baseline()



# Camera drivers whose frames carry the stereo baseline (meta['baseline_m']) from the device's calibration.
BASELINE_FROM_DEVICE = ("oak",)



def make_vslam_stage(cfg, baseline: Optional[float] = None) -> VslamStage:
    refusal = cfg.camera.rectified_refusal("the stereo VSLAM", "rectify the pair, e.g. with a stereo calibration "
                                           "file, or set vslam.metric_scale: odometry") \
        if cfg.vslam.metric_scale == "stereo" else ""
    if refusal:      # a monocular VSLAM's rays take the distortion; a stereo pair is rectified
        raise ValueError(refusal)
    return VslamStage(cfg.camera.to_model(), cfg.camera.mount.to_mount(), baseline or stereo_baseline_of(cfg),
                      cfg.vslam, baseline_from_frames=cfg.camera.driver in BASELINE_FROM_DEVICE)
