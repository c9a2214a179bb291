"""``vbnav doctor``: the checklist on the simulated robot, against the Dynamixel emulator on a pty, and with the
problems a new robot owner meets (a missing port, a wrong baud rate, a slow latency timer, a taken endpoint, an
unusable routes folder, a calibration for another size, no real-time rights)."""
from __future__ import annotations

import os
import socket

import pytest
import yaml

from vbnav.control import doctor
from vbnav.control.cli import main
from vbnav.control.config import ConfigError, load_config
from vbnav.drivers.sim.dynamixel_emulator import DynamixelBus


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_config(tmp_path, name="robot.yaml", **sections) -> str:
    # not the default 7447: another vbnav may be running on this machine
    data = {"controller": {"routes_dir": str(tmp_path / "routes")},
            "telemetry": {"listen": [f"tcp/127.0.0.1:{free_tcp_port()}"]}, **sections}
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return str(path)


def dxl_config(tmp_path, port, **options) -> str:
    return write_config(tmp_path, robot={"name": "dxl", "wheel_radius": 0.033, "max_wheel_speed": 6.0,
                                         "max_linear_speed": 0.18},
                        camera={"driver": "v4l2", "options": {"device": str(tmp_path / "video0")}},
                        drive={"driver": "dynamixel", "options": {"port": str(port), "margin_ms": 8.0, **options}})


@pytest.fixture(scope="module")
def bus():
    with DynamixelBus([1, 2]) as b:
        yield b


def test_the_simulated_robot_is_ready(tmp_path, capsys):
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"     # not 7447: another vbnav may be running on this machine
    assert main(["doctor", "-c", write_config(tmp_path, telemetry={"listen": [endpoint]})]) == 0
    out = capsys.readouterr().out
    assert "[ ok ] drive: sim" in out and "[ ok ] camera: sim: a 640x480 frame" in out
    assert "[ ok ] routes directory:" in out and f"[ ok ] telemetry endpoint: {endpoint} is free" in out
    assert out.rstrip().endswith("ready to run (0 warning(s))")


def test_dynamixel_servos_answer_on_the_emulated_bus(tmp_path, bus, capsys):
    assert main(["doctor", "-c", dxl_config(tmp_path, bus.path), "--no-camera"]) == 0
    out = capsys.readouterr().out
    assert (f"[ ok ] drive: dynamixel: servos 1 (left, XL430-W250), 2 (right, XL430-W250) answer on {bus.path} at "
            f"1000000 bit/s") in out
    assert "[skip] serial latency timer" in out and "[skip] camera: --no-camera" in out


def test_a_missing_port_and_camera_block_the_run_with_their_fixes(tmp_path, capsys):
    assert main(["doctor", "-c", dxl_config(tmp_path, tmp_path / "ttyUSB0")]) == 1
    out = capsys.readouterr().out
    assert f"[FAIL] drive permission: {tmp_path / 'ttyUSB0'} does not exist" in out
    assert "fix: plug the adapter in; 'vbnav find' lists the serial ports" in out
    assert f"[FAIL] camera: {tmp_path / 'video0'} does not exist" in out
    assert "2 problem(s) block a run" in out


def test_servos_at_another_baud_rate_fail_with_the_scan_command(tmp_path, capsys):
    with DynamixelBus([1, 2], baud=57_600) as slow:
        assert main(["doctor", "-c", dxl_config(tmp_path, slow.path), "--no-camera"]) == 1
    out = capsys.readouterr().out
    assert "[FAIL] drive: dynamixel: servo 1 (left)" in out and "did not answer ping at 1000000 bit/s" in out
    assert f"fix: 'vbnav find servos --port {slow.path}'" in out


def test_a_slow_ftdi_latency_timer_fails(tmp_path, bus, monkeypatch):
    timer = tmp_path / "sys/bus/usb-serial/devices" / os.path.basename(os.path.realpath(bus.path)) / "latency_timer"
    timer.parent.mkdir(parents=True)
    timer.write_text("16\n")
    from vbnav.drivers import discovery
    real = discovery.read_latency_timer
    monkeypatch.setattr(discovery, "read_latency_timer", lambda dev, sysfs="/sys": real(dev, str(tmp_path / "sys")))
    cfg = load_config(dxl_config(tmp_path, bus.path))
    from vbnav.control.runtime.factory import make_robot
    checks = {c.name: c for c in doctor.check_drive(cfg, make_robot(cfg, with_camera=False))}
    timer_check = checks["serial latency timer"]
    assert timer_check.status == doctor.FAIL and "16 ms, the driver waits 1 ms" in timer_check.detail
    assert timer_check.fix.startswith("echo 1 | sudo tee ")
    # the drive refuses to come up on it (a run's every answer would come too late)
    assert checks["drive"].status == doctor.FAIL and "latency timer is 16 ms" in checks["drive"].detail
    timer.write_text("1\n")
    checks = {c.name: c for c in doctor.check_drive(cfg, make_robot(cfg, with_camera=False))}
    assert checks["serial latency timer"].status == doctor.OK


