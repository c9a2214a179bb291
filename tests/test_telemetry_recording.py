"""Recordings of the simulated demo: teach and repeat runs in one MCAP file, read back by the mcap library."""
from __future__ import annotations

import json

import pytest

from vbnav.control.comms.recording import McapRecorder, iter_recording, read_recording


def _events(path):
    return [json.loads(d) for t, _, _, d in iter_recording(path) if t == "/vbnav/events"]


def test_demo_teach_and_repeat_segments_in_one_recording(tmp_path):
    """The demo's teach and repeat runs (session.Session) with a shared recorder, cut short (the full demo is
    slow)."""
    from vbnav.control.demo import demo_config, demo_route
    from vbnav.control.controllers.path import PathFollower
    from vbnav.control.route import load_route
    from vbnav.control.runtime.factory import make_robot
    from vbnav.control.session import Session

    cfg = demo_config(0)
    path, start = demo_route(), cfg.sim.start()
    rec_path = tmp_path / "demo.mcap"
    rec = McapRecorder(rec_path, cfg.robot.name)
    try:
        teach = Session(cfg, make_robot(cfg, with_camera=True), recorder=rec).teach(
            PathFollower(path, 0.4, start=start), tmp_path / "route", overwrite=True, duration_s=6.0)
        assert teach.keyframes >= 2
        rep = Session(cfg, make_robot(cfg, with_camera=True, run=1), recorder=rec).repeat(
            load_route(tmp_path / "route"), duration_s=4.0, segment="repeat 1")
        assert rep.reason in ("duration", "finished")
    finally:
        rec.close()
    s = read_recording(rec_path)
    assert s.complete
    assert set(s.channels) >= {"/vbnav/state", "/vbnav/events", "/vbnav/log", "/vbnav/pose/odom", "/vbnav/image"}
    assert s.channels["/vbnav/image"].schema == "foxglove.CompressedImage"
    rate = cfg.telemetry.state_rate_hz
    n_state = s.channels["/vbnav/state"].count
    assert abs(n_state - (6.0 + 4.0) * rate) <= 2                     # both segments at the state rate
    assert abs(s.channels["/vbnav/image"].count - (6.0 + 4.0) * 2) <= 2  # 2 Hz images
    ev = _events(rec_path)
    assert [e["segment"] for e in ev if e["kind"] == "run_start"] == ["teach", "repeat 1"]
    assert [e["kind"] for e in ev].count("run_end") == 2
    # Segments follow each other in log time although each run's simulated clock starts at the same value.
    times = [t for topic, _, t, _ in iter_recording(rec_path) if topic == "/vbnav/state"]
    assert times == sorted(times) and 10.0 < (times[-1] - times[0]) * 1e-9 < 12.0
    states = [json.loads(d) for topic, _, _, d in iter_recording(rec_path) if topic == "/vbnav/state"]
    assert states[0]["mode"] != states[-1]["mode"]                   # the teach driver, then the repeat controller
    repeat = [m for m in states if m["mode"] == states[-1]["mode"]]
    assert any(m["keyframe"] is not None for m in repeat) and any(m["pose"]["vbc"] for m in repeat)
    assert "/vbnav/pose/vbc" in s.channels


@pytest.mark.slow
def test_vbnav_demo_record_is_read_back_with_every_channel(tmp_path):
    from vbnav.control.cli import main
    rec_path = tmp_path / "demo.mcap"
    assert main(["demo", "--out", str(tmp_path / "out"), "--repeats", "1", "--record", str(rec_path)]) == 0
    s = read_recording(rec_path)
    assert s.complete and not (tmp_path / "demo.mcap.part").exists()
    assert set(s.channels) >= {"/vbnav/state", "/vbnav/events", "/vbnav/log", "/vbnav/pose/odom", "/vbnav/image"}
    ev = _events(rec_path)
    starts = [e for e in ev if e["kind"] == "run_start"]
    ends = [e for e in ev if e["kind"] == "run_end"]
    assert [e["segment"] for e in starts] == ["teach", "repeat 1"] and len(ends) == 2
    # Counts consistent with the rates over the simulated time of both runs.
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    duration = sum(e["cycles"] for e in ends) / 100.0      # 100 Hz loop
    n_state = s.channels["/vbnav/state"].count
    assert abs(n_state - duration * 20) <= 4, (n_state, duration)
    assert abs(s.channels["/vbnav/image"].count - duration * 2) <= 4
    # Every recorded image carries the stages' overlay (tracked features while teaching, the matched keyframe's
    # while repeating): an overlay that raised would be dropped silently, counted only in sink_errors.
    assert s.channels["/vbnav/image/annotations"].count == s.channels["/vbnav/image"].count
    assert s.channels["/vbnav/pose/odom"].count == n_state
    assert metrics["completed"]


