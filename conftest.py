"""Shared test fixtures: the real-data folder and seeded generators."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent


def data_dir() -> Path:
    """The real-data folder: $VBNAV_DATA, else ../shared/data beside the repository."""
    return Path(os.environ.get("VBNAV_DATA", REPO.parent / "shared" / "data")).resolve()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Real camera sequences. Missing in CI is a failure; elsewhere a skip."""
    d = data_dir()
    if not d.is_dir():
        msg = f"real-data folder {d} is missing (set VBNAV_DATA or put shared/data beside the repository)"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(msg)
        pytest.skip(msg)
    return d


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)
