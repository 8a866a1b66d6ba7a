"""contact-viz from Python: the public API (``contact_viz.<name>``, listed in ``contact_viz.__all__``).

A few functions over the same library code the command line runs, with the same frozen parameter objects
(:class:`PatchParams`, :class:`LabelParams`, :class:`DebuggerOptions`, :class:`SynthParams`). Units are in the
names (``distance_m``, ``force_n``). Tables are ``pyarrow.Table`` (pyarrow comes with rerun-sdk; ``.to_pandas()``
where pandas is installed). Anything not in ``contact_viz.__all__`` may change without notice.

    import contact_viz as cv
    path = cv.make_synthetic_session("/tmp/s1", frames=30, width=640, height=360)
    session = cv.open_session(path)
    table = cv.run_session(session)            # the columns of `contact-viz extract`
    print(table.column("distance_m").to_pylist()[:5])
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from contact_viz.io.session import Session, open_session as _open_session
from contact_viz.params import LabelParams, PatchParams

__all__ = ["FrameReadout", "check", "default_blueprint", "evaluate", "fit", "log_frame", "log_session",
           "make_synthetic_session", "open_session", "run_frame", "run_session"]


def open_session(path: str | Path, *, object_ids: Sequence[int] | None = None, contact_force_n: float = 2.0,
                 depth: str | None = "sgbm", cache_dir: str | Path | None = None) -> Session:
    """Open and check a session directory, as every command does (docs/session.md: the format).

    Args:
        path: the session directory (left/, masks/, depth/ or right/, a calibration; force.csv optional).
        object_ids: run on these instruments (object ids of palettized masks) only; default every one.
        contact_force_n: contact labels where the force magnitude is at least this, N (labels.csv wins).
        depth: without depth/ or disparity/, compute depth from the stereo pair: "sgbm", or None (never).
            To use your own depth network, write its output as depth/<stem>.npy (float32, m) first.
        cache_dir: cache of computed depth and features, outside the session (default ~/.cache/contact-viz).

    Returns:
        a :class:`contact_viz.io.session.Session`: ``len(session)`` frames, ``session.stems``,
        ``session.load_frame(i)``, ``session.calibration``; a SessionError names the file at fault.

    >>> session = open_session("/tmp/s1")                                  # doctest: +SKIP
    """
    return _open_session(path, object_ids=object_ids, label_params=LabelParams(contact_force_n=contact_force_n),
                         cache_dir=cache_dir, depth_method=depth)


@dataclass(frozen=True)
class FrameReadout:
    """The method on one frame: the distance of the instrument nearest the tissue and every layer.

    ``distance_m`` (m, NaN without a patch), ``signal`` (-log10 max(|d|, 1e-4 m), NaN without a patch),
    ``patch_center_xy`` ((x, y) px of the patch centre, or None), ``interior``, ``ring``, ``band`` and ``patch``
    ((H, W) bool layers of that instrument at the analysis resolution; ``patch`` the N2 window), ``reason``
    (why there is no patch, else None), ``instruments`` ({object id: (distance_m, signal)} of every instrument)
    and ``result`` (the full :class:`contact_viz.geometry.patch.PatchResult`)."""

    index: int
    stem: str
    distance_m: float
    signal: float
    patch_center_xy: tuple[int, int] | None
    interior: np.ndarray
    ring: np.ndarray
    band: np.ndarray
    patch: np.ndarray
    reason: str | None
    instruments: dict[int, tuple[float, float]]
    result: Any


def run_frame(session: Session, index: int, *, params: PatchParams = PatchParams()) -> FrameReadout:
    """The minimum-distance patch of frame ``index`` (0-based), as `contact-viz extract` computes it.

    >>> frame = run_frame(session, 10)                                     # doctest: +SKIP
    >>> frame.distance_m * 1000, frame.band.sum()                          # doctest: +SKIP
    """
    from contact_viz.pipeline.extract import session_frame_patches

    frame = session.load_frame(index, ("mask", "depth"))
    patch, tools = session_frame_patches(session, frame, params)
    window = np.zeros(patch.layer_ids.shape, dtype=bool)
    if patch.window_xyxy is not None:
        x0, y0, x1, y1 = patch.window_xyxy
        window[y0:y1, x0:x1] = True
    return FrameReadout(index=frame.index, stem=frame.stem, distance_m=float(patch.distance_m),
                        signal=float(patch.signal), patch_center_xy=patch.center_xy, interior=patch.interior,
                        ring=patch.ring, band=patch.band, patch=window, reason=patch.reason,
                        instruments={k: (float(p.distance_m), float(p.signal)) for k, p in tools.items()},
                        result=patch)


def _table(rows: Sequence[dict], columns: Sequence[str]):
    import pyarrow as pa

    def cell(value):
        return None if value == "" else value

    return pa.table({c: [cell(r.get(c, "")) for r in rows] for c in columns})


def run_session(session: Session, *, params: PatchParams = PatchParams(), cache_dir: str | Path | None = None,
                processes: int = 1):
    """Every frame's distance and signal: a ``pyarrow.Table`` with the columns of `contact-viz extract`'s CSV
    (``frame``, ``distance_m``, ``signal``, ``force_n``, ``label``, ...; one row per frame and instrument), cached
    outside the session as the CLI caches it.

    >>> table = run_session(session)                                       # doctest: +SKIP
    >>> table.to_pandas().plot(x="timestamp_s", y="distance_m")            # doctest: +SKIP
    """
    from contact_viz.pipeline.extract import cached_features, feature_columns

    rows, _ = cached_features(session, params, label_params=session.label_params, cache_dir=cache_dir,
                              processes=processes)
    typed = [_typed_row(r) for r in rows]
    return _table(typed, feature_columns(rows))


def _typed_row(row: dict) -> dict:
    """A features row (CSV text when read from the cache) with numbers as numbers."""
    out = {}
    for key, value in row.items():
        if isinstance(value, str) and value != "" and key not in ("frame", "reason", "detail", "session"):
            try:
                number = float(value)
                value = int(number) if key in ("label", "tool", "index") and number.is_integer() else number
            except ValueError:
                pass
        out[key] = value
    return out


def fit(sessions: Sequence[Session], *, model_kind: str | None = None, params: PatchParams = PatchParams(),
        cache_dir: str | Path | None = None):
    """The leave-one-session-out HMM ensemble and its threshold, as `contact-viz fit` fits it (at least two
    sessions with labels). ``model_kind``: None = fit's default (``contact_viz.model.kinds.FIT_DEFAULT_KIND``),
    "paper" = the paper's HMM exactly (docs/method.md). Returns a
    :class:`contact_viz.model.model_file.ContactModel`: ``model.predict_proba(signal)`` (the causal posterior of
    a (T,) signal), ``model.threshold``, ``save_model(model, path)``.

    >>> model = fit([s1, s2, s3])                                          # doctest: +SKIP
    >>> model.predict_proba(run_session(s4).column("signal").to_numpy())   # doctest: +SKIP
    """
    from contact_viz.model.hmm import HMMParams
    from contact_viz.model.kinds import FIT_DEFAULT_KIND
    from contact_viz.model.model_file import ContactModel
    from contact_viz.pipeline.features import fit_loso, session_features

    label_params = sessions[0].label_params if sessions else LabelParams()
    features = [session_features(s, params, s.label_params, cache_dir=cache_dir) for s in sessions]
    ensemble = fit_loso(features, HMMParams(model_kind=model_kind or FIT_DEFAULT_KIND))
    return ContactModel(ensemble=ensemble, patch_params=params, label_params=label_params,
                        training_sessions=tuple(f.training_entry(str(s.root)) for f, s in zip(features, sessions)))


def evaluate(model, sessions: Sequence[Session], *, cache_dir: str | Path | None = None):
    """Table 1 of the paper: a ``pyarrow.Table`` with a row per held-out session and the macro mean
    (``session``, ``accuracy``, ``precision``, ``recall``, ``f1``, ``auroc``, ``auprc``), as `contact-viz evaluate`
    prints it (None where a metric is undefined).

    >>> evaluate(model, [cup_test, kidney_test]).to_pylist()[-1]["f1"]    # doctest: +SKIP
    """
    from contact_viz.model.evaluation import metrics_table
    from contact_viz.pipeline.features import score_features, session_features

    features = [session_features(s, model.patch_params, s.label_params, cache_dir=cache_dir)
                for s in sessions]
    scores = [score_features(model.predict_proba, model.threshold, f) for f in features]
    table = metrics_table(scores, model.threshold)
    keys = ("accuracy", "precision", "recall", "f1", "auroc", "auprc")
    return _table([{"session": name, **{k: row.get(k) for k in keys}} for name, row in table.items()],
                  ("session", *keys))


def check(session_dir: str | Path, *, object_ids: Sequence[int] | None = None, cache_dir: str | Path | None = None):
    """Every mask, depth, sync and force check of `contact-viz check` on one session: a
    :class:`contact_viz.pipeline.check.CheckReport` (``report.flagged_frames``, ``report.counts`` {check: frames},
    ``report.fired`` {check: (first, last) frame ranges}, ``report.to_dict()``: the JSON of ``--json``).

    >>> check("/tmp/s1").counts                                            # doctest: +SKIP
    """
    from contact_viz.pipeline.check import check_session

    return check_session(session_dir, object_ids=object_ids, cache_dir=cache_dir)


def make_synthetic_session(out_dir: str | Path, *, phantom: str = "cup", frames: int = 60, width: int = 640,
                           height: int = 360, seed: int = 0, tools: int = 1, camera: str = "default",
                           overwrite: bool = False) -> Path:
    """A synthetic session with known truth, as `contact-viz synth` makes it (stereo renders, masks, depth,
    force, truth.csv with the true gap in m). ``camera``: "default" (tissue at 90 mm), "davinci" (50 mm) or
    "close" (30 mm). Returns the session directory.

    >>> make_synthetic_session("/tmp/s1", phantom="kidney", frames=40)    # doctest: +SKIP
    """
    from contact_viz.synth import SynthParams, generate_session
    from contact_viz.synth.camera import camera_fields

    params = SynthParams(phantom=phantom, frames=frames, seed=seed, width=width, height=height, tools=tools,
                         **camera_fields(camera))
    return Path(generate_session(out_dir, params, overwrite=overwrite))


def _model(model):
    if model is None or not isinstance(model, (str, Path)):
        return model
    from contact_viz.model.model_file import load_model

    return load_model(model)


def log_session(rec, session: Session, *, model=None, options=None, root: str | None = None, progress=None):
    """Log what the debugger (`contact-viz SESSION`) logs, frame by frame, into the caller's
    ``rr.RecordingStream`` ``rec``, every entity under ``root`` (None: the debugger's own paths). ``model``: a
    fitted model (or its model.json path) for the causal posterior and the evidence for contact. ``options``: a
    :class:`contact_viz.viz.options.DebuggerOptions` (frames ``start``/``end``/``stride``, images, ...). Only
    ``rec`` is written to: no global Rerun state, no blueprint (:func:`default_blueprint` makes it). Returns the
    run's summary (``.lines()``: what the CLI prints).

    >>> rec = rr.RecordingStream("my_robot"); rec.save("run.rrd")          # doctest: +SKIP
    >>> log_session(rec, session, model="model.json", root="contact_viz")  # doctest: +SKIP
    """
    from dataclasses import replace

    from contact_viz.viz.debugger import log_session as _log_session
    from contact_viz.viz.options import DebuggerOptions

    model = _model(model)
    options = DebuggerOptions() if options is None else options
    if model is not None and options.patch_params == PatchParams():
        options = replace(options, patch_params=model.patch_params)
    return _log_session(rec, session, model=model, options=options, root=root, progress=progress)


def log_frame(rec, session: Session, index: int, *, model=None, options=None, root: str | None = None):
    """:func:`log_session` of frame ``index`` alone (``--start index --end index+1``): its images, depth, cloud,
    layers, patch, distance and checks; with a model the posterior of that frame as the first the filter sees
    (the causal posterior needs the frames before it: log_session with ``options.start``/``end``)."""
    from dataclasses import replace

    from contact_viz.viz.options import DebuggerOptions

    options = DebuggerOptions() if options is None else options
    return log_session(rec, session, model=model, options=replace(options, start=index, end=index + 1), root=root)


def default_blueprint(session: Session | None = None, *, model=None, root: str | None = None):
    """The debugger's layout (a ``rerun.blueprint.Blueprint``) for entities logged under ``root``: send it with
    ``rec.send_blueprint(default_blueprint(session, model=model, root="contact_viz"))``."""
    from contact_viz.viz.blueprint import default_blueprint as _blueprint

    return _blueprint(with_right=session is None or session.has_right, with_model=model is not None, root=root)
