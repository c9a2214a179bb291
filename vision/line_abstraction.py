"""The slow loop of Marvin's map (Fig. 11.3, right block): segments abstracted to vertical edges, box and
wall polygons, and hypotheses of the lines that are missing.

Pure functions of the map's verified segments (world frame, y down, floor y = 0):

- ``vertical_edges``: segments within ``vertical_deg`` of the vertical whose lower end is within
  ``floor_band_m`` of the floor: the corners of boxes and walls, as (x, z, height). A vertical edge is
  assumed to stand on the floor (man-made objects do): LSD rarely follows a textured edge all the way
  down, so the band is wide;
- ``box_polygons``: vertical edges of similar height within ``box_max_m`` of each other are the corners of
  one object: its footprint is their convex hull on the floor (two corners give the face between them);
- ``missing_lines``: for an object with three corners seen, the fourth corner of the parallelogram is a
  hypothesis (a vertical segment of the same height), and so are the top edges between seen corners not in
  the map. The sensor loop verifies or prunes them like any candidate (``LineMap.add_hypotheses``).

``control/stages/line_abstraction.py`` runs this in its own thread, slower than the frame loop.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

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


@dataclass
class ObjectPolygon:
    footprint: np.ndarray           # (N, 2) x, z on the floor, convex, counter-clockwise
    height: float                   # m
    corners: int                    # vertical edges it was built from


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


def box_polygons(edges: np.ndarray, params: AbstractionParams = AbstractionParams()) -> list[ObjectPolygon]:
    """Group vertical edges (x, z, height) into objects of similar height and close corners."""
    n = len(edges)
    parent = list(range(n))

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i in range(n):
        for j in range(i + 1, n):
            if (math.hypot(*(edges[i, :2] - edges[j, :2])) <= params.box_max_m
                    and abs(edges[i, 2] - edges[j, 2]) <= params.height_tol_m):
                parent[root(j)] = root(i)
    groups: dict = {}
    for i in range(n):
        groups.setdefault(root(i), []).append(i)
    out = []
    for members in groups.values():
        if len(members) < 2:
            continue
        pts = edges[members, :2].astype(np.float32)
        hull = cv2.convexHull(pts).reshape(-1, 2) if len(pts) >= 3 else pts
        out.append(ObjectPolygon(hull.astype(float), float(edges[members, 2].mean()), len(members)))
    return out


def missing_lines(poly: ObjectPolygon) -> np.ndarray:
    """(K, 2, 3) hypothesised segments of a box seen at three corners: the fourth vertical edge, and the
    top edges joining the corners (world frame, y = -height at the top)."""
    if poly.corners != 3 or len(poly.footprint) != 3:
        return np.zeros((0, 2, 3))
    a, b, c = poly.footprint
    # The right angle of a box footprint is at the corner whose two sides are most nearly perpendicular.
    best, corner = math.inf, None
    for p, q, r in ((a, b, c), (b, c, a), (c, a, b)):
        u, v = q - p, r - p
        cosang = abs(u @ v) / max(np.linalg.norm(u) * np.linalg.norm(v), 1e-12)
        if cosang < best:
            best, corner = cosang, (p, q, r)
    p, q, r = corner
    fourth = q + r - p
    h = poly.height

    def vert(xz):
        return [[xz[0], 0.0, xz[1]], [xz[0], -h, xz[1]]]

    def top(s, e):
        return [[s[0], -h, s[1]], [e[0], -h, e[1]]]

    return np.array([vert(fourth), top(q, fourth), top(r, fourth), top(p, q), top(p, r)], float)
