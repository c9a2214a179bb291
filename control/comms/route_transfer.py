"""Taught routes over zenoh: every robot serves its ``controller.routes_dir``; ``vbnav route pull|push`` copy.

Keys (``<robot>`` is ``robot.name``; the robot declares one queryable on ``vbnav/<robot>/routes/**``):

- ``.../routes/list``                               -> ``{"schema": "vbnav.routes", "routes": [...]}``
- ``.../routes/files/<name>``                       -> ``{"schema": "vbnav.route.files", "name", "files":
  [{"name", "size", "sha256"}]}``: the manifest and every file its keyframes list
- ``.../routes/chunk/<name>/<file>/<offset>``       -> the raw bytes of that file from ``offset``, at most
  PULL_CHUNK of them
- ``.../routes/push/<name>/<id>/begin``             payload ``{"bytes": total, "overwrite": bool}``
- ``.../routes/push/<name>/<id>/chunk/<file>/<offset>`` payload raw bytes (at most PUSH_CHUNK)
- ``.../routes/push/<name>/<id>/file/<file>``       payload ``{"size", "sha256"}``: that file is complete
- ``.../routes/push/<name>/<id>/commit``            -> ``{"ok": true, "keyframes": n}``

Reads (list, files, chunk) follow the rule of telemetry reads: whoever the robot admits. A push is a write
to the robot and follows the rule of commands: network.py's access control lets only ``telemetry.operators``
query ``routes/push/**`` (exactly as it limits ``cmd/**``; behind a trusted router, the router's access
control does, docs/fleet.md), and a robot with ``telemetry.shared_secret_file`` accepts only push queries
signed with it (comms/command_auth.py: the signature covers the full key and the payload, so the file,
the offset and the bytes can be neither altered nor replayed).

Integrity: each file's size and SHA-256 travel beside it; the receiver writes into a hidden sibling of the
destination (``route.staging_dir``), checks every file's size and digest, loads the route
(``route.load_route`` validates the manifest and every keyframe file) and only then puts it in place
(``route.install_route_dir``: a rename, or with overwrite an atomic swap). Any failure leaves the
destination as it was and deletes the staging directory.

Pushed chunks are small because the robot's session refuses messages above ``network.RX_MESSAGE_LIMIT``;
the robot handles route queries on its own thread, one at a time, never on zenoh's threads.
"""
from __future__ import annotations

import hashlib
import json
import os
import queue
import re
import shutil
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

from vbnav.control.route import (MANIFEST, Route, RouteError, check_route_name, describe_route_error,
                                 install_route_dir, load_route, resolve_route, staging_dir)
from vbnav.drivers.atomic_file import fsync_file
from vbnav.drivers.plain_values import load_json

PUSH_CHUNK = 32 * 1024          # bytes per pushed chunk: well under the robot's 64 KiB receive limit
PULL_CHUNK = 256 * 1024         # bytes per pulled chunk (the reply leaves the robot: no such limit)
MAX_PUSH_BYTES = 2 << 30        # a pushed route larger than this is refused at begin
PUSH_IDLE_S = 60.0              # a push that sent nothing for this long is abandoned (staging deleted)
MAX_PUSHES = 4                  # pushes in progress at once on one robot
QUEUE_LIMIT = 64                # route queries waiting for the robot's route thread; beyond: "busy"
SCHEMA_VERSION = 1
_FILE = re.compile(r"^(manifest\.json|kf_\d{5}\.(png|npz))$")
_ID = re.compile(r"^[A-Za-z0-9]{8,64}$")
_SHA = re.compile(r"^[0-9a-f]{64}$")

VerifyFn = Callable[[str, bytes, Optional[bytes]], Optional[str]]


class TransferError(Exception):
    """A route transfer was refused or failed; the message says why (the robot's words when it refused)."""


class NoAnswer(TransferError):
    """Nobody answered the query: no such robot there, or its access control dropped the query unread."""


class NoRobot(NoAnswer):
    """No robot of that name answers for its route list (every robot serving routes does, to everyone)."""


def keys(robot: str) -> dict[str, str]:
    p = f"vbnav/{robot}/routes"
    return {"all": f"{p}/**", "list": f"{p}/list", "files": f"{p}/files", "chunk": f"{p}/chunk", "push": f"{p}/push"}


def _sha256_file(path: Path) -> tuple[int, str]:
    h, size = hashlib.sha256(), 0
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            h.update(block)
            size += len(block)
    return size, h.hexdigest()


