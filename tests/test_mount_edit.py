"""control/config/mount_edit.py: calibrate mount edits a config in place, keeping what it does not set."""
from __future__ import annotations

import os

from vbnav.control.config.mount_edit import set_camera_mount


def test_calibrate_mount_keeps_the_line_endings_of_a_config(tmp_path):
    """A config with CRLF line endings (edited on Windows) came back with LF on every line: ``calibrate
    mount`` promises to keep every line it does not edit as it was."""
    p = tmp_path / "robot.yaml"
    p.write_bytes(b"# my robot\r\ncamera:\r\n  driver: sim\r\n  mount:\r\n    height: 0.3  # tape\r\n  rate_hz: 15\r\n")
    set_camera_mount(p, {"height": 0.25, "pitch_deg": 2.0})
    assert p.read_bytes() == (b"# my robot\r\ncamera:\r\n  driver: sim\r\n  mount:\r\n    height: 0.25  # tape\r\n"
                              b"    pitch_deg: 2.0\r\n  rate_hz: 15\r\n")


def test_a_config_that_is_a_symbolic_link_stays_one(tmp_path):
    """``calibrate mount`` on a config that is a link (robot.yaml -> configs/robot-v2.yaml) replaced the link
    with an edited copy: the file it pointed at kept the old mount, and every other link to it too."""
    (tmp_path / "configs").mkdir()
    target = tmp_path / "configs" / "robot-v2.yaml"
    target.write_text("camera:\n  driver: sim\n  mount:\n    height: 0.3\n")
    link = tmp_path / "robot.yaml"
    link.symlink_to(os.path.join("configs", "robot-v2.yaml"))
    set_camera_mount(link, {"height": 0.25})
    assert link.is_symlink() and "height: 0.25" in target.read_text()
    assert sorted(p.name for p in (tmp_path / "configs").iterdir()) == ["robot-v2.yaml"]

