"""Files written whole or not at all.

Everything vbnav records (routes, maps, calibrations, trajectories, metrics, plots, service files)
goes through here: the data is written to a temporary file in the target's folder, flushed and
fsynced, renamed over the target (``os.replace`` is atomic within a file system), and the folder is
fsynced so the rename itself survives a power cut. A crash, a full disk or a Ctrl-C at any point
leaves either the old file or the new one, never half of one; the temporary file is removed on
failure. Files that belong together (a calibration's, a service's) are written as one set
(``write_atomic_set``): all to temporary files first, then renamed. Temporary names are
``.<name>.<random>.tmp[<suffix>]`` beside the target, so a reader that lists ``*.tmp`` (``vbnav route
check``) finds what an interrupted writer left.
"""
from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator, Optional


def write_atomic(path, data: str | bytes, mode: Optional[int] = None) -> Path:
    """Write ``data`` (text as UTF-8, or bytes) to ``path`` atomically; ``mode``: permission bits of the
    new file (default: those of the file it replaces, else what ``open`` would give under the umask)."""
    p = Path(path)
    tmp = _write_temporary(p, data, mode)
    try:
        replace_durably(tmp, p)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return p


def write_atomic_set(files: dict, check: Optional[Callable[[dict], None]] = None,
                     mode: Optional[int] = None) -> list[Path]:
    """Write several files that belong together (a stereo calibration's) as one set: every file is written
    and fsynced under a temporary name first, so a failure (a full disk, an exception) before the renames
    replaces none of them; then each is renamed into place and the folders fsynced. What remains: a crash
    during the renames themselves (microseconds, no writing) can leave some renamed and some not.

    ``check``, given {target: temporary file} (each temporary ends in its target's suffix, for loaders that
    go by it), may raise to refuse the set before anything is replaced: read the files back with their
    loaders, so nothing is written that cannot be loaded. ``mode``: as ``write_atomic``'s, for every file."""
    done: dict[Path, Path] = {}
    try:
        for path, data in files.items():
            done[Path(path)] = _write_temporary(Path(path), data, mode, ".tmp" + Path(path).suffix)
        if check is not None:
            check(dict(done))
        for path, tmp in done.items():
            os.replace(tmp, path)
    except BaseException:
        for tmp in done.values():
            tmp.unlink(missing_ok=True)
        raise
    for folder in {_folder(p) for p in done}:
        fsync_folder(folder)
    return list(done)


def _write_temporary(p: Path, data: str | bytes, mode: Optional[int], suffix: str = ".tmp") -> Path:
    """``data`` in a new fsynced file ``.<name>.<random><suffix>`` beside ``p``, with ``p``'s permission bits."""
    raw = data.encode() if isinstance(data, str) else bytes(data)
    fd, tmp = _mkstemp(p, suffix)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(raw)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, _mode_for(p) if mode is None else mode)
    except BaseException as exc:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(exc, OSError) and exc.errno is not None and exc.filename is None:   # a full disk: name it
            raise OSError(exc.errno, exc.strerror, str(p)) from exc
        raise
    return Path(tmp)


@contextmanager
def atomic_output(path, suffix: Optional[str] = None) -> Iterator[Path]:
    """For writers that want a file name (``cv2.imwrite``, matplotlib's ``savefig``): yields a temporary
    path ending in ``suffix`` (default: the target's own, so format-by-extension writers work), renamed
    over ``path`` when the block ends without an exception, removed otherwise."""
    p = Path(path)
    fd, tmp = _mkstemp(p, ".tmp" + (p.suffix if suffix is None else suffix))
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        with open(tmp_path, "rb") as f:
            os.fsync(f.fileno())
        os.chmod(tmp_path, _mode_for(p))
        replace_durably(tmp_path, p)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


def _mkstemp(p: Path, suffix: str) -> tuple[int, str]:
    """A new temporary file beside ``p``; an OSError (a folder that is not writable, or gone) names ``p``, the
    file the user asked for, not the temporary name nobody gave."""
    try:
        return tempfile.mkstemp(dir=_folder(p), prefix=f".{p.name}.", suffix=suffix)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror, str(p)) from exc


def replace_durably(src, dst) -> None:
    """Rename the complete, fsynced file ``src`` over ``dst`` (same folder) and fsync the folder, so the
    rename survives a power cut: the last step of every writer here, and of those that write a file in
    pieces under a temporary name (the MCAP recorder's ``PATH.part``)."""
    os.replace(src, dst)
    fsync_folder(_folder(Path(dst)))


def fsync_file(path) -> None:
    """Make a file written in pieces durable before it is renamed into place (its data, not just its name)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_folder(folder) -> None:
    """Make a rename in ``folder`` durable (POSIX: fsync the directory); a no-op where that is refused."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _mode_for(p: Path) -> int:
    """The permission bits the new file gets: the replaced file's, or 0666 less the umask (mkstemp's
    0600 would make a config or a route unreadable to the other users that could read it before)."""
    try:
        return p.stat().st_mode & 0o7777
    except OSError:
        return 0o666 & ~_umask()


def _umask() -> int:
    """The process umask, read without setting it (``os.umask`` would change it for every thread for a
    moment); 022 where /proc does not say."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    return 0o022


def _folder(p: Path) -> Path:
    return p.parent if str(p.parent) else Path(".")
