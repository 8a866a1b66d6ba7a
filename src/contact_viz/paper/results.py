"""The study's held-out results: Table 1 of both methods, the per-frame CSVs, config.json and the
printed summary."""

from __future__ import annotations

import platform
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from contact_viz import __version__
from contact_viz.io.jsonfile import write_json
from contact_viz.model.metrics import MACRO_ROW, format_table, macro_mean, session_metrics
from contact_viz.paper.profiles import StudyProfile
from contact_viz.paper.protocol import BaselineRun, HmmRun, MethodResult, Study, Timer
from contact_viz.paper.tables import write_per_frame, write_table1
from contact_viz.params import LabelParams, PatchParams, to_dict
from contact_viz.pipeline.features import Features

HMM_COLUMNS = ("session", "category", "frame", "timestamp_s", "signal", "posterior", "predicted", "label")
RGB_COLUMNS = ("session", "category", "frame", "timestamp_s", "raw_score", "posterior", "predicted", "label",
               "crop_x", "crop_y")


def metrics_rows(study: Study, methods: Sequence[MethodResult]) -> dict[str, dict[str, dict]]:
    """Table 1: test session -> method -> session_metrics, then the Macro row."""
    table: dict[str, dict[str, dict]] = {}
    for i, s in enumerate(study.test):
        labels = np.asarray(s.labels, dtype=np.int64)
        table[s.name] = {m.name: session_metrics(labels, m.posteriors[i], m.threshold, name=s.name) for m in methods}
    table[MACRO_ROW] = {m.name: macro_mean({n: row[m.name] for n, row in table.items()}) for m in methods}
    return table


def per_frame_rows(study: Study, hmm: MethodResult, hmm_signals: list[Features], rgb: MethodResult,
                   rgb_raw: list[np.ndarray], crops: list) -> tuple[list[dict], list[dict]]:
    """Rows of per_frame_hmm.csv and per_frame_rgb.csv (floats as repr: they read back exactly)."""
    hmm_rows, rgb_rows = [], []
    for i, (s, f) in enumerate(zip(study.test, hmm_signals)):
        for t, stem in enumerate(s.stems):
            common = {"session": s.name, "category": study.categories[s.name], "frame": stem,
                      "timestamp_s": repr(float(s.timestamps_s[t])),
                      "label": "" if s.labels[t] < 0 else int(s.labels[t])}
            p_hmm, p_rgb = float(hmm.posteriors[i][t]), float(rgb.posteriors[i][t])
            hmm_rows.append({**common, "signal": "" if np.isnan(f.signal[t]) else repr(float(f.signal[t])),
                             "posterior": repr(p_hmm), "predicted": int(p_hmm >= hmm.threshold)})
            rgb_rows.append({**common, "raw_score": repr(float(rgb_raw[i][t])), "posterior": repr(p_rgb),
                             "predicted": int(p_rgb >= rgb.threshold),
                             "crop_x": repr(float(crops[i].center_xy[t, 0])),
                             "crop_y": repr(float(crops[i].center_xy[t, 1]))})
    return hmm_rows, rgb_rows


def notes(rgb: BaselineRun) -> list[str]:
    """Notes every output carries: that the baseline is not the paper's configuration, when it is not."""
    return [] if rgb.paper_configuration else [rgb.note]


def write_results(out: Path, study: Study, hmm: HmmRun, rgb: BaselineRun) -> dict[str, dict[str, dict]]:
    """table1.md/.tex/.csv and per_frame_hmm.csv, per_frame_rgb.csv; returns the table."""
    methods = (hmm.result, rgb.result)
    table = metrics_rows(study, methods)
    write_table1(out, table, [m.name for m in methods], {m.name: m.threshold for m in methods}, study.categories,
                 {s.name: str(s.root) for s in study.test}, notes(rgb))
    hmm_rows, rgb_rows = per_frame_rows(study, hmm.result, hmm.test_features, rgb.result, rgb.raw, rgb.test_crops)
    write_per_frame(out / "per_frame_hmm.csv", HMM_COLUMNS, hmm_rows)
    write_per_frame(out / "per_frame_rgb.csv", RGB_COLUMNS, rgb_rows)
    return table


def write_config(out: Path, command: list[str], profile: StudyProfile, study: Study, params: PatchParams,
                 label_params: LabelParams, params_source: str, grid_result: dict | None, hmm: HmmRun,
                 rgb: BaselineRun, weights: Path | None, frame_info: dict, timer: Timer) -> None:
    """config.json: the resolved configuration, thresholds, versions and timings of the run."""
    import matplotlib
    import torch

    h, r = hmm.result, rgb.result
    config = {
        "contact_viz_version": __version__,
        "command": command,
        "profile": profile.name, "quick": profile.name == "quick", "tiny": profile.name == "tiny",
        "sessions_dir": str(study.sessions_dir.resolve()), "split_file": str(study.split_path.resolve()),
        "split": {"train": list(study.split.train),
                  "test": [{"session": e.session, "category": e.category} for e in study.split.test]},
        "synthetic_study": study.synthetic,
        "patch_params": to_dict(params), "label_params": to_dict(label_params),
        "patch_params_source": params_source,
        "grid_search": None if grid_result is None else {k: v for k, v in grid_result.items() if k != "points"},
        "hmm": {"method": h.name, "params": to_dict(hmm.ensemble.params), "threshold": h.threshold,
                "training_sessions": list(hmm.ensemble.session_names_), "model": str((out / "model.json").resolve())},
        "baseline": {"method": r.name, "paper_configuration": rgb.paper_configuration, "note": rgb.note,
                     "params": to_dict(profile.baseline), "init": rgb.ensemble.init_,
                     "weights": None if weights is None else str(weights.resolve()),
                     "device": str(rgb.ensemble.device), "threshold": r.threshold,
                     "platt": {"slope": rgb.ensemble.platt_.slope, "intercept": rgb.ensemble.platt_.intercept},
                     "checkpoints": str(rgb.checkpoint_dir.resolve())},
        "seeds": {"baseline": profile.baseline.seed,
                  "synthetic": None if study.synthetic is None else
                  {s["session"]: s["seed"] for s in study.synthetic["sessions"]}},
        "thresholds": {h.name: h.threshold, r.name: r.threshold},
        "pipeline_figure_frame": frame_info,
        "versions": {"python": platform.python_version(), "numpy": np.__version__, "torch": torch.__version__,
                     "matplotlib": matplotlib.__version__},
        "timings_s": {**timer.steps, "total": timer.total()},
    }
    write_json(out / "config.json", config)


def summary_lines(table: dict, hmm: HmmRun, rgb: BaselineRun) -> list[str]:
    """What the study prints: each method's Table 1 as text, then the notes."""
    lines = []
    for m in (hmm.result, rgb.result):
        lines.append(f"Table 1, {m.name} (threshold {m.threshold:.4f})")
        lines.append(format_table({name: row[m.name] for name, row in table.items()}, style="text"))
    for note in notes(rgb) + [n for row in table.values() for m in row.values() for n in m.get("notes", [])]:
        lines.append(f"note: {note}")
    return lines
