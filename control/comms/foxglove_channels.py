"""The Foxglove channels of a run: one set of definitions for the MCAP recorder and the live view.

Both the recorder (control/comms/recording.py) and the live WebSocket server
(control/comms/live_view.py) publish what this module builds: the same topics,
the same schemas (the foxglove-sdk's own protobuf definitions for the Foxglove
message types, JSON schema for vbnav's own state and event messages) and the
same bytes. A topic's schema is fixed here, in ``TOPICS``.

Frames, in Foxglove's convention (x forward, y left, z up): ``odom`` is the
run's odometry frame, vbnav's planar pose (x right, z forward, theta turning
right) maps to (x_fg, y_fg, yaw_fg) = (z, -x, -theta); ``camera`` is the image;
``vslam`` is the VSLAM world (camera axes x right, y down, z forward at the
reference frame, drawn as (z, -x, -y)). A taught route's keyframes are drawn in
``odom``: the teach run's odometry frame (a repeat starts where the teach started). The line map
(docs/line_map.md) is drawn in ``odom`` too: its world frame is the odometry frame of the run that built
it (x right, y down, z forward, floor at y = 0), drawn as (z, -x, -y).
"""
from __future__ import annotations

import json
import math
import struct
from typing import Iterable, NamedTuple

import numpy as np

from foxglove.messages import (Color, CompressedImage, Grid, ImageAnnotations, LinePrimitive, LinePrimitiveLineType,
                               Log, LogLevel, Odometry, PackedElementField, PackedElementFieldNumericType, Point2,
                               Point3, PointCloud, PointsAnnotation, PointsAnnotationType, Pose, PoseInFrame,
                               Quaternion, SceneEntity, SceneUpdate, SpherePrimitive, Timestamp, Vector2, Vector3)
from vbnav.vision.geometry import Pose2

# Event kinds that Foxglove's log panel shows as warnings / errors.
_LOG_LEVEL = {"safety_trip": LogLevel.Error, "safety_hold": LogLevel.Warning, "safety_hold_changed": LogLevel.Warning,
              "safety_warning": LogLevel.Warning, "command_rejected": LogLevel.Warning}

VBNAV_SCHEMAS = {
    "vbnav.state": {"title": "vbnav.state", "type": "object", "description": "robot state, see docs/telemetry.md",
                    "properties": {"schema": {"type": "string"}, "version": {"type": "integer"},
                                   "robot": {"type": "string"}, "seq": {"type": "integer"},
                                   "stamp_ns": {"type": "integer"}, "cycle": {"type": "integer"},
                                   "mode": {"type": "string"}, "safety": {"type": "object"},
                                   "drive": {"type": "object"},
                                   "pose": {"type": "object"}, "keyframe": {"type": ["integer", "null"]},
                                   "wheels": {"type": "object"}, "twist": {"type": "object"},
                                   "loop": {"type": "object"}}},
    "vbnav.event": {"title": "vbnav.event", "type": "object", "description": "event, see docs/telemetry.md",
                    "properties": {"schema": {"type": "string"}, "version": {"type": "integer"},
                                   "robot": {"type": "string"}, "seq": {"type": "integer"},
                                   "stamp_ns": {"type": "integer"}, "kind": {"type": "string"}}},
}

# topic -> schema name. Foxglove types are the SDK's message classes; vbnav.* are JSON.
TOPICS = {
    "/vbnav/state": "vbnav.state",
    "/vbnav/events": "vbnav.event",
    "/vbnav/log": "foxglove.Log",
    "/vbnav/pose/odom": "foxglove.PoseInFrame",
    "/vbnav/pose/vbc": "foxglove.PoseInFrame",
    "/vbnav/pose/vslam": "foxglove.PoseInFrame",
    "/vbnav/odometry": "foxglove.Odometry",
    "/vbnav/image": "foxglove.CompressedImage",
    "/vbnav/image/annotations": "foxglove.ImageAnnotations",
    "/vbnav/route": "foxglove.SceneUpdate",
    "/vbnav/landmarks": "foxglove.PointCloud",
    "/vbnav/map/lines": "foxglove.SceneUpdate",
    "/vbnav/map/grid": "foxglove.Grid",
}

# Sent when they change, not at a rate: the live view repeats the last one to each new subscriber.
LATCHED_TOPICS = frozenset({"/vbnav/map/lines", "/vbnav/map/grid"})

_SDK_TYPES = {"foxglove.Log": Log, "foxglove.PoseInFrame": PoseInFrame, "foxglove.Odometry": Odometry,
              "foxglove.CompressedImage": CompressedImage, "foxglove.ImageAnnotations": ImageAnnotations,
              "foxglove.SceneUpdate": SceneUpdate, "foxglove.PointCloud": PointCloud, "foxglove.Grid": Grid}


class ChannelSchema(NamedTuple):
    name: str
    encoding: str           # schema encoding: protobuf | jsonschema
    data: bytes
    message_encoding: str   # protobuf | json


