"""USB (UVC) cameras through OpenCV's V4L2 backend, or a video file for replay.

After opening, the driver reads back what the device actually delivers (FOURCC,
size, frame rate) and refuses to start if it differs from the configuration:
intrinsics calibrated at 640x480 are wrong at 1280x720, and a camera that
silently falls back to YUYV at 5 fps makes the vision stale.

A grabbing thread keeps only the latest frame (a mailbox, not a queue: the
loop wants the newest image, never a backlog). If the device stops delivering
(unplugged) the thread releases it and tries to reopen it every
``reconnect_interval_s``, verifying the format again; ``read()`` meanwhile
returns None and the runtime's stale-frame check stops the robot.

A ``device`` that is a regular file is replayed at the file's frame rate (or
``replay_rate_hz``), with the same mailbox semantics.
"""
from __future__ import annotations

import glob
import os
import time
from typing import Any, Literal, Optional

import cv2
from pydantic import ConfigDict, Field, field_validator
from vbnav.drivers.plain_values import PlainValues

from vbnav.drivers.camera import CameraError, Frame, GrabbingCamera
from vbnav.drivers.errors import InputError


def fourcc_to_str(value: float) -> str:
    v = int(value)
    return "".join(chr((v >> (8 * i)) & 0xFF) for i in range(4)) if v > 0 else "????"


# Options only a live device reads, and only a video file.
DEVICE_ONLY = ("fourcc", "backend", "fps_tolerance", "stall_timeout_s", "reconnect_interval_s")
FILE_ONLY = ("replay_rate_hz", "loop")


