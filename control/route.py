"""The taught route on disk: a directory with a versioned manifest and one image + landmark file per keyframe.

Layout::

    route/
      manifest.json        {"format": "vbnav-route", "version": 1, "robot": ..., "created": ...,
                            "camera": {...}, "mount": {...}, "complete": bool, "keyframes": [...]}
      kf_00000.png         the keyframe image
      kf_00000.npz         landmarks: pixels, alpha, beta, descriptors, inv_height, inv_height_var,
                           track_ids, odom (x, z, theta), distance, stamp_ns

Crash safety: every file is written to a temporary name in the same directory,
fsynced, then renamed over its final name (atomic on POSIX), and the manifest
is rewritten the same way after each keyframe's files are in place. The
manifest therefore only ever lists complete keyframes; an interruption leaves
at worst a stray ``.tmp`` file, which loading ignores.
"""
from __future__ import annotations

import datetime as _dt
import io
import json
import math
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from vbnav.drivers.errors import InputError
from vbnav.vision.camera_model import FisheyeCamera, PinholeCamera
from vbnav.vision.geometry import CameraMount, Pose2

FORMAT = "vbnav-route"
VERSION = 1
MANIFEST = "manifest.json"
_TMP = ".tmp"

#: npz arrays of a keyframe: name -> (dtype kind, trailing shape); N is the landmark count.
_LANDMARK_FIELDS = {
    "pixels": ("f", (2,)), "alpha": ("f", ()), "beta": ("f", ()), "descriptors": ("u", (32,)),
    "inv_height": ("f", ()), "inv_height_var": ("f", ()), "track_ids": ("i", ()),
}


class RouteError(InputError):
    """A route directory is missing, corrupt, foreign or from a newer version. The message says which file."""


@dataclass
class Keyframe:
    """One taught view: its image, landmarks (levelled bearings, descriptors, inverse heights) and odometry."""

    index: int
    image: np.ndarray
    pixels: np.ndarray           # (N, 2) float32
    alpha: np.ndarray            # (N,) levelled azimuth, rad
    beta: np.ndarray             # (N,) levelled elevation, rad
    descriptors: np.ndarray      # (N, 32) uint8 ORB
    inv_height: np.ndarray       # (N,) 1/y, 1/m (NaN = unknown)
    inv_height_var: np.ndarray   # (N,) variance of inv_height
    track_ids: np.ndarray        # (N,) int64 teach-time track ids (shared between keyframes)
    odom: Pose2                  # odometry pose of the robot at this keyframe
    distance: float              # m travelled along the route at this keyframe
    stamp_ns: int = 0

    def __len__(self) -> int:
        return len(self.alpha)


@dataclass
class Route:
    path: Path
    robot: str
    created: str
    camera: object
    mount: CameraMount
    complete: bool
    keyframes: list[Keyframe] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.keyframes)

    @property
    def length(self) -> float:
        return self.keyframes[-1].distance if self.keyframes else 0.0


def camera_to_dict(cam) -> dict:
    model = "fisheye" if isinstance(cam, FisheyeCamera) else "pinhole"
    return {"model": model, "width": int(cam.width), "height": int(cam.height), "fx": float(cam.fx),
            "fy": float(cam.fy), "cx": float(cam.cx), "cy": float(cam.cy), "dist": [float(d) for d in cam.dist]}


def camera_from_dict(d: dict, where: str):
    try:
        cls = FisheyeCamera if d["model"] == "fisheye" else PinholeCamera
        if d["model"] not in ("pinhole", "fisheye"):
            raise ValueError(f"model {d['model']!r}")
        return cls(int(d["width"]), int(d["height"]), float(d["fx"]), float(d["fy"]), float(d["cx"]),
                   float(d["cy"]), tuple(float(x) for x in d.get("dist", [])))
    except (KeyError, TypeError, ValueError) as e:
        raise RouteError(f"{where}: camera: expected model pinhole|fisheye, width, height, fx, fy, cx, cy, dist "
                         f"({e})") from None


