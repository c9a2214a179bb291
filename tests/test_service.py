"""vbnav as a systemd service (issue 15, point 3): sd_notify from the loop's heartbeat, the unit and the udev rules.

The notify tests bind an AF_UNIX datagram socket where systemd's would be and run the real runtime with
``$NOTIFY_SOCKET`` set. The unit is installed into a temporary root and checked by ``systemd-analyze verify``;
its ExecStart is the ``vbnav`` console script beside this interpreter (the venv's), which must exist for verify.
The udev rules are checked by ``udevadm verify`` where it exists (systemd >= 254) and always by a parser of
udev's rule syntax (udev(7)).
"""
from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml

from runtime_helpers import RecordingDrive, TickCamera
from vbnav.control import cli, service
from vbnav.control.commands import service as service_cmd
from vbnav.control.config import CONFIG_DIR, Config, load_config
from vbnav.control.controllers.manual import IdleController
from vbnav.control.runtime.pipeline import VisionPipeline
from vbnav.control.runtime.runtime import Runtime
from vbnav.control.runtime.systemd_notify import SystemdNotifier, socket_address, watchdog_ns
from vbnav.drivers.clock import MonotonicClock, SimClock
from vbnav.drivers.discovery import usb_identity

WATCHDOG_USEC = 40_000          # 40 ms: a ping at most every 10 ms


def _bind(address: str) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(socket_address(address))
    return s


def _drain(sock: socket.socket) -> list[str]:
    out = []
    sock.setblocking(False)
    while True:
        try:
            out.append(sock.recv(4096).decode())
        except BlockingIOError:
            return out


# ---- sd_notify ---------------------------------------------------------------------------------------

