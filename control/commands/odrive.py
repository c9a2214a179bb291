"""``vbnav odrive clear-errors -c CONFIG``: show and clear the error words of the configured ODrive.

After a crash (or a killed ``vbnav run``) the ODrive's axis watchdog has
expired and WATCHDOG_TIMER_EXPIRED stays latched: the next run refuses to start
until it is cleared (unless ``drive.options.clear_watchdog_error_at_start`` is
true). This command connects to the ODrive of the configuration, prints what
each axis reports, sends ``sc`` (clear errors) and repeats the safe bring-up;
the axes stay idle (read back: an axis not idle is named). Exit 0 when the ODrive
is clear, 3 when errors remain (a hardware fault whose cause is still there), an
axis is not idle after clearing, or the device does not answer.
"""
from __future__ import annotations

import argparse
import sys

from vbnav.control.commands._common import add_config_arg
from vbnav.drivers.errors import InputError

COMMAND = "vbnav odrive"


def register(sub) -> None:
    p = sub.add_parser("odrive", help="ODrive maintenance: clear-errors", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    act = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    c = act.add_parser("clear-errors", help="print and clear the ODrive's error words (after a crash)")
    add_config_arg(c)
    c.set_defaults(func=run_clear)


def run_clear(args) -> int:
    from vbnav.control.config import load_config
    from vbnav.drivers.clock import MonotonicClock
    from vbnav.drivers.odrive import ODriveDrive
    from vbnav.drivers.wheels import DriveError
    cfg = load_config(args.config)
    if cfg.drive.driver != "odrive":
        raise InputError(f"{cfg.source}: drive.driver is {cfg.drive.driver!r}; clear-errors is for an ODrive "
                         f"(drive.driver: odrive)")
    drive = ODriveDrive.from_config(cfg, MonotonicClock())
    try:
        try:
            drive.connect()
            for fault in drive.cleared_watchdogs:       # cleared by the bring-up itself (the option)
                print(f"ODrive on {drive.opt.port}: {fault}")
            if not drive.cleared_watchdogs:
                print(f"ODrive on {drive.opt.port}: no errors")
                return 0
            return _say_idle(drive, "errors cleared by the bring-up (drive.options.clear_watchdog_error_at_start)")
        except DriveError as exc:
            if not drive.faults:            # not an error word: the device is missing or silent
                print(f"{COMMAND} clear-errors: {exc}", file=sys.stderr)
                return 3
        for fault in drive.faults:
            print(f"ODrive on {drive.opt.port}: {fault}")
        try:
            drive.clear_faults()
        except DriveError as exc:       # an error word that 'sc' did not clear, or the device went silent
            print(f"{COMMAND} clear-errors: clearing did not succeed: {exc}", file=sys.stderr)
            return 3
        return _say_idle(drive, "errors cleared")
    finally:
        drive.close()


def _say_idle(drive, cleared: str) -> int:
    """'axes idle' once each axis's state is read back IDLE (the bring-up only asks for it); else the axis
    that is not, exit 3."""
    drive.disable()        # the stop sent again, each axis's current_state read back
    if drive.stop_failure:
        print(f"{COMMAND} clear-errors: {cleared}, but not every axis is idle: {drive.stop_failure}",
              file=sys.stderr)
        return 3
    print(f"ODrive on {drive.opt.port}: {cleared}, axes idle; 'vbnav run' can start")
    return 0