def mount_to_dict(m: CameraMount) -> dict:
    return {"height": m.height, "forward": m.forward, "lateral": m.lateral, "pitch": m.pitch, "yaw": m.yaw}


def _write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` via a fsynced temporary file and an atomic rename."""
    tmp = path.with_name(path.name + _TMP)
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def _fsync_dir(d: Path) -> None:
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class RouteWriter:
    """Appends keyframes to a new route directory, keeping it loadable after every keyframe.

    ``RouteWriter(path, robot, camera, mount)`` creates ``path`` (it must not exist or be
    empty unless ``overwrite``); ``append(kf)`` writes one keyframe; ``close()`` marks the
    route complete. Usable as a context manager (an exception leaves ``complete: false``).
    """

    def __init__(self, path, robot: str, camera, mount: CameraMount, overwrite: bool = False):
        self.path = Path(path)
        if self.path.exists():
            if not self.path.is_dir():
                raise RouteError(f"{self.path}: exists and is not a directory")
            if any(self.path.iterdir()) and not overwrite:
                raise RouteError(f"{self.path}: directory is not empty (choose a new route path)")
            if overwrite:
                for p in self.path.iterdir():
                    if p.is_file() and (p.name == MANIFEST or p.name.startswith("kf_")):
                        p.unlink()
        self.path.mkdir(parents=True, exist_ok=True)
        self._manifest = {
            "format": FORMAT, "version": VERSION, "robot": robot,
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "camera": camera_to_dict(camera), "mount": mount_to_dict(mount),
            "complete": False, "keyframes": [],
        }
        self._write_manifest()

    def __len__(self) -> int:
        return len(self._manifest["keyframes"])

    def append(self, kf: Keyframe) -> None:
        i = len(self)
        stem = f"kf_{i:05d}"
        ok, png = cv2.imencode(".png", kf.image)
        if not ok:
            raise RouteError(f"{self.path / (stem + '.png')}: could not encode the keyframe image")
        _write_atomic(self.path / f"{stem}.png", png.tobytes())
        buf = io.BytesIO()
        np.savez(buf, pixels=np.asarray(kf.pixels, np.float32), alpha=np.asarray(kf.alpha, np.float64),
                 beta=np.asarray(kf.beta, np.float64), descriptors=np.asarray(kf.descriptors, np.uint8),
                 inv_height=np.asarray(kf.inv_height, np.float64),
                 inv_height_var=np.asarray(kf.inv_height_var, np.float64),
                 track_ids=np.asarray(kf.track_ids, np.int64), odom=kf.odom.as_array(),
                 distance=np.float64(kf.distance), stamp_ns=np.int64(kf.stamp_ns))
        _write_atomic(self.path / f"{stem}.npz", buf.getvalue())
        self._manifest["keyframes"].append({
            "index": i, "image": f"{stem}.png", "landmarks": f"{stem}.npz", "n_landmarks": len(kf.alpha),
            "distance": float(kf.distance), "odom": [float(v) for v in kf.odom.as_array()],
        })
        self._write_manifest()

    def close(self, complete: bool = True) -> None:
        self._manifest["complete"] = bool(complete)
        self._write_manifest()

    def _write_manifest(self) -> None:
        _write_atomic(self.path / MANIFEST, json.dumps(self._manifest, indent=1).encode())

    def __enter__(self) -> "RouteWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(complete=exc_type is None)


def load_route(path, load_images: bool = True) -> Route:
    """Load and validate a route directory; raises RouteError naming the file and what was expected."""
    root = Path(path)
    if not root.is_dir():
        raise RouteError(f"{root}: route directory does not exist")
    mpath = root / MANIFEST
    if not mpath.is_file():
        raise RouteError(f"{mpath}: missing (not a vbnav route directory?)")
    try:
        m = json.loads(mpath.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise RouteError(f"{mpath}: not valid JSON ({e})") from None
    if not isinstance(m, dict) or m.get("format") != FORMAT:
        got = m.get("format") if isinstance(m, dict) else type(m).__name__
        raise RouteError(f"{mpath}: format is {got!r}, expected {FORMAT!r} (a foreign directory?)")
    ver = m.get("version")
    if not isinstance(ver, int) or isinstance(ver, bool):
        raise RouteError(f"{mpath}: version must be an integer, got {ver!r}")
    if ver > VERSION:
        raise RouteError(f"{mpath}: version {ver} is newer than this vbnav reads (<= {VERSION}); upgrade vbnav")
    for key in ("robot", "created", "camera", "mount", "keyframes"):
        if key not in m:
            raise RouteError(f"{mpath}: missing key {key!r}")
    camera = camera_from_dict(m["camera"], str(mpath))
    try:
        mount = CameraMount(**{k: float(m["mount"][k]) for k in ("height", "forward", "lateral", "pitch", "yaw")})
    except (KeyError, TypeError, ValueError) as e:
        raise RouteError(f"{mpath}: mount: expected height, forward, lateral, pitch, yaw numbers ({e})") from None
    if not isinstance(m["keyframes"], list):
        raise RouteError(f"{mpath}: keyframes must be a list")
    kfs = [_load_keyframe(root, mpath, i, entry, load_images) for i, entry in enumerate(m["keyframes"])]
    return Route(root, str(m["robot"]), str(m["created"]), camera, mount, bool(m.get("complete", False)), kfs)


def _load_keyframe(root: Path, mpath: Path, i: int, entry, load_images: bool) -> Keyframe:
    where = f"{mpath}: keyframes[{i}]"
    if not isinstance(entry, dict) or not {"image", "landmarks"} <= set(entry):
        raise RouteError(f"{where}: expected an object with 'image' and 'landmarks' file names")
    img_path, lm_path = root / str(entry["image"]), root / str(entry["landmarks"])
    for p in (img_path, lm_path):
        if p.parent.resolve() != root.resolve():
            raise RouteError(f"{where}: file {p.name!r} must be inside the route directory")
        if not p.is_file():
            raise RouteError(f"{p}: missing keyframe file (listed in {mpath.name} keyframes[{i}])")
    image = None
    if load_images:
        image = cv2.imread(str(img_path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise RouteError(f"{img_path}: not a readable PNG image")
    try:
        with np.load(lm_path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as e:
        raise RouteError(f"{lm_path}: corrupt or truncated landmark file, expected a numpy .npz ({e})") from None
    n = _check_landmarks(lm_path, data)
    if "n_landmarks" in entry and int(entry["n_landmarks"]) != n:
        raise RouteError(f"{lm_path}: has {n} landmarks, manifest says {entry['n_landmarks']}")
    odom = np.asarray(data["odom"], float).ravel()
    return Keyframe(i, image, data["pixels"], data["alpha"], data["beta"], data["descriptors"], data["inv_height"],
                    data["inv_height_var"], data["track_ids"], Pose2(*odom[:3]), float(data["distance"]),
                    int(data["stamp_ns"]))


def _check_landmarks(path: Path, data: dict) -> int:
    for k in list(_LANDMARK_FIELDS) + ["odom", "distance", "stamp_ns"]:
        if k not in data:
            raise RouteError(f"{path}: missing array {k!r}")
    n = len(data["alpha"])
    for k, (kind, trailing) in _LANDMARK_FIELDS.items():
        a = data[k]
        if a.shape != (n,) + trailing or a.dtype.kind != kind:
            raise RouteError(f"{path}: array {k!r} has shape {a.shape} dtype {a.dtype}, "
                             f"expected shape {(n,) + trailing} of kind {kind!r}")
    if data["odom"].shape != (3,) or not np.all(np.isfinite(data["odom"])):
        raise RouteError(f"{path}: 'odom' must be 3 finite numbers (x, z, theta)")
    if not math.isfinite(float(data["distance"])):
        raise RouteError(f"{path}: 'distance' must be finite")
    return n


def stray_temp_files(path) -> list[Path]:
    """Temporary files an interrupted writer left behind (harmless; loading ignores them)."""
    return sorted(Path(path).glob("*" + _TMP))
