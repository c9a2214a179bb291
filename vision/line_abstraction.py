"""The slow loop of Marvin's map (Fig. 11.3, right block): segments abstracted to vertical edges, box and
wall polygons, and hypotheses of the lines that are missing.

Pure functions of the map's verified segments (world frame, y down, floor y = 0):

- ``vertical_edges``: segments within ``vertical_deg`` of the vertical whose lower end is within
  ``floor_band_m`` of the floor: the corners of boxes and walls, as (x, z, height). A vertical edge is
  assumed to stand on the floor (man-made objects do): LSD rarely follows a textured edge all the way
  down, so the band is wide;
- ``floor_lines``: horizontal segments lying on the floor (the feet of boxes and walls, vision/line_floor.py);
- ``box_polygons``: vertical edges within ``box_max_m`` of each other, of similar height or joined by a
  foot (a floor line between them: a corner's top is where LSD's pieces of it ended, often early), are the
  corners of one object, and a floor line is its lower edge when two of them stand on it (within ``foot_on_m``, at least
  ``min_side_m`` apart along it: two edges of one corner are not two corners), or when
  it starts at the end of a face between two of them at right angles to it (``foot_angle_deg``). Boxes
  are rectangular: the footprint is the rectangle around the corners and the lower edges' ends whose sides
  follow the corners' right angle (else the points' right angle, else the smallest such rectangle), so
  an object seen at two faces (three corners, or two corners and a lower edge) is closed on the side the
  robot has not seen: the hypothesised corner is part of the footprint the grid marks as occupied
  (two points give the face between them);
- ``missing_lines``: the vertical edges at the footprint's corners where no vertical edge was seen, the
  top edges and the lower edges, are hypotheses. The sensor loop verifies or prunes them like any candidate
  (``LineMap.add_hypotheses``). A lower edge is posted too: a face whose contrast with the floor changes
  sign along it leaves LSD pieces too short to verify (box_b's far face in the room test), while the
  footprint from its verified corners says where the whole edge is.
- ``object_polygons``: all of it from the map's verified segments.

``AbstractionThread`` (control/stages/line_map.py) runs this in its own thread, slower than the frame loop;
``pinned_ends`` tells it which ends of a box's hypotheses stand at seen corners.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np


@dataclass(frozen=True)
class AbstractionParams:
    vertical_deg: float = 8.0
    floor_band_m: float = 0.5
    min_height_m: float = 0.15
    box_max_m: float = 1.3          # corners of one object are at most this far apart
    height_tol_m: float = 0.3       # and their tops within this of each other (LSD pieces end early)
    merge_m: float = 0.06           # vertical edges this close are one corner
    foot_band_m: float = 0.03       # a floor line lies this close to the floor (both ends)
    foot_on_m: float = 0.05         # vertical edges this close to a floor line stand on it
    foot_angle_deg: float = 10.0    # a floor line from one corner at right angles (this close) to a seen face
    corner_seen_m: float = 0.15     # a footprint corner this close to a seen vertical edge is not hypothesised
    min_side_m: float = 0.1         # a footprint thinner than this is a face, not a box: no hypotheses
    right_angle_tol_deg: float = 15.0  # a hull corner this close to 90 deg is a box corner (sets the footprint's axes)


@dataclass
class ObjectPolygon:
    footprint: np.ndarray           # (N, 2) x, z on the floor, convex (a rectangle when >= 3 points were seen)
    height: float                   # m
    corners: int                    # vertical edges it was built from
    seen_xz: np.ndarray = None      # (corners, 2) where those vertical edges stand


def vertical_edges(P: np.ndarray, params: AbstractionParams = AbstractionParams()) -> np.ndarray:
    """(K, 3) x, z, height of the vertical segments standing on the floor (nearby ones merged)."""
    if len(P) == 0:
        return np.zeros((0, 3))
    d = P[:, 1] - P[:, 0]
    cos_v = np.abs(d[:, 1]) / np.maximum(np.linalg.norm(d, axis=1), 1e-12)
    h = -P[..., 1]
    ok = (cos_v >= math.cos(math.radians(params.vertical_deg))) & (h.min(axis=1) <= params.floor_band_m) \
        & (h.max(axis=1) >= params.min_height_m)
    if not ok.any():
        return np.zeros((0, 3))
    xz = P[ok][..., [0, 2]].mean(axis=1)
    top = h[ok].max(axis=1)
    out = []
    used = np.zeros(len(xz), bool)
    for i in np.argsort(-top):
        if used[i]:
            continue
        near = ~used & (np.linalg.norm(xz - xz[i], axis=1) <= params.merge_m)
        used |= near
        out.append((*xz[near].mean(axis=0), top[near].max()))
    return np.array(out, float)


def floor_lines(P: np.ndarray, params: AbstractionParams = AbstractionParams()) -> np.ndarray:
    """(K, 2, 2) x, z of the segments lying on the floor (both ends within ``foot_band_m`` of it)."""
    if len(P) == 0:
        return np.zeros((0, 2, 2))
    on = (np.abs(P[..., 1]) <= params.foot_band_m).all(axis=1)
    return P[on][..., [0, 2]]


def box_polygons(edges: np.ndarray, params: AbstractionParams = AbstractionParams(),
                 feet: np.ndarray | None = None) -> list[ObjectPolygon]:
    """Group vertical edges (x, z, height) into objects of similar height and close corners; ``feet``
    (K, 2, 2): floor lines; an object's lower edges add their ends to its footprint (see the module)."""
    n = len(edges)
    parent = list(range(n))

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    feet = np.zeros((0, 2, 2)) if feet is None else np.asarray(feet, float).reshape(-1, 2, 2)
    for i in range(n):
        for j in range(i + 1, n):
            if math.hypot(*(edges[i, :2] - edges[j, :2])) <= params.box_max_m and (
                    abs(edges[i, 2] - edges[j, 2]) <= params.height_tol_m or _face_between(edges, i, j, feet, params)):
                parent[root(j)] = root(i)
    groups: dict = {}
    for i in range(n):
        groups.setdefault(root(i), []).append(i)
    out = []
    for members in groups.values():
        seen = edges[members, :2]
        pts = [seen]
        if len(feet):
            a, ab = feet[:, 0], feet[:, 1] - feet[:, 0]
            t = np.clip(((seen[:, None] - a[None]) * ab[None]).sum(-1) / np.maximum((ab ** 2).sum(-1), 1e-12), 0, 1)
            dist = np.linalg.norm(seen[:, None] - (a[None] + t[..., None] * ab[None]), axis=2)    # (corners, K)
            on = dist <= params.foot_on_m
            # A foot between two corners: the corners it passes stand at least min_side_m apart along it. Two
            # vertical edges of one corner (merge_m apart or a little more) are not two corners: a floor
            # texture line touching box_a's corner there, at 26 deg to its face, ran its footprint 0.86 m
            # off the box in `goto --map`'s grown map (seed 0 from (-0.9, -1.5); the route was held for good).
            s = t * np.linalg.norm(ab, axis=1)[None]                                    # (corners, K) along
            spans = np.where(on, s, -np.inf).max(axis=0) - np.where(on, s, np.inf).min(axis=0) >= params.min_side_m
            lower = spans | _square_to_a_face(feet, seen, on, params)
            lower &= np.linalg.norm(ab, axis=1) <= params.box_max_m
            # A lower edge's end within foot_on_m of a corner is that corner: as a hull vertex of its own
            # (a few mm outside) it made the corner's sides shorter than min_side_m, so its right angle
            # was skipped and the smallest rectangle could take the hypotenuse of three corners as a side.
            ends = feet[lower].reshape(-1, 2)
            away = np.linalg.norm(ends[:, None] - seen[None], axis=2).min(axis=1) > params.foot_on_m
            pts.append(ends[away])
        pts = np.vstack(pts)
        if len(members) < 2 and len(pts) < 3:
            continue
        out.append(ObjectPolygon(_rectangle(pts, params, seen), float(edges[members, 2].mean()), len(members), seen.copy()))
    return out


