"""`contact-viz fit / evaluate / predict` end to end on small synthetic sessions."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from sklearn.metrics import average_precision_score, f1_score, roc_auc_score

from contact_viz.model.hmm import LosoEnsemble
from contact_viz.model.model_file import ContactModel, load_model, save_model
from contact_viz.params import LabelParams, PatchParams
from contact_viz.synth import SynthParams, generate_session

CLI = [sys.executable, "-m", "contact_viz.cli"]
SIZE = dict(width=320, height=180)


def run(*args: str, ok: bool = True) -> subprocess.CompletedProcess:
    done = subprocess.run([*CLI, *args], capture_output=True, text=True, env={**os.environ, "COLUMNS": "120"})
    if ok:
        assert done.returncode == 0, done.stderr
    return done


@pytest.fixture(scope="module")
def study(tmp_path_factory) -> dict[str, object]:
    root = tmp_path_factory.mktemp("study")
    train = []
    for k in range(3):
        path = root / f"cup_train_{k}"
        generate_session(path, SynthParams(phantom="cup", frames=100, seed=10 + k, **SIZE))
        train.append(path)
    test = root / "kidney_test"
    generate_session(test, SynthParams(phantom="kidney", frames=100, seed=99, **SIZE))
    cache = root / "cache"
    model = root / "model.json"
    run("fit", *map(str, train), "-o", str(model), "--cache-dir", str(cache))
    return {"root": root, "train": train, "test": test, "cache": cache, "model": model}


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def test_model_json_is_readable_and_complete(study):
    data = json.loads(Path(study["model"]).read_text())
    assert data["format"] == "contact-viz-model/1"
    assert [s["name"] for s in data["training_sessions"]] == ["cup_train_0", "cup_train_1", "cup_train_2"]
    assert len(data["ensemble"]["models"]) == 3
    assert data["patch_params"] == {**data["patch_params"], "n1": 31, "n2": 17, "tau_tool": 30, "tau_patch": 8}
    assert 0 <= data["threshold"] <= 1
    assert data["contact_viz_version"]
    model = load_model(study["model"])
    # Each fold's means follow the physics: contact (state 1) has the larger signal (smaller distance).
    for hmm in model.ensemble.models_:
        assert hmm.means_[1] > hmm.means_[0]


def test_evaluate_prints_table_and_writes_consistent_outputs(study, tmp_path):
    per_frame, metrics_json = tmp_path / "frames.csv", tmp_path / "metrics.json"
    done = run("evaluate", str(study["model"]), str(study["test"]), "--per-frame", str(per_frame),
               "--json", str(metrics_json), "--markdown", "--latex", "--cache-dir", str(study["cache"]))
    for token in ("kidney_test", "Macro", "Accuracy", "AUPRC", "\\toprule", "| --- |"):
        assert token in done.stdout or token.replace("| --- |", "|---") in done.stdout
    rows = read_csv(per_frame)
    assert len(rows) == 100 and list(rows[0]) == ["session", "frame", "signal", "posterior", "predicted", "label"]
    metrics = json.loads(metrics_json.read_text())["metrics"]
    threshold = json.loads(metrics_json.read_text())["threshold"]
    # Recompute the metrics independently from the per-frame file with scikit-learn.
    labelled = [r for r in rows if r["label"] != ""]
    y = np.array([int(r["label"]) for r in labelled])
    p = np.array([float(r["posterior"]) for r in labelled])
    assert all(int(r["predicted"]) == int(float(r["posterior"]) >= threshold) for r in rows)
    got = metrics["kidney_test"]
    assert got["f1"] == pytest.approx(f1_score(y, p >= threshold), abs=1e-6)
    assert got["auroc"] == pytest.approx(roc_auc_score(y, p), abs=1e-5)
    assert got["auprc"] == pytest.approx(average_precision_score(y, p), abs=1e-5)
    assert metrics["Macro"]["f1"] == pytest.approx(got["f1"])
    # The posterior in the file is the ensemble's on the file's signal.
    model = load_model(study["model"])
    signal = np.array([float(r["signal"]) if r["signal"] else np.nan for r in rows])
    np.testing.assert_allclose([float(r["posterior"]) for r in rows], model.predict_proba(signal), rtol=0, atol=1e-12)


def test_features_are_cached_outside_the_session(study):
    entries = sorted((Path(study["cache"]) / "features").glob("*.csv"))
    assert len(entries) == 4  # three training sessions and the test session
    for session in [*study["train"], study["test"]]:
        assert not list(Path(session).rglob("*.tmp"))
    written = {path: path.stat().st_mtime_ns for path in entries}
    run("fit", *map(str, study["train"]), "-o", str(Path(study["root"]) / "again.json"),
        "--cache-dir", str(study["cache"]))
    assert sorted((Path(study["cache"]) / "features").glob("*.csv")) == entries
    assert {path: path.stat().st_mtime_ns for path in entries} == written  # read, not computed and written again
    first = json.loads(Path(study["model"]).read_text())["ensemble"]
    second = json.loads((Path(study["root"]) / "again.json").read_text())["ensemble"]
    assert first == second


def test_predict_on_a_session_without_labels(study, tmp_path):
    unlabelled = tmp_path / "unlabelled"
    shutil.copytree(study["test"], unlabelled)
    (unlabelled / "force.csv").unlink()
    out = tmp_path / "pred.csv"
    run("predict", str(study["model"]), str(unlabelled), "-o", str(out), "--cache-dir", str(study["cache"]))
    rows = read_csv(out)
    assert len(rows) == 100 and all(r["label"] == "" for r in rows)
    frames = tmp_path / "frames.csv"
    run("evaluate", str(study["model"]), str(study["test"]), "--per-frame", str(frames),
        "--cache-dir", str(study["cache"]))
    assert [r["posterior"] for r in rows] == [r["posterior"] for r in read_csv(frames)]


def test_model_refuses_features_with_other_parameters(study, tmp_path):
    params = tmp_path / "params.json"
    params.write_text(json.dumps({"n2": 15, "tau_patch": 6}))
    features = tmp_path / "features.csv"
    run("extract", str(study["test"]), "-o", str(features), "--params", str(params))
    done = run("evaluate", str(study["model"]), str(features), ok=False)
    assert done.returncode == 2
    assert "n2: model 17, features 15" in done.stderr and "tau_patch: model 8, features 6" in done.stderr
    # The same features file computed with the model's parameters is accepted.
    run("extract", str(study["test"]), "-o", str(features))
    done = run("evaluate", str(study["model"]), str(features))
    assert "kidney_test" in done.stdout


def test_fit_needs_two_sessions_and_load_model_errors(study, tmp_path):
    done = run("fit", str(study["train"][0]), "-o", str(tmp_path / "m.json"), ok=False)
    assert done.returncode == 2 and "at least 2" in done.stderr
    with pytest.raises(ValueError, match="not found"):
        load_model(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="bad.json"):
        load_model(bad)
    bad.write_text(json.dumps({"format": "something else"}))
    with pytest.raises(ValueError, match="contact-viz-model/1"):
        load_model(bad)


def square_wave_sessions(seed: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Three 200-frame sessions: contact labels in a square wave, the signal 3.0 in contact and 1.8 out, noise 0.3."""
    rng = np.random.default_rng(seed)
    signals, labels = [], []
    for _ in range(3):
        y = (np.sin(np.arange(200) / 15) > 0).astype(np.int8)
        signals.append(np.where(y == 1, 3.0, 1.8) + rng.normal(0, 0.3, 200))
        labels.append(y)
    return signals, labels


