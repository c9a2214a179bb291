"""The real dynamixel-sdk driver against the emulated bus over a pseudo-terminal.

Fault tests each end by checking, in the emulator, that both wheels stand still
and that the driver's error names the cause.
"""
from __future__ import annotations

import math
import os
import time

import pytest

from driver_test_utils import controller_script, drive_for, emulate_cli, kill_controller_while_driving, wait_until

from vbnav.drivers import dynamixel_table as dt
from vbnav.drivers.sim import dynamixel_emulator as de
from vbnav.drivers.dynamixel import VELOCITY_UNIT_RAD_S, DynamixelDrive
from vbnav.drivers.wheels import DriveError, DriveState, FaultKind

WATCHDOG_S = 0.2  # generous: a loaded CI machine may pause a test thread for 100+ ms


@pytest.fixture
def bus(tmp_path):
    b = de.DynamixelBus([1, 2], "XL430-W250", link=tmp_path / "ttyDXL")
    b.start()
    yield b
    b.stop()


def make_drive(bus, **opts) -> DynamixelDrive:
    options = DynamixelDrive.Options(port=bus.path, bus_watchdog_s=WATCHDOG_S, margin_ms=8.0, **opts)
    return DynamixelDrive(options=options, invert_right=True)


@pytest.fixture
def drive(bus):
    d = make_drive(bus)
    d.connect()
    d.enable()
    yield d
    d.close()


def wheels_stopped(bus) -> bool:
    return all(abs(bus.servo(i)._velocity) < 0.5 and bus.servo(i).target_velocity() == 0 for i in (1, 2))


def test_bring_up_in_safe_order(bus):
    d = make_drive(bus, profile_acceleration_rad_s2=20.0, velocity_limit_rad_s=5.0)
    d.connect()
    for i in (1, 2):
        ops = [(e.op, e.addr, e.value) for e in bus.log if e.dxl_id == i and e.op in ("ping", "write")]
        assert ops[0][0] == "ping"
        # (a write retried after a late answer would repeat itself: collapse repeats)
        steps = [(a, v) for k, (_, a, v) in enumerate(ops) if k > 0 and (a, v) != ops[k - 1][1:]]
        assert [a for a, _ in steps] == [64, 11, 44, 108, 9, 98, 98], steps
        values = dict(steps)
        assert values[11] == 1 and values[9] == 0 and values[98] == round(WATCHDOG_S / 0.02)
        assert values[44] == round(5.0 / VELOCITY_UNIT_RAD_S)
        assert not bus.servo(i).torque_on
    d.enable()
    assert all(bus.servo(i).torque_on for i in (1, 2))
    last = [e for e in bus.writes(1)][-1]
    assert (last.addr, last.value) == (64, 1)
    d.close()
    assert not any(bus.servo(i).torque_on for i in (1, 2))


def test_driver_writes_what_the_emulator_reads_by_name(bus):
    """Driver and emulator share one control table: every register the driver sets arrives, by name,
    with the value the driver meant."""
    d = make_drive(bus, profile_acceleration_rad_s2=20.0, velocity_limit_rad_s=5.0)
    d.connect()
    d.enable()
    d.write(1.0, -0.5)
    d.read()
    by_address = {r.address: r.name for r in dt.REGISTERS.values()}
    assert {by_address[e.addr] for e in bus.writes(1)} == {
        "Torque Enable", "Operating Mode", "Velocity Limit", "Profile Acceleration", "Return Delay Time",
        "Bus Watchdog", "Goal Velocity"}
    expected = {"Torque Enable": 1, "Operating Mode": dt.MODE_VELOCITY,
                "Velocity Limit": round(5.0 / dt.VELOCITY_UNIT_RAD_S),
                "Profile Acceleration": round(20.0 / dt.ACCEL_UNIT_RAD_S2), "Return Delay Time": 0,
                "Bus Watchdog": round(WATCHDOG_S / dt.WATCHDOG_UNIT_S)}
    for i, rate in ((1, 1.0), (2, 0.5)):  # the right wheel is mounted mirrored
        got = {name: bus.servo(i).get(dt.REGISTERS[name]) for name in [*expected, "Goal Velocity"]}
        assert got == {**expected, "Goal Velocity": round(rate / dt.VELOCITY_UNIT_RAD_S)}
    d.close()


