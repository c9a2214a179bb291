"""Rendering speed of the simulated camera against two naive peers, in one run.

Prints ms per 640x480 frame (median, p90) on ONE core (cv2.setNumThreads(1)),
along the room's suggested route, for:
  - ours, mono (image) and stereo (left + right + true disparity, via SimCamera);
  - painter: whole quads sorted far to near by centroid depth, each warped into
    the full frame with its full-resolution texture and a full-frame polygon
    mask (near-plane clipped so the floor is right; no tiles, no mip levels,
    no per-pixel depth test);
  - raycast: per-pixel ray / plane intersection with every quad in numpy,
    nearest hit kept, texture sampled bilinearly (cv2.remap): the obvious
    "correct" renderer.
and the ratio of each peer to ours. It also prints how far the peers' images
are from ours (mean absolute grey difference, and the fraction of pixels
whose surface id differs from the ray caster's), a check that the speed is not
bought with wrong pictures.

Usage: python benchmarks/sim_render.py [--frames N] [--threads T]
"""
from __future__ import annotations

import argparse
import math
import time

import cv2
import numpy as np

from vbnav.drivers.clock import SimClock
from vbnav.drivers.sim.camera import SimCamera
from vbnav.drivers.sim.render import NEAR_Z, Renderer
from vbnav.drivers.sim.world import World
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.geometry import CameraMount, Pose2, camera_pose

CAM = PinholeCamera(640, 480, 400.0, 400.0, 319.5, 239.5)
MOUNT = CameraMount(height=0.25, forward=0.10)


def route_poses(n: int) -> list[Pose2]:
    route = World.suggested_route()
    legs = [(route[i], route[(i + 1) % len(route)]) for i in range(len(route))]
    total = sum(math.dist(a, b) for a, b in legs)
    poses = []
    for k in range(n):
        s = total * k / n
        for a, b in legs:
            L = math.dist(a, b)
            if s <= L:
                f = s / L
                th = math.atan2(b[0] - a[0], b[1] - a[1]) + 0.3 * math.sin(k)   # some turning
                poses.append(Pose2(a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), th))
                break
            s -= L
    return poses


def _clip_near(P: np.ndarray):
    out = []
    for i in range(len(P)):
        a, b = P[i], P[(i + 1) % len(P)]
        if a[2] >= NEAR_Z:
            out.append(a)
        if (a[2] >= NEAR_Z) != (b[2] >= NEAR_Z):
            out.append(a + (NEAR_Z - a[2]) / (b[2] - a[2]) * (b - a))
    return np.array(out) if len(out) >= 3 else None


