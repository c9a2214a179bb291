"""vbnav service: install the robot's controller as a systemd service (with its udev rules), and look after it.

``install`` writes the unit and the rules (control/service.py); ``status``, ``logs`` and ``uninstall`` wrap
systemctl and journalctl, and say so plainly when this machine does not run systemd.
"""
from __future__ import annotations

import getpass
import os
import pwd
import shutil
import subprocess
import sys
from pathlib import Path

from vbnav.drivers.errors import InputError

#: present when systemd is the running init (sd_booted(3))
SYSTEMD_RUN_DIR = "/run/systemd/system"
EXIT_NO_SYSTEMD = 3      # like a missing device: nothing wrong with the command, the machine lacks it


def register(sub) -> None:
    p = sub.add_parser("service", help="install vbnav as a systemd service with its udev rules; status, logs",
                       description="Run the robot as a systemd service: 'install' writes a unit that runs "
                                   "'vbnav run -c CONFIG' (restarted on failure and when its control loop stops "
                                   "pinging the watchdog) and udev rules (FTDI latency timer, OAK access, "
                                   "/dev/vbnav-* names by USB serial number). See docs/service.md.")
    ops = p.add_subparsers(dest="operation", metavar="OPERATION", required=True)
    i = ops.add_parser("install", help="write the systemd unit and the udev rules",
                       description="Write /etc/systemd/system/vbnav.service and /etc/udev/rules.d/99-vbnav.rules "
                                   "(under --root). Needs root for /etc: sudo $(command -v vbnav) service install "
                                   "-c CONFIG.")
    i.add_argument("--config", "-c", required=True, metavar="FILE",
                   help="the robot's configuration YAML (a bare name like 'sentry-dynamixel' is looked up in configs/)")
    i.add_argument("--root", default="/", metavar="DIR",
                   help="install under DIR instead of / (an image of the robot's disk, a test); nothing is reloaded")
    i.add_argument("--overwrite", action="store_true", help="replace an installed unit and rules")
    i.add_argument("--user", default=None, metavar="USER",
                   help="the user the service runs as (default: the user who ran sudo, else the current user)")
    i.add_argument("--serial", action="append", default=[], metavar="ROLE=SERIAL",
                   help="the USB serial number of a configured device that is not plugged in now "
                        "(drive=FT6Z5XDZ, camera=...); by default it is read from the device")
    i.set_defaults(func=install)
    s = ops.add_parser("status", help="systemctl status of the service")
    s.set_defaults(func=status)
    lg = ops.add_parser("logs", help="the service's log (journalctl)")
    lg.add_argument("-f", "--follow", action="store_true", help="keep printing new lines")
    lg.add_argument("-n", "--lines", type=int, default=100, metavar="N", help="the last N lines (default 100)")
    lg.add_argument("--since", default=None, metavar="WHEN", help="from WHEN on ('1 hour ago', 'today', a date)")
    lg.add_argument("--boot", action="store_true", help="this boot only")
    lg.set_defaults(func=logs)
    u = ops.add_parser("uninstall", help="stop and disable the service, remove the unit and the rules")
    u.add_argument("--root", default="/", metavar="DIR", help="remove them under DIR instead of /")
    u.set_defaults(func=uninstall)


def _default_user() -> str:
    sudo_user = os.environ.get("SUDO_USER")
    if os.geteuid() == 0 and sudo_user:
        return sudo_user
    return getpass.getuser()


def _serials(pairs: list[str]) -> dict[str, str]:
    out = {}
    for pair in pairs:
        role, sep, serial = pair.partition("=")
        if not sep or not role or not serial:
            raise InputError(f"--serial {pair!r}: expected ROLE=SERIAL, e.g. drive=FT6Z5XDZ")
        if role in out:
            raise InputError(f"--serial {pair}: {role} is given twice ({role}={out[role]} before)")
        out[role] = serial
    return out


def install(args) -> int:
    from vbnav.control import service
    from vbnav.control.config import load_config
    cfg = load_config(args.config)
    user = args.user or _default_user()
    on_this_machine = Path(args.root).resolve() == Path("/")
    if on_this_machine:
        _check_user(user)
        _check_cpus(cfg)
    plan = service.plan(cfg, user, _serials(args.serial))
    written = service.install(plan, service.ServiceFiles(Path(args.root)), args.overwrite)
    for path in written:
        print(f"wrote {path}")
    for note in plan.notes:
        print(f"note: {note}")
    wd = service.watchdog_s(cfg.loop)
    print(f"the service runs 'vbnav run -c {Path(cfg.source).resolve()}' as {user}; the watchdog restarts it when "
          f"its control loop has not cycled for {wd:g} s")
    if not on_this_machine:
        return 0
    if _systemd_problem() is None:
        _reload()
        print("start it now and at every boot: sudo systemctl enable --now vbnav; logs: vbnav service logs -f")
    else:
        print(f"note: {_systemd_problem()}: the unit takes effect on a machine that runs systemd")
    return 0


