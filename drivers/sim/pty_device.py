"""An emulated serial device behind a pseudo-terminal: the part every emulator shares.

The driver under test opens the pty's slave side as if it were a USB serial
adapter; the emulator answers on the master side from a serving thread. The
device path is either the pty slave or, when ``link`` is given, a stable
symlink to it (as /dev/serial/by-id/... is), so ``unplug()``/``replug()`` can
make the adapter vanish and come back under the same name.

Subclasses implement ``_serve_bytes`` (answer what the host sent), ``_step``
(advance the device's own state) and, if they buffer input,
``_reset_input`` (a new pty starts with an empty buffer).

Baud rate: a pty carries bytes, not bits, so nothing on it is garbled by a
wrong rate. The rate the host asked for is still there: pyserial sets it in the
tty's termios (``c_ispeed``/``c_ospeed``, also for rates without a ``Bnnn``
constant), and ``host_baud()`` reads it back from the slave side with the Linux
``TCGETS2`` ioctl. An emulator compares it with the rate its device is set to
and treats a mismatch as a real device would (see the Dynamixel bus).

Logging: each emulator logs to ``vbnav.emulator.<device>`` (INFO: plug events,
watchdog expiry, faults; DEBUG: every exchange); ``vbnav emulate -v``/``-vv``
prints them.
"""
from __future__ import annotations

import abc
import fcntl
import logging
import os
import select
import struct
import termios
import threading
import time
import tty
from pathlib import Path
from typing import Optional


# Linux: struct termios2 (c_iflag c_oflag c_cflag c_lflag, c_line, c_cc[19], c_ispeed c_ospeed) by TCGETS2
_TCGETS2 = getattr(termios, "TCGETS2", 0x802C542A)
_TERMIOS2_SIZE = 44


def tty_speed(fd: int) -> int | None:
    """The output speed (bit/s) set on the tty ``fd``; None where it cannot be read."""
    try:
        raw = fcntl.ioctl(fd, _TCGETS2, bytes(_TERMIOS2_SIZE))
        return struct.unpack_from("I", raw, 40)[0]
    except OSError:
        return None


class LoggedFlag:
    """A fault-injection switch (``no_answer``, ``corrupt``) that logs when it changes, through the owner's
    ``_log_event(text)``: what a test or an operator did to the device shows in the emulator's log."""

    def __init__(self, on: str, off: str):
        self.on, self.off = on, off

    def __set_name__(self, owner, name: str) -> None:
        self.attr = "_" + name

    def __get__(self, obj, objtype=None):
        return self if obj is None else getattr(obj, self.attr, False)

    def __set__(self, obj, value) -> None:
        value = bool(value)
        if value != getattr(obj, self.attr, False):
            obj._log_event(self.on if value else self.off)
        setattr(obj, self.attr, value)


class PtyDevice(abc.ABC):
    """Pty lifecycle plus the serving thread; ``start()`` returns the device path."""

    thread_name = "pty-device"
    logger_name = "vbnav.emulator"

    def __init__(self, link: str | Path | None = None, step_s: float = 0.001):
        self.link = Path(link) if link else None
        self.step_s = step_s
        self.lock = threading.RLock()
        self._master = self._slave = -1
        self.slave_path = ""
        self._thread: Optional[threading.Thread] = None
        self._stop = threading.Event()
        self.logger = logging.getLogger(self.logger_name)

    # -- hooks ---------------------------------------------------------------------------
    @abc.abstractmethod
    def _serve_bytes(self, data: bytes) -> None:
        """Handle bytes read from the host (called under ``lock``); answer with ``_write``."""

    @abc.abstractmethod
    def _step(self, now: float, dt: float) -> None:
        """Advance the device by ``dt`` seconds (called under ``lock`` about every ``step_s``)."""

    def _reset_input(self) -> None:
        """Forget partial input: a fresh pty starts a fresh byte stream."""

    # -- lifecycle -------------------------------------------------------------------------
    @property
    def path(self) -> str:
        return str(self.link) if self.link else self.slave_path

    def start(self) -> str:
        self._open_pty()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=self.thread_name, daemon=True)
        self._thread.start()
        return self.path

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._close_pty()

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def unplug(self) -> None:
        """The USB adapter disappears: the pty closes and the device path is gone."""
        with self.lock:
            self._close_pty()
        self.logger.info("unplugged: %s is gone", self.path)

    def replug(self) -> None:
        """The adapter is back (new pty, same stable path); the device state is kept."""
        with self.lock:
            self._open_pty()
        self.logger.info("plugged in again at %s", self.path)

    def host_baud(self) -> int | None:
        """The baud rate the host set on its side of the pty (bit/s); None without a pty."""
        return tty_speed(self._slave) if self._slave >= 0 else None

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line discipline: bytes go through untouched
        self._master, self._slave = master, slave
        self.slave_path = os.ttyname(slave)
        self._reset_input()
        if self.link:
            # replace the symlink atomically: the path never points at nothing while plugged
            tmp = self.link.with_name(self.link.name + ".tmp")
            if tmp.is_symlink() or tmp.exists():
                tmp.unlink()
            tmp.symlink_to(self.slave_path)
            os.replace(tmp, self.link)

    def _close_pty(self) -> None:
        if self.link and self.link.is_symlink():
            self.link.unlink()
        for fd in (self._master, self._slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = -1

    # -- serving -----------------------------------------------------------------------------
    def _write(self, data: bytes) -> None:
        """Send bytes to the host; lost (as on a real wire) when the adapter is unplugged."""
        if self._master < 0:
            return
        try:
            os.write(self._master, data)
        except OSError:
            pass

    def _read_available(self) -> bytes:
        """Bytes the host sent within one step (b"" if none, or while unplugged)."""
        fd = self._master
        if fd < 0:
            time.sleep(self.step_s)
            return b""
        try:
            r, _, _ = select.select([fd], [], [], self.step_s)
            return os.read(fd, 4096) if r else b""
        except (OSError, ValueError):
            return b""

    def _run(self) -> None:
        last = time.monotonic()
        while not self._stop.is_set():
            data = self._read_available()
            now = time.monotonic()
            with self.lock:
                if data:
                    self._serve_bytes(data)
                dt = now - last
                if dt >= self.step_s * 0.5:
                    self._step(now, dt)
                    last = now
