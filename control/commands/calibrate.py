"""vbnav calibrate: camera intrinsics, a stereo pair, and the camera's mounting over the floor.

``intrinsics`` (a folder of images, or the configured camera live) and ``stereo`` (two folders) write
OpenCV YAML and ROS camera_info files with the RMS and per-view reprojection errors; ``mount`` measures
the camera's height, pitch and roll over the floor (a board lying on the floor, or the stereo ground
plane) and writes them into the config's ``camera.mount``. The views are chosen by
vision/board_calibration.py (blurred and duplicate views rejected); the files are written by
drivers/calibration.py.
"""
from __future__ import annotations

import argparse
import functools
import math
import re
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from vbnav.control.commands._common import add_config_arg, add_overwrite_arg, non_negative, not_recorded_yet, positive
from vbnav.drivers.atomic_file import write_atomic_set
from vbnav.drivers.camera import CameraError
from vbnav.drivers.errors import InputError

# --live's defaults; --images refuses the live options when given, so they default to None
LIVE_VIEWS, LIVE_TIMEOUT_S = 20, 120.0


def register(sub) -> None:
    p = sub.add_parser("calibrate", help="calibrate the camera (intrinsics, stereo pair) and its mounting",
                       description="Camera calibration from views of a chessboard or ChArUco board. See "
                                   "docs/hardware.md, 'Calibration'.")
    what = p.add_subparsers(dest="what", metavar="WHAT", required=True)

    i = what.add_parser("intrinsics", help="one camera's intrinsics and distortion from board views",
                        description="Detects the board in each view, rejects blurred and duplicate views, "
                                    "runs OpenCV's calibrateCamera and writes OUT/camera_opencv.yaml (OpenCV "
                                    "FileStorage, with the RMS and per-view errors) and OUT/camera_info.yaml "
                                    "(ROS camera_info). Either of them is a camera.calibration_file.")
    src = i.add_mutually_exclusive_group(required=True)
    src.add_argument("--images", metavar="DIR", help="folder of board images (png, jpg, pgm, bmp)")
    src.add_argument("--live", action="store_true", help="take views from the camera of --config (move the "
                                                         "board between views)")
    add_config_arg(i)
    _board_args(i)
    i.add_argument("--views", type=int, default=None,
                   help=f"--live: stop after this many accepted views (default {LIVE_VIEWS})")
    i.add_argument("--timeout", type=positive, default=None,
                   help=f"--live: give up after this long, s (default {LIVE_TIMEOUT_S:g})")
    i.add_argument("--out", required=True, metavar="DIR", help="folder for the calibration files (created)")
    add_overwrite_arg(i, "calibration files already in --out")
    i.add_argument("--fisheye", action="store_true", help="not supported yet: say so rather than fit pinhole")
    i.add_argument("--quiet", action="store_true", help="no per-view lines on stderr")
    i.set_defaults(func=_device_errors(run_intrinsics))

    s = what.add_parser("stereo", help="a stereo pair: each camera, their relative pose and the rectified rig",
                        description="Pairs LEFT and RIGHT images by sorted name, calibrates each camera, then "
                                    "stereoCalibrate (intrinsics fixed) and stereoRectify. Writes OUT/left_*.yaml, "
                                    "OUT/right_*.yaml, OUT/stereo_opencv.yaml (K1 D1 K2 D2 R T) and OUT/stereo.yaml "
                                    "(the rectified rig in vbnav's stereo format: a camera.calibration_file for "
                                    "rectified images). The baseline is in the unit of --square.")
    s.add_argument("left", metavar="LEFT_DIR", help="folder of the left camera's board views")
    s.add_argument("right", metavar="RIGHT_DIR", help="folder of the right camera's views, paired by sorted name "
                   "(numbered images by their number; an image without its partner is refused)")
    _board_args(s)
    s.add_argument("--out", required=True, metavar="DIR", help="folder for the calibration files (created)")
    add_overwrite_arg(s, "calibration files already in --out")
    s.add_argument("--quiet", action="store_true", help="no per-view lines on stderr")
    s.set_defaults(func=run_stereo)

    m = what.add_parser("mount", help="camera height, pitch and roll over the floor, into the config",
                        description="From a board lying flat on the floor (--image, or --live: one view of the "
                                    "configured camera), or from the stereo ground plane (--stereo LEFT RIGHT: a "
                                    "rectified pair of an empty stretch of floor, with the config's stereo "
                                    "calibration). The intrinsics are the config's (camera.calibration_file). "
                                    "Writes camera.mount.height, pitch_deg and roll_deg into the config file in "
                                    "place, keeping its comments (unless --dry-run). -c CONFIG is required "
                                    "unless --dry-run: there is no default file to write into.")
    add_config_arg(m)
    msrc = m.add_mutually_exclusive_group(required=True)
    msrc.add_argument("--image", metavar="FILE", help="an image of the board lying on the floor")
    msrc.add_argument("--live", action="store_true", help="one view of the board from the configured camera")
    msrc.add_argument("--stereo", nargs=2, metavar=("LEFT", "RIGHT"), help="a rectified stereo pair of the floor")
    _board_args(m)
    m.add_argument("--board-thickness", type=non_negative, default=None, metavar="M",
                   help="the board's top surface above the floor, m (added to the height; default 0)")
    m.add_argument("--dry-run", action="store_true",
                   help="print the mounting and check the edit, do not write the config")
    m.set_defaults(func=_device_errors(run_mount))


