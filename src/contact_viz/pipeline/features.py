"""Features of whole sessions for fitting and scoring: the per-frame rows of `contact-viz extract`
and the HMM's inputs made from them.

A source is either a session directory (extracted with the given patch parameters and cached
outside it, see :func:`contact_viz.pipeline.extract.cached_features`) or a features CSV written by
`contact-viz extract`, whose saved configuration must hold the same patch parameters. `fit`,
`evaluate` and `predict` and the paper's protocol (:mod:`contact_viz.paper`) all read features here.

Several instruments: features.csv has one row per frame and instrument (``tool`` = object id).
:class:`Features` then holds each instrument's signal over all frames of the session (NaN where it
is absent or has no patch) beside the scene's labels; :func:`fit_loso` fits the HMM on the
instruments' sequences (labels per instrument: :func:`contact_viz.model.instruments.training_labels`)
and :func:`score_features` scores the scene posterior (the max over the instruments present,
:func:`contact_viz.model.instruments.scene_posterior`). A session of one instrument (rows naming at
most one object id) is one sequence, exactly as before.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from contact_viz.io.session import Session, open_session
from contact_viz.model.evaluation import SessionScores, score_session
from contact_viz.model.hmm import HMMParams, LosoEnsemble
from contact_viz.model.instruments import training_labels
from contact_viz.model.model_file import check_params
from contact_viz.params import LabelParams, PatchParams
from contact_viz.pipeline.extract import (TOOL_COLUMN, cached_features, feature_arrays, read_features,
                                          read_features_config)


@dataclass
class Features:
    """Features of one session."""

    name: str  # session name (session.json "name", else the folder name)
    frames: list[str]  # frame stems, in order (one per frame, whatever the number of instruments)
    signal: np.ndarray  # (T,) float64 distance signal, NaN = no patch; several instruments: the largest (nearest)
    labels: np.ndarray  # (T,) int8 contact labels of the scene, -1 = unknown
    rows: list[dict]  # the feature rows (column -> text), as in features.csv
    cached: bool = False  # read from the features cache (or a features CSV) instead of extracted now
    tools: tuple[int, ...] = (1,)  # object ids of the instruments, ascending (one: the id the rows name, else 1)
    tool_signals: np.ndarray | None = None  # (K, T) float64 each instrument's signal, NaN = absent or no patch
    present: np.ndarray | None = None  # (K, T) bool: the instrument is in the frame (it has a row)
    tool_labels: np.ndarray | None = None  # (K, T) int8 per-instrument labels of labels.csv, -1 = none; None = none

    @property
    def several(self) -> bool:
        """The session has several instruments (its rows name more than one object id)."""
        return len(self.tools) > 1

    def training_entry(self, path: str) -> dict:
        """The session's entry in model.json's training_sessions (``tools`` only with several instruments)."""
        entry = {"name": self.name, "path": path, "frames": len(self.frames)}
        if self.several:
            entry["tools"] = list(self.tools)
        return entry


def _row_tool(row: dict) -> int | None:
    """The object id a feature row names (None: no instrument, or a file without a tool column)."""
    text = str(row.get(TOOL_COLUMN, "") or "").strip()
    if not text:
        return None
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"frame {row.get('frame')}: expected an object id in column {TOOL_COLUMN}, "
                         f"found {text!r}") from None


def _row_present(row: dict) -> bool:
    """The row's instrument is in the frame: it names one (or, in a file without a tool column, has tool pixels)."""
    if TOOL_COLUMN in row:
        return _row_tool(row) is not None
    return str(row.get("tool_area_px", "")) not in ("", "0")


