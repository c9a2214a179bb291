"""Visual odometry over a recorded dataset: run the VSLAM front end from the chosen initialisation.

``vbnav vo`` writes and evaluates the trajectory with ``control/trajectory_metrics.py``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from vbnav.drivers.datasets import Dataset
from vbnav.drivers.errors import InputError
from vbnav.vision.vslam import FrameResult, Vslam, VslamConfig
from vbnav.vision.vslam_init import TagGrid, init_from_tags, init_two_view

INIT_MODES = ("stereo", "depth", "tags", "essential")


class VoError(InputError):
    """The dataset cannot be processed with the chosen initialisation."""


@dataclass
class VoResult:
    stamps: np.ndarray  # seconds of the tracked frames
    poses: np.ndarray  # (K, 4, 4) world-from-camera
    frames: list[int]  # dataset index of each tracked frame
    results: list[FrameResult] = field(default_factory=list)
    init: str = ""
    scale_known: bool = True
    references: int = 1


def default_init(ds: Dataset) -> str:
    if ds.right is not None:
        return "stereo"
    if ds.depth is not None and ds.depth_image(0) is not None:
        return "depth"
    if "tag_grid" in ds.extras:
        return "tags"
    return "essential"


def run_vo(ds: Dataset, init: Optional[str] = None, config: Optional[VslamConfig] = None,
           progress: Optional[Callable[[str], None]] = None, essential_frames: int = 10) -> VoResult:
    init = init or default_init(ds)
    if init not in INIT_MODES:
        raise VoError(f"unknown --init {init!r} (expected one of {', '.join(INIT_MODES)})")
    say = progress or (lambda s: None)
    slam = Vslam(ds.camera, config, stereo_baseline=ds.stereo_baseline if init == "stereo" else None)
    scale_known = True
    if init == "stereo":
        if ds.right is None:
            raise VoError(f"{ds.root}: --init stereo needs right images (image_r/)")
        slam.initialise_stereo(ds.image(0), ds.right_image(0))
        start = 1
    elif init == "depth":
        depth = ds.depth_image(0)
        if depth is None:
            raise VoError(f"{ds.root}: --init depth needs a depth image for the first frame (depth.txt)")
        slam.initialise_depth(ds.image(0), depth)
        start = 1
    elif init == "tags":
        if "tag_grid" not in ds.extras:
            raise VoError(f"{ds.root}: --init tags needs a 'tag_grid' block in the camera YAML")
        grid = TagGrid.from_spec(ds.extras["tag_grid"])
        img = ds.image(0)
        extra = slam.tracker.detect(img, slam.cfg.max_landmarks)
        s = init_from_tags(img, ds.camera, grid, extra_pixels=extra)
        say(f"tags {s.info['tags']} seen; grid pose from {len(s.pixels)} landmarks, "
            f"{s.info['iterations']} iterations, residual {s.info['residual_px']:.2f} px")
        slam.initialise(img, s.pixels, s.points_cam, s.pose_wc)
        start = 1
    else:
        start, scale_known = _init_essential(ds, slam, essential_frames, say)
    stamps, poses, frames, results = [ds.stamps[start - 1]], [slam.pose_wc], [start - 1], []
    for i in range(start, len(ds)):
        r = slam.process(ds.image(i), ds.right_image(i) if init == "stereo" else None,
                         ds.depth_image(i) if init == "depth" else None)
        results.append(r)
        if r.ok:
            stamps.append(ds.stamps[i])
            poses.append(r.pose_wc)
            frames.append(i)
        if i % 10 == 0 or i == len(ds) - 1 or not r.ok:
            say(f"frame {i}/{len(ds) - 1}: {'ok' if r.ok else 'LOST'} landmarks {r.tracked} inliers {r.inliers} "
                f"iterations {r.iterations} residual {r.residual_px:.2f} px references {r.reference + 1}")
    return VoResult(np.array(stamps), np.array(poses), frames, results, init, scale_known, len(slam.references))


def _init_essential(ds: Dataset, slam: Vslam, max_frames: int, say) -> tuple[int, bool]:
    """Track corners from frame 0 until the parallax is enough, then two-view initialisation."""
    img0 = ds.image(0)
    px0 = slam.tracker.detect(img0, slam.cfg.max_landmarks)
    px, keep, prev = px0.copy(), np.ones(len(px0), bool), img0
    for k in range(1, min(max_frames, len(ds) - 1) + 1):
        img = ds.image(k)
        nxt, ok = slam.tracker.track(prev, img, px[keep])
        idx = np.flatnonzero(keep)
        keep[idx[~ok]] = False
        px[idx[ok]] = nxt[ok]
        prev = img
        flow = np.median(np.linalg.norm(px[keep] - px0[keep], axis=1)) if keep.any() else 0.0
        if flow > 20.0 or k == min(max_frames, len(ds) - 1):
            break
    if keep.sum() < 8:
        raise VoError(f"{ds.root}: essential initialisation lost the features in the first {k} frames")
    tv = init_two_view(ds.camera.rays(px0[keep]), ds.camera.rays(px[keep]))
    say(f"two-view initialisation frames 0-{k}: {tv.model} (E singular values {np.round(tv.singular_values, 3)}, "
        f"null-space ratio {tv.null_space_ratio:.2f}), {int(tv.valid.sum())} landmarks, unit baseline")
    v = tv.valid
    X1 = tv.depths1[v, None] * ds.camera.rays(px0[keep][v])
    X2 = X1 @ tv.R.T + tv.T
    pose_wc = np.eye(4)
    pose_wc[:3, :3], pose_wc[:3, 3] = tv.R.T, -tv.R.T @ tv.T
    slam.prev = None
    slam.initialise(img, px[keep][v], X2, pose_wc)
    return k + 1, False
