"""An operator's estop holds across restarts of the process (control/runtime/estop_latch.py).

Found by an audit: a robot estopped whose run then ended on a fault was restarted by systemd 2 s later without
the latch, and a service configured for repeat drove off with nobody's resume. The estop is now kept in a file
(safety.latch_file; under systemd $STATE_DIRECTORY/estop.json) written off the loop thread; a run that finds it
starts latched, before the wheels are powered, until a resume. All on the simulated robot and clock."""
from __future__ import annotations

import json
import threading
from pathlib import Path

import pytest

from vbnav.control.cli import main
from vbnav.control.config import load_config
from vbnav.control.controllers.manual import ScriptedController
from vbnav.control.runtime import estop_latch
from vbnav.control.runtime.factory import make_robot
from vbnav.control.runtime.mailbox import OperatorCommand
from vbnav.control.runtime.runtime import Runtime

S = 1_000_000_000


def _config(tmp_path: Path, latch_file: str | None = None, fail_after_s: float | None = None) -> Path:
    path = tmp_path / "robot.yaml"
    drive = {"driver": "sim", "reconnect_window_s": 0}
    if fail_after_s is not None:
        drive["options"] = {"fail_after_s": fail_after_s}
    data = {"drive": drive, "controller": {"kind": "scripted"}}
    if latch_file is not None:
        data["safety"] = {"latch_file": latch_file}
    path.write_text(json.dumps(data))          # JSON is YAML
    return path


def _run(config: Path, duration_s: float, at: dict | None = None):
    """One run of the simulated robot (no camera) with the configured scripted drive; ``at`` maps a time (ns
    from the start) to a function(runtime) called in that cycle. Returns the result, the runtime and, per
    cycle, (t, the drive powered, the commanded wheel speeds)."""
    cfg = load_config(str(config))
    robot = make_robot(cfg, with_camera=False)
    rt = Runtime(cfg, robot.drive, ScriptedController(cfg.controller.script), robot.clock)
    cycles = []
    start = []

    def observe(r, ctx, twist, wheels):
        if not start:
            start.append(ctx.now_ns)
        t = ctx.now_ns - start[0]
        cycles.append((t, robot.drive.physics.powered, wheels))
        if at and t in at:
            at[t](r)

    rt.cycle_observers.append(observe)
    return rt.run(duration_s), rt, cycles


def _estop(reason: str):
    return lambda r: r.submit(OperatorCommand("estop", (reason,), "test"))


def _resume(r) -> None:
    r.submit(OperatorCommand("resume", (r.safety.latched_ns,), "test"))


def _moving(cycles, since: int = 0, until: int | None = None) -> list:
    return [t for t, powered, (left, right) in cycles
            if since <= t and (until is None or t < until) and powered and (left or right)]


def test_an_estop_holds_across_a_fault_and_a_restart_until_a_resume(tmp_path, monkeypatch, capsys):
    state = tmp_path / "state"          # what systemd makes for StateDirectory=vbnav
    state.mkdir()
    monkeypatch.setenv("STATE_DIRECTORY", str(state))
    config = _config(tmp_path, fail_after_s=3.0)
    latch = state / "estop.json"

    first, _, cycles = _run(config, 10, {1 * S: _estop("person on the track")})
    assert first.reason == "drive", first.message          # the fault ended it: systemd restarts it
    assert _moving(cycles, until=1 * S) and not _moving(cycles, since=1 * S + 20_000_000)
    assert "person on the track" in json.loads(latch.read_text())["message"]

    # the restart, as the service does it: `vbnav run` with the same configuration, nobody resumes
    assert main(["run", "-c", str(config), "--no-camera", "--duration", "2", "--json", "--no-telemetry"]) == 0
    captured = capsys.readouterr()
    assert "estop kept from before a restart" in captured.err and str(latch) in captured.err, captured.err
    summary = json.loads(captured.out)
    trip = summary["events"][0]
    assert (trip["kind"], trip["cause"]) == ("trip", "estop"), summary["events"]
    assert "person on the track" in trip["message"] and str(latch) in trip["message"] and "latched at" in trip["message"]
    assert summary["final_odometry"] == [0.0, 0.0, 0.0]    # it never drove
    assert latch.exists()

    # the next restart: a resume naming the state's latched_ns clears it, and the robot drives again
    third, rt, cycles = _run(config, 2, {1 * S: _resume})
    assert not [c for c in cycles if c[0] < 1 * S and c[1]], "powered before the resume"
    assert _moving(cycles, since=1 * S)
    assert third.count("reset", "estop") == 1 and rt.safety.may_move
    assert not latch.exists()


