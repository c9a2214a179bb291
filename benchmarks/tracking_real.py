"""Feature tracking on the real hand-held ``target_sequence`` (501 grey frames, no ground truth), every frame:
vbnav's ``FeatureTracker`` (GFTT + forward-backward KLT) against a naive OpenCV peer (GFTT + pyramidal LK with
OpenCV's defaults and its status flag only) in the same run. Figures and their definitions:
tests/tracking_metrics.py (tracks per frame, survival of the first frame's tracks, forward-backward return
error over 50-frame windows and over the whole sequence, the share of reported points that come back more than
2 px off). Bars: tests/test_features.py.

    .venv/bin/python benchmarks/tracking_real.py [--data DIR] [--window 50]

DIR is the shared data folder (default $VBNAV_DATA, else ../shared/data beside the repository).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from tracking_metrics import load_sequence, measure, whole_return  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("VBNAV_DATA") or ROOT.parent / "shared" / "data"),
                    help="the shared data folder (default $VBNAV_DATA, else ../shared/data)")
    ap.add_argument("--window", type=int, default=50, help="frames forward (and back) per drift window")
    args = ap.parse_args(argv)
    folder = args.data / "target_sequence"
    if not folder.is_dir():
        ap.error(f"{folder}: no such folder (set --data or VBNAV_DATA to the shared data folder)")
    images = load_sequence(folder)
    print(f"{folder}: {len(images)} frames {images[0].shape[1]}x{images[0].shape[0]}")
    rows = {}
    for name in ("vbnav", "opencv_lk"):
        t0 = time.process_time()
        fig = measure(images, name, args.window).summary()
        whole = whole_return(images, name)
        rows[name] = (fig, whole)
        surv = " ".join(f"{k}:{v}" for k, v in fig["survival"].items())
        print(f"{name:10s} tracks/frame min {fig['tracks_min']} median {fig['tracks_median']:.0f}; first-frame "
              f"tracks alive at {surv}; {args.window}-frame return median {fig['return_median_px']:.3f} px, "
              f"p90 {fig['return_p90_px']:.2f} px ({fig['returned']} of {fig['started']} points); whole "
              f"sequence: {whole.reported} of {whole.started} reported at the last frame, {whole.wrong} of "
              f"{whole.returned} back > 2 px ({100 * whole.wrong_share:.0f} %), median "
              f"{np.median(whole.errors_px):.2f} px; {time.process_time() - t0:.1f} s CPU", flush=True)
    (a, wa), (b, wb) = rows["vbnav"], rows["opencv_lk"]
    print(f"ratios vbnav / opencv_lk: {args.window}-frame return p90 {a['return_p90_px'] / b['return_p90_px']:.2f}x, "
          f"wrong share over the whole sequence {wa.wrong_share / max(wb.wrong_share, 1e-9):.2f}x, "
          f"good points at the last frame (back within 2 px) {wa.returned - wa.wrong} vs {wb.returned - wb.wrong}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
