"""Closed-loop evaluation of the VSLAM on the simulated robot (used by hil_tests and benchmarks/vslam_loop.py).

``ChainedVoStage`` is the baseline: frame-to-frame motions with the VSLAM's own
tracker, stereo reconstruction and motion solver, chained.

``run_vslam_loop`` drives the simulated robot once around a ~10 m loop with
``PathFollower`` on odometry while two stages watch the same frames: the VSLAM
(pose against the reference set, ``VslamStage``) and the chained frame-to-frame
baseline (``ChainedVoStage``: same tracker, stereo reconstruction and motion
solver). Ground truth (the pose each frame was rendered from) is used only to
measure. Errors are planar, in the reference frame (the robot's start pose).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from vbnav.control.config import Config, deep_merge, load_config, parse_config
from vbnav.control.runtime.interfaces import Estimate, VisionStage
from vbnav.control.runtime.factory import make_robot
from vbnav.control.controllers.path import PathFollower, path_length, rounded_rectangle
from vbnav.control.runtime.runtime import Runtime
from vbnav.control.stages.vslam import VslamFix, camera_to_robot, make_vslam_stage, robot_to_camera_matrix
from vbnav.drivers.camera import Frame
from vbnav.vision.features import to_grey
from vbnav.vision.geometry import CameraMount, Pose2, wrap_angle
from vbnav.vision.vslam import Vslam, VslamConfig


class ChainedVoStage(VisionStage):
    """The baseline the reference set is judged against: frame-to-frame motions, chained.

    Same tracker, same stereo reconstruction and same motion solver as the
    VSLAM, but every frame's landmarks are reconstructed afresh from the
    previous stereo pair and the pose is the product of all frame-to-frame
    motions (what section 11.3.3.2 says the reference set avoids).
    """

    kind = "chained_vo"

    def __init__(self, camera, mount: CameraMount, stereo_baseline: float, cfg: VslamConfig | None = None):
        self.camera = camera
        self.mount = mount
        self.baseline = float(stereo_baseline)
        # No landmark top-up on the current frame: the next step reconstructs its own from the stereo pair.
        self.cfg = (cfg or VslamConfig()).model_copy(update={"min_landmarks": 4})
        self.pose_wc: Optional[np.ndarray] = None
        self._prev: Optional[tuple[np.ndarray, np.ndarray]] = None
        self.lost = 0

    def process(self, frame: Frame, odom: Pose2) -> Estimate:
        image, right = to_grey(frame.image), to_grey(frame.right)
        if self.pose_wc is None:
            self.pose_wc = robot_to_camera_matrix(odom, self.mount)
        else:
            step = Vslam(self.camera, self.cfg, stereo_baseline=self.baseline)
            step.initialise_stereo(*self._prev)
            res = step.process(image)
            if res.ok:
                self.pose_wc = self.pose_wc @ res.pose_wc   # res.pose_wc: previous-from-current camera
            else:
                self.lost += 1
        self._prev = (image, right)
        pose = camera_to_robot(self.pose_wc, self.mount)[0]
        return Estimate(frame.stamp_ns, self.kind, True, VslamFix(pose, odom, self.pose_wc.copy(), 0, 0))


def loop_route() -> np.ndarray:
    """A 10.3 m closed loop (3.4 m x 2.2 m, 0.5 m corner radius) in the south of World.room(), clear of boxes."""
    return rounded_rectangle((0.0, -2.3), (3.4, 2.2), 0.5)


def fast_stereo_config(rate_hz: float = 10.0, width: int = 320, base: Optional[Config] = None) -> Config:
    """configs/sim_stereo.yaml at a lower camera rate and resolution (same field of view), obstacle stop
    off, for short tests of the VSLAM's accuracy."""
    s = width / 640.0
    h = int(round(480 * s))
    over = {"camera": {"rate_hz": rate_hz, "width": width, "height": h, "fx": 400.0 * s, "fy": 400.0 * s,
                       "cx": (width - 1) / 2.0, "cy": (h - 1) / 2.0},
            # the comparison is about estimates, not loop timing: a loaded machine must not trip the stop
            "loop": {"max_missed_streak": 10 ** 6},
            # nor about the obstacle stop (hil_tests/test_hil_obstacle_stop.py): the loop passes 1 m from a wall
            "obstacles": {"enabled": False}}
    if base is not None:
        return parse_config(deep_merge(base.model_dump(), over), base.source or "<config>")
    return load_config("sim_stereo", overrides=over)


