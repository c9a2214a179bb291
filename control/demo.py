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

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from vbnav.control.config import Config, load_config
from vbnav.control.controllers.path import PathFollower, lateral_errors, path_length, room_loop
from vbnav.control.runtime.factory import Robot, make_robot
from vbnav.control.session import Session, teach_loop_speed
from vbnav.control.image_files import write_json
from vbnav.drivers.atomic_file import atomic_output
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

    def observer(self, drive, every: int = 5):
        """A cycle observer sampling the simulated ``drive``'s true pose every ``every`` cycles."""
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
    """The simulated robot of ``base`` (default configs/sim.yaml) on ``seed``, at the start of the demo route."""
    cfg = base or load_config(None)
    cfg = cfg.model_copy(deep=True)
    cfg.sim.seed = seed
    cfg.sim.set_start(start_pose(demo_route()))
    return cfg


def demo_route() -> np.ndarray:
    """The simulated room's 20.6 m loop (controllers/path.py ``room_loop``)."""
    return room_loop()


def start_pose(path: np.ndarray) -> Pose2:
    d = path[1] - path[0]
    return Pose2(float(path[0][0]), float(path[0][1]), math.atan2(d[0], d[1]))


def write_json_atomic(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, data, indent=2)


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
        for q in world.quads:
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
    try:
        with atomic_output(png) as tmp:
            fig.savefig(tmp)
    finally:
        plt.close(fig)


# ----------------------------------------------------------------------------- ground truth
class KeyframeTruth:
    """True positions at keyframe stamps: a cycle observer logs the true pose at every stamp."""

    def __init__(self, drive):
        self.drive = drive
        self.by_stamp: dict[int, tuple[float, float]] = {}

    def __call__(self, rt, ctx, twist, wheels) -> None:
        p = self.drive.physics.pose
        self.by_stamp[ctx.now_ns] = (p.x, p.z)

    def at(self, stamps: list[int]) -> np.ndarray:
        """(N, 2) true x, z at the cycle nearest each stamp."""
        return np.array([self._nearest(s) for s in stamps]).reshape(-1, 2)

    def _nearest(self, stamp: int):
        if not self.by_stamp:
            return (np.nan, np.nan)
        keys = np.fromiter(self.by_stamp.keys(), dtype=np.int64)
        return self.by_stamp[int(keys[np.argmin(np.abs(keys - stamp))])]