def test_a_recording_that_fails_is_said_and_the_run_exits_1(tmp_path, monkeypatch, capsys):
    """A full disk under --record: the run itself goes on (a recording is no safety function), but the
    failure is said on stderr and the exit code is not success; it was only counted."""
    import errno

    from vbnav.control.cli import main
    from vbnav.control.comms import recording

    calls = [0]
    real_write = recording.McapRecorder._write

    def full_disk(self, topic, log_ns, data):
        calls[0] += 1
        if calls[0] > 50:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(self, topic, log_ns, data)
    monkeypatch.setattr(recording.McapRecorder, "_write", full_disk)
    out = tmp_path / "run.mcap"
    assert main(["run", "--no-camera", "--duration", "3", "--record", str(out)]) == 1
    err = capsys.readouterr().err
    assert f"the recording {out} is incomplete" in err and "No space left on device" in err, err
    monkeypatch.setattr(recording.McapRecorder, "_write", real_write)
    assert main(["run", "--no-camera", "--duration", "1", "--record", str(tmp_path / "ok.mcap")]) == 0
    assert "incomplete" not in capsys.readouterr().err


def test_telemetry_lost_to_a_sink_that_raises_is_said_at_the_end_and_in_the_summary(monkeypatch, capsys):
    """publisher.sink_errors was counted and never shown: a sink that raised on every message (a live view, a
    viewer gone) left it empty without a word. The run's end says how many and the first error, and
    `vbnav run --json` has the count; the run itself goes on and ends well."""
    from vbnav.control.cli import main
    from vbnav.control.comms import link
    from vbnav.control.comms.telemetry import Sink, TelemetryPublisher

    class Broken(Sink):
        def state(self, *a):
            raise OSError("viewer gone")

    made = []

    class WithBroken(TelemetryPublisher):
        def __init__(self, robot, sinks, **kw):
            super().__init__(robot, [*sinks, Broken()], **kw)
            made.append(self)
    monkeypatch.setattr(link, "TelemetryPublisher", WithBroken)
    assert main(["run", "--no-camera", "--duration", "1", "--json"]) == 0
    out, err = capsys.readouterr()
    n = made[0].sink_errors
    assert n > 0 and json.loads(out)["telemetry_errors"] == n
    assert f"vbnav: telemetry: {n} errors: messages, overlays or scenes not published or recorded; the first: " \
           f"OSError('viewer gone')" in err, err
    monkeypatch.setattr(link, "TelemetryPublisher", TelemetryPublisher)
    assert main(["run", "--no-camera", "--duration", "1", "--json"]) == 0      # none: nothing said, 0
    out, err = capsys.readouterr()
    assert json.loads(out)["telemetry_errors"] == 0 and "vbnav: telemetry:" not in err


def test_a_failed_recording_over_an_old_one_names_the_file_that_holds_it(tmp_path, monkeypatch, capsys):
    """--record PATH --overwrite over an earlier recording, and the new one fails to close (a full disk at
    its summary): the old PATH is still there, untouched, and what this run wrote is in PATH.part. The
    message said it was in PATH, the previous run's file."""
    import errno

    from vbnav.control.cli import main
    from vbnav.control.comms import recording

    out = tmp_path / "run.mcap"
    assert main(["run", "--no-camera", "--duration", "1", "--record", str(out)]) == 0
    old = out.read_bytes()
    capsys.readouterr()

    def full_disk_at_close(self):
        self._closed = True
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(recording.McapRecorder, "close", full_disk_at_close)
    assert main(["run", "--no-camera", "--duration", "1", "--record", str(out), "--overwrite"]) == 1
    err = capsys.readouterr().err
    part = tmp_path / "run.mcap.part"
    assert out.read_bytes() == old and part.exists()
    assert f"what was written before is in {part}" in err, err


