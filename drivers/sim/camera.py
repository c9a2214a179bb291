"""The simulated camera: renders the simulated World from the robot's true pose.

``SimCamera`` implements the ``Camera`` interface on a clock (``SimClock`` in
tests and the demo, ``MonotonicClock`` in real-time runs). Frames are due at
multiples of 1/rate_hz on that clock; ``read()`` returns the newest due frame
not yet returned (older due frames are dropped, as a real driver's
latest-frame mailbox would), stamped with its due time.

The pose of a frame is the robot pose AT ITS STAMP: ``read()`` samples
``pose_fn()`` on every call and interpolates between the previous call and the
current one, so a 100 Hz loop reading a 15 Hz camera gets images that match
the odometry at the stamp (no hidden 0-10 ms latency).

Image effects (all deterministic for a seed and frame number): global gain
(lighting change), Gaussian pixel noise, occlusion (a covered lens gives a
uniform black frame). With ``stereo_baseline`` the frame also carries the
right image of a rectified pair (same intrinsics, camera shifted by the
baseline along its x axis) and the TRUE disparity of the left image,
d = fx * B / z (float32, NaN where no surface).
"""
from __future__ import annotations

import functools
import math
from typing import Callable, Optional

import cv2
import numpy as np
from pydantic import ConfigDict, Field
from vbnav.drivers.plain_values import PlainValues

from vbnav.drivers.camera import Camera, CameraError, Frame
from vbnav.drivers.errors import InputError
from vbnav.drivers.sim.render import Renderer
from vbnav.drivers.sim.world import World
from vbnav.vision.camera_model import PinholeCamera
from vbnav.vision.geometry import CameraMount, Pose2, camera_pose, wrap_angle


NOISE_BANK_SIZE = 4
NOISE_MARGIN = 64


@functools.lru_cache(maxsize=8)
def _noise_bank(seed: int, shape: tuple) -> tuple:
    """A few unit-variance float32 noise images, larger than a frame by NOISE_MARGIN.

    A frame's noise is a window into one of them at a random offset: drawing
    300k Gaussian numbers per frame costs ~3 ms, a window costs nothing, and
    with 4 x 64 x 64 windows no two consecutive frames share their noise.
    """
    rng = np.random.default_rng([int(seed), 0x401CE])
    big = (shape[0] + NOISE_MARGIN, shape[1] + NOISE_MARGIN) + tuple(shape[2:])
    return tuple(rng.standard_normal(big, dtype=np.float32) for _ in range(NOISE_BANK_SIZE))


def apply_effects(image: np.ndarray, gain: float, noise_std: float, rng: Optional[np.random.Generator],
                  noise_seed: int = 0) -> np.ndarray:
    """saturate(round(gain * image + noise_std * N(0, 1))) as uint8; rng picks the noise window."""
    if noise_std <= 0 or rng is None:
        if gain == 1.0:
            return image
        return cv2.convertScaleAbs(image, alpha=float(gain))     # gain > 0: abs is a no-op
    bank = _noise_bank(int(noise_seed), image.shape)
    k, dy, dx = rng.integers(0, NOISE_BANK_SIZE), rng.integers(0, NOISE_MARGIN), rng.integers(0, NOISE_MARGIN)
    noise = bank[k][dy:dy + image.shape[0], dx:dx + image.shape[1]]
    return cv2.addWeighted(image, float(gain), noise, float(noise_std), 0.0, dtype=cv2.CV_8U)


def right_camera_pose(R_wc: np.ndarray, t_wc: np.ndarray, baseline: float) -> tuple[np.ndarray, np.ndarray]:
    """World-from-camera pose of the right camera of a rectified pair (shifted +B along camera x)."""
    return R_wc, np.asarray(t_wc, float) + R_wc[:, 0] * float(baseline)


def interpolate_pose(p0: Pose2, p1: Pose2, a: float) -> Pose2:
    """Pose at fraction a in [0, 1] from p0 to p1 (linear in position and in wrapped heading)."""
    return Pose2(p0.x + a * (p1.x - p0.x), p0.z + a * (p1.z - p0.z),
                 wrap_angle(p0.theta + a * wrap_angle(p1.theta - p0.theta)))


