"""Mapping while driving for ``vbnav goto --map`` (docs/line_map.md, "Re-planning as the map grows").

``LiveMap`` puts together what keeps the loaded line map growing during a goto and the route clear:
- the line-map stage (Marvin's fast loop), posed by the VSLAM in the map's frame, into the loaded map;
  on a real clock off the VSLAM's thread (``BackgroundStage``);
- its slow abstraction loop;
- the re-planner (``map_planning.Replanner``), which hands the goto controller a new route when the grown
  map blocks the old one.
On a simulated clock the two slow loops are stepped inline by ``tick`` (deterministic runs); on a real
clock they run in their own threads between ``start`` and ``stop``.
"""
from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from vbnav.control.map_planning import Replanner
from vbnav.control.stages.background import BackgroundStage
from vbnav.control.stages.line_map import LineMapStage
from vbnav.vision.geometry import Pose2


class LiveMap:
    def __init__(self, line_stage: LineMapStage, meta: dict):
        self.line_stage = line_stage
        self.meta = meta
        self.stage = BackgroundStage(line_stage, inline=True)   # the pipeline's stage; see ``attach``
        self.replanner: Optional[Replanner] = None
        self.told = 0                      # re-planner events already printed
        self.ticks = 0                     # calls of ``tick``
        self.pose_in_map: Callable[[Pose2], Pose2] = lambda odom: odom   # odometry -> the robot in the map

    @classmethod
    def for_goto(cls, cfg, lmap, meta: dict, vslam_stage, start: Callable[[], Pose2]
                 ) -> tuple[Optional["LiveMap"], str]:
        """(LiveMap, "") mapping into ``lmap``, posed by ``vslam_stage`` in the map's frame (``start()``: the
        robot's start pose there); (None, why) when the camera has no stereo pair."""
        def pose_in_map(odom: Pose2) -> Pose2:
            # The VSLAM's last good pose carried to this frame's odometry (the frame's own pose when the
            # stage runs right after the VSLAM's; a later one's carried back when it runs in its thread).
            p = vslam_stage.pose_at(odom)
            return start().compose(odom if p is None else p)

        try:
            live = cls(LineMapStage.from_config(cfg, lmap=lmap, pose_fn=pose_in_map), meta)
            live.pose_in_map = pose_in_map
            return live, ""
        except ValueError as exc:
            return None, str(exc)

    def attach(self, controller, simulated_clock: bool, start: Pose2, goal_map: Pose2, robot_radius: float,
               goal_moved_m: float | None = None, approach=None, obstacle_stage=None) -> None:
        """Once the robot and the controller exist: the clock decides inline or threads; the re-planner
        steers ``controller`` from ``start`` (the robot's start pose in the map) to ``goal_map``;
        ``goal_moved_m``: how far the start plan ended from it (a goal in the planner's margin), None at it;
        ``approach``: the obstacle stop's band (``map_planning.stop_approach``) the routes' last legs must clear;
        ``obstacle_stage``: its sighting of what holds the robot is drawn into the planner's grid."""
        self.stage.inline = simulated_clock
        self.replanner = Replanner(self.line_stage, self.meta, start, goal_map, robot_radius, controller,
                                   lambda: controller.pose, approach=approach,
                                   sightings=None if obstacle_stage is None else lambda: self._sighting(obstacle_stage))
        self.replanner.goal_moved_m = goal_moved_m     # the map freeing the goal sends the robot to it

    def _sighting(self, obstacle_stage) -> Optional[np.ndarray]:
        """The obstacle stage's sighting (robot frame, at its frame's odometry) in the map's frame."""
        seen = obstacle_stage.sighting
        if seen is None:
            return None
        odom, pts = seen
        p = self.pose_in_map(odom)
        c, s = np.cos(p.theta), np.sin(p.theta)
        return np.column_stack([p.x + c * pts[:, 0] + s * pts[:, 1], p.z - s * pts[:, 0] + c * pts[:, 1]])

    @property
    def inline(self) -> bool:
        return self.stage.inline

    def tick(self, sim_s: float) -> None:
        """Called every ``sim_s`` simulated seconds on a simulated clock: steps the slow loops at their
        periods (the abstraction every ``period_s``, the re-planner every ``period_s``)."""
        if not self.inline:
            return
        self.ticks += 1
        if self.ticks % max(1, round(self.line_stage.abstraction.period_s / sim_s)) == 0:
            self.line_stage.abstraction.step()
        if self.ticks % max(1, round(self.replanner.period_s / sim_s)) == 0:
            self.replanner.step()

    def new_events(self) -> list[str]:
        """What the re-planner did since the last call."""
        ev, self.told = self.replanner.events_since(self.told)
        return ev

    def start(self) -> None:
        if not self.inline:
            self.stage.start()
            self.replanner.start_thread()

    def stop(self) -> None:
        if not self.inline:
            self.replanner.stop_thread()
            self.stage.stop()

    def summary(self) -> str:
        s = self.line_stage.map.summary()
        ms = np.array(self.line_stage.frame_ms) if self.line_stage.frame_ms else np.zeros(1)
        where = ("on the vision thread" if self.inline else
                 f"in its own thread; {self.stage.replaced} frames came while it was busy")
        return (f"map while driving: {self.line_stage.stats['frames']} frames, {s['verified']} verified segments, "
                f"{self.replanner.checks} checks of the route, {self.replanner.replans} re-plans; the map's fast "
                f"loop {np.median(ms):.0f} ms median, {np.percentile(ms, 95):.0f} ms p95, {ms.max():.0f} ms max "
                f"per frame (detection and update, {where})" + self._goal_moved())

    def _goal_moved(self) -> str:
        moved = self.replanner.goal_moved_m
        if moved is None:
            return ""
        return (f"; the goal lay within the planner's margin of what the map holds (map noise), so the route "
                f"ended at the nearest free point, {moved:.3f} m from it (the pose and errors below are against the goal as given)")

    def save(self, path: str) -> None:
        """Write the grown map; its objects abstracted again from the whole map (as ``map build`` does), not
        added to the file's: the same box would otherwise be stored once per drive."""
        from vbnav.control.line_map_file import objects_meta, save_map

        ab = self.line_stage.abstraction
        ab.step()
        meta = dict(self.meta, frames=int(self.meta.get("frames", 0)) + self.line_stage.stats["frames"],
                    objects=objects_meta(ab.polygons))
        save_map(self.line_stage.map, path, meta)
