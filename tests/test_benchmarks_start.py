"""Every benchmark starts: ``--help`` imports it and everything it uses, and prints its usage.

The benchmarks are not run by the suite (they are the slow speed and accuracy runs), so a change that renames
or removes something one of them imports would otherwise go unnoticed until somebody re-measures a README row.
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = sorted((Path(__file__).resolve().parents[1] / "benchmarks").glob("*.py"))
HELPERS = {"vo_peer"}   # imported by vo_real.py and vo_kitti.py, not a benchmark of its own


@pytest.mark.parametrize("path", [p for p in BENCHMARKS if p.stem not in HELPERS], ids=lambda p: p.stem)
def test_benchmark_starts_and_prints_its_usage(path: Path):
    r = subprocess.run([sys.executable, str(path), "--help"], capture_output=True, text=True, timeout=120,
                       cwd=path.parents[1])
    assert r.returncode == 0, f"{path.name} --help: exit {r.returncode}\n{r.stderr[-2000:]}"
    assert "usage:" in r.stdout, f"{path.name} --help printed no usage:\n{r.stdout[:500]}"


def test_the_peer_module_imports():
    r = subprocess.run([sys.executable, "-c", "import vo_peer"], capture_output=True, text=True, timeout=120,
                       cwd=BENCHMARKS[0].parent)
    assert r.returncode == 0, r.stderr[-2000:]
