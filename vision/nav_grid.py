"""A 2D traversability grid from the line map, and an A* planner on it (map-based goto).

Marvin's map lets the robot plan through places it has only seen. The grid is
the floor plan (x right, z forward, metres) at ``resolution_m`` per cell:

- a verified segment rising above the floor is part of a wall or an object
  standing there: its floor trace (the segment projected onto the floor) is
  an obstacle; a vertical one marks the point where it stands;
- segments entirely above ``robot_height_m`` are overhangs the robot passes
  under, segments lying within ``floor_band_m`` of the floor are markings it
  drives over; any other segment blocks its floor trace too;
- obstacles are grown by the robot radius plus ``clearance_m`` (distance
  transform), so the planner treats the robot as a point;
- cells the map never saw are free (the obstacle stop watches what the map
  missed); optionally a bounding polygon limits planning to the mapped area.

``plan`` is 8-connected A* with the Euclidean heuristic; the path is
thinned to waypoints where it turns (line of sight on the grown grid).
"""
from __future__ import annotations

import heapq
import math
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np


MAX_CELLS = 16_000_000   # 4000 x 4000 cells, 200 m square at 5 cm: about 100 MB to build, A* still in seconds


@dataclass(frozen=True)
class GridParams:
    resolution_m: float = 0.05
    robot_radius_m: float = 0.2
    clearance_m: float = 0.08        # covers the grid discretisation (half a cell diagonal, 3.5 cm)
    floor_band_m: float = 0.1
    robot_height_m: float = 0.5
    margin_m: float = 1.0          # grid extends this far beyond the mapped segments and the query points


@dataclass
class NavGrid:
    """occupied: (H, W) bool raw obstacles; blocked: grown by the robot radius. Cell (r, c) centre is at
    x = x0 + (c + 0.5) res, z = z0 + (r + 0.5) res."""

    x0: float
    z0: float
    res: float
    occupied: np.ndarray
    blocked: np.ndarray
    grown_m: float = 0.0        # how far the obstacles were grown (robot radius + clearance)

    def cell(self, x: float, z: float) -> tuple[int, int]:
        return int(math.floor((z - self.z0) / self.res)), int(math.floor((x - self.x0) / self.res))

    def centre(self, r: int, c: int) -> tuple[float, float]:
        return self.x0 + (c + 0.5) * self.res, self.z0 + (r + 0.5) * self.res

    def inside(self, r: int, c: int) -> bool:
        return 0 <= r < self.blocked.shape[0] and 0 <= c < self.blocked.shape[1]

    def is_free(self, x: float, z: float) -> bool:
        r, c = self.cell(x, z)
        return self.inside(r, c) and not self.blocked[r, c]


def obstacle_traces(P: np.ndarray, params: GridParams = GridParams()) -> np.ndarray:
    """(K, 2, 2) floor traces (x, z) of the segments that block the robot."""
    if len(P) == 0:
        return np.zeros((0, 2, 2))
    height = -P[..., 1]                                  # m above the floor
    low, high = height.min(axis=1), height.max(axis=1)
    # Lines lying on the floor (texture, tape, shadows) are not obstacles; lines wholly above the robot neither.
    blocks = (low <= params.robot_height_m) & (high >= params.floor_band_m)
    return P[blocks][..., [0, 2]]


def _extent(traces: np.ndarray, polygons: list, extra_points, params: GridParams):
    """(lo (x, z), W, H) of the grid over the traces, polygons and extra points plus ``margin_m``."""
    pts = np.vstack([traces.reshape(-1, 2)] + polygons) if polygons else traces.reshape(-1, 2)
    if extra_points is not None:
        pts = np.vstack((pts, np.asarray(extra_points, float).reshape(-1, 2)))
    if len(pts) == 0:
        pts = np.zeros((1, 2))
    lo = pts.min(axis=0) - params.margin_m
    hi = pts.max(axis=0) + params.margin_m
    res = params.resolution_m
    W, H = int(math.ceil((hi[0] - lo[0]) / res)), int(math.ceil((hi[1] - lo[1]) / res))
    if W * H > MAX_CELLS:
        raise ValueError(f"the planning grid over x {lo[0]:+.1f}..{hi[0]:+.1f} m, z {lo[1]:+.1f}..{hi[1]:+.1f} m "
                         f"would be {W} x {H} cells of {res} m, more than the {MAX_CELLS} cells planned on")
    return lo, W, H


