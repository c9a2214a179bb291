"""``vbnav servo set-id|set-baud``: first set-up of a Dynamixel X servo (its EEPROM id and baud rate).

A new XL430/XM430 is id 1 at 57600 bit/s. Connect one servo at a time, then
for example::

    vbnav servo set-id --port /dev/ttyUSB0 --id 1 --new-id 2
    vbnav servo set-baud --port /dev/ttyUSB0 --id 2 --new-baud 1000000

Torque is switched off first (the EEPROM area is locked while it is on). The
change is checked by pinging the servo under its new id / at its new rate.
Without ``--baud`` the servo's current rate is found by pinging it at the usual
rates.
"""
from __future__ import annotations

import argparse
import sys

COMMAND = "vbnav servo"


def _servo_id(text: str) -> int:
    """argparse type: a Dynamixel id, 0..252 (253 and 254, broadcast, are reserved)."""
    from vbnav.drivers.dynamixel_table import MAX_ID
    try:
        v = int(text)
    except ValueError:
        v = -1
    if not 0 <= v <= MAX_ID:
        raise argparse.ArgumentTypeError(f"expected a servo id 0..{MAX_ID}, got {text!r}")
    return v


def _rate(text: str) -> int:
    """argparse type: a Dynamixel X baud rate, bit/s."""
    from vbnav.drivers.dynamixel_table import rate_problem
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a baud rate like 57600, got {text!r}") from None
    if rate_problem(v):
        raise argparse.ArgumentTypeError(rate_problem(v))
    return v


def register(sub) -> None:
    p = sub.add_parser("servo", help="set a Dynamixel servo's id or baud rate (first set-up)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    act = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    for name, target, kind, help_ in (("set-id", "--new-id", _servo_id, "the id to give it (0..252)"),
                                      ("set-baud", "--new-baud", _rate,
                                       "the rate to switch it to, bit/s (e.g. 1000000)")):
        a = act.add_parser(name, help=f"{name.replace('-', ' ')} of one servo")
        a.add_argument("--port", required=True, metavar="DEVICE", help="the bus adapter (U2D2)")
        a.add_argument("--id", type=_servo_id, required=True, dest="dxl_id", help="the servo's id now")
        a.add_argument("--baud", type=_rate, default=None, help="its rate now, bit/s (default: found by pinging)")
        a.add_argument(target, type=kind, required=True, dest="new", help=help_)
        a.set_defaults(func=run)


def run(args) -> int:
    from vbnav.drivers.dynamixel_setup import SCAN_BAUDS, DynamixelBusTool
    from vbnav.drivers.wheels import DriveError
    try:
        with DynamixelBusTool(args.port) as bus:
            for baud in [args.baud] if args.baud else SCAN_BAUDS:
                if bus.at(baud).ping(args.dxl_id) is not None:
                    break
            else:
                print(f"{COMMAND} {args.action}: no servo with id {args.dxl_id} answers on {args.port} at "
                      f"{', '.join(str(b) for b in ([args.baud] if args.baud else SCAN_BAUDS))} bit/s "
                      f"('vbnav find servos --port {args.port}' shows what is there)", file=sys.stderr)
                return 3
            if args.action == "set-id":
                s = bus.set_id(args.dxl_id, args.new)
                print(f"servo {args.dxl_id} ({s.model}) at {s.baud} bit/s is now id {s.dxl_id}")
            else:
                s = bus.set_baud(args.dxl_id, args.new)
                print(f"servo {s.dxl_id} ({s.model}) now talks at {s.baud} bit/s (was {baud})")
    except DriveError as exc:
        print(f"{COMMAND} {args.action}: {exc}", file=sys.stderr)
        return 3
    return 0