def _device_errors(run):
    """``run`` with a camera that is not there or fails (--live) reported as a device error: one line, exit 3
    (the contract in control/cli.py), not a bug's traceback. A recorded source of the wrong size
    (CameraSizeError, also an InputError) stays bad input, exit 2."""
    @functools.wraps(run)
    def checked(args) -> int:
        try:
            return run(args)
        except CameraError as exc:
            if isinstance(exc, InputError):
                raise
            print(f"vbnav calibrate: {exc}", file=sys.stderr)
            return 3
    return checked


# The board options default to None and Board's own defaults apply, so that mount --stereo (no board) can tell
# an option given from one left alone. Option dest -> Board field.
BOARD_FIELDS = {"board": "kind", "cols": "cols", "rows": "rows", "square": "square", "marker": "marker",
                "dictionary": "dictionary"}


def _board_args(p) -> None:
    p.add_argument("--board", choices=["chessboard", "charuco"], default=None, help="the target (default chessboard)")
    p.add_argument("--cols", type=int, default=None, help="chessboard: inner corners across (default 9); ChArUco: "
                                                          "squares across")
    p.add_argument("--rows", type=int, default=None, help="chessboard: inner corners down (default 6); ChArUco: "
                                                          "squares down")
    p.add_argument("--square", type=positive, default=None, help="square side, m (default 0.025; the unit of "
                                                                 "baseline and mount height)")
    p.add_argument("--marker", type=positive, default=None, help="ChArUco: marker side, m")
    p.add_argument("--dictionary", type=_dictionary, default=None, metavar="NAME",
                   help="ChArUco: OpenCV ArUco dictionary name (default DICT_6X6_250)")
    p.add_argument("--min-sharpness", type=non_negative, default=None,
                   help="reject views less sharp than this (default: vision/board_calibration.py SHARPNESS_MIN)")


def _dictionary(text: str) -> str:
    """argparse type: one of OpenCV's predefined ArUco dictionaries."""
    from vbnav.vision.board_calibration import ARUCO_DICTIONARIES, unknown_dictionary
    if text not in ARUCO_DICTIONARIES:
        raise argparse.ArgumentTypeError(unknown_dictionary(text))
    return text


def _board(args):
    from vbnav.vision.board_calibration import Board
    given = {field: vars(args)[dest] for dest, field in BOARD_FIELDS.items() if vars(args)[dest] is not None}
    try:
        board = Board(**given)
    except ValueError as exc:
        raise InputError(f"--board: {exc}") from None
    if board.kind == "chessboard" and (charuco := _given(args, ("marker", "dictionary"))):
        raise InputError(f"{', '.join(charuco)}: ChArUco options, and the board is a chessboard (--board charuco "
                         f"for a ChArUco board)")
    return board


def _given(args, dests) -> list[str]:
    """The options among ``dests`` (defaults None) given on the command line, spelt as typed."""
    return [f"--{d.replace('_', '-')}" for d in dests if vars(args)[d] is not None]


def _say(args, text: str) -> None:
    if not args.quiet:                  # intrinsics and stereo, the subcommands that say per-view lines
        print(text, file=sys.stderr, flush=True)


def _images(folder: str, what: str) -> list[Path]:
    d = Path(folder)
    if not d.is_dir():
        raise InputError(f"{what} {d}: not a folder of images")
    files = sorted(p for p in d.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".pgm", ".bmp"))
    if not files:
        raise InputError(f"{what} {d}: no images (.png .jpg .pgm .bmp)")
    return files


