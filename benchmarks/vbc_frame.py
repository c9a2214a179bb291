"""Per-frame cost of VBC repeat (track + match + pose) at 640x480 with ~200 features, beside a plain OpenCV KLT tracker.

Two scenes, each with its peer measured in the same run on the same frames: a plain OpenCV
KLT tracker as real trackers run it (``KltPeer``: goodFeaturesToTrack(200) once, then
calcOpticalFlowPyrLK frame to frame with a forward-backward check, new corners only when
the live tracks fall below 85 % of 200, masked away from the live tracks):

1. Rendered: the simulated room (drivers/sim/camera.py, 640x480, f = 400, noise 2 grey
   levels), a route taught with <= 200 tracks at 14 Hz and 0.25 m/s (straight, 90 degree
   turn, straight), repeated in closed loop from a 0.3 m / 10 degree offset: the robot's case.
2. Real: KITTI odometry 06 (../shared/data/kitti06_stereo), 1226x370 resized to 640x480
(anisotropic; the intrinsics are scaled to match). A route is taught on the LEFT images
with the ground-truth poses as odometry (max 200 tracks; the mount pitched 1.22 deg, the
camera's tilt against its travel, kitti_util.mount_pitch_from_travel); it is then repeated
on the RIGHT images, i.e. from a 0.537 m lateral offset, through RepeatStage.process (KLT
tracking with forward-backward check, ORB re-acquisition when short, VBC pose,
keyframe switching). The peer is ``KltPeer`` on the same frames.
3. Real, native resolution, as tests/test_repeat_real.py holds it: the same teach and repeat
on the replay camera's 1226x370 frames, repeated from the first frame and from 1-3 frames
further along; per start: median / p95 lateral and heading error relative to the chosen
keyframe, keyframe right, and ms per frame beside ``KltPeer`` on the same right images.
Single-threaded: cv2.setNumThreads(1). Also prints the KITTI frame-to-frame accuracy.

    .venv/bin/python benchmarks/vbc_frame.py [--passes 4]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from kitti_util import (levelled_odometry, mount_pitch_from_travel, read_calib, read_poses,  # noqa: E402
                        repeat_right, teach_kitti, vbc_frame_pair_errors)
from vbnav.control.route import Route  # noqa: E402
from vbnav.control.stages.repeat import RepeatStage
from vbnav.control.stages.teach import TeachStage
from vbnav.control.config.vbc import VBCConfig  # noqa: E402
from vbnav.drivers.camera import Frame  # noqa: E402
from vbnav.vision.camera_model import PinholeCamera  # noqa: E402
from vbnav.vision.geometry import CameraMount, Pose2  # noqa: E402

W, H = 640, 480
PEER_NAME = "OpenCV KLT tracker (fb-checked LK, GFTT(200) only below 170 tracks)"


class KltPeer:
    """A plain OpenCV KLT tracker, the peer: what our repeat frame costs beyond tracking.

    Tracks from the previous frame with pyramidal LK (15 px window, 3 levels, as ours; OpenCV's
    default stopping rule, 30 iterations or 0.01 px, where ours stops at 10 or 0.03 px and starts
    the backward pass at the origin), keeps a track when the backward pass lands within ``fb_px`` of
    its start, and detects new corners only when fewer than ``redetect_below`` tracks live, in a mask
    that keeps ``min_distance`` px away from them. It matches nothing to keyframes and computes no pose.
    """

    LK = dict(winSize=(15, 15), maxLevel=3, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))

    def __init__(self, max_corners: int = 200, redetect_below: int = 170, min_distance: int = 10,
                 fb_px: float = 1.0):
        self.max_corners, self.redetect_below = max_corners, redetect_below
        self.min_distance, self.fb_px = min_distance, fb_px
        self.prev: np.ndarray | None = None
        self.pts = np.zeros((0, 1, 2), np.float32)
        self.detections = 0

    def track(self, img: np.ndarray) -> int:
        """Follow the tracks into ``img``, re-detect if too few survived; the number of live tracks."""
        if self.prev is not None and len(self.pts):
            nxt, st, _ = cv2.calcOpticalFlowPyrLK(self.prev, img, self.pts, None, **self.LK)
            back, st_back, _ = cv2.calcOpticalFlowPyrLK(img, self.prev, nxt, None, **self.LK)
            fb = np.linalg.norm((back - self.pts).reshape(-1, 2), axis=1)
            self.pts = nxt[(st.ravel() == 1) & (st_back.ravel() == 1) & (fb < self.fb_px)]
        if len(self.pts) < self.redetect_below:
            mask = np.full(img.shape[:2], 255, np.uint8)
            for x, y in self.pts.reshape(-1, 2):
                cv2.circle(mask, (int(round(x)), int(round(y))), self.min_distance, 0, -1)
            new = cv2.goodFeaturesToTrack(img, self.max_corners - len(self.pts), 0.01, self.min_distance, mask=mask)
            if new is not None:
                self.pts = np.concatenate((self.pts, new.astype(np.float32)))
            self.detections += 1
        self.prev = img
        return len(self.pts)


def data_dir() -> Path:
    sys.path.insert(0, str(ROOT))
    from conftest import data_dir as shared   # the same lookup as the tests' shared_data fixture
    return shared() / "kitti06_stereo"


def load(root: Path, mount: CameraMount):
    calib = read_calib(root / "calib.txt")
    poses = read_poses(root / "poses.txt")
    names = sorted(p.name for p in (root / "image_l").iterdir())
    sx, sy = W / 1226.0, H / 370.0
    cam = PinholeCamera(W, H, calib.fx * sx, calib.fx * sy, (calib.cx + 0.5) * sx - 0.5, (calib.cy + 0.5) * sy - 0.5)
    rd = lambda side, n: cv2.resize(cv2.imread(str(root / side / n), cv2.IMREAD_GRAYSCALE), (W, H),
                                    interpolation=cv2.INTER_AREA)
    left = [rd("image_l", n) for n in names]
    right = [rd("image_r", n) for n in names]
    return cam, left, right, levelled_odometry(poses, mount), calib.baseline


def teach(cam, images, odom, cfg, mount):
    st = TeachStage(cam, mount, cfg)
    for i, (img, p) in enumerate(zip(images, odom)):
        st.process(Frame(img, i, i), p)
    st.finish()
    return Route(None, "kitti", "", cam, mount, True, st.pop_keyframes())


def rendered_scene(passes: int):
    """Closed-loop repeat in the simulated room; times RepeatStage.process and the peer per frame."""
    from test_teach_repeat_rendered import (DT, FRAME_EVERY, START, ControlContext, RepeatController,
                                            WheelState, World, camera, drive, teach_route)
    world = World.room(seed=1)
    route, _ = teach_route(world)
    ours, peer, peer_tracks = [], [], []
    for _ in range(passes):
        cam = camera(world)
        cfg = VBCConfig()
        stage, ctl, klt = RepeatStage(route, cfg), RepeatController(route, cfg), KltPeer()
        true, odom, est = START.compose(Pose2(0.3, 0.0, math.radians(10))), Pose2(), None
        for step in range(int(40 / DT)):
            if step % FRAME_EVERY == 0:
                frame = cam.render_frame(true, step, step)
                t0 = time.perf_counter()
                est = stage.process(frame, odom)
                ours.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                peer_tracks.append(klt.track(frame.image))
                peer.append(time.perf_counter() - t0)
            cmd = ctl.update(ControlContext(step, DT, odom, WheelState(step, (0.0, 0.0), (0.0, 0.0)),
                                            {"vbc": est}, step))
            if ctl.finished:
                break
            true, odom = drive(true, cmd.v, cmd.w, DT), drive(odom, cmd.v, cmd.w, DT)
    return ours, peer, len(route.keyframes), stage.stats, (peer_tracks, klt.detections)


def components_at_200(passes: int):
    """Each stage at exactly 200 features on rendered frames: tracking, re-acquisition, pose."""
    from test_teach_repeat_rendered import CAM, START, camera, drive, World
    from vbc_scenes import bearings, levelled_points, room_points
    from vbnav.vision.features import FeatureTracker, describe, detect_and_describe, geometric_inliers, \
        match_descriptors
    from vbnav.vision.vbc import estimate_pose
    cam = camera(World.room(seed=1))
    frames, p = [], START
    for i in range(60):
        frames.append(cam.render_frame(p, i, i).image)
        p = drive(p, 0.25, -0.2, 1 / 14)
    t_track, t_match, t_pose = [], [], []
    for _ in range(passes):
        tr = FeatureTracker(max_features=200, win_size=11)
        tr.track(frames[0])
        for img in frames[1:]:
            t0 = time.perf_counter()
            tr.track(img)
            t_track.append(time.perf_counter() - t0)
        kf_desc, _ = describe(frames[0], FeatureTracker(max_features=200).track(frames[0]).pts)
        for img in frames[10::5]:
            t0 = time.perf_counter()
            pts, desc = detect_and_describe(img, 500)
            pairs = match_descriptors(desc, kf_desc)
            if len(pairs) >= 8:
                geometric_inliers(CAM.rays(pts[pairs[:, 0]]), CAM.rays(pts[pairs[:, 0]]), 2.0 / 400)
            t_match.append(time.perf_counter() - t0)
    rng = np.random.default_rng(0)
    mount = CameraMount(0.25, 0.10)
    for _ in range(30 * passes):
        pts = room_points(rng, 200, mount)
        truth = Pose2(rng.normal(0, 0.1), rng.normal(-0.2, 0.1), rng.normal(0, 0.1))
        a0, b0 = bearings(Pose2(), mount, pts)
        a1, b1 = bearings(truth, mount, pts)
        a1 += rng.normal(0, 1 / 400, 200)
        b1 += rng.normal(0, 1 / 400, 200)
        bad = rng.random(200) < 0.2
        a1[bad] += rng.uniform(-0.1, 0.1, bad.sum())
        w = 1 / levelled_points(Pose2(), mount, pts)[:, 1]
        guess = truth.compose(Pose2(0.01, 0.01, 0.005))          # the last fix moved by odometry
        t0 = time.perf_counter()
        estimate_pose(a0, b0, w, a1, b1, forward=0.10, sigma=1 / 400, initial=guess)
        t_pose.append(time.perf_counter() - t0)
    return t_track, t_match, t_pose


def native_repeat(root: Path) -> None:
    """Section 3: the test's teach-left / repeat-right at native resolution, with the peer on the same frames."""
    taught = teach_kitti(root)
    right = [f.right for f in taught.frames]
    print(f"[KITTI native] {right[0].shape[1]}x{right[0].shape[0]}, mount pitch "
          f"{math.degrees(taught.route.mount.pitch):.2f} deg, {len(taught.route.keyframes)} keyframes; repeat on the "
          f"right images (true offset {taught.baseline:.3f} m, heading 0) starting s frames along the route")
    for shift in (0, 1, 2, 3):
        r = repeat_right(taught, shift)
        klt, t_peer = KltPeer(), []
        for img in right[shift:]:
            t0 = time.perf_counter()
            klt.track(img)
            t_peer.append(time.perf_counter() - t0)
        print(f"  s={shift}: fixes ok {r.ok.sum()}/{len(r.ok)}, |lateral error| median "
              f"{1e3 * np.median(r.lateral_err):.1f} mm p95 {1e3 * np.percentile(r.lateral_err, 95):.1f} mm, "
              f"|heading error| median {np.median(r.heading_err):.3f} deg p95 {np.percentile(r.heading_err, 95):.3f} "
              f"deg, keyframe right {r.keyframe_right.sum()}/{len(r.ok)}; VBC repeat frame median "
              f"{pct(r.seconds, 50):.1f} ms, {PEER_NAME} {pct(t_peer, 50):.1f} ms, ratio "
              f"{pct(r.seconds, 50) / pct(t_peer, 50):.2f}")


