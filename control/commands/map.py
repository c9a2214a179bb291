"""``vbnav map build|info|plot|view``: Marvin's line-segment map (DLM) on disk (docs/line_map.md)."""
from __future__ import annotations

import json
import math
import sys

import cv2
import numpy as np

from vbnav.control.commands._common import (add_config_arg, apart_from_config, apply_realtime, distinct_files,
                                           duration_within_script, not_recorded_yet,
                                           output_file, positive, record_target_error, refuse_unserved_live_view)
from vbnav.control.commands._net import add_telemetry_args, attach_telemetry
from vbnav.drivers.errors import InputError


def register(sub) -> None:
    p = sub.add_parser("map", help="build, inspect and plot a 3D line-segment map (Marvin's DLM)",
                       description="Marvin's map of 3D line segments (section 11.2.1.1): 'build' drives the "
                                   "configured robot (controller.script) with a stereo camera while the line-map "
                                   "stage fuses the segments, then writes the map; 'info' prints its summary; "
                                   "'plot' draws a top view and a 3D view as PNG; 'view' serves it to the Foxglove "
                                   "app as a 3D scene.")
    sp = p.add_subparsers(dest="map_command", required=True, metavar="{build,info,plot,view}")
    b = sp.add_parser("build", help="drive the configured script while mapping, then save the map")
    add_config_arg(b, default="sim_stereo")
    b.add_argument("--out", required=True, metavar="MAP", help="map file to write (JSON)")
    b.add_argument("--duration", type=positive, default=None, metavar="S",
                   help="stop after S seconds (default: the script's length)")
    b.add_argument("--realtime", action="store_true",
                   help="simulated robot: run on the wall clock (sim.realtime: true) so telemetry and the live view "
                        "open; without it the simulated robot runs faster than real time and only records (refused with a "
                        "real drive or camera: always on the wall clock)")
    b.add_argument("--live-view", action="store_true",
                   help="serve the live view to the Foxglove app (telemetry.live_view.enabled: true), the map "
                        "growing as a 3D scene on /vbnav/map/lines")
    add_telemetry_args(b, overwrite_help="an existing --out map")
    b.set_defaults(func=run_build)
    i = sp.add_parser("info", help="print a map's summary as JSON")
    i.add_argument("map", metavar="MAP", help="map file (vbnav map build, goto --map-out)")
    i.set_defaults(func=run_info)
    pl = sp.add_parser("plot", help="top view and 3D view of a map as PNG")
    pl.add_argument("map", metavar="MAP", help="map file (vbnav map build, goto --map-out)")
    pl.add_argument("--out", required=True, metavar="PNG", help="the PNG to write: top view and oblique 3D view, "
                    "colour = height")
    pl.add_argument("--all", action="store_true", help="also draw unverified candidates (grey)")
    pl.set_defaults(func=run_plot)
    v = sp.add_parser("view", help="serve a map to the Foxglove app as a 3D scene until Ctrl-C",
                      description="Open a Foxglove WebSocket server on 127.0.0.1 that publishes the map's segments "
                                  "(/vbnav/map/lines, frame odom: green verified, grey candidates, orange "
                                  "hypotheses) and its planning grid (/vbnav/map/grid: 100 mapped obstacle, 50 "
                                  "within the robot radius, 0 free), until Ctrl-C. In Foxglove: Open connection, "
                                  "Foxglove WebSocket, ws://127.0.0.1:PORT.")
    v.add_argument("map", metavar="MAP", help="map file (vbnav map build, goto --map-out)")
    v.add_argument("--port", type=_port, default=8765, metavar="P",
                   help="WebSocket port (default 8765; 0: any free port)")
    v.add_argument("--robot-radius", type=positive, default=0.2, metavar="M",
                   help="robot radius the planning grid is grown by, m (default 0.2, as in vbnav goto --map)")
    v.add_argument("--duration", type=positive, default=None, metavar="S",
                   help="stop after S seconds (default: until Ctrl-C)")
    v.set_defaults(func=run_view)


def _port(text: str) -> int:
    import argparse
    try:
        port = int(text)
    except ValueError:
        port = -1
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"expected a port number 0..65535, got {text!r}")
    return port


