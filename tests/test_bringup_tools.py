"""Bring-up tools against the emulators on pseudo-terminals, through the real dynamixel-sdk and pyserial:
``vbnav find`` / ``find servos``, ``vbnav servo set-id/set-baud``, ``vbnav odrive clear-errors``, the
Dynamixel bus's baud rate, the emulators' log, and the duplicate-id check of ``config check``."""
from __future__ import annotations

import logging
import os
import time

import pytest
import yaml

from vbnav.control.cli import main
from vbnav.drivers import discovery
from vbnav.drivers import dynamixel_protocol as dp
from vbnav.drivers.dynamixel import DynamixelDrive
from vbnav.drivers.dynamixel_setup import DynamixelBusTool
from vbnav.drivers.dynamixel_table import BAUD_RATE, BAUD_VALUES, ID, TORQUE_ENABLE
from vbnav.drivers.odrive import ODriveDrive
from vbnav.drivers.sim import odrive_emulator as oe
from vbnav.drivers.sim.dynamixel_emulator import DynamixelBus
from vbnav.drivers.wheels import DriveError

EMULATOR_LOG = "vbnav.emulator"


def dxl_drive(path: str, baud: int) -> DynamixelDrive:
    return DynamixelDrive(options=DynamixelDrive.Options(port=path, baudrate=baud, margin_ms=8.0))


# -- the emulated bus honours the baud rate ------------------------------------------------------
def test_a_host_at_the_wrong_rate_gets_no_answer_and_the_log_says_why(caplog):
    caplog.set_level(logging.INFO, logger=EMULATOR_LOG)
    with DynamixelBus([1, 2], baud=57_600) as bus:
        drive = dxl_drive(bus.path, 1_000_000)
        with pytest.raises(DriveError, match=r"did not answer ping at 1000000 bit/s.*vbnav find servos"):
            drive.connect()
        drive.close()
        assert "host sends at 1000000 bit/s, the servos listen at 57600 bit/s" in caplog.text
        assert not any(e.op == "ping" for e in bus.log)          # the servos heard noise, not a ping
        drive = dxl_drive(bus.path, 57_600)                        # the factory rate of an XL430
        drive.connect()
        drive.close()
        assert any(e.op == "ping" for e in bus.log)


def test_id_and_baud_writes_answer_under_the_old_identity_then_take_effect():
    bus = DynamixelBus([1])
    s = bus.servo(1)
    s.put(TORQUE_ENABLE, 1)
    # EEPROM: refused with torque on
    assert dp.decode(bus.handle_bytes(dp.encode(1, dp.INST_WRITE, bytes([ID.address, 0, 7])))).error == dp.ERR_ACCESS
    bus.handle_bytes(dp.encode(1, dp.INST_WRITE, bytes([TORQUE_ENABLE.address, 0, 0])))
    status = dp.decode(bus.handle_bytes(dp.encode(1, dp.INST_WRITE, bytes([ID.address, 0, 7]))))
    assert (status.dxl_id, status.error) == (1, 0)
    bus._apply_identity_changes()                 # what serving the packet does after the answer is sent
    assert set(bus.servos) == {7} and bus.servo(7).dxl_id == 7
    assert dp.decode(bus.handle_bytes(dp.encode(7, dp.INST_PING))).dxl_id == 7
    bad = dp.decode(bus.handle_bytes(dp.encode(7, dp.INST_WRITE, bytes([BAUD_RATE.address, 0, 9]))))
    assert bad.error == dp.ERR_DATA_RANGE          # no such rate
    bus.handle_bytes(dp.encode(7, dp.INST_WRITE, bytes([BAUD_RATE.address, 0, BAUD_VALUES[2_000_000]])))
    assert bus.servo(7).baud == 2_000_000


# -- vbnav find ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def mixed_bus():
    """Servo 1 at the factory 57600 bit/s, servo 2 already at 1 Mbps."""
    bus = DynamixelBus([1, 2], baud=57_600)
    bus.servo(2).put(BAUD_RATE, BAUD_VALUES[1_000_000])
    bus.start()
    yield bus
    bus.stop()


