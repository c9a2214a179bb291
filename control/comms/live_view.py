"""The live view in Foxglove: the foxglove-sdk's WebSocket server as a telemetry sink, and teleop from it.

``LiveView`` is a telemetry ``Sink`` (it runs on the telemetry publisher's
thread, never the loop's): it logs the channels of control/comms/foxglove_channels.py
(the same topics, schemas and bytes as the MCAP recording) to a WebSocket server
(protocol ``foxglove.websocket.v1``) that the Foxglove app opens as
``ws://HOST:PORT`` (``telemetry.live_view``; docs/foxglove-layout.json shows everything).
The server starts with the robot's zenoh session (real-time runs) and binds to
loopback unless the telemetry section allows remote access (config/telemetry.py).

Teleop: a client (Foxglove's Teleop panel) advertises ``/vbnav/teleop`` with JSON
``geometry_msgs/Twist`` messages (``linear.x`` m/s forward, ``angular.z`` rad/s
turning left) and publishes on it. Each message becomes a ``teleop`` command with
the client as sender and goes through the link's ``CommandInbox``: the same
validation, limits (robot.max_linear_speed / max_angular_speed), mailbox
(order, freshness) and ``command_rejected`` events as ``vbnav send teleop``. A client
that goes (the SDK unadvertises its channels when it disconnects, cleanly or not) or
unadvertises the teleop topic while its last twist drove sends a zero twist in its name,
as ``vbnav teleop`` does when it ends: the robot stops then, not at its command timeout.
Who is an operator follows the same rules as the zenoh side:

- ``live_view.operator_token_file`` set: a client is an operator once it sets the
  parameter ``vbnav.operator_token`` to the file's content (Foxglove's Parameters
  panel); other clients' twists are refused;
- else, on a loopback-only robot without authentication or a shared secret (any
  local user may command it with ``vbnav send``): every client is an operator;
- else nobody may teleoperate through the live view.

Latched topics (``foxglove_channels.LATCHED_TOPICS``, the line map): sent only when they change, so the
last message of each is kept and sent again when a client subscribes (Foxglove keeps a scene entity until
it is replaced; a client that connects after the map stopped changing still sees it).

Log times are the wall clock (``time.time_ns``), so Foxglove shows the real time of day.
"""
from __future__ import annotations

import hmac
import json
import threading
import time
import uuid
from typing import Callable, Optional

import foxglove
from foxglove.websocket import Capability, ServerListener

from vbnav.control.comms import foxglove_channels as fc
from vbnav.control.comms.operator_commands import MAX_PAYLOAD
from vbnav.control.comms.telemetry import Sink
from vbnav.drivers.plain_values import load_json

TELEOP_TOPIC = "/vbnav/teleop"
TOKEN_PARAMETER = "vbnav.operator_token"


def operator_rule(tcfg) -> tuple[Optional[bytes], bool, str]:
    """(token, everyone_is_operator, why_nobody) of a telemetry section."""
    lv = tcfg.live_view
    if lv.operator_token_file is not None:
        from vbnav.control.comms.command_auth import read_secret
        return read_secret(lv.operator_token_file).strip(), False, ""
    if tcfg.authenticated or tcfg.trust_router or tcfg.shared_secret_file is not None:
        return None, False, ("only identified operators may command this robot and the live view cannot identify "
                             "anyone: set telemetry.live_view.operator_token_file")
    return None, True, ""


#: Live-view clients remembered as operators at once (the latest to give the token).
OPERATORS_KEPT = 64


