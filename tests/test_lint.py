"""The lint every change is checked with before it is committed: unused imports, redefinitions, undefined names
and unused variables (ruff's F401, F811, F821, F841) in every source folder. ruff comes with the ``[test]`` extra."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

from conftest import REPO, unavailable

RULES = "F401,F811,F821,F841"
FOLDERS = ["control", "drivers", "vision", "tests", "hil_tests", "benchmarks"]


def _ruff() -> str:
    """The ruff beside this interpreter (the venv's), else one on PATH."""
    here = Path(sys.executable).parent / "ruff"
    found = str(here) if here.is_file() else shutil.which("ruff")
    if found is None:
        unavailable("ruff is not installed: pip install -e '.[test]'")
    return found


def test_no_unused_or_undefined_names():
    r = subprocess.run([_ruff(), "check", "--no-cache", "--select", RULES, *FOLDERS],
                       cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, f"ruff check --select {RULES} found:\n{r.stdout}{r.stderr}"
