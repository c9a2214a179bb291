"""Obstacle detection: ms per 640x480 frame and detection rates, against a naive baseline in the same run.

Ours: robust ground-plane fit in (u, v, D) + per-pixel thresholds (vision/obstacles.py).
Naive: per-pixel 3D reconstruction from disparity (float64 points, rotated into the
floor frame with the KNOWN camera mounting) and a height threshold above that floor.

Scenes (640x480, fx 400, camera 0.25 m up, 7.5 cm baseline, as configs/sim.yaml):
- "sim": the simulated corridor (drivers/sim_world.py) with a 2 cm box at 3 m, a 1 cm box
  and a 5 cm box at 2 m and a flat sheet; the simulated camera's exact disparity, the same
  with 0.1 px Gaussian noise, and SGBM on the rendered pair;
- "step": the corridor with a 15 cm step down 1.5 m ahead.
Rates: fraction of each object's visible pixels labelled obstacle (negative for the step's
lower floor), fraction of floor pixels labelled obstacle. Rows "pitch+1deg" give both
methods a mounting that is 1 degree off (ours fits the plane; naive trusts the mounting).

With --kitti DIR (default: ../shared/data/kitti06_stereo when present) it also labels every
pair of KITTI 06 (SGBM, full resolution, 10 cm thresholds) with the piecewise ground and with
one plane (the peer) in the same run, and prints the road corridor's ground / negative /
obstacle shares (and 15-30 m ahead), the fitted camera height / pitch / roll and ms per pair.

Run: .venv/bin/python benchmarks/obstacles.py [--repeats N] [--kitti DIR | --no-kitti]
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from vbnav.drivers.clock import SimClock
from vbnav.drivers.sim.camera import SimCamera
from vbnav.drivers.sim.world import KINDS, World
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.geometry import CameraMount, Pose2, camera_pose, rot_x
from vbnav.vision.ground_plane import expected_plane
from vbnav.vision.obstacles import ObstacleParams, PixelClass, detect_obstacles
from vbnav.vision.stereo import SGBM_640x480, SGBM_KITTI, StereoRig, sgbm_disparity

CAM = PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5)
MOUNT = CameraMount(0.25, 0.10, 0.0, 0.0)
RIG = StereoRig(PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5), 0.075)
SGBM = SGBM_640x480


def naive_detect(disp: np.ndarray, rig: StereoRig, height: float, pitch: float, h_obs: float, h_neg: float,
                 max_height: float = 1.0, max_range: float = 6.0):
    """Per-pixel 3D points and a height threshold above the floor given by the mounting
    (same scope rules as ours: higher than max_height or farther than max_range is unknown)."""
    h, w = disp.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = rig.fb / disp.astype(np.float64)
        pts = np.stack([(u - rig.cx) * z / rig.fx, (v - rig.cy) * z / rig.fy, z], axis=-1)
    R = rot_x(-pitch)                                   # camera axes in the level robot frame
    world = pts @ R.T + np.array([0.0, -height, 0.0])
    elev = -world[..., 1]
    labels = np.full((h, w), PixelClass.UNKNOWN, np.uint8)
    valid = np.isfinite(elev) & (disp > 0) & (elev <= max_height) & (z <= max_range)
    labels[valid] = PixelClass.GROUND
    labels[valid & (elev > h_obs)] = PixelClass.OBSTACLE
    labels[valid & (elev < -h_neg)] = PixelClass.NEGATIVE
    return labels


def _data_dir() -> Path:
    """$VBNAV_DATA, else the first shared/data beside the repository or one level up."""
    import os
    if os.environ.get("VBNAV_DATA"):
        return Path(os.environ["VBNAV_DATA"])
    for up in Path(__file__).resolve().parents[1:4]:
        if (up / "shared" / "data").is_dir():
            return up / "shared" / "data"
    return Path("shared/data")


def timed(fn, repeats):
    ts = []
    out = None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t)
    return out, 1e3 * float(np.median(ts)), 1e3 * float(np.min(ts))


def build_scenes():
    w = World.corridor(seed=3)
    w.add_box("box2cm@3m", (0.0, 3.175), (0.3, 0.02, 0.15))
    w.add_box("box1cm@2m", (0.7, 2.175), (0.3, 0.01, 0.15))
    w.add_box("box5cm@2m", (-0.6, 2.175), (0.3, 0.05, 0.15))
    w.add_floor_sheet("sheet", (0.45, 1.4), (0.4, 0.5), thickness=0.001)
    step = World.corridor_with_step(seed=4, step_at=1.5, step_depth=0.15)
    out = {}
    for name, world in (("sim", w), ("step", step)):
        cam = SimCamera(world, CAM, MOUNT, lambda: Pose2(), SimClock(), 15.0, noise_std=2.0, seed=1, stereo_baseline=0.075)
        frame = cam.render_frame(Pose2(), 0, 1)
        ids, _ = world.label_image(CAM, *camera_pose(Pose2(), MOUNT))
        out[name] = (world, frame, ids)
    return out


def rates(world, ids, labels, objects):
    kinds = world.kind_image(ids)
    r = {}
    for name in objects:
        m = np.isin(ids, [q.pid for q in world.group(name)])
        r[name] = float(np.mean(labels[m] == PixelClass.OBSTACLE))
    r["floor FP"] = float(np.mean(labels[kinds == KINDS.index("floor")] == PixelClass.OBSTACLE))
    return r


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--kitti", default=str(_data_dir() / "kitti06_stereo"),
                    help="KITTI 06 folder (calib.txt, image_l, image_r)")
    ap.add_argument("--no-kitti", action="store_true")
    args = ap.parse_args(argv)
    scenes = build_scenes()
    world, frame, ids = scenes["sim"]
    rng = np.random.default_rng(0)
    noisy = frame.disparity + rng.normal(0, 0.1, frame.disparity.shape).astype(np.float32)
    prior = expected_plane(RIG, MOUNT.height, MOUNT.pitch)
    h_obs = 0.01

    print("== speed: ms per 640x480 frame (median / min of %d; the min is the figure on a busy machine) =="
          % args.repeats)
    ours_p = ObstacleParams(obstacle_height=h_obs, noise_px=0.3, max_height=1.0, max_range=6.0, report_range=6.0)
    _, ours_med, ours_min = timed(lambda: detect_obstacles(noisy, RIG, prior, params=ours_p), args.repeats)
    _, naive_med, naive_min = timed(lambda: naive_detect(noisy, RIG, MOUNT.height, MOUNT.pitch, h_obs, 0.03),
                                    args.repeats)
    from vbnav.vision.ground_model import GroundModelParams
    _, pw_med, pw_min = timed(lambda: detect_obstacles(noisy, RIG, prior, params=ours_p, ground=GroundModelParams()),
                              args.repeats)
    _, sgbm_med, sgbm_min = timed(lambda: sgbm_disparity(frame.image, frame.right, SGBM), max(3, args.repeats // 5))
    print(f"{'ours (fit + labels + floor points)':40s} {ours_med:7.2f} / {ours_min:6.2f}")
    print(f"{'ours, piecewise ground (the stage default)':40s} {pw_med:7.2f} / {pw_min:6.2f}")
    print(f"{'naive (3D points + height threshold)':40s} {naive_med:7.2f} / {naive_min:6.2f}")
    print(f"{'ratio naive / ours (min)':40s} {naive_min / ours_min:7.2f}x")
    print(f"{'SGBM (80 disparities, block 5)':40s} {sgbm_med:7.2f} / {sgbm_min:6.2f}")
    print(f"{'ours with SGBM':40s} {ours_med + sgbm_med:7.2f} / {ours_min + sgbm_min:6.2f}")
    print(f"{'naive with SGBM':40s} {naive_med + sgbm_med:7.2f} / {naive_min + sgbm_min:6.2f}")
    print(f"{'ratio (with SGBM) naive / ours (min)':40s} {(naive_min + sgbm_min) / (ours_min + sgbm_min):7.2f}x")

    print("\n== detection: fraction of visible pixels labelled obstacle ==")
    objects = ("box2cm@3m", "box1cm@2m", "box5cm@2m", "sheet")
    D_sgbm = sgbm_disparity(frame.image, frame.right, SGBM)
    wrong = expected_plane(RIG, MOUNT.height, MOUNT.pitch + math.radians(1.0))
    rows = [
        ("exact disparity, 1 cm", frame.disparity, 0.01, 0.0, 12, MOUNT.pitch, prior),
        ("exact disparity, 5 mm", frame.disparity, 0.005, 0.0, 12, MOUNT.pitch, prior),
        ("+0.1 px noise, 1 cm", noisy, 0.01, 0.3, 12, MOUNT.pitch, prior),
        ("SGBM, 2 cm", D_sgbm, 0.02, 0.6, 30, MOUNT.pitch, prior),
        ("+0.1 px noise, 1 cm, pitch+1deg", noisy, 0.01, 0.3, 12, MOUNT.pitch + math.radians(1.0), wrong),
    ]
    head = f"{'input':34s} {'method':6s} " + " ".join(f"{o:>10s}" for o in objects) + f" {'floor FP':>9s}"
    print(head)
    for label, D, h, noise, blob, pitch, pr in rows:
        s = detect_obstacles(D, RIG, pr, params=ObstacleParams(obstacle_height=h, noise_px=noise, min_blob_pixels=blob,
                                                                max_height=1.0, max_range=6.0))
        naive = naive_detect(D, RIG, MOUNT.height, pitch, h, 0.03)
        for meth, lab in (("ours", s.labels), ("naive", naive)):
            r = rates(world, ids, lab, objects)
            print(f"{label:34s} {meth:6s} " + " ".join(f"{100 * r[o]:9.1f}%" for o in objects)
                  + f" {100 * r['floor FP']:8.2f}%")

    sw, sf, sids = scenes["step"]
    lower = (sw.kind_image(sids) == KINDS.index("step")) & (sf.disparity > RIG.fb / 10.0)
    floor = sw.kind_image(sids) == KINDS.index("floor")
    s = detect_obstacles(sf.disparity, RIG, prior, params=ObstacleParams())
    naive = naive_detect(sf.disparity, RIG, MOUNT.height, MOUNT.pitch, 0.01, 0.03)
    print("\n== step down 15 cm at 1.5 m: lower floor (within 10 m) labelled negative; floor labelled negative ==")
    for meth, lab in (("ours", s.labels), ("naive", naive)):
        print(f"{meth:6s} lower floor {100 * np.mean(lab[lower] == PixelClass.NEGATIVE):6.1f}%   "
              f"floor {100 * np.mean(lab[floor] == PixelClass.NEGATIVE):5.2f}%")
    if not args.no_kitti and Path(args.kitti).is_dir():
        kitti_report(Path(args.kitti))


def kitti_report(root: Path) -> None:
    """Every pair of KITTI 06 at full resolution: the road corridor ahead (the one
    tests/test_obstacles_kitti_ground.py judges at half resolution) labelled by the piecewise
    ground (ours) and by one plane fitted to the whole image (the peer, as before), same run."""
    import cv2

    from vbnav.drivers.stereo_calib import load_stereo_calibration
    from vbnav.vision.ground_model import GroundModelParams, corridor_mask
    from vbnav.vision.ground_plane import PlaneFitParams
    H = 1.65
    calib = load_stereo_calibration(root / "calib.txt")
    rig = calib.rig(1226, 370)
    prior = expected_plane(rig, H, 0.0)
    road = corridor_mask(rig, H, rig.baseline / 2.0, 1.25, 7.0, 30.0)
    far = road & corridor_mask(rig, H, rig.baseline / 2.0, 1.25, 15.0, 30.0)
    # 3 sigma of SGBM's disparity noise on this road (0.22-0.30 px, docs/obstacles.md)
    params = ObstacleParams(obstacle_height=0.10, negative_depth=0.10, noise_px=0.75, max_height=2.0)
    fit = PlaneFitParams(inlier_height=0.05, max_height_change=0.15, max_pitch_change_deg=2.0, max_roll_change_deg=2.0)
    methods = {"piecewise": (fit, GroundModelParams(corridor_half_width=1.75)), "one plane": (PlaneFitParams(), None)}
    figs = {m: [] for m in methods}
    ms = {m: 0.0 for m in methods}
    files = sorted((root / "image_l").glob("*.png"))
    print(f"\n== KITTI 06 (Geiger et al., CC BY-NC-SA 3.0), {len(files)} pairs, full resolution, 10 cm thresholds ==")
    print("road: within 1.25 m of the car's centre line, 7-30 m ahead on the mounting's road plane")
    for f in files:
        left = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        right = cv2.imread(str(root / "image_r" / f.name), cv2.IMREAD_GRAYSCALE)
        disp = sgbm_disparity(left, right, SGBM_KITTI)
        for m, (fp, gp) in methods.items():
            t = time.perf_counter()
            s = detect_obstacles(disp, rig, prior, fp, params, gp)
            ms[m] += time.perf_counter() - t
            lab, lab_far = s.labels[road], s.labels[far]
            fl = s.fit.floor
            figs[m].append((np.mean(lab == PixelClass.GROUND), np.mean(lab == PixelClass.NEGATIVE),
                            np.mean(lab == PixelClass.OBSTACLE), np.mean(lab_far == PixelClass.GROUND),
                            fl.height, math.degrees(fl.pitch), math.degrees(fl.roll), s.fit.inlier_fraction))
    print(f"{'method':10s} {'ground min/mean':>16s} {'negative max':>13s} {'obstacle max':>13s} "
          f"{'15-30 m ground min':>19s} {'pairs >=97% & <=1% neg':>23s} {'ms/pair':>8s}")
    for m, rows in figs.items():
        a = np.array(rows)
        ok = int(np.sum((a[:, 0] >= 0.97) & (a[:, 1] <= 0.01)))
        print(f"{m:10s} {100 * a[:, 0].min():7.1f}/{100 * a[:, 0].mean():5.1f} % {100 * a[:, 1].max():11.2f} % "
              f"{100 * a[:, 2].max():11.2f} % {100 * a[:, 3].min():17.1f} % {ok:>17d}/{len(a)} "
              f"{1e3 * ms[m] / len(a):8.1f}")
        print(f"{'':10s} fitted camera height {a[:, 4].min():.3f}..{a[:, 4].max():.3f} m (nominal 1.65), pitch "
              f"{a[:, 5].min():.2f}..{a[:, 5].max():.2f} deg, roll {a[:, 6].min():.2f}..{a[:, 6].max():.2f} deg, "
              f"inliers {100 * a[:, 7].min():.0f}-{100 * a[:, 7].max():.0f} %")


if __name__ == "__main__":
    main()