def test_wrong_model_is_refused(tmp_path):
    with de.DynamixelBus([1, 2], "XM430-W350", link=tmp_path / "tty") as b:
        d = DynamixelDrive(options=DynamixelDrive.Options(port=b.path, model="XL430-W250"))
        with pytest.raises(DriveError, match="model number 1020"):
            d.connect()


def test_missing_adapter_is_a_clear_error(tmp_path):
    d = DynamixelDrive(options=DynamixelDrive.Options(port=str(tmp_path / "nothing")))
    with pytest.raises(DriveError, match="not found"):
        d.connect()


def test_velocity_commands_reach_servos_and_read_back_signed(bus, drive):
    before = bus.packets_seen
    drive.write(1.0, -0.5)
    drive.read()
    assert bus.packets_seen - before == 2  # one sync write + one sync read per cycle
    assert bus.servo(1).get(dt.GOAL_VELOCITY) == round(1.0 / VELOCITY_UNIT_RAD_S)
    # right wheel is mounted mirrored (invert_right): -0.5 rad/s is +21 units on the servo
    assert bus.servo(2).get(dt.GOAL_VELOCITY) == round(0.5 / VELOCITY_UNIT_RAD_S)
    assert wait_until(lambda: bus.servo(1).get(dt.PRESENT_VELOCITY) != 0)
    state = drive_for(drive, -1.0, 0.5, cycles=5)
    assert state.velocity[0] == pytest.approx(-1.0, abs=VELOCITY_UNIT_RAD_S)
    assert state.velocity[1] == pytest.approx(0.5, abs=VELOCITY_UNIT_RAD_S)
    assert state.enabled and not state.faults


def test_commands_clamp_to_velocity_limit(bus, drive):
    drive.write(100.0, -100.0)
    drive.read()  # the answer comes after the servos processed the write
    limit = round(6.0 / VELOCITY_UNIT_RAD_S)
    assert bus.servo(1).get(dt.GOAL_VELOCITY) == limit
    assert bus.servo(2).get(dt.GOAL_VELOCITY) == limit


def test_position_unwraps_across_int32_overflow(bus, drive):
    with bus.lock:
        bus.servo(1)._position = 2 ** 31 - 300.0
        bus.servo(1)._sync_present()
    start = drive.read().position[0]
    end = drive_for(drive, 6.0, 0.0, cycles=40).position[0]
    assert bus.servo(1).get(dt.PRESENT_POSITION) < 0  # the register wrapped
    assert 0 < end - start < 3.0  # ~0.2-0.5 s at 6 rad/s, continuous


def test_budgeted_answer_window_is_milliseconds():
    d = DynamixelDrive(options=DynamixelDrive.Options(port="/dev/null", latency_ms=1.0, margin_ms=1.0))
    from vbnav.drivers.dynamixel import BudgetedPort
    p = BudgetedPort("/dev/null", 1.0, 1.0)
    p.tx_time_per_byte = 0.01  # 1 Mbps
    p.setPacketTimeout((11 + 8) * 2)
    assert p.packet_timeout < 4.0  # ms; the stock SDK waits 2 x 16 + 2 = 34 ms
    assert d._watchdog_units == 5


def test_servo_that_stops_answering(bus, drive):
    drive_for(drive, 2.0, 2.0)
    bus.servo(2).no_answer = True
    with pytest.raises(DriveError, match=r"servo 2 \(right\).*not answering"):
        drive_for(drive, 2.0, 2.0)
    assert wait_until(lambda: wheels_stopped(bus))
    assert bus.servo(2).get(dt.BUS_WATCHDOG, signed=False) == 0xFF  # the silent one was stopped by its watchdog
    assert not bus.servo(1).torque_on
    with pytest.raises(DriveError, match="faulted"):
        drive.write(1.0, 1.0)


