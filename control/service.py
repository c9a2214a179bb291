"""The robot as a systemd service: the unit file and the udev rules that ``vbnav service install`` writes.

The unit runs ``vbnav run -c CONFIG`` as ``Type=notify``: the control loop tells
systemd when it runs (READY=1), pings the watchdog from its own cycles
(WATCHDOG=1) and says when it stops (STOPPING=1), see
``runtime/systemd_notify.py``. A process whose loop stopped cycling is killed and
started again; so is one that ended on a fault (``Restart=on-failure``). An operator's estop outlives
such a restart: systemd gives the service ``StateDirectory=vbnav`` (``$STATE_DIRECTORY``), where the run
keeps it in a file until a resume (``runtime/estop_latch.py``).

Watchdog timing (``watchdog_s``): the loop itself notices a stall of more than
``loop.stall_periods`` periods (50 ms at 100 Hz), stops the wheels and goes on;
such a stall is the loop's business, not a reason to restart a process whose
restart re-opens the camera and the drive (seconds). The wheels do not depend on
the systemd watchdog either: the drives' own watchdogs stop them when commands
stop. So systemd's watchdog only needs to catch a process that is hung, and is
set well above any stall the loop survives: ``WATCHDOG_STALLS`` times the stall
limit, at least ``WATCHDOG_FLOOR_S``. The loop pings 4 times per period
(``PINGS_PER_WATCHDOG``), so a restart follows at most one watchdog period after
the last completed cycle.

The udev rules set the FTDI latency timer of a U2D2 to 1 ms (the Dynamixel driver
budgets its bus time for it), give the OAK camera (USB vendor 03e7) to users,
and name the configured devices by their USB serial numbers (``/dev/vbnav-drive``,
``/dev/vbnav-camera``), so a robot with two USB-serial adapters does not swap
them at the next boot.
"""
from __future__ import annotations

import os
import re
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from vbnav.control.runtime.estop_latch import LATCH_NAME
from vbnav.control.runtime.systemd_notify import PINGS_PER_WATCHDOG
from vbnav.drivers.atomic_file import write_atomic_set
from vbnav.drivers.discovery import UsbIdentity, usb_identity
from vbnav.drivers.errors import InputError

UNIT_NAME = "vbnav.service"
UNIT_DIR = "etc/systemd/system"
RULES_NAME = "99-vbnav.rules"
RULES_DIR = "etc/udev/rules.d"

WATCHDOG_FLOOR_S = 5.0       # longer than a stall the loop reports and survives (a 2 s garbage collection)
WATCHDOG_STALLS = 20         # times the loop's own stall limit (loop.stall_periods x period)
START_TIMEOUT_S = 60         # imports on a small computer, drive bring-up, an OAK's boot and first frame
# The loop ends (wheels stopped) within a cycle of SIGTERM; closing down may then take the telemetry
# publisher's flush (10 s), the event echo (4 s), a mode switch still on its worker (5 s), the estop latch
# file's last write (3 s) and the drive and camera: past 15 s systemd killed it mid-close and the recording
# stayed a .part.
STOP_TIMEOUT_S = 30
STATE_DIRECTORY = "vbnav"     # StateDirectory=: where the estop latch file survives a restart (estop_latch.py)
RESTART_S = 2                # a USB device that re-enumerates after a brown-out is back by then

FTDI_VENDOR, U2D2_PRODUCT = "0403", "6014"
OAK_VENDOR = "03e7"
#: exit codes of vbnav run (control/cli.py): 2 bad input (a restart does not mend a configuration),
#: 130 stopped by a signal (systemctl stop: a clean end)
EXIT_BAD_INPUT, EXIT_INTERRUPTED = 2, 130

_SERIAL = re.compile(r"^[A-Za-z0-9._:+\-]+$")     # what a USB serial number may hold to sit in a udev rule
_USER = re.compile(r"^[a-z_][a-z0-9_.\-]*\$?$", re.IGNORECASE)


def watchdog_s(loop) -> float:
    """WatchdogSec of the unit for a ``LoopConfig``: WATCHDOG_STALLS x the loop's stall limit, at least
    WATCHDOG_FLOOR_S (see the module's docstring)."""
    stall_s = loop.stall_periods / loop.rate_hz
    return max(WATCHDOG_FLOOR_S, WATCHDOG_STALLS * stall_s)


