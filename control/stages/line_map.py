"""Marvin's three loops on the robot (section 11.2.1.1, Fig. 11.3).

- ``LineMapStage`` (a VisionStage, kind "line_map"): the fast sensor loop, on the vision thread at frame
  rate. Per stereo frame: predict the verified map segments from the pose, detect and match the pair with
  the prediction as a prior (guided matching), fuse the 3D segments into the DLM (vision/line_map.py),
  count misses, verify and prune. First it inserts the hypotheses the slow loop posted since the last frame.
- ``AbstractionThread``: the slow loop, in its own thread every ``period_s``: takes a snapshot of the
  verified segments, abstracts them to vertical edges and object polygons (vision/line_abstraction.py),
  measures a box's top and lower edges in a snapshot of the map's keyframes (vision/line_sighting.py) and
  posts the hypotheses with their measurements back through a queue; it never touches the map itself. The
  fast loop inserts them: a box's measurement (40-100 ms) is the slow loop's work, not a frame's. On a simulated
  clock (``LineMapStage.abstraction_inline``) the stage steps it itself, after the first frame whose stamp
  is ``period_s`` past the last pass: the map then does not depend on how fast the machine ran the drive.
- The mission loop (map-based goto, control/controllers/goto.py) reads the stage's object polygons and
  verified segments to plan on a traversability grid (vision/nav_grid.py).

The pose comes from ``pose_fn(odom)`` (default: the wheel odometry, in the frame the robot started in,
which is the map's frame).

The stage's overlay is a ``MapScene``: a copy of the map's segments taken when the map changed (a
``revision`` count), which the telemetry link publishes as a Foxglove scene at the scene rate
(comms/link.py, ``/vbnav/map/lines``); encoding happens on the telemetry thread.
"""
from __future__ import annotations

import queue
import threading
import time
from collections import deque
from types import SimpleNamespace
from typing import Callable, NamedTuple, Optional

import numpy as np

from vbnav.control.config import ONE_IMAGE_CAMERAS, no_right_image
from vbnav.control.runtime.interfaces import Estimate, StageOverlay, VisionStage
from vbnav.control.stages.frame_input import odometry_problem, stage_image
from vbnav.drivers.camera import Frame
from vbnav.vision.geometry import CameraMount, Pose2, camera_pose
from vbnav.vision.line_abstraction import AbstractionParams, missing_lines, object_polygons, pinned_ends
from vbnav.vision.line_map import LineMap, MapParams
from vbnav.vision.line_floor import floor_segments
from vbnav.vision.line_motion import motion_segments
from vbnav.vision.line_segments import LineParams, Segments3D, reconstruct_pair
from vbnav.vision.line_sighting import sight_hypotheses
from vbnav.vision.line_vertical_kernel import warm_up as warm_up_vertical_kernel

KEYFRAME_BASELINE_M = 0.15     # motion triangulation pairs the frame with a keyframe at least this far back


class MapScene(NamedTuple):
    """A copy of the map's segments at one ``revision`` (the count of map changes): P (N, 2, 3) world
    metres, verified and hypothesis (N,) bool."""

    revision: int
    P: np.ndarray
    verified: np.ndarray
    hypothesis: np.ndarray

    @classmethod
    def of(cls, lmap: LineMap, revision: int = 0) -> "MapScene":
        return cls(revision, lmap.P.copy(), lmap.verified.copy(), lmap.hypothesis.copy())