def test_find_servos_scans_rates_and_prints_model_id_firmware(mixed_bus, capsys):
    assert main(["find", "servos", "--port", mixed_bus.path, "--baud", "57600,1000000"]) == 0
    out = capsys.readouterr().out
    assert "57600 bit/s: id 1   XL430-W250 (model number 1060), firmware 46" in out
    assert "1000000 bit/s: id 2   XL430-W250" in out
    assert "2 servo(s) at 2 different rates: one bus runs at one rate" in out


def test_find_servos_on_a_silent_bus_exits_1_with_advice(capsys):
    with DynamixelBus([1], baud=57_600) as bus:
        bus.servo(1).no_answer = True
        assert main(["find", "servos", "--port", bus.path, "--baud", "57600"]) == 1
    out = capsys.readouterr().out
    assert "57600 bit/s: nothing" in out and "no servo answered at 57600 bit/s" in out


def test_find_servos_refuses_the_listings_options_and_an_empty_or_wrong_baud_list(mixed_bus, capsys):
    """find's own --port and --oak-timeout (before 'servos') were ignored by the scan, exit 0; '--baud ,'
    was an empty list that fell back to the default rates."""
    bus = mixed_bus.path
    assert main(["find", "--port", "/dev/ttyOTHER", "servos", "--port", bus, "--baud", "57600"]) == 2
    assert "--port /dev/ttyOTHER before 'servos'" in capsys.readouterr().err
    assert main(["find", "--oak-timeout", "9", "servos", "--port", bus, "--baud", "57600"]) == 2
    assert "--oak-timeout: 'find servos' does not search for OAK devices" in capsys.readouterr().err
    for baud, why in ((",", "expected baud rates like 57600,1000000, got ','"),
                      ("57600,12345", "12345 is not a Dynamixel X rate")):
        with pytest.raises(SystemExit) as exit_:
            main(["find", "servos", "--port", bus, "--baud", baud])
        out, err = capsys.readouterr()
        assert exit_.value.code == 2 and "argument --baud: " + why in err and "Scanning" not in out


def test_find_lists_a_given_port_and_reports_no_cameras_as_a_normal_result(mixed_bus, capsys):
    assert main(["find", "--port", mixed_bus.path, "--oak-timeout", "0.5"]) == 0
    out = capsys.readouterr().out
    assert f"  {mixed_bus.path}  -  not USB" in out
    assert "Cameras (V4L2):" in out and "OAK devices:" in out


def test_discovery_names_by_id_links_latency_timer_and_v4l2_nodes(tmp_path, mixed_bus):
    by_id = tmp_path / "by-id"
    by_id.mkdir()
    (by_id / "usb-FTDI_USB__-__Serial_Converter_FT1234-if00-port0").symlink_to(mixed_bus.path)
    [port] = discovery.serial_ports(extra=(mixed_bus.path,), by_id_dir=str(by_id))[-1:]
    assert port.by_id == [str(by_id / "usb-FTDI_USB__-__Serial_Converter_FT1234-if00-port0")]
    timer = discovery.latency_timer_path("/dev/ttyUSB0", str(tmp_path))
    timer.parent.mkdir(parents=True)
    timer.write_text("16\n")
    assert discovery.read_latency_timer("/dev/ttyUSB0", str(tmp_path)) == 16
    assert discovery.usb_kind(0x0403, 0x6014).startswith("ROBOTIS U2D2")
    assert discovery.usb_kind(0x1209, 0x0D32).startswith("ODrive")
    node = tmp_path / "class/video4linux/video0"
    node.mkdir(parents=True)
    (node / "name").write_text("HD USB Camera\n")
    [cam] = discovery.v4l2_devices(sysfs=str(tmp_path), dev=str(tmp_path / "dev"))
    assert cam.name == "HD USB Camera" and cam.error.startswith("cannot open")
    assert discovery.v4l2_devices(sysfs=str(tmp_path / "nothing")) == []


def test_v4l2_ioctl_numbers_are_the_kernels():
    # linux/videodev2.h on x86-64 and arm64: a wrong struct size would make every enumeration fail silently
    assert (discovery.VIDIOC_QUERYCAP, discovery.VIDIOC_ENUM_FMT, discovery.VIDIOC_ENUM_FRAMESIZES,
            discovery.VIDIOC_ENUM_FRAMEINTERVALS) == (0x80685600, 0xC0405602, 0xC02C564A, 0xC034564B)


