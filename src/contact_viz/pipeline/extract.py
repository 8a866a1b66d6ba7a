"""Per-frame features of a session: the minimum-distance patch of every frame, as table rows.

This module joins the session reader and the patch computation; it does no drawing and no
logging to Rerun. :class:`FeatureRows` computes the rows of `contact-viz extract`, in one
process or several (:mod:`contact_viz.pipeline.parallel`); :func:`extract_features` runs it;
:func:`write_features` saves the rows atomically with the resolved configuration beside them.
:func:`iter_frame_results` streams whole frames with their patches, for the viewer.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import os
import warnings
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from contact_viz import __version__
from contact_viz.io.atomic import all_or_nothing, atomic_write
from contact_viz.io.jsonfile import read_json, write_json
from contact_viz.params import PATCH_PARAMS_EXPECTED, LabelParams, PatchParams, patch_params_from_json, to_dict
from contact_viz.geometry.instruments import instrument_ids, instrument_patches
from contact_viz.geometry.occlusion import half_occluded
from contact_viz.geometry.patch import PatchResult, compute_patch, patch_depth_rows
from contact_viz.io.session import BadFrame, Frame, Session
from contact_viz.pipeline.allocator import keep_freed_memory

if TYPE_CHECKING:
    from contact_viz.pipeline.parallel import ProcessPool

REASON_BAD_FRAME = "bad_frame"
DEFAULT_WORKERS = min(2, os.cpu_count() or 1)  # frames whose patches the viewer computes at once (threads)
CHUNK_FRAMES = 8  # frames computed per job, in this process or a worker

# Columns of features.csv, in order. Units are in the names; see the README for each.
FEATURE_COLUMNS = (
    "frame", "timestamp", "distance_m", "signal", "patch_x", "patch_y", "force_n", "label",
    "label_source", "reason", "score_m", "tool_depth_m", "n_candidates", "shaft_width_px",
    "band_width_px", "invalid_depth_fraction", "tool_area_px", "bleeding_px", "detail",
)
TOOL_COLUMN = "tool"  # the instrument's object id, after "frame"; only in sessions with instruments other than id 1


def feature_columns(rows: Sequence[dict[str, object]]) -> tuple[str, ...]:
    """The columns of features.csv for ``rows``: FEATURE_COLUMNS, with TOOL_COLUMN after "frame" when a row
    names an instrument other than 1 (a session of one instrument, or binary masks, keeps today's columns)."""
    if any(str(r.get(TOOL_COLUMN, "")) not in ("", "1") for r in rows):
        return FEATURE_COLUMNS[:1] + (TOOL_COLUMN,) + FEATURE_COLUMNS[1:]
    return FEATURE_COLUMNS


class BadFrameWarning(UserWarning):
    """A frame could not be read; it was skipped and the run went on."""


@dataclass(frozen=True)
class FrameResult:
    """One processed frame: the decoded frame (or why it could not be read) and its patches."""

    frame: Frame | BadFrame
    # the patch of the frame's instrument; with several, of the one nearest the tissue (smallest |distance|);
    # of the empty mask when there is none. None for a BadFrame
    patch: PatchResult | None
    tool_patches: dict[int, PatchResult] | None = None  # {object id: patch} of every selected instrument

    @property
    def index(self) -> int:
        return self.frame.index


def iter_frame_results(
    session: Session,
    params: PatchParams = PatchParams(),
    *,
    layers: Sequence[str] = ("mask", "depth"),
    indices: Sequence[int] | None = None,
    workers: int = DEFAULT_WORKERS,
) -> Iterator[FrameResult]:
    """Decode and process the frames of ``session`` in order, streaming.

    Decoding runs in the session reader's background thread; the patches of up to ``workers``
    frames are computed at once in a thread pool (OpenCV and NumPy release the GIL), at most
    ``2 * workers`` frames ahead of the consumer, so memory stays bounded. A frame that cannot
    be read is yielded with ``patch=None`` and a :class:`BadFrameWarning` is issued; the
    iteration goes on. ``layers`` must include "mask" and "depth".
    """
    needed = {"mask", "depth"}
    if not needed <= set(layers):
        raise ValueError(f"layers must include {sorted(needed)}, got {list(layers)}")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    frames = session.iter_frames(layers=tuple(layers), indices=indices, prefetch=2 * workers + 2)
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="contact-viz-patch")
    pending: deque[tuple[Frame | BadFrame, Future | None]] = deque()

    def finish(item: Frame | BadFrame, future: Future | None) -> FrameResult:
        if future is None:
            warnings.warn(f"frame {item.stem} skipped: {item.reason}", BadFrameWarning, stacklevel=3)
            return FrameResult(item, None)
        return FrameResult(item, *future.result())

    try:
        for item in frames:
            future = None if isinstance(item, BadFrame) else pool.submit(
                session_frame_patches, session, item, params)
            pending.append((item, future))
            if len(pending) >= 2 * workers:
                yield finish(*pending.popleft())
        while pending:
            yield finish(*pending.popleft())
    finally:
        for _, future in pending:
            if future is not None:
                future.cancel()
        pool.shutdown(wait=True, cancel_futures=True)
        frames.close()