class AbstractionThread:
    """The slow loop: polygons and missing-line hypotheses from snapshots of the map, posted to a queue."""

    def __init__(self, snapshot: Callable[[], np.ndarray], period_s: float = 1.0,
                 params: AbstractionParams = AbstractionParams(),
                 sight: Optional[Callable[[np.ndarray, np.ndarray], list]] = None):
        """snapshot: the map's verified segments (a copy). sight(hypotheses, pinned ends): their measurements
        in the map's keyframes (one ``HorizontalFix`` or None each; ``LineMapStage.sight``); None posts them
        unmeasured."""
        self.snapshot = snapshot
        self.sight = sight
        self.period_s = float(period_s)
        self.params = params
        self.hypotheses: queue.Queue = queue.Queue()
        self.polygons: list = []
        self.runs = 0
        self._posted: set = set()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self.error: Optional[str] = None    # why the thread stopped; the fast loop raises it (check())
        self._exc: Optional[BaseException] = None

    def check(self) -> None:
        """Raise the thread's failure, if it failed: the stage's next frame fails with it, so the pipeline's
        fault stops the robot (the map would otherwise go on without objects or hypotheses, unannounced)."""
        if self.error is not None:
            raise RuntimeError(f"line-map abstraction thread failed: {self.error}") from self._exc

    def step(self) -> int:
        """One abstraction pass (also callable inline, e.g. on a simulated clock): posts (hypotheses (K, 2, 3),
        their fixes or None) per object not posted before. Returns the hypotheses posted."""
        P = self.snapshot()
        polys = object_polygons(P, self.params)
        self.polygons = polys
        posted = 0
        for poly in polys:
            hyp = missing_lines(poly, self.params)
            if len(hyp) == 0:
                continue
            key = tuple(np.round(poly.footprint.ravel(), 1))     # post each object's hypotheses once
            if key in self._posted:
                continue
            self._posted.add(key)
            self.hypotheses.put((hyp, self.sight(hyp, pinned_ends(hyp, poly)) if self.sight is not None else None))
            posted += len(hyp)
        self.runs += 1
        return posted

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="vbnav-line-abstraction", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def _run(self) -> None:
        try:
            while not self._stop.wait(self.period_s):
                self.step()
        except Exception as exc:        # an uncaught error would end the thread with a line on stderr only
            self._exc = exc             # with its traceback: the stage's failure is raised from it
            self.error = repr(exc)