def route_files(path) -> list[dict]:
    """The files that make route ``path``: the manifest and every file its keyframes list, each with its
    size and SHA-256. RouteError if the manifest is not a route's or lists a name that is no route file."""
    path = Path(path)
    mpath = path / MANIFEST
    try:
        m = load_json(mpath.read_bytes())       # a key given twice: refused, as every route loader does
        names = [MANIFEST] + [str(kf[k]) for kf in m["keyframes"] for k in ("image", "landmarks")]
    except FileNotFoundError:
        raise RouteError(f"{mpath}: missing (not a vbnav route directory?)") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise RouteError(f"{mpath}: not a route manifest ({type(exc).__name__}: {exc})") from None
    out = []
    for n in names:
        if not _FILE.fullmatch(n):
            raise RouteError(f"{mpath}: lists {n!r}, which is not a route file name")
        try:
            size, digest = _sha256_file(path / n)
        except OSError as exc:
            raise RouteError(f"{path / n}: {exc.strerror or exc}") from None
        out.append({"name": n, "size": size, "sha256": digest})
    return out


# ---- the robot's side ----------------------------------------------------------------------------------
@dataclass
class _Incoming:
    """A push in progress: where it is staged and which files are complete and verified."""

    name: str
    dest: Path
    staging: Path
    overwrite: bool
    limit: int                                        # bytes announced at begin
    written: int = 0
    sizes: dict = field(default_factory=dict)        # file -> bytes written so far
    verified: set = field(default_factory=set)
    last_s: float = 0.0


