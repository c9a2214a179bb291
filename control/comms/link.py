"""Connects a Runtime to telemetry, network commands and recording.

``TelemetryLink.attach(runtime, cfg, record=PATH)`` validates the ``telemetry:``
section, opens the robot's zenoh session (loopback only unless configured
otherwise, see network.py), and hooks into the runtime through its public
extension points only:

- ``runtime.cycle_observers``: once per cycle, after the wheels were written,
  a ``StateSample`` is built *only when a state message is due* and dropped into
  the publisher's queue (no JSON, no network on the loop thread);
- ``runtime.safety.listeners``: every safety event (trip, hold, release, reset,
  rejected command, drive reconnected) becomes a ``vbnav/<robot>/events`` message;
- ``runtime.submit``: validated network commands (estop, resume, teleop, mode)
  go to the loop's command mailbox, which the loop drains at the start of its
  next cycle and hands to the controller (the link never decides what a command
  does); ``runtime.command_listeners``: the ``command`` event is published
  once a command took effect, with its cycle, arrival time and the sender's
  ``ack`` id (preceded by ``mode_unchanged`` when a mode command asked for the
  current mode); ``runtime.command_observers`` (first in the list) notes the command
  being applied, so a ``command_rejected`` the loop raises for it carries the ack too;
- ``pipeline.frame_listeners``: decimated camera frames for ``.../image``, with what the vision
  stages saw in them (comms/overlays.py), and the 3D scene (taught route, VSLAM landmarks) at
  ``telemetry.live_view.scene_rate_hz``; the line map's segments at that rate too, but only when the map
  changed (and once more at ``close`` if it changed since, so a recording ends with the final map);
- ``telemetry.live_view.enabled``: the Foxglove WebSocket server (comms/live_view.py), a sink like
  the recording, whose Teleop panel submits to the same ``CommandInbox`` as zenoh commands.

``close(result)`` publishes the ``run_end`` event, drains the queue, finishes
the recording and closes the session.
"""
from __future__ import annotations

import sys
import time
import weakref
from typing import Optional

from vbnav.control.comms.operator_commands import ACK_IN_PAYLOAD, CommandInbox, CommandSubscriber, limits_from_config
from vbnav.control.config.telemetry import TelemetryConfig
from vbnav.control.comms.network import open_session, robot_session_config
from vbnav.control.comms.telemetry import StateSample, TelemetryPublisher, ZenohSink
from vbnav.control.runtime.interfaces import Estimate, PoseFix
from vbnav.vision.geometry import Pose2


# The ack id of a payload the robot refused before parsing it (vbnav send puts "ack" first, so it is in the
# excerpt even when the payload is long).


class _Borrowed:
    """A sink shared with other runs: written to, flushed, never closed by this link."""

    def __init__(self, sink):
        self._sink = sink

    def state(self, *a):
        self._sink.state(*a)

    def event(self, *a):
        self._sink.event(*a)

    def image(self, *a):
        self._sink.image(*a)

    def annotations(self, *a):
        self._sink.annotations(*a)

    def foxglove(self, *a):
        self._sink.foxglove(*a)

    def close(self):
        pass


def attach(cfg, runtime, record: Optional[str] = None, **kw) -> TelemetryLink:
    """``TelemetryLink.attach`` with the argument order of the teach/repeat commands."""
    return TelemetryLink.attach(runtime, cfg, record=record, **kw)


def _estimate_pose(est: Optional[Estimate]) -> Optional[Pose2]:
    """The planar pose in a trusted Estimate: its value if a Pose2, ``value.pose`` if a PoseFix (VBCFix,
    VslamFix), else None (a teach keyframe, an obstacle report)."""
    if est is None or not est.ok:
        return None
    v = est.value
    if isinstance(v, Pose2):
        return v
    return v.pose if isinstance(v, PoseFix) else None


def _verifier(tcfg: TelemetryConfig):
    """The signature check of incoming commands when ``telemetry.shared_secret_file`` is set, else None."""
    if tcfg.shared_secret_file is None:
        return None
    from vbnav.control.comms.command_auth import CommandVerifier, read_secret
    try:
        return CommandVerifier(read_secret(tcfg.shared_secret_file)).verify
    except ValueError as exc:  # checked at load; the file changed since
        from vbnav.control.config import ConfigError
        raise ConfigError(f"telemetry.shared_secret_file: {exc}") from None