def test_notify_socket_addresses_and_the_watchdog_environment():
    assert socket_address("@vbnav/notify") == "\0vbnav/notify"
    assert socket_address("/run/systemd/notify") == "/run/systemd/notify"
    assert watchdog_ns({"WATCHDOG_USEC": "5000000"}, 42) == 5_000_000_000
    assert watchdog_ns({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": "42"}, 42) == 5_000_000_000
    assert watchdog_ns({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": "43"}, 42) is None    # another process's
    assert watchdog_ns({}, 42) is None and watchdog_ns({"WATCHDOG_USEC": "0"}, 42) is None
    assert SystemdNotifier.from_environ({}) is None                                       # not under systemd
    assert SystemdNotifier.from_environ({"NOTIFY_SOCKET": "relative"}) is None
    n = SystemdNotifier.from_environ({"NOTIFY_SOCKET": "@x"})
    assert n is not None and n.ping_interval_ns is None                                   # no WatchdogSec


def test_pings_are_throttled_and_a_missing_socket_is_counted_not_raised(tmp_path):
    path = str(tmp_path / "notify")
    sock = _bind(path)
    t = [0]
    n = SystemdNotifier(path, watchdog_period_ns=400, now_ns=lambda: t[0])
    assert n.ping_interval_ns == 100
    for t[0] in range(0, 1000, 10):          # 100 cycles, 10 ns apart: a ping every 100 ns
        n.beat()
    assert n.ready("up\nand running")
    got = _drain(sock)
    assert got == ["WATCHDOG=1"] * 10 + ["READY=1\nSTATUS=up and running"]
    assert n.pings == 10 and n.failures == 0
    sock.close()
    os.unlink(path)                         # systemd went away
    t[0] = 10_000
    n.beat()
    assert not n.stopping("bye")
    assert n.failures == 2 and n.pings == 10 and "notify" in n.last_error
    n.close()


class StallingDrive(RecordingDrive):
    """The simulated drive, blocking the loop inside ``read`` number ``stall_at`` until released."""

    def __init__(self, clock, stall_at: int):
        super().__init__(clock)
        self.stall_at = stall_at
        self.reads = 0
        self.stalled = threading.Event()
        self.release = threading.Event()

    def read(self):
        self.reads += 1
        if self.reads == self.stall_at:
            self.stalled.set()
            self.release.wait(10.0)
        return super().read()


def test_the_loop_pings_the_watchdog_while_it_runs_and_stops_while_it_stalls(monkeypatch):
    address = f"@vbnav-test-notify-{os.getpid()}"          # an abstract socket, as systemd may give
    sock = _bind(address)
    monkeypatch.setenv("NOTIFY_SOCKET", address)
    monkeypatch.setenv("WATCHDOG_USEC", str(WATCHDOG_USEC))
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    clock = SimClock()
    drive = StallingDrive(clock, stall_at=300)
    rt = Runtime(Config(), drive, IdleController(), clock)
    assert rt.notifier is not None and rt.notifier.ping_interval_ns == WATCHDOG_USEC * 1000 // 4
    result = []
    t0 = time.monotonic()
    loop = threading.Thread(target=lambda: result.append(rt.run(duration_s=6.0)))
    loop.start()
    try:
        assert drive.stalled.wait(10.0)
        before = _drain(sock)                  # everything the loop sent up to its stall
        sock.settimeout(10 * WATCHDOG_USEC * 1e-6 / 4)
        with pytest.raises(socket.timeout):    # ten ping intervals: the stalled loop sends nothing
            sock.recv(4096)
    finally:
        drive.release.set()
        loop.join(20.0)
    elapsed = time.monotonic() - t0
    after = _drain(sock)
    sock.close()
    assert result and result[0].reason == "duration" and result[0].cycles == 601   # 0 to 6 s at 100 Hz
    assert before[0] == "READY=1\nSTATUS=loop running at 100 Hz"
    assert before[1:] and set(before[1:]) == {"WATCHDOG=1"}
    # the first cycle after the stall pings at once (its interval is long past), the last message says why it ended
    assert after[0] == "WATCHDOG=1" and set(after[:-1]) == {"WATCHDOG=1"}
    assert after[-1] == "STOPPING=1\nSTATUS=duration: duration reached"
    # throttled: never more than one ping per interval of wall time (+ the first and the one after the stall)
    pings = before.count("WATCHDOG=1") + after.count("WATCHDOG=1")
    assert pings == rt.notifier.pings and pings <= elapsed / (WATCHDOG_USEC * 1e-6 / 4) + 2
    assert rt.notifier.failures == 0


def test_a_run_that_cannot_start_still_says_stopping(monkeypatch, tmp_path):
    path = str(tmp_path / "notify")
    sock = _bind(path)
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    monkeypatch.delenv("WATCHDOG_USEC", raising=False)

    class DeadDrive(RecordingDrive):
        def connect(self):
            from vbnav.drivers.wheels import DriveError
            raise DriveError("no answer on /dev/ttyUSB0")

    clock = SimClock()
    result = Runtime(Config(), DeadDrive(clock), IdleController(), clock).run(1.0)
    assert result.reason == "drive"
    assert _drain(sock) == ["STOPPING=1\nSTATUS=drive: start-up: no answer on /dev/ttyUSB0"]    # never READY


# ---- the loop's CPU sets, applied by the process itself ----------------------------------------------

@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs to tell CPU sets apart")
def test_process_and_loop_cpu_sets_apply_and_the_vision_thread_does_not_inherit_the_loops():
    cpus = sorted(os.sched_getaffinity(0))
    every, loop_cpu = set(cpus), {cpus[-1]}
    seen = {}

    class Cam(TickCamera):
        def read(self, timeout_s=0.0):
            seen.setdefault("vision", os.sched_getaffinity(0))
            time.sleep(0.005)
            return super().read(timeout_s)

    class Drive(RecordingDrive):
        def read(self):
            seen.setdefault("loop", os.sched_getaffinity(0))
            return super().read()

    clock = MonotonicClock()
    cfg = Config.model_validate({"loop": {"process_cpu_affinity": cpus, "cpu_affinity": sorted(loop_cpu)}})
    rt = Runtime(cfg, Drive(clock), IdleController(), clock, VisionPipeline(Cam(clock), [], clock, inline=False))
    rt.notifier = None
    result = rt.run(duration_s=0.3)
    assert result.reason == "duration", result.message
    assert not [e for e in result.events if e.cause == "scheduling"]
    assert seen["loop"] == loop_cpu and seen["vision"] == every
    assert os.sched_getaffinity(0) == every                   # undone when the run ends

    # a process CPU set reaches threads that were already running
    other = threading.Event()
    ready = threading.Event()
    box = {}

    def worker():
        ready.set()
        other.wait(5.0)
        box["cpus"] = os.sched_getaffinity(0)

    th = threading.Thread(target=worker)
    th.start()
    ready.wait(5.0)
    cfg = Config.model_validate({"loop": {"process_cpu_affinity": [cpus[0]]}})
    rt = Runtime(cfg, Drive(clock), IdleController(), clock)
    undo = rt._apply_scheduling()
    other.set()
    th.join(5.0)
    undo()
    assert box["cpus"] == {cpus[0]} and os.sched_getaffinity(0) == every


def test_a_refused_cpu_set_or_real_time_priority_is_told_as_it_happens():
    """A loop CPU set the kernel refuses (or SCHED_FIFO refused) was only appended to the run's event list: the
    console's event echo and the telemetry's events (the safety listeners) never heard of it, so a service ran
    for weeks on normal scheduling with the 'scheduling' warning of docs/service.md unsaid until its end."""
    clock = MonotonicClock()                                           # scheduling is the real clock's
    cfg = Config.model_validate({"loop": {"cpu_affinity": [4000]}})    # no such CPU: the kernel refuses it
    rt = Runtime(cfg, RecordingDrive(clock), IdleController(), clock)
    heard = []
    rt.safety.listeners.append(heard.append)
    undo = rt._apply_scheduling()
    undo()
    assert [(e.kind, e.cause) for e in heard] == [("warning", "scheduling")], heard
    assert "cpu_affinity" in heard[0].message and heard[0] in rt.safety.events


# ---- install: the unit ---------------------------------------------------------------------------------

def _robot_config(tmp_path: Path, **loop) -> Path:
    data = yaml.safe_load((CONFIG_DIR / "sentry-dynamixel.yaml").read_text())
    data.setdefault("loop", {}).update(loop)
    path = tmp_path / "my robot.yaml"          # a space: ExecStart must quote it
    path.write_text(yaml.safe_dump(data))
    return path


def _user() -> str:
    import pwd
    return pwd.getpwuid(os.getuid()).pw_name


def test_watchdog_timing_is_derived_from_the_loop_period():
    cfg = Config()
    assert service.watchdog_s(cfg.loop) == service.WATCHDOG_FLOOR_S          # 20 x 5 x 10 ms = 1 s < 5 s
    slow = Config.model_validate({"loop": {"rate_hz": 10, "stall_periods": 5}}).loop
    assert service.watchdog_s(slow) == pytest.approx(20 * 5 * 0.1)          # 10 s


def test_install_writes_a_unit_that_systemd_accepts(tmp_path, capsys):
    config = _robot_config(tmp_path, realtime_priority=40, process_cpu_affinity=[0, 1], cpu_affinity=[1])
    root = tmp_path / "root"
    code = cli.main(["service", "install", "-c", str(config), "--root", str(root), "--user", _user(),
                     "--serial", "drive=FT6Z5XDZ"])
    out = capsys.readouterr().out
    assert code == 0, out
    unit_path = root / "etc/systemd/system/vbnav.service"
    assert f"wrote {unit_path}" in out
    unit = unit_path.read_text()
    exe = Path(sys.executable).parent / "vbnav"
    assert f'ExecStart={exe} run -c "{config.resolve()}"' in unit
    for line in ("Type=notify", "NotifyAccess=main", "WatchdogSec=5", "Restart=on-failure",
                 "RestartPreventExitStatus=2", "StartLimitIntervalSec=0", "StateDirectory=vbnav", "SuccessExitStatus=130", "LimitRTPRIO=40", "CPUAffinity=0 1",
                 f"User={_user()}", "WantedBy=multi-user.target"):
        assert re.search(rf"^{re.escape(line)}$", unit, re.M), line
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        if os.environ.get("CI") == "true":
            pytest.fail("systemd-analyze is not installed (apt install systemd)")
        pytest.skip("systemd-analyze is not installed")
    done = subprocess.run([analyze, "verify", str(unit_path)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stderr.strip() == "", done.stderr
    # verify does find errors: the same unit with a mistyped key and a missing executable
    bad = tmp_path / "bad" / "vbnav.service"
    bad.parent.mkdir()
    bad.write_text(unit.replace("WatchdogSec=", "WatchdogSecs=").replace(str(exe), str(tmp_path / "nope")))
    done = subprocess.run([analyze, "verify", str(bad)], capture_output=True, text=True, timeout=60)
    assert "Unknown key 'WatchdogSecs'" in done.stderr and done.returncode != 0


def test_systemd_waits_for_the_slowest_close_down_before_it_kills():
    """TimeoutStopSec was 15 s while closing down (after the wheels stopped) may take the publisher's flush
    (10 s), the event echo (2 + 2 s) and a mode switch still on its worker (5 s): systemd killed the process
    mid-close and the recording stayed a .part. The estop latch file's last write (3 s) counts too."""
    from vbnav.control.comms.telemetry import CLOSE_WAIT_S as flush
    from vbnav.control.controllers.operator import OperatorController
    from vbnav.control.runtime.estop_latch import CLOSE_WAIT_S as latch
    from vbnav.control.service import STOP_TIMEOUT_S
    worst = flush + 4.0 + OperatorController.close_wait_s + latch
    assert STOP_TIMEOUT_S >= worst + 5.0, (STOP_TIMEOUT_S, worst)     # 5 s for the drive, camera and route


def test_install_refuses_to_overwrite_without_overwrite(tmp_path, capsys):
    config = _robot_config(tmp_path)
    root = tmp_path / "root"
    args = ["service", "install", "-c", str(config), "--root", str(root), "--user", _user()]
    assert cli.main(args) == 0
    unit = root / "etc/systemd/system/vbnav.service"
    unit.write_text("# edited by hand\n")
    capsys.readouterr()
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    assert f"{unit} exists" in err and "--overwrite" in err
    assert unit.read_text() == "# edited by hand\n"
    assert cli.main(args + ["--overwrite"]) == 0
    assert "Type=notify" in unit.read_text()
    assert not list(unit.parent.glob(".*.tmp"))            # written beside, then renamed


def test_bad_install_input_is_named(tmp_path, capsys):
    config = _robot_config(tmp_path)
    base = ["service", "install", "-c", str(config), "--root", str(tmp_path / "r"), "--user", _user()]
    assert cli.main(base + ["--serial", "wheels=123"]) == 2
    assert "--serial wheels: the configuration names no such device" in capsys.readouterr().err
    assert cli.main(base + ["--serial", 'drive=a"b']) == 2
    assert "--serial drive='a\"b'" in capsys.readouterr().err
    assert cli.main(base + ["--serial", "drive"]) == 2
    assert "expected ROLE=SERIAL" in capsys.readouterr().err
    assert cli.main(["service", "install", "-c", str(config), "--user", "no-such-user-here"]) == 2
    assert "--user no-such-user-here: no such user on this machine" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()
    many = _robot_config(tmp_path, process_cpu_affinity=[0, 4096])     # checked on the machine it runs on
    assert cli.main(["service", "install", "-c", str(many), "--user", _user()]) == 2
    assert "loop.process_cpu_affinity: CPU 4096 does not exist here" in capsys.readouterr().err
    with pytest.raises(ValueError, match="CPU numbers are >= 0"):
        Config.model_validate({"loop": {"process_cpu_affinity": [-1]}})


# ---- install: the udev rules ---------------------------------------------------------------------------

# udev(7): KEY[{attr}] OP "value", comma separated; match keys compare (== !=), the others assign (= += -= :=)
MATCH_KEYS = {"ACTION", "DEVPATH", "KERNEL", "KERNELS", "NAME", "SUBSYSTEM", "SUBSYSTEMS", "DRIVER", "DRIVERS",
              "ATTR", "ATTRS", "ENV", "TAG", "TAGS", "TEST", "PROGRAM", "RESULT", "SYMLINK"}
ASSIGN_KEYS = {"NAME", "SYMLINK", "OWNER", "GROUP", "MODE", "ATTR", "ENV", "TAG", "RUN", "OPTIONS", "LABEL",
               "GOTO", "IMPORT"}
PAIR = re.compile(r'\s*(?P<key>[A-Z_]+)(\{(?P<attr>[A-Za-z0-9_]+)\})?\s*(?P<op>==|!=|\+=|-=|:=|=)\s*'
                  r'"(?P<value>[^"\\]*)"\s*(,|$)')


def parse_udev_rules(text: str) -> list[list[tuple[str, str, str, str]]]:
    rules = []
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        pos, pairs = 0, []
        while pos < len(line):
            m = PAIR.match(line, pos)
            assert m, f"line {n}: cannot parse from {line[pos:]!r}"
            key, op = m["key"], m["op"]
            assert (key in MATCH_KEYS) if op in ("==", "!=") else (key in ASSIGN_KEYS), f"line {n}: {key}{op}"
            pairs.append((key, m["attr"] or "", op, m["value"]))
            pos = m.end()
        assert any(op in ("==", "!=") for _, _, op, _ in pairs), f"line {n}: a rule with no match"
        rules.append(pairs)
    return rules


def _fake_usb_tty(sysfs: Path, dev: Path, name: str, vendor: str, product: str, serial: str) -> Path:
    usb = sysfs / "devices/pci0000:00/0000:00:14.0/usb1/1-2"
    iface = usb / "1-2:1.0" / name
    iface.mkdir(parents=True)
    for attr, value in (("idVendor", vendor), ("idProduct", product), ("serial", serial)):
        (usb / attr).write_text(value + "\n")
    (sysfs / "class/tty" / name).mkdir(parents=True)
    (sysfs / "class/tty" / name / "device").symlink_to(iface)
    dev.mkdir(exist_ok=True)
    node = dev / name
    node.touch()
    by_id = dev / f"usb-FTDI_{serial}-if00-port0"
    by_id.symlink_to(node)
    return by_id


def test_udev_rules_name_the_configured_devices_by_serial_number(tmp_path):
    by_id = _fake_usb_tty(tmp_path / "sys", tmp_path / "dev", "ttyUSB0", "0403", "6001", "A50285BI")
    assert usb_identity(str(by_id), str(tmp_path / "sys")).serial == "A50285BI"
    assert usb_identity(str(tmp_path / "dev/ttyUSB9"), str(tmp_path / "sys")) is None
    data = yaml.safe_load((CONFIG_DIR / "sentry-dynamixel.yaml").read_text())
    data["drive"]["options"]["port"] = str(by_id)
    config = tmp_path / "robot.yaml"
    config.write_text(yaml.safe_dump(data))
    cfg = load_config(config)
    p = service.plan(cfg, "robot", sysfs=str(tmp_path / "sys"), executable="/usr/bin/vbnav", pythonpath="")
    rules = parse_udev_rules(p.rules)
    by_key = {tuple(sorted((k, a, op, v) for k, a, op, v in r)): r for r in rules}
    assert len(by_key) == len(rules) == 4
    latency = [r for r in rules if ("ATTR", "latency_timer", "=", "1") in r]
    assert sorted(dict(((k, a), v) for k, a, op, v in r)[("ATTRS", "idProduct")] for r in latency) == ["6001", "6014"]
    oak = [r for r in rules if ("ATTRS", "idVendor", "==", "03e7") in r]
    assert oak == [[("SUBSYSTEM", "", "==", "usb"), ("ATTRS", "idVendor", "==", "03e7"), ("MODE", "", "=", "0666")]]
    named = [r for r in rules if any(k == "SYMLINK" for k, *_ in r)]
    assert named == [[("SUBSYSTEM", "", "==", "tty"), ("ATTRS", "idVendor", "==", "0403"),
                      ("ATTRS", "idProduct", "==", "6001"), ("ATTRS", "serial", "==", "A50285BI"),
                      ("SYMLINK", "", "+=", "vbnav-drive"), ("MODE", "", "=", "0660"), ("OWNER", "", "=", "robot")]]
    assert any("set drive.options.port: /dev/vbnav-drive" in n for n in p.notes)
    # a camera that is not plugged in gets no name, and the note says how to give one
    assert any(n.startswith("no stable name for the camera") and "--serial camera=SERIAL" in n for n in p.notes)
    udevadm = shutil.which("udevadm")
    if udevadm and subprocess.run([udevadm, "verify", "--help"], capture_output=True).returncode == 0:
        f = tmp_path / "99-vbnav.rules"
        f.write_text(p.rules)
        done = subprocess.run([udevadm, "verify", str(f)], capture_output=True, text=True)
        assert done.returncode == 0, done.stdout + done.stderr


def test_the_rule_parser_refuses_broken_rules():
    for broken in ('SUBSYSTEM=="tty" SYMLINK+="x"',          # no comma
                   'SUBSYSTEM=="tty", MODE=="0660"',          # MODE is no match key
                   'SUBSYSTEM=="tty", ATTRS{serial}=="a"b"',  # a quote inside a value
                   'MODE="0660"'):                            # matches nothing
        with pytest.raises(AssertionError):
            parse_udev_rules(broken)


# ---- status, logs, uninstall ---------------------------------------------------------------------------

def test_status_and_logs_say_when_systemd_is_not_there(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(service_cmd, "SYSTEMD_RUN_DIR", str(tmp_path / "no-systemd"))
    for op in (["status"], ["logs", "-n", "5"]):
        assert cli.main(["service"] + op) == 3
        err = capsys.readouterr().err
        assert f"vbnav service {op[0]}: systemd is not running on this machine" in err
        assert "missing: another init runs as PID 1): vbnav.service cannot run here" in err


def test_status_logs_and_uninstall_wrap_systemctl_and_journalctl(tmp_path, monkeypatch, capsys):
    bin_dir, log = tmp_path / "bin", tmp_path / "calls"
    bin_dir.mkdir()
    for tool in ("systemctl", "journalctl", "udevadm"):
        script = bin_dir / tool
        script.write_text(f'#!/bin/sh\necho "{tool} $*" >> {log}\n')
        script.chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setattr(service_cmd, "SYSTEMD_RUN_DIR", str(tmp_path))
    assert cli.main(["service", "status"]) == 0
    assert cli.main(["service", "logs", "-f", "--since", "1 hour ago"]) == 0
    assert log.read_text().splitlines() == [
        "systemctl status --no-pager vbnav.service",
        "journalctl --no-pager -u vbnav.service -n 100 --follow --since 1 hour ago"]
    root = tmp_path / "root"
    config = _robot_config(tmp_path)
    assert cli.main(["service", "install", "-c", str(config), "--root", str(root), "--user", _user()]) == 0
    capsys.readouterr()
    assert cli.main(["service", "uninstall", "--root", str(root)]) == 0
    out = capsys.readouterr().out
    assert "removed" in out and not (root / "etc/systemd/system/vbnav.service").exists()
    assert not (root / "etc/udev/rules.d/99-vbnav.rules").exists()
    assert cli.main(["service", "uninstall", "--root", str(root)]) == 0
    assert "nothing to remove" in capsys.readouterr().out


def test_a_serial_given_twice_for_one_device_is_refused(tmp_path, capsys):
    """--serial drive=A --serial drive=B installed rules for B only, A dropped without a word."""
    config = _robot_config(tmp_path)
    argv = ["service", "install", "-c", str(config), "--root", str(tmp_path / "r"), "--user", _user(),
            "--serial", "drive=FT6Z5XDZ", "--serial", "drive=A50285BI"]
    assert cli.main(argv) == 2
    assert "--serial drive=A50285BI: drive is given twice (drive=FT6Z5XDZ before)" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


def test_an_overwrite_that_fails_part_way_keeps_both_old_files(tmp_path, capsys, monkeypatch):
    """The unit and the udev rules are one installation: the second write failing left the new unit beside
    the old rules (a unit naming devices the rules do not create). Both are written beside first, then renamed."""
    import errno
    import tempfile
    config = _robot_config(tmp_path)
    root = tmp_path / "root"
    args = ["service", "install", "-c", str(config), "--root", str(root), "--user", _user(), "--overwrite"]
    assert cli.main(args) == 0
    unit, rules = root / "etc/systemd/system/vbnav.service", root / "etc/udev/rules.d/99-vbnav.rules"
    for f in (unit, rules):
        f.write_text(f"# the {f.name} in use\n")
    real, calls = tempfile.mkstemp, []

    def second_fails(*a, **kw):
        calls.append(kw.get("prefix"))
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(*a, **kw)

    monkeypatch.setattr(tempfile, "mkstemp", second_fails)
    capsys.readouterr()
    assert cli.main(args) == 1 and len(calls) == 2
    assert "No space left on device" in capsys.readouterr().err
    assert unit.read_text() == "# the vbnav.service in use\n" and rules.read_text() == f"# the {rules.name} in use\n"
    assert not list(unit.parent.glob(".*.tmp")) and not list(rules.parent.glob(".*.tmp"))
