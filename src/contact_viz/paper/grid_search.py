"""The grid search of N1, N2, tau_tool and tau_patch on training sessions only (paper, Sec. 2.1).

Every grid point is scored by the leave-one-session-out protocol of the HMM: the pooled
out-of-fold F1 at the threshold that protocol selects, with the pooled out-of-fold AUPRC as the
tie-breaker. Each frame is decoded once for the whole grid and its patch layers built once; the
tool-depth term is computed once per (N1, tau_tool) and the N2 sums once per N2, so the cost
grows with the number of window sizes, not with the number of grid points. Distances per grid
point are cached outside the sessions, so a rerun with a wider grid only pays for what is new.

`recipes/grid_search.py` runs it on the command line; `recipes/reproduce_paper.py --grid-search`
runs it as a step of the study (:func:`run_grid_search`).
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import product
from pathlib import Path

import numpy as np
from rich.progress import Progress
from sklearn.metrics import average_precision_score, f1_score

from contact_viz import __version__
from contact_viz.geometry.patch import distance_signal, patch_distance_grid
from contact_viz.io.atomic import atomic_write
from contact_viz.io.cache import cache_path
from contact_viz.io.jsonfile import write_json
from contact_viz.io.session import BadFrame, open_session
from contact_viz.model.hmm import LosoEnsemble
from contact_viz.params import PatchParams, to_dict
from contact_viz.pipeline.extract import BadFrameWarning

log = logging.getLogger(__name__)
SCORE = "pooled out-of-fold F1 of the LOSO HMM ensemble, AUPRC as tie-breaker"  # how grid points are ranked


# The default grid: N1 and N2 window sides (px), tau_tool (pixels) and tau_patch (distances).
DEFAULT_GRID = ((29, 31, 37), (11, 17, 23), (15, 30, 60), (4, 8, 16))


def build_grid(n1s, n2s, tau_tools, tau_patches, base: PatchParams) -> tuple[list[PatchParams], list[str]]:
    """Every valid combination, and a note for each one PatchParams refuses."""
    grid, skipped = [], []
    for n1, n2, tau_tool, tau_patch in product(n1s, n2s, tau_tools, tau_patches):
        try:
            grid.append(PatchParams(**{**to_dict(base), "n1": n1, "n2": n2, "tau_tool": tau_tool,
                                       "tau_patch": tau_patch}))
        except ValueError as exc:
            skipped.append(str(exc))
    return grid, skipped


def session_distances(session_dir: Path, grid: list[PatchParams], cache_dir, progress: Progress):
    """(T, G) distances in m for every frame and grid point, and the session's labels (T,)."""
    session = open_session(session_dir)
    key = {"grid": [to_dict(p) for p in grid]}
    path = cache_path(session.root, "grid", key, ".npy", cache_dir)
    if path.exists():
        return session.name, np.load(path), np.asarray(session.labels)
    task = progress.add_task(f"grid {session.name}", total=len(session))
    out = np.full((len(session), len(grid)), np.nan)
    for item in session.iter_frames(layers=("mask", "depth")):
        if isinstance(item, BadFrame):
            warnings.warn(f"frame {item.stem} skipped: {item.reason}", BadFrameWarning, stacklevel=1)
        else:
            out[item.index] = patch_distance_grid(item.depth_m, item.tool_mask, grid)
        progress.advance(task)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "wb") as handle:
        np.save(handle, out)
    return session.name, out, np.asarray(session.labels)


def loso_scores(signals: list[np.ndarray], labels: list[np.ndarray], names: list[str]) -> tuple[float, float]:
    """Pooled out-of-fold F1 (at the protocol's threshold) and AUPRC of the LOSO HMM ensemble."""
    ensemble = LosoEnsemble().fit(signals, labels, session_names=names)
    pooled_p = np.concatenate(ensemble.oof_posteriors_)
    pooled_y = np.concatenate(labels)
    keep = pooled_y >= 0
    y, p = pooled_y[keep], pooled_p[keep]
    return float(f1_score(y, p >= ensemble.threshold_)), float(average_precision_score(y, p))


@dataclass(frozen=True)
class GridPoint:
    """One scored grid point."""

    params: PatchParams
    oof_f1: float  # pooled out-of-fold F1 at the protocol's threshold
    oof_auprc: float  # pooled out-of-fold average precision
    found: float  # mean share of frames with a patch


def score_grid(sessions: list[Path], grid: list[PatchParams], cache_dir, on_skip=print) -> list[GridPoint]:
    """Every grid point scored on the training ``sessions``, best first (F1, then AUPRC)."""
    with Progress(transient=True) as progress:
        per_session = [session_distances(s, grid, cache_dir, progress) for s in sessions]
    names = [name for name, _, _ in per_session]
    labels = [y.astype(np.int8) for _, _, y in per_session]
    results = []
    for g, params in enumerate(grid):
        signals = [distance_signal(d[:, g], params.eps_m) for _, d, _ in per_session]
        try:
            f1, auprc = loso_scores(signals, labels, names)
        except ValueError as exc:
            on_skip(f"n1={params.n1} n2={params.n2} tau_tool={params.tau_tool} tau_patch={params.tau_patch} "
                    f"not scored: {exc}")
            continue
        results.append(GridPoint(params, f1, auprc, float(np.mean([np.isfinite(x).mean() for x in signals]))))
    if not results:
        raise ValueError("grid search: no grid point could be scored on the training sessions")
    results.sort(key=lambda r: (-r.oof_f1, -r.oof_auprc))
    return results


def run_grid_search(train_dirs: Sequence[Path], grid_values, cache_dir: Path | None,
                    out: Path) -> tuple[PatchParams, dict]:
    """The grid search as a step of the study: scores ``grid_values`` (n1s, n2s, tau_tools,
    tau_patches) on the training sessions, writes ``out/grid_search.json`` (every grid point's
    out-of-fold scores) and returns the best params and that file's content."""
    grid, skipped = build_grid(*grid_values, base=PatchParams())
    for note in skipped:
        log.info(f"  grid point skipped: {note}")
    points = score_grid(list(train_dirs), grid, cache_dir, on_skip=lambda note: log.info(f"  grid point {note}"))
    scored = [{"patch_params": to_dict(r.params), "oof_f1": r.oof_f1, "oof_auprc": r.oof_auprc} for r in points]
    result = {"score": SCORE,
              "grid": dict(zip(("n1", "n2", "tau_tool", "tau_patch"), (list(v) for v in grid_values))),
              "best": scored[0], "points": scored}
    write_json(out / "grid_search.json", result)
    return points[0].params, result


def write_best_params(path: Path, results: list[GridPoint], sessions: Sequence[Path], grid_values,
                      grid_points: int) -> None:
    """The best grid point as a ``--params`` file (``patch_params``) with how it was chosen (``grid_search``)."""
    best = results[0]
    n1s, n2s, tau_tools, tau_patches = (list(v) for v in grid_values)
    write_json(path, {"patch_params": to_dict(best.params), "grid_search": {
        "contact_viz_version": __version__, "sessions": [str(Path(s).resolve()) for s in sessions],
        "score": SCORE, "best_oof_f1": best.oof_f1, "best_oof_auprc": best.oof_auprc, "grid_points": grid_points,
        "n1": n1s, "n2": n2s, "tau_tool": tau_tools, "tau_patch": tau_patches}})