def features_from_rows(name: str, rows: list[dict], cached: bool = False) -> Features:
    """:class:`Features` of the feature ``rows`` of session ``name`` (one row per frame and instrument,
    the rows of a frame consecutive; a frame without an instrument has one row naming none)."""
    tools = sorted({t for t in map(_row_tool, rows) if t is not None})
    if len(tools) <= 1:  # one instrument: one row per frame, today's arrays
        signal, labels = feature_arrays(rows)
        present = np.array([[_row_present(r) for r in rows]], dtype=bool)
        return Features(name, [str(r["frame"]) for r in rows], signal, labels, rows, cached,
                        tools=(tools[0] if tools else 1,), tool_signals=signal[None, :], present=present)
    index = {tool: k for k, tool in enumerate(tools)}
    frames: list[str] = []
    labels: list[int] = []
    cells: list[dict[int, float]] = []  # per frame: instrument row -> signal
    for r in rows:
        stem = str(r["frame"])
        label = int(r["label"]) if r["label"] != "" else -1
        if not frames or frames[-1] != stem:
            frames.append(stem)
            labels.append(label)
            cells.append({})
        elif labels[-1] != label:
            raise ValueError(f"{name}: frame {stem}: its rows have different labels ({labels[-1]} and {label}); "
                             "expected the scene's label on every row of a frame")
        tool = _row_tool(r)
        if tool is None:
            continue
        if index[tool] in cells[-1]:
            raise ValueError(f"{name}: frame {stem} has two rows of instrument {tool}")
        cells[-1][index[tool]] = float(r["signal"]) if r["signal"] != "" else np.nan
    if len(set(frames)) != len(frames):
        raise ValueError(f"{name}: the rows of a frame are not consecutive; expected features.csv as "
                         "`contact-viz extract` writes it")
    tool_signals = np.full((len(tools), len(frames)), np.nan)
    present = np.zeros((len(tools), len(frames)), dtype=bool)
    for t, frame_cells in enumerate(cells):
        for k, value in frame_cells.items():
            tool_signals[k, t] = value
            present[k, t] = True
    finite = np.isfinite(tool_signals)
    signal = np.where(finite.any(axis=0), np.where(finite, tool_signals, -np.inf).max(axis=0), np.nan)
    return Features(name, frames, signal, np.array(labels, dtype=np.int8), rows, cached, tools=tuple(tools),
                    tool_signals=tool_signals, present=present)


def with_tool_labels(features: Features, tool_labels: dict[int, np.ndarray] | None, stems: Sequence[str]) -> Features:
    """``features`` with the session's per-instrument labels (``Session.tool_labels``: object id -> (n,) int8
    over the session's frames ``stems``) as (K, T) rows of its instruments; unchanged without any."""
    if not tool_labels:
        return features
    at = {stem: i for i, stem in enumerate(stems)}
    missing = [f for f in features.frames if f not in at]
    if missing:
        raise ValueError(f"{features.name}: frames {missing[:3]} of the features are not in the session")
    columns = np.array([at[f] for f in features.frames], dtype=np.int64)
    rows = np.full((len(features.tools), len(features.frames)), -1, dtype=np.int8)
    for k, tool in enumerate(features.tools):
        if tool in tool_labels:
            rows[k] = np.asarray(tool_labels[tool])[columns]
    if not (rows >= 0).any():
        return features
    return dataclasses.replace(features, tool_labels=rows)


def fit_loso(features: Sequence[Features], params: HMMParams | None = None) -> LosoEnsemble:
    """The leave-one-session-out HMM ensemble of `contact-viz fit` on ``features``.

    A session of one instrument (without per-instrument labels) is one sequence with the scene's
    labels, as always. A session of several instruments gives one sequence per instrument, labelled
    by :func:`contact_viz.model.instruments.training_labels` (labels.csv's per-instrument labels
    where it has them; else, in a frame labelled contact, the instrument nearest the tissue gets
    contact and the others no contact); its out-of-fold posterior, on which the threshold is chosen,
    is the scene posterior."""
    signals, labels, scene, present = [], [], [], []
    for f in features:
        if not f.several and f.tool_labels is None:
            signals.append(f.signal)
            labels.append(f.labels)
            scene.append(None)
            present.append(None)
        else:
            signals.append(f.tool_signals)
            labels.append(training_labels(f.tool_signals, f.labels, f.tool_labels))
            scene.append(f.labels)
            present.append(f.present)
    return LosoEnsemble(params).fit(signals, labels, session_names=[f.name for f in features],
                                    scene_labels=scene, present=present)