class RouteServer:
    """Serves the routes under ``root`` on ``vbnav/<robot>/routes/**`` and takes pushes into it.

    verify: the shared-secret check of command samples (link.py ``_verifier``), applied to push queries.
    busy: the reason route NAME may not be replaced now (it is being taught), or None.
    refusal: why this robot's repeat refuses a pushed route (default: whatever the configuration,
    ``Route.repeat_refusal``; the robot's link adds its camera and mount, ``config_repeat_refusal``), or None.
    """

    def __init__(self, session, robot: str, root, verify: Optional[VerifyFn] = None,
                 busy: Callable[[str], Optional[str]] = lambda name: None,
                 now_s: Callable[[], float] = time.monotonic,
                 refusal: Callable[[Route], Optional[str]] = lambda route: route.repeat_refusal()):
        self.root = Path(root)
        self._busy = busy
        self._refusal = refusal
        self._prefix = f"vbnav/{robot}/routes/"
        self._verify = verify
        self._now = now_s
        self._pushes: dict[str, _Incoming] = {}
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._serve, name="vbnav-routes", daemon=True)
        self._thread.start()
        self._queryable = session.declare_queryable(keys(robot)["all"], self._on_query)

    def _on_query(self, query) -> None:   # zenoh thread: hand over, never do file work here
        if self._q.qsize() >= QUEUE_LIMIT:
            _reply_error(query, "busy: too many route queries waiting; try again")
            return
        self._q.put(query)

    def _serve(self) -> None:
        while True:
            query = self._q.get()
            if query is None:
                return
            try:
                self._handle(query)
            except Exception as exc:   # never let one query end the route thread
                _reply_error(query, f"internal error: {type(exc).__name__}: {exc}")
            del query                  # the query is answered (finalised) once dropped

    def _handle(self, query) -> None:
        key = str(query.key_expr)
        parts = key[len(self._prefix):].split("/")
        name = parts[1] if len(parts) > 1 else ""
        try:
            if parts == ["list"]:
                _reply_json(query, key, {"schema": "vbnav.routes", "version": SCHEMA_VERSION, "routes": self._list()})
            elif parts[0] == "files" and len(parts) == 2:
                files = route_files(resolve_route(self.root, name, must_exist=True))
                _reply_json(query, key, {"schema": "vbnav.route.files", "version": SCHEMA_VERSION, "name": name,
                                         "files": files})
            elif parts[0] == "chunk" and len(parts) == 4:
                query.reply(key, self._chunk(name, parts[2], parts[3]))
            elif parts[0] == "push" and len(parts) >= 4:
                payload = query.payload.to_bytes() if query.payload is not None else b""
                if self._verify is not None:
                    att = query.attachment
                    refused = self._verify(key, payload, None if att is None else att.to_bytes())
                    if refused:
                        raise TransferError(f"push refused: {refused}")
                _reply_json(query, key, self._push(name, parts[2], parts[3], parts[4:], payload))
            else:
                raise TransferError("unknown route query; expected list, files/NAME, chunk/NAME/FILE/OFFSET "
                                    "or push/NAME/ID/...")
        except (RouteError, TransferError, OSError, ValueError) as exc:
            # Errors about network input name the route, never the robot's directories.
            routed = name and isinstance(exc, (RouteError, OSError))
            text = describe_route_error(exc, self.root / name, name) if routed else str(exc)
            _reply_error(query, text.replace(str(self.root), "routes_dir"))

    def _list(self) -> list[dict]:
        from vbnav.control.route_tools import list_routes
        if not self.root.is_dir():
            return []
        return [{"name": r.name, "keyframes": r.keyframes, "length_m": round(r.length_m, 3), "complete": r.complete,
                 "created": r.created, "robot": r.robot, "error": r.error} for r in list_routes(self.root)]

    def _chunk(self, name: str, file: str, offset: str) -> bytes:
        if not _FILE.fullmatch(file) or not offset.isdigit():
            raise TransferError("chunk: expected a route file name and a byte offset")
        path = resolve_route(self.root, name, must_exist=True) / file
        with open(path, "rb") as f:
            f.seek(int(offset))
            return f.read(PULL_CHUNK)

    # -- pushes --------------------------------------------------------------------------------------
    def _push(self, name: str, tid: str, op: str, rest: list[str], payload: bytes) -> dict:
        check_route_name(name)
        if not _ID.fullmatch(tid):
            raise TransferError("push: the transfer id must be 8-64 letters or digits")
        self._abandon_idle()
        if op == "begin" and not rest:
            return self._begin(name, tid, payload)
        inc = self._pushes.get(tid)
        if inc is None or inc.name != name:
            raise TransferError(f"push of route {name!r}: no transfer {tid} in progress (abandoned after "
                                f"{PUSH_IDLE_S:g} s idle, or never begun)")
        inc.last_s = self._now()
        try:
            if op == "chunk" and len(rest) == 2:
                return self._write_chunk(inc, rest[0], rest[1], payload)
            if op == "file" and len(rest) == 1:
                return self._file_done(inc, rest[0], payload)
            if op == "commit" and not rest:
                return self._commit(tid, inc)
            raise TransferError("push: expected begin, chunk/FILE/OFFSET, file/FILE or commit")
        except Exception:
            self._drop(tid)
            raise

    def _begin(self, name: str, tid: str, payload: bytes) -> dict:
        spec = _json_object(payload, "push begin")
        total, overwrite = spec.get("bytes"), spec.get("overwrite", False)
        if not isinstance(total, int) or isinstance(total, bool) or not 0 < total <= MAX_PUSH_BYTES:
            raise TransferError(f"push begin: 'bytes' must be an integer in 1..{MAX_PUSH_BYTES}")
        if not isinstance(overwrite, bool):
            raise TransferError("push begin: 'overwrite' must be true or false")
        dest = resolve_route(self.root, name, must_exist=False)
        if dest.exists() and not overwrite:
            raise TransferError(f"route {name!r} exists on this robot (push --overwrite replaces it)")
        reason = self._busy(name)
        if reason:
            raise TransferError(reason)
        if any(p.name == name for p in self._pushes.values()):
            raise TransferError(f"route {name!r}: another push of it is in progress")
        if len(self._pushes) >= MAX_PUSHES:
            raise TransferError(f"{MAX_PUSHES} pushes are in progress; try again later")
        self.root.mkdir(parents=True, exist_ok=True)
        free = shutil.disk_usage(self.root).free
        if total > free:
            raise TransferError(f"push of {total} bytes: only {free} bytes free on the robot")
        staging = staging_dir(dest, tid)
        staging.mkdir()
        self._pushes[tid] = _Incoming(name, dest, staging, overwrite, total, last_s=self._now())
        return {"ok": True, "chunk": PUSH_CHUNK}

    def _write_chunk(self, inc: _Incoming, file: str, offset: str, data: bytes) -> dict:
        if not _FILE.fullmatch(file) or not offset.isdigit():
            raise TransferError("push chunk: expected a route file name and a byte offset")
        have, at = inc.sizes.get(file, 0), int(offset)
        if file in inc.verified or at != have:
            raise TransferError(f"push chunk {file}@{at}: expected offset {have} (chunks come in order)")
        if inc.written + len(data) > inc.limit:
            raise TransferError(f"push: more than the {inc.limit} bytes announced at begin")
        with open(inc.staging / file, "ab") as f:
            f.write(data)
        inc.sizes[file] = have + len(data)
        inc.written += len(data)
        return {"ok": True, "size": inc.sizes[file]}

    def _file_done(self, inc: _Incoming, file: str, payload: bytes) -> dict:
        spec = _json_object(payload, "push file")
        if not _FILE.fullmatch(file) or not _SHA.fullmatch(str(spec.get("sha256", ""))):
            raise TransferError("push file: expected a route file name and its 'sha256' (64 hex digits)")
        path = inc.staging / file
        if not path.exists():
            path.touch()      # an empty file has no chunk
        size, digest = _sha256_file(path)
        if size != spec.get("size") or digest != spec["sha256"]:
            raise TransferError(f"push: {file} arrived damaged ({size} bytes, sha256 {digest[:12]}..., sender "
                                f"says {spec.get('size')} bytes, {spec['sha256'][:12]}...)")
        fsync_file(path)        # on disk before the commit renames the staging folder into the routes
        inc.verified.add(file)
        return {"ok": True}

    def _commit(self, tid: str, inc: _Incoming) -> dict:
        listed = {f["name"] for f in route_files(inc.staging)} if (inc.staging / MANIFEST).exists() else {MANIFEST}
        missing = sorted(listed - inc.verified)
        extra = sorted(set(inc.sizes) - listed)
        if missing or extra:
            raise TransferError(f"push commit: {'missing ' + ', '.join(missing[:3]) if missing else ''}"
                                f"{'; not in the manifest: ' + ', '.join(extra[:3]) if extra else ''}")
        route = load_route(inc.staging, load_images=False)
        why = self._refusal(route)          # it would replace a route that can be repeated by one that cannot
        if why:
            raise TransferError(f"push commit: route {inc.name!r}: this robot's repeat refuses it: {why}")
        reason = self._busy(inc.name)      # teaching may have begun since the push did
        if reason:
            raise TransferError(reason)
        install_route_dir(inc.staging, inc.dest, inc.overwrite)
        del self._pushes[tid]
        return {"ok": True, "keyframes": len(route), "complete": route.complete}

    def _drop(self, tid: str) -> None:
        inc = self._pushes.pop(tid, None)
        if inc is not None:
            shutil.rmtree(inc.staging, ignore_errors=True)

    def _abandon_idle(self) -> None:
        now = self._now()
        for tid in [t for t, p in self._pushes.items() if now - p.last_s > PUSH_IDLE_S]:
            self._drop(tid)

    def close(self) -> None:
        """Stop serving; pushes in progress are abandoned (their staging directories deleted)."""
        try:
            self._queryable.undeclare()
        except Exception:
            pass
        self._q.put(None)
        self._thread.join(10.0)
        for tid in list(self._pushes):
            self._drop(tid)


