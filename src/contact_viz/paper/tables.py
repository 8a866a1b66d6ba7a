"""Table 1 of a study as files: markdown, LaTeX and CSV, each written atomically.

The metrics themselves are computed in :mod:`contact_viz.model.metrics` (pure); this module only
writes them out.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

from contact_viz.io.atomic import atomic_write
from contact_viz.model.metrics import METRIC_KEYS, format_table


def _num(value) -> str:
    return "" if value is None else repr(float(value))


def write_table1(out: Path, table: dict, methods: Sequence[str], thresholds: dict[str, float],
                 categories: dict[str, str], paths: dict[str, str], notes: Sequence[str]) -> None:
    """table1.md, table1.tex and table1.csv (methods side by side; the CSV has a row per session and method)."""
    columns = ["session", "category", "method", "threshold", *METRIC_KEYS, "n_frames", "n_contact", "path", "notes"]
    with atomic_write(out / "table1.csv", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns)
        writer.writeheader()
        for row_name, per_method in table.items():
            for method in methods:
                m = per_method[method]
                writer.writerow({
                    "session": row_name, "category": categories.get(row_name, ""), "method": method,
                    "threshold": repr(thresholds[method]), **{k: _num(m.get(k)) for k in METRIC_KEYS},
                    "n_frames": m.get("n_frames", ""), "n_contact": m.get("n_contact", ""),
                    "path": paths.get(row_name, ""), "notes": "; ".join(m.get("notes", [])),
                })
    order = ", ".join(f"{name}: {categories[name]}" for name in table if name in categories)
    threshold_text = ", ".join(f"{m} {thresholds[m]:.4f}" for m in methods)
    md = ["# Table 1: held-out performance", "",
          f"Sessions in order of domain shift ({order}). Decision thresholds: {threshold_text}.", ""]
    md += [f"> {n}" for n in notes] + ([""] if notes else [])
    md.append(format_table(table, style="markdown", methods=methods).rstrip())
    metric_notes = [n for per_method in table.values() for m in per_method.values() for n in m.get("notes", [])]
    if metric_notes:
        md += ["", *(f"- {n}" for n in metric_notes)]
    with atomic_write(out / "table1.md") as handle:
        handle.write("\n".join(md).rstrip() + "\n")
    caption = f"Held-out performance of the {' and the '.join(methods)} models."
    tex = ["% Table 1 of the paper; needs \\usepackage{booktabs,graphicx}",
           *(f"% NOTE: {n}" for n in notes),
           "\\begin{table}[ht]", f"  \\caption{{{caption}}}", "  \\label{tab:results}", "  \\centering",
           "  \\scriptsize", "  \\resizebox{\\linewidth}{!}{%",
           format_table(table, style="latex", methods=methods).rstrip() + "%", "  }", "\\end{table}"]
    with atomic_write(out / "table1.tex") as handle:
        handle.write("\n".join(tex) + "\n")


def write_per_frame(path: Path, columns: Sequence[str], rows: list[dict]) -> None:
    """One row per frame as CSV with ``columns`` (atomically)."""
    with atomic_write(path, newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(columns))
        writer.writeheader()
        writer.writerows(rows)
