"""Shared test fixtures: the real-data folder and seeded generators."""
from __future__ import annotations

import importlib
import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent


def data_dir() -> Path:
    """The real-data folder: $VBNAV_DATA, else ../shared/data beside the repository."""
    return Path(os.environ.get("VBNAV_DATA", REPO.parent / "shared" / "data")).resolve()


def unavailable(msg: str) -> None:
    """A test's prerequisite is missing: a failure under CI (which installs everything), a skip elsewhere."""
    if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
        pytest.fail(msg, pytrace=False)
    pytest.skip(msg, allow_module_level=True)


def import_extra(module: str, extra: str):
    """The module of an optional extra (``vbnav[extra]``), or ``unavailable`` naming the install command."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        unavailable(f"{module} is not importable ({exc}): pip install -e '.[{extra}]'")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Real camera sequences. Missing in CI is a failure; elsewhere a skip."""
    d = data_dir()
    if not d.is_dir():
        unavailable(f"real-data folder {d} is missing (set VBNAV_DATA or put shared/data beside the repository)")
    return d


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)



class DiskLog(list):
    """Renames and folder fsyncs in order: ("rename", dst) and ("fsync folder", path)."""

    def durable(self, dst) -> bool:
        """``dst`` was renamed into place and its folder fsynced after that (the rename survives a power cut)."""
        key = ("rename", str(dst))
        return key in self and ("fsync folder", str(Path(dst).parent)) in self[self.index(key):]


@pytest.fixture
def disk_log(monkeypatch) -> DiskLog:
    """The renames (os.replace, os.rename) and folder fsyncs done while the test runs."""
    events = DiskLog()
    real_replace, real_rename, real_fsync = os.replace, os.rename, os.fsync

    def renamer(real):
        def rename(src, dst, *a, **kw):
            real(src, dst, *a, **kw)
            events.append(("rename", str(dst)))
        return rename

    def fsync(fd):
        real_fsync(fd)
        if os.path.isdir(f"/proc/self/fd/{fd}"):
            events.append(("fsync folder", os.readlink(f"/proc/self/fd/{fd}")))

    monkeypatch.setattr(os, "replace", renamer(real_replace))
    monkeypatch.setattr(os, "rename", renamer(real_rename))
    monkeypatch.setattr(os, "fsync", fsync)
    return events
