"""Camera interface: the one abstract base every camera driver implements.

A camera moves through the lifecycle connect -> read* -> disconnect and is a
context manager. ``read()`` never blocks longer than its timeout: the control
loop treats a stale frame as a safety event, not as a reason to wait.
"""
from __future__ import annotations

import abc
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

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


class LatestFrame:
    """A one-slot mailbox between a grabbing thread and the loop: the newest frame, each handed out once.

    Not a queue: the loop wants the newest image, never a backlog. ``publish``
    numbers frames with an increasing ``seq`` so a gap shows dropped frames.
    """

    def __init__(self):
        self._latest: Optional[Frame] = None
        self._returned_seq = 0
        self._seq = 0
        self._cond = threading.Condition()

    def publish(self, make_frame: Callable[[int], Frame]) -> None:
        """Store the frame ``make_frame(seq)`` builds with the next sequence number and wake readers."""
        with self._cond:
            self._seq += 1
            self._latest = make_frame(self._seq)
            self._cond.notify_all()

    def read(self, timeout_s: float = 0.0) -> Optional[Frame]:
        """The newest frame not returned before, waiting at most ``timeout_s``; None if none came."""
        end = time.monotonic() + timeout_s
        with self._cond:
            while self._latest is None or self._latest.seq <= self._returned_seq:
                remaining = end - time.monotonic()
                if remaining <= 0:
                    return None
                self._cond.wait(remaining)
            self._returned_seq = self._latest.seq
            return self._latest

    def age_s(self, now_ns: int) -> Optional[float]:
        """Age of the newest frame (returned or not), None before the first."""
        f = self._latest
        return None if f is None else f.age_s(now_ns)


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