def hidden_pixels(session: Session, frame: Frame, params: PatchParams) -> np.ndarray | None:
    """(rows of frame.depth_m, W) bool: the pixels the right camera cannot see beside the instruments
    (geometry.occlusion.half_occluded on the depth as disparity, fx * baseline / depth - offset, and every
    instrument of the mask), when ``params.hidden_strip`` leaves them out of the patch ("sgbm": with depth from
    contact-viz's SGBM only); else None. ``frame``'s mask and depth hold the same rows."""
    if params.hidden_strip == "never" or (params.hidden_strip == "sgbm" and session.depth_source != "sgbm"):
        return None
    if not isinstance(frame, Frame) or frame.depth_m is None or frame.tool_mask is None:
        return None
    depth = np.asarray(frame.depth_m, dtype=np.float64)
    tools = frame.tool_mask if frame.tool_ids is None else frame.tool_ids != 0
    cal = session.calibration
    with np.errstate(divide="ignore", invalid="ignore"):
        disparity = np.where(np.isfinite(depth) & (depth > 0),
                             cal.fx * cal.baseline_m / depth - cal.disparity_offset_px, np.nan)
    return half_occluded(disparity, tools[:depth.shape[0]])


def session_frame_patches(session: Session, frame: Frame, params: PatchParams
                          ) -> tuple[PatchResult, dict[int, PatchResult]]:
    """frame_patches of a whole decoded frame of ``session``: its selected instruments, its hidden pixels."""
    return frame_patches(frame, params, session.object_ids, 0, hidden_pixels(session, frame, params))


def frame_patches(frame: Frame, params: PatchParams, selected: Sequence[int] | None = None,
                  row0: int = 0, hidden: np.ndarray | None = None) -> tuple[PatchResult, dict[int, PatchResult]]:
    """(the frame's patch, {object id: patch}) of a decoded frame whose depth holds image rows ``row0`` on
    (see :class:`FrameResult`). One instrument: ``compute_patch`` on the tool mask, as for a binary mask.
    ``hidden``: the depth rows' pixels the right camera cannot see (:func:`hidden_pixels`), None = none."""
    depth_m = frame.depth_m
    ids = frame.tool_ids[row0:row0 + depth_m.shape[0]] if frame.tool_ids is not None else None
    tools = instrument_ids(ids, selected) if ids is not None else ()
    if ids is None or (len(tools) <= 1 and not (ids[(ids != 0)] != (tools[0] if tools else 0)).any()):
        patch = compute_patch(depth_m, frame.tool_mask[row0:row0 + depth_m.shape[0]], params, hidden)
        return patch, ({tools[0]: patch} if tools else {})
    patches = instrument_patches(depth_m, ids, params, selected, hidden)
    if not patches:
        return compute_patch(depth_m, np.zeros(ids.shape, bool), params), {}
    nearest = min(patches, key=lambda k: (not np.isfinite(patches[k].distance_m), abs(patches[k].distance_m)
                                          if np.isfinite(patches[k].distance_m) else 0.0, k))
    return patches[nearest], patches


