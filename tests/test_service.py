"""vbnav service: the systemd unit and udev rules it installs, and the watchdog the control loop feeds."""
import os
import shutil
import socket
import subprocess
import sys
import threading

import pytest

from vbnav.control.cli import main

VBNAV = [sys.executable, "-m", "vbnav.control.cli"]


def _install(tmp_path, *extra, config="configs/sentry-dynamixel.yaml"):
    return main(["service", "install", "-c", config, "--root", str(tmp_path), *extra])


def test_install_writes_a_unit_that_systemd_analyze_accepts_and_udev_rules(tmp_path, capsys):
    cfg = tmp_path / "robot.yaml"
    text = open("configs/sentry-dynamixel.yaml").read()
    cfg.write_text(text.replace("  rate_hz: 100\n", "  rate_hz: 100\n  cpu_affinity: [1]\n", 1))
    assert "cpu_affinity: [1]" in cfg.read_text()
    assert _install(tmp_path / "root", "--device", "u2d2=FT6Z5XYZ", config=str(cfg)) == 0
    unit = tmp_path / "root/etc/systemd/system/vbnav-sentry-dxl.service"
    body = unit.read_text()
    for line in ("Type=notify", "WatchdogSec=5", "Restart=on-failure", "RestartPreventExitStatus=2",
                 "CPUAffinity=1", "LimitRTPRIO=", f"-m vbnav.control.cli run -c {cfg}"):
        assert line in body, line
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze not installed")
    r = subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60)
    complaints = [ln for ln in (r.stdout + r.stderr).splitlines() if unit.name in ln]
    assert r.returncode == 0 and not complaints, r.stdout + r.stderr
    rules = (tmp_path / "root/etc/udev/rules.d/70-vbnav.rules").read_text()
    assert 'DRIVERS=="ftdi_sio", ATTR{latency_timer}="1"' in rules
    assert 'ATTRS{serial}=="FT6Z5XYZ", SYMLINK+="vbnav-u2d2"' in rules
    assert 'ATTRS{idVendor}=="03e7"' in rules


def test_the_oak_error_names_the_rule_vbnav_ships():
    from vbnav.control.service_files import OAK_RULE, UDEV_NAME
    src = open("drivers/oak_camera.py").read()
    assert UDEV_NAME in src and "vbnav service install" in src and "03e7" in OAK_RULE


def test_install_refuses_to_overwrite_without_overwrite_and_uninstall_removes_only_its_files(tmp_path, capsys):
    assert _install(tmp_path) == 0
    unit = tmp_path / "etc/systemd/system/vbnav-sentry-dxl.service"
    unit.write_text(unit.read_text() + "# edited by hand\n")
    assert _install(tmp_path) == 2
    assert "exists (use --overwrite" in capsys.readouterr().err
    assert unit.read_text().endswith("# edited by hand\n")           # untouched
    assert _install(tmp_path, "--overwrite") == 0
    assert not unit.read_text().endswith("# edited by hand\n")
    assert main(["service", "uninstall", "-c", "configs/sentry-dynamixel.yaml", "--root", str(tmp_path)]) == 0
    assert not unit.exists() and not (tmp_path / "etc/udev/rules.d/70-vbnav.rules").exists()
    foreign = tmp_path / "etc/udev/rules.d/70-vbnav.rules"
    foreign.write_text("# someone else's rules\n")
    assert main(["service", "uninstall", "-c", "configs/sentry-dynamixel.yaml", "--root", str(tmp_path)]) == 2
    assert foreign.exists()
    assert main(["service", "install", "-c", "configs/sentry-dynamixel.yaml", "--root", str(tmp_path),
                 "--device", "bad name=x"]) == 2


class NotifySocket:
    """A stand-in for systemd's notify socket: collects datagrams in arrival order."""

    def __init__(self, path):
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.2)
        self.messages: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.is_set():
            try:
                self.messages.append(self.sock.recv(4096).decode())
            except socket.timeout:
                pass

    def close(self):
        self._stop.set()
        self._thread.join(5)
        self.sock.close()


def test_watchdog_pings_come_from_the_running_loop_and_stop_while_it_stalls(tmp_path, monkeypatch):
    """The loop itself pings: between the loop's own 'stall begins' and 'stall ends' markers (sent on the
    same socket from the loop thread, so the datagram order is the loop's order) there is no WATCHDOG=1,
    and there are pings before and after. No timing is asserted."""
    from runtime_helpers import RecordingDrive
    from vbnav.control.config import Config
    from vbnav.control.controllers.manual import IdleController
    from vbnav.control.runtime import sd_notify
    from vbnav.control.runtime.runtime import Runtime
    from vbnav.drivers.clock import MonotonicClock
    path = tmp_path / "notify"
    systemd = NotifySocket(path)
    monkeypatch.setenv("NOTIFY_SOCKET", str(path))
    monkeypatch.setenv("WATCHDOG_USEC", "40000")            # a ping at most every 20 ms
    cfg = Config.model_validate({"loop": {"rate_hz": 100, "max_missed_streak": 10 ** 6, "stall_periods": 1e6}})
    clock = MonotonicClock()
    rt = Runtime(cfg, RecordingDrive(clock), IdleController(), clock)
    notifier = sd_notify.attach(rt)
    marker = sd_notify.SystemdNotifier()
    import time

    def stall(r, ctx, twist, wheels):
        if ctx.cycle == 60:
            marker.notify("X-STALL=begin")
            time.sleep(0.5)                                  # a hung driver call: 12 watchdog half-periods
            marker.notify("X-STALL=end")

    rt.cycle_observers.append(stall)
    try:
        rt.run(1.2)
    finally:
        sd_notify.stopping(notifier)
        time.sleep(0.3)
        systemd.close()
    msgs = systemd.messages
    assert msgs[0].startswith("READY=1")
    begin, end = msgs.index("X-STALL=begin"), msgs.index("X-STALL=end")
    assert "WATCHDOG=1" not in msgs[begin:end]
    assert msgs[:begin].count("WATCHDOG=1") >= 3 and msgs[end:].count("WATCHDOG=1") >= 3
    assert msgs[-1] == "STOPPING=1"


def test_without_notify_socket_the_notifier_does_nothing(monkeypatch):
    from vbnav.control.runtime.sd_notify import SystemdNotifier
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    n = SystemdNotifier()
    assert not n.enabled and not n.notify("READY=1")
    n.heartbeat(0)


def test_vbnav_run_tells_systemd_it_is_ready_and_stopping(tmp_path):
    path = tmp_path / "notify"
    systemd = NotifySocket(path)
    env = dict(os.environ, NOTIFY_SOCKET=str(path), WATCHDOG_USEC="5000000")
    try:
        r = subprocess.run(VBNAV + ["run", "--no-camera", "--duration", "0.5"], capture_output=True, text=True,
                           timeout=120, env=env)
    finally:
        import time
        time.sleep(0.3)
        systemd.close()
    assert r.returncode == 0, r.stderr
    assert systemd.messages[0].startswith("READY=1") and "WATCHDOG=1" in systemd.messages
    assert systemd.messages[-1] == "STOPPING=1"
