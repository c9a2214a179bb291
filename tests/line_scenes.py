"""Shared scenes for the line-segment map tests: the simulated room's true edges, a 6 m loop of stereo
frames, building the DLM along it and scoring a map against the world.

Scoring (docs/line_map.md):
- true edges: the 12 edges of every box and the edges of the walls (floor line, ceiling line, corners);
- an edge is *in view* when at least 0.3 m of it was seen unoccluded within the map's range
  (``MapParams.max_range_m``) in some frame of the drive (checked against the true disparity); *verifiable*
  when at least 0.3 m of it was, each point from at least ``verify_views`` (3) distinct viewpoints, the map's
  own rule (``same_viewpoint``: 0.15 m or 10 deg apart; ``in_view_verifiable``). Until 2026-12-02 it counted
  3 frames, which depends on the frame spacing: 3 frames of the sim robot's own 180-frame loop (3.3 cm
  apart) are one viewpoint;
- a verified map segment *belongs* to an edge when it is parallel (6 deg) and both endpoints are within
  10 cm of the edge's line (twice the false-segment distance, so the endpoint errors are not truncated at
  the 5 cm the acceptance asks of their 95th percentile), and it is not a floor line the map saw flat
  (``LineMap.structure``: floor beyond it too, so by the map's own evidence a texture line or a marking,
  not a box's or a wall's foot; the 10 cm tube of a foot holds 10 cm of open floor, whose texture lines
  are the floor's, not errors of the foot). Since 2026-12-02 (fifth session); before, every verified
  segment could belong. Nor is it a line painted on a wall's or a box's face (``painted_lines``: on its
  plane, 2 cm inside its border, along an edge of the face's own texture), which is correct map content,
  the map of no edge: a 6 cm texture vertical 5.9 cm from a box's corner on its face lies in the corner's
  10 cm tube.
  Since 2026-12-03 (``MapScore.painted_err`` holds their endpoint errors); an edge is *mapped* when
  segments belonging to it cover at least half of its seen length (or 0.3 m);
- endpoint error: distance of each endpoint of a belonging segment to the true edge (a segment, so an
  endpoint running past the corner counts);
- a verified segment is *false* when an endpoint is more than 5 cm from every surface of the world.

Edge classes (``edge_class``): ``box_vertical`` (box corners), ``box_horizontal`` (box tops and bottoms),
``wall_floor`` (where a wall meets the floor), ``wall_corner`` (two walls meeting), ``wall_ceiling``.
``MapScore.by_class`` holds (in view, mapped) per class.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from vbnav.drivers.sim.camera import SimCamera
from vbnav.drivers.sim.world import World
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.geometry import CameraMount, Pose2, camera_pose
from vbnav.vision.line_map import LineMap, MapParams
from vbnav.vision.line_segments import LineParams, reconstruct_pair
from vbnav.vision.line_sighting import distinct_views, sight_hypotheses, viewpoint

CAM = PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5)
# The mapping head looks out of the loop (yaw 70 deg to the right of travel on a counter-clockwise loop), so
# one 6 m circle sweeps the camera across both boxes and the south wall, like Marvin's panning head.
MOUNT = CameraMount(height=0.25, forward=0.10, yaw=math.radians(70.0))
BASELINE = 0.075
LOOP_CENTER = (0.0, -1.3)
LOOP_RADIUS = 6.0 / (2 * math.pi)      # a 6 m loop between box_a and box_b


def loop_poses(n: int, center=LOOP_CENTER, radius=LOOP_RADIUS, start_angle=-math.pi / 2) -> list[Pose2]:
    """n poses around a circle, counter-clockwise seen from above, heading along the tangent."""
    out = []
    for k in range(n):
        a = start_angle + 2 * math.pi * k / n
        x, z = center[0] + radius * math.cos(a), center[1] + radius * math.sin(a)
        # Tangent of increasing a: (-sin a, cos a); heading theta has forward (sin th, cos th).
        out.append(Pose2(x, z, math.atan2(-math.sin(a), math.cos(a))))
    return out


def stereo_camera(world: World, noise: float = 2.0, seed: int = 0) -> SimCamera:
    return SimCamera(world, CAM, MOUNT, lambda: Pose2(), None, 15.0, noise_std=noise, seed=seed,
                     stereo_baseline=BASELINE)


def true_edges(world: World) -> tuple[np.ndarray, list[str]]:
    """(E, 2, 3) world edges of boxes and walls, and their owners' names."""
    edges, names = [], []
    seen = set()
    for q in world.polygons:
        if q.kind not in ("box", "wall"):
            continue
        c = q.corners
        for i in range(4):
            a, b = c[i], c[(i + 1) % 4]
            key = tuple(sorted((tuple(np.round(a, 3)), tuple(np.round(b, 3)))))
            if key in seen:
                continue
            seen.add(key)
            edges.append((a, b))
            names.append(q.name)
    return np.array(edges, float), names


