"""Telemetry: the loop drops snapshots, a background thread serialises and publishes them.

The loop thread's whole cost per cycle is ``offer_state(sample)``: one integer
comparison on most cycles and, when a state message is due, a bounded
``SimpleQueue.put`` of the already-built tuple. No JSON, no network, no lock held
across I/O, never a wait: when the queue is full (the publisher thread is stuck)
the sample is dropped and counted. Events (command answers, safety changes) have
``EVENT_RESERVE`` places beyond the routine ones, so states and images never crowd
them out; an event dropped beyond those is counted by kind and announced by an
``events_dropped`` event as soon as the publisher thread runs again. A slow or absent subscriber cannot delay a
cycle because every zenoh publisher here uses congestion control DROP.

State messages are decimated by the *sample's* stamp (the loop's scheduled
tick), so a run under the simulated clock publishes and records the same
sequence as a real-time run, at exactly ``state_rate_hz`` of loop time.

Keys (``<robot>`` is ``robot.name``; every payload is a JSON object with
``schema`` and ``version``; docs/telemetry.md lists every field):

- ``vbnav/<robot>/state``  ``vbnav.state``  at ``telemetry.state_rate_hz``
- ``vbnav/<robot>/events`` ``vbnav.event``  mode changes, faults, safety stops, rejected commands
- ``vbnav/<robot>/image``  ``vbnav.image``  decimated JPEG frames (``telemetry.image_rate_hz`` > 0)
"""
from __future__ import annotations

import base64
import collections
import json
import math
import queue
import threading
import time
from typing import Any, Callable, NamedTuple, Optional, Sequence

from vbnav.vision.geometry import Pose2

STATE_SCHEMA, EVENT_SCHEMA, IMAGE_SCHEMA = "vbnav.state", "vbnav.event", "vbnav.image"
SCHEMA_VERSION = 1
QUEUE_LIMIT = 256
EVENT_RESERVE = 1024     # places beyond QUEUE_LIMIT only events may take: routine telemetry never crowds them out
CLOSE_WAIT_S = 10.0      # at the end of a run, how long the publisher thread may take to publish what is queued


def keys(robot: str) -> dict[str, str]:
    """The zenoh key expressions of one robot."""
    p = f"vbnav/{robot}"
    return {"state": f"{p}/state", "events": f"{p}/events", "image": f"{p}/image",
            "recent_events": f"{p}/events/recent",
            "cmd": f"{p}/cmd/**", "estop": f"{p}/cmd/estop", "resume": f"{p}/cmd/resume",
            "teleop": f"{p}/cmd/teleop", "mode": f"{p}/cmd/mode"}


class StateSample(NamedTuple):
    """One loop cycle as the loop sees it; built on the loop thread only when ``state_due``.

    Poses are ``Pose2``-like (``.x .z .theta``) or (x, z, theta) tuples or None.
    """

    stamp_ns: int                   # scheduled tick time of the cycle (loop clock)
    cycle: int
    mode: str                       # idle | teach | repeat | teleop | goto | scripted ...
    safety: str                     # ok | stopped | estop
    faults: tuple = ()              # active fault / stop-cause strings
    odom: Any = None
    vbc: Any = None
    vslam: Any = None
    keyframe: Optional[int] = None
    cmd_left: float = 0.0           # wheel command written this cycle, rad/s
    cmd_right: float = 0.0
    meas_left: float = 0.0          # measured wheel speed, rad/s
    meas_right: float = 0.0
    linear: float = 0.0             # commanded body twist after safety, m/s
    angular: float = 0.0            # rad/s
    compute_ns: int = 0             # time the cycle took (read -> write)
    lateness_ns: int = 0            # wake-up lateness against the tick
    overruns: int = 0               # cycles missed since start
    route: Optional[str] = None
    drive_state: Any = None         # the drive's DriveState
    drive_faults: tuple = ()        # its DriveFaults
    latched_ns: Optional[int] = None   # when the newest latched stop began (what a resume names)