def _check_user(user: str) -> None:
    try:
        pwd.getpwnam(user)
    except KeyError:
        raise InputError(f"--user {user}: no such user on this machine") from None


def _check_cpus(cfg) -> None:
    cpus = os.cpu_count() or 1
    for key in ("process_cpu_affinity", "cpu_affinity"):
        bad = [c for c in getattr(cfg.loop, key) if c >= cpus]
        if bad:
            raise InputError(f"{cfg.source}: loop.{key}: CPU {', '.join(map(str, bad))} does not exist here "
                             f"(this machine has CPUs 0-{cpus - 1})")


def _reload() -> None:
    """systemd and udev read the new files (a failure is reported, the files stay)."""
    for cmd in (["systemctl", "daemon-reload"], ["udevadm", "control", "--reload-rules"],
                ["udevadm", "trigger", "--subsystem-match=tty", "--subsystem-match=usb",
                 "--subsystem-match=usb-serial", "--subsystem-match=video4linux"]):
        if shutil.which(cmd[0]) is None:
            print(f"note: {cmd[0]} not found; run '{' '.join(cmd)}' where it is", file=sys.stderr)
            continue
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode != 0:
            print(f"note: '{' '.join(cmd)}' failed: {done.stderr.strip() or done.returncode}", file=sys.stderr)


def _systemd_problem() -> str | None:
    """Why systemctl cannot manage the service here, or None."""
    if shutil.which("systemctl") is None:
        return "systemctl is not installed"
    if not os.path.isdir(SYSTEMD_RUN_DIR):
        return f"systemd is not running on this machine ({SYSTEMD_RUN_DIR} is missing: another init runs as PID 1)"
    return None


def _systemctl_or_say(name: str, cmd: list[str]) -> int:
    from vbnav.control.service import UNIT_NAME
    problem = _systemd_problem()
    if problem is not None:
        print(f"vbnav service {name}: {problem}: {UNIT_NAME} cannot run here", file=sys.stderr)
        return EXIT_NO_SYSTEMD
    if shutil.which(cmd[0]) is None:
        print(f"vbnav service {name}: {cmd[0]} is not installed", file=sys.stderr)
        return EXIT_NO_SYSTEMD
    return subprocess.run(cmd).returncode


def status(args) -> int:
    from vbnav.control.service import UNIT_NAME
    return _systemctl_or_say("status", ["systemctl", "status", "--no-pager", UNIT_NAME])


def logs(args) -> int:
    from vbnav.control.service import UNIT_NAME
    if args.lines < 0:
        raise InputError(f"--lines {args.lines}: expected a number >= 0")
    cmd = ["journalctl", "--no-pager", "-u", UNIT_NAME, "-n", str(args.lines)]
    if args.follow:
        cmd.append("--follow")
    if args.since:
        cmd += ["--since", args.since]
    if args.boot:
        cmd.append("--boot")
    return _systemctl_or_say("logs", cmd)


def uninstall(args) -> int:
    from vbnav.control import service
    on_this_machine = Path(args.root).resolve() == Path("/")
    problem = _systemd_problem() if on_this_machine else None
    if on_this_machine and problem is None:
        done = subprocess.run(["systemctl", "disable", "--now", service.UNIT_NAME], capture_output=True, text=True)
        if done.returncode == 0:
            print(f"stopped and disabled {service.UNIT_NAME}")
        else:
            print(f"note: systemctl disable --now {service.UNIT_NAME}: {done.stderr.strip()}", file=sys.stderr)
    removed = service.uninstall(service.ServiceFiles(Path(args.root)))
    for path in removed:
        print(f"removed {path}")
    if not removed:
        print(f"nothing to remove: no {service.UNIT_NAME} or {service.RULES_NAME} under {args.root}")
    if on_this_machine and problem is None and removed:
        _reload()
    elif on_this_machine and problem is not None:
        print(f"note: {problem}: nothing to stop")
    return 0
