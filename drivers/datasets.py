"""Readers for recorded image sequences: KITTI odometry and TUM RGB-D layouts.

KITTI odometry layout (a folder):
    image_l/*.png            left images (``image_0/`` is accepted too), sorted by name
    image_r/*.png            optional right images (``image_1/``), the same names (a pair is one name); the
                             first pair's matched features must mostly have a positive disparity (left
                             minus right): folders swapped are refused
    calib.txt                P0 and P1 3x4 projection matrices, one per line
                             (with or without the ``P0:`` labels; read by
                             ``stereo_calib.read_kitti_calib``)
    poses.txt                optional: one 3x4 row-major camera-to-world matrix per frame
    times.txt                optional: one time in seconds per frame; 10 Hz otherwise

TUM RGB-D layout (a folder):
    rgb.txt                  ``timestamp path`` per line, ``#`` comments (a path with spaces is read whole;
                             any other third column is refused)
    depth.txt                optional, same format (16-bit PNG, or .npz with key ``data``)
    groundtruth.txt          optional: ``timestamp tx ty tz qx qy qz qw`` camera-to-world
    camera.yaml              intrinsics (or a file given explicitly), see ``load_camera_yaml``

Every problem is a ``DatasetError`` naming the file and what was expected.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import yaml

from vbnav.drivers.calibration import CalibrationError, check_baseline, check_intrinsics
from vbnav.drivers.errors import InputError, yaml_problem
from vbnav.drivers.plain_values import load_yaml
from vbnav.drivers.stereo_calib import read_kitti_calib
from vbnav.vision.camera_model import FisheyeCamera, PinholeCamera, check_distortion
from vbnav.vision.geometry import matrix_from_quat
from vbnav.vision.stereo import PAIR_ORDER_MIN_MATCHES, pair_disparity_signs

KITTI_RATE_HZ = 10.0
#: A TUM colour frame's depth image is the nearest in depth.txt within this many seconds (else it has none).
DEPTH_MAX_DT_S = 0.02


class DatasetError(InputError):
    """A dataset folder or file is missing or malformed."""


@dataclass
class Dataset:
    """One recorded sequence, loaded lazily frame by frame."""

    root: Path
    layout: str  # "kitti" or "tum"
    camera: PinholeCamera | FisheyeCamera
    stamps: np.ndarray  # seconds, one per frame
    left: list[Path]
    right: Optional[list[Path]] = None
    stereo_baseline: Optional[float] = None  # metres, right camera at +baseline along x
    depth: Optional[list[Optional[Path]]] = None
    depth_scale: float = 0.001  # metres per depth unit
    gt_stamps: Optional[np.ndarray] = None
    gt_poses: Optional[np.ndarray] = None  # (M, 4, 4) camera-to-world
    extras: dict = field(default_factory=dict)  # e.g. the tag_grid block of camera.yaml

    def __len__(self) -> int:
        return len(self.left)

    def every(self, n: int) -> "Dataset":
        """Every ``n``-th frame (0, n, 2n, ...): the same footage with ``n`` times the motion between frames
        (a faster robot, a slower camera, dropped frames). Ground truth is looked up by stamp as before."""
        if int(n) != n or n < 1:
            raise ValueError(f"every: the frame step must be a whole number >= 1, got {n}")
        n = int(n)
        return replace(self, stamps=self.stamps[::n], left=self.left[::n],
                       right=None if self.right is None else self.right[::n],
                       depth=None if self.depth is None else self.depth[::n])

    def image(self, i: int, grey: bool = True) -> np.ndarray:
        return self._sized(_read_image(self.left[i], grey), self.left[i])

    def right_image(self, i: int) -> Optional[np.ndarray]:
        return None if self.right is None else self._sized(_read_image(self.right[i], True), self.right[i])

    def _sized(self, img: np.ndarray, path: Path) -> np.ndarray:
        """The image, if it has the camera's size: the calibration holds for that size only."""
        h, w = img.shape[:2]
        if (w, h) != (self.camera.width, self.camera.height):
            raise DatasetError(f"{path}: the image is {w}x{h}, the camera (and the sequence's first image) is "
                               f"{self.camera.width}x{self.camera.height}")
        return img

    def depth_image(self, i: int) -> Optional[np.ndarray]:
        """Depth in metres (float32, 0 where unknown), or None."""
        if self.depth is None or self.depth[i] is None:
            return None
        p = self.depth[i]
        if p.suffix == ".npz":
            try:
                raw = np.load(p)["data"]
            except Exception as exc:
                raise DatasetError(f"{p}: cannot read depth npz (expected key 'data'): {exc}") from exc
        else:
            raw = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            if raw is None:
                raise DatasetError(f"{p}: cannot read depth image")
        if raw.ndim != 2 or raw.dtype.itemsize < 2:   # an 8-bit export would read as depths of a few cm
            raise DatasetError(f"{p}: the depth image is {raw.dtype.itemsize * 8}-bit with "
                               f"{1 if raw.ndim == 2 else raw.shape[2]} channel(s), expected one channel of "
                               f"16-bit depth units ({self.depth_scale:g} m each)")
        h, w = raw.shape
        if (w, h) != (self.camera.width, self.camera.height):   # depth is looked up at the colour pixels
            raise DatasetError(f"{p}: the depth image is {w}x{h}, expected the colour images' "
                               f"{self.camera.width}x{self.camera.height} (depth registered to colour)")
        return raw.astype(np.float32) * float(self.depth_scale)

    def ground_truth_at(self, stamps: np.ndarray, max_dt: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
        """Ground-truth poses nearest to each stamp (within max_dt s): (mask, poses)."""
        if self.gt_poses is None:
            return np.zeros(len(stamps), bool), np.zeros((0, 4, 4))
        idx = np.clip(np.searchsorted(self.gt_stamps, stamps), 1, len(self.gt_stamps) - 1)
        left = self.gt_stamps[idx - 1]
        right = self.gt_stamps[idx]
        idx = np.where(np.abs(stamps - left) <= np.abs(right - stamps), idx - 1, idx)
        if len(self.gt_stamps) == 1:
            idx = np.zeros(len(stamps), int)
        ok = np.abs(self.gt_stamps[idx] - stamps) <= max_dt
        return ok, self.gt_poses[idx]


def _read_image(path: Path, grey: bool) -> np.ndarray:
    try:
        data = Path(path).read_bytes()
    except OSError:
        data = b""
    if jpeg_cut_short(data):
        raise DatasetError(f"{path}: {JPEG_CUT_SHORT}")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE if grey else cv2.IMREAD_COLOR) \
        if data else None
    if img is None:
        raise DatasetError(f"{path}: missing or not a readable image")
    return img