def _pair_number(p: Path) -> str | None:
    """The number in an image's name (left03.jpg -> "03"), None if it has none or several."""
    found = re.findall(r"\d+", p.stem)
    return found[0] if len(found) == 1 else None


def _check_pair_numbers(left: list[Path], right: list[Path], left_dir: Path, right_dir: Path) -> None:
    """Stereo views are paired by sorted name; when every image is numbered (left03.jpg, right03.jpg), a pair
    must be of one number: with a view missing on each side, pairing by position calibrated left04 with
    right03 and so on. InputError names the first image without a partner."""
    nl, nr = [_pair_number(p) for p in left], [_pair_number(p) for p in right]
    if None in nl + nr or len(set(nl)) != len(nl) or len(set(nr)) != len(nr):
        return                                          # not numbered views: by sorted name, as documented
    for (files, nums, side), (other, other_dir) in (((right, nr, "left"), (set(nl), left_dir)),
                                                    ((left, nl, "right"), (set(nr), right_dir))):
        for f, n in zip(files, nums):
            if n not in other:
                raise InputError(f"{f}: no {side} image numbered {n} in {other_dir} (a stereo view is a left and "
                                 f"a right image of one number)")


def _out_folder(text: str) -> Path:
    """--out: a folder to create (or one that exists), checked before any view is examined."""
    out = Path(text)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: is a file, expected a folder for the calibration files")
    above = next(p for p in out.parents if p.exists())      # the folders below it are created
    if not above.is_dir():
        raise InputError(f"--out {out}: {above} is a file, not a folder")
    return out


def _grey(path: Path) -> np.ndarray:
    """The view in grey; InputError naming the file if it is unreadable or cut short (datasets' reader)."""
    from vbnav.drivers.datasets import _read_image
    return _read_image(path, True)


def _min_sharpness(args) -> float:
    from vbnav.vision.board_calibration import SHARPNESS_MIN
    return SHARPNESS_MIN if args.min_sharpness is None else args.min_sharpness


class ViewCollector:
    """Board views one by one: detected, sharp enough, not a repeat of an accepted one (each decision said)."""

    def __init__(self, args, board):
        from vbnav.vision.board_calibration import BoardDetector
        self.args, self.detector = args, BoardDetector(board)
        self.min_sharpness = _min_sharpness(args)
        self.views, self.size, self.rejected = [], None, 0

    def offer(self, grey: np.ndarray, name: str, tag: str = "", keep_duplicates: bool = False):
        from vbnav.vision.board_calibration import duplicate_of
        size = (grey.shape[1], grey.shape[0])
        if self.size is None:
            self.size = size
        elif size != self.size:
            raise InputError(f"{name}: is {size[0]}x{size[1]}, the first view was {self.size[0]}x{self.size[1]}")
        view = self.detector.detect(grey, name)
        why = None
        if view is None:
            why = "board not found"
        elif view.sharpness < self.min_sharpness:
            why = f"blurred (sharpness {view.sharpness:.1f} < {self.min_sharpness:g})"
        elif not keep_duplicates and (dup := duplicate_of(view, self.views, size)) is not None:
            why = f"duplicate of {dup.name} (the board did not move)"
        if why:
            self.rejected += 1
            _say(self.args, f"{tag}{name}: rejected: {why}")
            return None
        self.views.append(view)
        _say(self.args, f"{tag}{name}: {len(view.ids)} corners, sharpness {view.sharpness:.0f}")
        return view


def _intrinsics_files(out: Path, prefix: str, result, views, board, name: str) -> dict[Path, str]:
    """The OpenCV and ROS files of one camera's calibration: path -> text (written by the caller, with the
    other files of the set: ``write_atomic_set``)."""
    from vbnav.drivers.calibration import opencv_yaml_text, ros_camera_info_text
    per = {v.name: e for v, e in zip(views, result.per_view)}
    extra = {"avg_reprojection_error": result.rms, "per_view_reprojection_errors": result.per_view,
             "board": f"{board.kind} {board.cols}x{board.rows} square {board.square}"}
    notes = (f"calibrated by vbnav calibrate from {len(views)} views of a {board.kind} {board.cols}x{board.rows}",
             f"rms_reprojection_error_px: {result.rms:.4f}",
             *(f"view {n}: {e:.4f} px" for n, e in per.items()))
    return {out / f"{prefix}opencv.yaml": opencv_yaml_text(result.K, result.dist, result.size, extra=extra),
            out / f"{prefix}info.yaml": ros_camera_info_text(result.K, result.dist, result.size, name=name,
                                                             comments=notes)}


