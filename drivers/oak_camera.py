"""Luxonis OAK cameras through depthai 3.x: a mono or colour stream plus on-device stereo disparity, and with
``right_image`` the rectified right image of the pair (the line map matches segments in both images).

Start-up never lets depthai wait for an implicit device (``dai.Pipeline()``
with no device blocks ~11 s before failing): devices are listed first
(``dai.Device.getAllAvailableDevices()``, ~0.5 s) under a hard time limit, and
with none, or not the one asked for, ``connect()`` fails within
``discovery_timeout_s`` naming what it found.

Images and disparity (and right images) come from non-blocking output queues
and are paired by sequence number (``take_matching``). The calibration stored on the device
(``readCalibration``) is checked against the configured intrinsics and baseline,
which the stages were built from (``use_device_calibration``), and rides along in
each frame's meta.

``replay_file`` runs a host-only pipeline (``dai.Pipeline(createImplicitDevice=False)``
with a ReplayVideo node) that needs no hardware: the same host-side code path
(queues, ImgFrame conversion) for tests and CI.
"""
from __future__ import annotations

import atexit
import threading
import time
from datetime import timedelta
from typing import Any, Literal, Optional

import cv2
import numpy as np
from pydantic import ConfigDict, Field, model_validator
from vbnav.drivers.plain_values import PlainValues

from vbnav.drivers.camera import CameraError, Frame, GrabbingCamera
from vbnav.drivers.errors import InputError

# depthai (~370 MB) is the optional extra vbnav[oak]: a robot with a USB camera does not carry it.
DEPTHAI_MISSING = "the OAK camera driver needs depthai: pip install 'vbnav[oak]'"
try:
    import depthai as dai
except ImportError as _exc:
    raise ImportError(f"{DEPTHAI_MISSING} ({_exc})") from _exc


def timedelta_ns(td: timedelta) -> int:
    """Exact integer nanoseconds of a timedelta (depthai stamps are steady-clock = CLOCK_MONOTONIC)."""
    return ((td.days * 86400 + td.seconds) * 1_000_000 + td.microseconds) * 1000


def disparity_px(frame: "dai.ImgFrame", subpixel_bits: int = 3) -> np.ndarray:
    """Disparity in pixels (float32, NaN where the device found no match) from a StereoDepth output.

    RAW16 with subpixel carries ``subpixel_bits`` fractional bits; RAW8 is whole pixels.
    """
    raw = frame.getFrame()
    typ = frame.getType()
    out = raw.astype(np.float32)
    if typ == dai.ImgFrame.Type.RAW16 and subpixel_bits:
        out /= float(1 << subpixel_bits)
    elif typ not in (dai.ImgFrame.Type.RAW8, dai.ImgFrame.Type.RAW16):
        raise CameraError(f"disparity frame has type {typ}, expected RAW8 or RAW16")
    out[raw == 0] = np.nan
    return out


def frame_from_imgframes(img: "dai.ImgFrame", disp: Optional["dai.ImgFrame"] = None, seq: int = 0,
                         grey: bool = True, subpixel_bits: int = 3, meta: Optional[dict] = None,
                         right: Optional["dai.ImgFrame"] = None) -> Frame:
    """Host-side conversion of depthai messages into our Frame (``right``: the pair's rectified right image)."""
    image = _cv_image(img, grey)
    right_image = None
    if right is not None:
        right_image = _cv_image(right, grey=True)
        if right_image.shape[:2] != image.shape[:2]:
            raise CameraError(f"right image {right_image.shape[1]}x{right_image.shape[0]} is not the size of the "
                              f"left image {image.shape[1]}x{image.shape[0]} (camera.options.right_image takes the "
                              f"mono stream's rectified pair)")
        right_image = np.ascontiguousarray(right_image)
    disparity = None
    if disp is not None:
        disparity = disparity_px(disp, subpixel_bits)
        if disparity.shape[:2] != image.shape[:2]:
            raise CameraError(f"disparity {disparity.shape[1]}x{disparity.shape[0]} is not aligned with the image "
                              f"{image.shape[1]}x{image.shape[0]} (set the stereo depth alignment and output size)")
    m = {"device_seq": img.getSequenceNum()}
    m.update(meta or {})
    return Frame(np.ascontiguousarray(image), timedelta_ns(img.getTimestamp()), seq, right=right_image,
                 disparity=disparity, meta=m)


def _cv_image(msg: "dai.ImgFrame", grey: bool) -> np.ndarray:
    """The message's image, colour made grey when ``grey``."""
    image = msg.getCvFrame()
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if grey and image.ndim == 3 else image


