"""Run many ``vbnav`` command lines, or imports of its modules, each in its own process, without paying
Python's start-up for each.

``python tests/cli_forks.py`` reads a JSON list of argument lists on stdin, imports the command line once
(vbnav, numpy, OpenCV, numba: 0.8-1.5 s of CPU, nearly all of what a refused command costs), then forks one
child per command line, two at a time. Each child is a copy of that freshly started interpreter: it runs
``vbnav.control.cli.main`` on its arguments with its standard output and error on files of its own, runs
the interpreter's exit handlers and exits with main's code, as ``python -m vbnav.control.cli`` would. A
child that outlives its time limit is killed (exit -9). Prints a JSON list of {returncode, stdout, stderr}
in the order given.

``python tests/cli_forks.py --imports`` reads a JSON list of module names instead, imports the heavy
third-party libraries only (numpy, OpenCV, numba, yaml; no vbnav module), and forks one child per module
that imports it: each vbnav module loads in a process where no other vbnav module has, as in a fresh
interpreter (an exception's traceback on the child's stderr, exit 1).

Used by tests/test_cli_errors.py: its ~150 refused command lines took 124 s on two cores as separate
interpreters, 15 s forked (measured 2026-12-03); and by tests/test_imports.py (146 modules: 32 s alone and
54 s in the suite as separate interpreters). The parent starts no threads, so forking it is safe.
"""
from __future__ import annotations

import atexit
import contextlib
import importlib
import json
import os
import shutil
import signal
import sys
import tempfile
import time
import traceback

# Imported once by the parent of ``--imports`` (the start-up they cost is most of a module's import).
HEAVY_LIBRARIES = ("numpy", "cv2", "numba", "yaml")


def _child(run, out: str, err: str) -> None:
    """In the forked child: ``run()`` with stdout and stderr on the files ``out`` and ``err``, then exit with
    its code as the interpreter would (exit handlers run; an exception's traceback printed, exit 1)."""
    for path, fd in ((out, 1), (err, 2)):
        f = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        os.dup2(f, fd)
        os.close(f)
    code = 1
    try:
        code = run()
    except SystemExit as exc:        # argparse's own exits, as the interpreter would take them
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except BaseException:
        traceback.print_exc()
        code = 1
    finally:
        try:
            atexit._run_exitfuncs()
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code if isinstance(code, int) else 1)


def _command_line(argv: list[str]):
    def run() -> int:
        from vbnav.control.cli import main
        sys.argv = ["vbnav", *argv]
        return main(argv)
    return run


def _import(name: str):
    def run() -> int:
        importlib.import_module(name)
        return 0
    return run


def run_all(tasks: list, workers: int, timeout_s: float, child=_command_line) -> list[dict]:
    """Each task in a forked child running ``child(task)``, ``workers`` at a time."""
    results: list[dict] = [{} for _ in tasks]
    running: dict[int, tuple[int, float, str, str]] = {}
    todo = list(enumerate(tasks))
    # mkdtemp, not TemporaryDirectory: the latter's clean-up is an exit handler, which each child runs.
    tmp = tempfile.mkdtemp(prefix="vbnav-forks-")
    try:
        while todo or running:
            while todo and len(running) < workers:
                i, task = todo.pop(0)
                out, err = os.path.join(tmp, f"{i}.out"), os.path.join(tmp, f"{i}.err")
                sys.stdout.flush()
                sys.stderr.flush()
                pid = os.fork()
                if pid == 0:
                    _child(child(task), out, err)
                running[pid] = (i, time.monotonic() + timeout_s, out, err)
            pid, status = os.waitpid(-1, os.WNOHANG)
            if pid == 0:
                now = time.monotonic()
                for p, (_, deadline, _, _) in running.items():
                    if now > deadline:
                        os.kill(p, signal.SIGKILL)
                time.sleep(0.01)
                continue
            i, _, out, err = running.pop(pid)
            with open(out, errors="replace") as fo, open(err, errors="replace") as fe:
                results[i] = {"returncode": os.waitstatus_to_exitcode(status), "stdout": fo.read(),
                              "stderr": fe.read()}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return results


def main() -> int:
    tasks = json.load(sys.stdin)
    workers = int(os.environ.get("VBNAV_FORKS") or max(2, os.cpu_count() or 2))
    timeout_s = float(os.environ.get("VBNAV_FORK_TIMEOUT_S", "120"))
    if sys.argv[1:] == ["--imports"]:
        for lib in HEAVY_LIBRARIES:                         # not vbnav: each child imports its module afresh
            with contextlib.suppress(ImportError):
                importlib.import_module(lib)
        json.dump(run_all(tasks, workers, timeout_s, _import), sys.stdout)
        return 0
    from vbnav.control import cli                       # the imports every command line makes, done once
    cli.build_parser()
    json.dump(run_all(tasks, workers, timeout_s), sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
