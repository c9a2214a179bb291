"""Drive faults that heal, with the real drivers over a pty to their emulators, on the real clock.

- a motor that misses a few reads (shorter than ``max_missed_reads``) is no fault at all;
- a motor that stops answering and answers again is reconnected with the safe bring-up, and the robot
  waits, stopped, for ``resume`` (the run goes on: no exit);
- a device watchdog that expired while the host was frozen is re-armed the same way.
"""
from __future__ import annotations

import time

import pytest

from test_drive_reconnect import Dxl, ODrv, _cfg, _events
from test_safety import Cruise

from vbnav.control.runtime.runtime import OperatorCommand, Runtime
from vbnav.drivers.clock import MonotonicClock

RESUME_AFTER_S = 0.3


def silence(device, on: bool) -> None:
    with device.dev.lock:
        if isinstance(device, Dxl):
            device.dev.servo(2).no_answer = on
        else:
            device.dev.no_answer = on


@pytest.fixture(params=[Dxl, ODrv], ids=["dynamixel", "odrive"])
def device(request, tmp_path):
    d = request.param(tmp_path)
    with d.dev:              # the emulator serves its pty for the test
        yield d


def _run(device, script, duration_s: float, window_s: float = 3.0):
    """Cruise on the real clock; ``script(t, cycle)`` acts on the device; resume RESUME_AFTER_S after the
    drive is back. Returns (result, samples (t, wheel command, device moving), runtime)."""
    clock = MonotonicClock()
    cfg = _cfg(window_s, max_missed_streak=1000, stall_periods=1000)   # the loop's timing is not under test
    rt = Runtime(cfg, device.drive(clock), Cruise(), clock)
    samples, back_at = [], [None]

    def observe(r, ctx, twist, wheels):
        t = (ctx.now_ns - r._start_ns) * 1e-9
        with device.dev.lock:
            samples.append((t, r.wheel_command, device.moving()))
        script(t, ctx.cycle)
        if back_at[0] is not None and t >= back_at[0] + RESUME_AFTER_S:
            r.submit(OperatorCommand("resume", (), "test"))
            back_at[0] = None

    def on_event(ev):
        if ev.kind == "drive_reconnected":
            back_at[0] = (ev.stamp_ns - rt._start_ns) * 1e-9

    rt.cycle_observers.append(observe)
    rt.safety.listeners.append(on_event)
    return rt.run(duration_s=duration_s), samples, rt


def test_a_few_missed_reads_are_no_fault(device):
    marks = {}

    def script(t, cycle):
        if t >= 0.5 and "off" not in marks:
            silence(device, True)
            marks["off"] = cycle
        elif "off" in marks and "on" not in marks and cycle >= marks["off"] + 3:   # 3 reads unanswered
            silence(device, False)
            marks["on"] = cycle

    result, samples, _ = _run(device, script, duration_s=1.0)
    assert result.reason == "duration", result.message
    assert not [e for e in result.events if e.cause in ("drive", "drive_lost")], result.events
    assert samples[-1][2]                                     # still driving at the end


def test_a_motor_that_stops_answering_and_comes_back_is_reconnected_and_waits_for_resume(device):
    def script(t, cycle):
        if 0.5 <= t < 1.1:
            silence(device, True)
        elif t >= 1.1:
            silence(device, False)

    result, samples, rt = _run(device, script, duration_s=2.6)
    assert result.reason == "duration", result.message       # the run went on: no exit

    def at(kind, cause=None) -> float:     # the first such event (a loaded machine may add a later miss streak)
        return (_events(result, kind, cause)[0].stamp_ns - rt._start_ns) * 1e-9

    lost, back, reset = at("trip", "drive_lost"), at("drive_reconnected"), at("reset", "drive_lost")
    assert "no answer" in _events(result, "trip", "drive_lost")[0].message or \
        "not answering" in _events(result, "trip", "drive_lost")[0].message
    assert 0.5 < lost < 1.1 <= back < back + RESUME_AFTER_S <= reset
    assert all(cmd == (0.0, 0.0) for t, cmd, _ in samples if lost <= t < reset)     # stopped until resume
    assert any(moving for t, _, moving in samples if t >= reset + 0.5)               # drives again after it


def test_an_expired_device_watchdog_after_a_frozen_loop_is_rearmed_and_waits_for_resume(device):
    frozen = []

    def script(t, cycle):
        if t >= 0.5 and not frozen:
            frozen.append(t)
            time.sleep(0.45)          # the host silent beyond the 0.2 s device watchdog of these tests

    result, samples, rt = _run(device, script, duration_s=3.0)
    assert result.reason == "duration", result.message
    lost = _events(result, "trip", "drive_lost")
    assert lost and "watchdog" in lost[0].message.lower()
    assert _events(result, "drive_reconnected") and _events(result, "reset", "drive_lost")
    reset = (_events(result, "reset", "drive_lost")[0].stamp_ns - rt._start_ns) * 1e-9
    assert any(moving for t, _, moving in samples if t >= reset + 0.5)