def score_features(predict_proba, threshold: float, features: Features) -> SessionScores:
    """:func:`contact_viz.model.evaluation.score_session` on a session's features: one sequence for one
    instrument, else the scene posterior of the instruments' (with their posteriors, and their labels
    when labels.csv has per-instrument labels)."""
    f = features
    if not f.several and f.tool_labels is None:
        return score_session(predict_proba, threshold, f.name, f.frames, f.signal, f.labels)
    return score_session(predict_proba, threshold, f.name, f.frames, f.signal, f.labels, tools=f.tools,
                         tool_signals=f.tool_signals, present=f.present, tool_labels=f.tool_labels)


def session_features(session: Session, params: PatchParams, label_params: LabelParams = LabelParams(), *,
                     cache_dir: str | Path | None = None, progress: Callable[[int], None] | None = None,
                     processes: int = 1) -> Features:
    """Features of an opened ``session``: extracted with ``params`` (spread over ``processes``), or
    read back from the cache when the session's files and the parameters are unchanged; with
    labels.csv's per-instrument labels (``Session.tool_labels``)."""
    rows, cached = cached_features(session, params, label_params=label_params, cache_dir=cache_dir,
                                   progress=progress, processes=processes)
    return with_tool_labels(features_from_rows(session.name, rows, cached), session.tool_labels, session.stems)


def csv_features(path: Path, params: PatchParams) -> Features:
    """Features read from a features CSV of `contact-viz extract`; a ValueError if the file was
    computed with other patch parameters than ``params``. The CSV holds the scene's labels only:
    per-instrument labels (labels.csv with a tool column) come with a session directory."""
    file_params, name = read_features_config(path)
    check_params(params, file_params, str(path))
    return features_from_rows(name, read_features(path), cached=True)


def check_distinct_names(features: Sequence[Features]) -> None:
    """A ValueError unless every session name is distinct (the LOSO folds and tables are keyed by name)."""
    names = [f.name for f in features]
    if len(set(names)) != len(names):
        raise ValueError(f"session names must be distinct (set \"name\" in session.json); got {names}")


def load_features(sources: Sequence[Path], params: PatchParams, label_params: LabelParams = LabelParams(), *,
                  object_ids: Sequence[int] | None = None, cache_dir: str | Path | None = None, processes: int = 1,
                  on_open: Callable[[Session], Callable[[int], None] | None] | None = None,
                  on_done: Callable[[Path, Features], None] | None = None) -> list[Features]:
    """Features of every source, each a session directory (opened with ``object_ids`` and
    ``label_params``, extracted with ``params`` or read from the cache) or a features CSV with the
    same patch parameters. ``on_open(session)`` is called when a session is opened and may return a
    ``progress(frames done)`` callback; ``on_done(source, features)`` when a source's features are
    ready.
    Raises SessionError or ValueError naming the source, also when two sessions share a name."""
    out = []
    for source in sources:
        source = Path(source)
        if source.is_file() and source.suffix.lower() != ".csv":
            raise ValueError(f"{source}: expected a session directory or a features CSV from "
                             f"`contact-viz extract`, found a {source.suffix or 'plain'} file")
        if source.is_file():
            features = csv_features(source, params)
        else:
            session = open_session(source, object_ids=object_ids, label_params=label_params, cache_dir=cache_dir)
            progress = on_open(session) if on_open is not None else None
            features = session_features(session, params, label_params, cache_dir=cache_dir, progress=progress,
                                        processes=processes)
        if on_done is not None:
            on_done(source, features)
        out.append(features)
    check_distinct_names(out)
    return out
