"""Held-out evaluation of a contact model: per-session metrics, the macro mean, per-frame rows.

A session with several instruments is scored on its scene posterior
(:func:`contact_viz.model.instruments.scene_posterior` of the instruments' filtered posteriors)
against the scene's labels; where labels.csv labels the instruments themselves, each instrument is
also scored on its own posterior against its own labels (rows ``"<session> tool <id>"`` beside the
session's row, left out of the macro mean, which stays a mean over sessions).

Pure computation over arrays; reading sessions and writing files is the caller's job.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from contact_viz.model.instruments import instrument_posteriors, scene_posterior
from contact_viz.model.metrics import MACRO_ROW, macro_mean, session_metrics

PER_FRAME_COLUMNS = ("session", "frame", "signal", "posterior", "predicted", "label")
TOOL_POSTERIOR_COLUMN = "posterior_tool_{}"  # per-frame column of one instrument's posterior (several instruments)


@dataclass(frozen=True)
class SessionScores:
    """A model's output on one session."""

    name: str
    frames: Sequence[str]  # stems, (T,)
    signal: np.ndarray  # (T,) float64, NaN = no patch (several instruments: the nearest one's)
    labels: np.ndarray  # (T,) int8, -1 = unknown (the scene's)
    posterior: np.ndarray  # (T,) float64 P(contact | x_1..x_t) (several instruments: the scene's)
    predicted: np.ndarray  # (T,) bool, posterior >= threshold
    tools: tuple[int, ...] = ()  # object ids of the instruments scored separately (none: one sequence)
    tool_posteriors: np.ndarray | None = None  # (K, T) float64, each instrument's filtered posterior
    tool_labels: np.ndarray | None = None  # (K, T) int8 per-instrument labels (labels.csv), -1 = unknown


def score_session(predict_proba, threshold: float, name: str, frames: Sequence[str],
                  signal: np.ndarray, labels: np.ndarray, *, tools: Sequence[int] = (),
                  tool_signals: np.ndarray | None = None, present: np.ndarray | None = None,
                  tool_labels: np.ndarray | None = None) -> SessionScores:
    """Run ``predict_proba`` ((T,) signal -> (T,) posterior) on one session and threshold it.

    With ``tool_signals`` (K, T) (one row per instrument of ``tools``, NaN where absent or without a
    patch), each row is filtered separately and the posterior is the scene posterior over the
    instruments ``present`` (K, T) in each frame; ``tool_labels`` (K, T) are per-instrument labels to
    score each instrument against (None: none)."""
    if not (len(frames) == signal.shape[0] == labels.shape[0]):
        raise ValueError(f"session {name!r}: {len(frames)} frames, {signal.shape[0]} signals, "
                         f"{labels.shape[0]} labels; expected equal counts")
    if tool_signals is None:
        posterior = np.asarray(predict_proba(signal), dtype=np.float64)
        return SessionScores(name, list(frames), signal, labels, posterior, posterior >= threshold)
    tool_signals = np.asarray(tool_signals, dtype=np.float64)
    if tool_signals.ndim != 2 or tool_signals.shape != (len(tuple(tools)), len(frames)):
        raise ValueError(f"session {name!r}: instrument signals of shape {tool_signals.shape}; expected "
                         f"({len(tuple(tools))} instruments, {len(frames)} frames)")
    each = instrument_posteriors(predict_proba, tool_signals)
    posterior = scene_posterior(each, present)
    return SessionScores(name, list(frames), signal, labels, posterior, posterior >= threshold, tuple(tools), each,
                         None if tool_labels is None else np.asarray(tool_labels, dtype=np.int8))


def tool_row_name(session: str, tool: int) -> str:
    """The Table-1 row of one instrument of a session."""
    return f"{session} tool {tool}"


def metrics_table(scores: Sequence[SessionScores], threshold: float) -> dict[str, dict]:
    """Per-session metrics (in the given order), each followed by a row per instrument with its own
    labels (``tool_row_name``: its posterior against its labels), then the ``Macro`` row: the mean
    over the sessions' rows only."""
    rows, sessions = {}, {}
    for s in scores:
        rows[s.name] = sessions[s.name] = session_metrics(s.labels.astype(np.int64), s.posterior, threshold,
                                                          name=s.name)
        if s.tool_labels is None:
            continue
        for k, tool in enumerate(s.tools):
            if (s.tool_labels[k] >= 0).any():
                row = tool_row_name(s.name, tool)
                rows[row] = session_metrics(s.tool_labels[k].astype(np.int64), s.tool_posteriors[k], threshold,
                                            name=row)
    rows[MACRO_ROW] = macro_mean(sessions)
    return rows


def per_frame_columns(scores: Sequence[SessionScores]) -> tuple[str, ...]:
    """PER_FRAME_COLUMNS, then ``posterior_tool_<id>`` for every instrument of the sessions with several
    (ascending id); exactly PER_FRAME_COLUMNS when every session has one instrument."""
    tools = sorted({t for s in scores if len(s.tools) > 1 for t in s.tools})
    return PER_FRAME_COLUMNS + tuple(TOOL_POSTERIOR_COLUMN.format(t) for t in tools)


def per_frame_rows(scores: Sequence[SessionScores]) -> list[dict[str, object]]:
    """One row per frame: session, frame, signal, posterior, predicted (0/1), label ('' = unknown); for a
    session of several instruments also each instrument's posterior (``posterior_tool_<id>``; the
    instruments of other sessions are left out, i.e. empty in a CSV with ``per_frame_columns``)."""
    out = []
    for s in scores:
        several = len(s.tools) > 1
        for i, stem in enumerate(s.frames):
            row = {
                "session": s.name,
                "frame": stem,
                "signal": "" if np.isnan(s.signal[i]) else repr(float(s.signal[i])),
                "posterior": repr(float(s.posterior[i])),
                "predicted": int(s.predicted[i]),
                "label": "" if s.labels[i] < 0 else int(s.labels[i]),
            }
            if several:
                for k, tool in enumerate(s.tools):
                    row[TOOL_POSTERIOR_COLUMN.format(tool)] = repr(float(s.tool_posteriors[k, i]))
            out.append(row)
    return out
