"""Run recordings as MCAP files that open in Foxglove.

``McapRecorder`` is a telemetry ``Sink``: it runs on the telemetry publisher's
background thread and writes what is published, so the loop pays nothing
extra for recording. Its channels, schemas and message bytes are those of the
live Foxglove view, built in one place (control/comms/foxglove_channels.py):

- ``/vbnav/state``       ``vbnav.state`` (JSON)     every state message (docs/telemetry.md)
- ``/vbnav/events``      ``vbnav.event`` (JSON)     every event
- ``/vbnav/log``         ``foxglove.Log``           the events again, for Foxglove's log panel
- ``/vbnav/pose/odom``   ``foxglove.PoseInFrame``   odometry pose (and ``/vbnav/pose/vbc``,
  ``/vbnav/pose/vslam`` once those estimates appear); ``/vbnav/odometry`` ``foxglove.Odometry``
- ``/vbnav/image``       ``foxglove.CompressedImage`` decimated JPEG frames, and
  ``/vbnav/image/annotations`` ``foxglove.ImageAnnotations`` what the vision stages saw in them
- ``/vbnav/route``       ``foxglove.SceneUpdate``   the taught route; ``/vbnav/landmarks``
  ``foxglove.PointCloud`` VSLAM landmarks; ``/vbnav/map/lines`` ``foxglove.SceneUpdate`` the line map

Foxglove messages are protobuf with the foxglove-sdk's schemas.
Log times are the loop clock's stamps (monotonic or simulated ns); the wall
clock at the start is in the ``vbnav`` metadata record. A file may hold several
runs (``vbnav demo``: teach, then each repeat, each on a fresh simulated clock):
each run is a segment logged one second after the previous one ends
(``new_segment``); the ``stamp_ns`` inside the messages stays the loop's own.

Crash safety: the file is chunked and the chunk in progress is finished and
flushed to the OS at least every ``flush_interval_s``, so a process killed with
SIGKILL leaves a file readable up to its last completed chunk (it lacks the
summary section, so read it with ``read_recording``/``iter_recording``, which
stream through it). The file is written as ``PATH.part`` and renamed to ``PATH``
when the recording closes cleanly. A ``PATH.part`` already there is an earlier run's interrupted recording
(its only copy): ``--overwrite`` replaces ``PATH``, never that; it is renamed aside to
``STEM.interrupted-N.SUFFIX.part`` (``interrupted_name``) before the new recording opens, and said so.
"""
from __future__ import annotations

import datetime
import os
import struct
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Optional

from vbnav.control.comms import foxglove_channels as fc
from vbnav.control.comms.telemetry import Sink
from vbnav.drivers.atomic_file import fsync_folder, replace_durably

PART_SUFFIX = ".part"
MCAP_MAGIC = b"\x89MCAP0\r\n"

def check_record_target(path: str | os.PathLike, overwrite: bool = False) -> None:
    """Refuse to record over a recording (PATH, or PATH.part of an interrupted one) unless ``overwrite``;
    FileExistsError / FileNotFoundError name the file. With ``overwrite`` the old file stays until the
    new one is complete (it is written as PATH.part and renamed over PATH when it closes), and an
    interrupted PATH.part is kept under another name (``keep_interrupted``)."""
    p = Path(path)
    if p.parent and not p.parent.exists():
        raise FileNotFoundError(f"--record {p}: directory {p.parent} does not exist")
    if overwrite:
        return
    if p.exists():
        raise FileExistsError(f"--record {p}: exists (use --overwrite to replace it)")
    part = p.with_name(p.name + PART_SUFFIX)
    if part.exists():
        raise FileExistsError(f"--record {p}: {part.name} of an interrupted recording exists (read it with "
                              f"'vbnav record-info {p}'; with --overwrite it is kept as "
                              f"{free_interrupted_name(p).name} and a new recording starts)")


