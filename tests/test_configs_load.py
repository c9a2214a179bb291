"""Every robot configuration shipped in configs/ loads and validates, driver options included."""
from __future__ import annotations

from pathlib import Path

import pytest

from vbnav.control.config import CONFIG_DIR, ConfigError, load_config

CONFIGS = sorted(Path(CONFIG_DIR).glob("*.yaml"))


def test_there_are_sentry_configs():
    names = {p.name for p in CONFIGS}
    assert {"sentry-dynamixel.yaml", "sentry-odrive.yaml", "sentry-oak.yaml"} <= names


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_config_loads(path):
    cfg = load_config(path)
    assert cfg.source == str(path)


def test_sentry_driver_options_are_validated():
    from vbnav.control.config import validate_driver_options
    cfg = load_config(CONFIG_DIR / "sentry-dynamixel.yaml")
    opts = validate_driver_options(cfg)
    assert opts["drive"].model == "XL430-W250" and opts["drive"].bus_watchdog_s == 0.1
    assert opts["camera"].fourcc == "MJPG"
    assert cfg.drive.invert_right and not cfg.drive.invert_left


def test_unknown_driver_option_names_file_and_key(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text((CONFIG_DIR / "sentry-odrive.yaml").read_text().replace("checksum: true", "checksumm: true"))
    with pytest.raises(ConfigError, match=r"bad.yaml: drive.options.checksumm: unknown key"):
        load_config(bad)
