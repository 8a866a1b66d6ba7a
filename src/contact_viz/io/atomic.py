"""Atomic file output: a reader never sees a half-written file under the final name.

Every output is written under a hidden staging name beside it, ``.NAME.PID-NS.KIND``
(:func:`staging_path`), and renamed into place when complete. A process killed with SIGKILL
cannot remove its staging file; the next writer of the same name does (:func:`sweep_stale`:
entries whose process is gone), so nothing ever needs cleaning up by hand.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "w", **open_kwargs) -> Iterator[IO]:
    """Open a temporary file beside ``path``; rename it onto ``path`` only on success.

    If the block raises (or the process dies), ``path`` is left untouched and the
    temporary file is removed (or, after a hard kill, left under a ``.tmp`` name).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    tmp = Path(tmp_name)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the file the usual permissions
    try:
        with os.fdopen(fd, mode, **open_kwargs) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def staging_path(path: str | Path, kind: str = "tmp") -> Path:
    """A hidden name beside ``path`` that this process can write before renaming it onto ``path``:
    ``.NAME.PID-NS.KIND`` (unique per call; :func:`sweep_stale` recognises it)."""
    path = Path(path)
    return path.with_name(f".{path.name}.{os.getpid()}-{time.monotonic_ns()}.{kind}")


def sweep_stale(path: str | Path) -> list[Path]:
    """Remove the staging files and folders of ``path`` (:func:`staging_path`) left by processes that
    no longer run (killed with SIGKILL, a power cut); those of live processes are kept. The removed paths."""
    path = Path(path)
    pattern = re.compile(rf"^\.{re.escape(path.name)}\.(\d+)-\d+\.[A-Za-z0-9_.-]+$")
    removed = []
    try:
        entries = list(path.parent.iterdir())
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
    return True
