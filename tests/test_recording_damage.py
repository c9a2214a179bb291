"""Recordings are never silently replaced, and damage inside them is found and reported."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from vbnav.control.comms.recording import McapRecorder, format_summary, iter_recording, read_recording


def _record(path, n=600, **kw):
    rec = McapRecorder(path, "sim", chunk_size=4096, **kw)
    for k in range(n):
        msg = {"schema": "vbnav.state", "seq": k, "pose": {"odom": {"x": 0.0, "z": 0.01 * k, "theta": 0.0}}}
        rec.state(k * 50_000_000, json.dumps(msg).encode(), msg)
    return rec


def _chunks(path):
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        return make_reader(f).get_summary().chunk_indexes


def _chunk_spans_of_a_file_without_summary(path):
    """(offset, length) of each chunk record, walking the records (opcode, u64 length, body) after the magic."""
    import struct
    data = open(path, "rb").read()
    i, spans = 8, []
    while i + 9 <= len(data):
        op, n = data[i], struct.unpack_from("<Q", data, i + 1)[0]
        if op == 0x06:
            spans.append((i, 9 + n))
        i += 9 + n
    return spans


def _flip(path, offset, n=8):
    with open(path, "r+b") as f:
        f.seek(offset)
        data = f.read(n)
        f.seek(offset)
        f.write(bytes(b ^ 0xFF for b in data))


def _record_info(path):
    return subprocess.run([sys.executable, "-m", "vbnav.control.cli", "record-info", str(path)],
                          capture_output=True, text=True, timeout=60)


def test_a_flipped_chunk_is_named_with_its_lost_messages(tmp_path):
    path = tmp_path / "r.mcap"
    _record(path).close()
    total = read_recording(path).messages
    chunks = _chunks(path)
    assert len(chunks) >= 5 and not read_recording(path).damaged and _record_info(path).returncode == 0
    third = chunks[2]
    _flip(path, third.chunk_start_offset + third.chunk_length - 40)
    s = read_recording(path)
    assert [d.number for d in s.damaged_chunks] == [3] and s.damaged and s.complete
    lost = s.damaged_chunks[0].lost["/vbnav/state"]
    # a state carries a pose and an odometry message
    assert lost > 0 and s.lost == {"/vbnav/state": lost, "/vbnav/pose/odom": lost, "/vbnav/odometry": lost}
    assert s.messages == total - 3 * lost and sum(1 for _ in iter_recording(path)) == s.messages
    r = _record_info(path)
    assert r.returncode == 1 and "DAMAGED" in r.stdout and "damaged chunk 3" in r.stdout, r.stdout
    assert f"lost /vbnav/odometry {lost}, /vbnav/pose/odom {lost}, /vbnav/state {lost}" in r.stdout and "cannot decompress" in r.stdout


def test_a_chunk_whose_crc_does_not_match_is_damaged(tmp_path):
    path = tmp_path / "r.mcap"
    _record(path).close()
    second = _chunks(path)[1]
    _flip(path, second.chunk_start_offset + 1 + 8 + 3 * 8, n=4)      # the chunk's stored CRC (data intact)
    r = _record_info(path)
    assert r.returncode == 1 and "damaged chunk 2" in r.stdout and "CRC mismatch" in r.stdout, r.stdout


def test_damage_in_an_interrupted_recording_is_counted_from_the_message_index(tmp_path):
    path = tmp_path / "r.mcap"
    rec = _record(path)
    rec._writer.flush()          # what a SIGKILL leaves: PATH.part without summary (the recorder never closes)
    rec._file.flush()
    part = tmp_path / "r.mcap.part"
    chunks = _chunk_spans_of_a_file_without_summary(part)
    start, length = chunks[len(chunks) // 2]
    _flip(part, start + length - 40)       # inside the compressed data of a chunk in the middle
    s = read_recording(path)
    assert not s.complete and s.damaged and len(s.damaged_chunks) == 1, format_summary(s)
    assert sum(s.lost.values()) > 0
    assert _record_info(path).returncode == 1


def test_a_closed_recording_with_an_unreadable_end_is_damaged(tmp_path):
    path = tmp_path / "r.mcap"
    _record(path).close()
    with open(path, "r+b") as f:
        f.truncate(os.path.getsize(path) - 100)
    s = read_recording(path)
    assert s.damaged and _record_info(path).returncode == 1


def test_record_refuses_an_existing_file_unless_overwrite(tmp_path):
    path = tmp_path / "r.mcap"
    _record(path, n=10).close()
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="exists .use --overwrite"):
        McapRecorder(path, "sim")
    rec = _record(path, n=20, overwrite=True)
    assert path.read_bytes() == before               # the old one stays until the new one is complete
    rec.close()
    assert read_recording(path).channels["/vbnav/state"].count == 20
    (tmp_path / "i.mcap.part").write_bytes(b"interrupted")
    with pytest.raises(FileExistsError, match="i.mcap.part of an interrupted recording"):
        McapRecorder(tmp_path / "i.mcap", "sim")


@pytest.mark.parametrize("command", [["run", "--no-camera", "--duration", "0.3"],
                                     ["repeat", "--path", "nosuch", "--duration", "0.1"]])
def test_cli_record_onto_an_existing_file_is_refused(tmp_path, command):
    path = tmp_path / "old.mcap"
    path.write_bytes(b"precious")
    cli = [sys.executable, "-m", "vbnav.control.cli"]
    r = subprocess.run(cli + command + ["--record", str(path)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "exists (use --overwrite" in r.stderr and path.read_bytes() == b"precious"
    if command[0] == "run":
        r = subprocess.run(cli + command + ["--record", str(path), "--overwrite"], capture_output=True, text=True,
                           timeout=120)
        assert r.returncode == 0, r.stderr
        assert read_recording(path).channels["/vbnav/state"].count > 0


def test_no_flip_anywhere_loses_messages_silently(tmp_path):
    """8-byte flips spread over the whole file: every one that loses messages is reported as damage."""
    clean = tmp_path / "clean.mcap"
    _record(clean).close()
    data, total = clean.read_bytes(), read_recording(clean).messages
    path = tmp_path / "r.mcap"
    reported = 0
    for offset in range(64, len(data) - 8, len(data) // 40):
        path.write_bytes(data)
        _flip(path, offset)
        try:
            s = read_recording(path)
        except ValueError:               # refused outright (not an MCAP file): nothing silent either
            reported += 1
            continue
        assert s.messages == total or s.damaged, (offset, format_summary(s))
        reported += s.damaged
    assert reported >= 20


def test_overwrite_keeps_the_part_of_an_interrupted_recording(tmp_path, capsys):
    """--overwrite replaces PATH when the new recording is complete; the PATH.part of an earlier crash is
    another recording (the only copy of that run): it was truncated as soon as the new one opened."""
    path = tmp_path / "i.mcap"
    crashed = _record(tmp_path / "crashed.mcap", n=30)
    crashed._writer.flush()
    crashed._file.close()                               # as SIGKILL leaves it: no summary, still .part
    part = tmp_path / "crashed.mcap.part"
    os.rename(part, tmp_path / "i.mcap.part")
    before = (tmp_path / "i.mcap.part").read_bytes()
    rec = _record(path, n=10, overwrite=True)
    kept = tmp_path / "i.interrupted-1.mcap.part"
    assert kept.read_bytes() == before
    assert rec.kept_part == kept and f"kept as {kept}" in capsys.readouterr().err
    rec.close()
    assert read_recording(path).channels["/vbnav/state"].count == 10
    assert read_recording(kept).channels["/vbnav/state"].count > 0     # still readable as the crash left it
    (tmp_path / "i.mcap.part").write_bytes(b"a second crash")
    (tmp_path / "j.mcap.part").write_bytes(b"crashed")
    (tmp_path / "j.interrupted-1.mcap.part").write_bytes(b"crashed before")
    with pytest.raises(FileExistsError, match=r"kept as j\.interrupted-2\.mcap\.part"):   # the name it will get
        McapRecorder(tmp_path / "j.mcap", "sim")
    _record(path, n=5, overwrite=True).close()                       # a unique name: the first kept one stays
    assert kept.read_bytes() == before
    assert (tmp_path / "i.interrupted-2.mcap.part").read_bytes() == b"a second crash"



def test_close_makes_the_rename_durable(tmp_path, disk_log):
    """The rename PATH.part -> PATH is an entry of the folder: without an fsync of the folder after it, a power
    cut could leave only PATH.part although close() returned."""
    rec = _record(tmp_path / "r.mcap", n=10)
    rec.close()
    assert disk_log.durable(tmp_path / "r.mcap"), disk_log


def test_record_info_says_an_interrupted_recording_lies_beside_the_complete_one(tmp_path, capsys):
    """A run with --overwrite that was killed leaves the earlier complete PATH and its own PATH.part:
    record-info PATH described the earlier run as 'complete' and said nothing of the newer, interrupted one."""
    from vbnav.control import cli
    path = tmp_path / "r.mcap"
    _record(path, n=10).close()
    newer = _record(path, n=30, overwrite=True)
    newer._writer.flush()
    newer._file.close()                                  # killed: PATH.part stays beside PATH
    assert cli.main(["record-info", str(path)]) == 0
    out, err = capsys.readouterr()
    assert f"{path}: complete" in out
    assert f"note: {path.name}.part beside it is an interrupted recording (read it with 'vbnav record-info " \
           f"{path}.part')" in err, err


def test_a_recording_that_cannot_start_leaves_no_part(tmp_path, monkeypatch):
    """A failure while the recording's header is written (a full disk) left an empty PATH.part open: the next
    run then refused the path for an 'interrupted recording' that never held a message."""
    import errno

    from mcap.writer import Writer

    def full(self, *a, **kw):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Writer, "add_metadata", full)
    with pytest.raises(OSError, match="No space"):
        McapRecorder(tmp_path / "r.mcap", "sim")
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []
    _record(tmp_path / "r.mcap", n=3).close()                  # the path is free for the next run
