"""A slow vision stage off the vision thread.

The vision pipeline runs its stages one after the other on each frame. A stage that takes longer than a
frame period (the line map's fast loop with a grown map: 60-110 ms per frame, against a camera at 15 Hz)
would make every stage after and before it skip frames: the VSLAM that localises the robot then sees
fewer frames too. ``BackgroundStage`` runs such a stage in its own thread with a one-frame mailbox:
``process`` hands the frame over and returns at once with the stage's latest finished estimate; a frame
that arrives while the worker is busy replaces the waiting one (the worker always takes the newest).

On a simulated clock (``inline``) it runs the stage in place, so a simulated run stays deterministic.
A stage that fails in its thread fails the next ``process`` call on the vision thread, naming itself:
the pipeline records the fault and the runtime stops the robot, as for any stage.
"""
from __future__ import annotations

import threading
from typing import Optional

from vbnav.control.runtime.interfaces import Estimate, StageOverlay, VisionStage
from vbnav.drivers.camera import Frame
from vbnav.vision.geometry import Pose2


class BackgroundStage(VisionStage):
    def __init__(self, stage: VisionStage, inline: bool):
        if stage.safety_critical:             # a stage whose result may lag a frame must not gate safety
            raise ValueError(f"stage '{stage.kind}' is safety critical: it must run on the vision thread")
        self.stage = stage
        self.kind = stage.kind
        self.inline = bool(inline)
        self.replaced = 0                     # frames replaced in the mailbox before the worker took them
        self.done = 0                         # frames the worker finished
        self._cv = threading.Condition()
        self._waiting: Optional[tuple[Frame, Pose2]] = None
        self._latest: Optional[Estimate] = None
        self._error: Optional[BaseException] = None
        self._stop = False
        self._thread: Optional[threading.Thread] = None

    def start(self) -> None:
        self.stage.start()
        if not self.inline and self._thread is None:
            self._thread = threading.Thread(target=self._run, name=f"vbnav-{self.kind}", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self.stage.stop()

    def process(self, frame: Frame, odom: Pose2) -> Optional[Estimate]:
        if self._error is not None:
            raise RuntimeError(f"stage '{self.kind}' failed in its own thread: {self._error!r}") from self._error
        if self.inline or self._thread is None:
            return self.stage.process(frame, odom)
        with self._cv:
            if self._waiting is not None:
                self.replaced += 1
            self._waiting = (frame, odom)
            self._cv.notify()
            return self._latest

    def overlay(self, estimate: Optional[Estimate]) -> Optional[StageOverlay]:
        return self.stage.overlay(estimate)

    def _run(self) -> None:
        while True:
            with self._cv:
                while self._waiting is None and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                frame, odom = self._waiting
                self._waiting = None
            try:
                est = self.stage.process(frame, odom)
            except BaseException as exc:      # handed to the vision thread at its next call
                self._error = exc
                return
            with self._cv:
                self._latest = est
                self.done += 1
