"""``vbnav estop clear``: clear an estop kept in ``safety.latch_file`` by hand, without a network.

A run that finds the latch file starts latched (docs/safety.md "An estop across restarts"); a running robot is
resumed with ``vbnav send resume``. A robot run by hand without a network (``--no-telemetry``, the simulated
clock) cannot be resumed so: this command removes the file, refusing while a robot process runs with it (its
estop is in its memory), and appends who cleared it, when and why to ``<latch>.cleared.log`` beside it.
Exit 0 when no estop is kept any more, 1 when it was refused or failed.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from vbnav.control.commands._common import add_config_arg
from vbnav.drivers.errors import InputError

COMMAND = "vbnav estop clear"


def register(sub) -> None:
    p = sub.add_parser("estop", help="the estop kept across restarts: clear", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    act = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    c = act.add_parser("clear", help="remove the estop kept in safety.latch_file (no robot may be running with it)")
    add_config_arg(c)
    c.add_argument("--latch-file", default=None, metavar="PATH",
                   help="the latch file (default: the configuration's safety.latch_file, else "
                        "$STATE_DIRECTORY/estop.json under systemd)")
    c.add_argument("--reason", default="", help="why it is cleared, for the log")
    c.set_defaults(func=run_clear)


def run_clear(args) -> int:
    from vbnav.control.runtime.estop_latch import LatchBusy, clear_latch, cleared_log, latch_path
    if args.latch_file:
        path = Path(args.latch_file).expanduser()
    else:
        from vbnav.control.config import load_config
        cfg = load_config(args.config)
        path = latch_path(cfg)
        if path is None:
            # The operator's shell has no $STATE_DIRECTORY; the service's run keeps its estop where systemd
            # points it (service.py's StateDirectory).
            from vbnav.control.service import STATE_DIRECTORY
            service_file = f"/var/lib/{STATE_DIRECTORY}/estop.json"
            raise InputError(f"{cfg.source}: no safety.latch_file (and no $STATE_DIRECTORY in this shell): this run "
                             f"keeps no estop on disk; a robot run by 'vbnav service install' keeps it in "
                             f"{service_file}: give --latch-file {service_file}")
    try:
        kept = clear_latch(path, args.reason)
    except LatchBusy as exc:
        print(f"{COMMAND}: refused: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"{COMMAND}: {path}: not cleared: {exc.strerror or exc}", file=sys.stderr)
        return 1
    if kept is None:
        print(f"no estop kept in {path}: nothing to clear")
    else:
        print(f"cleared the estop kept in {path} ({kept}); logged in {cleared_log(path)}")
    return 0
