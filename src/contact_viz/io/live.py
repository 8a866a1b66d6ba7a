"""A session directory that a recorder is still writing: which frames are complete, in order.

The recorder contract (README, "Live"): write each file under a temporary name in its folder (a
name starting with ``.`` or ending in ``.tmp``/``.part``) and rename it into place when complete;
append whole lines to ``frames.csv`` and ``force.csv``. Recorders that write in place are coped
with: a file is taken only when it decodes completely (PNG ends with its IEND chunk, JPEG with its
EOI marker after its header segments, ``.npy`` holds all the bytes its header announces) and its size
and time have not changed for ``settle_s`` (two looks one poll apart); a CSV line only once it ends
with a newline.

A frame is complete when its left image, its mask, its depth or disparity (when the session has
that folder), its right image (when it has right/) and its ``frames.csv`` row (when it has that
file) are. Frames are taken in the session's order (numeric stems); a frame whose other files are
not complete ``frame_timeout_s`` after its left image is skipped, with one warning naming the file.

Names are found by probing the next stems of a numbered sequence (``000124`` after ``000123``)
at every poll, and by listing left/ when there is nothing to probe from or probing has found nothing
for ``rescan_s`` (a stem out of sequence, names that are not numbered); a listing sets aside the names
up to the last frame's by a plain comparison, so an hour-long session is not parsed at every listing.
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from contact_viz.errors import SessionError, SessionWarning
from contact_viz.io.session import IMAGE_SUFFIXES, Session, open_session
from contact_viz.io.session_files import natural_key
from contact_viz.params import check_fields, checked

PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # a PNG's last chunk, whole
JPEG_END = b"\xff\xd9"  # a JPEG's end-of-image marker
LAYER_FOLDERS = {"left": ("left", IMAGE_SUFFIXES), "right": ("right", IMAGE_SUFFIXES),
                 "mask": ("masks", (".png",)), "depth": ("depth", (".npy", ".png")),
                 "disparity": ("disparity", (".npy",))}


@dataclass(frozen=True)
class FollowParams:
    """How a session being recorded is followed."""

    poll_s: float = checked(0.005, gt=0)  # how often the folders are looked at, s
    settle_s: float = checked(0.005, ge=0)  # a file counts once its size and time have held this long, s
    frame_timeout_s: float = checked(5.0, gt=0)  # after its left image, how long a frame's other files may take, s
    idle_timeout_s: float | None = checked(None, gt=0)  # stop after this long without a new frame, s; None: never
    from_start: bool = False  # take the frames already there first (else start after the last of them)
    rescan_s: float = checked(0.5, gt=0)  # list left/ after this long without a frame found by probing, s

    def __post_init__(self) -> None:
        check_fields(self)


def decodes_completely(path: Path, size: int) -> bool:
    """Whether the ``size`` bytes of ``path`` are a whole file of its kind (PNG, JPEG, .npy; others: yes)."""
    suffix = path.suffix.lower()
    try:
        with open(path, "rb") as handle:
            if suffix == ".png":
                handle.seek(max(size - len(PNG_END), 0))
                return handle.read(len(PNG_END)) == PNG_END
            if suffix in (".jpg", ".jpeg"):
                return _jpeg_complete(handle, size)
            if suffix == ".npy":
                version = np.lib.format.read_magic(handle)
                read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                               else np.lib.format.read_array_header_2_0)
                shape, _, dtype = read_header(handle)
                return size == handle.tell() + math.prod(shape) * dtype.itemsize
    except (OSError, ValueError, EOFError):
        return False
    return True


def _jpeg_complete(handle, size: int) -> bool:
    """A JPEG's start-of-image marker, its header segments (skipped by their lengths: an EXIF thumbnail's
    own end-of-image marker is inside them) up to the first start-of-scan, and the end-of-image marker as its
    last two bytes (in the scan data a 0xFF byte is never followed by 0xD9)."""
    handle.seek(0)
    if handle.read(2) != b"\xff\xd8":
        return False
    position = 2
    while True:
        handle.seek(position)
        marker = handle.read(4)
        if len(marker) < 4 or marker[0] != 0xFF:
            return False
        if marker[1] == 0xFF:  # a fill byte before the marker
            position += 1
        elif marker[1] == 0xDA:  # start of scan: the entropy-coded data follows
            break
        else:
            position += 2 + int.from_bytes(marker[2:4], "big")
        if position >= size:
            return False
    handle.seek(size - len(JPEG_END))
    return handle.read(len(JPEG_END)) == JPEG_END


class _FileWatch:
    """When each file was first seen complete-looking, to tell a finished file from one being written."""

    def __init__(self, settle_s: float) -> None:
        self.settle_s = settle_s
        self._seen: dict[Path, tuple[int, int, float]] = {}  # path -> (size, mtime ns, when first seen so)

    def complete(self, path: Path, now: float) -> float | None:
        """When the file was completed (its status change time: the rename into place, or the last write;
        ``time.time()`` seconds), or None while it is missing or not complete."""
        try:
            st = os.stat(path)
        except OSError:
            return None
        key = (st.st_size, st.st_mtime_ns)
        seen = self._seen.get(path)
        if seen is None or seen[:2] != key:
            self._seen[path] = (*key, now)
            seen = self._seen[path]
        steady = now - seen[2] >= self.settle_s or time.time() - st.st_mtime_ns / 1e9 >= self.settle_s
        if st.st_size == 0 or not steady or not decodes_completely(path, st.st_size):
            return None
        del self._seen[path]
        return max(st.st_ctime_ns, st.st_mtime_ns) / 1e9


class CsvTail:
    """The whole lines appended to a CSV file since the last read, as dicts (header from its first line)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.offset = 0
        self.header: list[str] | None = None
        self.line = 0
        self.changed = math.nan  # the file's modification time at the last read (time.time() s): when the
        # last of the lines read was appended, at the latest

    def rows(self) -> list[dict[str, str]]:
        try:
            with open(self.path, "rb") as handle:
                handle.seek(self.offset)
                data = handle.read()
                self.changed = os.fstat(handle.fileno()).st_mtime_ns / 1e9
        except OSError:
            return []
        end = data.rfind(b"\n")
        if end < 0:
            return []
        self.offset += end + 1
        out = []
        for cells in csv.reader(io.StringIO(data[:end + 1].decode("utf-8", errors="replace"))):
            self.line += 1
            if not cells:
                continue
            if self.header is None:
                self.header = [c.strip() for c in cells]
                continue
            out.append(dict(zip(self.header, (c.strip() for c in cells))))
        return out


