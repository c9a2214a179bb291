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
at worst a stray ``.tmp`` file, which loading ignores. A route that replaces
another (``overwrite``) is written beside it and swapped in only when complete.
"""
from __future__ import annotations

import ctypes
import datetime as _dt
import errno
import io
import json
import math
import os
import re
import shutil
import zipfile
from typing import Optional
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from vbnav.drivers.atomic_file import fsync_folder, replace_durably, write_atomic
from vbnav.drivers.errors import InputError
from vbnav.drivers.plain_values import load_json
from vbnav.vision.camera_model import FisheyeCamera, PinholeCamera, check_distortion
from vbnav.vision.geometry import CameraMount, Pose2
from vbnav.vision.vbc import inverse_range, known_range

FORMAT = "vbnav-route"
VERSION = 1
MANIFEST = "manifest.json"
_TMP = ".tmp"

#: npz arrays of a keyframe: name -> (dtype kind, or the exact dtype, trailing shape); N is the landmark count.
#: ORB descriptors must be uint8: the matcher refuses another type (an OpenCV assertion mid-repeat).
_LANDMARK_FIELDS = {
    "pixels": ("f", (2,)), "alpha": ("f", ()), "beta": ("f", ()), "descriptors": ("uint8", (32,)),
    "inv_height": ("f", ()), "inv_height_var": ("f", ()), "track_ids": ("i", ()),
}


class RouteError(InputError):
    """A route directory is missing, corrupt, foreign or from a newer version. The message says which file."""


# -- routes by name (cmd/mode: network input) -------------------------------------------------
#: A route name: one path component of letters, digits, ``_ . -``, not starting with a dot
#: (so never ``.``, ``..`` or a hidden or temporary directory of a writer).
ROUTE_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9_.-]{0,127}")
NAME_RULE = "a plain name of letters, digits, '_', '.' and '-' (at most 128, not starting with '.')"


def check_route_name(name) -> str:
    """``name`` if it is a plain route name, else RouteError. The message does not repeat the name:
    a name with slashes is a path, and errors about network input never echo paths."""
    if not isinstance(name, str) or not ROUTE_NAME.fullmatch(name):    # match(): "$" also matches before a "\n"
        raise RouteError(f"route must be {NAME_RULE}, not a path")
    return name


def routes_root(routes_dir, config_source=None) -> Path:
    """The routes directory of a configuration: ``~`` expanded, a relative path taken from the config
    file's folder (or the working directory for a configuration not read from a file)."""
    p = Path(routes_dir).expanduser()
    if not p.is_absolute():
        p = (Path(config_source).parent if config_source else Path.cwd()) / p
    return p


def resolve_route(root, name: str, must_exist: bool) -> Path:
    """The directory of route ``name`` inside the routes directory ``root``; RouteError otherwise.

    The name must pass ``check_route_name``; the path is resolved (symlinks followed) and must still
    be a direct child of ``root``, so a symlink planted in ``root`` cannot lead outside it. Errors
    name only the route, never ``root`` or where a link points.
    """
    check_route_name(name)
    base = Path(root).resolve()
    path = (base / name).resolve()
    if path.parent != base or path.name != name:
        raise RouteError(f"route {name!r}: is a symbolic link; routes are directories inside the routes directory")
    if must_exist and not path.is_dir():
        raise RouteError(f"route {name!r}: no such route in the routes directory")
    return path


def describe_route_error(exc: Exception, route_path: Path, name: str) -> str:
    """An error of loading or writing route ``name`` with its directory shown as ``route 'name'``."""
    text = str(exc) if isinstance(exc, RouteError) else f"{type(exc).__name__}: {exc.strerror if isinstance(exc, OSError) and exc.strerror else exc}"
    return text.replace(f"{route_path}{os.sep}", f"route {name!r}: ").replace(str(route_path), f"route {name!r}")


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
    calibration: Optional[dict] = None   # the calibration it was taught with (file, sha256, intrinsics)

    def __len__(self) -> int:
        return len(self.keyframes)

    @property
    def length(self) -> float:
        return self.keyframes[-1].distance if self.keyframes else 0.0

    def repeat_refusal(self) -> Optional[str]:
        """Why a repeat of this route is refused whatever the configuration (None: it is not), said alike
        by ``vbnav repeat``, ``mode repeat``, the repeat stage and controller, and ``vbnav route check``."""
        if not self.keyframes:
            return "the route has no keyframes (a repeat steers from one keyframe to the next): teach it again"
        return None

    def incomplete_note(self) -> str:
        """'' for a complete route; else what exists of it (teaching was interrupted before the end)."""
        if self.complete:
            return ""
        return (f"the route is incomplete (complete: false, teaching was interrupted): {len(self)} keyframes "
                f"over {self.length:.2f} m exist; a repeat ends at the last of them")


