"""The demo scenario: teach a closed route in the simulated room, repeat it from an offset start.

Every run here is the real runtime (loop, safety, pipeline) with the simulated
base and camera on the simulated clock. Ground truth comes from the simulator
and is used only to measure, never to steer.

Lateral error is the distance of the repeated (true) positions to the taught
(true) path. It is measured once the robot has recovered from the deliberate
start offset: from ``settle_m`` metres along the route on (the recovery itself
is reported as the distance travelled until the error first falls under 5 cm).
"""
from __future__ import annotations

import json
import math
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from vbnav.control.config import Config, load_config
from vbnav.control.runtime.factory import make_pipeline
from vbnav.control.controllers.path import PathFollower, lateral_errors, path_length, rounded_rectangle
from vbnav.control.runtime.runtime import Runtime
from vbnav.drivers.clock import SimClock
from vbnav.drivers.sim.base import BaseParams, SimDiffDrive
from vbnav.vision.geometry import Pose2


@dataclass
class Scenario:
    seed: int = 0
    repeats: int = 2
    offset_lateral_m: float = 0.3
    offset_heading_deg: float = 10.0
    speed: float = 0.4                                  # m/s when teaching
    occlusion: Optional[tuple[int, float, float]] = None  # (repeat index, start s, duration s)
    lighting: dict = field(default_factory=dict)        # repeat index -> gain (e.g. {1: 0.6})
    moved_boxes: dict = field(default_factory=dict)     # repeat index -> {box: (x, z)}
    obstacle: Optional[dict] = None                      # {"repeat": i, "at": (x, z), "size": (...), "remove_s": t}
    settle_m: float = 3.0
    max_repeat_s: float = 240.0


@dataclass
class RunTrace:
    """What the simulator saw: true poses (t, x, z, theta) and commanded twists per cycle."""

    t: list = field(default_factory=list)
    xz: list = field(default_factory=list)
    theta: list = field(default_factory=list)
    v: list = field(default_factory=list)

    def observer(self, drive: SimDiffDrive, every: int = 5):
        def fn(rt, ctx, twist, wheels):
            if ctx.cycle % every == 0:
                p = drive.physics.pose
                self.t.append(ctx.now_ns * 1e-9)
                self.xz.append((p.x, p.z))
                self.theta.append(p.theta)
                self.v.append(twist.v)
        return fn

    def array(self) -> np.ndarray:
        return np.asarray(self.xz, dtype=float).reshape(-1, 2)


def demo_config(seed: int, base: Optional[Config] = None) -> Config:
    cfg = base or load_config(None)
    cfg = cfg.model_copy(deep=True)
    cfg.sim.seed = seed
    return cfg


def demo_route() -> np.ndarray:
    """A 20.6 m closed loop with four right turns, 1 m from the boxes and walls of World.room()."""
    return rounded_rectangle((0.0, 0.0), (7.0, 4.0), 0.8)


def start_pose(path: np.ndarray) -> Pose2:
    d = path[1] - path[0]
    return Pose2(float(path[0][0]), float(path[0][1]), math.atan2(d[0], d[1]))


def write_json_atomic(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        json.dump(data, f, indent=2)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def summarise_errors(trace: RunTrace, taught: np.ndarray, settle_m: float) -> dict:
    xz = trace.array()
    if len(xz) < 2:
        return {"rms_lateral_error_m": float("nan"), "max_lateral_error_m": float("nan"), "recovery_m": None}
    err = lateral_errors(xz, taught, closed=False)
    along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xz, axis=0), axis=1))])
    settled = along >= settle_m
    # Recovery from the deliberate start offset: distance travelled until the error first falls under 5 cm.
    # (What happens after that is judged by the RMS and max from settle_m on.)
    under = np.flatnonzero(err < 0.05)
    recovery = float(along[under[0]]) if len(under) else None
    e = err[settled] if settled.any() else err
    return {"rms_lateral_error_m": float(np.sqrt(np.mean(e ** 2))), "max_lateral_error_m": float(e.max()),
            "p95_lateral_error_m": float(np.percentile(e, 95)), "recovery_m": recovery,
            "distance_m": float(along[-1])}


