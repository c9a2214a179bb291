"""Operator commands under floods, stalls and oversized payloads (issue 12, points 1-3).

Deterministic on the simulated clock, through the real CommandInbox and the runtime's mailbox;
one set of flood-then-estop trials goes through a zenoh session on loopback (real clock).
"""
from __future__ import annotations

import json
import socket
import threading
import time

import pytest

from runtime_helpers import PERIOD_NS, RecordingDrive, make_runtime
from test_safety import Cruise          # drives forward, calls a hook every cycle
from vbnav.control.comms.operator_commands import MAX_PAYLOAD, CommandInbox, CommandSubscriber, limits_from_config
from vbnav.control.config import Config
from vbnav.control.controllers.manual import TeleopController
from vbnav.control.runtime.mailbox import MAX_SENDERS, CommandMailbox, OperatorCommand
from vbnav.control.runtime.runtime import Runtime
from vbnav.drivers.clock import SimClock

T0 = 1_000_000_000            # SimClock start
TIMEOUT_NS = 500_000_000      # safety.command_timeout_s
FLOOD = 10_000


def teleop(seq, stamp_ns, v=0.3, session="s1", sender="op"):
    return json.dumps({"linear": v, "angular": 0.0, "seq": seq, "stamp_ns": stamp_ns, "session": session,
                       "sender": sender})


def sim_teleop_runtime(cfg=None, clock=None):
    cfg = cfg or Config.model_validate({"safety": {"command_timeout_s": TIMEOUT_NS * 1e-9}})
    clock = clock or SimClock()
    drive = RecordingDrive(clock)
    rt = Runtime(cfg, drive, TeleopController(cfg.safety.command_timeout_s), clock)
    rejected = []
    inbox = CommandInbox(limits_from_config(cfg), deliver=rt.submit, now_ns=clock.now_ns,
                         on_reject=lambda k, r, p, v: rejected.append((k, r)))
    return rt, drive, clock, inbox, rejected


# ---- the mailbox ------------------------------------------------------------------------------

def _box():
    clock = SimClock()
    return CommandMailbox(clock.now_ns, TIMEOUT_NS), clock


def test_teleop_coalesces_per_sender_and_arrival_order_is_kept_across_lanes():
    box, clock = _box()
    assert box.post(OperatorCommand("teleop", (0.1, 0), "A", seq=1)) is None
    assert box.post(OperatorCommand("teleop", (0.2, 0), "B", seq=1)) is None
    assert box.post(OperatorCommand("estop", (), "C")) is None
    assert box.post(OperatorCommand("teleop", (0.3, 0), "A", seq=2)) is None    # replaces A's first
    applied, refused = box.drain(clock.now_ns())
    assert not refused and box.coalesced == 1
    assert [(c.kind, c.source, c.args[:1]) for c in applied] == [("teleop", "B", (0.2,)), ("estop", "C", ()),
                                                                 ("teleop", "A", (0.3,))]
    assert box.drain(clock.now_ns()) == ([], [])


def test_a_teleop_that_arrived_before_an_estop_is_applied_before_it():
    box, clock = _box()
    box.post(OperatorCommand("teleop", (0.3, 0), "A", seq=1))
    box.post(OperatorCommand("estop", (), "A"))
    applied, _ = box.drain(clock.now_ns())
    assert [c.kind for c in applied] == ["teleop", "estop"]


def test_out_of_order_seq_is_refused_and_a_new_session_or_silence_starts_afresh():
    box, clock = _box()
    assert box.post(OperatorCommand("teleop", (0.1, 0), "A", seq=5, session="x")) is None
    reason = box.post(OperatorCommand("teleop", (0.2, 0), "A", seq=3, session="x"))
    assert reason.startswith("out of order") and "seq 3 after 5" in reason
    assert box.post(OperatorCommand("teleop", (0.2, 0), "A", seq=5, session="x")).startswith("out of order")
    applied, _ = box.drain(clock.now_ns())
    assert [c.args[0] for c in applied] == [0.1]
    assert box.post(OperatorCommand("teleop", (0.4, 0), "A", seq=0, session="y")) is None   # restarted sender
    clock.advance(TIMEOUT_NS + 1)
    assert box.post(OperatorCommand("teleop", (0.5, 0), "A", seq=1, session="x")) is None   # silent > timeout


def test_refused_teleop_is_answered_each_time_it_carries_an_ack_and_summarised_otherwise():
    rt, drive, clock, inbox, rejected = sim_teleop_runtime()
    excerpts = []
    inbox._on_reject = lambda k, r, p, v: (rejected.append((k, r)), excerpts.append(p))
    assert inbox.submit("teleop", teleop(5, clock.now_ns())) is not None
    for seq in (3, 4):                                      # out of order, no ack: one report a second
        assert inbox.submit("teleop", teleop(seq, clock.now_ns())) is None
    for n, seq in enumerate((1, 2)):                        # out of order, with vbnav send's ack: every one
        assert inbox.submit("teleop", json.dumps({"ack": f"id{n}", **json.loads(teleop(seq, clock.now_ns()))})) is None
    assert [r.split()[0] for _, r in rejected] == ["out", "out", "out"]
    assert '"ack": "id0"' in excerpts[1] and '"ack": "id1"' in excerpts[2]


def test_stale_stamp_is_refused_by_the_senders_clock_whatever_its_offset():
    box, clock = _box()
    offset = -123_456_789_000      # the sender's clock reads 123 s less than the robot's
    assert box.post(OperatorCommand("teleop", (0.1, 0), "A", seq=1, stamp_ns=clock.now_ns() + offset)) is None
    clock.advance(650_000_000)
    # sent 0.6 s ago by the sender's clock (after seq 1), arriving only now (a transport backlog)
    sent = clock.now_ns() - 600_000_000 + offset
    reason = box.post(OperatorCommand("teleop", (0.2, 0), "A", seq=2, stamp_ns=sent))
    assert reason.startswith("stale") and "600 ms" in reason
    fresh = box.post(OperatorCommand("teleop", (0.3, 0), "A", seq=3, stamp_ns=clock.now_ns() - 20_000_000 + offset))
    assert fresh is None
    applied, _ = box.drain(clock.now_ns())
    assert [c.args[0] for c in applied] == [0.3]
    # its send time on the robot's clock (the offset estimate may rise by 100 ppm of the 650 ms between messages)
    assert applied[0].sent_ns == pytest.approx(clock.now_ns() - 20_000_000, abs=70_000)


@pytest.mark.parametrize("bogus", [10 ** 300, 10 ** 400, 2 ** 63, "far"])
def test_a_stamp_that_cannot_be_the_senders_clock_is_refused_and_does_not_move_its_clock(bogus):
    """One teleop stamped 10**300 (or 2**63, past an int64; or far ahead of what the sender's clock read a
    moment ago) was taken as fresh (sent 'now') and drove the robot, and it set the sender's clock offset so far
    back that every later teleop of that sender was stale, until its session was forgotten. Such a stamp is now
    refused, saying why, and the sender's clock is tracked as before it: its next teleop is taken."""
    box, clock = _box()
    offset = -123_456_789_000      # the sender's clock reads 123 s less than the robot's
    assert box.post(OperatorCommand("teleop", (0.1, 0), "A", seq=1, stamp_ns=clock.now_ns() + offset)) is None
    box.drain(clock.now_ns())
    clock.advance(50_000_000)
    stamp = bogus if bogus != "far" else clock.now_ns() + offset + TIMEOUT_NS + 1_000_000   # 501 ms ahead
    reason = box.post(OperatorCommand("teleop", (0.9, 0), "A", seq=2, stamp_ns=stamp))
    assert reason is not None and "cannot be a reading of A's clock" in reason, reason
    assert ("int64" in reason) if bogus != "far" else ("501 ms ahead" in reason and "500 ms" in reason), reason
    assert box.drain(clock.now_ns()) == ([], [])
    clock.advance(50_000_000)
    assert box.post(OperatorCommand("teleop", (0.3, 0), "A", seq=3, stamp_ns=clock.now_ns() - 5_000_000 + offset)) \
        is None
    applied, refused = box.drain(clock.now_ns())
    assert [c.args[0] for c in applied] == [0.3] and not refused
    assert applied[0].sent_ns == pytest.approx(clock.now_ns() - 5_000_000, abs=50_000)