def camera_to_dict(cam) -> dict:
    model = "fisheye" if isinstance(cam, FisheyeCamera) else "pinhole"
    return {"model": model, "width": int(cam.width), "height": int(cam.height), "fx": float(cam.fx),
            "fy": float(cam.fy), "cx": float(cam.cx), "cy": float(cam.cy), "dist": [float(d) for d in cam.dist]}


def camera_from_dict(d: dict, where: str):
    try:
        cls = FisheyeCamera if d["model"] == "fisheye" else PinholeCamera
        if d["model"] not in ("pinhole", "fisheye"):
            raise ValueError(f"model {d['model']!r}")
        w, h = int(d["width"]), int(d["height"])
        fx, fy, cx, cy = (float(d[k]) for k in ("fx", "fy", "cx", "cy"))
        dist = tuple(float(x) for x in d.get("dist", []))
    except (KeyError, TypeError, ValueError) as e:
        raise RouteError(f"{where}: camera: expected model pinhole|fisheye, width, height, fx, fy, cx, cy, dist "
                         f"({e})") from None
    # A NaN or negative focal length passed every later check (NaN compares false) and bent every bearing.
    if w <= 0 or h <= 0 or not all(math.isfinite(v) for v in (fx, fy, cx, cy)) or fx <= 0 or fy <= 0:
        raise RouteError(f"{where}: camera: expected width, height > 0, fx, fy > 0 and finite cx, cy; got "
                         f"{w}x{h} fx {fx} fy {fy} cx {cx} cy {cy}")
    try:
        dist = check_distortion(d["model"], dist)
    except ValueError as e:
        raise RouteError(f"{where}: camera: dist: {e}") from None
    return cls(w, h, fx, fy, cx, cy, dist)


def mount_to_dict(m: CameraMount) -> dict:
    return {"height": m.height, "forward": m.forward, "lateral": m.lateral, "pitch": m.pitch, "yaw": m.yaw,
            "roll": m.roll}


# Intrinsics of the camera a route was taught with and of the camera repeating it that differ by more than
# this share of the focal length (px) are two different calibrations: recalibrating one camera moves fx, cx
# by well under 1 %, a different lens or resolution by far more. Keyframe pixels are turned into bearings
# with the repeating camera's model, so a different calibration bends every bearing.
INTRINSICS_AGREEMENT = 0.02


def check_route_camera(route: "Route", camera, config_source: str = "the configuration",
                       calibration_file: Optional[str] = None) -> None:
    """Raise RouteError unless ``camera`` (the configured camera model) is the one ``route`` was taught
    with: the same lens model, the same image size and intrinsics within INTRINSICS_AGREEMENT."""
    taught = camera_to_dict(route.camera)
    now = camera_to_dict(camera)
    tf = (route.calibration or {}).get("file")
    cf = calibration_file

    def describe(d, f):
        return (f"{d['model']} {d['width']}x{d['height']} fx {d['fx']:.1f} fy {d['fy']:.1f} cx {d['cx']:.1f} "
                f"cy {d['cy']:.1f} distortion {d['dist'] if any(d['dist']) else 'none'}"
                + (f" from {f}" if f else ""))
    problem = None
    if taught["model"] != now["model"]:
        problem = "another lens model"
    elif (taught["width"], taught["height"]) != (now["width"], now["height"]):
        problem = "another image size"
    elif any(abs(taught[k] - now[k]) > INTRINSICS_AGREEMENT * taught["fx"] for k in ("fx", "fy", "cx", "cy")):
        problem = f"other intrinsics (beyond {INTRINSICS_AGREEMENT:.0%} of fx)"
    elif _distortion_bend(route.camera, camera) > INTRINSICS_AGREEMENT:
        problem = (f"another lens distortion (it turns a pixel at the image border into a ray more than "
                   f"{INTRINSICS_AGREEMENT:.2f} rad from the taught one)")
    if problem:
        raise RouteError(f"{route.path}: taught with camera {describe(taught, tf)}; {config_source} has "
                         f"{problem}: {describe(now, cf)}. Repeat with the configuration the route was taught "
                         f"with, or teach the route again")


