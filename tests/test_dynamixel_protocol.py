"""The emulated Dynamixel bus against the ROBOTIS e-Manual's Protocol 2.0 example packets.

Each example gives the instruction bytes a controller sends and the status bytes
a servo answers; the emulator must produce exactly those bytes from the same
control-table state.
"""
from __future__ import annotations

import pytest

from vbnav.drivers import dynamixel_protocol as dp
from vbnav.drivers import dynamixel_table as dt
from vbnav.drivers.sim import dynamixel_emulator as de

H = bytes.fromhex


def _bus(ids=(1, 2), model=None):
    bus = de.DynamixelBus(ids, model or de.MODELS["XL430-W250"])
    return bus


def test_control_table_is_consistent():
    regs = sorted(dt.REGISTERS.values(), key=lambda r: r.address)
    assert all(a.end <= b.address for a, b in zip(regs, regs[1:]))  # no overlaps
    assert dt.TABLE_SIZE == 147 and dt.REGISTERS["Present Temperature"].end == dt.TABLE_SIZE
    # the driver reads Present Velocity and Present Position in one block
    assert dt.PRESENT_POSITION.address == dt.PRESENT_VELOCITY.end
    assert dt.GOAL_VELOCITY.decode(dt.GOAL_VELOCITY.encode(-100)) == -100
    assert dt.GOAL_VELOCITY.encode(-1) == b"\xff\xff\xff\xff"
    assert dt.BUS_WATCHDOG.decode(b"\xff") == -1 and dt.BUS_WATCHDOG.decode(b"\xff", signed=False) == 0xFF
    assert {m.number for m in de.MODELS.values()} <= set(dt.MODEL_NUMBERS.values())


def test_emulator_access_follows_the_table():
    s = de.EmulatedServo(1, de.MODELS["XL430-W250"])
    for r in dt.REGISTERS.values():  # torque off: rewriting a register's own value is refused only if read-only
        assert s.write(r.address, s.table[r.address:r.end]) == (0 if r.writable else dp.ERR_ACCESS), r.name


def test_crc_of_the_manual_ping_packet():
    assert dp.crc16(H("FF FF FD 00 01 03 00 01")) == 0x4E19
    assert dp.encode(1, dp.INST_PING) == H("FF FF FD 00 01 03 00 01 19 4E")


def test_ping_example():
    # e-Manual: ping ID 1, answered by a model 1030 with firmware 0x26
    bus = _bus((1,), de.ServoModel("XM430-W210", 1030, 200, 120))
    bus.servo(1).put(dt.FIRMWARE_VERSION, 0x26)
    assert bus.handle_bytes(H("FF FF FD 00 01 03 00 01 19 4E")) == H("FF FF FD 00 01 07 00 55 00 06 04 26 65 5D")


def test_ping_of_absent_id_is_silent():
    assert _bus((1,)).handle_bytes(dp.encode(7, dp.INST_PING)) == b""


def test_read_example_present_position():
    bus = _bus((1,))
    bus.servo(1).put(dt.PRESENT_POSITION, 166)
    got = bus.handle_bytes(H("FF FF FD 00 01 07 00 02 84 00 04 00 1D 15"))
    assert got == H("FF FF FD 00 01 08 00 55 00 A6 00 00 00 8C C0")


def test_write_example_goal_position():
    bus = _bus((1,))
    got = bus.handle_bytes(H("FF FF FD 00 01 09 00 03 74 00 00 02 00 00 CA 89"))
    assert got == H("FF FF FD 00 01 04 00 55 00 A1 0C")
    assert bus.servo(1).get(dt.GOAL_POSITION) == 512


def test_write_whose_data_contains_a_header_is_stuffed_and_unstuffed():
    value = bytes([0xFF, 0xFF, 0xFD, 0x00])  # Goal Position 0x00FDFFFF
    pkt = dp.encode(1, dp.INST_WRITE, bytes([0x74, 0x00]) + value)
    # LEN counts the stuffed FD: INST(1) + addr(2) + data(4) + stuffing(1) + CRC(2) = 10
    assert pkt[:14] == H("FF FF FD 00 01 0A 00 03 74 00 FF FF FD FD")
    assert dp.crc16(pkt[:-2]) == pkt[-2] | pkt[-1] << 8
    bus = _bus((1,))
    assert dp.decode(bus.handle_bytes(pkt)).error == 0
    assert bus.servo(1).get(dt.GOAL_POSITION) == 0x00FDFFFF
    # reading it back: the status data contains the header too and comes back stuffed
    answer = bus.handle_bytes(dp.encode(1, dp.INST_READ, H("74 00 04 00")))
    assert H("FF FF FD FD") in answer[7:]
    assert dp.decode(answer).data == value


