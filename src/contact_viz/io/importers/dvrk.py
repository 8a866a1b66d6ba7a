"""The JHU dVRK ``data_collection`` extraction layout (see the package docstring)."""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from decimal import Decimal
from pathlib import Path


from contact_viz.io.calibration import read_calibration
from contact_viz.errors import SessionError

from contact_viz.io.decoders import read_image_size
from contact_viz.io.importers.common import FORCE_COLUMNS, ImportResult, NS_PER_S, _CAMERA_INFO_FIELDS, _DVRK_FRAME, _place, _place_calibration, _staging, _stem_width, _write_csv, _write_session_json

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
    from contact_viz.io.session import missing_inputs

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
            read_calibration(tmp, read_image_size(frames[0][2]))  # fail now, with the file named, if it is wrong
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


