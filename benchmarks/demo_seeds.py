"""The demo scenario closed-loop on every seed of hil_tests/test_hil_demo.py: teach the 20 m route, repeat it
twice from a 0.3 m / 10 degree start offset with motor and image noise, the second repeat with the camera
covered for 2 s mid-route; seeds 0 and 1 repeat under changed lighting (-40 %, +40 %) with two boxes of the
taught scene moved.

The test suite runs seeds 0 and 1 (both changed-lighting scenes, 75-95 s each on one core); this runs all
five (seeds 2-4 plain, with other noise), prints each repeat's lateral RMS and max error and
where it recovered from the start offset, and checks them against the test's bars (twice the worst
measured). The peer is the route itself: the figures are the repeated path's distance from the taught one.

Usage: python benchmarks/demo_seeds.py [--seeds 0,1,2,3,4]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "hil_tests"))
from test_hil_demo import MAX_BAR_M, RECOVERY_BAR_M, RMS_BAR_M, SCENARIOS, scenario_of  # noqa: E402

from vbnav.control.demo import run_demo  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default=",".join(str(s) for s in sorted(SCENARIOS)),
                    help=f"seeds of {sorted(SCENARIOS)} (default all)")
    args = ap.parse_args()
    try:
        seeds = [int(s) for s in args.seeds.split(",")]
    except ValueError:
        ap.error(f"--seeds: comma-separated integers expected, got {args.seeds!r}")
    unknown = [s for s in seeds if s not in SCENARIOS]
    if unknown:
        ap.error(f"--seeds: no scenario for {unknown}; known: {sorted(SCENARIOS)}")
    failed = 0
    rms, worst = [], []
    for seed in seeds:
        t = time.perf_counter()
        with tempfile.TemporaryDirectory(prefix=f"vbnav-demo-{seed}-") as out:
            m = run_demo(Path(out), scenario_of(seed))
        for r in m["repeats"]:
            ok = (r["completed"] and r["recovery_m"] is not None and r["recovery_m"] < RECOVERY_BAR_M
                  and r["rms_lateral_error_m"] <= RMS_BAR_M and r["max_lateral_error_m"] <= MAX_BAR_M)
            failed += not ok
            rms.append(r["rms_lateral_error_m"])
            worst.append(r["max_lateral_error_m"])
            rec = "never" if r["recovery_m"] is None else f"{r['recovery_m']:.2f} m"
            print(f"seed {seed} repeat {r['index']}: {'completed' if r['completed'] else 'NOT completed'}, lateral RMS "
                  f"{100 * r['rms_lateral_error_m']:.2f} cm, max {100 * r['max_lateral_error_m']:.2f} cm, recovered "
                  f"after {rec}  {'ok' if ok else 'OVER THE BARS'}", flush=True)
        print(f"seed {seed}: {time.perf_counter() - t:.0f} s", flush=True)
    print(f"{len(rms)} repeats: RMS {100 * min(rms):.2f}-{100 * max(rms):.2f} cm, max {100 * min(worst):.2f}-"
          f"{100 * max(worst):.2f} cm, means {100 * sum(rms) / len(rms):.2f} / {100 * sum(worst) / len(worst):.2f} cm (bars {100 * RMS_BAR_M:.1f} / {100 * MAX_BAR_M:.1f} cm, recovery "
          f"{RECOVERY_BAR_M} m); {failed} over the bars")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
