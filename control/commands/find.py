"""``vbnav find``: what is plugged in; ``vbnav find servos --port P``: which Dynamixel servos answer, at which rate.

``vbnav find`` lists the serial ports (USB id and what it probably is: U2D2,
ODrive, ...; the stable /dev/serial/by-id name to put in the configuration; an
FTDI adapter's latency timer), the V4L2 cameras with their formats, sizes and
frame rates, and the OAK devices (with depthai installed). Finding nothing is a
normal answer (exit 0).

``vbnav find servos --port P`` broadcast-pings at each usual baud rate (57600,
the factory rate, first) and prints id, model and firmware of every servo that
answers; exit 1 when none does.
"""
from __future__ import annotations

import argparse
import sys

from vbnav.control.commands._common import non_negative
from vbnav.drivers.errors import InputError

COMMAND = "vbnav find"
OAK_TIMEOUT_S = 3.0     # --oak-timeout when not given (it defaults to None: with 'servos' it is refused)


def _bauds(text: str) -> list[int]:
    """argparse type: Dynamixel X rates, comma-separated; an empty list would scan the default rates."""
    from vbnav.drivers.dynamixel_table import rate_problem
    try:
        bauds = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        bauds = []
    if not bauds:
        raise argparse.ArgumentTypeError(f"expected baud rates like 57600,1000000, got {text!r}")
    for b in bauds:
        if rate_problem(b):
            raise argparse.ArgumentTypeError(rate_problem(b))
    return bauds


def register(sub) -> None:
    p = sub.add_parser("find", help="list serial ports, cameras and OAK devices; 'find servos' scans a bus",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--port", action="append", default=[], metavar="DEVICE",
                   help="also describe this serial device (e.g. an emulator's pty), repeatable")
    p.add_argument("--oak-timeout", type=non_negative, default=None, metavar="S",
                   help=f"how long to search for OAK devices, s (default {OAK_TIMEOUT_S:g})")
    p.set_defaults(func=run)
    what = p.add_subparsers(dest="what", metavar="WHAT")
    s = what.add_parser("servos", help="scan a Dynamixel bus: ids, models, firmware at each baud rate")
    s.add_argument("--port", required=True, dest="bus_port", metavar="DEVICE",
                   help="the bus adapter (U2D2), e.g. /dev/serial/by-id/usb-FTDI_...")
    s.add_argument("--baud", type=_bauds, default=None, metavar="B[,B...]",
                   help="rates to try, bit/s (default 57600,1000000,115200,2000000,3000000,4000000)")
    s.set_defaults(func=run_servos)


def run(args) -> int:
    from vbnav.drivers import discovery
    for port in args.port:
        discovery.check_device(port, "a serial device such as /dev/ttyUSB0 or an emulator's pty")
    print("Serial ports:")
    ports = discovery.serial_ports(extra=tuple(args.port))
    for port in ports:
        print(f"  {port.device}  {port.usb_id}  {port.kind}" + (f"  [{port.description}]" if port.description
                                                                 and port.description != "n/a" else ""))
        for link in port.by_id:
            print(f"      stable name: {link}")
        if port.latency_timer_ms is not None:
            advice = "" if port.latency_timer_ms <= 1 else (
                f" (a Dynamixel bus wants 1 ms: echo 1 | sudo tee "
                f"{discovery.latency_timer_path(port.device)})")
            print(f"      latency timer: {port.latency_timer_ms} ms{advice}")
    if not ports:
        print("  none found (plug the adapter in; 'dmesg | tail' shows what the kernel saw)")
    print("Cameras (V4L2):")
    cams = discovery.v4l2_devices()
    for cam in cams:
        print(f"  {cam.device}  {cam.name!r}" + ("" if cam.capture is not False else "  (not a capture node)"))
        for link in cam.by_id:
            print(f"      stable name: {link}")
        if cam.error:
            print(f"      {cam.error}")
        for mode in cam.modes:
            sizes = "; ".join(f"{w}x{h}" + (f" @ {', '.join(f'{r:g}' for r in rates)} Hz" if rates else "")
                              for w, h, rates in mode.sizes)
            print(f"      {mode.fourcc} ({mode.description}): {sizes or 'no sizes listed'}")
    if not cams:
        print("  none found")
    print("OAK devices:")
    oaks, note = discovery.oak_devices(OAK_TIMEOUT_S if args.oak_timeout is None else args.oak_timeout)
    if oaks is None:
        print(f"  not searched: {note}")
    else:
        for d in oaks:
            print(f"  {d}")
        if not oaks:
            print("  none found")
    return 0


def run_servos(args) -> int:
    from vbnav.drivers.dynamixel_setup import SCAN_BAUDS, DynamixelBusTool
    from vbnav.drivers.wheels import DriveError
    if args.port:       # find's own --port, before 'servos': the listing's
        raise InputError(f"--port {args.port[0]} before 'servos' adds a port to the listing of 'vbnav find', "
                         "which 'find servos' does not print; the bus is the --port after 'servos'")
    if args.oak_timeout is not None:
        raise InputError("--oak-timeout: 'find servos' does not search for OAK devices")
    bauds = args.baud or list(SCAN_BAUDS)

    def say(baud, servos):
        if not servos:
            print(f"  {baud:>8} bit/s: nothing")
        for s in servos:
            print(f"  {baud:>8} bit/s: id {s.dxl_id:<3} {s.model} (model number {s.model_number}), "
                  f"firmware {s.firmware}", flush=True)

    try:
        with DynamixelBusTool(args.bus_port) as bus:       # refuses a --port that is no serial device
            print(f"Scanning {args.bus_port} (broadcast ping at each rate):", flush=True)
            found = bus.scan(bauds, progress=say)
    except DriveError as exc:
        print(f"{COMMAND} servos: {exc}", file=sys.stderr)
        return 3
    if not found:
        print(f"no servo answered at {', '.join(map(str, bauds))} bit/s: check the power (the servo LED "
              f"blinks once at power-on) and the cable; two servos with the same id garble each other, so "
              f"connect new ones one at a time")
        return 1
    ids = [s.dxl_id for s in found]
    rates = sorted({s.baud for s in found})
    if len(rates) > 1:
        print(f"{len(found)} servo(s) at {len(rates)} different rates: one bus runs at one rate; set each to the "
              f"configured drive.options.baudrate with 'vbnav servo set-baud --port {args.bus_port} --id N "
              f"--new-baud RATE'")
    if len(set(ids)) != len(ids):
        print("the same id answers at two rates: give each servo its own id ('vbnav servo set-id') before "
              "bringing them to one rate")
    if len(rates) == 1:
        print(f"{len(found)} servo(s). In the configuration: drive.options.port {args.bus_port}, baudrate "
              f"{rates[0]}" + (f", left_id and right_id two of {', '.join(map(str, ids))}" if len(found) > 1 else ""))
    return 0
