"""The DLM on disk: one versioned JSON file, written to a temporary file and renamed (like routes).

    {"format": "vbnav-line-map", "version": 1, "created": ..., "frames": N, "params": {...},
     "segments": [{"id", "p0", "p1", "cov0", "cov1", "support", "misses", "verified", "group",
                   "hypothesis", "ambiguous", "stance": [standing, flat],
                   "views": [[x, y, z, heading], ...]}, ...]}

Endpoints are world metres (x right, y down, z forward, floor y = 0). ``stance`` counts a floor line's
observations that had a face rising from them and those with floor beyond (``LineMap.stance_votes``); a
map written without it loads with none, as the map had none when it was built. The information form is rebuilt
from the covariances on load, so a loaded map keeps fusing.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from vbnav.drivers.atomic_file import write_atomic
from vbnav.drivers.errors import InputError
from vbnav.drivers.plain_values import load_json
from vbnav.vision.line_map import LineMap, MapParams

FORMAT, VERSION = "vbnav-line-map", 1


class MapFileError(InputError):
    """A map file is missing, corrupt, foreign or from a newer version; the message names the file."""


def objects_meta(polygons) -> list[dict]:
    """The ``objects`` block of a map file's meta: each object polygon's footprint (x, z, m) and height,
    from the abstraction (vision/line_abstraction.py)."""
    return [{"footprint": np.round(p.footprint, 4).tolist(), "height": round(float(p.height), 3)} for p in polygons]


def save_map(lmap: LineMap, path: str | Path, meta: dict | None = None) -> None:
    segs = []
    for k in range(len(lmap)):
        segs.append({"id": int(lmap.ids[k]), "p0": lmap.P[k, 0].round(6).tolist(), "p1": lmap.P[k, 1].round(6).tolist(),
                     "cov0": lmap.cov[k, 0].round(10).tolist(), "cov1": lmap.cov[k, 1].round(10).tolist(),
                     "support": int(lmap.support[k]), "misses": int(lmap.misses[k]),
                     "verified": bool(lmap.verified[k]), "group": int(lmap.group[k]),
                     "hypothesis": bool(lmap.hypothesis[k]), "ambiguous": bool(lmap.ambiguous[k]),
                     "stance": lmap.stance_votes[k].tolist(),
                     "views": [np.round(v, 5).tolist() for v in lmap.views[k]]})
    data = {"format": FORMAT, "version": VERSION, "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
            "frames": int(lmap.frames), "params": dataclasses.asdict(lmap.params), "meta": meta or {},
            "segments": segs}
    path = Path(path)
    try:
        text = json.dumps(data)
    except (TypeError, ValueError) as exc:      # a meta value JSON has no word for
        raise MapFileError(f"{path}: not saved: meta is not JSON ({exc})") from None
    try:    # what load_map would refuse is not written: a map that cannot be loaded back is no map
        map_from_data(path, json.loads(text))
    except MapFileError as exc:
        raise MapFileError(f"{path}: not saved, it could not be loaded back: "
                           f"{str(exc).removeprefix(f'{path}: ')}") from None
    try:
        write_atomic(path, text)
    except OSError as exc:                      # a folder not writable or gone, a full disk: the caller says so
        raise MapFileError(f"{path}: not saved: {exc.strerror or exc}") from None


def load_map(path: str | Path) -> tuple[LineMap, dict]:
    """(map, meta) from a map file; MapFileError names the file and what is wrong."""
    path = Path(path)
    if path.is_dir():
        raise MapFileError(f"{path}: is a directory, expected a map file (JSON, from vbnav map build)")
    if not path.is_file():
        raise MapFileError(f"{path}: " + ("is not a regular file, expected a map file" if path.exists()
                                          else "map file not found"))
    try:
        data = load_json(path.read_text())
    except ValueError as exc:       # not JSON, not UTF-8, a key given twice
        raise MapFileError(f"{path}: not a JSON map file ({exc})") from None
    except RecursionError:
        raise MapFileError(f"{path}: not a JSON map file (nested too deeply)") from None
    return map_from_data(path, data)


def map_from_data(path: Path, data) -> tuple[LineMap, dict]:
    """(map, meta) from a map file's parsed JSON, every check of load_map (and of save_map before it
    writes); MapFileError names ``path`` and what is wrong."""
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise MapFileError(f"{path}: not a vbnav line map (format {data.get('format') if isinstance(data, dict) else None!r},"
                           f" expected {FORMAT!r})")
    ver = data.get("version")
    if not isinstance(ver, int) or isinstance(ver, bool) or ver < 1:
        raise MapFileError(f"{path}: version must be an integer >= 1, got {ver!r}")
    if ver > VERSION:
        raise MapFileError(f"{path}: version {ver} is newer than this vbnav reads (<= {VERSION}); upgrade vbnav")
    known = {f.name for f in dataclasses.fields(MapParams)}
    given = data.get("params", {})
    unknown = sorted(set(given) - known) if isinstance(given, dict) else []
    if unknown:     # a parameter the map was built with that this vbnav would silently not apply
        raise MapFileError(f"{path}: params: unknown key(s) {', '.join(map(repr, unknown))} (this vbnav's map "
                           f"parameters: {', '.join(sorted(known))})")
    if not isinstance(given, dict):
        raise MapFileError(f"{path}: params: expected an object of map parameters, got {type(given).__name__}")
    for f in dataclasses.fields(MapParams):     # a word here was taken, and failed the first mapping frame
        v = given.get(f.name, 0)
        if not _finite(v) or (f.type == "int" and not float(v).is_integer()):
            raise MapFileError(f"{path}: params: {f.name}: expected a finite {'integer' if f.type == 'int' else 'number'}"
                               f", got {v!r}")
    meta = data.get("meta", {})
    if not isinstance(meta, dict) or not isinstance(meta.get("objects", []), list):
        raise MapFileError(f"{path}: meta: expected an object with a list 'objects', got {meta!r:.60}")
    if "frames" in meta:        # goto --map-out adds its own frames to it
        _check_count(path, "meta.frames", meta["frames"], 0)
    pose = meta.get("sim_start_pose", [0.0, 0.0, 0.0])     # map build on the simulator: its frame's world pose
    if not (isinstance(pose, list) and len(pose) == 3 and all(_finite(v) for v in pose)):
        raise MapFileError(f"{path}: meta.sim_start_pose: expected [x, z, heading_deg], finite numbers, got "
                           f"{pose!r:.60}")
    for k, o in enumerate(meta.get("objects", [])):
        try:
            fp = np.asarray(o["footprint"], float)
            ok = (fp.ndim == 2 and fp.shape[1] == 2 and np.isfinite(fp).all() and _finite(o["height"])
                  and o["height"] >= 0 and _numbers(o["footprint"], (len(fp), 2)))
        except (KeyError, TypeError, ValueError):
            ok = False
        if not ok:
            raise MapFileError(f"{path}: meta.objects[{k}]: expected footprint (a list of [x, z] pairs) and height "
                               f"(>= 0), finite numbers")
        # Two points are a face (vision/line_abstraction.py writes one for two corners seen); fewer distinct
        # points have no extent: a corrupt object, which the planning grid drew as one cell.
        if not np.ptp(fp, axis=0).max() > 1e-9:
            raise MapFileError(f"{path}: meta.objects[{k}]: footprint {o['footprint']!r:.60} is one point, expected "
                               f"at least two distinct [x, z] points (a face between two corners, or a polygon)")
    _check_count(path, "frames", data.get("frames", 0), 0)
    try:
        params = MapParams(**given)
    except ValueError as exc:       # finite but meaningless (a negative range, no views to verify): refused
        raise MapFileError(f"{path}: params: {exc}") from None
    segs = data.get("segments")
    if not isinstance(segs, list):
        raise MapFileError(f"{path}: segments: expected a list of segments, got {type(segs).__name__}")
    try:
        lmap = LineMap(params)
        n = len(segs)
        for k, s in enumerate(segs):    # np.array(..., bool) made "false" True; int arrays cut 2.5 to 2
            _check_entry(path, k, s)
            for name, low in (("support", 0), ("misses", 0), ("group", -1)):
                _check_count(path, f"segments[{k}].{name}", s[name], low)
            # "ambiguous" is newer than the format: a map written without it was built when only
            # verify_views viewpoints verified, so its candidates keep that rule (true).
            for name in ("verified", "hypothesis", "ambiguous"):
                if not isinstance(s.get(name, True), bool):
                    raise MapFileError(f"{path}: segments[{k}].{name}: expected true or false, got {s[name]!r}")
            stance = s.get("stance", [0, 0])
            if not (isinstance(stance, list) and len(stance) == 2):
                raise MapFileError(f"{path}: segments[{k}].stance: expected [standing, flat] counts, got {stance!r}")
            for e, name in enumerate(("standing", "flat")):
                _check_count(path, f"segments[{k}].stance[{e}] ({name})", stance[e], 0)
        P = np.array([[s["p0"], s["p1"]] for s in segs], float).reshape(n, 2, 3)
        C = np.array([[s["cov0"], s["cov1"]] for s in segs], float).reshape(n, 2, 3, 3)
        _check_segments(path, P, C, [s["id"] for s in segs])
        if n:
            lmap._insert(P, C, np.array([s["group"] for s in segs]), None)
            lmap.ids = np.array([s["id"] for s in segs], int)
            lmap.support = np.array([s["support"] for s in segs], int)
            lmap.misses = np.array([s["misses"] for s in segs], int)
            lmap.verified = np.array([s["verified"] for s in segs], bool)
            lmap.hypothesis = np.array([s["hypothesis"] for s in segs], bool)
            lmap.ambiguous = np.array([s.get("ambiguous", True) for s in segs], bool)
            lmap.stance_votes = np.array([s.get("stance", [0, 0]) for s in segs], int).reshape(n, 2)
            lmap.views = [[np.array(v, float) for v in s["views"]] for s in segs]
            lmap.next_id = int(lmap.ids.max()) + 1
            lmap.next_group = int(max(lmap.group.max(), -1)) + 1
        lmap.frames = int(data.get("frames", 0))
    except MapFileError:
        raise
    except (KeyError, TypeError, ValueError) as exc:
        raise MapFileError(f"{path}: segments: malformed entry ({type(exc).__name__}: {exc})") from None
    return lmap, meta


def _finite(v) -> bool:
    """A JSON number (not true/false) and finite (a JSON integer too large for a float is not)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        return bool(np.isfinite(float(v)))
    except OverflowError:
        return False


