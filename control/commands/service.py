"""``vbnav service install|status|logs|uninstall``: vbnav as a systemd service on the robot."""
from __future__ import annotations

import subprocess
from pathlib import Path

from vbnav.control.commands._common import add_config_arg
from vbnav.drivers.errors import InputError

_EPILOG = """\
install writes /etc/systemd/system/vbnav-<robot>.service (robot.name) and /etc/udev/rules.d/70-vbnav.rules
(run it as root, or with --root DIR to write the files under DIR and look at them), then prints the commands
that load them. The service runs 'vbnav run -c CONFIG' (Type=notify: the control loop's heartbeat feeds
systemd's watchdog, a stalled loop is restarted; Restart=on-failure; real-time limits; CPUAffinity from
loop.cpu_affinity). See docs/service.md."""


def register(sub) -> None:
    import argparse
    p = sub.add_parser("service", help="install vbnav as a systemd service with udev rules; status, logs, uninstall",
                       description="Run the robot as a systemd service that survives reboots and crashes.",
                       epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    cmds = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    i = cmds.add_parser("install", help="write the systemd unit and the udev rules")
    add_config_arg(i)
    i.add_argument("--root", default="/", metavar="DIR", help="write under DIR instead of / (to inspect or package)")
    i.add_argument("--overwrite", action="store_true", help="replace an existing unit or rules file")
    i.add_argument("--user", default=None, help="run the service as this user (default: root)")
    i.add_argument("--device", action="append", default=[], metavar="NAME=SERIAL",
                   help="a udev rule naming the USB serial adapter with this serial number /dev/vbnav-NAME "
                        "(repeatable; e.g. --device u2d2=FT6Z5XYZ, then drive.options.port: /dev/vbnav-u2d2)")
    for name, text in (("status", "systemctl status of the robot's service"),
                       ("logs", "the service's journal (journalctl -u ...)"),
                       ("uninstall", "remove the unit and the udev rules written by install")):
        c = cmds.add_parser(name, help=text)
        add_config_arg(c)
        if name == "logs":
            c.add_argument("--follow", "-f", action="store_true", help="keep printing new lines")
            c.add_argument("--lines", "-n", type=int, default=100, help="lines of history (default 100)")
        if name == "uninstall":
            c.add_argument("--root", default="/", metavar="DIR", help="remove under DIR instead of /")
    p.set_defaults(func=_run)


def _run(args) -> int:
    from vbnav.control.config import load_config
    cfg = load_config(args.config)
    unit = f"vbnav-{cfg.robot.name}.service"
    if args.action == "install":
        return _install(args, cfg)
    if args.action == "uninstall":
        from vbnav.control.service_files import uninstall
        try:
            removed = uninstall(Path(args.root), cfg.robot.name)
        except FileExistsError as exc:
            raise InputError(str(exc)) from None
        for path in removed:
            print(f"removed {path}")
        if not removed:
            print(f"nothing to remove under {args.root}")
        if removed and args.root == "/":
            print(f"now: systemctl disable --now {unit}; systemctl daemon-reload; udevadm control --reload")
        return 0
    cmd = ["systemctl", "status", "--no-pager", unit] if args.action == "status" else \
        ["journalctl", "--no-pager", "-u", unit, "-n", str(args.lines)] + (["-f"] if args.follow else [])
    try:
        return subprocess.call(cmd)
    except FileNotFoundError:
        print(f"vbnav service {args.action}: {cmd[0]} not found (is this a systemd machine?)")
        return 3


def _install(args, cfg) -> int:
    from vbnav.control.service_files import install, parse_devices, plan
    if not cfg.source:
        raise InputError("service install needs a configuration file (-c FILE)")
    try:
        devices = parse_devices(args.device)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    files = plan(cfg, Path(cfg.source).resolve(), Path(args.root), devices, user=args.user)
    try:
        written = install(files, overwrite=args.overwrite)
    except FileExistsError as exc:
        raise InputError(str(exc)) from None
    for path in written:
        print(f"wrote {path}")
    unit = files.unit_path.name
    if args.root == "/":
        print(f"now: systemctl daemon-reload && systemctl enable --now {unit}; "
              f"udevadm control --reload && udevadm trigger")
    else:
        print(f"check: systemd-analyze verify {files.unit_path}")
    return 0
