"""Marvin's 3D line segments on every real stereo folder of ../shared/data, against peers in the same run.

Issue 16's "real stereo" acceptance, measured as a figure with a peer rather than a test's pass/fail (the
bars are in tests/test_line_segments.py, tests/test_line_euroc.py and tests/test_line_map.py):

- ``indoor_stereo/middlebury`` (five Middlebury 2014 scenes, ground-truth disparity): each best match's
  endpoint disparity against the ground truth. An endpoint lies on a depth edge, so its truth is the
  ground-truth disparity nearest to the estimate within +-2 px (one side of the edge has it; the tests'
  rule). Peer: OpenCV's StereoSGBM on the same pair (block 5, the scene's ``ndisp`` rounded up to 16),
  read at the same endpoints (the rounded pixel) and scored by the same rule. SGBM finds no disparity at
  some of them (NaN: occluded side, uniqueness, speckle filter): they are given as its coverage and
  counted as misses in "within 2 px of all".
- ``indoor_stereo/euroc_v101`` (three raw EuRoC pairs, no ground-truth depth): rectified with
  ``stereo_rectify.yaml``; the checkerboard is flat, so its 42 sub-pixel inner corners give its plane in
  disparity space (d = a x + b y + c), and every endpoint of a segment on the board must have the plane's
  disparity. Peer: SGBM at the same endpoints. The board's border gives few segments (4 per pair): this
  is a check of the absolute disparity on a real rectified rig, not a statistic.
- ``kitti06_stereo`` (frames 0-7 with the ground-truth poses): the DLM built as
  tests/test_line_map.py builds it; segments verified from >= 3 viewpoints 0.5 m apart, reprojected into
  each frame, against the segments detected there (median endpoint distance to the projected line of the
  associated detections; the acceptance's 1.5 px). Peer: the same map built without prediction (every pair
  matched on its own, ``prior_fn=None``).

Time per pair (one core, CPU): ours (LSD both images, matching, 3D) against SGBM on the same pair.

Usage: python benchmarks/line_real.py [--data DIR] [--json]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import re
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from line_scenes import map_reprojection_errors, read_pfm  # noqa: E402

from vbnav.drivers.stereo_calib import load_stereo_calibration, read_kitti_calib  # noqa: E402
from vbnav.vision.line_map import LineMap, MapParams  # noqa: E402
from vbnav.vision.line_segments import LineParams, reconstruct_pair  # noqa: E402
from vbnav.vision.stereo import SgbmParams, sgbm_disparity  # noqa: E402

MIDDLEBURY = ("Shelves", "Playroom", "Recycle", "Vintage", "Playtable")
BOARD = (7, 6)                    # inner corners of the EuRoC scene's checkerboard
WINDOW_PX = 2                     # ground truth searched +-2 px around an endpoint (a depth edge's two sides)


def data_dir() -> Path:
    """$VBNAV_DATA, else ../shared/data beside the repository (as the tests' ``shared_data``)."""
    repo = Path(__file__).resolve().parents[1]
    return Path(os.environ.get("VBNAV_DATA", repo.parent / "shared" / "data")).resolve()


def cpu_ms(fn):
    t = time.process_time()
    out = fn()
    return out, 1e3 * (time.process_time() - t)


def endpoints(seg) -> tuple[np.ndarray, np.ndarray]:
    """(2K, 2) left-image endpoints of 3D segments and (2K,) their disparities."""
    return seg.left_xy.reshape(-1, 2), np.asarray(seg.extra["disparity"], float).reshape(-1)


def sample(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """image at the rounded pixels xy (N, 2); NaN outside."""
    H, W = image.shape
    xi, yi = np.rint(xy[:, 0]).astype(int), np.rint(xy[:, 1]).astype(int)
    inside = (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
    out = np.full(len(xy), np.nan)
    out[inside] = image[yi[inside], xi[inside]]
    return out


def window_error(gt: np.ndarray, xy: np.ndarray, d: np.ndarray, win: int = WINDOW_PX) -> np.ndarray:
    """(N,) |d - gt| for the ground truth nearest to d within +-win px of each point; NaN where d is NaN or
    the window holds no ground truth."""
    H, W = gt.shape
    out = np.full(len(xy), np.nan)
    for k, ((x, y), dk) in enumerate(zip(xy, d)):
        if not math.isfinite(dk):
            continue
        xi, yi = int(round(x)), int(round(y))
        w = gt[max(0, yi - win):min(H, yi + win + 1), max(0, xi - win):min(W, xi + win + 1)]
        w = w[np.isfinite(w)]
        if len(w):
            out[k] = float(np.min(np.abs(w - dk)))
    return out


def sgbm_for(max_disparity_px: float) -> SgbmParams:
    return SgbmParams(num_disparities=int(16 * math.ceil(max_disparity_px / 16.0)), block_size=5)


def summary(err: np.ndarray) -> dict:
    """Figures of endpoint errors; NaN = no estimate there."""
    ok = np.isfinite(err)
    e = err[ok]
    return {"endpoints": int(len(err)), "covered": float(ok.mean()) if len(err) else 0.0,
            "median_px": float(np.median(e)) if len(e) else float("nan"),
            "within_1px": float(np.mean(e <= 1.0)) if len(e) else 0.0,
            "within_2px_of_covered": float(np.mean(e <= 2.0)) if len(e) else 0.0,
            "within_2px_of_all": float(np.sum(e <= 2.0) / max(len(err), 1))}


# ---------------------------------------------------------------------------------------- Middlebury
def middlebury(root: Path) -> dict:
    ours_all, peer_all, rows, ms = [], [], [], {"ours": [], "sgbm": []}
    for scene in MIDDLEBURY:
        d = root / scene
        cal = (d / "calib.txt").read_text()
        f = float(re.search(r"cam0=\[\s*([\d.]+)", cal).group(1))
        ndisp = int(re.search(r"ndisp=\s*(\d+)", cal).group(1))
        left, right = cv2.imread(str(d / "im0.png")), cv2.imread(str(d / "im1.png"))
        if left is None or right is None:
            raise SystemExit(f"line_real: {d}: im0.png / im1.png not readable")
        gt = read_pfm(d / "disp0GT.pfm")
        params = LineParams(max_disparity_px=1.1 * ndisp)          # as tests/test_line_segments.py
        res, t_ours = cpu_ms(lambda: reconstruct_pair(left, right, f, f, 0.0, 0.0, 0.1, params))
        disp, t_sgbm = cpu_ms(lambda: sgbm_disparity(left, right, sgbm_for(1.1 * ndisp)))
        best = res.segments.subset(res.segments.best)
        xy, d_ours = endpoints(best)
        e_ours = window_error(gt, xy, d_ours)
        e_peer = window_error(gt, xy, sample(disp, xy))
        keep = np.isfinite(window_error(gt, xy, np.where(np.isfinite(d_ours), d_ours, 0.0)))   # truth known
        ours_all.append(e_ours[keep])
        peer_all.append(e_peer[keep])
        ms["ours"].append(t_ours)
        ms["sgbm"].append(t_sgbm)
        rows.append({"scene": scene, "segments": int(len(best)), "ours": summary(e_ours[keep]),
                     "sgbm": summary(e_peer[keep]), "ms_ours": t_ours, "ms_sgbm": t_sgbm})
    return {"scenes": rows, "ours": summary(np.concatenate(ours_all)), "sgbm": summary(np.concatenate(peer_all)),
            "ms_ours": float(np.median(ms["ours"])), "ms_sgbm": float(np.median(ms["sgbm"]))}


# -------------------------------------------------------------------------------------------- EuRoC
def board_plane(left: np.ndarray, right: np.ndarray):
    """The checkerboard's plane in disparity space from its inner corners (or None), and the board's
    outline (the corners' hull grown about its centre over the outer squares and the border)."""
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 0.01)
    corners = []
    for im in (left, right):
        ok, c = cv2.findChessboardCorners(im, BOARD, cv2.CALIB_CB_ADAPTIVE_THRESH)
        if not ok:
            return None, None
        corners.append(cv2.cornerSubPix(im, c, (4, 4), (-1, -1), crit).reshape(-1, 2))
    cl, cr = corners
    A = np.column_stack((cl, np.ones(len(cl))))
    plane, *_ = np.linalg.lstsq(A, cl[:, 0] - cr[:, 0], rcond=None)
    hull = cv2.convexHull(cl.astype(np.float32)).reshape(-1, 2)
    outline = (cl.mean(axis=0) + 1.8 * (hull - cl.mean(axis=0))).astype(np.float32)
    return plane, outline


def euroc(root: Path) -> dict:
    calib = load_stereo_calibration(root / "stereo_rectify.yaml", raw_images=True)
    params = dataclasses.replace(LineParams(), max_disparity_px=calib.fx / 8.0)   # vbnav lines' default range
    names = [ln.split(",")[1] for ln in (root / "frames.csv").read_text().splitlines()
             if ln.strip() and not ln.startswith("#")]
    e_ours, e_peer, ms = [], [], {"ours": [], "sgbm": []}
    for name in names:
        L = cv2.imread(str(root / "cam0" / name), cv2.IMREAD_GRAYSCALE)
        R = cv2.imread(str(root / "cam1" / name), cv2.IMREAD_GRAYSCALE)
        left, right = calib.rectify(L, R)
        res, t_ours = cpu_ms(lambda: reconstruct_pair(left, right, calib.fx, calib.fy, calib.cx, calib.cy,
                                                      calib.baseline, params))
        disp, t_sgbm = cpu_ms(lambda: sgbm_disparity(left, right, sgbm_for(params.max_disparity_px)))
        ms["ours"].append(t_ours)
        ms["sgbm"].append(t_sgbm)
        plane, outline = board_plane(left, right)
        if plane is None:
            raise SystemExit(f"line_real: {root / 'cam0' / name}: the checkerboard was not found")
        best = res.segments.subset(res.segments.best)
        for k in range(len(best)):
            ends = best.left_xy[k].reshape(2, 2)
            if not any(cv2.pointPolygonTest(outline, (float(x), float(y)), False) >= 0 for x, y in ends):
                continue
            truth = np.column_stack((ends, np.ones(2))) @ plane
            e_ours.extend(np.abs(best.extra["disparity"][k] - truth))
            e_peer.extend(np.abs(sample(disp, ends) - truth))
    return {"pairs": len(names), "ours": summary(np.array(e_ours)), "sgbm": summary(np.array(e_peer)),
            "ms_ours": float(np.median(ms["ours"])), "ms_sgbm": float(np.median(ms["sgbm"]))}


# ------------------------------------------------------------------------------------------- kitti06
def kitti_map(root: Path, guided: bool, frames: int = 8) -> dict:
    """The DLM over kitti06 frames 0..frames-1 with the ground-truth poses (tests/test_line_map.py's
    settings); the verified segments' reprojection onto each frame's detections."""
    cal = read_kitti_calib(root / "calib.txt")
    T = np.loadtxt(root / "poses.txt").reshape(-1, 3, 4)
    lp = LineParams(max_disparity_px=cal.fx * cal.baseline / 2.0)          # nearest 2 m
    lmap = LineMap(MapParams(max_range_m=25.0, min_range_m=2.0, view_baseline_m=0.5, assoc_extra_m=0.05))
    left, ms = {}, []
    for i in range(frames):
        L = cv2.imread(str(root / f"image_l/{i:06d}.png"), 0)
        R = cv2.imread(str(root / f"image_r/{i:06d}.png"), 0)
        Rw, tw = T[i][:, :3], T[i][:, 3]
        args = (cal.fx, cal.fy, cal.cx, cal.cy, cal.baseline, L.shape[1], L.shape[0])
        pred = lmap.predict(Rw, tw, *args)
        prior = (lambda s: lmap.prior_for(s, pred)) if guided else None
        res, t = cpu_ms(lambda: reconstruct_pair(L, R, cal.fx, cal.fy, cal.cx, cal.cy, cal.baseline, lp,
                                                 prior_fn=prior, vertical=Rw[1]))
        ms.append(t)
        lmap.update(res.segments, Rw, tw, lmap.predict(Rw, tw, *args, which=np.ones(len(lmap), bool)), res.left)
        left[i] = (res.left, args)
    e = map_reprojection_errors(lmap, left, T)
    return {"verified": int(lmap.verified.sum()), "associated": int(len(e)),
            "median_px": float(np.median(e)) if len(e) else float("nan"),
            "within_1_5px": float(np.mean(e <= 1.5)) if len(e) else 0.0, "ms_per_pair": float(np.median(ms))}


# ---------------------------------------------------------------------------------------------- main
def fmt(s: dict) -> str:
    return (f"{s['endpoints']:4d} endpoints, median {s['median_px']:.2f} px, within 1 px {100 * s['within_1px']:5.1f} %, "
            f"within 2 px {100 * s['within_2px_of_covered']:5.1f} % (of all {100 * s['within_2px_of_all']:5.1f} %, "
            f"covered {100 * s['covered']:5.1f} %)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=data_dir(), help="the real-data folder (default: $VBNAV_DATA or "
                    "../shared/data beside the repository)")
    ap.add_argument("--json", action="store_true", help="also print the figures as one JSON line")
    args = ap.parse_args(argv)
    need = {"middlebury": args.data / "indoor_stereo" / "middlebury",
            "euroc": args.data / "indoor_stereo" / "euroc_v101", "kitti06": args.data / "kitti06_stereo"}
    missing = [str(p) for p in need.values() if not p.is_dir()]
    if missing:
        print(f"line_real: missing real-data folder(s): {', '.join(missing)} (set --data or VBNAV_DATA)",
              file=sys.stderr)
        return 2
    cv2.setNumThreads(1)                                  # one core, as the robot's vision thread
    out = {}
    print("== Middlebury 2014, five scenes: endpoint disparity against the ground truth ==", flush=True)
    mb = out["middlebury"] = middlebury(need["middlebury"])
    for r in mb["scenes"]:
        print(f"  {r['scene']:10s} {r['segments']:4d} segments | ours {r['ours']['median_px']:.2f} px, "
              f"{100 * r['ours']['within_2px_of_all']:5.1f} % within 2 px | SGBM {r['sgbm']['median_px']:.2f} px, "
              f"{100 * r['sgbm']['within_2px_of_all']:5.1f} % | {r['ms_ours']:.0f} / {r['ms_sgbm']:.0f} ms", flush=True)
    print(f"  ours: {fmt(mb['ours'])}")
    print(f"  SGBM: {fmt(mb['sgbm'])}")
    print(f"  ratio SGBM / ours, median error: x{mb['sgbm']['median_px'] / mb['ours']['median_px']:.2f}; "
          f"time per pair {mb['ms_ours']:.0f} ms against SGBM {mb['ms_sgbm']:.0f} ms")
    print("== EuRoC V1_01, three raw pairs rectified: endpoints on the checkerboard against its plane ==",
          flush=True)
    eu = out["euroc"] = euroc(need["euroc"])
    print(f"  ours: {fmt(eu['ours'])}")
    print(f"  SGBM: {fmt(eu['sgbm'])}")
    print(f"  time per pair {eu['ms_ours']:.0f} ms against SGBM {eu['ms_sgbm']:.0f} ms")
    print("== kitti06 frames 0-7, ground-truth poses: verified segments reprojected (acceptance 1.5 px) ==",
          flush=True)
    ours, peer = kitti_map(need["kitti06"], True), kitti_map(need["kitti06"], False)
    out["kitti06"] = {"guided": ours, "unguided": peer}
    for name, r in (("ours (guided)", ours), ("peer (no prediction)", peer)):
        print(f"  {name:21s} {r['verified']:3d} verified, {r['associated']:4d} associated detections, median "
              f"{r['median_px']:.2f} px, within 1.5 px {100 * r['within_1_5px']:5.1f} %, {r['ms_per_pair']:.0f} ms "
              f"per pair")
    if args.json:
        print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