def _loads_back(temps: dict) -> None:
    """``write_atomic_set``'s check: each file that is a camera.calibration_file (all but the stereo_opencv.yaml
    record) loads as one, or the set is not written (InputError naming the file and the loader's reason)."""
    from vbnav.drivers.calibration import CalibrationError, load_camera_calibration
    for target, tmp in temps.items():
        if target.name == "stereo_opencv.yaml":     # K1 D1 K2 D2 R T: a record of the fit, not a calibration_file
            continue
        try:
            load_camera_calibration(tmp)
        except CalibrationError as exc:
            why = str(exc).replace(f"{tmp}: ", "").replace(str(tmp), str(target))
            swapped = " (LEFT_DIR and RIGHT_DIR the wrong way round?)" if "baseline" in why else ""
            raise InputError(f"{target}: not written (nor the other files of the calibration): it would not load "
                             f"as a camera.calibration_file: {why}{swapped}") from None


def _report(label: str, result) -> None:
    K = result.K
    print(f"{label}: RMS reprojection error {result.rms:.4f} px over {len(result.per_view)} views (worst "
          f"{max(result.per_view):.3f} px); fx {K[0, 0]:.3f} fy {K[1, 1]:.3f} cx {K[0, 2]:.3f} cy {K[1, 2]:.3f}; "
          f"distortion {' '.join(f'{d:.5f}' for d in result.dist)}")


def _calibrate(views, size):
    from vbnav.vision.board_calibration import calibrate_intrinsics
    try:
        return calibrate_intrinsics(views, size)
    except ValueError as exc:
        raise InputError(str(exc)) from None


def run_intrinsics(args) -> int:
    if args.fisheye:
        raise InputError("--fisheye: fisheye calibration is not implemented; calibrate a pinhole model or use "
                         "OpenCV's cv2.fisheye.calibrate and load its file")
    if args.images and (given := _given(args, ("config", "views", "timeout"))):
        raise InputError(f"{', '.join(given)}: for --live (the camera of the config); --images calibrates from "
                         f"every image of its folder")
    views = LIVE_VIEWS if args.views is None else args.views
    if views < 1:
        raise InputError(f"--views {views}: expected at least 1")
    board = _board(args)
    out = _out_folder(args.out)
    not_recorded_yet([out / "camera_opencv.yaml", out / "camera_info.yaml"], f"--out {out}", args.overwrite,
                     "a calibration is")
    collector = ViewCollector(args, board)
    t0 = time.monotonic()
    if args.images:
        files = _images(args.images, "--images")
        for k, f in enumerate(files, 1):
            collector.offer(_grey(f), f.name, f"[{k}/{len(files)}] ")
    else:
        _collect_live(args, collector, views)
    if collector.size is None:
        raise InputError("no views")
    _say(args, f"{len(collector.views)} views accepted, {collector.rejected} rejected; calibrating ...")
    result = _calibrate(collector.views, collector.size)
    out.mkdir(parents=True, exist_ok=True)
    files = write_atomic_set(_intrinsics_files(out, "camera_", result, collector.views, board, "camera"),
                             check=_loads_back)
    _report("intrinsics", result)
    print(f"wrote {', '.join(map(str, files))} ({time.monotonic() - t0:.1f} s); use one as camera.calibration_file")
    return 0


def _open_live_camera(args):
    from vbnav.control.config import load_config, validate_driver_options
    from vbnav.control.runtime.factory import make_camera
    from vbnav.drivers.clock import MonotonicClock
    cfg = load_config(args.config)
    if cfg.camera.driver == "sim":
        raise InputError(f"{cfg.source}: camera.driver sim renders a world without a calibration board; "
                         f"--live needs a real camera (or a replay of board images)")
    cam = make_camera(cfg, MonotonicClock(), options=validate_driver_options(cfg, cfg.source)["camera"])
    cam.connect()
    return cfg, cam


def _collect_live(args, collector, want: int) -> None:
    cfg, cam = _open_live_camera(args)
    deadline = time.monotonic() + (LIVE_TIMEOUT_S if args.timeout is None else args.timeout)
    n = 0
    try:
        while len(collector.views) < want and time.monotonic() < deadline:
            frame = cam.read(0.5)
            if frame is None:
                if cam.finished:
                    break
                continue
            n += 1
            img = frame.image if frame.image.ndim == 2 else cv2.cvtColor(frame.image, cv2.COLOR_BGR2GRAY)
            collector.offer(img, f"frame {frame.seq}", f"[{len(collector.views)}/{want}] ")
    finally:
        cam.disconnect()
    if len(collector.views) < want:
        _say(args, f"{cfg.camera.driver} camera: {len(collector.views)} of {want} views after {n} frames")


