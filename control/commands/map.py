"""``vbnav map build|info|plot``: Marvin's line-segment map (DLM) on disk (docs/line_map.md)."""
from __future__ import annotations

import json
import math
import sys

import cv2
import numpy as np

from vbnav.control.commands._common import add_config_arg, output_file, positive
from vbnav.drivers.errors import InputError


def register(sub) -> None:
    p = sub.add_parser("map", help="build, inspect and plot a 3D line-segment map (Marvin's DLM)",
                       description="Marvin's map of 3D line segments (section 11.2.1.1): 'build' drives the "
                                   "configured robot (controller.script) with a stereo camera while the line-map "
                                   "stage fuses the segments, then writes the map; 'info' prints its summary; "
                                   "'plot' draws a top view and a 3D view as PNG.")
    sp = p.add_subparsers(dest="map_command", required=True, metavar="{build,info,plot}")
    b = sp.add_parser("build", help="drive the configured script while mapping, then save the map")
    add_config_arg(b, default="sim_stereo")
    b.add_argument("--out", required=True, metavar="MAP", help="map file to write (JSON)")
    b.add_argument("--duration", type=positive, default=None, metavar="S",
                   help="stop after S seconds (default: the script's length)")
    b.set_defaults(func=run_build)
    i = sp.add_parser("info", help="print a map's summary as JSON")
    i.add_argument("map", metavar="MAP")
    i.set_defaults(func=run_info)
    pl = sp.add_parser("plot", help="top view and 3D view of a map as PNG")
    pl.add_argument("map", metavar="MAP")
    pl.add_argument("--out", required=True, metavar="PNG")
    pl.add_argument("--all", action="store_true", help="also draw unverified candidates (grey)")
    pl.set_defaults(func=run_plot)


def run_build(args) -> int:
    from vbnav.control.controllers.manual import ScriptedController
    from vbnav.control.config import load_config
    from vbnav.control.line_map_file import save_map
    from vbnav.control.runtime.factory import make_robot
    from vbnav.control.runtime.progress import ProgressPrinter
    from vbnav.control.runtime.runtime import Runtime
    from vbnav.control.stages.line_map import LineMapStage

    output_file(args.out, "--out")
    cfg = load_config(args.config)
    try:
        stage = LineMapStage.from_config(cfg)
    except ValueError as exc:
        raise InputError(f"{cfg.source}: {exc}") from None
    controller = ScriptedController(cfg.controller.script)
    robot = make_robot(cfg, [stage])
    rt = Runtime(cfg, robot.drive, controller, robot.clock, robot.pipeline)
    printer = ProgressPrinter()

    def progress(r) -> None:
        s = stage.map.summary()
        printer(f"map: {stage.stats['frames']} frames, {s['verified']} verified / {s['segments']} segments, "
                f"update {stage.stats['update_ms']:.0f} ms")

    duration = args.duration if args.duration is not None else controller.total_s + 0.5
    stage.start()
    try:
        result = rt.run(duration, progress)
    finally:
        stage.stop()
        printer.done()
    stage.abstraction.step()            # a last abstraction pass on the final map
    meta = {"config": str(cfg.source), "frames": stage.stats["frames"],
            "objects": [{"footprint": np.round(p.footprint, 4).tolist(), "height": round(p.height, 3)}
                        for p in stage.abstraction.polygons]}
    save_map(stage.map, args.out, meta)
    s = stage.map.summary()
    print(f"map build ended: {result.reason}; {stage.stats['frames']} frames, {s['verified']} verified segments "
          f"({s['total_length_m']} m), {s['candidates']} candidates, {len(meta['objects'])} objects -> {args.out}")
    return 0 if stage.stats["frames"] > 0 else 1


def map_info(lmap, meta) -> dict:
    s = lmap.summary()
    V = lmap.P[lmap.verified]
    if len(V):
        lo, hi = V.reshape(-1, 3).min(axis=0), V.reshape(-1, 3).max(axis=0)
        s["extent_m"] = {"x": [round(lo[0], 3), round(hi[0], 3)], "z": [round(lo[2], 3), round(hi[2], 3)],
                         "height": [round(-hi[1], 3), round(-lo[1], 3)]}
        s["support_median"] = float(np.median(lmap.support[lmap.verified]))
    s["objects"] = len(meta.get("objects", []))
    return s


def run_info(args) -> int:
    from vbnav.control.line_map_file import load_map
    lmap, meta = load_map(args.map)
    print(json.dumps(map_info(lmap, meta), indent=2))
    return 0


def _panel(P: np.ndarray, colours: list, project, size=(600, 600), title="") -> np.ndarray:
    img = np.full((size[1], size[0], 3), 255, np.uint8)
    if len(P):
        uv = project(P.reshape(-1, 3))
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        scale = 0.9 * min(size[0] / max(hi[0] - lo[0], 1e-6), size[1] / max(hi[1] - lo[1], 1e-6))
        off = np.array(size) / 2 - scale * (lo + hi) / 2
        px = (uv * scale + off).reshape(-1, 2, 2)
        for (a, b), c in zip(px, colours):
            cv2.line(img, (int(a[0]), int(size[1] - a[1])), (int(b[0]), int(size[1] - b[1])), c, 1, cv2.LINE_AA)
        # 1 m scale bar
        cv2.line(img, (20, size[1] - 20), (20 + int(scale), size[1] - 20), (0, 0, 0), 2)
        cv2.putText(img, "1 m", (20, size[1] - 28), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
    cv2.putText(img, title, (10, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1)
    return img


def run_plot(args) -> int:
    from vbnav.control.image_files import write_png
    from vbnav.control.line_map_file import load_map
    output_file(args.out, "--out")
    lmap, meta = load_map(args.map)
    sel = np.ones(len(lmap), bool) if args.all else lmap.verified
    P = lmap.P[sel]
    h = -P[..., 1].mean(axis=1) if len(P) else np.zeros(0)
    hmax = max(float(h.max()), 1e-6) if len(h) else 1.0
    colours = [((0, int(200 * (1 - a)), int(255 * a)) if v else (170, 170, 170))
               for a, v in zip(np.clip(h / hmax, 0, 1), lmap.verified[sel])]
    top = _panel(P, colours, lambda X: X[:, [0, 2]], title="top view (x right, z up), colour = height")
    az, el = math.radians(35.0), math.radians(25.0)

    def oblique(X):
        x, y, z = X[:, 0], -X[:, 1], X[:, 2]
        xr = math.cos(az) * x - math.sin(az) * z
        zr = math.sin(az) * x + math.cos(az) * z
        return np.column_stack((xr, math.cos(el) * y + math.sin(el) * zr))

    view3d = _panel(P, colours, oblique, title="3D view")
    write_png(args.out, np.hstack((top, view3d)))
    print(f"vbnav map plot: {len(P)} segments -> {args.out}", file=sys.stdout)
    return 0
