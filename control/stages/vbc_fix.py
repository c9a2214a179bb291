"""What the repeat stage hands the repeat controller: the robot relative to a keyframe."""
from __future__ import annotations

from dataclasses import dataclass, field

from vbnav.control.config.vbc import VBCConfig
from vbnav.control.runtime.interfaces import PoseFix
from vbnav.vision.geometry import Pose2


@dataclass
class VBCFix(PoseFix):
    """A repeat-stage result: the robot relative to keyframe ``keyframe`` at the frame's time."""

    keyframe: int
    pose: Pose2
    odom: Pose2
    n_agree: int
    quality: dict = field(default_factory=dict)
    finished: bool = False



def bearing_sigma(camera, cfg: VBCConfig) -> float:
    return cfg.bearing_sigma_px / float(camera.fx)
