"""The half-occluded strip beside each instrument: left-image tissue that the right camera cannot see.

A tool above the tissue hides, in the right view, the tissue just left of it in the left view. Left
pixel x of disparity d is seen at right column x - d; a tool run of the same row, columns a..b with
disparities d', covers the right columns from m = min(x' - d') to M = max(x' - d'). A tissue pixel
x < a of disparity d_s is hidden when its right column falls there: m <= x - d_s <= M, i.e. the
columns ceil(m + d_s) .. min(a - 1, floor(M + d_s)). The strip is as wide as the tool's disparity minus
the tissue's: 12 px at the synthetic scenes' 90 mm, 60-70 px for a shaft 20 mm above tissue at 50 mm
seen by a da Vinci endoscope at 1080p.

No stereo method measures the strip, so the tissue's disparity there is unknown: SGBM leaves it empty
or fills it with the tool's disparity or a made-up one; a learned network fills it from its priors.
:func:`half_occluded` therefore reads d_s from the tissue *beyond* the strip, which both cameras see,
and never from the strip's own pixels (a strip carrying the tool's disparity would otherwise look
like tissue touching the tool). The strip's edge depends on d_s and d_s on where the edge is, so the
edge is found by a fixed-point iteration that starts from the widest strip the tool can cast (tissue
at infinity, d_s = 0, edge at m) and moves towards the tool: d_s = the median of the ``probe_count``
valid tissue disparities of the row nearest to the strip on its left, past the ``probe_gap_px``
columns next to it, less those more than ``nearer_fraction`` nearer than the run's nearest tool
pixel (a fold of tissue in front of the tool is not what lies behind the strip: read, it moved the
edge past the strip's own pixels, and the tool's disparity dragged there was read next); fewer where
there are fewer; none: the strip is everything from m to the tool that it could hide, for nothing
right of there is read; the edge = ceil(m + d_s). On tissue of one depth it settles after one step;
on tissue rising towards the tool (a tool in contact), the strip shrinks to the gap left between the
tool and the rising tissue.

Pure functions over arrays, vectorised over every run of every row (:func:`half_occluded`); the tests
compare it with a literal loop over rows and runs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from contact_viz.params import check_fields, checked

__all__ = ["OcclusionParams", "half_occluded", "tool_runs"]


@dataclass(frozen=True)
class OcclusionParams:
    """How :func:`half_occluded` reads the tissue's disparity beyond the strip."""

    # the tissue's disparity is read left of the strip, past this many columns next to it, px (at the strip's
    # edge matchers and networks blur the two surfaces)
    probe_gap_px: int = checked(2, ge=0)
    probe_count: int = checked(8, ge=1)  # valid tissue pixels of the row whose median gives its disparity, px
    iterations: int = checked(6, ge=1)  # steps of the edge's fixed-point iteration (one settles on flat tissue)
    # a probed pixel whose disparity exceeds the run's largest (its nearest tool pixel's) by more than this share
    # lies in front of the tool (a fold of tissue towards the camera; 5%: 1.5 mm at 30 mm): not the tissue behind
    # the strip, not read, fraction
    nearer_fraction: float = checked(0.05, ge=0)

    def __post_init__(self) -> None:
        check_fields(self)


