"""Operator session: teleop in idle, cmd/mode teach records a route, cmd/mode repeat patrols it."""
from vbnav.control.config import load_config
from vbnav.control.runtime.factory import make_robot
from vbnav.control.controllers.operator import OperatorController
from vbnav.control.route import load_route
from vbnav.control.runtime.runtime import OperatorCommand, Runtime


def test_idle_teach_idle_repeat(tmp_path):
    cfg = load_config(None, overrides={"sim": {"start_pose": [-3.5, -1.0, 0.0]},
                                       "controller": {"routes_dir": str(tmp_path)}})
    start = cfg.sim.start()
    robot = make_robot(cfg, with_camera=True)
    pipeline = robot.pipeline
    ctl = OperatorController(cfg, pipeline, cfg.safety.command_timeout_s)
    rt = Runtime(cfg, robot.drive, ctl, robot.clock, pipeline)
    ctl.attach(rt)
    route = tmp_path / "route"
    t0 = robot.clock.now_ns()
    script = []   # (time s, command)
    for k in range(0, 60):                       # 0-6 s: teleop at 10 Hz, straight ahead
        script.append((0.1 * k, OperatorCommand("teleop", (0.3, 0.0), "op")))
    script.insert(5, (0.45, OperatorCommand("mode", ("teach", route.name), "op")))
    script.append((6.5, OperatorCommand("mode", ("idle",), "op")))
    script.append((7.0, OperatorCommand("mode", ("repeat", "missing"), "op")))
    script.sort(key=lambda x: x[0])
    modes, taught_end = [], {}

    def feed(r, ctx, twist, wheels):
        t = (ctx.now_ns - t0) * 1e-9
        while script and script[0][0] <= t:
            r.submit(script.pop(0)[1])
        modes.append(ctl.name)
        if t >= 7.5 and "repeat_sent" not in taught_end:
            # The operator carries the robot back to where teaching started, then asks for a repeat.
            robot.drive.physics.pose = start
            r.submit(OperatorCommand("mode", ("repeat", route.name), "op"))
            taught_end["repeat_sent"] = t
        if ctl.mode == "repeat":
            taught_end["repeating"] = True
        if taught_end.get("repeating") and ctl.name == "idle":
            r.loop.stop()

    rt.cycle_observers.append(feed)
    result = rt.run(duration_s=90.0)
    ctl.close()
    assert result.reason in ("stopped", "duration"), result.message
    kfs = load_route(route).keyframes
    assert len(kfs) >= 3, "teach mode recorded keyframes"
    assert {"idle", "teach", "repeat"} <= set(modes), set(modes)
    rejected = [e for e in result.events if e.kind == "rejected" and e.cause == "mode"]
    assert any("missing" in e.message for e in rejected), [e.message for e in rejected]
    # The repeat ended at the route's end and went back to idle on its own.
    assert modes[-1] == "idle"
    end = robot.drive.physics.pose
    last = kfs[-1].odom
    # measured 3.0 cm / 3.7 mm on 2026-11-30
    assert abs(end.z - (start.z + last.z)) < 0.06 and abs(end.x - start.x) < 0.008
