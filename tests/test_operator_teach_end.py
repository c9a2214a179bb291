"""An operator-mode teach that a fault ends is closed as ``vbnav teach`` closes it: incomplete.

Found by an audit of messages that promise something: ``vbnav run --controller operator`` closed the route
being taught complete whatever ended the run, so ``route info`` and ``repeat`` took a route a drive fault cut
short for a whole one. ``OperatorController.close(complete=...)`` is given the run's end (control/commands/run.py:
complete when it ended well, ``ENDED_WELL``).
"""
from __future__ import annotations

import json

import pytest

from vbnav.control.config import load_config
from vbnav.control.controllers.operator import OperatorController
from vbnav.control.runtime.factory import make_robot
from vbnav.control.runtime.mailbox import OperatorCommand
from vbnav.control.runtime.runtime import ENDED_WELL, Runtime


@pytest.mark.parametrize("fault", [True, False], ids=["drive-fault", "ended-well"])
def test_a_teach_a_fault_ends_is_closed_incomplete(tmp_path, fault):
    cfg = load_config(None)
    cfg.controller.routes_dir = str(tmp_path / "routes")
    (tmp_path / "routes").mkdir()
    if fault:
        cfg.drive.options = {"fail_after_s": 3.0}
        cfg.drive.reconnect_window_s = 0.0
    robot = make_robot(cfg, with_camera=True)
    ctl = OperatorController(cfg, robot.pipeline, cfg.safety.command_timeout_s)
    rt = Runtime(cfg, robot.drive, ctl, robot.clock, robot.pipeline)
    ctl.attach(rt)

    def teach_while_driving(r, ctx, twist, wheels):
        if r.cycle == 1:
            r.submit(OperatorCommand("mode", ("teach", "r1"), "test"))
        if r.cycle > 5 and r.cycle % 10 == 0:
            r.submit(OperatorCommand("teleop", (0.4, 0.0), "test"))
    rt.cycle_observers.append(teach_while_driving)
    result = rt.run(6.0)
    assert (result.reason not in ENDED_WELL) == fault, result.message
    assert ctl.followed_route == "r1"                         # the telemetry state's route (link.py)
    ctl.close(complete=result.reason in ENDED_WELL)          # as vbnav run closes it
    manifest = json.loads((tmp_path / "routes" / "r1" / "manifest.json").read_text())
    assert len(manifest["keyframes"]) >= 3
    assert manifest["complete"] is (not fault)