def _items(traces: np.ndarray, polygons: list, lo, res: float) -> list[tuple]:
    """What is drawn into the grid, in cells: ("line", a, b) per trace, ("poly", cells) per polygon."""
    out = []
    for (xa, za), (xb, zb) in traces:
        out.append(("line", (int((xa - lo[0]) / res), int((za - lo[1]) / res)),
                    (int((xb - lo[0]) / res), int((zb - lo[1]) / res))))
    for q in polygons:
        out.append(("poly", tuple(map(tuple, np.round((q - lo) / res).astype(np.int32).tolist()))))
    return out


def _draw(img: np.ndarray, item: tuple, off=(0, 0)) -> None:
    """Draw one ``_items`` item into ``img`` (its cell (0, 0) at cell ``off`` of the grid)."""
    ox, oz = off
    if item[0] == "line":
        (xa, za), (xb, zb) = item[1], item[2]
        cv2.line(img, (xa - ox, za - oz), (xb - ox, zb - oz), 1, 1)
        return
    cells = np.array(item[1], np.int32) - np.array([ox, oz], np.int32)
    if len(cells) >= 3:
        cv2.fillConvexPoly(img, cells, 1)
    else:
        cv2.line(img, tuple(map(int, cells[0])), tuple(map(int, cells[-1])), 1, 1)


def _bbox(item: tuple) -> tuple[int, int, int, int]:
    """(x0, z0, x1, z1) cells, inclusive, that ``_draw`` may touch."""
    pts = np.array([item[1], item[2]] if item[0] == "line" else item[1]).reshape(-1, 2)
    return int(pts[:, 0].min()), int(pts[:, 1].min()), int(pts[:, 0].max()), int(pts[:, 1].max())


def build_grid(P: np.ndarray, params: GridParams = GridParams(), extra_points: Optional[np.ndarray] = None,
               polygons: Optional[list] = None) -> NavGrid:
    """The grid of the given world segments (K, 2, 3); ``extra_points`` (N, 2) x, z must lie inside it;
    ``polygons``: object footprints ((N, 2) x, z, from vision/line_abstraction.py) filled as obstacles.
    ValueError when the grid would hold more than ``MAX_CELLS`` cells."""
    traces = obstacle_traces(P, params)
    polygons = [np.asarray(q, float).reshape(-1, 2) for q in (polygons or [])]
    lo, W, H = _extent(traces, polygons, extra_points, params)
    res = params.resolution_m
    occ = np.zeros((H, W), np.uint8)
    for item in _items(traces, polygons, lo, res):
        _draw(occ, item)
    free = (occ == 0).astype(np.uint8)
    dist = cv2.distanceTransform(free, cv2.DIST_L2, 5) * res
    blocked = dist <= params.robot_radius_m + params.clearance_m
    return NavGrid(float(lo[0]), float(lo[1]), res, occ.astype(bool), blocked,
                   params.robot_radius_m + params.clearance_m)