# A camera mount that moved since teaching moves every fix (docs/teach_repeat.md, "The camera's mount"): the
# fix places the camera where the taught camera was, so a forward or lateral change of d shifts the robot by d,
# and a height change of dh shifts a landmark seen at elevation beta by dh / tan(beta) in range. MOUNT_FIX_BUDGET_M
# is what a mount change may add to the repeat's error: the settled lateral RMS bar (1.8 cm, README) less the
# worst measured (0.75 cm), rounded down.
MOUNT_FIX_BUDGET_M = 0.01
# What a mount is measured to: a tape measure reads a height or an offset to 1 mm, an inclinometer (or
# ``vbnav calibrate mount``) an angle to 0.1 deg. The route's mount was measured so too, so a configured value
# closer to it than this is the same mount measured again, not a change: no tolerance is below it, though on a
# route of near-horizon or far landmarks that moves a fix by more than the budget (a tape measure cannot hold
# such a route to it, at teaching either).
MOUNT_MEASURE_M = 0.001
MOUNT_MEASURE_RAD = math.radians(0.1)


@dataclass(frozen=True)
class MountTolerances:
    """How far camera.mount may differ from a route's mount (``mount_tolerances``)."""

    height: float       # m
    offset: float       # m, forward and lateral
    angle: float        # rad, pitch, yaw and roll
    range: float        # m, the median in-plane range of the route's landmarks of known height (inf: none)


def mount_tolerances(route: "Route") -> MountTolerances:
    """The changes of the camera mount that move a fix by MOUNT_FIX_BUDGET_M on ``route``, never below what a
    mount is measured to (MOUNT_MEASURE_M, MOUNT_MEASURE_RAD):

    - height: the budget x the median |tan(elevation)| of its landmarks;
    - forward, lateral: the budget;
    - pitch, yaw, roll: a turn by a moves every landmark's image point by fx a px, and the budget moves the
      image point of a landmark at range r by fx budget / r px: a = budget / the median range of the route's
      landmarks of known height."""
    betas = np.concatenate([np.abs(np.asarray(kf.beta, float)) for kf in route.keyframes] or [np.zeros(0)])
    betas = betas[np.isfinite(betas)]
    slope = float(np.median(np.tan(np.minimum(betas, math.radians(80))))) if len(betas) else 1.0
    rho = np.concatenate([np.abs(inverse_range(kf.beta, kf.inv_height))[known_range(kf.beta, kf.inv_height,
                                                                                    kf.inv_height_var)]
                          for kf in route.keyframes] or [np.zeros(0)])
    rho = rho[np.isfinite(rho) & (rho > 0)]
    reach = float(1.0 / np.median(rho)) if len(rho) else math.inf
    return MountTolerances(max(MOUNT_FIX_BUDGET_M * slope, MOUNT_MEASURE_M), MOUNT_FIX_BUDGET_M,
                           max(MOUNT_FIX_BUDGET_M / reach, MOUNT_MEASURE_RAD), reach)


def check_route_mount(route: "Route", mount: CameraMount, config_source: str = "the configuration") -> None:
    """Raise RouteError when ``mount`` (camera.mount) puts or turns the camera otherwise than ``route`` was taught
    with by more than ``mount_tolerances``: every fix would be biased by more than MOUNT_FIX_BUDGET_M."""
    taught = route.mount
    tol = mount_tolerances(route)
    then, now = mount_to_dict(taught), mount_to_dict(mount)
    moved = {k: abs(now[k] - then[k]) for k in ("height", "forward", "lateral")}
    turned = {k: abs(math.remainder(now[k] - then[k], math.tau)) for k in ("pitch", "yaw", "roll")}
    limit = {"height": tol.height, "forward": tol.offset, "lateral": tol.offset}
    what = [f"{k} {1e3 * d:.1f} mm off, beyond {1e3 * limit[k]:.1f} mm" for k, d in moved.items() if d > limit[k]]
    what += [f"{k} {math.degrees(d):.2f} deg off, beyond {math.degrees(tol.angle):.2f} deg"
             for k, d in turned.items() if d > tol.angle]
    if not what:
        return

    def describe(m):
        return (f"height {m.height:.3f} m, forward {m.forward:.3f} m, lateral {m.lateral:.3f} m, pitch "
                f"{math.degrees(m.pitch):.2f} deg, yaw {math.degrees(m.yaw):.2f} deg, roll {math.degrees(m.roll):.2f} deg")
    why = f"the change that moves a fix by {100 * MOUNT_FIX_BUDGET_M:g} cm"
    if any(d > tol.angle for d in turned.values()):
        fx = float(route.camera.fx)
        why += (f"; a turn that moves the image points as far as {100 * MOUNT_FIX_BUDGET_M:g} cm does at the "
                f"landmarks' median range {tol.range:.1f} m, {fx * tol.angle:.1f} px at fx {fx:g}")
    raise RouteError(f"{route.path}: taught with the camera mounted at {describe(taught)}; {config_source} has "
                     f"camera.mount {describe(mount)} ({'; '.join(what)}: {why}; never below what a mount is "
                     f"measured to, {1e3 * MOUNT_MEASURE_M:g} mm and {math.degrees(MOUNT_MEASURE_RAD):g} deg, "
                     f"docs/teach_repeat.md). Mount the camera as it was taught and configure that, or teach "
                     f"the route again")