def _blank(value: float) -> float | str:
    return "" if value is None or (isinstance(value, float) and math.isnan(value)) else value


def feature_row(session: Session, result: FrameResult, patch_row0: int = 0, tool: int | None = None,
                patch: PatchResult | None = None) -> dict[str, object]:
    """The features.csv row of one processed frame and instrument (values ready for csv; '' = empty).

    ``patch_row0``: the first image row of the band of rows the patch was computed on (its
    coordinates are relative to it; see patch.patch_depth_rows), 0 for a whole frame. ``tool``:
    the instrument's object id and ``patch`` its patch (default: ``result.patch``, no id)."""
    i = result.index
    label = int(session.labels[i])
    row: dict[str, object] = {
        "frame": result.frame.stem,
        TOOL_COLUMN: "" if tool is None else tool,
        "timestamp": f"{session.timestamps_s[i]:.6f}",
        "force_n": _blank(float(session.force_n[i])),
        "label": "" if label < 0 else label,
        "label_source": str(session.label_source[i]),
    }
    patch = result.patch if patch is None else patch
    if patch is None:
        row.update(reason=REASON_BAD_FRAME, detail=result.frame.reason)
        return {c: row.get(c, "") for c in (TOOL_COLUMN, *FEATURE_COLUMNS)}
    row.update(
        distance_m=_blank(patch.distance_m),
        signal=_blank(patch.signal),
        patch_x="" if patch.center_xy is None else patch.center_xy[0],
        patch_y="" if patch.center_xy is None else patch.center_xy[1] + patch_row0,
        reason=patch.reason or "",
        score_m=_blank(patch.score_m),
        tool_depth_m=_blank(patch.tool_depth_m),
        n_candidates=patch.n_candidates,
        shaft_width_px=f"{patch.shaft_width_px:.2f}",
        band_width_px=f"{patch.band_width_px:.2f}",
        invalid_depth_fraction=_blank(round(patch.invalid_depth_fraction, 6)),
        tool_area_px=patch.tool_area_px,
        bleeding_px=patch.n_bleeding,
    )
    return {c: row.get(c, "") for c in (TOOL_COLUMN, *FEATURE_COLUMNS)}


def result_rows(session: Session, result: FrameResult, patch_row0: int = 0) -> list[dict[str, object]]:
    """The features.csv rows of one processed frame: one per instrument (by object id), or one without an
    id when the frame has none or could not be read."""
    if not result.tool_patches:
        return [feature_row(session, result, patch_row0)]
    return [feature_row(session, result, patch_row0, tool, p) for tool, p in result.tool_patches.items()]