@dataclass
class ServiceFiles:
    """Where the unit and the rules go under ``root`` (``/`` on the robot, a folder for an image or a test)."""
    root: Path

    @property
    def unit(self) -> Path:
        return self.root / UNIT_DIR / UNIT_NAME

    @property
    def rules(self) -> Path:
        return self.root / RULES_DIR / RULES_NAME


@dataclass
class Device:
    """A device the configuration names, and the stable name the udev rules give it."""
    role: str                        # "drive", "camera"
    key: str                         # the config key that names it: drive.options.port
    path: str                        # what it says now
    subsystem: str                   # udev SUBSYSTEM: "tty" or "video4linux"
    usb: Optional[UsbIdentity] = None

    @property
    def stable_name(self) -> str:
        return f"vbnav-{self.role}"


@dataclass
class Plan:
    """What ``install`` writes, and what it could not do (said to the user)."""
    unit: str
    rules: str
    devices: list[Device] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


# -- the configured devices ----------------------------------------------------------------------------
def configured_devices(cfg) -> list[Device]:
    """The USB devices the configuration opens by a device path: the drive's serial port, a V4L2 camera."""
    from vbnav.control.config import validate_driver_options
    opts = validate_driver_options(cfg, cfg.source or "<config>")
    out = []
    from vbnav.drivers import registry
    from vbnav.drivers.serial_drive import SerialWheelDrive
    # A serial drive's options name its port (SerialWheelDrive); a V4L2 camera's, its device.
    serial = issubclass(registry.load(registry.DRIVES, cfg.drive.driver), SerialWheelDrive)
    port = opts["drive"].port if serial else None
    if port:
        out.append(Device("drive", "drive.options.port", port, "tty"))
    device = opts["camera"].device if cfg.camera.driver == "v4l2" else None
    if device and not os.path.isfile(device):       # a video file is no device
        out.append(Device("camera", "camera.options.device", device, "video4linux"))
    return out


def identify(devices: list[Device], serials: dict[str, str], sysfs: str = "/sys") -> list[str]:
    """Give each device its USB identity: from ``serials`` (role -> serial number, from the command line)
    or from sysfs when it is plugged in. Returns notes for the devices left without a stable name."""
    notes = []
    unknown = set(serials) - {d.role for d in devices}
    if unknown:
        roles = ", ".join(d.role for d in devices) or "none"
        raise InputError(f"--serial {', '.join(sorted(unknown))}: the configuration names no such device "
                         f"(devices with a path: {roles})")
    for d in devices:
        found = usb_identity(d.path, sysfs)
        serial = serials.get(d.role)
        if serial is not None:
            if not _SERIAL.match(serial):
                raise InputError(f"--serial {d.role}={serial!r}: expected letters, digits and . _ : + -")
            d.usb = UsbIdentity(found.vendor if found else "", found.product if found else "", serial)
        elif found is None:
            notes.append(f"no stable name for the {d.role} ({d.key} {d.path}): it is not plugged in, or not on "
                         f"USB; plug it in and install again with --overwrite, or give --serial {d.role}=SERIAL "
                         f"('udevadm info --query=property --name=DEVICE' shows it as ID_SERIAL_SHORT where the "
                         f"device is plugged in)")
        elif not found.serial or not _SERIAL.match(found.serial):
            notes.append(f"no stable name for the {d.role} ({d.key} {d.path}, USB {found.vendor}:{found.product}):"
                         f" the device reports no usable serial number; keep a /dev/serial/by-path or "
                         f"/dev/v4l/by-path name in {d.key}")
        else:
            d.usb = found
    return notes


# -- the files -------------------------------------------------------------------------------------------
def vbnav_executable() -> str:
    """The installed ``vbnav`` of this Python environment (the console script beside the interpreter),
    else the one on PATH."""
    beside = Path(sys.executable).parent / "vbnav"
    if beside.is_file() and os.access(beside, os.X_OK):
        return str(beside)
    found = shutil.which("vbnav")
    if found:
        return os.path.abspath(found)
    raise InputError(f"no 'vbnav' executable beside {sys.executable} or on PATH: install the package in the "
                     f"robot's environment (pip install .) and run 'vbnav service install' from there")


def _unit_arg(text: str, what: str) -> str:
    """One ExecStart/Environment word: systemd expands % and $, and splits at spaces unless quoted."""
    if any(c in text for c in '"\\\n\'') or any(ord(c) < 32 for c in text):
        raise InputError(f"{what} {text!r}: quotes, backslashes and control characters cannot go into a "
                         f"systemd unit; use a path without them")
    text = text.replace("%", "%%").replace("$", "$$")
    return f'"{text}"' if " " in text else text


