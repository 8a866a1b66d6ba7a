"""Convert what a recorder wrote into a native session (``contact-viz import KIND SRC OUT``).

Importers never modify SRC: images are hard-linked into OUT where the file system allows it,
else symbolic-linked, else copied; CSV and JSON files are written new. OUT is built in a hidden
folder beside it and renamed into place at the end, so a failed import leaves nothing behind.
Masks and depth are not part of the recorders' layouts: the result lists what the user still
has to fill (:func:`contact_viz.session.missing_inputs`, the same text the reader's errors use).

Kinds:

``dvrk``
    The layout of the JHU dVRK ``data_collection`` extractor (``extract -a -f png|jpg -S``):
    stereo frames ``<video>_left_<t>.png|jpg`` and ``<video>_right_<t>.png|jpg`` (t = epoch
    seconds), and one CSV per ROS topic, each starting with ``# Topic: ...`` and ``# Type: ...``
    lines, then a header whose first column ``timestamp`` is in nanoseconds followed by the
    flattened message fields. SRC is that folder (or a recording folder holding exactly one
    ``extracted/<target>/``). Frames get stems 000000, 000001, ... in time order and frames.csv
    their timestamps; force.csv keeps the force topic's own samples and times (s). The force
    topic is the CSV with ``wrench.force.x|y|z`` or ``force.x|y|z`` columns (chosen with
    ``force_topic`` when there are several). ``sensor_msgs/CameraInfo`` topics whose names
    contain "left" and "right" become left.yaml + right.yaml.
``yang2024``
    The data of Yang et al. (2024), "Vision-based force estimation for minimally invasive
    telesurgery through contact detection and local stiffness models": ``img_<n>.jpg`` left
    frames, ``right_img/img_<n>.jpg`` right frames and a header-less comma-separated
    ``labels_30hz.txt`` with one row per left frame: column 1 = time (s), columns 2-4 = force
    Fx, Fy, Fz (N). Stems are n zero-padded to 6 digits; force.csv is indexed by frame.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import shutil
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from decimal import Decimal
from pathlib import Path

import numpy as np

from contact_viz.calibration import CALIBRATION_FILES, read_calibration
from contact_viz.errors import SessionError

__all__ = [
    "IMPORTERS",
    "ImportResult",
    "import_dvrk",
    "import_yang2024",
    "run_import_command",
]

STEM_DIGITS = 6  # stems are frame numbers zero-padded to at least this many digits
NS_PER_S = 10**9  # nanoseconds per second
FORCE_COLUMNS = (("wrench.force.x", "wrench.force.y", "wrench.force.z"), ("force.x", "force.y", "force.z"))
YANG_LABELS = "labels_30hz.txt"
YANG_FORCE_COLUMNS = (1, 2, 3)  # 0-based columns of Fx, Fy, Fz in labels_30hz.txt (column 0 = time)
_DVRK_FRAME = re.compile(r"^(?P<video>.+)_(?P<side>left|right)_(?P<t>\d+(?:\.\d+)?)\.(?P<ext>png|jpe?g)$", re.I)
_YANG_FRAME = re.compile(r"^img_(?P<n>\d+)\.(?P<ext>jpe?g|png)$", re.I)
_CAMERA_INFO_FIELDS = {  # ROS 2 / ROS 1 flattened CameraInfo field prefixes -> YAML key, shape
    "camera_matrix": (("k", "K"), (3, 3)),
    "distortion_coefficients": (("d", "D"), None),
    "rectification_matrix": (("r", "R"), (3, 3)),
    "projection_matrix": (("p", "P"), (3, 4)),
}


# --------------------------------------------------------------------------------------------
# Result
# --------------------------------------------------------------------------------------------


@dataclass
class ImportResult:
    """What an import produced."""

    kind: str  # importer name
    source: Path  # SRC as resolved
    out: Path  # the new session directory
    frames: int  # frames imported
    placed: dict[str, int]  # how image files got into OUT: {"hardlink": n, "symlink": n, "copy": n}
    force_samples: int  # rows in force.csv (0 = no force.csv)
    notes: list[str] = field(default_factory=list)  # things the user should know (skipped files, ...)
    to_fill: list[str] = field(default_factory=list)  # what the session still lacks (missing_inputs)

    def lines(self) -> list[str]:
        """Human-readable report, one line each."""
        how = ", ".join(f"{n} {way}ed" if way != "copy" else f"{n} copied" for way, n in self.placed.items() if n)
        out = [f"{self.out}: {self.frames} frames imported from {self.source} ({self.kind}; images {how or 'none'})"]
        out.append(f"force.csv: {self.force_samples} samples" if self.force_samples else "no force.csv written")
        out.extend(f"note: {note}" for note in self.notes)
        if self.to_fill:
            out.append("still to fill before `contact-viz extract`:")
            out.extend(f"  - {line}" for line in self.to_fill)
        return out


# --------------------------------------------------------------------------------------------
# File operations
# --------------------------------------------------------------------------------------------


def _place(src: Path, dst: Path, copy: bool) -> str:
    """Put ``src`` at ``dst`` by hard link, else symbolic link, else copy; returns which was used."""
    if not copy:
        try:
            os.link(src, dst)
            return "hardlink"
        except OSError:
            pass
        try:
            os.symlink(src.resolve(), dst)
            return "symlink"
        except OSError:
            pass
    shutil.copy2(src, dst)
    return "copy"


@contextmanager
def _staging(src: Path, out: Path) -> Iterator[Path]:
    """A hidden folder beside ``out`` to build the session in; renamed to ``out`` on success."""
    src = src.resolve()
    out = out.expanduser().resolve()
    if out == src or src in out.parents:
        raise ValueError(f"{out}: the new session must not be inside the source folder {src} (it is never modified)")
    if out in src.parents:
        raise ValueError(f"{out}: the new session must not contain the source folder {src}")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"{out}: expected a new or empty folder for the imported session")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.import-{os.getpid()}-{time.monotonic_ns()}"
    tmp.mkdir()
    try:
        yield tmp
        if out.exists():
            out.rmdir()
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence[object]]) -> None:
    with open(path, "w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        writer.writerows(rows)


def _write_session_json(path: Path, name: str, kind: str, src: Path, times_s: Sequence[float], extra: dict) -> None:
    data = {"name": name, "import": {"kind": kind, "source": str(src), **extra}}
    if len(times_s) > 1:
        gap = float(np.median(np.diff(np.asarray(times_s, dtype=np.float64))))
        if math.isfinite(gap) and gap > 0:
            data["fps"] = round(1.0 / gap, 3)
    path.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")


def _place_calibration(files: Sequence[str | Path], tmp: Path, copy: bool) -> list[str]:
    """Link/copy user-given calibration files into the new session under their own names."""
    names = []
    for given in files:
        path = Path(given).expanduser()
        if path.name not in CALIBRATION_FILES:
            raise ValueError(
                f"{path}: a calibration file must be named one of {', '.join(CALIBRATION_FILES)} "
                "(see the README: calibration)"
            )
        if not path.is_file():
            raise SessionError(path, "missing: expected a calibration file")
        if (tmp / path.name).exists():
            raise ValueError(f"{path}: two calibration files named {path.name}")
        _place(path, tmp / path.name, copy)
        names.append(path.name)
    return names


def _image_size(path: Path) -> tuple[int, int]:
    from PIL import Image

    try:
        with Image.open(path) as image:
            width, height = image.size
    except (OSError, ValueError, SyntaxError) as exc:
        raise SessionError(path, f"expected a readable PNG/JPEG image ({type(exc).__name__}: {exc})") from exc
    return height, width


def _stem_width(count: int) -> int:
    return max(STEM_DIGITS, len(str(max(count - 1, 0))))


# --------------------------------------------------------------------------------------------
# dVRK data_collection
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _TopicCsv:
    path: Path
    topic: str
    type: str
    header: list[str]
    first_line: int  # 1-based line number of the header row


def _read_topic_header(path: Path) -> _TopicCsv | None:
    """The topic, type and column names of a data_collection topic CSV; None if ``path`` is not one."""
    try:
        with open(path, newline="", encoding="utf-8") as handle:
            first, second = handle.readline(), handle.readline()
            if not (first.startswith("# Topic:") and second.startswith("# Type:")):
                return None
            header = next(csv.reader([handle.readline()]), [])
    except (OSError, UnicodeDecodeError):
        return None
    return _TopicCsv(path, first[len("# Topic:"):].strip(), second[len("# Type:"):].strip(),
                     [c.strip() for c in header], 3)


def _topic_rows(info: _TopicCsv) -> Iterator[tuple[int, dict[str, str]]]:
    with open(info.path, newline="", encoding="utf-8") as handle:
        for _ in range(info.first_line):
            handle.readline()
        reader = csv.reader(handle)
        for offset, row in enumerate(reader):
            if not any(cell.strip() for cell in row):
                continue
            line = info.first_line + 1 + offset
            if len(row) != len(info.header):
                raise SessionError(
                    info.path, f"line {line}: expected {len(info.header)} values as in the header, found {len(row)}"
                )
            yield line, dict(zip(info.header, (cell.strip() for cell in row)))


def _ns_to_seconds_text(ns: int) -> str:
    """Integer nanoseconds as an exact decimal string of seconds ("1737146000.123456789")."""
    sign = "-" if ns < 0 else ""
    whole, frac = divmod(abs(ns), NS_PER_S)
    return f"{sign}{whole}.{frac:09d}"


def _find_dvrk_folder(src: Path) -> Path:
    """The folder holding the frames: SRC itself, or the single extracted/<target>/ (or subfolder) with frames."""
    def has_frames(folder: Path) -> bool:
        return any(_DVRK_FRAME.match(p.name) for p in folder.iterdir() if p.is_file())

    if has_frames(src):
        return src
    candidates = []
    for parent in (src / "extracted", src):
        if parent.is_dir():
            candidates += [d for d in sorted(parent.iterdir()) if d.is_dir() and has_frames(d)]
    candidates = list(dict.fromkeys(candidates))
    if len(candidates) == 1:
        return candidates[0]
    if not candidates:
        raise SessionError(
            src, "expected dVRK data_collection stereo frames <video>_left_<t>.png|jpg and <video>_right_<t>.png|jpg "
            "(extract with -f png or -f jpg and -S to split side-by-side video), found none here or in extracted/*/"
        )
    raise SessionError(
        src, f"expected one extraction folder, found several with frames: {', '.join(str(c) for c in candidates)}; "
        "pass one of them as SRC"
    )


_DvrkFrame = tuple[Decimal, str, Path, Path | None]  # (time s, time text, left file, right file or None)


def _dvrk_frames(folder: Path, video: str | None, notes: list[str]) -> tuple[str, list[_DvrkFrame]]:
    """(video, [(time, time text, left file, right file or None)] sorted by time)."""
    by_video: dict[str, dict[str, dict[str, Path]]] = {}
    for path in folder.iterdir():
        match = _DVRK_FRAME.match(path.name)
        if match and path.is_file():
            sides = by_video.setdefault(match["video"], {}).setdefault(match["t"], {})
            side = match["side"].lower()
            if side in sides:
                raise SessionError(
                    folder, f"expected one {side} image per time, found {sides[side].name} and {path.name}"
                )
            sides[side] = path
    stereo_videos = sorted(v for v, times in by_video.items() if any("left" in s for s in times.values()))
    if video is None:
        if len(stereo_videos) > 1:
            raise SessionError(
                folder, f"expected frames of one video, found {', '.join(stereo_videos)}; choose one with --video"
            )
        video = stereo_videos[0]
    elif video not in by_video:
        raise SessionError(folder, f"expected frames of video {video!r} (<video>_left_<t>.png), found videos "
                                   f"{', '.join(sorted(by_video)) or 'none'}")
    frames = []
    right_only = 0
    for t_text, sides in by_video[video].items():
        if "left" not in sides:
            right_only += 1
            continue
        frames.append((Decimal(t_text), t_text, sides["left"], sides.get("right")))
    frames.sort(key=lambda f: f[0])
    no_right = sum(1 for f in frames if f[3] is None)
    if right_only:
        notes.append(f"{right_only} right image(s) without a left image at the same time were skipped")
    if no_right:
        notes.append(f"{no_right} frame(s) have no right image (no SGBM depth for them)")
    if not frames:
        raise SessionError(folder, f"expected left frames {video}_left_<t>.png|jpg, found only right ones")
    return video, frames


def _choose_force_topic(
    topics: list[_TopicCsv], force_topic: str | None, folder: Path
) -> tuple[_TopicCsv, tuple[str, str, str]] | None:
    """The force topic CSV and its x, y, z columns: ``force_topic`` if given, else the only one; None if none."""

    def columns(info: _TopicCsv):
        return next((cols for cols in FORCE_COLUMNS if all(c in info.header for c in cols)), None)

    if force_topic is not None:
        wanted = force_topic.strip()
        flat = wanted.replace("/", "_").strip("_")
        for info in topics:
            if wanted in (info.topic, info.path.name, info.path.stem) or flat == info.path.stem:
                cols = columns(info)
                if cols is None:
                    raise SessionError(
                        info.path, f"expected force columns {' / '.join(', '.join(c) for c in FORCE_COLUMNS)} in "
                        f"topic {info.topic}, found columns {info.header[:12]}"
                    )
                return info, cols
        raise SessionError(
            folder, f"expected a CSV of topic {force_topic!r}, found topics "
            f"{', '.join(sorted(i.topic for i in topics)) or 'none'}"
        )
    found = [(info, columns(info)) for info in topics if columns(info) is not None]
    if len(found) > 1:
        raise SessionError(
            folder, f"expected one force topic, found several with force columns: "
            f"{', '.join(sorted(i.topic for i, _ in found))}; choose one with --force-topic"
        )
    return found[0] if found else None


def _read_force(info: _TopicCsv, cols: tuple[str, str, str]) -> list[tuple[str, str, str, str]]:
    """Rows (timestamp s as exact text, fx, fy, fz) of a topic CSV; bad numbers are a SessionError."""
    rows = []
    for line, row in _topic_rows(info):
        try:
            ns = int(row["timestamp"])
        except ValueError:
            raise SessionError(
                info.path, f"line {line}: expected an integer timestamp in nanoseconds, found {row['timestamp']!r}"
            ) from None
        values = []
        for col in cols:
            try:
                value = float(row[col]) if row[col] != "" else math.nan
            except ValueError:
                raise SessionError(
                    info.path, f"line {line}: expected a number (N) in {col!r}, found {row[col]!r}"
                ) from None
            if math.isinf(value):
                raise SessionError(
                    info.path, f"line {line}: expected a finite number (N) in {col!r}, found {row[col]!r}"
                )
            values.append(repr(value) if math.isfinite(value) else "nan")
        rows.append((_ns_to_seconds_text(ns), *values))
    return rows


def _camera_info_yaml(info: _TopicCsv) -> str | None:
    """left/right.yaml text from the first message of a CameraInfo topic CSV (None if it has no rows)."""
    first = next(_topic_rows(info), None)
    if first is None:
        return None
    line, row = first

    def numbers(prefixes: tuple[str, ...]) -> list[float]:
        for prefix in prefixes:
            keys = sorted((k for k in row if re.fullmatch(rf"{prefix}\.\d+", k)), key=lambda k: int(k.split(".")[1]))
            if keys:
                return [float(row[k]) for k in keys]
        return []

    width = row.get("width") or row.get("image_width")
    height = row.get("height") or row.get("image_height")
    if not width or not height:
        raise SessionError(info.path, f"line {line}: expected width and height columns in the CameraInfo topic")
    out = [f"image_width: {int(float(width))}", f"image_height: {int(float(height))}", f"camera_name: {info.topic}"]
    model = row.get("distortion_model") or "plumb_bob"
    for key, (prefixes, shape) in _CAMERA_INFO_FIELDS.items():
        values = numbers(prefixes)
        if shape is not None and len(values) != shape[0] * shape[1]:
            raise SessionError(
                info.path, f"line {line}: expected {shape[0] * shape[1]} values {prefixes[0]}.0..., found {len(values)}"
            )
        rows_, cols_ = shape if shape is not None else (1, len(values))
        if key == "distortion_coefficients":
            out.append(f"distortion_model: {model}")
        data = ", ".join(repr(v) for v in values)
        out.append(f"{key}:\n  rows: {rows_}\n  cols: {cols_}\n  data: [{data}]")
    return "\n".join(out) + "\n"


def import_dvrk(
    src: str | Path,
    out: str | Path,
    *,
    force_topic: str | None = None,
    video: str | None = None,
    calibration: Sequence[str | Path] = (),
    copy: bool = False,
) -> ImportResult:
    """Import a dVRK data_collection extraction folder ``src`` as a new session ``out``.

    ``force_topic``: the force topic's name (or its CSV file name) when several CSVs have force
    columns; ``video``: the video name when frames of several videos are present;
    ``calibration``: calibration files to put into the session (named as CALIBRATION_FILES);
    ``copy``: copy images instead of linking them. Raises SessionError for a malformed source,
    ValueError for bad arguments (e.g. ``out`` exists and is not empty).
    """
    from contact_viz.session import missing_inputs

    src = Path(src).expanduser()
    if not src.is_dir():
        raise SessionError(src, "missing: expected the dVRK data_collection extraction folder")
    src = src.resolve()
    folder = _find_dvrk_folder(src)
    notes: list[str] = []
    video, frames = _dvrk_frames(folder, video, notes)
    topics = [t for t in (_read_topic_header(p) for p in sorted(folder.glob("*.csv"))) if t is not None]
    chosen = _choose_force_topic(topics, force_topic, folder)
    force_rows = _read_force(*chosen) if chosen else []
    if chosen is None:
        notes.append("no topic CSV with force columns (wrench.force.x|y|z or force.x|y|z): no force.csv, no labels")
    width = _stem_width(len(frames))
    stems = [f"{i:0{width}d}" for i in range(len(frames))]
    placed = {"hardlink": 0, "symlink": 0, "copy": 0}
    out_path = Path(out)
    with _staging(src, out_path) as tmp:
        (tmp / "left").mkdir()
        if any(f[3] is not None for f in frames):
            (tmp / "right").mkdir()
        for stem, (_, _, left, right) in zip(stems, frames):
            placed[_place(left, tmp / "left" / f"{stem}{left.suffix.lower()}", copy)] += 1
            if right is not None:
                placed[_place(right, tmp / "right" / f"{stem}{right.suffix.lower()}", copy)] += 1
        _write_csv(tmp / "frames.csv", ("frame", "timestamp"), [(s, f[1]) for s, f in zip(stems, frames)])
        if force_rows:
            _write_csv(tmp / "force.csv", ("timestamp", "fx", "fy", "fz"), force_rows)
            sample_times = [Decimal(row[0]) for row in force_rows]
            lo, hi = min(sample_times), max(sample_times)
            if frames[-1][0] < lo or frames[0][0] > hi:
                notes.append(f"the force samples ({lo}-{hi} s) do not overlap the frames ({frames[0][1]}-"
                             f"{frames[-1][1]} s): different clocks?")
            notes.append(f"force from topic {chosen[0].topic} ({chosen[0].path.name}), columns {', '.join(chosen[1])}")
        calib_names = _place_calibration(calibration, tmp, copy)
        if not calib_names:
            calib_names = _camera_info_calibration(topics, tmp, notes)
        if calib_names:
            read_calibration(tmp, _image_size(frames[0][2]))  # fail now, with the file named, if it is wrong
        extra = {"video": video, "force_topic": chosen[0].topic if chosen else None}
        _write_session_json(tmp / "session.json", out_path.name, "dvrk", folder, [float(f[0]) for f in frames], extra)
    out_path = out_path.expanduser().resolve()
    return ImportResult("dvrk", folder, out_path, len(frames), placed, len(force_rows), notes, missing_inputs(out_path))


def _camera_info_calibration(topics: list[_TopicCsv], tmp: Path, notes: list[str]) -> list[str]:
    """left.yaml + right.yaml from CameraInfo topic CSVs whose names say left and right (if both exist)."""
    infos = [t for t in topics if t.type.replace("/msg/", "/").endswith("sensor_msgs/CameraInfo")]
    left = [t for t in infos if "left" in t.topic.lower()]
    right = [t for t in infos if "right" in t.topic.lower()]
    if len(left) != 1 or len(right) != 1:
        if infos:
            notes.append(f"CameraInfo topics {', '.join(t.topic for t in infos)} not used: expected exactly one "
                         "with 'left' and one with 'right' in its name")
        return []
    texts = [_camera_info_yaml(left[0]), _camera_info_yaml(right[0])]
    if None in texts:
        return []
    (tmp / "left.yaml").write_text(texts[0], encoding="utf-8")
    (tmp / "right.yaml").write_text(texts[1], encoding="utf-8")
    notes.append(f"calibration from {left[0].topic} and {right[0].topic} written as left.yaml + right.yaml")
    return ["left.yaml", "right.yaml"]


# --------------------------------------------------------------------------------------------
# Yang et al. 2024
# --------------------------------------------------------------------------------------------


def _read_yang_labels(path: Path) -> list[list[str]]:
    """Rows of labels_30hz.txt as lists of number strings (at least 4 columns, all numeric)."""
    if not path.is_file():
        raise SessionError(
            path, "missing: expected the header-less labels_30hz.txt (column 1 time in s, columns 2-4 Fx, Fy, Fz in N)"
        )
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SessionError(path, f"expected a readable text file ({exc})") from exc
    rows = []
    for line_no, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        cells = [c.strip() for c in re.split(r"[,\s]+", line.strip()) if c.strip()]
        if len(cells) < 1 + len(YANG_FORCE_COLUMNS):
            raise SessionError(path, f"line {line_no}: expected at least 4 comma-separated numbers "
                                     f"(time, Fx, Fy, Fz), found {len(cells)}")
        for cell in cells[: 1 + len(YANG_FORCE_COLUMNS)]:
            try:
                value = float(cell)
            except ValueError:
                raise SessionError(path, f"line {line_no}: expected a number, found {cell!r}") from None
            if not math.isfinite(value):
                raise SessionError(path, f"line {line_no}: expected a finite number, found {cell!r}")
        rows.append(cells)
    if not rows:
        raise SessionError(path, "expected one row per left frame (time, Fx, Fy, Fz, ...), found an empty file")
    return rows


def import_yang2024(
    src: str | Path,
    out: str | Path,
    *,
    calibration: Sequence[str | Path] = (),
    copy: bool = False,
) -> ImportResult:
    """Import one recording of Yang et al. (2024) (``img_<n>.jpg``, ``right_img/``, ``labels_30hz.txt``).

    Row n of labels_30hz.txt belongs to img_<n>.jpg: its time (column 1) goes to frames.csv and
    its force (columns 2-4) to force.csv, indexed by frame. ``calibration`` and ``copy`` as in
    :func:`import_dvrk`.
    """
    from contact_viz.session import missing_inputs

    src = Path(src).expanduser()
    if not src.is_dir():
        raise SessionError(src, "missing: expected a Yang et al. 2024 recording folder (img_<n>.jpg, labels_30hz.txt)")
    src = src.resolve()
    rows = _read_yang_labels(src / YANG_LABELS)
    left = {int(m["n"]): p for p in src.iterdir() if p.is_file() and (m := _YANG_FRAME.match(p.name))}
    right_dir = src / "right_img"
    right = ({int(m["n"]): p for p in right_dir.iterdir() if p.is_file() and (m := _YANG_FRAME.match(p.name))}
             if right_dir.is_dir() else {})
    if not left:
        raise SessionError(src, "expected left frames img_<n>.jpg, found none")
    numbers = sorted(left)
    beyond = [n for n in numbers if n >= len(rows)]
    if beyond:
        raise SessionError(
            src / YANG_LABELS, f"expected a row for every left frame: {len(rows)} rows, but img_{beyond[0]} needs "
            f"row {beyond[0] + 1} ({len(beyond)} frame(s) without a row)"
        )
    notes = []
    if len(rows) > len(numbers):
        notes.append(f"{len(rows) - len(numbers)} row(s) of {YANG_LABELS} have no left image and were skipped")
    no_right = [n for n in numbers if n not in right]
    if no_right:
        notes.append(f"{len(no_right)} frame(s) have no right_img/ image (no SGBM depth for them)")
    orphans = sorted(set(right) - set(left))
    if orphans:
        notes.append(f"{len(orphans)} right_img/ image(s) without a left image were skipped")
    times = [float(rows[n][0]) for n in numbers]
    if any(b <= a for a, b in zip(times, times[1:])):
        notes.append(f"the times in {YANG_LABELS} are not strictly increasing")
    notes.append("force is the sensor's latest value at each left frame (the recorder wrote zeros before the "
                 "first sensor message)")
    width = _stem_width(numbers[-1] + 1)
    placed = {"hardlink": 0, "symlink": 0, "copy": 0}
    out_path = Path(out)
    with _staging(src, out_path) as tmp:
        (tmp / "left").mkdir()
        if right:
            (tmp / "right").mkdir()
        frame_rows, force_rows = [], []
        for n in numbers:
            stem = f"{n:0{width}d}"
            placed[_place(left[n], tmp / "left" / f"{stem}{left[n].suffix.lower()}", copy)] += 1
            if n in right:
                placed[_place(right[n], tmp / "right" / f"{stem}{right[n].suffix.lower()}", copy)] += 1
            frame_rows.append((stem, rows[n][0]))
            force_rows.append((stem, *(rows[n][c] for c in YANG_FORCE_COLUMNS)))
        _write_csv(tmp / "frames.csv", ("frame", "timestamp"), frame_rows)
        _write_csv(tmp / "force.csv", ("frame", "fx", "fy", "fz"), force_rows)
        if _place_calibration(calibration, tmp, copy):
            read_calibration(tmp, _image_size(left[numbers[0]]))
        _write_session_json(tmp / "session.json", out_path.name, "yang2024", src, times, {})
    out_path = out_path.expanduser().resolve()
    return ImportResult(
        "yang2024", src, out_path, len(numbers), placed, len(force_rows), notes, missing_inputs(out_path)
    )


# --------------------------------------------------------------------------------------------
# Command
# --------------------------------------------------------------------------------------------

IMPORTERS: dict[str, Callable[..., ImportResult]] = {"dvrk": import_dvrk, "yang2024": import_yang2024}


def run_import_command(
    kind: str,
    src: str | Path,
    out: str | Path,
    *,
    force_topic: str | None = None,
    video: str | None = None,
    calibration: Sequence[str | Path] = (),
    copy: bool = False,
) -> list[str]:
    """`contact-viz import KIND SRC OUT_SESSION`: returns the lines to print.

    Raises ValueError (bad arguments) or SessionError (malformed source) with the message to show.
    """
    if kind not in IMPORTERS:
        raise ValueError(f"KIND must be one of {', '.join(IMPORTERS)}, got {kind!r}")
    if kind == "yang2024":
        unused = [name for name, value in (("--force-topic", force_topic), ("--video", video)) if value is not None]
        if unused:
            raise ValueError(f"{', '.join(unused)} only apply to dvrk imports")
        result = import_yang2024(src, out, calibration=calibration, copy=copy)
    else:
        result = import_dvrk(src, out, force_topic=force_topic, video=video, calibration=calibration, copy=copy)
    return result.lines()
