"""``vbnav route ...``: work with taught routes. The subcommands come from modules ``_route_*.py`` in this
folder, each defining ``register_route(subparsers)`` (e.g. ``_route_transfer.py``: pull, push, list over
zenoh), so features add a module and never edit this file."""
from __future__ import annotations

import importlib
import pkgutil


def register(sub) -> None:
    from vbnav.control import commands
    p = sub.add_parser("route", help="taught routes: copy them between robots (pull, push, list)",
                       description="Work with taught routes.")
    cmds = p.add_subparsers(dest="route_command", metavar="SUBCOMMAND", required=True)
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_route_"):
            importlib.import_module(f"{commands.__name__}.{info.name}").register_route(cmds)
