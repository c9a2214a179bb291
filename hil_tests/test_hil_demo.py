"""The demo scenario closed-loop: real runtime, simulated base and camera, two seeds of five.

Each seed teaches the 20 m route and repeats it twice from a 0.3 m / 10 degree start offset with motor and
image noise; the second repeat has the camera covered for 2 s mid-route. The two seeds here repeat under
changed lighting (-40 %, +40 %) with two boxes of the taught scene moved. Seeds 2-4 (plain, other noise) run
in ``benchmarks/demo_seeds.py`` with the same bars: 75-95 s each on one core, five made this file the suite's
longest by far, and three (2026-12-03) left the suite at 890 s of its 900 on a slow machine.
"""
import json

import pytest

from vbnav.control.demo import Scenario, run_demo

# Measured on 2026-11-30 over the 10 repeats: RMS 0.38-0.86 cm, max 0.96-2.95 cm, recovered within
# 0.60-1.25 m of the start; the bars are twice the worst.
RMS_BAR_M = 0.018
MAX_BAR_M = 0.06
RECOVERY_BAR_M = 2.5

SCENARIOS = {
    0: dict(lighting={0: 0.6}, moved_boxes={0: {"box_a": (-1.0, 0.0), "box_b": (1.0, 0.3)}}),
    1: dict(lighting={0: 1.4}, moved_boxes={0: {"box_a": (-1.6, 0.6), "box_e": (-0.5, 3.5)}}),
    2: {},
    3: {},
    4: {},
}


# Both changed-lighting scenes; all five, the worst plain one among them (seed 3, 2026-12-03: RMS 1.18 cm,
# max 4.74 cm): benchmarks/demo_seeds.py.
TEST_SEEDS = (0, 1)


def scenario_of(seed: int) -> Scenario:
    return Scenario(seed=seed, repeats=2, occlusion=(1, 25.0, 2.0), **SCENARIOS[seed])


@pytest.mark.slow
@pytest.mark.parametrize("seed", TEST_SEEDS)
def test_demo_seed(seed, tmp_path):
    m = run_demo(tmp_path, scenario_of(seed))
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["completed"] == m["completed"]
    assert (tmp_path / "paths.png").stat().st_size > 10_000
    assert m["keyframes"] >= 31          # measured 62 on 2026-11-30, bar 1/2
    assert m["route_length_m"] >= 20.0
    for r in m["repeats"]:
        where = f"seed {seed} repeat {r['index']}"
        assert r["completed"], f"{where}: {r['message']}"
        recovered = "never" if r["recovery_m"] is None else f"after {r['recovery_m']:.2f} m"
        print(f"{where}: lateral RMS {100 * r['rms_lateral_error_m']:.2f} cm, max "
              f"{100 * r['max_lateral_error_m']:.2f} cm, recovered {recovered}")   # the README row's figures
        # Recovered from the start offset: the error fell under 5 cm and stayed there.
        assert r["recovery_m"] is not None and r["recovery_m"] < RECOVERY_BAR_M, where
        assert r["rms_lateral_error_m"] <= RMS_BAR_M, (where, r["rms_lateral_error_m"])
        assert r["max_lateral_error_m"] <= MAX_BAR_M, (where, r["max_lateral_error_m"])