class LiveView(Sink, ServerListener):
    """The WebSocket server and its channels. ``teleop(sender, session, payload)`` submits a command."""

    def __init__(self, tcfg, robot: str, submit_teleop: Callable[[str, bytes], None],
                 refuse: Callable[[str, str, bytes], None], to_wall_ns: Callable[[int], int]):
        lv = tcfg.live_view
        self._token, self._everyone, self._why_nobody = operator_rule(tcfg)
        self._submit, self._refuse, self._to_wall = submit_teleop, refuse, to_wall_ns
        self._lock = threading.Lock()
        # Client ids that gave the operator token, oldest first. The SDK tells no disconnect, and the Foxglove
        # app reconnects after every network blip under a new id: only the latest OPERATORS_KEPT are kept (an
        # older one still connected sets the token again).
        self._operators: dict[int, None] = {}
        self._teleop_channels: set[tuple[int, int]] = set()   # the SDK unadvertises them when a client goes
        self._driving: set[tuple[int, int]] = set()   # of those, the ones whose last twist submitted was not zero
        self._seq = 0           # teleop seq, one counter for every client: it increases per sender all the same
        self._session = uuid.uuid4().hex[:8]
        self.bytes_sent = 0
        self.latched = Latched()
        self.context = foxglove.Context()
        tls = {}
        if lv.tls_certificate is not None:
            from pathlib import Path
            tls = dict(tls_cert=Path(lv.tls_certificate).expanduser().read_bytes(),
                       tls_key=Path(lv.tls_private_key).expanduser().read_bytes())
        self.server = foxglove.start_server(
            name=f"vbnav {robot}", host=lv.host, port=lv.port, context=self.context,
            capabilities=[Capability.ClientPublish, Capability.Parameters], supported_encodings=["json"],
            server_listener=self, **tls)
        self.port = self.server.port
        self.channels = {topic: _channel(topic, self.context) for topic in fc.TOPICS}

    # ---- Sink (telemetry publisher thread) ------------------------------------------------
    def _log(self, topic: str, wall_ns: int, build) -> None:
        """Encode and send ``build()`` only when a client subscribes to ``topic`` (bytes: already encoded);
        a latched topic's message is always encoded and kept for later subscribers."""
        ch = self.channels[topic]
        if topic in fc.LATCHED_TOPICS:
            data = build if isinstance(build, bytes) else fc.encode(build())
            self.latched.log(topic, ch, data, wall_ns)
            self.bytes_sent += len(data)
        elif ch.has_sinks():
            data = build if isinstance(build, bytes) else fc.encode(build())
            ch.log(data, log_time=wall_ns)
            self.bytes_sent += len(data)

    def state(self, stamp_ns, payload, msg):
        t = self._to_wall(stamp_ns)
        self._log("/vbnav/state", t, payload)
        if any(self.channels[k].has_sinks() for k in ("/vbnav/odometry", "/vbnav/pose/odom", "/vbnav/pose/vbc",
                                                     "/vbnav/pose/vslam")):
            for topic, m in fc.state_messages(t, msg):
                self._log(topic, t, lambda m=m: m)

    def event(self, stamp_ns, payload, msg):
        t = self._to_wall(stamp_ns)
        self._log("/vbnav/events", t, payload)
        self._log("/vbnav/log", t, lambda: fc.log_message(t, msg))

    def image(self, stamp_ns, payload, msg, jpeg):
        t = self._to_wall(stamp_ns)
        self._log("/vbnav/image", t, lambda: fc.image_message(t, jpeg))

    def annotations(self, stamp_ns, overlay):
        t = self._to_wall(stamp_ns)
        self._log("/vbnav/image/annotations", t, lambda: fc.annotations_message(t, overlay))

    def foxglove(self, stamp_ns, topic, build):
        t = self._to_wall(stamp_ns)
        self._log(topic, t, lambda: build(t))

    def close(self):
        try:
            self.server.stop()
        except Exception:
            pass

    # ---- ServerListener (the server's threads) ---------------------------------------------
    def on_subscribe(self, client, channel) -> None:
        self.latched.on_subscribe(channel.topic)

    def on_client_advertise(self, client, channel) -> None:
        if channel.topic == TELEOP_TOPIC:
            with self._lock:
                self._teleop_channels.add((client.id, channel.id))

    def on_client_unadvertise(self, client, client_channel_id: int) -> None:
        key = (client.id, client_channel_id)
        with self._lock:
            self._teleop_channels.discard(key)
            if key in self._driving:     # the client went (or stopped its teleop) while driving: stop now
                self._driving.discard(key)
                self._submit_twist(client.id, 0.0, 0.0)

    def on_set_parameters(self, client, parameters, request_id=None):
        out = []
        for p in parameters:
            if p.name != TOKEN_PARAMETER:
                continue
            value = p.get_value()
            good = self._token is not None and isinstance(value, str) and \
                hmac.compare_digest(value.strip().encode(), self._token)
            with self._lock:
                self._operators.pop(client.id, None)
                if good:
                    self._operators[client.id] = None
                    while len(self._operators) > OPERATORS_KEPT:
                        del self._operators[next(iter(self._operators))]
            out.append(foxglove.Parameter(TOKEN_PARAMETER, value="accepted" if good else "refused"))
        return out

    def on_get_parameters(self, client, param_names, request_id=None):
        return []

    def is_operator(self, client_id: int) -> bool:
        with self._lock:
            return self._everyone or client_id in self._operators

    def on_message_data(self, client, client_channel_id: int, data: bytes) -> None:
        with self._lock:
            teleop = (client.id, client_channel_id) in self._teleop_channels
        if not teleop:
            return
        if not self.is_operator(client.id):
            why = self._why_nobody or (f"Foxglove client {client.id} is not an operator (set the parameter "
                                       f"{TOKEN_PARAMETER} to the content of telemetry.live_view.operator_token_file)")
            self._refuse("teleop", why, bytes(data[:200]))
            return
        if len(data) > MAX_PAYLOAD:                 # as on the zenoh path: refused unread
            self._refuse("teleop", f"Foxglove teleop: payload of {len(data)} bytes exceeds {MAX_PAYLOAD}; not read", b"")
            return
        try:
            twist = load_json(bytes(data))          # a key given twice is refused, as on the zenoh path
            x, z = twist["linear"]["x"], twist["angular"]["z"]
            # numbers as JSON gives them, never coerced (as the zenoh path): true is no 1 m/s, "0.3" no 0.3 m/s
            if not all(isinstance(n, (int, float)) and not isinstance(n, bool) for n in (x, z)):
                raise TypeError(f"linear.x and angular.z must be numbers, got {x!r} and {z!r}")
            linear, angular = float(x), -float(z)       # ROS/Foxglove: positive turns left; vbnav: right
        except (ValueError, KeyError, TypeError, OverflowError) as exc:   # Overflow: an int too large for a float
            self._refuse("teleop", f"Foxglove teleop: expected a JSON geometry_msgs/Twist ({exc!r})",
                         bytes(data[:200]))
            return
        except RecursionError:                      # raised into the server's callback, the twist was unanswered
            self._refuse("teleop", "Foxglove teleop: expected a JSON geometry_msgs/Twist (nested too deep)",
                         bytes(data[:200]))
            return
        key = (client.id, client_channel_id)
        with self._lock:     # one at a time: a twist in flight when its client goes is never sent after the stop
            if key not in self._teleop_channels:
                return       # unadvertised meanwhile (the client went): its stop was sent, this twist comes late
            if linear or angular:
                self._driving.add(key)
            else:
                self._driving.discard(key)
            self._submit_twist(client.id, linear, angular)

    def _submit_twist(self, client_id: int, linear: float, angular: float) -> None:
        """A teleop command in the client's name (under ``_lock``: the seq and the order of submission agree)."""
        seq = self._seq = self._seq + 1
        payload = json.dumps({"sender": f"foxglove-{client_id}", "session": f"{self._session}-{client_id}",
                              "seq": seq, "stamp_ns": time.monotonic_ns(), "linear": linear,
                              "angular": angular}, allow_nan=True)
        try:
            self._submit("teleop", payload.encode())
        except Exception:    # the link is still being built: the next message of the stream gets through
            pass


