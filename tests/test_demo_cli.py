"""`vbnav demo -c FILE` takes the file's seed and says what of it the demo cannot use."""
from __future__ import annotations

import pytest

from vbnav.control import demo
from vbnav.control.cli import main


@pytest.fixture
def ran(monkeypatch):
    """The demo's inputs, without its two minutes of simulation."""
    seen = {}

    def fake(out, scenario, cfg, **kw):
        seen.update(scenario=scenario, cfg=cfg)
        return {"completed": True, "rms_lateral_error_m": 0.0, "max_lateral_error_m": 0.0}
    monkeypatch.setattr(demo, "run_demo", fake)
    return seen


def test_the_seed_comes_from_the_config_unless_given(tmp_path, ran, capsys):
    cfg = tmp_path / "sim7.yaml"
    cfg.write_text("sim:\n  seed: 7\n")
    assert main(["demo", "-c", str(cfg), "--out", str(tmp_path / "d")]) == 0
    assert ran["scenario"].seed == 7
    assert "note" not in capsys.readouterr().err       # its start pose is the route's: nothing to say
    assert main(["demo", "-c", str(cfg), "--seed", "2", "--out", str(tmp_path / "d")]) == 0
    assert ran["scenario"].seed == 2
    assert main(["demo", "--out", str(tmp_path / "d")]) == 0
    assert ran["scenario"].seed == 0


def test_a_start_pose_the_demo_cannot_use_is_named(tmp_path, ran, capsys):
    cfg = tmp_path / "elsewhere.yaml"
    cfg.write_text("sim:\n  start_pose: [1.0, 2.0, 90.0]\n")
    assert main(["demo", "-c", str(cfg), "--out", str(tmp_path / "d")]) == 0
    err = capsys.readouterr().err
    assert f"{cfg}: sim.start_pose [1.0, 2.0, 90.0] is not used" in err and "(-3.50, 0.00, 0.0 deg)" in err


def test_metrics_json_is_strict_json_with_null_for_what_was_not_measured(tmp_path):
    """A repeat that never moved has no lateral error: it was written as NaN, which is not JSON (jq, browsers
    and most JSON readers refuse the whole file). Non-finite numbers are written as null."""
    import json as _json

    from vbnav.control.demo import write_json_atomic

    def refuse(name):
        raise ValueError(f"not JSON: {name}")

    path = tmp_path / "out" / "metrics.json"
    write_json_atomic(path, {"rms_lateral_error_m": float("nan"), "repeats": [{"max": float("inf"), "ok": 0.5}]})
    data = _json.loads(path.read_text(), parse_constant=refuse)
    assert data == {"rms_lateral_error_m": None, "repeats": [{"max": None, "ok": 0.5}]}
