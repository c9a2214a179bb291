"""Marvin's fast loop at 640x480: segments per frame, DLM prediction and update time, and the map figures.

Renders the simulated room's 6 m loop (stereo, 640x480, the mapping head of tests/line_scenes.py) once,
then, frame by frame on one core:

- peer: unguided LSD + stereo matching of the pair (detect both images, match, triangulate), no map;
- DLM: the same with the map in the loop: prediction of the verified segments, guided matching,
  prediction of all segments for the miss count, update (association, fusion, verification, pruning).

Prints the median / 95th percentile per frame of each part, the fast loop's total against the 15 Hz
budget (66.7 ms), and the ratio to the peer measured in the same run. Then scores the map against the
world's true edges (tests/line_scenes.py: coverage of box and wall edges in view, endpoint error,
false fraction). Usage: python benchmarks/line_map.py [--frames 60] [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from line_scenes import BASELINE, CAM, loop_poses, render_drive, score_map  # noqa: E402
from vbnav.drivers.sim.world import World  # noqa: E402
from vbnav.vision.line_map import LineMap  # noqa: E402
from vbnav.vision.line_segments import LineParams, detect_segments, match_stereo, triangulate  # noqa: E402


def stats(ms: list) -> dict:
    a = np.asarray(ms)
    return {"median_ms": round(float(np.median(a)), 2), "p95_ms": round(float(np.percentile(a, 95)), 2)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})     # one core
    world = World.room(0)
    drive = render_drive(world, loop_poses(args.frames))
    params = LineParams()
    fx, fy, cx, cy = CAM.fx, CAM.fy, CAM.cx, CAM.cy
    W, H = CAM.width, CAM.height
    t = {k: [] for k in ("detect", "peer_match", "predict", "guided_match", "update")}
    nseg, nrec = [], []
    lmap = LineMap()
    for f, (R, c) in zip(drive.frames, drive.cams):
        t0 = time.perf_counter()
        ls, rs = detect_segments(f.image, params), detect_segments(f.right, params)
        t1 = time.perf_counter()
        m = match_stereo(ls, rs, params)
        triangulate(ls, rs, m, fx, fy, cx, cy, BASELINE, params)
        t2 = time.perf_counter()
        pred = lmap.predict(R, c, fx, fy, cx, cy, BASELINE, W, H)
        prior = lmap.prior_for(ls, pred)
        t3 = time.perf_counter()
        mg = match_stereo(ls, rs, params, prior)
        seg = triangulate(ls, rs, mg, fx, fy, cx, cy, BASELINE, params)
        t4 = time.perf_counter()
        everything = lmap.predict(R, c, fx, fy, cx, cy, BASELINE, W, H, which=np.ones(len(lmap), bool))
        lmap.update(seg, R, c, everything, ls)
        t5 = time.perf_counter()
        for k, dt in zip(t, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4)):
            t[k].append(dt * 1e3)
        nseg.append(len(ls))
        nrec.append(len(seg))
    peer = np.add(t["detect"], t["peer_match"])
    fast = np.add(np.add(t["detect"], t["predict"]), np.add(t["guided_match"], t["update"]))
    score = score_map(lmap, world, drive)
    e = score.endpoint_err
    out = {
        "frames": args.frames, "image": f"{W}x{H}",
        "segments_per_frame": float(np.median(nseg)), "reconstructed_per_frame": float(np.median(nrec)),
        "time": {k: stats(v) for k, v in t.items()},
        "peer_unguided_total": stats(peer), "dlm_fast_loop_total": stats(fast),
        "dlm_only (predict+update)": stats(np.add(t["predict"], t["update"])),
        "ratio_fast_loop_to_peer": round(float(np.median(fast) / np.median(peer)), 3),
        "keeps_up_with_15_hz": bool(np.median(fast) <= 1000.0 / 15.0),
        "map": {**lmap.summary(), "edges_in_view": score.in_view, "edges_mapped": score.mapped,
                "coverage": round(score.coverage, 3),
                "endpoint_err_median_m": round(float(np.median(e)), 4) if len(e) else None,
                "endpoint_err_p95_m": round(float(np.percentile(e, 95)), 4) if len(e) else None,
                "false_fraction": round(score.false_fraction, 3)},
    }
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"{args.frames} frames {W}x{H}: {out['segments_per_frame']:.0f} segments/frame (left), "
          f"{out['reconstructed_per_frame']:.0f} 3D segments/frame")
    for k, v in out["time"].items():
        print(f"  {k:14s} median {v['median_ms']:7.2f} ms   p95 {v['p95_ms']:7.2f} ms")
    print(f"  peer (unguided LSD matching)  median {out['peer_unguided_total']['median_ms']:.1f} ms")
    print(f"  DLM fast loop                 median {out['dlm_fast_loop_total']['median_ms']:.1f} ms "
          f"(x{out['ratio_fast_loop_to_peer']} the peer; 15 Hz budget 66.7 ms: "
          f"{'kept' if out['keeps_up_with_15_hz'] else 'NOT kept'})")
    print(f"  map: {json.dumps(out['map'])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