def schema_of(topic: str) -> ChannelSchema:
    """The schema of one of ``TOPICS``."""
    name = TOPICS[topic]
    if name in VBNAV_SCHEMAS:
        return ChannelSchema(name, "jsonschema", json.dumps(VBNAV_SCHEMAS[name]).encode(), "json")
    s = _SDK_TYPES[name].get_schema()
    return ChannelSchema(s.name, s.encoding, bytes(s.data), "protobuf")


def encode(msg) -> bytes:
    """Wire bytes of a message built here: protobuf for SDK messages, compact JSON for dicts."""
    if isinstance(msg, dict):
        return json.dumps(msg, separators=(",", ":"), allow_nan=False, default=str).encode()
    return msg.encode()


def timestamp(stamp_ns: int) -> Timestamp:
    stamp_ns = max(0, int(stamp_ns))
    return Timestamp(stamp_ns // 1_000_000_000, stamp_ns % 1_000_000_000)


def _planar_pose(p: dict) -> Pose:
    yaw = -float(p["theta"])
    return Pose(position=Vector3(x=float(p["z"]), y=-float(p["x"]), z=0.0),
                orientation=Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)))


# ---- from telemetry messages (the publisher thread's dicts, docs/telemetry.md) --------------

def state_messages(stamp_ns: int, msg: dict) -> list[tuple[str, object]]:
    """The pose and odometry messages of one ``vbnav.state`` (the state itself goes out as JSON)."""
    out: list[tuple[str, object]] = []
    ts = timestamp(stamp_ns)
    for name, pose in msg["pose"].items():
        if pose is not None:
            out.append((f"/vbnav/pose/{name}", PoseInFrame(timestamp=ts, frame_id="odom", pose=_planar_pose(pose))))
    odom, twist = msg["pose"].get("odom"), msg.get("twist") or {}
    if odom is not None:
        lin, ang = twist.get("linear") or 0.0, twist.get("angular") or 0.0
        out.append(("/vbnav/odometry", Odometry(
            timestamp=ts, frame_id="odom", body_frame_id="base_link", pose=_planar_pose(odom),
            linear_velocity=Vector3(x=float(lin), y=0.0, z=0.0),
            angular_velocity=Vector3(x=0.0, y=0.0, z=-float(ang)))))
    return out


def log_message(stamp_ns: int, msg: dict) -> Log:
    """A ``vbnav.event`` as a Foxglove log line."""
    text = " ".join(f"{k}={v}" for k, v in msg.items()
                    if k not in ("schema", "version", "robot", "seq", "stamp_ns", "kind"))
    return Log(timestamp=timestamp(stamp_ns), level=_LOG_LEVEL.get(msg.get("kind"), LogLevel.Info),
               message=f"{msg.get('kind')}: {text}".strip(), name=f"vbnav/{msg.get('robot')}")


def image_message(stamp_ns: int, jpeg: bytes) -> CompressedImage:
    return CompressedImage(timestamp=timestamp(stamp_ns), frame_id="camera", data=bytes(jpeg), format="jpeg")


# ---- overlays: what the vision stages saw in a frame ------------------------------------------

class Overlay(NamedTuple):
    """Image-space overlays of one frame, in the published image's pixels (already scaled).

    tracked: (N, 2) tracked feature pixels; matched: (M, 2) the matched keyframe's features (where they
    were in the keyframe image); zone: (K, 2) outline of the obstacle stop zone on the floor; mask: (L, 2)
    pixels the obstacle stage labels as obstacle (subsampled); text: a line about the frame.
    """

    tracked: object = None
    matched: object = None
    zone: object = None
    mask: object = None
    text: str = ""

    def scaled(self, s: float) -> "Overlay":
        def sc(a):
            return None if a is None else [(float(x) * s, float(y) * s) for x, y in a]
        return Overlay(sc(self.tracked), sc(self.matched), sc(self.zone), sc(self.mask), self.text)


_GREEN, _CYAN = Color(r=0.1, g=0.9, b=0.2, a=1.0), Color(r=0.1, g=0.8, b=1.0, a=1.0)
_RED, _RED_FILL = Color(r=1.0, g=0.2, b=0.1, a=1.0), Color(r=1.0, g=0.2, b=0.1, a=0.25)


def annotations_message(stamp_ns: int, ov: Overlay) -> ImageAnnotations:
    ts = timestamp(stamp_ns)
    points = []

    def pts(a):
        return [Point2(x=float(x), y=float(y)) for x, y in a]

    if ov.tracked is not None and len(ov.tracked):
        points.append(PointsAnnotation(timestamp=ts, type=PointsAnnotationType.Points, points=pts(ov.tracked),
                                       outline_color=_GREEN, thickness=4.0))
    if ov.matched is not None and len(ov.matched):
        points.append(PointsAnnotation(timestamp=ts, type=PointsAnnotationType.Points, points=pts(ov.matched),
                                       outline_color=_CYAN, thickness=3.0))
    if ov.mask is not None and len(ov.mask):
        points.append(PointsAnnotation(timestamp=ts, type=PointsAnnotationType.Points, points=pts(ov.mask),
                                       outline_color=_RED, thickness=2.0))
    if ov.zone is not None and len(ov.zone) >= 3:
        points.append(PointsAnnotation(timestamp=ts, type=PointsAnnotationType.LineLoop, points=pts(ov.zone),
                                       outline_color=_RED, fill_color=_RED_FILL, thickness=2.0))
    return ImageAnnotations(points=points)