def test_corrupted_packets(bus, drive):
    drive_for(drive, 2.0, 2.0)
    bus.servo(1).corrupt = True
    with pytest.raises(DriveError, match=r"servo 1 \(left\).*corrupted"):
        drive_for(drive, 2.0, 2.0)
    assert wait_until(lambda: wheels_stopped(bus))
    assert not bus.servo(1).torque_on and not bus.servo(2).torque_on


def test_hardware_error_bit_then_reboot(bus, drive):
    drive_for(drive, 2.0, 2.0)
    with bus.lock:
        bus.servo(2).set_hardware_error(1 << 5)
    with pytest.raises(DriveError, match=r"servo 2 \(right\) hardware error: overload \(bit 5\)"):
        drive_for(drive, 2.0, 2.0)
    assert wait_until(lambda: wheels_stopped(bus))
    assert drive.state is DriveState.ERROR
    assert [(f.kind, f.device) for f in drive.read().faults] == [(FaultKind.HARDWARE_ERROR, "servo 2 (right)")]
    assert "overload" in drive.faults[0].message
    with pytest.raises(DriveError):
        drive.enable()
    drive.clear_faults()
    assert [e.dxl_id for e in bus.log if e.op == "reboot"] == [2]
    assert bus.servo(2).hardware_error == 0
    drive.enable()
    state = drive_for(drive, 1.0, 1.0, cycles=20)
    assert state.velocity == pytest.approx((1.0, 1.0), abs=VELOCITY_UNIT_RAD_S) and not state.faults


def test_adapter_disappears_then_comes_back(bus, drive):
    drive_for(drive, 2.0, 2.0)
    bus.unplug()
    with pytest.raises(DriveError, match=r"ttyDXL lost.*watchdog"):
        drive_for(drive, 2.0, 2.0)
    assert wait_until(lambda: wheels_stopped(bus))  # by the servos' own bus watchdog
    with pytest.raises(DriveError, match="gone"):
        drive.read()
    bus.replug()
    assert wait_until(lambda: _reads(drive), timeout=3.0)
    drive.enable()
    state = drive_for(drive, 1.0, 1.0, cycles=20)
    assert state.velocity == pytest.approx((1.0, 1.0), abs=VELOCITY_UNIT_RAD_S)


def _reads(drive) -> bool:
    try:
        drive.read()
        return True
    except DriveError:
        return False


CONTROLLER = controller_script("dynamixel", "DynamixelDrive", "bus_watchdog_s")


def test_controlling_process_killed_with_sigkill(bus):
    kill_controller_while_driving(CONTROLLER, bus.path, WATCHDOG_S,
                                  moving=lambda: abs(bus.servo(1)._velocity) > 100,
                                  stopped=lambda: wheels_stopped(bus))
    with bus.lock:
        expired = [e for e in bus.log if e.op == "watchdog_expired"]
        assert sorted(e.dxl_id for e in expired) == [1, 2]
        last_packet = max(e.t for e in bus.log if e.op == "write")
    # the wheel stops within the configured watchdog time (plus the emulator's 1 ms step)
    for e in expired:
        assert WATCHDOG_S <= e.t - last_packet <= WATCHDOG_S + 0.5, e.t - last_packet  # upper: emulator scheduling slack
    assert math.isclose(bus.servo(1).get(dt.BUS_WATCHDOG), -1)


def test_vbnav_emulate_dynamixel_prints_device_path_first(tmp_path):
    with emulate_cli("dynamixel", "--ids", "3,4", "--model", "XM430-W350") as path:
        assert os.path.exists(path)
        d = DynamixelDrive(options=DynamixelDrive.Options(port=path, left_id=3, right_id=4, model="XM430-W350",
                                                          margin_ms=3.0))
        d.connect()
        assert d.models == {3: 1020, 4: 1020}
        d.close()


def test_a_stalled_controller_finds_the_watchdog_expired(bus, drive):
    drive_for(drive, 2.0, 2.0)
    time.sleep(WATCHDOG_S * 2)  # the loop stalls longer than the watchdog: the servos stop themselves
    assert wheels_stopped(bus)
    with pytest.raises(DriveError, match=r"bus watchdog expired after \d+ ms without commands \(limit \d+ ms\)"):
        drive.write(1.0, 1.0)
    drive.clear_faults()
    drive.enable()  # clears the latched watchdog error (0xFF) and re-arms it
    assert drive_for(drive, 1.0, 1.0, cycles=20).velocity == pytest.approx((1.0, 1.0), abs=VELOCITY_UNIT_RAD_S)