def _num(x) -> Optional[float]:
    """A JSON-safe float: NaN and infinities (a failed sensor read) become null, not invalid JSON."""
    x = float(x)
    return x if math.isfinite(x) else None


def _pose(p) -> Optional[dict]:
    if p is None:
        return None
    if isinstance(p, Pose2):
        x, z, th = p.x, p.z, p.theta
    else:                       # (x, z, theta), as tests and replays give it
        x, z, th = p
    x, z, th = _num(x), _num(z), _num(th)
    if x is None or z is None or th is None:
        return None
    return {"x": round(x, 6), "z": round(z, 6), "theta": round(th, 6)}


def state_message(robot: str, seq: int, s: StateSample, rate_hz: float) -> dict:
    """The ``vbnav.state`` JSON object for one sample (publisher thread)."""
    return {
        "schema": STATE_SCHEMA, "version": SCHEMA_VERSION, "robot": robot, "seq": seq,
        "stamp_ns": int(s.stamp_ns), "cycle": int(s.cycle),
        "mode": s.mode, "route": s.route,
        "safety": {"state": s.safety, "faults": list(s.faults), "latched_ns": s.latched_ns},
        "drive": {"state": s.drive_state.value if s.drive_state is not None else None,
                  "faults": [f.as_dict() for f in s.drive_faults]},
        "pose": {"odom": _pose(s.odom), "vbc": _pose(s.vbc), "vslam": _pose(s.vslam)},
        "keyframe": s.keyframe,
        "wheels": {"cmd": {"left": _num(s.cmd_left), "right": _num(s.cmd_right)},
                   "meas": {"left": _num(s.meas_left), "right": _num(s.meas_right)}},
        "twist": {"linear": _num(s.linear), "angular": _num(s.angular)},
        "loop": {"rate_hz": rate_hz, "compute_ms": s.compute_ns * 1e-6, "lateness_ms": s.lateness_ns * 1e-6,
                 "overruns": int(s.overruns)},
    }


def event_message(robot: str, seq: int, stamp_ns: int, kind: str, fields: dict) -> dict:
    msg = {"schema": EVENT_SCHEMA, "version": SCHEMA_VERSION, "robot": robot, "seq": seq,
           "stamp_ns": int(stamp_ns), "kind": kind}
    msg.update(fields)
    return msg


