"""A TUM-layout view of ``room_rgbd5`` for ``vbnav vo`` (benchmarks/vo_real.py and tests/test_vo_real.py)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from vbnav.control.trajectory_metrics import write_tum
from vbnav.vision.geometry import matrix_from_quat


def room_view(src: Path, dst: Path) -> Path:
    """TUM-layout view of room_rgbd5: rgb.txt, depth.txt, groundtruth.txt, camera.yaml (1 s apart)."""
    dst.mkdir(parents=True, exist_ok=True)
    rows = np.loadtxt(src / "pose.txt").reshape(-1, 7)
    rgb, dep, poses = ["# timestamp filename"], ["# timestamp filename"], []
    for k in range(len(rows)):
        for sub, ext, lst in (("color", "png", rgb), ("depth", "pgm", dep)):
            link = dst / f"{sub}_{k + 1}.{ext}"
            if not link.exists():
                link.symlink_to(src / sub / f"{k + 1}.{ext}")
            lst.append(f"{float(k):.6f} {link.name}")
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = matrix_from_quat(rows[k, 3:7]), rows[k, :3]
        poses.append(M)
    (dst / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (dst / "depth.txt").write_text("\n".join(dep) + "\n")
    write_tum(dst / "groundtruth.txt", np.arange(len(rows), dtype=float), np.array(poses))
    (dst / "camera.yaml").write_text(yaml.safe_dump({"width": 640, "height": 480, "fx": 518.0, "fy": 519.0,
                                                     "cx": 325.5, "cy": 253.5, "depth_scale": 0.001}))
    return dst