def test_the_latch_file_is_written_off_the_loop_thread(tmp_path, monkeypatch):
    """A writer blocked on the disk (a slow SD card) does not hold the loop: it cycles on meanwhile."""
    config = _config(tmp_path, latch_file="estop.json")
    entered, release = threading.Event(), threading.Event()
    writers = []
    real_write = estop_latch.write_atomic

    def slow_write(path, data, mode=None):
        writers.append(threading.current_thread())
        entered.set()
        release.wait(10)
        return real_write(path, data, mode)

    monkeypatch.setattr(estop_latch, "write_atomic", slow_write)
    seen = {}

    def while_blocked(r):
        seen["writing"] = entered.is_set() and not release.is_set()
        seen["file"] = (tmp_path / "estop.json").exists()
        release.set()

    result, _, _ = _run(config, 2, {1 * S: _estop("test"), 1 * S + 10_000_000: lambda r: entered.wait(10),
                                    1 * S + 500_000_000: while_blocked})
    assert writers and threading.main_thread() not in writers, writers
    assert seen == {"writing": True, "file": False}, seen      # 49 cycles ran while the write was blocked
    assert result.reason == "duration" and result.cycles == 201
    assert json.loads((tmp_path / "estop.json").read_text())["message"] == "estop from test: test"


@pytest.mark.parametrize("damage, says", [(b"{not json", "cannot be parsed"), (b"", "cannot be parsed"),
                                          (b'{"message": "x"}', "cannot be parsed (no 'since')"),
                                          (None, "cannot be read")])
def test_a_latch_file_that_cannot_be_read_keeps_the_robot_latched(tmp_path, damage, says):
    config = _config(tmp_path, latch_file="estop.json")
    latch = tmp_path / "estop.json"
    if damage is None:
        latch.mkdir()                  # something there that is no file
    else:
        latch.write_bytes(damage)
    result, rt, cycles = _run(config, 1)
    trip = result.events[0]
    assert (trip.kind, trip.cause) == ("trip", "estop") and says in trip.message and str(latch) in trip.message
    assert not [c for c in cycles if c[1]], "powered while latched"
    if damage is not None:             # a resume clears it and removes the file
        _, _, cycles = _run(config, 2, {1 * S: _resume})
        assert _moving(cycles, since=1 * S) and not latch.exists()


def test_a_latch_file_that_cannot_be_written_is_said_and_the_estop_holds_in_memory(tmp_path):
    config = _config(tmp_path, latch_file="missing/estop.json")
    result, rt, cycles = _run(config, 2, {1 * S: _estop("test")})
    warnings = [e.message for e in result.events if (e.kind, e.cause) == ("warning", "latch_file")]
    assert len(warnings) == 2, warnings
    assert "does not exist" in warnings[0] and "could not be written" in warnings[1], warnings
    assert all(str(tmp_path / "missing/estop.json") in w for w in warnings)
    assert not _moving(cycles, since=1 * S + 20_000_000) and "estop" in rt.safety.latched


def test_a_kept_estop_is_announced_once_on_the_console_of_a_real_clock_run(tmp_path, capsys):
    """Found by an audit: on the wall clock the runtime printed 'estop kept from before a restart' and the console's
    event echo printed the same estop's trip again. Now the echo says it, once."""
    config = _config(tmp_path, latch_file="estop.json")
    (tmp_path / "estop.json").write_text(estop_latch.latch_record("estop from test: person on the track", 5))
    assert main(["run", "-c", str(config), "--no-camera", "--duration", "0.2", "--no-telemetry", "--realtime"]) == 0
    err = capsys.readouterr().err
    said = [line for line in err.splitlines() if "person on the track" in line and "safety=" not in line]
    assert len(said) == 1 and "estop kept from before a restart" in said[0], err


def test_a_kept_estop_is_cleared_by_hand_logged_and_refused_while_a_robot_runs_with_it(tmp_path, capsys):
    """Found by an audit: a run by hand with safety.latch_file and no network could not be resumed; the docs said
    to delete the file (unlogged, and a robot still running with it stayed latched in memory while the next
    restart would not be). `vbnav estop clear` refuses while a run holds the file, else removes it and logs who
    cleared it."""
    config = _config(tmp_path, latch_file="estop.json")
    latch = tmp_path / "estop.json"
    _run(config, 1, {500_000_000: _estop("person on the track")})
    assert latch.exists()

    refused = []
    _, _, cycles = _run(config, 1, {500_000_000: lambda r: refused.append(
        main(["estop", "clear", "-c", str(config), "--reason", "test"]))})
    err = capsys.readouterr().err
    assert refused == [1] and "a robot process (pid" in err and "vbnav send resume" in err, err
    assert latch.exists() and not _moving(cycles)

    assert main(["estop", "clear", "--latch-file", str(latch), "--reason", "track checked"]) == 0
    out = capsys.readouterr().out
    assert "person on the track" in out and not latch.exists(), out
    log = [json.loads(line) for line in (tmp_path / "estop.json.cleared.log").read_text().splitlines()]
    assert len(log) == 1 and log[0]["reason"] == "track checked" and log[0]["by"] and "person on the track" in \
        log[0]["estop"], log
    _, _, cycles = _run(config, 1)
    assert _moving(cycles), "still latched after the clear"
    assert main(["estop", "clear", "--latch-file", str(latch)]) == 0
    assert "nothing to clear" in capsys.readouterr().out


