"""drivers/atomic_file.py: what every recorder writes through (routes, maps, calibrations, plots)."""
from __future__ import annotations

import os

import pytest

from vbnav.drivers import atomic_file
from vbnav.drivers.atomic_file import atomic_output, write_atomic


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path, monkeypatch):
    p = tmp_path / "route.json"
    write_atomic(p, "old")

    def full_disk(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(atomic_file.os, "replace", full_disk)
    with pytest.raises(OSError, match="No space"):
        write_atomic(p, "new")
    monkeypatch.undo()
    assert p.read_text() == "old" and sorted(x.name for x in tmp_path.iterdir()) == ["route.json"]


def test_the_replaced_file_keeps_its_permissions_and_a_new_one_follows_the_umask(tmp_path):
    p = tmp_path / "robot.yaml"
    p.write_text("a: 1\n")
    os.chmod(p, 0o640)
    write_atomic(p, "a: 2\n")
    assert p.read_text() == "a: 2\n" and (p.stat().st_mode & 0o777) == 0o640
    q = write_atomic(tmp_path / "new.txt", b"\x00\x01")
    umask = os.umask(0o022)
    os.umask(umask)
    assert (q.stat().st_mode & 0o777) == 0o666 & ~umask and q.read_bytes() == b"\x00\x01"


def test_a_writer_that_wants_a_file_name_gets_one_with_the_target_s_suffix(tmp_path):
    out = tmp_path / "plot.png"
    with atomic_output(out) as tmp:
        assert tmp.parent == tmp_path and tmp.name.endswith(".png") and not out.exists()
        tmp.write_bytes(b"png")
    assert out.read_bytes() == b"png" and sorted(x.name for x in tmp_path.iterdir()) == ["plot.png"]
    with pytest.raises(ValueError):
        with atomic_output(out) as tmp:
            tmp.write_bytes(b"half")
            raise ValueError("the plot failed")
    assert out.read_bytes() == b"png" and sorted(x.name for x in tmp_path.iterdir()) == ["plot.png"]



def test_a_folder_that_cannot_take_the_temporary_file_is_said_naming_the_target(tmp_path):
    """A folder gone (or not writable) since the command's checks: the error named the hidden temporary file
    ('.m.json.aezxbq8s.tmp: Permission denied'), a name the user never gave. It names the target."""
    gone = tmp_path / "gone"
    gone.mkdir()
    gone.rmdir()
    for write in (lambda p: write_atomic(p, "x"), lambda p: atomic_output(p).__enter__()):
        with pytest.raises(OSError) as exc:
            write(gone / "m.json")
        assert exc.value.filename == str(gone / "m.json") and exc.value.strerror


def test_a_map_that_cannot_be_written_is_a_map_file_error_naming_it(tmp_path):
    """save_map's callers (map build, goto --map-out) say 'NOT SAVED' and keep their summary on a MapFileError;
    an OSError from the disk went past them as an error of the command, the run's summary lost."""
    from vbnav.control.line_map_file import MapFileError, save_map
    from vbnav.vision.line_map import LineMap
    target = tmp_path / "gone" / "m.json"
    with pytest.raises(MapFileError, match=f"{target}: not saved: No such file or directory"):
        save_map(LineMap(), target)


def test_an_output_folder_this_user_cannot_write_is_refused_before_the_run(tmp_path, monkeypatch):
    """Found as a user without write access: map build and goto --map-out drove to the end, then lost the map.
    The folder is checked with the command's other output checks. (The suite runs as root, who may write
    anywhere, so the permission is denied by os.access here.)"""
    from vbnav.control.commands._common import output_file
    from vbnav.drivers.errors import InputError
    output_file(tmp_path / "m.json", "--out")                      # writable: accepted
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if str(p) == str(tmp_path) else real(p, mode, **kw))
    with pytest.raises(InputError, match=f"--out {tmp_path / 'm.json'}: the folder {tmp_path} is not writable"):
        output_file(tmp_path / "m.json", "--out")