def interrupted_name(path: Path, n: int) -> Path:
    """Where the n-th kept interrupted recording of ``path`` goes: ``run.mcap`` -> ``run.interrupted-1.mcap.part``
    (still a ``.part``: ``vbnav record-info`` reads it as the interrupted file it is)."""
    return path.with_name(f"{path.stem}.interrupted-{n}{path.suffix}{PART_SUFFIX}")


def free_interrupted_name(path: Path) -> Path:
    """The first ``interrupted_name`` of ``path`` not taken (earlier kept recordings stay)."""
    n = 1
    while interrupted_name(path, n).exists():
        n += 1
    return interrupted_name(path, n)


def keep_interrupted(path: Path) -> Optional[Path]:
    """Rename an interrupted ``PATH.part`` aside to ``free_interrupted_name`` (the new recording is written
    as ``PATH.part``: opening it would truncate the earlier run's); its new path, or None."""
    part = path.with_name(path.name + PART_SUFFIX)
    if not part.exists():
        return None
    kept = free_interrupted_name(path)
    os.rename(part, kept)
    fsync_folder(kept.parent)
    return kept


class McapRecorder(Sink):
    """Writes telemetry to an MCAP file (call only from one thread: the telemetry publisher's).

    An existing PATH (or PATH.part) is refused unless ``overwrite``: see ``check_record_target``. With
    ``overwrite``, a PATH.part left by an interrupted run is renamed aside first (``kept_part``, said on stderr).
    """

    def __init__(self, path: str | os.PathLike, robot: str, chunk_size: int = 256 * 1024,
                 flush_interval_s: float = 1.0, metadata: Optional[dict] = None, overwrite: bool = False):
        from mcap.writer import CompressionType, Writer
        self.path = Path(path)
        check_record_target(self.path, overwrite)
        self.part_path = self.path.with_name(self.path.name + PART_SUFFIX)
        self.kept_part = keep_interrupted(self.path) if overwrite else None
        if self.kept_part is not None:
            print(f"vbnav: --record {self.path}: the interrupted recording {self.part_path.name} of an earlier run "
                  f"is kept as {self.kept_part} (--overwrite replaces {self.path.name} only)", file=sys.stderr)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._flush_interval_s = flush_interval_s
        self._last_flush = time.monotonic()
        self._closed = False
        self.counts: dict[str, int] = {}
        # Log time = loop stamp + offset. Each run of a multi-run recording (vbnav demo: teach, then
        # repeats, each on a fresh simulated clock) is a segment placed after the previous one.
        self._offset_ns = 0
        self._last_log_ns = 0
        self._rebase_gap_ns: Optional[int] = None
        self.segments: list[str] = []
        self._file = open(self.part_path, "xb")
        try:        # a recording that cannot start leaves no PATH.part (the next run would take it for a crash's)
            self._writer = Writer(self._file, chunk_size=chunk_size, compression=CompressionType.ZSTD)
            self._writer.start(profile="", library="vbnav")
            meta = {"robot": robot, "wall_time_start": datetime.datetime.now(datetime.timezone.utc).isoformat(),
                    "monotonic_start_ns": str(time.monotonic_ns())}
            meta.update({k: str(v) for k, v in (metadata or {}).items()})
            self._writer.add_metadata("vbnav", meta)
            for topic in ("/vbnav/state", "/vbnav/events", "/vbnav/log", "/vbnav/pose/odom"):
                self._channel(topic)
            self._writer.flush()  # header, metadata and channels reach the disk first
        except BaseException:
            try:
                self._file.close()      # may fail again flushing to the full disk
            except OSError:
                pass
            self.part_path.unlink(missing_ok=True)
            raise

    def _channel(self, topic: str) -> int:
        if topic not in self._channels:
            sch = fc.schema_of(topic)
            if sch.name not in self._schemas:
                self._schemas[sch.name] = self._writer.register_schema(sch.name, sch.encoding, sch.data)
            self._channels[topic] = self._writer.register_channel(topic, sch.message_encoding,
                                                                  self._schemas[sch.name])
        return self._channels[topic]

    def new_segment(self, name: str, gap_s: float = 1.0) -> None:
        """Start a new run in the same file: its first message is logged ``gap_s`` after the last one."""
        if self.segments:
            self._rebase_gap_ns = int(gap_s * 1e9)
        self.segments.append(name)

    def log_time(self, stamp_ns: int) -> int:
        """The file's log time of a loop stamp (stamps of a new segment are re-based on first use)."""
        if self._rebase_gap_ns is not None:
            self._offset_ns = self._last_log_ns + self._rebase_gap_ns - int(stamp_ns)
            self._rebase_gap_ns = None
        return int(stamp_ns) + self._offset_ns

    def _write(self, topic: str, log_ns: int, data: bytes) -> None:
        if self._closed:
            return
        cid = self._channel(topic)
        seq = self.counts.get(topic, 0)
        self._writer.add_message(cid, log_time=log_ns, publish_time=log_ns, data=data, sequence=seq)
        self._last_log_ns = max(self._last_log_ns, log_ns)
        self.counts[topic] = seq + 1
        now = time.monotonic()
        if now - self._last_flush >= self._flush_interval_s:
            self._writer.flush()
            self._last_flush = now

    # ---- Sink ----------------------------------------------------------------------------
    def state(self, stamp_ns, payload, msg):
        t = self.log_time(stamp_ns)
        self._write("/vbnav/state", t, payload)
        for topic, m in fc.state_messages(t, msg):
            self._write(topic, t, fc.encode(m))

    def event(self, stamp_ns, payload, msg):
        t = self.log_time(stamp_ns)
        self._write("/vbnav/events", t, payload)
        self._write("/vbnav/log", t, fc.encode(fc.log_message(t, msg)))

    def image(self, stamp_ns, payload, msg, jpeg):
        t = self.log_time(stamp_ns)
        self._write("/vbnav/image", t, fc.encode(fc.image_message(t, jpeg)))

    def annotations(self, stamp_ns, overlay):
        t = self.log_time(stamp_ns)
        self._write("/vbnav/image/annotations", t, fc.encode(fc.annotations_message(t, overlay)))

    def foxglove(self, stamp_ns, topic, build):
        t = self.log_time(stamp_ns)
        self._write(topic, t, fc.encode(build(t)))

    def discard(self) -> None:
        """Drop a recording whose run never started (the network or the live view failed to open): PATH.part
        is removed and a recording already at PATH is kept, as ``--overwrite`` promises ("the new one takes
        its place only when complete"); close() would have put an empty recording over it."""
        if self._closed:
            return
        self._closed = True
        self._file.close()
        self.part_path.unlink(missing_ok=True)

    def close(self) -> None:
        """Write the summary and index, fsync, then rename PATH.part -> PATH durably (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._writer.finish()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        replace_durably(self.part_path, self.path)


# ---- reading ---------------------------------------------------------------------------

@dataclass
class ChannelSummary:
    topic: str
    schema: str
    count: int = 0
    first_ns: Optional[int] = None
    last_ns: Optional[int] = None

    @property
    def rate_hz(self) -> float:
        if self.count < 2 or self.last_ns == self.first_ns:
            return 0.0
        return (self.count - 1) / ((self.last_ns - self.first_ns) * 1e-9)


@dataclass
class DamagedChunk:
    """A chunk whose bytes fail their CRC (or do not decompress): its messages are lost."""

    number: int                  # 1-based, in file order
    start_ns: int                # log time span the chunk's header claims
    end_ns: int
    reason: str
    lost: dict[str, int] = field(default_factory=dict)    # topic -> messages, from the chunk's message index


@dataclass
class RecordingSummary:
    path: Path
    channels: dict[str, ChannelSummary] = field(default_factory=dict)
    metadata: dict[str, dict] = field(default_factory=dict)
    complete: bool = False           # summary/footer present (closed cleanly)
    truncated_reason: str = ""
    damaged_chunks: list[DamagedChunk] = field(default_factory=list)
    expected: dict[str, int] = field(default_factory=dict)   # topic -> count from the file's statistics

    @property
    def messages(self) -> int:
        return sum(c.count for c in self.channels.values())

    @property
    def lost(self) -> dict[str, int]:
        """Messages per topic the file says it holds but that could not be read (empty if none)."""
        if self.expected:
            got = {t: c.count for t, c in self.channels.items()}
            out = {t: n - got.get(t, 0) for t, n in self.expected.items() if n > got.get(t, 0)}
        else:
            out = {}
            for d in self.damaged_chunks:
                for t, n in d.lost.items():
                    out[t] = out.get(t, 0) + n
        return out

    @property
    def damaged(self) -> bool:
        """Messages are lost, or the file was closed (renamed from PATH.part) but its end is unreadable."""
        closed = not self.path.name.endswith(PART_SUFFIX)
        return bool(self.damaged_chunks or self.lost or (self.truncated_reason and (self.complete or closed)))

    @property
    def duration_s(self) -> float:
        firsts = [c.first_ns for c in self.channels.values() if c.first_ns is not None]
        lasts = [c.last_ns for c in self.channels.values() if c.last_ns is not None]
        return (max(lasts) - min(firsts)) * 1e-9 if firsts else 0.0


def resolve_recording(path: str | os.PathLike) -> Path:
    """PATH, or PATH.part left by an interrupted recording."""
    p = Path(path)
    if p.exists():
        return p
    part = p.with_name(p.name + PART_SUFFIX)
    if part.exists():
        return part
    raise FileNotFoundError(f"{p}: no such recording (nor {part.name} from an interrupted run)")


def _file_summary(f):
    """The summary section of a cleanly closed file (read from its end), or None (interrupted, damaged)."""
    from mcap.reader import make_reader
    try:
        return make_reader(f).get_summary()
    except Exception:  # the library raises many kinds on a damaged footer; then there is no summary to use
        return None
    finally:
        f.seek(0)


def iter_recording(path: str | os.PathLike, summary: Optional[RecordingSummary] = None
                   ) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, schema name, log_time ns, data) for every message, streaming; stops quietly at a truncation.

    Every chunk's CRC is checked: a damaged chunk is skipped and, with ``summary``, reported in
    ``summary.damaged_chunks`` with the messages per topic it held (from its message index). A
    cleanly closed file's statistics give ``summary.expected``, so messages lost anywhere show.
    """
    from mcap.exceptions import McapError
    from mcap.records import Channel, Chunk, Footer, Message, MessageIndex, Metadata, Schema
    from mcap.stream_reader import StreamReader, breakup_chunk

    p = resolve_recording(path)
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str]] = {}
    with open(p, "rb") as f:
        file_summary = _file_summary(f)
        if file_summary is not None:   # channels first registered inside a damaged chunk keep their names
            schemas.update({i: s.name for i, s in file_summary.schemas.items()})
            channels.update({i: (c.topic, schemas.get(c.schema_id, "")) for i, c in file_summary.channels.items()})
            if summary is not None and file_summary.statistics is not None:
                for cid, n in file_summary.statistics.channel_message_counts.items():
                    topic = channels.get(cid, (f"channel {cid}", ""))[0]
                    summary.expected[topic] = summary.expected.get(topic, 0) + n
        bad: Optional[DamagedChunk] = None      # the damaged chunk whose message indexes follow
        n_chunks = 0
        try:
            for rec in StreamReader(f, record_size_limit=1 << 30, emit_chunks=True).records:
                if isinstance(rec, Chunk):
                    n_chunks += 1
                    try:
                        inner = breakup_chunk(rec, validate_crc=True)
                        bad = None
                    except Exception as exc:  # a chunk that fails its CRC or its decompression is damaged
                        bad = DamagedChunk(n_chunks, rec.message_start_time, rec.message_end_time,
                                           _crc_reason(exc))
                        if summary is not None:
                            summary.damaged_chunks.append(bad)
                        continue
                elif isinstance(rec, MessageIndex):
                    if bad is not None:
                        topic = channels.get(rec.channel_id, (f"channel {rec.channel_id}", ""))[0]
                        bad.lost[topic] = bad.lost.get(topic, 0) + len(rec.records)
                    continue
                else:
                    inner = [rec]
                for r in inner:
                    if isinstance(r, Schema):
                        schemas[r.id] = r.name
                    elif isinstance(r, Channel):
                        channels[r.id] = (r.topic, schemas.get(r.schema_id, ""))
                    elif isinstance(r, Message):
                        topic, schema = channels.get(r.channel_id, (f"channel {r.channel_id}", ""))
                        yield topic, schema, r.log_time, r.data
                    elif isinstance(r, Metadata) and summary is not None:
                        summary.metadata[r.name] = dict(r.metadata)
                    elif isinstance(r, Footer) and summary is not None:
                        summary.complete = True
        except (McapError, struct.error, EOFError, ValueError, KeyError) as exc:
            # An interrupted file ends inside a record: everything before it is intact.
            if summary is not None:
                summary.truncated_reason = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        if summary is not None and file_summary is not None:
            summary.complete = True    # closed cleanly, even if damage stopped the stream before the footer


