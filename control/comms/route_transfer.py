"""Taught routes over zenoh: each robot serves its routes as queryables; ``vbnav route pull/push`` copy them.

Keys (``<robot>`` is ``robot.name``), all answered by the robot's own session:

- ``vbnav/<robot>/routes`` (query): ``{"schema": "vbnav.routes", "routes": [{"name", "keyframes",
  "complete"}...]}``, the routes in its ``controller.routes_dir``;
- ``vbnav/<robot>/routes/<name>?chunk=K`` (query, anyone who may read telemetry): chunk K of the
  route packed as a tar archive (its manifest and keyframe files, nothing else):
  ``{"schema": "vbnav.route_chunk", "name", "sha256", "size", "chunk", "chunks", "data": base64}``;
- ``vbnav/<robot>/cmd/route/<name>`` (query with a payload, commands: operators only, as ``cmd/**``):
  one chunk of a pushed route, ``{"transfer", "chunk", "chunks", "sha256", "size", "data", "sender"}``,
  answered ``{"ok": true}`` or ``{"ok": false, "reason": "..."}``. With
  ``telemetry.shared_secret_file`` every chunk must carry the command signature as its attachment
  (comms/command_auth.py), exactly like a ``vbnav send`` command.

Chunks of a push stay under the robot's receive limit (network.py ``RX_MESSAGE_LIMIT``). A route is
written beside its destination and swapped in only when complete: the archive is gathered in
``.NAME.push-<transfer>``, its SHA-256 checked against the sender's, unpacked into
``.NAME.partial-<pid>`` (only plain route file names are accepted, no paths), loaded as a route
(``load_route`` must accept it) and then exchanged with the old route (route.py ``_swap_in``). The
same holds for ``pull`` on the receiving machine.
"""
from __future__ import annotations

import base64
import hashlib
import io
import json
import os
import shutil
import tarfile
import threading
import time
import uuid
from pathlib import Path
from typing import Callable, Optional

from vbnav.control.route import (_PARTIAL, _ROUTE_FILE, RouteError, _sibling, _swap_in, check_route_name,
                                 load_route, resolve_route)

PUSH_CHUNK = 36 * 1024          # raw bytes per pushed chunk: ~49 KiB of base64 JSON, under the 64 KiB limit
PULL_CHUNK = 512 * 1024         # raw bytes per pulled chunk (the robot sends; clients take large messages)
PUSH_STALE_S = 120.0            # an unfinished push untouched this long is dropped


def keys(robot: str) -> dict[str, str]:
    p = f"vbnav/{robot}"
    return {"list": f"{p}/routes", "route": f"{p}/routes/*", "push": f"{p}/cmd/route/*"}


# ---- packing -------------------------------------------------------------------------------

