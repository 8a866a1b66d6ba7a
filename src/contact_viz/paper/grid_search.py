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

import io
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


GRID_CHUNK_FRAMES = 64  # frames per grid task when an engine spreads the work, frames


def grid_chunk_task(session_dir: str, grid: list[PatchParams], lo: int, hi: int) -> tuple[np.ndarray, list[str]]:
    """(hi - lo, G) distances in m of frames ``lo .. hi-1`` for every grid point, and the
    unreadable frames' messages (a task an engine runs in any process or node)."""
    session = open_session(session_dir)
    out = np.full((hi - lo, len(grid)), np.nan)
    bad = []
    for item in session.iter_frames(layers=("mask", "depth"), indices=range(lo, hi)):
        if isinstance(item, BadFrame):
            bad.append(f"frame {item.stem} skipped: {item.reason}")
        else:
            out[item.index - lo] = patch_distance_grid(item.depth_m, item.tool_mask, grid)
    return out, bad


def _load_cached(path: Path, shape: tuple[int, int]) -> np.ndarray | None:
    """A cached (T, G) distance array, or None if absent, unreadable or not whole (a torn write)."""
    try:
        array = np.load(path)
    except (OSError, ValueError, EOFError):
        return None
    return array if array.shape == shape and array.dtype == np.float64 else None


def session_distances(sessions: Sequence[Path], grid: list[PatchParams], cache_dir, engine, progress: Progress):
    """Per session: (name, (T, G) distances in m for every frame and grid point, labels (T,)).

    Sessions already in the cache are read from it; the others are computed in chunks of
    ``GRID_CHUNK_FRAMES`` frames on ``engine`` and cached."""
    opened = [open_session(s) for s in sessions]
    key = {"grid": [to_dict(p) for p in grid]}
    paths = [cache_path(session.root, "grid", key, ".npy", cache_dir) for session in opened]
    distances = {}
    for i, path in enumerate(paths):
        cached = _load_cached(path, (len(opened[i]), len(grid)))
        if cached is not None:
            distances[i] = cached
    calls, owners = [], []
    for i, session in enumerate(opened):
        if i not in distances:
            distances[i] = np.full((len(session), len(grid)), np.nan)
            for lo in range(0, len(session), GRID_CHUNK_FRAMES):
                calls.append((grid_chunk_task, (str(session.root), grid, lo, min(lo + GRID_CHUNK_FRAMES, len(session)))))
                owners.append((i, lo))
    task = progress.add_task("grid distances", total=sum(c[1][3] - c[1][2] for c in calls))
    for position, result in engine.run(calls):
        if isinstance(result, BaseException):
            raise result
        i, lo = owners[position]
        block, bad = result
        distances[i][lo:lo + block.shape[0]] = block
        for message in bad:
            warnings.warn(message, BadFrameWarning, stacklevel=1)
        progress.advance(task, block.shape[0])
    for i in {i for i, _ in owners}:
        buffer = io.BytesIO()  # np.save into a real file reports a full disk without its errno
        np.save(buffer, distances[i])
        try:
            with atomic_write(paths[i], "wb") as handle:
                handle.write(buffer.getbuffer())
        except OSError as exc:  # a full disk, a read-only cache: the distances are still right
            from contact_viz.io.atomic import os_reason

            warnings.warn(f"{paths[i].parent}: could not write the grid cache ({os_reason(exc)}); the distances "
                          "are computed again on every run", stacklevel=2)
    return [(session.name, distances[i], np.asarray(session.labels)) for i, session in enumerate(opened)]


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


def _score_point(signals: list[np.ndarray], labels: list[np.ndarray], names: list[str]) -> tuple[float, float]:
    return loso_scores(signals, labels, names)


def score_grid(sessions: list[Path], grid: list[PatchParams], cache_dir, on_skip=print, engine=None) -> list[GridPoint]:
    """Every grid point scored on the training ``sessions``, best first (F1, then AUPRC).

    ``engine`` (a :mod:`contact_viz.pipeline.engines` engine; default: this process) runs the
    frame chunks of the distances and the grid points' LOSO fits; the scores do not depend on it."""
    from contact_viz.pipeline.engines import LocalEngine

    engine = engine if engine is not None else LocalEngine(1)
    with Progress(transient=True) as progress:
        per_session = session_distances(sessions, grid, cache_dir, engine, progress)
    names = [name for name, _, _ in per_session]
    labels = [y.astype(np.int8) for _, _, y in per_session]
    signals = [[distance_signal(d[:, g], params.eps_m) for _, d, _ in per_session] for g, params in enumerate(grid)]
    scores: dict[int, object] = dict(engine.run([(_score_point, (signals[g], labels, names)) for g in range(len(grid))]))
    results = []
    for g, params in enumerate(grid):
        if isinstance(scores[g], ValueError):
            on_skip(f"n1={params.n1} n2={params.n2} tau_tool={params.tau_tool} tau_patch={params.tau_patch} "
                    f"not scored: {scores[g]}")
            continue
        if isinstance(scores[g], BaseException):
            raise scores[g]
        f1, auprc = scores[g]
        results.append(GridPoint(params, f1, auprc, float(np.mean([np.isfinite(x).mean() for x in signals[g]]))))
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
