"""What the vision stages saw in a frame, for the live view and the recording (foxglove_channels.Overlay).

Read on the thread that ran the stages, right after they processed the frame (a
``pipeline.frame_listeners`` callback), from the stages' public state: the
feature tracker of the teach or repeat stage (``tracker.tracks``), the keyframe
the repeat stage is matching (``kfs[index]``), the obstacle stage's stop
corridor and, when it keeps them, its obstacle labels; the VSLAM stage's
landmarks (``slam.lm.P``). A stage without such state contributes nothing.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from vbnav.control.comms.foxglove_channels import Overlay

MAX_POINTS = 400          # per overlay kind: enough to see, small enough for 2 Hz over a slow link
MASK_STEP = 8             # obstacle labels are sampled every MASK_STEP pixels


def _thin(a: np.ndarray) -> np.ndarray:
    if len(a) <= MAX_POINTS:
        return a
    return a[:: int(np.ceil(len(a) / MAX_POINTS))]


def _tracked(stage) -> Optional[np.ndarray]:
    tracker = getattr(stage, "tracker", None) or getattr(getattr(stage, "slam", None), "tracker", None)
    tracks = getattr(tracker, "tracks", None)
    pts = getattr(tracks, "pts", None)
    return None if pts is None else _thin(np.asarray(pts, float).reshape(-1, 2))


def _matched(stage) -> Optional[np.ndarray]:
    """The features of the keyframe being matched that are tracked in this frame, at their keyframe pixels."""
    kfs, index = getattr(stage, "kfs", None), getattr(stage, "index", None)
    tracks = getattr(getattr(stage, "tracker", None), "tracks", None)
    if not kfs or index is None or tracks is None:
        return None
    kf = kfs[min(index, len(kfs) - 1)]
    seen = np.isin(kf.track_ids, tracks.ids)
    return _thin(np.asarray(kf.pixels, float)[seen])


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


def _obstacles(stage, results) -> tuple[Optional[np.ndarray], Optional[np.ndarray]]:
    rig = getattr(stage, "rig", None)
    zone = None
    if rig is not None and hasattr(stage, "_stop_half_width"):
        zone = stop_zone_outline(rig.camera, stage.mount, stage._stop_half_width, stage.cfg.max_range)
    mask = None
    est = results.get(getattr(stage, "kind", ""))
    labels = getattr(getattr(est, "value", None), "labels", None)
    if labels is not None:
        sub = np.asarray(labels)[::MASK_STEP, ::MASK_STEP]
        vv, uu = np.nonzero(sub > 0)
        mask = _thin(np.column_stack([uu, vv]).astype(float) * MASK_STEP)
    return zone, mask


def frame_overlay(stages, results: dict) -> Overlay:
    """The overlay of the frame the ``stages`` just processed (``results``: their estimates by kind)."""
    tracked = matched = zone = mask = None
    text = []
    for stage in stages:
        kind = getattr(stage, "kind", "")
        if kind == "obstacles":
            zone, mask = _obstacles(stage, results)
            continue
        if tracked is None:
            tracked = _tracked(stage)
        if matched is None:
            matched = _matched(stage)
        est = results.get(kind)
        if est is not None and isinstance(est.info, dict):
            text.append(f"{kind}: " + " ".join(f"{k}={v}" for k, v in est.info.items()
                                               if isinstance(v, (int, float, str))))
    return Overlay(tracked, matched, zone, mask, "; ".join(text))


def route_keyframes(stages) -> Optional[tuple[str, list]]:
    """(name, keyframe odometry poses) of the route a repeat stage follows, or None."""
    for stage in stages:
        kfs = getattr(stage, "kfs", None)
        if kfs:
            route = getattr(stage, "route", None)
            name = getattr(getattr(route, "path", None), "name", None) or "route"
            return name, [kf.odom for kf in kfs]
    return None


def landmarks(stages) -> Optional[np.ndarray]:
    """The VSLAM stage's landmarks (N, 3) in its world frame, or None."""
    for stage in stages:
        lm = getattr(getattr(stage, "slam", None), "lm", None)
        P = getattr(lm, "P", None)
        if P is not None and len(P):
            return _thin(np.asarray(P, float).reshape(-1, 3))
    return None