JPEG_CUT_SHORT = "the JPEG is cut short (no end-of-image marker after its last scan): a truncated copy"


def jpeg_cut_short(data: bytes) -> bool:
    """A JPEG file that ends before its end-of-image marker: OpenCV decodes it with a warning and grey where the
    data ended. The marker follows the last scan (an EXIF thumbnail's own marker comes before it; scan data
    cannot hold the marker's bytes); bytes after it are allowed."""
    if not data.startswith(b"\xff\xd8"):
        return False
    return data.find(b"\xff\xd9", data.rfind(b"\xff\xda")) < 0


def _text(path: Path, what: str) -> str:
    """The text of a dataset's text file; DatasetError naming it if it cannot be read or is not UTF-8."""
    try:
        return path.read_text(encoding="utf-8")
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read {what}: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{path}: not UTF-8 text (byte {exc.start}: {exc.reason}), expected {what} as plain "
                           f"text (saved as UTF-16?)") from None


def _numbers(path: Path, per_line: int, what: str) -> tuple[np.ndarray, list[int]]:
    """The numbers of each line (comments and blank lines skipped) and the line numbers they are on."""
    rows, lines = [], []
    text = _text(path, what)
    for k, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            vals = [float(v) for v in line.split()]
        except ValueError:
            raise DatasetError(f"{path}:{k}: expected {per_line} numbers ({what}), got {line[:60]!r}") from None
        if len(vals) != per_line:
            raise DatasetError(f"{path}:{k}: expected {per_line} numbers ({what}), got {len(vals)}")
        if not all(np.isfinite(vals)):       # float() takes 'nan' and 'inf'; a pose or time cannot be either
            raise DatasetError(f"{path}:{k}: expected finite numbers ({what}), got {line[:60]!r}")
        rows.append(vals)
        lines.append(k)
    if not rows:
        raise DatasetError(f"{path}: empty, expected {what}")
    return np.array(rows), lines


