"""The systemd unit and udev rules that run vbnav as a service on the robot (``vbnav service install``).

Unit ``vbnav-<robot>.service`` (``robot.name``):

- ``Type=notify``: ready when the control loop runs its first cycle; ``WatchdogSec``:
  the loop thread pings ``WATCHDOG=1`` (control/runtime/sd_notify.py), so a stalled
  loop is killed and restarted;
- ``Restart=on-failure`` (a device that failed, exit 3; a crash; the watchdog), but
  not after bad input (exit 2: ``RestartPreventExitStatus=2``, restarting cannot fix a
  configuration); SIGTERM's exit 130 counts as a clean stop;
- real-time limits: ``LimitRTPRIO`` for ``loop.realtime_priority`` (SCHED_FIFO needs
  it), ``LimitMEMLOCK``; ``CPUAffinity`` from ``loop.cpu_affinity`` (the process; the
  loop thread pins itself within it).

udev rules ``70-vbnav.rules``: FTDI adapters (the U2D2 is an FT232H) get their latency
timer set to 1 ms (the default 16 ms delays every Dynamixel status packet); each
``--device NAME=SERIAL`` gets a stable ``/dev/vbnav-NAME`` for the USB serial adapter
with that serial number (put it in ``drive.options.port``); Luxonis OAK cameras
(Movidius, USB vendor 03e7) are readable by the ``plugdev`` group and the robot's user.

Every file this module writes starts with ``MARK``; uninstall removes only such files.
"""
from __future__ import annotations

import os
import re
import shlex
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

MARK = "# Written by 'vbnav service install'"
UNIT_DIR = "etc/systemd/system"
UDEV_DIR = "etc/udev/rules.d"
UDEV_NAME = "70-vbnav.rules"
WATCHDOG_S = 5            # systemd kills a loop silent this long (the loop pings every 2.5 s at most)
DEVICE_NAME = re.compile(r"^[a-z0-9][a-z0-9_-]{0,31}$")
SERIAL = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
OAK_RULE = 'SUBSYSTEM=="usb", ATTRS{idVendor}=="03e7", MODE="0666"'


def unit_name(robot: str) -> str:
    return f"vbnav-{robot}.service"


@dataclass
class ServiceFiles:
    unit_path: Path
    unit: str
    udev_path: Path
    udev: str


def parse_devices(items: list[str]) -> dict[str, str]:
    """``NAME=SERIAL`` pairs (``--device``); raises ValueError naming the bad one."""
    out: dict[str, str] = {}
    for item in items:
        name, sep, serial = item.partition("=")
        if not sep or not DEVICE_NAME.match(name) or not SERIAL.match(serial):
            raise ValueError(f"--device {item!r}: expected NAME=SERIAL (NAME: lower-case letters, digits, _ -; "
                             f"SERIAL: the adapter's USB serial number, e.g. from 'udevadm info /dev/ttyUSB0 | "
                             f"grep ID_SERIAL_SHORT')")
        if name in out:
            raise ValueError(f"--device {name}: given twice")
        out[name] = serial
    return out


def exec_start(cfg, config_path: Path, python: Optional[str] = None) -> str:
    """The command line of the service: this Python's vbnav, the configuration by absolute path."""
    args = [python or sys.executable, "-m", "vbnav.control.cli", "run", "-c", str(config_path)]
    if cfg.drive.driver == "sim" and cfg.camera.driver == "sim":
        args.append("--realtime")          # a simulated robot as a service: on the wall clock, or it just ends
    return " ".join(shlex.quote(a) for a in args)


def render_unit(cfg, config_path: Path, user: Optional[str] = None, python: Optional[str] = None) -> str:
    lc = cfg.loop
    lines = [
        MARK,
        f"# robot {cfg.robot.name}, configuration {config_path}",
        "[Unit]",
        f"Description=vbnav robot controller ({cfg.robot.name})",
        "After=network-online.target",
        "Wants=network-online.target",
        "StartLimitIntervalSec=120",
        "StartLimitBurst=10",
        "",
        "[Service]",
        "Type=notify",
        "NotifyAccess=main",
        f"ExecStart={exec_start(cfg, config_path, python)}",
        f"WorkingDirectory={config_path.parent}",
        "Environment=PYTHONUNBUFFERED=1",
        f"WatchdogSec={WATCHDOG_S}",
        "TimeoutStartSec=120",
        "TimeoutStopSec=15",
        "KillSignal=SIGTERM",
        "Restart=on-failure",
        "RestartSec=2",
        "RestartPreventExitStatus=2",
        "SuccessExitStatus=130",
        f"LimitRTPRIO={max(lc.realtime_priority, 1)}",
        "LimitMEMLOCK=infinity",
    ]
    if lc.cpu_affinity:
        lines.append("CPUAffinity=" + " ".join(str(c) for c in lc.cpu_affinity))
    if user:
        lines += [f"User={user}", "SupplementaryGroups=dialout plugdev video"]
    lines += ["", "[Install]", "WantedBy=multi-user.target", ""]
    return "\n".join(lines)


def render_udev(devices: dict[str, str]) -> str:
    lines = [
        MARK,
        "# FTDI USB serial adapters (U2D2 = FT232H): 1 ms latency timer instead of 16 ms, so a Dynamixel",
        "# status packet reaches vbnav in about a millisecond.",
        'ACTION=="add", SUBSYSTEM=="usb-serial", DRIVERS=="ftdi_sio", ATTR{latency_timer}="1"',
        "# Stable names by USB serial number (vbnav service install --device NAME=SERIAL): /dev/vbnav-NAME.",
    ]
    for name, serial in sorted(devices.items()):
        lines.append(f'SUBSYSTEM=="tty", ATTRS{{serial}}=="{serial}", SYMLINK+="vbnav-{name}", '
                     f'MODE="0660", GROUP="dialout"')
    lines += [
        "# Luxonis OAK cameras (Movidius, USB vendor 03e7), booted and running, for users without root.",
        OAK_RULE,
        "",
    ]
    return "\n".join(lines)


def plan(cfg, config_path: Path, root: Path, devices: dict[str, str], user: Optional[str] = None,
         python: Optional[str] = None) -> ServiceFiles:
    return ServiceFiles(root / UNIT_DIR / unit_name(cfg.robot.name), render_unit(cfg, config_path, user, python),
                        root / UDEV_DIR / UDEV_NAME, render_udev(devices))


def ours(path: Path) -> bool:
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            return f.readline().startswith(MARK)
    except OSError:
        return False


def install(files: ServiceFiles, overwrite: bool = False) -> list[Path]:
    """Write the unit and the rules (temporary file, then rename); refuse existing ones without ``overwrite``.
    Raises FileExistsError naming the file before anything is written."""
    targets = [(files.unit_path, files.unit), (files.udev_path, files.udev)]
    if not overwrite:
        for path, _ in targets:
            if path.exists():
                raise FileExistsError(f"{path} exists (use --overwrite to replace it)")
    for path, text in targets:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
        tmp.write_text(text)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    return [p for p, _ in targets]


def uninstall(root: Path, robot: str) -> list[Path]:
    """Remove the robot's unit and the vbnav rules if this module wrote them; returns what was removed."""
    removed = []
    for path in (root / UNIT_DIR / unit_name(robot), root / UDEV_DIR / UDEV_NAME):
        if path.exists():
            if not ours(path):
                raise FileExistsError(f"{path} was not written by 'vbnav service install': left alone")
            path.unlink()
            removed.append(path)
    return removed
