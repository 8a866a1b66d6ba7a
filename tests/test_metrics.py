"""Tests of per-session metrics, their macro mean and the Table-1 formatter."""

from __future__ import annotations

import re

import numpy as np
import pytest

from contact_viz.model.metrics import MACRO_ROW, format_table, macro_mean, session_metrics

# labelled frames (the -1 frame is dropped):  pos 0.9 0.6 0.3 | neg 0.7 0.2 0.1 0.3
HAND_LABELS = np.array([1, 1, 1, 0, 0, 0, 0, -1])
HAND_POSTERIOR = np.array([0.9, 0.6, 0.3, 0.7, 0.2, 0.1, 0.3, 0.95])


def slow_auroc(labels, scores):
    """P(score of a random positive > score of a random negative), ties count 1/2."""
    pos = [s for s, y in zip(scores, labels) if y == 1]
    neg = [s for s, y in zip(scores, labels) if y == 0]
    wins = sum(1.0 if p > n else 0.5 if p == n else 0.0 for p in pos for n in neg)
    return wins / (len(pos) * len(neg))


def slow_average_precision(labels, scores):
    """AP = sum_n (R_n - R_{n-1}) P_n over the distinct thresholds, highest first."""
    n_pos = sum(1 for y in labels if y == 1)
    ap, prev_recall = 0.0, 0.0
    for c in sorted(set(scores), reverse=True):
        tp = sum(1 for s, y in zip(scores, labels) if s >= c and y == 1)
        fp = sum(1 for s, y in zip(scores, labels) if s >= c and y == 0)
        recall, precision = tp / n_pos, tp / (tp + fp)
        ap += (recall - prev_recall) * precision
        prev_recall = recall
    return ap


@pytest.mark.filterwarnings("error")
def test_hand_worked_example():
    m = session_metrics(HAND_LABELS, HAND_POSTERIOR, threshold=0.5, name="hand")
    # threshold 0.5 -> predicted contact: 0.9, 0.6 (pos), 0.7 (neg)
    tp, fp, fn, tn = 2, 1, 1, 3
    assert m["accuracy"] == pytest.approx((tp + tn) / 7, abs=1e-12)  # 5/7
    assert m["precision"] == pytest.approx(tp / (tp + fp), abs=1e-12)  # 2/3
    assert m["recall"] == pytest.approx(tp / (tp + fn), abs=1e-12)  # 2/3
    assert m["f1"] == pytest.approx(2 * tp / (2 * tp + fp + fn), abs=1e-12)  # 2/3
    # AUROC: 0.9 beats 4 negatives, 0.6 beats 3, 0.3 beats 2 and ties 1 -> 9.5 / 12
    assert m["auroc"] == pytest.approx(9.5 / 12, abs=1e-12)
    # AP: thresholds 0.9 (P=1, R=1/3), 0.7 (1/2, 1/3), 0.6 (2/3, 2/3), 0.3 (3/5, 1)
    #     = 1/3 * 1 + 0 + 1/3 * 2/3 + 1/3 * 3/5 = 34/45
    assert m["auprc"] == pytest.approx(34 / 45, abs=1e-12)
    assert m["n_frames"] == 7 and m["n_contact"] == 3 and m["notes"] == []
    # the frame at threshold exactly counts as predicted contact
    at = session_metrics(HAND_LABELS, HAND_POSTERIOR, threshold=0.6)
    assert at["recall"] == pytest.approx(2 / 3, abs=1e-12)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_auroc_auprc_vs_slow_formulas(seed):
    rng = np.random.default_rng(seed)
    labels = rng.integers(-1, 2, 120)
    scores = np.round(rng.random(120) * 0.6 + 0.3 * (labels == 1), 2)  # rounding gives ties
    m = session_metrics(labels, scores, threshold=0.5)
    keep = labels != -1
    assert m["auroc"] == pytest.approx(slow_auroc(labels[keep].tolist(), scores[keep].tolist()), abs=1e-12)
    assert m["auprc"] == pytest.approx(slow_average_precision(labels[keep].tolist(), scores[keep].tolist()), abs=1e-12)


@pytest.mark.filterwarnings("error")
def test_single_class_and_nothing_predicted():
    # only no-contact frames, some predicted contact: recall, AUROC, AUPRC undefined; F1 = 0
    m = session_metrics(np.array([0, 0, 0, -1]), np.array([0.9, 0.1, 0.2, 0.5]), 0.5, name="empty")
    assert m["recall"] is None and m["auroc"] is None and m["auprc"] is None
    assert m["precision"] == 0.0 and m["f1"] == 0.0
    assert m["accuracy"] == pytest.approx(2 / 3, abs=1e-12)
    assert any("recall" in n for n in m["notes"]) and any("AUROC" in n for n in m["notes"])
    assert all(n.startswith("empty: ") for n in m["notes"])
    # only no-contact frames, nothing predicted: precision, recall and F1 all undefined
    m = session_metrics(np.array([0, 0]), np.array([0.1, 0.2]), 0.5)
    assert m["precision"] is None and m["recall"] is None and m["f1"] is None and m["accuracy"] == 1.0
    # contact frames but nothing predicted: precision 0 as in the paper's Table 1 (with a note),
    # recall and F1 are a real 0
    m = session_metrics(np.array([1, 1, 0]), np.array([0.1, 0.2, 0.05]), 0.5)
    assert m["precision"] == 0.0 and m["recall"] == 0.0 and m["f1"] == 0.0
    assert m["auroc"] == 1.0
    assert any("precision" in n for n in m["notes"])
    # only contact frames: AUROC / AUPRC undefined
    m = session_metrics(np.array([1, 1]), np.array([0.9, 0.2]), 0.5)
    assert m["auroc"] is None and m["auprc"] is None and m["recall"] == 0.5