def pct(a, q):
    return float(np.percentile(np.asarray(a) * 1e3, q))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--passes", type=int, default=4, help="repeats of the 51-frame sequence")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    root = data_dir()
    if not root.is_dir():
        print(f"missing {root}")
        return 2
    ours, peer, n_kf, stats, (peer_tracks, peer_detections) = rendered_scene(max(1, args.passes // 2))
    print(f"[rendered room] {n_kf} keyframes, {len(ours)} repeat frames, cv2 threads = {cv2.getNumThreads()}")
    print(f"VBC repeat frame (track + match + pose): median {pct(ours, 50):.2f} ms, p99 {pct(ours, 99):.2f} ms")
    print(f"{PEER_NAME}: median {pct(peer, 50):.2f} ms, p99 {pct(peer, 99):.2f} ms, median "
          f"{np.median(peer_tracks):.0f} tracks, corners detected in {peer_detections} of {len(peer)} frames "
          f"(last pass)")
    print(f"ratio VBC / OpenCV KLT tracker (median): {pct(ours, 50) / pct(peer, 50):.2f}")
    tt, tm, tp = components_at_200(max(1, args.passes // 2))
    print(f"  components at 200 features: KLT tracking (fb-checked, re-detection when short) median "
          f"{pct(tt, 50):.2f} ms p99 {pct(tt, 99):.2f}; VBC pose (200 landmarks, 20 % outliers, warm start) "
          f"median {pct(tp, 50):.2f} ms p99 {pct(tp, 99):.2f}; re-acquisition (500 ORB vs 200) median "
          f"{pct(tm, 50):.2f} ms")
    print()
    mount = CameraMount(height=1.65, pitch=mount_pitch_from_travel(read_poses(root / "poses.txt")))
    cam, left, right, odom, baseline = load(root, mount)
    cfg = VBCConfig(max_features=200, keyframe_distance_m=2.5, min_distance_px=10, reacquire_below=60)
    route = teach(cam, left, odom, cfg, mount)

    t_ours, t_peer, lat_err, head_err, n_agree, t_match, peer_tracks = [], [], [], [], [], [], []
    for _ in range(args.passes):
        stage = RepeatStage(route, cfg)
        for i, (img, p) in enumerate(zip(right, odom)):
            before = stage.stats["reacquired"]
            t0 = time.perf_counter()
            est = stage.process(Frame(img, i, i), p)
            dt = time.perf_counter() - t0
            t_ours.append(dt)
            if stage.stats["reacquired"] != before:
                t_match.append(dt)
            if est.ok:
                n_agree.append(est.value.n_agree)
                # truth: the right camera is `baseline` to the right of the left camera at the same time;
                # relative to keyframe k (a left pose) it is at kf^-1 * (odom_i * (baseline, 0, 0)).
                kf = route.keyframes[est.value.keyframe]
                truth = kf.odom.between(p.compose(Pose2(baseline, 0.0, 0.0)))
                lat_err.append(abs(est.value.pose.x - truth.x))
                head_err.append(abs(math.degrees(math.remainder(est.value.pose.theta - truth.theta, 2 * math.pi))))
        # peer: a plain OpenCV KLT tracker on the same frames
        klt = KltPeer()
        for img in right:
            t0 = time.perf_counter()
            peer_tracks.append(klt.track(img))
            t_peer.append(time.perf_counter() - t0)

    med_o, med_p = pct(t_ours, 50), pct(t_peer, 50)
    print(f"[KITTI] images: KITTI 06 resized to {W}x{H}; route taught on left images ({len(route.keyframes)} keyframes, "
          f"<= {cfg.max_features} tracks), repeated on right images (0.537 m lateral offset); "
          f"{len(t_ours)} frames, cv2 threads = {cv2.getNumThreads()}")
    print(f"VBC repeat frame (track + match + pose): median {med_o:.2f} ms, p99 {pct(t_ours, 99):.2f} ms, "
          f"median landmarks agreeing {np.median(n_agree):.0f}")
    if t_match:
        steady = [t for t in t_ours if t not in set(t_match)]
        print(f"  frames with descriptor re-acquisition: {len(t_match)} of {len(t_ours)}, median "
              f"{pct(t_match, 50):.2f} ms; the others (track + pose): median {pct(steady, 50):.2f} ms")
    print(f"{PEER_NAME}: median {med_p:.2f} ms, p99 {pct(t_peer, 99):.2f} ms, median "
          f"{np.median(peer_tracks):.0f} tracks, corners detected in {klt.detections} of {len(right)} frames "
          f"(last pass)")
    print(f"ratio VBC / OpenCV KLT tracker (median): {med_o / med_p:.2f}")
    print(f"repeat from the right camera: |lateral error| median {1e3 * np.median(lat_err):.1f} mm, p95 "
          f"{1e3 * np.percentile(lat_err, 95):.1f} mm (true offset {baseline:.3f} m), |heading error| median "
          f"{np.median(head_err):.3f} deg p95 {np.percentile(head_err, 95):.3f} deg, fixes ok "
          f"{len(lat_err)}/{len(t_ours)}")
    native_repeat(root)
    e = vbc_frame_pair_errors(root)
    print(f"KITTI 06 frame-to-frame VBC with stereo heights (50 pairs, full resolution): median translation "
          f"error {100 * np.median(e[:, 0]):.2f} % of distance, median heading error {np.median(e[:, 1]):.4f} deg")
    return 0


if __name__ == "__main__":
    sys.exit(main())
