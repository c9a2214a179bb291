"""What ``vbnav route list|info|plot|check`` know about taught routes (format: control/route.py).

``summary`` reads only a manifest (fast, for listing a folder of routes);
``describe`` loads and validates the whole route without decoding images;
``plot`` draws the keyframes' odometry poses from above; ``check`` verifies
every byte that carries a checksum (each PNG chunk's CRC-32, each ``.npz``
member's CRC-32), decodes every image and landmark file, and compares the
manifest with the files (sizes, landmark counts, poses) and each image with its landmarks' ORB
descriptors (an image swapped with another keyframe's passes every checksum).
"""
from __future__ import annotations

import math
import os
import struct
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from vbnav.control.route import MANIFEST, RouteError, config_repeat_refusal, load_route, stray_route_dirs, stray_temp_files
from vbnav.drivers.atomic_file import atomic_output
from vbnav.drivers.plain_values import load_json
from vbnav.vision.features import describe as orb_descriptors

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_KF_FILE = ("kf_", (".png", ".npz"))


@dataclass
class RouteSummary:
    name: str
    path: Path
    keyframes: int = 0
    length_m: float = 0.0
    camera: str = ""
    complete: bool = False
    created: str = ""
    robot: str = ""
    error: str = ""             # why the manifest could not be read (then the rest is empty)


def summary(path) -> RouteSummary:
    """What the manifest says, without opening the keyframe files."""
    path = Path(path)
    s = RouteSummary(path.name, path)
    try:
        m = load_json((path / MANIFEST).read_text())
        kfs = m["keyframes"]
        cam = m["camera"]
        s.keyframes = len(kfs)
        s.length_m = float(kfs[-1]["distance"]) if kfs else 0.0
        s.camera = f"{cam['model']} {cam['width']}x{cam['height']} fx {float(cam['fx']):.0f}"
        s.complete = m.get("complete", False)
        if not isinstance(s.complete, bool):        # load_route refuses it: not listed as complete
            raise ValueError(f"complete: expected true or false, got {s.complete!r}")
        s.created, s.robot = str(m.get("created", "")), str(m.get("robot", ""))
    except FileNotFoundError:
        s.error = f"no {MANIFEST} (not a route)"
    except (OSError, ValueError, KeyError, TypeError, IndexError, RecursionError) as exc:
        s.error = f"{MANIFEST} unreadable ({type(exc).__name__}: {exc})"
    return s


