"""``vbnav vo``: monocular VSLAM (section 11.3) over a recorded dataset."""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from vbnav.control.commands._common import DefaultsHelpFormatter
from vbnav.drivers.atomic_file import atomic_output, write_atomic

GROUND_TRUTH_FILE = {"kitti": "poses.txt", "tum": "groundtruth.txt"}
#: The files of a dataset folder besides its images (drivers/datasets.py): never an output.
#: How far (s) a ground-truth pose may be from a frame's time to be its ground truth.
GT_MAX_DT_S = 0.02
DATASET_FILES = ("calib.txt", "times.txt", "poses.txt", "rgb.txt", "depth.txt", "groundtruth.txt", "camera.yaml")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "vo", help="run the VSLAM over a KITTI- or TUM-layout dataset and write the trajectory",
        description="Track a recorded sequence with the VSLAM front end (pose always against the reference "
                    "landmark set) and write the camera trajectory in TUM format "
                    "(timestamp tx ty tz qx qy qz qw, camera-to-world, one line per tracked frame). "
                    "With ground truth, prints ATE (SE(3) Umeyama alignment) and RPE.",
        formatter_class=DefaultsHelpFormatter)
    p.add_argument("dataset", help="folder in KITTI odometry layout (image_l/, image_r/, calib.txt, poses.txt, "
                                   "times.txt) or TUM RGB-D layout (rgb.txt, depth.txt, groundtruth.txt)")
    p.add_argument("--out", required=True, metavar="FILE", help="trajectory output (TUM format)")
    p.add_argument("--init", choices=["stereo", "depth", "tags", "essential"], default=None,
                   help="initialisation (default: stereo if right images, depth if depth images, tags if the "
                        "camera YAML has tag_grid, else essential)")
    p.add_argument("--camera", metavar="YAML", default=None,
                   help="intrinsics (fx, fy, cx, cy, width, height[, dist, model, depth_scale, tag_grid]); "
                        "default camera.yaml in the dataset (TUM) or calib.txt (KITTI)")
    p.add_argument("--plot", metavar="PNG", default=None,
                   help="plot of the trajectory against ground truth (a dataset without ground truth is refused)")
    p.add_argument("--status-out", metavar="FILE", default=None,
                   help="one line per frame: index, state (init, tracked, reinit: started again after a loss, "
                        "lost: no pose), landmarks, inliers")
    p.add_argument("--max-lost", type=float, default=0.10, metavar="FRACTION",
                   help="exit 1 when more than this fraction of the frames has no pose")
    p.add_argument("--ba-window", type=int, default=0, metavar="N",
                   help="monocular landmarks: windowed bundle adjustment of the last N frames (vslam.ba_window; "
                        "0: off, the default; refused with --init stereo, whose landmarks the pair measures; see "
                        "docs/vslam.md)")
    p.add_argument("--quiet", action="store_true", help="no per-frame progress")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np

    from vbnav.control.trajectory_metrics import ate_rmse, rpe, rpe_pairs, scale_to, write_tum
    from vbnav.control.vo import VoError, VoStopped, run_vo
    from vbnav.drivers.datasets import DEPTH_MAX_DT_S, DatasetError, open_dataset
    from vbnav.vision.vslam import VslamConfig

    from vbnav.control.commands._common import distinct_files, output_file
    output_file(args.out, "--out")          # before minutes of tracking, not after
    output_file(args.plot, "--plot")
    output_file(args.status_out, "--status-out")
    distinct_files({"--out": args.out, "--plot": args.plot, "--status-out": args.status_out},
                   {"--camera": args.camera})
    if args.ba_window < 0:
        print(f"vbnav vo: --ba-window {args.ba_window}: expected a number of frames >= 0", file=sys.stderr)
        return 2
    if not 0.0 <= args.max_lost <= 1.0:
        print(f"vbnav vo: --max-lost {args.max_lost}: expected a fraction of the frames in [0, 1]", file=sys.stderr)
        return 2
    say = (lambda s: None) if args.quiet else (lambda s: print(s, flush=True))
    try:
        ds = open_dataset(args.dataset, args.camera)
        # An output that is one of the dataset's files (--out SEQ/poses.txt) would replace recorded data.
        dataset_files = {os.path.realpath(p) for p in [ds.root / n for n in DATASET_FILES] + list(ds.left)
                         + list(ds.right or []) + [d for d in ds.depth or [] if d is not None] if p.exists()}
        outputs = {"--out": args.out, "--plot": args.plot, "--status-out": args.status_out}
        for option, path in outputs.items():
            if path is not None and os.path.realpath(path) in dataset_files:
                print(f"vbnav vo: {option} {path}: is a file of the dataset {ds.root}; writing it would replace "
                      f"recorded data (choose another file)", file=sys.stderr)
                return 2
        if args.plot and ds.gt_poses is None:     # the plot is the aligned trajectory over the ground truth
            print(f"vbnav vo: --plot {args.plot}: the dataset {ds.root} has no ground truth to plot against "
                  f"(no {GROUND_TRUTH_FILE[ds.layout]}); leave out --plot", file=sys.stderr)
            return 2
        say(f"{ds.root}: {ds.layout} layout, {len(ds)} frames, camera fx={ds.camera.fx:.1f}"
            + (f", stereo baseline {ds.stereo_baseline:.4f} m" if ds.stereo_baseline else ""))
        t0 = time.perf_counter()
        res = run_vo(ds, args.init, VslamConfig(ba_window=args.ba_window), progress=say)
        dt = time.perf_counter() - t0
    except VoStopped as exc:            # the frames tracked before the unreadable one are kept
        res = exc.result
        if len(res.stamps):
            write_tum(args.out, res.stamps, res.poses)
        if args.status_out:
            _write_status(args.status_out, res.status)
        print(f"vbnav vo: {exc}; stopped there: "
              + (f"the trajectory of the {len(res.stamps)} frame(s) with a pose (frames 0-{res.frames[-1]}) "
                 f"written to {args.out}" if len(res.stamps) else f"no frame had a pose, {args.out} not written")
              + (f", the frames' states to {args.status_out}" if args.status_out else ""), file=sys.stderr)
        return 2
    except (DatasetError, VoError, ValueError) as exc:
        print(f"vbnav vo: {exc}", file=sys.stderr)
        return 2
    write_tum(args.out, res.stamps, res.poses)
    if args.status_out:
        _write_status(args.status_out, res.status)
    no_depth = [i for i, d in enumerate(ds.depth or []) if d is None] if res.init == "depth" else []
    if no_depth:
        print(f"{len(no_depth)} of {len(ds)} frames have no depth image within {DEPTH_MAX_DT_S:g} s in "
              f"{ds.root / 'depth.txt'} (frame{'s' if len(no_depth) > 1 else ''} {_ranges(no_depth)}): "
              f"tracked without depth")
    lost = res.count("lost")
    print(f"pose for {len(res.stamps)}/{len(ds)} frames in {dt:.1f} s ({len(ds) / max(dt, 1e-9):.1f} fps): "
          f"{res.count('init')} initialisation, {res.count('tracked')} tracked, {res.count('reinit')} "
          f"re-initialised, {lost} lost; {res.references} reference frame(s); trajectory written to {args.out}")
    if ds.gt_poses is not None:
        ok, gt = ds.ground_truth_at(res.stamps, GT_MAX_DT_S)
        if not ok.all():
            missing = [res.frames[k] for k in np.flatnonzero(~ok)]
            print(f"{len(missing)} of {len(ok)} frames with a pose have no ground truth within {GT_MAX_DT_S:g} s "
                  f"(frame{'s' if len(missing) > 1 else ''} {_ranges(missing)}): left out of ATE and RPE")
        if ok.sum() >= 3:
            est, gt = res.poses[ok], gt[ok]
            frames = np.asarray(res.frames)[ok]
            ate, aligned = ate_rmse(est, gt, with_scale=not res.scale_known)
            t_rpe, r_rpe = rpe(est if res.scale_known else scale_to(est, gt), gt, frames=frames)
            kind = "SE(3)" if res.scale_known else "Sim(3) (monocular, scale unknown)"
            print(f"ATE RMSE {ate:.4f} m ({kind} alignment, {int(ok.sum())} poses); "
                  f"RPE (1 frame, {len(rpe_pairs(len(frames), 1, frames))} pairs"
                  f"{'' if res.scale_known else ', after the Sim(3) scale'}) {t_rpe:.4f} m, {r_rpe:.3f} deg")
            if args.plot:
                _plot_trajectory(args.plot, aligned, gt[:, :3, 3], f"{ds.root.name}: ATE {ate:.3f} m")
        else:
            print("ground truth present but fewer than 3 poses match the tracked frames' times"
                  + (f"; --plot {args.plot} not written" if args.plot else ""))
    if lost > args.max_lost * len(ds) or len(res.stamps) < 2:
        print(f"vbnav vo: {lost} of {len(ds)} frames ({100 * lost / len(ds):.0f} %) have no pose, more than "
              f"--max-lost {args.max_lost:g}", file=sys.stderr)
        return 1
    return 0


