"""``vbnav vo`` against an OpenCV peer on every real sequence with ground truth, in one run.

Peer: ``benchmarks/vo_peer.py``, the "afternoon baseline" of issue 13 written with plain OpenCV and sharing
nothing with vbnav's tracker: Shi-Tomasi corners, plain pyramidal KLT, solvePnPRansac of every frame against a
growing map (stereo: disparity; RGB-D: depth; monocular: a two-view start, then corners triangulated between
their keyframe and the current frame once their rays part by a degree), ORB matching when KLT loses the map.

Printed per sequence, for vbnav and the peer: frames with a pose, APE (translation RMSE after SE(3)
alignment, or Sim(3) for monocular runs whose scale is unknown; labelled), ms per frame, and the ratios
vbnav / peer of APE and of time. The peer of the desk's tag-grid run is the depth peer (no tags).

    VBNAV_DATA=../shared/data .venv/bin/python benchmarks/vo_real.py [--data DIR] [--only NAME ...] [--seeds N] [--stride N]

``--stride N`` keeps every N-th frame: N times the motion between frames on the same footage (kitti03 at
stride 3: up to 10 degrees of turn and 0.7-2.2 m between frames).

``--seeds N`` (default 3) runs vbnav and the peer again with seeds 1..N-1 and prints the spread of their APE
and the ratio of the medians: a monocular run's figure is one draw (the peer's kitti06 left-only APE ranges
over 0.040-0.211 m over seeds 0-7, median 0.098 m; vbnav's over 0.041-0.049 m). The closing verdict, issue 13's
acceptance, compares the medians over the seeds, not one draw of each: a comparison of seed 0 alone is a
comparison of two random draws (on kitti06 left only the peer's seed 0 is its best of eight). A missing sequence folder is an error under CI (CI=true) and a warning elsewhere.

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

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from desk_view import build_desk_view  # noqa: E402
from room_view import room_view  # noqa: E402
from vo_peer import PeerVo  # noqa: E402

from vbnav.control.trajectory_metrics import ate_rmse  # noqa: E402
from vbnav.control.vo import run_vo  # noqa: E402
from vbnav.drivers.datasets import open_dataset  # noqa: E402

SEQUENCE_FOLDERS = ("kitti06_stereo", "vo_turns_kitti03", "desk_rgbd", "room_rgbd5")


def sequences(data: Path, tmp: Path):
    """(name, dataset folder, vbnav --init, peer mode) of the sequence folders that are there."""
    if (data / "kitti06_stereo").is_dir():
        yield "kitti06 stereo", data / "kitti06_stereo", "stereo", "stereo"
        yield "kitti06 mono", data / "kitti06_stereo", "essential", "mono"
    if (data / "vo_turns_kitti03").is_dir():
        yield "kitti03 turns mono", data / "vo_turns_kitti03", "essential", "mono"
    if (data / "desk_rgbd").is_dir():
        desk = build_desk_view(data / "desk_rgbd", tmp / "desk")
        yield "desk tags / depth", desk, "tags", "depth"
        yield "desk depth", desk, "depth", "depth"
    if (data / "room_rgbd5").is_dir():
        yield "room_rgbd5 depth", room_view(data / "room_rgbd5", tmp / "room"), "depth", "depth"


KITTI03_BOUND_M = 0.30     # issue 13: vo_turns_kitti03 at most 0.30 m (the peer's 0.31 m when it was filed)


def missing_folders(data: Path) -> list[Path]:
    """The sequence folders this benchmark needs that are not in ``data``."""
    return [data / f for f in SEQUENCE_FOLDERS if not (data / f).is_dir()]


def _ape(ds, frames, poses, sim3: bool) -> float:
    ok, g = ds.ground_truth_at(ds.stamps[frames])
    if ok.sum() < 3:
        return float("nan")
    return ate_rmse(poses[ok], g[ok], with_scale=sim3)[0]


def _spread(what: str, apes: list[float]) -> str:
    return (f"{what} APE over seeds 0-{len(apes) - 1}: median {np.median(apes):.4f} m, "
            f"range {min(apes):.4f}-{max(apes):.4f} m")


def _row(name, n, posed, ape, kind, ms, p_posed, p_ape, p_kind, p_ms) -> str:
    return (f"{name:<19} {n:>4} | {posed:>4} {100 * posed / n:>3.0f}% {ape:>7.4f} {kind:<4} {ms:>5.0f} | "
            f"{p_posed:>4} {100 * p_posed / n:>3.0f}% {p_ape:>7.4f} {p_kind:<4} {p_ms:>5.0f} | "
            f"{ape / p_ape:>6.2f}x {ms / p_ms:>6.2f}x")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    default = Path(os.environ.get("VBNAV_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--data", type=Path, default=default, help="the shared data folder (default $VBNAV_DATA)")
    ap.add_argument("--only", nargs="*", default=None, help="run only sequences whose name contains one of these")
    ap.add_argument("--stride", type=int, default=1, metavar="N",
                    help="use every N-th frame of each sequence (N times the motion between frames: the "
                         "'large inter-frame motion' of issue 13 on the same footage); sequences left with "
                         "fewer than 10 frames are skipped")
    ap.add_argument("--seeds", type=int, default=3, metavar="N",
                    help="also run vbnav and the peer with seeds 1..N-1 (RANSAC draws) and print the spread of "
                         "their APE (monocular runs depend on the draws: one figure is one draw); the verdict "
                         "compares the medians over the seeds (default 3; 1: seed 0 alone)")
    args = ap.parse_args(argv)
    args.data = args.data.resolve()   # the desk and room views link to its files from a temporary folder
    if args.stride < 1:
        ap.error(f"--stride {args.stride}: expected a whole number >= 1")
    if args.seeds < 1:
        ap.error(f"--seeds {args.seeds}: expected a whole number >= 1")
    missing = missing_folders(args.data)
    if missing:
        msg = "sequence folder(s) missing: " + ", ".join(str(m) for m in missing) + \
            " (set VBNAV_DATA or --data to the shared data folder)"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            raise SystemExit(f"vo_real: {msg}")  # CI has the data: a missing sequence is a failure, not a skip
        if len(missing) == len(SEQUENCE_FOLDERS):
            ap.error(msg)
        print(f"WARNING: {msg}; their rows are left out", flush=True)
    print("APE: translation RMSE (m) after SE3 alignment, or Sim3 where the scale is unknown (monocular); "
          "ms/fr over all frames; ratios vbnav / peer" + (f"; one frame in {args.stride}" if args.stride > 1 else ""))
    print(f"{'sequence':<19} {'fr':>4} | {'vbnav: posed':>9} {'APE m':>7} {'':<4} {'ms/fr':>5} | "
          f"{'peer: posed':>9} {'APE m':>7} {'':<4} {'ms/fr':>5} | {'APE':>7} {'time':>7}")
    verdicts = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, root, init, mode in sequences(args.data, Path(tmp)):
            if args.only and not any(o in name for o in args.only):
                continue
            ds = open_dataset(root)
            if args.stride > 1:
                ds = ds.every(args.stride)
                if len(ds) < 10:
                    print(f"{name:<19} {len(ds):>4} | skipped: fewer than 10 frames at --stride {args.stride}")
                    continue
            t0 = time.perf_counter()
            res = run_vo(ds, init)
            t_ours = (time.perf_counter() - t0) / len(ds) * 1e3
            ape_ours = _ape(ds, res.frames, res.poses, not res.scale_known)
            t0 = time.perf_counter()
            pf, pp = PeerVo(ds, mode).run()
            t_peer = (time.perf_counter() - t0) / len(ds) * 1e3
            ape_peer = _ape(ds, pf, pp, mode == "mono")
            print(_row(name, len(ds), len(res.frames), ape_ours, "SE3" if res.scale_known else "Sim3", t_ours,
                       len(pf), ape_peer, "Sim3" if mode == "mono" else "SE3", t_peer), flush=True)
            ours, peer = [ape_ours], [ape_peer]
            if args.seeds > 1:
                for seed in range(1, args.seeds):
                    r = run_vo(ds, init, seed=seed)
                    ours.append(_ape(ds, r.frames, r.poses, not r.scale_known))
                    peer.append(_ape(ds, *PeerVo(ds, mode, seed=seed).run(), mode == "mono"))
                print(f"{'':<19} {_spread('vbnav', ours)}; {_spread('peer', peer)}; "
                      f"ratio of the medians {np.median(ours) / np.median(peer):.2f}x", flush=True)
            verdicts.append(_verdict(name, len(res.frames) / len(ds), ours, peer))
    print(f"issue 13 acceptance (frames posed >= 97 %, APE median over seeds 0-{args.seeds - 1} <= the peer's):")
    for line in verdicts:
        print("  " + line)
    return 0


def _verdict(name: str, posed: float, ours: list[float], peer: list[float]) -> str:
    """One sequence against issue 13's acceptance, by the medians over the seeds (NaN: not met)."""
    mo, mp = float(np.median(ours)), float(np.median(peer))
    bound = KITTI03_BOUND_M if name.startswith("kitti03") else float("inf")
    met = posed >= 0.97 and mo <= mp and mo <= bound
    return (f"{name:<19} {'met' if met else 'NOT MET'}: posed {100 * posed:.0f} %, APE {mo:.4f} m vs peer "
            f"{mp:.4f} m ({mo / mp:.2f}x)" + (f", bound {bound:.2f} m" if bound < float("inf") else ""))


if __name__ == "__main__":
    raise SystemExit(main())