class SimCamera(Camera):
    """A camera looking at a simulated World from the pose given by ``pose_fn``.

    world: the World to render. camera_model: PinholeCamera (OpenCV distortion is
    rendered by remapping an ideal pinhole image; stereo needs none).
    mount: where the camera sits on the robot. pose_fn: returns the TRUE robot
    Pose2 now (the simulated base's ``true_pose``). clock: ``now_ns()`` and
    ``sleep_until(ns)``. rate_hz: frame rate. noise_std: grey levels.
    seed: noise seed. stereo_baseline: metres, or None for mono. gain: global
    brightness factor. color: deliver BGR images (right image too).

    Settable while running: ``gain``, ``occluded``, ``noise_std``.
    """

    name = "sim"

    class Options(PlainValues):
        """The ``camera.options`` block of a configuration for driver ``sim``."""

        model_config = ConfigDict(extra="forbid")
        stereo_baseline: Optional[float] = Field(None, gt=0, le=2.0,
                                                 description="m; set for a stereo pair with true disparity")
        color: bool = Field(False, description="deliver BGR instead of grey images")
        gain: float = Field(1.0, gt=0, le=10.0, description="global brightness factor")

    def __init__(self, world: World, camera_model: PinholeCamera, mount: CameraMount,
                 pose_fn: Callable[[], Pose2], clock, rate_hz: float, noise_std: float = 2.0, seed: int = 0,
                 stereo_baseline: Optional[float] = None, gain: float = 1.0, color: bool = False):
        if rate_hz <= 0:
            raise ValueError(f"SimCamera rate_hz must be > 0, got {rate_hz}")
        if stereo_baseline is not None and stereo_baseline <= 0:
            raise ValueError(f"SimCamera stereo_baseline must be > 0 m or None, got {stereo_baseline}")
        if stereo_baseline is not None and camera_model.has_distortion:
            raise ValueError("SimCamera stereo pairs are rectified: give a camera model without distortion "
                             f"(got dist={camera_model.dist})")
        self.world = world
        self.model = camera_model
        self.mount = mount
        self.pose_fn = pose_fn
        self.clock = clock
        self.rate_hz = float(rate_hz)
        self.noise_std = float(noise_std)
        self.seed = int(seed)
        self.stereo_baseline = stereo_baseline
        self.gain = float(gain)
        self.color = bool(color)
        self.occluded = False
        self.renderer = Renderer(world, camera_model)   # validates the model (pinhole)
        self._connected = False
        self._next_index = 0
        self._seq = 0
        self._last_sample: Optional[tuple[int, Pose2]] = None

    @classmethod
    def from_config(cls, cfg, clock, options=None, pose_fn: Optional[Callable[[], Pose2]] = None,
                    world: Optional[World] = None, seed: Optional[int] = None) -> "SimCamera":
        """Build from a validated vbnav Config (duck-typed: drivers do not import control).

        options: a ``SimCamera.Options`` (or its dict; default ``cfg.camera.options``).
        pose_fn: the simulated base's true pose (required). world: default
        ``World.by_name(cfg.sim.world, cfg.sim.seed)``. seed: of the image noise (default ``cfg.sim.seed``).
        """
        if pose_fn is None:
            raise ValueError("camera.driver 'sim' needs pose_fn: the simulated base's true pose")
        if options is None:
            options = cfg.camera.options
        opts = options if isinstance(options, cls.Options) else cls.Options.model_validate(options)
        if world is None:
            world = World.by_name(cfg.sim.world, cfg.sim.seed)
        # the rig of camera.calibration_file (a stereo file's baseline), else options.stereo_baseline: the
        # configuration checked that they agree, and the stages use the same one
        rig = getattr(cfg.camera, "stereo_baseline", None)
        baseline = (rig() if callable(rig) else None) or opts.stereo_baseline
        if cfg.camera.model != "pinhole":
            raise InputError(f"{cfg.source or '<config>'}: camera.model {cfg.camera.model}: the simulated camera "
                             f"renders pinhole cameras (with their camera.distortion) only")
        distorted = cfg.camera.rectified_problem() if baseline else ""
        if distorted:
            raise InputError(f"{cfg.source or '<config>'}: camera.options.stereo_baseline: the simulated stereo pair "
                             f"is rectified (a pinhole camera without distortion), and {distorted} describes a "
                             f"distorted one (remove the distortion, or the stereo baseline for a single camera)")
        return cls(world, cfg.camera.to_model(), cfg.camera.mount.to_mount(), pose_fn, clock,
                   cfg.camera.rate_hz, noise_std=cfg.sim.image_noise_std,
                   seed=cfg.sim.seed if seed is None else seed,
                   stereo_baseline=baseline, gain=opts.gain, color=opts.color)

    # ------------------------------------------------------------ lifecycle
    def connect(self) -> None:
        now = self.clock.now_ns()
        # First frame: the first due time at or after now.
        self._next_index = math.ceil(now * self.rate_hz / 1e9 - 1e-9)
        self._last_sample = (now, self.pose_fn())
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    def due_ns(self, index: int) -> int:
        """Clock time of frame ``index`` (frames are due at multiples of 1/rate_hz)."""
        return int(round(index * 1e9 / self.rate_hz))

    # ----------------------------------------------------------------- read
    def read(self, timeout_s: float = 0.0) -> Optional[Frame]:
        """The newest due frame not yet returned, or None.

        If none is due, waits on the clock for the next one, at most
        ``timeout_s`` (like a real camera; on a SimClock waiting advances
        simulated time, so the simulated loop calls ``read(0)``).
        """
        if not self._connected:
            raise CameraError("sim camera: read() before connect()")
        now = self.clock.now_ns()
        due = self.due_ns(self._next_index)
        if due > now:
            if timeout_s > 0:
                self._sample(now)
                self.clock.sleep_until(min(due, now + int(timeout_s * 1e9)))
                now = self.clock.now_ns()
            if due > now:
                self._sample(now)
                return None
        # Newest due frame: index = floor(now * rate); frames in between are dropped.
        index = max(self._next_index, int(math.floor(now * self.rate_hz / 1e9 + 1e-9)))
        while self.due_ns(index) > now:
            index -= 1
        stamp = self.due_ns(index)
        pose = self._pose_at(stamp, now)
        dropped = index - self._next_index
        self._next_index = index + 1
        frame = self.render_frame(pose, stamp, self._seq)
        frame.meta["dropped"] = dropped       # due frames skipped because read() came late
        self._seq += 1
        return frame

    def _sample(self, now: int) -> Pose2:
        pose = self.pose_fn()
        self._last_sample = (now, pose)
        return pose

    def _pose_at(self, stamp: int, now: int) -> Pose2:
        prev = self._last_sample
        pose_now = self._sample(now)
        if prev is None or prev[0] >= stamp or now <= prev[0]:
            return pose_now
        a = (stamp - prev[0]) / (now - prev[0])
        return interpolate_pose(prev[1], pose_now, a)

    # ------------------------------------------------------------ rendering
    def render_frame(self, pose: Pose2, stamp_ns: int = 0, seq: int = 0) -> Frame:
        """Render the frame seen from robot pose ``pose`` (no clock involved).

        Noise is seeded by (seed, seq), so a frame depends only on the world,
        the pose, the settings and its sequence number.
        """
        R_wc, t_wc = camera_pose(pose, self.mount)
        stereo = self.stereo_baseline is not None
        meta = {"true_pose": pose, "R_wc": R_wc, "t_wc": t_wc, "occluded": self.occluded, "gain": self.gain}
        shape = (self.model.height, self.model.width) + ((3,) if self.color else ())
        if self.occluded:
            # A covered lens: uniform black, no features; disparity unknown everywhere.
            black = np.zeros(shape, np.uint8)
            disp = np.full(shape[:2], np.nan, np.float32) if stereo else None
            return Frame(black, int(stamp_ns), int(seq), disparity=disp, right=black.copy() if stereo else None,
                         meta=meta)
        rng = np.random.default_rng([self.seed, int(seq)])
        out = self.renderer.render(R_wc, t_wc, image=True, color=self.color)
        left = apply_effects(out.image, self.gain, self.noise_std, rng, self.seed)
        right = disparity = None
        if stereo:
            R_r, t_r = right_camera_pose(R_wc, t_wc, self.stereo_baseline)
            right = apply_effects(self.renderer.render(R_r, t_r, image=True, color=self.color).image,
                                  self.gain, self.noise_std, rng, self.seed)
            disparity = out.disparity(self.model.fx, self.stereo_baseline)
        return Frame(left, int(stamp_ns), int(seq), disparity=disparity, right=right, meta=meta)