def test_bad_input():
    with pytest.raises(ValueError, match="session 'Glove'.*NaN"):
        session_metrics(np.array([1, 0, 1]), np.array([0.2, np.nan, 0.9]), 0.5, name="Glove")
    with pytest.raises(ValueError, match="labels"):
        session_metrics(np.array([1, 0, 2]), np.array([0.2, 0.1, 0.9]), 0.5)
    with pytest.raises(ValueError, match="posterior"):
        session_metrics(np.array([1, 0, 1]), np.array([0.2, 0.1]), 0.5)
    with pytest.raises(ValueError, match="no labelled frames"):
        session_metrics(np.array([-1, -1]), np.array([0.2, 0.1]), 0.5)


def test_macro_mean_ignores_none():
    per_session = {
        "Cup": {"accuracy": 0.9, "precision": 0.8, "recall": 1.0, "f1": 0.9, "auroc": 0.95, "auprc": 0.97},
        "Kidney": {"accuracy": 0.6, "precision": None, "recall": 0.0, "f1": 0.0, "auroc": 0.85, "auprc": 0.9},
        "Glove": {"accuracy": 0.3, "precision": 0.5, "recall": 0.2, "f1": 0.3, "auroc": None, "auprc": None},
    }
    macro = macro_mean(per_session)
    assert macro["accuracy"] == pytest.approx(1.8 / 3, abs=1e-12)
    assert macro["precision"] == pytest.approx(1.3 / 2, abs=1e-12)
    assert macro["recall"] == pytest.approx(1.2 / 3, abs=1e-12)
    assert macro["auroc"] == pytest.approx(1.8 / 2, abs=1e-12)
    assert macro["n_sessions"] == 3
    assert any(n.startswith("precision: mean over 2 of 3") and "Kidney" in n for n in macro["notes"])
    assert not any(n.startswith("accuracy") for n in macro["notes"])
    assert macro_mean({"a": {"auroc": None}})["auroc"] is None


def _rows():
    per_session = {
        "cup_1": session_metrics(HAND_LABELS, HAND_POSTERIOR, 0.5),
        "Glove": session_metrics(np.array([0, 0, 0]), np.array([0.9, 0.1, 0.2]), 0.5),
    }
    return {**per_session, MACRO_ROW: macro_mean(per_session)}


def test_format_markdown_and_text():
    rows = _rows()
    md = format_table(rows, style="markdown").splitlines()
    assert [c.strip() for c in md[0].split("|")[1:-1]] == [
        "Session", "Accuracy", "Precision", "Recall", "F1", "AUROC", "AUPRC"
    ]
    assert re.fullmatch(r"\|(\s*:?-{3,}:?\s*\|){7}", md[1])
    assert md[2].split(" | ")[1:] == ["0.714", "0.667", "0.667", "0.667", "0.792", "0.756 |"]
    assert "| —" in md[3]  # Glove recall / AUROC / AUPRC are None
    assert md[4].startswith("| **Macro** | 0.690 | 0.333 | 0.667 | 0.333 | 0.792 | 0.756 |")
    text = format_table(rows)
    assert text.splitlines()[0].split() == ["Session", "Accuracy", "Precision", "Recall", "F1", "AUROC", "AUPRC"]
    assert "—" in text and "0.714" in text
    with pytest.raises(ValueError, match="style"):
        format_table(rows, style="html")


def test_format_latex_booktabs():
    tex = format_table(_rows(), style="latex")
    lines = tex.splitlines()
    assert lines[0] == r"\begin{tabular}{lcccccc}" and lines[-1] == r"\end{tabular}"
    assert lines[1] == r"\toprule" and lines[3] == r"\midrule" and lines[-2] == r"\bottomrule"
    assert lines[4].startswith(r"cup\_1 & 0.714 & 0.667")
    assert "--" in lines[5] and "—" not in tex
    assert lines[6].startswith(r"\textbf{Macro} & \textbf{0.690} & \textbf{0.333}")
    assert lines[6].endswith(r"\\")


def test_format_two_methods_side_by_side():
    rows = _rows()
    grouped = {name: {"HMM": m, "RGB": rows["cup_1"]} for name, m in rows.items()}
    tex = format_table(grouped, style="latex", methods=["HMM", "RGB"]).splitlines()
    assert tex[0] == r"\begin{tabular}{l" + "c" * 12 + "}"
    assert tex[2] == r" & \multicolumn{6}{c}{HMM} & \multicolumn{6}{c}{RGB} \\"
    assert tex[3] == r"\cmidrule(lr){2-7} \cmidrule(lr){8-13}"
    assert tex[6].count("&") == 12
    md = format_table(grouped, style="markdown", methods=["HMM", "RGB"]).splitlines()
    assert "AUPRC (RGB)" in md[0] and md[0].count("|") == 14
    with pytest.raises(ValueError, match="method 'X'"):
        format_table(grouped, methods=["X"])
