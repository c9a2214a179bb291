"""systemd's notify protocol from the control loop: READY=1, WATCHDOG=1 from the loop's heartbeat, STOPPING=1.

Under a unit with ``Type=notify`` and ``WatchdogSec=`` (``vbnav service install``),
systemd passes ``$NOTIFY_SOCKET`` (a unix datagram socket; a leading ``@`` names an
abstract socket) and ``$WATCHDOG_USEC``. The loop thread itself sends ``WATCHDOG=1``
from a cycle observer, at most every half watchdog period: a loop that stalls
(a hung driver call, a deadlock) stops pinging, and systemd kills and restarts the
process after ``WatchdogSec``. No ping ever comes from another thread, so a live
process with a dead loop cannot keep itself alive. Sending a datagram is one
non-blocking ``sendto`` (a few microseconds) a few times a second.

No dependency: the protocol is one datagram per message (sd_notify(3)).
"""
from __future__ import annotations

import os
import socket
import time
from typing import Optional


class SystemdNotifier:
    """Sends notify messages to ``$NOTIFY_SOCKET``; a no-op object when the variable is not set."""

    def __init__(self, address: Optional[str] = None, watchdog_usec: Optional[int] = None):
        address = os.environ.get("NOTIFY_SOCKET") if address is None else address
        if watchdog_usec is None:
            text = os.environ.get("WATCHDOG_USEC", "")
            watchdog_usec = int(text) if text.isdigit() else 0
        self.watchdog_ns = int(watchdog_usec) * 1000
        self._addr = None
        self._sock = None
        if address:
            self._addr = "\0" + address[1:] if address.startswith("@") else address
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.setblocking(False)
        self._next_ping_ns: Optional[int] = None
        self.sent = 0
        self.errors = 0

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def notify(self, message: str) -> bool:
        if self._sock is None:
            return False
        try:
            self._sock.sendto(message.encode(), self._addr)
            self.sent += 1
            return True
        except OSError:       # systemd gone or its queue full: never raise into the loop
            self.errors += 1
            return False

    def heartbeat(self, now_ns: int) -> None:
        """Loop thread, every cycle: WATCHDOG=1 when half the watchdog period has passed since the last one."""
        if not self.watchdog_ns:
            return
        nxt = self._next_ping_ns
        if nxt is not None and now_ns < nxt:
            return
        self._next_ping_ns = now_ns + self.watchdog_ns // 2
        self.notify("WATCHDOG=1")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def attach(runtime, notifier: Optional[SystemdNotifier] = None) -> SystemdNotifier:
    """Hook a notifier into ``runtime``: READY=1 on the first cycle, then the watchdog heartbeat from every
    cycle (``runtime.cycle_observers``, the loop thread). Call ``stopping(notifier)`` when the run ends."""
    n = notifier or SystemdNotifier()
    if not n.enabled:
        return n
    state = {"ready": False}

    def on_cycle(rt, ctx, twist, wheels) -> None:
        if not state["ready"]:
            state["ready"] = True
            n.notify(f"READY=1\nSTATUS=vbnav {rt.controller.name} loop running\nMAINPID={os.getpid()}")
        n.heartbeat(time.monotonic_ns())   # the machine's clock, whatever clock the loop runs on

    runtime.cycle_observers.append(on_cycle)
    return n


def stopping(notifier: SystemdNotifier) -> None:
    notifier.notify("STOPPING=1")
    notifier.close()
