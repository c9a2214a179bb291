"""sd_notify(3) without libsystemd: READY, STOPPING, STATUS and the watchdog pings.

systemd starts a ``Type=notify`` service with ``$NOTIFY_SOCKET`` (a path, or an
abstract socket name starting with ``@``) and, when the unit has ``WatchdogSec=``,
``$WATCHDOG_USEC`` (and ``$WATCHDOG_PID``). A notification is one datagram of
``KEY=VALUE`` lines on an AF_UNIX datagram socket: that is the whole protocol, so
a plain socket does it and no dependency is needed.

The runtime calls :meth:`SystemdNotifier.beat` once per completed loop cycle, on
the loop's thread: a stalled loop stops the pings and systemd restarts the
process after ``WatchdogSec``. ``beat`` is cheap enough for the hot path: one
monotonic clock read per cycle, and every ``watchdog / PINGS_PER_WATCHDOG`` a
non-blocking ``sendto``. A failed send (the socket gone, its queue full) is
counted, never raised: the loop must not stop because systemd did not listen.
"""
from __future__ import annotations

import os
import socket
import time
from typing import Callable, Mapping, Optional

#: pings per watchdog period: a healthy loop pings this often within ``WatchdogSec``, so one late ping (a
#: slow cycle, a busy machine) never lets the watchdog fire; sd_watchdog_enabled(3) asks for at least 2.
PINGS_PER_WATCHDOG = 4


def socket_address(name: str):
    """``$NOTIFY_SOCKET`` as a socket address: ``@name`` is Linux's abstract namespace (a leading NUL)."""
    return "\0" + name[1:] if name.startswith("@") else name


def watchdog_ns(environ: Mapping[str, str], pid: int) -> Optional[int]:
    """The watchdog period systemd asks for, ns, or None (no watchdog, or one meant for another process)."""
    usec = environ.get("WATCHDOG_USEC", "")
    owner = environ.get("WATCHDOG_PID", "")
    if not usec.isdigit() or int(usec) == 0:
        return None
    if owner and (not owner.isdigit() or int(owner) != pid):
        return None
    return int(usec) * 1000


def _status(text: str) -> str:
    """A STATUS line (one line: a newline would start another assignment)."""
    return "\nSTATUS=" + " ".join(text.split()) if text else ""


class SystemdNotifier:
    """Notifications to the service manager on ``address`` (``$NOTIFY_SOCKET``)."""

    def __init__(self, address: str, watchdog_period_ns: Optional[int] = None,
                 now_ns: Callable[[], int] = time.monotonic_ns):
        self.address = address
        self.watchdog_period_ns = watchdog_period_ns
        self.ping_interval_ns = (watchdog_period_ns // PINGS_PER_WATCHDOG) if watchdog_period_ns else None
        self._now_ns = now_ns
        self._next_ping_ns = 0
        self.sent = 0                 # datagrams delivered to the socket
        self.pings = 0                # of which WATCHDOG=1
        self.failures = 0             # sends that failed (counted, never raised)
        self.last_error: Optional[str] = None
        self._sock: Optional[socket.socket] = None      # opened at the first notification
        self._dest = socket_address(address)

    @classmethod
    def from_environ(cls, environ: Optional[Mapping[str, str]] = None,
                     now_ns: Callable[[], int] = time.monotonic_ns) -> Optional["SystemdNotifier"]:
        """A notifier when started by systemd (``$NOTIFY_SOCKET`` set), else None."""
        environ = os.environ if environ is None else environ
        address = environ.get("NOTIFY_SOCKET", "")
        if not address or not (address.startswith("/") or address.startswith("@")):
            return None
        return cls(address, watchdog_ns(environ, os.getpid()), now_ns)

    def notify(self, message: str) -> bool:
        """Send one notification (``KEY=VALUE`` lines); False if it could not be sent."""
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                self._sock.setblocking(False)
            self._sock.sendto(message.encode(), self._dest)
        except OSError as exc:        # BlockingIOError (queue full), FileNotFoundError, ConnectionRefusedError
            self.failures += 1
            self.last_error = f"{self.address}: {exc.strerror or exc}"
            return False
        self.sent += 1
        return True

    def ready(self, status: str = "") -> bool:
        """The service is up: systemd's start job completes and the watchdog starts counting."""
        return self.notify("READY=1" + _status(status))

    def stopping(self, status: str = "") -> bool:
        """The service is shutting down (the wheels are being stopped, devices closed)."""
        return self.notify("STOPPING=1" + _status(status))

    def beat(self) -> None:
        """One completed loop cycle: a ``WATCHDOG=1`` ping if the last one is ``ping_interval`` old."""
        if self.ping_interval_ns is None:
            return
        now = self._now_ns()
        if now < self._next_ping_ns:
            return
        self._next_ping_ns = now + self.ping_interval_ns
        if self.notify("WATCHDOG=1"):
            self.pings += 1

    def close(self) -> None:
        """Close the socket (a later notification opens it again)."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None
