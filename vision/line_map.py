"""Marvin's local map of 3D line segments, the DLM (section 11.2.1.1, Figs. 11.3 and 11.4).

The map is the centre of the fast sensor loop. Per stereo frame, given the
camera pose (VSLAM, odometry or the map's own localisation):

1. ``predict``: every map segment seen from the current pose, projected into
   the left image with its expected disparity (inverse depth is affine along
   the image of a 3D line, so the disparity at any point of the predicted
   segment is a linear interpolation of the endpoints').
2. ``prior_for``: guided matching. Each detected left segment that lies on a
   predicted one (direction within ``predict_angle_deg``, distance within
   ``predict_dist_px``) gets that prediction's disparity; the stereo matcher
   raises the score of the candidates agreeing with it (vision/line_segments.py).
3. ``update``: the reconstructed segments, moved into the world frame, are
   associated with map segments (direction, and the Mahalanobis distance of
   both endpoints across the line under both covariances), fused
   (information-weighted: the covariance-weighted mean of the line; the extent
   is where the observed endpoints reach along the line as it is now), or
   inserted as new candidates. Rival stereo hypotheses of one left segment
   are inserted together under one ``group`` and wait for another viewpoint
   to decide (Fig. 11.4). A segment takes at most one of several observations
   whose left-image lines are distinct parallel lines of the frame
   (``_exclusive``): two lines apart in one image are two 3D lines.
   Association and collinear merging look only at the map segments near
   what they update (``SegmentGrid``, a 3-D grid hash, once the map is large
   enough for it to pay), so their work is bounded by what is in view, not
   by the size of the map.

Verification rule (the chapter: correct matches stay close to their true
position from every viewpoint, false matches move with the viewpoint): a
segment is *verified* once it has been re-observed from ``verify_views``
distinct viewpoints (camera centres at least ``view_baseline_m`` apart, or
headings ``view_angle_deg`` apart), or, when it was never one of several rival
matches, re-observed ``verify_views`` times from two viewpoints whose rays to
it differ enough that a false match ``ghost_error_m`` off along its ray would
have left the association gate (``separating_views``). Verifying one
hypothesis deletes its rivals.
A candidate that the prediction says should be visible (in range, long enough
in the image, steep enough to the epipolar lines to be reconstructed) but is
not re-observed collects a miss; ``miss_limit`` misses before verification
delete it. A verified segment is deleted once its misses exceed
``verified_miss_factor`` x its support (the object moved).

Everything here is pure: numbers in, numbers out, no I/O (vision/line_map_io.py
reads and writes map files).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from itertools import chain
from typing import Optional

import numpy as np

from vbnav.vision.line_projection import in_view_reach, project_segments
from vbnav.vision.line_segments import FLAT, STANDING, Segments2D, Segments3D, grey
from vbnav.vision.line_sighting import (HYPOTHESIS_SIGMA_M, HorizontalFix, Keyframe, distinct_views,
                                        same_viewpoint, sight_hypotheses, viewpoint)

CHI2_3_99 = 11.34        # 99 % quantile of chi-square with 3 degrees of freedom
CHI2_1_99 = 6.63         # ... with 1 (a height)
ENDS_KEPT = 64           # observations' endpoints kept per segment for its extent (_bound_ends)
ALONG_VAR = 1.0          # m^2 added along a line: positions along it carry no information about the line
ASSOC_PERP_M = 0.5       # association's coarse gate: both endpoints of an observation within this of the map line
MERGE_PERP_M = 0.2       # merging's coarse gate: both endpoints of the other piece within this of the line
# A candidate's view log is exact for its first VIEW_LOG_EXACT views (a candidate is verified or pruned long
# before: 3 distinct viewpoints 0.15 m apart are 0.3 m of driving, 9 frames at 0.5 m/s and 15 Hz); past them
# a view the same viewpoint as a logged one is not logged, so a parked robot's log stops growing.
VIEW_LOG_EXACT = 64
# LineMap's per-segment state: one row per map segment in each of these arrays. ``_insert`` appends to and
# ``_remove`` drops from every one of them through this tuple, so a new per-segment array is named once here
# (tests/test_line_map.py checks that every array field of a built map is listed). The per-segment lists
# (``views``, and the derived ``view_log``, ``ends`` and ``serial``) have their own rules there.
SEGMENT_ARRAYS = ("P", "info", "info_vec", "cov", "anchor", "anchor_cov", "support", "misses", "verified",
                  "group", "ids", "hypothesis", "ambiguous", "stance_votes")
GRID_CELL_M = 0.6        # the spatial hash's cell: about the association reach (hypot(0.3, 0.5) m)
GRID_MIN_SEGMENTS = 10000  # below this the update scans the map (boxes, then directions): cheaper (see _near)
_CELL_OFFSET = 1 << 19   # cell coordinates are packed as 20-bit fields (+-300 km at 0.6 m), then 2 bits of class


class SegmentGrid:
    """A uniform 3-D grid hash of the map's segments, so the update looks only at the segments near what it
    is updating and roughly parallel to it, not at the whole map.

    A segment is listed in every cell its bounding box touches (the box of its estimate and its anchor: the
    association compares observations with the anchor of a candidate), under its direction class (the axis
    its direction is nearest to; both the estimate's and the anchor's). Entries are the segments' serial
    numbers (stable while other segments are removed; removed ones are dropped when a query meets them).
    A segment that grows, moves or turns is listed in the cells and classes it now reaches as well, so its
    listing always covers it. ``near`` returns every segment whose box comes within ``r`` of a query box
    in the classes asked for: a superset of the segments within ``r`` of the query segment and within the
    angle gate of it. The gates that follow are exact, so restricting them to this set changes nothing but
    the work.
    """

    def __init__(self, cell: float = GRID_CELL_M):
        self.cell = cell
        self.cells: dict = {}
        self.lo = np.zeros((0, 3), np.int64)     # per map segment, the cell range and classes it is listed in
        self.hi = np.zeros((0, 3), np.int64)
        self.mask = np.zeros(0, np.int64)
        self.entries = 0
        self.live_entries = 0

    @staticmethod
    def _box_cells(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """All cells of the integer boxes [lo, hi] (B, 3): (owner box, cell coordinates (E, 3))."""
        dims = np.maximum(hi - lo + 1, 0)
        n = dims.prod(axis=1)
        owner = np.repeat(np.arange(len(n)), n)
        local = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        dy, dz = dims[owner, 1], dims[owner, 2]
        off = np.column_stack((local // (dy * dz), (local // dz) % dy, local % dz))
        return owner, lo[owner] + off

    @staticmethod
    def _keys(owner: np.ndarray, c: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(owner, key) of every cell c (E, 3) in every class of its owner's class mask."""
        c = c + _CELL_OFFSET
        base = (c[:, 0] << 42) | (c[:, 1] << 22) | (c[:, 2] << 2)
        parts = [(owner[sel], base[sel] | b) for b in range(3) for sel in [(mask[owner] >> b) & 1 == 1]]
        return np.concatenate([o for o, _ in parts]), np.concatenate([k for _, k in parts])

    def _range(self, lo: np.ndarray, hi: np.ndarray, r: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        return (np.floor((lo - r) / self.cell).astype(np.int64), np.floor((hi + r) / self.cell).astype(np.int64))

    def add(self, serial: np.ndarray, lo: np.ndarray, hi: np.ndarray, mask: np.ndarray) -> None:
        """New segments (appended to the map) with their bounding boxes (n, 3) and class masks (n,)."""
        clo, chi = self._range(lo, hi)
        self.lo = np.concatenate((self.lo, clo))
        self.hi = np.concatenate((self.hi, chi))
        self.mask = np.concatenate((self.mask, mask))
        owner, c = self._box_cells(clo, chi)
        self._list(serial, *self._keys(owner, c, mask))

    def grow(self, pos: np.ndarray, serial: np.ndarray, lo: np.ndarray, hi: np.ndarray, mask: np.ndarray) -> None:
        """Segments at map positions ``pos`` that changed: list them in the cells and classes they now reach."""
        clo, chi = self._range(lo, hi)
        olo, ohi, omask = self.lo[pos], self.hi[pos], self.mask[pos]
        out = (clo < olo).any(axis=1) | (chi > ohi).any(axis=1) | (mask & ~omask != 0)
        if not out.any():
            return
        pos, serial, olo, ohi, omask = pos[out], serial[out], olo[out], ohi[out], omask[out]
        nlo, nhi, nmask = np.minimum(clo[out], olo), np.maximum(chi[out], ohi), mask[out] | omask
        owner, c = self._box_cells(nlo, nhi)
        new_cell = ((c < olo[owner]) | (c > ohi[owner])).any(axis=1)
        # Classes already listed: the new cells only; a new class: every cell of the grown box.
        o1, k1 = self._keys(owner[new_cell], c[new_cell], omask)
        o2, k2 = self._keys(owner, c, nmask & ~omask)
        self._list(serial, np.concatenate((o1, o2)), np.concatenate((k1, k2)))
        self.lo[pos], self.hi[pos], self.mask[pos] = nlo, nhi, nmask

    def _list(self, serial: np.ndarray, owner: np.ndarray, keys: np.ndarray) -> None:
        cells = self.cells
        for k, s in zip(keys.tolist(), serial[owner].tolist()):
            cells.setdefault(k, []).append(s)
        self.entries += len(owner)
        self.live_entries += len(owner)

    def remove(self, keep: np.ndarray) -> None:
        gone = ~keep
        ncls = sum((self.mask[gone] >> b) & 1 for b in range(3))
        self.live_entries -= int((np.maximum(self.hi[gone] - self.lo[gone] + 1, 0).prod(axis=1) * ncls).sum())
        self.lo, self.hi, self.mask = self.lo[keep], self.hi[keep], self.mask[keep]

    def near(self, serials: np.ndarray, lo: np.ndarray, hi: np.ndarray, r: float,
             mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(q, pos): the map segments (positions; ``serials`` the map's serial numbers, ascending) listed in
        a cell within ``r`` of query box q (Q, 3) under one of the classes of ``mask`` (Q,), each pair
        once, sorted by q then position."""
        owner, keys = self._keys(*self._box_cells(*self._range(lo, hi, r)), mask)
        get = self.cells.get
        lists = [get(k, ()) for k in keys.tolist()]
        n = np.fromiter(map(len, lists), np.int64, len(lists))
        found = np.fromiter(chain.from_iterable(lists), np.int64, int(n.sum()))
        q = np.repeat(owner, n)
        if len(serials) == 0 or len(found) == 0:
            return np.zeros(0, int), np.zeros(0, int)
        pos = np.minimum(np.searchsorted(serials, found), len(serials) - 1)
        ok = serials[pos] == found
        m = len(serials)
        pair = _sorted_unique(q[ok] * m + pos[ok])
        return pair // m, pair % m


def direction_classes(P: np.ndarray) -> np.ndarray:
    """(K,) bit mask of the axis each segment (K, 2, 3) is nearest to (bit 0 x, 1 y, 2 z)."""
    return np.left_shift(1, np.abs(P[:, 1] - P[:, 0]).argmax(axis=1)).astype(np.int64)


def classes_within(d: np.ndarray, angle_deg: float) -> np.ndarray:
    """(K,) bit mask of the direction classes holding some direction within ``angle_deg`` of the unit
    directions d (K, 3) or their opposites. A direction u within the angle differs from d by at most the
    chord c = 2 sin(angle / 2) in every component, so it can be nearest to axis b only if
    max|d| - |d_b| <= 2 c."""
    a = np.abs(d)
    c = 2.0 * math.sin(math.radians(angle_deg) / 2.0)
    near = (a.max(axis=1, keepdims=True) - a) <= 2.0 * c + 1e-9
    return (near * np.array([1, 2, 4])).sum(axis=1).astype(np.int64)


@dataclass(frozen=True)
class MapParams:
    max_range_m: float = 3.0           # insert/predict only nearer segments (depth sigma grows as z^2)
    min_range_m: float = 0.35          # nearer "segments" are mostly high-order false matches (largest disparities)
    min_length_m: float = 0.05
    assoc_angle_deg: float = 6.0
    assoc_extra_m: float = 0.004       # added to both covariances (calibration/pose error), per axis sigma
    overlap_margin_m: float = 0.3      # collinear pieces this far apart along the line are one edge (LSD breaks edges)
    merge_gap_m: float = 0.15          # map segments on one line (covariance gate) with a gap up to this merge
    verify_views: int = 3
    view_baseline_m: float = 0.15
    view_angle_deg: float = 10.0
    miss_limit: int = 4
    verified_miss_factor: float = 3.0
    predict_angle_deg: float = 5.0
    predict_dist_px: float = 3.0
    predict_min_length_px: float = 25.0
    min_epipolar_angle_deg: float = 20.0
    prior_sigma_floor_px: float = 0.3
    # Two viewpoints verify an unambiguous candidate (never one of several rival matches) re-observed
    # verify_views times when a false match this far off along its ray would have moved out of the
    # association gate between them (separating_views; 0: never). The false-segment distance of the scoring.
    ghost_error_m: float = 0.05
    # A horizontal hypothesis (a box's top or lower edge) is looked for in the left segments of the
    # keyframes (``keyframes``), its height measured on its corners' vertical lines (vision/line_sighting.py), with this sigma of
    # an image line across itself (LineParams.sigma_perp_px; 0: never).
    sight_sigma_px: float = 0.3
    # A box's top may lie this far above its hypothesis (the corners' LSD pieces end early: the abstraction's
    # height_tol_m), searched in a keyframe's image (``line_sighting.ridge_sighting``), whose ridge must stand this many
    # sigma of the gradient's noise (LineParams.vertical_k_sigma).
    sight_up_m: float = 0.3
    ridge_k_sigma: float = 3.0
    # Two observations of one frame whose left-image lines are parallel (``assoc_angle_deg``), overlap along
    # the line and lie apart across it by more than the 1-dof 99 % gate of the difference of two image
    # lines, sqrt(chi2_1,99 %) sqrt(2) x this sigma (LineParams.sigma_perp_px: 1.1 px), are two distinct
    # lines, whatever the 3D gates say: a map segment takes at most one of them (``_exclusive``; 0: off).
    line_sigma_px: float = 0.3

    def __post_init__(self):
        """Refuse a value the map cannot work with (a map file's params are applied to the mapping that goes
        on from it): ValueError naming the field and the range."""
        for name, low, high, low_open in _PARAM_RANGES:
            v = getattr(self, name)
            if not (math.isfinite(v) and (v > low if low_open else v >= low) and v <= high):
                raise ValueError(f"{name}: expected {'>' if low_open else '>='} {low:g}"
                                 + (f" and <= {high:g}" if math.isfinite(high) else "") + f", got {v!r}")
        if not self.min_range_m < self.max_range_m:
            raise ValueError(f"min_range_m {self.min_range_m!r} must be below max_range_m {self.max_range_m!r}")
        if int(self.verify_views) != self.verify_views or int(self.miss_limit) != self.miss_limit:
            raise ValueError(f"verify_views and miss_limit are counts, got {self.verify_views!r} and "
                             f"{self.miss_limit!r}")


# (field, lowest, highest, lowest excluded): what each MapParams value means allows. 0 is "off" for
# ghost_error_m, sight_sigma_px and line_sigma_px (their comments); angles to a line lie within 90 deg.
_INF = math.inf
_PARAM_RANGES = (
    ("max_range_m", 0.0, _INF, True), ("min_range_m", 0.0, _INF, False), ("min_length_m", 0.0, _INF, False),
    ("assoc_angle_deg", 0.0, 90.0, True), ("assoc_extra_m", 0.0, _INF, False),
    ("overlap_margin_m", 0.0, _INF, False), ("merge_gap_m", 0.0, _INF, False), ("verify_views", 1, _INF, False),
    ("view_baseline_m", 0.0, _INF, True), ("view_angle_deg", 0.0, 180.0, True), ("miss_limit", 1, _INF, False),
    ("verified_miss_factor", 1.0, _INF, False), ("predict_angle_deg", 0.0, 90.0, True),
    ("predict_dist_px", 0.0, _INF, True), ("predict_min_length_px", 0.0, _INF, False),
    ("min_epipolar_angle_deg", 0.0, 90.0, True), ("prior_sigma_floor_px", 0.0, _INF, True),
    ("ghost_error_m", 0.0, _INF, False), ("sight_sigma_px", 0.0, _INF, False), ("sight_up_m", 0.0, _INF, False),
    ("ridge_k_sigma", 0.0, _INF, True), ("line_sigma_px", 0.0, _INF, False),
)


@dataclass
class Prediction:
    """Map segments expected in the current view: ``index`` into the map's arrays, the clipped left-image
    segments ``xy`` (K, 4), the disparity at their endpoints ``disparity`` (K, 2) and its sigma (K,)."""

    index: np.ndarray
    xy: np.ndarray
    disparity: np.ndarray
    sigma: np.ndarray

    def __len__(self) -> int:
        return len(self.index)


@dataclass
class UpdateStats:
    observed: int = 0
    fused: int = 0
    inserted: int = 0
    verified: int = 0
    pruned: int = 0
    rivals_dropped: int = 0
    merged: int = 0
    # (observation or segment, map segment) pairs the association and the merging looked at: bounded by
    # what is near this frame's observations, whatever the size of the map.
    pairs: int = 0


@dataclass
class LineMap:
    """The DLM: M segments as parallel arrays (world frame: x right, y down, z forward, floor y = 0)."""

    params: MapParams = field(default_factory=MapParams)
    P: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))        # endpoints
    info: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3, 3)))  # summed information per endpoint
    info_vec: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))
    cov: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3, 3)))   # inverse of info, kept in step
    # Where a candidate was first seen: until verified it is re-observed only there, so a false match that
    # drifts with the viewpoint cannot drag a fused estimate along with it frame by frame.
    anchor: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3)))
    anchor_cov: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 3, 3)))
    support: np.ndarray = field(default_factory=lambda: np.zeros(0, int))     # observations fused
    misses: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    verified: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    group: np.ndarray = field(default_factory=lambda: np.zeros(0, int))       # rival hypotheses share one
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    hypothesis: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # inserted from an abstraction
    # Inserted as one of several rival matches of a left segment, or merged with one: the false matches of a
    # periodic texture lie on a lattice of ray crossings, which another viewpoint re-observes within the
    # gate, so two viewpoints do not verify it (separating_views); it needs verify_views of them.
    ambiguous: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    # Per segment: how many of its floor-line observations stood (a face rising from the line) and how many
    # were flat (floor beyond it), vision/line_floor.py. A foot and a texture line are never one segment.
    stance_votes: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), int))
    views: list = field(default_factory=list)        # per segment: list of (x, y, z, heading) viewpoints
    # Per unverified segment: the viewpoints it was observed from, (n, 5) [frame, x, y, z, heading] in time
    # order; its distinct views (``views``) are those apart from every earlier distinct one in that order, so
    # they do not depend on which of two merged pieces survives (``_merge_views``). Past VIEW_LOG_EXACT
    # views, one the same viewpoint as a logged one is not logged (a parked robot: the log is bounded by
    # where the segment was seen from, not by how long); a verified segment's log is dropped. Frame -1:
    # unknown (a map file).
    view_log: list = field(default_factory=list, repr=False)
    # Per segment: the endpoints of every observation fused or merged into it ((N, 2, 3), world frame; a
    # hypothesis's or a loaded map's extent counts as one). Its extent is where they reach along its
    # current line (``_extent``), not the union of its earlier estimates.
    ends: list = field(default_factory=list, repr=False)
    # Keyframes: the left segments (xy (N, 4)) and camera pose (R_wc, t_wc) of frames a distinct viewpoint
    # apart (``_add_view``'s rule), while their camera lies within ``max_range_m`` of the current one.
    keyframes: list = field(default_factory=list, repr=False)     # of line_sighting.Keyframe
    next_id: int = 0
    next_group: int = 0
    frames: int = 0
    _pairs = 0                                       # work counter of the current update (UpdateStats.pairs)
    _stops = np.zeros((0, 3))                        # this update's corner feet (_corner_feet)
    _corners = np.zeros(0, bool)                     # which of them two faces' feet end at (_corner_feet)
    # The spatial hash of the segments (SegmentGrid) and the serial numbers it knows them by. Derived
    # state: rebuilt from the arrays when they were replaced from outside (a map file, a test).
    serial: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)
    next_serial: int = field(default=0, repr=False)
    grid: Optional[SegmentGrid] = field(default=None, repr=False)
    grid_min_segments: int = field(default=GRID_MIN_SEGMENTS, repr=False)

    def __len__(self) -> int:
        return len(self.P)

    # ------------------------------------------------------------------ geometry
    @property
    def direction(self) -> np.ndarray:
        return _directions(self.P)

    @property
    def length(self) -> np.ndarray:
        return _norms(self.P[:, 1] - self.P[:, 0], axis=1)

    def covariance(self) -> np.ndarray:
        """(M, 2, 3, 3) endpoint covariances across the line (the along-line part is the extent, not fused)."""
        return self.cov

    def verified_segments(self) -> np.ndarray:
        return self.P[self.verified]

    def structure(self) -> np.ndarray:
        """(K, 2, 3) the verified segments objects are made of (vision/line_abstraction.py): all but the floor
        lines seen flat, with floor beyond them too (a texture line or a marking, not a box's foot: World.room
        seed 5's box_b footprint ran 0.46 m past its corner along a flat texture line 5 cm off its foot)."""
        return self.P[self.verified & (self.stance(slice(None)) != FLAT)]

    # ---------------------------------------------------------------- prediction
    def predict(self, R_wc: np.ndarray, t_wc: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                baseline: float, width: int, height: int, which: Optional[np.ndarray] = None) -> Prediction:
        """The map segments (``which``: a bool mask; default the verified ones and the abstraction's hypotheses)
        seen from camera pose (R_wc, t_wc), clipped to the image and to ``max_range_m``."""
        sel = (self.verified | self.hypothesis) if which is None else which
        idx = np.nonzero(sel)[0]
        # A point in the image and within max_range_m in depth is within max_range_m sqrt(1 + a^2 + b^2) of
        # the camera (a, b: the image's half-extents over the focal lengths): segments whose boxes lie
        # farther cannot be predicted, and are not projected (what a long drive left behind).
        reach = in_view_reach(fx, fy, cx, cy, width, height, self.params.max_range_m)
        P0, P1 = self.P[idx, 0], self.P[idx, 1]
        gap = np.maximum(np.maximum(np.minimum(P0, P1) - t_wc, t_wc - np.maximum(P0, P1)), 0.0)
        idx = idx[np.einsum("ki,ki->k", gap, gap) <= reach ** 2]
        empty = Prediction(np.zeros(0, int), np.zeros((0, 4)), np.zeros((0, 2)), np.zeros(0))
        if len(idx) == 0:
            return empty
        pr = project_segments(self.P[idx], R_wc, t_wc, fx, fy, cx, cy, width, height, self.params.max_range_m,
                              self.params.predict_min_length_px)
        keep = pr.keep
        fb = fx * baseline
        disp = pr.inv_depth * fb
        # Sigma of the predicted disparity from the map's covariance along the viewing direction.
        cov = self.covariance()[idx[keep]]                         # (K, 2, 3, 3) world
        ray = np.einsum("ij,kj->ki", R_wc, np.column_stack((np.zeros((keep.sum(), 2)), np.ones(keep.sum()))))
        var_ray = np.einsum("ki,keij,kj->ke", ray, cov, ray).max(axis=1)
        sig = np.maximum(disp.max(axis=1) ** 2 / fb * np.sqrt(var_ray), self.params.prior_sigma_floor_px)
        return Prediction(idx[keep], pr.xy, disp, sig)

    def prior_for(self, segs: Segments2D, pred: Prediction) -> np.ndarray:
        """(N, 2): predicted disparity at each detected left segment's midpoint and its sigma (NaN: none)."""
        out = np.full((len(segs), 2), np.nan)
        if len(segs) == 0 or len(pred) == 0:
            return out
        ok, dist, s = self._support_matrix(segs, pred)
        cost = np.where(ok, dist, np.inf)
        k = cost.argmin(axis=1)
        has = np.isfinite(cost[np.arange(len(segs)), k])
        sk = np.clip(s[np.arange(len(segs)), k], 0.0, 1.0)
        d = pred.disparity[k, 0] + (pred.disparity[k, 1] - pred.disparity[k, 0]) * sk
        out[has, 0] = d[has]
        out[has, 1] = pred.sigma[k][has]
        return out

    def supported(self, pred: Prediction, segs: Segments2D) -> np.ndarray:
        """(K,) bool: some detected segment lies along each predicted one (direction and distance gates)."""
        if len(segs) == 0 or len(pred) == 0:
            return np.zeros(len(pred), bool)
        # Anywhere along the predicted line's extension counts: LSD finds other pieces of a textured edge.
        return self._support_matrix(segs, pred, -1.0, 2.0)[0].any(axis=0)

    def _support_matrix(self, segs: Segments2D, pred: Prediction, s_lo: float = -0.1,
                        s_hi: float = 1.1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(N, K) bool: detected segment n lies along predicted segment k; with the distances (px) and the
        position of n's midpoint along k (0..1)."""
        mid = 0.5 * (segs.xy[:, 0:2] + segs.xy[:, 2:4])
        a, ab = pred.xy[:, 0:2], pred.xy[:, 2:4] - pred.xy[:, 0:2]
        L2 = np.maximum((ab ** 2).sum(axis=1), 1e-9)
        L = np.sqrt(L2)
        # Position along and distance across each predicted line as (N, K) matrix products (no (N, K, 2)
        # temporaries: this runs for every detected x predicted segment, every frame).
        s = (mid @ ab.T - (a * ab).sum(axis=1)[None]) / L2[None]
        nrm = np.column_stack((ab[:, 1], -ab[:, 0]))
        dist = np.abs(mid @ nrm.T - (a * nrm).sum(axis=1)[None]) / L[None]
        cosang = np.abs(segs.direction @ (ab / L[:, None]).T)
        ok = ((dist <= self.params.predict_dist_px) & (s >= s_lo) & (s <= s_hi)
              & (cosang >= math.cos(math.radians(self.params.predict_angle_deg))))
        return ok, dist, s

    # -------------------------------------------------------------------- update
    def update(self, obs: Segments3D, R_wc: np.ndarray, t_wc: np.ndarray, pred: Optional[Prediction] = None,
               left: Optional[Segments2D] = None, image: Optional[np.ndarray] = None) -> UpdateStats:
        """Fuse one frame's 3D segments (left camera frame) seen from camera pose (R_wc, t_wc).

        pred: this frame's prediction of ALL map segments (``predict(..., which=all)``), used to count
        misses; None skips the miss bookkeeping. left: the frame's left-image segments; a predicted segment
        that some detected segment lies along is not missed even if stereo did not reconstruct it this time
        (LSD breaks textured edges into different pieces from frame to frame). image: the frame's left image,
        kept with a keyframe so a box's top or lower edge hypothesis can be looked for in its gradient
        (vision/line_sighting.py).
        """
        st = UpdateStats()
        self.frames += 1
        if left is not None and self.params.sight_sigma_px > 0:
            self._remember(left, R_wc, t_wc, image)
        self._pairs = 0
        p = self.params
        if len(obs):
            zc = obs.P[..., 2]
            keep = (zc.max(axis=1) <= p.max_range_m) & (zc.min(axis=1) >= p.min_range_m) & (_norms(obs.P[:, 1] - obs.P[:, 0], axis=1) >= p.min_length_m)
            obs = obs.subset(keep)
        Pw = obs.P @ R_wc.T + t_wc
        Cw = np.einsum("ij,kejl,ml->keim", R_wc, obs.cov, R_wc)
        view = viewpoint(R_wc, t_wc)
        st.observed = len(obs)
        seen = np.zeros(len(self), bool)
        # Rival hypotheses of one left segment: one group id per left segment with > 1 candidate.
        gid, ginv, gcount = np.unique(obs.group, return_inverse=True, return_counts=True)
        rival = gcount > 1
        new_gid = np.full(len(gid), -1)
        new_gid[rival] = self.next_group + np.arange(rival.sum())
        self.next_group += int(rival.sum())
        self._stops, self._corners = self._corner_feet()
        j = self._associate_and_fuse(Pw, Cw, view, obs.left_xy, obs.stance)
        fused = j >= 0
        seen[j[fused]] = True
        self._vote(j[fused], obs.stance[fused])
        st.fused = int(fused.sum())
        new_P, new_C, new_group = Pw[~fused], Cw[~fused], new_gid[ginv.reshape(-1)][~fused]
        new_stance = obs.stance[~fused]
        if pred is not None:
            if left is not None and len(pred):
                seen[pred.index[self.supported(pred, left)]] = True
            self._count_misses(pred, seen)
        touched = np.nonzero(seen)[0]
        if len(new_P):
            self._insert(new_P, new_C, new_group, view, stance=new_stance)
            st.inserted = len(new_P)
            touched = np.concatenate((touched, np.arange(len(self) - len(new_P), len(self))))
        # Merging, verification and pruning each decide which rows go; they are removed once, together
        # (removing copies every array of the map).
        st.merged, gone, grown = self._merge_collinear(touched)
        st.verified, st.rivals_dropped, drop = self._verify(gone, np.concatenate((touched, grown)).astype(int))
        st.pruned = self._prune(drop)
        st.pairs = self._pairs
        return st

    def _associate_and_fuse(self, Pw: np.ndarray, Cw: np.ndarray, view: np.ndarray,
                            xy: Optional[np.ndarray] = None, stance: Optional[np.ndarray] = None) -> np.ndarray:
        """Associate a frame's observations with the map as it stood before the frame, then fuse them;
        returns (K,) the segment each was fused into, or -1.

        xy: the observations' left-image lines (K, 4): a segment takes at most one of several that are
        distinct lines of this image (``_exclusive``). stance: the observations' (K,) (``_gate_pairs``).
        Each observation takes its best gated segment; several observations of one segment (LSD's pieces of
        one edge) fuse into it one after the other, in their order (``_fuse_all``).
        """
        out = np.full(len(Pw), -1)
        if len(self) == 0 or len(Pw) == 0:
            return out
        stance = np.zeros(len(Pw), np.int8) if stance is None else stance
        k_all, c_all, score_all = self._gate_pairs(Pw, Cw, stance)
        distinct = self._exclusive(xy)
        if distinct is not None:
            keep = self._resolve_exclusive(k_all, c_all, score_all, distinct)
            k_all, c_all = k_all[keep], c_all[keep]
        if len(k_all):
            best = np.r_[True, k_all[1:] != k_all[:-1]]           # sorted by observation, then score
            out[k_all[best]] = c_all[best]
        fused = np.nonzero(out >= 0)[0]
        self._fuse_all(out[fused], Pw[fused], Cw[fused])
        for j in out[fused].tolist():
            self._add_view(j, view)
        return out

    def _exclusive(self, xy: Optional[np.ndarray]) -> Optional[np.ndarray]:
        """(K, K) bool: observations' left-image lines xy (K, 4) that are two distinct lines of this image
        (``_distinct_lines`` either way round), apart by more than sqrt(chi2_1,99 % x 2) ``line_sigma_px``
        (1.1 px): the 99 % gate of the difference of two image lines' positions, each with that sigma across.
        None when off (no image lines, or ``line_sigma_px`` 0). Rivals of one left segment share its line
        (0 px apart): not distinct, their group decides between them."""
        p = self.params
        if xy is None or p.line_sigma_px <= 0 or len(xy) < 2:
            return None
        a, b = np.triu_indices(len(xy), 1)
        d = xy[:, 2:] - xy[:, :2]
        d = d / np.maximum(_norms(d, axis=1), 1e-12)[:, None]
        with np.errstate(invalid="ignore"):
            par = np.abs(np.einsum("ki,ki->k", d[a], d[b])) >= math.cos(math.radians(p.assoc_angle_deg))
        a, b = a[par], b[par]
        gate = math.sqrt(CHI2_1_99 * 2.0) * p.line_sigma_px
        ok = _distinct_lines(xy[a], xy[b], p.assoc_angle_deg, gate) | \
            _distinct_lines(xy[b], xy[a], p.assoc_angle_deg, gate)
        out = np.zeros((len(xy), len(xy)), bool)
        out[a[ok], b[ok]] = out[b[ok], a[ok]] = True
        return out

    @staticmethod
    def _resolve_exclusive(k_all: np.ndarray, c_all: np.ndarray, score_all: np.ndarray,
                           distinct: np.ndarray) -> np.ndarray:
        """(E,) bool: the gated pairs (sorted by observation, score) that stay when a segment takes at most one
        of several observations that are distinct lines of one image, the best by Mahalanobis distance; the
        others lose that segment and take their next best (or become candidates). Two parallel lines a few
        px apart are two 3D lines: at 3 m the floor-line covariance (3 mm of camera height common to every
        floor line of the frame) puts a line 10 cm off inside the 3D gate."""
        keep = np.ones(len(k_all), bool)
        while True:
            idx = np.nonzero(keep)[0]
            kk = k_all[idx]
            first = idx[np.r_[True, kk[1:] != kk[:-1]]] if len(idx) else idx     # each observation's best
            first = first[np.lexsort((score_all[first], c_all[first]))]          # by segment, then score
            bounds = np.r_[0, np.nonzero(np.diff(c_all[first]))[0] + 1, len(first)]
            lost = False
            for a in np.nonzero(np.diff(bounds) >= 2)[0].tolist():
                accepted: list = []
                for e in first[bounds[a]:bounds[a + 1]].tolist():
                    if accepted and distinct[k_all[e], k_all[accepted]].any():
                        keep[e], lost = False, True
                    else:
                        accepted.append(e)
            if not lost:
                return keep

    def _gate_pairs(self, Pw: np.ndarray, Cw: np.ndarray, stance: Optional[np.ndarray] = None):
        """The (observation, map segment) pairs that pass association, against the map as it is now.

        Gates: direction within ``assoc_angle_deg``; overlap along the line (``overlap_margin_m``) and both
        endpoints within 0.5 m of it; then the Mahalanobis distance of both endpoints across the line under
        both covariances (chi-square, 3 dof, 99 %), evaluated only for the pairs that pass the cheap gates.
        The pairs considered are those the spatial hash finds within the coarse gate's reach of each
        observation, hypot(``overlap_margin_m``, 0.5 m): a pair that passes the coarse gate has a point of
        the observation that near the map segment. stance: the observations' (K,): a foot's observation
        never pairs with a flat segment, nor a flat one with a foot (``stance``; unknown pairs with either).
        Returns (k, c, score) sorted by observation, score, segment (the score prefers verified segments,
        then the smaller distance).
        """
        p = self.params
        none = np.zeros(0, int)
        reach = math.hypot(p.overlap_margin_m, ASSOC_PERP_M) + 1e-6
        t_obs = _directions(Pw)
        k, c = self._near(Pw.min(axis=1), Pw.max(axis=1), reach, t_obs,
                          lambda i: _directions(np.where(self.verified[i, None, None], self.P[i], self.anchor[i])))
        self._pairs += len(k)
        ref = np.where(self.verified[c, None, None], self.P[c], self.anchor[c])
        dirs = ref[:, 1] - ref[:, 0]
        lengths = _norms(dirs, axis=1)
        dirs = dirs / np.maximum(lengths, 1e-12)[:, None]
        par = np.abs(np.einsum("ki,ki->k", t_obs[k], dirs)) >= math.cos(math.radians(p.assoc_angle_deg))
        if stance is not None:
            par &= stance[k] * self.stance(c) >= 0
        k, c, ref, dirs, lengths = k[par], c[par], ref[par], dirs[par], lengths[par]
        # Coarse gate: overlap along the map line and both endpoints within 0.5 m of it.
        a, d, ext = ref[:, 0], dirs, lengths
        s_obs = np.einsum("kei,ki->ke", Pw[k] - a[:, None], d)                        # (P, 2) along the line
        lo, hi = s_obs.min(axis=1, initial=np.inf), s_obs.max(axis=1, initial=-np.inf)
        margin = np.full(len(k), p.overlap_margin_m)
        if stance is not None:
            margin[_one_stance_unknown(stance[k], self.stance(c))] = 0.0
        overlap = (hi >= -margin) & (lo <= ext + margin)
        r = Pw[k] - (a[:, None] + s_obs[..., None] * d[:, None])                       # (P, 2, 3)
        coarse = overlap & (_norms(r, axis=2).max(axis=1, initial=0.0) < ASSOC_PERP_M)
        k, c, r, d = k[coarse], c[coarse], r[coarse], d[coarse]
        if len(k) and len(self._stops):
            apart = self._across_a_corner(ref[coarse], Pw[k])
            k, c, r, d = k[~apart], c[~apart], r[~apart], d[~apart]
        if len(k) == 0:
            return none, none, np.zeros(0)
        Cm = np.where(self.verified[c, None, None, None], self.cov[c], self.anchor_cov[c])
        extra = p.assoc_extra_m ** 2 * np.eye(3)
        # Match the observation's endpoints to the map's perpendicular covariances by the nearer map end.
        S = ((Cm[:, 0] + Cm[:, 1]) / 2)[:, None] + Cw[k] + extra + ALONG_VAR * np.einsum("ki,kj->kij", d, d)[:, None]
        m2 = np.einsum("kei,keij,kej->ke", r, np.linalg.inv(S), r)
        ok = (m2 <= CHI2_3_99).all(axis=1)
        k, c, m2 = k[ok], c[ok], m2[ok]
        score = m2.sum(axis=1) - 1e3 * self.verified[c]
        order = np.lexsort((c, score, k))
        return k[order], c[order], score[order]

    def _fuse_all(self, j: np.ndarray, Pw: np.ndarray, Cw: np.ndarray) -> None:
        """Fuse observations (K, 2, 3) into map segments j (K,); several into one segment fuse one after
        the other in their order (each round fuses at most one observation per segment, vectorised)."""
        rank = np.zeros(len(j), int)
        order = np.argsort(j, kind="stable")
        js = j[order]
        start = np.r_[0, np.nonzero(js[1:] != js[:-1])[0] + 1] if len(js) else np.zeros(0, int)
        run_start = np.repeat(start, np.diff(np.r_[start, len(js)]))
        rank[order] = np.arange(len(js)) - run_start
        for rnd in range(int(rank.max()) + 1 if len(j) else 0):
            sel = rank == rnd
            self._fuse_distinct(j[sel], Pw[sel], Cw[sel])

    def _fuse_distinct(self, j: np.ndarray, Pw: np.ndarray, Cw: np.ndarray) -> None:
        """Fuse one observation into each of the distinct map segments j (information form)."""
        t = _directions(self.P[j])                                                      # (K, 3)
        flip = np.einsum("ki,ki->k", Pw[:, 1] - Pw[:, 0], t) < 0
        if flip.any():
            Pw, Cw = Pw.copy(), Cw.copy()
            Pw[flip], Cw[flip] = Pw[flip, ::-1], Cw[flip, ::-1]
        W = np.linalg.inv(Cw + ALONG_VAR * np.einsum("ki,kj->kij", t, t)[:, None])       # (K, 2, 3, 3)
        self.info[j] += W
        self.info_vec[j] += np.einsum("keij,kej->kei", W, Pw)
        # Fused line (information-weighted), extent = what was seen along it.
        self.cov[j] = np.linalg.inv(self.info[j])
        q = np.einsum("keij,kej->kei", self.cov[j], self.info_vec[j])                  # (K, 2, 3)
        tq = q[:, 1] - q[:, 0]
        tq = tq / np.maximum(_norms(tq, axis=1), 1e-12)[:, None]
        self._ends_in_step()
        for k, jj in enumerate(j.tolist()):
            self.ends[jj] = np.concatenate((self.ends[jj], Pw[k:k + 1]))
        self.P[j] = self._extent(j, q[:, 0], tq)
        self.support[j] += 1
        self.misses[j] = np.maximum(0, self.misses[j] - 1)
        self._moved(j)

    # ------------------------------------------------------------ collinear merging
    def _merge_collinear(self, touched: np.ndarray, partners: Optional[np.ndarray] = None) -> tuple[int, np.ndarray, list]:
        """Fuse map segments that lie on one 3D line and overlap or nearly meet along it (LSD breaks a
        textured edge into pieces, differently in every frame): the pieces' observations are repeated
        observations of one edge, so their information, support and viewpoints add up, and the edge is
        verified from the viewpoints of all its pieces. Only pairs with a segment ``touched`` this frame are
        tested (the others were tested when they last changed); ``partners`` (bool per segment, default all)
        limits what they may merge with. Returns the number of merges, the segments merged into others (to
        be removed) and those that absorbed one.

        In rounds, as the sequential rule it batches (the newest segment first takes its best partner):
        every pair that may merge is scored in one batch (``_partner_scores``); then, newest segment first
        (the highest row: this frame's pieces are inserted last), each segment takes its best partner
        unless one of the two merged already in this round, in which case it waits for the next; the
        segments that grew are paired with what is near them, both ways round, for the next round, until
        no pair merges. One batch a round instead of a search per segment (~30 a frame, ~60 on the patrol's
        closing frames): merging went from 17.8-28.3 ms at p95 to 6.8-11.4 (benchmarks/line_map.py --laps 3,
        lap 3, runs alternating with the search)."""
        merged = 0
        alive = np.ones(len(self), bool)
        D, L = self.direction, self.length       # kept in step with the merges below
        touched = np.asarray(touched, int)
        grown: list = []
        if len(touched) == 0 or len(self) < 2:
            return 0, ~alive, grown
        allowed = np.ones(len(self), bool) if partners is None else partners
        i, m = self._merge_pairs(touched, alive & allowed, D, L)
        while len(i):
            score = self._partner_scores(i, m, D, L)
            ok = np.isfinite(score)
            if not ok.any():
                break
            i, m, score = i[ok], m[ok], score[ok]
            used = np.zeros(len(self), bool)
            kept: list = []
            tried: set = set()
            for k in np.lexsort((m, score, -i)).tolist():       # newest first, then best first
                a, b = int(i[k]), int(m[k])
                if a in tried:
                    continue
                tried.add(a)                                     # its best partner: taken, or it waits
                if used[a] or used[b]:
                    continue
                used[a] = used[b] = True
                keep, gone = (a, b) if self._rank(a) >= self._rank(b) else (b, a)
                self._absorb(keep, gone)
                d = self.P[keep, 1] - self.P[keep, 0]
                L[keep] = np.linalg.norm(d)
                D[keep] = d / max(L[keep], 1e-12)
                alive[gone] = False
                kept.append(keep)
                merged += 1
            grown.extend(k for k in kept if k not in grown)
            q, r = self._merge_pairs(np.array(kept), alive & allowed, D, L)   # a grown one may reach another
            i, m = np.concatenate((q, r)), np.concatenate((r, q))
        return merged, ~alive, [k for k in grown if alive[k]]

    def _merge_pairs(self, idx: np.ndarray, alive: np.ndarray, D: np.ndarray, L: np.ndarray) -> tuple:
        """(i, m): segments idx paired with the alive segments that may be their pieces in merging, by a
        cheap vectorised prefilter: parallel, the midpoint near i's line and within its extent widened by
        the gap. Every pair ``_partner_scores`` accepts passes it (both endpoints near i's line put the
        midpoint there; overlapping or within the gap puts it within the extent), and is among the
        segments the spatial hash finds within the reach below: the midpoint is within MERGE_PERP_M
        across and 0.5 L + merge_gap_m along, so walking from it along the segment (at most
        assoc_angle_deg off) reaches a point within merge_gap_m + MERGE_PERP_M of segment i plus the
        segment's own margin (the hash lists it in a box widened by that, see _bbox)."""
        p = self.params
        ang = math.radians(p.assoc_angle_deg)
        reach = p.merge_gap_m + MERGE_PERP_M + 1e-6
        lo, hi, _ = self._bbox(idx)
        k, m = self._near(lo, hi, reach, D[idx], lambda j: D[j])
        self._pairs += len(k)
        i = idx[k]
        eps = 1e-9
        dot = np.abs(np.einsum("ki,ki->k", D[i], D[m]))
        ok = (dot >= math.cos(ang) - eps) & (m != i) & alive[m]
        i, m = i[ok], m[ok]
        rel = 0.5 * (self.P[m, 0] + self.P[m, 1]) - self.P[i, 0]
        s = (rel * D[i]).sum(axis=1)
        perp = _norms(rel - s[:, None] * D[i], axis=1)
        half = 0.5 * L[m] + p.merge_gap_m
        near = (perp < MERGE_PERP_M + eps) & (s >= -half - eps) & (s <= L[i] + half + eps)
        return i[near], m[near]

    def _partner_scores(self, i: np.ndarray, m: np.ndarray, t: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        """(K,) of segment pairs (i[k], m[k]): m's Mahalanobis distances across i's line (both endpoints,
        summed) when m may be merged into i: direction within ``assoc_angle_deg``, not a rival of one left
        segment, overlapping i or ending within ``merge_gap_m`` of it along its line, both endpoints within
        ``MERGE_PERP_M`` across it and within the chi-square gate of both covariances; inf when not."""
        p = self.params
        out = np.full(len(i), np.inf)
        if len(i) == 0:
            return out
        ok = (np.abs(np.einsum("ki,ki->k", t[m], t[i])) >= math.cos(math.radians(p.assoc_angle_deg))) & (m != i)
        ok &= (self.group[i] < 0) | (self.group[m] != self.group[i])        # rivals are alternatives, not pieces
        ok &= self.stance(i) * self.stance(m) >= 0                           # a foot and a texture line
        a, d, L = self.P[i, 0], t[i], lengths[i]
        s = np.einsum("kei,ki->ke", self.P[m] - a[:, None], d)                       # (K, 2) along i
        gap = np.where(_one_stance_unknown(self.stance(i), self.stance(m)), 0.0, p.merge_gap_m)
        ok &= np.maximum(s.min(axis=1) - L, -s.max(axis=1)) <= gap
        r = self.P[m] - (a[:, None] + s[..., None] * d[:, None])                     # (K, 2, 3) across i
        ok &= _norms(r, axis=2).max(axis=1) < MERGE_PERP_M
        if ok.any() and len(self._stops):
            ok[ok] = ~self._across_a_corner(self.P[i[ok]], self.P[m[ok]])
        k = np.nonzero(ok)[0]
        if len(k):
            Ci = (self.cov[i[k], 0] + self.cov[i[k], 1]) / 2          # the mean of i's two ends' covariances
            S = (Ci[:, None] + self.cov[m[k]] + p.assoc_extra_m ** 2 * np.eye(3)
                 + ALONG_VAR * np.einsum("ki,kj->kij", d[k], d[k])[:, None])
            m2 = np.einsum("kei,keij,kej->ke", r[k], np.linalg.inv(S), r[k])
            out[k] = np.where((m2 <= CHI2_3_99).all(axis=1), m2.sum(axis=1), np.inf)
        return out

    def _corner_feet(self) -> tuple[np.ndarray, np.ndarray]:
        """(S, 3) the feet of the vertical segments that stand on the floor (lower end within ``ghost_error_m``
        of it): a box's or a wall's corner, where a floor line ends; and (S,) bool, the feet where two faces'
        feet end that cannot be one line (directions apart by more than ``assoc_angle_deg``): a corner
        seen from both of its faces, past which neither face's floor line runs on.

        Candidates count as well as verified segments (not a hypothesis no camera has seen yet): a vertical
        seen standing on a floor line is the evidence of a corner, and a false one only keeps two pieces of
        a line apart. Verified ones alone left seed 4's box_b foot 0.49 m past a corner whose vertical was
        still a candidate (60 frames). The floor lines that make a foot a corner are faces' feet: the map's
        standing ones and the abstraction's hypotheses (a box's lower edge it expects there). A wall's or a
        box's texture vertical that reaches the floor has one foot through it, not two that end there; an
        undecided floor line ending there may be a floor texture line running into the face (World.room(2):
        one made a texture vertical on box_b's west face a corner, and a ghost of that foot stayed apart)."""
        p = self.params
        none = np.zeros((0, 3)), np.zeros(0, bool)
        seen = self.support >= 1
        V = np.nonzero(seen | self.hypothesis)[0]
        if len(V) == 0:
            return none
        P = self.P[V]
        t = _directions(P)
        cos_par = math.cos(math.radians(p.assoc_angle_deg))
        up = np.abs(t[:, 1]) >= cos_par
        low = np.where((P[:, 0, 1] > P[:, 1, 1])[:, None], P[:, 0], P[:, 1])      # y down: the larger y
        on_floor = seen[V] & up & (np.abs(low[:, 1]) <= p.ghost_error_m)
        feet = low[on_floor]
        if len(feet) == 0:
            return none
        feet_of_faces = (self.stance(V) == STANDING) | self.hypothesis[V]
        lines = np.nonzero((np.abs(P[:, :, 1]).max(axis=1) <= p.ghost_error_m) & feet_of_faces)[0]
        # The line ends within ghost_error_m of each foot: candidates by x (sorted), then the distance.
        ends = P[lines].reshape(-1, 3)
        order = np.argsort(ends[:, 0], kind="stable")
        xs = ends[order, 0]
        lo = np.searchsorted(xs, feet[:, 0] - p.ghost_error_m, side="left")
        n = np.searchsorted(xs, feet[:, 0] + p.ghost_error_m, side="right") - lo
        foot = np.repeat(np.arange(len(feet)), n)
        end = order[np.repeat(lo - np.cumsum(n) + n, n) + np.arange(n.sum())]
        near = _norms(ends[end] - feet[foot], axis=1) <= p.ghost_error_m
        foot, line = foot[near], lines[end[near] // 2]
        corner = np.zeros(len(feet), bool)
        for s_i in np.nonzero(np.bincount(foot, minlength=len(feet)) >= 2)[0]:
            d = t[line[foot == s_i]]
            corner[s_i] = (np.abs(d @ d.T) < cos_par).any()
        return feet, corner

    def _across_a_corner(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        """(K,) bool for pairs of floor lines (A, B: (K, 2, 3), B an observation or another piece on A's line):
        a corner foot (``_corner_feet``) on A's line separates them, A on one side of it and B on the other
        (each within ``ghost_error_m``).

        A floor line cannot run on through a box's corner: beyond the corner, on the line of one face's foot,
        lies the open floor, where only a texture line can be (World.room seeds 2, 4, 7: a floor texture
        line within 2-5 cm and 6 deg of a box's foot, fused or merged into it across the gaps that join LSD's
        broken pieces, ran the foot 0.2-1.5 m past the corner). A wall's floor line ends at the room's
        corner the same way. Where the corner is seen from both faces (``_corner_feet``), a line that ends
        there and one that runs on past it by more than ``merge_gap_m`` are apart too, whichever is A: a
        piece through box_a's corner, 6 deg off its east foot, merged into the foot, ran it 0.31 m past the
        corner and grew the box's footprint over the goal (World.room(6), goto from (0, -2.25))."""
        p = self.params
        tol = p.ghost_error_m
        out = np.zeros(len(A), bool)
        floor = (np.abs(A[:, :, 1]).max(axis=1) <= tol) & (np.abs(B[:, :, 1]).max(axis=1) <= tol)
        if not floor.any():
            return out
        f = np.nonzero(floor)[0]
        a = A[f, 0]
        d = A[f, 1] - a
        L = np.maximum(_norms(d, axis=1), 1e-12)
        d = d / L[:, None]
        feet = self._stops                                                             # (S, 3)
        rel = feet[None] - a[:, None]                                                  # (F, S, 3)
        sc = np.einsum("fsi,fi->fs", rel, d)
        across = _norms(rel - sc[..., None] * d[:, None], axis=2)
        sb = np.einsum("fei,fi->fe", B[f] - a[:, None], d)
        lo_b, hi_b = sb.min(axis=1)[:, None], sb.max(axis=1)[:, None]
        # A within [0, L]; a foot at s_c with A after it and B before it, or A before it and B after it.
        a_after = (0 >= sc - tol) & (hi_b <= sc + tol)
        a_before = (L[:, None] <= sc + tol) & (lo_b >= sc - tol)
        # At a corner (two faces' feet end there) one of the two ending there and the other running on past it
        # by more than the gap that joins a line's pieces (``merge_gap_m``): a line through the corner.
        gap = p.merge_gap_m
        a_ends = (np.abs(L[:, None] - sc) <= tol) & (hi_b > sc + gap) | (np.abs(sc) <= tol) & (lo_b < sc - gap)
        b_ends = (np.abs(hi_b - sc) <= tol) & (L[:, None] > sc + gap) | (np.abs(lo_b - sc) <= tol) & (sc > gap)
        through = self._corners[None] & (a_ends | b_ends)
        out[f] = ((across <= tol) & (a_after | a_before | through)).any(axis=1)
        return out

    def _rank(self, k: int) -> tuple:
        return (bool(self.verified[k]), len(self.views[k]), int(self.support[k]))

    def _absorb(self, i: int, j: int) -> None:
        """Segment j's information, extent, support and viewpoints into segment i (j is then removed)."""
        t = _directions(self.P[i:i + 1])[0]
        Pj, Cj = self.P[j], self.cov[j]
        if (Pj[1] - Pj[0]) @ t < 0:
            Pj, Cj = Pj[::-1], Cj[::-1]
        # j's line evaluated where i's endpoints are along it (its information constrains the line, not
        # the positions along it), with j's covariance; then summed like any repeated observation.
        tj = (Pj[1] - Pj[0]) / max(np.linalg.norm(Pj[1] - Pj[0]), 1e-12)
        W = np.linalg.inv(Cj + ALONG_VAR * np.outer(t, t))                          # (2, 3, 3)
        for e in range(2):
            sj = (self.P[i, e] - Pj[0]) @ tj
            x = Pj[0] + sj * tj
            self.info[i, e] += W[e]
            self.info_vec[i, e] += W[e] @ x
        self.cov[i] = np.linalg.inv(self.info[i])
        q = np.einsum("eij,ej->ei", self.cov[i], self.info_vec[i])
        tq = q[1] - q[0]
        tq = tq / max(np.linalg.norm(tq), 1e-12)
        self._ends_in_step()
        self.ends[i] = np.concatenate((self.ends[i], self.ends[j]))
        self.P[i] = self._extent(np.array([i]), q[None, 0], tq[None])[0]
        if not self.verified[i]:
            # A candidate's anchor (where it is re-observed) becomes the merged estimate.
            self.anchor[i] = self.P[i]
            self.anchor_cov[i] = self.cov[i]
        self._moved(np.array([i]))
        self.support[i] += self.support[j]
        self.stance_votes[i] += self.stance_votes[j]
        self.misses[i] = min(self.misses[i], self.misses[j])
        self.hypothesis[i] &= self.hypothesis[j]
        self.ambiguous[i] |= self.ambiguous[j]
        if self.group[i] != self.group[j]:
            self.group[i] = -1                   # the merged edge is no longer one left segment's alternative
        self._merge_views(i, j)

    def _ends_in_step(self) -> None:
        """One list of observed endpoints per segment; a map whose arrays were replaced from outside (a test)
        starts from its segments' extents."""
        if len(self.ends) != len(self):
            self.ends = [self.P[k:k + 1].copy() for k in range(len(self))]

    def _extent(self, j: np.ndarray, q0: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(K, 2, 3): segments j's endpoints on their lines (points q0 (K, 3), unit directions t (K, 3)): the
        farthest any observed endpoint reaches along each line, both ways.

        Each end is taken from the observations themselves, projected on the line as it is now. The union of
        the previous extent and the new observation (before) kept an extent computed on a line that was
        still poorly determined: two short pieces of a vertical edge at 0.5 m, their endpoints a few cm
        apart along it and ~1 cm apart in depth, tilt the fused line by tens of degrees for a frame, the
        projection there put an end 9 cm past box_b's top corner, 8.6 cm beyond every observation, and the
        union kept it for good after the line had settled (issue 16, 120 frames)."""
        if len(j) == 1:                          # one segment (a fusion, an absorption): no grouping
            i = int(j[0])
            s = np.einsum("mei,i->me", self.ends[i] - q0[0], t[0])
            self._bound_ends(i, s)
            return np.stack((q0 + s.min() * t, q0 + s.max() * t), axis=1)
        E = [self.ends[i] for i in j.tolist()]
        n = np.array([len(e) for e in E])
        owner = np.repeat(np.arange(len(E)), n)
        s = np.einsum("mei,mi->me", np.concatenate(E) - q0[owner, None], t[owner])    # (M, 2) along
        start = np.concatenate(([0], np.cumsum(n)[:-1]))
        lo, hi = np.minimum.reduceat(s.min(axis=1), start), np.maximum.reduceat(s.max(axis=1), start)
        for k in np.nonzero(n > ENDS_KEPT)[0]:
            self._bound_ends(int(j[k]), s[start[k]:start[k] + n[k]])
        return np.stack((q0 + lo[:, None] * t, q0 + hi[:, None] * t), axis=1)

    def _bound_ends(self, i: int, s: np.ndarray) -> None:
        """Keep at most ENDS_KEPT observations of segment i (s: (N, 2), their ends along its current line): the
        half that reach farthest each way. A segment seen every frame of a long drive would otherwise keep
        (and project, at every fusion) every observation it ever had: memory and time growing without
        bound. The extent is the farthest reach along the line; an observation amid the others can only
        become the farthest if the line turns far enough to carry it past every kept one."""
        if len(s) <= ENDS_KEPT:
            return
        half = ENDS_KEPT // 2
        lo, hi = np.argsort(s.min(axis=1), kind="stable"), np.argsort(-s.max(axis=1), kind="stable")
        keep = np.zeros(len(s), bool)
        keep[lo[:half]] = True
        keep[hi[:ENDS_KEPT - half]] = True
        self.ends[i] = self.ends[i][keep]

    def stance(self, idx) -> np.ndarray:
        """STANDING, FLAT or 0 for segments idx: what most of their floor-line observations had above them
        (a face rising from the line, or floor beyond it; vision/line_floor.py); 0 on a tie or none."""
        v = self.stance_votes[idx]
        return np.sign(v[..., 0] - v[..., 1]).astype(np.int8)

    def _vote(self, j: np.ndarray, stance: np.ndarray) -> None:
        np.add.at(self.stance_votes, (j[stance == STANDING], 0), 1)
        np.add.at(self.stance_votes, (j[stance == FLAT], 1), 1)

    def _add_view(self, j: int, view: np.ndarray) -> None:
        """Segment j observed from ``view`` (x, y, z, heading) in this frame."""
        self._log_in_step()
        if not self.verified[j]:
            log = self.view_log[j]
            if len(log) < VIEW_LOG_EXACT or not any(same_viewpoint(v, view, self.params) for v in log[:, 1:]):
                self.view_log[j] = np.concatenate((log, np.r_[self.frames, view][None]))
        if not any(same_viewpoint(v, view, self.params) for v in self.views[j]):
            self.views[j].append(view.copy())

    def _merge_views(self, i: int, j: int) -> None:
        """Segment j's viewpoints into segment i's: both logs in time order, and the distinct views counted
        again on it. Adding j's distinct views to i's would count the views from where the survivor was
        seen first: of pieces seen from 0.1 m apart, the older one keeps the views 0.15 m on from it that
        the newer one's first view hides (seed 6, box_a's corner: 3 views or 2 from one drive). A verified
        survivor (the survivor is verified when either was) only adds j's distinct views: it is verified."""
        self._log_in_step()
        if self.verified[i]:
            self.views[i] = distinct_views(self.views[i] + self.views[j], self.params)
            return
        log = np.concatenate((self.view_log[i], self.view_log[j]))
        log = log[np.argsort(log[:, 0], kind="stable")]                 # stable: i's first
        self.view_log[i] = log
        self.views[i] = [v.copy() for v in distinct_views(list(log[:, 1:]), self.params)]

    def _log_in_step(self) -> None:
        """A map whose arrays were replaced from outside (a map file, a test) starts each candidate's log from
        its distinct views, time unknown."""
        if len(self.view_log) != len(self):
            self.view_log = [np.zeros((0, 5)) if v else _logged(vs) for vs, v in zip(self.views, self.verified)]

    def _insert(self, Pw: np.ndarray, Cw: np.ndarray, group: np.ndarray, view: np.ndarray,
                hypothesis: bool = False, stance: Optional[np.ndarray] = None) -> np.ndarray:
        n = len(Pw)
        votes = np.zeros((n, 2), int)
        if stance is not None:
            votes[:, 0], votes[:, 1] = stance == STANDING, stance == FLAT
        indexed = self._indexed()
        t = Pw[:, 1] - Pw[:, 0]
        t = t / np.maximum(_norms(t, axis=1), 1e-12)[:, None]
        info = np.linalg.inv(Cw + ALONG_VAR * np.einsum("ki,kj->kij", t, t)[:, None])    # (n, 2, 3, 3)
        vec = np.einsum("keij,kej->kei", info, Pw)
        cov = np.linalg.inv(info)
        new_ids = np.arange(self.next_id, self.next_id + n)
        rows = {"P": Pw, "info": info, "info_vec": vec, "cov": cov, "anchor": Pw, "anchor_cov": cov,
                "support": np.ones(n, int), "misses": np.zeros(n, int), "verified": np.zeros(n, bool),
                "group": group.astype(int), "ids": new_ids, "hypothesis": np.full(n, hypothesis),
                "ambiguous": group >= 0, "stance_votes": votes}
        if rows.keys() != set(SEGMENT_ARRAYS):
            raise AssertionError(f"LineMap._insert: new rows for {sorted(rows)}, expected {SEGMENT_ARRAYS}")
        for name in SEGMENT_ARRAYS:
            setattr(self, name, np.concatenate((getattr(self, name), rows[name])))
        self.next_id += n
        logged = len(self.view_log) == len(self) - n
        self.views.extend([[view.copy()] if view is not None else [] for _ in range(n)])
        if logged:
            first = np.r_[self.frames, view][None] if view is not None else np.zeros((0, 5))
            self.view_log.extend(first.copy() for _ in range(n))
        if len(self.ends) == len(self) - n:
            self.ends.extend(Pw[k:k + 1].copy() for k in range(n))
        if len(self.serial) == len(self) - n:
            serial = np.arange(self.next_serial, self.next_serial + n)
            self.serial = np.concatenate((self.serial, serial))
            self.next_serial += n
            if indexed:
                self.grid.add(serial, *self._bbox(np.arange(len(self) - n, len(self))))
        return new_ids

    def _count_misses(self, pred: Prediction, seen: np.ndarray) -> None:
        if len(pred) == 0:
            return
        d = pred.xy[:, 2:4] - pred.xy[:, 0:2]
        steep = np.abs(d[:, 1]) / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9) >= \
            math.sin(math.radians(self.params.min_epipolar_angle_deg))
        idx = pred.index[steep]
        idx = idx[idx < len(seen)]
        missed = idx[~seen[idx]]
        self.misses[missed] += 1

    def _verify(self, gone: np.ndarray, changed: np.ndarray) -> tuple[int, int, np.ndarray]:
        """Verify the segments (not ``gone``) seen from enough viewpoints (two separating ones: tested for the
        segments ``changed`` this frame, fused, inserted or grown by a merge, as only those can have become
        separated); returns how many, how many rivals that drops, and the rows to remove (``gone`` and the
        rivals)."""
        p = self.params
        nviews = np.fromiter(map(len, self.views), int, len(self.views))
        newly = (~self.verified) & (nviews >= p.verify_views) & ~gone
        pair = np.zeros(len(self), bool)
        pair[changed] = True
        pair &= (~self.verified) & ~newly & ~gone & ~self.ambiguous & (nviews >= 2) & (self.support >= p.verify_views)
        ks = np.nonzero(pair)[0]
        newly[ks] = self._separated(ks)
        self.verified |= newly
        if len(self.view_log) == len(self):
            for k in np.nonzero(newly)[0].tolist():
                self.view_log[k] = np.zeros((0, 5))         # verified: the count no longer matters
        # A verified hypothesis decides its group: its rivals go.
        drop = gone.copy()
        for g in np.unique(self.group[newly]):
            if g >= 0:
                drop |= (self.group == g) & ~self.verified
        return int(newly.sum()), int((drop & ~gone).sum()), drop

    def separating_views(self, k: int) -> bool:
        """Candidate k was re-observed, at its anchor, from two viewpoints between which a false match would
        have moved out of the association gate.

        A false match lies off the edge along its viewing ray; ``ghost_error_m`` off from viewpoints i and j
        (unit rays r_i, r_j to the anchor's midpoint), the two lie e |(I - t t^T)(r_i - r_j)| apart across the
        line (t its direction; moving along the line moves it little across). The association compares an
        observation with the anchor under both covariances plus ``assoc_extra_m``: a gate of
        sqrt(chi2_3,99 % (2 u^T C u + extra^2)) in that direction u (C: the anchor's covariance, for both).
        A pair whose separation exceeds the gate has tested the candidate: a false match this far off would
        have been inserted as a new candidate instead. Rivals of a periodic texture are exempt (``ambiguous``)."""
        return bool(self._separated(np.array([k]))[0])

    def _separated(self, ks: np.ndarray) -> np.ndarray:
        """``separating_views`` of the candidates ``ks`` at once, (len(ks),) bool: every pair of each one's
        views in one batch (a frame tests a few tens, nearly all with two views: per candidate, the array
        set-up cost ten times the arithmetic)."""
        p = self.params
        out = np.zeros(len(ks), bool)
        pair_k, pair_i, pair_j, pos = [], [], [], []
        for n, k in enumerate(ks.tolist()):
            v, first = self.views[k], len(pos)
            for i in range(len(v)):
                for j in range(i + 1, len(v)):
                    pair_k.append(n)
                    pair_i.append(first + i)
                    pair_j.append(first + j)
            pos.extend(w[:3] for w in v)
        if not pair_k:
            return out
        pk = np.array(pair_k)
        A = self.anchor[ks]                                                      # (K, 2, 3)
        t = A[:, 1] - A[:, 0]
        t /= np.maximum(_norms(t, axis=1, keepdims=True), 1e-12)
        view_of = np.repeat(np.arange(len(ks)), [len(self.views[k]) for k in ks.tolist()])
        r = A.mean(axis=1)[view_of] - np.array(pos)
        r /= _norms(r, axis=1, keepdims=True)
        u = r[pair_i] - r[pair_j]
        tk = t[pk]
        u -= (u * tk).sum(axis=1, keepdims=True) * tk
        n = _norms(u, axis=1)
        u /= np.maximum(n, 1e-12)[:, None]
        C = self.anchor_cov[ks].mean(axis=1)[pk]                                 # (pairs, 3, 3)
        gate2 = CHI2_3_99 * (2.0 * np.einsum("ki,kij,kj->k", u, C, u) + p.assoc_extra_m ** 2)
        np.logical_or.at(out, pk, (p.ghost_error_m * n) ** 2 >= gate2)
        return out

    def _prune(self, drop: np.ndarray) -> int:
        """Remove the rows ``drop`` and the segments missed too often; returns how many of the latter."""
        p = self.params
        missed = (~self.verified & (self.misses >= p.miss_limit)) | \
            (self.verified & (self.misses > p.verified_miss_factor * self.support))
        self._remove(drop | missed)
        return int((missed & ~drop).sum())

    def _remove(self, drop: np.ndarray) -> None:
        if not drop.any():
            return
        keep = ~drop
        indexed = self._indexed()
        if len(self.serial) == len(self):
            self.serial = self.serial[keep]
        if indexed:
            self.grid.remove(keep)
        for name in SEGMENT_ARRAYS:
            setattr(self, name, getattr(self, name)[keep])
        kept = np.flatnonzero(keep).tolist()    # indices as ints: zipping a numpy bool array is 5x slower
        if len(self.view_log) == len(self.views):
            self.view_log = [self.view_log[i] for i in kept]
        self.views = [self.views[i] for i in kept]
        if len(self.ends) == len(keep):
            self.ends = [self.ends[i] for i in kept]

    # ------------------------------------------------------------- spatial hash
    def _near(self, lo: np.ndarray, hi: np.ndarray, reach: float, qdir: np.ndarray, ref_dirs) -> tuple:
        """(q, pos), sorted: the pairs of query segments (boxes lo, hi (Q, 3), unit directions qdir) and map
        segments that can be within ``reach`` of them and within ``assoc_angle_deg`` of their direction
        (``ref_dirs(i)``: the directions of map segments i the caller's gate uses). From the spatial hash
        once the map holds ``grid_min_segments``; below that a scan costs less than the hash's Python
        lookups: the segments whose boxes meet the queries' joint box, then their directions (one matrix
        product). Measured on the 60-frame room loop with far copies of its map added (update CPU median /
        p95, scan vs hash): 2954 segments 10.7 / 22.7 vs 15.0 / 34.8 ms, 10369: 21.5 / 35.4 vs
        20.0 / 43.4 ms, 19267: 35.5 / 56.8 vs 26.8 / 50.8 ms."""
        angle = self.params.assoc_angle_deg
        if len(self) >= self.grid_min_segments:
            return self._index().near(self.serial, lo, hi, reach, classes_within(qdir, angle))
        # The scan: the segments whose boxes meet the queries' joint box (widened by the reach), then their
        # directions against the queries'.
        blo, bhi = self._boxes()
        sub = np.nonzero(((blo <= hi.max(axis=0) + reach) & (bhi >= lo.min(axis=0) - reach)).all(axis=1))[0]
        q, k = np.nonzero(np.abs(qdir @ ref_dirs(sub).T) >= math.cos(math.radians(angle)) - 1e-9)
        return q, sub[k]

    def _indexed(self) -> bool:
        """The grid is in step with the arrays (else the next query rebuilds it)."""
        return self.grid is not None and len(self.grid.lo) == len(self) == len(self.serial)

    def _index(self) -> SegmentGrid:
        """The spatial hash, rebuilt when out of step with the arrays or when removed segments make up
        more than half of its entries."""
        if len(self.serial) != len(self):
            self.serial = np.arange(self.next_serial, self.next_serial + len(self))
            self.next_serial += len(self)
            self.grid = None
        g = self.grid
        if not self._indexed() or g.entries > 2 * g.live_entries + 4096:
            self.grid = SegmentGrid()
            self.grid.add(self.serial, *self._bbox(np.arange(len(self))))
        return self.grid

    def _boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """All segments' boxes as in ``_bbox`` (lo, hi)."""
        P, A = self.P, self.anchor
        a = math.radians(self.params.assoc_angle_deg)
        d = P[:, 1] - P[:, 0]
        e = (0.5 * (1.0 - math.cos(a) + math.sin(a)) * np.sqrt(np.einsum("ki,ki->k", d, d)))[:, None]
        lo = np.minimum(np.minimum(P[:, 0], P[:, 1]), np.minimum(A[:, 0], A[:, 1]))
        hi = np.maximum(np.maximum(P[:, 0], P[:, 1]), np.maximum(A[:, 0], A[:, 1]))
        return lo - e, hi + e

    def _bbox(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Boxes (lo, hi) of segments idx and their direction classes: their estimates and anchors, widened
        by 0.5 L (1 - cos a + sin a) (a = ``assoc_angle_deg``): how much nearer to a touched segment than its
        midpoint a piece of length L reaches (the merging prefilter tests midpoints)."""
        pts = np.concatenate((self.P[idx], self.anchor[idx]), axis=1)
        a = math.radians(self.params.assoc_angle_deg)
        e = (0.5 * (1.0 - math.cos(a) + math.sin(a)) * _norms(self.P[idx, 1] - self.P[idx, 0], axis=1))[:, None]
        return (pts.min(axis=1) - e, pts.max(axis=1) + e,
                direction_classes(self.P[idx]) | direction_classes(self.anchor[idx]))

    def _moved(self, idx: np.ndarray) -> None:
        if self._indexed():
            self.grid.grow(idx, self.serial[idx], *self._bbox(idx))

    # --------------------------------------------------------- abstraction input
    def add_hypotheses(self, P: np.ndarray, sigma_m: float = HYPOTHESIS_SIGMA_M, camera: Optional[tuple] = None,
                       fixes: Optional[list] = None) -> np.ndarray:
        """Insert missing-line hypotheses from the abstraction module (world frame, (K, 2, 3)): candidates
        with no viewpoint yet, verified or pruned by the sensor loop like stereo candidates. fixes: one
        ``HorizontalFix`` or None per hypothesis, measured by the slow loop in a snapshot of the keyframes
        (``sight_hypotheses``, vision/line_sighting.py): a fixed one is inserted at the fix's heights,
        verified. Without fixes and with camera ((fx, fy, cx, cy, baseline, width, height) of the left
        image), they are measured here, now (40-100 ms for a box's eight: the slow loop's work; a test or a
        caller without a slow loop). Hypotheses shorter than ``min_length_m`` are not inserted. Returns the
        inserted ones' ids."""
        P = np.asarray(P, float).reshape(-1, 2, 3)
        if fixes is None:
            fixes = (sight_hypotheses(P, self.keyframes, camera, self.params, sigma_m) if camera is not None
                     else [None] * len(P))
        if len(fixes) != len(P):
            raise ValueError(f"add_hypotheses: {len(fixes)} fixes for {len(P)} hypotheses")
        # Shorter than the map takes from stereo is no line (a degenerate footprint side; zero length would
        # also make a map file that cannot be loaded back).
        long_enough = _norms(P[:, 1] - P[:, 0], axis=1) >= self.params.min_length_m
        P, fixes = P[long_enough], [f for f, ok in zip(fixes, long_enough) if ok]
        P, fixes = self._new_hypotheses(P, fixes, sigma_m)
        if len(P) == 0:
            return np.zeros(0, int)
        C = np.broadcast_to(sigma_m ** 2 * np.eye(3), (len(P), 2, 3, 3)).copy()
        ids = self._insert(P, C, np.full(len(P), -1), None, hypothesis=True)
        for k, fix in zip(range(len(self) - len(P), len(self)), fixes):
            self.views[k] = []
            if len(self.view_log) == len(self):
                self.view_log[k] = np.zeros((0, 5))
            self.support[k] = 0
            if fix is not None:
                self._apply_fix(k, fix)
        # A hypothesis's region may have been in view before it was posted (the slow loop posts a box's
        # missing lines once its corners are verified, often as the robot leaves it): the stereo pieces seen
        # there are in the map as candidates, observations of the line it hypothesises, and merge into it
        # as pieces of one edge do (their viewpoints add up: ``_merge_collinear``). Not with another
        # hypothesis: one the same line was dropped above, and two lines 10 cm apart are two lines.
        new = np.arange(len(self) - len(P), len(self))
        merged, gone, grown = self._merge_collinear(new[~self.verified[new]], partners=~self.hypothesis)
        if merged:
            _, _, drop = self._verify(gone, np.asarray(grown, int))
            self._remove(drop)
        return ids

    def _new_hypotheses(self, P: np.ndarray, fixes: list, sigma_m: float) -> tuple[np.ndarray, list]:
        """The hypotheses P (K, 2, 3) (and their fixes) that are not already in the map. The slow loop posts an
        object's hypotheses again when its footprint changes (rounded to 0.1 m), and most of its lines are
        the same lines (room seeds 1-3, 60 frames: 2-3 pairs each, some verified twice): one of the same kind
        (a corner, a lower edge, a top: ``_hypothesis_kind``) as an earlier hypothesis whose ends' x and z
        both lie within ``sigma_m`` (the hypothesis's sigma, per axis) of its ends', either way round, is that
        line (a top's height is where it was measured, not compared). It is dropped, unless it comes measured
        (a fix) and the earlier one is not verified yet: then the earlier one takes its place and its
        measurement."""
        old = np.nonzero(self.hypothesis)[0]
        if len(old) == 0 or len(P) == 0:
            return P, fixes
        Q, H = P[..., [0, 2]], self.P[old][..., [0, 2]]                          # (K, 2, 2), (M, 2, 2)
        same = np.minimum(np.abs(Q[:, None] - H[None]).max(axis=(2, 3)),
                          np.abs(Q[:, None] - H[None, :, ::-1]).max(axis=(2, 3))) <= sigma_m      # (K, M)
        same &= _hypothesis_kind(P, sigma_m)[:, None] == _hypothesis_kind(self.P[old], sigma_m)[None]
        keep = np.ones(len(P), bool)
        for q in np.nonzero(same.any(axis=1))[0]:
            keep[q] = False
            k = int(old[np.argmax(same[q])])
            if fixes[q] is not None and not self.verified[k]:
                self.P[k] = P[q]
                self._apply_fix(k, fixes[q])
        return P[keep], [f for f, ok in zip(fixes, keep) if ok]

    def _remember(self, left: Segments2D, R_wc: np.ndarray, t_wc: np.ndarray,
                  image: Optional[np.ndarray] = None) -> None:
        """Keep this frame's left segments (and grey image) as a keyframe when its viewpoint is distinct from
        the last kept one; forget the keyframes farther than ``max_range_m`` from the camera (what they saw in
        range of them and is still in range of here lies within 2 ``max_range_m``; a hypothesis comes from
        what was just verified near the robot), and all but the newest 2 ``max_range_m`` / ``view_baseline_m``
        (40). The list is replaced, never changed in place: a snapshot (``list(keyframes)``) taken by the slow
        loop stays as it was."""
        p = self.params
        if self.keyframes:
            last = self.keyframes[-1]
            if same_viewpoint(viewpoint(last.R, last.t), viewpoint(R_wc, t_wc), p):
                return
        kept = [f for f in self.keyframes if np.linalg.norm(f.t - t_wc) <= p.max_range_m]
        kept.append(Keyframe(left.xy.copy(), R_wc.copy(), t_wc.copy(), None if image is None else grey(image).copy()))
        # A robot that circles or turns in place within max_range_m would keep one more every view step for
        # ever: the newest as many as a straight drive across the range keeps (2 max_range_m / view_baseline_m).
        self.keyframes = kept[-max(int(math.ceil(2 * p.max_range_m / p.view_baseline_m)), p.verify_views):]

    def _apply_fix(self, k: int, fix: HorizontalFix) -> None:
        """Hypothesis k measured in the keyframes (vision/line_sighting.py): its ends at the fix's heights,
        across-line sigma ``assoc_extra_m`` horizontally and the fix's along y, verified from its views."""
        p = self.params
        self.P[k, :, 1] = fix.y
        self.anchor[k] = self.P[k]
        self._ends_in_step()
        self.ends[k] = self.P[k:k + 1].copy()
        var = np.array([p.assoc_extra_m ** 2, 0.0, p.assoc_extra_m ** 2])
        cov = np.zeros((2, 3, 3))
        for e in range(2):
            cov[e] = np.diag(var + np.array([0.0, fix.var_y[e], 0.0]))
        self.cov[k] = self.anchor_cov[k] = cov
        t_dir = _directions(self.P[k:k + 1])[0]
        self.info[k] = np.linalg.inv(cov + ALONG_VAR * np.outer(t_dir, t_dir)[None])
        self.info_vec[k] = np.einsum("eij,ej->ei", self.info[k], self.P[k])
        self.support[k] = fix.support
        self.views[k] = [v.copy() for v in fix.views]
        if len(self.view_log) == len(self):
            self.view_log[k] = np.zeros((0, 5))             # verified: its log is not kept
        self.verified[k] = True
        self._moved(np.array([k]))

    def summary(self) -> dict:
        return {"segments": int(len(self)), "verified": int(self.verified.sum()),
                "candidates": int((~self.verified).sum()), "hypotheses": int(self.hypothesis.sum()),
                "frames": int(self.frames),
                "total_length_m": round(float(self.length[self.verified].sum()), 3) if len(self) else 0.0}


def _hypothesis_kind(P: np.ndarray, tol_m: float) -> np.ndarray:
    """(K,) of hypotheses P (K, 2, 3): 0 a corner (vertical: its ends' x, z within tol_m), 1 a lower edge (on
    the floor: both ends within tol_m of y = 0), 2 a top."""
    vertical = np.abs(P[:, 0, [0, 2]] - P[:, 1, [0, 2]]).max(axis=1) <= tol_m
    lower = np.abs(P[..., 1]).max(axis=1) <= tol_m
    return np.where(vertical, 0, np.where(lower, 1, 2))


def _one_stance_unknown(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(K,) bool: of two floor lines' stances, one known (STANDING or FLAT) and the other not. Such pieces
    are one line only where they overlap: across a gap the unknown one may be the other kind, as a box's
    foot is beyond the corner where a texture line on its line ends (World.room seed 2, 180 frames: a foot
    seen once, of unknown stance, joined a flat texture line 0.09 m past box_a's corner, and the segment ran
    1.5 m along the floor beyond it)."""
    return (a != b) & (a * b == 0)


def _sorted_unique(a: np.ndarray) -> np.ndarray:
    a = np.sort(a)
    keep = np.empty(len(a), bool)
    keep[:1], keep[1:] = True, a[1:] != a[:-1]
    return a[keep]


def _distinct_lines(A: np.ndarray, B: np.ndarray, angle_deg: float, gate_px: float) -> np.ndarray:
    """(P,) bool: image segments A[p] and B[p] ((P, 4): x0 y0 x1 y1) are two distinct lines: parallel within
    ``angle_deg``, overlapping along A's line, and B on one side of A's line farther than ``gate_px`` all
    along the overlap (lines that cross are one where they cross). Pieces of one edge that do not overlap
    (LSD breaking it) are not distinct; rows with NaN never are."""
    a0, d = A[:, :2], A[:, 2:] - A[:, :2]
    L = _norms(d, axis=1)
    u = d / np.maximum(L, 1e-12)[:, None]
    n = np.column_stack((-u[:, 1], u[:, 0]))
    e = B.reshape(-1, 2, 2) - a0[:, None]
    s, h = np.einsum("pei,pi->pe", e, u), np.einsum("pei,pi->pe", e, n)     # B's ends along and across A
    db = B[:, 2:] - B[:, :2]
    cos = np.abs(np.einsum("pi,pi->p", db, u)) / np.maximum(_norms(db, axis=1), 1e-12)
    lo, hi = np.maximum(s.min(axis=1), 0.0), np.minimum(s.max(axis=1), L)
    slope = (h[:, 1] - h[:, 0]) / np.where(np.abs(s[:, 1] - s[:, 0]) > 1e-9, s[:, 1] - s[:, 0], np.inf)
    h_lo, h_hi = h[:, 0] + slope * (lo - s[:, 0]), h[:, 0] + slope * (hi - s[:, 0])
    with np.errstate(invalid="ignore"):
        return ((cos >= math.cos(math.radians(angle_deg))) & (hi > lo) & (h_lo * h_hi > 0)
                & (np.minimum(np.abs(h_lo), np.abs(h_hi)) > gate_px))


def _norms(x: np.ndarray, axis: int, keepdims: bool = False) -> np.ndarray:
    """Euclidean norms along ``axis``: what ``np.linalg.norm(x, axis=axis)`` computes for a real array (the
    same sum of squares, so the same bits) without its argument handling (~5 us a call, thousands a frame)."""
    return np.sqrt(np.add.reduce(x * x, axis=axis, keepdims=keepdims))


def _logged(views: list) -> np.ndarray:
    """A view log (n, 5) of distinct views whose time is unknown (frame -1)."""
    return np.array([np.r_[-1.0, v] for v in views], float).reshape(-1, 5)


def _directions(P: np.ndarray) -> np.ndarray:
    """Unit directions (K, 3) of segments (K, 2, 3)."""
    d = P[:, 1] - P[:, 0]
    return d / np.maximum(_norms(d, axis=1, keepdims=True), 1e-12)