class LineMapStage(VisionStage):
    kind = "line_map"

    def __init__(self, fx: float, fy: float, cx: float, cy: float, width: int, height: int, baseline: float,
                 mount: CameraMount, line_params: LineParams = LineParams(), map_params: MapParams = MapParams(),
                 lmap: Optional[LineMap] = None, pose_fn: Optional[Callable[[Pose2], Pose2]] = None,
                 abstraction_period_s: Optional[float] = 1.0, guided: bool = True, motion: bool = False,
                 floor: bool = True):
        self.cam = (fx, fy, cx, cy)
        self.size = (width, height)
        self._frame_size = SimpleNamespace(width=width, height=height)    # what stage_image checks frames against
        self.baseline = baseline
        self.mount = mount
        self.line_params = line_params
        self.map = lmap if lmap is not None else LineMap(map_params)
        self.pose_fn = pose_fn or (lambda odom: odom)
        self.guided = guided
        self.motion = motion
        self.floor = floor
        self._key = None              # (left segments, R_wc, t_wc) of the last keyframe
        self.lock = threading.Lock()
        self.stats = {"frames": 0, "hypotheses_in": 0, "update_ms": 0.0, "detect_ms": 0.0, "unusable": 0}
        self.frame_ms: deque = deque(maxlen=4096)  # detection + update of the recent frames, for summaries
        self.revision = 0             # counts the frames that changed the map
        self.unusable_reason = ""     # why the last frame the stage could not use was refused
        self._scene: Optional[MapScene] = None
        self.abstraction = None
        self.abstraction_inline = False     # step the slow loop on the frames' time (a simulated clock)
        self._last_pass_ns: Optional[int] = None
        if abstraction_period_s is not None:
            self.abstraction = AbstractionThread(self.structure_snapshot, abstraction_period_s, sight=self.sight)
        warm_up_vertical_kernel()     # compile now (or load numba's cache), not in the vision thread's first frame

    @classmethod
    def from_config(cls, cfg, lmap: Optional[LineMap] = None, **kw) -> "LineMapStage":
        cam = cfg.camera.to_model()
        refusal = cfg.camera.rectified_refusal("the line map", "rectify the pair, e.g. with a stereo calibration "
                                               "file")
        if refusal:
            raise ValueError(refusal)
        baseline = cfg.camera.stereo_baseline()    # the calibration file's, else camera.options.stereo_baseline
        one_image = no_right_image(cfg) if cfg.camera.driver in ONE_IMAGE_CAMERAS else ""
        if one_image:
            # Its frames were each skipped as unusable: `map build` drove its whole script to save an empty map,
            # `goto --map` re-planned on a map that never grew (and a stereo baseline, as the message below
            # asks, would not have helped)
            raise ValueError(f"the line map matches segments in both images of a stereo pair, and {one_image}")
        if not baseline:
            if cfg.camera.driver == "oak":     # its options have no baseline: the device's is checked against it
                raise ValueError("the line map needs the stereo baseline, and no camera.calibration_file gives one: "
                                 "give it a stereo calibration (the OAK checks it against its own at start-up)")
            raise ValueError("the line map needs a stereo pair: neither camera.calibration_file nor "
                             "camera.options.stereo_baseline gives a stereo baseline")
        return cls(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, float(baseline),
                   cfg.camera.mount.to_mount(), lmap=lmap, **kw)

    def verified_snapshot(self) -> np.ndarray:
        with self.lock:
            return self.map.P[self.map.verified].copy()

    def structure_snapshot(self) -> np.ndarray:
        """The verified segments objects are abstracted from (``LineMap.structure``)."""
        with self.lock:
            return self.map.structure().copy()

    def sight(self, hyp: np.ndarray, pinned: Optional[np.ndarray] = None) -> list:
        """The slow loop's measurements of hypotheses hyp (K, 2, 3) in a snapshot of the map's keyframes
        (taken under the lock; the map replaces its keyframe list, never changes it in place). pinned (K, 2):
        the ends at seen corners (``pinned_ends``; None: all)."""
        with self.lock:
            keyframes = list(self.map.keyframes)
            params = self.map.params
        fx, fy, cx, cy = self.cam
        return sight_hypotheses(hyp, keyframes, (fx, fy, cx, cy, self.baseline, *self.size), params, pinned=pinned)

    def overlay(self, estimate: Optional[Estimate]) -> StageOverlay:
        """The map's segments, copied once per revision (the link publishes them at the scene rate)."""
        return StageOverlay(line_map=self.scene())

    def scene(self) -> MapScene:
        with self.lock:
            if self._scene is None or self._scene.revision != self.revision:
                self._scene = MapScene.of(self.map, self.revision)
            return self._scene

    def start(self) -> None:
        if self.abstraction is not None and not self.abstraction_inline:
            self.abstraction.start()

    def stop(self) -> None:
        if self.abstraction is not None:
            self.abstraction.stop()

    def process(self, frame: Frame, odom: Pose2) -> Optional[Estimate]:
        if self.abstraction is not None:
            self.abstraction.check()
        left, right, why = self._images(frame)
        why = why or odometry_problem(odom)
        if why:
            # One frame without its right image (or of another size) is no fault of the run: not ok, the
            # map is left as it is and the next frame goes on. A camera with no stereo baseline at all is
            # refused when the stage is built (from_config).
            self.stats["unusable"] += 1
            self.unusable_reason = why
            with self.lock:
                summary = self.map.summary()
            return Estimate(frame.stamp_ns, self.kind, False, summary, {"reason": f"line map: {why}"})
        fx, fy, cx, cy = self.cam
        W, H = self.size
        pose = self.pose_fn(odom)
        R, t = camera_pose(pose, self.mount)
        t0 = time.perf_counter()
        with self.lock:
            if self._drain_hypotheses():
                self.revision += 1
            pred = self.map.predict(R, t, fx, fy, cx, cy, self.baseline, W, H)
        prior_fn = (lambda segs: self.map.prior_for(segs, pred)) if self.guided else None
        # The world's vertical in the camera frame (R: camera to world) for the vertical lines' pencil.
        res = reconstruct_pair(left, right, fx, fy, cx, cy, self.baseline, self.line_params, prior_fn,
                               vertical=R[1])
        segs = res.segments
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        if self.floor:
            # Near-horizontal segments on the floor (box and wall feet): the known floor plane, checked in the pair.
            segs = Segments3D.concat([segs, floor_segments(res.left, left, right, K, self.baseline, R, t)])
        if self.motion:
            # Near-horizontal segments (no disparity of their own) from the robot's motion since the keyframe.
            if self._key is not None:
                segs = Segments3D.concat([segs, motion_segments(res.left, R, t, *self._key, K)])
            if self._key is None or np.linalg.norm(t - self._key[2]) >= KEYFRAME_BASELINE_M:
                self._key = (res.left, R, t)
        t1 = time.perf_counter()
        with self.lock:
            everything = self.map.predict(R, t, fx, fy, cx, cy, self.baseline, W, H,
                                          which=np.ones(len(self.map), bool))
            st = self.map.update(segs, R, t, everything, res.left, left)   # left: kept with a keyframe
            if st.fused or st.inserted or st.verified or st.pruned or st.rivals_dropped:
                self.revision += 1
            summary = self.map.summary()
        t2 = time.perf_counter()
        self.stats["frames"] += 1
        self._step_inline(frame.stamp_ns)
        self.stats["detect_ms"] = (t1 - t0) * 1e3
        self.stats["update_ms"] = (t2 - t1) * 1e3
        self.frame_ms.append((t2 - t0) * 1e3)
        return Estimate(frame.stamp_ns, self.kind, True, summary,
                        {"segments": len(res.left), "reconstructed": len(segs), "fused": st.fused,
                         "inserted": st.inserted, "verified_now": st.verified, "pruned": st.pruned,
                         "predicted": len(pred)})

    def _step_inline(self, stamp_ns: int) -> None:
        """On a simulated clock: the slow loop's pass once ``period_s`` of frame time has passed since the
        last (or since the first frame); its hypotheses are inserted before the next frame."""
        if self.abstraction is None or not self.abstraction_inline:
            return
        if self._last_pass_ns is None:
            self._last_pass_ns = stamp_ns
        elif stamp_ns - self._last_pass_ns >= self.abstraction.period_s * 1e9 - 1e3:
            self._last_pass_ns = stamp_ns
            self.abstraction.step()

    def _images(self, frame: Frame) -> tuple[Optional[np.ndarray], Optional[np.ndarray], str]:
        """(left, right, "") as the line map takes them (``stage_image``: HxW grey uint8 of the camera's size;
        colour and HxWx1 made grey), or (None, None, why the line map cannot use this frame): no right image,
        an image of another size than the camera's calibration (the segments would be triangulated with the
        wrong intrinsics), or of another dtype than uint8."""
        if frame.right is None:
            return None, None, "the frame has no right image (the line map needs a stereo pair)"
        left, why = stage_image(frame.image, self._frame_size, "image")
        right, why_right = stage_image(frame.right, self._frame_size, "right image")
        why = why or why_right
        return (None, None, why) if why else (left, right, "")

    def _drain_hypotheses(self) -> int:
        """Insert the hypotheses the slow loop posted; returns how many."""
        n = 0
        while self.abstraction is not None:
            try:
                hyp, fixes = self.abstraction.hypotheses.get_nowait()
            except queue.Empty:
                break
            # A top or lower edge comes measured in the keyframes by the slow loop (it comes when its box's
            # corners were verified, often as the box leaves the view).
            self.map.add_hypotheses(hyp, fixes=fixes)
            n += len(hyp)
        self.stats["hypotheses_in"] += n
        return n