def test_model_file_round_trip(tmp_path):
    signals, labels = square_wave_sessions(seed=0)
    ens = LosoEnsemble().fit(signals, labels, session_names=["a", "b", "c"])
    model = ContactModel(ens, PatchParams(n2=15), LabelParams(3.0), ({"name": "a", "path": "/x", "frames": 200},))
    back = load_model(save_model(model, tmp_path / "m.json"))
    assert back.patch_params == PatchParams(n2=15) and back.label_params == LabelParams(3.0)
    assert back.threshold == model.threshold
    np.testing.assert_array_equal(back.predict_proba(signals[0]), model.predict_proba(signals[0]))


def test_grid_search_recipe_best_params_feed_fit(study, tmp_path):
    """The recipe's best grid point, refitted through `fit --params --model-kind paper`, reproduces its OOF score.

    The recipe computes distances with the shared-stage grid code; `fit` extracts them with
    compute_patch one parameter set at a time: the pooled out-of-fold F1 must agree.
    """
    best = tmp_path / "best.json"
    done = subprocess.run(
        [sys.executable, str(Path(__file__).parents[1] / "recipes" / "grid_search.py"), *map(str, study["train"]),
         "-o", str(best), "--n1", "29,31", "--n2", "11,17", "--tau-tool", "30", "--tau-patch", "4,8",
         "--cache-dir", str(tmp_path / "cache")], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert "OOF F1" in done.stdout and "best:" in done.stdout
    chosen = json.loads(best.read_text())
    assert chosen["grid_search"]["grid_points"] == 8
    model_path = tmp_path / "model.json"
    run("fit", *map(str, study["train"]), "--params", str(best), "-o", str(model_path),
        "--cache-dir", str(tmp_path / "cache"), "--model-kind", "paper")  # the recipe scores with the paper's HMM
    model = load_model(model_path)
    assert {k: getattr(model.patch_params, k) for k in ("n1", "n2", "tau_tool", "tau_patch")} == \
        {k: chosen["patch_params"][k] for k in ("n1", "n2", "tau_tool", "tau_patch")}
    ens = model.ensemble
    labels = []
    for session in study["train"]:
        rows = read_csv(next((tmp_path / "cache" / "features").glob(f"{Path(session).name}-*.csv")))
        labels.append(np.array([int(r["label"]) if r["label"] else -1 for r in rows]))
    y = np.concatenate(labels)
    p = np.concatenate(ens.oof_posteriors_)
    keep = y >= 0
    assert f1_score(y[keep], p[keep] >= ens.threshold_) == pytest.approx(chosen["grid_search"]["best_oof_f1"], abs=1e-12)
    assert average_precision_score(y[keep], p[keep]) == pytest.approx(chosen["grid_search"]["best_oof_auprc"], abs=1e-12)


# ------------------------------------------------------------------ model kinds (issue 34)


def test_fit_records_the_model_kind_and_model_kind_selects_one(study, tmp_path):
    from contact_viz.model.hmm import HMMParams
    from contact_viz.model.kinds import FIT_DEFAULT_KIND
    from contact_viz.params import PatchParams as Params
    from contact_viz.pipeline.features import fit_loso, load_features

    default = json.loads(Path(study["model"]).read_text())
    assert default["model_kind"] == FIT_DEFAULT_KIND
    assert {m["params"]["model_kind"] for m in default["ensemble"]["models"]} == {FIT_DEFAULT_KIND}
    features = load_features(study["train"], Params(), cache_dir=study["cache"])
    for kind in ("paper", "tied"):
        out = tmp_path / f"{kind}.json"
        done = run("fit", *map(str, study["train"]), "-o", str(out), "--cache-dir", str(study["cache"]),
                   "--model-kind", kind)
        assert f"({kind})" in done.stdout
        model = load_model(out)
        assert model.model_kind == kind and json.loads(out.read_text())["model_kind"] == kind
        # the same ensemble as fitting that kind through the library
        direct = fit_loso(features, HMMParams(model_kind=kind))
        assert model.threshold == direct.threshold_
        np.testing.assert_array_equal(model.predict_proba(features[0].signal), direct.predict_proba(features[0].signal))
    done = run("fit", *map(str, study["train"]), "-o", str(tmp_path / "x.json"), "--model-kind", "gaussian", ok=False)
    assert done.returncode == 2 and "--model-kind must be one of paper, flat, tied, isotonic, clip" in done.stderr
    assert not (tmp_path / "x.json").exists()


def test_a_model_file_without_model_kind_loads_as_the_papers(tmp_path):
    """A model.json written before the kinds existed: no "model_kind", HMMParams without it, no emission."""
    signals, labels = square_wave_sessions(seed=1)
    ens = LosoEnsemble().fit(signals, labels, session_names=["a", "b", "c"])
    data = json.loads(save_model(ContactModel(ens, PatchParams(), LabelParams(), ()), tmp_path / "new.json").read_text())
    old = json.loads(json.dumps(data))
    del old["model_kind"]
    for params in [old["ensemble"]["params"]] + [m["params"] for m in old["ensemble"]["models"]]:
        assert params.pop("model_kind") == "paper"
        params.pop("calibration_min_prob")
    (tmp_path / "old.json").write_text(json.dumps(old))
    back = load_model(tmp_path / "old.json")
    assert back.model_kind == "paper"
    np.testing.assert_array_equal(back.predict_proba(signals[0]), ens.predict_proba(signals[0]))
    mixed = json.loads(json.dumps(data))
    mixed["model_kind"] = "flat"
    (tmp_path / "mixed.json").write_text(json.dumps(mixed))
    with pytest.raises(ValueError, match=r"mixed.json: malformed model.json .*model_kind is 'flat' but the "
                                         r"ensemble holds 'paper'"):
        load_model(tmp_path / "mixed.json")