# -- vbnav servo -----------------------------------------------------------------------------------
def test_servo_set_id_then_set_baud_on_a_new_servo(caplog, capsys):
    caplog.set_level(logging.INFO, logger=EMULATOR_LOG)
    with DynamixelBus([1], baud=57_600) as bus:
        bus.servo(1).put(TORQUE_ENABLE, 1)        # torque on: the tool must switch it off first
        assert main(["servo", "set-id", "--port", bus.path, "--id", "1", "--new-id", "2"]) == 0
        assert "servo 1 (XL430-W250) at 57600 bit/s is now id 2" in capsys.readouterr().out
        assert main(["servo", "set-baud", "--port", bus.path, "--id", "2", "--baud", "57600",
                     "--new-baud", "1000000"]) == 0
        assert "now talks at 1000000 bit/s (was 57600)" in capsys.readouterr().out
        assert set(bus.servos) == {2} and bus.servo(2).baud == 1_000_000
        assert bus.servo(2).torque_on is False
    assert "servo 1: ID is now 2" in caplog.text and "Baud Rate is now 1000000" in caplog.text


def test_servo_set_id_refuses_an_id_in_use_and_a_missing_servo(capsys):
    with DynamixelBus([1, 2]) as bus:
        assert main(["servo", "set-id", "--port", bus.path, "--id", "1", "--new-id", "2", "--baud", "1000000"]) == 3
        assert "id 2 is taken" in capsys.readouterr().err       # errors on stderr
        assert set(bus.servos) == {1, 2}
        assert main(["servo", "set-id", "--port", bus.path, "--id", "9", "--new-id", "3", "--baud", "1000000"]) == 3
        assert "no servo with id 9 answers" in capsys.readouterr().err
    assert main(["servo", "set-id", "--port", "/nonexistent/tty", "--id", "1", "--new-id", "3"]) == 2


# -- ODrive after a crash ----------------------------------------------------------------------------
@pytest.fixture
def crashed_odrive(tmp_path):
    """An ODrive whose axis watchdog expired while a killed controller was driving it."""
    emu = oe.ODriveEmulator(link=tmp_path / "ttyODRV")
    emu.start()
    for ax in emu.axes:
        ax.error |= oe.AXIS_ERROR_WATCHDOG_EXPIRED
    yield emu
    emu.stop()


def odrive_config(tmp_path, port, **options) -> str:
    path = tmp_path / "odrive.yaml"
    path.write_text(yaml.safe_dump({"robot": {"name": "od"}, "drive": {"driver": "odrive", "options": {
        "port": str(port), "reply_timeout_s": 0.02, **options}}}))
    return str(path)


def test_a_latched_watchdog_error_names_the_command_that_clears_it(crashed_odrive, tmp_path, capsys):
    cfg = odrive_config(tmp_path, crashed_odrive.path)
    drive = ODriveDrive(options=ODriveDrive.Options(port=crashed_odrive.path, reply_timeout_s=0.02))
    with pytest.raises(DriveError, match=r"WATCHDOG_TIMER_EXPIRED.*vbnav odrive clear-errors -c CONFIG.*"
                                         r"clear_watchdog_error_at_start"):
        drive.connect()
    drive.close()
    assert main(["odrive", "clear-errors", "-c", cfg]) == 0
    out = capsys.readouterr().out
    assert "axis0 (left): error=WATCHDOG_TIMER_EXPIRED" in out and "errors cleared" in out
    assert not any(ax.any_error() for ax in crashed_odrive.axes)
    assert main(["odrive", "clear-errors", "-c", cfg]) == 0
    assert "no errors" in capsys.readouterr().out


def test_the_config_may_allow_clearing_a_watchdog_error_at_start(crashed_odrive):
    drive = ODriveDrive(options=ODriveDrive.Options(port=crashed_odrive.path, reply_timeout_s=0.02,
                                                    clear_watchdog_error_at_start=True))
    drive.connect()
    drive.close()
    assert not any(ax.any_error() for ax in crashed_odrive.axes)


