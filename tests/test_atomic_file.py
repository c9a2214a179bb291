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