class IncrementalGrid:
    """``build_grid`` kept up to date as the map changes: ``update`` takes the same arguments and returns a
    grid equal to ``build_grid``'s, redrawing only the segments and polygons whose cells changed since the
    last call, and the grown margin around them. A change of the grid's extent (the map, the robot or its
    route reaching a new edge) builds it whole again.

    The margin: ``build_grid`` marks the cells whose distance transform (OpenCV's 5x5 chamfer, a minimum
    over paths of fixed steps, so the same for every obstacle cell) is within the radius; that is the
    obstacle cells dilated by the stamp of one obstacle cell, which is exact in any window padded by it."""

    def __init__(self, params: GridParams = GridParams()):
        self.params = params
        grown = params.robot_radius_m + params.clearance_m
        n = int(math.ceil(grown / params.resolution_m)) + 2
        one = np.ones((2 * n + 1, 2 * n + 1), np.uint8)
        one[n, n] = 0
        self._stamp = (cv2.distanceTransform(one, cv2.DIST_L2, 5) * params.resolution_m <= grown).astype(np.uint8)
        self._n = n
        self._extent = None
        self._items: dict = {}              # item -> how many times it is drawn
        self._count: Optional[np.ndarray] = None    # per cell: how many items cover it
        self.grid: Optional[NavGrid] = None
        self.redrawn = 0                    # items drawn or taken out by the last update (a whole build: all)

    def update(self, P: np.ndarray, extra_points: Optional[np.ndarray] = None,
               polygons: Optional[list] = None) -> NavGrid:
        params = self.params
        traces = obstacle_traces(P, params)
        polygons = [np.asarray(q, float).reshape(-1, 2) for q in (polygons or [])]
        lo, W, H = _extent(traces, polygons, extra_points, params)
        items: dict = {}
        for item in _items(traces, polygons, lo, params.resolution_m):
            items[item] = items.get(item, 0) + 1
        extent = (float(lo[0]), float(lo[1]), W, H)
        if extent != self._extent:
            self._extent, self._items = extent, {}
            self._count = np.zeros((H, W), np.uint16)
            occ = np.zeros((H, W), np.uint8)
            self.grid = NavGrid(extent[0], extent[1], params.resolution_m, occ.astype(bool), occ.astype(bool),
                                params.robot_radius_m + params.clearance_m)
        changed = [(it, items.get(it, 0) - self._items.get(it, 0))
                   for it in set(items) | set(self._items) if items.get(it, 0) != self._items.get(it, 0)]
        self._items = items
        self.redrawn = len(changed)
        if len(changed) > 64:           # most of the grid: the whole of it at once
            self._count[:] = 0
            for item, k in items.items():
                self._add(item, k)
            self._window(0, 0, W - 1, H - 1)
            return self.grid
        for item, k in changed:
            self._window(*self._add(item, k))
        return self.grid

    def _add(self, item: tuple, k: int) -> tuple[int, int, int, int]:
        """Count ``item`` k more times (k < 0: fewer) in the cells it covers; returns its cells' box."""
        x0, z0, x1, z1 = _bbox(item)
        mask = np.zeros((z1 - z0 + 1, x1 - x0 + 1), np.uint8)
        _draw(mask, item, (x0, z0))
        cnt = self._count[z0:z1 + 1, x0:x1 + 1].astype(np.int32) + mask.astype(np.int32) * k
        self._count[z0:z1 + 1, x0:x1 + 1] = cnt
        return x0, z0, x1, z1

    def _window(self, x0: int, z0: int, x1: int, z1: int) -> None:
        """Occupied and blocked again over the cells (x0..x1, z0..z1) and the margin around them."""
        g, n = self.grid, self._n
        H, W = g.blocked.shape
        g.occupied[z0:z1 + 1, x0:x1 + 1] = self._count[z0:z1 + 1, x0:x1 + 1] > 0
        bx0, bz0, bx1, bz1 = max(x0 - n, 0), max(z0 - n, 0), min(x1 + n, W - 1), min(z1 + n, H - 1)
        px0, pz0, px1, pz1 = max(bx0 - n, 0), max(bz0 - n, 0), min(bx1 + n, W - 1), min(bz1 + n, H - 1)
        occ = g.occupied[pz0:pz1 + 1, px0:px1 + 1].astype(np.uint8)
        grown = cv2.dilate(occ, self._stamp, borderType=cv2.BORDER_CONSTANT, borderValue=0)
        g.blocked[bz0:bz1 + 1, bx0:bx1 + 1] = grown[bz0 - pz0:bz1 - pz0 + 1, bx0 - px0:bx1 - px0 + 1] > 0


_STEPS = [(-1, 0, 1.0), (1, 0, 1.0), (0, -1, 1.0), (0, 1, 1.0),
          (-1, -1, math.sqrt(2)), (-1, 1, math.sqrt(2)), (1, -1, math.sqrt(2)), (1, 1, math.sqrt(2))]


def goal_cells(grid: NavGrid, goal_xz, tolerance_m: float = 0.0) -> list[tuple[int, int]]:
    """The cells a path to ``goal_xz`` may end in: the goal's own when it is free; when only the grown margin
    blocks it (no mapped obstacle in its cell), the free cells whose nearest point lies within ``tolerance_m``
    of the goal, nearest first; none when the goal is on a mapped obstacle or outside the grid."""
    g = grid.cell(*goal_xz)
    if not grid.inside(*g) or grid.occupied[g]:
        return []
    if not grid.blocked[g]:
        return [g]
    if tolerance_m <= 0.0:
        return []
    n = int(math.ceil(tolerance_m / grid.res)) + 1
    near = []
    for r in range(g[0] - n, g[0] + n + 1):
        for c in range(g[1] - n, g[1] + n + 1):
            if not grid.inside(r, c) or grid.blocked[r, c]:
                continue
            x, z = grid.centre(r, c)
            dx, dz = abs(x - goal_xz[0]), abs(z - goal_xz[1])
            edge = math.hypot(max(dx - grid.res / 2, 0.0), max(dz - grid.res / 2, 0.0))
            if edge <= tolerance_m:
                near.append((edge, math.hypot(dx, dz), (r, c)))
    return [cell for *_, cell in sorted(near)]


