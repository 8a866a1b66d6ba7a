"""The project's small JSON files (parameters, split, model, configurations): read with one error
that names the file, written atomically."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from contact_viz.io.atomic import atomic_write


def read_json(path: str | Path, expected: str, missing: str | None = None) -> Any:
    """The parsed JSON of ``path``.

    A missing file is a ValueError ``"<path>: <missing>"`` (when ``missing`` is given); a missing,
    unreadable or malformed file otherwise is ``"<path>: <expected> (<what went wrong>)"``.
    """
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError as exc:
        if missing is not None:
            raise ValueError(f"{path}: {missing}") from None
        raise ValueError(f"{path}: {expected} ({exc})") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: {expected} ({exc})") from None


def write_json(path: str | Path, data: Any, indent: int = 2) -> None:
    """Write ``data`` as JSON with a final newline to ``path``, atomically."""
    with atomic_write(path) as handle:
        json.dump(data, handle, indent=indent)
        handle.write("\n")