class Latched:
    """The last message of each latched channel, sent again when a client subscribes to it (the SDK then
    sends it to every subscriber of the channel: a repeat of the current scene is harmless)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._last: dict[str, tuple] = {}       # topic -> (channel, data, log time)

    def log(self, topic: str, channel, data: bytes, log_ns: int) -> None:
        with self._lock:
            self._last[topic] = (channel, data, log_ns)
        channel.log(data, log_time=log_ns)

    def on_subscribe(self, topic: str) -> None:
        with self._lock:
            last = self._last.get(topic)
        if last is not None:
            channel, data, log_ns = last
            channel.log(data, log_time=log_ns)


class SceneServer(ServerListener):
    """A publish-only Foxglove server of latched topics (``vbnav map view``): no teleop, no parameters."""

    def __init__(self, name: str, topics, host: str = "127.0.0.1", port: int = 8765):
        self.latched = Latched()
        self.context = foxglove.Context()
        self.server = foxglove.start_server(name=name, host=host, port=port, context=self.context,
                                            server_listener=self)
        self.port = self.server.port
        self.channels = {topic: _channel(topic, self.context) for topic in topics}

    def publish(self, topic: str, msg, log_ns: int) -> None:
        self.latched.log(topic, self.channels[topic], fc.encode(msg), log_ns)

    def on_subscribe(self, client, channel) -> None:
        self.latched.on_subscribe(channel.topic)

    def close(self) -> None:
        self.server.stop()


def _channel(topic: str, context) -> "foxglove.Channel":
    """The SDK channel of one of foxglove_channels.TOPICS."""
    sch = fc.schema_of(topic)
    return foxglove.Channel(topic, schema=foxglove.Schema(name=sch.name, encoding=sch.encoding, data=sch.data),
                            message_encoding=sch.message_encoding, context=context)
