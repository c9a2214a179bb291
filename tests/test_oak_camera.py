"""OakCamera without hardware: host-side conversion of real dai.ImgFrame objects, fast failure
with no device, and a host-only depthai pipeline (ReplayVideo) through the driver."""
from __future__ import annotations

import re
import time
from datetime import timedelta

import cv2
import numpy as np
import pytest

from conftest import import_extra
dai = import_extra("depthai", "oak")  # CI installs the extra: there a missing depthai fails

from vbnav.drivers.camera import CameraError  # noqa: E402
from vbnav.drivers.oak_camera import OakCamera, frame_from_imgframes, take_matching, timedelta_ns  # noqa: E402


def grey_frame(img: np.ndarray, seq: int, stamp: timedelta) -> "dai.ImgFrame":
    f = dai.ImgFrame()
    f.setCvFrame(img, dai.ImgFrame.Type.GRAY8)
    f.setSequenceNum(seq)
    f.setTimestamp(stamp)
    return f


def raw16_frame(values: np.ndarray, seq: int) -> "dai.ImgFrame":
    f = dai.ImgFrame()
    f.setFrame(values.astype(np.uint16))
    f.setType(dai.ImgFrame.Type.RAW16)
    f.setWidth(values.shape[1])
    f.setHeight(values.shape[0])
    f.setSequenceNum(seq)
    return f


def test_timedelta_to_integer_nanoseconds():
    assert timedelta_ns(timedelta(days=1, seconds=2, microseconds=3)) == 86_402_000_003_000


def test_grey_image_and_subpixel_disparity_conversion(rng):
    img = rng.integers(0, 256, (40, 64), dtype=np.uint8)
    raw = rng.integers(1, 96 * 8, (40, 64)).astype(np.uint16)
    raw[5, 7] = 0  # no match there
    frame = frame_from_imgframes(grey_frame(img, 17, timedelta(seconds=12, microseconds=345678)),
                                 raw16_frame(raw, 17), seq=3, subpixel_bits=3, meta={"baseline_m": 0.075})
    assert frame.seq == 3 and frame.meta["device_seq"] == 17 and frame.meta["baseline_m"] == 0.075
    assert frame.stamp_ns == 12_345_678_000
    np.testing.assert_array_equal(frame.image, img)
    assert frame.disparity.dtype == np.float32
    assert np.isnan(frame.disparity[5, 7])
    valid = raw != 0
    np.testing.assert_allclose(frame.disparity[valid], raw[valid] / 8.0)