def test_a_peer_posing_as_another_sender_cannot_make_its_teleop_stale_with_a_far_stamp():
    """sender and session are what the message says (every authorised peer shares the signing secret): a
    peer that copies another operator's sender and session and sends one far-future stamp made all of that
    operator's teleop stale. The stamp is refused and the operator's clock is tracked as before."""
    rt, drive, clock, inbox, rejected = sim_teleop_runtime()
    assert inbox.submit("teleop", teleop(1, clock.now_ns(), session="op-1")) is not None
    assert inbox.submit("teleop", teleop(10 ** 6, 10 ** 18, session="op-1")) is None   # the peer's, refused
    clock.advance(20_000_000)
    assert inbox.submit("teleop", teleop(2, clock.now_ns(), session="op-1")) is not None
    applied, refused = rt.mailbox.drain(clock.now_ns())
    assert [c.seq for c in applied] == [2] and not refused, (applied, refused, rejected)
    assert any("cannot be a reading of zenoh:op's clock" in r for _, r in rejected), rejected


def test_a_far_future_stamp_on_a_senders_first_teleop_does_not_make_its_later_teleop_stale_for_good():
    """The first teleop of a (sender, session) set its clock offset alone: one stamped an hour ahead (a
    clock glitch, or a peer copying the operator's sender and session) made every later teleop of that
    session 'stale: sent 3600000 ms ago', untrue, for good. A later message with a higher seq but a lower
    stamp cannot come from the same monotonic clock (vbnav send and teleop number and stamp each message in
    order): the offset estimate starts afresh from it, as for a new session; without seq nothing tells
    them apart and such a sender needs a new session."""
    box, clock = _box()
    hour = 3_600_000_000_000
    assert box.post(OperatorCommand("teleop", (0.1, 0), "A", seq=1, session="x", stamp_ns=clock.now_ns() + hour)) \
        is None
    box.drain(clock.now_ns())
    for seq in (2, 3, 4):
        clock.advance(50_000_000)
        assert box.post(OperatorCommand("teleop", (0.2, 0), "A", seq=seq, session="x", stamp_ns=clock.now_ns())) \
            is None, seq
        applied, refused = box.drain(clock.now_ns())
        assert [c.seq for c in applied] == [seq] and not refused, (applied, refused)
        assert applied[0].sent_ns == clock.now_ns()
    # the lower stamp of a message without a higher seq (reordered on the way) does not restart the estimate,
    # and a backlog after the restart is refused: still aged by the sender's clock
    clock.advance(10_000_000)
    assert box.post(OperatorCommand("teleop", (0.2, 0), "A", seq=3, session="x", stamp_ns=0)).startswith("out of order")
    clock.advance(640_000_000)
    reason = box.post(OperatorCommand("teleop", (0.2, 0), "A", seq=5, session="x", stamp_ns=clock.now_ns() - 600_000_000))
    assert reason is not None and reason.startswith("stale: sent 600 ms ago"), reason


def test_a_huge_first_seq_does_not_make_its_senders_later_teleop_out_of_order_for_good():
    """Found by an audit: a sender's first teleop numbered 10**12 (a bug, a peer copying its sender and session)
    made every later teleop of that session 'out of order' while it kept sending. A message numbered lower but
    stamped later than the last one taken cannot be a reordered one (one monotonic clock numbers and stamps in
    order): its numbering restarted, and it is taken. Reordered messages (lower seq, lower stamp) are still
    refused."""
    box, clock = _box()
    assert box.post(OperatorCommand("teleop", (0.1, 0), "A", seq=10 ** 12, session="x", stamp_ns=clock.now_ns())) \
        is None
    box.drain(clock.now_ns())
    for seq in (1, 2, 3):
        clock.advance(50_000_000)
        assert box.post(OperatorCommand("teleop", (0.2, 0), "A", seq=seq, session="x", stamp_ns=clock.now_ns())) \
            is None, seq
        applied, refused = box.drain(clock.now_ns())
        assert [c.seq for c in applied] == [seq] and not refused, (applied, refused)
    stamp = clock.now_ns()
    clock.advance(10_000_000)
    reason = box.post(OperatorCommand("teleop", (0.2, 0), "A", seq=2, session="x", stamp_ns=stamp - 1))
    assert reason is not None and reason.startswith("out of order"), reason
    assert box.post(OperatorCommand("teleop", (0.2, 0), "A", seq=3, session="x", stamp_ns=stamp)).startswith(
        "out of order")                                                     # a duplicate


def test_a_signed_teleop_stamped_ahead_of_the_shared_clock_is_refused_rather_than_locking_its_session():
    """Found by an audit: without seq, a first teleop stamped an hour ahead set its sender's clock offset and
    every later teleop of that session was stale until a new session. Signed commands come from this machine
    (command_auth.py): sender and robot read one monotonic clock, and a stamp more than FUTURE_SLACK_NS (100 ms)
    ahead of it is no reading of it: refused, saying so, and the offset is not moved. (Unsigned senders may be
    on another machine, any offset: no bound on a first stamp exists there.)"""
    box, clock = _box()
    rejected = []
    inbox = CommandInbox(limits_from_config(Config()), deliver=box.post, now_ns=clock.now_ns,
                         on_reject=lambda k, r, p, v: rejected.append(r), shared_clock=clock.now_ns)
    hour = 3_600_000_000_000
    body = {"linear": 0.1, "angular": 0.0, "sender": "op", "session": "x"}
    assert inbox.submit("teleop", json.dumps({**body, "stamp_ns": clock.now_ns() + hour})) is None
    assert len(rejected) == 1 and "ahead of this machine's monotonic clock" in rejected[0], rejected
    for _ in range(3):
        clock.advance(50_000_000)
        assert inbox.submit("teleop", json.dumps({**body, "stamp_ns": clock.now_ns() - 1_000_000})) is not None
        applied, refused = box.drain(clock.now_ns())
        assert len(applied) == 1 and not refused, (applied, refused)
    assert inbox.submit("teleop", json.dumps({**body, "stamp_ns": clock.now_ns() + 50_000_000})) is not None
    assert len(rejected) == 1


def test_a_teleop_that_waited_too_long_for_the_loop_is_refused_when_taken():
    box, clock = _box()
    box.post(OperatorCommand("teleop", (0.1, 0), "A", seq=1, stamp_ns=5))
    clock.advance(TIMEOUT_NS + PERIOD_NS)
    applied, refused = box.drain(clock.now_ns())
    assert applied == [] and refused[0][1].startswith("stale") and "when the loop took it" in refused[0][1]