def edge_class(edge: np.ndarray, owner_kind: str) -> str:
    """The class of a true edge (world frame, floor y = 0, y down): see the module docstring."""
    d = edge[1] - edge[0]
    vertical = abs(d[1]) >= 0.9 * np.linalg.norm(d)
    if owner_kind == "box":
        return "box_vertical" if vertical else "box_horizontal"
    if vertical:
        return "wall_corner"
    return "wall_floor" if abs(edge[:, 1]).max() < 1e-6 else "wall_ceiling"


def point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances of points p (N, 3) to segments a->b (broadcast (M, 3)): (N, M)."""
    ab = b - a
    t = np.clip(((p[:, None] - a[None]) * ab[None]).sum(-1) / np.maximum((ab ** 2).sum(-1), 1e-12)[None], 0, 1)
    return np.linalg.norm(p[:, None] - (a[None] + t[..., None] * ab[None]), axis=-1)


def point_quad_distance(p: np.ndarray, world: World) -> np.ndarray:
    """(N,) distance of points to the nearest world surface."""
    best = np.full(len(p), np.inf)
    for q in world.polygons:
        d = p - q.origin
        a = np.clip(d @ q.u, 0, q.width)
        b = np.clip(d @ q.v, 0, q.height)
        foot = q.origin + a[:, None] * q.u + b[:, None] * q.v
        best = np.minimum(best, np.linalg.norm(p - foot, axis=1))
    return best


# A texture line on a face: both ends within PAINT_PLANE_M of the face's plane, PAINT_MARGIN_M inside its
# border (so the band sampled across it stays on the face, off the face's own edge), and the face's texture
# differs across it by PAINT_CONTRAST grey levels (the median over its length, sampled PAINT_BAND_TEXELS
# either side): the texture's grain is sigma ~4 grey levels after its 1-texel blur (14 x 1 / (2 sqrt(pi))),
# its painted shapes' edges tens of grey levels.
PAINT_PLANE_M = 0.02
PAINT_MARGIN_M = 0.02
PAINT_BAND_TEXELS = 2.0
PAINT_CONTRAST = 24.0


def painted_lines(V: np.ndarray, world: World) -> np.ndarray:
    """(K,) bool: segments V (K, 2, 3) that lie along a line painted on a face of a wall or a box (an edge of
    its texture, not of its geometry): correct map content, the map of no edge however near one it lies.
    Not the floor's: under a box's foot the floor's texture, hidden in the images, may have an edge too."""
    out = np.zeros(len(V), bool)
    s = (np.arange(9) + 0.5) / 9
    for q in world.polygons:
        if q.kind not in ("wall", "box"):
            continue
        n = q.normal / np.linalg.norm(q.normal)
        d = V - q.origin
        a, b, off = d @ q.u, d @ q.v, d @ n                                   # (K, 2) each
        m = PAINT_MARGIN_M
        on = ((np.abs(off) <= PAINT_PLANE_M) & (a >= m) & (a <= q.width - m) & (b >= m)
              & (b <= q.height - m)).all(axis=1) & ~out
        for k in np.nonzero(on)[0]:
            ta, tb = a[k, 1] - a[k, 0], b[k, 1] - b[k, 0]
            length = math.hypot(ta, tb)
            if length < 1e-6:
                continue
            na, nb = -tb / length, ta / length
            ca, cb = a[k, 0] + s * ta, b[k, 0] + s * tb                        # along the segment, metres
            h = PAINT_BAND_TEXELS / q.ppm
            sides = []
            for sign in (-1.0, 1.0):
                col = ((ca + sign * h * na) * q.ppm - 0.5).astype(np.float32)
                row = ((cb + sign * h * nb) * q.ppm - 0.5).astype(np.float32)
                sides.append(cv2.remap(q.texture, col[None], row[None], cv2.INTER_LINEAR,
                                       borderMode=cv2.BORDER_REPLICATE)[0].astype(float))
            out[k] = np.median(np.abs(sides[1] - sides[0])) >= PAINT_CONTRAST
    return out