@dataclass(frozen=True)
class Approach:
    """The obstacle stop's band, for the planner. Driving a route's last leg the robot watches a band reaching
    ``reach_m`` ahead of its axle, ``half_width_m`` either side; a mapped obstacle there holds it short of the
    goal for good (the goal lies nearer an obstacle than the stop's reach, along the leg). ``legs_m``: the
    lengths of the straight last leg the planner adds to come in from another side, tried in turn (a longer
    one needs more free floor, and turns less); ``tolerance_m``: how far from the leg's first point the
    controller may pass it (its waypoint tolerance), which turns the leg by up to asin(tolerance / length)
    about the goal: 14.5, 9.6 and 7.2 deg for the legs of 4, 6 and 8 tolerances; 16 headings are 22.5 deg
    apart, within twice the shortest leg's turn."""

    reach_m: float
    half_width_m: float
    legs_m: tuple = (0.6, 0.9, 1.2)
    tolerance_m: float = 0.15
    headings: int = 16          # the directions of approach tried, evenly spaced


def band_clear(grid: NavGrid, a, g, approach: Approach, turned: bool = True) -> bool:
    """No mapped obstacle (``grid.occupied``) in the band the obstacle stop watches while the robot drives the
    straight leg ``a`` -> ``g`` (x, z): from ``a`` to ``reach_m`` beyond ``g``, ``half_width_m`` either side,
    for the leg as planned and turned about ``g`` either way by what passing ``a`` within ``tolerance_m``
    allows (``turned``; not for a leg the robot drives from where it stands: no waypoint is passed on it).
    Only the last ``max(legs_m)`` of a longer leg counts: there the goal's surroundings hold the robot."""
    a, g = np.asarray(a, float), np.asarray(g, float)
    length = float(np.hypot(*(g - a)))
    if length < 1e-9:
        return True
    length = min(length, max(approach.legs_m))
    spread = math.asin(min(1.0, approach.tolerance_m / length)) if turned else 0.0
    base = math.atan2(*(g - a))                          # heading: atan2(dx, dz)
    step = grid.res / 2
    along = np.arange(-length, approach.reach_m + step, step)
    across = np.arange(-approach.half_width_m, approach.half_width_m + step / 2, step)
    u, v = np.meshgrid(along, across)
    H, W = grid.occupied.shape
    for phi in (base - spread, base, base + spread):
        d = np.array([math.sin(phi), math.cos(phi)])
        n = np.array([d[1], -d[0]])
        x = g[0] + u * d[0] + v * n[0]
        z = g[1] + u * d[1] + v * n[1]
        r = np.floor((z - grid.z0) / grid.res).astype(int)
        c = np.floor((x - grid.x0) / grid.res).astype(int)
        inside = (r >= 0) & (r < H) & (c >= 0) & (c < W)
        if grid.occupied[r[inside], c[inside]].any():
            return False
    return True


def plan(grid: NavGrid, start_xz, goal_xz, goal_tolerance_m: float = 0.0,
         approach: Optional[Approach] = None) -> Optional[list[tuple[float, float]]]:
    """Waypoints (x, z) from start to goal avoiding blocked cells, or None when there is no path.

    The start cell may be blocked (the robot already stands close to something): the search leaves the
    grown margin from there, through cells no mapped obstacle occupies, within ``grown_m`` of the start.
    A goal in the grown margin but on no mapped obstacle is replaced, with ``goal_tolerance_m``, by the centre
    of the nearest reachable free cell within that distance of it (``goal_cells``): the path's last point is
    then that centre, not ``goal_xz``.

    With ``approach`` (the obstacle stop's band): when a mapped obstacle lies in the band of the path's last
    leg (``band_clear``), the path comes in instead along one of ``approach.headings`` straight last legs, of
    the first length in ``approach.legs_m`` that has any whose band is clear and whose line is free, the one
    reached first; when none is, the path stays as it was (the stop may hold the robot short of the goal
    there, as any mapped obstacle that near would).
    """
    s = grid.cell(*start_xz)
    targets = goal_cells(grid, goal_xz, goal_tolerance_m)
    if not grid.inside(*s) or not targets:
        return None
    came, g = _search(grid, s, set(targets[:1]), targets[0], 0.0)
    if g is None:
        # The search ran out: every cell reachable from the start is in ``came``; the nearest such target.
        g = next((t for t in targets[1:] if t in came or t == s), None)
        if g is None:
            return None
    end = tuple(goal_xz) if g == grid.cell(*goal_xz) else grid.centre(*g)
    path = _waypoints(grid, start_xz, came, s, g, end)
    if approach is None:
        return path
    if band_clear(grid, path[-2], path[-1], approach, turned=len(path) > 2):   # straight from the start: not turned
        return path
    return _plan_approach(grid, start_xz, s, end, approach) or path


