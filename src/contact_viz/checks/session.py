"""Per-session checks: force-to-signal lag (cross-correlation) and frame-time problems. Pure, no I/O."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from contact_viz.checks.params import DiagnosticParams

__all__ = ["ForceLag", "force_lag", "frame_time_problems"]


@dataclass(frozen=True)
class ForceLag:
    """The lag at which the force magnitude best matches the distance signal."""

    lag_frames: int  # force(t + lag) matches signal(t): > 0 = the force comes late, frames
    lag_s: float  # the same in seconds (lag x median frame interval), s
    correlation: float  # Pearson correlation at that lag, -1..1 (NaN = not measurable)
    zero_lag_correlation: float  # Pearson correlation at lag 0, -1..1
    fired: bool  # |lag| >= min_lag_frames and correlation >= min_lag_correlation


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 8:
        return math.nan
    a, b = a[ok] - a[ok].mean(), b[ok] - b[ok].mean()
    denom = math.sqrt(float((a * a).sum()) * float((b * b).sum()))
    return float((a * b).sum()) / denom if denom > 0 else math.nan


def force_lag(force_n: np.ndarray, signal: np.ndarray, timestamps_s: np.ndarray,
              params: DiagnosticParams = DiagnosticParams(), suspect=None) -> ForceLag | None:
    """Cross-correlation of force contact (on/off) with signal contact (on/off) over lags within +- max_lag_s.

    ``signal`` is ``-log10(max(|d|, eps))`` per frame (NaN = no patch): it rises as the tool nears the
    tissue, like the force in contact. Measured around complete contacts only (None without one).
    ``suspect``: frames (bool per frame) where a frame check fired;
    their signal is left out (a mask or depth failure would look like a lag). None when the session has
    no force, too few frames, or a force that never leaves its noise (``min_force_swing_n``).
    """
    force = np.asarray(force_n, dtype=np.float64)
    signal = np.array(signal, dtype=np.float64)
    if suspect is not None:
        signal[np.asarray(suspect, dtype=bool)] = np.nan
    times = np.asarray(timestamps_s, dtype=np.float64)
    n = force.size
    if n < 16 or not np.isfinite(force).any() or np.nanstd(force) == 0:
        return None
    dt = float(np.median(np.diff(times))) if n > 1 else math.nan
    if not (math.isfinite(dt) and dt > 0):
        return None
    max_lag = max(1, min(int(round(params.max_lag_s / dt)), n // 4))
    # Both as on/off: the force above a low level of its range (contact), the signal above a high level
    # of its range (tool at the tissue). Raw values lag each other by the physics (the signal rises while
    # approaching, the force only with indentation); the on/off edges of the two coincide within a frame.
    f_lo, f_hi = np.nanpercentile(force, 20), np.nanpercentile(force, 95)
    finite = np.isfinite(signal)
    if finite.sum() < 8 or not f_hi > f_lo or f_hi - f_lo < params.min_force_swing_n:
        return None  # (a force within its noise has no contact whose timing could be compared)
    s_lo, s_hi = np.nanpercentile(signal, 5), np.nanpercentile(signal, 95)
    force = np.where(np.isfinite(force), (force > f_lo + params.force_level * (f_hi - f_lo)).astype(float), np.nan)
    signal = np.where(finite, (signal > s_lo + params.signal_level * (s_hi - s_lo)).astype(float), np.nan)
    # Only complete contacts (force on, then off again, inside the session) tell a lag: where a contact is
    # cut by the session's start or end, a later level crossing of the ramping signal looks the same as a
    # lag. Both series are kept only around the complete contacts (+- the lags searched).
    on = np.nan_to_num(force, nan=0.0) > 0.5
    edges = np.flatnonzero(np.diff(on.astype(np.int8)))
    starts = [int(e) + 1 for e in edges if not on[e]]
    ends = [int(e) + 1 for e in edges if on[e]]
    keep = np.zeros(n, bool)
    complete = 0
    for a in starts:
        later = [b for b in ends if b > a]
        if later:
            keep[max(a - max_lag, 0):min(later[0] + max_lag, n)] = True
            complete += 1
    if not complete:
        return None
    force[~keep] = np.nan
    signal[~keep] = np.nan
    correlations = {}
    for lag in range(-max_lag, max_lag + 1):
        if lag >= 0:
            c = _corr(force[lag:], signal[:n - lag])
        else:
            c = _corr(force[:n + lag], signal[-lag:])
        correlations[lag] = c
    finite = {lag: c for lag, c in correlations.items() if math.isfinite(c)}
    if not finite:
        return None
    best = max(finite.values())
    # on/off runs of different lengths correlate equally over a plateau of lags: take its middle
    plateau = [lag for lag, c in finite.items() if c >= best - 1e-6]
    best_lag = int(round(float(np.median(plateau))))
    fired = abs(best_lag) >= params.min_lag_frames and best >= params.min_lag_correlation
    return ForceLag(best_lag, best_lag * dt, best, correlations.get(0, math.nan), fired)


def frame_time_problems(timestamps_s: np.ndarray, params: DiagnosticParams = DiagnosticParams()) -> list[int]:
    """Indices of frames whose time is not after the previous one's, or follows a gap longer than
    ``frame_gap_factor`` x the median frame interval."""
    times = np.asarray(timestamps_s, dtype=np.float64)
    if times.size < 3:
        return []
    step = np.diff(times)
    median = float(np.median(step))
    bad = (step <= 0) | ((median > 0) & (step > params.frame_gap_factor * median))
    return [int(i) + 1 for i in np.nonzero(bad)[0]]