def pack_route(path: Path) -> bytes:
    """The route directory as an uncompressed tar (PNGs are compressed already), deterministic."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.PAX_FORMAT) as tar:
        for f in sorted(Path(path).iterdir()):
            if not (f.is_file() and _ROUTE_FILE.match(f.name)) or f.name.endswith(".tmp"):
                continue
            info = tarfile.TarInfo(f.name)
            info.size, info.mode, info.mtime = f.stat().st_size, 0o644, 0
            with open(f, "rb") as fh:
                tar.addfile(info, fh)
    return buf.getvalue()


def unpack_route(data: bytes, dest: Path) -> None:
    """Unpack a ``pack_route`` archive into the new directory ``dest``; refuses anything but route files."""
    dest.mkdir()
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:") as tar:
        for m in tar.getmembers():
            if not m.isfile() or "/" in m.name or not _ROUTE_FILE.match(m.name) or m.name.endswith(".tmp"):
                raise RouteError(f"route archive: unexpected member {m.name[:60]!r}")
            src = tar.extractfile(m)
            with open(dest / m.name, "wb") as out:
                shutil.copyfileobj(src, out)
                out.flush()
                os.fsync(out.fileno())


def install_archive(data: bytes, sha256: str, routes_dir: Path, name: str) -> Path:
    """Check, unpack beside and swap in route ``name``; RouteError says what is wrong (the old route stays)."""
    got = hashlib.sha256(data).hexdigest()
    if got != sha256:
        raise RouteError(f"route {name!r}: checksum mismatch (sha256 {got[:12]}... received, {sha256[:12]}... sent)")
    routes_dir.mkdir(parents=True, exist_ok=True)
    route = resolve_route(routes_dir, name, must_exist=False)
    partial = _sibling(route, _PARTIAL)
    if partial.exists():
        shutil.rmtree(partial)
    try:
        unpack_route(data, partial)
        load_route(partial, load_images=False)        # a complete, loadable route, or nothing changes
    except Exception as exc:
        shutil.rmtree(partial, ignore_errors=True)
        raise RouteError(f"route {name!r}: not a usable route: {exc}") from None
    if route.exists():
        _swap_in(partial, route)
    else:
        os.rename(partial, route)
    return route


def list_routes(routes_dir: Path) -> list[dict]:
    out = []
    if not routes_dir.is_dir():
        return out
    for d in sorted(routes_dir.iterdir()):
        if d.name.startswith(".") or not (d / "manifest.json").is_file():
            continue
        try:
            m = json.loads((d / "manifest.json").read_text())
            out.append({"name": d.name, "keyframes": len(m.get("keyframes", [])), "complete": bool(m.get("complete"))})
        except (OSError, ValueError):
            out.append({"name": d.name, "keyframes": None, "complete": False})
    return out


# ---- the robot's side ----------------------------------------------------------------------

class RouteServer:
    """Queryables of one robot's routes (zenoh threads). ``on_event(kind, **fields)`` reports pushes."""

    def __init__(self, session, robot: str, routes_dir: Path, verify=None,
                 on_event: Optional[Callable[..., None]] = None):
        self.robot, self.routes_dir = robot, Path(routes_dir)
        self._verify, self._event = verify, on_event or (lambda kind, **f: None)
        self._lock = threading.Lock()
        self._packed: dict[str, tuple[float, bytes, str]] = {}    # name -> (manifest mtime, archive, sha256)
        self._pushes: dict[str, dict] = {}                         # transfer -> state
        k = keys(robot)
        self._prefix_route, self._prefix_push = k["route"][:-1], k["push"][:-1]
        self._q = [session.declare_queryable(k["list"], self._on_list),
                   session.declare_queryable(k["route"], self._on_pull),
                   session.declare_queryable(k["push"], self._on_push)]

    def close(self) -> None:
        for q in self._q:
            try:
                q.undeclare()
            except Exception:
                pass

    @staticmethod
    def _reply(query, body: dict) -> None:
        try:
            query.reply(query.key_expr, json.dumps(body, separators=(",", ":")))
        except Exception:
            pass

    def _on_list(self, query) -> None:
        self._reply(query, {"schema": "vbnav.routes", "robot": self.robot, "routes": list_routes(self.routes_dir)})

    def _archive(self, name: str) -> tuple[bytes, str]:
        route = resolve_route(self.routes_dir, name, must_exist=True)
        mtime = (route / "manifest.json").stat().st_mtime
        with self._lock:
            cached = self._packed.get(name)
            if cached is None or cached[0] != mtime:
                data = pack_route(route)
                cached = self._packed[name] = (mtime, data, hashlib.sha256(data).hexdigest())
        return cached[1], cached[2]

    def _on_pull(self, query) -> None:
        name = str(query.key_expr)[len(self._prefix_route):]
        try:
            params = dict(p.split("=", 1) for p in str(query.parameters).split(";") if "=" in p)
            chunk = int(params.get("chunk", "0"))
            data, sha = self._archive(name)
        except (RouteError, ValueError, OSError) as exc:
            self._reply(query, {"schema": "vbnav.route_chunk", "error": str(exc)})
            return
        chunks = max(1, -(-len(data) // PULL_CHUNK))
        if not 0 <= chunk < chunks:
            self._reply(query, {"schema": "vbnav.route_chunk", "error": f"chunk {chunk} outside 0..{chunks - 1}"})
            return
        part = data[chunk * PULL_CHUNK:(chunk + 1) * PULL_CHUNK]
        self._reply(query, {"schema": "vbnav.route_chunk", "name": name, "sha256": sha, "size": len(data),
                            "chunk": chunk, "chunks": chunks, "data": base64.b64encode(part).decode()})

    def _on_push(self, query) -> None:
        key = str(query.key_expr)
        name = key[len(self._prefix_push):]
        payload = query.payload.to_bytes() if query.payload is not None else b""
        try:
            check_route_name(name)
            if self._verify is not None:
                att = query.attachment
                refused = self._verify(key, payload, None if att is None else att.to_bytes())
                if refused:
                    raise RouteError(refused)
            body = json.loads(payload)
            done = self._take_chunk(name, body)
        except (RouteError, ValueError, KeyError, TypeError, OSError) as exc:
            self._event("command_rejected", command="route_push", reason=f"route {name[:130]!r}: {exc}")
            self._reply(query, {"ok": False, "reason": str(exc)})
            return
        if done is not None:
            self._event("route_received", route=name, sender=str(body.get("sender", ""))[:64],
                        sha256=body["sha256"], bytes=body["size"])
        self._reply(query, {"ok": True, "complete": done is not None})

    def _take_chunk(self, name: str, body: dict) -> Optional[Path]:
        transfer, chunk, chunks = str(body["transfer"]), int(body["chunk"]), int(body["chunks"])
        sha, size = str(body["sha256"]), int(body["size"])
        if not (0 < len(transfer) <= 64 and transfer.isalnum()) or not 0 <= chunk < chunks <= 100_000:
            raise ValueError("bad transfer id or chunk numbers")
        data = base64.b64decode(body["data"], validate=True)
        now = time.monotonic()
        with self._lock:
            for t in [t for t, s in self._pushes.items() if now - s["touched"] > PUSH_STALE_S]:
                self._drop(t)
            st = self._pushes.get(transfer)
            if st is None:
                if chunk != 0:
                    raise ValueError(f"transfer {transfer}: chunk {chunk} before chunk 0")
                self.routes_dir.mkdir(parents=True, exist_ok=True)
                part = resolve_route(self.routes_dir, name, must_exist=False).with_name(f".{name}.push-{transfer}")
                st = self._pushes[transfer] = {"name": name, "next": 0, "chunks": chunks, "sha256": sha,
                                               "size": size, "path": part, "file": open(part, "wb"), "touched": now}
            if (st["name"], st["chunks"], st["sha256"], st["size"]) != (name, chunks, sha, size):
                raise ValueError(f"transfer {transfer}: chunk {chunk} does not belong to it")
            if chunk != st["next"]:
                raise ValueError(f"transfer {transfer}: chunk {chunk} arrived, expected {st['next']}")
            st["file"].write(data)
            st["next"], st["touched"] = chunk + 1, now
            if st["next"] < chunks:
                return None
            st["file"].close()
            archive = st["path"].read_bytes()
            self._drop(transfer)
        if len(archive) != size:
            raise RouteError(f"route {name!r}: {len(archive)} bytes received, {size} sent")
        return install_archive(archive, sha, self.routes_dir, name)

    def _drop(self, transfer: str) -> None:
        st = self._pushes.pop(transfer, None)
        if st is not None:
            st["file"].close()
            try:
                os.unlink(st["path"])
            except OSError:
                pass


# ---- the client's side (vbnav route pull/push) -----------------------------------------------

def _get_one(session, selector: str, timeout_s: float, payload: Optional[bytes] = None,
             attachment: Optional[bytes] = None) -> dict:
    kw = {"timeout": timeout_s}
    if payload is not None:
        kw["payload"] = payload
    if attachment is not None:
        kw["attachment"] = attachment
    for reply in session.get(selector, **kw):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    raise ConnectionError(f"no answer on {selector.split('?')[0]} within {timeout_s:g} s (is the robot there, "
                          f"and are you allowed to ask it?)")


def fetch_route_list(session, robot: str, timeout_s: float = 5.0) -> list[dict]:
    return _get_one(session, keys(robot)["list"], timeout_s)["routes"]


def pull_route(session, robot: str, name: str, routes_dir: Path, timeout_s: float = 10.0) -> tuple[Path, str]:
    """Copy route ``name`` from ``robot`` into ``routes_dir`` (checked, written beside, swapped in)."""
    check_route_name(name)
    parts, sha, chunks, k = [], None, 1, 0
    while k < chunks:
        msg = _get_one(session, f"vbnav/{robot}/routes/{name}?chunk={k}", timeout_s)
        if "error" in msg:
            raise RouteError(f"robot {robot}: {msg['error']}")
        if sha is not None and (msg["sha256"] != sha or msg["chunks"] != chunks):
            raise RouteError(f"route {name!r} changed on robot {robot} during the copy; pull it again")
        sha, chunks = msg["sha256"], msg["chunks"]
        parts.append(base64.b64decode(msg["data"]))
        k += 1
    return install_archive(b"".join(parts), sha, Path(routes_dir), name), sha


def push_route(session, robot: str, name: str, source: Path, secret: Optional[bytes] = None,
               sender: str = "vbnav-route", timeout_s: float = 10.0) -> str:
    """Copy the local route directory ``source`` to ``robot`` as ``name``; returns the archive's sha256.
    Raises RouteError with the robot's reason when it refuses."""
    check_route_name(name)
    load_route(source, load_images=False)        # only a usable route leaves this machine
    data = pack_route(source)
    sha = hashlib.sha256(data).hexdigest()
    chunks = max(1, -(-len(data) // PUSH_CHUNK))
    transfer = uuid.uuid4().hex
    key = f"vbnav/{robot}/cmd/route/{name}"
    for k in range(chunks):
        payload = json.dumps({"transfer": transfer, "chunk": k, "chunks": chunks, "sha256": sha, "size": len(data),
                              "sender": sender,
                              "data": base64.b64encode(data[k * PUSH_CHUNK:(k + 1) * PUSH_CHUNK]).decode()},
                             separators=(",", ":")).encode()
        attachment = None
        if secret is not None:
            from vbnav.control.comms.command_auth import sign
            attachment = sign(secret, key, payload)
        answer = _get_one(session, key, timeout_s, payload=payload, attachment=attachment)
        if not answer.get("ok"):
            raise RouteError(f"robot {robot} refused the route: {answer.get('reason')}")
    return sha