def test_hardware_error_found_at_bring_up_then_cleared(bus):
    bus.servo(1).set_hardware_error(1 << 2)
    d = make_drive(bus)
    with pytest.raises(DriveError, match=r"servo 1 \(left\) hardware error: overheating \(bit 2\).*REBOOT"):
        d.connect()
    assert not any(bus.servo(i).torque_on for i in (1, 2))
    d.clear_faults()
    assert [e.dxl_id for e in bus.log if e.op == "reboot"] == [1]
    d.enable()
    assert drive_for(d, 1.0, 1.0, cycles=20).velocity == pytest.approx((1.0, 1.0), abs=VELOCITY_UNIT_RAD_S)
    d.close()


def test_a_baud_rate_no_dynamixel_x_servo_runs_at_is_refused_by_the_config():
    """A baud rate outside the X series' table passed the config check and failed only at start-up, as "cannot
    open the adapter" or as servo 1 "did not answer ping": the field and the rates it takes went unsaid."""
    from vbnav.control.config import ConfigError, parse_config
    with pytest.raises(ConfigError, match=r"drive\.options\.baudrate.*100000.*57600.*1000000"):
        parse_config({"drive": {"driver": "dynamixel", "options": {"baudrate": 100000}}}, "robot.yaml")
    assert DynamixelDrive.Options(baudrate=57600).baudrate == 57600


def test_adapter_unplugged_while_the_loop_stalled_is_a_lost_bus(bus, drive):
    """The first write after a stall longer than the watchdog reads the servos' Bus Watchdog; with the adapter
    gone meanwhile that read raised termios.error out of write(): the runtime ended the run on an "exception"
    instead of a lost bus it waits for. It is a BUS_LOST fault now, and the adapter is looked for again."""
    drive_for(drive, 2.0, 2.0)
    time.sleep(WATCHDOG_S * 2)
    bus.unplug()
    with pytest.raises(DriveError, match=r"ttyDXL lost.*watchdog"):
        drive.write(1.0, 1.0)
    assert drive.state is DriveState.ERROR and [f.kind for f in drive.faults] == [FaultKind.BUS_LOST]
    assert wait_until(lambda: wheels_stopped(bus))
    bus.replug()
    assert wait_until(lambda: _reads(drive), timeout=3.0)
    assert drive.state is DriveState.INACTIVE


def test_a_velocity_limit_above_the_register_range_is_refused_not_cut():
    """velocity_limit_rad_s above what Velocity Limit (44) holds (1023 units, 24.5 rad/s) was accepted and
    cut to 1023 units without a word: the robot drove slower than its configuration said."""
    with pytest.raises(ValueError, match=r"velocity_limit_rad_s[\s\S]*24\.5"):
        DynamixelDrive.Options(velocity_limit_rad_s=30.0)
    assert DynamixelDrive(options=DynamixelDrive.Options(velocity_limit_rad_s=24.53))._limit_units == 1023


def test_a_small_profile_acceleration_is_not_rounded_to_no_limit(bus):
    """Profile Acceleration counts in 0.3745 rad/s^2 units and 0 means no limit: a gentle 0.1 rad/s^2 was
    rounded to 0, so the configured limit turned into none at all. A positive setting writes at least 1."""
    d = make_drive(bus, profile_acceleration_rad_s2=0.1)
    d.connect()
    try:
        assert all(bus.servo(i).get(dt.PROFILE_ACCELERATION) == 1 for i in (1, 2))
    finally:
        d.close()