def _check_increasing(path: Path, stamps: np.ndarray, lines: list[int]) -> None:
    """Frame times must increase: the replay camera plays them in order and the velocities divide by them.
    ``lines``: the line of each time in ``path``, for the error."""
    bad = np.flatnonzero(np.diff(stamps) <= 0)
    if len(bad):
        k = int(bad[0])
        raise DatasetError(f"{path}:{lines[k + 1]}: {stamps[k + 1]:g} s is not after line {lines[k]}'s "
                           f"{stamps[k]:g} s: expected increasing times")


def detect_layout(root: Path, fallback: Optional[str] = None) -> str:
    """'tum' or 'kitti' by the files that make them; else ``fallback`` if given (the replay camera's plain
    folder of images), else an error naming the folder."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: is a file, expected a dataset folder" if root.exists()
                           else f"{root}: dataset folder does not exist")
    if (root / "rgb.txt").is_file():
        return "tum"
    if (root / "calib.txt").is_file() or (root / "image_l").is_dir() or (root / "image_0").is_dir():
        return "kitti"
    if fallback is not None:
        return fallback
    raise DatasetError(f"{root}: neither a KITTI odometry folder (image_l/ + calib.txt) "
                       f"nor a TUM RGB-D folder (rgb.txt)")


def open_dataset(root: str | Path, camera_yaml: str | Path | None = None, layout: str = "auto") -> Dataset:
    root = Path(root)
    layout = detect_layout(root) if layout == "auto" else layout
    if layout == "kitti":
        return open_kitti(root, camera_yaml)
    if layout == "tum":
        return open_tum(root, camera_yaml)
    raise DatasetError(f"unknown dataset layout {layout!r} (expected kitti, tum or auto)")


def _image_dir(root: Path, names: tuple[str, ...]) -> Optional[Path]:
    for n in names:
        if (root / n).is_dir():
            return root / n
    return None


def _images_in(d: Path) -> list[Path]:
    return sorted(p for p in d.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".pgm", ".bmp"))


def _refuse_unused_keys(yaml_path, extras: dict, depth: bool, right: bool, root: Path) -> None:
    """A camera YAML's depth_scale without depth images, or its baseline without right images, would be accepted
    and never read: DatasetError naming the file, the key and what the folder lacks."""
    if "depth_scale" in extras and not depth:
        raise DatasetError(f"{yaml_path}: depth_scale: {root} has no depth images (a KITTI folder has none; a TUM "
                           f"folder lists them in depth.txt, and it has no depth.txt): remove depth_scale")
    if "baseline" in extras and not right:
        raise DatasetError(f"{yaml_path}: baseline: {root} has no right images (a KITTI folder's image_r/ or "
                           f"image_1/; a TUM folder has none): remove baseline, or add the right images")


def _check_numbered(folder: Path, images: list[Path]) -> None:
    """KITTI images are numbered frames (000000.png, ...), paired with times.txt and poses.txt by position: a
    frame left out would give every later image the time and pose of the frame before it. DatasetError names
    the first missing (or doubled) frame's file; images not named by numbers are taken in name order."""
    stems = [p.stem for p in images]
    if not all(s.isdigit() for s in stems):
        return
    for prev, p in zip(images, images[1:]):
        a, b = int(prev.stem), int(p.stem)
        if b == a:
            raise DatasetError(f"{p}: frame {a} again ({prev.name}); expected one image per frame number")
        if b != a + 1:
            name = f"{a + 1:0{len(prev.stem)}d}{prev.suffix}"
            raise DatasetError(f"{folder / name}: missing (expected the frames {stems[0]} to {stems[-1]} without "
                               f"a gap; {b - a - 1} missing before {p.name})")