def _ranges(frames: list[int]) -> str:
    """Frame numbers as ranges: 3, 7-9, 12."""
    out, start = [], None
    for k, f in enumerate(frames):
        start = f if start is None else start
        if k + 1 == len(frames) or frames[k + 1] != f + 1:
            out.append(f"{start}" if start == f else f"{start}-{f}")
            start = None
    return ", ".join(out)


def _write_status(path: str, status) -> None:
    """``frame state landmarks inliers`` per dataset frame, written atomically."""
    path = Path(path)
    lines = ["# frame state landmarks inliers (state: init, tracked, reinit, lost)"]
    lines += [f"{s.frame} {s.state} {s.landmarks} {s.inliers}" for s in status]
    write_atomic(path, "\n".join(lines) + "\n")


def _plot_trajectory(path: str, aligned, gt, title: str) -> None:
    """The aligned trajectory over the ground truth, seen from above (x, z), written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 6))
    ax.plot(gt[:, 0], gt[:, 2], "k-", label="ground truth")
    ax.plot(aligned[:, 0], aligned[:, 2], "r-", label="vbnav vo (aligned)")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("z [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend()
    ax.set_title(title)
    try:
        with atomic_output(path) as tmp:
            fig.savefig(tmp, dpi=100)
    finally:
        plt.close(fig)