def test_a_taken_telemetry_endpoint_fails(tmp_path, capsys):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        port = s.getsockname()[1]
        endpoint = f"tcp/127.0.0.1:{port}"
        check = doctor.check_endpoint(endpoint)
        assert check.status == doctor.FAIL and "another process listens there" in check.detail
        assert main(["doctor", "-c", write_config(tmp_path, telemetry={"listen": [endpoint]})]) == 1
    assert doctor.check_endpoint(endpoint).status == doctor.OK
    assert doctor.check_endpoint("unixsock-stream//tmp/x.sock").status == doctor.SKIP


def test_routes_directory_problems(tmp_path):
    (tmp_path / "afile").write_text("")
    cfg = load_config(write_config(tmp_path))
    cfg.controller.routes_dir = str(tmp_path / "afile" / "routes")
    check = doctor.check_routes_dir(cfg)
    assert check.status == doctor.FAIL and "is not a directory" in check.detail
    cfg.controller.routes_dir = str(tmp_path)
    assert doctor.check_routes_dir(cfg).status == doctor.OK


def test_calibration_present_and_plausible(tmp_path):
    cfg = load_config(write_config(tmp_path, camera={"driver": "v4l2"}))
    assert doctor.check_calibration(cfg).status == doctor.WARN            # none: the inline placeholders
    calib = tmp_path / "cam.yaml"
    ros = {"image_width": 320, "image_height": 240, "distortion_model": "plumb_bob",
           "camera_matrix": {"rows": 3, "cols": 3, "data": [300, 0, 160, 0, 300, 120, 0, 0, 1]},
           "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0, 0, 0, 0, 0]}}
    calib.write_text(yaml.safe_dump(ros))
    # relative: to the config's folder; the file's size replaces the inline 640x480
    cfg = load_config(write_config(tmp_path, camera={"driver": "v4l2", "calibration_file": "cam.yaml"}))
    check = doctor.check_calibration(cfg)
    assert check.status == doctor.OK and "320x240, fx 300.0" in check.detail
    ros["camera_matrix"]["data"][0] = ros["camera_matrix"]["data"][4] = 10.0     # 173 deg: not a pinhole lens
    calib.write_text(yaml.safe_dump(ros))
    cfg = load_config(write_config(tmp_path, camera={"driver": "v4l2", "calibration_file": "cam.yaml"}))
    check = doctor.check_calibration(cfg)
    assert check.status == doctor.WARN and "173 deg horizontal field of view" in check.detail
    # a missing file fails at config load already, naming it (doctor reports config errors first)
    with pytest.raises(ConfigError, match="gone.yaml"):
        load_config(write_config(tmp_path, camera={"driver": "v4l2", "calibration_file": "gone.yaml"}))


def test_real_time_rights(monkeypatch):
    assert doctor.check_realtime(0).status == doctor.SKIP

    def refuse(*a):
        raise PermissionError(1, "Operation not permitted")
    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    check = doctor.check_realtime(50)
    assert check.status == doctor.WARN and "rtprio 50" in check.fix


def test_oak_udev_rule(tmp_path):
    check = doctor.check_oak_udev_rule((str(tmp_path),))
    assert check.status in (doctor.FAIL, doctor.WARN) and "80-movidius.rules" in check.fix
    assert "service install -c CONFIG writes it (/etc/udev/rules.d/99-vbnav.rules" in check.fix
    (tmp_path / "80-movidius.rules").write_text('SUBSYSTEM=="usb", ATTRS{idVendor}=="03e7", MODE="0666"\n')
    assert doctor.check_oak_udev_rule((str(tmp_path),)).status == doctor.OK


def test_devices_without_permission_name_the_group_to_join(tmp_path, bus, monkeypatch, capsys):
    video = tmp_path / "video0"
    video.symlink_to(os.devnull)                         # a character device, not a file to replay
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if str(p) in (bus.path, str(video))
                        else real_access(p, mode, **kw))
    assert main(["doctor", "-c", dxl_config(tmp_path, bus.path)]) == 1
    out = capsys.readouterr().out
    assert f"[FAIL] drive permission: no permission to open {bus.path}" in out
    assert "fix: sudo usermod -aG dialout $USER" in out
    assert f"[FAIL] camera permission: no permission to open {video}" in out
    assert "fix: sudo usermod -aG video $USER" in out


def test_no_camera_is_refused_when_the_obstacle_stop_needs_the_camera(capsys):
    """doctor -c sim_stereo --no-camera skipped the camera and said 'ready to run', for a run that
    'vbnav run --no-camera' refuses (obstacles.enabled: the obstacle stop needs the camera)."""
    assert main(["doctor", "-c", "sim_stereo", "--no-camera"]) == 2
    out, err = capsys.readouterr()
    assert "sim_stereo.yaml: obstacles.enabled is true, and the obstacle stop needs the camera" in err
    assert "ready to run" not in out