# Counts and ids: what a float holds exactly (JSON's numbers), far beyond any map (2^53 frames at 15 Hz
# are 19 million years); 10^30 overflowed numpy's integers with a traceback.
MAX_COUNT = 2 ** 53
# An endpoint's sigma, m: 1 nm to 1 km along every axis. 1e-300 passed as positive definite and failed the
# information form's inverse ("Singular matrix"); 1e300 overflowed the gates.
SIGMA_RANGE_M = (1e-9, 1e3)
SEGMENT_FIELDS = ("id", "p0", "p1", "cov0", "cov1", "support", "misses", "verified", "group", "hypothesis",
                  "views")


def _check_count(path: Path, field: str, v, low: int) -> None:
    if isinstance(v, bool) or not isinstance(v, int) or v < low:
        raise MapFileError(f"{path}: {field}: expected an integer >= {low}, got {v!r:.40}")
    if v > MAX_COUNT:
        raise MapFileError(f"{path}: {field}: expected an integer >= {low}, at most 2^53, got {v!r:.40}")


def _numbers(v, shape: tuple) -> bool:
    """Whether ``v`` is nested JSON lists of finite numbers (not strings, not true/false) of this shape."""
    if not shape:
        return _finite(v)
    return isinstance(v, list) and len(v) == shape[0] and all(_numbers(x, shape[1:]) for x in v)


