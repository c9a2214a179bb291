"""``vbnav vo`` against an OpenCV peer on every real sequence with ground truth, in one run.

Peer (the "afternoon baseline" of issue 13), written here and sharing nothing with vbnav's
tracker: Shi-Tomasi corners (cv2.goodFeaturesToTrack), plain pyramidal KLT
(cv2.calcOpticalFlowPyrLK, no forward-backward check), cv2.solvePnPRansac of every frame
against a growing map of 3D points. The map starts and grows by
- stereo: corners matched left -> right by KLT on the same rows, depth from disparity;
- depth: corners back-projected with the depth image (where there is one);
- monocular: a two-view start (cv2.findEssentialMat + recoverPose once the median flow
  passes 20 px), new corners triangulated (cv2.triangulatePoints) between the frame where
  they were first seen and the current one once their rays part by 2 degrees (kept if they
  reproject within 2 px in both views).

Printed per sequence: frames with a pose, APE (translation RMSE after SE(3) alignment, or
Sim(3) for monocular runs whose scale is unknown), ms per frame, and the ratio vbnav / peer.

    VBNAV_DATA=../shared/data .venv/bin/python benchmarks/vo_real.py [--data DIR] [--only NAME ...] [--seeds N]

``--seeds N`` runs vbnav again with RANSAC seeds 1..N-1 and prints the spread of its APE: a monocular
run's figure is one draw (on vo_turns_kitti03 the seeds move it by more than most code changes do).

Sequences (those of the data folder that have ground truth): kitti06_stereo (stereo, and its
left images alone, monocular), vo_turns_kitti03 (monocular), desk_rgbd (tag grid, and depth of
its first 5 frames), room_rgbd5 (RGB-D, 5 frames). indoor_stereo/euroc_v101 is left out: three
stereo pairs 2.35 s apart are not a sequence to track.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from desk_view import build_desk_view  # noqa: E402

from vbnav.control.trajectory_metrics import ate_rmse, write_tum  # noqa: E402
from vbnav.control.vo import run_vo  # noqa: E402
from vbnav.drivers.datasets import open_dataset  # noqa: E402
from vbnav.vision.geometry import matrix_from_quat  # noqa: E402

LK = dict(winSize=(21, 21), maxLevel=3, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))


def _gftt(img, n, existing=None):
    mask = np.full(img.shape[:2], 255, np.uint8)
    if existing is not None:
        for x, y in np.asarray(existing).reshape(-1, 2):
            cv2.circle(mask, (int(x), int(y)), 10, 0, -1)
    p = cv2.goodFeaturesToTrack(img, n, 0.01, 10, mask=mask, blockSize=7)
    return np.zeros((0, 2), np.float32) if p is None else p.reshape(-1, 2).astype(np.float32)


def _klt(a, b, p):
    if len(p) == 0:
        return p, np.zeros(0, bool)
    q, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p.reshape(-1, 1, 2).astype(np.float32), None, **LK)
    q = q.reshape(-1, 2)
    h, w = b.shape[:2]
    inside = (q[:, 0] >= 0) & (q[:, 0] < w - 1) & (q[:, 1] >= 0) & (q[:, 1] < h - 1)
    return q, (st.ravel() == 1) & inside


class PeerVo:
    """The OpenCV peer: map points X (world), their current pixels, PnP every frame."""

    def __init__(self, ds, mode: str, max_points: int = 400, min_points: int = 250):
        self.ds, self.mode, self.K = ds, mode, ds.camera.K
        self.max_points, self.min_points = max_points, min_points
        self.X = np.zeros((0, 3))
        self.px = np.zeros((0, 2), np.float32)
        self.cand_px = np.zeros((0, 2), np.float32)  # monocular: waiting for parallax
        self.cand_px0 = np.zeros((0, 2), np.float32)
        self.cand_pose = np.zeros((0, 4, 4))  # camera-from-world at first sight

    def _add_metric(self, i, img, cw):
        """Stereo / depth: new corners with a metric depth, into the world with camera-from-world cw."""
        ds, cam = self.ds, self.ds.camera
        px = _gftt(img, self.max_points - len(self.X), self.px)
        if len(px) == 0:
            return
        if self.mode == "stereo":
            pr, ok = _klt(img, ds.right_image(i), px)
            d = px[:, 0] - pr[:, 0]
            ok &= (np.abs(pr[:, 1] - px[:, 1]) < 1.0) & (d > 0.5)
            z = np.where(ok, cam.fx * ds.stereo_baseline / np.maximum(d, 1e-6), 0)
            ok &= z < 80 * ds.stereo_baseline
        else:
            depth = ds.depth_image(i)
            if depth is None:
                return self._add_mono(img, cw)
            ij = np.round(px).astype(int)
            z = depth[np.clip(ij[:, 1], 0, depth.shape[0] - 1), np.clip(ij[:, 0], 0, depth.shape[1] - 1)]
            ok = z > 0
        px, z = px[ok], z[ok]
        Xc = np.column_stack(((px[:, 0] - cam.cx) / cam.fx * z, (px[:, 1] - cam.cy) / cam.fy * z, z))
        wc = np.linalg.inv(cw)
        self.X = np.vstack((self.X, Xc @ wc[:3, :3].T + wc[:3, 3]))
        self.px = np.vstack((self.px, px))

    def _add_mono(self, img, cw):
        """Triangulate candidates whose rays part by >= 2 degrees; top the candidates up."""
        if len(self.cand_px):
            Kinv = np.linalg.inv(self.K)
            r0 = np.column_stack((self.cand_px0, np.ones(len(self.cand_px0)))) @ Kinv.T
            r1 = np.column_stack((self.cand_px, np.ones(len(self.cand_px)))) @ Kinv.T
            r0w = np.einsum("nji,nj->ni", self.cand_pose[:, :3, :3], r0)  # R^T r: world directions
            r1w = r1 @ cw[:3, :3]
            cosang = np.sum(r0w * r1w, 1) / np.linalg.norm(r0w, axis=1) / np.linalg.norm(r1w, axis=1)
            ready = cosang < np.cos(np.deg2rad(2.0))
            new = []
            for k in np.flatnonzero(ready):
                P0 = self.K @ self.cand_pose[k, :3]
                P1 = self.K @ cw[:3]
                Xh = cv2.triangulatePoints(P0, P1, self.cand_px0[k].reshape(2, 1).astype(float),
                                           self.cand_px[k].reshape(2, 1).astype(float)).ravel()
                X = Xh[:3] / Xh[3]
                x0 = P0 @ np.append(X, 1.0)
                x1 = P1 @ np.append(X, 1.0)
                if x0[2] > 0 and x1[2] > 0 and np.linalg.norm(x0[:2] / x0[2] - self.cand_px0[k]) < 2.0 \
                        and np.linalg.norm(x1[:2] / x1[2] - self.cand_px[k]) < 2.0:
                    new.append((X, self.cand_px[k]))
            if new:
                self.X = np.vstack((self.X, [n[0] for n in new]))
                self.px = np.vstack((self.px, [n[1] for n in new]))
            keep = ~ready
            self.cand_px, self.cand_px0, self.cand_pose = self.cand_px[keep], self.cand_px0[keep], self.cand_pose[keep]
        room = 300 - len(self.cand_px)
        if room > 0 and len(self.X) < self.max_points:
            px = _gftt(img, room, np.vstack((self.px, self.cand_px)))
            self.cand_px = np.vstack((self.cand_px, px))
            self.cand_px0 = np.vstack((self.cand_px0, px))
            self.cand_pose = np.concatenate((self.cand_pose, np.repeat(cw[None], len(px), 0)))

    def _start_mono(self):
        """Two-view start: track corners of frame 0 until the median flow passes 20 px."""
        ds = self.ds
        img0 = ds.image(0)
        p0 = _gftt(img0, self.max_points)
        p, keep, prev = p0.copy(), np.ones(len(p0), bool), img0
        for k in range(1, min(10, len(ds) - 1) + 1):
            img = ds.image(k)
            q, ok = _klt(prev, img, p)
            keep &= ok
            p, prev = q, img
            if np.median(np.linalg.norm(p[keep] - p0[keep], axis=1)) > 20:
                break
        E, inl = cv2.findEssentialMat(p0[keep], p[keep], self.K, cv2.RANSAC, 0.999, 1.0)
        _, R, t, inl = cv2.recoverPose(E, p0[keep], p[keep], self.K, mask=inl)
        good = inl.ravel() > 0
        P0, P1 = self.K @ np.eye(4)[:3], self.K @ np.hstack((R, t))
        Xh = cv2.triangulatePoints(P0, P1, p0[keep][good].T.astype(float), p[keep][good].T.astype(float))
        X = (Xh[:3] / Xh[3]).T
        front = (X[:, 2] > 0) & ((X @ R.T + t.ravel())[:, 2] > 0)
        self.X, self.px = X[front], p[keep][good][front]
        cw = np.eye(4)
        cw[:3, :3], cw[:3, 3] = R, t.ravel()
        return k, img, cw

    def run(self):
        """(frames with a pose, world-from-camera poses)."""
        ds = self.ds
        if self.mode == "mono":
            start, prev, cw = self._start_mono()
            frames, poses = [0, start], [np.eye(4), np.linalg.inv(cw)]
        else:
            start, prev, cw = 0, ds.image(0), np.eye(4)
            self._add_metric(0, prev, cw)
            frames, poses = [0], [np.eye(4)]
        for i in range(start + 1, len(ds)):
            img = ds.image(i)
            self.px, ok = _klt(prev, img, self.px)
            self.X, self.px = self.X[ok], self.px[ok]
            if len(self.cand_px):
                self.cand_px, okc = _klt(prev, img, self.cand_px)
                self.cand_px, self.cand_px0, self.cand_pose = self.cand_px[okc], self.cand_px0[okc], self.cand_pose[okc]
            prev = img
            if len(self.X) < 6:
                continue
            rv0, _ = cv2.Rodrigues(cw[:3, :3])
            good, rv, tv, inl = cv2.solvePnPRansac(self.X, self.px.astype(float), self.K, None, rv0.copy(),
                                                   cw[:3, 3].reshape(3, 1).copy(), True, 200, 2.0, 0.999)
            if not good or inl is None or len(inl) < 6:
                continue
            m = np.zeros(len(self.X), bool)
            m[inl.ravel()] = True
            self.X, self.px = self.X[m], self.px[m]
            cw = np.eye(4)
            cw[:3, :3], cw[:3, 3] = cv2.Rodrigues(rv)[0], tv.ravel()
            frames.append(i)
            poses.append(np.linalg.inv(cw))
            if self.mode == "mono":
                self._add_mono(img, cw)
            elif len(self.X) < self.min_points:
                self._add_metric(i, img, cw)
        return frames, np.array(poses)


def room_view(src: Path, dst: Path) -> Path:
    """TUM-layout view of room_rgbd5: rgb.txt, depth.txt, groundtruth.txt, camera.yaml (1 s apart)."""
    dst.mkdir(parents=True, exist_ok=True)
    rows = np.loadtxt(src / "pose.txt").reshape(-1, 7)
    rgb, dep, poses = ["# timestamp filename"], ["# timestamp filename"], []
    for k in range(len(rows)):
        for sub, ext, lst in (("color", "png", rgb), ("depth", "pgm", dep)):
            link = dst / f"{sub}_{k + 1}.{ext}"
            if not link.exists():
                link.symlink_to(src / sub / f"{k + 1}.{ext}")
            lst.append(f"{float(k):.6f} {link.name}")
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = matrix_from_quat(rows[k, 3:7]), rows[k, :3]
        poses.append(M)
    (dst / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (dst / "depth.txt").write_text("\n".join(dep) + "\n")
    write_tum(dst / "groundtruth.txt", np.arange(len(rows), dtype=float), np.array(poses))
    (dst / "camera.yaml").write_text(yaml.safe_dump({"width": 640, "height": 480, "fx": 518.0, "fy": 519.0,
                                                     "cx": 325.5, "cy": 253.5, "depth_scale": 0.001}))
    return dst


def sequences(data: Path, tmp: Path):
    """(name, dataset folder, vbnav --init, peer mode)."""
    yield "kitti06 stereo", data / "kitti06_stereo", "stereo", "stereo"
    yield "kitti06 mono", data / "kitti06_stereo", "essential", "mono"
    yield "kitti03 turns mono", data / "vo_turns_kitti03", "essential", "mono"
    desk = build_desk_view(data / "desk_rgbd", tmp / "desk")
    yield "desk tags / depth", desk, "tags", "depth"
    yield "desk depth", desk, "depth", "depth"
    yield "room_rgbd5 depth", room_view(data / "room_rgbd5", tmp / "room"), "depth", "depth"


def _ape(ds, frames, poses, sim3: bool) -> float:
    ok, g = ds.ground_truth_at(ds.stamps[frames])
    if ok.sum() < 3:
        return float("nan")
    return ate_rmse(poses[ok], g[ok], with_scale=sim3)[0]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    default = Path(os.environ.get("VBNAV_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--data", type=Path, default=default, help="the shared data folder (default $VBNAV_DATA)")
    ap.add_argument("--only", nargs="*", default=None, help="run only sequences whose name contains one of these")
    ap.add_argument("--seeds", type=int, default=1, metavar="N",
                    help="also run vbnav with RANSAC seeds 1..N-1 and print the spread of its APE (monocular "
                         "runs depend on the draws: one figure is one draw)")
    args = ap.parse_args(argv)
    if not args.data.is_dir():
        ap.error(f"--data {args.data}: not a folder")
    print(f"{'sequence':<20} {'frames':>6} | {'vbnav: pose':>11} {'APE':>9} {'ms/fr':>6} | "
          f"{'peer: pose':>10} {'APE':>9} {'ms/fr':>6} | {'APE ratio':>9}")
    with tempfile.TemporaryDirectory() as tmp:
        for name, root, init, mode in sequences(args.data, Path(tmp)):
            if args.only and not any(o in name for o in args.only):
                continue
            ds = open_dataset(root)
            t0 = time.perf_counter()
            res = run_vo(ds, init)
            t_ours = (time.perf_counter() - t0) / len(ds) * 1e3
            ape_ours = _ape(ds, res.frames, res.poses, not res.scale_known)
            t0 = time.perf_counter()
            pf, pp = PeerVo(ds, mode).run()
            t_peer = (time.perf_counter() - t0) / len(ds) * 1e3
            ape_peer = _ape(ds, pf, pp, mode == "mono")
            kind = "Sim3" if not res.scale_known else "SE3"
            print(f"{name:<20} {len(ds):>6} | {len(res.frames):>5} {100 * len(res.frames) / len(ds):>4.0f}% "
                  f"{ape_ours:>7.4f}m {t_ours:>6.0f} | {len(pf):>4} {100 * len(pf) / len(ds):>4.0f}% "
                  f"{ape_peer:>7.4f}m {t_peer:>6.0f} | {ape_ours / ape_peer:>8.2f}x  ({kind})", flush=True)
            if args.seeds > 1:
                apes = [ape_ours]
                for seed in range(1, args.seeds):
                    r = run_vo(ds, init, seed=seed)
                    apes.append(_ape(ds, r.frames, r.poses, not r.scale_known))
                print(f"{'':<20} vbnav APE over RANSAC seeds 0-{args.seeds - 1}: median {np.median(apes):.4f} m, "
                      f"range {min(apes):.4f}-{max(apes):.4f} m", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
