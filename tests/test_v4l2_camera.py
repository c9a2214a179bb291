"""V4L2Camera: format verification and the latest-frame mailbox, on video files made here."""
from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from vbnav.drivers.camera import CameraError
from vbnav.drivers.v4l2_camera import V4L2Camera, fourcc_to_str

W, H, N = 64, 48, 40


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    """N frames; frame k is uniformly grey at level 5*k (survives MJPEG compression)."""
    path = tmp_path_factory.mktemp("video") / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (W, H))
    assert writer.isOpened()
    for k in range(N):
        writer.write(np.full((H, W, 3), 5 * k, np.uint8))
    writer.release()
    return path


def camera(path, **opts):
    return V4L2Camera(options=V4L2Camera.Options(device=str(path), **opts), width=W, height=H, fps=30.0)


def level(frame) -> int:
    return int(round(float(frame.image.mean()) / 5.0))


def test_replays_the_file_in_order_at_its_rate(video):
    cam = camera(video, replay_rate_hz=50.0)
    cam.connect()
    try:
        got = []
        while True:
            f = cam.read(timeout_s=1.0)
            if f is None:
                break
            got.append(f)
    finally:
        cam.disconnect()
    # every frame delivered is the right one; a frame the reader was too slow for shows as a seq gap
    assert all(level(f) == f.seq - 1 for f in got)
    assert all(b.seq > a.seq and b.stamp_ns > a.stamp_ns for a, b in zip(got, got[1:]))
    assert got[-1].seq == N and len(got) >= N // 2
    assert got[0].image.shape == (H, W) and got[0].image.dtype == np.uint8  # grey by default
    span_s = (got[-1].stamp_ns - got[0].stamp_ns) * 1e-9
    assert span_s > 0.5 * (got[-1].seq - got[0].seq) / 50.0  # paced, not decoded as fast as possible


def test_only_the_latest_frame_is_kept(video):
    cam = camera(video, replay_rate_hz=0, grey=False)  # as fast as the file decodes
    cam.connect()
    try:
        # no read before the file is exhausted: a first read could already return the last frame
        # (a fast machine decodes all N before it), leaving nothing newer to read after
        deadline = time.monotonic() + 5.0
        while not cam.finished and time.monotonic() < deadline:
            time.sleep(0.01)
        assert cam.finished, "the grabbing thread did not reach the end of the file within 5 s"
        last = cam.read(timeout_s=0.5)
        assert last is not None and last.image.shape == (H, W, 3)
        assert level(last) == N - 1 and last.seq == N  # older frames were overwritten, not queued
        assert cam.read(timeout_s=0.05) is None  # nothing newer than what was returned
        assert cam.latest_age_s() >= 0.0
    finally:
        cam.disconnect()


def test_loop_replay_wraps_around(video):
    cam = camera(video, replay_rate_hz=0, loop=True)
    cam.connect()
    try:
        deadline = time.monotonic() + 5.0
        seq = 0
        while seq <= N + 5 and time.monotonic() < deadline:
            f = cam.read(timeout_s=0.5)
            seq = f.seq if f else seq
        assert seq > N
    finally:
        cam.disconnect()


def test_wrong_size_fails_clearly(video):
    cam = V4L2Camera(options=V4L2Camera.Options(device=str(video)), width=640, height=480, fps=30.0)
    with pytest.raises(CameraError, match=r"is 64x48, the configuration expects 640x480"):
        cam.connect()


def test_missing_device_lists_what_exists(tmp_path):
    cam = V4L2Camera(options=V4L2Camera.Options(device="/dev/video-nonexistent"))
    with pytest.raises(CameraError, match="not found; video devices present"):
        cam.connect()


def test_fourcc_option_is_validated():
    with pytest.raises(ValueError, match="4 characters"):
        V4L2Camera.Options(fourcc="MJPEG")
    assert fourcc_to_str(cv2.VideoWriter_fourcc(*"YUYV")) == "YUYV"


def test_format_verification_names_each_mismatch(video):
    # a capture whose read-back differs from the request: the video file reports MJPG 64x48 at 30 fps
    cam = V4L2Camera(options=V4L2Camera.Options(device=str(video), fourcc="YUYV", source="device"), width=W,
                     height=32, fps=15.0)
    cap = cv2.VideoCapture(str(video))
    try:
        with pytest.raises(CameraError) as err:
            cam._verify(cap)
    finally:
        cap.release()
    msg = str(err.value)
    assert "format MJPG instead of YUYV" in msg and "size 64x48 instead of 64x32" in msg and "30 fps instead of 15" in msg


def test_reconnects_after_the_device_goes_away_and_comes_back(video, tmp_path):
    # A live source that stops delivering and whose path disappears, as an unplugged camera does.
    # The "device" is the clip behind a symlink opened as a live source (OpenCV picks the backend);
    # the end of the clip is the moment it stops delivering.
    link = tmp_path / "video-by-id"
    link.symlink_to(video)
    cam = V4L2Camera(options=V4L2Camera.Options(device=str(link), source="device", backend="any",
                                                stall_timeout_s=0.1, reconnect_interval_s=0.05),
                     width=W, height=H, fps=30.0)
    cam.connect()
    try:
        seen = [cam.read(timeout_s=1.0)]
        link.unlink()  # unplugged
        deadline = time.monotonic() + 5.0
        while (cam.error is None or "not found" not in cam.error) and time.monotonic() < deadline:
            cam.read(timeout_s=0.05)
        assert cam.error and f"camera {link} not found" in cam.error
        link.symlink_to(video)  # plugged back
        while cam.reconnects == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert cam.reconnects >= 1
        f = cam.read(timeout_s=1.0)
        assert f is not None and f.seq > seen[0].seq and f.meta["reconnects"] >= 1
    finally:
        cam.disconnect()