@dataclass(frozen=True)
class FeatureRows:
    """The features rows of positions ``lo`` to ``hi - 1`` of ``indices``, one frame at a time:
    the one function that computes extract's rows, in this process or in the workers of a
    :class:`contact_viz.pipeline.parallel.ProcessPool` (a ``ChunkTask``).

    Each frame's depth is read only in the rows the patch needs (patch.patch_depth_rows); the
    rows equal those of :func:`feature_row` over :func:`iter_frame_results` on whole frames.
    """

    session: Session
    params: PatchParams
    indices: tuple[int, ...]

    def __call__(self, lo: int, hi: int) -> list[list[dict[str, object]]]:
        """The rows of each frame of positions lo..hi-1 (a list per frame: one row per instrument)."""
        return [self._rows(index) for index in self.indices[lo:hi]]

    def _rows(self, index: int) -> list[dict[str, object]]:
        """One row per selected instrument in the frame, by object id; one row without an id when there is none."""
        frame = self.session.load_frame(index, layers=("mask",))
        if isinstance(frame, BadFrame):
            return [feature_row(self.session, FrameResult(frame, None))]
        row0, row1 = patch_depth_rows(frame.tool_mask, self.params)
        if frame.tool_ids is not None and (frame.tool_ids[frame.tool_ids != 0] != frame.tool_ids.max()).any():
            margin = int(np.ceil(self.params.ring_px))  # other instruments' safety ring reaches this far in
            row0, row1 = max(row0 - margin, 0), min(row1 + margin, frame.tool_ids.shape[0])
        depth_m = self.session.load_depth_rows(index, row0, row1)
        if isinstance(depth_m, BadFrame):
            return [feature_row(self.session, FrameResult(depth_m, None))]
        cropped = dataclasses.replace(frame, depth_m=depth_m, tool_mask=frame.tool_mask[row0:row1],
                                      tool_ids=None if frame.tool_ids is None else frame.tool_ids[row0:row1])
        hidden = hidden_pixels(self.session, cropped, self.params)
        return result_rows(self.session, FrameResult(frame, *frame_patches(cropped, self.params,
                                                                          self.session.object_ids, 0, hidden)), row0)


def extract_features(
    session: Session,
    params: PatchParams = PatchParams(),
    *,
    indices: Sequence[int] | None = None,
    progress: Callable[[int], None] | None = None,
    processes: int = 1,
    pool: ProcessPool | None = None,
) -> list[dict[str, object]]:
    """One features row per frame and instrument of ``session`` (one row without an instrument for a frame
    that has none; bad frames included, with reason ``bad_frame``, and a :class:`BadFrameWarning` each),
    computed by :class:`FeatureRows`.

    ``progress`` is called with the number of frames done. ``processes`` > 1 spreads the frames
    over this process and ``processes - 1`` spawned ones (threads cannot use more than about
    one core for this work); ``pool`` instead uses a pool started beforehand, whose workers import while the
    caller opens the session (the CLI starts ``ProcessPool(n, initializer=keep_freed_memory,
    preload=("contact_viz.pipeline.extract",))`` first thing). The rows
    are the same whatever the number of processes.
    """
    from contact_viz.pipeline.parallel import run_chunks

    order = tuple(range(len(session))) if indices is None else tuple(int(i) for i in indices)
    bad = [i for i in order if not 0 <= i < len(session)]
    if bad:
        raise IndexError(f"frame indices {bad[:5]} out of range for a session of {len(session)} frames")
    task = FeatureRows(session, params, order)
    if pool is not None:
        per_frame = pool.map_chunks(task, len(order), chunk_size=CHUNK_FRAMES, progress=progress)
    else:
        per_frame = run_chunks(task, len(order), chunk_size=CHUNK_FRAMES, processes=processes, progress=progress,
                               initializer=keep_freed_memory)
    rows = [row for frame_rows in per_frame for row in frame_rows]
    for row in rows:
        if row["reason"] == REASON_BAD_FRAME:
            warnings.warn(f"frame {row['frame']} skipped: {row['detail']}", BadFrameWarning, stacklevel=2)
    return rows


def run_config(session: Session, **sections: object) -> dict[str, object]:
    """The resolved configuration saved with every result (features.csv.json, the viewer's recording):
    the package version, the session, then ``sections`` in order (a config dataclass as its dict; None left out)."""
    config: dict[str, object] = {
        "contact_viz_version": __version__,
        "session": {"path": str(session.root.resolve()), "name": session.name, "frames": len(session)},
    }
    for key, value in sections.items():
        if value is not None:
            config[key] = to_dict(value) if dataclasses.is_dataclass(value) else value
    return config


def write_features(rows: Sequence[dict[str, object]], path: str | Path, config: dict[str, object]) -> Path:
    """Write ``rows`` to ``path`` (CSV) and ``config`` to ``<path>.json``, atomically and together: the
    ``.json`` is renamed into place first and the CSV last, and if either cannot be written (a full
    disk) neither appears."""
    path = Path(path)
    with all_or_nothing():
        write_json(path.with_name(path.name + ".json"), config)
        with atomic_write(path, newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=feature_columns(rows), extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)
    return path


