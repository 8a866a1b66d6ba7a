"""The dataset steps of `contact-viz batch`: ``fit`` and ``evaluate`` over the sessions' features.

``fit`` writes ``OUT/model.json``: the leave-one-session-out HMM ensemble of `contact-viz fit` over
every session with labels. ``evaluate`` writes ``OUT/metrics.json`` and ``OUT/per_frame.csv``:
after ``fit`` each session is scored by the ensemble member fitted without it (a cross-validated
Table 1 of the dataset; the threshold is the ensemble's, chosen on the pooled out-of-fold
posteriors); with ``--model`` every session is scored by that model. Sessions with several
instruments are fitted and scored per instrument as in `contact-viz fit` / `evaluate`
(:func:`contact_viz.pipeline.features.fit_loso`, :func:`~contact_viz.pipeline.features.score_features`),
with labels.csv's per-instrument labels taken from the sessions.
"""

from __future__ import annotations

import csv
import dataclasses
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

from contact_viz.io.atomic import all_or_nothing, atomic_write
from contact_viz.io.jsonfile import write_json
from contact_viz.model.evaluation import metrics_table, per_frame_columns, per_frame_rows
from contact_viz.params import to_dict

__all__ = ["run_dataset_steps"]


def run_dataset_steps(summary, out: Path, names: Sequence[str], options, tick: Callable[[str], None],
                      sessions: Mapping[str, object] | None = None) -> None:
    """Run ``fit`` and/or ``evaluate`` (as in ``options.steps``) on the features under ``out``;
    ``sessions`` (name -> the opened Session) give labels.csv's per-instrument labels."""
    from contact_viz.model.model_file import ContactModel, check_params, load_model, save_model
    from contact_viz.model.hmm import HMMParams
    from contact_viz.model.kinds import FIT_DEFAULT_KIND
    from contact_viz.pipeline.features import csv_features, fit_loso, score_features, with_tool_labels

    features = {}
    for name in names:
        path = out / name / "features.csv"
        if not path.exists():
            continue
        try:
            found = csv_features(path, options.params)
        except ValueError:  # features of other parameters (an older run): not this batch's
            continue
        if found.name != name:
            found = dataclasses.replace(found, name=name)
        session = (sessions or {}).get(name)
        if session is not None:
            try:
                found = with_tool_labels(found, session.tool_labels, session.stems)
            except ValueError:  # features of other frames (an older run): not this batch's
                continue
        features[name] = found
    model = None
    if "fit" in options.steps:
        labelled = [n for n in names if n in features and (features[n].labels >= 0).any()]
        try:
            if len(labelled) < 2:
                raise ValueError(f"fit: expected at least 2 sessions with labels and features, found {len(labelled)}"
                                 " (run the extract step too)")
            # the model kind `contact-viz fit` fits by default
            ensemble = fit_loso([features[n] for n in labelled], HMMParams(model_kind=FIT_DEFAULT_KIND))
            model = ContactModel(ensemble=ensemble, patch_params=options.params, label_params=options.label_params,
                                 training_sessions=tuple(features[n].training_entry(s.path) | {"frames": s.frames}
                                                         for n in labelled for s in summary.sessions if s.name == n))
            save_model(model, out / "model.json")
            summary.dataset["fit"] = f"done: {len(labelled)} LOSO models, threshold {model.threshold:.4f}"
        except ValueError as exc:
            summary.dataset["fit"] = f"failed: {exc}"
        tick("fit")
    if "evaluate" in options.steps:
        try:
            if model is not None:
                members = dict(zip(model.ensemble.session_names_, model.ensemble.models_))
                threshold = model.threshold
                scored = [n for n in names if n in members]
                scores = [score_features(members[n].predict_proba, threshold, features[n]) for n in scored]
                how = "each session by the LOSO model fitted without it"
            elif options.model_path is not None:
                loaded = load_model(options.model_path)
                check_params(loaded.patch_params, options.params, f"--model {options.model_path}")
                threshold = loaded.threshold
                scores = [score_features(loaded.predict_proba, threshold, features[n]) for n in names if n in features]
                how = f"every session by {options.model_path}"
            else:
                raise ValueError("evaluate: no model (fit failed or was not run, and no --model)")
            if not scores:
                raise ValueError("evaluate: no session has features (run the extract step too)")
            table = metrics_table(scores, threshold)
            with all_or_nothing():  # both files or neither (a full disk on the second)
                with atomic_write(out / "per_frame.csv", newline="") as handle:
                    writer = csv.DictWriter(handle, fieldnames=per_frame_columns(scores))
                    writer.writeheader()
                    writer.writerows(per_frame_rows(scores))
                write_json(out / "metrics.json", {"scored": how, "threshold": threshold,
                                                  "patch_params": to_dict(options.params), "metrics": table})
            summary.metrics = table
            summary.dataset["evaluate"] = f"done: {len(scores)} sessions, {how}"
        except ValueError as exc:
            summary.dataset["evaluate"] = f"failed: {exc}"
        tick("evaluate")
