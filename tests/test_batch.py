"""Tests for `contact-viz batch` (contact_viz.pipeline.batch): steps over sessions, resume,
failure isolation, and the same results on local processes and on a local Ray."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

from contact_viz.errors import SessionError
from contact_viz.io.session import open_session
from contact_viz.params import PatchParams
from contact_viz.pipeline.batch import BatchOptions, find_sessions, run_batch, summary_lines
from contact_viz.pipeline.engines import LocalEngine
from contact_viz.pipeline.extract import BadFrameWarning, extract_features, feature_columns, read_features
from contact_viz.synth import SynthParams, generate_session

CLI = [sys.executable, "-m", "contact_viz.cli"]
FRAMES = 80  # long enough for one contact episode that ends (the LOSO fit needs one per fold)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("dataset")
    for seed in range(3):
        generate_session(root / f"cup_{seed}", SynthParams(phantom="cup", frames=FRAMES, seed=seed, width=96, height=64))
    return root


def _copy(dataset: Path, tmp_path: Path) -> Path:
    out = tmp_path / "sessions"
    shutil.copytree(dataset, out, symlinks=True)
    return out


def _whole_session_rows(path: Path) -> list[dict[str, str]]:
    """The rows of the whole session in one call: the path `contact-viz extract` takes, with the columns
    it writes (no tool column for a session of one instrument)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BadFrameWarning)
        rows = extract_features(open_session(path), PatchParams())
    return [{k: str(r[k]) for k in feature_columns(rows)} for r in rows]


def test_find_sessions(dataset, tmp_path):
    names = [p.name for p in find_sessions(dataset)]
    assert names == ["cup_0", "cup_1", "cup_2"]
    assert find_sessions(dataset / "cup_1") == [(dataset / "cup_1").resolve()]
    listing = tmp_path / "list.txt"
    listing.write_text(f"# two of them\n{dataset / 'cup_2'}\n\n{os.path.relpath(dataset / 'cup_0', tmp_path)}  # relative\n")
    assert [p.name for p in find_sessions(listing)] == ["cup_2", "cup_0"]
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(SessionError, match="expected session folders"):
        find_sessions(empty)
    with pytest.raises(SessionError, match="expected a session folder"):
        find_sessions(tmp_path / "missing")


def test_options_are_checked():
    with pytest.raises(ValueError, match="--steps"):
        BatchOptions(steps=("extract", "render"))
    with pytest.raises(ValueError, match="--model"):
        BatchOptions(steps=("extract", "evaluate"))


@pytest.mark.parametrize("processes, chunk", [(1, 7), (2, 16)])
def test_chunked_rows_equal_whole_session_rows(dataset, tmp_path, processes, chunk):
    engine = LocalEngine(processes)
    try:
        summary = run_batch(dataset, tmp_path / "out", BatchOptions(steps=("extract",), chunk_frames=chunk), engine)
    finally:
        engine.close()
    assert not summary.failed
    for name in ("cup_0", "cup_1", "cup_2"):
        assert read_features(tmp_path / "out" / name / "features.csv") == _whole_session_rows(dataset / name)
        config = json.loads((tmp_path / "out" / name / "features.csv.json").read_text())
        assert config["session"]["frames"] == FRAMES


def test_resume_skips_unchanged_and_redoes_changed(dataset, tmp_path):
    sessions = _copy(dataset, tmp_path)
    out = tmp_path / "out"
    engine = LocalEngine(1)
    options = BatchOptions(steps=("extract",), chunk_frames=32)
    first = run_batch(sessions, out, options, engine)
    assert [s.steps["extract"] for s in first.sessions] == ["done"] * 3
    mtimes = {n: (out / n / "features.csv").stat().st_mtime_ns for n in ("cup_0", "cup_1", "cup_2")}
    again = run_batch(sessions, out, options, engine)
    assert [s.steps["extract"] for s in again.sessions] == ["reused"] * 3
    # A changed input file (here: the force of cup_1) makes that session's step run again, only it.
    force = sessions / "cup_1" / "force.csv"
    force.write_text(force.read_text())
    os.utime(force, ns=(force.stat().st_atime_ns, force.stat().st_mtime_ns + 10**9))
    third = run_batch(sessions, out, options, engine)
    assert [s.steps["extract"] for s in third.sessions] == ["reused", "done", "reused"]
    assert (out / "cup_0" / "features.csv").stat().st_mtime_ns == mtimes["cup_0"]
    # Other parameters: every session again.
    fourth = run_batch(sessions, out, BatchOptions(steps=("extract",), params=PatchParams(n2=15)), engine)
    assert [s.steps["extract"] for s in fourth.sessions] == ["done"] * 3


def test_a_broken_session_does_not_stop_the_others(dataset, tmp_path):
    sessions = _copy(dataset, tmp_path)
    (sessions / "cup_1" / "K.txt").write_text("not a calibration\n")
    before = {p: p.read_bytes() for p in sessions.rglob("*") if p.is_file()}
    result = subprocess.run([*CLI, "batch", str(sessions), "-o", str(tmp_path / "out"), "--steps", "extract",
                             "--processes", "1"], capture_output=True, text=True)
    assert result.returncode == 1, result.stderr
    assert "Traceback" not in result.stderr
    assert "failed: cup_1:" in result.stdout and "K.txt" in result.stdout
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["failed"] == ["cup_1"]
    assert (tmp_path / "out" / "cup_0" / "features.csv").exists()
    assert (tmp_path / "out" / "cup_2" / "features.csv").exists()
    assert not (tmp_path / "out" / "cup_1").exists()
    assert {p: p.read_bytes() for p in sessions.rglob("*") if p.is_file()} == before  # sessions untouched