def check_route_config(route: "Route", cfg) -> None:
    """Raise RouteError unless the configuration ``cfg`` (control.config.Config) repeats ``route`` with the camera
    and mount it was taught with (``check_route_camera``, ``check_route_mount``): what a repeat refuses, said alike
    by ``vbnav repeat`` and ``vbnav route check -c``."""
    source = cfg.source or "the configuration"
    cal = cfg.camera.calibration
    check_route_camera(route, cfg.camera.to_model(), source, cal.file if cal else None)
    check_route_mount(route, cfg.camera.mount.to_mount(), source)


def config_repeat_refusal(route: "Route", cfg) -> Optional[str]:
    """Why a repeat of ``route`` with the configuration ``cfg`` is refused (``Route.repeat_refusal``, then
    ``check_route_config``), without the route's path; None when it is not."""
    why = route.repeat_refusal()
    if why:
        return why
    try:
        check_route_config(route, cfg)
    except RouteError as exc:
        return str(exc).removeprefix(f"{route.path}: ")
    return None


def _distortion_bend(taught, camera) -> float:
    """The largest angle (rad) between the rays the two distortions give the same pixel of the image border
    (corners and edge midpoints), with the taught intrinsics for both: what the distortion alone changes."""
    w, h = taught.width - 1, taught.height - 1
    px = np.array([(u, v) for u in (0, w / 2, w) for v in (0, h / 2, h)], float)
    same_k = type(taught)(taught.width, taught.height, taught.fx, taught.fy, taught.cx, taught.cy, camera.dist)
    cos = np.clip(np.sum(taught.rays(px) * same_k.rays(px), axis=1), -1.0, 1.0)
    bend = np.arccos(cos)
    return float(np.max(bend)) if np.all(np.isfinite(bend)) else math.inf


# -- replacing a route ---------------------------------------------------------------------------
_PARTIAL, _OLD = ".partial-", ".old-"
#: A route's files, and the temporary files of an interrupted write_atomic of one (``.NAME.<random>.tmp``).
_ROUTE_FILE = re.compile(r"^(manifest\.json|kf_\d{5}\.(png|npz))(\.tmp)?$|"
                         r"^\.(manifest\.json|kf_\d{5}\.(png|npz))\.\w+\.tmp$")
_RENAME_EXCHANGE = 2        # renameat2(2) flag: swap two paths atomically (Linux >= 3.15)


def _sibling(route: Path, kind: str) -> Path:
    return route.with_name(f".{route.name}{kind}{os.getpid()}")


def _free_sibling(route: Path, kind: str) -> Path:
    """``_sibling``, or ``.1``, ``.2``... after it where one exists: left by an earlier process that had our
    pid (a service after a reboot), it holds recorded keyframes and is kept."""
    base = path = _sibling(route, kind)
    n = 1
    while path.exists():
        path, n = base.with_name(f"{base.name}.{n}"), n + 1
    return path


def _swap_in(new: Path, route: Path) -> None:
    """Put the complete directory ``new`` at ``route`` and delete the route it replaces.

    One atomic exchange where the OS has it, so ``route`` is a complete route at every instant;
    else two renames with the old route at ``.NAME.old-<pid>`` in between (a crash in that gap
    leaves both beside the path; ``stray_route_dirs`` and ``load_route`` point at them).
    """
    old = _free_sibling(route, _OLD)
    if _exchange(new, route):
        os.rename(new, old)          # ``new`` now holds the old route
    else:
        os.rename(route, old)
        os.rename(new, route)
    fsync_folder(route.parent)
    shutil.rmtree(old)


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths in one step (renameat2 RENAME_EXCHANGE); False where the OS cannot."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    at_cwd = -100
    if fn(at_cwd, os.fsencode(a), at_cwd, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP):
        return False                 # this kernel or file system cannot exchange
    raise OSError(err, os.strerror(err), str(b))


def staging_dir(route, tag: str = "") -> Path:
    """Where a copy of ``route`` is written before it is put in place: the hidden sibling
    ``.NAME.partial-<pid>-<tag>`` (``stray_route_dirs`` points at it if the writer dies; the tag keeps it
    apart from a RouteWriter's and from other copies in the same process)."""
    return Path(route).with_name(f".{Path(route).name}{_PARTIAL}{os.getpid()}-{tag}")