def run_stereo(args) -> int:
    from vbnav.vision.board_calibration import calibrate_stereo
    board = _board(args)
    out = _out_folder(args.out)
    not_recorded_yet([out / f"{side}_{kind}.yaml" for side in ("left", "right") for kind in ("opencv", "info")]
                     + [out / "stereo_opencv.yaml", out / "stereo.yaml"], f"--out {out}", args.overwrite,
                     "a calibration is")
    left, right = _images(args.left, "LEFT_DIR"), _images(args.right, "RIGHT_DIR")
    _check_pair_numbers(left, right, Path(args.left), Path(args.right))
    if len(left) != len(right):
        raise InputError(f"{args.left} has {len(left)} images, {args.right} has {len(right)}: expected pairs "
                         f"(matched by sorted name)")
    lc, rc = ViewCollector(args, board), ViewCollector(args, board)
    pairs = []
    for k, (a, b) in enumerate(zip(left, right), 1):
        tag = f"[{k}/{len(left)}] "
        va = lc.offer(_grey(a), a.name, tag)
        vb = rc.offer(_grey(b), b.name, tag)
        if va is not None and vb is not None:
            pairs.append((va, vb))
    if lc.size != rc.size:
        raise InputError(f"left images are {lc.size}, right images {rc.size}: a stereo pair has one size")
    _say(args, f"calibrating: {len(lc.views)} left, {len(rc.views)} right views, {len(pairs)} pairs ...")
    lres, rres = _calibrate(lc.views, lc.size), _calibrate(rc.views, rc.size)
    try:
        st = calibrate_stereo(pairs, lres, rres)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    files = {**_intrinsics_files(out, "left_", lres, lc.views, board, "left"),
             **_intrinsics_files(out, "right_", rres, rc.views, board, "right")}
    fs = cv2.FileStorage(".yaml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fs.write("image_width", lc.size[0])
    fs.write("image_height", lc.size[1])
    for key, val in (("K1", lres.K), ("D1", lres.dist.reshape(1, -1)), ("K2", rres.K),
                     ("D2", rres.dist.reshape(1, -1)), ("R", st.R), ("T", st.T.reshape(3, 1))):
        fs.write(key, np.asarray(val, float))
    fs.write("rms_reprojection_error", st.rms)
    fs.write("baseline", st.baseline)
    files[out / "stereo_opencv.yaml"] = fs.releaseAndGetString()
    r = st.rectified
    files[out / "stereo.yaml"] = (
        f"# the rectified pair of {out / 'stereo_opencv.yaml'} (vbnav stereo format, docs/obstacles.md)\n"
        f"# stereoCalibrate RMS {st.rms:.4f} px over {len(pairs)} pairs; baseline in --square units\n"
        f"width: {lc.size[0]}\nheight: {lc.size[1]}\nfx: {r['fx']:.6f}\nfy: {r['fy']:.6f}\n"
        f"cx: {r['cx']:.6f}\ncy: {r['cy']:.6f}\nbaseline: {r['baseline']:.6f}\n")
    out.mkdir(parents=True, exist_ok=True)
    files = write_atomic_set(files, check=_loads_back)     # one calibration: all replaced, or none
    _report("left", lres)
    _report("right", rres)
    print(f"stereo: RMS {st.rms:.4f} px over {len(pairs)} pairs; baseline {st.baseline:.5f} (T "
          f"{' '.join(f'{t:.4f}' for t in st.T)}), rotation {math.degrees(np.linalg.norm(cv2.Rodrigues(st.R)[0])):.3f}"
          f" deg; rectified fx {r['fx']:.3f}, baseline {r['baseline']:.5f}")
    print(f"wrote {', '.join(map(str, files))}")
    return 0


def run_mount(args) -> int:
    from vbnav.control.config import load_config, resolve_config_path
    from vbnav.control.config.mount_edit import set_camera_mount
    if args.config is None and not args.dry_run:
        # It edits the file in place: without -c that was the shipped example configs/sim.yaml of the checkout.
        raise InputError("calibrate mount writes camera.mount into the configuration file in place: give "
                         "-c CONFIG (the robot's own file; there is no default to write into), or --dry-run")
    if args.stereo and (given := _given(args, (*BOARD_FIELDS, "min_sharpness", "board_thickness"))):
        raise InputError(f"{', '.join(given)}: board options, and --stereo uses no board (it fits the floor "
                         f"plane of the pair); leave them out")
    cfg = load_config(args.config)
    camera = cfg.camera.to_model()
    if args.stereo:
        pose = _mount_from_stereo(args, cfg)
        height = pose.height        # the floor itself, no board on it
        how = "stereo ground plane"
    else:
        board = _board(args)        # its options checked before a camera opens
        if args.image:
            grey = _grey(Path(args.image))
            name = args.image
        else:
            _, cam = _open_live_camera(args)
            try:
                frame = cam.read(2.0)
            finally:
                cam.disconnect()
            if frame is None:
                raise InputError(f"{cfg.source}: the camera gave no frame in 2 s")
            grey = frame.image if frame.image.ndim == 2 else cv2.cvtColor(frame.image, cv2.COLOR_BGR2GRAY)
            name = f"{cfg.camera.driver} camera frame"
        if (grey.shape[1], grey.shape[0]) != (camera.width, camera.height):
            raise InputError(f"{name}: is {grey.shape[1]}x{grey.shape[0]}, the camera of {cfg.source} is "
                             f"{camera.width}x{camera.height}")
        from vbnav.vision.board_calibration import BoardDetector, floor_pose_from_board
        view = BoardDetector(board).detect(grey, name)
        if view is None:
            raise InputError(f"{name}: the board ({board.kind} {board.cols}x{board.rows}) is not in view")
        if view.sharpness < (limit := _min_sharpness(args)):     # blurred corners: a biased pose, as in intrinsics
            raise InputError(f"{name}: the board is blurred (sharpness {view.sharpness:.1f} < {limit:g}, "
                             f"--min-sharpness); take a sharper view")
        pose = floor_pose_from_board(view, camera.K, np.asarray(camera.dist, float))
        height = pose.height + (args.board_thickness or 0.0)        # the plane measured is the board's top
        how = f"board on the floor ({len(view.ids)} corners, RMS {pose.rms:.3f} px)"
    values = {"height": height, "pitch_deg": math.degrees(pose.pitch), "roll_deg": math.degrees(pose.roll)}
    print(f"camera mount from the {how}: height {height:.4f} m, pitch {values['pitch_deg']:.3f} deg (down), "
          f"roll {values['roll_deg']:.3f} deg")
    path = resolve_config_path(args.config)
    set_camera_mount(path, values, write=not args.dry_run)     # a dry run is checked as the real edit is
    if args.dry_run:
        print(f"{path}: --dry-run: camera.mount not written (the edit would be valid)")
        return 0
    print(f"{path}: camera.mount height, pitch_deg, roll_deg written (the rest of the file unchanged)")
    return 0


def _mount_from_stereo(args, cfg):
    from vbnav.vision.board_calibration import floor_pose_from_down
    from vbnav.vision.camera_model import PinholeCamera
    from vbnav.vision.ground_plane import fit_ground_plane
    from vbnav.vision.stereo import StereoRig, sgbm_disparity, sgbm_params_for
    baseline = cfg.camera.stereo_baseline() or cfg.obstacles.baseline
    if not baseline:
        raise InputError(f"{cfg.source}: --stereo needs a stereo baseline (a stereo camera.calibration_file, or "
                         f"camera.options.stereo_baseline)")
    c = cfg.camera
    rig = StereoRig(PinholeCamera(c.width, c.height, c.fx, c.fy, c.cx, c.cy), float(baseline))
    left, right = (_grey(Path(f)) for f in args.stereo)
    for f, img in zip(args.stereo, (left, right)):
        if (img.shape[1], img.shape[0]) != (c.width, c.height):
            raise InputError(f"{f}: is {img.shape[1]}x{img.shape[0]}, the camera of {cfg.source} is "
                             f"{c.width}x{c.height}")
    # No prior from the configured mount: it is what is being measured (and may be far off). The fit then
    # takes the lower image half as the floor's candidates; the matching covers depths down to half the
    # configured height, nearer than any floor point of a camera not looking straight down.
    disp = sgbm_disparity(left, right, sgbm_params_for(rig, 0.5 * c.mount.height))
    try:
        fit = fit_ground_plane(disp, rig, None)
    except ValueError as exc:
        raise InputError(f"{args.stereo[0]}: no floor plane found ({exc}); point the camera at an empty stretch "
                         f"of floor") from None
    return floor_pose_from_down(np.asarray(fit.floor.down), fit.floor.height)