def test_a_missing_video_file_is_named_as_missing(tmp_path):
    """With source: file a path that does not exist was reported as a file OpenCV "cannot open (unknown
    container or codec?)": the wrong path looked like a wrong file."""
    missing = tmp_path / "clips" / "run1.avi"
    cam = V4L2Camera(options=V4L2Camera.Options(device=str(missing), source="file"), width=W, height=H, fps=30.0)
    with pytest.raises(CameraError, match=rf"video file {missing} not found \(camera.options.device\)"):
        cam.connect()


@pytest.mark.parametrize("opts, says", [
    ({"fourcc": "YUYV", "stall_timeout_s": 3.0},
     r"fourcc: YUYV, stall_timeout_s: 3\.0: .*live device.* is a video file"),
    ({"device": "/dev/video99", "loop": True}, r"loop: True: .*video file.*/dev/video99 is a live device"),
    ({"device": "/dev/video99", "replay_rate_hz": 5.0}, r"replay_rate_hz: 5\.0: .*video file"),
])
def test_options_of_the_other_source_are_refused(video, opts, says):
    """The file options (replay_rate_hz, loop) on a live device, and the device's (fourcc, backend,
    fps_tolerance, stall_timeout_s, reconnect_interval_s) on a video file, were accepted and never read: a
    loop: true on a camera, a fourcc YUYV on a clip. They are refused when the camera is built, naming the
    options and what the device is; the defaults written out are taken."""
    from vbnav.drivers.errors import InputError
    with pytest.raises(InputError, match=says):
        camera(opts.pop("device", video), **opts)
    camera(video, fourcc="MJPG", loop=True, replay_rate_hz=0)
    camera("/dev/video99", fourcc="YUYV", loop=False)


def test_a_live_source_that_stops_delivering_is_not_read_in_a_busy_loop(video, tmp_path):
    """A live device whose reads fail at once (unplugged: the ioctl answers ENODEV) was read again without a
    pause until stall_timeout_s had passed: tens of thousands of reads in 0.3 s here, a core spinning on a
    two-core robot beside the control loop. A failed read now waits half a frame period before the next (no
    frame is due sooner)."""
    reads = []

    class Counting:                              # the real capture, its reads counted
        def __init__(self, cap):
            self.cap = cap

        def read(self):
            ok, img = self.cap.read()
            reads.append(ok)
            return ok, img

        def __getattr__(self, name):
            return getattr(self.cap, name)

    class Counted(V4L2Camera):
        def _open(self):
            return Counting(super()._open())

    link = tmp_path / "video-by-id"
    link.symlink_to(video)            # a live source (OpenCV picks the backend): the clip's end is the stall
    stall_s = 0.3
    cam = Counted(options=V4L2Camera.Options(device=str(link), source="device", backend="any",
                                             stall_timeout_s=stall_s, reconnect_interval_s=30.0),
                  width=W, height=H, fps=30.0)
    cam.connect()
    try:
        deadline = time.monotonic() + 10.0
        while cam.error is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert cam.error and "stopped delivering" in cam.error
    finally:
        cam.disconnect()
    failed = reads.count(False)
    # one failed read every half frame period for stall_timeout_s at most (a slower machine reads fewer)
    assert 1 <= failed <= stall_s * 30.0 * 2 + 2, f"{failed} failed reads in {stall_s} s"


def test_a_read_that_never_returns_is_named_in_the_cameras_error(video, tmp_path):
    """A hung V4L2 read (a driver stuck in its ioctl) never returns to the grabbing thread: no error was set
    (the stall check runs only after a read fails), so the stale-camera hold said only 'last frame 3.00 s old'.
    The camera's error now says its read has not returned for how long, naming the device, once that passes
    stall_timeout_s, and clears when the read returns. Time is the driver's own clock, stepped here."""
    import threading

    entered, release, done = threading.Event(), threading.Event(), threading.Event()
    now = [100.0]

    class Hanging:
        def __init__(self, cap):
            self.cap = cap

        def read(self):
            entered.set()
            if not done.is_set():
                release.wait(10.0)
                release.clear()
            return self.cap.read()

        def __getattr__(self, name):
            return getattr(self.cap, name)

    class Hung(V4L2Camera):
        def _open(self):
            return Hanging(super()._open())

    link = tmp_path / "video-by-id"
    link.symlink_to(video)
    cam = Hung(options=V4L2Camera.Options(device=str(link), source="device", backend="any", stall_timeout_s=1.0),
               width=W, height=H, fps=30.0)
    cam._monotonic = lambda: now[0]
    cam.connect()
    try:
        assert entered.wait(5.0)                       # the thread is inside the read
        assert cam.error is None
        now[0] += 0.9
        assert cam.error is None                       # within stall_timeout_s: a slow frame, not a hung read
        now[0] += 2.1
        assert cam.error == (f"camera {link}: its read has not returned for 3.0 s (a hung driver or device; "
                             f"camera.options.stall_timeout_s 1 s)")
        entered.clear()
        release.set()                                  # the read returns a frame
        assert cam.read(timeout_s=5.0) is not None and entered.wait(5.0)
        assert cam.error is None
    finally:
        done.set()
        release.set()
        cam.disconnect()
