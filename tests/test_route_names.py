"""Routes named over the network (cmd/mode) stay inside controller.routes_dir, and errors show no outside path."""
from __future__ import annotations

import os

import numpy as np
import pytest

from vbnav.control.config import load_config
from vbnav.control.controllers.operator import OperatorController
from vbnav.control.route import RouteError, RouteWriter, resolve_route, routes_root
from vbnav.control.runtime.factory import make_robot
from vbnav.control.runtime.runtime import OperatorCommand, Runtime

from test_route import CAM, MOUNT, make_kf

BAD_NAMES = ["../x", "../../etc/x", "/etc/x", "a/b", "..", ".", ".hidden", "", "a\\b", "x" * 129, "a\nb", "hall\n"]


@pytest.mark.parametrize("name", BAD_NAMES)
def test_paths_are_refused_and_the_message_holds_no_path(tmp_path, name):
    root = tmp_path / "routes"
    root.mkdir()
    for must_exist in (False, True):
        with pytest.raises(RouteError) as e:
            resolve_route(root, name, must_exist)
        assert "/" not in str(e.value) and str(tmp_path) not in str(e.value)


def test_symlinks_leading_out_are_refused(tmp_path):
    root, outside = tmp_path / "routes", tmp_path / "secret"
    root.mkdir()
    outside.mkdir()
    (root / "escape").symlink_to(outside)
    (root / "dangling").symlink_to(tmp_path / "nowhere" / "new")     # teach would create it outside
    for name in ("escape", "dangling"):
        for must_exist in (False, True):
            with pytest.raises(RouteError, match="symbolic link") as e:
                resolve_route(root, name, must_exist)
            assert str(tmp_path) not in str(e.value) and "secret" not in str(e.value)


def test_names_resolve_inside_the_routes_dir(tmp_path):
    root = tmp_path / "routes"
    root.mkdir()
    assert resolve_route(root, "hall-2.v1", must_exist=False) == (root / "hall-2.v1").resolve()
    with pytest.raises(RouteError, match=r"route 'hall': no such route") as e:
        resolve_route(root, "hall", must_exist=True)
    assert str(tmp_path) not in str(e.value)
    (root / "hall").mkdir()
    assert resolve_route(root, "hall", must_exist=True) == (root / "hall").resolve()


def test_routes_dir_relative_to_the_config_file_and_home(tmp_path):
    assert routes_root("routes", str(tmp_path / "robot.yaml")) == tmp_path / "routes"
    assert routes_root("~/r", None) == __import__("pathlib").Path(os.path.expanduser("~/r"))
    assert routes_root(str(tmp_path / "abs"), "/elsewhere/robot.yaml") == tmp_path / "abs"


def _operator(tmp_path):
    cfg = load_config(None, overrides={"controller": {"routes_dir": str(tmp_path / "routes")}})
    robot = make_robot(cfg, with_camera=True)
    ctl = OperatorController(cfg, robot.pipeline, cfg.safety.command_timeout_s)
    rt = Runtime(cfg, robot.drive, ctl, robot.clock, robot.pipeline)
    ctl.attach(rt)
    return ctl, rt


def _switch(ctl, rt, mode, name):
    ctl.handle_command(OperatorCommand("mode", (mode, name), "op"), 0)
    if ctl._worker is not None:
        ctl._worker.join(timeout=10.0)
    if ctl._pending is not None:
        ctl._apply_pending()


def test_operator_teach_and_repeat_only_inside_routes_dir(tmp_path):
    ctl, rt = _operator(tmp_path)
    (tmp_path / "routes").mkdir()
    (tmp_path / "routes" / "out").symlink_to(tmp_path)
    (tmp_path / "elsewhere").mkdir()
    RouteWriter(tmp_path / "elsewhere" / "r", "sim", CAM, MOUNT).close()
    for mode in ("teach", "repeat"):
        for name in ("../../etc/x", str(tmp_path / "elsewhere" / "r"), "../elsewhere/r", "out", "nosuch/x"):
            _switch(ctl, rt, mode, name)
            assert ctl.mode == "idle", (mode, name)
            assert str(tmp_path) not in ctl.errors[-1] and "elsewhere" not in ctl.errors[-1], ctl.errors[-1]
    assert not (tmp_path / "etc").exists() and sorted(os.listdir(tmp_path / "routes")) == ["out"]
    _switch(ctl, rt, "repeat", "missing")
    assert ctl.errors[-1] == "mode repeat: route 'missing': no such route in the routes directory"
    # A broken route inside the routes directory: the error names the route, not where it lives.
    bad = tmp_path / "routes" / "broken"
    with RouteWriter(bad, "sim", CAM, MOUNT) as w:
        w.append(make_kf(np.random.default_rng(0), 0))
    os.remove(bad / "kf_00000.npz")
    _switch(ctl, rt, "repeat", "broken")
    assert ctl.mode == "idle" and "route 'broken': kf_00000.npz: missing" in ctl.errors[-1], ctl.errors[-1]
    assert str(tmp_path) not in ctl.errors[-1]
    _switch(ctl, rt, "teach", "new")
    assert ctl.mode == "teach" and (tmp_path / "routes" / "new" / "manifest.json").is_file()
    ctl.close()


def test_a_trailing_newline_is_no_route_name():
    """The name's pattern ended in '$', which also matches before a final newline: 'hall\\n' passed the check
    (and the command model) and teach made a directory named with a newline."""
    from vbnav.control.comms.operator_commands import CommandRejected, TeleopLimits, parse_command
    with pytest.raises(CommandRejected, match="route must be a plain name"):
        parse_command("mode", '{"mode": "teach", "route": "hall\\n"}', TeleopLimits(1.0, 1.0))