def test_fit_evaluate_view_and_summary(dataset, tmp_path):
    out = tmp_path / "out"
    engine = LocalEngine(2)
    try:
        summary = run_batch(dataset, out, BatchOptions(steps=("extract", "view", "fit", "evaluate")), engine)
    finally:
        engine.close()
    assert summary.dataset["fit"].startswith("done: 3 LOSO models"), summary.dataset
    assert summary.dataset["evaluate"].startswith("done: 3 sessions"), summary.dataset
    # The cross-validated scores are the ensemble's own out-of-fold posteriors.
    from contact_viz.model.model_file import load_model

    model = load_model(out / "model.json")
    per_frame = list(__import__("csv").DictReader((out / "per_frame.csv").open()))
    for name, oof in zip(model.ensemble.session_names_, model.ensemble.oof_posteriors_):
        posterior = [float(r["posterior"]) for r in per_frame if r["session"] == name]
        assert posterior == pytest.approx(list(oof), abs=0, rel=0)
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics["metrics"]) == {"cup_0", "cup_1", "cup_2", "Macro"}
    # The recording opens and holds the pipeline's entities.
    from rerun.chunk import RrdReader

    paths = set()
    for chunk in RrdReader(out / "cup_0" / "view.rrd").stream():
        paths.add(str(chunk.entity_path))
    assert "/series/distance" in paths and "/world/camera/left/image" in paths
    lines = summary_lines(summary)
    assert lines[0].startswith("engine: local")
    assert any(line.startswith("3 sessions, 240 frames, 0 frames skipped") for line in lines)


def test_refuses_output_inside_a_session(dataset):
    with pytest.raises(ValueError, match="refusing to write inside"):
        run_batch(dataset / "cup_0", dataset / "cup_0" / "out", BatchOptions(steps=("extract",)), LocalEngine(1))


def test_ray_gives_the_same_results_as_local(dataset, tmp_path):
    import ray  # the test extra installs it

    from contact_viz.pipeline.engines import RayEngine

    local = LocalEngine(2)
    try:
        run_batch(dataset, tmp_path / "local", BatchOptions(steps=("extract", "check", "fit", "evaluate"),
                                                           chunk_frames=32), local)
    finally:
        local.close()
    engine = RayEngine(num_cpus=2)
    try:
        assert ray.is_initialized()
        summary = run_batch(dataset, tmp_path / "ray", BatchOptions(steps=("extract", "check", "fit", "evaluate"),
                                                                   chunk_frames=32), engine)
        assert summary.engine.startswith("ray (local Ray: 1 node, 2 CPUs)")
    finally:
        engine.close()
    assert not ray.is_initialized()
    for name in ("cup_0", "cup_1", "cup_2"):
        assert (tmp_path / "ray" / name / "features.csv").read_bytes() == \
            (tmp_path / "local" / name / "features.csv").read_bytes()
    for name in ("model.json", "per_frame.csv"):
        assert (tmp_path / "ray" / name).read_bytes() == (tmp_path / "local" / name).read_bytes()
    for name in ("cup_0", "cup_1", "cup_2"):  # the same check reports, but for the time they took
        reports = [json.loads((tmp_path / engine / name / "check.json").read_text()) for engine in ("local", "ray")]
        for report in reports:
            report.pop("elapsed_s")
        assert reports[0] == reports[1]
    local_metrics = json.loads((tmp_path / "local" / "metrics.json").read_text())
    ray_metrics = json.loads((tmp_path / "ray" / "metrics.json").read_text())
    assert ray_metrics == local_metrics


def test_check_step_writes_the_check_report(dataset, tmp_path):
    from contact_viz.pipeline.check import check_session

    engine = LocalEngine(1)
    summary = run_batch(dataset, tmp_path / "out", BatchOptions(steps=("check",)), engine)
    assert [s.steps["check"] for s in summary.sessions] == ["done"] * 3
    for outcome in summary.sessions:
        written = json.loads((tmp_path / "out" / outcome.name / "check.json").read_text())
        direct = check_session(dataset / outcome.name).to_dict()
        written.pop("elapsed_s"), direct.pop("elapsed_s")
        assert written == direct
        fired = {code: c["frames"] for code, c in direct["checks"].items() if c["frames"]}
        assert outcome.checks_fired == fired


def test_grid_search_scores_do_not_depend_on_the_engine(dataset, tmp_path):
    from contact_viz.paper.grid_search import build_grid, score_grid

    grid, _ = build_grid([29, 31], [17], [30], [8], base=PatchParams(reject_bleeding=False))
    sessions = [dataset / f"cup_{k}" for k in range(3)]
    alone = score_grid(sessions, grid, tmp_path / "c1", on_skip=lambda note: None)
    engine = LocalEngine(2)
    try:
        spread = score_grid(sessions, grid, tmp_path / "c2", on_skip=lambda note: None, engine=engine)
    finally:
        engine.close()
    assert [(p.params, p.oof_f1, p.oof_auprc, p.found) for p in spread] == \
        [(p.params, p.oof_f1, p.oof_auprc, p.found) for p in alone]
    assert len(alone) == 2
