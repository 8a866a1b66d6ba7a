"""A cache of derived per-session data, kept outside the session directory.

Entries are keyed by the session's absolute path, the names, sizes and modification times of its
files, the parameters and the package version: any change to the inputs or the parameters gives
a new key, so a stale entry is never reused. Entries are written atomically.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from contact_viz import __version__


def default_cache_dir() -> Path:
    """``$CONTACT_VIZ_CACHE``, else ``$XDG_CACHE_HOME/contact-viz``, else ``~/.cache/contact-viz``."""
    if os.environ.get("CONTACT_VIZ_CACHE"):
        return Path(os.environ["CONTACT_VIZ_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "contact-viz"


def session_fingerprint(root: str | Path) -> list[tuple[str, int, int]]:
    """(relative path, size in bytes, mtime in ns) of every file under ``root``, sorted."""
    root = Path(root).resolve()
    entries = []
    for dirpath, _, filenames in os.walk(root):
        for name in filenames:
            path = Path(dirpath) / name
            stat = path.stat()
            entries.append((str(path.relative_to(root)), stat.st_size, stat.st_mtime_ns))
    entries.sort()
    return entries


def cache_key(root: str | Path, kind: str, params: dict) -> str:
    """A hex digest naming the cache entry of ``kind`` for session ``root`` and ``params``."""
    payload = json.dumps(
        {"version": __version__, "kind": kind, "root": str(Path(root).resolve()),
         "files": session_fingerprint(root), "params": params},
        sort_keys=True,
    )
    return hashlib.sha256(payload.encode()).hexdigest()[:32]


def cache_path(root: str | Path, kind: str, params: dict, suffix: str, cache_dir: str | Path | None = None) -> Path:
    """Where the cache entry of ``kind`` for session ``root`` and ``params`` lives (may not exist)."""
    directory = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    return directory / kind / f"{Path(root).resolve().name}-{cache_key(root, kind, params)}{suffix}"
