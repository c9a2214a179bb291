"""``vbnav obstacles``: ground-plane suppression on one stereo pair or disparity image.

Prints a JSON summary; optionally writes the label mask (0 ground, 1 obstacle,
2 negative obstacle, 255 unknown) and an overlay of the classes on the left image.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from vbnav.control.commands._common import DefaultsHelpFormatter, distinct_files, finite, non_negative, output_file, positive
from vbnav.control.image_files import (display_bgr, pair_problem, png_name_problem, read_image, same_pair_problem,
                                      write_png)
from vbnav.drivers.errors import InputError
from vbnav.drivers.stereo_calib import CalibrationError, load_stereo_calibration
from vbnav.vision.ground_model import GroundModelParams
from vbnav.vision.ground_plane import PlaneFitParams, expected_plane
from vbnav.vision.obstacles import ObstacleParams, PixelClass, detect_obstacles, nearest_in_corridor
from vbnav.vision.stereo import (MAX_SGBM_DISPARITIES, as_disparity, sgbm_disparities_for, sgbm_disparity,
                                 sgbm_params_for)

EXIT_OK, EXIT_BAD_INPUT = 0, 2

# Defaults of the options that apply to one input or ground model only: the options default to None, so
# that one given where it does not apply is refused (a setting that is accepted is used).
DEFAULTS = {"block_size": 5, "height_tol": 0.05, "tilt_tol_deg": 2.0, "ground_half_width": 1.0,
            "max_grade_change": 0.08, "cross_slope_allowance": 0.06}

COLOURS_BGR = {PixelClass.GROUND: (60, 200, 60), PixelClass.OBSTACLE: (40, 40, 230),
               PixelClass.NEGATIVE: (230, 120, 30)}


def _block_size(text: str) -> int:
    """argparse type: SGBM's block size, an odd number of pixels."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an odd integer, got {text!r}") from None
    if v < 1 or v > 51 or v % 2 == 0:
        raise argparse.ArgumentTypeError(f"expected an odd integer in 1..51, got {text!r}")
    return v


