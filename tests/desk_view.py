"""Build a TUM-layout view of ``desk_rgbd`` (symlinks, rgb.txt, groundtruth.txt, camera.yaml) in a folder.

The tag grid's layout is not listed in the data; it follows from the per-tag
poses in the grid frame, inv(grid[i]) @ cMo_tag, averaged over all frames and
put in the grid's plane (z = 0). ViSP's tag frame has its corners at
(-s/2, -s/2), (s/2, -s/2), (s/2, s/2), (-s/2, s/2) in the order (1, 0, 3, 2)
of OpenCV's ArUco corner order (checked by projecting cMo onto the detections).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import yaml

from vbnav.control.trajectory_metrics import write_tum

RATE_HZ = 30.0
GRID_ROWS, GRID_COLS = 4, 3
VISP_CORNERS_IN_CV_ORDER = np.array([[1, -1], [-1, -1], [-1, 1], [1, 1]]) * 0.5


def build_desk_view(src: Path, dst: Path) -> Path:
    data = json.loads((src / "apriltag_data.json").read_text())
    cam = json.loads((src / "cam.json").read_text())
    s = float(data["tag_size"])
    grids = [np.array(g) for g in data["grid"]]
    # Tag centres in the grid frame (median over frames of inv(grid) @ cMo_tag); the physical board is a
    # regular 3 x 4 grid (ids column by column) of tags turned 90 degrees about the normal, in the z = 0
    # plane: fit that regular layout rather than trusting each tag's noisy pose.
    centres: dict[int, list] = {}
    for G, det in zip(grids, data["detections"]):
        Ginv = np.linalg.inv(G)
        for tid, d in det.items():
            centres.setdefault(int(tid), []).append((Ginv @ np.array(d["cMo"]))[:3, 3])
    ids = np.array(sorted(centres))
    med = np.array([np.median(centres[i], axis=0) for i in ids])
    col, row = ids // GRID_ROWS, ids % GRID_ROWS
    ax = np.linalg.lstsq(np.column_stack((np.ones(len(ids)), col)), med[:, 0], rcond=None)[0]
    ay = np.linalg.lstsq(np.column_stack((np.ones(len(ids)), row)), med[:, 1], rcond=None)[0]
    R_tag = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    local = np.column_stack((VISP_CORNERS_IN_CV_ORDER * s, np.zeros(4)))
    layout = {}
    for tid in range(GRID_ROWS * GRID_COLS):
        c = np.array([ax[0] + ax[1] * (tid // GRID_ROWS), ay[0] + ay[1] * (tid % GRID_ROWS), 0.0])
        layout[tid] = (local @ R_tag.T + c).round(5).tolist()
    dst.mkdir(parents=True, exist_ok=True)
    rgb = ["# timestamp filename"]
    stamps = np.arange(len(grids)) / RATE_HZ
    for i, t in enumerate(stamps):
        name = f"color_image_{i:04d}.png"
        link = dst / name
        if not link.exists():
            link.symlink_to(src / name)
        rgb.append(f"{t:.6f} {name}")
    depth = ["# timestamp filename"]
    for p in sorted(src.glob("depth_image_*.npz")):  # depth (mm, registered to colour) for the first frames
        i = int(p.stem.rsplit("_", 1)[1])
        if not (dst / p.name).exists():
            (dst / p.name).symlink_to(p)
        depth.append(f"{i / RATE_HZ:.6f} {p.name}")
    (dst / "depth.txt").write_text("\n".join(depth) + "\n")
    (dst / "rgb.txt").write_text("\n".join(rgb) + "\n")
    write_tum(dst / "groundtruth.txt", stamps, np.linalg.inv(np.asarray(grids)))  # camera-to-world, grid = world
    camera = {"width": cam["w"], "height": cam["h"], "fx": cam["px"], "fy": cam["py"], "cx": cam["u0"],
              "cy": cam["v0"], "depth_scale": float(cam.get("depthScale", 0.001)), "tag_grid": {"family": "36h11", "corners": layout}}
    (dst / "camera.yaml").write_text(yaml.safe_dump(camera))
    return dst