def plot_paths(png: Path, taught: np.ndarray, repeats: list[np.ndarray], keyframes: np.ndarray, world=None,
               title: str = "") -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 7.5), dpi=110)
    if world is not None:
        for q in getattr(world, "quads", []):
            if q.kind in ("wall", "box"):
                pts = np.array([q.origin, q.origin + q.width * q.u, q.origin + q.width * q.u + q.height * q.v,
                                q.origin + q.height * q.v])
                ax.plot(pts[[0, 1], 0], pts[[0, 1], 2], color="0.35" if q.kind == "wall" else "tab:brown", lw=2)
    ax.plot(taught[:, 0], taught[:, 1], color="black", lw=2.5, label="taught path (true)")
    colours = ["tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:red"]
    for i, r in enumerate(repeats):
        if len(r):
            ax.plot(r[:, 0], r[:, 1], color=colours[i % len(colours)], lw=1.2, label=f"repeat {i + 1} (true)")
            ax.plot(r[0, 0], r[0, 1], "o", color=colours[i % len(colours)], ms=6)
    if len(keyframes):
        ax.plot(keyframes[:, 0], keyframes[:, 1], "^", color="crimson", ms=5, label=f"keyframes ({len(keyframes)})")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, right)")
    ax.set_ylabel("z (m, forward at start)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    tmp = png.with_suffix(".tmp.png")
    fig.savefig(tmp)
    plt.close(fig)
    os.replace(tmp, png)


# ----------------------------------------------------------------------------- runs
@dataclass
class SimRobot:
    """One simulated robot on its own clock: base, camera, pipeline pieces."""

    clock: SimClock
    drive: SimDiffDrive
    camera: object
    world: object


def make_sim_robot(cfg: Config, world, start: Pose2, seed_offset: int = 0) -> SimRobot:
    from vbnav.control.config import validate_driver_options
    from vbnav.drivers.sim.camera import SimCamera

    clock = SimClock()
    drive = SimDiffDrive(BaseParams.from_config(cfg), clock, seed=cfg.sim.seed * 1000 + seed_offset, start=start)
    opts = validate_driver_options(cfg, cfg.source or "<config>")["camera"]
    camera = SimCamera.from_config(cfg, clock, opts, pose_fn=lambda: drive.true_pose, world=world)
    camera.seed = cfg.sim.seed * 1000 + seed_offset
    return SimRobot(clock, drive, camera, world)


@dataclass
class TeachResult:
    trace: RunTrace
    keyframes: int
    keyframe_xz: np.ndarray
    reason: str
    message: str
    timing: object


def teach_route(cfg: Config, robot: SimRobot, controller, route_dir: Path,
                progress: Optional[Callable[[str], None]] = None, duration_s: Optional[float] = None,
                recorder=None) -> TeachResult:
    """Drive with ``controller`` while a TeachStage records keyframes into ``route_dir``."""
    from vbnav.control.route import RouteWriter
    from vbnav.control.stages.teach import TeachStage

    model, mount = cfg.camera.to_model(), cfg.camera.mount.to_mount()
    stage = TeachStage(model, mount, cfg.vbc)
    pipeline = make_pipeline(cfg, robot.clock, robot.camera, [stage])
    trace = RunTrace()
    stamps: dict[int, int] = {}
    with RouteWriter(route_dir, cfg.robot.name, model, mount, overwrite=True) as writer:
        def save(frame, results):
            for kf in stage.pop_keyframes():
                writer.append(kf)
                stamps[kf.index] = kf.stamp_ns

        pipeline.frame_listeners.append(save)
        rt = Runtime(cfg, robot.drive, controller, robot.clock, pipeline)
        rt.cycle_observers.append(trace.observer(robot.drive))
        rt.cycle_observers.append(_stamp_pose_recorder(robot.drive, stamps_pose := {}))
        link = _record(rt, cfg, recorder, "teach")
        result = None
        try:
            result = rt.run(duration_s, _progress_fn(progress, "teach", lambda: f"{stage.n_keyframes} keyframes"))
        finally:
            if link is not None:
                link.close(result)
        stage.finish()
        save(None, None)
    kf_xz = np.array([_nearest_pose(stamps_pose, s) for _, s in sorted(stamps.items())]).reshape(-1, 2)
    return TeachResult(trace, len(stamps), kf_xz, result.reason, result.message, result.timing)


@dataclass
class RepeatResult:
    trace: RunTrace
    completed: bool
    reason: str
    message: str
    keyframe_reached: int
    events: list
    timing: object
    stops: int


def repeat_route(cfg: Config, robot: SimRobot, route, progress: Optional[Callable[[str], None]] = None,
                 duration_s: float = 240.0, events: Optional[Callable] = None,
                 extra_stages: tuple = (), recorder=None, segment: str = "repeat") -> RepeatResult:
    """Patrol ``route`` with the RepeatStage/RepeatController; ``events(rt, ctx)`` injects scenario changes."""
    from vbnav.control.controllers.repeat import RepeatController
    from vbnav.control.stages.repeat import RepeatStage

    vcfg = cfg.vbc
    stage = RepeatStage(route, vcfg, cfg.camera.to_model(), cfg.camera.mount.to_mount())
    controller = RepeatController(route, vcfg, cfg.robot.max_linear_speed, cfg.robot.max_angular_speed)
    pipeline = make_pipeline(cfg, robot.clock, robot.camera, [stage, *extra_stages])
    rt = Runtime(cfg, robot.drive, controller, robot.clock, pipeline)
    trace = RunTrace()
    rt.cycle_observers.append(trace.observer(robot.drive))
    if events is not None:
        rt.cycle_observers.append(lambda r, ctx, twist, wheels: events(r, ctx))
    link = _record(rt, cfg, recorder, segment)
    result = None
    try:
        result = rt.run(duration_s, _progress_fn(progress, "repeat",
                                                 lambda: f"keyframe {stage.index + 1}/{len(route.keyframes)}"))
    finally:
        if link is not None:
            link.close(result)
    stops = sum(1 for e in result.events if e.kind == "hold")
    return RepeatResult(trace, result.reason == "finished", result.reason, result.message, stage.index,
                        [e.as_dict() for e in result.events], result.timing, stops)


def _record(rt: Runtime, cfg: Config, recorder, segment: str):
    """Record this run into a shared MCAP recorder (no network: simulated runs go faster than real time)."""
    if recorder is None:
        return None
    from vbnav.control.comms.link import TelemetryLink
    return TelemetryLink.attach(rt, cfg, recorder=recorder, network=False, segment=segment)


def _stamp_pose_recorder(drive, store: dict):
    def fn(rt, ctx, twist, wheels):
        p = drive.physics.pose
        store[ctx.now_ns] = (p.x, p.z)
    return fn


def _nearest_pose(store: dict, stamp: int):
    if not store:
        return (np.nan, np.nan)
    keys = np.fromiter(store.keys(), dtype=np.int64)
    return store[int(keys[np.argmin(np.abs(keys - stamp))])]


def _progress_fn(progress, label: str, extra: Callable[[], str]):
    if progress is None:
        return None

    def fn(rt: Runtime) -> None:
        t = (rt.clock.now_ns() - rt._start_ns) * 1e-9
        safety = "ok" if rt.safety.may_move else "STOP " + ",".join(rt.safety.latched | rt.safety.holds)
        progress(f"{label}: t={t:5.1f}s  travelled {rt.odometry.distance:5.1f} m  {extra()}  "
                 f"v={rt.last_twist.v:+.2f} w={rt.last_twist.w:+.2f}  {safety}")
    return fn


# ----------------------------------------------------------------------------- the scenario
def run_demo(out_dir: Path, scenario: Scenario = Scenario(), cfg: Optional[Config] = None,
             progress: Optional[Callable[[str], None]] = None, record: Optional[str] = None) -> dict:
    """Teach the demo route, repeat it ``scenario.repeats`` times; write metrics.json, paths.png, route/.

    ``record``: one MCAP file holding the teach run and every repeat, one segment each.
    """
    from vbnav.drivers.sim.world import World

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cfg = demo_config(scenario.seed, cfg)
    say = progress or (lambda s: None)
    path = demo_route()
    start = start_pose(path)
    t_wall = time.perf_counter()

    world = World.by_name(cfg.sim.world, cfg.sim.seed)
    robot = make_sim_robot(cfg, world, start, seed_offset=0)
    recorder = None
    if record:
        from vbnav.control.comms.recording import McapRecorder
        recorder = McapRecorder(record, cfg.robot.name, metadata={"demo_seed": scenario.seed,
                                                                  "repeats": scenario.repeats})
    try:
        return _run_demo_phases(out_dir, scenario, cfg, say, progress, path, start, world, robot, recorder, t_wall)
    finally:
        if recorder is not None:
            recorder.close()


def _run_demo_phases(out_dir, scenario, cfg, say, progress, path, start, world, robot, recorder, t_wall) -> dict:
    from vbnav.control.route import load_route
    from vbnav.drivers.sim.world import World

    teach = teach_route(cfg, robot, PathFollower(path, scenario.speed, start=start), out_dir / "route", say,
                        recorder=recorder)
    if progress:
        say(f"taught {teach.keyframes} keyframes over {path_length(teach.trace.array()):.1f} m")
    route = load_route(out_dir / "route")
    taught_xz = teach.trace.array()

    repeats = []
    for i in range(scenario.repeats):
        world_i = World.by_name(cfg.sim.world, cfg.sim.seed)
        for name, xz in scenario.moved_boxes.get(i, {}).items():
            world_i.move_box(name, xz)
        offset = Pose2(scenario.offset_lateral_m * (1 if i % 2 == 0 else -1), 0.0,
                       math.radians(scenario.offset_heading_deg) * (1 if i % 2 == 0 else -1))
        robot_i = make_sim_robot(cfg, world_i, start.compose(offset), seed_offset=i + 1)
        robot_i.camera.gain = scenario.lighting.get(i, 1.0)
        events = _scenario_events(scenario, i, robot_i)
        rep = repeat_route(cfg, robot_i, route, say, scenario.max_repeat_s, events, recorder=recorder,
                           segment=f"repeat {i + 1}")
        errs = summarise_errors(rep.trace, taught_xz, scenario.settle_m)
        repeats.append({"index": i + 1, "completed": rep.completed, "end": rep.reason, "message": rep.message,
                        "keyframe_reached": rep.keyframe_reached + 1, "start_offset": offset.as_array().tolist(),
                        "lighting_gain": robot_i.camera.gain, "safety_stops": rep.stops,
                        "duration_s": rep.trace.t[-1] - rep.trace.t[0] if rep.trace.t else 0.0,
                        "loop_timing": rep.timing.as_dict(), **errs})
        if progress:
            say(f"repeat {i + 1}: {'completed' if rep.completed else 'NOT completed (' + rep.message + ')'}, "
                f"RMS lateral error {errs['rms_lateral_error_m'] * 100:.1f} cm, "
                f"max {errs['max_lateral_error_m'] * 100:.1f} cm")
        repeats[-1]["_trace"] = rep.trace.array()

    all_err = []
    for r in repeats:
        all_err.append((r["rms_lateral_error_m"], r["max_lateral_error_m"]))
    metrics = {
        "schema": "vbnav.demo.metrics", "version": 1, "seed": scenario.seed,
        "route_length_m": path_length(taught_xz), "keyframes": teach.keyframes,
        "completed": all(r["completed"] for r in repeats),
        "rms_lateral_error_m": float(np.sqrt(np.mean([e[0] ** 2 for e in all_err]))),
        "max_lateral_error_m": float(max(e[1] for e in all_err)),
        "settle_m": scenario.settle_m,
        "repeats": [{k: v for k, v in r.items() if not k.startswith("_")} for r in repeats],
        "wall_time_s": time.perf_counter() - t_wall,
    }
    write_json_atomic(out_dir / "metrics.json", metrics)
    plot_paths(out_dir / "paths.png", taught_xz, [r["_trace"] for r in repeats], teach.keyframe_xz, world,
               f"seed {scenario.seed}: {teach.keyframes} keyframes, RMS lateral "
               f"{metrics['rms_lateral_error_m'] * 100:.1f} cm, max {metrics['max_lateral_error_m'] * 100:.1f} cm")
    return metrics


def _scenario_events(scenario: Scenario, i: int, robot: SimRobot):
    occ = scenario.occlusion if scenario.occlusion and scenario.occlusion[0] == i else None
    if occ is None:
        return None
    t0 = robot.clock.now_ns()

    def events(rt, ctx):
        t = (ctx.now_ns - t0) * 1e-9
        robot.camera.occluded = occ[1] <= t < occ[1] + occ[2]
    return events
