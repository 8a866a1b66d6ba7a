"""SGBM depth only where the patch reads it: a coarse full-frame pass, then fine tiles around the tools.

The minimum-distance patch reads depth on the tools and at most ``PatchParams`` reach (ring + band +
the bleeding test's tissue beyond: 15 px by default) outside them; at 1920x1080 that is 5-20% of the
frame. :func:`region_sgbm_disparity` therefore

1. shrinks both views once to the matching resolution (``SGBMParams.downscale``, from
   ``match_width_px``, 960: 1920 px wide -> 960, 1280 -> 640; full-resolution matching of the
   weakly textured tissue loses most matches beside the tool, docs/depth.md);
2. runs a **coarse** pass over the whole frame at ``coarse_width_px`` (plain SGBM with the
   left-right check and the median): it feeds the 3D cloud and the depth pane, and gives each fine
   tile its disparity search range (the whole range: SGBMParams.resolve, from the calibration);
3. matches the **region** (the tools and the background within ``region_px`` of them) with the
   mask-aware matcher (:func:`masked_sgbm_disparity`, which also leaves the half-occluded strip
   without depth) in horizontal tiles of ``tile_rows_px`` rows, each searching only the coarse
   disparities found in it +- ``range_margin_px``, within the whole range: from the farthest found
   in it or up to ``range_context_px`` beside it along the rows (by default as far as the widest
   strip reaches: the coarse pass may have no tissue inside the region, beside a wide half-occluded
   strip or between two instruments, its own tool fattened over the rest), to the nearest found in
   it, or to the whole range's nearest where the coarse pass matched too few of the tile's tool
   pixels (``range_tool_seen_min``: a tool too thin for it);
4. upsamples to the image: inside the region the fine disparity (no value crosses the tool's
   edge: a pixel whose tool/background class differs between the image and the matching
   resolution is NaN), outside it the coarse one; no depth on the half-occluded strips left of the
   tools (geometry.occlusion), found again on the whole rows.

:class:`RegionDisparity` says which pixels are fine; the patch never reads a coarse one, since
the region holds everything it reads (tested).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from contact_viz.geometry.occlusion import half_occluded
from contact_viz.geometry.stereo import (
    SUBPIXEL,
    SGBMParams,
    _as_pair,
    _sgbm,
    masked_sgbm_disparity,
    median_by_region,
)

__all__ = ["RegionDisparity", "coarse_disparity", "fine_region", "region_sgbm_disparity"]

_CONTEXT_ROWS = 8  # rows matched above and below each tile and then dropped, px at the matching resolution


@dataclass(frozen=True)
class RegionDisparity:
    """A frame's disparity: fine around the tools, coarse elsewhere."""

    disparity_px: np.ndarray  # (H, W) float32 px, NaN = no match
    fine: np.ndarray  # (H, W) bool: True where disparity_px comes from the fine tiles (the region)