def _check_entry(path: Path, k: int, s) -> None:
    """A segment entry's fields are there and their numbers are numbers: np.array(..., float) read "1" as 1
    and true as 1.0, and a field left out said "malformed entry (KeyError: 'cov0')" without the segment."""
    if not isinstance(s, dict):
        raise MapFileError(f"{path}: segments[{k}]: expected an object, got {type(s).__name__}")
    missing = [name for name in SEGMENT_FIELDS if name not in s]
    if missing:
        raise MapFileError(f"{path}: segments[{k}]: missing {', '.join(missing)}")
    _check_count(path, f"segments[{k}].id", s["id"], 0)
    for name, shape, what in (("p0", (3,), "[x, y, z]"), ("p1", (3,), "[x, y, z]"),
                              ("cov0", (3, 3), "a 3x3 matrix"), ("cov1", (3, 3), "a 3x3 matrix")):
        if not _numbers(s[name], shape):
            raise MapFileError(f"{path}: segments[{k}].{name}: expected {what} of finite numbers, got "
                               f"{s[name]!r:.60}")
    if not (isinstance(s["views"], list) and all(_numbers(v, (4,)) for v in s["views"])):
        raise MapFileError(f"{path}: segments[{k}].views: expected [x, y, z, heading] finite numbers per view")


def _check_segments(path: Path, P: np.ndarray, C: np.ndarray, ids: list) -> None:
    """Each segment has two finite, distinct endpoints, symmetric positive definite endpoint covariances and
    an id of its own (a zero-length segment has no direction, a singular or indefinite covariance no
    information form: both were taken and bent every later fusion or match)."""
    if not np.isfinite(P).all():
        raise MapFileError(f"{path}: segments: endpoints must be finite numbers")
    if not np.isfinite(C).all():
        raise MapFileError(f"{path}: segments: cov0/cov1 must be finite numbers")
    seen = {}
    for k in range(len(P)):
        if not np.linalg.norm(P[k, 1] - P[k, 0]) > 1e-9:
            raise MapFileError(f"{path}: segments[{k}]: p0 and p1 are the same point (a segment of zero length), "
                               f"expected two distinct endpoints")
        for e in (0, 1):
            c = C[k, e]
            if not np.allclose(c, c.T, rtol=1e-6, atol=1e-9) or not np.linalg.eigvalsh(c).min() > 0:
                raise MapFileError(f"{path}: segments[{k}]: cov{e} {c.tolist()} is not a symmetric positive "
                                   f"definite 3x3 matrix")
            lo, hi = SIGMA_RANGE_M
            sigma = np.sqrt(np.linalg.eigvalsh(c))
            if sigma.min() < lo or sigma.max() > hi:
                raise MapFileError(f"{path}: segments[{k}]: cov{e}: sigmas {sigma.min():.3g}-{sigma.max():.3g} m, "
                                   f"expected between {lo:g} and {hi:g} m")
        i = int(ids[k])
        if i != ids[k]:
            raise MapFileError(f"{path}: segments[{k}]: id {ids[k]!r} is not an integer")
        if i in seen:
            raise MapFileError(f"{path}: segments[{k}]: id {i} is also segments[{seen[i]}]'s; expected one id per "
                               f"segment")
        seen[i] = k
