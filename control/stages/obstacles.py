"""Obstacle stop and slow-down zones (like nav2's collision monitor), fed by stereo ground suppression.

``ObstacleStage`` (a VisionStage, kind "obstacles") runs on every frame: the
disparity comes from ``Frame.disparity`` (the OAK's on-device matcher, the
simulated camera's true disparity) or from SGBM on ``Frame.image`` /
``Frame.right``; vision/obstacles.py labels the pixels and lists obstacle
points on the floor; ``ObstacleMonitor`` turns those points into a speed scale
in [0, 1] that the estimate carries in ``info["speed_scale"]`` (the runtime
applies the smallest scale of all estimates; 0 is a held stop).

Zones are in the robot frame: origin at the wheel-axle centre on the floor, x to
the right, z forward (metres). A zone is either a band (``distance``,
``half_width``: 0 < z <= distance, |x| <= half_width) or a polygon of (x, z)
vertices. A "stop" zone stops the robot, a "slow" zone scales the speed by its
``slow_scale``. A zone triggers when it holds at least ``min_points`` obstacle
pixels (after blob filtering), or negative-obstacle pixels when
``negative_stops``. Temporal filtering: a zone's trigger counts only when it
held in ``persist_k`` of the last ``persist_n`` frames (one noisy frame does not
stop the robot); the scale drops at once and rises again only after the
condition has been clear for ``release_s`` (debounce on release, frame stamps).

Config section ``obstacles:`` (``cfg.obstacles``, an ``ObstaclesConfig`` validated with the rest at load)::

    obstacles:
      enabled: true           # off by default: a mono camera has no disparity (the stage would stop the robot)
      source: auto            # auto: Frame.disparity if present, else SGBM on image/right
      baseline: 0.075         # m; default: camera.options.stereo_baseline, else frame.meta['baseline_m']
      obstacle_height: 0.02   # m above the floor
      negative_depth: 0.03    # m below the floor
      zones:
        - {name: stop, action: stop, distance: 0.8, half_width: 0.25}
        - {name: slow, action: slow, distance: 1.5, half_width: 0.35, slow_scale: 0.4}
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Optional

import cv2
import numpy as np
from vbnav.control.config.obstacles import ObstaclesConfig, ZoneConfig
from vbnav.control.runtime.interfaces import Estimate, StageOverlay, VisionStage
from vbnav.control.stages.frame_input import disparity_problem, dtype_problem, frame_baseline
from vbnav.drivers.calibration import CalibrationError, check_intrinsics
from vbnav.drivers.camera import Frame
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.geometry import CameraMount, Pose2
from vbnav.vision.ground_model import GroundModelParams
from vbnav.vision.ground_plane import PlaneFitParams, expected_plane
from vbnav.vision.obstacles import (
    KOfN,
    ObstacleParams,
    detect_obstacles,
    nearest_in_corridor,
)
from vbnav.vision.stereo import StereoRig, nearest_floor_m, sgbm_disparity, sgbm_params_for


#: The stop's sighting of what holds the robot, one point per cell this wide (m): the planner's grid cell.
SIGHTING_CELL_M = 0.05


def make_obstacle_stage(cfg) -> Optional["ObstacleStage"]:
    """The obstacle stage for a vbnav Config, or None when ``obstacles.enabled`` is false."""
    return ObstacleStage.from_config(cfg) if cfg.obstacles.enabled else None



def ground_model_params(cfg: ObstaclesConfig) -> Optional[GroundModelParams]:
    """The piecewise ground's settings from the ``obstacles:`` section, or None for one plane."""
    if cfg.ground_model == "plane":
        return None
    return GroundModelParams(band_ratio=cfg.ground_band_ratio, corridor_half_width=cfg.ground_corridor_half_width,
                             max_grade_change=cfg.max_grade_change,
                             cross_slope_allowance=cfg.cross_slope_allowance)


