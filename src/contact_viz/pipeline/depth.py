"""`contact-viz depth`: precompute the SGBM depth of every frame of a session into the cache."""

from __future__ import annotations

import contextlib
import io
import os
import shutil
import time
import warnings
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from contact_viz.errors import SessionError
from contact_viz.io.atomic import reported_as, staging_path, sweep_stale
from contact_viz.io.depth_cache import CacheWarning

from contact_viz.geometry.stereo import DEPTH_METHODS, SGBMParams

# --------------------------------------------------------------------------------------------


@dataclass
class DepthRunSummary:
    """What `contact-viz depth` did."""

    session: str  # session name
    source: str  # the session's depth source: depth, disparity or sgbm
    frames: int  # frames handled
    computed: int  # frames whose disparity was computed now
    cached: int  # frames already in the cache
    failed: list[str]  # "<stem>: <reason>" of frames that could not be computed
    valid_fraction: float  # mean share of pixels with a valid depth over the frames handled
    seconds: float  # wall time, s
    cache_dir: Path | None  # where the disparities are cached
    output: Path | None  # where depth .npy files were written, if asked

    def lines(self) -> list[str]:
        """Human-readable report, one line each."""
        out = []
        if self.source != "sgbm":
            out.append(f"{self.session}: depth comes from {self.source}/ (no SGBM needed)")
        per_frame = 1000 * self.seconds / max(self.computed, 1)
        out.append(
            f"{self.session}: {self.frames} frames, {self.computed} computed ({per_frame:.0f} ms/frame), "
            f"{self.cached} from cache, {len(self.failed)} failed; valid depth on {100 * self.valid_fraction:.1f}% "
            "of pixels"
        )
        if self.cache_dir is not None and self.source == "sgbm":
            out.append(f"cache: {self.cache_dir}")
        if self.output is not None:
            out.append(f"depth written to {self.output} (float32 metres, <stem>.npy)")
        out.extend(f"failed: {reason}" for reason in self.failed)
        if self.source == "sgbm":
            out.append("note: a learned stereo network (FoundationStereo) gives far better depth; put its "
                       "depth_meter.npy as depth/<stem>.npy or its disparity as disparity/<stem>.npy")
        return out


def _write_npy(path: Path, array: np.ndarray) -> None:
    """``np.save`` through an ordinary write, so that a full disk is an OSError with its errno (NumPy's own
    file writing reports only "N requested and M written")."""
    buffer = io.BytesIO()
    np.save(buffer, array)
    with open(path, "wb") as handle:
        handle.write(buffer.getbuffer())


def precompute_depth(
    session,
    *,
    output: str | Path | None = None,
    workers: int = 2,
    progress: Callable[[int, int], None] | None = None,
    require_cache: bool = False,
) -> DepthRunSummary:
    """Compute (or load from the cache) the depth of every frame of an opened ``session``.

    SGBM frames run in ``workers`` threads (OpenCV releases the GIL while matching; each match
    also uses OpenCV's own threads). With ``output``, each frame's depth is also written as
    ``<output>/<stem>.npy`` (float32 m, NaN invalid, rectified left view); ``output`` must be new
    or empty and outside the session directory, and is filled through a temporary folder beside
    it that is renamed at the end. ``progress(done, total)`` is called after each frame. With
    ``require_cache`` (the cache is the only output), an entry that cannot be stored (a disk that fills up)
    stops the run with the cache's error instead of a warning.
    """
    from contact_viz.io.session import BadFrame

    out_dir = tmp_dir = None
    if output is not None:
        out_dir = Path(output).expanduser().resolve()
        if out_dir == session.root or session.root in out_dir.parents:
            raise ValueError(f"{out_dir}: refusing to write inside the session directory {session.root}; "
                             "choose another output folder")
        if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
            raise ValueError(f"{out_dir}: expected a new or empty folder for the depth files")
        with reported_as(out_dir):
            out_dir.parent.mkdir(parents=True, exist_ok=True)
            sweep_stale(out_dir)  # what a killed run left
            tmp_dir = staging_path(out_dir, "partial")
            tmp_dir.mkdir()

    total = len(session)
    failed: list[str] = []
    valid_sum = 0.0
    counts = {"computed": 0, "cached": 0}
    start = time.perf_counter()

    def one(index: int):
        return index, session.load_depth(index, with_origin=True)

    cache = session.sgbm_cache if require_cache else None
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="contact-viz-depth")
    try:
        with reported_as(out_dir, tmp_dir) if tmp_dir is not None else contextlib.nullcontext():
            done = 0
            for index, result in pool.map(one, range(total)):
                if cache is not None and cache.problem is not None:
                    raise cache.problem
                stem = session.stems[index]
                if isinstance(result, BadFrame):
                    failed.append(f"{stem}: {result.reason}")
                else:
                    depth_m, origin = result
                    counts[origin] = counts.get(origin, 0) + 1
                    valid_sum += float(np.isfinite(depth_m).mean())
                    if tmp_dir is not None:
                        _write_npy(tmp_dir / f"{stem}.npy", depth_m)
                done += 1
                if progress is not None:
                    progress(done, total)
            if tmp_dir is not None:
                if out_dir.exists():
                    out_dir.rmdir()
                os.replace(tmp_dir, out_dir)
                tmp_dir = None
    finally:
        # a stop (an error, a signal) waits for the frames being matched, not for those queued behind them
        pool.shutdown(wait=True, cancel_futures=True)
        if tmp_dir is not None:
            shutil.rmtree(tmp_dir, ignore_errors=True)
    handled = total - len(failed)
    return DepthRunSummary(
        session=session.name,
        source=session.depth_source,
        frames=total,
        computed=counts["computed"],
        cached=counts["cached"],
        failed=failed,
        valid_fraction=valid_sum / handled if handled else 0.0,
        seconds=time.perf_counter() - start,
        cache_dir=session.depth_cache_dir,
        output=out_dir,
    )


