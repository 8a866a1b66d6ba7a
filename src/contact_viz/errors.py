"""Exceptions raised for malformed input."""

from __future__ import annotations

from pathlib import Path


class SessionError(ValueError):
    """A session file or directory is missing or malformed.

    The message always names the offending path and what was expected there.
    """

    def __init__(self, path: str | Path, expected: str) -> None:
        self.path = Path(path)
        self.expected = expected
        super().__init__(f"{self.path}: {expected}")


class SessionFormatError(SessionError):
    """A frame's file decodes but holds the wrong kind of data (shape, dtype, channels, bit depth).

    Such a fault is usually shared by a whole folder: when the first frame's file has it (and so
    does the last's), the session is refused up front (contact_viz.io.session.open_session)
    instead of every frame being skipped one by one.
    """


class NoPatchWarning(UserWarning):
    """A frame was read but its input gives nothing to measure (no valid depth around the tool,
    a mask without background); the message names the file (contact_viz.console.no_patch_message)."""


class SessionWarning(UserWarning):
    """Something in a session is odd but usable (e.g. a CSV row for a stem not in left/)."""