def take_matching(pending: dict, seq: int):
    """The message of device sequence number ``seq`` from ``pending`` (seq -> message; None when it has not
    come), dropping it and every older one: an image's disparity and right image share its sequence number,
    and one that came too late for its image is never used."""
    found = pending.pop(seq, None)
    for k in [k for k in pending if k < seq]:
        del pending[k]
    return found


# Searches still running when the process exits are waited for, this long in all, before the interpreter
# shuts down: one returning into a finalising interpreter aborts the process (C++ terminate, exit 134).
SEARCH_EXIT_GRACE_S = 10.0
_searching: set = set()         # the done-events of the searches running now


@atexit.register
def _wait_for_searches() -> None:
    deadline = time.monotonic() + SEARCH_EXIT_GRACE_S
    for done in list(_searching):
        done.wait(max(0.0, deadline - time.monotonic()))


def list_devices(timeout_s: float) -> list:
    """``dai.Device.getAllAvailableDevices()`` under a hard time limit (None if it did not return in time).
    A search that did not return in time is waited for at exit (SEARCH_EXIT_GRACE_S)."""
    result: list = []
    done = threading.Event()

    def work():
        try:
            result.extend(dai.Device.getAllAvailableDevices())
        finally:
            done.set()
            _searching.discard(done)

    _searching.add(done)
    threading.Thread(target=work, name="oak-discovery", daemon=True).start()
    if not done.wait(timeout_s):
        return None
    return result


def describe(info) -> str:
    try:
        return f"{info.getDeviceId()} ({info.name}, {info.state.name})"
    except Exception:  # pragma: no cover - field names differ between depthai versions
        return str(info)


# How far the configured intrinsics may be from the device's before start-up is refused. The stream is the
# rectified left image, whose camera matrix is the calibrated one after rectification (a few px and well
# under 1 % between the two mono sensors of one board); a config left at another camera's values (400 px
# for a 450 px device) is 10 % off.
FOCAL_TOL = 0.02        # relative
CENTRE_TOL = 0.02       # of the image width / height
BASELINE_TOL = 0.01     # relative


def calibration_mismatch(K_device, baseline_device: Optional[float], cam, baseline_cfg: Optional[float]) -> list[str]:
    """What of the configured camera (``cam``: fx, fy, cx, cy, width, height) and baseline (None: not
    configured, the frames' own is used) disagrees with the device's calibration, as 'name: config vs device'."""
    K = np.asarray(K_device, float)
    out = []
    for name, cfg_v, dev_v, tol in (("fx", cam.fx, K[0, 0], FOCAL_TOL * K[0, 0]),
                                    ("fy", cam.fy, K[1, 1], FOCAL_TOL * K[1, 1]),
                                    ("cx", cam.cx, K[0, 2], CENTRE_TOL * cam.width),
                                    ("cy", cam.cy, K[1, 2], CENTRE_TOL * cam.height)):
        if abs(cfg_v - dev_v) > tol:
            out.append(f"camera.{name} {cfg_v:g} vs the device's {dev_v:.2f}")
    if baseline_cfg is not None and baseline_device is not None \
            and abs(baseline_cfg - baseline_device) > BASELINE_TOL * baseline_device:
        out.append(f"stereo baseline {baseline_cfg:g} m vs the device's {baseline_device:.4f} m")
    return out


