"""``vbnav goto --map`` re-planning as the map grows, against planning once from the file (``--static-map``),
on the full simulated robot (stereo camera, VSLAM, obstacle stop), simulated clock, in the same run.

Scenarios (docs/line_map.md, "Re-planning as the map grows"):
- ``box_b, empty map``: start (1.4, -2.6) facing box_b, a map that holds nothing, goal (1.4, 1.4) behind the
  box: the planned path runs straight through it;
- ``box_a from S``: the 60-frame loop map of tests/line_scenes.py (the mapping head looking out of a 6 m
  loop), goal (-1.3, 1.2) behind box_a, from the three start poses of tests/test_line_nav.py.

Printed per scenario and mode: the exit code, the ground-truth distance to the goal, the closest approach of
the robot's centre to a wall or box (radius 0.2 m), re-plans, and the map's fast loop per frame.

``--seed`` drives another room (``World.room(seed)``: the same boxes and walls, other textures) with the map
built in it; seed 0 is the room the map was developed in (benchmarks/line_room.py scores the others).

    .venv/bin/python benchmarks/goto_replan.py [--only box_a|box_b] [--rate HZ] [--seed N]
"""
from __future__ import annotations

import argparse
import contextlib
import io
import math
import re
import sys
import tempfile
import time
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from line_scenes import build_map, loop_poses, render_drive  # noqa: E402
from test_line_nav import ABSTRACTION_EVERY  # noqa: E402

from vbnav.control.cli import main as vbnav  # noqa: E402
from vbnav.control.config import CONFIG_DIR  # noqa: E402
from vbnav.control.line_map_file import save_map  # noqa: E402
from vbnav.drivers.sim.world import World  # noqa: E402
from vbnav.vision.line_map import LineMap  # noqa: E402

BOX_A_STARTS = [(0.0, -2.25, -20.0), (0.8, -1.0, -60.0), (-0.9, -1.5, 10.0)]


def _run(cfg: dict, tmp: Path, map_path: Path, start, goal, static: bool) -> dict:
    cfg = dict(cfg, sim=dict(cfg["sim"], start_pose=list(start)))
    (tmp / "robot.yaml").write_text(yaml.safe_dump(cfg))
    args = ["goto", "-c", str(tmp / "robot.yaml"), "--map", str(map_path), "--start", *map(str, start),
            "--goal", *map(str, goal), "--duration", "90"] + (["--static-map"] if static else [])
    out = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = vbnav(args)
    text = out.getvalue()

    def num(pattern: str) -> float:
        m = re.search(pattern, text)
        return float(m.group(1)) if m else math.nan

    return {"rc": rc, "err_cm": num(r"position error ([0-9.]+) cm"),
            "closest_m": num(r"closest approach of the robot centre to a wall or box ([0-9.]+) m"),
            "replans": num(r"([0-9]+) re-plans"), "loop_ms": num(r"fast loop ([0-9]+) ms median"),
            "loop_p95": num(r"ms median, ([0-9]+) ms p95"), "wall_s": time.perf_counter() - t0}


def _row(name: str, mode: str, r: dict) -> str:
    fast = "" if math.isnan(r["loop_ms"]) else f"{r['loop_ms']:.0f} / {r['loop_p95']:.0f} ms"
    rp = "" if math.isnan(r["replans"]) else f"{r['replans']:.0f}"
    return (f"{name:<22} {mode:<10} exit {r['rc']}  {r['err_cm']:>6.1f} cm  closest {r['closest_m']:.3f} m  "
            f"re-plans {rp:>3}  fast loop {fast:<13} ({r['wall_s']:.0f} s)")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", choices=("box_a", "box_b"), default=None)
    ap.add_argument("--rate", type=float, default=15.0, help="camera rate, Hz (default 15)")
    ap.add_argument("--seed", type=int, default=0, help="World.room seed of the simulator and the map (default 0)")
    args = ap.parse_args(argv)
    cfg = yaml.safe_load((CONFIG_DIR / "sim_stereo.yaml").read_text())
    if cfg["sim"].get("world") != "room":
        ap.error(f"configs/sim_stereo.yaml: sim.world must be 'room' for these scenarios, got {cfg['sim'].get('world')!r}")
    cfg["camera"]["rate_hz"] = args.rate
    cfg["sim"]["seed"] = args.seed
    print(f"World.room({args.seed}); goal error and closest approach from the simulator's ground truth; fast loop: "
          "the line map's detection + update per frame, median / p95")
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        if args.only in (None, "box_b"):
            save_map(LineMap(), tmp / "empty.json")
            for static in (True, False):
                r = _run(cfg, tmp, tmp / "empty.json", (1.4, -2.6, 0.0), (1.4, 1.4, 0.0), static)
                print(_row("box_b, empty map", "static" if static else "re-plan", r), flush=True)
        if args.only in (None, "box_a"):
            print("building the 60-frame loop map ...", flush=True)
            # The map the room test scores: the slow loop runs inline as in `vbnav map build` (tests/test_line_nav.py).
            lmap, _ = build_map(render_drive(World.room(args.seed), loop_poses(60)), floor=True,
                                abstraction_every=ABSTRACTION_EVERY)
            save_map(lmap, tmp / "loop60.json")
            for start in BOX_A_STARTS:
                for static in (True, False):
                    r = _run(cfg, tmp, tmp / "loop60.json", start, (-1.3, 1.2, 0.0), static)
                    print(_row(f"box_a from {start[:2]}", "static" if static else "re-plan", r), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
