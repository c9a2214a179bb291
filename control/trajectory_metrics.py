"""Trajectory files and errors for ``vbnav vo``: TUM writing, ATE after alignment, RPE.

Implemented here rather than through ``evo``: ATE with an SE(3) (or Sim(3)) Umeyama
alignment and RPE over a frame delta are a few lines of numpy, and evo would pull a
large dependency tree into the robot's install for two numbers. The definitions
follow evo's ``evo_ape tum -a`` and ``evo_rpe tum`` (translation part, RMSE). Tests
and benchmarks that score trajectories use these same functions.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from vbnav.drivers.atomic_file import write_atomic
from vbnav.vision.geometry import absolute_orientation, quat_from_matrix


def write_tum(path: str | Path, stamps: np.ndarray, poses: np.ndarray) -> None:
    """``timestamp tx ty tz qx qy qz qw`` per line (camera-to-world), written atomically."""
    path = Path(path)
    lines = []
    for t, M in zip(stamps, poses):
        q = quat_from_matrix(M[:3, :3])
        lines.append(f"{t:.6f} {M[0, 3]:.6f} {M[1, 3]:.6f} {M[2, 3]:.6f} {q[0]:.7f} {q[1]:.7f} {q[2]:.7f} {q[3]:.7f}")
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, "# timestamp tx ty tz qx qy qz qw (camera-to-world)\n" + "\n".join(lines) + "\n")


def ate_rmse(est: np.ndarray, gt: np.ndarray, with_scale: bool = False) -> tuple[float, np.ndarray]:
    """Absolute trajectory error (translation RMSE, m) after aligning est to gt; also the aligned est."""
    R, t, s = absolute_orientation(est[:, :3, 3], gt[:, :3, 3], with_scale=with_scale)
    aligned = s * est[:, :3, 3] @ R.T + t
    return float(np.sqrt(np.mean(np.sum((aligned - gt[:, :3, 3]) ** 2, axis=1)))), aligned


def rpe(est: np.ndarray, gt: np.ndarray, delta: int = 1, frames=None) -> tuple[float, float]:
    """Relative pose error over ``delta`` frames: (translation RMSE m, rotation RMSE deg). ``frames``: the
    frame number of each pose (default 0, 1, 2, ...); only pairs ``delta`` frames apart count (a frame with no
    pose or no ground truth between two others does not make them neighbours)."""
    te, re = [], []
    for i, j in rpe_pairs(len(est), delta, frames):
        E = np.linalg.inv(est[i]) @ est[j]
        G = np.linalg.inv(gt[i]) @ gt[j]
        D = np.linalg.inv(G) @ E
        te.append(np.linalg.norm(D[:3, 3]))
        re.append(np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))))
    if not te:
        return float("nan"), float("nan")
    return float(np.sqrt(np.mean(np.square(te)))), float(np.sqrt(np.mean(np.square(re))))


def rpe_pairs(n: int, delta: int = 1, frames=None) -> list[tuple[int, int]]:
    """Index pairs (i, j) of the poses whose frames are ``delta`` apart (``rpe``)."""
    frames = range(n) if frames is None else [int(f) for f in frames]
    at = {f: k for k, f in enumerate(frames)}
    return [(k, at[f + delta]) for k, f in enumerate(frames) if f + delta in at]


def scale_to(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """``est`` with its translations multiplied by the Sim(3) scale that aligns it to ``gt`` (for the
    RPE of a monocular run, whose scale is arbitrary)."""
    _, _, s = absolute_orientation(est[:, :3, 3], gt[:, :3, 3], with_scale=True)
    out = np.array(est, float, copy=True)
    out[:, :3, 3] *= s
    return out
