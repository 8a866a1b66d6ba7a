"""The small files of a session: session.json, frames.csv, force.csv, labels.csv; which layer folders exist.

Pure readers: each returns arrays or raises one :class:`SessionError` naming the file.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from contact_viz.io.calibration import StereoCalibration
from contact_viz.errors import SessionError, SessionWarning
from contact_viz.params import LabelParams


_SESSION_JSON_KEYS = ("name", "phantom", "task", "fps")

# --------------------------------------------------------------------------------------------
# Small pure helpers
# --------------------------------------------------------------------------------------------

_DIGIT_RUNS = re.compile(r"(\d+)")


def natural_key(stem: str) -> tuple:
    """Sort key ordering stems by their numbers: "2" < "10", "frame_000012" by 12.

    Digit runs compare as integers, other runs as strings; the full stem breaks ties
    ("01" vs "1") so the order is total and deterministic.
    """
    parts = _DIGIT_RUNS.split(stem)  # text, digits, text, digits, ...
    key = tuple((0, int(part), "") if i % 2 else (1, 0, part) for i, part in enumerate(parts) if part)
    return key, stem


def _as_int(text: str) -> int | None:
    """``text`` as a non-negative integer if it is one (digits only), else None."""
    return int(text) if text.isdigit() else None


def _match_stems(csv_path: Path, names: Sequence[str], stems: Sequence[str]) -> np.ndarray:
    """Index into ``stems`` for each frame name in a CSV, -1 where it matches no stem.

    A name matches a stem by exact string first, then by integer value when both are integers
    ("12" matches "000012"). Returns (len(names),) int64.
    """
    exact = {stem: i for i, stem in enumerate(stems)}
    by_int: dict[int, list[int]] = {}
    for i, stem in enumerate(stems):
        value = _as_int(stem)
        if value is not None:
            by_int.setdefault(value, []).append(i)
    out = np.full(len(names), -1, dtype=np.int64)
    for row, name in enumerate(names):
        if name in exact:
            out[row] = exact[name]
            continue
        value = _as_int(name)
        candidates = by_int.get(value, []) if value is not None else []
        if len(candidates) == 1:
            out[row] = candidates[0]
        elif len(candidates) > 1:
            raise SessionError(
                csv_path,
                f"frame {name!r} matches several stems by number ({', '.join(stems[i] for i in candidates)}); "
                "write the stem exactly as in left/",
            )
    return out


def _warn_unmatched(csv_path: Path, names: Sequence[str], matched: np.ndarray) -> None:
    """Warn (SessionWarning) about CSV frame names that are not stems in left/."""
    missing = [names[i] for i in np.flatnonzero(matched < 0)]
    if missing:
        shown = ", ".join(missing[:5]) + (" ..." if len(missing) > 5 else "")
        warnings.warn(
            f"{csv_path}: {len(missing)} frame(s) not found in left/ were ignored: {shown}",
            SessionWarning,
            stacklevel=4,
        )


def _check_unique(csv_path: Path, names: Sequence[str], matched: np.ndarray) -> None:
    """One row per frame: two rows naming the same stem are an error."""
    seen: dict[int, str] = {}
    for name, idx in zip(names, matched.tolist()):
        if idx < 0:
            continue
        if idx in seen:
            raise SessionError(
                csv_path, f"expected one row per frame, found frame {seen[idx]!r} and {name!r} for the same stem"
            )
        seen[idx] = name


def nearest_indices(sample_t: np.ndarray, query_t: np.ndarray) -> np.ndarray:
    """Index of the nearest entry of sorted ``sample_t`` (m,) to each of ``query_t`` (n,); ties go earlier.

    Vectorized with np.searchsorted. Returns (n,) int64. ``sample_t`` must be non-empty and ascending.
    """
    last = len(sample_t) - 1
    after = np.searchsorted(sample_t, query_t, side="left")  # first sample >= query
    hi = np.clip(after, 0, last)
    lo = np.clip(after - 1, 0, last)
    take_lo = np.abs(query_t - sample_t[lo]) <= np.abs(sample_t[hi] - query_t)
    return np.where(take_lo, lo, hi)


def force_labels(force_n: np.ndarray, params: LabelParams) -> np.ndarray:
    """Contact labels from force magnitude (n,) N: 1 where >= threshold, 0 below, -1 where NaN. (n,) int8."""
    labels = np.full(force_n.shape, -1, dtype=np.int8)
    known = np.isfinite(force_n)
    labels[known] = (force_n[known] >= params.contact_force_n).astype(np.int8)
    return labels


# --------------------------------------------------------------------------------------------
# Session-wide files
# --------------------------------------------------------------------------------------------


def _read_session_json(path: Path) -> dict:
    """session.json as a dict with validated name/phantom/task (str or None) and fps (> 0)."""
    if not path.exists():
        return {}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SessionError(
            path, f"expected valid JSON {{\"name\", \"phantom\", \"task\", \"fps\"}}, could not parse it ({exc})"
        ) from exc
    if not isinstance(data, dict):
        raise SessionError(
            path, f"expected a JSON object with keys {list(_SESSION_JSON_KEYS)}, found {type(data).__name__}"
        )
    # Other keys (e.g. the generator's settings in synthetic sessions) are free-form metadata.
    for key in ("name", "phantom", "task"):
        if data.get(key) is not None and not isinstance(data[key], str):
            raise SessionError(path, f"expected \"{key}\" to be a string, found {data[key]!r}")
    if "fps" in data:
        fps = data["fps"]
        if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not (math.isfinite(fps) and fps > 0):
            raise SessionError(path, f"expected \"fps\" to be a positive number (frames/s), found {fps!r}")
    return data


def _read_csv(path: Path) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """A CSV with a header row: (lower-cased column names, [(line number, cells)]); blank rows skipped."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:
            rows = list(_numbered_rows(csv.reader(handle, skipinitialspace=True)))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise SessionError(
            path, f"expected a readable CSV file with a header row, could not read it ({exc})"
        ) from exc
    if not rows:
        raise SessionError(path, "expected a CSV file with a header row, found an empty file")
    header = [cell.strip().lower() for cell in rows[0][1]]
    body = []
    for line, row in rows[1:]:
        cells = [cell.strip() for cell in row]
        if len(cells) != len(header):
            raise SessionError(
                path, f"line {line}: expected {len(header)} values ({', '.join(header)}), found {len(cells)}"
            )
        body.append((line, cells))
    return header, body