def unit_text(cfg, config_path: str, executable: str, user: str, pythonpath: str = "") -> str:
    """The systemd unit that runs ``vbnav run -c config_path`` (absolute) as ``user``."""
    loop = cfg.loop
    wd = watchdog_s(loop)
    stall_s = loop.stall_periods / loop.rate_hz
    lines = [
        f"# {UNIT_NAME}: written by 'vbnav service install' from {config_path}.",
        "# Change the configuration, then install again with --overwrite (see docs/service.md).",
        "[Unit]",
        f"Description=vbnav robot controller ({cfg.robot.name})",
        "Wants=network-online.target",
        "After=network-online.target",
        f"# retried every {RESTART_S} s for as long as it fails (an unplugged device): no start limit",
        "StartLimitIntervalSec=0",
        "",
        "[Service]",
        "# the control loop: READY=1 after its first cycle, WATCHDOG=1 from its cycles, STOPPING=1 at the end",
        "Type=notify",
        "NotifyAccess=main",
        f"ExecStart={_unit_arg(executable, 'vbnav executable')} run -c {_unit_arg(config_path, 'config')}",
        f"User={user}",
        "WorkingDirectory=~",
        "Environment=PYTHONUNBUFFERED=1",
        f"# /var/lib/{STATE_DIRECTORY} for the user, as $STATE_DIRECTORY: an operator's estop is kept there "
        f"({LATCH_NAME}, safety.latch_file) and holds across restarts until a resume",
        f"StateDirectory={STATE_DIRECTORY}",
    ]
    if pythonpath:
        lines.append(f"Environment={_unit_arg('PYTHONPATH=' + pythonpath, 'PYTHONPATH')}")
    lines += [
        f"# no completed loop cycle for this long is a hung process: {WATCHDOG_STALLS} x the loop's own stall limit "
        f"(loop.stall_periods {loop.stall_periods:g} x period {1e3 / loop.rate_hz:g} ms = {stall_s * 1e3:g} ms), "
        f"at least {WATCHDOG_FLOOR_S:g} s; pings every 1/{PINGS_PER_WATCHDOG} of it",
        f"WatchdogSec={_seconds(wd)}",
        "Restart=on-failure",
        f"RestartSec={RESTART_S}",
        f"# exit {EXIT_BAD_INPUT}: the configuration or a file is wrong, a restart does not mend it; "
        f"exit {EXIT_INTERRUPTED}: stopped by SIGTERM",
        f"RestartPreventExitStatus={EXIT_BAD_INPUT}",
        f"SuccessExitStatus={EXIT_INTERRUPTED}",
        f"TimeoutStartSec={START_TIMEOUT_S}",
        f"TimeoutStopSec={STOP_TIMEOUT_S}",
    ]
    if loop.realtime_priority:
        lines += [f"# loop.realtime_priority {loop.realtime_priority}: the loop thread may take SCHED_FIFO up to it",
                  f"LimitRTPRIO={loop.realtime_priority}"]
    if loop.process_cpu_affinity:
        lines += ["# loop.process_cpu_affinity (the loop thread narrows itself to loop.cpu_affinity)",
                  "CPUAffinity=" + " ".join(str(c) for c in sorted(set(loop.process_cpu_affinity)))]
    lines += ["", "[Install]", "WantedBy=multi-user.target", ""]
    return "\n".join(lines)


def _seconds(s: float) -> str:
    return f"{s:g}" if s == int(s) else f"{s * 1000:.0f}ms"