def _face_between(edges: np.ndarray, i: int, j: int, feet: np.ndarray, params: AbstractionParams) -> bool:
    """Vertical edges i and j are two corners of one face, whatever their tops: a floor line at least
    ``min_side_m`` long lies on the line between them (both its ends within ``foot_on_m`` of it, between the
    two along it: the face's foot) and no other vertical edge stands on that line between them. A corner's
    top is where LSD's pieces of it ended, often early (room seeds 3 and 4 at 60 frames: box_a's near corner
    at 0.36-0.56 m of its 0.9 m), so tops more than ``height_tol_m`` apart do not prove two objects; a foot
    joining the two does prove one."""
    if len(feet) == 0:
        return False
    a, b = edges[i, :2], edges[j, :2]
    L = float(np.linalg.norm(b - a))
    if L < params.min_side_m:
        return False
    u = (b - a) / L
    w = np.array([-u[1], u[0]])
    along, across = (feet - a) @ u, (feet - a) @ w                                   # (K, 2)
    on = (np.abs(across) <= params.foot_on_m).all(axis=1) & (along.min(axis=1) >= -params.foot_on_m) \
        & (along.max(axis=1) <= L + params.foot_on_m) & (np.ptp(along, axis=1) >= params.min_side_m)
    if not on.any():
        return False
    rel = edges[:, :2] - a
    others = (np.abs(rel @ w) <= params.foot_on_m) & (rel @ u > params.foot_on_m) & (rel @ u < L - params.foot_on_m)
    others[[i, j]] = False
    return not others.any()


