"""Per-session contact-detection metrics, their macro mean, and Table-1 style formatting.

Rules for undefined metrics (reported as ``None`` with an explanation in ``notes``, never NaN):

* precision when no frame is predicted contact: 0 if the session has contact frames (the
  paper's Table 1 convention, scikit-learn's ``zero_division=0``: a method that never fires
  scores 0 and that 0 counts in the macro mean), None if it has none either;
* recall is None when no frame is labelled contact (TP + FN = 0);
* F1 = 2 TP / (2 TP + FP + FN) is None only when there are neither labelled nor predicted
  contact frames; with labelled contact frames but no predictions it is 0 (a real miss);
* AUROC and AUPRC (average precision) are None for a single-class session: AUROC needs both
  classes, AP needs a contact frame and is trivially 1 without a no-contact frame.

``macro_mean`` says how many sessions each mean covers.
Frames labelled -1 (unknown) are excluded everywhere. Pure computation: no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

METRIC_KEYS = ("accuracy", "precision", "recall", "f1", "auroc", "auprc")
METRIC_TITLES = ("Accuracy", "Precision", "Recall", "F1", "AUROC", "AUPRC")
MACRO_ROW = "Macro"
DECIMALS = 3
MISSING_TEXT = "—"  # None in text / markdown tables
MISSING_LATEX = "--"  # None in LaTeX tables
TABLE_STYLES = ("text", "markdown", "latex")


def session_metrics(labels: Any, posterior: Any, threshold: float, name: str | None = None) -> dict[str, Any]:
    """Metrics of one session.

    Args:
        labels: (T,) int in {-1, 0, 1}; -1 = unknown, excluded.
        posterior: (T,) float P(contact) per frame; must be finite on labelled frames.
        threshold: predict contact where ``posterior >= threshold``.
        name: session name, used in error messages and notes.

    Returns:
        dict with accuracy, precision, recall, f1 (from thresholded predictions), auroc, auprc
        (average precision, from the posteriors), each a float or None (see module docstring);
        n_frames (labelled frames scored), n_contact (frames labelled contact), and notes (list of
        str explaining every None).
    """
    from sklearn.metrics import (
        accuracy_score,
        average_precision_score,
        f1_score,
        precision_score,
        recall_score,
        roc_auc_score,
    )

    who = f"session {name!r}" if name is not None else "session"
    y = np.asarray(labels)
    p = np.asarray(posterior)
    if y.ndim != 1 or not np.issubdtype(y.dtype, np.integer):
        raise ValueError(f"{who}: labels: expected a 1-D integer array, got shape {y.shape} dtype {y.dtype}")
    if p.ndim != 1 or p.shape[0] != y.shape[0] or not np.issubdtype(p.dtype, np.number):
        raise ValueError(f"{who}: posterior: expected a 1-D float array of {y.shape[0]} values, got shape {p.shape}")
    bad = ~np.isin(y, (-1, 0, 1))
    if bad.any():
        raise ValueError(f"{who}: labels: expected values in {{-1, 0, 1}}, found {sorted(set(y[bad].tolist()))[:5]}")
    if not math.isfinite(threshold):
        raise ValueError(f"{who}: threshold: expected a finite number, got {threshold!r}")
    keep = y != -1
    y, p = (y[keep] == 1).astype(np.int64), p[keep].astype(np.float64)
    if not np.isfinite(p).all():
        raise ValueError(f"{who}: posterior has {int((~np.isfinite(p)).sum())} NaN/inf value(s) on labelled frames")
    if y.shape[0] == 0:
        raise ValueError(f"{who}: no labelled frames (every label is -1)")

    pred = (p >= threshold).astype(np.int64)
    n_pos = int(y.sum())
    n_neg = int(y.shape[0] - n_pos)
    n_pred = int(pred.sum())
    notes: list[str] = []
    out: dict[str, Any] = {"accuracy": float(accuracy_score(y, pred))}
    if n_pred > 0:
        out["precision"] = float(precision_score(y, pred))
    elif n_pos > 0:
        # The paper's Table 1 convention (sklearn's zero_division=0): a method that never fires on
        # a session with contact frames scores precision 0, and that 0 counts in the macro mean.
        out["precision"] = 0.0
        notes.append(f"precision set to 0: no frame predicted contact at threshold {threshold:g}")
    else:
        out["precision"] = None
        notes.append(f"precision undefined: no frame labelled or predicted contact at threshold {threshold:g}")
    if n_pos > 0:
        out["recall"] = float(recall_score(y, pred))
    else:
        out["recall"] = None
        notes.append("recall undefined: no frame labelled contact")
    if n_pos > 0 or n_pred > 0:
        out["f1"] = float(f1_score(y, pred))
    else:
        out["f1"] = None
        notes.append("F1 undefined: no frame labelled or predicted contact")
    if n_pos > 0 and n_neg > 0:
        out["auroc"] = float(roc_auc_score(y, p))
        out["auprc"] = float(average_precision_score(y, p))
    else:
        out["auroc"] = out["auprc"] = None
        only = "contact" if n_pos else "no contact"
        notes.append(f"AUROC and AUPRC undefined: every labelled frame is {only} (single class)")
    out["n_frames"] = int(y.shape[0])
    out["n_contact"] = n_pos
    out["notes"] = [f"{name}: {n}" for n in notes] if name is not None else notes
    return out


def macro_mean(per_session: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """Mean over sessions of each metric in METRIC_KEYS, ignoring None.

    Returns:
        dict with each metric (float, or None when no session defines it), n_sessions, and
        notes: one line per metric that fewer than all sessions contributed to.
    """
    if len(per_session) == 0:
        raise ValueError("per_session: expected at least one session, got none")
    out: dict[str, Any] = {}
    notes: list[str] = []
    for key in METRIC_KEYS:
        missing = [name for name, m in per_session.items() if m.get(key) is None]
        values = [float(m[key]) for m in per_session.values() if m.get(key) is not None]
        out[key] = float(np.mean(values)) if values else None
        if missing:
            notes.append(
                f"{key}: mean over {len(values)} of {len(per_session)} sessions (undefined in {', '.join(missing)})"
            )
    out["n_sessions"] = len(per_session)
    out["notes"] = notes
    return out


def _cell(value: Any, missing: str) -> str:
    return missing if value is None else f"{float(value):.{DECIMALS}f}"


def _latex_escape(text: str) -> str:
    special = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
               "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}"}
    return "".join(special.get(c, c) for c in text)


def format_table(
    rows: Mapping[str, Mapping[str, Any]],
    style: str = "text",
    methods: Sequence[str] | None = None,
) -> str:
    """Table-1 style table: one row per entry of ``rows`` in order, columns Accuracy .. AUPRC.

    Args:
        rows: row name (a session, then typically ``MACRO_ROW``) -> metrics dict as returned by
            ``session_metrics`` / ``macro_mean``. With ``methods``, each row maps method name ->
            metrics dict instead, and the six columns repeat once per method, side by side.
        style: "text" (aligned plain text), "markdown" (pipe table) or "latex" (a booktabs
            ``tabular``: \\toprule, \\midrule, \\bottomrule; the ``MACRO_ROW`` row in \\textbf).
        methods: optional method names, e.g. ("HMM", "EfficientNet").

    Values print with 3 decimals; None prints as "—" (text, markdown) or "--" (LaTeX).
    """
    if style not in TABLE_STYLES:
        raise ValueError(f"style: expected one of {TABLE_STYLES}, got {style!r}")
    if len(rows) == 0:
        raise ValueError("rows: expected at least one row, got none")
    groups = list(methods) if methods is not None else [None]
    missing = MISSING_LATEX if style == "latex" else MISSING_TEXT

    body: list[tuple[str, list[str]]] = []
    for row_name, row in rows.items():
        cells = []
        for method in groups:
            metrics = row if method is None else row.get(method)
            if metrics is None:
                raise ValueError(f"rows[{row_name!r}]: expected metrics for method {method!r}, found none")
            cells.extend(_cell(metrics.get(key), missing) for key in METRIC_KEYS)
        body.append((str(row_name), cells))

    if style == "latex":
        n_cols = len(METRIC_KEYS) * len(groups)
        lines = [rf"\begin{{tabular}}{{l{'c' * n_cols}}}", r"\toprule"]
        if methods is not None:
            width = len(METRIC_KEYS)
            spans = [rf"\multicolumn{{{width}}}{{c}}{{{_latex_escape(m)}}}" for m in groups]
            lines.append(" & " + " & ".join(spans) + r" \\")
            rules = [rf"\cmidrule(lr){{{2 + g * width}-{1 + (g + 1) * width}}}" for g in range(len(groups))]
            lines.append(" ".join(rules))
        lines.append("Session & " + " & ".join(list(METRIC_TITLES) * len(groups)) + r" \\")
        lines.append(r"\midrule")
        for row_name, cells in body:
            if row_name == MACRO_ROW:
                row_cells = [rf"\textbf{{{row_name}}}"] + [rf"\textbf{{{c}}}" for c in cells]
            else:
                row_cells = [_latex_escape(row_name)] + cells
            lines.append(" & ".join(row_cells) + r" \\")
        lines += [r"\bottomrule", r"\end{tabular}"]
        return "\n".join(lines) + "\n"

    titles = [t if method is None else f"{t} ({method})" for method in groups for t in METRIC_TITLES]
    header = ["Session"] + titles
    if style == "markdown":
        lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] + ["---:"] * len(titles)) + "|"]
        for row_name, cells in body:
            label = f"**{row_name}**" if row_name == MACRO_ROW else row_name.replace("|", "\\|")
            lines.append("| " + " | ".join([label] + cells) + " |")
        return "\n".join(lines) + "\n"

    table = [header] + [[name] + cells for name, cells in body]
    widths = [max(len(r[c]) for r in table) for c in range(len(header))]
    lines = []
    for i, r in enumerate(table):
        lines.append("  ".join([r[0].ljust(widths[0])] + [v.rjust(w) for v, w in zip(r[1:], widths[1:])]).rstrip())
        if i == 0:
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines) + "\n"
