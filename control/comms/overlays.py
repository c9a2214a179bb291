"""What the vision stages saw in a frame, for the live view and the recording (foxglove_channels.Overlay).

Read on the thread that ran the stages, right after they processed the frame (a
``pipeline.frame_listeners`` callback), from each stage's ``overlay`` member
(runtime/interfaces.py StageOverlay): the features the teach or repeat stage
tracks, the keyframe features the repeat stage matches and its route, the
obstacle stage's stop corridor and, when it keeps them, its obstacle labels; the
VSLAM stage's landmarks; the line-map stage's segments. A stage without such state contributes nothing.
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


def frame_overlay(stages, results: dict) -> Overlay:
    """The overlay of the frame the ``stages`` just processed (``results``: their estimates by kind)."""
    tracked = matched = zone = mask = None
    text = []
    for stage in stages:
        est = results.get(stage.kind)
        drawn = stage.overlay(est)
        if stage.kind == "obstacles":
            if drawn is not None:
                zone, mask = drawn.stop_zone, _obstacle_pixels(drawn.obstacle_labels)
            continue
        if drawn is not None and tracked is None and drawn.tracked is not None:
            tracked = _thin(np.asarray(drawn.tracked, float).reshape(-1, 2))
        if drawn is not None and matched is None and drawn.matched is not None:
            matched = _thin(np.asarray(drawn.matched, float))
        if est is not None and isinstance(est.info, dict):
            text.append(f"{stage.kind}: " + " ".join(f"{k}={v}" for k, v in est.info.items()
                                                     if isinstance(v, (int, float, str))))
    return Overlay(tracked, matched, zone, mask, "; ".join(text))


def _obstacle_pixels(labels) -> Optional[np.ndarray]:
    """Pixels (u, v) of the obstacle labels, sampled every MASK_STEP pixels."""
    if labels is None:
        return None
    sub = np.asarray(labels)[::MASK_STEP, ::MASK_STEP]
    vv, uu = np.nonzero(sub > 0)
    return _thin(np.column_stack([uu, vv]).astype(float) * MASK_STEP)


def route_keyframes(stages) -> Optional[tuple[str, list]]:
    """(name, keyframe odometry poses) of the route a repeat stage follows, or None."""
    for stage in stages:
        drawn = stage.overlay(None)
        if drawn is not None and drawn.route is not None and drawn.route[1]:
            return drawn.route
    return None


def landmarks(stages) -> Optional[np.ndarray]:
    """The VSLAM stage's landmarks (N, 3) in its world frame, or None."""
    for stage in stages:
        drawn = stage.overlay(None)
        P = None if drawn is None else drawn.landmarks
        if P is not None and len(P):
            return _thin(np.asarray(P, float).reshape(-1, 3))
    return None


def line_map_scene(stages):
    """The line-map stage's ``MapScene`` (stages/line_map.py: its segments and revision), or None."""
    for stage in stages:
        drawn = stage.overlay(None)
        if drawn is not None and drawn.line_map is not None:
            return drawn.line_map
    return None