def _right_angle_axis(pts: np.ndarray, params: AbstractionParams):
    """The unit direction of the longer side at the hull corner of pts nearest to a right angle (within
    ``right_angle_tol_deg``, both sides at least ``min_side_m``), or None (and the hull)."""
    hull = _face_hull(pts, params)
    best_cos, axis = math.sin(math.radians(params.right_angle_tol_deg)), None
    if len(hull) >= 3:
        for _, c, a, b, na, nb in _hull_angles(hull, params):
            if c <= best_cos:
                best_cos, axis = c, (a if na >= nb else b)
    return axis, hull


def _face_hull(pts: np.ndarray, params: AbstractionParams) -> np.ndarray:
    """The convex hull of pts (N, 2) at full precision (the input points nearest to its vertices), without
    the vertices that lie on a face (``_on_faces_dropped``); fewer than 3 vertices when (nearly) collinear."""
    hull = cv2.convexHull(pts.astype(np.float32)).reshape(-1, 2)
    if len(hull) < 3:
        return hull.astype(float)
    hull = pts[np.argmin(np.linalg.norm(pts[None] - hull[:, None].astype(float), axis=2), axis=1)]
    return _on_faces_dropped(hull, params.foot_on_m)


def _hull_angles(hull: np.ndarray, params: AbstractionParams):
    """Per hull vertex whose two sides are at least ``min_side_m``: (index, |cos| of its angle, the unit
    directions to its two neighbours, their lengths)."""
    for k in range(len(hull)):
        a, b = hull[k - 1] - hull[k], hull[(k + 1) % len(hull)] - hull[k]
        na, nb = np.linalg.norm(a), np.linalg.norm(b)
        if min(na, nb) >= params.min_side_m:
            yield k, abs(a @ b) / (na * nb), a / na, b / nb, na, nb


