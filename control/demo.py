"""The demo scenario: teach a closed route in the simulated room, repeat it from an offset start.

Every run here is the real runtime (loop, safety, pipeline) with the simulated
base and camera on the simulated clock. Ground truth comes from the simulator
and is used only to measure, never to steer.

Lateral error is the distance of the repeated (true) positions to the taught
(true) path. It is measured once the robot has recovered from the deliberate
start offset: from ``settle_m`` metres along the route on (the recovery itself
is reported as the distance travelled until the error first stays under 5 cm).
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
from vbnav.control.factory import make_pipeline
from vbnav.control.path_tools import PathFollower, lateral_errors, path_length, rounded_rectangle
from vbnav.control.runtime import Runtime
from vbnav.drivers.clock import SimClock
from vbnav.drivers.sim_base import BaseParams, SimDiffDrive
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
    recovery = None
    under = err < 0.05
    for i in range(len(err)):
        if under[i:].all():
            recovery = float(along[i])
            break
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
