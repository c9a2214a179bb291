"""An operator's estop kept on disk, so it holds across restarts of the process.

A run that ends on a fault (a camera, a bus, the network, an exception) while an operator's estop is
latched is restarted by systemd a few seconds later (``vbnav service install``, ``Restart=on-failure``); a
latch kept only in memory would be gone, and a service configured for repeat would drive off with nobody's
resume. So the latch is also a file (``safety.latch_file``; by default ``$STATE_DIRECTORY/estop.json``, the
folder systemd makes for ``StateDirectory=vbnav``, and none outside systemd):

- an estop that latches writes it (``write_atomic``: temporary file, rename, folder fsync) on the writer's
  own thread (``LatchWriter``): the loop only posts, it never waits on a disk;
- the resume that clears the estop removes it, the same way;
- at start-up, before the wheels are powered, a file that is there latches the run (``read_latch``), named
  with the estop's reason and stamp; one that cannot be read or parsed latches it too (fail safe), saying why.

A file that cannot be written or removed is a ``warning`` event (cause ``latch_file``) naming it and the
error: the estop holds in memory all the same, but no longer across a restart.

A run holds an exclusive ``flock`` on ``<latch>.lock`` beside the file while it runs (``LatchHold``), so
``vbnav estop clear`` (``clear_latch``: the local way to clear a kept estop without a network) refuses while a
robot process uses the file: that process's estop is in its memory, and only a ``resume`` clears it. The clear
removes the file under that lock and appends who cleared it, when and why to ``<latch>.cleared.log``.
"""
from __future__ import annotations

import fcntl
import getpass
import json
import os
import socket
import threading
import time
from collections import deque
from pathlib import Path
from typing import Optional

from vbnav.drivers.atomic_file import fsync_folder, write_atomic

LATCH_NAME = "estop.json"
#: How long the end of a run waits for a latch file still being written (a slow SD card's fsync).
CLOSE_WAIT_S = 3.0


def latch_path(cfg, environ=None) -> Optional[Path]:
    """``safety.latch_file`` (~ expanded, relative to the config file's folder), else
    ``$STATE_DIRECTORY/estop.json`` under systemd's ``StateDirectory=``, else None (no file)."""
    environ = os.environ if environ is None else environ
    f = cfg.safety.latch_file
    if f:
        p = Path(f).expanduser()
        source = cfg.source or ""
        if not p.is_absolute() and source and not source.startswith("<"):
            p = Path(source).resolve().parent / p
        return p
    state = environ.get("STATE_DIRECTORY", "")
    return Path(state.split(":")[0]) / LATCH_NAME if state else None     # systemd joins several with ':'


def latch_record(message: str, latched_ns: int) -> str:
    """What the file holds: the estop's message, its loop-clock stamp and the wall-clock time it latched."""
    return json.dumps({"cause": "estop", "message": message, "latched_ns": latched_ns,
                       "since": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "pid": os.getpid()}) + "\n"


def read_latch(path: Path) -> Optional[str]:
    """None when no latch file is there; else the message of the latched stop it stands for."""
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as exc:
        return (f"latch file {path} cannot be read ({exc.strerror or exc}): latched all the same (fail safe); "
                f"resume to clear it")
    try:
        data = json.loads(raw)
        message, since, stamp = data["message"], data["since"], data["latched_ns"]
        if not (isinstance(message, str) and isinstance(since, str) and isinstance(stamp, int)):
            raise TypeError("expected message and since as text, latched_ns as an integer")
    except (ValueError, KeyError, TypeError, RecursionError) as exc:
        why = f"no {exc}" if isinstance(exc, KeyError) else str(exc)
        return (f"latch file {path} cannot be parsed ({why}): latched all the same (fail safe); resume to "
                f"clear it")
    return (f"estop kept from before a restart: {message}; latched at {since} (latched_ns {stamp} of the run before), kept in {path} across a "
            f"restart; resume to clear it")


def _lock_path(path: Path) -> Path:
    return path.with_name(path.name + ".lock")


def cleared_log(path: Path) -> Path:
    """Where ``clear_latch`` records who cleared the kept estop of ``path``."""
    return path.with_name(path.name + ".cleared.log")


class LatchHold:
    """A run's exclusive lock on ``<latch>.lock`` (its pid written in it) while the run uses the latch file;
    nothing held when the lock cannot be made (a folder not writable: said as ``folder_problem``)."""

    def __init__(self, path: Path):
        self._fd: Optional[int] = None
        try:
            fd = os.open(_lock_path(path), os.O_RDWR | os.O_CREAT, 0o644)
        except OSError:
            return
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
        except OSError:            # another process holds it (two runs on one latch file) or the write failed
            os.close(fd)
            return
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)     # closing the descriptor releases the lock
            self._fd = None


class LatchBusy(RuntimeError):
    """A robot process holds the latch file: its estop is in its memory, cleared only by a resume."""