@pytest.mark.parametrize("body", [b"", b"\xff\xff\xfd", b"\xff\xff\xfd\xfd", b"a\xff\xff\xfd\xff\xff\xfdb", bytes(range(256))])
def test_stuffing_round_trip(body):
    assert dp.unstuff(dp.stuff(body)) == body
    assert dp.decode(dp.encode(3, dp.INST_WRITE, body)).params == body


def test_sync_read_example():
    bus = _bus((1, 2))
    bus.servo(1).put(dt.PRESENT_POSITION, 166)
    bus.servo(2).put(dt.PRESENT_POSITION, 2079)
    got = bus.handle_bytes(H("FF FF FD 00 FE 09 00 82 84 00 04 00 01 02 CE FA"))
    assert got == H("FF FF FD 00 01 08 00 55 00 A6 00 00 00 8C C0") + H("FF FF FD 00 02 08 00 55 00 1F 08 00 00 BA BE")


def test_sync_write_example():
    bus = _bus((1, 2))
    got = bus.handle_bytes(H("FF FF FD 00 FE 11 00 83 74 00 04 00 01 96 00 00 00 02 AA 00 00 00 82 87"))
    assert got == b""  # broadcast: no status packets
    assert bus.servo(1).get(dt.GOAL_POSITION) == 150
    assert bus.servo(2).get(dt.GOAL_POSITION) == 170


def test_bulk_read_example():
    # ID 1: Present Input Voltage (144, 2 bytes), ID 2: Present Temperature (146, 1 byte)
    bus = _bus((1, 2))
    bus.servo(1).put(dt.PRESENT_INPUT_VOLTAGE, 119)
    bus.servo(2).put(dt.PRESENT_TEMPERATURE, 36)
    got = bus.handle_bytes(H("FF FF FD 00 FE 0D 00 92 01 90 00 02 00 02 92 00 01 00 1A 05"))
    first = H("FF FF FD 00 01 06 00 55 00 77 00 C3 69")
    assert got[:len(first)] == first
    second = dp.decode(got[len(first):])
    assert (second.dxl_id, second.error, second.data, second.crc_ok) == (2, 0, bytes([36]), True)


def test_bulk_write_sets_different_registers_per_servo():
    bus = _bus((1, 2))
    params = bytes([1, 65, 0, 1, 0, 1]) + bytes([2, 116, 0, 4, 0]) + dp.u32(300)
    assert bus.handle_bytes(dp.encode(dp.BROADCAST_ID, dp.INST_BULK_WRITE, params)) == b""
    assert bus.servo(1).get(dt.LED) == 1
    assert bus.servo(2).get(dt.GOAL_POSITION) == 300


def test_reboot_example_clears_hardware_error():
    bus = _bus((1,))
    bus.servo(1).set_hardware_error(1 << 5)
    alert = dp.decode(bus.handle_bytes(dp.encode(1, dp.INST_PING)))
    assert alert.error & dp.ERR_ALERT
    assert bus.handle_bytes(H("FF FF FD 00 01 03 00 08 2F 4E")) == H("FF FF FD 00 01 04 00 55 00 A1 0C")
    assert bus.servo(1).hardware_error == 0


def test_reg_write_waits_for_action():
    bus = _bus((1, 2))
    for i in (1, 2):
        bus.handle_bytes(dp.encode(i, dp.INST_REG_WRITE, bytes([116, 0]) + dp.u32(1000 + i)))
    assert bus.servo(1).get(dt.GOAL_POSITION) == 0
    assert bus.servo(1).get(dt.REGISTERED_INSTRUCTION) == 1
    assert bus.handle_bytes(dp.encode(dp.BROADCAST_ID, dp.INST_ACTION)) == b""
    assert [bus.servo(i).get(dt.GOAL_POSITION) for i in (1, 2)] == [1001, 1002]