@dataclass
class Drive:
    poses: list
    frames: list          # sim Frames (left, right, true disparity)
    cams: list            # (R_wc, t_wc) per frame


def render_drive(world: World, poses: list[Pose2], noise: float = 2.0) -> Drive:
    sc = stereo_camera(world, noise)
    frames = [sc.render_frame(p, seq=k) for k, p in enumerate(poses)]
    return Drive(poses, frames, [camera_pose(p, MOUNT) for p in poses])


def seen_samples(edges: np.ndarray, drive: Drive, max_range: float, n: int = 30, per_frame: bool = False) -> np.ndarray:
    """(E, n) bool: edge sample points seen unoccluded within max_range in some frame (with ``per_frame``:
    (F, E, n) bool, in each frame)."""
    t = (np.arange(n) + 0.5) / n
    pts = edges[:, None, 0] + (edges[:, None, 1] - edges[:, None, 0]) * t[None, :, None]   # (E, n, 3)
    flat = pts.reshape(-1, 3)
    seen = np.zeros((len(drive.frames), len(flat)), bool)
    fb = CAM.fx * BASELINE
    for k, (f, (R, c)) in enumerate(zip(drive.frames, drive.cams)):
        pc = (flat - c) @ R
        z = pc[:, 2]
        ok = (z > 0.1) & (z <= max_range)
        u = CAM.fx * pc[:, 0] / np.where(ok, z, 1) + CAM.cx
        v = CAM.fy * pc[:, 1] / np.where(ok, z, 1) + CAM.cy
        ok &= (u >= 2) & (u < CAM.width - 2) & (v >= 2) & (v < CAM.height - 2)
        ui, vi = np.round(u[ok]).astype(int), np.round(v[ok]).astype(int)
        # Unoccluded: some pixel within 1 px has the point's disparity (edges sit on depth boundaries).
        d_pt = fb / z[ok]
        best = np.full(ok.sum(), np.inf)
        for dv in (-1, 0, 1):
            for du in (-1, 0, 1):
                dd = f.disparity[np.clip(vi + dv, 0, CAM.height - 1), np.clip(ui + du, 0, CAM.width - 1)]
                best = np.minimum(best, np.abs(np.nan_to_num(dd, nan=-1e9) - d_pt) / d_pt)
        idx = np.nonzero(ok)[0]
        seen[k, idx[best < 0.03]] = True
    seen = seen.reshape(len(drive.frames), len(edges), n)
    return seen if per_frame else seen.any(axis=0)


def distinct_viewpoints(seen: np.ndarray, drive: Drive, params: MapParams) -> np.ndarray:
    """(E, n) int: from how many distinct viewpoints (the map's own rule, ``same_viewpoint``: 0.15 m or 10 deg
    apart) each edge sample was seen; seen (F, E, n) from ``seen_samples(..., per_frame=True)``, counted
    greedily in the drive's order as the map counts a segment's views."""
    views = [viewpoint(R, c) for R, c in drive.cams]
    out = np.zeros(seen.shape[1:], int)
    memo: dict = {}                          # neighbouring samples of an edge are mostly seen by the same frames
    for e, i in zip(*np.nonzero(seen.any(axis=0))):
        frames = tuple(np.nonzero(seen[:, e, i])[0].tolist())
        if frames not in memo:
            memo[frames] = len(distinct_views([views[f] for f in frames], params))
        out[e, i] = memo[frames]
    return out


