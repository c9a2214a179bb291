"""Shared pieces for runtime tests: a drive that records what it was told, a test camera."""
from __future__ import annotations

import numpy as np

from vbnav.control.config import Config
from vbnav.control.runtime.pipeline import VisionPipeline
from vbnav.control.runtime.runtime import Runtime
from vbnav.drivers.camera import Camera, Frame
from vbnav.drivers.clock import SimClock
from vbnav.drivers.sim.base import BaseParams, SimDiffDrive

PERIOD_NS = 10_000_000  # 100 Hz


class RecordingDrive(SimDiffDrive):
    """The simulated drive, logging every command it receives: (t_ns, left, right, powered)."""

    def __init__(self, clock, **kw):
        super().__init__(BaseParams(slip_std=0.0), clock, **kw)
        self.log: list[tuple[int, float, float, bool]] = []

    def write(self, left, right):
        super().write(left, right)
        self.log.append((self.clock.now_ns(), left, right, self.physics.powered))

    def disable(self):
        super().disable()
        self.log.append((self.clock.now_ns(), 0.0, 0.0, False))

    def last_motion_ns(self) -> int:
        """Time of the last command that could move a wheel."""
        moving = [t for t, l, r, p in self.log if p and (abs(l) > 1e-12 or abs(r) > 1e-12)]
        return moving[-1] if moving else -1

    def stopped_since(self, t_ns: int) -> bool:
        """Every command from t_ns on is zero or unpowered, and the last one leaves it unpowered or zero."""
        after = [(l, r, p) for t, l, r, p in self.log if t >= t_ns]
        return all((not p) or (l == 0 and r == 0) for l, r, p in after)


class TickCamera(Camera):
    """A camera on a clock that delivers a small textured frame at ``rate_hz`` until ``stop_at_ns``.

    Like a live sensor, one pixel differs from frame to frame (read noise); from ``freeze_at_ns`` until
    ``thaw_at_ns`` the frames keep coming with the image they froze on (a frozen camera)."""

    name = "tick"

    def __init__(self, clock, rate_hz=15.0, stop_at_ns=None, resume_at_ns=None, freeze_at_ns=None,
                 thaw_at_ns=None):
        self.clock = clock
        self.period = int(1e9 / rate_hz)
        self.stop_at_ns = stop_at_ns
        self.resume_at_ns = resume_at_ns
        self.freeze_at_ns = freeze_at_ns
        self.thaw_at_ns = thaw_at_ns
        self._next = None
        self._seq = 0
        self._connected = False
        self._img = (np.random.default_rng(0).random((48, 64)) * 255).astype(np.uint8)

    def connect(self):
        self._connected = True
        self._next = self.clock.now_ns()

    def disconnect(self):
        self._connected = False

    @property
    def is_connected(self):
        return self._connected

    def read(self, timeout_s=0.0):
        now = self.clock.now_ns()
        if now < self._next:
            return None
        due = self._next
        self._next += self.period * max(1, (now - due) // self.period + 1)
        silent = self.stop_at_ns is not None and due >= self.stop_at_ns and (
            self.resume_at_ns is None or due < self.resume_at_ns)
        if silent:
            return None
        self._seq += 1
        frozen = self.freeze_at_ns is not None and due >= self.freeze_at_ns and (
            self.thaw_at_ns is None or due < self.thaw_at_ns)
        if not frozen:
            self._img = self._img.copy()
            self._img[0, 0] = self._seq % 256
        return Frame(self._img, due, self._seq)


def make_runtime(controller, stages=(), camera=True, cfg=None, cam_kw=None, drive_kw=None):
    cfg = cfg or Config()
    clock = SimClock()
    drive = RecordingDrive(clock, **(drive_kw or {}))
    pipeline = None
    if camera:
        cam = TickCamera(clock, **(cam_kw or {}))
        pipeline = VisionPipeline(cam, list(stages), clock, inline=True)
    return Runtime(cfg, drive, controller, clock, pipeline), drive, clock
