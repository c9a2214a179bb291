"""`vbnav run --realtime`: the simulated robot on the wall clock, with telemetry open, so monitor and send
work against it without hardware; the default simulated run says why it opens no network."""
import json
import subprocess
import sys
import time

from test_telemetry_net import free_port

VBNAV = [sys.executable, "-m", "vbnav.control.cli"]


def _wait_for_state(ep, tries=100):
    for _ in range(tries):
        mon = subprocess.run(VBNAV + ["monitor", "--once", "--json", *ep], capture_output=True, text=True,
                             timeout=30)
        if mon.returncode == 0:
            return json.loads(mon.stdout)
        time.sleep(0.2)
    raise AssertionError(f"no state from the robot: {mon.stderr}")


def test_realtime_sim_run_is_watched_and_driven_with_monitor_and_send(tmp_path):
    port = free_port()
    cfg = tmp_path / "sim.yaml"
    # A loaded test machine must not trip the deadline or stall stops: not what is tested here.
    cfg.write_text(f"telemetry:\n  listen: ['tcp/127.0.0.1:{port}']\n"
                   "loop: {max_missed_streak: 1000000, stall_periods: 1000000}\n")
    robot = subprocess.Popen(VBNAV + ["run", "--realtime", "--no-camera", "--controller", "teleop", "-c", str(cfg),
                                      "--duration", "60", "--json"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ep = ["--connect", f"tcp/127.0.0.1:{port}"]
    try:
        before = _wait_for_state(ep)
        assert before["mode"] == "teleop"
        sent = subprocess.run(VBNAV + ["send", "teleop", "0.3", "0", "--duration", "2", *ep],
                              capture_output=True, text=True, timeout=60)
        assert sent.returncode == 0, sent.stderr
        after = _wait_for_state(ep)
    finally:
        robot.terminate()
        out, err = robot.communicate(timeout=60)
    assert "simulated clock" not in err
    # 2 s of 0.3 m/s teleop (less the acceleration ramp and any scheduling gap): well over 0.2 m forward.
    assert after["pose"]["odom"]["z"] - before["pose"]["odom"]["z"] > 0.2, (before["pose"], after["pose"])
    summary = json.loads(out)
    assert summary["reason"] == "signal"


def test_simulated_clock_run_says_the_network_is_not_opened():
    r = subprocess.run(VBNAV + ["run", "--no-camera", "--duration", "0.5"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    assert "add --realtime to watch and command the simulated robot" in r.stderr


def test_a_simulated_vision_latency_on_the_wall_clock_is_refused(tmp_path, capsys):
    """sim.vision_latency_s is added to the estimates on the simulated clock only; with sim.realtime: true (or
    run --realtime) the vision thread's own time is the latency, and a written value was accepted and never
    read. Refused, naming it, at load and by --realtime; on the simulated clock it loads and is used."""
    import pytest

    from vbnav.control.cli import main
    from vbnav.control.config import ConfigError, parse_config
    from vbnav.control.runtime.factory import make_pipeline, make_robot
    with pytest.raises(ConfigError, match=r"sim\.vision_latency_s 0\.2 s.*sim\.realtime"):
        parse_config({"sim": {"realtime": True, "vision_latency_s": 0.2}})
    cfg = tmp_path / "late.yaml"
    cfg.write_text("sim: {vision_latency_s: 0.2}\n")
    assert main(["run", "-c", str(cfg), "--realtime", "--no-telemetry", "--no-camera", "--duration", "0.1"]) == 2
    err = capsys.readouterr().err
    assert "--realtime" in err and "sim.vision_latency_s 0.2 s" in err, err
    sim = parse_config({"sim": {"vision_latency_s": 0.2}})          # the simulated clock: used
    robot = make_robot(sim, with_camera=True)
    assert make_pipeline(sim, robot.clock, robot.camera, []).latency_ns == 200_000_000
    # the simulated section of a robot with real drivers is kept, unused (the simulator is off)
    parse_config({"sim": {"realtime": True, "vision_latency_s": 0.2},
                  "drive": {"driver": "dynamixel"}, "camera": {"driver": "v4l2"}})