def test_unstamped_teleop_is_aged_from_its_arrival():
    box, clock = _box()
    assert box.post(OperatorCommand("teleop", (0.1, 0), "A")) is None
    clock.advance(PERIOD_NS)
    applied, _ = box.drain(clock.now_ns())
    assert applied[0].sent_ns == clock.now_ns() - PERIOD_NS


def test_senders_are_bounded_and_silent_ones_are_forgotten():
    box, clock = _box()
    for i in range(MAX_SENDERS):
        assert box.post(OperatorCommand("teleop", (0.1, 0), f"s{i}", seq=1)) is None
    assert box.post(OperatorCommand("teleop", (0.1, 0), "one-too-many", seq=1)).startswith("too many teleop senders")
    box.drain(clock.now_ns())
    clock.advance(TIMEOUT_NS + 1)
    assert box.post(OperatorCommand("teleop", (0.1, 0), "one-too-many", seq=1)) is None


# ---- flood then estop ---------------------------------------------------------------------------

def _flood_then_estop_trial(trial: int) -> None:
    rt, drive, clock, inbox, _ = sim_teleop_runtime()
    # One sender session: teleop at every cycle (the robot drives once the start-up command_timeout hold has
    # released, 0.5 s), then at 0.8 s a burst of 10,000 and the estop behind them.
    estop = json.dumps({"reason": f"trial {trial}", "sender": "op", "session": "s1"})
    arrival = {}

    def operator(r, ctx, twist, wheels):
        t = ctx.now_ns - T0
        if t == 800_000_000:
            for k in range(FLOOD):
                inbox.submit("teleop", teleop(100 + k, ctx.now_ns))
            assert inbox.submit("estop", estop) is not None
            arrival["t"] = clock.now_ns()
        elif t < 800_000_000:
            inbox.submit("teleop", teleop(ctx.cycle, ctx.now_ns))

    rt.cycle_observers.append(operator)
    rt.run(1.1)
    t_a = arrival["t"]
    trips = [e for e in rt.safety.events if e.kind == "trip" and e.cause == "estop"]
    assert len(trips) == 1 and f"trial {trial}" in trips[0].message
    assert trips[0].stamp_ns <= t_a + 2 * PERIOD_NS
    assert drive.last_motion_ns() > t_a - 5 * PERIOD_NS, "the robot was not moving when the estop came"
    assert drive.stopped_since(t_a + 2 * PERIOD_NS) and drive.log[-1][3] is False
    assert inbox.accepted >= FLOOD + 1


def test_estop_behind_10000_teleops_trips_within_two_periods_in_20_of_20_trials():
    for trial in range(20):
        _flood_then_estop_trial(trial)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_estop_behind_10000_teleops_over_zenoh_loopback_trips_in_20_of_20_trials():
    """The real path: zenoh subscriber -> CommandInbox -> mailbox -> loop, on the real clock."""
    import zenoh

    from vbnav.control.comms.link import TelemetryLink
    from vbnav.control.comms.network import client_session_config, open_session
    from vbnav.drivers.clock import MonotonicClock
    port = _free_port()
    cfg = Config.model_validate({"telemetry": {"listen": [f"tcp/127.0.0.1:{port}"]},
                                 "safety": {"command_timeout_s": 0.5},
                                 # the trip is checked in cycles: a loaded test machine must not stop the run
                                 "loop": {"max_missed_streak": 10 ** 6, "stall_periods": 1e6}})
    clock = MonotonicClock()
    drive = RecordingDrive(clock)
    rt = Runtime(cfg, drive, TeleopController(0.5), clock)
    arrivals = {}                       # trial -> (arrival cycle, arrival ns)
    applied = {}                        # trial -> (applied cycle, ns)
    submit = rt.submit

    def logged_submit(cmd):             # zenoh thread: when the estop reached the runtime
        if cmd.kind == "estop":
            arrivals[cmd.args[0]] = (rt.cycle, clock.now_ns())
        return submit(cmd)

    rt.submit = logged_submit
    rt.command_listeners.append(lambda r, cmd, outcome, now: applied.__setitem__(cmd.args[0], (r.cycle, now))
                                if cmd.kind == "estop" else None)
    link = TelemetryLink.attach(rt, cfg)
    runner = threading.Thread(target=rt.run, args=(120.0,), daemon=True)
    runner.start()
    op = open_session(client_session_config([f"tcp/127.0.0.1:{port}"]))
    try:
        pub = {k: op.declare_publisher(f"vbnav/sim/cmd/{k}", congestion_control=zenoh.CongestionControl.BLOCK)
               for k in ("teleop", "estop", "resume")}
        deadline = time.monotonic() + 10
        while not pub["estop"].matching_status and time.monotonic() < deadline:
            time.sleep(0.02)
        seq = 0
        for trial in range(20):
            for _ in range(FLOOD):
                seq += 1
                pub["teleop"].put(teleop(seq, time.monotonic_ns()))
            pub["estop"].put(json.dumps({"reason": f"trial {trial}", "sender": "op", "session": "s1"}))
            end = time.monotonic() + 30
            while f"trial {trial}" not in applied and time.monotonic() < end:
                time.sleep(0.005)
            pub["resume"].put(json.dumps({"sender": "op", "session": "s1"}))
            end = time.monotonic() + 10
            while "estop" in rt.safety.latched and time.monotonic() < end:
                time.sleep(0.005)
    finally:
        op.close()
        rt.loop.stop()
        runner.join(20)
        link.close()
    lateness = rt.loop.timing.max_lateness_ns
    for trial in range(20):
        key = f"trial {trial}"
        assert key in applied, f"{key}: estop never applied"
        (c_a, t_a), (c_e, t_e) = arrivals[key], applied[key]
        # The cycle running at arrival may still write; the next one applies it: two periods counted in
        # cycles, and in time unless the loop itself woke late.
        assert c_e <= c_a + 2, (trial, c_a, c_e)
        assert t_e - t_a <= 2 * PERIOD_NS + lateness, (trial, (t_e - t_a) * 1e-6)
    trips = [e for e in rt.safety.events if e.kind == "trip" and e.cause == "estop"]
    assert len(trips) == 20


# ---- flood then silence --------------------------------------------------------------------------

def test_after_a_flood_the_wheels_stop_within_timeout_plus_two_periods_of_the_last_message_sent():
    """10,000 teleops sent at 10 kHz for 1 s reach the robot at half that rate: the last one arrives 1 s
    after it was sent. The sender's clock is 50 s ahead of the robot's."""
    rt, drive, clock, inbox, rejected = sim_teleop_runtime()
    offset = 50_000_000_000
    start = T0 + 200_000_000
    sent = [start + k * 100_000 for k in range(FLOOD)]          # robot-clock send times
    arrive = [start + k * 200_000 for k in range(FLOOD)]        # the backlog grows by 100 us a message
    nxt = [0]

    def transport(r, ctx, twist, wheels):
        while nxt[0] < FLOOD and arrive[nxt[0]] <= ctx.now_ns:
            k = nxt[0]
            inbox.submit("teleop", teleop(k + 1, sent[k] + offset))
            nxt[0] += 1

    rt.cycle_observers.append(transport)
    rt.run(4.0)
    last_sent = sent[-1]
    assert arrive[-1] - last_sent == pytest.approx(1e9, abs=1e5)       # it arrived 1 s after it left
    assert drive.last_motion_ns() > start                                    # the stream drove it ...
    assert drive.last_motion_ns() <= last_sent + TIMEOUT_NS + 2 * PERIOD_NS   # ... not a moment longer
    assert drive.stopped_since(last_sent + TIMEOUT_NS + 2 * PERIOD_NS)
    stale = [r for k, r in rejected if r.startswith("stale")]
    assert stale and len(stale) < 10, "stale teleops are refused, their reports rate-limited"
    assert inbox.rejected >= FLOOD // 2 - 200


