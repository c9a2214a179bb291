"""How good is the desk_rgbd ground truth, and where does our error come from?

    .venv/bin/python benchmarks/desk_groundtruth.py [--data DATA_DIR]

DATA_DIR is the shared data folder (default $VBNAV_DATA, else ../shared/data beside the repository).

Peer: a per-frame OpenCV pose of the tag grid (SQPNP + Levenberg-Marquardt on every
detected tag corner, same layout as the test) -- the best any tracker of those
tags could do frame by frame. Printed: its ATE against the grid poses (same SE(3)
Umeyama alignment as the issue), jitter of both about a local quadratic in camera
axes, our VO's ATE (tag grid in frame 0, natural features after) against both,
and our error by segment with the number of tag corners still tracked.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from desk_view import build_desk_view  # noqa: E402

from vbnav.control.trajectory_metrics import ate_rmse  # noqa: E402
from vbnav.control.vo import run_vo  # noqa: E402
from vbnav.drivers.datasets import open_dataset  # noqa: E402
from vbnav.vision.vslam_init import TagGrid  # noqa: E402


def tag_pnp_poses(ds, grid: TagGrid) -> tuple[np.ndarray, float]:
    out, res = [], []
    for i in range(len(ds)):
        px, P, _ = grid.detect(ds.image(i))
        _, rv, tv = cv2.solvePnP(P, px, ds.camera.K, None, flags=cv2.SOLVEPNP_SQPNP)
        _, rv, tv = cv2.solvePnP(P, px, ds.camera.K, None, rv, tv, True, flags=cv2.SOLVEPNP_ITERATIVE)
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = cv2.Rodrigues(rv)[0], tv.ravel()
        proj = cv2.projectPoints(P, rv, tv, ds.camera.K, None)[0].reshape(-1, 2)
        res.append(np.sqrt(np.mean(np.sum((proj - px) ** 2, axis=1))))
        out.append(np.linalg.inv(M))
    return np.array(out), float(np.median(res))


def jitter(poses: np.ndarray, window: int = 7) -> np.ndarray:
    """RMS of each camera centre about a local quadratic fit, in camera axes (x, y, z = optical)."""
    h, t, out = window // 2, poses[:, :3, 3], []
    for i in range(h, len(t) - h):
        k = np.arange(-h, h + 1)
        c = np.linalg.lstsq(np.vander(k, 3), t[i + k], rcond=None)[0][-1]
        out.append(poses[i, :3, :3].T @ (t[i] - c))
    return np.sqrt(np.mean(np.square(out), axis=0))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("VBNAV_DATA") or
                                                      Path(__file__).resolve().parents[2] / "shared" / "data"),
                    help="the shared data folder (default $VBNAV_DATA, else ../shared/data)")
    data = ap.parse_args().data
    if not (data / "desk_rgbd").is_dir():
        ap.error(f"{data / 'desk_rgbd'}: no such folder (set --data or VBNAV_DATA to the shared data folder)")
    with tempfile.TemporaryDirectory() as tmp:
        ds = open_dataset(build_desk_view(data / "desk_rgbd", Path(tmp) / "desk"))
        gt = ds.gt_poses
        pnp, res = tag_pnp_poses(ds, TagGrid.from_spec(ds.extras["tag_grid"]))
        print(f"tag PnP (peer) vs grid poses: ATE {100 * ate_rmse(pnp, gt)[0]:.2f} cm; "
              f"median corner reprojection {res:.2f} px")
        for name, p in (("grid poses", gt), ("tag PnP", pnp)):
            j = 100 * jitter(p)
            print(f"{name}: jitter about a 7-frame quadratic (cm) x {j[0]:.2f} y {j[1]:.2f} z(optical) {j[2]:.2f}")
        r = run_vo(ds, "tags")
        idx = np.array(r.frames)
        ate, aligned = ate_rmse(r.poses, gt[idx])
        ate_p = ate_rmse(r.poses, pnp[idx])[0]
        print(f"vbnav vo --init tags: ATE {100 * ate:.2f} cm vs grid poses, {100 * ate_p:.2f} cm vs tag PnP; "
              f"ratio to the peer's ATE {ate / ate_rmse(pnp, gt)[0]:.1f}")
        e = 100 * np.linalg.norm(aligned - gt[idx][:, :3, 3], axis=1)
        for a, b in ((0, 30), (30, 45), (45, 60), (60, 78), (78, 88), (88, len(ds))):
            m = (idx >= a) & (idx < b)
            print(f"  frames {a:2d}-{b - 1:2d}: error rms {np.sqrt(np.mean(e[m] ** 2)):.2f} cm, "
                  f"max {e[m].max():.2f} cm")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