def _plan_approach(grid: NavGrid, start_xz, s, end, approach: Approach):
    """The shortest path to ``end`` whose last leg is straight, free and band-clear (``plan``)."""
    for length in approach.legs_m:
        legs = {}
        for k in range(approach.headings):
            phi = 2.0 * math.pi * k / approach.headings
            a = (end[0] - length * math.sin(phi), end[1] - length * math.cos(phi))
            cell = grid.cell(*a)
            if (grid.inside(*cell) and not grid.blocked[cell] and _line_free(grid, cell, grid.cell(*end))
                    and band_clear(grid, a, end, approach)):
                legs.setdefault(cell, a)
        if not legs:
            continue
        came, hit = _search(grid, s, set(legs), grid.cell(*end), length / grid.res)
        if hit is not None:
            return _waypoints(grid, start_xz, came, s, hit, legs[hit]) + [tuple(end)]
    return None


def _search(grid: NavGrid, s, targets: set, toward, near: float):
    """A* from cell ``s`` to the nearest of ``targets`` (cells); the heuristic is the distance to ``toward`` less
    ``near`` cells (every target lies that far from it, so it never overestimates). Returns (came, the target
    reached or None)."""
    blocked, occupied = grid.blocked, grid.occupied
    H, W = blocked.shape
    leave = grid.grown_m / grid.res + 1.0       # cells a blocked start goes through to leave the margin

    def passable(cur, nr, nc) -> bool:
        if not blocked[nr, nc]:
            return True
        return bool(blocked[cur]) and not occupied[nr, nc] and math.hypot(nr - s[0], nc - s[1]) <= leave

    def h(r, c) -> float:
        return max(0.0, math.hypot(r - toward[0], c - toward[1]) - near)
    best = {s: 0.0}
    came: dict = {}
    heap = [(h(*s), 0.0, s)]
    while heap:
        _, cost, cur = heapq.heappop(heap)
        if cur in targets:
            return came, cur
        if cost > best.get(cur, math.inf):
            continue
        for dr, dc, step in _STEPS:
            nr, nc = cur[0] + dr, cur[1] + dc
            if not (0 <= nr < H and 0 <= nc < W) or not passable(cur, nr, nc):
                continue
            if dr and dc and not (passable(cur, cur[0] + dr, cur[1]) and passable(cur, cur[0], cur[1] + dc)):
                continue                                  # no corner cutting
            nxt = (nr, nc)
            c2 = cost + step
            if c2 < best.get(nxt, math.inf):
                best[nxt] = c2
                came[nxt] = cur
                heapq.heappush(heap, (c2 + h(nr, nc), c2, nxt))
    return came, None


def _waypoints(grid: NavGrid, start_xz, came: dict, s, g, end) -> list:
    """The searched cells from ``s`` to ``g`` thinned to waypoints, from ``start_xz`` to ``end``."""
    cells = [g]
    while cells[-1] != s:
        cells.append(came[cells[-1]])
    cells.reverse()
    keep = _thin(grid, cells)
    return [tuple(start_xz)] + [grid.centre(*c) for c in keep[1:-1]] + [tuple(end)]


def _line_free(grid: NavGrid, a, b) -> bool:
    n = int(max(abs(b[0] - a[0]), abs(b[1] - a[1]))) * 2 + 1
    for t in np.linspace(0.0, 1.0, n):
        r, c = int(round(a[0] + t * (b[0] - a[0]))), int(round(a[1] + t * (b[1] - a[1])))
        if grid.blocked[r, c]:
            return False
    return True


def _thin(grid: NavGrid, cells: list) -> list:
    """Keep the cells where the straight line from the last kept one would cross a blocked cell."""
    if len(cells) <= 2:
        return cells
    out = [cells[0]]
    i = 0
    while i < len(cells) - 1:
        j = len(cells) - 1
        if grid.blocked[cells[i]]:      # leaving a blocked start: follow the search's cells
            j = i + 1
        while j > i + 1 and not _line_free(grid, cells[i], cells[j]):
            j -= 1
        out.append(cells[j])
        i = j
    return out


def path_length(path: list) -> float:
    return float(sum(math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in zip(path, path[1:])))