def test_an_estop_accepted_as_the_run_ends_on_a_fault_is_kept_across_the_restart(tmp_path):
    """Found by an audit: an estop the mailbox had accepted but the loop had not applied when a fault ended the run
    was answered 'refused: the run ended' and never written to the latch file; systemd restarted the service 2 s
    later and a robot configured for repeat drove off, the operator's estop forgotten. An accepted estop is
    applied: it is latched, kept in the file and answered applied, however the run ends."""
    config = _config(tmp_path, latch_file="estop.json")
    answered = []

    def fault_with_an_estop_waiting(r):
        r.end_run("network", "the zenoh session died")       # a fatal cause: the run ends at the next cycle
        r.command_listeners.append(lambda rt, cmd, outcome, now: answered.append((cmd.kind, outcome.applied)))
        r.submit(OperatorCommand("estop", ("person on the track",), "test", ack="E1"))

    result, rt, _ = _run(config, 2, {500_000_000: fault_with_an_estop_waiting})
    assert result.reason == "network", result.message
    assert answered == [("estop", True)], (answered, [e.message for e in result.events])
    assert "person on the track" in json.loads((tmp_path / "estop.json").read_text())["message"]
    _, _, cycles = _run(config, 1)            # the restart
    assert not _moving(cycles), "the restarted run drove: the estop was forgotten"


def test_an_estop_that_comes_after_the_run_ended_is_kept_for_the_next_run(tmp_path):
    """Found by an audit: an estop that arrived after a fault ended the run, while the process was still closing
    (a mode switch's worker, the telemetry flush: seconds), was refused 'the run ended' and kept nowhere: the
    service restarted 2 s later and drove. It is still refused (the loop is over), but kept in the latch file,
    and its refusal says so; the next run starts latched."""
    config = _config(tmp_path, latch_file="estop.json")
    result, rt, _ = _run(config, 0.5)
    reason = rt.submit(OperatorCommand("estop", ("person on the track",), "zenoh:op"))
    assert reason is not None and "the run ended" in reason and "kept in" in reason and "starts latched" in reason
    assert "person on the track" in json.loads((tmp_path / "estop.json").read_text())["message"]
    _, _, cycles = _run(config, 1)
    assert not _moving(cycles), "the next run drove: the estop was forgotten"


def test_estop_clear_without_a_latch_file_names_where_the_service_keeps_it(tmp_path, monkeypatch, capsys):
    """The operator's shell has no $STATE_DIRECTORY, so a config without safety.latch_file names no file; the
    refusal points at the file the installed service's runs keep (/var/lib/vbnav/estop.json)."""
    monkeypatch.delenv("STATE_DIRECTORY", raising=False)
    config = _config(tmp_path)
    assert main(["estop", "clear", "-c", str(config)]) == 2
    err = capsys.readouterr().err
    assert "no safety.latch_file" in err and "--latch-file /var/lib/vbnav/estop.json" in err, err


def test_a_latch_file_that_cannot_be_removed_after_a_resume_says_the_estop_is_cleared(tmp_path, monkeypatch):
    """A removal follows a resume: the warning said 'the estop holds in memory' while the robot drove on. It
    says the estop is cleared in this run and a restart would start latched, and how to clear the file."""
    from pathlib import Path

    from vbnav.control.runtime.estop_latch import LatchWriter
    path = tmp_path / "estop.json"
    w = LatchWriter(path)
    w.write('{"reason": "operator"}')
    real_unlink = Path.unlink

    def refuse(self, *a, **kw):
        if self == path:
            raise PermissionError(13, "Permission denied")
        return real_unlink(self, *a, **kw)
    monkeypatch.setattr(Path, "unlink", refuse)
    w.remove()
    w.close()
    errors = w.errors()
    assert len(errors) == 1, errors
    assert "could not be removed (Permission denied): the estop is cleared in this run, but a restart would " \
           "start latched again" in errors[0] and "holds in memory" not in errors[0], errors


def test_the_answer_that_a_late_estop_is_kept_waits_for_the_write(tmp_path):
    """An estop after the run ended, while the run's latch writer was still open, was only posted to it and
    answered 'kept in PATH' at once, even with a folder that could not be written. The answer now waits for the
    write and says what happened."""
    good = estop_latch.LatchWriter(tmp_path / "estop.json")
    assert good.write_and_wait('{"message": "late"}') is None
    assert json.loads((tmp_path / "estop.json").read_text())["message"] == "late"
    good.close()
    bad = estop_latch.LatchWriter(tmp_path / "missing" / "estop.json")
    why = bad.write_and_wait('{"message": "late"}')
    bad.close()
    assert why and "No such file" in why, why
    assert not (tmp_path / "missing").exists()