def install_route_dir(new, route, overwrite: bool) -> None:
    """Put the complete route directory ``new`` (a sibling, same file system) at ``route``.

    A missing ``route`` is a rename; an existing one is replaced only with ``overwrite`` and only if it
    holds nothing but route files, in one atomic swap (``_swap_in``). RouteError otherwise.
    """
    new, route = Path(new), Path(route)
    fsync_folder(new)           # its entries (files written into it without write_atomic: a pull, a push)
    if not route.exists():
        replace_durably(new, route)
        return
    if not overwrite:
        raise RouteError(f"{route}: exists (replace it with --overwrite)")
    if not route.is_dir():
        raise RouteError(f"{route}: exists and is not a directory")
    foreign = sorted(p.name for p in route.iterdir() if not _ROUTE_FILE.fullmatch(p.name))
    if foreign:
        raise RouteError(f"{route}: holds {foreign[0]!r}, which is not a route file; not replacing a directory "
                         f"that is not a vbnav route")
    _swap_in(new, route)


def stray_route_dirs(route) -> list[Path]:
    """Directories an interrupted replacement of ``route`` left beside it: ``.NAME.partial-<pid>`` (a new
    route that was never completed: the old one is intact) or ``.NAME.old-<pid>`` (the old route, when a
    crash hit between the two renames of a swap). Nothing deletes them: they hold recorded keyframes."""
    route = Path(route)
    if not route.parent.is_dir():
        return []
    return sorted(p for p in route.parent.iterdir()
                  if p.name.startswith(f".{route.name}{_PARTIAL}") or p.name.startswith(f".{route.name}{_OLD}"))


class RouteWriter:
    """Appends keyframes to a new route directory, keeping it loadable after every keyframe.

    ``RouteWriter(path, robot, camera, mount)`` creates ``path`` (it must not exist or be
    empty unless ``overwrite``); ``append(kf)`` writes one keyframe; ``close()`` marks the
    route complete. Usable as a context manager (an exception leaves ``complete: false``).

    Replacing a route (``overwrite`` of a non-empty ``path``) never touches the old one before the
    new one is complete: keyframes go to the sibling ``.NAME.partial-<pid>``, and only
    ``close(complete=True)`` swaps it into place (``_swap_in``). Killed before that, the old route
    is intact and the partial one stays beside it (``stray_route_dirs``). Only a directory holding
    nothing but route files is replaced: ``--overwrite`` of a wrong directory must not delete it.
    """

    def __init__(self, path, robot: str, camera, mount: CameraMount, overwrite: bool = False,
                 calibration: Optional[dict] = None):
        self.path = Path(path)          # where the route is (once complete)
        self._dir = self.path           # where its files are written now
        if self.path.exists():
            if not self.path.is_dir():
                raise RouteError(f"{self.path}: exists and is not a directory")
            names = [p.name for p in self.path.iterdir()]
            if names and not overwrite:
                raise RouteError(f"{self.path}: directory is not empty (choose a new route path)")
            foreign = sorted(n for n in names if not _ROUTE_FILE.fullmatch(n))
            if foreign:
                raise RouteError(f"{self.path}: holds {foreign[0]!r}, which is not a route file; not replacing "
                                 f"a directory that is not a vbnav route")
            if names:
                self._dir = _free_sibling(self.path, _PARTIAL)
        self._dir.mkdir(parents=True, exist_ok=True)
        self._camera = camera
        self._last: Optional[Keyframe] = None     # the keyframe appended last (its index, odometry, distance)
        self._manifest = {
            "format": FORMAT, "version": VERSION, "robot": robot,
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "camera": camera_to_dict(camera), "mount": mount_to_dict(mount),
            "calibration": calibration, "complete": False, "keyframes": [],
        }
        self._write_manifest()

    def __len__(self) -> int:
        return len(self._manifest["keyframes"])

    def append(self, kf: Keyframe) -> None:
        i = len(self)
        stem = f"kf_{i:05d}"
        ok, png = cv2.imencode(".png", kf.image)
        if not ok:
            raise RouteError(f"{self._dir / (stem + '.png')}: could not encode the keyframe image")
        arrays = dict(pixels=np.asarray(kf.pixels, np.float32), alpha=np.asarray(kf.alpha, np.float64),
                      beta=np.asarray(kf.beta, np.float64), descriptors=np.asarray(kf.descriptors, np.uint8),
                      inv_height=np.asarray(kf.inv_height, np.float64),
                      inv_height_var=np.asarray(kf.inv_height_var, np.float64),
                      track_ids=np.asarray(kf.track_ids, np.int64), odom=np.asarray(kf.odom.as_array(), np.float64),
                      distance=np.float64(kf.distance), stamp_ns=np.int64(kf.stamp_ns))
        # What load_route would refuse is refused here: written, it would make the whole route unloadable.
        _check_landmarks(self._dir / f"{stem}.npz", arrays, f"keyframes[{i}]")
        _check_pixels(self._dir / f"{stem}.npz", f"keyframes[{i}]", arrays["pixels"], self._camera)
        if self._last is not None:
            _check_step(self._dir / MANIFEST, self._last, _step(i, kf))
        write_atomic(self._dir / f"{stem}.png", png.tobytes())
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        write_atomic(self._dir / f"{stem}.npz", buf.getvalue())
        self._last = _step(i, kf)
        self._manifest["keyframes"].append({
            "index": i, "image": f"{stem}.png", "landmarks": f"{stem}.npz", "n_landmarks": len(kf.alpha),
            "distance": float(kf.distance), "odom": [float(v) for v in kf.odom.as_array()],
        })
        self._write_manifest()

    @property
    def directory(self) -> Path:
        """Where the route's files are: its path, or (a replacement not yet complete) the sibling beside it."""
        return self._dir

    def close(self, complete: bool = True) -> None:
        """Mark the route complete (or not); a complete replacement takes the old route's place."""
        self._manifest["complete"] = bool(complete)
        self._write_manifest()
        if complete and self._dir != self.path:
            _swap_in(self._dir, self.path)
            self._dir = self.path

    def _write_manifest(self) -> None:
        write_atomic(self._dir / MANIFEST, json.dumps(self._manifest, indent=1).encode())

    def __enter__(self) -> "RouteWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(complete=exc_type is None)


