"""Driver registry: configuration picks a class by name.

Each entry is "module:Class", imported only when chosen, so a robot without
depthai or a serial port never imports them. A driver module whose SDK is an
optional extra raises ImportError naming the extra (``pip install 'vbnav[oak]'``)
and ``load`` passes that message on. Every driver class carries a pydantic model
``Options`` that validates its ``options:`` block in the YAML.
"""
from __future__ import annotations

import importlib
import importlib.util
from typing import Optional

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


# Driver modules that need a vendor SDK, which an installation may lack: module -> the SDK's import name.
SDKS: dict[str, str] = {
    "vbnav.drivers.oak_camera": "depthai",
}


class DriverNotAvailable(ImportError):
    pass


def missing_sdk(table: dict[str, str], name: str) -> Optional[str]:
    """The package driver ``name`` needs that is not installed here, or None; nothing is imported."""
    sdk = SDKS.get(table[name].partition(":")[0])
    return sdk if sdk is not None and importlib.util.find_spec(sdk) is None else None


def load(table: dict[str, str], name: str):
    """The driver class registered under ``name`` in ``table``."""
    if name not in table:
        raise KeyError(name)
    module, _, cls = table[name].partition(":")
    try:
        return getattr(importlib.import_module(module), cls)
    except (ImportError, AttributeError) as exc:  # pragma: no cover - depends on install
        raise DriverNotAvailable(f"driver '{name}' ({table[name]}) cannot be loaded: {exc}") from exc
