"""The command line's edge: one-line errors and warnings, the skipped-frames summary, quiet libraries.

Every `contact-viz` command reports bad input the same way:

* an error is one line, ``error: PATH: what was expected``, and exit status 2 (never a
  traceback; ``--verbose`` shows it): :func:`describe_error` turns the exceptions that mean
  "bad input" (SessionError, ValueError, OSError, the Rerun SDK's gRPC errors) into that line;
* a frame that is skipped (unreadable) or gives nothing to measure (no valid depth near the
  tool, a mask with no background) is one line, ``warning: frame STEM ...``, and the run ends
  with one summary line, ``12 frames skipped: 10 empty depth, 2 unreadable masks``
  (:class:`FrameReport`);
* library noise (OpenCV's ``[ WARN:0@...]`` lines, Rerun's Rust log) stays off the console
  unless ``--verbose`` (:func:`quiet_libraries`);
* SIGTERM and SIGHUP (``kill``, ``timeout``, a job scheduler, a closed terminal) stop a command
  as Ctrl-C does (:func:`stop_on_signals`): a :class:`Stopped` (a KeyboardInterrupt) unwinds it,
  temporary files are removed, and the edge prints one line and exits with 128 + the signal.

Output paths are checked before any work (:func:`check_output_file`), so a command that fails
leaves nothing under its final name and prints no result first.
"""

from __future__ import annotations

import errno
import os
import re
import signal
import socket
import warnings
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from contact_viz.io.atomic import staging_path

VERBOSE = False  # set by --verbose: tracebacks and library logs reach the console

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)  # each stops a command the way Ctrl-C does

# What each errno means for the user, in the "PATH: what was expected" form.
_ERRNO_TEXT = {
    errno.EISDIR: "is a directory; expected a file name",
    errno.ENOTDIR: "a part of this path is a file, not a directory",
    errno.EACCES: "permission denied; expected a path this user can read or write",
    errno.EPERM: "operation not permitted; expected a path this user can read or write",
    errno.ELOOP: "too many levels of symbolic links (a link loop); expected a file or directory",
    errno.ENOENT: "missing: no such file or directory",
    errno.EROFS: "read-only file system; choose a path on a writable disk",
    errno.ENOSPC: "no space left on the device",
    errno.ENAMETOOLONG: "file name too long",
    errno.EEXIST: "already exists",
}


def quiet_libraries(verbose: bool = False) -> None:
    """Keep OpenCV's and Rerun's own log lines off the console unless ``verbose``.

    Environment variables reach spawned worker processes and must be set before Rerun's SDK
    starts (it reads RUST_LOG once); OpenCV's level is also set in this process if it is loaded.
    """
    global VERBOSE
    VERBOSE = bool(verbose)
    if verbose:
        return
    warnings.showwarning = _one_line_warning
    os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")  # OpenCV's "[ WARN:0@...]" lines (PNG buffer incomplete ...)
    os.environ.setdefault("RUST_LOG", "off")  # Rerun's Rust log (gRPC retries, sink errors): reported by us
    import sys

    cv2 = sys.modules.get("cv2")
    if cv2 is not None:
        try:
            cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        except AttributeError:  # very old OpenCV builds
            cv2.setLogLevel(2)


class Stopped(KeyboardInterrupt):
    """A command was stopped by a signal (SIGINT, SIGTERM or SIGHUP); every ``except
    KeyboardInterrupt`` (a clean stop: flush, say what is partial) handles all three alike."""

    def __init__(self, signum: int) -> None:
        self.signum = int(signum)
        super().__init__(signal.Signals(signum).name)


_STOP = {"signum": None, "reported": False}  # the last stop signal this process got, and whether its line was said


def _raise_stopped(signum, frame) -> None:
    _STOP["signum"], _STOP["reported"] = int(signum), False
    raise Stopped(signum)


def stop_reported() -> None:
    """The command's edge said the stop line (:func:`stop_line`) of the last stop signal."""
    _STOP["reported"] = True


def unreported_stop() -> tuple[str, int] | None:
    """The stop line and exit status of a stop signal whose line was not said: one that came before or after
    the command ran (while the command line was parsed), which typer ends with exit status 130 and no word."""
    if _STOP["signum"] is None or _STOP["reported"]:
        return None
    return stop_line(Stopped(_STOP["signum"]))


def stop_on_signals() -> None:
    """Make SIGTERM and SIGHUP (and SIGINT, to name it) raise :class:`Stopped` in the main thread.

    Call once, in the main thread, before any work (the console script does)."""
    for signum in STOP_SIGNALS:
        signal.signal(signum, _raise_stopped)