def test_a_run_says_which_watchdog_error_its_start_up_cleared(crashed_odrive):
    """With drive.options.clear_watchdog_error_at_start a run's bring-up cleared an expired axis watchdog (the
    last run crashed) and started without a word: nobody learned the previous run had died driving. A warning
    event, echoed on the console, names each axis, its error and that it was cleared."""
    import io

    from vbnav.control.config import Config
    from vbnav.control.controllers.manual import IdleController
    from vbnav.control.runtime.progress import EventEcho
    from vbnav.control.runtime.runtime import Runtime
    from vbnav.drivers.clock import MonotonicClock
    clock = MonotonicClock()
    drive = ODriveDrive(clock=clock, options=ODriveDrive.Options(port=crashed_odrive.path, reply_timeout_s=0.02,
                                                                 clear_watchdog_error_at_start=True))
    # timing is not under test: a loaded machine must not end the run on missed deadlines
    rt = Runtime(Config.model_validate({"loop": {"max_missed_streak": 1000, "stall_periods": 1000}}), drive,
                 IdleController(), clock)
    console = io.StringIO()
    echo = EventEcho(console).attach(rt)
    result = rt.run(duration_s=0.2)
    echo.close()
    assert result.reason == "duration", result.message
    cleared = [e for e in result.events if e.kind == "warning" and e.cause == "drive_watchdog_cleared"]
    assert [e.message for e in cleared] == [
        f"ODrive {crashed_odrive.path} axis{ax} ({side}): error=WATCHDOG_TIMER_EXPIRED found at start-up (the "
        f"host went silent before: a crash?) and cleared (drive.options.clear_watchdog_error_at_start)"
        for ax, side in ((0, "left"), (1, "right"))], result.events
    assert console.getvalue().count("safety warning: drive_watchdog_cleared: ") == 2, console.getvalue()
    assert not any(ax.any_error() for ax in crashed_odrive.axes)


def test_a_hardware_fault_is_never_cleared_at_start_and_clear_errors_reports_it(crashed_odrive, tmp_path, capsys):
    crashed_odrive.axis(1).inject(motor=0x1000)
    drive = ODriveDrive(options=ODriveDrive.Options(port=crashed_odrive.path, reply_timeout_s=0.02,
                                                    clear_watchdog_error_at_start=True))
    with pytest.raises(DriveError, match=r"CURRENT_LIMIT_VIOLATION.*find the cause.*vbnav odrive clear-errors"):
        drive.connect()
    drive.close()
    assert main(["odrive", "clear-errors", "-c", odrive_config(tmp_path, crashed_odrive.path)]) == 0
    assert "motor.error=CURRENT_LIMIT_VIOLATION" in capsys.readouterr().out


def test_clear_errors_refuses_another_drive_and_a_missing_port(tmp_path, capsys):
    assert main(["odrive", "clear-errors", "-c", "sim"]) == 2
    assert "drive.driver is 'sim'" in capsys.readouterr().err
    assert main(["odrive", "clear-errors", "-c", odrive_config(tmp_path, tmp_path / "gone")]) == 3
    assert "not found" in capsys.readouterr().err


# -- the emulators' log ------------------------------------------------------------------------------
def test_emulators_log_traffic_watchdog_expiry_and_faults(caplog):
    caplog.set_level(logging.DEBUG, logger=EMULATOR_LOG)
    with DynamixelBus([1, 2]) as bus:
        drive = DynamixelDrive(options=DynamixelDrive.Options(port=bus.path, margin_ms=8.0, bus_watchdog_s=0.04))
        drive.connect()
        drive.enable()
        drive.write(1.0, 1.0)
        end = time.monotonic() + 3.0
        while time.monotonic() < end and "bus watchdog expired" not in caplog.text:
            time.sleep(0.01)
        bus.servo(2).set_hardware_error(0x20)
        drive.close()
    text = caplog.text
    assert "PING to id 1" in text and "SYNC_WRITE to id broadcast" in text          # DEBUG: traffic
    assert "servo 1: bus watchdog expired (no packet for 40 ms)" in text             # INFO: expiry
    assert "servo 2: hardware error 0x20" in text                                   # INFO: fault
    emu = oe.ODriveEmulator()
    emu.handle_bytes(b"w axis0.config.watchdog_timeout 0.1\nw axis0.config.enable_watchdog 1\n"
                     b"w axis0.controller.config.control_mode 2\nw axis0.requested_state 8\n")
    emu.axis(0).check_watchdog(emu.axis(0).last_feed + 1.0)
    emu.corrupt = True
    emu.handle_bytes(b"sc\n")
    assert "axis0: watchdog expired (no feed for 100 ms)" in caplog.text
    assert "garbles its answers (fault injected)" in caplog.text and "sc: errors cleared" in caplog.text
    assert "'w axis0.requested_state 8' -> None" in caplog.text


