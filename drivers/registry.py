"""Driver registry: configuration picks a class by name.

Each entry is "module:Class", imported only when chosen, so a robot without
depthai or a serial port never imports them. A driver module whose SDK is an
optional extra raises ImportError naming the extra (``pip install 'vbnav[oak]'``)
and ``load`` passes that message on. Every driver class carries a pydantic model
``Options`` that validates its ``options:`` block in the YAML.
"""
from __future__ import annotations

import importlib

CAMERAS: dict[str, str] = {
    "sim": "vbnav.drivers.sim.camera:SimCamera",
    "v4l2": "vbnav.drivers.v4l2_camera:V4L2Camera",
    "oak": "vbnav.drivers.oak_camera:OakCamera",
    "replay": "vbnav.drivers.replay_camera:ReplayCamera",
}

DRIVES: dict[str, str] = {
    "sim": "vbnav.drivers.sim.base:SimDiffDrive",
    "dynamixel": "vbnav.drivers.dynamixel:DynamixelDrive",
    "odrive": "vbnav.drivers.odrive:ODriveDrive",
}


class DriverNotAvailable(ImportError):
    pass


def load(table: dict[str, str], name: str):
    """The driver class registered under ``name`` in ``table``."""
    if name not in table:
        raise KeyError(name)
    module, _, cls = table[name].partition(":")
    try:
        return getattr(importlib.import_module(module), cls)
    except (ImportError, AttributeError) as exc:  # pragma: no cover - depends on install
        raise DriverNotAvailable(f"driver '{name}' ({table[name]}) cannot be loaded: {exc}") from exc
