"""Camera + vision stages, producing the latest estimate of each kind.

Two modes, same stages:
- threaded (real time): one thread reads the camera and runs the stages on each
  new frame; the loop only picks up the latest results (never waits on it).
- inline (simulated clock): ``poll`` reads the camera and runs the stages in the
  loop's thread when a frame is due, and releases the result ``latency_s``
  later in simulated time. Deterministic, and as fast as the computation allows.

Each stage gets the wheel odometry at its frame's stamp (``odometry_at``), interpolated
in the loop's ``OdometryHistory``, not the newest pose: a frame processed 60 ms after
its exposure while turning would otherwise pair its image with where the robot is
now. Without a history (a pipeline driven by hand) the newest pose stands in.

Each frame is also checked for a frozen camera (``frozen_image``): a frozen frame goes to no stage, and
``last_fresh_ns`` is when the last frame that showed a new image (or the same one while the robot stood
still) was taken, from which the loop's stale-camera check counts: its stamp, or when the pipeline received
it on the robot's own clock if that is earlier. Staleness does not rest on the device's stamps alone.

Before any check or stage a frame is refused (``refused`` says why; it counts as no frame, so the stale-camera
hold stops the robot if it goes on) when its stamp is not integer nanoseconds (a NaN made the age NaN, never
above the limit), when it has no image (None, or an empty array), when its stamp is more than
``FUTURE_STAMP_TOLERANCE_S`` after the robot's clock at its reception (an image is exposed before it is
received, on the same clock: such a stamp is another clock's, and an hour ahead it made the age negative and
the camera never stale), or when its stamp is not after the last frame taken (repeated or going back: the
stages would pair a new image with odometry from the past, or take a time step of zero).

A stage exception is captured as ``fault`` (the loop turns it into a safety
trip), and so is any other exception in the vision thread (the frozen-image
check, a frame listener): the thread never ends without a fault that says why;
the pipeline never raises into the loop. ``fault_reason`` is the run's end it
makes: ``camera`` for a camera whose read raised ``CameraError`` (a device's
failure, as at start-up or in the loop's own read), else ``exception``.
"""
from __future__ import annotations

import threading
import time
import traceback
from collections import deque
from typing import Callable, Optional

import numpy as np

from vbnav.control.runtime.frozen_image import FrozenImageWatch
from vbnav.control.runtime.interfaces import Estimate, VisionStage
from vbnav.control.runtime.odometry import OdometryHistory
from vbnav.drivers.camera import Camera, CameraError, Frame
from vbnav.vision.geometry import Pose2

#: How far a frame's stamp may be after the robot's clock when the pipeline receives it. Exposure comes before
#: reception on the same clock (V4L2 and the simulated cameras stamp with the robot's clock, an OAK's stamps
#: are the host's steady clock, synced by depthai to well under a millisecond); 50 ms leaves room for that
#: sync and for reading the clock after the read returned, and none for a camera on another clock.
FUTURE_STAMP_TOLERANCE_S = 0.05