def search_line(params: SGBMParams, calibration) -> str:
    """One line on how SGBM matched: where, at which scale, the disparity search range and the nearest depth it
    reaches with ``calibration`` (contact_viz.io.calibration.Calibration)."""
    scale = params.downscale or 1
    low, high = params.min_disparity * scale, (params.min_disparity + params.num_disparities - 1) * scale
    shifted = high + calibration.disparity_offset_px
    nearest = f"{1000 * calibration.fx * calibration.baseline_m / shifted:.1f} mm" if shifted > 0 else "any depth"
    where = "whole frames" if not params.region else "around the instruments (whole frames where none is in view)"
    return f"SGBM: {where} at 1/{scale} scale, disparities {low}-{high} px: depth from {nearest}"


def run_depth_command(
    session_dir: str | Path,
    *,
    method: str = "sgbm",
    output: str | Path | None = None,
    cache_dir: str | Path | None = None,
    params: SGBMParams | None = None,
    workers: int = 2,
    progress: Callable[[int, int], None] | None = None,
) -> list[str]:
    """`contact-viz depth SESSION [--method sgbm] [-o OUT] [--cache-dir DIR]`: returns the lines to print.

    Opens the session (masks not required), fills the depth cache, optionally writes depth
    files to ``output``. Raises SessionError / ValueError with a message for the user.
    """
    from contact_viz.io.session import open_session

    if method not in DEPTH_METHODS:
        raise ValueError(f"--method must be one of {', '.join(DEPTH_METHODS)}, got {method!r}")
    with warnings.catch_warnings(record=True) as caught:  # a cache that cannot be written: see below
        warnings.simplefilter("always")
        session = open_session(session_dir, cache_dir=cache_dir, depth_method=method, sgbm_params=params,
                               require_masks=False)
    cache = session.sgbm_cache
    if cache is not None and cache.problem is not None and output is None:  # filling the cache is all this
        raise cache.problem  # command would do: an error
    for w in caught:  # otherwise (depth files written to -o) the warnings, as they came
        warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    with warnings.catch_warnings():  # without -o, a cache that fills up is the error raised below, not a warning
        if output is None:
            warnings.simplefilter("ignore", CacheWarning)
        summary = precompute_depth(session, output=output, workers=workers, progress=progress,
                                   require_cache=output is None)
    lines = [session.depth_note] + summary.lines()
    if cache is not None:
        lines.insert(1, search_line(cache.params, session.calibration))
    if summary.frames and len(summary.failed) == summary.frames:
        raise SessionError(session.root, "no frame's depth could be computed:\n" + "\n".join(summary.failed[:5]))
    return lines
