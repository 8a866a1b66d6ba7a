"""recipes/reproduce_paper.py end to end in its --tiny configuration (a few seconds of training)."""

from __future__ import annotations

import csv
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from contact_viz.model.metrics import MACRO_ROW, METRIC_KEYS, session_metrics

RECIPE = Path(__file__).resolve().parents[1] / "recipes" / "reproduce_paper.py"
OUTPUTS = ("table1.md", "table1.tex", "table1.csv", "timelines.png", "timelines.pdf", "pipeline.png",
           "pipeline.pdf", "per_frame_hmm.csv", "per_frame_rgb.csv", "config.json", "model.json")


def load_recipe():
    spec = importlib.util.spec_from_file_location("reproduce_paper", RECIPE)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def recipe():
    return load_recipe()


@pytest.fixture(scope="module")
def run(recipe, tmp_path_factory):
    """The synthetic study in the tiny configuration: (output folder, printed text)."""
    root = tmp_path_factory.mktemp("paper")
    out = root / "results"
    import contextlib
    import io

    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = recipe.main(["--tiny", "-o", str(out), "--cache-dir", str(root / "cache")])
    assert code == 0
    return out, printed.getvalue()


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def test_every_output_exists_and_no_temp_file_is_left(run):
    out, printed = run
    for name in OUTPUTS:
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert not [p for p in out.rglob("*.tmp")]
    assert (out / "timelines.png").read_bytes()[:4] == b"\x89PNG"
    assert (out / "pipeline.pdf").read_bytes()[:5] == b"%PDF-"
    assert "Macro" in printed and str(out) in printed


def test_table1_equals_the_metrics_recomputed_from_the_per_frame_csvs(run):
    out, _ = run
    table = read_csv(out / "table1.csv")
    config = json.loads((out / "config.json").read_text())
    methods = list(config["thresholds"])
    assert methods[0] == "HMM" and len(methods) == 2
    per_frame = dict(zip(methods, (read_csv(out / "per_frame_hmm.csv"), read_csv(out / "per_frame_rgb.csv"))))
    test_names = [t["session"] for t in config["split"]["test"]]
    assert [r["session"] for r in table] == [n for n in [*test_names, MACRO_ROW] for _ in methods]
    by_key = {(r["session"], r["method"]): r for r in table}
    for method, frames in per_frame.items():
        threshold = config["thresholds"][method]
        macro = {k: [] for k in METRIC_KEYS}
        for name in test_names:
            rows = [r for r in frames if r["session"] == name]
            labels = np.array([int(r["label"]) if r["label"] != "" else -1 for r in rows])
            posterior = np.array([float(r["posterior"]) for r in rows])
            np.testing.assert_array_equal([int(r["predicted"]) for r in rows], (posterior >= threshold).astype(int))
            expected = session_metrics(labels, posterior, threshold, name=name)
            got = by_key[(name, method)]
            assert float(got["threshold"]) == threshold
            for key in METRIC_KEYS:
                if expected[key] is None:
                    assert got[key] == ""
                else:
                    assert float(got[key]) == pytest.approx(expected[key], abs=1e-12), (name, method, key)
                    macro[key].append(expected[key])
            assert int(got["n_frames"]) == expected["n_frames"]
        for key in METRIC_KEYS:
            assert float(by_key[(MACRO_ROW, method)][key]) == pytest.approx(np.mean(macro[key]), abs=1e-12)


def test_per_frame_csvs_cover_every_test_frame_with_its_time(run):
    out, _ = run
    config = json.loads((out / "config.json").read_text())
    sessions_dir = Path(config["sessions_dir"])
    hmm, rgb = read_csv(out / "per_frame_hmm.csv"), read_csv(out / "per_frame_rgb.csv")
    for entry in config["split"]["test"]:
        session_json = json.loads((sessions_dir / entry["session"] / "session.json").read_text())
        fps, frames = session_json["fps"], session_json["generator"]["frames"]
        for rows in (hmm, rgb):
            mine = [r for r in rows if r["session"] == entry["session"]]
            assert len(mine) == frames
            assert {r["category"] for r in mine} == {entry["category"]}
            np.testing.assert_allclose([float(r["timestamp_s"]) for r in mine], np.arange(frames) / fps)


def test_config_records_the_run_and_says_the_baseline_is_not_the_papers(run):
    out, printed = run
    config = json.loads((out / "config.json").read_text())
    from contact_viz import __version__

    assert config["contact_viz_version"] == __version__
    assert config["profile"] == "tiny" and config["quick"] is False
    assert config["split"]["train"] == ["cup_train_0", "cup_train_1", "cup_train_2"]
    assert [t["category"] for t in config["split"]["test"]] == ["same phantom and task", "new phantom and task"]
    assert config["baseline"]["paper_configuration"] is False
    # the recorded baseline params are the ones the folds were trained with (as their ensemble.json says)
    trained = json.loads((Path(config["baseline"]["checkpoints"]) / "ensemble.json").read_text())
    assert config["baseline"]["params"] == trained["params"] and config["baseline"]["params"]["crop_px"] == 64
    assert config["seeds"]["synthetic"] == {"cup_train_0": 0, "cup_train_1": 1, "cup_train_2": 2,
                                            "cup_test": 100, "glove_test": 103}
    model = json.loads((out / "model.json").read_text())
    assert model["threshold"] == config["thresholds"]["HMM"]
    for name in ("table1.md", "table1.tex"):
        assert "NOT the paper's configuration" in (out / name).read_text()
    assert "NOT the paper's configuration" in printed
    tex = (out / "table1.tex").read_text()
    assert r"\toprule" in tex and r"\bottomrule" in tex and r"\multicolumn{6}{c}{HMM}" in tex


def test_rerun_on_a_given_split_reuses_the_baseline_checkpoints(run, recipe, tmp_path):
    """SESSIONS + SPLIT (the generated study's) with --grid-search: same baseline rows (folds loaded)."""
    out, _ = run
    config = json.loads((out / "config.json").read_text())
    out2 = tmp_path / "again"
    # The baseline checkpoints live in the results folder: start from a copy of the first run's.
    import shutil

    shutil.copytree(out / "baseline", out2 / "baseline")
    code = recipe.main([config["sessions_dir"], config["split_file"], "--tiny", "--grid-search", "-o", str(out2),
                        "--cache-dir", str(Path(config["sessions_dir"]).parents[2] / "cache")])
    assert code == 0
    grid = json.loads((out2 / "grid_search.json").read_text())
    config2 = json.loads((out2 / "config.json").read_text())
    assert config2["patch_params"] == grid["best"]["patch_params"]
    assert config2["patch_params_source"] == "grid search"
    rgb = [m for m in config["thresholds"] if m != "HMM"][0]
    first = [r for r in read_csv(out / "table1.csv") if r["method"] == rgb]
    second = [r for r in read_csv(out2 / "table1.csv") if r["method"] == rgb]
    assert [{k: r[k] for k in METRIC_KEYS} for r in first] == [{k: r[k] for k in METRIC_KEYS} for r in second]


def test_missing_split_file_is_one_error_line(recipe, tmp_path):
    assert recipe.main([str(tmp_path), str(tmp_path / "missing.json"), "--tiny", "-o", str(tmp_path / "o")]) == 1