class V4L2Camera(GrabbingCamera):
    name = "v4l2"

    class Options(PlainValues):
        model_config = ConfigDict(extra="forbid")
        device: str = Field("/dev/video0", description="V4L2 device (prefer /dev/v4l/by-id/...) or a video file")
        fourcc: str = Field("MJPG", description="pixel format to request, e.g. MJPG, YUYV, GREY")
        grey: bool = Field(True, description="deliver single-channel images (the vision code works in grey)")
        fps_tolerance: float = Field(0.5, ge=0, description="accepted |delivered - requested| frame rate")
        reconnect_interval_s: float = Field(1.0, gt=0, description="how often an unplugged camera is opened "
                                                                  "again, s")
        stall_timeout_s: float = Field(1.0, gt=0, description="no frame for this long counts as unplugged")
        replay_rate_hz: Optional[float] = Field(None, ge=0, description="files: frames per second "
                                                "(None: the file's own rate, 0: as fast as read)")
        loop: bool = Field(False, description="files: start again at the end")
        source: Literal["auto", "device", "file"] = Field(
            "auto", description="auto: a regular file is replayed, anything else is a live device")
        backend: Literal["v4l2", "any"] = Field(
            "v4l2", description="OpenCV capture backend for live devices (any: OpenCV chooses, e.g. for "
                                "GStreamer/FFmpeg URLs)")

        def plays_a_file(self) -> bool:
            """Whether ``device`` is a video file that is replayed (else a live device)."""
            return self.source == "file" or (self.source == "auto" and os.path.isfile(self.device))

        @field_validator("fourcc")
        @classmethod
        def _four_chars(cls, v: str) -> str:
            if len(v) != 4:
                raise ValueError(f"a FOURCC has 4 characters, got {v!r}")
            return v.upper()

    def __init__(self, cfg: Any = None, clock=None, *, options: Optional["V4L2Camera.Options"] = None,
                 width: Optional[int] = None, height: Optional[int] = None, fps: Optional[float] = None):
        super().__init__(cfg, clock, options=options, width=width, height=height, fps=fps)
        options = self.opt
        self.is_file = options.plays_a_file()
        # An option of the other kind of source is never read: refuse it rather than ignore it.
        values = options.model_dump()
        changed = {n for n in options.model_fields_set if values[n] != type(options).model_fields[n].default}
        idle = [n for n in (DEVICE_ONLY if self.is_file else FILE_ONLY) if n in changed]
        if idle:
            what, other = ("video file", "live device") if self.is_file else ("live device", "video file")
            raise InputError(f"camera.options {', '.join(f'{n}: {values[n]}' for n in idle)}: only a {other} "
                             f"reads it, and camera.options.device {options.device} is a {what} (remove it)")
        self.reconnects = 0
        self.finished = False
        self._cap = None
        self._read_began: Optional[float] = None   # when the grabbing thread's current read began (monotonic)
        self._monotonic = time.monotonic

    @property
    def error(self) -> Optional[str]:
        """What the driver knows of why no frame comes: a read that has not returned for longer than
        ``stall_timeout_s`` (a hung driver or device: the thread never gets to its own stall check), else
        what the thread said."""
        began = self._read_began
        waited = self._monotonic() - began if began is not None else 0.0
        if waited > self.opt.stall_timeout_s:
            return (f"camera {self.opt.device}: its read has not returned for {waited:.1f} s "
                    f"(a hung driver or device; camera.options.stall_timeout_s {self.opt.stall_timeout_s:g} s)")
        return self._error

    @error.setter
    def error(self, value: Optional[str]) -> None:
        self._error = value

    @staticmethod
    def find() -> list[str]:
        """Video devices present, stable names first."""
        return sorted(glob.glob("/dev/v4l/by-id/*")) + sorted(glob.glob("/dev/video*"))

    # -- lifecycle -----------------------------------------------------------------------
    def connect(self) -> None:
        self._cap = self._open()
        self._start_grabbing(f"v4l2:{self.opt.device}")

    def disconnect(self) -> None:
        self._stop.set()
        self._join_grabbing(2.0)
        self._release()
        self._connected = False

    # -- opening and verifying ------------------------------------------------------------------
    def _open(self):
        if self.is_file:
            return self._open_file()
        dev = self.opt.device
        if self.opt.backend == "v4l2" and not os.path.exists(dev):
            raise CameraError(f"camera {dev} not found; video devices present: {', '.join(self.find()) or 'none'}")
        if not os.path.exists(dev) and "://" not in dev:
            raise CameraError(f"camera {dev} not found")
        cap = cv2.VideoCapture(dev, cv2.CAP_V4L2 if self.opt.backend == "v4l2" else cv2.CAP_ANY)
        if not cap.isOpened():
            raise CameraError(f"camera {dev} cannot be opened through {self.opt.backend} "
                              f"(busy, or not a capture device?)")
        cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*self.opt.fourcc))
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
        cap.set(cv2.CAP_PROP_FPS, self.fps)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # the driver's queue: keep it short, we want the newest frame
        try:
            self._verify(cap)
        except CameraError:
            cap.release()
            raise
        return cap

    def _verify(self, cap) -> None:
        got_fourcc = fourcc_to_str(cap.get(cv2.CAP_PROP_FOURCC))
        got_w, got_h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        got_fps = float(cap.get(cv2.CAP_PROP_FPS))
        problems = []
        if got_fourcc != self.opt.fourcc:
            problems.append(f"format {got_fourcc} instead of {self.opt.fourcc}")
        if (got_w, got_h) != (self.width, self.height):
            problems.append(f"size {got_w}x{got_h} instead of {self.width}x{self.height}")
        if abs(got_fps - self.fps) > self.opt.fps_tolerance:
            problems.append(f"{got_fps:g} fps instead of {self.fps:g}")
        if problems:
            raise CameraError(f"camera {self.opt.device} delivers {', '.join(problems)}; change camera.width/"
                              f"height/rate_hz or camera.options.fourcc to a mode it supports "
                              f"(list them with: v4l2-ctl -d {self.opt.device} --list-formats-ext)")

    def _open_file(self):
        if not os.path.isfile(self.opt.device):
            what = "is a directory, not a video file" if os.path.isdir(self.opt.device) else "not found"
            raise CameraError(f"video file {self.opt.device} {what} (camera.options.device)")
        cap = cv2.VideoCapture(self.opt.device)
        if not cap.isOpened():
            raise CameraError(f"video file {self.opt.device} cannot be opened (unknown container or codec?)")
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        if (w, h) != (self.width, self.height):
            cap.release()
            raise CameraError(f"video file {self.opt.device} is {w}x{h}, the configuration expects "
                              f"{self.width}x{self.height} (camera.width/height must match its calibration)")
        file_fps = float(cap.get(cv2.CAP_PROP_FPS)) or self.fps
        rate = self.opt.replay_rate_hz if self.opt.replay_rate_hz is not None else file_fps
        self._replay_period = 1.0 / rate if rate > 0 else 0.0
        return cap

    def _release(self) -> None:
        if self._cap is not None:
            try:
                self._cap.release()
            except Exception:
                pass
        self._cap = None

    # -- grabbing thread ----------------------------------------------------------------------------
    def _grab_loop(self) -> None:
        next_due = time.monotonic()
        last_frame = time.monotonic()
        while not self._stop.is_set():
            if self._cap is None:
                if self._stop.wait(self.opt.reconnect_interval_s):
                    return
                self._try_reopen()
                last_frame = time.monotonic()
                continue
            if self.is_file and self._replay_period:
                delay = next_due - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    return
                next_due = max(next_due + self._replay_period, time.monotonic() - self._replay_period)
            self._read_began = self._monotonic()
            try:
                ok, img = self._cap.read()
            finally:
                self._read_began = None
            if not ok or img is None:
                if self.is_file:
                    if self.opt.loop:
                        self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
                        continue
                    self.finished = True
                    return
                if time.monotonic() - last_frame > self.opt.stall_timeout_s or not os.path.exists(self.opt.device):
                    self.error = f"camera {self.opt.device} stopped delivering frames (unplugged?); reconnecting"
                    self._release()
                # A read that fails at once (a device gone answers ENODEV) is not tried again in a busy loop
                # beside the control loop: no frame is due within half a period.
                elif self._stop.wait(0.5 / self.fps):
                    return
                continue
            last_frame = time.monotonic()
            stamp = self.clock.now_ns()
            if self.opt.grey and img.ndim == 3:
                img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            meta = {"device": self.opt.device, "reconnects": self.reconnects}
            self._frames.publish(lambda seq: Frame(img, stamp, seq, meta=meta))

    def _try_reopen(self) -> None:
        try:
            self._cap = self._open()
            self.reconnects += 1
            self.error = None
        except CameraError as exc:
            self.error = str(exc)