def _check_pair_order(left: np.ndarray, right: np.ndarray, left_dir: Path, right_dir: Path, name: str) -> None:
    """The first pair's matched features must lie further right in the left image (positive disparity): a copy
    with the two folders swapped puts every point behind the camera. DatasetError naming both folders."""
    positive, negative = pair_disparity_signs(left, right)
    if positive + negative >= PAIR_ORDER_MIN_MATCHES and negative > positive:
        raise DatasetError(f"{left_dir} and {right_dir}: in the first pair ({name}) {negative} of "
                           f"{positive + negative} matched features have a negative disparity (left minus right): "
                           f"the left and right images are swapped (expected the left camera's in {left_dir.name}/)")


def open_kitti(root: Path, camera_yaml: str | Path | None = None) -> Dataset:
    left_dir = _image_dir(root, ("image_l", "image_0"))
    if left_dir is None:
        raise DatasetError(f"{root}: KITTI layout needs a folder image_l/ (or image_0/) of left images")
    left = _images_in(left_dir)
    if not left:
        raise DatasetError(f"{left_dir}: no images (.png/.jpg) found")
    right_dir = _image_dir(root, ("image_r", "image_1"))
    right = _images_in(right_dir) if right_dir is not None else None
    if right is not None and len(right) != len(left):
        raise DatasetError(f"{right_dir}: {len(right)} right images but {len(left)} left images in {left_dir}")
    if right is not None:   # a pair is two images of one name: by position, a frame missing on each side mispairs
        lonely = sorted({p.name for p in left} ^ {p.name for p in right})
        if lonely:
            has, lacks = (left_dir, right_dir) if (left_dir / lonely[0]) in left else (right_dir, left_dir)
            raise DatasetError(f"{lacks / lonely[0]}: missing, {has} has it (expected a left and a right image "
                               f"of each name; {len(lonely)} image(s) without their partner)")
    _check_numbered(left_dir, left)
    first = _read_image(left[0], True)
    if right is not None:
        _check_pair_order(first, _read_image(right[0], True), left_dir, right_dir, left[0].name)
    h, w = first.shape[:2]
    calib_path = root / "calib.txt"
    baseline = None
    if camera_yaml is not None:
        camera, extras = load_camera_yaml(camera_yaml)
    else:
        if not calib_path.is_file():
            raise DatasetError(f"{calib_path}: missing (KITTI layout needs P0 and P1 projection matrices)")
        try:
            calib = read_kitti_calib(calib_path, need_right=False)
        except CalibrationError as exc:
            raise DatasetError(str(exc)) from None
        camera, baseline, extras = calib.camera(w, h), calib.baseline, {}
    if camera_yaml is not None:
        _refuse_unused_keys(camera_yaml, extras, depth=False, right=right is not None, root=root)
    if right is not None and baseline is None:
        baseline = extras.get("baseline")
        if baseline is None:
            raise DatasetError(f"{calib_path}: image_r/ present but no P1 line (or 'baseline' in the camera YAML)")
    if (camera.width, camera.height) != (w, h):
        raise DatasetError(f"{left[0]}: the image is {w}x{h}, the camera YAML {camera_yaml} says "
                           f"{camera.width}x{camera.height}")
    times_path = root / "times.txt"
    if times_path.is_file():
        stamps, lines = _numbers(times_path, 1, "one time in seconds per line")
        stamps = stamps.ravel()
        if len(stamps) != len(left):
            raise DatasetError(f"{times_path}: {len(stamps)} times but {len(left)} images")
        _check_increasing(times_path, stamps, lines)
    else:
        stamps = np.arange(len(left)) / KITTI_RATE_HZ
    gt_stamps = gt_poses = None
    poses_path = root / "poses.txt"
    if poses_path.is_file():
        rows, _ = _numbers(poses_path, 12, "a row-major 3x4 camera-to-world matrix per line")
        if len(rows) != len(left):
            raise DatasetError(f"{poses_path}: {len(rows)} poses but {len(left)} images")
        gt_poses = np.tile(np.eye(4), (len(rows), 1, 1))
        gt_poses[:, :3, :] = rows.reshape(-1, 3, 4)
        gt_stamps = stamps.copy()
    return Dataset(root, "kitti", camera, stamps, left, right, baseline, gt_stamps=gt_stamps, gt_poses=gt_poses,
                   extras=extras)