def _json_object(payload: bytes, what: str) -> dict:
    try:
        obj = json.loads(payload or b"{}")
    except ValueError as exc:
        raise TransferError(f"{what}: payload is not JSON ({exc})") from None
    if not isinstance(obj, dict):
        raise TransferError(f"{what}: expected a JSON object")
    return obj


def _reply_json(query, key: str, obj: dict) -> None:
    query.reply(key, json.dumps(obj, separators=(",", ":")))


def _reply_error(query, text: str) -> None:
    try:
        query.reply_err(json.dumps({"error": text}))
    except Exception:
        pass


# ---- the client's side -------------------------------------------------------------------------------
def _ask(session, key: str, timeout_s: float, payload: Optional[bytes] = None,
         attachment: Optional[bytes] = None) -> bytes:
    """The single answer to a query; TransferError with the robot's reason, NoAnswer when nobody replied."""
    kw = {} if payload is None else {"payload": payload}
    if attachment is not None:
        kw["attachment"] = attachment
    for reply in session.get(key, timeout=timeout_s, **kw):
        if reply.ok is not None:
            return reply.ok.payload.to_bytes()
        try:
            text = json.loads(reply.err.payload.to_bytes()).get("error", "?")
        except (ValueError, AttributeError):
            text = reply.err.payload.to_string()
        raise TransferError(text)
    raise NoAnswer(f"no answer on {key} within {timeout_s:g} s")


def list_remote(session, robot: str, timeout_s: float = 5.0) -> list[dict]:
    """The routes robot ``robot`` serves; NoAnswer when no robot of that name answers."""
    try:
        return json.loads(_ask(session, keys(robot)["list"], timeout_s))["routes"]
    except NoAnswer:
        raise NoRobot(f"no robot named {robot} answers on {keys(robot)['list']} (is it running, with telemetry "
                       f"on, connected to this router?)") from None