def test_emulate_verbose_prints_the_log_to_stderr(capsys):
    from vbnav.control.cli import build_parser
    from vbnav.control.commands import emulate
    args = build_parser().parse_args(["emulate", "dynamixel", "--ids", "1", "--baud", "57600", "-v"])
    logger = logging.getLogger(EMULATOR_LOG)
    before = list(logger.handlers), logger.level
    try:
        emulate._log_to_stderr(args.verbose)          # what `vbnav emulate ... -v` sets up before serving
        with DynamixelBus(args.ids, baud=args.baud) as bus, DynamixelBusTool(bus.path) as tool:
            assert tool.at(1_000_000).ping(1) is None
    finally:
        logger.handlers[:] = before[0]
        logger.setLevel(before[1])
    assert "vbnav.emulator.dynamixel: host sends at 1000000 bit/s, the servos listen at 57600 bit/s" in \
        capsys.readouterr().err


# -- config check ------------------------------------------------------------------------------------
@pytest.mark.parametrize("driver, options, fields", [
    ("dynamixel", {"left_id": 2, "right_id": 2}, "left_id and right_id are both 2"),
    ("odrive", {"left_axis": 1, "right_axis": 1}, "left_axis and right_axis are both 1"),
])
def test_config_check_rejects_a_duplicate_servo_id_or_axis(tmp_path, capsys, driver, options, fields):
    path = tmp_path / "dup.yaml"
    path.write_text(yaml.safe_dump({"drive": {"driver": driver, "options": {"port": os.devnull, **options}}}))
    assert main(["config", "check", "-c", str(path)]) == 2
    assert f"{path}: drive.options: {fields}" in capsys.readouterr().err


