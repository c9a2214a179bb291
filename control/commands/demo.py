"""vbnav demo: teach a route in the simulated room and repeat it twice from an offset start."""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from vbnav.control.commands._common import add_record_overwrite_arg, apart_from_config, output_file, record_target_error
from vbnav.drivers.errors import InputError


def _seed(text: str) -> int:
    """argparse type: a seed, an integer >= 0 (numpy's generators take no negative seed)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}")
    return v


def register(sub) -> None:
    p = sub.add_parser(
        "demo", help="teach and repeat a 20 m route on the simulated robot (no hardware needed)",
        description="Teach a closed 20 m route with four turns in the simulated room, then repeat it twice from a "
                    "start offset of 0.3 m lateral and 10 degrees heading, with motor and image noise. Writes "
                    "metrics.json, paths.png (top view) and the route directory to --out.")
    p.add_argument("--out", default="out/demo", metavar="DIR", help="output directory (default out/demo)")
    p.add_argument("--seed", type=_seed, default=None, help="seed of the world textures and all noise (default: "
                                                          "the configuration's sim.seed, 0 in configs/sim.yaml)")
    p.add_argument("--repeats", type=int, default=2, help="number of repeats (default 2)")
    p.add_argument("--config", "-c", default=None, metavar="FILE", help="simulated robot configuration "
                   "(default configs/sim.yaml)")
    p.add_argument("--record", default=None, metavar="FILE.mcap", help="also record the runs (MCAP)")
    add_record_overwrite_arg(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from vbnav.control.config import ROOM_WORLDS, load_config
    from vbnav.control.demo import Scenario, demo_route, run_demo, start_pose
    from vbnav.control.runtime.progress import ProgressPrinter

    cfg = load_config(args.config)
    if cfg.camera.driver != "sim" or cfg.drive.driver != "sim":
        raise InputError(f"{cfg.source}: uses camera '{cfg.camera.driver}' and drive '{cfg.drive.driver}'; the "
                         "demo needs the simulated robot (use 'vbnav teach' and 'vbnav repeat' on hardware)")
    if cfg.sim.world not in ROOM_WORLDS:
        raise InputError(f"{cfg.source}: sim.world {cfg.sim.world!r}: the demo teaches the simulated room's 7 m x "
                         f"4 m loop, which needs sim.world {' or '.join(ROOM_WORLDS)}")
    why = record_target_error(args, overwrite_is_record_only=True)
    if why:
        raise InputError(why)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: is a file, expected an output directory")
    if args.repeats < 1:
        raise InputError(f"--repeats {args.repeats}: expected at least 1")
    output_file(args.record, "--record")
    apart_from_config(cfg, {"--record": args.record})
    seed = cfg.sim.seed if args.seed is None else args.seed
    route_start = start_pose(demo_route())
    if "start_pose" in cfg.sim.model_fields_set and not _same_pose(cfg.sim.start(), route_start):
        print(f"vbnav demo: note: {cfg.source}: sim.start_pose {cfg.sim.start_pose} is not used: the demo teaches "
              f"its route from the route's start ({route_start.x:.2f}, {route_start.z:.2f}, "
              f"{math.degrees(route_start.theta):.1f} deg)", file=sys.stderr)
    printer = ProgressPrinter()
    printer(f"vbnav demo: seed {seed}, output in {out}/", force=True)
    metrics = run_demo(out, Scenario(seed=seed, repeats=args.repeats), cfg,
                       progress=lambda s: printer(s, force=s.startswith(("taught", "repeat 1:", "repeat 2:",
                                                                         "repeat 3:"))),
                       record=args.record, record_overwrite=args.overwrite)
    printer.done()
    print(json.dumps({k: v for k, v in metrics.items() if k != "repeats"}, indent=2))
    print(f"wrote {out / 'metrics.json'}, {out / 'paths.png'} and the route in {out / 'route'}")
    ok = metrics["completed"] and metrics["rms_lateral_error_m"] <= 0.03 and metrics["max_lateral_error_m"] <= 0.10
    print("result: " + ("PASS" if ok else "OUTSIDE the bars (completed, RMS <= 3 cm, max <= 10 cm)"))
    return 0 if metrics["completed"] and not metrics.get("recording_error") else 1   # a --record not made


def _same_pose(a, b) -> bool:
    return abs(a.x - b.x) < 1e-6 and abs(a.z - b.z) < 1e-6 and abs(math.remainder(a.theta - b.theta, math.tau)) < 1e-6