def painter(world: World, R_wc, t_wc) -> np.ndarray:
    """Far-to-near whole-quad painter's algorithm into full frames."""
    H, W = CAM.height, CAM.width
    img = np.full((H, W), world.background, np.uint8)
    K = CAM.K
    items = []
    for q in world.polygons:
        Pc = (q.corners - t_wc) @ R_wc
        if (Pc[:, 2] < NEAR_Z).all():
            continue
        if q.normal @ (t_wc - q.origin) <= 0 and not q.two_sided:
            continue
        items.append((Pc[:, 2].mean(), q, Pc))
    for _, q, Pc in sorted(items, key=lambda it: -it[0]):
        poly = _clip_near(Pc)
        if poly is None:
            continue
        px = np.column_stack((CAM.fx * poly[:, 0] / poly[:, 2] + CAM.cx, CAM.fy * poly[:, 1] / poly[:, 2] + CAM.cy))
        mask = np.zeros((H, W), np.uint8)
        cv2.fillConvexPoly(mask, np.round(np.clip(px, -1e5, 1e5) * 16).astype(np.int32), 1, cv2.LINE_8, 4)
        th, tw = q.texture.shape
        sa, sb = q.width / tw, q.height / th
        Ru, Rv = R_wc.T @ q.u, R_wc.T @ q.v
        o = R_wc.T @ (q.origin - t_wc) + 0.5 * sa * Ru + 0.5 * sb * Rv
        M = K @ np.column_stack((Ru * sa, Rv * sb, o))
        warped = cv2.warpPerspective(q.texture, M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        np.copyto(img, warped, where=mask.view(bool))
    return img


class RayCaster:
    """Per-pixel ray casting against every quad (numpy), bilinear texture lookup."""

    def __init__(self, world: World):
        self.world = world
        v, u = np.mgrid[0:CAM.height, 0:CAM.width].astype(np.float64)
        self.rays = np.stack(((u - CAM.cx) / CAM.fx, (v - CAM.cy) / CAM.fy, np.ones_like(u)), axis=-1)

    def render(self, R_wc, t_wc) -> tuple[np.ndarray, np.ndarray]:
        H, W = CAM.height, CAM.width
        rays_w = self.rays @ R_wc.T                       # world directions, z-component scaled to camera z = 1
        best = np.full((H, W), np.inf)
        ids = np.zeros((H, W), np.int32)
        img = np.full((H, W), float(self.world.background), np.float32)
        for q in self.world.polygons:
            n = q.normal
            denom = rays_w @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                z = ((q.origin - t_wc) @ n) / denom        # camera depth along each ray
            hit = (z > NEAR_Z) & (z < best)
            if not q.two_sided:
                hit &= denom < 0
            if not hit.any():
                continue
            P = t_wc + rays_w * z[..., None]
            a = (P - q.origin) @ q.u
            b = (P - q.origin) @ q.v
            hit &= (a >= 0) & (a <= q.width) & (b >= 0) & (b <= q.height)
            if not hit.any():
                continue
            th, tw = q.texture.shape
            col = (a * tw / q.width - 0.5).astype(np.float32)
            row = (b * th / q.height - 0.5).astype(np.float32)
            val = cv2.remap(q.texture, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            best[hit] = z[hit]
            ids[hit] = q.pid
            img[hit] = val[hit]
        return np.rint(img).astype(np.uint8), ids


def timed(fn, poses, repeat=1):
    ts, last = [], None
    for p in poses:
        t0 = time.perf_counter()
        for _ in range(repeat):
            last = fn(p)
        ts.append((time.perf_counter() - t0) / repeat * 1e3)
    return np.array(ts), last


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60, help="poses along the route (default 60)")
    ap.add_argument("--threads", type=int, default=1, help="OpenCV threads (default 1: one core)")
    args = ap.parse_args()
    cv2.setNumThreads(args.threads)
    world = World.room(seed=0)
    poses = route_poses(args.frames)
    views = [camera_pose(p, MOUNT) for p in poses]
    renderer = Renderer(world, CAM)
    mono_cam = SimCamera(world, CAM, MOUNT, lambda: Pose2(), SimClock(), 15, noise_std=2.0)
    stereo_cam = SimCamera(world, CAM, MOUNT, lambda: Pose2(), SimClock(), 15, noise_std=2.0, stereo_baseline=0.1)
    caster = RayCaster(world)
    for v in views[:3]:                                   # warm caches (pyramids) outside the timing
        renderer.render(*v)
    stereo_cam.render_frame(poses[0])

    t_ours, _ = timed(lambda v: renderer.render(*v).image, views)
    t_cam, _ = timed(lambda p: mono_cam.render_frame(p), poses)
    t_stereo, _ = timed(lambda p: stereo_cam.render_frame(p), poses)
    # The peers are slow: a subset of the poses, with ours timed again on the same poses,
    # interleaved, so that the ratio is immune to load changes on a shared machine.
    sub = views[:: max(1, len(views) // 12)]
    t_sub, t_paint, t_ray = [], [], []
    diffs_paint, diffs_ray, id_mismatch = [], [], []
    for v in sub:
        t_sub.append(timed(lambda v: renderer.render(*v).image, [v])[0][0])
        t, paint_img = timed(lambda v: painter(world, *v), [v])
        t_paint.append(t[0])
        t, (ray_img, ray_ids) = timed(lambda v: caster.render(*v), [v])
        t_ray.append(t[0])
        ours = renderer.render(*v, ids=True)
        diffs_ray.append(np.abs(ours.image.astype(int) - ray_img).mean())
        diffs_paint.append(np.abs(paint_img.astype(int) - ray_img).mean())
        id_mismatch.append(np.mean(ours.ids != ray_ids))
    t_sub, t_paint, t_ray = np.array(t_sub), np.array(t_paint), np.array(t_ray)

    def row(name, t, ref=None):
        ratio = "" if ref is None else f"   peer/ours = {np.median(t) / np.median(ref):6.1f}x"
        print(f"{name:<38} median {np.median(t):7.2f} ms   p90 {np.percentile(t, 90):7.2f} ms{ratio}")

    print(f"640x480, {len(views)} poses along the room route ({len(sub)} for the peers), "
          f"OpenCV threads = {args.threads}")
    row("ours: render (image only)", t_ours)
    row("ours: SimCamera mono frame (+noise)", t_cam)
    row("ours: SimCamera stereo frame (+disp)", t_stereo)
    row("ours: render, peers' poses", t_sub)
    row("peer: painter, full-frame warps", t_paint, t_sub)
    row("peer: numpy per-pixel ray casting", t_ray, t_sub)
    print(f"mean |grey difference| to the ray caster: ours {np.mean(diffs_ray):.1f}, "
          f"painter {np.mean(diffs_paint):.1f} (texture filtering differs: ours pre-filters by distance, the peers sample full resolution)")
    print(f"pixels whose surface id differs from the ray caster: ours {100 * np.mean(id_mismatch):.3f} %")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