def clear_latch(path: Path, reason: str = "") -> Optional[str]:
    """Remove the kept estop ``path`` by hand, under the runs' lock, and log who did it.

    Returns the message of the estop cleared (as a run would have latched it), or None when there was none.
    Raises LatchBusy while a run holds the file, OSError when it cannot be removed or logged."""
    lock = _lock_path(path)
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        if not path.exists():
            return None
        raise OSError(exc.errno, f"cannot open the lock {lock} ({exc.strerror}) to check that no robot runs "
                                 f"with {path}") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "?"
            raise LatchBusy(f"a robot process (pid {pid}) runs with {path}: its estop is latched in its memory and "
                            f"a removed file would not clear it; clear it with `vbnav send resume`, or stop that "
                            f"process first") from None
        kept = read_latch(path)
        if kept is None:
            return None
        if path.is_dir():
            raise OSError(f"{path} is a folder, not a latch file: remove it yourself if it is not needed")
        record = {"cleared": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "by": getpass.getuser(),
                  "uid": os.getuid(), "host": socket.gethostname(), "pid": os.getpid(), "reason": reason,
                  "estop": kept}
        with open(cleared_log(path), "a", encoding="utf-8") as log:   # first: a clear is never unrecorded
            log.write(json.dumps(record) + "\n")
            log.flush()
            os.fsync(log.fileno())
        path.unlink()
        fsync_folder(path.parent)
        return kept
    finally:
        os.close(fd)


def folder_problem(path: Path) -> Optional[str]:
    """Why the latch file could not be written (its folder missing or not writable), or None."""
    folder = path.parent
    if not folder.is_dir():
        return f"its folder {folder} does not exist"
    if not os.access(folder, os.W_OK | os.X_OK):
        return f"its folder {folder} is not writable by this user"
    return None


class LatchWriter:
    """Writes and removes the latch file on a thread of its own. ``write`` and ``remove`` only post (the
    newest post wins: what counts is the latch's last state); ``errors`` hands the failures to the loop."""

    def __init__(self, path: Path):
        self.path = path
        self._cond = threading.Condition()
        self._pending: Optional[str] = None    # the text to write, or "" to remove
        self._posted = 0                        # posts so far, and how many of them are done (written, removed
        self._done = 0                          # or failed; a post replaced by a newer one is done with it)
        self._last_error: Optional[str] = None  # the newest done op's failure
        self._closed = False
        self._errors: deque = deque()
        self._thread = threading.Thread(target=self._run, name="estop-latch-writer", daemon=True)
        self._thread.start()

    def write(self, text: str) -> None:
        self._post(text)

    def remove(self) -> None:
        self._post("")

    def write_and_wait(self, text: str, wait_s: float = 1.0) -> Optional[str]:
        """Post ``text`` and wait (up to ``wait_s``) until it is written: None when it was, else why not. For an
        answer that says the estop is kept (an estop after the run ended), which must be true when sent."""
        with self._cond:
            self._pending = text
            self._posted += 1
            mine = self._posted
            self._cond.notify_all()
            if not self._cond.wait_for(lambda: self._done >= mine, timeout=wait_s):
                return f"not written within {wait_s:g} s"
            return self._last_error

    def errors(self) -> list[str]:
        out = []
        while self._errors:
            out.append(self._errors.popleft())
        return out

    def close(self, wait_s: float = CLOSE_WAIT_S) -> None:
        """Finish what was posted (up to ``wait_s``), then end the thread; what is left unfinished is an error."""
        with self._cond:
            self._closed = True
            self._cond.notify()
        self._thread.join(wait_s)
        if self._thread.is_alive():
            self._errors.append(f"latch file {self.path} was still being written or removed {wait_s:g} s after "
                                f"the run ended: a restart may not start as this run ended (latched after an "
                                f"estop, free after a resume)")

    def _post(self, op: str) -> None:
        with self._cond:
            self._pending = op
            self._posted += 1
            self._cond.notify_all()

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._pending is None and not self._closed:
                    self._cond.wait()
                op, self._pending = self._pending, None
                upto = self._posted                  # the posts this op answers (older ones it replaced)
            if op is None:
                return
            error = None
            try:
                if op:
                    write_atomic(self.path, op)
                else:
                    self.path.unlink(missing_ok=True)
                    fsync_folder(self.path.parent)
            except OSError as exc:
                error = str(exc.strerror or exc)
                # A removal follows a resume: the estop is cleared (the robot drives), only the file stays.
                self._errors.append(f"latch file {self.path} could not be written ({exc.strerror or exc}): the "
                                    f"estop holds in memory but not across a restart" if op else
                                    f"latch file {self.path} could not be removed ({exc.strerror or exc}): the "
                                    f"estop is cleared in this run, but a restart would start latched again "
                                    f"(remove the file, or 'vbnav estop clear')")
            with self._cond:
                self._done, self._last_error = upto, error
                self._cond.notify_all()