def list_routes(folder) -> list[RouteSummary]:
    """Every sub-directory of ``folder`` that holds a manifest (hidden ones are a writer's scratch space)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise RouteError(f"{folder}: " + ("is a file, expected a folder of routes" if folder.exists()
                                         else "no such directory"))
    return [summary(p) for p in sorted(folder.iterdir())
            if p.is_dir() and not p.name.startswith(".") and (p / MANIFEST).exists()]


def describe(path) -> dict:
    """Everything ``vbnav route info`` prints, from a validated load (images not decoded)."""
    route = load_route(path, load_images=False)
    manifest = load_json((Path(path) / MANIFEST).read_text())
    n = np.array([len(k) for k in route.keyframes]) if route.keyframes else np.zeros(0, int)
    xz = np.array([(k.odom.x, k.odom.z) for k in route.keyframes]).reshape(-1, 2)
    cam = route.camera
    info = {
        "path": str(route.path), "robot": route.robot, "created": route.created, "complete": route.complete,
        "keyframes": len(route), "length_m": route.length,
        "camera": f"{type(cam).__name__.replace('Camera', '').lower()} {cam.width}x{cam.height}, fx {cam.fx:.1f} "
                  f"fy {cam.fy:.1f} cx {cam.cx:.1f} cy {cam.cy:.1f}, distortion {list(cam.dist) or 'none'}",
        "mount": f"height {route.mount.height:.3f} m, forward {route.mount.forward:.3f} m, pitch "
                 f"{math.degrees(route.mount.pitch):.1f} deg, yaw {math.degrees(route.mount.yaw):.1f} deg",
        "landmarks": (f"{int(n.min())} / {int(np.median(n))} / {int(n.max())} per keyframe (min / median / max)"
                      if len(n) else "none"),
        "extent": (f"x {xz[:, 0].min():.2f}..{xz[:, 0].max():.2f} m, z {xz[:, 1].min():.2f}..{xz[:, 1].max():.2f} m; "
                   f"end {math.hypot(*(xz[-1] - xz[0])):.2f} m from the start" if len(xz) else "none"),
        "note": route.incomplete_note(),
    }
    if "calibration" in manifest:
        info["calibration"] = manifest["calibration"]
    return info


def plot(path, out) -> Path:
    """A top view of the taught path: keyframe positions by odometry, their headings, start and end."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    route = load_route(path, load_images=False)
    out = Path(out)
    poses = np.array([(k.odom.x, k.odom.z, k.odom.theta) for k in route.keyframes]).reshape(-1, 3)
    fig, ax = plt.subplots(figsize=(8, 7), dpi=100)
    if len(poses):
        ax.plot(poses[:, 0], poses[:, 1], color="black", lw=1.5, label="taught path (odometry at keyframes)")
        ax.plot(poses[:, 0], poses[:, 1], "^", color="crimson", ms=5, label=f"keyframes ({len(poses)})")
        span = max(np.ptp(poses[:, 0]), np.ptp(poses[:, 1]), 0.5)
        # heading: theta turns right from +z (forward at the start) towards +x
        ax.quiver(poses[:, 0], poses[:, 1], np.sin(poses[:, 2]), np.cos(poses[:, 2]), angles="xy",
                  scale_units="xy", scale=25.0 / span, width=0.003, color="tab:blue", alpha=0.7)
        ax.plot(*poses[0, :2], "o", color="tab:green", ms=10, label="start")
        ax.plot(*poses[-1, :2], "s", color="tab:red", ms=9, label="end" + ("" if route.complete else " (incomplete)"))
        step = max(1, len(poses) // 12)
        for i in range(0, len(poses), step):
            ax.annotate(str(i), poses[i, :2], textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m, right of the start)")
    ax.set_ylabel("z (m, forward at the start)")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(f"{route.path.name}: {len(route)} keyframes, {route.length:.2f} m, "
                 f"{'complete' if route.complete else 'incomplete'}", fontsize=10)
    fig.tight_layout()
    try:
        with atomic_output(out, ".png") as tmp:
            fig.savefig(tmp, format="png")
    finally:
        plt.close(fig)
    return out


# -- check --------------------------------------------------------------------------------------------
@dataclass
class CheckReport:
    path: Path
    problems: list[str] = field(default_factory=list)    # damage: the route must not be trusted
    notes: list[str] = field(default_factory=list)       # harmless leftovers, incompleteness
    keyframes: int = 0
    complete: bool = False
    repeat_refusal: Optional[str] = None     # intact, but vbnav repeat refuses it (Route.repeat_refusal)

    @property
    def intact(self) -> bool:
        return not self.problems


def png_crc_problem(path: Path) -> Optional[str]:
    """The first PNG chunk whose CRC-32 does not match (or a truncated file), else None."""
    data = path.read_bytes()
    if not data.startswith(_PNG_SIGNATURE):
        return f"{path.name}: not a PNG file (bad signature)"
    pos = len(_PNG_SIGNATURE)
    while pos + 12 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        end = pos + 8 + length
        if end + 4 > len(data):
            return f"{path.name}: truncated in chunk {kind.decode(errors='replace')!r} at byte {pos}"
        (crc,) = struct.unpack(">I", data[end:end + 4])
        if zlib.crc32(data[pos + 4:end]) != crc:
            return f"{path.name}: CRC-32 mismatch in chunk {kind.decode(errors='replace')!r} at byte {pos}"
        if kind == b"IEND":
            return None
        pos = end + 4
    return f"{path.name}: truncated (no IEND chunk)"


def npz_crc_problem(path: Path) -> Optional[str]:
    try:
        with zipfile.ZipFile(path) as z:
            bad = z.testzip()
    except (zipfile.BadZipFile, OSError, EOFError) as exc:
        return f"{path.name}: not a readable .npz ({exc})"
    except zlib.error as exc:
        return f"{path.name}: compressed data corrupt ({exc})"
    return f"{path.name}: CRC-32 mismatch in member {bad!r}" if bad else None


def _same(compare) -> bool:
    """``compare()``; False when the manifest's value is not a number or of another shape (damage too)."""
    try:
        return bool(compare())
    except (TypeError, ValueError):
        return False


# An ORB descriptor is 256 bits; two of unrelated patches differ in about half of them (128), one recomputed
# from the same pixels by another OpenCV build in a few. A landmark whose recomputed descriptor is more than a
# quarter of its bits (64) from the stored one is not the same patch; an image is not the keyframe's when most of
# its landmarks are (a few may sit where a build's rounding moves the patch).
ORB_SAME_PATCH_BITS = 64


def image_problem(kf) -> Optional[str]:
    """Whether ``kf``'s image is the one its landmarks were taken from: teach stores the ORB descriptors of
    that image at the stored pixels (TeachStage._candidate, ``describe``), so recomputed they match (to the bit
    with the same OpenCV). An image swapped with another keyframe's, or edited, passes every checksum; this
    says how many landmarks no longer match."""
    n = len(kf.pixels)
    if n == 0:
        return None
    desc, idx = orb_descriptors(kf.image, kf.pixels)
    stored = np.asarray(kf.descriptors, np.uint8)
    bits = np.unpackbits(np.bitwise_xor(desc, stored[idx]), axis=1).sum(axis=1) if len(idx) else np.zeros(0)
    differ = n - len(idx) + int(np.count_nonzero(bits > ORB_SAME_PATCH_BITS))
    if 2 * differ <= n:
        return None
    return (f"the ORB descriptors at {differ} of its {n} landmarks' pixels differ from the stored ones by more "
            f"than {ORB_SAME_PATCH_BITS} of 256 bits: the image is not the one this keyframe was taught from "
            f"(swapped with another keyframe's, or edited)")


def check(path, cfg=None) -> CheckReport:
    """Verify checksums, decode everything, compare manifest and files, and each keyframe's image with its
    landmarks (``image_problem``). With a configuration ``cfg``, an intact route that a repeat with it would
    refuse (another camera or mount, ``check_route_config``) has that as its ``repeat_refusal``. RouteError only
    when ``path`` is not a route at all (no directory, no manifest)."""
    root = Path(path)
    if not root.is_dir():
        load_route(root)                       # raises the RouteError that says why (with stray siblings)
    if not (root / MANIFEST).is_file():
        raise RouteError(f"{root / MANIFEST}: missing (not a vbnav route directory?)")
    report = CheckReport(root)
    try:
        manifest = load_json((root / MANIFEST).read_text())
        listed = manifest["keyframes"]
    except (ValueError, KeyError, TypeError, RecursionError) as exc:
        report.problems.append(f"{MANIFEST}: unreadable ({exc})")
        return report
    files = set()
    for i, entry in enumerate(listed if isinstance(listed, list) else []):
        for key, crc in (("image", png_crc_problem), ("landmarks", npz_crc_problem)):
            name = entry.get(key) if isinstance(entry, dict) else None
            if not name or not (root / str(name)).is_file():
                continue                       # load_route below names the missing file
            files.add(str(name))
            problem = crc(root / str(name))
            if problem:
                report.problems.append(f"keyframes[{i}]: {problem}")
    if report.problems:
        return report
    try:
        route = load_route(root, load_images=True)
    except RouteError as exc:
        report.problems.append(str(exc).replace(f"{root}{os.sep}", ""))
        return report
    report.keyframes, report.complete = len(route), route.complete
    report.repeat_refusal = route.repeat_refusal() if cfg is None else config_repeat_refusal(route, cfg)
    for i, (entry, kf) in enumerate(zip(listed, route.keyframes)):
        odom = entry.get("odom")
        if odom is not None and not _same(lambda: np.allclose(np.asarray(odom, float), kf.odom.as_array(),
                                                              atol=1e-9)):
            report.problems.append(f"keyframes[{i}]: the manifest's odom {odom} differs from "
                                   f"{entry['landmarks']}'s {kf.odom.as_array().tolist()}")
        if "distance" in entry and not _same(lambda: math.isclose(float(entry["distance"]), kf.distance,
                                                                  abs_tol=1e-9)):
            report.problems.append(f"keyframes[{i}]: the manifest's distance {entry['distance']!r} differs from "
                                   f"{entry['landmarks']}'s {kf.distance}")
        problem = image_problem(kf)
        if problem:
            report.problems.append(f"keyframes[{i}]: {entry['image']}: {problem}")
    unlisted = sorted(p.name for p in root.iterdir()
                      if p.name.startswith(_KF_FILE[0]) and p.suffix in _KF_FILE[1] and p.name not in files)
    if unlisted:
        report.notes.append(f"files not in the manifest (a keyframe being written when teaching stopped): "
                            f"{', '.join(unlisted)}")
    temps = stray_temp_files(root)
    if temps:
        report.notes.append(f"temporary files an interrupted writer left: {', '.join(p.name for p in temps)}")
    siblings = stray_route_dirs(root)
    if siblings:
        report.notes.append(f"an interrupted replacement left {', '.join(p.name for p in siblings)} beside it")
    if not route.complete:
        report.notes.append(route.incomplete_note())
    return report