# ----------------------------------------------------------------------------- the scenario
def run_demo(out_dir: Path, scenario: Scenario = Scenario(), cfg: Optional[Config] = None,
             progress: Optional[Callable[[str], None]] = None, record: Optional[str] = None,
             record_overwrite: bool = False) -> dict:
    """Teach the demo route, repeat it ``scenario.repeats`` times; write metrics.json, paths.png, route/.

    ``record``: one MCAP file holding the teach run and every repeat, one segment each (an existing one
    only with ``record_overwrite``). A route already in ``out_dir`` is replaced only once the new one
    is complete (RouteWriter's overwrite).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cfg = demo_config(scenario.seed, cfg)
    t_wall = time.perf_counter()
    recorder = None
    if record:
        from vbnav.control.comms.recording import McapRecorder
        recorder = McapRecorder(record, cfg.robot.name, metadata={"demo_seed": scenario.seed,
                                                                  "repeats": scenario.repeats},
                                overwrite=record_overwrite)
    try:
        return _run_demo_phases(out_dir, scenario, cfg, progress, recorder, t_wall)
    finally:
        if recorder is not None:
            recorder.close()


def _run_demo_phases(out_dir, scenario, cfg, progress, recorder, t_wall) -> dict:
    from vbnav.control.route import load_route

    say = progress or (lambda s: None)
    path = demo_route()
    start = cfg.sim.start()
    robot = make_robot(cfg, with_camera=True, run=0)
    trace, truth = RunTrace(), KeyframeTruth(robot.drive)
    sessions = [Session(cfg, robot, recorder=recorder, progress=say)]
    teach = sessions[0].teach(
        PathFollower(path, teach_loop_speed(cfg, scenario.speed), start=start), out_dir / "route", overwrite=True,
        observers=[trace.observer(robot.drive), truth])
    taught_xz = trace.array()
    if not teach.complete:      # an earlier demo's route may still be at out_dir/route: never repeat that one
        raise RuntimeError(f"the demo's teach run did not complete a route ({teach.reason}: {teach.message}; "
                           f"{teach.keyframes} keyframes)")
    if progress:
        say(f"taught {teach.keyframes} keyframes over {path_length(taught_xz):.1f} m"
            + (f" ({teach.note})" if teach.note else ""))
    route = load_route(out_dir / "route")

    repeats = []
    for i in range(scenario.repeats):
        offset = Pose2(scenario.offset_lateral_m * (1 if i % 2 == 0 else -1), 0.0,
                       math.radians(scenario.offset_heading_deg) * (1 if i % 2 == 0 else -1))
        cfg_i = cfg.model_copy(deep=True)
        cfg_i.sim.set_start(start.compose(offset))
        robot_i = make_robot(cfg_i, with_camera=True, run=i + 1)
        for name, xz in scenario.moved_boxes.get(i, {}).items():
            robot_i.world.move_box(name, xz)
        robot_i.camera.gain = scenario.lighting.get(i, 1.0)
        trace_i = RunTrace()
        observers = [trace_i.observer(robot_i.drive)]
        events = _scenario_events(scenario, i, robot_i)
        if events is not None:
            observers.append(events)
        sessions.append(Session(cfg_i, robot_i, recorder=recorder, progress=say))
        rep = sessions[-1].repeat(route, scenario.max_repeat_s, observers, segment=f"repeat {i + 1}")
        errs = summarise_errors(trace_i, taught_xz, scenario.settle_m)
        repeats.append({"index": i + 1, "completed": rep.completed, "end": rep.reason, "message": rep.message,
                        "keyframes_passed": rep.keyframes_passed, "start_offset": offset.as_array().tolist(),
                        "lighting_gain": robot_i.camera.gain, "safety_stops": rep.stops,
                        "duration_s": trace_i.t[-1] - trace_i.t[0] if trace_i.t else 0.0,
                        "loop_timing": rep.timing.as_dict(), **errs})
        if progress:
            say(f"repeat {i + 1}: {'completed' if rep.completed else 'NOT completed (' + rep.message + ')'}, "
                f"RMS lateral error {errs['rms_lateral_error_m'] * 100:.1f} cm, "
                f"max {errs['max_lateral_error_m'] * 100:.1f} cm")
        repeats[-1]["_trace"] = trace_i.array()

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
    if recorder is not None:      # the first write of the --record that failed (said on stderr), or None
        metrics["recording_error"] = next((s.recording_error for s in sessions if s.recording_error), None)
    write_json_atomic(out_dir / "metrics.json", metrics)
    plot_paths(out_dir / "paths.png", taught_xz, [r["_trace"] for r in repeats],
               truth.at(teach.keyframe_stamps), robot.world,
               f"seed {scenario.seed}: {teach.keyframes} keyframes, RMS lateral "
               f"{metrics['rms_lateral_error_m'] * 100:.1f} cm, max {metrics['max_lateral_error_m'] * 100:.1f} cm")
    return metrics


def _scenario_events(scenario: Scenario, i: int, robot: Robot):
    """The occlusion of repeat ``i`` (the camera covered for a while), as a cycle observer; None if none."""
    occ = scenario.occlusion if scenario.occlusion and scenario.occlusion[0] == i else None
    if occ is None:
        return None
    t0 = robot.clock.now_ns()

    def events(rt, ctx, twist, wheels):
        t = (ctx.now_ns - t0) * 1e-9
        robot.camera.occluded = occ[1] <= t < occ[1] + occ[2]
    return events