def load_route(path, load_images: bool = True) -> Route:
    """Load and validate a route directory; raises RouteError naming the file and what was expected."""
    root = Path(path)
    if root.exists() and not root.is_dir():
        raise RouteError(f"{root}: is a file, expected a route directory")
    if not root.is_dir():
        left = stray_route_dirs(root)
        hint = f" (an interrupted replacement left {', '.join(p.name for p in left)} beside it)" if left else ""
        raise RouteError(f"{root}: route directory does not exist{hint}")
    mpath = root / MANIFEST
    if not mpath.is_file():
        raise RouteError(f"{mpath}: missing (not a vbnav route directory?)")
    try:
        m = load_json(mpath.read_text())
    except ValueError as e:         # not JSON, not UTF-8, a key given twice
        raise RouteError(f"{mpath}: not valid JSON ({e})") from None
    except RecursionError:
        raise RouteError(f"{mpath}: not a route manifest (JSON nested too deeply)") from None
    if not isinstance(m, dict) or m.get("format") != FORMAT:
        got = m.get("format") if isinstance(m, dict) else type(m).__name__
        raise RouteError(f"{mpath}: format is {got!r}, expected {FORMAT!r} (a foreign directory?)")
    ver = m.get("version")
    if not isinstance(ver, int) or isinstance(ver, bool):
        raise RouteError(f"{mpath}: version must be an integer, got {ver!r}")
    if ver > VERSION:
        raise RouteError(f"{mpath}: version {ver} is newer than this vbnav reads (<= {VERSION}); upgrade vbnav")
    if ver < 1:
        raise RouteError(f"{mpath}: version {ver} is not a route version (versions start at 1)")
    for key in ("robot", "created", "camera", "mount", "keyframes"):
        if key not in m:
            raise RouteError(f"{mpath}: missing key {key!r}")
    camera = camera_from_dict(m["camera"], str(mpath))
    try:
        mount = CameraMount(**{k: float(m["mount"][k]) for k in ("height", "forward", "lateral", "pitch", "yaw")},
                            roll=float(m["mount"].get("roll", 0.0)))
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise RouteError(f"{mpath}: mount: expected height, forward, lateral, pitch, yaw numbers ({e})") from None
    if not all(math.isfinite(v) for v in mount_to_dict(mount).values()):
        raise RouteError(f"{mpath}: mount: expected finite numbers, got {mount_to_dict(mount)}")
    if not isinstance(m.get("complete", False), bool):
        raise RouteError(f"{mpath}: complete: expected true or false, got {m['complete']!r}")
    calibration = m.get("calibration")
    if calibration is not None and not isinstance(calibration, dict):
        raise RouteError(f"{mpath}: calibration: expected an object (file, sha256, fx, ...) or null")
    if not isinstance(m["keyframes"], list):
        raise RouteError(f"{mpath}: keyframes must be a list")
    kfs = [_load_keyframe(root, mpath, i, entry, camera, load_images) for i, entry in enumerate(m["keyframes"])]
    _check_progress(mpath, kfs)
    return Route(root, str(m["robot"]), str(m["created"]), camera, mount, bool(m.get("complete", False)), kfs,
                 calibration)


