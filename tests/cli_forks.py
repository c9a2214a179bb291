"""Run many ``vbnav`` command lines, each in its own process, without paying Python's start-up for each.

``python tests/cli_forks.py`` reads a JSON list of argument lists on stdin, imports the command line once
(vbnav, numpy, OpenCV, numba: 0.8-1.5 s of CPU, nearly all of what a refused command costs), then forks one
child per command line, two at a time. Each child is a copy of that freshly started interpreter: it runs
``vbnav.control.cli.main`` on its arguments with its standard output and error on files of its own, runs
the interpreter's exit handlers and exits with main's code, as ``python -m vbnav.control.cli`` would. A
child that outlives its time limit is killed (exit -9). Prints a JSON list of {returncode, stdout, stderr}
in the order given.

Used by tests/test_cli_errors.py: its ~150 refused command lines took 124 s on two cores as separate
interpreters, 15 s forked (measured 2026-12-03). The parent starts no threads, so forking it is safe.
"""
from __future__ import annotations

import atexit
import json
import os
import shutil
import signal
import sys
import tempfile
import time


def _child(argv: list[str], out: str, err: str) -> None:
    for path, fd in ((out, 1), (err, 2)):
        f = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        os.dup2(f, fd)
        os.close(f)
    code = 1
    try:
        from vbnav.control.cli import main
        sys.argv = ["vbnav", *argv]
        code = main(argv)
    except SystemExit as exc:        # argparse's own exits, as the interpreter would take them
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        try:
            atexit._run_exitfuncs()
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code if isinstance(code, int) else 1)


def run_all(argvs: list[list[str]], workers: int, timeout_s: float) -> list[dict]:
    results: list[dict] = [{} for _ in argvs]
    running: dict[int, tuple[int, float, str, str]] = {}
    todo = list(enumerate(argvs))
    # mkdtemp, not TemporaryDirectory: the latter's clean-up is an exit handler, which each child runs.
    tmp = tempfile.mkdtemp(prefix="vbnav-forks-")
    try:
        while todo or running:
            while todo and len(running) < workers:
                i, argv = todo.pop(0)
                out, err = os.path.join(tmp, f"{i}.out"), os.path.join(tmp, f"{i}.err")
                sys.stdout.flush()
                sys.stderr.flush()
                pid = os.fork()
                if pid == 0:
                    _child(argv, out, err)
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
    argvs = json.load(sys.stdin)
    workers = int(os.environ.get("VBNAV_FORKS") or max(2, os.cpu_count() or 2))
    timeout_s = float(os.environ.get("VBNAV_FORK_TIMEOUT_S", "120"))
    from vbnav.control import cli                       # the imports every command line makes, done once
    cli.build_parser()
    json.dump(run_all(argvs, workers, timeout_s), sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
