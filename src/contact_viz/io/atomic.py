"""Atomic file output: a reader never sees a half-written file under the final name.

Every output is written under a hidden staging name beside it, ``.NAME.PID-NS.KIND``
(:func:`staging_path`), and renamed into place when complete. A process killed with SIGKILL
cannot remove its staging file; the next writer of the same name does (:func:`sweep_stale`:
entries whose process is gone; :func:`sweep_stale_in` for a whole cache folder), so nothing ever
needs cleaning up by hand.

A write that fails (a full disk, a read-only place) is an OSError about the output the user named,
never about the staging name (:func:`reported_as`), so the command's one error line reads
``error: PATH: no space left on the device``; files that belong together (a CSV and its ``.json``)
appear together or not at all (:func:`all_or_nothing`).
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import os
import re
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "w", *, sweep: bool = True, **open_kwargs) -> Iterator[IO]:
    """Open a staging file beside ``path`` (:func:`staging_path`, kind ``tmp``); fsync it and rename it
    onto ``path`` only when the block succeeds.

    If the block raises, ``path`` is left untouched and the staging file is removed; after a hard
    kill it stays, and the next writer of ``path`` removes it (``sweep``: :func:`sweep_stale` first;
    a writer of many files in one folder of its own may sweep once with :func:`sweep_stale_in`
    and pass ``sweep=False``). Inside :func:`all_or_nothing` the rename waits for the end of that block.
    An OSError while writing (a full disk, a read-only place) names ``path``, not the staging file.
    """
    path = Path(path)
    with reported_as(path):  # a read-only place, a file where a folder should be: about the output
        path.parent.mkdir(parents=True, exist_ok=True)
    if sweep:
        sweep_stale(path)
    tmp = staging_path(path, "tmp")
    with reported_as(path, tmp):
        # O_EXCL: never through a link or onto another writer's file; 0o666 & ~umask, as open() makes files
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666)
        try:
            with os.fdopen(fd, mode, **open_kwargs) as handle:
                yield handle
                handle.flush()
                os.fsync(handle.fileno())
            staged = _GROUP.get()
            if staged is None:
                os.replace(tmp, path)
            else:
                staged.append((tmp, path))
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise


_GROUP: contextvars.ContextVar[list[tuple[Path, Path]] | None] = contextvars.ContextVar("atomic_group", default=None)


@contextlib.contextmanager
def all_or_nothing() -> Iterator[None]:
    """The files written with :func:`atomic_write` in this block (this thread) appear together at its
    end, in the order they were written, or none does (e.g. a CSV and its ``.json``, or the two outputs
    of `evaluate`: a full disk on the second leaves no first either). Nested blocks join the outer one."""
    if _GROUP.get() is not None:
        yield
        return
    staged: list[tuple[Path, Path]] = []
    token = _GROUP.set(staged)
    try:
        yield
    except BaseException:
        for tmp, _ in staged:
            tmp.unlink(missing_ok=True)
        raise
    finally:
        _GROUP.reset(token)
    for k, (tmp, path) in enumerate(staged):
        try:
            with reported_as(path, tmp):
                os.replace(tmp, path)
        except BaseException:
            for rest, _ in staged[k:]:
                rest.unlink(missing_ok=True)
            raise


@contextlib.contextmanager
def reported_as(path: str | Path, *staging: str | Path) -> Iterator[None]:
    """An OSError raised in the block about one of the ``staging`` places (a file or folder under it) or
    about no file at all (a write to a full disk) is raised again as the same error about ``path``,
    the output the user asked for, so that the one error line names it (``PATH: no space left on
    the device``). Errors about other files (an input) pass unchanged. Without ``staging``, every
    OSError of the block is about ``path`` (e.g. making the folders it goes in)."""
    try:
        yield
    except OSError as exc:
        if exc.errno is None or (staging and not _about(exc, staging)):
            raise
        raise _named(exc, path) from exc


def _named(exc: OSError, path: Path | str) -> OSError:
    """``exc`` as the same error about ``path`` (unchanged when it carries no errno)."""
    if exc.errno is None:
        return exc
    return OSError(exc.errno, exc.strerror or os.strerror(exc.errno), str(path))


def _about(exc: OSError, staging: tuple) -> bool:
    names = [n for n in (exc.filename, exc.filename2) if n is not None]
    if not names:
        return True
    for name in names:
        if isinstance(name, int):  # a file descriptor: one this writer opened
            return True
        name = os.fsdecode(os.fspath(name))
        for place in staging:
            place = str(place)
            if name == place or name.startswith(place.rstrip(os.sep) + os.sep):
                return True
    return False


_REASONS = {
    errno.ENOSPC: "no space left on the device",
    errno.EROFS: "read-only file system",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.EDQUOT: "disk quota exceeded",
    errno.ENOTDIR: "a part of the path is a file, not a directory",
}


def os_reason(exc: OSError) -> str:
    """What went wrong, in the words of the one-line messages (``no space left on the device``), without the path."""
    return _REASONS.get(exc.errno or 0) or (exc.strerror or str(exc)).lower()


def staging_path(path: str | Path, kind: str = "tmp") -> Path:
    """A hidden name beside ``path`` that this process can write before renaming it onto ``path``:
    ``.NAME.PID-NS.KIND`` (unique per call; :func:`sweep_stale` recognises it)."""
    path = Path(path)
    return path.with_name(f".{path.name}.{os.getpid()}-{time.monotonic_ns()}.{kind}")


def sweep_stale(path: str | Path) -> list[Path]:
    """Remove the staging files and folders of ``path`` (:func:`staging_path`) left by processes that
    no longer run (killed with SIGKILL, a power cut); those of live processes are kept. The removed paths."""
    path = Path(path)
    return _sweep(path.parent, re.compile(rf"^\.{re.escape(path.name)}\.(\d+)-\d+\.[A-Za-z0-9_.-]+$"))


_ANY_STAGING = re.compile(r"^\..+\.(\d+)-\d+\.[A-Za-z0-9_.-]+$")


def sweep_stale_in(directory: str | Path) -> list[Path]:
    """:func:`sweep_stale` for every name at once: remove the staging entries in ``directory`` left by
    processes that no longer run. For folders only this package writes into (a cache), where one
    listing per run is cheaper than one per file. The removed paths."""
    return _sweep(Path(directory), _ANY_STAGING)


def _sweep(directory: Path, pattern: re.Pattern) -> list[Path]:
    """Remove the entries of ``directory`` whose name matches ``pattern`` (group 1: the writer's pid)
    and whose writer is gone."""
    removed = []
    try:
        entries = list(directory.iterdir())
    except OSError:
        return removed
    for entry in entries:
        match = pattern.match(entry.name)
        if match is None or _alive(int(match.group(1))):
            continue
        try:
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry)
            else:
                entry.unlink()
            removed.append(entry)
        except OSError:
            pass
    return removed


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    except (OverflowError, ValueError):  # not a pid: not a staging name of ours, keep it
        return True
    try:  # a zombie (killed, not yet reaped: an init that does not reap, in a container) writes nothing
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True
