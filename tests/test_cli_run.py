"""`vbnav run` as a process: finishes a scripted drive, stops on real SIGINT/SIGTERM."""
import json
import signal
import subprocess
import sys
import time

import pytest

VBNAV = [sys.executable, "-m", "vbnav.control.cli"]


def test_no_camera_is_refused_when_the_config_enables_the_obstacle_stop():
    """--no-camera would silently switch off a safety function the configuration asks for."""
    from vbnav.control.cli import main
    r = subprocess.run(VBNAV + ["run", "-c", "sim_stereo", "--no-camera", "--duration", "0.1"], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and "--no-camera" in r.stderr and "obstacles.enabled is true" in r.stderr, r.stderr
    assert main(["run", "-c", "sim_stereo", "--duration", "0.1", "--no-telemetry"]) == 0   # with it: runs


def test_run_scripted_sim_clock(tmp_path):
    r = subprocess.run(VBNAV + ["run", "--no-camera", "--json"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["reason"] == "finished"
    x, z, th = summary["final_odometry"]
    # Default script: 3 s straight at 0.3 m/s, then a 4 s arc at 0.4 rad/s: it ends ahead and to the right.
    assert z > 1.5 and x > 0.3 and th > 1.0
    assert summary["timing"]["cycles"] > 700



def test_run_json_counts_the_cycles_the_loop_ran_once(capsys):
    """`run --json` reported "cycles": 50 beside "timing": {"cycles": 51} for a 0.5 s run at 100 Hz: the top one
    was the index of the last cycle (cycles 0 to 50 ran; the one at 0.5 s drives too, then ends the run). Both
    are now the count of cycles run, the same number."""
    from vbnav.control.cli import main
    assert main(["run", "--no-camera", "--json", "--duration", "0.5", "--no-telemetry"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["reason"] == "duration"
    assert summary["cycles"] == summary["timing"]["cycles"] == 51

# Real-clock runs on a shared 2-core machine: a scheduling hiccup of 50 ms would latch the loop-stall stop
# (5 periods at 100 Hz) and the robot would sit still; stalls themselves are tested on the simulated clock.
RELAXED_STALL = "loop:\n  stall_periods: 100\n"


def _wait_for_first_progress_line(p, timeout_s: float) -> str:
    """Read the run's stderr until its first progress line ("t=...", printed as the loop starts), not a fixed
    sleep: start-up takes seconds longer on a loaded machine."""
    seen, deadline = "", time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = p.stderr.readline()
        if not line:
            break
        seen += line
        if line.startswith("t="):
            return seen
    p.kill()
    pytest.fail(f"no progress line from vbnav run within {timeout_s} s: {seen}")


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 130)])
def test_run_realtime_stops_on_signal(tmp_path, sig, code):
    cfg = tmp_path / "rt.yaml"
    cfg.write_text("sim:\n  realtime: true\ncontroller:\n  kind: scripted\n  script: [[0.2, 0.0, 60.0]]\n" + RELAXED_STALL)
    # --no-telemetry: a real-time run would listen on tcp/127.0.0.1:7447, which parallel test runs share.
    p = subprocess.Popen(VBNAV + ["run", "--no-camera", "--no-telemetry", "-c", str(cfg)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    first = _wait_for_first_progress_line(p, timeout_s=60)     # the loop runs: its handlers are installed
    time.sleep(0.5)
    p.send_signal(sig)
    out, err = p.communicate(timeout=30)
    err = first + err
    assert p.returncode == code, (out, err)
    assert f"run ended: signal (received {signal.Signals(sig).name})" in out
    assert "safety trip: signal" in out


def test_run_realtime_with_threaded_camera(tmp_path):
    """Real clock: the camera and vision run on their own thread; frames stay fresh (no stale-camera stop)."""
    cfg = tmp_path / "rt.yaml"
    cfg.write_text("sim:\n  realtime: true\ncamera:\n  rate_hz: 10\n"
                   "controller:\n  kind: scripted\n  script: [[0.2, 0.0, 60.0]]\n" + RELAXED_STALL)
    r = subprocess.run(VBNAV + ["run", "-c", str(cfg), "--camera", "--duration", "3", "--json", "--no-telemetry"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["reason"] == "duration"
    assert not [e for e in summary["events"] if e["cause"] == "camera_stale"], summary["events"]
    assert summary["final_odometry"][1] > 0.3     # it drove: ~0.2 m/s for ~3 s


def test_teach_and_repeat_exit_3_when_the_drive_is_lost(tmp_path):
    """vbnav's exit codes: 3 is a hardware fault (as for run), 1 a job that ran and failed."""
    from vbnav.control.cli import main
    assert main(["teach", "--out", str(tmp_path / "route"), "--duration", "4"]) == 0
    lossy = tmp_path / "lossy.yaml"
    lossy.write_text("drive:\n  driver: sim\n  reconnect_window_s: 0.2\n  options: {fail_after_s: 1.0}\n")
    assert main(["repeat", "-c", str(lossy), "--path", str(tmp_path / "route"), "--duration", "5"]) == 3


@pytest.mark.parametrize("argv, says", [
    (["run", "--live-view", "--no-telemetry", "--realtime", "--duration", "0.1"], "--no-telemetry"),
    (["run", "--live-view", "--duration", "0.1"], "add --realtime"),
    (["map", "build", "-c", "sim_stereo", "--live-view", "--duration", "0.1", "--out", "{tmp}/m.json"],
     "add --realtime"),
])
def test_a_live_view_that_could_not_be_served_is_refused(tmp_path, capsys, argv, says):
    """--live-view was accepted and nothing was served (no telemetry session; or the simulated clock)."""
    from vbnav.control.cli import main
    assert main([a.format(tmp=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err
    assert "--live-view" in err and says in err, err
    assert not (tmp_path / "m.json").exists()


def test_map_build_that_ends_in_a_fault_keeps_the_map_and_says_so(tmp_path, capsys):
    """The drive lost 1 s in: the map mapped so far is written, labelled, and the exit code is a hardware
    fault's (it exited 0, as for a finished drive)."""
    from pathlib import Path

    from vbnav.control.cli import main
    from vbnav.control.line_map_file import load_map
    text = (Path(__file__).resolve().parents[1] / "configs" / "sim_stereo.yaml").read_text()
    lossy = tmp_path / "lossy_stereo.yaml"
    lossy.write_text(text.replace("drive:\n  driver: sim\n", "drive:\n  driver: sim\n  reconnect_window_s: 0.2\n"
                                  "  options: {fail_after_s: 1.0}\n"))
    assert main(["map", "build", "-c", str(lossy), "--out", str(tmp_path / "m.json"), "--duration", "3"]) == 3
    out = capsys.readouterr().out
    assert "map build ended: drive" in out and "(the map up to the fault)" in out, out
    lmap, meta = load_map(tmp_path / "m.json")
    assert meta["frames"] > 0


@pytest.mark.parametrize("argv", [["--controller", "teleop", "--no-telemetry"],
                                  ["--controller", "operator", "--no-telemetry", "--no-camera"],
                                  ["--controller", "teleop", "-c", "{tmp}/quiet.yaml"]])
def test_a_run_driven_from_the_network_without_the_network_is_refused(tmp_path, capsys, argv):
    """--controller teleop (or operator) with --no-telemetry or telemetry.enabled: false was accepted and
    ran holding the robot still until --duration: its commands only come over the network, kept closed."""
    from vbnav.control.cli import main
    (tmp_path / "quiet.yaml").write_text("telemetry: {enabled: false}\n")
    assert main(["run", "--realtime", "--duration", "0.5", *[a.format(tmp=tmp_path) for a in argv]]) == 2
    err = capsys.readouterr().err
    assert f"--controller {argv[1]}: takes its commands over the network, which " in err, err


@pytest.mark.parametrize("argv, says", [
    (["run", "--duration", "0.1"], "simulated clock"),
    (["run", "--realtime", "--no-telemetry", "--duration", "0.1"], "--no-telemetry keeps closed"),
    (["run", "--realtime", "-c", "{tmp}/closed.yaml", "--duration", "0.1"], "telemetry.enabled: false keeps closed"),
    (["teach", "--out", "{tmp}/route", "--duration", "0.1"], "simulated clock"),
    (["repeat", "--path", "{tmp}/none", "--duration", "0.1"], "simulated clock"),
    (["goto", "-c", "{tmp}/stereo.yaml", "--goal", "0", "1", "0", "--duration", "0.1"], "simulated clock"),
    (["map", "build", "-c", "{tmp}/stereo.yaml", "--out", "{tmp}/m.json", "--duration", "0.1"], "simulated clock"),
])
def test_a_configured_live_view_that_could_not_be_served_is_refused(tmp_path, capsys, argv, says):
    """telemetry.live_view.enabled: true in the configuration was accepted and nothing was served where
    --live-view is refused (the simulated clock, --no-telemetry, telemetry.enabled: false): teach, repeat,
    goto and map build said nothing at all. Refused in every mode, naming the field and why, before any
    device opens."""
    import yaml
    from pathlib import Path

    from vbnav.control.cli import main
    from vbnav.control.config import CONFIG_DIR
    lv = {"live_view": {"enabled": True}}
    sim = yaml.safe_load((CONFIG_DIR / "sim.yaml").read_text())
    stereo = yaml.safe_load((CONFIG_DIR / "sim_stereo.yaml").read_text())
    for name, base, telemetry in (("sim", sim, lv), ("closed", sim, {**lv, "enabled": False}),
                                  ("stereo", stereo, lv)):
        base = dict(base, telemetry={**base.get("telemetry", {}), **telemetry},
                    controller={**base.get("controller", {}), "teach": "room_loop"})
        (tmp_path / f"{name}.yaml").write_text(yaml.safe_dump(base))
    argv = [a.format(tmp=tmp_path) for a in argv]
    if "-c" not in argv:
        argv[1:1] = ["-c", str(tmp_path / "sim.yaml")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "telemetry.live_view.enabled" in err and says in err, err
    assert not Path(tmp_path / "route").exists() and not Path(tmp_path / "m.json").exists()


@pytest.mark.parametrize("argv", [["run", "-c", "sentry-dynamixel", "--realtime", "--no-telemetry", "--duration", "0.1"],
                                  ["map", "build", "-c", "sentry-dynamixel", "--realtime", "--no-telemetry",
                                   "--duration", "0.1", "--out", "{tmp}/m.json"]])
def test_realtime_on_a_robot_already_on_the_wall_clock_is_refused(tmp_path, capsys, argv):
    """--realtime (simulated robot: the wall clock instead of the simulated one) on a configuration with real
    drivers was accepted and changed nothing (hardware always runs on the wall clock); it is refused, naming
    the option and the drivers, before any device opens."""
    from vbnav.control.cli import main
    assert main([a.format(tmp=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err
    assert "--realtime" in err and "drive.driver dynamixel" in err, err
    assert not (tmp_path / "m.json").exists()
