"""Read a recorded session directory: calibration, frame order, force, labels and per-frame layers.

The session directory format (the contract)::

    SESSION/
      session.json        optional: {"name", "phantom", "task", "fps"} (fps default 30)
      K.txt               line 1 = 9 numbers, row-major 3x3 K (px); line 2 = stereo baseline (m)
                          (or ROS left.yaml + right.yaml, or an OpenCV stereo.yaml: see calibration.py)
      left/<stem>.png|jpg|jpeg    left frames (the frame list); rectified, unless the calibration
                                  says otherwise (then left/right/masks/depth are rectified on load)
      right/<stem>.png|jpg|jpeg   right frames (optional; needed for SGBM depth)
      masks/<stem>.png    tool mask: palettized (index = object id) or 8-bit 0/255 (or RGB, nonzero = tool)
      depth/<stem>.npy    float32 metres, or depth/<stem>.png uint16 millimetres; 0, NaN, inf = invalid
      disparity/<stem>.npy  float32 px (FoundationStereo's raw output), used when depth/ is absent
      force.csv           optional: `frame` (stem) or `timestamp` (s) column, plus fx, fy, fz (N)
      frames.csv          optional: frame,timestamp (s); needed when force.csv is indexed by timestamp
      labels.csv          optional manual labels: frame,contact (0/1); they replace the force labels

Depth comes from one source per session, chosen in this order and logged (``Session.depth_note``):
``depth/``; else ``disparity/`` (depth = fx * baseline / (disparity + offset)); else OpenCV
semi-global matching of the left/right pair (``stereo.py``), computed lazily per frame and cached
outside the session directory.

``open_session`` validates everything that is session-wide up front and raises one
:class:`SessionError` naming the file and what was expected. Per-frame problems never raise:
``Session.iter_frames`` yields a :class:`BadFrame` for them and carries on. Nothing here ever
writes into the session directory (the SGBM cache lives in the cache folder).
"""

from __future__ import annotations

import contextlib
import csv
import functools
import io
import json
import logging
import math
import os
import re
import warnings
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from contact_viz.calibration import Calibration, Rectification, StereoCalibration, read_calibration
from contact_viz.errors import SessionError
from contact_viz.npy_rows import read_npy_rows
from contact_viz.palette_png import is_palette_png, palette_indices
from contact_viz.prefetch import prefetched
from contact_viz.params import LabelParams
from contact_viz.stereo import DEPTH_METHODS, DisparityCache, SGBMParams, disparity_to_depth

__all__ = [
    "LAYERS",
    "BadFrame",
    "Calibration",
    "DEPTH_SOURCES",
    "Frame",
    "Session",
    "SessionWarning",
    "missing_inputs",
    "natural_key",
    "open_session",
    "read_depth_m",
    "read_disparity_px",
    "read_rgb",
    "read_tool_mask",
]

log = logging.getLogger(__name__)

LAYERS = frozenset({"mask", "depth", "left", "right"})  # names of the per-frame layers iter_frames can decode
DEFAULT_FPS = 30.0  # frame rate used when session.json gives none, frames/s
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")  # accepted left/right image file types, in lookup preference
MM_PER_M = 1000.0  # millimetres per metre (uint16 depth PNGs hold millimetres)
DEPTH_SOURCES = ("depth", "disparity", "sgbm")  # where a session's depth can come from, in preference order

_SESSION_JSON_KEYS = ("name", "phantom", "task", "fps")
# Exceptions that mean "this file could not be decoded" (PIL raises SyntaxError for some broken PNGs).
_DECODE_ERRORS = (OSError, ValueError, EOFError, SyntaxError, zlib.error, cv2.error)


class SessionWarning(UserWarning):
    """Something in a session is odd but usable (e.g. a CSV row for a stem not in left/)."""