# ---- 3D: the taught route and the VSLAM landmarks ---------------------------------------------

def route_message(stamp_ns: int, name: str, keyframes: Iterable) -> SceneUpdate:
    """The taught path (a line through its keyframes) and each keyframe as a sphere, in ``odom``.

    keyframes: planar poses (``.x .z .theta`` or (x, z, theta))."""
    xy = []
    for p in keyframes:
        x, z = (p.x, p.z) if isinstance(p, Pose2) else (p[0], p[1])
        xy.append((float(z), -float(x)))
    pts = [Point3(x=a, y=b, z=0.0) for a, b in xy]
    spheres = [SpherePrimitive(pose=Pose(position=Vector3(x=a, y=b, z=0.0),
                                         orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
                               size=Vector3(x=0.12, y=0.12, z=0.12), color=_CYAN) for a, b in xy]
    lines = [LinePrimitive(type=LinePrimitiveLineType.LineStrip, thickness=0.03, points=pts, color=_GREEN)] \
        if len(pts) >= 2 else []
    return SceneUpdate(entities=[SceneEntity(timestamp=timestamp(stamp_ns), frame_id="odom", id=f"route/{name}",
                                             lines=lines, spheres=spheres)])


def landmarks_message(stamp_ns: int, points_vslam) -> PointCloud:
    """VSLAM landmarks (N, 3) in the VSLAM world frame (camera axes) as a Foxglove point cloud."""
    data = bytearray()
    for x, y, z in points_vslam:
        data += struct.pack("<fff", float(z), -float(x), -float(y))
    f32 = PackedElementFieldNumericType.Float32
    return PointCloud(timestamp=timestamp(stamp_ns), frame_id="vslam",
                      pose=Pose(position=Vector3(x=0.0, y=0.0, z=0.0),
                                orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
                      point_stride=12, fields=[PackedElementField(name="x", offset=0, type=f32),
                                               PackedElementField(name="y", offset=4, type=f32),
                                               PackedElementField(name="z", offset=8, type=f32)],
                      data=bytes(data))


# ---- the line map (vision/line_map.py): its 3D segments and the planning grid -----------------

LINE_MAP_ENTITY = "line_map"
# Colours of the segment kinds: the verified map, stereo candidates not verified yet, and the abstraction's
# missing-line hypotheses not verified yet (docs/line_map.md).
LINE_MAP_RGBA = {"verified": (0.1, 0.9, 0.2, 1.0), "candidate": (0.6, 0.6, 0.6, 0.7),
                 "hypothesis": (1.0, 0.6, 0.1, 1.0)}


def _fg_point(p) -> Point3:
    """A world point (x right, y down, z forward) in Foxglove's axes (x forward, y left, z up)."""
    return Point3(x=float(p[2]), y=-float(p[0]), z=-float(p[1]))


def line_map_message(stamp_ns: int, P, verified, hypothesis) -> SceneUpdate:
    """The map's segments (N, 2, 3) world metres as one scene entity in ``odom``: one line list per kind
    (``LINE_MAP_RGBA``; an empty kind has no line list), two points per segment."""
    kinds = {"verified": verified, "candidate": ~verified & ~hypothesis, "hypothesis": ~verified & hypothesis}
    lines = []
    for kind, sel in kinds.items():
        seg = P[sel]
        if len(seg):
            lines.append(LinePrimitive(type=LinePrimitiveLineType.LineList, thickness=0.02,
                                       points=[_fg_point(p) for p in seg.reshape(-1, 3)],
                                       color=Color(**dict(zip("rgba", LINE_MAP_RGBA[kind])))))
    return SceneUpdate(entities=[SceneEntity(timestamp=timestamp(stamp_ns), frame_id="odom", id=LINE_MAP_ENTITY,
                                             lines=lines)])


def grid_message(stamp_ns: int, x0: float, z0: float, res: float, cells) -> Grid:
    """A floor grid (rows along z, columns along x; cell (0, 0)'s corner at (x0, z0)) of uint8 ``cells`` as a
    Foxglove grid in ``odom``: columns run along -y, rows along x (a -90 degree yaw of the grid's axes)."""
    cells = np.ascontiguousarray(cells, np.uint8)
    half = math.sqrt(0.5)
    return Grid(timestamp=timestamp(stamp_ns), frame_id="odom",
                pose=Pose(position=Vector3(x=float(z0), y=-float(x0), z=0.0),
                          orientation=Quaternion(x=0.0, y=0.0, z=-half, w=half)),
                column_count=int(cells.shape[1]), cell_size=Vector2(x=float(res), y=float(res)),
                row_stride=int(cells.shape[1]), cell_stride=1,
                fields=[PackedElementField(name="cost", offset=0, type=PackedElementFieldNumericType.Uint8)],
                data=cells.tobytes())