def test_eeprom_locked_while_torque_on_and_limits_checked():
    bus = _bus((1,))
    s = bus.servo(1)
    write = lambda addr, data: dp.decode(bus.handle_bytes(dp.encode(1, dp.INST_WRITE, bytes([addr, 0]) + data))).error  # noqa: E731
    assert write(dt.OPERATING_MODE.address, b"\x01") == 0
    assert write(dt.TORQUE_ENABLE.address, b"\x01") == 0
    assert write(dt.OPERATING_MODE.address, b"\x03") == dp.ERR_ACCESS
    assert s.get(dt.OPERATING_MODE) == 1
    assert write(dt.GOAL_VELOCITY.address, dp.u32(s.get(dt.VELOCITY_LIMIT) + 1)) == dp.ERR_DATA_LIMIT
    assert write(dt.PRESENT_POSITION.address, dp.u32(5)) == dp.ERR_ACCESS
    assert write(dt.BUS_WATCHDOG.address, b"\x80") == dp.ERR_DATA_RANGE


def test_corrupted_instruction_is_answered_with_crc_error():
    pkt = bytearray(dp.encode(1, dp.INST_PING))
    pkt[-1] ^= 0xFF
    assert dp.decode(_bus((1,)).handle_bytes(bytes(pkt))).error == dp.ERR_CRC


def test_fault_injection_silence_and_corrupt_crc():
    bus = _bus((1, 2))
    bus.servo(1).no_answer = True
    bus.servo(2).corrupt = True
    assert bus.handle_bytes(dp.encode(1, dp.INST_PING)) == b""
    assert not dp.decode(bus.handle_bytes(dp.encode(2, dp.INST_PING))).crc_ok


def test_return_delay_and_garbage_before_header():
    bus = _bus((1,))
    # line noise before the header is skipped by the parser
    assert dp.decode(bus.handle_bytes(b"\x00\xff\x13" + dp.encode(1, dp.INST_PING))).dxl_id == 1
    assert bus.servo(1).get(dt.RETURN_DELAY_TIME) == 250  # factory 500 us


def test_bus_watchdog_stops_wheel_and_locks_goals():
    bus = _bus((1,))
    s = bus.servo(1)
    s.put(dt.OPERATING_MODE, 1)
    s.put(dt.TORQUE_ENABLE, 1)
    s.put(dt.GOAL_VELOCITY, 100)
    s.put(dt.BUS_WATCHDOG, 5)  # 100 ms
    t0 = s.last_comm
    assert not s.check_watchdog(t0 + 0.099)
    for _ in range(10):
        s.step(0.01)
    assert s.get(dt.PRESENT_VELOCITY) == 100
    assert s.check_watchdog(t0 + 0.101)
    assert s.get(dt.BUS_WATCHDOG) == -1
    s.step(0.01)
    assert s.get(dt.PRESENT_VELOCITY) == 0
    assert s.write(dt.GOAL_VELOCITY.address, dp.u32(50)) == dp.ERR_RESULT_FAIL
    assert s.write(dt.BUS_WATCHDOG.address, b"\x00") == 0
    assert s.write(dt.GOAL_VELOCITY.address, dp.u32(50)) == 0


def test_velocity_mode_integrates_position_with_profile_acceleration():
    s = de.EmulatedServo(1, de.MODELS["XM430-W350"])
    s.put(dt.OPERATING_MODE, 1)
    s.put(dt.TORQUE_ENABLE, 1)
    s.put(dt.PROFILE_ACCELERATION, 100)  # 21457.7 rev/min^2 -> ~1562 units/s^2
    s.put(dt.GOAL_VELOCITY, -100)
    s.step(0.01)
    assert -20 < s.get(dt.PRESENT_VELOCITY) < -10
    for _ in range(200):
        s.step(0.01)
    assert s.get(dt.PRESENT_VELOCITY) == -100
    # 100 units = 22.9 rpm; over ~2 s minus the ramp, about -0.72 rev
    pos = s.get(dt.PRESENT_POSITION)
    assert -4096 * 0.80 < pos < -4096 * 0.65