class SessionFollower:
    """The complete frames of a session being recorded, appended to one growing :class:`Session`.

    ``new``: the session was made after following began, so every frame in it is new (taken, and not
    replayed with ``from_start``). ``open_kwargs`` go to :func:`contact_viz.io.session.open_session`.
    :meth:`poll` returns the indices added since the last call, each with the time (``time.monotonic``)
    its last file was completed; :attr:`session` is None until the first frame is.
    """

    def __init__(self, root: str | Path, params: FollowParams = FollowParams(), *, new: bool = False,
                 **open_kwargs) -> None:
        self.root = Path(root).expanduser()
        if not (self.root / "left").is_dir():
            raise SessionError(self.root / "left", "missing: expected the left/ folder of a session being "
                               "recorded (the recorder makes left/, masks/ and K.txt first)")
        self.params = params
        self.open_kwargs = open_kwargs
        self.session: Session | None = None
        self.layers = ["left", "mask"] + [layer for layer in ("right", "depth", "disparity")
                                          if (self.root / LAYER_FOLDERS[layer][0]).is_dir()]
        if "depth" in self.layers and "disparity" in self.layers:
            self.layers.remove("disparity")  # depth/ wins, as in open_session
        self.frames_csv = CsvTail(self.root / "frames.csv") if (self.root / "frames.csv").is_file() else None
        self.force_csv = CsvTail(self.root / "force.csv")
        # frames.csv rows not yet used: stem -> (its time, s; when it was appended, at the latest: time.time() s)
        self.times: dict[str, tuple[float, float]] = {}
        self.files = _FileWatch(params.settle_s)
        self.pending: dict[str, float] = {}  # stems whose left image is there, not yet taken -> when first seen
        self.done: set[str] = set()  # stems taken or skipped (pruned as the session moves on)
        self.last_stem: str | None = None
        self.skipped: list[str] = []  # stems skipped (their files never completed)
        self._last_left = ""  # the left image file name of the last frame taken
        self._suffix: dict[str, str] = {}  # layer -> the suffix of its last file found
        self._ready: dict[str, dict[str, tuple[Path, float]]] = {}  # pending stem -> its files found complete
        self._last_scan = -math.inf
        self.started = self._last_probed = time.monotonic()
        existing = [] if new else sorted(self._list(), key=natural_key)
        self.backlog: set[str] = set(existing) if params.from_start else set()  # there at the start, not taken yet
        if params.from_start:  # to be taken first
            self.pending.update(dict.fromkeys(existing, self.started))
        elif existing:  # start after the frames already there
            self.last_stem = existing[-1]
            path = self._file("left", self.last_stem)
            self._last_left = path.name if path is not None else ""
            self.done.update(existing)
        self.force_rows: list[dict[str, str]] = []  # force.csv rows not yet logged

    # -- names ------------------------------------------------------------------------------

    def _list(self) -> list[str]:
        """The stems of the left images, but those of names as long as the last frame's and not after it
        (for stems of one width, the order of the names; a plain comparison, so that an hour-long session's
        names are not parsed at every listing)."""
        folder, suffixes = LAYER_FOLDERS["left"]
        try:
            names = os.listdir(self.root / folder)
        except OSError:
            return []
        last = self._last_left
        if last:
            width = len(last)
            names = [name for name in names if len(name) != width or name > last]
        return [name.rsplit(".", 1)[0] for name in names if _visible(name) and name.lower().endswith(suffixes)]

    def _probe(self) -> list[str]:
        """The next stems of a numbered sequence that exist (no listing)."""
        if self.last_stem is None or not self.last_stem.isdigit():
            return []
        out, width, number = [], len(self.last_stem), int(self.last_stem)
        for k in range(1, 4):
            stem = f"{number + k:0{width}d}"
            if stem not in self.pending and self._file("left", stem) is not None:
                out.append(stem)
        return out

    def _file(self, layer: str, stem: str) -> Path | None:
        """Frame ``stem``'s file of ``layer``, or None; the suffix the layer's last file had is tried first."""
        folder, suffixes = LAYER_FOLDERS[layer]
        last = self._suffix.get(layer)
        for suffix in ((last,) + suffixes if last else suffixes):
            path = f"{self.root}/{folder}/{stem}{suffix}"
            if os.path.exists(path):
                self._suffix[layer] = suffix
                return Path(path)
        return None

    # -- polling ------------------------------------------------------------------------------

    def poll(self) -> list[tuple[int, float]]:
        """Take every frame complete now, in order; (index in the session, when its last file was completed,
        on the ``time.monotonic`` clock) each. A file's completion is its change time (the rename into place,
        or the last write of a recorder writing in place), so the time a frame waited for this poll counts."""
        now = time.monotonic()
        wall_offset = time.time() - now  # file times are wall-clock: to the monotonic clock and back
        found = self._probe()
        if found:
            self._last_probed = now
        # left/ is listed when there is no stem to probe from, or when probing has found nothing for rescan_s
        # (a stem out of sequence, names that are not numbered): not while a numbered sequence flows
        rescan = self.params.rescan_s
        if self.last_stem is None or (now - self._last_scan >= rescan and now - self._last_probed >= rescan):
            self._last_scan = now
            found += self._list()
        for stem in found:
            if stem not in self.done and stem not in self.pending and (
                    self.last_stem is None or natural_key(stem) > natural_key(self.last_stem)):
                self.pending[stem] = now
        if self.frames_csv is not None:
            for row in self.frames_csv.rows():
                try:
                    self.times[row["frame"]] = (float(row["timestamp"]),
                                                min(self.frames_csv.changed, now + wall_offset))
                except (KeyError, ValueError):
                    raise SessionError(self.frames_csv.path, f"line {self.frames_csv.line}: expected frame,timestamp "
                                       "(stem, seconds)") from None
        self.force_rows.extend(self.force_csv.rows())
        taken: list[tuple[str, dict[str, Path], float]] = []
        for stem in sorted(self.pending, key=natural_key):
            files, missing, completed = self._complete(stem, now)
            if missing is None:
                taken.append((stem, files, min(now, completed - wall_offset)))
                self._last_left = files["left"].name
            elif now - self.pending[stem] > self.params.frame_timeout_s:
                warnings.warn(f"frame {stem} skipped: {missing} did not arrive complete within "
                              f"{self.params.frame_timeout_s:g} s (--frame-timeout)", SessionWarning, stacklevel=2)
                self.skipped.append(stem)
                self.times.pop(stem, None)
                self._ready.pop(stem, None)
            else:
                break  # frames are taken in order: wait for this one
            del self.pending[stem]
            self.last_stem = stem
        return self._add(taken, now)

    def _complete(self, stem: str, now: float) -> tuple[dict[str, Path], str | None, float]:
        """The frame's files, the first one missing or incomplete (None: all complete), and when the last
        of them was completed (``time.time()`` seconds; a frames.csv row counts at frames.csv's modification
        time when it was read)."""
        files = self._ready.setdefault(stem, {})  # layer -> (path, completed): not looked at again
        last = max((completed for _, completed in files.values()), default=-math.inf)
        for layer in self.layers:
            if layer in files:
                continue
            path = self._file(layer, stem)
            if path is None:
                folder, suffixes = LAYER_FOLDERS[layer]
                return {}, str(self.root / folder / f"{stem}{suffixes[0]}"), last
            completed = self.files.complete(path, now)
            if completed is None:
                return {}, str(path), last
            files[layer] = (path, completed)
            last = max(last, completed)
        if self.frames_csv is not None:
            if stem not in self.times:
                return {}, f"{self.frames_csv.path} row of frame {stem}", last
            last = max(last, self.times[stem][1])
        del self._ready[stem]
        return {layer: path for layer, (path, _) in files.items()}, None, last

    def _add(self, taken: list[tuple[str, dict[str, Path], float]], now: float) -> list[tuple[int, float]]:
        if not taken:
            return []
        stems = [stem for stem, _, _ in taken]
        completed = [when for _, _, when in taken]
        if self.session is None:
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", SessionWarning)  # rows of frames not taken yet
                    self.session = open_session(self.root, only_stems=stems, **self.open_kwargs)
            except SessionError:  # a CSV line being written, a calibration not there yet: try again
                if now - self.started > self.params.frame_timeout_s:
                    raise
                for stem in stems:
                    self.pending[stem] = now
                self.last_stem = None if not self.done else max(self.done, key=natural_key)
                return []
            for stem in stems:
                self.times.pop(stem, None)
            self.done.update(stems)
            return list(enumerate(completed))
        session = self.session
        first = len(session)
        by_layer: dict[str, dict[str, Path]] = {}
        for stem, files, _ in taken:
            for layer, path in files.items():
                by_layer.setdefault("depth" if layer == "disparity" else layer, {})[stem] = path
        if self.frames_csv is not None:
            times = [self.times.pop(stem)[0] for stem in stems]
        else:
            times = [(first + i) / session.fps for i in range(len(stems))]
        session.extend(stems, by_layer, times)
        self.done.update(stems)
        return [(first + i, when) for i, when in enumerate(completed)]

    def from_backlog(self, stem: str) -> bool:
        """Whether a frame taken was there when following started (``from_start``); asked once per frame."""
        if stem in self.backlog:
            self.backlog.discard(stem)
            return True
        return False

    def take_force_rows(self) -> list[dict[str, str]]:
        """force.csv rows read since the last call."""
        rows, self.force_rows = self.force_rows, []
        return rows

    def prune(self, keep: int = 256) -> None:
        """Forget what the frames taken before the last ``keep`` needed (bounded memory over hours)."""
        if self.last_stem is not None and len(self.done) > 4 * keep:
            key = natural_key(self.last_stem)
            self.done = {s for s in self.done if natural_key(s) >= key}
        if self.session is not None and len(self.session) > 2 * keep:
            self.session.forget_files(len(self.session) - keep)


def _visible(name: str) -> bool:
    """Not a recorder's temporary name (a hidden file, *.tmp, *.part)."""
    return not name.startswith(".") and not re.search(r"\.(tmp|part)$", name, re.IGNORECASE)