@dataclass
class LoopResult:
    stamps: np.ndarray          # s
    truth: np.ndarray           # (K, 3) x, z, theta of the robot in the reference frame
    vslam: np.ndarray           # (K, 3)
    chained: np.ndarray         # (K, 3)
    anchor: list                # per frame: anchor the VSLAM pose was computed against directly (or None)
    vslam_ok: np.ndarray        # (K,) bool
    distance_m: float           # true path length driven
    stats: dict
    chained_lost: int
    wall_s: float
    reason: str
    others: dict = None         # kind -> (K, 3) poses of extra stages (peers run on the same frames)

    @staticmethod
    def _err(est: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
        return (float(math.hypot(est[0] - truth[0], est[1] - truth[1])),
                float(abs(math.degrees(wrap_angle(est[2] - truth[2])))))

    def return_frame(self, anchor: int = 0) -> int:
        """Index of the last frame whose pose was computed directly against ``anchor`` (-1 if none)."""
        hits = [i for i, a in enumerate(self.anchor) if a == anchor]
        return hits[-1] if hits else -1

    def errors_at(self, i: int) -> dict:
        """Position (m) and heading (deg) errors of both estimates at frame ``i``."""
        pv, hv = self._err(self.vslam[i], self.truth[i])
        pc, hc = self._err(self.chained[i], self.truth[i])
        return {"frame": i if i >= 0 else len(self.stamps) + i, "vslam_m": pv, "vslam_deg": hv,
                "chained_m": pc, "chained_deg": hc, "ratio": pv / pc if pc > 0 else float("inf"),
                "anchor": self.anchor[i]}

    def max_vslam_error_m(self) -> float:
        return float(np.max(np.hypot(*(self.vslam[:, :2] - self.truth[:, :2]).T)))


def run_vslam_loop(cfg: Optional[Config] = None, speed: float = 0.4, extra_stages: tuple = ()) -> LoopResult:
    """One lap of ``loop_route()``; ``extra_stages`` (VisionStages whose Estimate.value has a ``pose``
    Pose2 in the reference frame) run on the same frames as peers."""
    cfg = cfg or fast_stereo_config()
    path = loop_route()
    d = path[1] - path[0]
    start = Pose2(float(path[0][0]), float(path[0][1]), math.atan2(d[0], d[1]))
    cfg = cfg.model_copy(deep=True)
    cfg.sim.set_start(start)
    stage = make_vslam_stage(cfg)
    chained = ChainedVoStage(stage.camera, stage.mount, stage.baseline, stage.cfg)
    robot = make_robot(cfg, [stage, chained, *extra_stages])
    pipeline = robot.pipeline
    rows: list = []

    def record(frame, results):
        t = start.between(frame.meta["true_pose"])
        v, c = results["vslam"], results["chained_vo"]
        rows.append((frame.stamp_ns * 1e-9, t.as_array(), v.value.pose.as_array(), c.value.pose.as_array(),
                     v.value.anchor, v.ok, {s.kind: results[s.kind].value.pose.as_array() for s in extra_stages}))

    pipeline.frame_listeners.append(record)
    rt = Runtime(cfg, robot.drive, PathFollower(path, speed, start=start), robot.clock, pipeline)
    t0 = time.perf_counter()
    result = rt.run(3.0 * path_length(path) / speed)
    wall = time.perf_counter() - t0
    truth = np.array([r[1] for r in rows])
    return LoopResult(np.array([r[0] for r in rows]), truth, np.array([r[2] for r in rows]),
                      np.array([r[3] for r in rows]), [r[4] for r in rows], np.array([r[5] for r in rows]),
                      path_length(truth[:, :2]), dict(stage.stats), chained.lost, wall, result.reason,
                      {s.kind: np.array([r[6][s.kind] for r in rows]) for s in extra_stages})