def encode_jpeg(image, width: int, quality: int) -> tuple[bytes, int, int]:
    """Scale to ``width`` (keeping the aspect) and JPEG-encode; returns (jpeg, width, height)."""
    import cv2
    h, w = image.shape[:2]
    if w > width:
        image = cv2.resize(image, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes(), image.shape[1], image.shape[0]


class Sink:
    """Where serialised telemetry goes (zenoh, an MCAP recording). Called on the publisher thread only."""

    def state(self, stamp_ns: int, payload: bytes, msg: dict) -> None: ...
    def event(self, stamp_ns: int, payload: bytes, msg: dict) -> None: ...
    def image(self, stamp_ns: int, payload: bytes, msg: dict, jpeg: bytes) -> None: ...

    def annotations(self, stamp_ns: int, overlay) -> None:
        """What the vision stages saw in the image just sent (foxglove_channels.Overlay); Foxglove sinks only."""

    def foxglove(self, stamp_ns: int, topic: str, build: Callable[[int], Any]) -> None:
        """A message only Foxglove sinks carry (taught route, landmarks): ``build(stamp_ns)`` makes it."""

    def close(self) -> None: ...


class ZenohSink(Sink):
    """Publishes on a robot's keys. Telemetry: express (no batching delay), congestion control DROP.

    Also answers queries on ``vbnav/<robot>/events/recent`` with the last ``history`` events, so a
    monitor started late still shows what happened (a ``vbnav.events.recent`` object).
    """

    def __init__(self, session, robot: str, history: int = 20):
        import zenoh
        k = keys(robot)
        opts = dict(express=True, congestion_control=zenoh.CongestionControl.DROP)
        self._state = session.declare_publisher(k["state"], **opts)
        # Events are rare and matter more: reliable, but still never block the publisher thread.
        self._events = session.declare_publisher(k["events"], reliability=zenoh.Reliability.RELIABLE, **opts)
        self._image = session.declare_publisher(k["image"], **opts)
        self._recent: collections.deque = collections.deque(maxlen=history)
        self._recent_key = k["recent_events"]
        self._queryable = session.declare_queryable(self._recent_key, self._on_query)

    def _on_query(self, query) -> None:  # zenoh thread
        events = [json.loads(p) for p in list(self._recent)]
        body = {"schema": "vbnav.events.recent", "version": SCHEMA_VERSION, "events": events}
        try:
            query.reply(self._recent_key, json.dumps(body, separators=(",", ":")))
        except Exception:
            pass

    def state(self, stamp_ns, payload, msg):
        self._state.put(payload)

    def event(self, stamp_ns, payload, msg):
        self._recent.append(payload)
        self._events.put(payload)

    def image(self, stamp_ns, payload, msg, jpeg):
        self._image.put(payload)

    def close(self):
        for p in (self._queryable, self._state, self._events, self._image):
            try:
                p.undeclare()
            except Exception:
                pass


class TelemetryPublisher:
    """Feeds sinks from a background thread.

    Loop thread (cheap, never blocks): ``state_due(stamp_ns)``, ``offer_state(sample)``.
    Any thread: ``event(kind, **fields)``, ``offer_image(image, stamp_ns)``.
    Lifecycle: ``start()``, ``close()`` (drains what is queued, then closes the sinks).
    """

    def __init__(self, robot: str, sinks: Sequence[Sink], state_rate_hz: float = 20.0,
                 loop_rate_hz: float = 0.0, image_rate_hz: float = 0.0, image_width: int = 320,
                 jpeg_quality: int = 70, now_ns: Callable[[], int] = time.monotonic_ns):
        self.robot = robot
        self.sinks = list(sinks)
        self.state_rate_hz = float(state_rate_hz)
        self.loop_rate_hz = float(loop_rate_hz)
        self._state_period_ns = int(round(1e9 / state_rate_hz))
        self._image_period_ns = int(round(1e9 / image_rate_hz)) if image_rate_hz > 0 else 0
        self._image_width, self._jpeg_quality = image_width, jpeg_quality
        self._next_state_ns: Optional[int] = None
        # Loop stamps are wake-up times that jitter after their tick: accept a sample up to half a
        # loop period before the grid point so jitter never pushes a message to the next cycle.
        self._tol_ns = int(0.5e9 / loop_rate_hz) if loop_rate_hz > 0 else 0
        self._next_image_ns: Optional[int] = None
        self._now_ns = now_ns
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._thread: Optional[threading.Thread] = None
        self._closed = False
        self._busy: Optional[Sink] = None    # the sink the publisher thread is in (close names one that blocks)
        self.dropped = 0            # samples not queued because the queue was full
        self._lock = threading.Lock()
        self._events_unsaid: collections.Counter = collections.Counter()   # events dropped, by kind, not yet said
        self.sink_errors = 0        # messages, overlays or scenes lost to an error (said when the run ends)
        self.first_error: Optional[Exception] = None    # the first of them, for the end-of-run warning
        self.sink_failures: dict = {}   # sink -> its first error (a full disk under a recording, say)
        self.published = {"state": 0, "event": 0, "image": 0}
        self._seq = {"state": 0, "event": 0, "image": 0}

    # ---- loop thread -------------------------------------------------------------------
    def state_due(self, stamp_ns: int) -> bool:
        """True when a state sample stamped ``stamp_ns`` would be published (saves building it)."""
        nxt = self._next_state_ns
        return nxt is None or stamp_ns >= nxt - self._tol_ns

    def offer_state(self, sample: StateSample) -> bool:
        """Queue ``sample`` if a state message is due at its stamp. Never blocks; returns whether queued."""
        stamp = sample.stamp_ns
        nxt = self._next_state_ns
        if nxt is not None and stamp < nxt - self._tol_ns:
            return False
        period = self._state_period_ns
        # Stay on the grid start + k*period; after a stall, jump to the next grid point ahead.
        if nxt is None:
            self._next_state_ns = stamp + period
        else:
            self._next_state_ns = nxt + period * (max(0, stamp - nxt) // period + 1)
        return self._put(("state", sample))

    # ---- any thread ----------------------------------------------------------------------
    def event(self, kind: str, stamp_ns: Optional[int] = None, **fields) -> bool:
        """Publish an event (mode change, fault, safety stop, rejected command ...). Never blocks."""
        return self._put(("event", self._now_ns() if stamp_ns is None else stamp_ns, kind, fields))

    def image_due(self, stamp_ns: int) -> bool:
        if not self._image_period_ns:
            return False
        return self._next_image_ns is None or stamp_ns >= self._next_image_ns

    def offer_image(self, image, stamp_ns: int, seq: int = 0, overlay=None) -> bool:
        """Queue a frame for JPEG encoding if one is due (the array must not be modified afterwards).

        overlay: what the vision stages saw in it (foxglove_channels.Overlay, in the frame's pixels)."""
        if not self.image_due(stamp_ns):
            return False
        nxt, period = self._next_image_ns, self._image_period_ns
        self._next_image_ns = stamp_ns + period if nxt is None else nxt + period * ((stamp_ns - nxt) // period + 1)
        return self._put(("image", stamp_ns, seq, image, overlay))

    def offer_foxglove(self, stamp_ns: int, topic: str, build: Callable[[int], Any]) -> bool:
        """Queue a Foxglove-only message (``build(stamp_ns)`` runs on the publisher thread). Never blocks."""
        return self._put(("foxglove", stamp_ns, topic, build))

    def _put(self, item) -> bool:
        event = item[0] == "event"
        if self._closed or self._q.qsize() >= QUEUE_LIMIT + (EVENT_RESERVE if event else 0):
            self.dropped += 1
            if event and not self._closed:
                with self._lock:
                    self._events_unsaid[item[2]] += 1
            return False
        self._q.put(item)
        return True

    # ---- lifecycle -----------------------------------------------------------------------
    def start(self) -> "TelemetryPublisher":
        self._thread = threading.Thread(target=self._run, name="vbnav-telemetry", daemon=True)
        self._thread.start()
        return self

    def close(self, timeout_s: Optional[float] = None) -> None:
        """Publish what is queued, stop the thread and close the sinks (idempotent)."""
        if self._closed:
            return
        timeout_s = CLOSE_WAIT_S if timeout_s is None else timeout_s
        self._closed = True
        self._q.put(None)
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():  # a sink hangs: closing it under the thread's feet would corrupt it
                self.sink_errors += 1
                busy = self._busy
                where = type(busy).__name__ if busy is not None else "a sink"
                for s in self.sinks:     # none is closed: a recording stays PATH.part, which is said
                    self._sink_failed(s, TimeoutError(f"not closed: the telemetry thread was still in {where} "
                                                      f"after {timeout_s:g} s"))
                return
        else:
            self._drain()
        for s in self.sinks:
            try:
                s.close()
            except Exception as exc:
                self._sink_failed(s, exc)

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()

    # ---- publisher thread ----------------------------------------------------------------
    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            self._handle(item)
            self._say_dropped_events()

    def _drain(self) -> None:
        while True:
            try:
                item = self._q.get_nowait()
            except queue.Empty:
                return
            if item is not None:
                self._handle(item)
                self._say_dropped_events()

    def _handle(self, item) -> None:
        try:
            kind = item[0]
            if kind == "state":
                sample = item[1]
                msg = state_message(self.robot, self._next_seq("state"), sample, self.loop_rate_hz)
                self._emit("state", sample.stamp_ns, msg)
            elif kind == "event":
                _, stamp, ekind, fields = item
                msg = event_message(self.robot, self._next_seq("event"), stamp, ekind, fields)
                self._emit("event", stamp, msg)
            elif kind == "foxglove":
                _, stamp, topic, build = item
                self._each_sink(lambda s: s.foxglove(stamp, topic, build))
            elif kind == "image":
                _, stamp, seq, image, overlay = item
                jpeg, w, h = encode_jpeg(image, self._image_width, self._jpeg_quality)
                msg = {"schema": IMAGE_SCHEMA, "version": SCHEMA_VERSION, "robot": self.robot,
                       "seq": self._next_seq("image"), "frame_seq": int(seq), "stamp_ns": int(stamp),
                       "format": "jpeg", "width": w, "height": h,
                       "data": base64.b64encode(jpeg).decode("ascii")}
                self._emit("image", stamp, msg, jpeg)
                if overlay is not None:
                    scaled = overlay.scaled(w / image.shape[1])
                    self._each_sink(lambda s: s.annotations(stamp, scaled))
        except Exception as exc:  # a bad sample must never kill telemetry
            self.count_error(exc)

    def _say_dropped_events(self) -> None:
        """Publisher thread: the events dropped for a full queue since the last time, announced."""
        if not self._events_unsaid:
            return
        with self._lock:
            unsaid, self._events_unsaid = self._events_unsaid, collections.Counter()
        n = sum(unsaid.values())
        listed = ", ".join(f"{k} x{c}" for k, c in unsaid.most_common())
        message = (f"{n} events were not published ({listed}): the telemetry queue was full (a sink blocked); a "
                   f"sender waiting for the answer of a command may wait in vain")
        stamp = self._now_ns()
        try:
            self._emit("event", stamp, event_message(self.robot, self._next_seq("event"), stamp, "events_dropped",
                                                     {"count": n, "kinds": dict(unsaid), "message": message}))
        except Exception as exc:
            self.count_error(exc)

    def _each_sink(self, call: Callable[[Sink], None]) -> None:
        """``call`` on every sink; one that raises is counted, one that blocks is named by ``close``."""
        for s in self.sinks:
            self._busy = s
            try:
                call(s)
            except Exception as exc:
                self._sink_failed(s, exc)
        self._busy = None

    def count_error(self, exc: Exception) -> None:
        """Something lost to ``exc`` (a message, an overlay, a scene): counted, and the first error kept, so the
        run's end can say what went wrong (``TelemetryLink.close``)."""
        self.sink_errors += 1
        if self.first_error is None:
            self.first_error = exc

    def _sink_failed(self, sink, exc: Exception) -> None:
        self.count_error(exc)
        self.sink_failures.setdefault(sink, exc)

    def _next_seq(self, kind: str) -> int:
        self._seq[kind] += 1
        return self._seq[kind]

    def _emit(self, kind: str, stamp: int, msg: dict, jpeg: bytes = b"") -> None:
        payload = json.dumps(msg, separators=(",", ":"), allow_nan=False, default=str).encode()
        if kind == "state":
            self._each_sink(lambda s: s.state(stamp, payload, msg))
        elif kind == "event":
            self._each_sink(lambda s: s.event(stamp, payload, msg))
        else:
            self._each_sink(lambda s: s.image(stamp, payload, msg, jpeg))
        self.published[kind] += 1


def decode(payload: bytes | str) -> dict:
    """Parse a telemetry payload (for monitors and tests); raises ValueError if it is not one of ours."""
    msg = json.loads(payload)
    if not isinstance(msg, dict) or not str(msg.get("schema", "")).startswith("vbnav."):
        raise ValueError("not a vbnav telemetry message")
    return msg
