"""Signed commands: a shared secret that closes a loopback robot to other local users.

Without authentication, anything that can open a connection to the robot's
loopback listener (any local user or process) can command it. With
``telemetry.shared_secret_file`` set, the robot accepts a command only if it
carries an HMAC made with the secret in that file, which only the robot's user
(and root) can read: the file must be a regular file with no group or other
permission bits (``chmod 600``), owned by the robot's user.

Wire format: the zenoh *attachment* of the command sample (the JSON payload is
unchanged) is the ASCII text ``vbnav-hmac1 <stamp_ns> <nonce> <mac>``:

- ``stamp_ns``: the sender's ``time.monotonic_ns()`` when it signed;
- ``nonce``: 16 or more hex digits, new for every message;
- ``mac``: hex HMAC-SHA256 with the secret over
  ``b"vbnav-hmac1\\n" + key + b"\\n" + stamp_ns + b"\\n" + nonce + b"\\n" + payload``,
  where ``key`` is the full key expression (``vbnav/<robot>/cmd/<kind>``) and
  ``payload`` the exact payload bytes. The MAC therefore covers the robot, the
  command and every payload field (``seq``, ``stamp_ns`` and ``ack`` included):
  none can be changed, and an estop cannot be replayed as a resume.

Replay: the robot refuses a signed message older than ``window_s`` (5 s) by
its own monotonic clock, and one whose MAC it has already seen within that
window. At most ``REPLAY_CACHE_LIMIT`` MACs are remembered: beyond that (a flood) new commands
are refused until older ones leave the window, except an estop, which is never refused for it.
The secret is allowed only on a robot that is reachable from this
machine alone, so sender and robot read the same monotonic clock (the clock
of the machine, shared by all its processes).
"""
from __future__ import annotations

import collections
import hashlib
import hmac
import os
import secrets
import stat
import threading
import time
from pathlib import Path
from typing import Callable, Optional

SCHEME = b"vbnav-hmac1"
MIN_SECRET_BYTES = 16
REPLAY_WINDOW_S = 5.0
FUTURE_SLACK_NS = 100_000_000     # a stamp may lead the robot's clock by this much (it is the same clock)
REPLAY_CACHE_LIMIT = 200_000      # MACs remembered at once; beyond that new commands (but estop) are refused, never
                                  # forgotten


def read_secret(path: str, check_owner: bool = True) -> bytes:
    """The secret in ``path``; raises ValueError saying what is wrong with the file.

    check_owner: the file must belong to this process's user (the robot); a sender may be another
    user allowed to read it (root).
    """
    p = Path(path).expanduser()
    try:
        st = p.stat()
    except OSError as exc:
        raise ValueError(f"{p}: cannot read the shared secret: {exc.strerror}") from None
    if not stat.S_ISREG(st.st_mode):
        raise ValueError(f"{p}: not a regular file")
    if st.st_mode & 0o077:
        raise ValueError(f"{p}: mode {stat.S_IMODE(st.st_mode):04o} lets other users read the secret; "
                         f"run `chmod 600 {p}` (and make a new secret: the old one may have been read)")
    if check_owner and st.st_uid != os.geteuid():
        raise ValueError(f"{p}: owned by uid {st.st_uid}, not by the robot's user (uid {os.geteuid()})")
    try:
        secret = p.read_bytes().strip()
    except OSError as exc:
        raise ValueError(f"{p}: cannot read the shared secret: {exc.strerror}") from None
    if len(secret) < MIN_SECRET_BYTES:
        raise ValueError(f"{p}: the secret has {len(secret)} bytes, at least {MIN_SECRET_BYTES} are needed "
                         f"(e.g. `head -c 32 /dev/urandom | base64 > {p}`)")
    return secret


def _mac(secret: bytes, key: str, stamp: bytes, nonce: bytes, payload: bytes) -> str:
    msg = b"\n".join((SCHEME, key.encode(), stamp, nonce, payload))
    return hmac.new(secret, msg, hashlib.sha256).hexdigest()


