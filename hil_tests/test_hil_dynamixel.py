"""The full control loop, the real dynamixel-sdk driver, a pty, the emulated servo bus, and the
simulated base under it: a scripted route, and odometry against the simulator's true pose."""
from __future__ import annotations

import math

from hil_helpers import run_route

from vbnav.drivers.sim.dynamixel_emulator import DynamixelBus

SCRIPT = [[0.15, 0.0, 1.5], [0.12, 0.8, 1.5], [0.0, 0.0, 0.4]]


def test_scripted_route_odometry_matches_simulator():
    # right servo mounted mirrored (config invert_right: true): it turns backwards to drive forwards
    result, rt, coupling = run_route(
        "sentry-dynamixel.yaml",
        lambda c: DynamixelBus([1, 2], "XL430-W250", coupling=c),
        {"margin_ms": 5.0, "max_missed_reads": 3, "bus_watchdog_s": 0.5}, SCRIPT, channels={1: (0, 1), 2: (1, -1)})
    assert result.reason == "finished", result.message
    truth, odom = coupling.true_pose, rt.odometry.pose
    travelled = 0.15 * 1.5 + 0.12 * 1.5
    assert 0.85 * travelled < rt.odometry.distance < 1.1 * travelled
    assert odom.z > 0.25 and odom.x > 0.02  # forward, then curving right (theta grows to the right)
    # measured 0.015 mm / 2e-4 rad on 2026-11-30; the run is on the real clock, so the bars keep room
    # for sampling jitter on a loaded machine
    assert math.hypot(truth.x - odom.x, truth.z - odom.z) < 0.001
    assert abs(math.remainder(truth.theta - odom.theta, 2 * math.pi)) < 0.001
    assert 0.8 * 0.8 * 1.5 < truth.theta < 1.1 * 0.8 * 1.5
    assert result.timing.cycles > 300
