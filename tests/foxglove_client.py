"""A minimal Foxglove WebSocket client over RFC 6455, as the Foxglove app speaks it, and a protobuf wire
decoder for the messages it receives. Tests only.

It offers both subprotocols the app offers: ``foxglove.sdk.v1`` (what the foxglove-sdk 0.30 server accepts)
and ``foxglove.websocket.v1`` (the older ws-protocol servers); the messages are the same."""
from __future__ import annotations

import base64
import json
import os
import socket
import struct
import time

SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")


class FoxgloveClient:
    def __init__(self, host: str, port: int, timeout_s: float = 10.0):
        self.sock = socket.create_connection((host, port), timeout=timeout_s)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                           f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                           f"Sec-WebSocket-Protocol: {', '.join(SUBPROTOCOLS)}\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(1)
            if not chunk:
                raise ConnectionError("closed during the handshake")
            head += chunk
        lines = head.decode().split("\r\n")
        if " 101 " not in lines[0]:
            raise ConnectionError(f"handshake refused: {lines[0]}")
        self.protocol = next((ln.split(":", 1)[1].strip() for ln in lines
                              if ln.lower().startswith("sec-websocket-protocol:")), None)
        self.sock.settimeout(0.5)                  # poll() loops until its own deadline
        self.channels: dict[int, dict] = {}       # server channel id -> advertisement
        self.server_info: dict | None = None
        self.parameters: list = []

    # ---- frames ---------------------------------------------------------------------------
    def _recv_exact(self, n: int, may_time_out: bool = False) -> bytes:
        """n bytes. Only before the first byte of a frame may the socket's timeout end the wait (poll's
        deadline); inside a frame it waits on, or the rest of the frame would be read as a new one."""
        buf = b""
        while len(buf) < n:
            try:
                chunk = self.sock.recv(n - len(buf))
            except socket.timeout:
                if may_time_out and not buf:
                    raise
                continue
            if not chunk:
                raise ConnectionError("connection closed")
            buf += chunk
        return buf

    def recv_frame(self) -> tuple[int, bytes]:
        b0, b1 = self._recv_exact(2, may_time_out=True)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", self._recv_exact(2))[0]
        elif n == 127:
            n = struct.unpack(">Q", self._recv_exact(8))[0]
        data = self._recv_exact(n)
        op = b0 & 0x0F
        if op == 0x9:                      # ping -> pong
            self._send(0xA, data)
            return self.recv_frame()
        return op, data

    def _send(self, op: int, data: bytes) -> None:
        mask = os.urandom(4)
        n = len(data)
        head = bytes([0x80 | op])
        if n < 126:
            head += bytes([0x80 | n])
        elif n < 65536:
            head += bytes([0x80 | 126]) + struct.pack(">H", n)
        else:
            head += bytes([0x80 | 127]) + struct.pack(">Q", n)
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def send_json(self, msg: dict) -> None:
        self._send(0x1, json.dumps(msg).encode())

    # ---- protocol -------------------------------------------------------------------------
    def poll(self, deadline_s: float = 10.0):
        """Read until one binary message arrives or ``deadline_s`` passes; returns (subscription id, log time,
        payload) or None. Text messages (serverInfo, advertise, parameterValues, status) are noted."""
        end = time.monotonic() + deadline_s
        while time.monotonic() < end:
            try:
                op, data = self.recv_frame()
            except socket.timeout:
                continue
            if op == 0x1:
                msg = json.loads(data)
                if msg["op"] == "serverInfo":
                    self.server_info = msg
                elif msg["op"] == "advertise":
                    for ch in msg["channels"]:
                        self.channels[ch["id"]] = ch
                elif msg["op"] == "parameterValues":
                    self.parameters.extend(msg["parameters"])
            elif op == 0x2 and data[0] == 0x01:        # MessageData
                sub, t = struct.unpack_from("<IQ", data, 1)
                return sub, t, data[13:]
            elif op == 0x8:
                code = struct.unpack(">H", data[:2])[0] if len(data) >= 2 else None
                raise ConnectionError(f"server closed the connection (code {code}: {data[2:].decode(errors='replace')})")
        return None

    def wait_for_channels(self, topics, deadline_s: float = 10.0) -> dict[str, dict]:
        end = time.monotonic() + deadline_s
        while True:
            by_topic = {c["topic"]: c for c in self.channels.values()}
            if all(t in by_topic for t in topics):
                return by_topic
            if time.monotonic() > end:
                break
            self.poll(0.2)
        raise AssertionError(f"channels {topics} not advertised; got {sorted(c['topic'] for c in self.channels.values())}")

    def subscribe(self, channel_ids: dict[int, int]) -> None:
        """channel_ids: subscription id -> server channel id."""
        self.send_json({"op": "subscribe", "subscriptions": [{"id": s, "channelId": c} for s, c in channel_ids.items()]})

    def advertise(self, channel_id: int, topic: str, schema_name: str = "geometry_msgs/Twist") -> None:
        self.send_json({"op": "advertise", "channels": [{"id": channel_id, "topic": topic, "encoding": "json",
                                                          "schemaName": schema_name}]})

    def publish(self, channel_id: int, payload: bytes) -> None:
        self._send(0x2, bytes([0x01]) + struct.pack("<I", channel_id) + payload)

    def set_parameter(self, name: str, value) -> None:
        self.send_json({"op": "setParameters", "parameters": [{"name": name, "value": value}], "id": "set"})

    def close(self) -> None:
        try:
            self._send(0x8, b"")
        except OSError:
            pass
        self.sock.close()


def protobuf_fields(data: bytes) -> dict[int, list]:
    """Field number -> values of a protobuf message (varint -> int, fixed64/32 -> bytes, length-delimited ->
    bytes); nested messages are decoded by calling this again on their bytes."""
    out: dict[int, list] = {}
    i = 0
    while i < len(data):
        key, i = _varint(data, i)
        field, wire = key >> 3, key & 7
        if wire == 0:
            v, i = _varint(data, i)
        elif wire == 1:
            v, i = data[i:i + 8], i + 8
        elif wire == 2:
            n, i = _varint(data, i)
            v, i = data[i:i + n], i + n
        elif wire == 5:
            v, i = data[i:i + 4], i + 4
        else:
            raise ValueError(f"unsupported wire type {wire}")
        out.setdefault(field, []).append(v)
    return out


def _varint(data: bytes, i: int) -> tuple[int, int]:
    shift = v = 0
    while True:
        b = data[i]
        i += 1
        v |= (b & 0x7F) << shift
        if not b & 0x80:
            return v, i
        shift += 7


def double(b: bytes) -> float:
    return struct.unpack("<d", b)[0]