def stop_line(exc: KeyboardInterrupt) -> tuple[str, int]:
    """The one line and the exit status (128 + the signal) of a command stopped by ``exc``."""
    signum = getattr(exc, "signum", signal.SIGINT)
    if signum == signal.SIGINT:
        return "interrupted (Ctrl-C)", 128 + signum
    name = signal.Signals(signum).name
    why = " (the terminal closed)" if signum == signal.SIGHUP else ""
    return f"stopped by {name}{why}", 128 + signum


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Python warnings as ``warning: MESSAGE`` (no source file and line), as the commands print them."""
    import sys

    print(f"warning: {message}", file=file or sys.stderr)


def describe_error(exc: BaseException) -> str | None:
    """The one line (without ``error: ``) that tells the user what was wrong, or None when
    ``exc`` is not about the input (a bug: the caller lets its traceback through)."""
    from contact_viz.errors import SessionError

    if isinstance(exc, SessionError):
        return str(exc)
    if isinstance(exc, OSError):
        return describe_os_error(exc)
    if isinstance(exc, ValueError):
        text = str(exc)
        return text.splitlines()[0] if text else type(exc).__name__
    if isinstance(exc, RuntimeError):
        text = str(exc)
        if "address already in use" in text.lower():
            return f"{text.splitlines()[0]}; expected free ports: choose others with --grpc-port / --web-port"
        if re.search(r"grpc|endpoint|connect|sink|viewer", text, re.IGNORECASE):
            return f"Rerun: {text.splitlines()[0]}; expected a running viewer (start one with `rerun`) or --save out.rrd"
    return None


def describe_os_error(exc: OSError, what: str | None = None) -> str:
    """``PATH: what happened; what was expected`` for an OSError (``what``: e.g. "-o")."""
    path = exc.filename if exc.filename is not None else ""
    text = _ERRNO_TEXT.get(exc.errno or 0, exc.strerror or str(exc))
    if exc.filename2 is not None:
        text += f" (with {exc.filename2})"
    prefix = f"{what}: " if what else ""
    return f"{path}: {prefix}{text}" if path else f"{prefix}{text}"


class OutputError(ValueError):
    """An output path that cannot be written; the message names it and the option."""


def check_output_file(path: Path, option: str, *, session_root: Path | None = None,
                      example: str = "out.csv") -> Path:
    """Check now, before any work, that the file ``path`` given by ``option`` can be written:
    not a directory, not inside the session, in a directory that exists (or can be made) and
    accepts a new file. The directory is made (as the atomic writer would); nothing else is
    left behind. Raises OutputError naming the path and the option."""
    path = Path(path).expanduser()
    if path.is_dir():
        raise OutputError(f"{path}: {option}: is a directory; expected a file name, e.g. {path / example}")
    if session_root is not None and _inside(path, session_root):
        raise OutputError(f"{path}: {option}: inside the session directory {session_root}, which contact-viz "
                          "never writes into; choose a path outside it")
    parent = path.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        probe = staging_path(path, "probe")  # a name the next run sweeps if this one is killed right here
        with open(probe, "x"):
            pass
        probe.unlink()
    except OSError as exc:
        raise OutputError(f"{path}: {option}: cannot write here ({exc.strerror or exc}); expected a path in a "
                          "writable directory") from None
    return path


def _inside(path: Path, directory: Path) -> bool:
    try:
        path.resolve().relative_to(Path(directory).resolve())
        return True
    except (ValueError, OSError):
        return False


def check_output_dir(path: Path, option: str) -> Path:
    """Check now that the new folder ``path`` given by ``option`` can be made: not a file, and its
    parent (made if needed) accepts a new entry. Raises OutputError naming the path and option."""
    path = Path(path).expanduser()
    if path.exists() and not path.is_dir():
        raise OutputError(f"{path}: {option}: is a file; expected a new or empty directory")
    parent = path.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        probe = staging_path(path, "probe")
        probe.mkdir()
        probe.rmdir()
    except OSError as exc:
        raise OutputError(f"{path}: {option}: cannot make a directory here ({exc.strerror or exc}); expected a "
                          "path in a writable directory") from None
    return path


_CONNECT_URL = re.compile(r"^rerun(\+https?)?://(?P<host>[A-Za-z0-9.\-]+|\[[0-9a-fA-F:]+\]):(?P<port>\d{1,5})(/proxy)?/?$")


def check_connect_url(url: str, timeout_s: float = 2.0) -> None:
    """ValueError (naming --connect) unless ``url`` is a Rerun gRPC URL with a viewer listening
    there; checked before the recording starts, so that no gRPC retry loop runs for seconds and
    no Rust log reaches the console."""
    match = _CONNECT_URL.match(url.strip())
    if match is None:
        raise ValueError(f"--connect: expected a Rerun viewer URL like rerun+http://127.0.0.1:9876/proxy, "
                         f"got {url!r}")
    host, port = match["host"].strip("[]"), int(match["port"])
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except OSError as exc:
        raise ValueError(f"--connect {url}: no Rerun viewer is listening at {host}:{port} "
                         f"({exc.strerror or exc}); start one with `rerun`, or write a file with --save out.rrd"
                         ) from None


# --------------------------------------------------------------------------------------------
# Frames named as the user named them (their stems)
# --------------------------------------------------------------------------------------------


def frame_name(index: int, stems: Sequence[str] | None) -> str:
    """Frame ``index``'s stem (its files' name in left/), or the index itself when ``stems`` is not known."""
    return str(stems[index]) if stems and 0 <= index < len(stems) else str(index)


def _consecutive(a: str, b: str) -> bool:
    """Stem ``b`` is the integer after stem ``a`` (``000020``, ``000021``)."""
    return a.isdigit() and b.isdigit() and int(b) == int(a) + 1


def stem_runs(ranges: Iterable[tuple[int, int]], stems: Sequence[str] | None) -> list[tuple[str, str]]:
    """(first, last) frame index ranges as (first, last) stems of runs whose stems are consecutive integers:
    frames 20-22 of a session whose stems are 000020-000022 are one run; frames whose stems skip numbers
    (021300, 022225) each make their own (first = last). Without ``stems``, the indices as text."""
    out: list[tuple[str, str]] = []
    for a, b in ranges:
        if not stems:
            out.append((str(a), str(b)))
            continue
        start = a
        for i in range(a, b + 1):
            if i == b or not _consecutive(stems[i], stems[i + 1]):
                out.append((stems[start], stems[i]))
                start = i + 1
    return out


def frames_text(ranges: Iterable[tuple[int, int]], stems: Sequence[str] | None, max_runs: int) -> str:
    """``000020-000022, 000024`` (stem_runs), at most ``max_runs`` of them, then ``, ... (12 ranges)``."""
    runs = stem_runs(ranges, stems)
    text = ", ".join(a if a == b else f"{a}-{b}" for a, b in runs[:max_runs])
    return text + (f", ... ({len(runs)} ranges)" if len(runs) > max_runs else "")


# --------------------------------------------------------------------------------------------
# Frame warnings and the end-of-run summary
# --------------------------------------------------------------------------------------------

_LAYER_NAMES = {"masks": "mask", "depth": "depth", "disparity": "disparity", "left": "left image",
                "right": "right image"}
EMPTY_DEPTH = "empty depth"  # every depth value in the band around the tool is invalid
FULL_MASK = "mask without background"  # the mask leaves no background around the tool


def skip_kind(detail: str) -> str:
    """The summary category of a skipped frame's reason ``"PATH: what was expected"``:
    "missing mask", "unreadable depth", ... (the folder of the file names the layer)."""
    path, _, rest = detail.partition(": ")
    layer = _LAYER_NAMES.get(Path(path).parent.name, "file")
    missing = rest.startswith("missing") or rest.endswith("file missing")
    return f"{'missing' if missing else 'unreadable'} {layer}"


def no_patch_problem(reason: str | None, invalid_depth_fraction: float | str | None) -> str | None:
    """The input fault behind a frame without a patch, if it is one the user should hear of:
    EMPTY_DEPTH (no valid depth in the band around the tool), FULL_MASK (no background
    around the tool), or None (a patch was found, the tool is out of view, too few pixels ...)."""
    if reason == "no_band":
        return FULL_MASK
    try:
        invalid = float(invalid_depth_fraction) if invalid_depth_fraction not in (None, "") else float("nan")
    except (TypeError, ValueError):
        return None
    if reason and invalid >= 1.0:
        return EMPTY_DEPTH
    return None


def no_patch_message(stem: str, problem: str, file: Path | None) -> str:
    """The warning text (without ``warning: ``) of a frame whose input gives nothing to measure."""
    where = f"{file}: " if file is not None else ""
    if problem == EMPTY_DEPTH:
        return (f"frame {stem} has no patch: {where}no valid depth around the tool (0, NaN, inf or negative in "
                "every band pixel); expected depth > 0 m beside the tool")
    return (f"frame {stem} has no patch: {where}the mask leaves no background around the tool; expected a tool "
            "mask that does not cover the whole image")


def _plural(n: int, word: str) -> str:
    if n == 1:
        return word
    if word.endswith("depth") or word.endswith("background"):
        return word
    return word + "s"


@dataclass
class FrameReport:
    """Frames skipped or without a measurable input in one run: their warning lines and the
    end-of-run summary line."""

    lines: list[str] = field(default_factory=list)  # "warning: ..." lines, in frame order
    kinds: Counter = field(default_factory=Counter)  # summary category -> frames

    def skipped(self, stem: str, detail: str) -> None:
        self.lines.append(f"warning: frame {stem} skipped: {detail}")
        self.kinds[skip_kind(detail)] += 1

    def no_patch(self, stem: str, problem: str, file: Path | None) -> None:
        self.lines.append(f"warning: {no_patch_message(stem, problem, file)}")
        self.kinds[problem] += 1

    def other(self, message: str) -> None:
        self.lines.append(f"warning: {message}")

    @property
    def n_frames(self) -> int:
        return sum(self.kinds.values())

    def summary(self) -> str | None:
        """``12 frames skipped: 10 empty depth, 2 unreadable masks``, or None when none was."""
        n = self.n_frames
        if not n:
            return None
        parts = ", ".join(f"{count} {_plural(count, kind)}" for kind, count in self.kinds.most_common())
        return f"{n} frame{'s' * (n != 1)} skipped: {parts}"

    @classmethod
    def from_rows(cls, rows: Sequence[dict], layer_file=None) -> FrameReport:
        """From features rows (`extract`): ``bad_frame`` rows and rows whose input gives no patch.
        ``layer_file(layer, stem)`` names the mask / depth file of a frame (or None)."""
        report = cls()
        for row in rows:
            stem = str(row["frame"])
            if row.get("reason") == "bad_frame":
                report.skipped(stem, str(row.get("detail", "")))
                continue
            problem = no_patch_problem(row.get("reason") or None, row.get("invalid_depth_fraction"))
            if problem is not None:
                layer = "mask" if problem == FULL_MASK else "depth"
                report.no_patch(stem, problem, None if layer_file is None else layer_file(layer, stem))
        return report

    def add_warnings(self, caught: Iterable[warnings.WarningMessage]) -> None:
        """Warnings recorded during a run: frame warnings (BadFrameWarning, NoPatchWarning)
        are counted, any other (e.g. a CSV row naming no frame) becomes one plain line."""
        from contact_viz.errors import NoPatchWarning, SessionWarning
        from contact_viz.pipeline.extract import BadFrameWarning

        for w in caught:
            message = str(w.message)
            if issubclass(w.category, BadFrameWarning):
                stem, _, detail = message.removeprefix("frame ").partition(" skipped: ")
                self.skipped(stem, detail)
            elif issubclass(w.category, NoPatchWarning):
                self.lines.append(f"warning: {message}")
                self.kinds[EMPTY_DEPTH if "no valid depth" in message else FULL_MASK] += 1
            elif VERBOSE or issubclass(w.category, SessionWarning):
                self.other(message)


def session_training_problem(names: Sequence[str], labels: Sequence[np.ndarray],
                             signals: Sequence[np.ndarray]) -> str | None:
    """Why the leave-one-session-out fit cannot work on these sessions, in the user's words, or
    None. Every fold fits on all sessions but one, so that fold's sessions must hold, between
    them, frames of both states with a patch and a contact episode that starts and one that ends."""
    per = []
    for y, x in zip(labels, signals):
        y = np.asarray(y)
        both = (y[:-1] >= 0) & (y[1:] >= 0)
        starts = int(((y[:-1] == 0) & (y[1:] == 1) & both).sum())
        ends = int(((y[:-1] == 1) & (y[1:] == 0) & both).sum())
        finite = np.isfinite(np.asarray(x, dtype=np.float64))
        per.append((starts, ends, int(((y == 0) & finite).sum()), int(((y == 1) & finite).sum()), len(y)))
    for k, name in enumerate(names):
        others = [i for i in range(len(names)) if i != k]
        total = [sum(per[i][j] for i in others) for j in range(4)]
        lacks = [what for what, n in zip(("contact episode that starts (no contact -> contact)",
                                          "contact episode that ends (contact -> no contact)",
                                          "frame without contact that has a patch",
                                          "frame in contact that has a patch"), total)
                 if n == 0]
        if lacks:
            short = [f"{names[i]} ({per[i][4]} frames, {per[i][1]} ending episode{'s' * (per[i][1] != 1)})"
                     for i in others]
            return (f"fit: leaving out {name}, the other training sessions ({', '.join(short)}) have no "
                    f"{' and no '.join(lacks)}; expected every training session to hold at least one whole "
                    "contact episode (approach, contact, release) with labels, so that each fold sees one: use "
                    "longer sessions (synthetic ones: --frames 60 or more) or add sessions")
    return None