def tool_runs(tool_mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every maximal horizontal run of tool pixels: (rows, first columns, last columns), each (R,) int64,
    in row-major order."""
    tool = np.asarray(tool_mask, dtype=bool)
    height, width = tool.shape
    padded = np.zeros((height, width + 2), np.int8)
    padded[:, 1:-1] = tool
    step = np.diff(padded, axis=1)  # +1 where a run starts (at column c), -1 one past where it ends
    rows, starts = np.nonzero(step == 1)
    _, stops = np.nonzero(step == -1)  # the same order: both row-major, one stop per start
    return rows.astype(np.int64), starts.astype(np.int64), stops.astype(np.int64) - 1


def half_occluded(
    disparity_px: np.ndarray, tool_mask: np.ndarray, params: OcclusionParams = OcclusionParams()
) -> np.ndarray:
    """Left-image pixels left of an instrument that the right camera cannot see: (H, W) bool.

    ``disparity_px`` (H, W) float, px of these images (right column = x - disparity), NaN = invalid:
    on the tool, its own disparity (a run without any finite value casts no strip); elsewhere any
    depth, SGBM's or a supplied one converted to disparity (fx * baseline / depth - the cameras' cx
    offset), the strip's own values never read. ``tool_mask`` (H, W) bool, every instrument.

    Per row, per run of tool pixels a..b: the footprint m, M (min and max of x' - d' over its finite
    pixels), the tissue's disparity d_s beyond the strip (the module docstring: fixed-point iteration
    from the widest strip), and the strip: non-tool columns ceil(m + d_s) .. min(a - 1, floor(M + d_s)),
    clipped to the image; without valid tissue left of the strip's widest edge, all that the tool could
    hide whatever the tissue's depth: columns max(m, 0) .. a - 1. The union over all runs is returned;
    tool pixels are never in it.
    """
    tool = np.asarray(tool_mask, dtype=bool)
    disparity = np.asarray(disparity_px)
    if disparity.shape != tool.shape or disparity.ndim != 2:
        raise ValueError(f"disparity_px {disparity.shape} and tool_mask {tool.shape} must be the same (H, W)")
    out = np.zeros(tool.shape, bool)
    any_rows = np.flatnonzero(tool.any(axis=1))
    if any_rows.size == 0:
        return out
    # Only the rows with a tool and the columns up to the last tool pixel can hold a strip or its tissue.
    r0, r1 = int(any_rows[0]), int(any_rows[-1]) + 1
    c1 = int(np.flatnonzero(tool[r0:r1].any(axis=0))[-1]) + 1
    out[r0:r1, :c1] = _strips(disparity[r0:r1, :c1].astype(np.float64), tool[r0:r1, :c1], params)
    return out


def _strips(disparity: np.ndarray, tool: np.ndarray, params: OcclusionParams) -> np.ndarray:
    """:func:`half_occluded` of a checked (H, W) float64 disparity and bool tool mask."""
    height, width = tool.shape
    out = np.zeros((height, width), bool)
    rows, firsts, _ = tool_runs(tool)

    # The runs' footprints in the right view: min and max of x' - d' over each run's tool pixels (flat,
    # row-major, so each run is one contiguous slice of them).
    flat_d = disparity.ravel()
    pixels = np.flatnonzero(tool.ravel())
    right_col = (pixels % width) - flat_d[pixels]
    finite = np.isfinite(right_col)
    starts = rows * width + firsts
    bounds = np.searchsorted(pixels, starts)
    low = np.minimum.reduceat(np.where(finite, right_col, np.inf), bounds)
    high = np.maximum.reduceat(np.where(finite, right_col, -np.inf), bounds)
    nearest = np.maximum.reduceat(np.where(finite, flat_d[pixels], -np.inf), bounds)  # the run's largest d'
    known = np.isfinite(low)
    rows, firsts, low, high, nearest = rows[known], firsts[known], low[known], high[known], nearest[known]
    if rows.size == 0:
        return out

    # Valid tissue pixels in flat order; those of a run's row start at tissue[lo].
    tissue = np.flatnonzero(np.isfinite(flat_d) & ~tool.ravel())
    values = flat_d[tissue]
    row_start = rows * width
    lo = np.searchsorted(tissue, row_start)
    count = params.probe_count
    offsets = np.arange(count)
    tissue_d = np.zeros(rows.size)
    found = np.zeros(rows.size, bool)  # tissue_d was read from tissue (else: none left of the strip, d_s = 0)
    for _ in range(params.iterations if tissue.size else 0):
        # d_s: the median of the count valid tissue pixels nearest left of the strip (past probe_gap_px)
        edge = np.ceil(low + tissue_d)  # the strip's first column
        probe = np.clip(edge - 1 - params.probe_gap_px, -1, firsts - 1).astype(np.int64)
        at = np.searchsorted(tissue, row_start + probe, side="right")  # tissue pixels at or left of the probe
        first = np.maximum(at - count, lo)  # the (at most) count nearest of them on this row
        index = first[:, None] + offsets[None, :]
        window = np.where(index < at[:, None], values[np.minimum(index, values.size - 1)], np.nan)
        window[window > nearest[:, None] * (1 + params.nearer_fraction)] = np.nan  # in front of the tool
        found = np.isfinite(window).any(axis=1)
        with np.errstate(all="ignore"):
            new = np.where(found, np.nanmedian(np.where(found[:, None], window, 0.0), axis=1), 0.0)
        if np.array_equal(new, tissue_d):
            break
        tissue_d = new

    begin = np.maximum(np.ceil(low + tissue_d), 0).astype(np.int64)
    # inclusive; tissue unknown: all that the tool could hide, whatever the tissue's depth (a thin tool too)
    end = np.where(found, np.minimum(np.floor(high + tissue_d), firsts - 1), firsts - 1).astype(np.int64)
    keep = end >= begin
    marks = np.zeros((height, width + 1), np.int32)
    np.add.at(marks, (rows[keep], begin[keep]), 1)
    np.add.at(marks, (rows[keep], end[keep] + 1), -1)
    out = np.cumsum(marks, axis=1)[:, :width] > 0
    out &= ~tool
    return out