# ---- estop, then resume ------------------------------------------------------------------------------

def test_after_an_estop_and_a_quick_resume_teleop_from_before_the_estop_never_moves_the_robot():
    """docs/safety.md: after a latched stop the robot needs fresh commands. A 10 Hz stream ends at 1.0 s, the
    estop arrives at 1.01 s, then a last teleop of the stream sent at 1.005 s (both taken in the same cycle),
    and resume comes at 1.2 s, well within the 0.5 s the last teleops would otherwise still drive for."""
    rt, drive, clock, inbox, rejected = sim_teleop_runtime()
    events = []
    rt.command_listeners.append(lambda r, cmd, outcome, now: events.append(("applied", cmd.kind, now)))
    rt.safety.listeners.append(lambda ev: events.append((ev.kind, ev.cause, ev.message)))
    plan = [(T0 + k * 100_000_000, "teleop", teleop(k + 1, T0 + k * 100_000_000)) for k in range(11)]
    plan += [(T0 + 1_010_000_000, "estop", "{}"),
             (T0 + 1_010_000_000, "teleop", teleop(12, T0 + 1_005_000_000)),
             (T0 + 1_200_000_000, "resume", "{}"),
             (T0 + 1_500_000_000, "teleop", teleop(1, T0 + 1_500_000_000, session="fresh"))]

    def transport(r, ctx, twist, wheels):
        while plan and plan[0][0] <= ctx.now_ns:
            _, kind, payload = plan.pop(0)
            inbox.submit(kind, payload)

    rt.cycle_observers.append(transport)
    rt.run(2.5)
    estop_at = T0 + 1_010_000_000
    moving = [t for t, l, r, p in drive.log if p and (l or r)]
    assert [t for t in moving if t < estop_at] and not [t for t in moving if estop_at + 2 * PERIOD_NS <= t <
                                                        T0 + 1_500_000_000], "old teleop drove after the resume"
    assert [t for t in moving if t > T0 + 1_500_000_000], "a fresh teleop after the resume drives"
    late = [e for e in events if e[:2] == ("rejected", "teleop")]
    assert len(late) == 1 and "before the estop" in late[0][2], events
    applied = [now for kind, what, now in events if (kind, what) == ("applied", "teleop")]
    assert not [t for t in applied if estop_at < t < T0 + 1_500_000_000], applied


# ---- stalls ------------------------------------------------------------------------------------------

def test_a_2s_stall_inside_a_cycle_trips_safety_and_zeroes_the_wheels_in_the_next_cycle():
    def hook(ctx):
        if ctx.now_ns == T0 + 1_000_000_000:
            rt.clock.advance(2_000_000_000)            # the process froze for 2 s in this cycle

    def operator(r, ctx, twist, wheels):
        if ctx.now_ns == T0 + 4_000_000_000:
            r.submit(OperatorCommand("resume", (), "op"))

    rt, drive, clock = make_runtime(Cruise(hook), camera=False)
    rt.cycle_observers.append(operator)
    result = rt.run(duration_s=5)
    assert result.reason == "duration"                  # not fatal
    trips = [e for e in result.events if e.kind == "trip" and e.cause == "stall"]
    assert len(trips) == 1
    t_stall = trips[0].stamp_ns
    assert t_stall == T0 + 3_010_000_000 and "stalled 2000 ms" in trips[0].message
    assert drive.stopped_since(t_stall) is False         # it drives again after the resume ...
    stopped = [(l, p) for t, l, r, p in drive.log if t_stall <= t < T0 + 4_000_000_000]
    assert stopped and all(p is False or l == 0 for l, p in stopped)   # ... and not before it
    assert any(e.kind == "reset" and e.cause == "stall" for e in result.events)


def test_a_resume_that_arrived_during_a_stall_does_not_clear_it():
    """A resume that arrived while the loop was frozen (sent before anyone could know of the stall) was taken
    in the cycle the stall tripped, after the trip: the stall latch was cleared the moment it was set and the
    robot drove on. It is refused, saying why; a resume after the stall clears it."""
    def hook(ctx):
        if ctx.now_ns == T0 + 1_000_000_000:
            rt.clock.advance(2_000_000_000)            # the process froze for 2 s in this cycle ...
            rt.submit(OperatorCommand("resume", (), "op", ack="early"))   # ... and a resume came meanwhile

    def operator(r, ctx, twist, wheels):
        if ctx.now_ns == T0 + 4_000_000_000:
            r.submit(OperatorCommand("resume", (), "op", ack="late"))

    rt, drive, clock = make_runtime(Cruise(hook), camera=False)
    rt.cycle_observers.append(operator)
    applied = []
    rt.command_listeners.append(lambda r, cmd, outcome, now: applied.append((cmd.ack, now)))
    result = rt.run(duration_s=5)
    t_stall = next(e for e in result.events if e.kind == "trip" and e.cause == "stall").stamp_ns
    rejected = [e.message for e in result.events if e.kind == "rejected" and e.cause == "resume"]
    assert len(rejected) == 1 and "before the stall" in rejected[0], rejected
    assert [a for a, t in applied] == ["late"]
    assert not [t for t, l, r, p in drive.log if p and l != 0 and t_stall <= t < T0 + 4_000_000_000]
    assert [t for t, l, r, p in drive.log if p and l != 0 and t > T0 + 4_000_000_000]


class FreezingClock(SimClock):
    """A simulated clock on which the process freezes once, in its sleep, for ``length_ns`` at ``at_ns``."""

    def __init__(self, at_ns, length_ns):
        super().__init__()
        self.at_ns, self.length_ns = at_ns, length_ns

    def sleep_until(self, deadline_ns):
        super().sleep_until(deadline_ns)
        if self.at_ns is not None and self._now >= self.at_ns:
            self._now += self.length_ns
            self.at_ns = None


@pytest.mark.parametrize("stall_ns", [2_000_000_000, 100_000_000])
def test_after_a_stall_teleop_from_before_it_never_moves_the_robot_again(stall_ns):
    """The operator streams teleop until the stall; after it a resume alone does not move the robot
    (the 100 ms stall is shorter than the teleop timeout: the held command is forgotten, not aged out);
    a fresh teleop after the resume does."""
    clock = FreezingClock(T0 + 1_000_000_000, stall_ns)
    rt, drive, clock, inbox, rejected = sim_teleop_runtime(clock=clock)
    t_resume = T0 + 1_000_000_000 + stall_ns + 200_000_000
    t_fresh = t_resume + 300_000_000
    seq = [0]

    def operator(r, ctx, twist, wheels):
        seq[0] += 1
        if ctx.now_ns < T0 + 1_000_000_000 or ctx.now_ns >= t_fresh:
            inbox.submit("teleop", teleop(seq[0], ctx.now_ns))
        if ctx.now_ns == t_resume:
            inbox.submit("resume", json.dumps({"sender": "op"}))

    rt.cycle_observers.append(operator)
    rt.run(duration_s=(t_fresh - T0) * 1e-9 + 1.5)     # + the command_timeout hold's 0.5 s release
    trips = [e for e in rt.safety.events if e.kind == "trip" and e.cause == "stall"]
    assert len(trips) == 1 and f"stalled {stall_ns * 1e-6:.0f} ms" in trips[0].message
    t_stall = trips[0].stamp_ns
    assert t_stall == T0 + 1_000_000_000 + stall_ns
    moving = [t for t, l, r, p in drive.log if p and l != 0]
    assert [t for t in moving if t < T0 + 1_000_000_000], "the robot drove before the stall"
    assert not [t for t in moving if t_stall <= t < t_fresh], "it moved after the stall without a fresh command"
    assert [t for t in moving if t >= t_fresh + PERIOD_NS], "a fresh teleop after the resume drives it again"