def _degrees(limit: float):
    """argparse type: an angle in degrees within +-limit, the bounds of the stereo YAML's mount (and of
    camera.mount in a configuration)."""
    def angle(text: str) -> float:
        v = finite(text)
        if abs(v) > limit:
            raise argparse.ArgumentTypeError(f"expected degrees in -{limit:g}..{limit:g}, got {text!r}")
        return v
    return angle


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "obstacles", help="find obstacles in a stereo pair by ground-plane suppression",
        description="Fit the ground plane D(u,v) = rho1 u + rho2 v + rho3 in (u, v, disparity) space, label every "
                    "pixel ground / obstacle / negative obstacle / unknown with thresholds given in metres, and "
                    "report the nearest obstacle in the driving corridor. Input: a rectified pair (--left/--right, "
                    "disparity by OpenCV SGBM) or a disparity image (--disparity). Prints JSON.",
        formatter_class=DefaultsHelpFormatter)
    src = p.add_argument_group("input")
    src.add_argument("--left", metavar="L", help="rectified left image")
    src.add_argument("--right", metavar="R", help="rectified right image")
    src.add_argument("--disparity", metavar="D",
                     help="disparity image instead of --left/--right: .npy or PNG/TIFF, multiplied by "
                          "--disparity-scale (a .npy of float px needs none: its default is the YAML's "
                          "disparity_scale, else 1); 0 or NaN is unknown")
    src.add_argument("--image", metavar="IMG",
                     help="image for --overlay-out when --disparity is given (with --left/--right: the left image)")
    src.add_argument("--calib", required=True, metavar="FILE",
                     help="KITTI calib.txt (P0/P1) or a vbnav stereo YAML (docs/obstacles.md)")
    src.add_argument("--disparity-scale", type=positive, default=None,
                     help="px per unit of the --disparity file (default: the YAML's disparity_scale, else "
                          "1/256 for a 16-bit image as in KITTI's devkit, 1 for an 8-bit one or a .npy); with "
                          "--disparity only")
    geo = p.add_argument_group("camera above the floor (seeds the plane fit)")
    geo.add_argument("--camera-height", type=positive, default=None,
                     help="m; default: the YAML's mount.height; without it the fit is unseeded")
    geo.add_argument("--pitch-deg", type=_degrees(90), default=None,
                     help="positive looking down, -90..90 (default: YAML or 0); needs the camera height")
    geo.add_argument("--roll-deg", type=_degrees(45), default=None,
                     help="camera roll over the floor, -45..45 (default: YAML or 0); needs the camera height")
    gm = p.add_argument_group("ground model (docs/obstacles.md)")
    gm.add_argument("--ground", choices=("auto", "piecewise", "plane"), default="auto",
                    help="piecewise: near band under the mounting's bounds, farther bands hinged (needs a camera "
                         "height); plane: one plane; auto: piecewise when the camera height is known")
    gm.add_argument("--height-tol", type=positive, default=None,
                    help="m: reject a near-band fit whose camera height is further from the mounting's (default: "
                         f"{DEFAULTS['height_tol']}; needs the camera height)")
    gm.add_argument("--tilt-tol-deg", type=positive, default=None,
                    help="deg: reject a near-band fit whose pitch or roll is further from the mounting's (default: "
                         f"{DEFAULTS['tilt_tol_deg']}; needs the camera height)")
    gm.add_argument("--ground-half-width", type=positive, default=None,
                    help="m: the ground is fitted within this of the camera's line ahead (default: "
                         f"{DEFAULTS['ground_half_width']}; piecewise ground only)")
    gm.add_argument("--max-grade-change", type=non_negative, default=None,
                    help="rise over run a band may bend by from the one before (default: "
                         f"{DEFAULTS['max_grade_change']}; piecewise ground only)")
    gm.add_argument("--cross-slope-allowance", type=non_negative, default=None,
                    help="m per m: thresholds grow by this beyond the ground corridor (camber) (default: "
                         f"{DEFAULTS['cross_slope_allowance']}; piecewise ground only)")
    gm.add_argument("--fit-inlier-height", type=positive, default=0.02, help="m, ground fit inlier band")
    det = p.add_argument_group("detection")
    det.add_argument("--obstacle-height", type=positive, default=0.05, help="m above the floor")
    det.add_argument("--negative-depth", type=positive, default=0.05, help="m below the floor")
    det.add_argument("--noise-px", type=non_negative, default=0.4, help="disparity noise floor, px")
    det.add_argument("--max-height", type=positive, default=None, help="m; higher points are unknown (overhangs)")
    det.add_argument("--max-range", type=positive, default=None, help="m; farther points are unknown")
    det.add_argument("--corridor-half-width", type=positive, default=0.3, help="m, for the nearest obstacle")
    det.add_argument("--corridor-range", type=positive, default=10.0, help="m, for the nearest obstacle")
    det.add_argument("--block-size", type=_block_size, default=None,
                     help=f"SGBM block size (odd; default: {DEFAULTS['block_size']}); with --left/--right only")
    det.add_argument("--min-depth", type=positive, default=None,
                     help="m, nearest depth SGBM must cover (sets numDisparities); default: 8 baselines, or 0.85 x "
                          "the nearest floor depth in view if that is nearer; with --left/--right only")
    out = p.add_argument_group("output")
    out.add_argument("--mask-out", metavar="M.png", help="labels: 0 ground, 1 obstacle, 2 negative, 255 unknown")
    out.add_argument("--overlay-out", metavar="O.png", help="the classes drawn on the left image")
    p.set_defaults(func=run)


def _bad(msg: str) -> int:
    print(f"vbnav obstacles: {msg}", file=sys.stderr)
    return EXIT_BAD_INPUT


def _given(args, *dests: str) -> list[str]:
    """The options among ``dests`` given on the command line (their defaults are None)."""
    return ["--" + d.replace("_", "-") for d in dests if getattr(args, d) is not None]


def _not_for_input(args) -> Optional[str]:
    """Why an option given does not apply to the input chosen (a pair, or a disparity image), or None."""
    if args.disparity is not None:
        given = _given(args, "block_size", "min_depth")
        if given:
            return (f"{', '.join(given)}: set(s) OpenCV SGBM, which runs on --left/--right; with --disparity it "
                    "does not run")
        if args.image is not None and args.overlay_out is None:
            return "--image is the image --overlay-out draws on; without --overlay-out it would not be used"
        return None
    if args.image is not None:
        return "--image goes with --disparity; with --left/--right the overlay is drawn on the --left image"
    if args.disparity_scale is not None:
        return "--disparity-scale scales a --disparity file; with --left/--right SGBM computes the disparity"
    return None


def _not_for_ground(args, height, model: str) -> Optional[str]:
    """Why a mounting or ground-model option given is unused (no camera height; one plane), or None."""
    if height is None:
        given = _given(args, "pitch_deg", "roll_deg", "height_tol", "tilt_tol_deg")
        if given:
            return (f"{', '.join(given)}: the mounting needs the camera height (--camera-height, or mount.height "
                    "in the YAML); without it the fit is unseeded and these are not used")
    if model == "plane":
        given = _given(args, "ground_half_width", "max_grade_change", "cross_slope_allowance")
        if given:
            why = ("--ground plane" if args.ground == "plane" else
                   "--ground auto without a camera height (--camera-height, or mount.height in the YAML)")
            return f"{', '.join(given)}: shape(s) the piecewise ground; {why} fits one plane"
    return None