class OakCamera(GrabbingCamera):
    name = "oak"
    default_size = (640, 400)  # the mono cameras' 400p mode

    class Options(PlainValues):
        model_config = ConfigDict(extra="forbid")
        device_id: Optional[str] = Field(None, description="device id (MxID) or IP; None: the only device attached")
        stream: Literal["mono", "color"] = Field("mono", description="mono: the left mono camera (CAM_B), "
                                                 "rectified with disparity on, its raw image without; color: CAM_A")
        disparity: bool = Field(True, description="on-device stereo disparity aligned with the stream")
        right_image: bool = Field(False, description="also deliver the rectified right image with each frame (the "
                                  "line map of `vbnav map build` and `goto --map` matches segments in both images of "
                                  "the pair); needs stream mono and disparity true; twice the images over USB")
        subpixel: bool = Field(False, description="subpixel disparity (finer depth far away)")
        subpixel_bits: int = Field(3, ge=3, le=5, description="fractional bits of subpixel disparity")
        extended_disparity: bool = Field(False, description="twice the disparity search range: nearer "
                                                            "minimum depth")
        lr_check: bool = Field(True, description="left-right consistency check of the disparity")
        use_device_calibration: bool = Field(
            True, description="read the device's EEPROM calibration at start-up and refuse to start when the "
                              "intrinsics the stages use (camera.fx/fy/cx/cy, inline or from calibration_file) "
                              "or the stereo baseline differ from it (focal length 2 %, principal point 2 % of "
                              "the image, baseline 1 %; the error prints the device's values); the frames then "
                              "carry the device's K and baseline_m. false: the configured values, unchecked")
        grey: bool = Field(True, description="deliver single-channel images")
        discovery_timeout_s: float = Field(2.0, gt=0, le=30, description="fail start-up after this long")
        replay_file: Optional[str] = Field(None, description="host-only replay of a recorded video (no device)")
        replay_fps: float = Field(30.0, gt=0, description="frame rate of replay_file, Hz")

        @model_validator(mode="after")
        def _options_of_a_mode_that_is_on(self):
            # An option of a mode that is off is never read by the pipeline: refuse it rather than ignore it.
            values = self.model_dump()
            changed = {n for n in self.model_fields_set if values[n] != type(self).model_fields[n].default}
            for names, mode, off in ((("subpixel", "subpixel_bits", "extended_disparity", "lr_check"),
                                      "disparity: true", not self.disparity),
                                     (("subpixel_bits",), "subpixel: true", not self.subpixel),
                                     # the stereo node's rectified right image, the pair of the mono stream's left
                                     (("right_image",), "disparity: true", not self.disparity),
                                     (("right_image",), "stream: mono", self.stream != "mono"),
                                     (("replay_fps",), "replay_file", self.replay_file is None),
                                     (("device_id", "stream", "subpixel", "subpixel_bits", "extended_disparity",
                                       "lr_check", "use_device_calibration", "discovery_timeout_s", "right_image"),
                                      "replay_file: null (a device)", self.replay_file is not None)):
                idle = [n for n in names if n in changed]
                if off and idle:
                    raise ValueError(f"{', '.join(f'{n}: {values[n]}' for n in idle)}: takes effect only with "
                                     f"{mode} (remove it, or set {mode})")
            return self

    def __init__(self, cfg: Any = None, clock=None, *, options: Optional["OakCamera.Options"] = None,
                 width: Optional[int] = None, height: Optional[int] = None, fps: Optional[float] = None):
        super().__init__(cfg, clock, options=options, width=width, height=height, fps=fps)
        self._camera_cfg = getattr(cfg, "camera", None)   # what the stages use, checked against the device
        distorted = self._camera_cfg.rectified_problem() if self._camera_cfg is not None else ""
        if distorted and self.opt.stream == "mono" and self.opt.disparity and not self.opt.replay_file:
            raise InputError(f"camera.options.stream mono with camera.options.disparity is the device's rectified "
                             f"left image (no distortion), and {distorted} describes a distorted one: every stage "
                             f"would undistort it again (remove the distortion, set camera.model: pinhole, or use "
                             f"the raw left image: camera.options.disparity: false)")
        obstacles = getattr(cfg, "obstacles", None)
        self._baseline_cfg = (getattr(obstacles, "baseline", None)
                              or (self._camera_cfg.stereo_baseline() if self._camera_cfg is not None else None))
        self.intrinsics: Optional[np.ndarray] = None
        self.distortion: Optional[np.ndarray] = None
        self.baseline_m: Optional[float] = None
        self.device_id: Optional[str] = None
        self._device = None
        self._pipeline = None
        self._img_q = self._disp_q = self._right_q = None
        self._pending_disp: dict[int, Any] = {}
        self._pending_right: dict[int, Any] = {}

    @staticmethod
    def find(timeout_s: float = 2.0) -> list[str]:
        devices = list_devices(timeout_s) or []
        return [describe(d) for d in devices]

    # -- lifecycle ------------------------------------------------------------------------
    def connect(self) -> None:
        try:
            if self.opt.replay_file:
                self._build_replay()
            else:
                self._build_device()
            self._pipeline.start()
        except Exception as exc:
            self.disconnect()      # a device left open is busy for the next start
            if isinstance(exc, CameraError):
                raise
            # depthai's own errors (a size or rate the sensors do not offer, a pipeline the device cannot
            # start): a camera that cannot run as configured, said of which device and what it was asked for
            raise CameraError(f"OAK {self.device_id or self.opt.device_id or 'device'}: {self._asked()} could not "
                              f"start: {type(exc).__name__}: {exc}. Expected settings this device offers "
                              f"(camera.width/height/rate_hz, camera.options)") from exc
        self._start_grabbing("oak-grab")

    def _asked(self) -> str:
        """What the pipeline was asked for, as an error names it."""
        if self.opt.replay_file:
            return f"replay pipeline ({self.width}x{self.height} at {self.opt.replay_fps:g} fps)"
        stereo = " with stereo disparity" if self.opt.disparity else " without disparity"
        return f"{self.opt.stream} stream of {self.width}x{self.height} at {self.fps:g} fps{stereo}"

    def disconnect(self) -> None:
        self._stop.set()
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            except Exception:
                pass
        self._join_grabbing(3.0)
        if self._device is not None:
            try:
                self._device.close()
            except Exception:
                pass
        self._pipeline = self._device = None
        self._connected = False

    # -- pipelines --------------------------------------------------------------------------
    def _build_replay(self) -> None:
        import os
        if not os.path.isfile(self.opt.replay_file):
            raise CameraError(f"OAK replay file {self.opt.replay_file} not found")
        # depthai's ReplayVideo takes any file and its pipeline just stops: a file that is no video ran as
        # a camera that never delivered ('pipeline stopped'). Read its first frame here instead.
        probe = cv2.VideoCapture(self.opt.replay_file)
        try:
            readable = probe.isOpened() and probe.read()[0]
        finally:
            probe.release()
        if not readable:
            raise CameraError(f"OAK replay file {self.opt.replay_file}: no video frame could be read from it "
                              f"(expected a recorded video, e.g. .mp4 or .avi)")
        self.device_id = "replay:" + self.opt.replay_file
        p = dai.Pipeline(createImplicitDevice=False)
        replay = p.create(dai.node.ReplayVideo)
        replay.setReplayVideoFile(self.opt.replay_file)
        replay.setOutFrameType(dai.ImgFrame.Type.GRAY8 if self.opt.grey else dai.ImgFrame.Type.BGR888i)
        replay.setSize(self.width, self.height)
        replay.setFps(self.opt.replay_fps)
        replay.setLoop(False)
        self._pipeline = p
        self._img_q = replay.out.createOutputQueue(maxSize=1, blocking=False)
        self._disp_q = self._right_q = None

    def _select_device(self):
        t0 = time.monotonic()
        devices = list_devices(self.opt.discovery_timeout_s)
        took = time.monotonic() - t0
        if devices is None:
            raise CameraError(f"OAK device discovery did not finish within {self.opt.discovery_timeout_s:g} s")
        found = ", ".join(describe(d) for d in devices) or "none"
        if not devices:
            raise CameraError(f"no OAK device found (searched {took:.1f} s over USB and network; found: {found}). "
                              f"Check the cable/power, and that a udev rule lets this user open Movidius (03e7) devices: "
                              f"'sudo $(command -v vbnav) service install -c CONFIG' writes one to "
                              f"/etc/udev/rules.d/99-vbnav.rules (docs/service.md).")
        if self.opt.device_id is None:
            if len(devices) > 1:
                raise CameraError(f"{len(devices)} OAK devices found ({found}); set camera.options.device_id")
            return devices[0]
        for d in devices:
            if self.opt.device_id in (d.getDeviceId(), getattr(d, "name", None)):
                return d
        raise CameraError(f"OAK device {self.opt.device_id} not found; found: {found}")

    def _build_device(self) -> None:
        info = self._select_device()
        try:
            self._device = dai.Device(info)
        except Exception as exc:
            raise CameraError(f"OAK device {describe(info)} cannot be opened: {exc}") from exc
        self.device_id = info.getDeviceId()   # from here on, connect() names it in depthai's errors
        calib = self._device.readCalibration()
        p = dai.Pipeline(self._device)
        size = (self.width, self.height)
        mono_type = dai.ImgFrame.Type.GRAY8
        if self.opt.stream == "mono" or self.opt.disparity:
            left = p.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_B)
            right = p.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_C)
            left_out = left.requestOutput(size, mono_type, fps=self.fps)
            right_out = right.requestOutput(size, mono_type, fps=self.fps)
        stereo = None
        if self.opt.disparity:
            stereo = p.create(dai.node.StereoDepth)
            stereo.setLeftRightCheck(self.opt.lr_check)
            stereo.setSubpixel(self.opt.subpixel)
            if self.opt.subpixel:
                stereo.setSubpixelFractionalBits(self.opt.subpixel_bits)
            stereo.setExtendedDisparity(self.opt.extended_disparity)
            left_out.link(stereo.left)
            right_out.link(stereo.right)
        if self.opt.stream == "mono":
            socket = dai.CameraBoardSocket.CAM_B
            img_out = stereo.rectifiedLeft if stereo is not None else left_out
        else:
            socket = dai.CameraBoardSocket.CAM_A
            color = p.create(dai.node.Camera).build(socket)
            img_out = color.requestOutput(size, dai.ImgFrame.Type.BGR888i, fps=self.fps)
            if stereo is not None:
                stereo.setDepthAlign(socket)
                stereo.setOutputSize(self.width, self.height)
        if stereo is not None and self.opt.stream == "mono":
            stereo.setDepthAlign(dai.StereoDepthConfig.AlgorithmControl.DepthAlign.RECTIFIED_LEFT)
        if self.opt.use_device_calibration:
            self.read_calibration(calib, socket)
        self._pipeline = p
        self._img_q = img_out.createOutputQueue(maxSize=1, blocking=False)
        self._disp_q = stereo.disparity.createOutputQueue(maxSize=4, blocking=False) if stereo is not None else None
        self._right_q = (stereo.rectifiedRight.createOutputQueue(maxSize=4, blocking=False) if self.opt.right_image
                         else None)      # the Options refuse right_image without the stereo node's mono pair

    def read_calibration(self, calib: "dai.CalibrationHandler", socket: "dai.CameraBoardSocket") -> None:
        """The device's intrinsics of the stream (at its size), distortion and stereo baseline, checked
        against the configured camera."""
        self.intrinsics = np.array(calib.getCameraIntrinsics(socket, self.width, self.height), dtype=float)
        self.distortion = np.array(calib.getDistortionCoefficients(socket), dtype=float)
        self.baseline_m = float(calib.getBaselineDistance(dai.CameraBoardSocket.CAM_C,
                                                          dai.CameraBoardSocket.CAM_B)) / 100.0   # cm
        self._check_calibration()

    def _check_calibration(self) -> None:
        """The stages were built from the configured intrinsics: refuse to run them on a device they do
        not describe."""
        cam = self._camera_cfg
        if cam is None:
            return
        bad = calibration_mismatch(self.intrinsics, self.baseline_m, cam, self._baseline_cfg)
        if bad:
            K = self.intrinsics
            raise CameraError(
                f"OAK {self.device_id}: the configured camera does not match the device's own calibration "
                f"({'; '.join(bad)}). Set camera.fx: {K[0, 0]:.2f}, fy: {K[1, 1]:.2f}, cx: {K[0, 2]:.2f}, "
                f"cy: {K[1, 2]:.2f} (and a stereo baseline of {self.baseline_m:.4f} m, where one is set) for "
                f"{self.width}x{self.height}, or set camera.options.use_device_calibration: false to run on the "
                f"configured values unchecked")

    # -- grabbing ----------------------------------------------------------------------------------
    def _meta(self) -> dict:
        m = {"device": self.device_id}
        if self.intrinsics is not None:
            m["K"] = self.intrinsics
            m["baseline_m"] = self.baseline_m
        return m

    def _grab_loop(self) -> None:
        while not self._stop.is_set():
            try:
                if not self._pipeline.isRunning():
                    self.error = self.error or "OAK pipeline stopped (device lost or replay finished)"
                    # a recording has delivered its last frame (a device pipeline that stops is lost, not done)
                    self.finished = bool(self.opt.replay_file)
                    return
                img = self._img_q.tryGet()
                for q, pending in ((self._disp_q, self._pending_disp), (self._right_q, self._pending_right)):
                    if q is not None:
                        for d in q.tryGetAll():
                            pending[d.getSequenceNum()] = d
                if img is None:
                    time.sleep(0.002)
                    continue
                # disparity, the right image and their rectified left image share the device sequence number
                # (a queue that is off leaves its pending dict empty: None)
                disp = take_matching(self._pending_disp, img.getSequenceNum())
                right = take_matching(self._pending_right, img.getSequenceNum())
                meta = self._meta()
                self._frames.publish(lambda seq: frame_from_imgframes(img, disp, seq, self.opt.grey,
                                                                      self.opt.subpixel_bits, meta, right))
            except Exception as exc:  # device unplugged mid-stream: report, the runtime sees stale frames
                if self._stop.is_set():
                    return
                self.error = f"OAK camera {self.device_id} failed: {exc}"
                return