def _numbered_rows(reader) -> Iterator[tuple[int, list[str]]]:
    """Non-blank CSV rows with their 1-based line numbers."""
    for row in reader:
        if any(cell.strip() for cell in row):
            yield reader.line_num, row


def _require_columns(path: Path, header: list[str], needed: Sequence[str], what: str) -> None:
    missing = [c for c in needed if c not in header]
    if missing:
        raise SessionError(
            path,
            f"expected columns {', '.join(needed)} ({what}); missing {', '.join(missing)}; found columns {header}",
        )


def _column_floats(
    path: Path, header: list[str], body: list[tuple[int, list[str]]], column: str, unit: str
) -> np.ndarray:
    """One CSV column as (rows,) float64; "nan" is allowed (unknown), anything else non-numeric is an error."""
    col = header.index(column)
    out = np.empty(len(body), dtype=np.float64)
    for r, (line, cells) in enumerate(body):
        try:
            value = float(cells[col])
        except ValueError:
            raise SessionError(
                path, f"line {line}: expected a number ({unit}) in column {column!r}, found {cells[col]!r}"
            ) from None
        if math.isinf(value):
            raise SessionError(
                path, f"line {line}: expected a finite number ({unit}) in column {column!r}, found {cells[col]!r}"
            )
        out[r] = value
    return out


def _read_frames_csv(path: Path, stems: list[str]) -> np.ndarray:
    """frames.csv -> (n,) float64 timestamps, s, one per stem (every stem must have one)."""
    header, body = _read_csv(path)
    _require_columns(path, header, ("frame", "timestamp"), "frame stem, timestamp in seconds")
    names = [cells[header.index("frame")] for _, cells in body]
    times = _column_floats(path, header, body, "timestamp", "seconds")
    if np.isnan(times).any():
        line = body[int(np.flatnonzero(np.isnan(times))[0])][0]
        raise SessionError(path, f"line {line}: expected a timestamp in seconds, found nan")
    matched = _match_stems(path, names, stems)
    _check_unique(path, names, matched)
    _warn_unmatched(path, names, matched)
    out = np.full(len(stems), np.nan)
    ok = matched >= 0
    out[matched[ok]] = times[ok]
    missing = [stems[i] for i in np.flatnonzero(np.isnan(out))]
    if missing:
        shown = ", ".join(missing[:5]) + (" ..." if len(missing) > 5 else "")
        raise SessionError(path, f"expected a timestamp for every frame in left/, missing {len(missing)}: {shown}")
    check_times_increase(path, stems, out, {int(i): line for (line, _), i in zip(body, matched.tolist()) if i >= 0})
    return out