def test_a_recording_whose_writer_blocks_is_said_and_the_run_exits_1(tmp_path, monkeypatch, capsys):
    """A sink that blocks (a stalled network file system under --record): the loop never waits on it, and
    at the end the telemetry thread is given telemetry.CLOSE_WAIT_S to finish; it was then left, the
    recording unclosed (PATH.part), and the run exited 0 without a word. It is said now, naming the sink
    the thread was stuck in, and the exit code is not success."""
    import threading

    from vbnav.control.cli import main
    from vbnav.control.comms import recording, telemetry

    release = threading.Event()
    calls = [0]
    real_write = recording.McapRecorder._write

    def stalled_disk(self, topic, log_ns, data):
        calls[0] += 1
        if calls[0] > 50:
            release.wait(30)
        return real_write(self, topic, log_ns, data)
    monkeypatch.setattr(recording.McapRecorder, "_write", stalled_disk)
    monkeypatch.setattr(telemetry, "CLOSE_WAIT_S", 0.3)
    out = tmp_path / "run.mcap"
    try:
        assert main(["run", "--no-camera", "--duration", "2", "--record", str(out)]) == 1
    finally:
        release.set()
    err = capsys.readouterr().err
    assert f"the recording {out} is incomplete" in err and "still in McapRecorder after 0.3 s" in err, err
    assert not out.exists() and (tmp_path / "run.mcap.part").exists()


@pytest.mark.parametrize("argv", [["teach", "--out", "{tmp}/route", "--duration", "3"],
                                  ["map", "build", "-c", "sim_stereo", "--out", "{tmp}/m.json", "--duration", "1.5"]])
def test_a_recording_that_fails_makes_teach_and_map_build_exit_1_as_run(tmp_path, monkeypatch, capsys, argv):
    """teach and map build said a failed --record on stderr and exited 0 (run and goto exit 1: a --record asked
    for and not made); they exit 1 now, their route or map still written."""
    import errno

    from vbnav.control.cli import main
    from vbnav.control.comms import recording

    calls = [0]
    real_write = recording.McapRecorder._write

    def full_disk(self, topic, log_ns, data):
        calls[0] += 1
        if calls[0] > 50:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(self, topic, log_ns, data)
    monkeypatch.setattr(recording.McapRecorder, "_write", full_disk)
    out = tmp_path / "run.mcap"
    assert main([a.format(tmp=tmp_path) for a in argv] + ["--record", str(out)]) == 1
    err = capsys.readouterr().err
    assert f"the recording {out} is incomplete" in err, err
    assert (tmp_path / "route").is_dir() or (tmp_path / "m.json").is_file()


def test_a_shared_recording_that_fails_is_said_and_the_demo_exits_1(tmp_path, monkeypatch, capsys):
    """The demo's runs write one recording shared by its teach and repeats (a borrowed recorder): a write that
    failed there (a full disk) was counted and never said, and vbnav demo printed its results and exited 0. The
    run that failed says it as a recording of its own does, the session keeps it, and the demo exits 1."""
    import errno

    from vbnav.control import demo
    from vbnav.control.cli import main
    from vbnav.control.comms import recording
    from vbnav.control.controllers.path import PathFollower
    from vbnav.control.runtime.factory import make_robot
    from vbnav.control.session import Session

    calls = [0]
    real_write = recording.McapRecorder._write

    def full_disk(self, topic, log_ns, data):
        calls[0] += 1
        if calls[0] > 50:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(self, topic, log_ns, data)
    cfg = demo.demo_config(0)
    rec = McapRecorder(tmp_path / "demo.mcap", cfg.robot.name)
    monkeypatch.setattr(recording.McapRecorder, "_write", full_disk)
    try:
        session = Session(cfg, make_robot(cfg, with_camera=True), recorder=rec)
        session.teach(PathFollower(demo.demo_route(), 0.4, start=cfg.sim.start()), tmp_path / "route",
                      overwrite=True, duration_s=3.0)
    finally:
        monkeypatch.setattr(recording.McapRecorder, "_write", real_write)
        rec.close()
    err = capsys.readouterr().err
    assert f"the recording {tmp_path / 'demo.mcap'} is incomplete" in err and "No space left" in err, err
    assert "No space left on device" in session.recording_error

    def failed_demo(out, scenario, cfg, **kw):
        return {"completed": True, "rms_lateral_error_m": 0.0, "max_lateral_error_m": 0.0,
                "recording_error": session.recording_error}
    monkeypatch.setattr(demo, "run_demo", failed_demo)
    assert main(["demo", "--out", str(tmp_path / "d"), "--record", str(tmp_path / "d.mcap")]) == 1