def test_a_servo_that_does_not_take_the_stop_is_named_in_stop_failure(bus, drive):
    """disable() never raises, so a servo that did not answer the torque-off went unsaid: the caller took
    the wheels for stopped. The drive keeps what it could not stop in ``stop_failure``."""
    drive_for(drive, 2.0, 2.0)
    bus.servo(2).no_answer = True
    drive.disable()
    assert drive.stop_failure is not None and "servo 2" in drive.stop_failure, drive.stop_failure
    assert "servo 1" not in drive.stop_failure and not bus.servo(1).torque_on
    bus.servo(2).no_answer = False
    drive.enable()
    drive.disable()
    assert drive.stop_failure is None


def test_a_servo_that_refuses_the_torque_off_is_named_in_stop_failure(bus, drive):
    """A status packet that answers the torque-off with an error (CRC Error: the instruction arrived corrupted
    and the servo applied nothing) was taken as the stop taken: only no answer at all was noticed."""
    drive_for(drive, 2.0, 2.0)
    bus.servo(2).garbled_rx = True
    drive.disable()
    assert drive.stop_failure is not None and "servo 2 (right): torque off refused" in drive.stop_failure, \
        drive.stop_failure
    assert "CRC" in drive.stop_failure and "servo 1" not in drive.stop_failure
    assert bus.servo(2).torque_on and not bus.servo(1).torque_on     # the emulated servo really is still on
    bus.servo(2).garbled_rx = False


def test_an_adapter_slower_than_latency_ms_is_refused_at_bring_up(bus, monkeypatch):
    """drive.options.latency_ms is the FTDI latency timer the answer window assumes (2 x latency_ms +
    margin_ms): only 'vbnav doctor' compared it with the adapter's own. A run on an adapter left at the
    kernel's 16 ms waited 1 ms and every ping timed out as 'a wrong id or baud rate?'. The bring-up now refuses
    it, naming the adapter's timer, the option and the fix; an adapter as fast as the option is taken."""
    from vbnav.drivers import discovery
    monkeypatch.setattr(discovery, "read_latency_timer", lambda port, sysfs="/sys": 16)
    d = make_drive(bus)
    with pytest.raises(DriveError, match=r"latency timer is 16 ms.*drive.options.latency_ms 1 ms.*latency_timer"):
        d.connect()
    d.close()
    monkeypatch.setattr(discovery, "read_latency_timer", lambda port, sysfs="/sys": 1)
    d = make_drive(bus)
    d.connect()
    d.close()


def test_a_run_says_which_servo_watchdog_its_start_up_cleared(bus):
    """A run that died driving leaves a servo's Bus Watchdog expired (0xFF, goals locked); the bring-up cleared it
    without a word, so nobody learned the last run had died. A drive_watchdog_cleared warning event names each
    servo it cleared, and only those."""
    import io

    from vbnav.control.config import Config
    from vbnav.control.controllers.manual import IdleController
    from vbnav.control.runtime.progress import EventEcho
    from vbnav.control.runtime.runtime import Runtime
    from vbnav.drivers.clock import MonotonicClock
    bus.servo(2).put(dt.BUS_WATCHDOG, -1)   # what the servo's own watchdog leaves after the host went silent
    drive = DynamixelDrive(clock=MonotonicClock(), options=DynamixelDrive.Options(
        port=bus.path, bus_watchdog_s=WATCHDOG_S, margin_ms=8.0), invert_right=True)
    # timing is not under test: a loaded machine must not end the run on missed deadlines
    rt = Runtime(Config.model_validate({"loop": {"max_missed_streak": 1000, "stall_periods": 1000}}), drive,
                 IdleController(), drive.clock)
    console = io.StringIO()
    echo = EventEcho(console).attach(rt)
    result = rt.run(duration_s=0.2)
    echo.close()
    assert result.reason == "duration", result.message
    cleared = [e.message for e in result.events if e.kind == "warning" and e.cause == "drive_watchdog_cleared"]
    assert cleared == [f"servo 2 (right) on {bus.path}: Bus Watchdog expired (0xFF) found at start-up (the host "
                       f"went silent before: a crash?) and cleared"], result.events
    assert console.getvalue().count("safety warning: drive_watchdog_cleared: ") == 1, console.getvalue()
    assert bus.servo(2).get(dt.BUS_WATCHDOG) == round(WATCHDOG_S / dt.WATCHDOG_UNIT_S)