def _square_to_a_face(feet: np.ndarray, seen: np.ndarray, on: np.ndarray, params: AbstractionParams) -> np.ndarray:
    """(K,) bool: the floor line starts at a corner that ends a face between two corners, and runs at right
    angles to that face (the other face's foot). A face is a side of the corners seen: all of them on one
    side of its line (within ``foot_on_m``), and the corner an end of it: no other corner on its line
    beyond. Vertical texture lines on faces are verified vertical edges too: the line between two of them on
    adjacent faces crosses the box, and a floor line leaving the middle of a face is floor texture meeting
    it, not a foot (room seed 1, 120 frames: a 0.46 m floor line at right angles to the line between two
    texture lines put box_b's footprint 0.3 m outside the box and turned it 45 deg, IoU 0.30)."""
    out = np.zeros(len(feet), bool)
    if len(seen) < 2:
        return out
    ends = np.linalg.norm(feet[:, :, None, :] - seen[None, None], axis=3).min(axis=1) <= params.foot_on_m  # (K, C)
    u = feet[:, 1] - feet[:, 0]
    u = u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
    sin_tol = math.sin(math.radians(params.foot_angle_deg))
    for k in np.nonzero(ends.any(axis=1) & (on.sum(axis=0) == 1))[0]:
        c = int(np.nonzero(ends[k])[0][0])
        rel = seen - seen[c]
        n = np.linalg.norm(rel, axis=1)
        for f in rel[n > 2 * params.foot_on_m] / n[n > 2 * params.foot_on_m][:, None]:
            if abs(f @ u[k]) > sin_tol:
                continue
            along, across = rel @ f, rel @ np.array([-f[1], f[0]])
            one_side = (across >= -params.foot_on_m).all() or (across <= params.foot_on_m).all()
            beyond = (np.abs(across) <= params.foot_on_m) & (along < -params.foot_on_m)
            if one_side and not beyond.any():
                out[k] = True
                break
    return out


def _on_faces_dropped(hull: np.ndarray, tol: float) -> np.ndarray:
    """The hull without the vertices that lie on a face: within ``tol`` of the line between their two
    neighbours, the nearest first, while more than 3 remain. A vertical texture line on a box face is a
    verified vertical edge too, a few cm off the face's line (the corners' own error); as a hull vertex it
    split the face in two, hid the corner's right angle and let the smallest rectangle turn 45 deg
    (room seed 3: box_b's footprint across its diagonal)."""
    hull = hull.copy()
    while len(hull) > 3:
        prev, nxt = np.roll(hull, 1, axis=0), np.roll(hull, -1, axis=0)
        chord = nxt - prev
        n = np.linalg.norm(chord, axis=1)
        d = np.abs(chord[:, 0] * (hull - prev)[:, 1] - chord[:, 1] * (hull - prev)[:, 0]) / np.maximum(n, 1e-12)
        k = int(np.argmin(d))
        if d[k] > tol:
            break
        hull = np.delete(hull, k, axis=0)
    return hull


def _rectangle(pts: np.ndarray, params: AbstractionParams = AbstractionParams(),
               corners: Optional[np.ndarray] = None) -> np.ndarray:
    """The rectangle (4, 2) around the points (boxes are rectangular), or their hull when they are (nearly)
    collinear or fewer than 3. Its sides follow the hull's corner nearest to a right angle (two faces of a
    box, or a face and a lower edge, within ``right_angle_tol_deg``): the smallest rectangle alone cannot
    tell a right triangle's legs from its hypotenuse (same area); failing such a corner, the smallest one
    (a side of it along a side of the hull). ``corners``: the seen vertical edges among pts; when their own
    hull has such a corner it sets the sides: a lower edge's end is a floor line's, which LSD may run on past
    the corner into the floor's texture, and as a hull vertex it hid the corners' right angle and turned the
    rectangle (room seed 2, 120 frames: box_a's east foot 0.2 m past its corner, IoU 0.62). Every point
    stays inside the rectangle."""
    axis, hull = _right_angle_axis(corners, params) if corners is not None else (None, None)
    if axis is None:
        axis, hull = _right_angle_axis(pts, params)
    else:
        hull = _face_hull(pts, params)
    if len(hull) < 3:
        return hull
    axes = [axis] if axis is not None else [(b - a) / max(np.linalg.norm(b - a), 1e-12)
                                             for a, b in zip(hull, np.roll(hull, -1, axis=0))]
    best = None
    for u in axes:
        v = np.array([-u[1], u[0]])
        su, sv = pts @ u, pts @ v
        area = np.ptp(su) * np.ptp(sv)
        if best is None or area < best[0]:
            best = (area, u, v, su.min(), su.max(), sv.min(), sv.max())
    area, u, v, u0, u1, v0, v1 = best
    if min(u1 - u0, v1 - v0) < 1e-3:
        return hull.astype(float)
    return np.array([u0 * u + v0 * v, u1 * u + v0 * v, u1 * u + v1 * v, u0 * u + v1 * v])


