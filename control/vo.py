"""Visual odometry over a recorded dataset: run the VSLAM front end from the chosen initialisation.

``vbnav vo`` writes and evaluates the trajectory with ``control/trajectory_metrics.py``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import cv2
import numpy as np

from vbnav.drivers.datasets import Dataset, DatasetError
from vbnav.drivers.errors import InputError
from vbnav.vision.geometry import similarity_moved
from vbnav.vision.motion import recover_motion_robust
from vbnav.vision.vslam import FrameResult, Vslam, VslamConfig
from vbnav.vision.vslam_init import TagGrid, init_from_tags, init_two_view

INIT_MODES = ("stereo", "depth", "tags", "essential")


# A two-view start waits for this median image motion (px): at 1 px of tracking noise, depths from 20 px
# of parallax are good to ~5 %; and for this much of it beyond the rotation between the views, so that a
# turn (every point moving alike, no depth in it) does not start it with no baseline: 5 px is 5 times the
# tracking noise, which makes the translation direction of the essential matrix (a few hundred rays)
# good to a few degrees. Far points dominate the median, so the first bound alone is not a parallax.
TWO_VIEW_FLOW_PX = 20.0
TWO_VIEW_PARALLAX_PX = 5.0


# Relocalisation after a restart: landmarks of earlier runs kept (newest first), and the matches that must
# agree on one pose (20 inliers of a 3-point RANSAC: a chance consensus that large is negligible).
MAX_KEPT = 5000
RELOCALISE_MIN_INLIERS = 20


class VoError(InputError):
    """The dataset cannot be processed with the chosen initialisation."""


class VoStopped(VoError):
    """A frame could not be read mid-run: the message names its file; ``result`` is the trajectory up to it
    (the frames from it on have no pose)."""

    def __init__(self, message: str, result: "VoResult"):
        super().__init__(message)
        self.result = result


@dataclass
class FrameStatus:
    """What happened to one dataset frame: ``init`` (the first initialisation), ``tracked`` (pose
    against the landmarks), ``reinit`` (tracking was lost and started again here; the pose is the
    start's) or ``lost`` (no pose)."""

    frame: int
    state: str
    landmarks: int = 0
    inliers: int = 0

    @property
    def has_pose(self) -> bool:
        return self.state != "lost"


@dataclass
class VoResult:
    stamps: np.ndarray  # seconds of the frames with a pose
    poses: np.ndarray  # (K, 4, 4) world-from-camera
    frames: list[int]  # dataset index of each frame with a pose
    results: list[FrameResult] = field(default_factory=list)
    init: str = ""
    scale_known: bool = True
    references: int = 1
    status: list[FrameStatus] = field(default_factory=list)  # one per dataset frame

    def count(self, state: str) -> int:
        return sum(s.state == state for s in self.status)


def default_init(ds: Dataset) -> str:
    if ds.right is not None:
        return "stereo"
    if ds.depth is not None and ds.depth_image(0) is not None:
        return "depth"
    if "tag_grid" in ds.extras:
        return "tags"
    return "essential"


class _Trajectory:
    """Poses and per-frame states as the run goes; the motion model bridges lost frames."""

    def __init__(self, ds: Dataset):
        self.ds = ds
        self.poses: dict[int, np.ndarray] = {}
        self.status: dict[int, FrameStatus] = {}
        self.ids: dict[int, int] = {}  # front end's image id -> dataset frame

    def put(self, i: int, state: str, pose: Optional[np.ndarray], landmarks: int = 0, inliers: int = 0) -> None:
        self.status[i] = FrameStatus(i, state, landmarks, inliers)
        if pose is not None:
            self.poses[i] = np.asarray(pose, float)

    def adjust(self, slam: Vslam, i: int) -> None:
        """Frame ``i`` is the front end's last image; the poses its bundle adjustment changed (the
        frames of its window) replace those written when they were tracked."""
        self.ids[slam.image_id] = i
        for k, W in slam.adjusted.items():
            j = self.ids.get(k)
            if j is not None and j in self.poses:
                self.poses[j] = W

    def predicted(self, i: int) -> np.ndarray:
        """World-from-camera of frame ``i`` at constant velocity from the last two frames with a pose."""
        known = sorted(k for k in self.poses if k < i)
        if not known:
            return np.eye(4)
        if len(known) == 1:
            return self.poses[known[-1]]
        a, b = known[-2], known[-1]
        step = np.linalg.inv(self.poses[a]) @ self.poses[b]  # motion over (b - a) frames
        n = (i - b) / max(b - a, 1)
        return self.poses[b] @ _power(step, n)

    def rotation(self, i: int, n: float) -> np.ndarray:
        """Rotation (camera i -> camera i + n, point coordinates) at the angular rate of the last two
        frames with a pose (identity if unknown)."""
        known = sorted(k for k in self.poses if k < i)
        if len(known) < 2:
            return np.eye(3)
        a, b = known[-2], known[-1]
        return _power(np.linalg.inv(np.linalg.inv(self.poses[a]) @ self.poses[b]), n / (b - a))[:3, :3]

    def speed(self, i: int) -> float:
        """Distance per frame over the last two frames with a pose before ``i`` (0 if unknown)."""
        known = sorted(k for k in self.poses if k < i)
        if len(known) < 2:
            return 0.0
        a, b = known[-2], known[-1]
        return float(np.linalg.norm(self.poses[b][:3, 3] - self.poses[a][:3, 3]) / (b - a))

    def result(self, init: str, scale_known: bool, references: int, results: list[FrameResult]) -> VoResult:
        frames = sorted(self.poses)
        status = [self.status.get(i, FrameStatus(i, "lost")) for i in range(len(self.ds))]
        return VoResult(self.ds.stamps[frames], np.array([self.poses[i] for i in frames]).reshape(-1, 4, 4),
                        frames, results, init, scale_known, references, status)


def _power(M: np.ndarray, n: float) -> np.ndarray:
    """Rigid motion ``M`` applied ``n`` times (n real: rotation angle and translation scaled)."""
    rv, _ = cv2.Rodrigues(M[:3, :3])
    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(rv * n)[0]
    out[:3, 3] = M[:3, 3] * n
    return out


def run_vo(ds: Dataset, init: Optional[str] = None, config: Optional[VslamConfig] = None,
           progress: Optional[Callable[[str], None]] = None, essential_frames: int = 10, seed: int = 0) -> VoResult:
    """Track the whole dataset. When a frame is lost, the front end starts again at once (stereo,
    depth: new landmarks from that frame; monocular: a two-view start over the next frames whose
    unit baseline takes the speed of the last good frames), at the pose the motion model predicts,
    and the trajectory goes on from there."""
    init = init or default_init(ds)
    if init not in INIT_MODES:
        raise VoError(f"unknown --init {init!r} (expected one of {', '.join(INIT_MODES)})")
    if init == "stereo" and config is not None and config.ba_window > 0:
        # every landmark of a stereo run is measured by the pair: none is placed by the camera's own motion
        raise VoError(f"--ba-window {config.ba_window}: the bundle adjustment moves landmarks placed by the "
                      f"camera's own motion; with --init stereo the pair measures every landmark, so it would "
                      f"change nothing (leave it out, or --init essential for the left images alone)")
    say = progress or (lambda s: None)
    slam = Vslam(ds.camera, config, stereo_baseline=ds.stereo_baseline if init == "stereo" else None, seed=seed)
    traj = _Trajectory(ds)
    scale_known = True
    if init == "stereo":
        if ds.right is None:
            raise VoError(f"{ds.root}: --init stereo needs right images (image_r/)")
        start = _metric_start(ds, slam, init, traj, say)
    elif init == "depth":
        if ds.depth_image(0) is None:
            raise VoError(f"{ds.root}: --init depth needs a depth image for the first frame (depth.txt)")
        start = _metric_start(ds, slam, init, traj, say)
    elif init == "tags":
        if "tag_grid" not in ds.extras:
            raise VoError(f"{ds.root}: --init tags needs a 'tag_grid' block in the camera YAML")
        grid = TagGrid.from_spec(ds.extras["tag_grid"])
        img = ds.image(0)
        extra = slam.tracker.detect(img, slam.cfg.max_landmarks)
        s = init_from_tags(img, ds.camera, grid, extra_pixels=extra)
        say(f"tags {s.info['tags']} seen; grid pose from {len(s.pixels)} landmarks, "
            f"{s.info['iterations']} iterations, residual {s.info['residual_px']:.2f} px")
        n = slam.initialise(img, s.pixels, s.points_cam, s.pose_wc)
        traj.put(0, "init", slam.pose_wc, n)
        start = 1
    else:
        start = _two_view_start(ds, slam, 0, essential_frames, traj, "init", np.eye(4), 1.0, say)
        if start is None:
            raise VoError(f"{ds.root}: essential initialisation lost the features in the first "
                          f"{essential_frames} frames")
        scale_known = False
    results: list[FrameResult] = []
    earlier_refs = 0  # reference frames of the runs before the last start
    kept_w, kept_desc = np.zeros((0, 3)), np.zeros((0, 32), np.uint8)  # landmarks of earlier runs (world)
    restarted_at = None  # first frame of the current run while it is not yet relocalised
    last_seen = slam.world_landmarks()
    i = start
    try:
        while i < len(ds):
            r = slam.process(ds.image(i), ds.right_image(i) if init == "stereo" else None,
                             ds.depth_image(i) if init == "depth" else None)
            results.append(r)
            if r.ok:
                traj.put(i, "tracked", r.pose_wc, r.tracked, r.inliers)
                traj.adjust(slam, i)
                last_seen = slam.world_landmarks()  # what to relocalise against should this run be lost
                if restarted_at is not None and _relocalise(ds, slam, i, restarted_at, kept_w, kept_desc, traj,
                                                             say, scale_known):
                    restarted_at = None
            if i % 10 == 0 or i == len(ds) - 1 or not r.ok:
                say(f"frame {i}/{len(ds) - 1}: {'ok' if r.ok else 'LOST'} landmarks {r.tracked} "
                    f"inliers {r.inliers} iterations {r.iterations} residual {r.residual_px:.2f} px references "
                    f"{earlier_refs + len(slam.references)}")
            i += 1
            if r.ok:
                continue
            refs = len(slam.references)
            w, d = last_seen
            kept_w, kept_desc = np.vstack((kept_w, w))[-MAX_KEPT:], np.vstack((kept_desc, d))[-MAX_KEPT:]
            last_seen = (np.zeros((0, 3)), np.zeros((0, 32), np.uint8))  # kept once, not once per lost frame
            nxt = _restart(ds, slam, init, i - 1, traj, essential_frames, say)
            if nxt is None:
                traj.put(i - 1, "lost", None, r.tracked, r.inliers)
            else:
                earlier_refs += refs
                restarted_at = i - 1
                i = nxt
    except DatasetError as exc:      # an unreadable frame: what was tracked before it is kept
        raise VoStopped(str(exc), traj.result(init, scale_known, earlier_refs + len(slam.references),
                                              results)) from None
    return traj.result(init, scale_known, earlier_refs + len(slam.references), results)


def _metric_init(ds: Dataset, slam: Vslam, init: str, i: int, pose: Optional[np.ndarray] = None
                 ) -> tuple[int, bool]:
    """Start the stereo or depth front end on frame ``i`` at ``pose``: (landmarks, whether they are enough to
    track against: ``min_inliers``, at least 3; a black or uniform frame, or one without depth, gives none)."""
    if init == "stereo":
        n = slam.initialise_stereo(ds.image(i), ds.right_image(i), pose)
    else:
        n = slam.initialise_depth(ds.image(i), ds.depth_image(i), pose) if ds.depth_image(i) is not None else 0
    return n, n >= max(slam.cfg.min_inliers, 3)


def _metric_start(ds: Dataset, slam: Vslam, init: str, traj: _Trajectory, say) -> int:
    """The first start of a stereo or depth run: on the first frame that gives at least ``min_inliers``
    landmarks (a black or uniform frame gives none: nothing could be tracked against it), the frames before
    it lost. Returns the next frame to process."""
    for i in range(len(ds)):
        n, started = _metric_init(ds, slam, init, i)
        if started:
            traj.put(i, "init", slam.pose_wc, n)
            return i + 1
        say(f"frame {i}: {n} landmarks, fewer than min_inliers ({slam.cfg.min_inliers}) to start on; "
            "the next frame is tried")
        traj.put(i, "lost", None, n)
    raise VoError(f"{ds.root}: no frame gives the {slam.cfg.min_inliers} landmarks a start needs")


def _relocalise(ds: Dataset, slam: Vslam, i: int, since: int, kept_w: np.ndarray, kept_desc: np.ndarray,
                traj: _Trajectory, say, scale_known: bool = True) -> bool:
    """Look for landmarks of the earlier runs in frame ``i``; when found, move the current run (and its
    poses since the restart at ``since``) onto them: rigidly, or for a monocular run by a similarity
    (its restart took the scale from the last speed, which the kept landmarks now correct).
    True when relocalised."""
    if not scale_known:
        sim = slam.similarity_to(kept_w, kept_desc, RELOCALISE_MIN_INLIERS)
        if sim is not None:
            s, R, t, n = sim
            slam.correct_world_similarity(s, R, t)
            _move_poses(traj, since, i, s, R, t)
            say(f"frame {i}: relocalised against {n} landmarks kept from before the restart at frame {since} "
                f"(scale x{s:.3f})")
            return True
    pose = slam.relocalise(ds.image(i), kept_w, kept_desc, RELOCALISE_MIN_INLIERS)
    if pose is None:
        return False
    C = pose @ np.linalg.inv(slam.pose_wc)
    slam.correct_world(C)
    _move_poses(traj, since, i, 1.0, C[:3, :3], C[:3, 3])
    say(f"frame {i}: relocalised against the landmarks kept from before the restart at frame {since} "
        f"(moved {np.linalg.norm(C[:3, 3]):.3f} m)")
    return True


def _move_poses(traj: _Trajectory, since: int, i: int, s: float, R: np.ndarray, t: np.ndarray) -> None:
    """The run's poses of frames ``since``..``i`` moved by the world correction X' = s R X + t."""
    for k in range(since, i + 1):
        if k in traj.poses:
            traj.poses[k] = similarity_moved(traj.poses[k], s, R, t)


def _restart(ds: Dataset, slam: Vslam, init: str, i: int, traj: _Trajectory, essential_frames: int, say
             ) -> Optional[int]:
    """Start the front end again at lost frame ``i``; the next frame to process, or None (still lost)."""
    pose = traj.predicted(i)
    if init == "stereo" or (init == "depth" and ds.depth_image(i) is not None):
        n, started = _metric_init(ds, slam, init, i, pose)
    else:  # monocular (or no depth here): two views, at the speed of the last good frames
        speed = traj.speed(i)
        # on failure the front end keeps what it still tracks and the next frame tries again
        return _two_view_start(ds, slam, i, essential_frames, traj, "reinit", pose, speed, say) if speed > 0 else None
    if not started:
        return None
    say(f"frame {i}: re-initialised with {n} landmarks at the predicted pose")
    traj.put(i, "reinit", slam.pose_wc, n)
    return i + 1


def _parallax_px(camera, rays0: np.ndarray, px: np.ndarray, R_model: np.ndarray) -> float:
    """Median image motion of ``rays0`` -> ``px`` beyond the rotation between the views: the rotation
    from the essential matrix of these correspondences (the motion model's ``R_model`` if that fails)."""
    R = R_model
    rays1 = camera.rays(px)
    u0, u1 = rays0[:, :2] / rays0[:, 2:], rays1[:, :2] / rays1[:, 2:]
    f = float(camera.fx)
    E, inl = cv2.findEssentialMat(u0, u1, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=1.0 / f)
    if E is not None and E.shape == (3, 3):
        n, R_e, _, _ = cv2.recoverPose(E, u0, u1, np.eye(3), mask=inl)
        if n >= 8:
            R = R_e
    rotated, _ = camera.project(rays0 @ R.T)
    return float(np.median(np.linalg.norm(px - rotated, axis=1)))


def _two_view_start(ds: Dataset, slam: Vslam, first: int, max_frames: int, traj: _Trajectory, state: str,
                    pose_wc0: np.ndarray, speed: float, say) -> Optional[int]:
    """Track corners from frame ``first`` until the parallax is enough, then a two-view start whose
    baseline is ``speed`` per frame (1 for the very first start: unit baseline). Frames in between get
    their pose from the two-view landmarks. Returns the next frame to process, None if it failed."""
    img0 = ds.image(first)
    px0 = slam.tracker.detect(img0, slam.cfg.max_landmarks)
    rays0 = ds.camera.rays(px0)
    px, keep, prev = px0.copy(), np.ones(len(px0), bool), img0
    seen: dict[int, np.ndarray] = {}  # frame -> pixels of the features kept, for the poses in between
    last = min(first + max_frames, len(ds) - 1)
    if last <= first or len(px0) < 8:
        return None
    for k in range(first + 1, last + 1):
        img = ds.image(k)
        nxt, ok = slam.tracker.track(prev, img, px[keep])
        idx = np.flatnonzero(keep)
        keep[idx[~ok]] = False
        px[idx[ok]] = nxt[ok]
        seen[k] = px.copy()
        prev = img
        if keep.sum() < 8:
            break
        # Parallax, not flow, makes a two-view start: take out the rotation between the two views (a
        # turn moves every point alike and tells nothing of depth).
        # Start anyway once half of the corners are gone (a turn takes them out of view): waiting longer
        # for parallax would leave too few to start with.
        flow = np.median(np.linalg.norm(px[keep] - px0[keep], axis=1))
        if keep.sum() < 0.5 * len(px0) or (flow > TWO_VIEW_FLOW_PX and _parallax_px(
                ds.camera, rays0[keep], px[keep], traj.rotation(first, k - first)) > TWO_VIEW_PARALLAX_PX):
            break
    if keep.sum() < 8:
        return None
    baseline = 1.0 if state == "init" else speed * (k - first)
    try:
        tv = init_two_view(ds.camera.rays(px0[keep]), ds.camera.rays(px[keep]), scale=baseline)
    except ValueError:
        return None
    v = tv.valid
    if v.sum() < 8:
        return None
    say(f"two-view {'initialisation' if state == 'init' else 're-initialisation'} frames {first}-{k}: {tv.model} "
        f"(E singular values {np.round(tv.singular_values, 3)}, null-space ratio {tv.null_space_ratio:.2f}), "
        f"{int(v.sum())} landmarks, " + ("unit baseline" if state == "init" else f"baseline {baseline:.3f} m "
                                          "from the last speed"))
    X1 = tv.depths1[v, None] * ds.camera.rays(px0[keep][v])
    X2 = X1 @ tv.R.T + tv.T
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = tv.R, tv.T  # first -> frame k camera
    traj.put(first, state, pose_wc0, int(v.sum()))
    for j in range(first + 1, k):  # the frames in between: pose against the two-view landmarks
        rays = ds.camera.rays(seen[j][keep][v])
        try:
            est = recover_motion_robust(X1, rays, prior=(tv.R, tv.T * (j - first) / (k - first)),
                                        threshold=slam.cfg.inlier_threshold_px / ds.camera.fx, angular=True)
        except ValueError:
            continue
        if est.inliers.sum() >= slam.cfg.min_inliers:
            Mj = np.eye(4)
            Mj[:3, :3], Mj[:3, 3] = est.R, est.T
            traj.put(j, state, pose_wc0 @ np.linalg.inv(Mj), int(v.sum()), int(est.inliers.sum()))
    pose_k = pose_wc0 @ np.linalg.inv(M)
    slam.prev = None
    slam.initialise(img, px[keep][v], X2, pose_k, estimated=True)
    traj.put(k, state, slam.pose_wc, int(v.sum()))
    traj.adjust(slam, k)
    return k + 1
