"""fit / evaluate / predict with several instruments: each instrument filtered on its own, the scene
posterior the max over the instruments present, per-instrument training labels and Table rows, and
single-instrument sessions exactly as before. Expected numbers are computed here independently (a
literal forward pass with Python floats, hand-worked labels, scikit-learn metrics)."""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from sklearn.metrics import accuracy_score, average_precision_score, f1_score, roc_auc_score

from contact_viz.errors import SessionError
from contact_viz.io.session import open_session
from contact_viz.model.evaluation import (PER_FRAME_COLUMNS, metrics_table, per_frame_columns, per_frame_rows,
                                         score_session)
from contact_viz.model.hmm import LosoEnsemble, SupervisedGaussianHMM, select_f1_threshold
from contact_viz.model.instruments import scene_posterior, training_labels
from contact_viz.model.metrics import MACRO_ROW, macro_mean, session_metrics
from contact_viz.model.model_file import ContactModel, model_to_dict
from contact_viz.params import LabelParams, PatchParams, to_dict
from contact_viz.pipeline.extract import feature_arrays, write_features
from contact_viz.pipeline.features import (csv_features, features_from_rows, fit_loso, score_features,
                                           with_tool_labels)

CLI = [sys.executable, "-m", "contact_viz.cli"]

# A hand-set model (dec, dec^2): no contact around 1.7 (2 cm), contact around 3.0 (1 mm).
MEANS, VARS = [1.7, 3.0], [0.09, 0.12]
TRANSMAT = [[0.9, 0.1], [0.25, 0.75]]
STARTPROB = [0.25 / 0.35, 0.1 / 0.35]  # stationary distribution of TRANSMAT


def hand_model() -> SupervisedGaussianHMM:
    return SupervisedGaussianHMM.from_dict({"params": {"var_floor": 1e-6}, "means": MEANS, "vars": VARS,
                                            "transmat": TRANSMAT, "startprob": STARTPROB, "n_frames": [1, 1],
                                            "transition_counts": [[9, 1], [1, 3]]})


def slow_forward(x: list[float]) -> list[float]:
    """Literal forward filter: alpha_t ∝ e(x_t) * (A^T alpha_{t-1}), normalised; NaN = no emission."""
    out, alpha = [], None
    for xt in x:
        if math.isnan(xt):
            e = [1.0, 1.0]
        else:
            e = [math.exp(-(xt - MEANS[s]) ** 2 / (2 * VARS[s])) / math.sqrt(2 * math.pi * VARS[s]) for s in (0, 1)]
        if alpha is None:
            prior = list(STARTPROB)
        else:
            prior = [alpha[0] * TRANSMAT[0][0] + alpha[1] * TRANSMAT[1][0],
                     alpha[0] * TRANSMAT[0][1] + alpha[1] * TRANSMAT[1][1]]
        a = [prior[0] * e[0], prior[1] * e[1]]
        alpha = [a[0] / (a[0] + a[1]), a[1] / (a[0] + a[1])]
        out.append(alpha[1])
    return out


# One scene, frame by frame: {object id: signal (None = in the frame, no patch)}; label of the scene.
# Instrument 2 touches (frames 3-7) while 1 hovers; 2 leaves the view after its contact (10-12) while 1
# stays, so its last belief must not count; frame 9 has no instrument at all; frame 1 has 1 without a patch.
SCENE = [
    ({1: 1.65, 2: 1.80}, 0), ({1: None, 2: 1.90}, 0), ({1: 1.75, 2: 2.20}, 0), ({1: 1.70, 2: 2.90}, 1),
    ({1: 1.60, 2: 3.10}, 1), ({1: 1.72, 2: 3.05}, 1), ({2: 3.20}, 1), ({1: 1.68, 2: 2.95}, 1),
    ({1: 1.70, 2: 2.10}, 0), ({}, 0), ({1: 1.66}, 0), ({1: 1.71}, 0), ({1: 1.69}, 0), ({1: 1.73, 2: 1.85}, 0),
]