def read_features(path: str | Path) -> list[dict[str, str]]:
    """Read a features.csv written by :func:`write_features` (values as strings)."""
    path = Path(path)
    with path.open(newline="") as handle:
        reader = csv.DictReader(handle)
        missing = [c for c in ("frame", "signal", "label") if c not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{path}: not a contact-viz features file (missing columns {missing})")
        return list(reader)


def read_features_config(path: str | Path) -> tuple[PatchParams, str]:
    """The patch parameters and session name saved beside a features CSV (``<path>.json``, as
    :func:`write_features` writes it). A missing or malformed file is a ValueError naming it."""
    config_path = Path(path).with_name(Path(path).name + ".json")
    config = read_json(config_path, PATCH_PARAMS_EXPECTED,
                       missing="missing; a features CSV needs the configuration `extract` writes beside it")
    params = patch_params_from_json(config, config_path)
    try:
        name = config["session"]["name"]
    except (KeyError, TypeError) as exc:
        raise ValueError(f"{config_path}: expected the session's name at session.name ({exc!r})") from None
    if not isinstance(name, str) or not name:
        raise ValueError(f"{config_path}: expected a non-empty session.name, got {name!r}")
    return params, name


def cached_features(
    session: Session,
    params: PatchParams = PatchParams(),
    *,
    label_params: LabelParams = LabelParams(),
    cache_dir: str | Path | None = None,
    progress: Callable[[int], None] | None = None,
    processes: int = 1,
) -> tuple[list[dict[str, object]], bool]:
    """Features of ``session``, reused from the cache when its files and the parameters are unchanged.

    Returns ``(rows, from_cache)``. The cache lives outside the session directory
    (:func:`contact_viz.io.cache.default_cache_dir`, or ``cache_dir``). ``processes``: as in
    :func:`extract_features`.
    """
    from contact_viz.io.cache import cache_path

    key = {"patch_params": to_dict(params), "label_params": to_dict(label_params), "object_ids": session.object_ids,
           "depth": session.depth_config}
    path = cache_path(session.root, "features", key, ".csv", cache_dir)
    cached = _read_cached_features(path, session)
    if cached is not None:
        return cached, True
    rows = extract_features(session, params, progress=progress, processes=processes)
    try:
        write_features(rows, path, run_config(session, patch_params=params, label_params=label_params))
    except OSError as exc:  # a full disk, a read-only cache: the features are still right
        from contact_viz.io.atomic import os_reason
        from contact_viz.io.depth_cache import CacheWarning

        warnings.warn(f"{path.parent}: could not write the features cache ({os_reason(exc)}); the features are "
                      "computed again on every run", CacheWarning, stacklevel=2)
    return [{k: str(v) for k, v in r.items()} for r in rows], False


def _read_cached_features(path: Path, session: Session) -> list[dict[str, str]] | None:
    """The rows of a features cache entry, or None if it is absent or not whole: every frame of the
    session present and every row complete (an entry cut short by a crash on a filesystem without
    atomic rename is computed and written again, never used)."""
    try:
        rows = read_features(path)
    except (OSError, ValueError, csv.Error, UnicodeDecodeError):
        return None
    if any(None in row or None in row.values() for row in rows):  # a row cut short, or one too long
        return None
    if {row["frame"] for row in rows} != set(session.stems):
        return None
    return rows


def feature_arrays(rows: Sequence[dict[str, object]]) -> tuple[np.ndarray, np.ndarray]:
    """The HMM's inputs from feature rows: signal (T,) float64 (NaN = no patch) and labels (T,) int8 (-1 = unknown)."""
    signal = np.array([float(r["signal"]) if r["signal"] != "" else np.nan for r in rows], dtype=np.float64)
    labels = np.array([int(r["label"]) if r["label"] != "" else -1 for r in rows], dtype=np.int8)
    return signal, labels
