"""Held-out evaluation of a contact model: per-session metrics, the macro mean, per-frame rows.

Pure computation over arrays; reading sessions and writing files is the caller's job.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from contact_viz.model.metrics import MACRO_ROW, macro_mean, session_metrics

PER_FRAME_COLUMNS = ("session", "frame", "signal", "posterior", "predicted", "label")


@dataclass(frozen=True)
class SessionScores:
    """A model's output on one session."""

    name: str
    frames: Sequence[str]  # stems, (T,)
    signal: np.ndarray  # (T,) float64, NaN = no patch
    labels: np.ndarray  # (T,) int8, -1 = unknown
    posterior: np.ndarray  # (T,) float64 P(contact | x_1..x_t)
    predicted: np.ndarray  # (T,) bool, posterior >= threshold


def score_session(predict_proba, threshold: float, name: str, frames: Sequence[str],
                  signal: np.ndarray, labels: np.ndarray) -> SessionScores:
    """Run ``predict_proba`` ((T,) signal -> (T,) posterior) on one session and threshold it."""
    if not (len(frames) == signal.shape[0] == labels.shape[0]):
        raise ValueError(f"session {name!r}: {len(frames)} frames, {signal.shape[0]} signals, "
                         f"{labels.shape[0]} labels; expected equal counts")
    posterior = np.asarray(predict_proba(signal), dtype=np.float64)
    return SessionScores(name, list(frames), signal, labels, posterior, posterior >= threshold)


def metrics_table(scores: Sequence[SessionScores], threshold: float) -> dict[str, dict]:
    """Per-session metrics (in the given order) followed by the ``Macro`` row."""
    rows = {s.name: session_metrics(s.labels.astype(np.int64), s.posterior, threshold, name=s.name) for s in scores}
    rows[MACRO_ROW] = macro_mean(rows)
    return rows


def per_frame_rows(scores: Sequence[SessionScores]) -> list[dict[str, object]]:
    """One row per frame: session, frame, signal, posterior, predicted (0/1), label ('' = unknown)."""
    out = []
    for s in scores:
        for i, stem in enumerate(s.frames):
            out.append({
                "session": s.name,
                "frame": stem,
                "signal": "" if np.isnan(s.signal[i]) else repr(float(s.signal[i])),
                "posterior": repr(float(s.posterior[i])),
                "predicted": int(s.predicted[i]),
                "label": "" if s.labels[i] < 0 else int(s.labels[i]),
            })
    return out