def fine_region(tool_mask: np.ndarray, region_px: int) -> np.ndarray:
    """The tools and the background within ``region_px`` (Euclidean) of them: (H, W) bool."""
    tool = np.asarray(tool_mask) != 0
    if region_px <= 0 or not tool.any():
        return tool.copy()
    rows, cols = np.flatnonzero(tool.any(axis=1)), np.flatnonzero(tool.any(axis=0))
    y0, y1 = max(rows[0] - region_px, 0), min(rows[-1] + region_px + 1, tool.shape[0])
    x0, x1 = max(cols[0] - region_px, 0), min(cols[-1] + region_px + 1, tool.shape[1])
    crop = tool[y0:y1, x0:x1]
    distance = cv2.distanceTransform((~crop).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    out = np.zeros_like(tool)
    out[y0:y1, x0:x1] = distance <= region_px
    return out


def _shrink(image: np.ndarray, n: int) -> np.ndarray:
    if n == 1:
        return image
    return cv2.resize(image, (max(1, image.shape[1] // n), max(1, image.shape[0] // n)), interpolation=cv2.INTER_AREA)


def _grow(disparity: np.ndarray, shape: tuple[int, int], n: int) -> np.ndarray:
    """A disparity in the pixels of an image shrunk by ``n``, nearest-upsampled to ``shape`` (any size)
    and scaled by ``n`` to the pixels of the image of that shape."""
    if disparity.shape == tuple(shape):
        return disparity * np.float32(n) if n != 1 else disparity
    return cv2.resize(disparity, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST) * np.float32(n)


def coarse_disparity(left: np.ndarray, right: np.ndarray, params: SGBMParams) -> tuple[np.ndarray, int]:
    """Plain SGBM (left-right check, median) of a pair shrunk to at most ``params.coarse_width_px`` wide.

    ``left``, ``right``: a checked pair at any resolution; ``params`` for matching it (its search
    range is scaled to the shrunk pair, its block size is the width rule's there). Returns (disparity (h, w) float32 in the
    pixels of the given pair, NaN = no match, at its own resolution; the factor n it was shrunk by).
    """
    width = left.shape[1]
    n = max(1, -(-width // params.coarse_width_px))
    p = params.resolve(width)
    num = max(SUBPIXEL, -(-p.num_disparities // n // SUBPIXEL) * SUBPIXEL) if n > 1 else p.num_disparities
    p = replace(p, num_disparities=num, min_disparity=p.min_disparity // n, block_size=None,
                downscale=1).resolve(width // n)
    small_l, small_r = _shrink(left, n), _shrink(right, n)
    disparity = _sgbm(small_l, small_r, p)
    disparity = median_by_region(disparity, [np.ones(disparity.shape, bool)], p.median_px)
    return disparity * np.float32(n), n


def _tiles(region: np.ndarray, rows_per_tile: int) -> list[tuple[int, int, int, int]]:
    """(y0, y1, x0, x1) of the region's horizontal tiles: each ``rows_per_tile`` rows, its columns
    the span of the region's pixels in them."""
    out = []
    rows = np.flatnonzero(region.any(axis=1))
    if rows.size == 0:
        return out
    for y0 in range(int(rows[0]), int(rows[-1]) + 1, rows_per_tile):
        y1 = min(y0 + rows_per_tile, region.shape[0])
        cols = np.flatnonzero(region[y0:y1].any(axis=0))
        if cols.size:
            out.append((y0, y1, int(cols[0]), int(cols[-1]) + 1))
    return out


def _search_range(coarse_px: np.ndarray, p: SGBMParams, nearest: bool = False,
                  beside_px: np.ndarray | None = None) -> tuple[int, int]:
    """(min_disparity, num_disparities) covering the finite ``coarse_px`` (matching px) +- the margin,
    from the smallest of them and of ``beside_px`` (the coarse disparities beside the region), with
    ``nearest`` up to the full range's largest disparity; the full range of ``p`` when none is finite."""
    values = coarse_px[np.isfinite(coarse_px)]
    if values.size == 0:
        return p.min_disparity, p.num_disparities
    farthest = values.min()
    if beside_px is not None and np.isfinite(beside_px).any():
        farthest = min(farthest, np.nanmin(beside_px))
    top = p.min_disparity + p.num_disparities - 1
    lo = max(int(np.floor(farthest)) - p.range_margin_px, p.min_disparity)
    hi = top if nearest else min(int(np.ceil(values.max())) + p.range_margin_px, top)
    hi = max(hi, lo)
    return lo, -(-(hi - lo + 1) // SUBPIXEL) * SUBPIXEL


def region_sgbm_disparity(
    left_rgb: np.ndarray,
    right_rgb: np.ndarray,
    tool_mask: np.ndarray,
    params: SGBMParams = SGBMParams(),
) -> RegionDisparity:
    """Disparity of a rectified pair whose left tool mask is known: fine around the tools, coarse elsewhere.

    ``left_rgb``, ``right_rgb`` (H, W, 3) or (H, W) uint8; ``tool_mask`` (H, W) bool or integer
    (nonzero = tool; every instrument of a scene). The steps are in the module docstring. With an
    empty mask, or ``params.region`` off, the whole frame is matched finely (plain SGBM or the
    mask-aware matcher at the matching resolution).
    """
    left, right = _as_pair(left_rgb, right_rgb)
    tool = np.asarray(tool_mask) != 0
    if tool.shape != left.shape[:2]:
        raise ValueError(f"tool_mask shape {tool.shape} differs from the images' {left.shape[:2]}")
    shape = tool.shape
    p = params.resolve(shape[1])
    n = p.downscale
    small_l, small_r = _shrink(left, n), _shrink(right, n)
    small_tool = _shrink(tool.astype(np.float32), n) >= 0.5
    p1 = replace(p, downscale=1)
    if not p.region or not tool.any():
        small = masked_sgbm_disparity(small_l, small_r, small_tool, p1)
        return RegionDisparity(_split_at_edge(_grow(small, shape, n), tool, small_tool, n), np.ones(shape, bool))
    coarse, _ = coarse_disparity(small_l, small_r, p1)
    coarse_small = _grow(coarse, small_tool.shape, 1)  # matching resolution, matching px
    region = fine_region(tool, p.region_px)
    small_region = _shrink(region.astype(np.float32), n) > 0
    fine_small = np.full(small_tool.shape, np.nan, np.float32)
    height, width = small_tool.shape
    reach = p1.min_disparity + p1.num_disparities if p.range_context_px is None else p.range_context_px
    beside = cv2.dilate(small_region.astype(np.uint8), np.ones((1, 2 * reach + 1), np.uint8)).astype(bool)
    for y0, y1, x0, x1 in _tiles(small_region, p.tile_rows_px):
        tool_seen = np.isfinite(coarse_small[y0:y1][small_tool[y0:y1]])
        nearest = tool_seen.size > 0 and tool_seen.mean() < p.range_tool_seen_min
        lo, num = _search_range(coarse_small[y0:y1, x0:x1][small_region[y0:y1, x0:x1]], p1, nearest,
                                coarse_small[y0:y1][beside[y0:y1]])
        cy0, cy1 = max(y0 - _CONTEXT_ROWS, 0), min(y1 + _CONTEXT_ROWS, height)
        # columns: the right view's match of the tile's first column lies up to lo + num left of it, and the
        # left-right check matches the right view's last matched column up to num right of the tile
        cx0, cx1 = max(x0 - lo - num - p.block_size, 0), min(x1 + num + p.block_size, width)
        tile = replace(p1, min_disparity=lo, num_disparities=num)
        got = masked_sgbm_disparity(small_l[cy0:cy1, cx0:cx1], small_r[cy0:cy1, cx0:cx1],
                                    small_tool[cy0:cy1, cx0:cx1], tile)
        fine_small[y0:y1, x0:x1] = got[y0 - cy0:y1 - cy0, x0 - cx0:x1 - cx0]
    fine = _split_at_edge(_grow(fine_small, shape, n), tool, small_tool, n)
    out = _grow(coarse, shape, n)
    out[region] = fine[region]
    if p.half_occluded_strip:  # again on whole rows at the image's pixels: a tile's crop may hold no tissue
        out[half_occluded(out, tool)] = np.nan  # beyond a wide strip; this also clears the coarse pass's strip
    return RegionDisparity(out, region)


def _split_at_edge(disparity: np.ndarray, tool: np.ndarray, small_tool: np.ndarray, n: int) -> np.ndarray:
    """``disparity`` (image resolution) with NaN where the pixel's tool/background class differs from
    that of its matching-resolution pixel: no tool value lands on the tissue or the reverse."""
    if n == 1:
        return disparity
    grown = cv2.resize(small_tool.astype(np.uint8), (tool.shape[1], tool.shape[0]),
                       interpolation=cv2.INTER_NEAREST).astype(bool)
    disparity[grown != tool] = np.nan
    return disparity
