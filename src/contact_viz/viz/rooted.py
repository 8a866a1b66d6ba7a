"""A caller's ``rr.RecordingStream`` with every entity path the debugger logs put under a root of the caller's
choosing (``contact_viz.log_session(rec, ..., root="contact_viz")``): the debugger's paths
(:mod:`contact_viz.viz.entities`) stay as they are, and the recording holds them at ``<root>/<path>``. Only the
calls that name an entity are rewritten; everything else goes to the stream unchanged. No global Rerun state
is touched: the debugger logs to the stream it is given only.
"""

from __future__ import annotations

from typing import Any

__all__ = ["RootedRecording", "rooted", "root_path"]


def root_path(root: str | None, path: str) -> str:
    """``path`` under ``root`` (None or "": ``path`` itself), without doubled or trailing slashes."""
    root = (root or "").strip("/")
    path = path.strip("/")
    return f"{root}/{path}" if root else path


class RootedRecording:
    """``rec`` with the entity path of every ``log`` and ``send_columns`` call under ``root``."""

    def __init__(self, rec: Any, root: str) -> None:
        self._rec = rec
        self.root = root.strip("/")

    def log(self, entity_path: str, *args: Any, **kwargs: Any) -> None:
        self._rec.log(root_path(self.root, entity_path), *args, **kwargs)

    def send_columns(self, entity_path: str, *args: Any, **kwargs: Any) -> None:
        self._rec.send_columns(root_path(self.root, entity_path), *args, **kwargs)

    def __getattr__(self, name: str) -> Any:  # set_time, flush, ...: the stream's own
        return getattr(self._rec, name)


def rooted(rec: Any, root: str | None) -> Any:
    """``rec`` itself without a root, else a :class:`RootedRecording`."""
    return rec if not (root or "").strip("/") else RootedRecording(rec, root)