def test_whole_pixel_raw8_disparity_and_colour_to_grey(rng):
    bgr = rng.integers(0, 256, (30, 50, 3), dtype=np.uint8)
    col = dai.ImgFrame()
    col.setCvFrame(bgr, dai.ImgFrame.Type.BGR888i)
    d = dai.ImgFrame()
    raw = rng.integers(0, 95, (30, 50)).astype(np.uint8)
    d.setFrame(raw)
    d.setType(dai.ImgFrame.Type.RAW8)
    d.setWidth(50)
    d.setHeight(30)
    frame = frame_from_imgframes(col, d, seq=1)
    np.testing.assert_array_equal(frame.image, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    np.testing.assert_array_equal(np.nan_to_num(frame.disparity, nan=0.0), raw.astype(np.float32))
    keep = frame_from_imgframes(col, None, seq=2, grey=False)
    np.testing.assert_array_equal(keep.image, bgr)


def test_misaligned_disparity_is_refused(rng):
    img = grey_frame(np.zeros((40, 64), np.uint8), 1, timedelta(seconds=1))
    with pytest.raises(CameraError, match="not aligned"):
        frame_from_imgframes(img, raw16_frame(np.ones((20, 32)), 1))


def test_no_device_fails_fast_listing_what_was_found():
    if dai.Device.getAllAvailableDevices():
        pytest.skip("an OAK device is attached here")
    cam = OakCamera(options=OakCamera.Options(device_id="14442C10D13EABCE00"))
    t0 = time.monotonic()
    # ... and points at the udev rule the project ships (vbnav service install, docs/service.md)
    with pytest.raises(CameraError, match="no OAK device found.*found: none.*vbnav. service install -c CONFIG. "
                                          "writes one to /etc/udev/rules.d/99-vbnav.rules"):
        cam.connect()
    assert time.monotonic() - t0 < 2.0  # not depthai's ~11 s implicit-device wait


def test_host_only_replay_pipeline(tmp_path):
    path = tmp_path / "rec.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (64, 48))
    for k in range(30):
        writer.write(np.full((48, 64, 3), 8 * k, np.uint8))
    writer.release()
    cam = OakCamera(options=OakCamera.Options(replay_file=str(path), replay_fps=60.0, disparity=False),
                    width=64, height=48)
    cam.connect()
    try:
        frames = []
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and len(frames) < 10:
            f = cam.read(timeout_s=0.5)
            if f is not None:
                frames.append(f)
    finally:
        cam.disconnect()
    assert len(frames) >= 10
    assert all(f.image.shape == (48, 64) and f.image.dtype == np.uint8 for f in frames)
    levels = [float(f.image.mean()) for f in frames]
    assert all(b > a for a, b in zip(levels, levels[1:]))  # the recording, in order (latest-only may skip)
    assert all(b.stamp_ns > a.stamp_ns for a, b in zip(frames, frames[1:]))
    assert abs(frames[-1].stamp_ns - time.monotonic_ns()) < 10e9  # device/steady clock = our monotonic clock


def test_missing_replay_file_is_a_clear_error(tmp_path):
    with pytest.raises(CameraError, match="replay file .* not found"):
        OakCamera(options=OakCamera.Options(replay_file=str(tmp_path / "nope.mp4"))).connect()
    # a file that is no video connected, then delivered nothing ('pipeline stopped')
    (tmp_path / "notvideo.mp4").write_text("not a video\n")
    with pytest.raises(CameraError, match="notvideo.mp4: no video frame could be read"):
        OakCamera(options=OakCamera.Options(replay_file=str(tmp_path / "notvideo.mp4"))).connect()


def device_calibration(fx: float, baseline_cm: float, size=(640, 400)) -> "dai.CalibrationHandler":
    """A real depthai calibration (as read from a device's EEPROM), built on the host."""
    calib = dai.CalibrationHandler()
    K = [[fx, 0.0, size[0] / 2], [0.0, fx, size[1] / 2], [0.0, 0.0, 1.0]]
    for socket in (dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C):
        calib.setCameraIntrinsics(socket, K, size[0], size[1])
    calib.setCameraExtrinsics(dai.CameraBoardSocket.CAM_C, dai.CameraBoardSocket.CAM_B, np.eye(3).tolist(),
                              [baseline_cm, 0.0, 0.0], [baseline_cm, 0.0, 0.0])
    return calib


def test_device_calibration_is_checked_against_the_configured_camera(tmp_path):
    """use_device_calibration: the stages run on camera.fx/fy/cx/cy and the stereo baseline, so a device
    whose own calibration says otherwise is refused at start-up with the values to set."""
    from vbnav.control.config import load_config
    size = {"width": 640, "height": 400}
    cfg = load_config("sentry-oak", overrides={"camera": {**size, "fx": 452.0, "fy": 452.0, "cx": 320.0, "cy": 200.0}})
    cam = OakCamera(cfg)
    cam.read_calibration(device_calibration(450.0, 7.5), dai.CameraBoardSocket.CAM_B)   # 0.4 % off: the same
    assert cam.intrinsics[0, 0] == 450.0 and cam._meta()["baseline_m"] == pytest.approx(0.075)
    with pytest.raises(CameraError) as err:                       # the config left at another camera's 400 px
        OakCamera(load_config("sentry-oak", overrides={"camera": {**size, "fx": 400.0, "fy": 400.0, "cx": 320.0,
                                                                  "cy": 200.0}})
                  ).read_calibration(device_calibration(450.0, 7.5), dai.CameraBoardSocket.CAM_B)
    msg = str(err.value)
    assert "camera.fx 400 vs the device's 450.00" in msg and "camera.fy 400" in msg and "camera.cx" not in msg
    assert "Set camera.fx: 450.00" in msg and "use_device_calibration: false" in msg
    rig = tmp_path / "rig.yaml"                                   # a stereo calibration file with its baseline
    rig.write_text("width: 640\nheight: 400\nfx: 450\nfy: 450\ncx: 320\ncy: 200\nbaseline: 0.075\n")
    filed = OakCamera(load_config("sentry-oak", overrides={"camera": {**size, "calibration_file": str(rig)}}))
    filed.read_calibration(device_calibration(450.0, 7.5), dai.CameraBoardSocket.CAM_B)
    with pytest.raises(CameraError, match=r"stereo baseline 0.075 m vs the device's 0.0600 m"):
        filed.read_calibration(device_calibration(450.0, 6.0), dai.CameraBoardSocket.CAM_B)
    by_obstacles = OakCamera(load_config("sentry-oak", overrides={"obstacles": {"baseline": 0.06}}))
    with pytest.raises(CameraError, match=r"stereo baseline 0.06 m vs the device's 0.0750 m"):
        by_obstacles.read_calibration(device_calibration(400.0, 7.5), dai.CameraBoardSocket.CAM_B)


def test_a_replay_that_ended_is_finished(tmp_path):
    """A recorded source says when it has delivered its last frame (Camera.finished): the OAK replay never
    did, so a reader that stops at the end (vbnav calibrate --live) waited out its whole timeout."""
    path = tmp_path / "rec.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (64, 48))
    for k in range(5):
        writer.write(np.full((48, 64, 3), 8 * k, np.uint8))
    writer.release()
    cam = OakCamera(options=OakCamera.Options(replay_file=str(path), replay_fps=60.0, disparity=False),
                    width=64, height=48)
    cam.connect()
    try:
        deadline = time.monotonic() + 8.0
        while time.monotonic() < deadline and not cam.finished:
            cam.read(timeout_s=0.1)
        assert cam.finished
    finally:
        cam.disconnect()


def test_a_replay_pipeline_that_fails_to_start_is_a_camera_error_naming_the_source(tmp_path, monkeypatch):
    """depthai's own start-up errors (a pipeline that fails to start) came out as its bare RuntimeError: the
    runtime called them a bug (exit 1), and nothing named the device or what it was asked for. They are now a
    CameraError with both. The host-only replay pipeline, its start failing as depthai's does."""
    path = tmp_path / "rec.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (64, 48))
    for k in range(3):
        writer.write(np.full((48, 64, 3), 8 * k, np.uint8))
    writer.release()

    def refuse(self):
        raise RuntimeError("Pipeline build failed: node ReplayVideo has no output")
    monkeypatch.setattr(dai.Pipeline, "start", refuse)
    cam = OakCamera(options=OakCamera.Options(replay_file=str(path), replay_fps=60.0, disparity=False),
                    width=64, height=48, fps=20.0)
    with pytest.raises(CameraError) as err:
        cam.connect()
    msg = str(err.value)
    assert f"OAK replay:{path}" in msg and "64x48" in msg and "could not start" in msg, msg
    assert "RuntimeError: Pipeline build failed: node ReplayVideo has no output" in msg, msg
    assert not cam.is_connected and cam._pipeline is None


class _Refused(RuntimeError):
    pass


def _fake_device_layer(monkeypatch, fail_at: str):
    """depthai's device side without a device: a real DeviceInfo and a real calibration, and a pipeline whose
    ``fail_at`` step ('requestOutput' or 'start') raises as depthai does for settings the device cannot run."""
    import vbnav.drivers.oak_camera as oak

    opened = []

    class Device:
        def __init__(self, info):
            self.closed = False
            opened.append(self)

        def readCalibration(self):
            return device_calibration(450.0, 7.5)

        def close(self):
            self.closed = True

    class Node:
        def build(self, socket):
            return self

        def requestOutput(self, size, typ, fps):
            if fail_at == "requestOutput":
                raise _Refused(f"CAM_B: no sensor configuration for {size[0]}x{size[1]} at {fps:g} fps")
            return self

        def __getattr__(self, name):      # setters, links, outputs and their queues: all fine
            return self

        def __call__(self, *args, **kwargs):
            return self

    class Pipeline:
        def __init__(self, device):
            assert isinstance(device, Device)

        def create(self, node):
            return Node()

        def start(self):
            if fail_at == "start":
                raise _Refused("Device booted but the pipeline failed to start: out of memory on the device")

    fake = type("FakeDai", (), {})()
    for name in ("CameraBoardSocket", "ImgFrame", "node", "StereoDepthConfig", "CalibrationHandler"):
        setattr(fake, name, getattr(dai, name))
    fake.Device, fake.Pipeline = Device, Pipeline
    monkeypatch.setattr(oak, "dai", fake)
    monkeypatch.setattr(oak, "list_devices", lambda timeout_s: [dai.DeviceInfo("14442C10D13EABCE00")])
    return opened


@pytest.mark.parametrize("fail_at", ["requestOutput", "start"])
def test_a_device_that_refuses_its_settings_is_a_camera_error_naming_it_and_what_was_asked(monkeypatch, fail_at):
    """An unsupported resolution, or a pipeline that fails to start on the device, raised depthai's error as
    it was (the run called it a bug, exit 1) and left the device open (the next start finds it busy). It is
    now a CameraError naming the device and the stream, size and rate it was asked for, and the device is
    closed."""
    opened = _fake_device_layer(monkeypatch, fail_at)
    cam = OakCamera(options=OakCamera.Options(use_device_calibration=False), width=1234, height=567, fps=45.0)
    with pytest.raises(CameraError) as err:
        cam.connect()
    msg = str(err.value)
    assert "OAK 14442C10D13EABCE00" in msg and "mono" in msg and "1234x567 at 45 fps" in msg, msg
    assert "disparity" in msg and "camera.width" in msg and "_Refused" in msg, msg
    assert opened and opened[0].closed, "the device was left open"
    assert not cam.is_connected


@pytest.mark.parametrize("camera, says", [
    ({"distortion": [-0.1, 0.02, 0.0, 0.0, 0.0]}, "camera.distortion [-0.1, 0.02, 0.0, 0.0, 0.0]"),
    ({"model": "fisheye"}, "camera.model fisheye"),
])
def test_a_distorted_camera_on_the_rectified_mono_stream_is_refused(camera, says):
    """The mono stream with on-device stereo is the RECTIFIED left image (stereo.rectifiedLeft): a
    camera.distortion or fisheye model (a calibration of the raw sensor) was accepted and every stage
    undistorted images that have none; the device check compares fx/fy/cx/cy only. It is refused when the
    camera is built, naming the field; without disparity (the raw left image) and on the colour stream the
    distortion is the lens's and is taken."""
    from vbnav.control.config import load_config
    from vbnav.drivers.errors import InputError
    off = {"obstacles": {"enabled": False}}          # the obstacle stage refuses it at load (test_config.py)
    with pytest.raises(InputError, match=r"camera\.options\.stream mono .*rectified.*" + re.escape(says)):
        OakCamera(load_config("sentry-oak", overrides={"camera": camera, **off}))
    OakCamera(load_config("sentry-oak", overrides={"camera": {**camera, "options": {"disparity": False}}, **off}))
    OakCamera(load_config("sentry-oak", overrides={"camera": {**camera, "options": {"stream": "color"}}, **off}))
    OakCamera(load_config("sentry-oak", overrides={"camera": {"distortion": [0.0] * 5}, **off}))


@pytest.mark.parametrize("options, says", [
    ({"disparity": False, "subpixel": True, "extended_disparity": True},
     r"subpixel: True, extended_disparity: True: .*only with disparity: true"),
    ({"subpixel_bits": 5}, r"subpixel_bits: 5: .*only with subpixel: true"),
    ({"replay_fps": 10.0}, r"replay_fps: 10\.0: .*only with replay_file"),
    ({"right_image": True, "disparity": False}, r"right_image: True: .*only with disparity: true"),
    ({"right_image": True, "stream": "color"}, r"right_image: True: .*only with stream: mono"),
    ({"replay_file": "x.mp4", "device_id": "1844", "use_device_calibration": False},
     r"device_id: 1844, use_device_calibration: False: .*only with replay_file: null \(a device\)"),
])
def test_oak_options_of_a_mode_that_is_off_are_refused(options, says):
    """subpixel, subpixel_bits, extended_disparity and lr_check tune the on-device stereo, subpixel_bits the
    subpixel disparity, replay_fps the host-only replay: set while that is off they were accepted and the
    pipeline never read them (no finer depth, no nearer range). They are refused, naming the option and what
    turns it on; the defaults written out, and the same options with their mode on, are taken. The device's
    options (device_id, stream, the stereo's, use_device_calibration, discovery_timeout_s) with replay_file
    likewise: the host-only replay builds no device pipeline."""
    from pydantic import ValidationError
    with pytest.raises(ValidationError, match=says):
        OakCamera.Options(**options)
    OakCamera.Options(disparity=False, subpixel=False, lr_check=True)        # the defaults, written out
    OakCamera.Options(subpixel=True, subpixel_bits=5, extended_disparity=True)
    OakCamera.Options(replay_file="x.mp4", replay_fps=10.0, disparity=False)   # a replay has no disparity
    OakCamera.Options(right_image=True)                                         # the mono stream's pair


def test_the_rectified_right_image_rides_with_its_left_image_and_disparity(monkeypatch, rng):
    """camera.options.right_image (the line map matches segments in both images of the pair): the stereo node's
    rectifiedRight is the frame's right image, paired with the rectified left image and the disparity by the
    device's sequence number; one whose left image never came is dropped. Before, an OAK never gave a right
    image, so the line map skipped every frame. depthai's device side is faked here (no device, no emulator);
    the messages are real dai.ImgFrames."""
    import vbnav.drivers.oak_camera as oak
    left, right = (rng.integers(0, 256, (40, 64), dtype=np.uint8) for _ in range(2))
    raw = rng.integers(1, 64 * 8, (40, 64)).astype(np.uint16)
    stamp = timedelta(seconds=3)
    sent = {"rectifiedLeft": [grey_frame(left, 7, stamp)], "disparity": [raw16_frame(raw, 7)],
            "rectifiedRight": [grey_frame(255 - right, 6, stamp), grey_frame(right, 7, stamp)]}
    asked = []

    class Queue:
        def __init__(self, msgs):
            self.msgs = msgs

        def tryGet(self):
            return self.msgs.pop(0) if self.msgs else None

        def tryGetAll(self):
            out, self.msgs[:] = list(self.msgs), []
            return out

    class Output:
        def __init__(self, name):
            self.name = name

        def createOutputQueue(self, maxSize, blocking):
            asked.append(self.name)
            return Queue(sent[self.name])

        def link(self, other):
            pass

    class Node:
        def build(self, socket):
            return self

        def requestOutput(self, size, typ, fps):
            return Output("sensor")

        def __getattr__(self, name):        # the stereo node's outputs by name; its setters and inputs
            return Output(name) if name in sent else (lambda *args, **kwargs: None)

    class Pipeline:
        def __init__(self, device):
            pass

        def create(self, node):
            return Node()

        def start(self):
            pass

        def isRunning(self):
            return True

        def stop(self):
            pass

    class Device:
        def __init__(self, info):
            pass

        def readCalibration(self):
            return device_calibration(450.0, 7.5)

        def close(self):
            pass

    fake = type("FakeDai", (), {})()
    for name in ("CameraBoardSocket", "ImgFrame", "node", "StereoDepthConfig"):
        setattr(fake, name, getattr(dai, name))
    fake.Device, fake.Pipeline = Device, Pipeline
    monkeypatch.setattr(oak, "dai", fake)
    monkeypatch.setattr(oak, "list_devices", lambda timeout_s: [dai.DeviceInfo("14442C10D13EABCE00")])
    cam = OakCamera(options=OakCamera.Options(right_image=True, use_device_calibration=False), width=64, height=40)
    cam.connect()
    try:
        frame = cam.read(timeout_s=5.0)
    finally:
        cam.disconnect()
    assert sorted(asked) == ["disparity", "rectifiedLeft", "rectifiedRight"], asked
    assert frame is not None and frame.meta["device_seq"] == 7
    np.testing.assert_array_equal(frame.image, left)
    np.testing.assert_array_equal(frame.right, right)       # seq 7's, not the older seq 6 (255 - right)
    np.testing.assert_allclose(frame.disparity, raw / 8.0)


def test_a_right_image_of_another_size_is_refused(rng):
    img = grey_frame(rng.integers(0, 256, (40, 64), dtype=np.uint8), 3, timedelta(0))
    other = grey_frame(rng.integers(0, 256, (20, 32), dtype=np.uint8), 3, timedelta(0))
    with pytest.raises(CameraError, match=r"right image 32x20 is not the size of the left image 64x40"):
        frame_from_imgframes(img, right=other)


def test_take_matching_pairs_by_sequence_number_and_drops_the_older():
    pending = {5: "five", 6: "six", 8: "eight"}
    assert take_matching(pending, 6) == "six" and pending == {8: "eight"}
    assert take_matching(pending, 7) is None and pending == {8: "eight"}     # not come yet: the newer kept