@dataclass
class MapScore:
    in_view: int
    mapped: int
    endpoint_err: np.ndarray
    false_fraction: float
    verified: int
    missing: list
    by_class: dict        # class -> [in view, mapped]
    # Edges in view from at least ``verify_views`` distinct viewpoints (>= min_len of them; the chapter's
    # verification needs that many, so an edge glimpsed from one or two cannot be in a verified map), and
    # how many of them are mapped.
    in_view_verifiable: int = 0
    mapped_verifiable: int = 0
    # The endpoint errors of the lines painted on a face within an edge's tube (``painted_lines``), which
    # belong to no edge: endpoint_err plus these is the score of every segment in the tube (before 2026-12-03).
    painted_err: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def coverage(self) -> float:
        return self.mapped / max(self.in_view, 1)


def score_map(lmap: LineMap, world: World, drive: Drive, min_len: float = 0.3, tol: float = 0.10,
              angle_deg: float = 6.0, false_m: float = 0.05) -> MapScore:
    edges, names = true_edges(world)
    kinds = {q.name: q.kind for q in world.polygons}
    classes = [edge_class(e, kinds[nm]) for e, nm in zip(edges, names)]
    by_class: dict = {}
    n = 30
    per_frame = seen_samples(edges, drive, lmap.params.max_range_m, n, per_frame=True)
    seen = per_frame.any(axis=0)
    count = distinct_viewpoints(per_frame, drive, lmap.params)
    seg_len = np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1)
    seen_len = seen.mean(axis=1) * seg_len
    in_view = np.nonzero(seen_len >= min_len)[0]
    verifiable = (count >= lmap.params.verify_views).mean(axis=1) * seg_len >= min_len
    mapped_verifiable = 0
    V = lmap.structure()
    painted = painted_lines(V, world)
    t = (np.arange(n) + 0.5) / n
    mapped, errs, painted_errs, missing = 0, [], [], []
    for e in in_view:
        a, b = edges[e]
        d = (b - a) / seg_len[e]
        counts = by_class.setdefault(classes[e], [0, 0])
        counts[0] += 1
        if len(V) == 0:
            missing.append(f"{names[e]}:{classes[e]}")
            continue
        sd = V[:, 1] - V[:, 0]
        sd = sd / np.linalg.norm(sd, axis=1, keepdims=True)
        par = np.abs(sd @ d) >= math.cos(math.radians(angle_deg))
        s = ((V - a) @ d)                                       # (K, 2) along the edge
        perp = np.linalg.norm(V - a - s[..., None] * d, axis=2).max(axis=1)
        tube = par & (perp <= tol) & (s.max(axis=1) >= 0) & (s.min(axis=1) <= seg_len[e])
        own = tube & ~painted
        for k in np.nonzero(tube & painted)[0]:
            painted_errs.extend(point_segment_distance(V[k], a[None], b[None])[:, 0])
        cover = np.zeros(n, bool)
        for k in np.nonzero(own)[0]:
            lo, hi = s[k].min() / seg_len[e], s[k].max() / seg_len[e]
            cover |= (t >= lo) & (t <= hi)
            errs.extend(point_segment_distance(V[k], a[None], b[None])[:, 0])
        covered = (cover & seen[e]).mean() * seg_len[e]
        if covered >= min(min_len, 0.5 * seen_len[e]):
            mapped += 1
            counts[1] += 1
            mapped_verifiable += int(verifiable[e])
        else:
            missing.append(f"{names[e]}:{classes[e]}")
    every = lmap.P[lmap.verified]                # false or not: every verified segment, flat floor lines too
    if len(every):
        far = point_quad_distance(every.reshape(-1, 3), world).reshape(-1, 2).max(axis=1) > false_m
        false_fraction = float(far.mean())
    else:
        false_fraction = 0.0
    return MapScore(len(in_view), mapped, np.array(errs), false_fraction, len(every), missing, by_class,
                    int(verifiable[in_view].sum()), mapped_verifiable, np.array(painted_errs))


