"""Camera interface: the one abstract base every camera driver implements.

A camera moves through the lifecycle connect -> read* -> disconnect and is a
context manager. ``read()`` never blocks longer than its timeout: the control
loop treats a stale frame as a safety event, not as a reason to wait.
"""
from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Optional

import numpy as np


@dataclass
class Frame:
    """One image from a camera.

    image: HxW (grey) or HxWx3 (BGR) uint8.
    stamp_ns: ``time.monotonic_ns()`` (or the simulated clock) at exposure.
    seq: increasing sequence number from the driver; a gap means dropped frames.
    disparity: optional HxW float32 disparity in pixels (stereo cameras), NaN
        where unknown; aligned with ``image``.
    right: optional right image of a stereo pair (rectified).
    meta: driver-specific extras (exposure, device id, ...).
    """

    image: np.ndarray
    stamp_ns: int
    seq: int
    disparity: Optional[np.ndarray] = None
    right: Optional[np.ndarray] = None
    meta: dict = field(default_factory=dict)

    def age_s(self, now_ns: int) -> float:
        return (now_ns - self.stamp_ns) * 1e-9


class CameraError(RuntimeError):
    """A camera could not be opened, gave the wrong format or went away."""


class Camera(abc.ABC):
    """Abstract camera. Subclasses set ``name`` and implement the four methods."""

    name: str = "camera"

    @abc.abstractmethod
    def connect(self) -> None:
        """Open the device and verify it delivers what the configuration asks."""

    @abc.abstractmethod
    def read(self, timeout_s: float = 0.0) -> Optional[Frame]:
        """Latest frame not returned before, or None if none arrived in time."""

    @abc.abstractmethod
    def disconnect(self) -> None:
        """Release the device. Safe to call twice."""

    @property
    @abc.abstractmethod
    def is_connected(self) -> bool: ...

    def __enter__(self) -> "Camera":
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.disconnect()