def _read_disparity(path: str, scale_arg, calib) -> np.ndarray:
    if path.endswith(".npy"):
        if not Path(path).is_file():
            raise FileNotFoundError(f"disparity {path}: file not found")
        d = np.load(path)
        scale = scale_arg if scale_arg is not None else (calib.disparity_scale or 1.0)
    else:
        d = read_image(path, "disparity")
        if d.ndim != 2:
            raise ValueError(f"disparity {path}: expected a single-channel image, got shape {d.shape}")
        default = 1.0 / 256.0 if d.dtype == np.uint16 else 1.0
        scale = scale_arg if scale_arg is not None else (calib.disparity_scale or default)
    if d.ndim != 2:
        raise ValueError(f"disparity {path}: expected an HxW array, got shape {d.shape}")
    return as_disparity(d.astype(np.float32) * np.float32(scale))


def overlay(image: np.ndarray, labels: np.ndarray, alpha: float = 0.45) -> np.ndarray:
    """The classes drawn over the image (BGR): ground green, obstacle red, negative blue."""
    base = display_bgr(image)
    colour = base.copy()
    for cls, bgr in COLOURS_BGR.items():
        colour[labels == cls] = bgr
    return cv2.addWeighted(base, 1.0 - alpha, colour, alpha, 0.0)


def _nearest_json(n):
    if n is None:
        return None
    return {"distance_m": round(n.distance, 3), "bearing_deg": round(math.degrees(n.bearing), 2),
            "lateral_m": round(n.lateral, 3)}


def _min_depth(args, rig, prior) -> float:
    """Nearest depth SGBM must cover: 8 baselines, or nearer if the floor in view is nearer."""
    if args.min_depth:
        return args.min_depth
    depth = 8.0 * rig.baseline
    if prior is not None:
        d_floor = float(prior.image(rig.height, rig.width)[-1, [0, -1]].max())
        if d_floor > 0:
            depth = min(depth, 0.85 * rig.fb / d_floor)
    return depth


