"""Marvin's fast loop at 640x480: segments per frame, detection, DLM prediction and update time, and the map.

Renders the simulated room's 6 m loop (stereo, 640x480, the mapping head of tests/line_scenes.py) once,
then, frame by frame on ONE core (the process pinned to one CPU, OpenCV limited to one thread):

- the fast loop (the DLM in the loop, as control/stages/line_map.py runs it): detection in both images
  (vision/line_segments.py: LSD at ``detect_scale`` + full-resolution line re-fit + side grey levels),
  prediction of the verified segments and the prior, guided stereo matching and triangulation, then the
  update (prediction of all segments for the miss count, association, fusion, verification, pruning);
- the peer, in the same run on the same frames: unguided matching of LSD segments frame by frame, no map
  (LSD at OpenCV's defaults on both images, stereo matching, triangulation) -- the pipeline without the DLM
  as it was before the fast loop was tuned;
- the DLM's own overhead: the same detections matched without a prior (no map) against the fast loop.

Each part is timed in CPU time of the thread (time.thread_time: what the loop costs one core, unaffected by
other processes waiting for the CPU) and in wall time (what it took under the machine's load, printed with
the load average). Prints median / 95th percentile per frame, the fast loop's rate against 15 Hz (66.7 ms)
and the ratio to the peer. One warm-up frame runs first (OpenCV's detector set-up and numpy's lazy imports
are not per-frame costs). Then scores the map against the world's true edges (tests/line_scenes.py).
Usage: python benchmarks/line_map.py [--frames 60] [--json]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from line_scenes import BASELINE, CAM, loop_poses, render_drive, score_map  # noqa: E402
from vbnav.drivers.sim.world import World  # noqa: E402
from vbnav.vision.line_map import LineMap  # noqa: E402
from vbnav.vision.line_segments import LineParams, detect_segments, match_stereo, triangulate  # noqa: E402

BUDGET_MS = 1000.0 / 15.0
# The peer's detector: LSD at OpenCV's defaults (scale 0.8, angle tolerance 22.5 deg), no re-fit.
PEER_PARAMS = replace(LineParams(), detect_scale=0.8, lsd_angle_deg=22.5, refine_radius_px=0.0)


class Clock:
    """Per-frame wall and CPU milliseconds of named parts."""

    def __init__(self):
        self.wall: dict = {}
        self.cpu: dict = {}
        self._t = None

    def start(self) -> None:
        self._t = (time.perf_counter(), time.thread_time())

    def lap(self, name: str) -> None:
        w, c = time.perf_counter(), time.thread_time()
        self.wall.setdefault(name, []).append((w - self._t[0]) * 1e3)
        self.cpu.setdefault(name, []).append((c - self._t[1]) * 1e3)
        self._t = (w, c)

    def total(self, name: str, parts: tuple) -> None:
        for d in (self.wall, self.cpu):
            d[name] = list(np.sum([d[p] for p in parts], axis=0))


def stats(ms: list) -> dict:
    a = np.asarray(ms)
    return {"median_ms": round(float(np.median(a)), 2), "p95_ms": round(float(np.percentile(a, 95)), 2)}


def run_frame(lmap: LineMap, f, R, c, params: LineParams, clock: Clock):
    """One frame of the fast loop, then the same detections matched without a map."""
    fx, fy, cx, cy, W, H = CAM.fx, CAM.fy, CAM.cx, CAM.cy, CAM.width, CAM.height
    clock.start()
    ls, rs = detect_segments(f.image, params), detect_segments(f.right, params)
    clock.lap("detect")
    pred = lmap.predict(R, c, fx, fy, cx, cy, BASELINE, W, H)
    prior = lmap.prior_for(ls, pred)
    clock.lap("predict")
    m = match_stereo(ls, rs, params, prior)
    seg = triangulate(ls, rs, m, fx, fy, cx, cy, BASELINE, params)
    clock.lap("guided_match")
    everything = lmap.predict(R, c, fx, fy, cx, cy, BASELINE, W, H, which=np.ones(len(lmap), bool))
    lmap.update(seg, R, c, everything, ls)
    clock.lap("update")
    triangulate(ls, rs, match_stereo(ls, rs, params), fx, fy, cx, cy, BASELINE, params)
    clock.lap("unguided_match")
    return len(ls), len(seg)


def run_peer(f, clock: Clock) -> None:
    clock.start()
    ls, rs = detect_segments(f.image, PEER_PARAMS), detect_segments(f.right, PEER_PARAMS)
    triangulate(ls, rs, match_stereo(ls, rs, PEER_PARAMS), CAM.fx, CAM.fy, CAM.cx, CAM.cy, BASELINE, PEER_PARAMS)
    clock.lap("peer")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    cpu = sorted(os.sched_getaffinity(0))[0]
    os.sched_setaffinity(0, {cpu})          # one core
    cv2.setNumThreads(1)
    world = World.room(0)
    drive = render_drive(world, loop_poses(args.frames))
    params = LineParams()
    run_frame(LineMap(), drive.frames[0], *drive.cams[0], params, Clock())      # warm-up
    run_peer(drive.frames[0], Clock())
    load0 = os.getloadavg()
    clock, lmap, nseg, nrec = Clock(), LineMap(), [], []
    for f, (R, c) in zip(drive.frames, drive.cams):
        n, k = run_frame(lmap, f, R, c, params, clock)
        run_peer(f, clock)
        nseg.append(n)
        nrec.append(k)
    load1 = os.getloadavg()
    clock.total("fast_loop", ("detect", "predict", "guided_match", "update"))
    clock.total("no_map", ("detect", "unguided_match"))
    score = score_map(lmap, world, drive)
    e = score.endpoint_err
    timing = {}
    for kind, d in (("cpu", clock.cpu), ("wall", clock.wall)):
        fast, peer = np.median(d["fast_loop"]), np.median(d["peer"])
        timing[kind] = {**{k: stats(v) for k, v in d.items()},
                        "fast_loop_hz": round(1000.0 / fast, 1),
                        "ratio_fast_loop_to_peer": round(float(fast / peer), 3),
                        "ratio_fast_loop_to_no_map": round(float(fast / np.median(d["no_map"])), 3),
                        "keeps_up_with_15_hz": bool(fast <= BUDGET_MS),
                        "p95_within_15_hz": bool(np.percentile(d["fast_loop"], 95) <= BUDGET_MS)}
    out = {
        "frames": args.frames, "image": f"{CAM.width}x{CAM.height}", "cpu": cpu,
        "load_average_1_5_15": {"start": [round(x, 2) for x in load0], "end": [round(x, 2) for x in load1]},
        "segments_per_frame": float(np.median(nseg)), "reconstructed_per_frame": float(np.median(nrec)),
        "detector": {"detect_scale": params.detect_scale, "lsd_angle_deg": params.lsd_angle_deg,
                     "refine_radius_px": params.refine_radius_px},
        "time": timing,
        "map": {**lmap.summary(), "edges_in_view": score.in_view, "edges_mapped": score.mapped,
                "coverage": round(score.coverage, 3),
                "endpoint_err_median_m": round(float(np.median(e)), 4) if len(e) else None,
                "endpoint_err_p95_m": round(float(np.percentile(e, 95)), 4) if len(e) else None,
                "false_fraction": round(score.false_fraction, 3)},
    }
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    print(f"{args.frames} frames {CAM.width}x{CAM.height} on cpu {cpu} (one core, cv2 1 thread), load average "
          f"{load0[0]:.2f} at start, {load1[0]:.2f} at end: {out['segments_per_frame']:.0f} segments/frame "
          f"(left), {out['reconstructed_per_frame']:.0f} 3D segments/frame")
    labels = {"detect": "detection (both images)", "predict": "prediction + prior", "guided_match":
              "guided matching + 3D", "update": "DLM update", "fast_loop": "FAST LOOP total",
              "peer": "peer (OpenCV LSD, unguided)", "no_map": "same detection, no map"}
    print(f"  {'per frame (ms)':30s} {'cpu median':>10s} {'p95':>7s}   {'wall median':>11s} {'p95':>7s}")
    for k, label in labels.items():
        c, w = timing["cpu"][k], timing["wall"][k]
        print(f"  {label:30s} {c['median_ms']:10.2f} {c['p95_ms']:7.2f}   {w['median_ms']:11.2f} {w['p95_ms']:7.2f}")
    for kind in ("cpu", "wall"):
        t = timing[kind]
        print(f"  {kind}: fast loop {t['fast_loop']['median_ms']:.1f} ms = {t['fast_loop_hz']} Hz, "
              f"x{t['ratio_fast_loop_to_peer']} the peer, x{t['ratio_fast_loop_to_no_map']} the same detection "
              f"without the map; 15 Hz (66.7 ms): {'met' if t['keeps_up_with_15_hz'] else 'NOT met'} "
              f"(median), {'met' if t['p95_within_15_hz'] else 'NOT met'} (p95)")
    print(f"  map: {json.dumps(out['map'])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
