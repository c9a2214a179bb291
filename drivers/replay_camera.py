"""Replay camera: recorded image sequences served like a live camera.

Layouts: a plain folder of images (sorted by name), KITTI odometry (left and,
when present, right images: ``Frame.right``) and TUM RGB-D (colour images,
depth in ``Frame.meta["depth"]`` in metres). Frames come at the recorded rate
(dataset stamps) or at ``rate_hz``, on the given clock: under the simulated
clock ``read(timeout)`` jumps to the next frame's time, so replays are exact
and fast. Like a live camera, ``read`` returns the latest frame that is due;
frames that fell due while nobody read are dropped (``meta["dropped"]`` counts
them), which is what the vision thread would see from a real device.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Literal, Optional

import numpy as np
from pydantic import ConfigDict, Field
from vbnav.drivers.plain_values import PlainValues

from vbnav.drivers.camera import Camera, CameraError, CameraSizeError, Frame, RecordedCameraError
from vbnav.drivers.clock import MonotonicClock
from vbnav.drivers.datasets import DatasetError, _images_in, _read_image, detect_layout, open_dataset
from vbnav.vision.camera_model import FisheyeCamera

FOLDER_DEFAULT_RATE_HZ = 10.0
# How far the configured intrinsics may be from a recording's own (as the OAK driver checks its device's):
# focal lengths relative, the principal point as a share of the image size.
FOCAL_TOL = 0.02
CENTRE_TOL = 0.02
DIST_RTOL, DIST_ATOL = 0.02, 1e-3   # distortion coefficients
BASELINE_TOL = 0.01                 # relative


class ReplayCamera(Camera):
    name = "replay"

    class Options(PlainValues):
        model_config = ConfigDict(extra="forbid")
        path: str = Field(..., description="folder of images, KITTI odometry folder or TUM RGB-D folder")
        layout: Literal["auto", "folder", "kitti", "tum"] = Field(
            "auto", description="auto: TUM if rgb.txt, KITTI if calib.txt or image_l/, else a folder of images")
        rate_hz: Optional[float] = Field(None, gt=0, description="fixed rate; None: the recorded times "
                                                                   "(folders without times: 10 Hz)")
        loop: bool = Field(False, description="start again after the last frame")
        camera_yaml: Optional[str] = Field(None, description="intrinsics of a TUM (or KITTI) recording instead of "
                                           "its camera.yaml (calib.txt); refused for a folder of images")
        grey: bool = Field(True, description="single-channel images (the vision code works in grey)")

    def __init__(self, options: "ReplayCamera.Options | dict", clock=None, size: Optional[tuple[int, int]] = None):
        """``size``: the (width, height) the configuration expects; images of another size are refused
        (the intrinsics are for one size, and a route records it)."""
        self.opt = options if isinstance(options, self.Options) else self.Options.model_validate(options)
        self.size = tuple(size) if size is not None else None
        self.clock = clock or MonotonicClock()
        self._connected = False
        self._files: list[Path] = []
        self._right: Optional[list[Path]] = None
        self._depth = None
        self._stamps = np.zeros(0)
        self._dataset = None
        self._next = 0  # index of the next frame not yet returned
        self._t0_ns = 0
        self._seq = 0
        self._lap = 0
        self.finished = False

    @classmethod
    def from_config(cls, cfg: Any, clock, options=None) -> "ReplayCamera":
        if options is None:
            options = cls.Options.model_validate(getattr(getattr(cfg, "camera", None), "options", {}) or {})
        cam = getattr(cfg, "camera", None)
        replay = cls(options, clock, (cam.width, cam.height) if cam is not None else None)
        # The stereo baseline the stages take (the obstacle stage's own first, as it does).
        baseline = getattr(getattr(cfg, "obstacles", None), "baseline", None)
        if baseline:
            named = ("obstacles.baseline", baseline)
        else:
            named = ("camera.calibration_file's stereo baseline", cam.stereo_baseline() if cam is not None else None)
        # Recordings of another size are bad input: refused now, before a run starts (and a teach creates
        # its route). Any other problem (a missing folder) is reported when the run connects, as before.
        try:
            replay.connect()
        except CameraSizeError:
            raise
        except CameraError:
            pass
        else:
            replay.check_camera(cam, named)
        finally:
            replay.disconnect()
        return replay

    def check_camera(self, cam: Any, baseline: tuple[str, Optional[float]] = ("", None)) -> None:
        """A recording that carries its camera (TUM ``camera.yaml`` or ``camera_yaml``, KITTI ``calib.txt``) is
        replayed only to stages built for that camera: the configured ``cam`` (fx, fy, cx, cy, width, height,
        model, distortion) must agree with it (focal lengths 2 %, principal point 2 % of the image, distortion
        coefficients 2 % + 0.001), and so must the configured stereo ``baseline`` (its field name, metres;
        None: not configured) with the recording's (1 %), else RecordedCameraError names both. A plain folder
        of images carries none."""
        ds = self._dataset
        if ds is None or cam is None:
            return
        rec = ds.camera
        bad = [f"camera.{name} {mine:g} vs the recording's {theirs:g}"
               for name, mine, theirs, tol in (("fx", cam.fx, rec.fx, FOCAL_TOL * rec.fx),
                                               ("fy", cam.fy, rec.fy, FOCAL_TOL * rec.fy),
                                               ("cx", cam.cx, rec.cx, CENTRE_TOL * cam.width),
                                               ("cy", cam.cy, rec.cy, CENTRE_TOL * cam.height))
               if abs(mine - theirs) > tol]
        rec_model = "fisheye" if isinstance(rec, FisheyeCamera) else "pinhole"
        if cam.model != rec_model:
            bad.append(f"camera.model {cam.model} vs the recording's {rec_model}")
        mine_d = [float(d) for d in cam.distortion]
        theirs_d = [float(d) for d in rec.dist] if any(rec.dist) else []
        n = max(len(mine_d), len(theirs_d))
        if not np.allclose(mine_d + [0.0] * (n - len(mine_d)), theirs_d + [0.0] * (n - len(theirs_d)),
                           rtol=DIST_RTOL, atol=DIST_ATOL):
            bad.append(f"camera.distortion {mine_d} vs the recording's {theirs_d}")
        name, b = baseline
        if b and ds.stereo_baseline and abs(b - ds.stereo_baseline) > BASELINE_TOL * ds.stereo_baseline:
            bad.append(f"{name} {b:g} m vs the recording's {ds.stereo_baseline:g} m")
        if bad:
            source = self.opt.camera_yaml or ds.root / ("calib.txt" if ds.layout == "kitti" else "camera.yaml")
            raise RecordedCameraError(
                f"replay camera: {source}: the recording's camera is not the configured one ({'; '.join(bad)}); "
                f"set camera.fx/fy/cx/cy, model and distortion (or camera.calibration_file) to the recording's "
                f"camera")

    @property
    def is_connected(self) -> bool:
        return self._connected

    def __len__(self) -> int:
        return len(self._files)

    def connect(self) -> None:
        root = Path(self.opt.path)
        if not root.exists():
            raise CameraError(f"replay camera: {root} does not exist")
        layout = self.opt.layout
        if layout == "auto":
            layout = detect_layout(root, fallback="folder") if root.is_dir() else "folder"
        try:
            if layout == "folder":
                if not root.is_dir():
                    raise DatasetError(f"{root}: not a folder of images")
                if self.opt.camera_yaml is not None:
                    raise DatasetError(f"camera_yaml {self.opt.camera_yaml}: {root} is a folder of images, whose "
                                       f"intrinsics are camera.fx, fy, cx, cy (camera_yaml is read for a TUM or "
                                       f"KITTI recording): remove camera_yaml")
                self._files = _images_in(root)
                if not self._files:
                    raise DatasetError(f"{root}: no images (.png/.jpg/.pgm/.bmp) found")
                self._stamps = np.arange(len(self._files)) / FOLDER_DEFAULT_RATE_HZ
            else:
                ds = open_dataset(root, self.opt.camera_yaml, layout)
                self._dataset = ds
                self._files, self._right, self._depth, self._stamps = ds.left, ds.right, ds.depth, ds.stamps
            self._check_size(_read_image(self._files[0], self.opt.grey), self._files[0])  # fail now, not in the loop
        except DatasetError as exc:
            raise CameraError(f"replay camera: {exc}") from exc
        if self.opt.rate_hz is not None:
            self._stamps = np.arange(len(self._files)) / self.opt.rate_hz
        self._period_s = float(np.median(np.diff(self._stamps))) if len(self._stamps) > 1 else 0.1
        self._t0_ns = self.clock.now_ns()
        self._next = 0
        self._lap = 0
        self.finished = False
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False

    def _check_size(self, image: np.ndarray, path: Path) -> np.ndarray:
        if self.size is not None and (image.shape[1], image.shape[0]) != self.size:
            raise CameraSizeError(f"replay camera: {path} is {image.shape[1]}x{image.shape[0]}, the configuration "
                                  f"expects {self.size[0]}x{self.size[1]} (camera.width/height and the calibration "
                                  f"must be those of the recorded images)")
        return image

    @property
    def dataset(self):
        """The opened KITTI/TUM dataset (intrinsics, ground truth), None for a plain folder."""
        return self._dataset

    def _due_ns(self, k: int, lap: int) -> int:
        span = (self._stamps[-1] - self._stamps[0]) + self._period_s
        return self._t0_ns + int(round(((self._stamps[k] - self._stamps[0]) + lap * span) * 1e9))

    def _latest_due(self, now: int) -> Optional[tuple[int, int]]:
        """(index, lap) of the latest frame due at ``now`` at or after the next unread one."""
        k, lap = self._next, self._lap
        if k >= len(self._files):
            if not self.opt.loop:
                return None
            k, lap = 0, lap + 1
        if self._due_ns(k, lap) > now:
            return None
        while True:
            k2, lap2 = k + 1, lap
            if k2 >= len(self._files):
                if not self.opt.loop:
                    break
                k2, lap2 = 0, lap + 1
            if self._due_ns(k2, lap2) > now:
                break
            k, lap = k2, lap2
        return k, lap

    def read(self, timeout_s: float = 0.0) -> Optional[Frame]:
        if not self._connected:
            raise CameraError("replay camera: read() before connect()")
        now = self.clock.now_ns()
        hit = self._latest_due(now)
        if hit is None and timeout_s > 0 and not self.finished:
            k, lap = (self._next, self._lap) if self._next < len(self._files) else (0, self._lap + 1)
            if self._next < len(self._files) or self.opt.loop:
                self.clock.sleep_until(min(self._due_ns(k, lap), now + int(timeout_s * 1e9)))
                hit = self._latest_due(self.clock.now_ns())
        if hit is None:
            if self._next >= len(self._files) and not self.opt.loop:
                self.finished = True
            return None
        k, lap = hit
        skipped = (k - self._next) if lap == self._lap else (len(self._files) - self._next + k)
        self._next, self._lap = k + 1, lap
        self._seq += 1
        try:
            ds = self._dataset   # a recording's own images are of its calibration's size, both sides
            image = self._check_size(ds.image(k, self.opt.grey) if ds is not None
                                     else _read_image(self._files[k], self.opt.grey), self._files[k])
            right = self._check_size(ds.right_image(k), self._right[k]) if self._right is not None else None
            meta = {"index": k, "lap": lap, "path": str(self._files[k]), "dropped": int(skipped),
                    "dataset_stamp_s": float(self._stamps[k])}
            if self._depth is not None and self._dataset is not None:
                meta["depth"] = self._dataset.depth_image(k)
        except DatasetError as exc:
            raise CameraError(f"replay camera: {exc}") from exc
        return Frame(image, self._due_ns(k, lap), self._seq, right=right, meta=meta)