def build_map(drive: Drive, params: LineParams = LineParams(), map_params: MapParams = MapParams(),
              guided: bool = True, compare: bool = False, motion: bool = False, floor: bool = False,
              abstraction_every: int = 0):
    """Run the DLM's fast loop over the drive (true poses). With ``compare`` every frame is also matched
    without prediction and both best-match false rates are returned (true disparity decides).
    ``abstraction_every`` k > 0: the slow loop (``AbstractionThread.step``) runs inline after every k-th
    frame and its hypotheses are inserted before the next, as ``LineMapStage`` does."""
    lmap = LineMap(map_params)
    slow = None
    if abstraction_every:
        from vbnav.control.stages.line_map import AbstractionThread
        camera = (CAM.fx, CAM.fy, CAM.cx, CAM.cy, BASELINE, CAM.width, CAM.height)
        slow = AbstractionThread(lambda: lmap.structure().copy(),
                                 sight=lambda hyp, pinned: sight_hypotheses(hyp, list(lmap.keyframes), camera,
                                                                            lmap.params, pinned=pinned))
    counts = {"guided": [0, 0], "unguided": [0, 0]}
    key = None                       # (left segments, R, c) of the last keyframe, for motion triangulation
    for n, (f, (R, c)) in enumerate(zip(drive.frames, drive.cams)):
        while slow is not None and not slow.hypotheses.empty():
            hyp, fixes = slow.hypotheses.get_nowait()
            lmap.add_hypotheses(hyp, fixes=fixes)
        pred_v = lmap.predict(R, c, CAM.fx, CAM.fy, CAM.cx, CAM.cy, BASELINE, CAM.width, CAM.height)
        prior_fn = (lambda segs: lmap.prior_for(segs, pred_v)) if guided else None
        res = reconstruct_pair(f.image, f.right, CAM.fx, CAM.fy, CAM.cx, CAM.cy, BASELINE, params, prior_fn,
                               vertical=R[1])
        if compare:
            from vbnav.vision.line_segments import match_stereo
            un = match_stereo(res.left, res.right, params, None)
            for key, m in (("guided", res.matches), ("unguided", un)):
                wrong, total = false_matches(res.left, m, f.disparity)
                counts[key][0] += wrong
                counts[key][1] += total
        segs3d = res.segments
        if motion:
            from vbnav.vision.line_motion import motion_segments
            from vbnav.vision.line_segments import Segments3D
            if key is not None:
                segs3d = Segments3D.concat([segs3d, motion_segments(res.left, R, c, key[0], key[1], key[2], CAM.K)])
            if key is None or np.linalg.norm(c - key[2]) >= 0.15:
                key = (res.left, R, c)
        if floor:
            from vbnav.vision.line_floor import floor_segments
            from vbnav.vision.line_segments import Segments3D
            segs3d = Segments3D.concat([segs3d, floor_segments(res.left, f.image, f.right, CAM.K, BASELINE, R, c)])
        pred_all = lmap.predict(R, c, CAM.fx, CAM.fy, CAM.cx, CAM.cy, BASELINE, CAM.width, CAM.height,
                                which=np.ones(len(lmap), bool))
        lmap.update(segs3d, R, c, pred_all, res.left, f.image)
        if slow is not None and (n + 1) % abstraction_every == 0:
            slow.step()
    return lmap, counts


def false_matches(left, matches, true_disp: np.ndarray, tol_px: float = 1.0) -> tuple[int, int]:
    """(wrong, total) among the best matches: disparity at the left midpoint off the truth by > tol_px
    (the truth: the nearest disparity within 2 px, since segments sit on depth edges)."""
    b = matches.best
    if not b.any():
        return 0, 0
    xy = left.xy[matches.left[b]]
    d = matches.disparity[b].mean(axis=1)
    mx, my = (xy[:, 0] + xy[:, 2]) / 2, (xy[:, 1] + xy[:, 3]) / 2
    H, W = true_disp.shape
    wrong = 0
    for x, y, dd in zip(mx, my, d):
        xi, yi = int(round(x)), int(round(y))
        win = true_disp[max(0, yi - 2):min(H, yi + 3), max(0, xi - 2):min(W, xi + 3)]
        if not np.isfinite(win).any() or np.nanmin(np.abs(win - dd)) > tol_px:
            wrong += 1
    return wrong, int(b.sum())