def _route_server(session, cfg, verify, runtime):
    """Serve ``controller.routes_dir`` to the network (pull by anyone admitted, push by operators only).

    A push never replaces the route the operator controller is teaching (``send mode teach --route NAME``), and
    never installs a route this robot's repeat refuses (its camera and mount, ``config_repeat_refusal``)."""
    from vbnav.control.comms.route_transfer import RouteServer
    from vbnav.control.route import config_repeat_refusal, routes_root

    def busy(name: str) -> Optional[str]:     # the route thread reads two strings the loop sets
        if runtime.controller.teaching_route == name:
            return f"route {name!r} is being taught on this robot; push it after `mode idle`"
        return None
    return RouteServer(session, cfg.robot.name, routes_root(cfg.controller.routes_dir, cfg.source), verify=verify,
                       busy=busy, refusal=lambda route: config_repeat_refusal(route, cfg))


class TelemetryLink:
    def __init__(self, runtime, tcfg: TelemetryConfig, publisher: TelemetryPublisher, session=None,
                 recorder=None):
        self.runtime = runtime
        self.tcfg = tcfg
        self.publisher = publisher
        self.session = session
        self.recorder = recorder
        self.commands: Optional[CommandSubscriber] = None
        self.live_view = None            # comms/live_view.LiveView when telemetry.live_view.enabled
        self.routes = None               # the RouteServer of controller.routes_dir (comms/route_transfer.py)
        self._taught: list = []          # odometry poses of the keyframes of the latest teach in this run
        self._taught_by = None           # weakref to the teach stage they come from
        self._next_scene_ns: Optional[int] = None
        self._map_revision: Optional[int] = None    # of the line map last offered
        self.inbox: CommandInbox
        self._mode: Optional[str] = None
        self._applying = None            # the command the loop is applying (loop thread)
        self._closed = False
        self._network_sink = None        # the ZenohSink: a put it raised means the session is gone
        self._network_lost = False
        # The route being taught or repeated, for the state's ``route`` (vbnav teach / repeat set it; an
        # operator-mode run's controller says its own, ``followed_route``). It was never filled in.
        self.route: Optional[str] = None
        self._borrowed: Optional[_Borrowed] = None   # the recording shared with other runs (not closed here)
        self.recording_error: Optional[str] = None   # the recording failed (set by close, said on stderr)
        self.telemetry_errors = 0        # publisher.sink_errors when the run ended (set by close, said on stderr)

    # ---- construction ----------------------------------------------------------------------
    @classmethod
    def attach(cls, runtime, cfg, record: Optional[str] = None, recorder=None, network: bool = True,
               segment: str = "run", record_overwrite: bool = False) -> "TelemetryLink":
        """Validate, open and hook everything into ``runtime``; raises ConfigError / ConnectionError.

        record: MCAP path for this run. recorder: an open McapRecorder shared by several runs (it gets a
        new segment and is not closed by this link). network: False skips zenoh even when enabled.
        record_overwrite: replace an existing recording at ``record`` (refused otherwise).
        """
        tcfg = cfg.telemetry
        robot = cfg.robot.name
        sinks, session, network_sink = [], None, None
        verify = _verifier(tcfg) if tcfg.enabled and network else None   # before anything is opened
        borrowed = None
        if recorder is not None:
            recorder.new_segment(segment)
            borrowed = _Borrowed(recorder)
            sinks.append(borrowed)
            recorder = None
        elif record:  # first: a bad path fails before any network resource is opened
            from vbnav.control.comms.recording import McapRecorder
            recorder = McapRecorder(record, robot, metadata={"config": cfg.source or "",
                                                             "loop_rate_hz": cfg.loop.rate_hz,
                                                             "state_rate_hz": tcfg.state_rate_hz},
                                    overwrite=record_overwrite)
            sinks.append(recorder)
        if tcfg.enabled and network:
            conf = robot_session_config(tcfg, robot)
            try:
                session = open_session(conf)
            except Exception as exc:
                if recorder is not None:
                    recorder.discard()          # the run never starts: an earlier recording at PATH is kept
                raise ConnectionError(f"telemetry: cannot open the zenoh session listening on "
                                      f"{', '.join(tcfg.listen) or '(nothing)'}: {exc} (another vbnav run on the "
                                      f"same port? set telemetry.listen)") from None
            network_sink = ZenohSink(session, robot)
            sinks.append(network_sink)
        clock = runtime.clock
        live_view, holder = None, {}
        if session is not None and tcfg.live_view.enabled:
            from vbnav.control.comms.live_view import LiveView
            wall_offset = time.time_ns() - clock.now_ns()
            try:
                live_view = LiveView(tcfg, robot, submit_teleop=lambda k, p: holder["link"].inbox.submit(k, p),
                                     refuse=lambda k, r, p: holder["link"].inbox.refuse(k, r, p, stream=True),
                                     to_wall_ns=lambda t: t + wall_offset)
            except Exception as exc:
                for s in sinks:
                    (s.discard if s is recorder else s.close)()     # as above: the run never starts
                session.close()
                raise ConnectionError(f"telemetry.live_view: cannot start the Foxglove server on "
                                      f"{tcfg.live_view.host}:{tcfg.live_view.port}: {exc}") from None
            sinks.append(live_view)
        publisher = TelemetryPublisher(robot, sinks, state_rate_hz=tcfg.state_rate_hz,
                                       loop_rate_hz=cfg.loop.rate_hz, image_rate_hz=tcfg.image_rate_hz,
                                       image_width=tcfg.image_width, jpeg_quality=tcfg.jpeg_quality,
                                       now_ns=clock.now_ns)
        link = cls(runtime, tcfg, publisher, session, recorder)
        link._borrowed = borrowed
        link.live_view = live_view
        link._network_sink = network_sink
        holder["link"] = link
        # The inbox also takes commands from local sources (tests, a future local console).
        link.inbox = CommandInbox(limits_from_config(cfg), deliver=lambda cmd: link.runtime.submit(cmd),
                                  on_reject=link._on_reject, now_ns=clock.now_ns,
                                  shared_clock=None if verify is None else time.monotonic_ns)
        if session is not None:
            link.commands = CommandSubscriber(session, robot, link.inbox, verify=verify)
            link.routes = _route_server(session, cfg, verify, runtime)
        runtime.command_observers.insert(0, link._on_command_start)
        runtime.command_listeners.append(link._on_command_applied)
        runtime.pending_listeners.append(link._on_command_pending)
        runtime.cycle_observers.append(link._on_cycle)
        runtime.safety.listeners.append(link._on_safety)
        if runtime.pipeline is not None:
            runtime.pipeline.frame_listeners.append(link._on_frame)
        publisher.start()
        publisher.event("run_start", controller=runtime.controller.name,
                        loop_rate_hz=cfg.loop.rate_hz, listen=list(tcfg.listen) if session is not None else [],
                        recording=str(record) if record else None, segment=segment)
        return link

    # ---- runtime hooks (loop thread) -------------------------------------------------------
    def _on_cycle(self, rt, ctx, twist, wheel_command) -> None:
        self._applying = None   # a command refused in this cycle: later refusals are not its answer
        failed = self.publisher.sink_failures.get(self._network_sink) if self._network_sink is not None else None
        if failed is not None and not self._network_lost:
            # zenoh raises on a put only when the session is unusable (closed, broken); a peer gone is no error
            self._network_lost = True
            rt.end_run("network", f"telemetry: the zenoh session failed ({failed!r}): no network command, an "
                                  f"estop included, can reach the robot any more")
        mode = rt.controller.name
        if mode != self._mode:
            self.publisher.event("mode_change", stamp_ns=ctx.now_ns, mode=mode, previous=self._mode)
            self._mode = mode
        pub = self.publisher
        if not pub.state_due(ctx.now_ns):
            return
        safety = rt.safety
        if safety.may_move:
            state = "ok"
        elif "estop" in safety.latched:
            state = "estop"
        else:
            state = "stopped"
        est = ctx.estimates
        vbc, vslam = est.get("vbc"), est.get("vslam")
        keyframe = None
        if vbc is not None:
            keyframe = vbc.info.get("keyframe") if isinstance(vbc.info, dict) else None
        timing = rt.loop.timing
        i = (timing.cycles - 1) % timing.capacity if timing.cycles else 0
        wheels = ctx.wheels
        pub.offer_state(StateSample(
            ctx.now_ns, ctx.cycle, mode, state, tuple(safety.reasons()) if not safety.may_move else (),
            ctx.odom, _estimate_pose(vbc), _estimate_pose(vslam), keyframe,
            wheel_command[0], wheel_command[1], wheels.velocity[0], wheels.velocity[1],
            twist.v, twist.w, int(timing.compute[i]), int(timing.lateness[i]), timing.overruns,
            route=self.route if self.route is not None else rt.controller.followed_route,
            drive_state=wheels.drive_state, drive_faults=wheels.faults, latched_ns=safety.latched_ns))

    def _on_command_start(self, rt, cmd, now_ns: int) -> None:
        """First observer of every command: a refusal raised while it is applied answers its ``ack``."""
        self._applying = cmd

    def _on_safety(self, ev) -> None:
        if ev.kind == "drive_reconnected":   # news, not a stop: its own event kind
            self.publisher.event("drive_reconnected", stamp_ns=ev.stamp_ns, cause=ev.cause, message=ev.message)
        elif ev.kind == "rejected":
            fields = dict(command=ev.cause, reason=ev.message)
            cmd = self._applying
            if cmd is not None and cmd.kind == ev.cause and cmd.ack:   # refused while being applied
                fields["ack"] = cmd.ack
            self.publisher.event("command_rejected", stamp_ns=ev.stamp_ns, **fields)
        else:
            self.publisher.event(f"safety_{ev.kind}", stamp_ns=ev.stamp_ns, cause=ev.cause, message=ev.message)

    def _on_frame(self, frame, results) -> None:
        """Vision thread (loop thread on the simulated clock), right after the stages ran on ``frame``.

        A failure here must not become a pipeline fault (which stops the robot): what to show is telemetry,
        so an error costs the overlay or the scene of this frame and is counted in ``publisher.sink_errors``
        (said when the run ends)."""
        try:
            self._offer_frame(frame, results)
        except Exception as exc:
            self.publisher.count_error(exc)

    def _offer_frame(self, frame, results) -> None:
        from vbnav.control.comms import foxglove_channels as fc
        from vbnav.control.comms.overlays import frame_overlay, landmarks, route_keyframes
        pub, stages, stamp = self.publisher, self.runtime.pipeline.stages, frame.stamp_ns
        teach = results.get("teach")
        if teach is not None and teach.value is not None:     # a Keyframe, on the frames that emit one
            # The route being taught: an operator run teaches many, one after another, for months; each
            # new teach stage starts its own list (the scene shows the latest teach, not all of them).
            stage = next((st for st in stages if st.kind == "teach"), None)
            by = self._taught_by
            if stage is not None and (by is None or by() is not stage):
                self._taught, self._taught_by = [], weakref.ref(stage)
            self._taught.append(teach.value.odom)
        if pub.image_due(stamp):
            pub.offer_image(frame.image, stamp, frame.seq, overlay=frame_overlay(stages, results))
        if self._next_scene_ns is not None and stamp < self._next_scene_ns:
            return
        self._next_scene_ns = stamp + int(1e9 / self.tcfg.live_view.scene_rate_hz)
        route = route_keyframes(stages) or (("teaching", list(self._taught)) if self._taught else None)
        if route is not None:
            name, poses = route
            pub.offer_foxglove(stamp, "/vbnav/route", lambda t: fc.route_message(t, name, poses))
        points = landmarks(stages)
        if points is not None:
            pub.offer_foxglove(stamp, "/vbnav/landmarks", lambda t: fc.landmarks_message(t, points))
        self._offer_line_map(stamp)

    def _offer_line_map(self, stamp: int) -> None:
        """The line map's segments if it changed since they were last offered (a dropped offer is retried)."""
        from vbnav.control.comms import foxglove_channels as fc
        from vbnav.control.comms.overlays import line_map_scene
        pipeline = self.runtime.pipeline
        scene = None if pipeline is None else line_map_scene(pipeline.stages)
        if scene is None or scene.revision == self._map_revision:
            return
        if self.publisher.offer_foxglove(stamp, "/vbnav/map/lines", lambda t: fc.line_map_message(
                t, scene.P, scene.verified, scene.hypothesis)):
            self._map_revision = scene.revision

    def _on_command_pending(self, rt, cmd, now_ns: int) -> None:
        """``command_pending``: the controller took the command and finishes it later (a mode switch loading
        its route); its ``command`` or ``command_rejected`` follows."""
        self._applying = None
        fields = dict(command=cmd.kind, args=list(cmd.args), sender=cmd.source, cycle=rt.cycle,
                      arrival_ns=cmd.arrival_ns)
        if cmd.ack:
            fields["ack"] = cmd.ack
        self.publisher.event("command_pending", stamp_ns=now_ns, **fields)

    def _on_command_applied(self, rt, cmd, outcome, now_ns: int) -> None:
        """``command``: published once the loop applied it. Teleop streams at 10-20 Hz: only a teleop that
        asks for an answer (``ack``) is news."""
        self._applying = None
        if cmd.kind == "mode" and outcome.unchanged:
            self.publisher.event("mode_unchanged", stamp_ns=now_ns, mode=rt.controller.name)
        if cmd.kind == "teleop" and not cmd.ack:
            return
        fields = dict(command=cmd.kind, args=list(cmd.args), sender=cmd.source, cycle=rt.cycle,
                      arrival_ns=cmd.arrival_ns)
        if outcome.reason:
            fields["note"] = outcome.reason
        elif cmd.kind == "mode" and outcome.unchanged:
            # 'applied' alone reads as a switch done (a repeat restarted): vbnav send prints the note, not the
            # mode_unchanged event
            fields["note"] = f"mode {rt.controller.name} was already running: nothing changed"
        if cmd.ack:
            fields["ack"] = cmd.ack
        self.publisher.event("command", stamp_ns=now_ns, **fields)

    # ---- network command thread ------------------------------------------------------------
    def _on_reject(self, kind: str, reason: str, excerpt: str, verified: bool = True) -> None:
        fields = dict(command=kind, reason=reason, payload=excerpt)
        m = ACK_IN_PAYLOAD.search(excerpt)
        if m:       # a payload whose signature failed may be a copy of an operator's: its ack is no answer to it
            fields["ack" if verified else "unverified_ack"] = m.group(1)
        self.publisher.event("command_rejected", **fields)

    # ---- end -------------------------------------------------------------------------------
    def close(self, result=None) -> None:
        """Publish run_end, drain, finish the recording, close zenoh (idempotent, never raises)."""
        if self._closed:
            return
        self._closed = True
        if self.commands is not None:
            self.commands.close()
        if self.routes is not None:
            self.routes.close()
        try:
            self._offer_line_map(self.runtime.clock.now_ns())
        except Exception as exc:
            self.publisher.count_error(exc)
        if result is not None:
            self.publisher.event("run_end", reason=result.reason, message=result.message, cycles=result.cycles,
                                 telemetry_dropped=self.publisher.dropped)
        self.publisher.close()
        self._report_recording()
        self._report_errors()
        if self.session is not None:
            time.sleep(0.05)  # let the last express puts leave before the transport closes
            try:
                self.session.close()
            except Exception:
                pass

    def _report_recording(self) -> None:
        """A recording that failed (a full disk) is said, not only counted: the run's own result says
        nothing about it, and its file is incomplete or left as PATH.part."""
        rec = self.recorder
        exc = self.publisher.sink_failures.get(rec) if rec is not None else None
        if exc is None and self._borrowed is not None:      # a recording shared with other runs (the demo's)
            exc = self.publisher.sink_failures.get(self._borrowed)
            if exc is not None:
                self.recording_error = repr(exc)
                print(f"vbnav: the recording {self._borrowed._sink.path} is incomplete: writing this run's segment "
                      f"failed ({exc}); it stays open for the runs that share it", file=sys.stderr)
            return
        if exc is None:
            return
        # PATH.part while the recording was not closed; PATH only once it was renamed (with --overwrite, a PATH
        # beside a PATH.part is the earlier run's recording, left as it was)
        where = rec.part_path if rec.part_path.exists() else rec.path
        self.recording_error = repr(exc)
        print(f"vbnav: the recording {rec.path} is incomplete: writing it failed ({exc}); what was written before "
              f"is in {where}", file=sys.stderr)

    def _report_errors(self) -> None:
        """Telemetry lost to errors is said, not only counted: a sink that raised on every message (a live view, a
        recording) or an overlay that could not be built left a viewer or a file without them, and nothing said so."""
        pub = self.publisher
        self.telemetry_errors = n = pub.sink_errors
        if n:
            first = f"; the first: {pub.first_error!r}" if pub.first_error is not None else ""
            print(f"vbnav: telemetry: {n} error{'s' if n > 1 else ''}: messages, overlays or scenes not published or "
                  f"recorded{first}", file=sys.stderr)
