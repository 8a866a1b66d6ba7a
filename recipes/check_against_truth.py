"""Compare extracted distances with a synthetic session's true tool-tissue gap.

Prints, per gap range, the median measured distance and how often a patch was found, and the
rank correlation between distance and gap. Works on sessions made by `contact-viz synth`
(they carry truth.csv).

    python recipes/check_against_truth.py demo/sessions/cup_test demo/results/cup_test/features.csv
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("session", type=Path)
    parser.add_argument("features", type=Path)
    args = parser.parse_args()
    truth = {int(t["frame"]): t for t in read_csv(args.session / "truth.csv")}
    rows = read_csv(args.features)
    gap_mm = np.array([1000 * float(truth[int(r["frame"])]["gap_m"]) for r in rows])
    dist_mm = np.array([1000 * float(r["distance_m"]) if r["distance_m"] else np.nan for r in rows])
    print(f"{args.session.name}: {len(rows)} frames, patch found on {np.isfinite(dist_mm).sum()}")
    print(f"{'true gap (mm)':>16} {'frames':>7} {'median distance (mm)':>21} {'found':>6}")
    edges = [(0, 0), (0, 2), (2, 5), (5, 10), (10, 20), (20, np.inf)]
    for lo, hi in edges:
        sel = (gap_mm == 0) if hi == 0 else (gap_mm > lo) & (gap_mm <= hi)
        if not sel.any():
            continue
        label = "0 (contact)" if hi == 0 else f"{lo}-{hi:g}"
        found = np.isfinite(dist_mm[sel])
        median = np.median(dist_mm[sel][found]) if found.any() else float("nan")
        print(f"{label:>16} {sel.sum():>7} {median:>21.2f} {found.mean():>6.0%}")
    ok = np.isfinite(dist_mm)
    rank = lambda v: np.argsort(np.argsort(v))
    print(f"Spearman rank correlation distance vs gap: {np.corrcoef(rank(dist_mm[ok]), rank(gap_mm[ok]))[0, 1]:.3f}")


if __name__ == "__main__":
    main()