def test_a_stop_a_motor_did_not_take_is_sent_again_until_it_is_taken(device):
    """An estop whose stop one motor did not take (the Dynamixel servo heard the sync write, Goal Velocity 0
    and the torque-off corrupted; the ODrive axis lost its 'v' and 'w' lines) was reported with 'only the
    device's own watchdog stops it now', and never sent again. But the loop goes on reading the motors, and
    a Dynamixel bus watchdog counts every packet: fed by the reads, it never trips, and the servo drove on.
    The stop is now sent again until the motor takes it, and the report says when it did."""
    marks = {}

    def script(t, cycle):
        with device.dev.lock:
            if t >= 0.5 and "estop" not in marks:
                if isinstance(device, Dxl):
                    device.dev.servo(2).drops_stops = 3       # the stop's sync write, Goal Velocity 0, torque off
                else:
                    device.dev.axis(1).ignores_commands = True
                marks["estop"] = t
            elif "estop" in marks and "taken" not in marks and not isinstance(device, Dxl):
                if _events_so_far(rt, "warning", "stop_unconfirmed"):
                    device.dev.axis(1).ignores_commands = False   # the first stop is over: the next one is taken
                    marks["taken"] = t
        if marks.get("estop") == t:
            rt.submit(OperatorCommand("estop", (), "test"))

    def _events_so_far(r, kind, cause):
        return [e for e in r.safety.events if e.kind == kind and e.cause == cause]

    rt = None

    def run():
        nonlocal rt
        clock = MonotonicClock()
        cfg = _cfg(3.0, max_missed_streak=1000, stall_periods=1000)
        # The devices' own watchdogs at 1 s: a loop starved of CPU for 0.2 s (a shared 2-core machine) tripped
        # the ODrive's and ended the scenario as drive_lost; the resent stop, not a watchdog, must stop the motor.
        rt = Runtime(cfg, device.drive(clock, watchdog_s=1.0), Cruise(), clock)
        stopped_at = []

        def observe(r, ctx, twist, wheels):
            t = (ctx.now_ns - r._start_ns) * 1e-9
            script(t, ctx.cycle)
            with device.dev.lock:
                if "estop" in marks and device.stopped() and not device.powered() and not stopped_at:
                    stopped_at.append(t)

        rt.cycle_observers.append(observe)
        return rt.run(duration_s=1.5), stopped_at

    result, stopped_at = run()
    assert result.reason == "duration", result.message
    assert len(_events(result, "warning", "stop_unconfirmed")) == 1, result.events
    warning, = _events(result, "warning", "stop_unconfirmed")
    assert ("servo 2 (right)" if isinstance(device, Dxl) else "axis1 (right)") in warning.message, warning
    assert "sending it again" in warning.message and "only the device's own watchdog" not in warning.message
    confirmed, = _events(result, "stop_confirmed")
    assert confirmed.stamp_ns > warning.stamp_ns and "is confirmed now" in confirmed.message, confirmed
    assert stopped_at and stopped_at[0] < 1.5, "the motor was still moving or powered when the run ended"


def test_a_stop_not_taken_is_not_confirmed_by_a_close_that_reached_nothing(device):
    """A motor did not take a stop; the bus was then lost and the reconnect met a device fault, which leaves the
    port released. The drive's close sent its stop into nothing (no port: no motor named as missing it), and
    the runtime reported 'the stop it had not taken is confirmed now'. The close keeps the stop not taken."""
    from vbnav.drivers.clock import MonotonicClock
    drive = device.drive(MonotonicClock(), watchdog_s=1.0)
    drive.connect()
    drive.enable()
    with device.dev.lock:
        if isinstance(device, Dxl):
            device.dev.servo(2).drops_stops = 3
        else:
            device.dev.axis(1).ignores_commands = True
    drive.disable()
    assert drive.stop_failure, "the injected fault did not keep a motor from the stop"
    drive._release()                 # what a reconnect that met a device fault leaves (wheels.reconnect)
    drive.close()
    assert drive.stop_failure and "reached nothing" in drive.stop_failure, drive.stop_failure


def test_a_stop_not_taken_stays_said_through_a_stop_sent_while_the_device_is_released(device):
    """A motor did not take an estop's stop; the bus was then lost (the port released) and the reconnect met a
    device fault. Every stop the runtime sent meanwhile (the loss's, the run's end) reached no port, and the
    drive's disable() called that silence 'every motor stopped': the stop not taken was forgotten, and the run
    ended saying 'the stop it had not taken is confirmed now: sent again as the drive closed'. A disable that
    reaches nothing keeps the stop not taken; the close says it reached nothing."""
    from vbnav.drivers.clock import MonotonicClock
    from vbnav.drivers.wheels import DriveError, DriveState
    drive = device.drive(MonotonicClock(), watchdog_s=1.0)
    drive.connect()
    drive.enable()
    with device.dev.lock:
        if isinstance(device, Dxl):
            device.dev.servo(2).drops_stops = 10 ** 6
        else:
            device.dev.axis(1).ignores_commands = True
    drive.disable()                  # the estop's stop: one motor does not take it
    missed = drive.stop_failure
    assert missed and "(right)" in missed, missed
    device.dev.unplug()
    with pytest.raises(DriveError, match="lost"):
        drive.read()                 # the loss: the port is released
    assert drive.state is DriveState.ERROR
    drive.disable()                  # the runtime's stop at the loss, and at the end of the run
    assert drive.stop_failure == missed, drive.stop_failure
    drive.close()
    assert drive.stop_failure and missed in drive.stop_failure and "reached nothing" in drive.stop_failure, \
        drive.stop_failure
    device.dev.replug()


def test_an_enable_makes_a_stop_not_taken_before_moot(device):
    """The drive armed again (a resume) is no longer stopped: a stop not taken before is not reported as the
    stop of a later loss, which reached nothing."""
    from vbnav.drivers.clock import MonotonicClock
    drive = device.drive(MonotonicClock(), watchdog_s=1.0)
    drive.connect()
    drive.enable()
    with device.dev.lock:
        if isinstance(device, Dxl):
            device.dev.servo(2).drops_stops = 2     # the disable's Goal Velocity 0 and torque off
        else:
            device.dev.axis(1).ignores_commands = True
    drive.disable()
    assert drive.stop_failure
    with device.dev.lock:
        if not isinstance(device, Dxl):
            device.dev.axis(1).ignores_commands = False
    drive.enable()
    assert drive.stop_failure is None
    drive.close()