def object_polygons(P: np.ndarray, params: AbstractionParams = AbstractionParams()) -> list[ObjectPolygon]:
    """Objects standing on the floor, from the map's verified segments (world frame)."""
    return box_polygons(vertical_edges(P, params), params, floor_lines(P, params))


def pinned_ends(hyp: np.ndarray, poly: ObjectPolygon) -> np.ndarray:
    """(K, 2) bool: the ends of ``missing_lines(poly)`` that stand at a seen corner (``poly.seen_xz``; the
    others are footprint corners, where the rectangle says the box ends)."""
    seen = np.zeros((0, 2)) if poly.seen_xz is None else poly.seen_xz
    xz = np.asarray(hyp, float).reshape(-1, 2, 3)[..., [0, 2]]
    if len(seen) == 0:
        return np.zeros(xz.shape[:2], bool)
    return (np.abs(xz[:, :, None] - seen[None, None]).max(axis=3) <= 1e-9).any(axis=2)


def missing_lines(poly: ObjectPolygon, params: AbstractionParams = AbstractionParams()) -> np.ndarray:
    """(K, 2, 3) hypothesised segments of a box whose footprint is a rectangle: the vertical edges at its
    corners where none was seen (first), then its four top edges (world frame, y = -height at the top), then
    its four lower edges (y = 0).
    Nothing for a face (a footprint thinner than ``min_side_m``)."""
    fp = poly.footprint
    if len(fp) != 4:
        return np.zeros((0, 2, 3))
    sides = np.linalg.norm(np.roll(fp, -1, axis=0) - fp, axis=1)
    if sides.min() < params.min_side_m:
        return np.zeros((0, 2, 3))
    h = poly.height
    seen = np.zeros((0, 2)) if poly.seen_xz is None else poly.seen_xz
    out = []
    # The top and lower edges run between the corners' vertical lines: a seen corner's where it was seen
    # (the footprint is a rectangle fitted to all of them, a few cm off each), else the footprint's.
    at = fp.astype(float).copy()
    for i, c in enumerate(fp):
        if len(seen) == 0 or np.linalg.norm(seen - c, axis=1).min() > params.corner_seen_m:
            out.append([[c[0], 0.0, c[1]], [c[0], -h, c[1]]])
            continue
        # A seen corner moves only the footprint corner nearest to it: two corners of a narrow footprint
        # within corner_seen_m of one seen corner made an edge of zero length (a map that cannot be saved).
        j = int(np.argmin(np.linalg.norm(seen - c, axis=1)))
        if int(np.argmin(np.linalg.norm(fp - seen[j], axis=1))) == i:
            at[i] = seen[j]
    for a, b in zip(at, np.roll(at, -1, axis=0)):
        out.append([[a[0], -h, a[1]], [b[0], -h, b[1]]])
    for a, b in zip(at, np.roll(at, -1, axis=0)):
        out.append([[a[0], 0.0, a[1]], [b[0], 0.0, b[1]]])
    return np.array(out, float)
