"""``vbnav emulate {dynamixel,odrive}``: a device emulator on a pseudo-terminal.

Prints the device path as the first line of standard output, then serves until
interrupted (Ctrl-C or SIGTERM). Point a robot configuration's ``drive.options.port``
at that path to run the real driver without hardware.

``-v`` prints what the emulator does to standard error (plug events, watchdog
expiry, faults, refused writes, id and baud changes); ``-vv`` also every packet.
The Dynamixel servos listen at ``--baud`` (default 1000000; a new XL430 is at
57600): a host at another rate gets no answer, as on a real bus.
"""
from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from pathlib import Path

from vbnav.control.commands._common import non_negative
from vbnav.drivers.errors import InputError


def _ids(text: str) -> list[int]:
    try:
        ids = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated servo ids like 1,2, got {text!r}") from None
    if not ids or any(not 0 <= i <= 252 for i in ids) or len(set(ids)) != len(ids):
        raise argparse.ArgumentTypeError(f"servo ids must be distinct integers in 0..252, got {text!r}")
    return ids


def register(sub) -> None:
    p = sub.add_parser("emulate", help="run a Dynamixel bus or ODrive emulator on a pseudo-terminal",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    dev = p.add_subparsers(dest="device", metavar="DEVICE", required=True)
    d = dev.add_parser("dynamixel", help="Dynamixel X-series servos, Protocol 2.0")
    d.add_argument("--ids", type=_ids, default=[1, 2], help="servo ids on the bus, comma-separated (default 1,2)")
    d.add_argument("--model", default="XL430-W250", help="servo model: XL430-W250 (default) or XM430-W350")
    d.add_argument("--link", default=None, metavar="PATH", help="also create this symlink to the pty "
                   "(a stable path, like /dev/serial/by-id/...); the symlink is what gets printed")
    d.add_argument("--baud", type=int, default=1_000_000, help="the servos' baud rate, bit/s (default 1000000; "
                   "a new XL430 is at 57600); a host at another rate gets no answer")
    d.set_defaults(func=_run_dynamixel)
    o = dev.add_parser("odrive", help="ODrive with two axes, ASCII protocol")
    o.add_argument("--link", default=None, metavar="PATH", help="also create this symlink to the pty")
    o.add_argument("--watchdog-s", type=non_negative, default=0.0,
                   help="axis watchdog timeout preset, s (0 = off until the driver sets it)")
    o.set_defaults(func=_run_odrive)
    for q in (d, o):
        q.add_argument("-v", "--verbose", action="count", default=0,
                       help="print events to stderr (-v: watchdog, faults, plug events; -vv: every packet too)")


def _check_link(link: str | None) -> None:
    """The --link path must be free (or an old symlink to replace) in a folder that exists."""
    if link is None:
        return
    p = Path(link)
    if not p.parent.is_dir():
        raise InputError(f"--link {p}: the folder {p.parent} does not exist")
    if p.exists() and not p.is_symlink():
        raise InputError(f"--link {p}: exists and is not a symlink (it would be replaced by the device link)")


def _log_to_stderr(verbosity: int) -> None:
    if verbosity <= 0:
        return
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s.%(msecs)03d %(name)s: %(message)s", "%H:%M:%S"))
    logger = logging.getLogger("vbnav.emulator")
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG if verbosity > 1 else logging.INFO)


def _serve(emulator, verbosity: int = 0) -> int:
    _log_to_stderr(verbosity)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *a: stop.set())
    path = emulator.start()
    print(path, flush=True)
    try:
        while not stop.wait(0.2):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        emulator.stop()
    return 0


def _run_dynamixel(args) -> int:
    from vbnav.drivers.sim.dynamixel_emulator import DynamixelBus, model_by_name
    try:
        model = model_by_name(args.model)
    except ValueError as exc:
        print(f"vbnav emulate dynamixel: {exc}", file=sys.stderr)
        return 2
    _check_link(args.link)
    try:
        bus = DynamixelBus(args.ids, model, link=args.link, baud=args.baud)
    except ValueError as exc:
        raise InputError(f"--baud: {exc}") from None
    return _serve(bus, args.verbose)


def _run_odrive(args) -> int:
    from vbnav.drivers.sim.odrive_emulator import ODriveEmulator
    _check_link(args.link)
    emu = ODriveEmulator(link=args.link)
    for axis in emu.axes:
        axis.watchdog_timeout = args.watchdog_s
    return _serve(emu, args.verbose)