def _crc_reason(exc: Exception) -> str:
    from mcap.stream_reader import CRCValidationError
    if isinstance(exc, CRCValidationError):
        return f"CRC mismatch (stored {exc.expected:#010x}, computed {exc.actual:#010x})"
    return f"cannot decompress ({type(exc).__name__}: {exc})"


def read_recording(path: str | os.PathLike) -> RecordingSummary:
    """Channels, message counts and time span of a recording (complete or interrupted), and its damage."""
    p = resolve_recording(path)
    with open(p, "rb") as f:
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            raise ValueError(f"{p}: not an MCAP file (no MCAP magic at the start)")
    summary = RecordingSummary(p)
    for topic, schema, t, _ in iter_recording(p, summary):
        ch = summary.channels.get(topic)
        if ch is None:
            ch = summary.channels[topic] = ChannelSummary(topic, schema)
        ch.count += 1
        ch.first_ns = t if ch.first_ns is None else min(ch.first_ns, t)
        ch.last_ns = t if ch.last_ns is None else max(ch.last_ns, t)
    return summary


def format_summary(s: RecordingSummary) -> str:
    state = "complete" if s.complete else "INTERRUPTED (read up to the last complete chunk)"
    lost = s.lost
    if s.damaged:
        state = (f"DAMAGED ({len(s.damaged_chunks)} chunk(s) fail their CRC, {sum(lost.values())} messages lost; "
                 f"{'closed cleanly' if s.complete else 'interrupted'})")
    lines = [f"{s.path}: {state}",
             f"  duration {s.duration_s:.2f} s, {s.messages} messages, {len(s.channels)} channels"]
    for d in s.damaged_chunks:
        held = ", ".join(f"{t} {n}" for t, n in sorted(d.lost.items())) or "unknown (no message index)"
        lines.append(f"  damaged chunk {d.number} (log time {d.start_ns * 1e-9:.3f}-{d.end_ns * 1e-9:.3f} s): "
                     f"{d.reason}; lost {held}")
    if lost:
        lines.append("  lost messages: " + ", ".join(f"{t} {n}" for t, n in sorted(lost.items())))
    for name, meta in s.metadata.items():
        lines.append(f"  metadata {name}: " + ", ".join(f"{k}={v}" for k, v in sorted(meta.items())))
    w = max((len(t) for t in s.channels), default=5)
    lines.append(f"  {'topic':<{w}}  {'schema':<26} {'count':>7} {'rate Hz':>8}")
    for topic in sorted(s.channels):
        c = s.channels[topic]
        lines.append(f"  {topic:<{w}}  {c.schema:<26} {c.count:>7} {c.rate_hz:>8.2f}")
    if s.truncated_reason:
        lines.append(f"  stopped at: {s.truncated_reason}")
    return "\n".join(lines)