def test_find_with_an_oak_search_cut_short_exits_cleanly():
    """--oak-timeout shorter than depthai's device search (0.5 s here) said 'not searched' and then the
    process aborted (exit 134, a C++ 'terminate called' and a stack trace) when the search returned into
    an interpreter that was shutting down."""
    import subprocess
    import sys
    pytest.importorskip("depthai")
    p = subprocess.run([sys.executable, "-m", "vbnav.control.cli", "find", "--oak-timeout", "0"],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "not searched: the device search did not return within 0 s" in p.stdout
    assert "terminate called" not in p.stderr and "Stack trace" not in p.stderr


@pytest.mark.parametrize("argv, why", [
    (["--id", "-1", "--new-id", "2"], "argument --id: expected a servo id 0..252, got '-1'"),
    (["--id", "300", "--new-id", "2"], "argument --id: expected a servo id 0..252, got '300'"),
    (["--id", "1", "--new-id", "999"], "argument --new-id: expected a servo id 0..252, got '999'"),
    (["--id", "1", "--baud", "0", "--new-id", "2"], "argument --baud: 0 is not a Dynamixel X rate"),
])
def test_servo_refuses_an_id_or_rate_out_of_range_before_touching_the_bus(argv, why, capsys):
    """--id -1 crashed with a traceback (a byte out of range), --id 300 scanned six rates and said no servo
    answers (exit 3), --baud 0 was ignored (every rate scanned, the servo changed), --new-id 999 was refused
    only once a servo was found: now each is bad input (exit 2) naming the option, and the bus is untouched."""
    with DynamixelBus([1], baud=57_600) as bus:
        with pytest.raises(SystemExit) as exit_:
            main(["servo", "set-id", "--port", bus.path, *argv])
        assert exit_.value.code == 2 and why in capsys.readouterr().err
        assert set(bus.servos) == {1}


@pytest.mark.parametrize("kind, why", [("missing", "no such device"), ("folder", "is not a device"),
                                       ("file", "is not a device")])
def test_find_refuses_a_port_that_is_not_a_device(tmp_path, capsys, kind, why):
    """find --port /no/such/tty was left out of the listing without a word (exit 0), and a folder or a plain
    file was listed as 'not USB (a pseudo-terminal or built-in UART)'."""
    path = tmp_path / kind
    if kind == "folder":
        path.mkdir()
    elif kind == "file":
        path.write_text("x")
    assert main(["find", "--port", str(path), "--oak-timeout", "0.5"]) == 2
    out, err = capsys.readouterr()
    assert f"vbnav find: --port {path}: {why}" in err and "Serial ports:" not in out


@pytest.mark.parametrize("kind", ["folder", "file"])
def test_servo_tools_refuse_a_port_that_is_not_a_device(tmp_path, capsys, kind):
    """find servos / servo set-id --port on a folder or plain file was a device error ('cannot open ...',
    exit 3) after 'Scanning'; it is bad input (exit 2) naming --port, like a path that is not there."""
    path = tmp_path / kind
    path.mkdir() if kind == "folder" else path.write_text("x")
    assert main(["find", "servos", "--port", str(path), "--baud", "57600"]) == 2
    assert f"--port {path}: is not a device" in capsys.readouterr().err
    assert main(["servo", "set-id", "--port", str(path), "--id", "1", "--new-id", "2", "--baud", "57600"]) == 2
    assert f"--port {path}: is not a device" in capsys.readouterr().err


@pytest.mark.parametrize("command", [["run", "--no-camera", "--no-telemetry", "--duration", "0.2"], ["doctor"]])
def test_the_odrive_refusal_names_the_configuration_given(crashed_odrive, tmp_path, capsys, command):
    """The refusal of a latched watchdog error told the user to run 'vbnav odrive clear-errors -c CONFIG',
    the placeholder, not the configuration the run was given: the command to copy is now whole."""
    cfg = odrive_config(tmp_path, crashed_odrive.path)
    data = yaml.safe_load(open(cfg))
    data["robot"].update(max_wheel_speed=10.0, max_linear_speed=0.4)     # within the ODrive's vel_limit
    with open(cfg, "w") as f:
        yaml.safe_dump(data, f)
    main([command[0], "-c", cfg, *command[1:]])
    captured = capsys.readouterr()
    text = captured.out + captured.err
    assert "WATCHDOG_TIMER_EXPIRED" in text, text
    assert f"vbnav odrive clear-errors -c {cfg}'" in text and "-c CONFIG" not in text, text


def test_clear_errors_says_the_watchdog_error_the_bring_up_cleared(crashed_odrive, tmp_path, capsys):
    """With drive.options.clear_watchdog_error_at_start the bring-up clears an expired axis watchdog by itself,
    and 'vbnav odrive clear-errors' then printed "no errors" for a device that had one on each axis: it prints
    the error words it found and that they were cleared, as without the option."""
    cfg = odrive_config(tmp_path, crashed_odrive.path, clear_watchdog_error_at_start=True)
    assert main(["odrive", "clear-errors", "-c", cfg]) == 0
    out = capsys.readouterr().out
    assert "no errors" not in out, out
    assert "axis0 (left): error=WATCHDOG_TIMER_EXPIRED" in out and "errors cleared" in out, out
    assert not any(ax.any_error() for ax in crashed_odrive.axes)
    assert main(["odrive", "clear-errors", "-c", cfg]) == 0
    assert "no errors" in capsys.readouterr().out


def test_clear_errors_says_axes_idle_only_when_they_are(crashed_odrive, tmp_path, capsys):
    """clear-errors printed 'errors cleared, axes idle' after sending IDLE, never reading it back: an axis still
    in closed loop (its state machine slow to leave it) was called idle, exit 0. The state is read back first;
    an axis not idle is named, exit 3."""
    ax = crashed_odrive.axis(1)
    with crashed_odrive.lock:
        ax.error = 0                                  # the other axis: no error, still driving
        ax.current_state, ax.idle_after_s = oe.AXIS_STATE_CLOSED_LOOP, 30.0
    assert main(["odrive", "clear-errors", "-c", odrive_config(tmp_path, crashed_odrive.path)]) == 3
    out, err = capsys.readouterr()
    assert "axes idle" not in out, out
    assert f"axis1 (right): did not take the stop: current_state {oe.AXIS_STATE_CLOSED_LOOP}" in err, err
    with crashed_odrive.lock:
        ax.idle_after_s = 0.0
        for a in crashed_odrive.axes:
            a.error |= oe.AXIS_ERROR_WATCHDOG_EXPIRED
    assert main(["odrive", "clear-errors", "-c", odrive_config(tmp_path, crashed_odrive.path)]) == 0
    assert "errors cleared, axes idle" in capsys.readouterr().out