def pull(session, robot: str, name: str, dest_root, overwrite: bool = False, timeout_s: float = 5.0,
         progress: Optional[Callable[[int, int], None]] = None) -> Path:
    """Copy route ``name`` of robot ``robot`` to ``dest_root/name``; returns that path.

    Staged beside the destination, every file checked against its size and SHA-256, the route loaded,
    then put in place (replacing an existing route only with ``overwrite``).
    """
    check_route_name(name)
    dest = resolve_route(Path(dest_root), name, must_exist=False)
    if dest.exists() and not overwrite:
        raise RouteError(f"{dest}: exists (replace it with --overwrite)")
    listing = json.loads(_ask(session, f"{keys(robot)['files']}/{name}", timeout_s))
    files = listing["files"]
    total, done = sum(f["size"] for f in files), 0
    dest.parent.mkdir(parents=True, exist_ok=True)
    staging = staging_dir(dest, uuid.uuid4().hex[:12])
    staging.mkdir()
    try:
        for f in files:
            if not _FILE.fullmatch(str(f["name"])):
                raise TransferError(f"robot {robot} lists {f['name']!r} in route {name!r}: not a route file name")
            h = hashlib.sha256()
            with open(staging / f["name"], "wb") as out:
                while out.tell() < f["size"]:
                    data = _ask(session, f"{keys(robot)['chunk']}/{name}/{f['name']}/{out.tell()}", timeout_s)
                    if not data:
                        break
                    out.write(data)
                    h.update(data)
                    done += len(data)
                    if progress is not None:
                        progress(done, total)
                size = out.tell()
                out.flush()
                os.fsync(out.fileno())     # the staging folder is renamed into place: its files must be on disk
            if size != f["size"] or h.hexdigest() != f["sha256"]:
                raise TransferError(f"{f['name']}: received {size} bytes with sha256 {h.hexdigest()[:12]}..., robot "
                                    f"{robot} listed {f['size']} bytes, {f['sha256'][:12]}... (did the route change "
                                    f"on the robot meanwhile? pull again)")
        refusal = load_route(staging, load_images=False).repeat_refusal()
        if refusal:
            raise TransferError(f"robot {robot}'s route {name!r}: a repeat refuses it: {refusal}; not pulling it")
        install_route_dir(staging, dest, overwrite)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return dest


def push(session, robot: str, path, name: Optional[str] = None, overwrite: bool = False,
         secret: Optional[bytes] = None, timeout_s: float = 5.0,
         progress: Optional[Callable[[int, int], None]] = None) -> dict:
    """Copy the local route ``path`` into robot ``robot``'s routes as ``name`` (default: the folder's name).

    The route is loaded and checked here first; the robot stages, verifies and swaps it in (commit).
    secret: sign every query with the robot's shared secret (``telemetry.shared_secret_file``).
    Returns the robot's commit answer (``keyframes``, ``complete``).
    """
    from vbnav.control.route_tools import check
    path = Path(path)
    name = check_route_name(name or path.name)
    report = check(path)
    if not report.intact:
        raise RouteError(f"{path}: damaged ({'; '.join(report.problems[:2])}); not pushing it")
    if report.repeat_refusal:
        raise RouteError(f"{path}: vbnav repeat refuses it: {report.repeat_refusal}; not pushing it")
    files = route_files(path)
    base = f"{keys(robot)['push']}/{name}/{uuid.uuid4().hex}"

    def ask(key: str, payload: bytes) -> dict:
        att = None
        if secret is not None:
            from vbnav.control.comms.command_auth import sign
            att = sign(secret, key, payload)
        try:
            return json.loads(_ask(session, key, timeout_s, payload=payload, attachment=att))
        except NoAnswer:
            raise NoAnswer(f"robot {robot} did not answer the push: it refuses writes from this client (only "
                           f"telemetry.operators may push), or it went away") from None

    total, done = sum(f["size"] for f in files), 0
    list_remote(session, robot, timeout_s)          # a robot that is not there is told apart from a refusal
    ask(f"{base}/begin", json.dumps({"bytes": max(1, total), "overwrite": overwrite}).encode())
    for f in files:
        with open(path / f["name"], "rb") as src:
            offset = 0
            while block := src.read(PUSH_CHUNK):
                ask(f"{base}/chunk/{f['name']}/{offset}", block)
                offset += len(block)
                done += len(block)
                if progress is not None:
                    progress(done, total)
        ask(f"{base}/file/{f['name']}", json.dumps({"size": f["size"], "sha256": f["sha256"]}).encode())
    return ask(f"{base}/commit", b"{}")