def udev_rules_text(devices: list[Device], config_path: str, user: str) -> str:
    """FTDI latency timer, OAK access, and the configured devices' stable names."""
    owner = f', OWNER="{user}"' if user != "root" else ""
    lines = [
        f"# {RULES_NAME}: written by 'vbnav service install' from {config_path} (see docs/service.md).",
        "",
        f"# ROBOTIS U2D2 (FTDI FT232H, {FTDI_VENDOR}:{U2D2_PRODUCT}): USB latency timer 1 ms instead of 16; the "
        "Dynamixel driver waits 2 x drive.options.latency_ms for an answer",
        _latency_rule(U2D2_PRODUCT),
    ]
    for d in devices:       # another FTDI adapter on the drive (a USB2Dynamixel, 0403:6001) wants the same
        if d.usb and d.usb.vendor == FTDI_VENDOR and d.usb.product not in ("", U2D2_PRODUCT):
            lines += [f"# the {d.role}'s FTDI adapter ({FTDI_VENDOR}:{d.usb.product})", _latency_rule(d.usb.product)]
    lines += [
        "",
        f"# OAK cameras (Luxonis, Movidius USB vendor {OAK_VENDOR}, before and after their boot): open to users, "
        "as Luxonis documents",
        f'SUBSYSTEM=="usb", ATTRS{{idVendor}}=="{OAK_VENDOR}", MODE="0666"',
    ]
    named = [d for d in devices if d.usb is not None]
    if named:
        lines += ["", "# the configured devices by USB serial number"]
    for d in named:
        match = [f'SUBSYSTEM=="{d.subsystem}"']
        if d.usb.vendor:
            match.append(f'ATTRS{{idVendor}}=="{d.usb.vendor}"')
        if d.usb.product:
            match.append(f'ATTRS{{idProduct}}=="{d.usb.product}"')
        match.append(f'ATTRS{{serial}}=="{d.usb.serial}"')
        if d.subsystem == "video4linux":
            match.append('ATTR{index}=="0"')     # the capture node, not the metadata node of the same camera
        lines += [f"# {d.role}: {d.key} is {d.path} now; /dev/{d.stable_name} is the same device at every boot",
                  ", ".join(match) + f', SYMLINK+="{d.stable_name}", MODE="0660"{owner}']
    return "\n".join(lines) + "\n"


def _latency_rule(product: str) -> str:
    return (f'ACTION=="add", SUBSYSTEM=="usb-serial", DRIVERS=="ftdi_sio", ATTRS{{idVendor}}=="{FTDI_VENDOR}", '
            f'ATTRS{{idProduct}}=="{product}", ATTR{{latency_timer}}="1"')


# -- install, uninstall ----------------------------------------------------------------------------------
def plan(cfg, user: str, serials: Optional[dict[str, str]] = None, sysfs: str = "/sys",
         executable: Optional[str] = None, pythonpath: Optional[str] = None) -> Plan:
    """The unit and the rules for a loaded configuration (``cfg.source`` is its file)."""
    if not _USER.match(user):
        raise InputError(f"--user {user!r}: not a user name")
    config_path = str(Path(cfg.source).resolve())
    devices = configured_devices(cfg)
    notes = identify(devices, serials or {}, sysfs)
    for d in devices:
        stable = f"/dev/{d.stable_name}"
        if d.usb is not None and d.path != stable:
            notes.append(f"set {d.key}: {stable} in {config_path} to use the stable name (it is {d.path})")
    pythonpath = os.environ.get("PYTHONPATH", "") if pythonpath is None else pythonpath
    unit = unit_text(cfg, config_path, executable or vbnav_executable(), user, pythonpath)
    return Plan(unit, udev_rules_text(devices, config_path, user), devices, notes)


def install(p: Plan, files: ServiceFiles, overwrite: bool = False) -> list[Path]:
    """Write the unit and the rules as one set (both to temporary files, then both renamed: a failure leaves
    the old pair). Refuses to replace an existing unit or rules file without ``overwrite``, before writing
    anything."""
    targets = [(files.unit, p.unit), (files.rules, p.rules)]
    if not overwrite:
        for path, _ in targets:
            if path.exists():
                raise InputError(f"{path} exists (installed before?); give --overwrite to replace it, or "
                                 f"'vbnav service uninstall' first")
    try:
        for path, _ in targets:
            path.parent.mkdir(parents=True, exist_ok=True)
        return write_atomic_set(dict(targets), mode=0o644)
    except PermissionError as exc:     # named by the folder (the file refused may be a temporary one)
        folder = next((t.parent for t, _ in targets if str(exc.filename).startswith(str(t.parent))), exc.filename)
        raise InputError(f"{folder}: permission denied; writing there needs root "
                         f"(sudo $(command -v vbnav) service install ...)") from None


def uninstall(files: ServiceFiles) -> list[Path]:
    """Remove the unit and the rules; returns those that were there."""
    removed = []
    for path in (files.unit, files.rules):
        try:
            path.unlink()
            removed.append(path)
        except FileNotFoundError:
            continue
        except PermissionError:
            raise InputError(f"{path}: permission denied; removing it needs root (sudo)") from None
    return removed