def footprint_overlap(fp: np.ndarray, true: np.ndarray) -> tuple[float, float]:
    """(IoU, the fraction of ``true`` inside ``fp``) of two footprints (N, 2) x, z, each taken as its convex
    hull; its own convex clipping (Sutherland-Hodgman): cv2.intersectConvexConvex returned 0 for a map
    footprint nearly coinciding with the truth (room seed 1's box_b at 120 frames, IoU 0.996)."""
    a, b = _ccw(true), _ccw(fp)
    area_a, area_b = _polygon_area(a), _polygon_area(b)
    if area_a <= 0:
        return 0.0, 0.0
    inter = _polygon_area(_clip_convex(a, b))
    return inter / (area_a + area_b - inter), inter / area_a


def _ccw(poly: np.ndarray) -> np.ndarray:
    hull = cv2.convexHull(np.asarray(poly, np.float32)).reshape(-1, 2).astype(float)
    return hull if len(hull) < 3 or signed_area(hull) > 0 else hull[::-1]


def signed_area(poly: np.ndarray) -> float:
    """Signed area of a polygon (N, 2) (the shoelace formula; positive counter-clockwise)."""
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(x @ np.roll(y, -1) - y @ np.roll(x, -1))


def _polygon_area(poly: np.ndarray) -> float:
    return abs(signed_area(poly)) if len(poly) >= 3 else 0.0


def _clip_convex(subject: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """Convex polygon ``subject`` clipped to convex ``clip`` (both counter-clockwise)."""
    out = subject
    for a, b in zip(clip, np.roll(clip, -1, axis=0)):
        if len(out) == 0:
            break
        e = b - a
        side = e[0] * (out[:, 1] - a[1]) - e[1] * (out[:, 0] - a[0])          # >= 0: inside (left of a->b)
        nxt = []
        for k in range(len(out)):
            p, q, sp, sq = out[k], out[(k + 1) % len(out)], side[k], side[(k + 1) % len(out)]
            if sp >= 0:
                nxt.append(p)
            if (sp >= 0) != (sq >= 0):
                nxt.append(p + (q - p) * (sp / (sp - sq)))
        out = np.array(nxt).reshape(-1, 2)
    return out


def map_reprojection_errors(lmap: LineMap, detections: dict, poses: np.ndarray) -> np.ndarray:
    """The map's verified segments reprojected into each frame, against the segments detected there: for each
    predicted segment with a detection within the prediction gate (``LineMap._support_matrix``), the nearest
    one's larger endpoint distance to the projected line, px. detections: frame -> (left Segments2D, camera
    args of ``LineMap.predict``); poses (F, 3, 4) camera-to-world (kitti06's issue-16 reprojection figure)."""
    errs = []
    for i, (segs, args) in detections.items():
        pred = lmap.predict(poses[i][:, :3], poses[i][:, 3], *args)
        if len(pred) == 0:
            continue
        ok, dist, _ = lmap._support_matrix(segs, pred)
        for k in range(len(pred)):
            cand = np.nonzero(ok[:, k])[0]
            if len(cand) == 0:
                continue
            n = cand[np.argmin(dist[cand, k])]
            a, b = pred.xy[k, :2], pred.xy[k, 2:]
            d = (b - a) / np.linalg.norm(b - a)
            errs.append(np.abs((segs.xy[n].reshape(2, 2) - a) @ np.array([-d[1], d[0]])).max())
    return np.array(errs)


def read_pfm(path) -> np.ndarray:
    """A PFM image (Middlebury's ground-truth disparity) as float32, rows top to bottom; ValueError naming
    the file when it is not one."""
    with open(path, "rb") as fh:
        if fh.readline().strip() not in (b"Pf", b"PF"):
            raise ValueError(f"{path}: not a PFM file")
        w, h = map(int, fh.readline().split())
        scale = float(fh.readline())
        a = np.frombuffer(fh.read(), dtype="<f4" if scale < 0 else ">f4")
    if a.size != w * h:
        raise ValueError(f"{path}: expected {w}x{h} floats, found {a.size}")
    return np.flipud(a.reshape(h, w)).astype(np.float32)
