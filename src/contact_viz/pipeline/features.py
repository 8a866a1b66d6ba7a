"""Features of whole sessions for fitting and scoring: the per-frame rows of `contact-viz extract`
and the HMM's inputs made from them.

A source is either a session directory (extracted with the given patch parameters and cached
outside it, see :func:`contact_viz.pipeline.extract.cached_features`) or a features CSV written by
`contact-viz extract`, whose saved configuration must hold the same patch parameters. `fit`,
`evaluate` and `predict` and the paper's protocol (:mod:`contact_viz.paper`) all read features here.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from contact_viz.io.session import Session, open_session
from contact_viz.model.model_file import check_params
from contact_viz.params import LabelParams, PatchParams
from contact_viz.pipeline.extract import cached_features, feature_arrays, read_features, read_features_config


@dataclass
class Features:
    """Features of one session."""

    name: str  # session name (session.json "name", else the folder name)
    frames: list[str]  # frame stems, in order
    signal: np.ndarray  # (T,) float64 distance signal, NaN = no patch
    labels: np.ndarray  # (T,) int8 contact labels, -1 = unknown
    rows: list[dict]  # the feature rows (column -> text), as in features.csv
    cached: bool = False  # read from the features cache (or a features CSV) instead of extracted now


def features_from_rows(name: str, rows: list[dict], cached: bool = False) -> Features:
    """:class:`Features` of the feature ``rows`` of session ``name``."""
    signal, labels = feature_arrays(rows)
    return Features(name, [str(r["frame"]) for r in rows], signal, labels, rows, cached)


def session_features(session: Session, params: PatchParams, label_params: LabelParams = LabelParams(), *,
                     cache_dir: str | Path | None = None, progress: Callable[[int], None] | None = None,
                     processes: int = 1) -> Features:
    """Features of an opened ``session``: extracted with ``params`` (spread over ``processes``), or
    read back from the cache when the session's files and the parameters are unchanged."""
    rows, cached = cached_features(session, params, label_params=label_params, cache_dir=cache_dir,
                                   progress=progress, processes=processes)
    return features_from_rows(session.name, rows, cached)


def csv_features(path: Path, params: PatchParams) -> Features:
    """Features read from a features CSV of `contact-viz extract`; a ValueError if the file was
    computed with other patch parameters than ``params``."""
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