class VisionPipeline:
    def __init__(self, camera: Optional[Camera], stages: list[VisionStage], clock, inline: bool,
                 latency_s: float = 0.0, focal_px: Optional[float] = None):
        """``focal_px``: the camera's focal length, for the frozen-image watch's thresholds (None: 500 px)."""
        self.camera = camera
        self.stages = list(stages)
        self.clock = clock
        self.inline = inline
        self.latency_ns = int(latency_s * 1e9)
        self.latest: dict[str, Estimate] = {}
        self.last_frame: Optional[Frame] = None
        self.last_fresh_ns: Optional[int] = None   # the last frame not frozen: min(stamp, reception)
        self.last_fresh_received_ns: Optional[int] = None   # ... when it was received, on the robot's clock
        self.refused: Optional[str] = None         # why the newest frame was refused, None once one is taken
        self.refused_frames = 0
        self.last_refusal: Optional[str] = None    # why the last refused frame was (kept after a good one)
        self._taken_stamp: Optional[int] = None    # of the newest frame taken: stamps must increase
        self.frozen = FrozenImageWatch() if focal_px is None else FrozenImageWatch.for_focal(focal_px)
        self.frames = 0
        self.fault: Optional[str] = None
        self.fault_traceback: Optional[str] = None   # of an exception (None for a CameraError)
        self.fault_reason = "exception"              # the run's end for ``fault``: "camera" or "exception"
        self.frame_listeners: list[Callable[[Frame, dict], None]] = []
        self.odom: Pose2 = Pose2()          # the newest pose, written by the loop every cycle
        self.history: Optional[OdometryHistory] = None   # the loop's stamped odometry (Runtime sets it)
        self._pending: deque = deque()      # inline mode: (release_ns, frame, estimates)
        self._thread: Optional[threading.Thread] = None
        self._stop = threading.Event()
        # frames the vision thread began and ended processing (stages and listeners): ``wait_released``
        self._frame_done = threading.Condition()
        self._frames_begun = 0
        self._frames_ended = 0
        self.process_ms: deque = deque(maxlen=1000)

    # -- lifecycle ---------------------------------------------------------
    def start(self) -> None:
        if self.camera is not None and not self.camera.is_connected:
            self.camera.connect()
        if not self.inline and self.camera is not None:
            self._thread = threading.Thread(target=self._run, name="vbnav-vision", daemon=True)
            self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> bool:
        """Stop the vision thread; False when it had not ended after ``timeout_s`` (a frame still in a stage,
        a slow fsync): ``still_running`` then says so, and ``wait_stopped`` waits on for it."""
        self._stop.set()
        stopped = self.wait_stopped(timeout_s)
        if self.camera is not None:
            try:
                self.camera.disconnect()
            except Exception:
                pass
        return stopped

    @property
    def still_running(self) -> bool:
        """Stopped (``stop``), but the vision thread has not ended yet: its stages and frame listeners may run."""
        return self._stop.is_set() and self._thread is not None and self._thread.is_alive()

    def wait_stopped(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for a stopped vision thread to end; True when no thread runs after ``stop``."""
        if self._stop.is_set() and self._thread is not None:
            self._thread.join(timeout=timeout_s)
        return not self.still_running

    def wait_released(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` until the vision thread no longer runs a stage it held at this call: once
        stopped, until the thread has ended (``wait_stopped``); while it runs, until the frame it is processing
        now is done (a stage taken out of ``stages`` before this call is then never called again). True when
        released (also when no thread runs: inline, or no camera)."""
        if self._stop.is_set():
            return self.wait_stopped(timeout_s)
        thread = self._thread
        with self._frame_done:
            begun = self._frames_begun
            return self._frame_done.wait_for(lambda: self._frames_ended >= begun or thread is None
                                             or not thread.is_alive(), timeout_s)

    @property
    def last_frame_stamp(self) -> Optional[int]:
        f = self.last_frame
        return None if f is None else f.stamp_ns

    # -- work --------------------------------------------------------------
    def poll(self, now_ns: int, odom: Pose2) -> None:
        """Called by the loop every cycle."""
        self.odom = odom
        if not self.inline or self.camera is None:
            return
        try:
            frame = self.camera.read(0.0)
        except Exception as exc:
            self._read_failed(exc)
            return
        if frame is not None and self._take(frame, now_ns):
            fresh, results = self._process(frame)
            self._pending.append((frame.stamp_ns + self.latency_ns, frame, fresh, results, now_ns))
        while self._pending and self._pending[0][0] <= now_ns:
            _, frame, fresh, results, received_ns = self._pending.popleft()
            self._publish(frame, fresh, results, received_ns)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                frame = self.camera.read(0.05)
            except BaseException as exc:    # a SystemExit too: it ends a thread without a word
                self._read_failed(exc)
                return
            if frame is None:
                time.sleep(0.001)
                continue
            with self._frame_done:
                self._frames_begun += 1
            try:
                received_ns = self.clock.now_ns()
                if self._take(frame, received_ns):
                    fresh, results = self._process(frame)
                    self._publish(frame, fresh, results, received_ns)
            except BaseException as exc:
                # Beyond the stages (the frozen-image check, the odometry at the frame's stamp), or a SystemExit
                # from anywhere (a library's sys.exit): uncaught, it would end this thread with a line on stderr
                # at most, and the robot would wait for the stale-camera hold without a word of why.
                self.fault_traceback = traceback.format_exc()
                self.fault = f"vision thread: {exc!r}"
                return
            finally:
                with self._frame_done:
                    self._frames_ended += 1
                    self._frame_done.notify_all()

    def _read_failed(self, exc: BaseException) -> None:
        """The camera's read raised (on either path): the fault names the camera; a ``CameraError`` is the
        device's failure, anything else a bug whose traceback the run result keeps."""
        if isinstance(exc, CameraError):
            self.fault_reason = "camera"
        else:
            self.fault_traceback = traceback.format_exc()
        self.fault = f"camera {self.camera.name}: {exc!r}"

    def odometry_at(self, stamp_ns: int) -> Pose2:
        """The wheel odometry at ``stamp_ns`` (interpolated in the loop's history), else the newest pose."""
        pose = self.history.at(stamp_ns) if self.history is not None else None
        return self.odom if pose is None else pose

    def _take(self, frame: Frame, received_ns: int) -> bool:
        """Whether ``frame``, received at ``received_ns`` on the robot's clock, may be used; else ``refused``
        says why (the stale-camera hold names it)."""
        stamp, image = frame.stamp_ns, frame.image
        if not isinstance(stamp, (int, np.integer)):
            why = f"frame {frame.seq} stamped {stamp!r} ({type(stamp).__name__}), not integer nanoseconds: refused"
        elif not isinstance(image, np.ndarray):
            why = f"frame {frame.seq} has no image ({type(image).__name__} instead of an array): refused"
        elif image.size == 0:
            why = f"frame {frame.seq} has no image (an empty array of shape {image.shape}): refused"
        elif (ahead_s := (stamp - received_ns) * 1e-9) > FUTURE_STAMP_TOLERANCE_S:
            why = (f"frame {frame.seq} stamped {ahead_s:.3f} s in the future of the robot's clock (more than "
                   f"{FUTURE_STAMP_TOLERANCE_S:g} s): refused")
        elif self._taken_stamp is not None and stamp <= self._taken_stamp:
            why = (f"frame {frame.seq} stamped {stamp} ns, not after the last frame's "
                   f"{self._taken_stamp} ns (stamps must increase): refused")
        else:
            self._taken_stamp = stamp
            return True
        self.refused = self.last_refusal = why
        self.refused_frames += 1
        return False

    def _process(self, frame: Frame) -> tuple[bool, dict]:
        """(whether the frame is fresh, the stages' estimates)."""
        odom = self.odometry_at(frame.stamp_ns)
        fresh = self.frozen.fresh(frame.image, odom)
        if not fresh:
            # An old image with new odometry: no stage may take it (teach would pull heights towards far,
            # VSLAM would stop its pose while the robot drives). Their estimates age meanwhile.
            return False, {}
        out = {}
        t0 = time.perf_counter()
        for stage in self.stages:
            try:
                est = stage.process(frame, odom)
            except Exception as exc:
                self.fault = f"vision stage '{stage.kind}': {exc!r}"
                self.fault_traceback = traceback.format_exc()
                break
            if est is not None:
                out[stage.kind] = est
        self.process_ms.append((time.perf_counter() - t0) * 1e3)
        return fresh, out

    def _publish(self, frame: Frame, fresh: bool, results: dict, received_ns: int) -> None:
        self.latest.update(results)
        self.last_frame = frame
        self.refused = None
        if fresh:
            self.last_fresh_ns = min(frame.stamp_ns, received_ns)
            self.last_fresh_received_ns = received_ns
        self.frames += 1
        for fn in self.frame_listeners:
            try:
                fn(frame, results)
            except Exception as exc:
                # Naming the listener, not probing it: any callable may listen (a functools.partial has no
                # __qualname__, its repr then names it).
                self.fault = f"frame listener {getattr(fn, '__qualname__', fn)}: {exc!r}"