def _load_keyframe(root: Path, mpath: Path, i: int, entry, camera, load_images: bool) -> Keyframe:
    where = f"{mpath}: keyframes[{i}]"
    if not isinstance(entry, dict) or not {"image", "landmarks"} <= set(entry):
        raise RouteError(f"{where}: expected an object with 'image' and 'landmarks' file names")
    img_path, lm_path = root / str(entry["image"]), root / str(entry["landmarks"])
    if "index" in entry and (not isinstance(entry["index"], int) or entry["index"] != i):
        raise RouteError(f"{where}: index {entry['index']!r}, expected {i} (its position in the list)")
    if img_path.stem != lm_path.stem:       # written as kf_NNNNN.png + kf_NNNNN.npz
        raise RouteError(f"{where}: image {img_path.name!r} and landmarks {lm_path.name!r} are not the files of "
                         f"one keyframe (expected the same name, .png and .npz)")
    for p in (img_path, lm_path):
        try:
            inside = p.resolve().parent == root.resolve()   # resolved: a symlinked keyframe file must not lead out
        except (RuntimeError, OSError):                     # a symbolic link loop
            raise RouteError(f"{p}: a symbolic link loop, expected a keyframe file (listed in {mpath.name} "
                             f"keyframes[{i}])") from None
        if not inside:
            raise RouteError(f"{where}: file {p.name!r} must be inside the route directory")
        if not p.is_file():
            raise RouteError(f"{p}: missing keyframe file (listed in {mpath.name} keyframes[{i}])")
    image = None
    size, depth, colour = _png_header(img_path)
    if load_images:
        image = cv2.imread(str(img_path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise RouteError(f"{img_path}: not a readable PNG image")
        size = (image.shape[1], image.shape[0])
    if depth != 8 or colour not in _PNG_COLOURS:
        raise RouteError(f"{img_path}: keyframes[{i}] image is {depth}-bit with "
                         f"{_PNG_COLOURS.get(colour, f'PNG colour type {colour}')}, expected an 8-bit grey or "
                         f"colour image (the repeat's tracker reads no other)")
    if size != (camera.width, camera.height):
        raise RouteError(f"{img_path}: keyframes[{i}] image is {size[0]}x{size[1]}, the route's camera is "
                         f"{camera.width}x{camera.height}")
    try:
        with np.load(lm_path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as e:
        raise RouteError(f"{lm_path}: corrupt or truncated landmark file, expected a numpy .npz ({e})") from None
    n = _check_landmarks(lm_path, data, f"keyframes[{i}]")
    _check_pixels(lm_path, f"keyframes[{i}]", data["pixels"], camera)
    if "n_landmarks" in entry and (not isinstance(entry["n_landmarks"], int) or entry["n_landmarks"] != n):
        raise RouteError(f"{lm_path}: has {n} landmarks, manifest keyframes[{i}].n_landmarks says "
                         f"{entry['n_landmarks']!r}")
    odom = np.asarray(data["odom"], float).ravel()
    return Keyframe(i, image, data["pixels"], data["alpha"], data["beta"], data["descriptors"], data["inv_height"],
                    data["inv_height_var"], data["track_ids"], Pose2(*odom[:3]), float(data["distance"]),
                    int(data["stamp_ns"]))


#: PNG colour types of a keyframe image (what cv2.imencode writes for 8-bit grey and BGR images).
_PNG_COLOURS = {0: "1 channel (grey)", 2: "3 channels (colour)"}


def _png_header(path: Path) -> tuple[tuple[int, int], int, int]:
    """((width, height), bit depth, colour type) from a PNG's header, without decoding the image."""
    with open(path, "rb") as f:
        head = f.read(26)
    if len(head) < 26 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        raise RouteError(f"{path}: not a readable PNG image")
    return (int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")), head[24], head[25]


def _check_landmarks(path: Path, data: dict, which: str) -> int:
    for k in list(_LANDMARK_FIELDS) + ["odom", "distance", "stamp_ns"]:
        if k not in data:
            raise RouteError(f"{path}: missing array {k!r}")
    if data["alpha"].ndim != 1:
        raise RouteError(f"{path}: array 'alpha' has shape {data['alpha'].shape}, expected one value per landmark")
    n = len(data["alpha"])
    for k, kind in (("odom", "f"), ("distance", "f"), ("stamp_ns", "i")):
        a = data[k]
        if a.dtype.kind not in ("iu" if kind == "i" else "fiu") or (k != "odom" and a.shape != ()):
            raise RouteError(f"{path}: {k!r} has shape {a.shape} dtype {a.dtype}, expected "
                             + ("3 numbers (x, z, theta)" if k == "odom" else
                                "one integer (ns)" if kind == "i" else "one number"))
    for k, (kind, trailing) in _LANDMARK_FIELDS.items():
        a = data[k]
        if a.shape != (n,) + trailing or (a.dtype.kind != kind if len(kind) == 1 else a.dtype != np.dtype(kind)):
            raise RouteError(f"{path}: array {k!r} has shape {a.shape} dtype {a.dtype}, "
                             f"expected shape {(n,) + trailing} of " + (f"kind {kind!r}" if len(kind) == 1
                                                                         else f"dtype {kind}"))
    if data["odom"].shape != (3,) or not np.all(np.isfinite(data["odom"])):
        raise RouteError(f"{path}: 'odom' must be 3 finite numbers (x, z, theta)")
    if not math.isfinite(float(data["distance"])):
        raise RouteError(f"{path}: 'distance' must be finite")
    if n == 0:      # teach writes a keyframe only from a frame with vbc.min_keyframe_landmarks tracks
        raise RouteError(f"{path}: {which} has no landmarks, expected those of the frame it was taught from (a "
                         f"repeat takes its fixes from them): the file is damaged; teach the route again")
    for k in ("pixels", "alpha", "beta"):
        bad = ~np.isfinite(data[k]).reshape(n, -1).all(axis=1)
        if bad.any():
            raise RouteError(f"{path}: {which}: landmark {int(np.argmax(bad))} has a non-finite {k!r} "
                             f"({int(bad.sum())} of {n} landmarks)")
    # An unknown inverse height is NaN with an infinite variance; anything else must be a number.
    if np.isinf(data["inv_height"]).any() or np.isnan(data["inv_height_var"]).any() or \
            (data["inv_height_var"] < 0).any():
        raise RouteError(f"{path}: {which}: inverse heights must be finite or NaN (unknown), their variances "
                         f">= 0 or inf")
    return n


def _check_pixels(path: Path, which: str, px: np.ndarray, camera) -> None:
    """Where each landmark was seen in the keyframe image: inside it (give or take a pixel at its edge)."""
    out = (px[:, 0] < -1) | (px[:, 1] < -1) | (px[:, 0] > camera.width) | (px[:, 1] > camera.height)
    if out.any():
        k = int(np.argmax(out))
        raise RouteError(f"{path}: {which}: landmark {k}'s pixel ({float(px[k, 0]):.1f}, {float(px[k, 1]):.1f}) "
                         f"is outside the {camera.width}x{camera.height} image ({int(out.sum())} of {len(px)} "
                         f"landmarks)")


def _check_progress(mpath: Path, kfs: list) -> None:
    """Keyframes follow the route: along-route distance increases; at the same distance only a turn on
    the spot (another heading) makes a new keyframe. A copy of the keyframe before is an error."""
    for a, b in zip(kfs, kfs[1:]):
        _check_step(mpath, a, b)


def _step(i: int, kf: Keyframe) -> Keyframe:
    """What ``_check_step`` compares of keyframe ``kf`` written as number ``i`` (no image, no landmarks)."""
    return Keyframe(i, None, *(None,) * 7, odom=kf.odom, distance=float(kf.distance))


def is_step(distance_before: float, theta_before: float, distance: float, theta: float) -> bool:
    """Whether a keyframe at ``distance``/``theta`` is a step along the route after one at the values
    before: further along, or turned on the spot. The route refuses any other (teach keeps to it too)."""
    return distance > distance_before or (distance == distance_before and theta != theta_before)


def _check_step(mpath: Path, a: Keyframe, b: Keyframe) -> None:
    if not is_step(a.distance, a.odom.theta, b.distance, b.odom.theta):
        what = "repeats" if b.distance == a.distance else "is less than"
        raise RouteError(f"{mpath}: keyframes[{b.index}]: along-route distance {b.distance:.3f} m {what} "
                         f"keyframes[{a.index}]'s {a.distance:.3f} m (distance must increase along the route)")
    # Teach adds up the odometry it drives into the distance: a keyframe is never farther from the one before
    # than the distance grew (a chord is no longer than its arc), up to rounding. The repeat drives to the
    # keyframes' odometry poses, so one that says otherwise would take it elsewhere.
    chord, arc = math.hypot(b.odom.x - a.odom.x, b.odom.z - a.odom.z), b.distance - a.distance
    if chord > arc + 1e-9 * max(1.0, abs(b.distance)):
        raise RouteError(f"{mpath}: keyframes[{b.index}]: odometry {chord:.3f} m from keyframes[{a.index}]'s, "
                         f"beyond the {arc:.3f} m of along-route distance between them (teach drove that distance "
                         f"between them: its odometry or distance is damaged, or from another route)")


def stray_temp_files(path) -> list[Path]:
    """Temporary files an interrupted writer left behind (harmless; loading ignores them)."""
    return sorted(Path(path).glob("*" + _TMP))