def check_times_increase(path: Path, stems: list[str], times_s: np.ndarray, line_of: dict[int, int]) -> None:
    """SessionError naming the lines when frame times (in frame order) go backwards or repeat:
    the causal filter runs in frame order, so the `time` timeline must follow it."""
    bad = np.flatnonzero(np.diff(times_s) <= 0)
    if not bad.size:
        return
    i = int(bad[0])
    verb = "repeats" if times_s[i + 1] == times_s[i] else "goes back from"
    more = f" ({bad.size} such places)" if bad.size > 1 else ""
    raise SessionError(
        path,
        f"line {line_of[i + 1]}: the time of frame {stems[i + 1]!r} ({times_s[i + 1]:.6g} s) {verb} that of the "
        f"frame before it, {stems[i]!r} on line {line_of[i]} ({times_s[i]:.6g} s){more}; expected times that "
        "increase in frame order (frames are ordered by the numbers in their stems)",
    )


def _read_force_csv(path: Path, stems: list[str], timestamps_s: np.ndarray | None, frames_csv: Path) -> np.ndarray:
    """force.csv -> (n, 3) float64 force per frame, N; NaN where no sample is matched.

    Indexed by ``frame``: rows matched to stems (see _match_stems). Indexed by ``timestamp``:
    nearest sample to each frame time, for frames inside the force recording's span widened by
    one median force sampling interval on each side (frames farther out get NaN).
    ``timestamps_s`` are the frame times from frames.csv (None when there is no frames.csv).
    """
    header, body = _read_csv(path)
    key = "frame" if "frame" in header else "timestamp" if "timestamp" in header else None
    missing = ([] if key else ["frame or timestamp"]) + [c for c in ("fx", "fy", "fz") if c not in header]
    if missing:
        raise SessionError(
            path,
            f"expected a 'frame' (stem) or 'timestamp' (s) column plus fx, fy, fz (N); "
            f"missing {', '.join(missing)}; found columns {header}",
        )
    xyz = np.stack([_column_floats(path, header, body, c, "newtons") for c in ("fx", "fy", "fz")], axis=1)
    force = np.full((len(stems), 3), np.nan)
    if key == "frame":
        names = [cells[header.index("frame")] for _, cells in body]
        matched = _match_stems(path, names, stems)
        _check_unique(path, names, matched)
        _warn_unmatched(path, names, matched)
        ok = matched >= 0
        force[matched[ok]] = xyz[ok]
        return force
    if timestamps_s is None:
        raise SessionError(
            frames_csv, f"missing: {path.name} is indexed by timestamp, so frames.csv (frame,timestamp in seconds) "
            "is needed to match force samples to frames"
        )
    sample_t = _column_floats(path, header, body, "timestamp", "seconds")
    if np.isnan(sample_t).any():
        line = body[int(np.flatnonzero(np.isnan(sample_t))[0])][0]
        raise SessionError(path, f"line {line}: expected a timestamp in seconds, found nan")
    if len(sample_t) == 0:
        return force
    order = np.argsort(sample_t, kind="stable")
    sample_t, xyz = sample_t[order], xyz[order]
    gap_s = float(np.median(np.diff(sample_t))) if len(sample_t) > 1 else 0.0
    inside = (timestamps_s >= sample_t[0] - gap_s) & (timestamps_s <= sample_t[-1] + gap_s)
    nearest = nearest_indices(sample_t, timestamps_s)
    force[inside] = xyz[nearest[inside]]
    return force