def sign(secret: bytes, key: str, payload: bytes, stamp_ns: Optional[int] = None) -> bytes:
    """The attachment that authenticates ``payload`` put on ``key``."""
    stamp = str(time.monotonic_ns() if stamp_ns is None else stamp_ns).encode()
    nonce = secrets.token_hex(12).encode()
    return b" ".join((SCHEME, stamp, nonce, _mac(secret, key, stamp, nonce, payload).encode()))


class CommandVerifier:
    """Checks the signature of each command sample (zenoh callback threads; thread-safe).

    ``verify(key, payload, attachment)`` returns None when the command may pass, else the reason
    it is refused.
    """

    def __init__(self, secret: bytes, window_s: float = REPLAY_WINDOW_S,
                 now_ns: Callable[[], int] = time.monotonic_ns):
        self._secret = secret
        self._window_ns = int(window_s * 1e9)
        self._now = now_ns
        self._lock = threading.Lock()
        self._seen: collections.OrderedDict[str, int] = collections.OrderedDict()   # mac -> arrival ns

    def verify(self, key: str, payload: bytes, attachment: Optional[bytes]) -> Optional[str]:
        if not attachment:
            return ("unsigned: this robot accepts only commands signed with its shared secret "
                    "(telemetry.shared_secret_file; vbnav send --secret-file)")
        parts = bytes(attachment).split(b" ")
        # A monotonic_ns stamp has at most 20 digits (2^64); a longer one failed int() past Python's 4300-digit
        # limit after a valid MAC, an internal error instead of this refusal
        if (len(parts) != 4 or parts[0] != SCHEME or not parts[1].isdigit() or len(parts[1]) > 20
                or len(parts[2]) < 16):
            return f"malformed signature: expected '{SCHEME.decode()} <stamp_ns> <nonce> <mac>'"
        _, stamp, nonce, mac = parts
        if not hmac.compare_digest(_mac(self._secret, key, stamp, nonce, payload).encode(), mac):
            return "bad signature: not signed with this robot's shared secret (telemetry.shared_secret_file)"
        now = self._now()
        age_ns = now - int(stamp)
        if age_ns > self._window_ns:
            return (f"stale: signed {age_ns * 1e-9:.1f} s ago, more than {self._window_ns * 1e-9:g} s "
                    f"(a replay, or a sender on another machine's clock)")
        if age_ns < -FUTURE_SLACK_NS:
            return f"signed {-age_ns * 1e-9:.1f} s in the future of this machine's monotonic clock"
        tag = mac.decode()
        with self._lock:
            seen = self._seen
            while seen and next(iter(seen.values())) < now - self._window_ns - FUTURE_SLACK_NS:
                seen.popitem(last=False)
            if tag in seen:
                return "replayed: this signed command was already received"
            # An estop is never refused for a full cache (a flood of other signed commands): it is kept
            # beyond the limit, still checked for replay.
            if len(seen) >= REPLAY_CACHE_LIMIT and not key.endswith("/cmd/estop"):
                return (f"more than {REPLAY_CACHE_LIMIT} signed commands within {self._window_ns * 1e-9:g} s; "
                        f"refused until older ones expire")
            seen[tag] = now
        return None


def signing_secret(secret_file: Optional[str], config: Optional[str]) -> Optional[bytes]:
    """A sender's secret: ``secret_file``, else the ``telemetry.shared_secret_file`` of the robot
    configuration ``config``, else None (unsigned). Raises ValueError naming the file."""
    path = secret_file
    if path is None and config:
        from vbnav.control.config import ConfigError, load_config
        try:
            path = load_config(config).telemetry.shared_secret_file
        except ConfigError as exc:
            raise ValueError(str(exc)) from None
    return None if path is None else read_secret(path, check_owner=False)
