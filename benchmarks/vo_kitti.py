"""Trajectory error on KITTI 06 (frames 0-50): our VSLAM against an OpenCV stereo odometry baseline.

Baseline ("an afternoon's OpenCV stereo odometry"): every frame, Shi-Tomasi
corners in the previous left image, depth from the stereo pair (KLT left ->
right), tracked into the current left image (KLT), cv2.solvePnPRansac
(ITERATIVE refinement), motions chained frame to frame. Ours: ``vbnav vo
--init stereo`` (pose against the reference landmark set). Both printed with
the same SE(3)-aligned ATE and RPE, in one run.

    .venv/bin/python benchmarks/vo_kitti.py [--data ../shared/data]
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import cv2
import numpy as np

from vbnav.control.trajectory_metrics import ate_rmse, rpe
from vbnav.control.vo import run_vo
from vbnav.drivers.datasets import open_dataset
from vbnav.vision.features import KltTracker


def opencv_chained_stereo(ds) -> np.ndarray:
    cam, b = ds.camera, ds.stereo_baseline
    K = cam.K
    tracker = KltTracker()
    poses = [np.eye(4)]
    prev_l, prev_r = ds.image(0), ds.right_image(0)
    for i in range(1, len(ds)):
        cur = ds.image(i)
        px = tracker.detect(prev_l, 500)
        px_r, ok_r = tracker.track(prev_l, prev_r, px, levels=4)
        disp = px[:, 0] - px_r[:, 0]
        ok_r &= (np.abs(px_r[:, 1] - px[:, 1]) < 1.0) & (disp > 0.5)
        px, disp = px[ok_r], disp[ok_r]
        z = cam.fx * b / disp
        X = np.column_stack(((px[:, 0] - cam.cx) / cam.fx * z, (px[:, 1] - cam.cy) / cam.fy * z, z))
        nxt, ok = tracker.track(prev_l, cur, px)
        X, nxt = X[ok & (z < 80 * b)], nxt[ok & (z < 80 * b)]
        good, rv, tv, _ = cv2.solvePnPRansac(X, nxt, K, None, reprojectionError=1.0, iterationsCount=200,
                                             confidence=0.999, flags=cv2.SOLVEPNP_ITERATIVE)
        M = np.eye(4)
        if good:
            M[:3, :3], M[:3, 3] = cv2.Rodrigues(rv)[0], tv.ravel()  # previous -> current camera
        poses.append(poses[-1] @ np.linalg.inv(M))
        prev_l, prev_r = cur, ds.right_image(i)
    return np.array(poses)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    default = Path(os.environ.get("VBNAV_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--data", type=Path, default=default)
    args = ap.parse_args(argv)
    ds = open_dataset(args.data / "kitti06_stereo")
    gt = ds.gt_poses
    t0 = time.perf_counter()
    res = run_vo(ds, "stereo")
    t_ours = time.perf_counter() - t0
    t0 = time.perf_counter()
    base = opencv_chained_stereo(ds)
    t_base = time.perf_counter() - t0
    ours_ate = ate_rmse(res.poses, gt[res.frames])[0]
    base_ate = ate_rmse(base, gt)[0]
    print(f"KITTI 06 frames 0-{len(ds) - 1} (~60 m), SE(3)-aligned ATE RMSE and 1-frame RPE:")
    for name, poses, g, ate, t in (("vbnav vo (reference set)", res.poses, gt[res.frames], ours_ate, t_ours),
                                   ("OpenCV chained stereo PnP", base, gt, base_ate, t_base)):
        tr, rr = rpe(poses, g)
        print(f"  {name:<28} ATE {ate:.3f} m  RPE {tr:.4f} m {rr:.3f} deg  {len(poses)} poses  "
              f"{len(ds) / t:.1f} fps")
    print(f"  ratio ours/baseline ATE: {ours_ate / base_ate:.2f}")
    print(f"  issue bound 0.3 m: {'PASS' if ours_ate <= 0.3 else 'FAIL'}; target 0.1 m: "
          f"{'PASS' if ours_ate <= 0.1 else 'not met'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