def run_build(args) -> int:
    from vbnav.control.controllers.manual import ScriptedController
    from vbnav.control.config import load_config
    from vbnav.control.line_map_file import MapFileError, objects_meta, save_map
    from vbnav.control.runtime.factory import make_robot
    from vbnav.control.runtime.progress import ProgressPrinter
    from vbnav.control.commands._common import enable_live_view
    from vbnav.control.runtime.runtime import DEVICE_FAULTS, ENDED_WELL, Runtime
    from vbnav.control.stages.line_map import LineMapStage

    output_file(args.out, "--out")
    output_file(args.record, "--record")
    distinct_files({"--out": args.out, "--record": args.record})
    not_recorded_yet([args.out], f"--out {args.out}", args.overwrite, "a map is")
    why = record_target_error(args)
    if why:
        raise InputError(why)
    cfg = load_config(args.config)
    apart_from_config(cfg, {"--out": args.out, "--record": args.record})
    if cfg.controller.kind != "scripted":      # it drove the (default) script whatever the robot's controller was
        raise InputError(f"{cfg.source}: controller.kind is {cfg.controller.kind!r}; map build drives "
                         f"controller.script, so it needs controller.kind: scripted and the script to drive")
    duration_within_script(cfg.controller.script, args.duration, f"{cfg.source}: controller.script")
    apply_realtime(cfg, args.realtime)
    if args.live_view:
        enable_live_view(cfg, args.no_telemetry)
    refuse_unserved_live_view(cfg, args.no_telemetry, "add --realtime")
    try:
        stage = LineMapStage.from_config(cfg)
    except ValueError as exc:
        raise InputError(f"{cfg.source}: {exc}") from None
    controller = ScriptedController(cfg.controller.script)
    robot = make_robot(cfg, [stage])
    # On the simulated clock (faster than real time) the slow loop runs on the frames' time, not in a thread
    # woken by the wall clock: the map is then the same on any machine.
    stage.abstraction_inline = robot.clock.simulated
    rt = Runtime(cfg, robot.drive, controller, robot.clock, robot.pipeline)
    link = attach_telemetry(rt, cfg, args)
    if link is None:
        return 3
    printer = ProgressPrinter()

    def progress(r) -> None:
        s = stage.map.summary()
        printer(f"map: {stage.stats['frames']} frames, {s['verified']} verified / {s['segments']} segments, "
                f"update {stage.stats['update_ms']:.0f} ms")

    duration = args.duration if args.duration is not None else controller.total_s + 0.5
    stage.start()
    result = None
    try:
        result = rt.run(duration, progress)
    finally:
        stage.stop()
        link.close(result)          # a recording / the live view ends with the final map
        printer.done()
    if stage.abstraction.error is None:
        stage.abstraction.step()        # a last abstraction pass on the final map
    meta = {"config": str(cfg.source), "frames": stage.stats["frames"],
            "objects": objects_meta(stage.abstraction.polygons)}
    if cfg.drive.driver == "sim":       # where the map's frame lies in the simulated world (goto checks --start)
        meta["sim_start_pose"] = [float(v) for v in cfg.sim.start_pose]
    try:
        save_map(stage.map, args.out, meta)     # also after a fault: what was mapped is kept, and said so
        refused = None
    except MapFileError as exc:                 # the run's summary is still said, and that its map is not kept
        refused = exc
    s = stage.map.summary()
    ended_well = result.reason in ENDED_WELL
    print(f"map build ended: {result.reason} ({result.message}); {stage.stats['frames']} frames, "
          f"{s['verified']} verified segments ({s['total_length_m']} m), {s['candidates']} candidates, "
          f"{len(meta['objects'])} objects " + (f"NOT SAVED to {args.out}" if refused else f"-> {args.out}")
          + ("" if ended_well else " (the map up to the fault)"))
    if refused:
        print(f"vbnav map build: --out: {refused}; the map of this run was not saved", file=sys.stderr)
    if stage.stats["unusable"]:
        print(f"map build: {stage.stats['unusable']} frames not mapped, the last because {stage.unusable_reason}",
              file=sys.stderr)
    if not ended_well:
        return 3 if result.reason in DEVICE_FAULTS else 1
    # a --record asked for and not made, as run
    return 0 if stage.stats["frames"] > 0 and refused is None and link.recording_error is None else 1


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
    from vbnav.control.image_files import png_name_problem, write_png
    from vbnav.control.line_map_file import load_map
    output_file(args.out, "--out")
    distinct_files({"--out": args.out}, {"MAP": args.map})
    why = png_name_problem(args.out, "--out")
    if why:
        raise InputError(why)
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


def run_view(args) -> int:
    import signal
    import threading
    import time

    from vbnav.control.map_planning import map_grid
    from vbnav.control.line_map_file import load_map
    lmap, meta = load_map(args.map)
    try:
        from vbnav.control.comms import foxglove_channels as fc
        from vbnav.control.comms.live_view import SceneServer
    except ImportError as exc:
        raise InputError(f"view needs the foxglove-sdk package ({exc}); install vbnav's dependencies") from None
    try:
        grid = map_grid(lmap, meta, args.robot_radius)
    except ValueError as exc:       # a map wider than the grid planned on
        raise InputError(f"{args.map}: {exc}") from None
    cells = np.where(grid.occupied, 100, np.where(grid.blocked, 50, 0)).astype(np.uint8)
    try:
        server = SceneServer("vbnav map", ["/vbnav/map/lines", "/vbnav/map/grid"], port=args.port)
    except Exception as exc:
        raise InputError(f"cannot start the Foxglove server on 127.0.0.1:{args.port}: {exc}") from None
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    try:
        now = time.time_ns()
        server.publish("/vbnav/map/lines", fc.line_map_message(now, lmap.P, lmap.verified, lmap.hypothesis), now)
        server.publish("/vbnav/map/grid", fc.grid_message(now, grid.x0, grid.z0, grid.res, cells), now)
        s = lmap.summary()
        print(f"vbnav map view: {args.map}: {s['verified']} verified segments, {s['candidates']} candidates on "
              f"ws://127.0.0.1:{server.port} (Foxglove: Open connection, Foxglove WebSocket; topics "
              f"/vbnav/map/lines, /vbnav/map/grid in frame odom); Ctrl-C stops", file=sys.stderr, flush=True)
        end = None if args.duration is None else time.monotonic() + args.duration
        while not stop.wait(0.2) and (end is None or time.monotonic() < end):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        server.close()
    return 0