def _tum_list(path: Path, what: str) -> tuple[np.ndarray, list[str], list[int]]:
    """Times, names and the line of each entry of a TUM list (comments and blank lines skipped)."""
    stamps, names, lines = [], [], []
    for k, line in enumerate(_text(path, f"'timestamp {what}' lines").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        try:
            stamps.append(float(parts[0]))
        except ValueError:
            raise DatasetError(f"{path}:{k}: expected 'timestamp {what}', got {line[:60]!r}") from None
        if not np.isfinite(stamps[-1]):
            raise DatasetError(f"{path}:{k}: expected a finite timestamp, got {line[:60]!r}")
        if len(parts) < 2:
            raise DatasetError(f"{path}:{k}: expected 'timestamp {what}', got {line[:60]!r}")
        name = line[len(parts[0]):].strip()
        if len(parts) > 2 and not (path.parent / name).is_file():   # a name with spaces is read whole if it is one
            raise DatasetError(f"{path}:{k}: expected 'timestamp filename', got {len(parts)} columns "
                               f"({line[:60]!r}), and {name!r} is not a file in {path.parent}")
        names.append(name)
        lines.append(k)
    if not stamps:
        raise DatasetError(f"{path}: no entries (expected 'timestamp {what}' lines)")
    return np.array(stamps), names, lines


def _listed(root: Path, names: list[str], list_path: Path) -> list[Path]:
    """The files a TUM list names (relative to ``root``); DatasetError naming the first one missing."""
    paths = [root / n for n in names]
    for p in paths:
        if not p.is_file():
            raise DatasetError(f"{p}: listed in {list_path} but missing")
    return paths


def open_tum(root: Path, camera_yaml: str | Path | None = None) -> Dataset:
    rgb_path = root / "rgb.txt"
    if not rgb_path.is_file():
        raise DatasetError(f"{rgb_path}: missing (TUM layout needs rgb.txt)")
    stamps, names, lines = _tum_list(rgb_path, "path/to/image.png")
    _check_increasing(rgb_path, stamps, lines)
    left = _listed(root, names, rgb_path)
    yaml_path = Path(camera_yaml) if camera_yaml is not None else root / "camera.yaml"
    if not yaml_path.is_file():
        raise DatasetError(f"{yaml_path}: missing (TUM layout needs intrinsics: pass --camera FILE "
                           f"or put camera.yaml in the folder)")
    camera, extras = load_camera_yaml(yaml_path)
    depth = None
    depth_path = root / "depth.txt"
    _refuse_unused_keys(yaml_path, extras, depth=depth_path.is_file(), right=False, root=root)
    if depth_path.is_file():
        d_stamps, d_names, _ = _tum_list(depth_path, "path/to/depth.png")
        d_paths = _listed(root, d_names, depth_path)
        depth = []
        for t in stamps:  # nearest depth image within DEPTH_MAX_DT_S of each colour image
            k = int(np.argmin(np.abs(d_stamps - t)))
            depth.append(d_paths[k] if abs(d_stamps[k] - t) <= DEPTH_MAX_DT_S else None)
    gt_stamps = gt_poses = None
    gt_path = root / "groundtruth.txt"
    if gt_path.is_file():
        rows, lines = _numbers(gt_path, 8, "timestamp tx ty tz qx qy qz qw")
        order = np.argsort(rows[:, 0], kind="stable")       # out of order is fine: sorted
        same = np.flatnonzero(np.diff(rows[order, 0]) == 0)
        for k in same:                                      # a line repeated is fine; two poses at one time not
            i, j = sorted((int(order[k]), int(order[k + 1])))
            if not np.array_equal(rows[i], rows[j]):
                raise DatasetError(f"{gt_path}: lines {lines[i]} and {lines[j]} are both at {rows[i, 0]:g} s with "
                                   f"different poses: expected one pose per time")
        rows = np.delete(rows[order], same + 1, axis=0)
        gt_stamps = rows[:, 0]
        gt_poses = np.tile(np.eye(4), (len(rows), 1, 1))
        for k, r in enumerate(rows):
            gt_poses[k, :3, :3] = matrix_from_quat(r[4:8])
            gt_poses[k, :3, 3] = r[1:4]
    return Dataset(root, "tum", camera, stamps, left, None, extras.get("baseline"), depth,
                   float(extras.get("depth_scale", 1.0 / 5000.0)), gt_stamps, gt_poses, extras)


def _number(v) -> float:
    """A YAML value as a float, NaN if it is not a number (so the range checks refuse it)."""
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


#: The keys of a dataset camera YAML (``load_camera_yaml``): intrinsics, then what the sequence needs.
CAMERA_YAML_KEYS = ("fx", "fy", "cx", "cy", "width", "height", "model", "dist", "depth_scale", "baseline", "tag_grid")


def load_camera_yaml(path: str | Path) -> tuple[PinholeCamera | FisheyeCamera, dict]:
    """Intrinsics YAML: fx, fy, cx, cy, width, height, optional model (pinhole|fisheye), dist,
    depth_scale (metres per depth unit), baseline (stereo, m), tag_grid (see vision/vslam_init.py).
    Returns the camera model and the remaining keys."""
    path = Path(path)
    try:
        data = load_yaml(_text(path, "a camera YAML"))
    except yaml.YAMLError as exc:
        raise DatasetError(f"{path}: {yaml_problem(exc)}") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a mapping with fx, fy, cx, cy, width, height")
    missing = [k for k in ("fx", "fy", "cx", "cy", "width", "height") if k not in data]
    if missing:
        raise DatasetError(f"{path}: missing key(s) {', '.join(missing)} (camera intrinsics)")
    unknown = [str(k) for k in data if k not in CAMERA_YAML_KEYS]
    if unknown:       # a misspelt depth_scale or baseline would be left out without a word
        raise DatasetError(f"{path}: {', '.join(unknown)}: unknown key(s) (check the spelling); a camera YAML takes "
                           f"{', '.join(CAMERA_YAML_KEYS)}")
    # YAML gives the types: int() would cut 32.5 to 32, float() read true as 1 and "16" as 16
    for k in ("width", "height"):
        if isinstance(data[k], bool) or not isinstance(data[k], int):
            raise DatasetError(f"{path}: {k}: expected a whole number of pixels, got {data[k]!r}")
    for k in ("fx", "fy", "cx", "cy"):
        if isinstance(data[k], (bool, str)):
            raise DatasetError(f"{path}: {k}: expected a number, got {data[k]!r}")
    try:
        args = dict(width=int(data["width"]), height=int(data["height"]), fx=float(data["fx"]),
                    fy=float(data["fy"]), cx=float(data["cx"]), cy=float(data["cy"]),
                    dist=tuple(float(v) for v in data.get("dist", []) or []))
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"{path}: intrinsics must be numbers: {exc}") from exc
    try:
        check_intrinsics(str(path), args["fx"], args["fy"], args["cx"], args["cy"], args["width"], args["height"])
        if args["width"] <= 0 or args["height"] <= 0:
            raise CalibrationError(f"{path}: width/height: expected positive sizes, got "
                                   f"{args['width']}x{args['height']}")
        if data.get("baseline") is not None:
            data["baseline"] = check_baseline(str(path), data["baseline"])
        if data.get("depth_scale") is not None and not _number(data["depth_scale"]) > 0:
            raise CalibrationError(f"{path}: depth_scale: expected metres per depth unit > 0, "
                                   f"got {data['depth_scale']!r}")
    except CalibrationError as exc:
        raise DatasetError(str(exc)) from None
    model = data.get("model", "pinhole")
    if model not in ("pinhole", "fisheye"):
        raise DatasetError(f"{path}: model must be 'pinhole' or 'fisheye', got {model!r}")
    try:
        args["dist"] = check_distortion(model, args["dist"])
    except ValueError as exc:
        raise DatasetError(f"{path}: dist: {exc}") from None
    if model == "pinhole":
        cam = PinholeCamera(**args)
    else:
        cam = FisheyeCamera(**{**args, "dist": args["dist"] or (0.0, 0.0, 0.0, 0.0)})
    extras = {k: v for k, v in data.items() if k not in ("fx", "fy", "cx", "cy", "width", "height", "dist", "model")}
    return cam, extras