def points_in_polygon(pts: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd rule, vectorised over points: (N, 2) x (M, 2) -> (N,) bool."""
    x, z = pts[:, 0:1], pts[:, 1:2]
    x0, z0 = poly[:, 0][None, :], poly[:, 1][None, :]
    x1, z1 = np.roll(poly[:, 0], -1)[None, :], np.roll(poly[:, 1], -1)[None, :]
    crosses = (z0 > z) != (z1 > z)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = x0 + (z - z0) * (x1 - x0) / (z1 - z0)
    return np.count_nonzero(crosses & (x < x_at), axis=1) % 2 == 1



def in_zone(zone: ZoneConfig, pts: np.ndarray) -> np.ndarray:
    """Which of the (N, 2) x, z points lie inside the zone (a band or a polygon)."""
    if len(pts) == 0:
        return np.zeros(0, bool)
    if zone.polygon is not None:
        return points_in_polygon(pts, np.asarray(zone.polygon, dtype=np.float64))
    x, z = pts[:, 0], pts[:, 1]
    return (z > 0) & (z <= zone.distance) & (np.abs(x) <= zone.half_width)


def zone_counts(zone: ZoneConfig, pts: np.ndarray) -> int:
    return int(np.count_nonzero(in_zone(zone, pts)))


def _in_band(zone: ZoneConfig, pts: np.ndarray) -> np.ndarray:
    """The forward distances z of the points inside a band zone."""
    return pts[in_zone(zone, pts), 1]


def band_reach(zone: ZoneConfig, pts: np.ndarray) -> float:
    """How far ahead a band holds ``min_points`` of the points (the min_points-th nearest: fewer noise
    pixels than a zone needs to trigger do not set the distance either), inf when it holds fewer."""
    z = _in_band(zone, pts) if len(pts) else np.zeros(0)
    if len(z) < zone.min_points:
        return math.inf
    return float(np.partition(z, zone.min_points - 1)[zone.min_points - 1])


def approach_scale(zone: ZoneConfig, reach: float) -> float:
    """The speed scale of a stop band with ``min_distance`` for an obstacle ``reach`` m ahead.

    The band's length at full speed (``distance``) covers the stopping distance from full speed; at a
    fraction s of it the robot needs less: reaction time x speed + speed^2 / (2 deceleration), which is
    convex in the speed and so never longer than the straight line from ``min_distance`` at standstill to
    ``distance`` at full speed. Holding the speed to that line's s at an obstacle ``reach`` ahead keeps it
    able to stop before it, the way a safety laser scanner switches its protective field with the speed."""
    s = (reach - zone.min_distance) / (zone.distance - zone.min_distance)
    return min(1.0, max(0.0, s))



@dataclass
class ZoneVerdict:
    scale: float
    reason: str
    counts: dict
    turn_ok: bool = False       # a held stop (scale 0) that lets a turn on the spot through (turn_when_held)



class ObstacleMonitor:
    """Zones + k-of-n persistence + release debounce -> speed scale in [0, 1]. Pure logic, frame stamps."""

    def __init__(self, cfg: ObstaclesConfig):
        self.cfg = cfg
        self._filters = {z.name: KOfN(cfg.persist_k, cfg.persist_n) for z in cfg.zones}
        self._reach = {z.name: math.inf for z in cfg.zones}     # a speed-following band's last obstacle, m
        self.scale = 1.0
        self.reason = ""
        self.seen = False           # the held stop came from an obstacle seen in a stop zone, not from blindness
        self._raise_since: Optional[int] = None

    def update(self, stamp_ns: int, points: np.ndarray, negative_points: Optional[np.ndarray] = None) -> ZoneVerdict:
        """Feed one frame's obstacle points (robot frame, (N, 2) x/z); returns the debounced verdict."""
        pts = points
        if self.cfg.negative_stops and negative_points is not None and len(negative_points):
            pts = np.vstack([points, negative_points]) if len(points) else negative_points
        target, why, counts = 1.0, "", {}
        for z in self.cfg.zones:
            n = zone_counts(z, pts)
            counts[z.name] = n
            if self._filters[z.name].update(n >= z.min_points):
                s, why_z = (0.0 if z.action == "stop" else z.slow_scale), f"obstacle in zone {z.name!r} ({n} px)"
                if z.min_distance is not None:
                    # The band follows the speed: this frame's obstacle, or (a frame of the k-of-n without
                    # enough pixels) the last one seen.
                    reach = band_reach(z, pts)
                    self._reach[z.name] = reach = reach if math.isfinite(reach) else self._reach[z.name]
                    s = approach_scale(z, reach)
                    why_z += (f" {reach:.2f} m ahead, within {z.min_distance:g} m" if s <= 0.0 else
                              f" {reach:.2f} m ahead: speed x{s:.2f}")
                if s < target:
                    target, why = s, why_z
        if target < self.scale:                      # more caution: at once
            self.scale, self.reason, self._raise_since = target, why, None
            self.seen = True
        elif target > self.scale:                    # less caution: only after release_s clear
            if self._raise_since is None:
                self._raise_since = stamp_ns
            if stamp_ns - self._raise_since >= self.cfg.release_s * 1e9:
                self.scale, self.reason, self._raise_since = target, why, None
                self.seen = True
        else:
            self._raise_since = None
            if target < 1.0:
                self.reason = why
                self.seen = True        # an obstacle seen now holds it, not a blind frame before
        return ZoneVerdict(self.scale, self.reason, counts, self.turn_ok)

    @property
    def turn_ok(self) -> bool:
        """A held stop that lets a turn on the spot through: held by an obstacle seen, with turn_when_held."""
        return self.scale <= 0.0 and self.seen and self.cfg.turn_when_held

    def blind(self, reason: str) -> ZoneVerdict:
        """A frame on which the zones could not be seen: stop at once, and rise again only after
        ``release_s`` of frames that show them clear (a first clear frame is not enough)."""
        self.scale, self.reason, self._raise_since = 0.0, reason, None
        self.seen = False           # nothing seen: no turn either, until frames show the zones again
        return ZoneVerdict(0.0, reason, {})

    def reset(self) -> None:
        for f in self._filters.values():
            f.reset()
        self._reach = dict.fromkeys(self._reach, math.inf)
        self.scale, self.reason, self._raise_since = 1.0, "", None
        self.seen = False



@dataclass
class ObstacleReport:
    """Estimate.value of the obstacle stage (robot frame, metres / radians)."""

    speed_scale: float
    nearest: Optional[tuple[float, float]]            # (distance ahead, bearing) in the stop zone's width
    nearest_negative: Optional[tuple[float, float]]
    zone_counts: dict
    fractions: dict
    camera_height: float
    pitch: float
    fit_ok: bool
    labels: Optional[np.ndarray] = field(default=None, repr=False)



def to_robot_frame(points: np.ndarray, mount: CameraMount) -> np.ndarray:
    """Camera-floor (lateral, forward) points to the robot frame (x right, z forward), via the mount."""
    if len(points) == 0:
        return points.reshape(0, 2)
    c, s = math.cos(mount.yaw), math.sin(mount.yaw)
    px, pz = points[:, 0], points[:, 1]
    # Pose2(lateral, forward, yaw).compose(point), vectorised (vision/geometry.py)
    return np.column_stack([mount.lateral + c * px + s * pz, mount.forward - s * px + c * pz]).astype(np.float32)



def stop_zone_outline(camera, mount, half_width: float, max_range: float, near: float = 0.3) -> np.ndarray:
    """The stop corridor on the floor (|x| <= half_width, near <= z <= max_range, robot frame) in pixels.

    Robot frame: x right, y down, z forward, floor at y = 0; ``mount`` places the camera in it."""
    zs = np.linspace(near, max_range, 8)
    floor = np.array([(-half_width, 0.0, z) for z in zs] + [(half_width, 0.0, z) for z in zs[::-1]])
    R, t = mount.rotation(), mount.translation()
    pc = (floor - t) @ R                 # R^T (p - t), row-wise
    pc = pc[pc[:, 2] > 0.05]             # in front of the camera
    if len(pc) < 3:
        return np.zeros((0, 2))
    u = camera.fx * pc[:, 0] / pc[:, 2] + camera.cx
    v = camera.fy * pc[:, 1] / pc[:, 2] + camera.cy
    return np.column_stack([u, v])


def nearest_floor_ahead(camera, mount, half_width: float, max_range: float = 5.0, step: float = 0.005) -> float:
    """How far ahead of the axle (robot frame z, m) the camera's view of the floor begins across a band
    |x| <= half_width: for each lateral offset the nearest floor point that projects into the image, the
    farthest of those (sampled every ``step``; a lateral offset the camera does not see within ``max_range``:
    inf). Nearer than that an object lower than the camera's view (a step down, a low obstacle) is not seen."""
    x = np.linspace(-half_width, half_width, 51)
    z = np.arange(step, max_range + step, step)
    X, Z = np.meshgrid(x, z)                                                        # (nz, nx)
    floor = np.stack([X.ravel(), np.zeros(X.size), Z.ravel()], axis=1)
    pc = (floor - mount.translation()) @ mount.rotation()                          # R^T (p - t), row-wise
    with np.errstate(divide="ignore", invalid="ignore"):
        u = camera.fx * pc[:, 0] / pc[:, 2] + camera.cx
        v = camera.fy * pc[:, 1] / pc[:, 2] + camera.cy
    seen = ((pc[:, 2] > 1e-6) & (u >= 0) & (u <= camera.width - 1) & (v >= 0) & (v <= camera.height - 1)).reshape(X.shape)
    if not seen.any(axis=0).all():
        return math.inf
    return float(z[seen.argmax(axis=0)].max())


#: A "clear" verdict needs at least this share of the stop zones' floor to have a disparity. Measured
#: share in normal use: 0.91-1.00 (simulated room and corridor, frames' own disparity and SGBM, 60-frame
#: loop) and 0.96-1.00 on a real road (kitti06, SGBM, rows 250-370); a covered lens, a dark scene or
#: an all-NaN disparity gives 0.00. Half is far from both; below it most of where an obstacle would
#: stand was not seen, and a verdict from the rest is no verdict.
MIN_SEEN_FRACTION = 0.5


def _stop_zones(zones) -> list:
    """The stop zones (all zones when none stops)."""
    return [z for z in zones if z.action == "stop"] or list(zones)


def stop_half_width(zones) -> float:
    """The widest half-width of the stop zones (a polygon's: its largest |x|), m."""
    return max((z.half_width if z.polygon is None else max(abs(x) for x, _ in z.polygon)) for z in _stop_zones(zones))


def stop_reach(zones) -> float:
    """How far ahead of the axle an obstacle holds the robot for good, m: a stop band's ``distance`` (its
    ``min_distance`` when its length follows the speed: it crawls on to there), a polygon's farthest z."""
    def reach(z) -> float:
        if z.polygon is not None:
            return max(zz for _, zz in z.polygon)
        return z.min_distance if z.min_distance is not None else z.distance
    return max(reach(z) for z in _stop_zones(zones))


def watched_floor(camera, mount, zones) -> Optional[np.ndarray]:
    """(H, W) bool: the pixels that see the floor under the stop zones (the corridor of their widest
    half-width out to their farthest point, from 0.3 m), None if none of it is in view."""
    stops = _stop_zones(zones)
    half = stop_half_width(zones)
    far = max((z.distance if z.polygon is None else max(zz for _, zz in z.polygon)) for z in stops)
    outline = stop_zone_outline(camera, mount, half, far)
    if len(outline) < 3:
        return None
    mask = np.zeros((camera.height, camera.width), np.uint8)
    cv2.fillPoly(mask, [np.round(outline).astype(np.int32)], 1)
    return mask.astype(bool) if mask.any() else None


def seen_fraction(disp: np.ndarray, watched: Optional[np.ndarray]) -> float:
    """Share of the watched pixels with a disparity (finite, > 0); 1 when nothing is watched."""
    if watched is None:
        return 1.0
    d = disp[watched]
    return float(np.count_nonzero(np.isfinite(d) & (d > 0))) / max(d.size, 1)


class ObstacleStage(VisionStage):
    """Stereo obstacle detection and stop zones as a vision stage (kind "obstacles")."""

    kind = "obstacles"
    #: the runtime stops the robot when this stage's estimate is older than safety.estimate_timeout_s,
    #: so a slow or stalled disparity source never leaves an old "clear" in force.
    safety_critical = True

    def __init__(self, rig: Optional[StereoRig], mount: CameraMount, cfg: Optional[ObstaclesConfig] = None,
                 keep_labels: bool = False, camera: Optional[PinholeCamera] = None):
        """``rig``: the stereo pair; or None with the left ``camera``, and the baseline (and K, if
        given) is taken from the first frame's meta["baseline_m"] / meta["K"] (the OAK driver
        reports its device calibration there)."""
        self.cfg = cfg or ObstaclesConfig()
        self.mount = mount
        self.params = ObstacleParams(obstacle_height=self.cfg.obstacle_height,
                                     negative_depth=self.cfg.negative_depth, noise_px=self.cfg.noise_px,
                                     min_blob_pixels=self.cfg.min_blob_pixels, max_height=self.cfg.max_height,
                                     max_range=self.cfg.max_range, report_range=self.cfg.max_range)
        c = self.cfg
        self.fit_params = PlaneFitParams(inlier_height=c.fit_inlier_height, max_height_change=c.mount_height_tol,
                                         max_pitch_change_deg=c.mount_tilt_tol_deg,
                                         max_roll_change_deg=c.mount_tilt_tol_deg)
        self.ground = ground_model_params(c)
        self.monitor = ObstacleMonitor(self.cfg)
        self.keep_labels = keep_labels
        self._stop_half_width = stop_half_width(self.cfg.zones)
        # What holds the robot: (odometry at its frame, (N, 2) robot-frame x, z of the obstacle points in the
        # stop zones, one per 5 cm cell), or None while nothing does (``held_sighting``).
        self.sighting: Optional[tuple] = None
        self._camera = camera
        self.watched: Optional[np.ndarray] = None   # the stop zones' floor in the image (with the rig)
        self.rig: Optional[StereoRig] = None
        if rig is not None:
            self._set_rig(rig)
        elif camera is None:
            raise ValueError("ObstacleStage needs a StereoRig, or the camera intrinsics and frames that carry "
                             "meta['baseline_m']")

    def _set_rig(self, rig: StereoRig) -> None:
        self.rig = rig
        self.watched = watched_floor(rig.camera, self.mount, self.cfg.zones)
        self.prior = expected_plane(rig, self.mount.height, self.mount.pitch, self.mount.roll)
        nearest_floor = nearest_floor_m(rig, self.mount.height, self.mount.pitch)
        # More than 256 disparities: refused at config load when the rig is configured (config
        # sgbm_reach_problem); a rig from the frames' meta is an OAK's, whose own disparity is used.
        self.sgbm = sgbm_params_for(rig, self.cfg.sgbm_near_margin * nearest_floor, self.cfg.sgbm_block_size)

    def _rig_for(self, frame: Frame) -> tuple[Optional[StereoRig], str]:
        """(the stereo rig, ""), from the first frame whose meta['baseline_m'] is a finite distance > 0 (and
        meta['K'], if given, intrinsics of this image size) when the configuration gave none; else (None, why
        this frame gives none)."""
        if self.rig is not None:
            return self.rig, ""
        b, why = frame_baseline(frame)
        if b is None:
            return None, (f"no stereo baseline: {why} (set obstacles.baseline or camera.options.stereo_baseline, "
                          "or use a camera reporting meta['baseline_m'])")
        camera = self._camera
        K = frame.meta.get("K")
        if K is not None:
            try:
                K = np.asarray(K, dtype=np.float64)
            except (TypeError, ValueError):
                return None, (f"no stereo rig: the frame's meta['K'] is {K!r}: not numbers, expected a 3x3 camera "
                              "matrix")
            if K.shape != (3, 3):
                return None, (f"no stereo rig: the frame's meta['K'] has shape {K.shape}, expected a 3x3 camera "
                              "matrix")
            fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
            try:
                check_intrinsics("the frame's meta['K']", fx, fy, cx, cy, camera.width, camera.height)
            except CalibrationError as exc:
                return None, f"no stereo rig: {exc}"
            camera = replace(camera, fx=fx, fy=fy, cx=cx, cy=cy)
        self._set_rig(StereoRig(camera, b))
        return self.rig, ""

    @classmethod
    def from_config(cls, cfg, keep_labels: bool = False) -> "ObstacleStage":
        """From a vbnav Config: camera intrinsics and mount, ``obstacles:`` section, baseline from
        ``obstacles.baseline``, the camera's calibration file, ``camera.options.stereo_baseline`` or, failing
        all, the frames' meta (a calibration file that disagrees with the others is refused at config load)."""
        ocfg = cfg.obstacles
        baseline = ocfg.baseline or cfg.camera.stereo_baseline()
        c = cfg.camera
        # Rectified: no distortion (a distorted camera with obstacles on is refused at config load).
        camera = PinholeCamera(c.width, c.height, c.fx, c.fy, c.cx, c.cy)
        if not baseline:
            return cls(None, c.mount.to_mount(), ocfg, keep_labels, camera=camera)
        return cls(StereoRig(camera, float(baseline)), c.mount.to_mount(), ocfg, keep_labels)

    def _blind(self, frame: Frame, why: str) -> Estimate:
        """A frame on which the zones cannot be judged: not ok, stop (and the release debounce after it)."""
        self.monitor.blind(why)
        self.sighting = None
        return Estimate(frame.stamp_ns, self.kind, False, None, {"speed_scale": 0.0, "reason": why})

    def _sgbm_pair(self, frame: Frame) -> bool:
        """Whether this frame's disparity comes from SGBM on its stereo pair."""
        src = self.cfg.source
        if src in ("auto", "disparity") and frame.disparity is not None:
            return False
        return src in ("auto", "sgbm") and frame.right is not None

    @staticmethod
    def _pair_problem(frame: Frame) -> str:
        """Why SGBM cannot match this frame's pair ("" when it can): images of two sizes or dtypes, of
        another dtype than uint8 (as the tracking stages, ``dtype_problem``: each image stretched to 8 bits
        on its own matched two different exposures), or not HxW grey / HxWx3 BGR / HxWx4."""
        left, right = np.asarray(frame.image), np.asarray(frame.right)
        for what, im in (("left", left), ("right", right)):
            if not (im.ndim == 2 or (im.ndim == 3 and im.shape[2] in (1, 3, 4))):
                return f"the {what} image has shape {im.shape}, not HxW grey or HxWx3 BGR"
        if left.shape[:2] != right.shape[:2]:
            (lh, lw), (rh, rw) = left.shape[:2], right.shape[:2]
            return f"the left image is {lw}x{lh}, the right one {rw}x{rh}"
        if left.dtype != right.dtype:
            return f"the left image is {left.dtype}, the right one {right.dtype}"
        return dtype_problem(left, "left image")

    def disparity(self, frame: Frame) -> Optional[np.ndarray]:
        if self._sgbm_pair(frame):
            return sgbm_disparity(frame.image, frame.right, self.sgbm)
        return frame.disparity if self.cfg.source in ("auto", "disparity") else None

    def overlay(self, estimate: Optional[Estimate]) -> StageOverlay:
        """The stop corridor once the stereo rig is known, and the obstacle labels of ``estimate``
        when this stage keeps them (``keep_labels``)."""
        zone = None
        if self.rig is not None:
            zone = stop_zone_outline(self.rig.camera, self.mount, self._stop_half_width, self.cfg.max_range)
        report = estimate.value if estimate is not None else None
        return StageOverlay(stop_zone=zone, obstacle_labels=None if report is None else report.labels)

    def _keep_sighting(self, verdict: ZoneVerdict, pts: np.ndarray, neg: np.ndarray, odom: Pose2) -> None:
        """While an obstacle seen in a stop zone holds the robot, the points there (a held frame of the k-of-n or
        of the release debounce that shows none keeps the last ones); none once the hold ends."""
        if verdict.scale > 0.0 or not self.monitor.seen:
            self.sighting = None
            return
        both = np.vstack([pts, neg]) if len(neg) and self.cfg.negative_stops else pts
        inside = np.zeros(len(both), bool)
        for z in _stop_zones(self.cfg.zones):
            inside |= in_zone(z, both)
        if inside.any():
            cells = np.unique(np.round(both[inside] / SIGHTING_CELL_M).astype(np.int64), axis=0)
            self.sighting = (odom, cells * SIGHTING_CELL_M)

    def process(self, frame: Frame, odom: Pose2) -> Optional[Estimate]:
        rig, got = self._rig_for(frame)
        if rig is None:
            self.sighting = None
            return Estimate(frame.stamp_ns, self.kind, False, None, {"speed_scale": 0.0, "reason": f"obstacles: {got}"})
        why = self._pair_problem(frame) if self._sgbm_pair(frame) else ""
        if why:
            return self._blind(frame, f"obstacles: blind: {why}: no stereo matching between them")
        disp = self.disparity(frame)
        if disp is None:
            # No depth at all: blind, so stop (a stale or missing stage would stop the robot too).
            src = self.cfg.source
            if src == "disparity" and frame.right is not None:
                why = "obstacles: frame has no disparity (obstacles.source is disparity: its right image is not used)"
            elif src == "sgbm" and frame.disparity is not None:
                why = "obstacles: frame has no right image (obstacles.source is sgbm: its disparity is not used)"
            else:
                why = "obstacles: frame has no disparity and no right image"
            return self._blind(frame, why)
        why = disparity_problem(disp, self.rig)
        if why:
            # An integer one taken as pixels puts the floor above the plane; the zones are laid out for the
            # configured size, and a frame of another one cannot be judged.
            return self._blind(frame, f"obstacles: blind: {why}")
        seen = seen_fraction(disp, self.watched)
        if seen < MIN_SEEN_FRACTION:
            # A covered lens, darkness or a blank view gives no disparity where the zones are: nothing
            # there can be found, so nothing there can be called clear.
            return self._blind(frame, f"obstacles: blind: {seen:.0%} of the stop zones' floor has a disparity "
                                      f"(needs {MIN_SEEN_FRACTION:.0%}): covered lens, darkness or no texture")
        scene = detect_obstacles(disp, self.rig, self.prior, self.fit_params, self.params, self.ground)
        pts = to_robot_frame(scene.obstacle_points, self.mount)
        neg = to_robot_frame(scene.negative_points, self.mount)
        verdict = self.monitor.update(frame.stamp_ns, pts, neg)
        self._keep_sighting(verdict, pts, neg, odom)
        near = nearest_in_corridor(pts, self._stop_half_width, self.cfg.max_range)
        near_neg = nearest_in_corridor(neg, self._stop_half_width, self.cfg.max_range)
        fl = scene.fit.floor
        report = ObstacleReport(verdict.scale, None if near is None else (near.distance, near.bearing),
                                None if near_neg is None else (near_neg.distance, near_neg.bearing),
                                verdict.counts, scene.fractions, fl.height, fl.pitch, scene.fit.ok,
                                scene.labels if self.keep_labels else None)
        info = {"speed_scale": verdict.scale, "reason": f"obstacles: {verdict.reason}" if verdict.reason else "",
                "nearest_m": report.nearest[0] if report.nearest else None, "zones": verdict.counts,
                "turn_ok": verdict.turn_ok}
        return Estimate(frame.stamp_ns, self.kind, True, report, info)