def test_stall_bound_is_a_setting():
    def hook(ctx):
        if ctx.now_ns == T0 + 1_000_000_000:
            rt.clock.advance(80_000_000)                # 8 periods late

    cfg = Config.model_validate({"loop": {"stall_periods": 10}})
    rt, drive, clock = make_runtime(Cruise(hook), camera=False, cfg=cfg)
    assert rt.run(duration_s=2).reason == "duration"
    assert not [e for e in rt.safety.events if e.cause == "stall"]
    rt, drive, clock = make_runtime(Cruise(hook), camera=False)      # default 5 periods
    rt.run(duration_s=2)
    assert [e for e in rt.safety.events if e.cause == "stall" and "stalled 80 ms" in e.message]


# ---- oversized payloads ---------------------------------------------------------------------------

class _Payload:
    """A zenoh payload that must not be read: its length is known without copying it."""

    def __init__(self, n):
        self.n = n

    def __len__(self):
        return self.n

    def to_bytes(self):
        raise AssertionError("an oversized payload was copied into Python")


class _Sample:
    def __init__(self, key, payload):
        self.key_expr, self.payload = key, payload


class _Session:
    def declare_subscriber(self, key, callback):
        self.callback = callback
        return self


def test_oversized_payload_is_refused_unread_and_never_reaches_the_loop():
    box, clock = _box()
    rejected = []
    inbox = CommandInbox(limits_from_config(Config()), deliver=box.post,
                         on_reject=lambda k, r, p, v: rejected.append((k, r, p)))
    session = _Session()
    CommandSubscriber(session, "sim", inbox)
    session.callback(_Sample("vbnav/sim/cmd/teleop", _Payload(100_000_000)))
    assert rejected == [("teleop", f"payload of 100000000 bytes exceeds {MAX_PAYLOAD}; not read", "")]
    assert box.waiting == 0