def run(args) -> int:
    t0 = time.perf_counter()
    output_file(args.mask_out, "--mask-out")
    output_file(args.overlay_out, "--overlay-out")
    for path, option in ((args.mask_out, "--mask-out"), (args.overlay_out, "--overlay-out")):
        why = png_name_problem(path, option)
        if why:
            raise InputError(why)
    distinct_files({"--mask-out": args.mask_out, "--overlay-out": args.overlay_out},
                   {"--left": args.left, "--right": args.right, "--disparity": args.disparity, "--image": args.image,
                    "--calib": args.calib})
    if args.disparity is None and not (args.left and args.right):
        return _bad("give --left and --right, or --disparity")
    if args.disparity is not None and (args.left or args.right):
        return _bad("give either --left/--right or --disparity, not both")
    why = _not_for_input(args)
    if why:
        return _bad(why)
    try:
        calib = load_stereo_calibration(args.calib)
        if args.disparity is not None:
            disp = _read_disparity(args.disparity, args.disparity_scale, calib)
            image = read_image(args.image, "image") if args.image else None
            source = "file"
        else:
            left = read_image(args.left, "left image")
            right = read_image(args.right, "right image")
            why = pair_problem(left, right, args.left, args.right)
            if why:
                return _bad(why)
            image, disp, source = left, None, "sgbm"
        h, w = (disp.shape if disp is not None else image.shape[:2])
        if image is not None and image.shape[:2] != (h, w):
            return _bad(f"image {args.image} is {image.shape[1]}x{image.shape[0]}, disparity is {w}x{h}")
        rig = calib.rig(w, h)
        # after the calibration's checks (as the pair's size): one image twice has no disparity, and failed late
        why = same_pair_problem(args.left, args.right, image, right) if disp is None else ""
        if why:
            return _bad(why)
    except (CalibrationError, ValueError, FileNotFoundError) as exc:
        return _bad(str(exc))

    height = args.camera_height if args.camera_height is not None else calib.mount_height
    pitch = args.pitch_deg if args.pitch_deg is not None else calib.mount_pitch_deg
    roll = args.roll_deg if args.roll_deg is not None else calib.mount_roll_deg
    prior = expected_plane(rig, height, math.radians(pitch), math.radians(roll)) if height is not None else None
    if args.ground == "piecewise" and prior is None:
        return _bad("--ground piecewise needs the camera height (--camera-height, or mount.height in the YAML); "
                    "give it, or --ground plane")
    model = args.ground if args.ground != "auto" else ("piecewise" if prior is not None else "plane")
    why = _not_for_ground(args, height, model)
    if why:
        return _bad(why)
    for dest, value in DEFAULTS.items():       # the options that apply here and were not given
        if getattr(args, dest) is None:
            setattr(args, dest, value)

    t1 = time.perf_counter()
    if disp is None:
        min_depth = _min_depth(args, rig, prior)
        if sgbm_disparities_for(rig, min_depth) > MAX_SGBM_DISPARITIES:
            nearest = rig.fb / MAX_SGBM_DISPARITIES
            if args.min_depth:          # it was cut to what 256 disparities reach without a word
                raise InputError(f"--min-depth {args.min_depth:g} m needs {rig.fb / args.min_depth:.0f} px of "
                                 f"disparity (fx B {rig.fb:g} px m); SGBM searches at most {MAX_SGBM_DISPARITIES}: "
                                 f"the nearest depth it can cover is {nearest:.3g} m")
            print(f"vbnav obstacles: note: the floor in view comes nearer than {MAX_SGBM_DISPARITIES} disparities "
                  f"reach: depths under {nearest:.3g} m are not matched", file=sys.stderr)
        sgbm = sgbm_params_for(rig, min_depth, args.block_size)
        if w < sgbm.num_disparities + sgbm.block_size:
            raise InputError(f"--left {args.left}: the pair is {w}x{h}, too narrow for a search over "
                             f"{sgbm.num_disparities} disparities (needs at least "
                             f"{sgbm.num_disparities + sgbm.block_size} px across; raise --min-depth)")
        disp = sgbm_disparity(image, right, sgbm)
    t2 = time.perf_counter()
    params = ObstacleParams(obstacle_height=args.obstacle_height, negative_depth=args.negative_depth,
                            noise_px=args.noise_px, max_height=args.max_height, max_range=args.max_range,
                            report_range=args.corridor_range)
    try:
        fit = PlaneFitParams(inlier_height=args.fit_inlier_height, max_height_change=args.height_tol,
                             max_pitch_change_deg=args.tilt_tol_deg, max_roll_change_deg=args.tilt_tol_deg)
        ground = None if model == "plane" else GroundModelParams(
            corridor_half_width=args.ground_half_width, max_grade_change=args.max_grade_change,
            cross_slope_allowance=args.cross_slope_allowance)
        scene = detect_obstacles(disp, rig, prior, fit, params, ground)
    except ValueError as exc:
        print(f"vbnav obstacles: {exc}", file=sys.stderr)
        return 1
    t3 = time.perf_counter()
    near = nearest_in_corridor(scene.obstacle_points, args.corridor_half_width, args.corridor_range)
    near_neg = nearest_in_corridor(scene.negative_points, args.corridor_half_width, args.corridor_range)
    fl = scene.fit.floor
    if args.mask_out:
        write_png(args.mask_out, scene.labels)
    if args.overlay_out:
        if image is None:
            base = cv2.normalize(np.nan_to_num(disp), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
        else:
            base = image
        write_png(args.overlay_out, overlay(base, scene.labels))
    summary = {
        "image": {"width": w, "height": h},
        "disparity_source": source,
        "plane": {"rho": [round(x, 6) for x in scene.plane.rho], "camera_height_m": round(fl.height, 4),
                  "pitch_deg": round(math.degrees(fl.pitch), 3), "roll_deg": round(math.degrees(fl.roll), 3),
                  "fit_ok": scene.fit.ok, "used_prior": scene.fit.used_prior,
                  "inlier_fraction": round(scene.fit.inlier_fraction, 4), "note": scene.fit.reason},
        "ground_model": model,
        "ground_bands": None if scene.ground is None else [
            {"from_m": round(rig.fb / b.near_disparity, 2) if math.isfinite(b.near_disparity) else 0.0,
             "grade_change_deg": round(math.degrees(b.grade_change), 3), "fitted": b.fitted,
             "inliers": b.inliers, "note": b.reason} for b in scene.ground.bands],
        "fractions": {k: round(v, 5) for k, v in scene.fractions.items()},
        "nearest_obstacle": _nearest_json(near),
        "nearest_negative": _nearest_json(near_neg),
        "corridor": {"half_width_m": args.corridor_half_width, "range_m": args.corridor_range},
        "time_ms": {"load": round((t1 - t0) * 1e3, 2), "disparity": round((t2 - t1) * 1e3, 2),
                    "detection": round((t3 - t2) * 1e3, 2), "total": round((time.perf_counter() - t0) * 1e3, 2)},
    }
    print(json.dumps(summary, indent=2))
    return EXIT_OK
