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
from typing import Any, Callable, Optional

import numpy as np

from vbnav.drivers.clock import MonotonicClock
from vbnav.drivers.errors import InputError


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


class CameraSizeError(CameraError, InputError):
    """Recorded images are not of the configured size: bad input (exit 2), not a device fault."""


class RecordedCameraError(CameraError, InputError):
    """A recording's own camera (its intrinsics file) is not the configured one: bad input (exit 2)."""


class Camera(abc.ABC):
    """Abstract camera. Subclasses set ``name`` and implement the four methods."""

    name: str = "camera"
    #: a recorded source (a replay, a video file) has delivered its last frame; a live camera never has
    finished: bool = False
    #: why the camera is not delivering, as far as the driver knows (unplugged and reconnecting, its grabbing
    #: thread failed), else None; the runtime's stale-camera hold names it
    error: Optional[str] = None

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


class GrabbingCamera(Camera):
    """A device camera whose frames a grabbing thread puts into a ``LatestFrame`` mailbox.

    Settings come from the ``camera`` config section (``options`` validated by
    the subclass's ``Options``; width, height and rate unless given). A
    subclass opens its device in ``connect()`` and then calls
    ``_start_grabbing``; ``disconnect()`` sets ``_stop``, releases what could
    block the thread and calls ``_join_grabbing``.
    """

    Options: type  # the pydantic model of ``camera.options``
    default_size = (640, 480)  # without a config

    def __init__(self, cfg: Any = None, clock=None, *, options: Any = None, width: Optional[int] = None,
                 height: Optional[int] = None, fps: Optional[float] = None):
        cam = getattr(cfg, "camera", None)
        if options is None:
            options = self.Options.model_validate(cam.options if cam is not None else {})
        self.opt = options
        self.clock = clock or MonotonicClock()
        self.width = width or (cam.width if cam is not None else self.default_size[0])
        self.height = height or (cam.height if cam is not None else self.default_size[1])
        self.fps = fps or (cam.rate_hz if cam is not None else 30.0)
        self.error: Optional[str] = None
        self._frames = LatestFrame()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._connected = False

    @classmethod
    def from_config(cls, cfg, clock, options=None):
        return cls(cfg, clock, options=options)

    @property
    def is_connected(self) -> bool:
        return self._connected

    def read(self, timeout_s: float = 0.0) -> Optional[Frame]:
        return self._frames.read(timeout_s)

    def latest_age_s(self) -> Optional[float]:
        """Age of the newest frame grabbed (returned or not), None before the first."""
        return self._frames.age_s(self.clock.now_ns())

    @abc.abstractmethod
    def _grab_loop(self) -> None:
        """The grabbing thread: ``self._frames.publish(...)`` each frame until ``_stop`` is set."""

    def _start_grabbing(self, thread_name: str) -> None:
        self._connected = True
        self._stop.clear()
        self._thread = threading.Thread(target=self._grab_guarded, name=thread_name, daemon=True)
        self._thread.start()

    def _grab_guarded(self) -> None:
        """The grabbing thread: a bug or an unexpected driver error ends it, and says so in ``error`` (the
        runtime's stale-camera hold names it) instead of ending it silently."""
        try:
            self._grab_loop()
        except Exception as exc:
            self.error = f"{type(self).__name__}: the grabbing thread failed: {type(exc).__name__}: {exc}"

    def _join_grabbing(self, timeout_s: float) -> None:
        """Wait for the grabbing thread to end (``_stop`` is set)."""
        if self._thread is not None:
            self._thread.join(timeout=timeout_s)
            self._thread = None