def test_zenoh_drops_large_messages_and_the_subscriber_refuses_oversized_ones_on_loopback():
    import zenoh

    from vbnav.control.comms.network import RX_MESSAGE_LIMIT, client_session_config, open_session, \
        robot_session_config
    from vbnav.control.config.telemetry import TelemetryConfig
    port = _free_port()
    robot = open_session(robot_session_config(TelemetryConfig(listen=[f"tcp/127.0.0.1:{port}"]), "sim"))
    box, clock = _box()
    rejected = []
    inbox = CommandInbox(limits_from_config(Config()), deliver=box.post,
                         on_reject=lambda k, r, p, v: rejected.append((k, r)))
    sub = CommandSubscriber(robot, "sim", inbox)
    op = open_session(client_session_config([f"tcp/127.0.0.1:{port}"]))
    try:
        pub = op.declare_publisher("vbnav/sim/cmd/estop", congestion_control=zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + 10
        while not pub.matching_status and time.monotonic() < deadline:
            time.sleep(0.02)
        for n in (2_000_000, 2 * RX_MESSAGE_LIMIT, 10_000):
            pub.put(b" " * n)                         # whitespace: would parse as an empty estop if read
        pub.put(json.dumps({"reason": "after"}))
        deadline = time.monotonic() + 10
        while box.waiting < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        op.close()
        sub.close()
        robot.close()
    # the larger ones zenoh dropped; the one of 10000 bytes is not read, and stops the robot all the same
    assert rejected == []
    applied, _ = box.drain(clock.now_ns())
    assert [c.args for c in applied] == [(f"its payload was refused (payload of 10000 bytes exceeds {MAX_PAYLOAD}; "
                                          f"not read), stopped all the same",), ("after",)]


def test_vbnav_send_stamps_and_numbers_teleop(tmp_path):
    import subprocess
    import sys

    from vbnav.control.comms.network import open_session, robot_session_config
    from vbnav.control.config.telemetry import TelemetryConfig
    port = _free_port()
    robot = open_session(robot_session_config(TelemetryConfig(listen=[f"tcp/127.0.0.1:{port}"]), "sim"))
    got = []

    def on_command(sample):   # a robot's answers, so that vbnav send finds a robot and its acknowledgement
        msg = json.loads(sample.payload.to_bytes())
        got.append(msg)
        if msg.get("ack"):
            robot.put("vbnav/sim/events", json.dumps({"kind": "command", "command": "teleop", "ack": msg["ack"],
                                                      "cycle": len(got)}))

    sub = robot.declare_subscriber("vbnav/sim/cmd/**", on_command)
    recent = robot.declare_queryable("vbnav/sim/events/recent",
                                     lambda q: q.reply("vbnav/sim/events/recent", json.dumps({"events": []})))
    try:
        t0 = time.monotonic_ns()
        r = subprocess.run([sys.executable, "-m", "vbnav.control.cli", "send", "teleop", "0.1", "0", "--duration",
                            "0.5", "--rate", "10", "--connect", f"tcp/127.0.0.1:{port}"], capture_output=True,
                           text=True, timeout=60)
        assert r.returncode == 0, r.stderr
    finally:
        recent.undeclare()
        sub.undeclare()
        robot.close()
    # 5 messages of the stream, then the stop that ends it (the robot does not drive on to its timeout)
    assert [m["seq"] for m in got] == list(range(6))
    assert [m["linear"] for m in got] == [0.1] * 5 + [0.0]
    stamps = [m["stamp_ns"] for m in got]
    assert stamps == sorted(stamps) and stamps[0] > t0 and len({m["session"] for m in got}) == 1


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM", "SIGHUP"])
def test_vbnav_send_teleop_stream_cut_short_ends_with_a_stop(sig):
    """`vbnav send teleop V W --for S` ends its stream with a zero command, but one cut short (Ctrl-C, a
    SIGTERM, the terminal gone) ended without it: the robot drove on the last command until its command
    timeout. Every end of the stream now sends the stop."""
    import signal
    import subprocess
    import sys

    from vbnav.control.comms.network import open_session, robot_session_config
    from vbnav.control.config.telemetry import TelemetryConfig
    port = _free_port()
    robot = open_session(robot_session_config(TelemetryConfig(listen=[f"tcp/127.0.0.1:{port}"]), "sim"))
    got = []

    def on_command(sample):
        msg = json.loads(sample.payload.to_bytes())
        got.append(msg)
        if msg.get("ack"):
            robot.put("vbnav/sim/events", json.dumps({"kind": "command", "command": "teleop", "ack": msg["ack"],
                                                      "cycle": len(got)}))

    sub = robot.declare_subscriber("vbnav/sim/cmd/**", on_command)
    recent = robot.declare_queryable("vbnav/sim/events/recent",
                                     lambda q: q.reply("vbnav/sim/events/recent", json.dumps({"events": []})))
    try:
        # Started as a terminal starts a foreground command: SIGINT at its default (Python then installs its
        # KeyboardInterrupt handler) and no signal blocked. A child inherits an ignored SIGINT, and a suite
        # started as a background job of a shell without job control (`make test &` in a script) has SIGINT
        # ignored (POSIX): the child then ran its whole 30 s stream and the test failed for how the suite was
        # started, not for what `vbnav send` does (seen twice at 6893338 and 912eefb; reproduced with
        # `(trap '' INT; pytest ...)`).
        def as_in_a_terminal():
            signal.signal(signal.SIGINT, signal.SIG_DFL)
            signal.pthread_sigmask(signal.SIG_SETMASK, [])

        p = subprocess.Popen([sys.executable, "-m", "vbnav.control.cli", "send", "teleop", "0.1", "0", "--for", "30",
                              "--rate", "20", "--connect", f"tcp/127.0.0.1:{port}"], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, preexec_fn=as_in_a_terminal)
        for _ in range(3000):
            if len(got) >= 3 or p.poll() is not None:
                break
            time.sleep(0.01)
        assert len(got) >= 3, p.communicate(timeout=30)
        p.send_signal(getattr(signal, sig))
        p.communicate(timeout=30)
        for _ in range(200):             # the last message on its way
            if got[-1]["linear"] == 0.0:
                break
            time.sleep(0.01)
    finally:
        if p.poll() is None:
            p.kill()
        recent.undeclare()
        sub.undeclare()
        robot.close()
    assert got[-1]["linear"] == 0.0 and all(m["linear"] == 0.1 for m in got[:-1]), [m["linear"] for m in got]


def test_a_teleop_refused_when_the_loop_took_it_is_answered_with_its_ack():
    """Teleop the mailbox refuses as stale when the loop drains it was reported without the sender's ack
    (vbnav send waited for its timeout, 'no acknowledgement') and, without an ack, not summarised like
    every other refusal of a stream. It is answered as the loop's other refusals are."""
    from test_operator_modes import _Events
    from vbnav.control.comms.link import TelemetryLink
    rt, drive, clock, inbox, rejected = sim_teleop_runtime()
    sink = _Events()
    link = TelemetryLink.attach(rt, rt.cfg, recorder=sink, network=False)

    def operator(r, ctx, twist, wheels):
        k = (ctx.now_ns - T0) // PERIOD_NS
        if k == 10:      # fixes the sender's clock offset
            r.submit(OperatorCommand("teleop", (0.1, 0.0), "op", seq=1, stamp_ns=ctx.now_ns))
        if k == 60:      # fresh when it arrives (495 ms old, sent after seq 1), stale when the loop takes it
            r.submit(OperatorCommand("teleop", (0.1, 0.0), "op", seq=2, ack="A1",
                                     stamp_ns=ctx.now_ns - TIMEOUT_NS + 5_000_000))
        if 70 <= k < 80:  # a stream without ack, each stale when taken: one report, not ten
            r.submit(OperatorCommand("teleop", (0.1, 0.0), "op", seq=k, stamp_ns=ctx.now_ns - TIMEOUT_NS + 5_000_000))

    rt.cycle_observers.append(operator)
    result = rt.run(0.9)
    link.close(result)
    answers = [(e["kind"], e.get("ack"), e.get("reason", "")) for e in sink.events if e["kind"] == "command_rejected"]
    assert answers[0][:2] == ("command_rejected", "A1") and "when the loop took it" in answers[0][2], answers
    assert len(answers) == 2 and answers[1][1] is None, answers


# ---- a resume names the stop it has seen ------------------------------------------------------------

def test_a_resume_sent_before_another_operators_estop_does_not_clear_it(tmp_path):
    """Commands apply in arrival order: operator B saw A's estop (the state's safety.latched_ns) and resumed;
    operator C's estop arrived before B's resume and was cleared by it, a stop B never knew of (a second
    estop while one is latched did not even count as a new stop). A resume that names the newest stop it has
    seen (latched_ns) clears nothing that began after it, and says so; a resume naming C's estop clears it,
    and a resume without latched_ns (older senders) clears as before."""
    from vbnav.control.comms.link import TelemetryLink
    from vbnav.control.comms.operator_commands import CommandInbox, limits_from_config
    from vbnav.control.comms.recording import iter_recording

    cfg = Config.model_validate({"telemetry": {"enabled": False}})
    rt, drive, clock = make_runtime(Cruise(), camera=False, cfg=cfg)
    link = TelemetryLink.attach(rt, cfg, record=str(tmp_path / "run.mcap"))
    inbox = CommandInbox(limits_from_config(cfg), deliver=rt.submit, now_ns=clock.now_ns)
    seen = {}

    def operators(r, ctx, twist, wheels):
        t = ctx.now_ns - T0
        if t == 500_000_000:
            inbox.submit("estop", json.dumps({"sender": "A", "reason": "person ahead"}))
        elif t == 600_000_000:
            seen["B"] = r.safety.latched_ns            # what B's dashboard shows (safety.latched_ns)
        elif t == 1_000_000_000:
            inbox.submit("estop", json.dumps({"sender": "C", "reason": "cable on the floor"}))
        elif t == 1_010_000_000:                       # B's resume, sent before C's estop, arrives after it
            inbox.submit("resume", json.dumps({"sender": "B", "latched_ns": seen["B"], "ack": "b1"}))
        elif t == 1_500_000_000:
            seen["B2"] = r.safety.latched_ns
            inbox.submit("resume", json.dumps({"sender": "B", "latched_ns": seen["B2"], "ack": "b2"}))
        elif t == 2_000_000_000:
            inbox.submit("estop", json.dumps({"sender": "A"}))
        elif t == 2_500_000_000:
            inbox.submit("resume", json.dumps({"sender": "old-client"}))

    rt.cycle_observers.append(operators)
    result = rt.run(duration_s=3.0)
    link.close(result)
    estop_a, estop_c = T0 + 500_000_000 + PERIOD_NS, T0 + 1_000_000_000 + PERIOD_NS
    assert seen["B"] == estop_a and seen["B2"] == estop_c, seen
    refused = [e.message for e in result.events if e.kind == "rejected" and e.cause == "resume"]
    assert len(refused) == 1 and "estop" in refused[0] and "cable on the floor" in refused[0], refused
    assert f"latched_ns {estop_a}" in refused[0] and f"began at {estop_c}" in refused[0], refused[0]
    moving = [t for t, l, r, p in drive.log if p and (l or r)]
    assert not [t for t in moving if estop_a + PERIOD_NS < t <= T0 + 1_500_000_000], "B's resume cleared C's estop"
    assert [t for t in moving if T0 + 1_500_000_000 < t < T0 + 2_000_000_000], "B's second resume clears it"
    assert [t for t in moving if t > T0 + 2_500_000_000 + PERIOD_NS], "a resume without latched_ns clears"
    states = [json.loads(d) for t, _, _, d in iter_recording(tmp_path / "run.mcap") if t == "/vbnav/state"]
    assert {s["safety"]["latched_ns"] for s in states if s["safety"]["state"] == "estop"} == \
        {estop_a, estop_c, T0 + 2_000_000_000 + PERIOD_NS}
    assert all(s["safety"]["latched_ns"] is None for s in states if s["safety"]["state"] == "ok")


def test_vbnav_send_resume_names_the_stop_it_has_seen():
    from vbnav.control.cli import build_parser
    from vbnav.control.commands.send import build_payload

    args = build_parser().parse_args(["send", "resume", "--latched-ns", "1510000000", "--robot", "r1"])
    what, body = build_payload(args)
    assert what == "resume" and body["latched_ns"] == 1_510_000_000
    what, body = build_payload(build_parser().parse_args(["send", "resume", "--robot", "r1"]))
    assert "latched_ns" not in body


def test_an_estop_stops_the_wheels_in_its_cycle_even_when_a_resume_and_a_teleop_come_in_the_same_drain():
    """A flood from three operators: A's estop, B's resume without latched_ns (every latch), C's fresh teleop
    arrive within one loop period. The estop was answered 'applied at cycle N' while the wheels of cycle N
    were driven: B's resume cleared it in the same drain, before anyone could have seen it (the state that
    shows it goes out after the cycle), and C's teleop drove. Such a resume is refused now, as one that
    arrived before a stall was detected; a resume after the estop's cycle clears it."""
    rt, drive, clock, inbox, rejected = sim_teleop_runtime()
    events = []
    rt.command_listeners.append(lambda r, cmd, outcome, now: events.append(("applied", cmd.kind, now)))
    rt.safety.listeners.append(lambda ev: events.append((ev.kind, ev.cause, ev.message)))
    t_flood = T0 + 500_000_000
    plan = [(T0 + k * 50_000_000, "teleop", teleop(k + 1, T0 + k * 50_000_000, sender="C")) for k in range(10)]
    plan += [(t_flood, "estop", json.dumps({"sender": "A", "reason": "person ahead"})),
             (t_flood, "resume", json.dumps({"sender": "B"})),
             (t_flood, "teleop", teleop(11, t_flood, sender="C")),
             (T0 + 800_000_000, "resume", json.dumps({"sender": "B"})),
             (T0 + 800_000_000, "teleop", teleop(12, T0 + 800_000_000, sender="C"))]

    def transport(r, ctx, twist, wheels):
        while plan and plan[0][0] <= ctx.now_ns:
            _, kind, payload = plan.pop(0)
            clock.advance(1)           # each arrives a moment after the one before
            inbox.submit(kind, payload)

    rt.cycle_observers.append(transport)
    rt.run(1.2)
    (estop_cycle,) = [now for kind, what, now in events if (kind, what) == ("applied", "estop")]
    assert drive.log and drive.stopped_since(estop_cycle) is False     # it drives again after the later resume
    at_estop = [(l, r, p) for t, l, r, p in drive.log if estop_cycle <= t < estop_cycle + PERIOD_NS]
    assert at_estop and all(not p or (l == 0 and r == 0) for l, r, p in at_estop), at_estop
    refused = [m for kind, cause, m in events if (kind, cause) == ("rejected", "resume")]
    assert len(refused) == 1 and "estop" in refused[0], [e for e in events if e[0] != "applied"]
    moving = [t for t, l, r, p in drive.log if p and (l or r)]
    assert not [t for t in moving if estop_cycle <= t < T0 + 800_000_000], "the estop did not hold"
    assert [t for t in moving if t > T0 + 800_000_000], "the later resume and a fresh teleop drive"
def test_an_estop_and_a_resume_arriving_between_the_tick_and_the_drain_do_not_both_apply_in_one_cycle():
    """On the real clock commands also reach the mailbox after the cycle's tick and before its drain (the wheels'
    serial read takes milliseconds). A resume that arrived behind an estop there came after the cycle's time, so
    the rule 'a resume that arrived before the estop took effect' let it clear the estop in the cycle the estop
    was answered applied, and a fresh teleop behind both drove the wheels of that cycle. Simulated here by a read
    that takes 3 ms, during which the three commands arrive."""
    rt, drive, clock, inbox, rejected = sim_teleop_runtime()
    events = []
    rt.command_listeners.append(lambda r, cmd, outcome, now: events.append(("applied", cmd.kind, cmd.ack)))
    rt.safety.listeners.append(lambda ev: events.append((ev.kind, ev.cause, ev.message)))
    read, seq = drive.read, [0]

    def slow_read():                   # the zenoh thread posts while the loop reads the wheels
        state = read()
        t = clock.now_ns() - T0
        arrivals = [("teleop", "C")] if t % 50_000_000 == 0 and t < 800_000_000 else []
        if t == 500_000_000:
            arrivals = [("estop", json.dumps({"sender": "A", "ack": "E1"})),
                        ("resume", json.dumps({"sender": "B", "ack": "R1"})), ("teleop", "C")]
        for kind, payload in arrivals:
            clock.advance(1_000_000)
            if kind == "teleop":
                seq[0] += 1
                payload = teleop(seq[0], clock.now_ns(), sender=payload)
            inbox.submit(kind, payload)
        return state

    drive.read = slow_read
    rt.run(1.0)
    estop_cycle = T0 + 500_000_000
    assert ("applied", "estop", "E1") in events and ("applied", "resume", "R1") not in events, events
    refused = [m for kind, cause, m in events if (kind, cause) == ("rejected", "resume")]
    assert len(refused) == 1 and "estop from zenoh:A" in refused[0], refused
    assert drive.last_motion_ns() > T0, "the stream drove before the estop"
    assert drive.stopped_since(estop_cycle), "the wheels drove in the estop's cycle, or after it"
    assert "estop" in rt.safety.latched


@pytest.mark.parametrize("payload", ['{"reason": null}', '{"reason": "' + "x" * 201 + '"}', '{"reason": 5}',
                                     '{"why": "cable"}', "not json", '["estop"]', '{"ack": "not an ack!"}'])
def test_an_estop_whose_payload_is_malformed_still_stops_the_robot(payload):
    """An estop whose body failed validation ({"reason": null}, a reason of 201 characters, an unknown key,
    not JSON) was refused, and the robot drove on: a stop asked for on cmd/estop by a peer allowed to command
    is taken whatever else its body says; the trip's message names what was wrong with it."""
    rt, drive, clock, inbox, rejected = sim_teleop_runtime()
    trips = []
    rt.safety.listeners.append(lambda ev: trips.append(ev.message) if ev.kind == "trip" else None)
    t_estop = T0 + 300_000_000

    def transport(r, ctx, twist, wheels):
        if ctx.now_ns < t_estop and (ctx.now_ns - T0) % 50_000_000 == 0:
            inbox.submit("teleop", teleop((ctx.now_ns - T0) // 50_000_000 + 1, ctx.now_ns))
        if ctx.now_ns == t_estop:
            inbox.submit("estop", payload)

    rt.cycle_observers.append(transport)
    rt.run(0.6)
    assert drive.last_motion_ns() > T0
    assert drive.stopped_since(t_estop + PERIOD_NS), "the robot drove on after the estop"
    assert len(trips) == 1 and "estop" in trips[0] and "its payload" in trips[0], (trips, rejected)
    assert not rejected, rejected


def test_an_estop_taken_despite_a_malformed_payload_is_answered_with_its_ack():
    """An estop whose body failed validation stops the robot all the same, but its answer lost the sender's ack:
    a sender waiting for it (vbnav send, another tool) heard nothing and said the robot did not answer, of a stop
    that took effect. The ack, when the payload carries one, is kept."""
    rt, drive, clock, inbox, rejected = sim_teleop_runtime()
    answered = []
    rt.command_listeners.append(lambda r, cmd, outcome, now: answered.append((cmd.kind, cmd.ack)))
    inbox.submit("estop", '{"ack": "E1", "reason": 5}')
    rt.run(0.05)
    assert answered == [("estop", "E1")] and "estop" in rt.safety.latched, answered


def test_vbnav_send_estop_goes_out_when_the_robot_takes_commands_but_its_event_history_is_slow():
    """vbnav send asks the robot's event history (events/recent) whether it is there before sending: a robot
    too busy to answer that query within --wait (a flood on its network) got no estop, 'no robot named sim is
    listening', exit 3, while its command subscriber was there. An estop now goes out as soon as the robot's
    command subscriber matches, whatever the query says; the answer is waited for as before."""
    import subprocess
    import sys

    from vbnav.control.comms.network import open_session, robot_session_config
    from vbnav.control.config.telemetry import TelemetryConfig
    port = _free_port()
    robot = open_session(robot_session_config(TelemetryConfig(listen=[f"tcp/127.0.0.1:{port}"]), "sim"))
    got = []

    def on_command(sample):
        msg = json.loads(sample.payload.to_bytes())
        got.append((str(sample.key_expr), msg))
        robot.put("vbnav/sim/events", json.dumps({"kind": "command", "command": "estop", "ack": msg["ack"],
                                                  "cycle": 7}))

    sub = robot.declare_subscriber("vbnav/sim/cmd/**", on_command)     # no events/recent queryable answers
    try:
        r = subprocess.run([sys.executable, "-m", "vbnav.control.cli", "send", "estop", "--robot", "sim", "--wait",
                            "1", "--connect", f"tcp/127.0.0.1:{port}"], capture_output=True, text=True, timeout=60)
    finally:
        sub.undeclare()
        robot.close()
    assert [k for k, _ in got] == ["vbnav/sim/cmd/estop"], (got, r.stderr)
    assert r.returncode == 0 and "estop applied by robot sim at cycle 7" in r.stdout, (r.stdout, r.stderr)


@pytest.mark.parametrize("reason", ["x" * 300, "door\nopen", "bell\x07"])
def test_vbnav_send_estop_is_sent_whatever_its_reason(reason, capsys):
    """`vbnav send estop --reason TEXT` checked the reason with the robot's model and refused it locally, exit 2,
    no estop sent, for a reason over 200 characters or with a line break (a note pasted in an emergency).
    The estop is sent; the reason is cut to 200 characters and its control characters escaped, and vbnav send
    says so."""
    from vbnav.control.cli import build_parser
    from vbnav.control.commands.send import build_payload
    from vbnav.control.comms.operator_commands import TeleopLimits, parse_command

    what, body = build_payload(build_parser().parse_args(["send", "estop", "--reason", reason, "--robot", "r1"]))
    assert what == "estop" and len(body["reason"]) <= 200 and body["reason"].isprintable(), body
    parse_command("estop", json.dumps(body), TeleopLimits(1.0, 1.0))     # the robot takes it as it is
    assert "--reason" in capsys.readouterr().err


def test_a_resume_naming_a_latched_ns_ahead_of_the_robots_clock_clears_nothing():
    """Found by an audit: a resume naming latched_ns T clears only the stops that began up to T, so one naming a
    T ahead of the robot's clock (another robot's state: each robot's monotonic clock counts from its own boot,
    or a sender's bug) cleared every latched stop, though the robot never showed such a T. Refused now, saying
    why; the estop holds."""
    rt, drive, clock, inbox, rejected = sim_teleop_runtime()
    t_estop, t_resume = T0 + 200_000_000, T0 + 400_000_000

    def transport(r, ctx, twist, wheels):
        if ctx.now_ns == t_estop:
            inbox.submit("estop", json.dumps({"sender": "A"}))
        if ctx.now_ns == t_resume:
            inbox.submit("resume", json.dumps({"sender": "B", "latched_ns": ctx.now_ns + 3_600_000_000_000}))

    rt.cycle_observers.append(transport)
    rt.run(0.6)
    assert "estop" in rt.safety.latched, "a resume naming a latched_ns the robot never showed cleared the estop"
    refused = [e.message for e in rt.safety.events if (e.kind, e.cause) == ("rejected", "resume")]
    assert len(refused) == 1 and "ahead of this robot's clock" in refused[0], refused


def test_a_mode_already_running_is_answered_as_such_not_as_a_switch(capsys):
    """'mode idle' to a run already idle (or 'mode repeat --route hall' to the run repeating hall) was answered
    'command' without a note, and vbnav send printed 'mode applied by robot at cycle N', as for a switch done (in an
    operator run the same repeat command restarts the route); only the mode_unchanged event, which vbnav send does
    not read, said nothing changed."""
    import argparse

    from test_operator_modes import _Events
    from vbnav.control.commands.send import _report
    from vbnav.control.comms.link import TelemetryLink
    from vbnav.control.controllers.manual import IdleController

    cfg = Config.model_validate({"telemetry": {"enabled": False}})
    rt, drive, clock = make_runtime(IdleController(), camera=False, cfg=cfg)
    sink = _Events()
    link = TelemetryLink.attach(rt, cfg, recorder=sink, network=False)
    rt.submit(OperatorCommand("mode", ("idle",), "op", ack="M1"))
    link.close(rt.run(0.05))
    (answer,) = [e for e in sink.events if e["kind"] == "command"]
    assert answer["ack"] == "M1" and "already running: nothing changed" in answer.get("note", ""), answer
    _report(argparse.Namespace(wait=1.0, user=None, tls_cert=None), "sim", "mode", answer, 1)
    assert "mode idle was already running: nothing changed" in capsys.readouterr().out


def test_vbnav_send_teleop_stream_refused_after_its_first_answer_ends_and_says_so(monkeypatch, capsys):
    """send teleop V W --for S took the robot's answer to its first message for the whole stream: the later
    messages carried no ack, and the robot summarises refusals of a stream without one, so an estop latched a
    moment later refused the other 59 unheard and vbnav send printed 'teleop applied ... (60 messages sent)', exit
    0. One message a second now asks again; its refusal ends the stream, with its stop, and exit 1. On a fake
    clock: no sleeping."""
    from test_telemetry_units import _Robot
    from vbnav.control import cli
    from vbnav.control.commands import send

    class EstoppedAfterTheFirst(_Robot):
        """Applies the first message, then (another operator's estop) refuses every teleop."""

        def answer(self, msg):
            if len(self.sent) == 1:
                return super().answer(msg)
            return {"ack": msg["ack"], "kind": "command_rejected", "reason": "stopped by estop (latched)"}

    class FakeTime:
        now = 0.0

        def monotonic(self):
            return self.now

        def sleep(self, dt):
            self.now += dt

    robot = EstoppedAfterTheFirst()
    monkeypatch.setattr(send, "open_client", lambda args: robot)
    monkeypatch.setattr(send, "time", FakeTime())
    assert cli.main(["send", "teleop", "0.2", "0", "--for", "3", "--rate", "20", "--robot", "sim"]) == send.REFUSED
    asked = [m for m in robot.sent if "ack" in m]
    assert len(asked) == 2 and asked[0]["ack"] != asked[1]["ack"], asked     # the first, then one a second later
    assert len(robot.sent) == 22 and (robot.sent[-1]["linear"], robot.sent[-1]["angular"]) == (0.0, 0.0)
    captured = capsys.readouterr()
    assert "applied teleop at cycle 7, then refused a later message of the stream: stopped by estop" in captured.err
    assert "teleop applied" not in captured.out, captured.out
