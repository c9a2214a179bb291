"""The ``vbnav`` command line.

Each subcommand is a module in ``vbnav/control/commands/`` that defines
``register(subparsers)``; it adds its parser and sets ``func`` (a callable
taking the parsed args and returning an exit code). New features add a module
there and never edit this file.

Exit codes: 0 success, 1 the job ran but failed (e.g. a route did not complete),
2 bad input (configuration, files, arguments), 3 hardware/device error,
130 interrupted, 141 standard output closed early (``vbnav ... | head``, as a
process ended by SIGPIPE).

Bad input is reported here, in one place: a command raises
:class:`~vbnav.drivers.errors.InputError` (ConfigError, RouteError, DatasetError,
CalibrationError, ... derive from it), or an OSError naming a file, and the user
sees ``vbnav <command>: <message>`` and exit code 2, never a traceback. A disk that
is full or read-only (``DISK_ERRORS``) is said the same way, naming the file being
written, with exit code 1 (the input was fine). Any other exception is a bug: its
traceback is printed, with a note saying so, and the exit code is 1.
"""
from __future__ import annotations

import argparse
import errno
import importlib
import os
import pkgutil
import sys
import traceback

from vbnav.control import commands
from vbnav.drivers.errors import InputError

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_DEVICE, EXIT_INTERRUPTED, EXIT_BROKEN_PIPE = 0, 1, 2, 3, 130, 141

# OSErrors about a path the user gave (an output that is a directory, a parent folder that is not
# there): bad input, reported with the path. Any other OSError (a device, the network) is not.
PATH_ERRORS = (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError, FileExistsError)
# OSErrors of the disk being written (full, over quota, read-only, failing): no bug of vbnav's, no bad input.
DISK_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EIO)


class ArgumentParser(argparse.ArgumentParser):
    """argparse with one-line errors: ``vbnav demo: argument --seed: invalid int value: 'x' (see ...)``."""

    def error(self, message: str):
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: {message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(
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
    name = f"vbnav {args.command}"
    try:
        code = int(args.func(args) or 0)
        sys.stdout.flush()      # a closed pipe shows here, not in the interpreter's last flush
        return code
    except InputError as exc:
        return _say(f"{name}: {exc}", EXIT_BAD_INPUT)
    except PATH_ERRORS as exc:
        where = f"{exc.filename}: " if exc.filename else ""
        return _say(f"{name}: {where}{exc.strerror or exc}", EXIT_BAD_INPUT)
    except KeyboardInterrupt:
        return _say(f"{name}: interrupted", EXIT_INTERRUPTED)
    except BrokenPipeError:
        return _stdout_closed()
    except OSError as exc:
        if exc.errno not in DISK_ERRORS:
            return _bug(name)
        where = f"{exc.filename}: " if exc.filename else ""
        return _say(f"{name}: {where}{exc.strerror or exc}", EXIT_FAILED)
    except Exception:
        return _bug(name)


def _bug(name: str) -> int:
    """Inside an ``except``: the traceback, and that it is a bug (exit 1)."""
    traceback.print_exc()
    return _say(f"{name}: this is a bug in vbnav (the traceback above says where); please report it "
                "with the command line that caused it", EXIT_FAILED)


def _say(message: str, code: int) -> int:
    try:
        print(message, file=sys.stderr)
    except BrokenPipeError:
        return _stdout_closed()
    return code


def _stdout_closed() -> int:
    """Whoever read our output has gone (``vbnav run | head -1``): nothing more to say. Point stdout and
    stderr at /dev/null so the interpreter's final flush does not fail again (Python's documented way),
    and exit like a process ended by SIGPIPE. A robot run has already stopped its wheels by then."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    for stream in (sys.stdout, sys.stderr):
        try:
            os.dup2(devnull, stream.fileno())
        except (OSError, ValueError):
            pass
    return EXIT_BROKEN_PIPE


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