def rows_of(scene, tool_column: bool = True) -> list[dict]:
    """Feature rows as `extract` gives them (the columns the model reads): one per frame and instrument."""
    rows = []
    for t, (tools, label) in enumerate(scene):
        base = {"frame": f"{t:06d}", "label": label, "distance_m": "", "tool_area_px": ""}
        for tool, value in sorted(tools.items()) or [(None, None)]:
            row = dict(base, signal="" if value is None else repr(value),
                       tool_area_px="" if tool is None else 500)
            if tool_column:
                row["tool"] = "" if tool is None else tool
            rows.append(row)
    return rows


def test_scene_posterior_is_the_max_over_present_instruments_of_literal_forward_passes():
    features = features_from_rows("scene", rows_of(SCENE))
    assert features.tools == (1, 2) and features.frames == [f"{t:06d}" for t in range(len(SCENE))]
    model = hand_model()
    scores = score_features(model.predict_proba, 0.5, features)
    each = {k: slow_forward([math.nan if tools.get(k) is None else tools[k] for tools, _ in SCENE]) for k in (1, 2)}
    expected = []
    for t, (tools, _) in enumerate(SCENE):
        here = [k for k in (1, 2) if k in tools] or [1, 2]
        expected.append(max(each[k][t] for k in here))
    np.testing.assert_allclose(scores.posterior, expected, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(scores.tool_posteriors, [each[1], each[2]], rtol=1e-12, atol=1e-15)
    # the rule matters here: after 2 left the view its belief is far above 1's, which the scene follows
    assert all(each[2][t] > each[1][t] + 0.05 and scores.posterior[t] == pytest.approx(each[1][t], rel=1e-12)
               for t in (10, 11, 12))
    assert scores.posterior[9] == pytest.approx(max(each[1][9], each[2][9]), rel=1e-12)
    assert list(scores.labels) == [label for _, label in SCENE]
    # per-frame output: the scene's posterior and each instrument's, the nearest instrument's signal
    rows = per_frame_rows([scores])
    assert per_frame_columns([scores]) == PER_FRAME_COLUMNS + ("posterior_tool_1", "posterior_tool_2")
    assert [float(r["posterior_tool_2"]) for r in rows] == pytest.approx(each[2], rel=1e-12)
    assert rows[4]["signal"] == repr(3.10) and rows[1]["signal"] == repr(1.90) and rows[9]["signal"] == ""


def test_streaming_scene_filter_equals_the_whole_session_bit_for_bit():
    from contact_viz.model.hmm import SceneStreamingFilter

    rng = np.random.default_rng(11)
    feats = [features_from_rows(f"s{k}", rows_of(random_scene(rng, n, 2, [2, 3])))
             for k, n in enumerate((80, 60, 70))]
    ensemble = fit_loso(feats)
    for scene, tools in ((SCENE, (1, 2)), (random_scene(rng, 50, 3, [1, 2, 6]), (1, 2, 6)),
                         (random_scene(rng, 40, 1), (1,))):
        features = features_from_rows("s", rows_of(scene))
        scores = score_features(ensemble.predict_proba, ensemble.threshold_, features)
        stream = SceneStreamingFilter(ensemble)
        for t, (present, _) in enumerate(scene):
            value, each = stream.update({k: math.nan if v is None else v for k, v in present.items()})
            assert value == scores.posterior[t]
            if features.several:
                assert all(each[k] == scores.tool_posteriors[features.tools.index(k), t] for k in each)
        assert tools == features.tools


def test_scene_posterior_rule_directly():
    p = np.array([[0.2, 0.9, 0.4, 0.3], [0.6, 0.1, 0.7, 0.8]])
    present = np.array([[True, True, False, False], [True, False, True, False]])
    assert scene_posterior(p, present).tolist() == [0.6, 0.9, 0.7, 0.8]
    assert scene_posterior(p).tolist() == [0.6, 0.9, 0.7, 0.8]
    one = np.array([[0.1, 0.7, 0.3]])  # one instrument: its posterior, present or not
    assert scene_posterior(one, np.array([[False, True, False]])).tolist() == [0.1, 0.7, 0.3]


def test_training_labels_worked_example():
    nan = math.nan
    scene = [0, 1, 1, 1, 1, -1, 1, 1, 0, 1, 0, 1, 1, 1]
    signals = [
        [1.0, 2.0, nan, nan, 1.0, 1.0, nan, nan, 1.0, 2.0, 1.0, nan, 1.5, 2.5],  # id 1
        [1.0, 3.0, nan, nan, 2.5, 1.0, nan, nan, 1.0, 2.0, 1.0, nan, 1.0, 1.0],  # id 2
        [nan, 1.0, nan, nan, 2.9, nan, nan, nan, nan, nan, nan, nan, 2.2, 2.0],  # id 5
    ]
    # frame 1: 2 is nearest; 2-3 have no signal: the run keeps 2; 4: 5 is nearest; 5 unknown; 6-7: a run
    # without any signal (unknown); 9: a tie goes to the lowest id; 11 takes the run's first measured pick (12,
    # not 13's)
    expected = [
        [0, 0, 0, 0, 0, -1, -1, -1, 0, 1, 0, 0, 0, 1],
        [0, 1, 1, 1, 0, -1, -1, -1, 0, 0, 0, 0, 0, 0],
        [0, 0, 0, 0, 1, -1, -1, -1, 0, 0, 0, 1, 1, 0],
    ]
    got = training_labels(np.array(signals), np.array(scene))
    assert got.dtype == np.int8 and got.tolist() == expected
    # labels.csv's per-instrument labels win in the frames they name (others there: unknown)
    given = np.full((3, 14), -1)
    given[0, 6] = 1
    given[:, 0] = [0, 1, 0]  # frame 0: the scene said 0, but instrument 2 is labelled in contact
    got = training_labels(np.array(signals), np.array(scene), given)
    assert got[:, 6].tolist() == [1, -1, -1] and got[:, 7].tolist() == [-1, -1, -1]
    assert got[:, 0].tolist() == [0, 1, 0]
    assert got[:, 1:6].tolist() == np.array(expected)[:, 1:6].tolist()
    # one instrument: the scene's labels, also where it has no signal
    assert training_labels(np.array([[nan, nan, 1.0, nan]]), np.array([1, 1, 0, -1])).tolist() == [[1, 1, 0, -1]]


def random_scene(rng: np.random.Generator, n: int, n_tools: int, tool_ids=None):
    """A scene of ``n_tools`` instruments: contact episodes of one instrument at a time, some absences."""
    tool_ids = tool_ids or list(range(1, n_tools + 1))
    who = np.zeros(n, dtype=int)  # 0 = no contact, else the touching instrument's index + 1
    t = 5
    while t < n - 10:
        length = int(rng.integers(4, 9))
        who[t:t + length] = rng.integers(1, n_tools + 1)
        t += length + int(rng.integers(5, 12))
    scene = []
    for t in range(n):
        tools = {}
        for k, tool in enumerate(tool_ids):
            if rng.random() < 0.08 and who[t] != k + 1:
                continue  # absent
            mean = 3.0 if who[t] == k + 1 else 1.7
            tools[tool] = None if rng.random() < 0.05 else float(np.round(rng.normal(mean, 0.25), 6))
        scene.append((tools, int(who[t] > 0) if rng.random() > 0.03 else -1))
    return scene


def test_single_instrument_rows_fit_and_predict_exactly_as_without_a_tool_column(tmp_path):
    rng = np.random.default_rng(7)
    scenes = [random_scene(rng, n, 1) for n in (90, 70, 80)]
    plain = [features_from_rows(f"s{k}", rows_of(s, tool_column=False)) for k, s in enumerate(scenes)]
    tooled = [features_from_rows(f"s{k}", rows_of(s)) for k, s in enumerate(scenes)]
    # the single instrument under another id (a tool column in the file) is still one sequence
    other_id = [features_from_rows(f"s{k}", [dict(r, tool=3 if r["tool"] != "" else "") for r in rows_of(s)])
                for k, s in enumerate(scenes)]
    # and read back from a features CSV (no tool column: instrument 1 only)
    config = {"session": {"name": "x"}, "patch_params": to_dict(PatchParams())}
    from_csv = []
    for k, s in enumerate(scenes):
        path = write_features(rows_of(s), tmp_path / f"s{k}.csv", dict(config, session={"name": f"s{k}"}))
        assert path.read_text().startswith("frame,timestamp,")
        from_csv.append(csv_features(path, PatchParams()))
    # the code before several instruments: one row per frame, LosoEnsemble on (signal, labels)
    arrays = [feature_arrays(rows_of(s, tool_column=False)) for s in scenes]
    reference = LosoEnsemble().fit([x for x, _ in arrays], [y for _, y in arrays], session_names=["s0", "s1", "s2"])

    def dump(ensemble):
        model = ContactModel(ensemble, PatchParams(), LabelParams(), ())
        return json.dumps(model_to_dict(model))

    for group in (plain, tooled, other_id, from_csv):
        ensemble = fit_loso(group)
        assert dump(ensemble) == dump(reference)
        for f, (x, y) in zip(group, arrays):
            scores = score_features(ensemble.predict_proba, ensemble.threshold_, f)
            old = score_session(reference.predict_proba, reference.threshold_, f.name, f.frames, x, y)
            assert scores.posterior.tobytes() == old.posterior.tobytes()
            assert per_frame_columns([scores]) == PER_FRAME_COLUMNS
            assert per_frame_rows([scores]) == per_frame_rows([old])
            assert metrics_table([scores], ensemble.threshold_) == metrics_table([old], reference.threshold_)


def test_loso_on_instrument_sequences():
    rng = np.random.default_rng(3)
    feats = [features_from_rows(f"s{k}", rows_of(random_scene(rng, n, 2, [1, 4])))
             for k, n in enumerate((120, 90, 100))]
    assert all(f.tools == (1, 4) for f in feats)
    ensemble = fit_loso(feats)
    seqs = [(f.tool_signals, training_labels(f.tool_signals, f.labels)) for f in feats]
    pooled = []
    for k, f in enumerate(feats):
        rest = [i for i in range(3) if i != k]
        fold = SupervisedGaussianHMM().fit([row for i in rest for row in seqs[i][0]],
                                           [row for i in rest for row in seqs[i][1]])
        assert ensemble.models_[k].to_dict() == fold.to_dict()
        each = np.stack([fold.predict_proba(row) for row in f.tool_signals])
        expected = np.where(f.present, each, -np.inf).max(axis=0)
        empty = ~f.present.any(axis=0)
        expected[empty] = each[:, empty].max(axis=0)
        np.testing.assert_array_equal(ensemble.oof_posteriors_[k], expected)
        pooled.append(expected)
    scores, labels = np.concatenate(pooled), np.concatenate([f.labels for f in feats]).astype(int)
    keep = labels >= 0
    candidates = sorted(set(scores[keep].tolist()))
    f1 = [f1_score(labels[keep], (scores[keep] >= c).astype(int), zero_division=0) for c in candidates]
    assert ensemble.threshold_ == candidates[int(np.argmax(f1))]
    assert ensemble.threshold_ == select_f1_threshold(scores, labels)


def test_per_instrument_labels_give_table_rows_scored_on_each_instruments_posterior():
    scene = SCENE
    features = features_from_rows("S", rows_of(scene))
    stems = features.frames
    label_1 = np.array([0] * len(scene), np.int8)
    label_2 = np.array([label for _, label in scene], np.int8)
    label_2[13] = -1  # no row for 2 in the last frame
    label_1[[4, 5]] = 1  # (say) 1 was in contact too
    features = with_tool_labels(features, {1: label_1, 2: label_2, 7: np.zeros(len(scene), np.int8)}, stems)
    assert features.tool_labels.tolist() == [label_1.tolist(), label_2.tolist()]
    threshold = 0.5
    scores = score_features(hand_model().predict_proba, threshold, features)
    table = metrics_table([scores], threshold)
    assert list(table) == ["S", "S tool 1", "S tool 2", MACRO_ROW]
    for tool, labels in ((1, label_1), (2, label_2)):
        posterior = slow_forward([math.nan if tools.get(tool) is None else tools[tool] for tools, _ in scene])
        expected = session_metrics(labels.astype(np.int64), np.array(posterior), threshold, name=f"S tool {tool}")
        got = table[f"S tool {tool}"]
        assert got.keys() == expected.keys()
        for key in ("accuracy", "precision", "recall", "f1", "auroc", "auprc", "n_frames", "n_contact"):
            assert got[key] == pytest.approx(expected[key], rel=1e-12), key
        # and against scikit-learn directly
        keep = labels >= 0
        y, p = labels[keep], np.array(posterior)[keep]
        assert got["accuracy"] == pytest.approx(accuracy_score(y, p >= threshold))
        assert got["f1"] == pytest.approx(f1_score(y, p >= threshold))
        assert got["auroc"] == pytest.approx(roc_auc_score(y, p))
        assert got["auprc"] == pytest.approx(average_precision_score(y, p))
    assert table[MACRO_ROW] == macro_mean({"S": table["S"]})  # sessions only


# ------------------------------------------------------------------ labels.csv with a tool column

H, W = 64, 96
TOOL_COLUMNS = {1: (10, 26), 2: (60, 76)}  # the instruments' shafts, image columns (from the top edge)


def write_palette_png(path: Path, ids: np.ndarray) -> None:
    image = Image.fromarray(ids.astype(np.uint8))
    image.putpalette([0, 0, 0, 255, 0, 0, 0, 255, 0] + [0] * (256 * 3 - 9))
    image.save(path)


def write_session(root: Path, gaps: dict[int, list], force_n: list[float] | None = None,
                  labels_csv: str | None = None, seed: int = 0) -> Path:
    """A session of instruments 1 and 2 over a tissue plane at 0.10 m: each a vertical shaft from the top
    edge whose depth is ``gap`` nearer the camera (None = out of the frame); depth as .npy."""
    rng = np.random.default_rng(seed)
    for sub in ("left", "masks", "depth"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    (root / "K.txt").write_text("300 0 48 0 300 32 0 0 1\n0.005\n")
    n = len(next(iter(gaps.values())))
    for t in range(n):
        stem = f"{t:04d}"
        ids = np.zeros((H, W), np.uint8)
        depth = 0.10 + rng.normal(0.0, 0.0001, (H, W))
        for tool, gap in gaps.items():
            if gap[t] is None:
                continue
            c0, c1 = TOOL_COLUMNS[tool]
            ids[:30, c0:c1] = tool
            depth[:30, c0:c1] = 0.10 - gap[t] + rng.normal(0.0, 0.0001, (30, c1 - c0))
        Image.fromarray(rng.integers(0, 256, (H, W, 3), dtype=np.uint8)).save(root / "left" / f"{stem}.png")
        write_palette_png(root / "masks" / f"{stem}.png", ids)
        np.save(root / "depth" / f"{stem}.npy", depth.astype(np.float32))
    if force_n is not None:
        (root / "force.csv").write_text("frame,fx,fy,fz\n" + "".join(f"{t},0,0,{f}\n" for t, f in enumerate(force_n)))
    if labels_csv is not None:
        (root / "labels.csv").write_text(labels_csv)
    return root


def episode(n: int, contact: list[range], hover: float = 0.02) -> list[float]:
    """Gaps (m): hovering, approaching over 4 frames, 0.8 mm in contact, leaving over 4 frames."""
    gap = [hover + 0.003 * math.sin(t) for t in range(n)]
    for r in contact:
        for i, g in enumerate((0.012, 0.006, 0.003, 0.0015)):
            if 0 <= r.start - 4 + i < n:
                gap[r.start - 4 + i] = g
            if 0 <= r.stop + 3 - i < n:
                gap[r.stop + 3 - i] = g
        for t in r:
            gap[t] = 0.0008
    return gap


def test_labels_csv_with_a_tool_column(tmp_path):
    gaps = {1: [0.02] * 5, 2: [0.02] * 5}
    rows = "frame,tool,contact\n0,1,0\n0,2,0\n1,2,1\n1,1,0\n2,1,1\n3,2,0\n"
    root = write_session(tmp_path / "s", gaps, force_n=[0.0, 0.0, 0.0, 0.0, 5.0], labels_csv=rows)
    session = open_session(root)
    assert session.labels.tolist() == [0, 1, 1, 0, 1]  # any instrument in contact; frame 4: the force
    assert session.label_source.tolist() == ["manual"] * 4 + ["force"]
    assert {k: v.tolist() for k, v in session.tool_labels.items()} == {1: [0, 0, 1, -1, -1], 2: [0, 1, -1, 0, -1]}
    only_1 = open_session(root, object_ids=[1])  # instrument 2 not selected: its labels do not count
    assert only_1.labels.tolist() == [0, 0, 1, 0, 1] and list(only_1.tool_labels) == [1]
    assert open_session(root, object_ids=[1]).label_source.tolist()[3] == "force"
    (root / "labels.csv").write_text("frame,contact\n1,1\n")
    assert open_session(root).tool_labels is None
    for text, words in (("frame,tool,contact\n1,2,1\n01,2,0\n", ["one row per frame and instrument", "tool 2"]),
                        ("frame,tool,contact\n1,0,1\n", ["object id", "'0'"]),
                        ("frame,tool,contact\n1,,1\n", ["object id", "line 2"])):
        (root / "labels.csv").write_text(text)
        with pytest.raises(SessionError) as info:
            open_session(root)
        assert all(w in str(info.value) for w in words), str(info.value)


# ------------------------------------------------------------------ CLI round trip


def run(*args: str) -> subprocess.CompletedProcess:
    done = subprocess.run([*CLI, *args], capture_output=True, text=True, env={**os.environ, "COLUMNS": "120"})
    assert done.returncode == 0, done.stderr
    return done


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


N_FRAMES = 40
TOUCH_2, TOUCH_1 = range(8, 16), range(24, 32)  # the held-out session: 2 touches, then 1
LABELS_1 = [int(t in TOUCH_1) for t in range(N_FRAMES)]
LABELS_2 = [int(t in TOUCH_2) for t in range(N_FRAMES)]


@pytest.fixture(scope="module")
def two_tool_sessions(tmp_path_factory) -> dict:
    """Two training sessions where 2 touches while 1 hovers (force labels; 1 out of view for a few frames),
    and a held-out one where each instrument touches once, labelled per instrument in labels.csv."""
    root, n = tmp_path_factory.mktemp("two_tools"), N_FRAMES
    train = []
    for k, (first, second) in enumerate(((range(10, 18), range(28, 34)), (range(8, 15), range(25, 32)))):
        gap_2 = episode(n, [first, second])
        gap_1 = [None if (k == 0 and t < 4) or (k == 1 and t >= 36) else g for t, g in enumerate(episode(n, []))]
        force = [3.0 if (t in first or t in second) else 0.1 for t in range(n)]
        train.append(write_session(root / f"train_{k}", {1: gap_1, 2: gap_2}, force_n=force, seed=k))
    text = "frame,tool,contact\n" + "".join(f"{t},1,{LABELS_1[t]}\n{t},2,{LABELS_2[t]}\n" for t in range(n))
    gap_1 = [None if t < 3 else g for t, g in enumerate(episode(n, [TOUCH_1]))]
    test = write_session(root / "test_c", {1: gap_1, 2: episode(n, [TOUCH_2])}, labels_csv=text, seed=5)
    return {"train": train, "test": test}


def test_cli_fit_evaluate_predict_with_two_instruments(two_tool_sessions, tmp_path):
    n, train, test = N_FRAMES, two_tool_sessions["train"], two_tool_sessions["test"]
    labels_1, labels_2 = LABELS_1, LABELS_2
    cache, model = tmp_path / "cache", tmp_path / "model.json"

    run("fit", *map(str, train), "-o", str(model), "--cache-dir", str(cache))
    data = json.loads(model.read_text())
    assert [s["tools"] for s in data["training_sessions"]] == [[1, 2], [1, 2]]
    for hmm in data["ensemble"]["models"]:  # contact (instrument 2's touches) has the larger signal
        assert hmm["means"][1] > hmm["means"][0] + 0.5

    per_frame, metrics_json = tmp_path / "frames.csv", tmp_path / "metrics.json"
    done = run("evaluate", str(model), str(test), "--per-frame", str(per_frame), "--json", str(metrics_json),
               "--cache-dir", str(cache))
    lines = [line.split()[0:3] for line in done.stdout.splitlines()]
    assert ["test_c", "tool", "1"] in lines and ["test_c", "tool", "2"] in lines
    rows = read_csv(per_frame)
    assert len(rows) == n and list(rows[0]) == [*PER_FRAME_COLUMNS, "posterior_tool_1", "posterior_tool_2"]
    scene = np.array([float(r["posterior"]) for r in rows])
    p1 = np.array([float(r["posterior_tool_1"]) for r in rows])
    p2 = np.array([float(r["posterior_tool_2"]) for r in rows])
    assert scene[3:].tolist() == np.maximum(p1, p2)[3:].tolist()  # both present
    assert scene[:3].tolist() == p2[:3].tolist()  # 1 absent: its prediction does not count
    assert [int(r["label"]) for r in rows] == [max(a, b) for a, b in zip(labels_1, labels_2)]
    metrics = json.loads(metrics_json.read_text())
    threshold = metrics["threshold"]
    for tool, labels, p in ((1, labels_1, p1), (2, labels_2, p2)):
        got = metrics["metrics"][f"test_c tool {tool}"]
        assert got["f1"] == pytest.approx(f1_score(labels, p >= threshold))
        assert got["auroc"] == pytest.approx(roc_auc_score(labels, p))
        assert got["auprc"] == pytest.approx(average_precision_score(labels, p))
        assert got["f1"] > 0.8  # each instrument's own posterior finds its own touches
    scene_labels = [max(a, b) for a, b in zip(labels_1, labels_2)]
    assert metrics["metrics"]["test_c"]["auroc"] == pytest.approx(roc_auc_score(scene_labels, scene))
    assert metrics["metrics"][MACRO_ROW]["n_sessions"] == 1

    out = tmp_path / "pred.csv"
    run("predict", str(model), str(test), "-o", str(out), "--cache-dir", str(cache))
    assert read_csv(out) == rows


def test_batch_fits_and_evaluates_per_instrument(two_tool_sessions, tmp_path):
    from contact_viz.pipeline.batch import BatchOptions, run_batch
    from contact_viz.pipeline.engines import LocalEngine

    listing = tmp_path / "sessions.txt"
    listing.write_text("".join(f"{p}\n" for p in [*two_tool_sessions["train"], two_tool_sessions["test"]]))
    out = tmp_path / "out"
    engine = LocalEngine(1)
    try:
        summary = run_batch(listing, out, BatchOptions(steps=("extract", "fit", "evaluate"),
                                                       cache_dir=str(tmp_path / "cache")), engine)
    finally:
        engine.close()
    assert not summary.failed and summary.dataset["fit"].startswith("done: 3 LOSO models"), summary.dataset
    features = read_csv(out / "test_c" / "features.csv")  # one row per frame and instrument (1 enters at 3)
    assert [(r["frame"], r["tool"]) for r in features[:5]] == [("0000", "2"), ("0001", "2"), ("0002", "2"),
                                                               ("0003", "1"), ("0003", "2")]
    model = json.loads((out / "model.json").read_text())
    assert all(s["tools"] == [1, 2] for s in model["training_sessions"])
    rows = [r for r in read_csv(out / "per_frame.csv") if r["session"] == "test_c"]
    assert list(rows[0])[-2:] == ["posterior_tool_1", "posterior_tool_2"] and len(rows) == N_FRAMES
    p1 = np.array([float(r["posterior_tool_1"]) for r in rows])
    p2 = np.array([float(r["posterior_tool_2"]) for r in rows])
    assert [float(r["posterior"]) for r in rows][3:] == np.maximum(p1, p2)[3:].tolist()
    metrics = json.loads((out / "metrics.json").read_text())
    assert list(metrics["metrics"]) == ["train_0", "train_1", "test_c", "test_c tool 1", "test_c tool 2", MACRO_ROW]
    threshold = metrics["threshold"]
    for labels, p, tool in ((LABELS_1, p1, 1), (LABELS_2, p2, 2)):
        assert metrics["metrics"][f"test_c tool {tool}"]["f1"] == pytest.approx(f1_score(labels, p >= threshold))
    assert metrics["metrics"][MACRO_ROW]["n_sessions"] == 3