# --------------------------------------------------------------------------------------------
# Data types
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Frame:
    """One decoded frame. Layers that were not requested are None."""

    index: int  # position in the session's frame order, 0-based
    stem: str  # file stem shared by left/, right/, masks/, depth/
    timestamp_s: float  # frame time, s
    tool_mask: np.ndarray | None  # (H, W) bool, True = tool
    depth_m: np.ndarray | None  # (H, W) float32, m, read-only; invalid where not a finite number > 0
    left_rgb: np.ndarray | None  # (H, W, 3) uint8 RGB
    right_rgb: np.ndarray | None  # (H, W, 3) uint8 RGB; None also when the frame has no right image


@dataclass(frozen=True)
class BadFrame:
    """A frame whose requested layers could not be read; ``error`` names the file and the expectation."""

    index: int  # position in the session's frame order, 0-based
    stem: str  # file stem
    timestamp_s: float  # frame time, s
    error: SessionError  # what went wrong, naming the file

    @property
    def reason(self) -> str:
        """The error message: "<path>: <what was expected>"."""
        return str(self.error)


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
    return out


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


def _read_labels_csv(path: Path, stems: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """labels.csv -> (frame indices (k,) int64, contact (k,) int8 in {0, 1})."""
    header, body = _read_csv(path)
    _require_columns(path, header, ("frame", "contact"), "frame stem, contact 0/1")
    fcol, ccol = header.index("frame"), header.index("contact")
    names = [cells[fcol] for _, cells in body]
    contact = np.empty(len(body), dtype=np.int8)
    for r, (line, cells) in enumerate(body):
        if cells[ccol] not in ("0", "1"):
            raise SessionError(path, f"line {line}: expected contact 0 or 1, found {cells[ccol]!r}")
        contact[r] = int(cells[ccol])
    matched = _match_stems(path, names, stems)
    _check_unique(path, names, matched)
    _warn_unmatched(path, names, matched)
    ok = matched >= 0
    return matched[ok], contact[ok]


def _list_stems(directory: Path, suffixes: Sequence[str]) -> dict[str, Path]:
    """stem -> file for the files in ``directory`` whose lower-cased suffix is in ``suffixes``.

    Two files with the same stem (e.g. 7.png and 7.jpg) are an error.
    """
    found: dict[str, Path] = {}
    with os.scandir(directory) as entries:
        for entry in entries:
            suffix = os.path.splitext(entry.name)[1]
            if suffix.lower() not in suffixes or not entry.is_file():
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
    from contact_viz.calibration import calibration_files

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
# --------------------------------------------------------------------------------------------


def _read_bytes(path: Path, what: str) -> np.ndarray:
    """The file's bytes as (k,) uint8; a missing, unreadable or empty file is a SessionError."""
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise SessionError(path, f"expected {what}, could not read the file ({exc.strerror or exc})") from exc
    if data.size == 0:
        raise SessionError(path, f"expected {what}, found an empty file")
    return data


def read_tool_mask(path: Path, object_id: int | None = None) -> np.ndarray:
    """Decode a tool mask PNG to (H, W) bool, True = tool.

    Palettized (SAM2/DAVIS) and single-channel masks: pixel value = object id, 0 = background;
    tool = nonzero, or == ``object_id`` when given. Multi-channel masks: tool = any colour channel
    nonzero (``object_id`` is then an error). Palettized PNGs are decoded to their palette
    indices (contact_viz.palette_png; PIL for bit depths other than 8), the rest by OpenCV.
    """
    what = "a tool mask PNG (palettized object ids, or 8-bit 0/255)"
    data = _read_bytes(path, what)
    try:
        raw = data.tobytes()
        if is_palette_png(raw):
            ids = palette_indices(raw)
            if ids is None:
                with Image.open(io.BytesIO(raw)) as image:
                    ids = np.asarray(image)
        else:
            ids = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except _DECODE_ERRORS as exc:
        raise SessionError(path, f"expected {what}, could not decode it ({type(exc).__name__}: {exc})") from exc
    if ids is None:
        raise SessionError(path, f"expected {what}, could not decode it")
    if ids.ndim == 2:
        return ids == object_id if object_id is not None else ids != 0
    if ids.ndim == 3 and ids.shape[2] in (3, 4):
        if object_id is not None:
            raise SessionError(
                path,
                f"expected a palettized or single-channel mask to select object_id={object_id}, "
                f"found {ids.shape[2]} channels",
            )
        return np.any(ids[:, :, :3] != 0, axis=2)
    raise SessionError(path, f"expected {what}, found an array of shape {ids.shape}")


def _invalid_to_nan(depth_m: np.ndarray) -> np.ndarray:
    """In place: NaN wherever depth is not a finite positive number. Returns ``depth_m``."""
    valid = depth_m > 0
    valid &= depth_m < np.inf
    np.copyto(depth_m, np.float32(np.nan), where=~valid)
    return depth_m


@contextlib.contextmanager
def _loading(path: Path, what: str) -> Iterator[None]:
    """Turn a failure to open or parse ``path`` inside the block into one SessionError naming it."""
    try:
        yield
    except SessionError:
        raise  # already names the file
    except FileNotFoundError as exc:
        raise SessionError(path, f"expected {what}, file missing") from exc
    except _DECODE_ERRORS as exc:
        raise SessionError(path, f"expected {what}, could not load it ({type(exc).__name__}: {exc})") from exc


def _check_float_2d(path: Path, what: str, dtype: object, shape: object) -> None:
    """SessionError unless ``dtype``/``shape`` describe a 2-D float32 or float64 array."""
    is_float = isinstance(dtype, np.dtype) and dtype.kind == "f" and dtype.itemsize in (4, 8)
    if not is_float or not isinstance(shape, tuple) or len(shape) != 2:
        raise SessionError(path, f"expected {what} (float32 or float64), found dtype {dtype} with shape {shape}")


def _check_image_shape(path: Path, shape: tuple[int, ...], image_size: tuple[int, int], what: str) -> None:
    """SessionError unless ``shape`` (an array's, channels ignored) is ``image_size`` (H, W),
    the left images' size."""
    if tuple(shape[:2]) != tuple(image_size):
        raise SessionError(
            path,
            f"expected a {what} of {image_size[0]}x{image_size[1]} px (height x width, as the left images), "
            f"found {shape[0]}x{shape[1]}",
        )


def _load_float_npy(path: Path, what: str) -> np.ndarray:
    """A 2-D float32/float64 .npy as a writable, C-contiguous float32 array; SessionError naming ``what``."""
    with _loading(path, what):
        raw = np.load(path, allow_pickle=False)
    _check_float_2d(path, what, getattr(raw, "dtype", type(raw).__name__), getattr(raw, "shape", None))
    return np.ascontiguousarray(raw, dtype=np.float32)


def read_depth_m(path: Path) -> np.ndarray:
    """Read a depth file as (H, W) float32 metres, read-only, values as stored.

    ``.npy``: 2-D float32/float64 metres (FoundationStereo depth_meter.npy).
    ``.png``: 16-bit single-channel millimetres.
    Invalid depth (0, NaN, inf or negative in the file) is left as it is: every consumer treats a
    value as valid only when it is a finite number > 0, so no pass over the frame is spent on it.
    """
    suffix = path.suffix.lower()
    if suffix == ".npy":
        depth = _load_float_npy(path, "a 2-D float32 depth array in metres (.npy)")
        depth.flags.writeable = False
        return depth
    if suffix == ".png":
        what = "a 16-bit single-channel depth PNG in millimetres"
        data = _read_bytes(path, what)
        try:
            raw = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        except _DECODE_ERRORS as exc:
            raise SessionError(path, f"expected {what}, could not decode it ({type(exc).__name__}: {exc})") from exc
        if raw is None:
            raise SessionError(path, f"expected {what}, could not decode it")
        if raw.dtype != np.uint16 or raw.ndim != 2:
            channels = 1 if raw.ndim == 2 else raw.shape[2]
            raise SessionError(
                path, f"expected {what}, found {raw.dtype.itemsize * 8}-bit {channels}-channel ({raw.dtype})"
            )
        depth = raw.astype(np.float32)
        depth /= np.float32(MM_PER_M)
        depth.flags.writeable = False
        return depth
    raise SessionError(path, "expected a depth file ending in .npy (float32 m) or .png (uint16 mm)")


def read_depth_rows_m(path: Path, row0: int, row1: int, image_size: tuple[int, int]) -> np.ndarray:
    """Rows ``row0`` to ``row1 - 1`` of a depth .npy of ``image_size`` (H, W), as a writable
    (row1 - row0, W) float32 array in metres, values as stored; only those rows are read.
    SessionError naming the file for a missing, malformed or truncated file, a dtype other than
    float32/float64, or another shape (checked from the header, before any row is read)."""
    what = "a 2-D float32 depth array in metres (.npy)"

    def check(dtype: np.dtype, shape: tuple[int, ...]) -> None:
        _check_float_2d(path, what, dtype, shape)
        _check_image_shape(path, shape, image_size, "depth map")

    with _loading(path, what):
        rows, _ = read_npy_rows(path, row0, row1, check=check)
    return np.ascontiguousarray(rows, dtype=np.float32)


def read_disparity_px(path: Path) -> np.ndarray:
    """Decode a disparity .npy (FoundationStereo's raw output) to (H, W) float32 px.

    NaN where the disparity is not a finite positive number.
    """
    return _invalid_to_nan(_load_float_npy(path, "a 2-D float32 disparity array in pixels (.npy)"))


_IMREAD_RGB = getattr(cv2, "IMREAD_COLOR_RGB", None)  # OpenCV >= 4.10 decodes straight to RGB


def read_rgb(path: Path) -> np.ndarray:
    """Decode a colour image to (H, W, 3) uint8 RGB (grey images are expanded, alpha dropped)."""
    what = "a colour image (PNG or JPEG)"
    data = _read_bytes(path, what)
    try:
        if _IMREAD_RGB is not None:
            rgb = cv2.imdecode(data, _IMREAD_RGB)
        else:
            bgr = cv2.imdecode(data, cv2.IMREAD_COLOR)
            rgb = None if bgr is None else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    except _DECODE_ERRORS as exc:
        raise SessionError(path, f"expected {what}, could not decode it ({type(exc).__name__}: {exc})") from exc
    if rgb is None or rgb.size == 0:
        raise SessionError(path, f"expected {what}, could not decode it")
    if rgb.dtype != np.uint8:  # 16-bit colour PNGs: keep the high byte
        rgb = (rgb >> 8).astype(np.uint8)
    return rgb


# --------------------------------------------------------------------------------------------
# Session
# --------------------------------------------------------------------------------------------


class Session:
    """An opened session: metadata, calibration, per-frame times/force/labels, lazy frame decoding.

    Attributes (arrays are read-only, n = number of frames):
        root: session directory (absolute). name / phantom / task: from session.json.
        fps: frames/s. calibration: rectified left K (px) and baseline (m).
        stereo: the calibration file(s) read and, when the images are raw, the rectification.
        rectification: maps applied on load to left/right/masks/depth (None if already rectified).
        stems: frame stems in numeric order. image_size: (height, width) px of the left images.
        timestamps_s: (n,) float64, s. force_xyz_n: (n, 3) float64, N (NaN = no sample).
        force_n: (n,) float64 magnitude, N (NaN = unknown). labels: (n,) int8 1/0/-1 (unknown).
        label_source: (n,) str "manual" / "force" / "none". has_right: right/ holds images.
        depth_source: "depth", "disparity" or "sgbm" (see DEPTH_SOURCES). depth_note: one line
        saying where depth comes from. depth_config: what the depth depends on, for cache keys.
        depth_cache_dir: where SGBM disparities are cached (None for other sources).
    """

    def __init__(
        self,
        *,
        root: Path,
        name: str,
        phantom: str | None,
        task: str | None,
        fps: float,
        calibration: Calibration,
        stems: list[str],
        image_size: tuple[int, int],
        timestamps_s: np.ndarray,
        force_xyz_n: np.ndarray,
        force_n: np.ndarray,
        labels: np.ndarray,
        label_source: np.ndarray,
        left_files: dict[str, Path],
        right_files: dict[str, Path],
        mask_files: dict[str, Path],
        depth_files: dict[str, Path],
        object_id: int | None,
        depth_source: str = "depth",
        depth_note: str = "depth from depth/",
        stereo: StereoCalibration | None = None,
        sgbm_cache: DisparityCache | None = None,
    ) -> None:
        if depth_source not in DEPTH_SOURCES:
            raise ValueError(f"depth_source must be one of {DEPTH_SOURCES}, got {depth_source!r}")
        if depth_source == "sgbm" and sgbm_cache is None:
            raise ValueError("depth_source 'sgbm' needs an sgbm_cache")
        self.root = root
        self.name = name
        self.phantom = phantom
        self.task = task
        self.fps = fps
        self.calibration = calibration
        self.stereo = stereo
        self.rectification: Rectification | None = stereo.rectification if stereo is not None else None
        self.stems = stems
        self.image_size = image_size
        self.timestamps_s = _read_only(timestamps_s)
        self.force_xyz_n = _read_only(force_xyz_n)
        self.force_n = _read_only(force_n)
        self.labels = _read_only(labels)
        self.label_source = _read_only(label_source)
        self.has_right = bool(right_files)
        self.object_id = object_id
        self.depth_source = depth_source
        self.depth_note = depth_note
        self._left_files = left_files
        self._right_files = right_files
        self._mask_files = mask_files
        self._depth_files = depth_files  # stem -> depth/ or disparity/ file, by depth_source
        self._sgbm = sgbm_cache if depth_source == "sgbm" else None
        self.depth_cache_dir = self._sgbm.directory if self._sgbm is not None else None
        self.depth_config = {"source": depth_source}
        if self._sgbm is not None:
            self.depth_config["sgbm"] = asdict(self._sgbm.params)

    def __len__(self) -> int:
        return len(self.stems)

    def __repr__(self) -> str:
        height, width = self.image_size
        return f"Session({self.name!r}, {len(self)} frames, {width}x{height} px, root={str(self.root)!r})"

    # ---- per-frame decoding ----

    def _check_shape(self, path: Path, shape: tuple[int, ...], what: str) -> None:
        """SessionError unless ``shape`` (an array's, channels ignored) is the left images' (H, W)."""
        _check_image_shape(path, shape, self.image_size, what)

    def _layer_path(self, files: dict[str, Path], stem: str, expected: Path, what: str) -> Path:
        path = files.get(stem)
        if path is None:
            raise SessionError(expected, f"missing: expected {what} for frame {stem!r}")
        return path

    def image_path(self, side: str, index: int) -> Path | None:
        """The ``side`` ("left" or "right") image file of frame ``index``, or None when there is none."""
        if side not in ("left", "right"):
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        files = self._left_files if side == "left" else self._right_files
        return files.get(self.stems[index])

    def _image(self, side: str, stem: str, decoded: dict[str, np.ndarray]) -> np.ndarray:
        """Frame ``stem``'s ``side`` image, (H, W, 3) uint8 RGB, rectified if needed; memoized in ``decoded``."""
        if side not in decoded:
            files = self._left_files if side == "left" else self._right_files
            expected = self.root / side / f"{stem}.png"
            path = self._layer_path(files, stem, expected, f"a {side} image")
            rgb = read_rgb(path)
            self._check_shape(path, rgb.shape, f"{side} image")
            if self.rectification is not None:
                rgb = self.rectification.apply(side, rgb)
            decoded[side] = rgb
        return decoded[side]

    def _mask(self, stem: str) -> np.ndarray:
        expected = self.root / "masks" / f"{stem}.png"
        path = self._layer_path(self._mask_files, stem, expected, "a tool mask PNG")
        tool_mask = read_tool_mask(path, self.object_id)
        self._check_shape(path, tool_mask.shape, "tool mask")
        if self.rectification is not None:
            tool_mask = self.rectification.apply("left", tool_mask, nearest=True)
        return tool_mask

    def _depth(self, stem: str, decoded: dict[str, np.ndarray]) -> tuple[np.ndarray, str]:
        """(depth (H, W) float32 m NaN-invalid, origin "file" / "cached" / "computed") of frame ``stem``."""
        cal = self.calibration
        if self.depth_source == "depth":
            path = self._layer_path(
                self._depth_files, stem, self.root / "depth" / f"{stem}.npy",
                "a depth map (.npy float32 m or .png uint16 mm)",
            )
            depth_m = read_depth_m(path)
            self._check_shape(path, depth_m.shape, "depth map")
            if self.rectification is not None:
                depth_m = self.rectification.apply("left", depth_m, nearest=True)
            return depth_m, "file"
        if self.depth_source == "disparity":
            path = self._layer_path(
                self._depth_files, stem, self.root / "disparity" / f"{stem}.npy", "a disparity map (.npy float32 px)"
            )
            disparity = read_disparity_px(path)
            self._check_shape(path, disparity.shape, "disparity map")
            return disparity_to_depth(disparity, cal.fx, cal.baseline_m, cal.disparity_offset_px), "file"
        left_path = self._left_files[stem]
        right_path = self._layer_path(
            self._right_files, stem, self.root / "right" / f"{stem}.png",
            "a right image (SGBM depth needs the stereo pair)",
        )
        disparity, cached = self._sgbm.disparity(
            stem, left_path, right_path,
            lambda: (self._image("left", stem, decoded), self._image("right", stem, decoded)),
        )
        return disparity_to_depth(disparity, cal.fx, cal.baseline_m, cal.disparity_offset_px), (
            "cached" if cached else "computed"
        )

    def load_depth(self, index: int, with_origin: bool = False):
        """Frame ``index``'s depth (H, W) float32 m (NaN invalid), or a BadFrame.

        With ``with_origin`` a (depth, origin) pair, origin = "file" (depth/ or disparity/),
        "cached" or "computed" (SGBM). Used by `contact-viz depth` to fill the cache.
        """
        if not 0 <= index < len(self):
            raise IndexError(f"frame index {index} out of range for a session of {len(self)} frames")
        stem = self.stems[index]
        try:
            depth_m, origin = self._depth(stem, {})
        except SessionError as error:
            return BadFrame(index=index, stem=stem, timestamp_s=float(self.timestamps_s[index]), error=error)
        return (depth_m, origin) if with_origin else depth_m

    def load_depth_rows(self, index: int, row0: int, row1: int) -> np.ndarray | BadFrame:
        """Rows ``row0`` to ``row1 - 1`` of frame ``index``'s depth, (row1 - row0, W) float32 m,
        read-only, values as stored (see read_depth_m); or a BadFrame.

        From depth/*.npy files stored rectified, only those rows are read (`contact-viz extract`
        needs the depth only around the tool); from any other source the whole map is decoded
        and cut. The file's shape and dtype are checked either way.
        """
        if not 0 <= index < len(self):
            raise IndexError(f"frame index {index} out of range for a session of {len(self)} frames")
        height = self.image_size[0]
        if not 0 <= row0 <= row1 <= height:
            raise ValueError(f"rows {row0}..{row1 - 1} out of range for images of {height} rows")
        stem = self.stems[index]
        try:
            path = self._depth_files.get(stem) if self.depth_source == "depth" else None
            if path is not None and path.suffix.lower() == ".npy" and self.rectification is None:
                depth_m = read_depth_rows_m(path, row0, row1, self.image_size)
            else:
                depth_m, _ = self._depth(stem, {})
                depth_m = depth_m[row0:row1]
        except SessionError as error:
            return BadFrame(index=index, stem=stem, timestamp_s=float(self.timestamps_s[index]), error=error)
        depth_m.flags.writeable = False
        return depth_m

    def load_frame(self, index: int, layers: Sequence[str] = ("mask", "depth")) -> Frame | BadFrame:
        """Decode the requested ``layers`` of frame ``index`` (synchronously); a BadFrame on any problem."""
        wanted = _check_layers(layers)
        if not 0 <= index < len(self):
            raise IndexError(f"frame index {index} out of range for a session of {len(self)} frames")
        return self._load(index, wanted)

    def _load(self, index: int, layers: frozenset[str]) -> Frame | BadFrame:
        stem = self.stems[index]
        timestamp_s = float(self.timestamps_s[index])
        tool_mask = depth_m = left_rgb = right_rgb = None
        decoded: dict[str, np.ndarray] = {}  # rectified images decoded for this frame, shared by the layers
        try:
            if "mask" in layers:
                tool_mask = self._mask(stem)
            if "depth" in layers:
                depth_m, _ = self._depth(stem, decoded)
                depth_m.flags.writeable = False  # whatever its source, a frame's depth is read-only
            if "left" in layers:
                left_rgb = self._image("left", stem, decoded)
            if "right" in layers and stem in self._right_files:
                right_rgb = self._image("right", stem, decoded)
        except SessionError as error:
            return BadFrame(index=index, stem=stem, timestamp_s=timestamp_s, error=error)
        return Frame(
            index=index,
            stem=stem,
            timestamp_s=timestamp_s,
            tool_mask=tool_mask,
            depth_m=depth_m,
            left_rgb=left_rgb,
            right_rgb=right_rgb,
        )

    def iter_frames(
        self,
        layers: Sequence[str] = ("mask", "depth"),
        indices: Sequence[int] | None = None,
        prefetch: int = 4,
        workers: int = 1,
    ) -> Iterator[Frame | BadFrame]:
        """Yield the frames ``indices`` (default: all) in order, decoding only ``layers``.

        Decoding runs in ``workers`` background threads, at most ``prefetch`` frames ahead of
        the consumer, so it overlaps the caller's compute. Per-frame problems are yielded as
        BadFrame. Closing the generator early (break) cancels pending work and joins the threads.
        Arguments are checked now (ValueError / IndexError), not at the first ``next``.
        """
        wanted = _check_layers(layers)
        if isinstance(prefetch, bool) or not isinstance(prefetch, int) or prefetch < 1:
            raise ValueError(f"prefetch must be a positive integer, got {prefetch!r}")
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise ValueError(f"workers must be a positive integer, got {workers!r}")
        order = list(range(len(self))) if indices is None else [int(i) for i in indices]
        bad = [i for i in order if not 0 <= i < len(self)]
        if bad:
            raise IndexError(f"frame indices {bad[:5]} out of range for a session of {len(self)} frames")
        return prefetched(functools.partial(self._load, layers=wanted), order, prefetch,
                          workers=min(workers, prefetch), thread_name="contact-viz-decode")


def _read_only(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


def _check_layers(layers: Sequence[str]) -> frozenset[str]:
    if isinstance(layers, str):
        layers = (layers,)
    wanted = frozenset(layers)
    unknown = sorted(wanted - LAYERS)
    if unknown:
        raise ValueError(f"layers: unknown layer(s) {unknown}; expected a subset of {sorted(LAYERS)}")
    return wanted


def _image_size(path: Path) -> tuple[int, int]:
    """(height, width) px from an image header (no full decode)."""
    try:
        with Image.open(path) as image:
            width, height = image.size
    except _DECODE_ERRORS as exc:
        raise SessionError(
            path,
            f"expected a readable PNG/JPEG left image to take the image size from ({type(exc).__name__}: {exc})",
        ) from exc
    if width <= 0 or height <= 0:
        raise SessionError(path, f"expected a non-empty left image, found {width}x{height} px")
    return height, width


def open_session(
    path: str | Path,
    *,
    object_id: int | None = None,
    label_params: LabelParams = LabelParams(),
    cache_dir: str | Path | None = None,
    depth_method: str | None = "sgbm",
    sgbm_params: SGBMParams | None = None,
    require_masks: bool = True,
) -> Session:
    """Open and validate a session directory (see the module docstring for the format).

    ``object_id`` picks one object id from palettized / single-channel masks (default: any
    nonzero pixel is tool). ``label_params`` sets the force threshold of the contact labels.
    ``depth_method`` computes depth from the stereo pair when there is neither depth/ nor
    disparity/ ("sgbm", with ``sgbm_params``; None = never compute), cached under ``cache_dir``
    (default: the package cache, see contact_viz.cache; never inside the session).
    ``require_masks=False`` allows a session without masks/ (mask layers then give BadFrames),
    e.g. to precompute depth. The chosen depth source is logged (INFO) and kept in
    ``Session.depth_note``. Raises SessionError (naming the file and what was expected) on any
    session-wide problem; warns (SessionWarning) about CSV rows naming stems that are not in left/.
    """
    if depth_method is not None and depth_method not in DEPTH_METHODS:
        raise ValueError(f"depth_method must be one of {DEPTH_METHODS} or None, got {depth_method!r}")
    if object_id is not None and (isinstance(object_id, bool) or not isinstance(object_id, int) or object_id < 1):
        raise ValueError(f"object_id must be a positive integer (0 is background) or None, got {object_id!r}")
    root = Path(path).expanduser()
    if not root.exists():
        raise SessionError(root, "missing: expected a session directory (left/, masks/, depth/, K.txt)")
    if not root.is_dir():
        raise SessionError(root, "expected a session directory (left/, masks/, depth/, K.txt), found a file")
    root = root.resolve()

    meta = _read_session_json(root / "session.json")
    left_dir = root / "left"
    if not left_dir.is_dir():
        raise SessionError(left_dir, "missing: expected a directory of rectified left frames left/<stem>.png|jpg")
    left_files = _list_stems(left_dir, IMAGE_SUFFIXES)
    if not left_files:
        raise SessionError(left_dir, "expected rectified left frames left/<stem>.png|jpg|jpeg, found none")
    stems = sorted(left_files, key=natural_key)
    image_size = _image_size(left_files[stems[0]])
    stereo = read_calibration(root, image_size)
    mask_files = _find_masks(root, required=require_masks)
    right_dir = root / "right"
    right_files = _list_stems(right_dir, IMAGE_SUFFIXES) if right_dir.is_dir() else {}
    source = find_depth_source(root, right_files, stereo, depth_method)
    sgbm_cache = None
    if source.kind == "sgbm":
        resolved = (sgbm_params or SGBMParams()).resolve(image_size[1])
        sgbm_cache = DisparityCache.for_session(root, stereo.files, resolved, cache_dir)
    note = f"{root.name}: {source.note}; {stereo.describe()}"
    log.info(note)

    fps = float(meta.get("fps", DEFAULT_FPS))
    frames_csv = root / "frames.csv"
    frame_times = _read_frames_csv(frames_csv, stems) if frames_csv.is_file() else None
    timestamps_s = frame_times if frame_times is not None else np.arange(len(stems), dtype=np.float64) / fps

    force_csv = root / "force.csv"
    if force_csv.is_file():
        force_xyz_n = _read_force_csv(force_csv, stems, frame_times, frames_csv)
    else:
        force_xyz_n = np.full((len(stems), 3), np.nan)
    force_n = np.linalg.norm(force_xyz_n, axis=1)
    labels = force_labels(force_n, label_params)
    label_source = np.where(labels >= 0, "force", "none").astype("<U6")

    labels_csv = root / "labels.csv"
    if labels_csv.is_file():
        manual_index, manual_contact = _read_labels_csv(labels_csv, stems)
        labels[manual_index] = manual_contact
        label_source[manual_index] = "manual"

    return Session(
        root=root,
        name=meta.get("name") or root.name,
        phantom=meta.get("phantom"),
        task=meta.get("task"),
        fps=fps,
        calibration=stereo.calibration,
        stems=stems,
        image_size=image_size,
        timestamps_s=timestamps_s,
        force_xyz_n=force_xyz_n,
        force_n=force_n,
        labels=labels,
        label_source=label_source,
        left_files=left_files,
        right_files=right_files,
        mask_files=mask_files,
        depth_files=source.files,
        object_id=object_id,
        depth_source=source.kind,
        depth_note=note,
        stereo=stereo,
        sgbm_cache=sgbm_cache,
    )
