"""The ``vbnav`` command line.

Each subcommand is a module in ``vbnav/control/commands/`` that defines
``register(subparsers)``; it adds its parser and sets ``func`` (a callable
taking the parsed args and returning an exit code). New features add a module
there and never edit this file.

Exit codes: 0 success, 1 the job ran but failed (e.g. a route did not complete),
2 bad input (configuration, files, arguments), 3 hardware/device error,
130 interrupted.
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from vbnav.control import commands
from vbnav.control.config import ConfigError

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_DEVICE, EXIT_INTERRUPTED = 0, 1, 2, 3, 130


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vbnav",
        description="Vision-based navigation for small wheeled robots (teach-and-repeat, VSLAM, obstacle stop).")
    try:
        from importlib.metadata import version
        ver = version("vbnav")
    except Exception:  # pragma: no cover
        ver = "unknown"
    parser.add_argument("--version", action="version", version=f"vbnav {ver}")
    parser.set_defaults(func=None)      # no command given: main prints the help
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.func is None:
        parser.print_help()
        return EXIT_BAD_INPUT
    try:
        return int(args.func(args) or 0)
    except ConfigError as exc:
        print(f"vbnav: configuration error:\n{exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except FileNotFoundError as exc:
        print(f"vbnav: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("vbnav: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
