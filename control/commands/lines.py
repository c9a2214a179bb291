"""``vbnav lines``: 3D line segments from one rectified stereo pair (Marvin, section 11.2.1.1).

Writes a JSON file with every reconstructed segment: its endpoints in the left
camera frame (metres, x right, y down, z forward) with their covariances, its
endpoints in both images and its match score; optionally an overlay of the
segments on the left image coloured by depth.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import cv2
import numpy as np

from vbnav.control.commands._common import DefaultsHelpFormatter, distinct_files, output_file, positive
from vbnav.control.image_files import (display_bgr, json_text, pair_problem, png_bytes, png_name_problem, read_image,
                                      same_pair_problem)
from vbnav.drivers.atomic_file import write_atomic_set
from vbnav.drivers.stereo_calib import CalibrationError, load_stereo_calibration
from vbnav.vision.line_segments import LineParams, reconstruct_pair

EXIT_OK, EXIT_BAD_INPUT = 0, 2
FORMAT, VERSION = "vbnav-line-segments", 1


def _angle(text: str) -> float:
    """argparse type: an angle to the image rows, degrees, in (0, 90) (past 90 its sine, which the
    matcher compares, falls again: 180 would let horizontal segments through)."""
    v = positive(text)
    if v >= 90.0:
        raise argparse.ArgumentTypeError(f"expected an angle to the rows in degrees, 0 < A < 90, got {text!r}")
    return v


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "lines", help="3D line segments from one rectified stereo pair",
        description="Detect line segments (OpenCV LSD) in both rectified images, match them under the epipolar "
                    "constraint (row overlap, direction and contrast polarity, side grey levels) and reconstruct "
                    "each match as a 3D segment with the covariance of its endpoints (docs/line_map.md). Segments "
                    "within --min-epipolar-angle of horizontal are not reconstructed: their disparity is "
                    "undetermined. Writes JSON; prints a one-line summary.",
        formatter_class=DefaultsHelpFormatter)
    p.add_argument("--left", required=True, metavar="L", help="left image (rectified, or raw with an OpenCV "
                   "stereo rectification as --calib)")
    p.add_argument("--right", required=True, metavar="R", help="right image (as --left)")
    p.add_argument("--calib", required=True, metavar="FILE",
                   help="KITTI calib.txt (P0/P1) or a vbnav stereo YAML (as for vbnav obstacles), or an OpenCV "
                        "stereo rectification (K0 D0 K1 D1 R1 R2 P1 P2: the images are raw and are rectified "
                        "with it; drivers/stereo_calib.py)")
    p.add_argument("--out", required=True, metavar="SEGMENTS.json", help="the segments (JSON)")
    p.add_argument("--overlay-out", metavar="PNG", help="segments drawn on the (rectified) left image, colour = depth")
    p.add_argument("--min-length", type=positive, default=LineParams.min_length_px, help="px")
    p.add_argument("--min-depth", type=positive, default=None,
                   help="m, nearest depth searched (sets the largest disparity); default 8 baselines")
    p.add_argument("--min-epipolar-angle", type=_angle, default=LineParams.min_epipolar_angle_deg,
                   help="degrees to the image rows below which a segment is not reconstructed")
    p.add_argument("--all-hypotheses", action="store_true",
                   help="also write the rival matches of ambiguous segments (default: the best match only)")
    p.set_defaults(func=run)


def _bad(msg: str) -> int:
    print(f"vbnav lines: {msg}", file=sys.stderr)
    return EXIT_BAD_INPUT


def depth_colour(z: float, z_max: float) -> tuple:
    """BGR from red (near) to blue (far)."""
    a = float(np.clip(z / z_max, 0.0, 1.0))
    return (int(255 * a), 60, int(255 * (1 - a)))


def draw_segments(image: np.ndarray, xy: np.ndarray, depth: np.ndarray) -> np.ndarray:
    base = display_bgr(image)
    z_max = float(np.percentile(depth, 95)) if len(depth) else 1.0
    for s, z in zip(xy, depth):
        cv2.line(base, (int(round(s[0])), int(round(s[1]))), (int(round(s[2])), int(round(s[3]))),
                 depth_colour(z, z_max), 2, cv2.LINE_AA)
    return base


def _swapped(left: np.ndarray, right: np.ndarray, rig, params: LineParams, matched: int) -> bool:
    """Whether the pair looks swapped: few matches, and many more once both images are mirrored. Mirrored,
    a swapped pair is a stereo pair again (a point at x in the true left image and x - d in the true right one
    is at W - 1 - x + d in the mirrored given left and W - 1 - x in the mirrored given right)."""
    w = left.shape[1]
    mirrored = reconstruct_pair(np.ascontiguousarray(left[:, ::-1]), np.ascontiguousarray(right[:, ::-1]),
                                rig.fx, rig.fy, w - 1 - rig.cx, rig.cy, rig.baseline, params)
    found = int(mirrored.segments.best.sum())
    return found >= 10 and found >= 3 * max(matched, 1)


def _max_disparity(rig, min_depth: float, width: int, given: bool) -> float:
    """The largest disparity searched (fx B / min_depth, at most half the image); ValueError when it leaves
    nothing to match (a very small focal length, or --min-depth beyond what the rig resolves), or when a
    --min-depth ``given`` asks for more than half the image (the default, 8 baselines, is cut to it)."""
    if given and rig.fb / min_depth > width / 2.0:      # it was cut to half the image without a word
        raise ValueError(f"--min-depth {min_depth:g} m: the largest disparity searched, fx B / depth = "
                         f"{rig.fb:g} / {min_depth:g} = {rig.fb / min_depth:.0f} px, is more than half the image "
                         f"width ({width / 2.0:g} px), the most the matcher searches: the nearest depth it can "
                         f"search is {rig.fb / (width / 2.0):.3g} m")
    d_max = min(rig.fb / min_depth, width / 2.0)
    if d_max <= LineParams.min_disparity_px:
        what = f"--min-depth {min_depth:g} m" if given else f"the default nearest depth, 8 baselines ({min_depth:g} m)"
        raise ValueError(f"{what}: the largest disparity searched, fx B / depth = {rig.fb:g} / {min_depth:g} = "
                         f"{rig.fb / min_depth:.3g} px, is not above the smallest the matcher takes "
                         f"({LineParams.min_disparity_px:g} px): nothing could be matched (fx {rig.fx:g} px, "
                         f"baseline {rig.baseline:g} m)")
    return d_max


def run(args) -> int:
    t0 = time.perf_counter()
    output_file(args.out, "--out")
    output_file(args.overlay_out, "--overlay-out")
    why = png_name_problem(args.overlay_out, "--overlay-out")
    if why:
        return _bad(why)
    distinct_files({"--out": args.out, "--overlay-out": args.overlay_out},
                   {"--left": args.left, "--right": args.right, "--calib": args.calib})
    why = same_pair_problem(args.left, args.right)      # before the calibration is read
    if why:
        return _bad(why)
    try:
        calib = load_stereo_calibration(args.calib, raw_images=True)
        left = read_image(args.left, "left image")
        right = read_image(args.right, "right image")
        why = pair_problem(left, right, args.left, args.right) or same_pair_problem(args.left, args.right, left, right)
        if why:
            return _bad(why)
        left, right = calib.rectify(left, right)
        h, w = left.shape[:2]
        rig = calib.rig(w, h)
        min_depth = args.min_depth if args.min_depth is not None else 8.0 * rig.baseline
        d_max = _max_disparity(rig, min_depth, w, args.min_depth is not None)
    except (CalibrationError, ValueError, FileNotFoundError) as exc:
        return _bad(str(exc))
    params = dataclasses.replace(LineParams(), min_length_px=args.min_length,
                                 min_epipolar_angle_deg=args.min_epipolar_angle, max_disparity_px=d_max)
    res = reconstruct_pair(left, right, rig.fx, rig.fy, rig.cx, rig.cy, rig.baseline, params)
    seg = res.segments if args.all_hypotheses else res.segments.subset(res.segments.best)
    items = []
    for k in range(len(seg)):
        items.append({
            "p0_m": [round(float(v), 5) for v in seg.P[k, 0]], "p1_m": [round(float(v), 5) for v in seg.P[k, 1]],
            "cov0_m2": np.round(seg.cov[k, 0], 8).tolist(), "cov1_m2": np.round(seg.cov[k, 1], 8).tolist(),
            "left_px": [round(float(v), 3) for v in seg.left_xy[k]],
            "right_px": [round(float(v), 3) for v in seg.right_xy[k]],
            "score": round(float(seg.score[k]), 4), "best": bool(seg.best[k]), "group": int(seg.group[k])})
    data = {"format": FORMAT, "version": VERSION, "frame": "left camera: x right, y down, z forward (m)",
            "image": {"width": w, "height": h}, "baseline_m": rig.baseline,
            "detected": {"left": len(res.left), "right": len(res.right)}, "segments": items}
    if calib.rectification is not None:      # image coordinates are those of the rectified pair
        data["rectified_with"] = str(args.calib)
    files = {args.out: json_text(data)}
    if args.overlay_out:
        files[args.overlay_out] = png_bytes(args.overlay_out, draw_segments(left, seg.left_xy,
                                                                            seg.P[..., 2].mean(axis=1)))
    write_atomic_set(files)                  # both or neither: a failed overlay does not leave a new --out
    ambiguous = len(set(res.segments.group[~res.segments.best].tolist()))
    print(f"vbnav lines: {len(res.left)} left / {len(res.right)} right segments, {len(seg)} reconstructed "
          f"({ambiguous} ambiguous), {(time.perf_counter() - t0) * 1e3:.0f} ms -> {args.out}")
    matched = int(res.segments.best.sum())
    if len(res.left) >= 20 and matched < 0.1 * len(res.left) and _swapped(left, right, rig, params, matched):
        print(f"vbnav lines: note: only {matched} of {len(res.left)} left segments matched, and many more do with "
              f"the images mirrored: are --left and --right swapped?", file=sys.stderr)
    return EXIT_OK
