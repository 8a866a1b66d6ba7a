"""Score the crowd workers' labels against the ground truth (sessions from `contact-viz import yang2024 --labels`).

Reads each session's labels.csv (ground truth) and crowd_labels.csv (the crowd's labels for the
same frames) and prints Table-1 metrics of the crowd as a classifier: accuracy, precision, recall,
F1 (a crowd label is a 0/1 prediction), AUROC and AUPRC of those 0/1 scores, per session and their
macro mean.

    python recipes/score_crowd.py sessions/C_M1_T1_4 sessions/C_M1_T1_7 [--markdown]
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

from contact_viz.model.metrics import MACRO_ROW, format_table, macro_mean, session_metrics


def read_labels(path: Path) -> dict[str, int]:
    with path.open(newline="", encoding="utf-8") as handle:
        return {row["frame"]: int(row["contact"]) for row in csv.DictReader(handle)}


def crowd_metrics(session: Path) -> dict:
    """Metrics of crowd_labels.csv against labels.csv of ``session``, on the frames both have."""
    truth = read_labels(session / "labels.csv")
    crowd = read_labels(session / "crowd_labels.csv")
    frames = sorted(set(truth) & set(crowd))
    if not frames:
        raise ValueError(f"{session}: expected frames in both labels.csv and crowd_labels.csv, found none")
    labels = np.array([truth[f] for f in frames], dtype=np.int8)
    scores = np.array([crowd[f] for f in frames], dtype=np.float64)
    return session_metrics(labels, scores, 0.5, name=session.name)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sessions", type=Path, nargs="+")
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args()
    rows = {}
    for session in args.sessions:
        try:
            rows[session.name] = crowd_metrics(session)
        except (OSError, KeyError, ValueError) as exc:
            sys.exit(f"error: {session}: expected labels.csv and crowd_labels.csv (frame,contact) ({exc})")
    rows[MACRO_ROW] = macro_mean(rows)
    print(format_table(rows, style="markdown" if args.markdown else "text"))


if __name__ == "__main__":
    main()