def _read_labels_csv(path: Path, stems: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """labels.csv -> (frame indices (k,) int64, contact (k,) int8 in {0, 1}, object ids (k,) int64 or None).

    With a ``tool`` column (frame,tool,contact) each row labels one instrument of a frame (one row per
    frame and instrument); without one (None), each row labels the frame (one row per frame)."""
    header, body = _read_csv(path)
    _require_columns(path, header, ("frame", "contact"), "frame stem, contact 0/1")
    fcol, ccol = header.index("frame"), header.index("contact")
    tcol = header.index("tool") if "tool" in header else None
    names = [cells[fcol] for _, cells in body]
    contact = np.empty(len(body), dtype=np.int8)
    for r, (line, cells) in enumerate(body):
        if cells[ccol] not in ("0", "1"):
            raise SessionError(path, f"line {line}: expected contact 0 or 1, found {cells[ccol]!r}")
        contact[r] = int(cells[ccol])
    tools = None
    if tcol is not None:
        tools = np.empty(len(body), dtype=np.int64)
        for r, (line, cells) in enumerate(body):
            tool = _as_int(cells[tcol].strip())
            if tool is None or tool < 1:
                raise SessionError(path, f"line {line}: expected the instrument's object id (an integer >= 1) in "
                                         f"column tool, found {cells[tcol]!r}")
            tools[r] = tool
    matched = _match_stems(path, names, stems)
    if tools is None:
        _check_unique(path, names, matched)
    else:
        seen: dict[tuple[int, int], str] = {}
        for name, idx, tool in zip(names, matched.tolist(), tools.tolist()):
            if idx >= 0 and (idx, tool) in seen:
                raise SessionError(path, f"expected one row per frame and instrument, found frame {seen[idx, tool]!r} "
                                         f"and {name!r} for the same stem and tool {tool}")
            seen[idx, tool] = name
    _warn_unmatched(path, names, matched)
    ok = matched >= 0
    return matched[ok], contact[ok], None if tools is None else tools[ok]


def tool_label_arrays(n_frames: int, index: np.ndarray, contact: np.ndarray, tools: np.ndarray,
                      selected: Sequence[int] | None) -> tuple[dict[int, np.ndarray], np.ndarray, np.ndarray]:
    """labels.csv's per-instrument rows (from ``_read_labels_csv``) as ({object id: (n,) int8, -1 where it
    has no row}, frame indices, scene contact): the scene label of a frame is 1 when any instrument it
    labels is in contact, else 0. Only the ``selected`` object ids count (None = all)."""
    keep = np.ones(tools.shape, dtype=bool) if selected is None else np.isin(tools, list(selected))
    index, contact, tools = index[keep], contact[keep], tools[keep]
    per_tool = {}
    for tool in np.unique(tools).tolist():
        labels = np.full(n_frames, -1, dtype=np.int8)
        labels[index[tools == tool]] = contact[tools == tool]
        per_tool[int(tool)] = labels
    frames = np.unique(index)
    scene = np.zeros(n_frames, dtype=np.int8)
    np.maximum.at(scene, index, contact)
    return per_tool, frames, scene[frames]


def _list_stems(directory: Path, suffixes: Sequence[str]) -> dict[str, Path]:
    """stem -> file for the files in ``directory`` whose lower-cased suffix is in ``suffixes``.

    Two files with the same stem (e.g. 7.png and 7.jpg) are an error.
    """
    found: dict[str, Path] = {}
    try:
        entries = list(os.scandir(directory))
    except OSError as exc:
        raise SessionError(directory, f"expected a readable directory, could not list it ({exc.strerror or exc})"
                           ) from None
    for entry in sorted(entries, key=lambda e: e.name):
        suffix = os.path.splitext(entry.name)[1]
        if suffix.lower() not in suffixes:
            continue
        try:
            is_file = entry.is_file()
        except OSError as exc:  # e.g. a symbolic link loop
            raise SessionError(entry.path, f"expected a {suffix} file, could not follow it "
                                           f"({exc.strerror or exc})") from None
        if not is_file:
            continue
        stem = entry.name[: -len(suffix)]
        if stem in found:
            raise SessionError(
                directory, f"expected one file per frame, found both {found[stem].name} and {entry.name}"
            )
        found[stem] = Path(entry.path)
    return found


_MASKS_HINT = (
    "masks/<stem>.png: the tool masks (e.g. from SAM2), one per left frame "
    "(palettized PNG with object ids, or 8-bit 0/255)"
)
_DEPTH_HINT = (
    "depth/<stem>.npy (float32 metres, e.g. FoundationStereo's depth_meter.npy) or depth/<stem>.png "
    "(uint16 millimetres), or disparity/<stem>.npy (float32 px, FoundationStereo's raw disparity); "
    "FoundationStereo is recommended"
)


def missing_inputs(root: str | Path) -> list[str]:
    """What session ``root`` still lacks before `contact-viz extract` can run on it, one line each.

    Checks masks/, a depth source (depth/, disparity/, or right/ for SGBM) and a calibration file;
    an empty list means nothing is missing. Importers print this; the reader's errors say the same.
    """
    from contact_viz.io.calibration import calibration_files

    root = Path(root)
    out = []
    if not (root / "masks").is_dir():
        out.append(_MASKS_HINT)
    has_depth = any(
        (root / sub).is_dir() and any((root / sub).iterdir()) for sub in ("depth", "disparity")
    )
    if not has_depth:
        has_right = (root / "right").is_dir() and any((root / "right").iterdir())
        fallback = ("; without them depth is computed from left/ + right/ with OpenCV SGBM (much worse)"
                    if has_right else "; there is no right/ to compute SGBM depth from, so one of them is needed")
        out.append(_DEPTH_HINT + fallback)
    if not calibration_files(root):
        out.append("K.txt (or left.yaml + right.yaml, or stereo.yaml): the stereo calibration")
    return out


def _find_masks(root: Path, required: bool = True) -> dict[str, Path]:
    """stem -> tool mask file (masks/<stem>.png); {} when masks/ is absent and not ``required``."""
    masks_dir = root / "masks"
    if not masks_dir.is_dir():
        if not required:
            return {}
        still = [line for line in missing_inputs(root) if not line.startswith("masks/")]
        also = ("; still to fill as well: " + "; ".join(still)) if still else ""
        raise SessionError(masks_dir, f"missing: {_MASKS_HINT}{also}")
    return _list_stems(masks_dir, (".png",))


@dataclass(frozen=True)
class _DepthSource:
    """Where a session's depth comes from (one choice per session)."""

    kind: str  # one of DEPTH_SOURCES
    files: dict[str, Path]  # stem -> depth or disparity file ({} for sgbm)
    note: str  # one line for logs and the CLI


def find_depth_source(
    root: Path,
    right_files: dict[str, Path],
    stereo: StereoCalibration,
    depth_method: str | None = "sgbm",
) -> _DepthSource:
    """Choose the session's depth source: depth/, else disparity/, else ``depth_method`` from right/.

    This is the one place that decides the depth source; new sources are added here. A folder
    counts only if it holds files of its kind. Raises SessionError listing the options when
    there is none (or disparity/ comes with a calibration whose images still need rectifying).
    """
    depth_dir = root / "depth"
    if depth_dir.is_dir():
        files = {**_list_stems(depth_dir, (".png",)), **_list_stems(depth_dir, (".npy",))}  # .npy wins over .png
        if files:
            return _DepthSource("depth", files, f"depth from depth/ ({len(files)} files)")
    disparity_dir = root / "disparity"
    if disparity_dir.is_dir():
        files = _list_stems(disparity_dir, (".npy",))
        if files:
            if stereo.rectification is not None:
                raise SessionError(
                    disparity_dir, f"expected disparities of rectified pairs, but {stereo.describe()}: the "
                    "left/right images are raw. Rectify them before running the stereo network and use a "
                    "calibration of the rectified cameras (K.txt, or rectified: 1)"
                )
            return _DepthSource(
                "disparity", files, f"depth from disparity/ ({len(files)} files) with fx * baseline / disparity"
            )
    if depth_method is not None and right_files:
        return _DepthSource(
            depth_method, {}, f"depth computed from left/ + right/ with OpenCV {depth_method.upper()} "
            "(no depth/ or disparity/; FoundationStereo gives far better depth)"
        )
    if right_files:
        third = "right/ is present but depth_method=None turns SGBM off"
    else:
        third = "right/<stem>.png|jpg rectified right frames, to compute depth with OpenCV SGBM (worse)"
    raise SessionError(
        depth_dir, "missing: no depth source; expected one of: (1) depth/<stem>.npy (float32 metres, e.g. "
        "FoundationStereo's depth_meter.npy) or depth/<stem>.png (uint16 millimetres); (2) disparity/<stem>.npy "
        f"(float32 px, FoundationStereo's raw disparity, converted with the calibration); (3) {third}. "
        "FoundationStereo is recommended"
    )


# --------------------------------------------------------------------------------------------
# Per-frame decoders (pure: path in, array out; raise SessionError naming the file)
