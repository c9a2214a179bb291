"""A robot process for the telemetry tests: the real Runtime with the simulated base and TelemetryLink.

Run as a script (the tests start it as a separate process):
    python tests/telemetry_robot.py --port P [--controller teleop|scripted|idle] [--duration S]
        [--sim-clock] [--record PATH] [--remote DICTFILE --operators NAME,.. [--loopback]] [--report PATH]
        [--name ROBOT] [--secret-file PATH] [--connect ROUTER [--router-auth USER:PASSWORD:DICT]]
        [--routes-dir DIR]

Prints "READY" once the zenoh session is up and the loop is about to start. At the end writes a JSON
report: every command the runtime received (loop time, cycle) and the drive's write log, so a test can
check how many loop periods passed between a network estop and zero wheels.
"""
from __future__ import annotations

import argparse
import json
import sys

from runtime_helpers import RecordingDrive  # same directory

from vbnav.control.config import ConfigError, parse_config
from vbnav.control.controllers.manual import IdleController, ScriptedController, TeleopController
from vbnav.control.runtime.runtime import Runtime
from vbnav.control.comms.link import TelemetryLink
from vbnav.drivers.clock import MonotonicClock, SimClock


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--controller", default="teleop", choices=["teleop", "scripted", "idle"])
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--state-rate", type=float, default=20.0)
    ap.add_argument("--sim-clock", action="store_true")
    ap.add_argument("--record", default=None)
    ap.add_argument("--remote", default=None, metavar="DICTFILE", help="listen on 0.0.0.0 with usrpwd + ACL")
    ap.add_argument("--tls", default=None, metavar="DIR", help="listen on tls/0.0.0.0 with mutual TLS + ACL "
                    "(DIR holds ca.pem, robot.pem, robot.key)")
    ap.add_argument("--operators", default="operator")
    ap.add_argument("--report", default=None)
    ap.add_argument("--listen", default=None, help="override telemetry.listen (no auth added)")
    ap.add_argument("--loopback", action="store_true", help="with --remote: listen on 127.0.0.1 (auth + ACL there)")
    ap.add_argument("--name", default="sim", help="robot.name")
    ap.add_argument("--secret-file", default=None, help="telemetry.shared_secret_file")
    ap.add_argument("--connect", default=None, help="connect to this router (trust_router: the router's access "
                    "control decides who may command)")
    ap.add_argument("--router-auth", default=None, metavar="USER:PASSWORD:DICTFILE",
                    help="with --connect: authenticate to the router with zenoh user/password")
    ap.add_argument("--routes-dir", default=None, help="controller.routes_dir (served to the network)")
    a = ap.parse_args()

    tele = {"listen": [f"tcp/127.0.0.1:{a.port}"], "state_rate_hz": a.state_rate}
    if a.remote:
        tele.update(listen=[f"tcp/0.0.0.0:{a.port}"], operators=a.operators.split(","),
                    auth={"usrpwd": {"user": "robot", "password": "robot-secret", "dictionary_file": a.remote}})
    if a.tls:
        tele.update(listen=[f"tls/0.0.0.0:{a.port}"], operators=a.operators.split(","),
                    auth={"tls": {"root_ca_certificate": f"{a.tls}/ca.pem", "listen_certificate": f"{a.tls}/robot.pem",
                                  "listen_private_key": f"{a.tls}/robot.key"}})
    if a.listen:
        tele["listen"] = [a.listen]
    if a.loopback:
        tele["listen"] = [f"tcp/127.0.0.1:{a.port}"]
    if a.secret_file:
        tele["shared_secret_file"] = a.secret_file
    if a.connect:
        tele.update(connect=[a.connect], trust_router=True)
    if a.router_auth:
        user, password, dictionary = a.router_auth.split(":", 2)
        tele["auth"] = {"usrpwd": {"user": user, "password": password, "dictionary_file": dictionary}}
    controller = {"kind": a.controller}
    if a.routes_dir:
        controller["routes_dir"] = a.routes_dir
    # This robot tests the network path on the real clock beside other processes on a 2-core machine: a
    # scheduling hiccup there must not latch a stall (stalls are tested on the simulated clock in
    # tests/test_command_path.py), nor end the run on a streak of missed deadlines (the robot would vanish
    # from the network under the clients' feet), as other real-clock test runs already ignore them.
    loop = {"rate_hz": a.rate, "stall_periods": 10 ** 6, "max_missed_streak": 10 ** 6}
    try:   # the telemetry section refuses a remote listener without authentication here
        cfg = parse_config({"loop": loop, "telemetry": tele, "robot": {"name": a.name},
                            "controller": controller,
                            "safety": {"command_timeout_s": 0.5}}, "telemetry_robot")
    except ConfigError as exc:
        print(f"configuration error: {exc}", file=sys.stderr)
        return 2
    clock = SimClock() if a.sim_clock else MonotonicClock()
    drive = RecordingDrive(clock)
    controller = {"teleop": lambda: TeleopController(cfg.safety.command_timeout_s),
                  "scripted": lambda: ScriptedController(cfg.controller.script, repeat=True),
                  "idle": IdleController}[a.controller]()
    rt = Runtime(cfg, drive, controller, clock)
    received = []
    submit = rt.submit

    def logged_submit(cmd):  # runs on the zenoh thread: note when the command reached the runtime
        received.append({"kind": cmd.kind, "args": list(cmd.args), "t_ns": clock.now_ns(), "cycle": rt.cycle})
        return submit(cmd)    # None, or the mailbox's reason for refusing it

    rt.submit = logged_submit
    # (loop cycle, left, right, powered) of every write and disable, to count periods in cycles (a drive
    # accepts writes only while enabled: after a stop, the disables are what the loop tells it)
    cycle_log = []
    write, disable = drive.write, drive.disable

    def logged_write(left, right):
        write(left, right)
        cycle_log.append((rt.cycle, left, right, drive.physics.powered))

    def logged_disable():
        disable()
        cycle_log.append((rt.cycle, 0.0, 0.0, drive.physics.powered))

    drive.write, drive.disable = logged_write, logged_disable
    try:
        link = TelemetryLink.attach(rt, cfg, record=a.record)
    except ConfigError as exc:
        print(f"configuration error: {exc}", file=sys.stderr)
        return 2
    print("READY", flush=True)
    result = None
    try:
        result = rt.run(a.duration)
    finally:
        link.close(result)
    if a.report:
        with open(a.report, "w") as f:
            json.dump({"received": received, "period_ns": rt.loop.period_ns, "reason": result.reason,
                       "drive_log": drive.log, "cycle_log": cycle_log, "published": link.publisher.published,
                       "dropped": link.publisher.dropped,
                       "overruns": rt.loop.timing.overruns,
                       "max_lateness_ms": rt.loop.timing.max_lateness_ns * 1e-6}, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
