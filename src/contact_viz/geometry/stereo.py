"""Depth from a rectified stereo pair with OpenCV semi-global matching (SGBM): pure functions over arrays.

This is the fallback for sessions that come without depth: a learned stereo network such as
FoundationStereo gives far better depth on endoscopic images (weak texture, specular highlights,
thin tools); feed its output in as ``depth/<stem>.npy`` (float32 m) or ``disparity/<stem>.npy``
(float32 px) and this module is never used.

The matcher (:func:`sgbm_disparity`) runs ``cv2.StereoSGBM`` with the left images padded on the
left (so pixels near the left edge can still be matched), OpenCV's speckle filter and
uniqueness test, then a left-right consistency check of our own (OpenCV's contrib
``ximgproc`` is not used): the right-view disparity is computed by matching the horizontally
flipped pair, and a left pixel is kept only where the right view maps it back within
``lr_max_diff_px``.

When the frame's tool mask is known, :func:`masked_sgbm_disparity` matches the tissue with the
tool inpainted out of both views, so that the tool's disparity is not dragged over the tissue
beside it (foreground fattening), which is where the contact patch reads the tissue
(docs/depth.md has the measurements).

Disparities are cached per frame outside the session directory (``contact_viz.io.depth_cache``), as
16-bit PNGs of the fixed-point (1/16 px) disparity, keyed by the session's path, the sizes and
modification times of the calibration and image files they depend on, and the resolved
parameters, so the second run is fast and a changed input never reuses a stale entry.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from contact_viz.geometry.occlusion import half_occluded, tool_runs
from contact_viz.params import check_fields, checked

__all__ = [
    "DEPTH_METHODS",
    "SGBMParams",
    "disparity_to_depth",
    "masked_sgbm_disparity",
    "right_view_tool_mask",
    "sgbm_disparity",
]

DEPTH_METHODS = ("sgbm",)  # methods `contact-viz depth` can compute
SUBPIXEL = 16  # StereoSGBM returns disparities in 1/16 px fixed point
_MODES = {
    "sgbm": cv2.STEREO_SGBM_MODE_SGBM,
    "sgbm_3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    "hh": cv2.STEREO_SGBM_MODE_HH,
    "hh4": cv2.STEREO_SGBM_MODE_HH4,
}
_MAX_CODE = np.iinfo(np.uint16).max  # largest value a 16-bit PNG holds
_MIN_BLOCK = 3  # smallest matching block side, px
_BLOCK_STEP = 2  # block sides are odd
_PLAIN_BLOCK = 3  # plain whole-frame matching's block side when no block size is given, px (SGBMParams)


# --------------------------------------------------------------------------------------------
# Parameters
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SGBMParams:
    """Semi-global matching settings; ``None`` fields are sized from the image width by :meth:`resolve`."""

    # disparity search range, px at the matching resolution (multiple of 16); None = from the calibration (resolve)
    num_disparities: int | None = checked(None, ge=SUBPIXEL, lt=_MAX_CODE // SUBPIXEL + 1, multiple_of=SUBPIXEL)
    # the nearest depth a scene can have, m: with a calibration, the search reaches fx * baseline / this (minus
    # the rectified cameras' cx offset), px at full resolution (15 mm: 301 px for a da Vinci endoscope at 1080p,
    # fx 1103 px and 4.1 mm baseline; 381 px for the synthetic camera at 1080p, fx 1144 px and 5 mm)
    min_depth_m: float = checked(0.015, gt=0)
    # with a calibration, the search reaches at most this share of the matching width (the rest of a view
    # then sees so little of a point that near: Middlebury's 0.19 m baseline would otherwise search 12,800 px)
    max_disparity_fraction: float = checked(0.25, gt=0, le=1)
    # without a calibration (resolve() given no fx and baseline): range = this * width (rounded up to 16)
    disparity_range_fraction: float = checked(0.125, gt=0, le=1)
    min_disparity: int = 0  # smallest disparity searched, px
    block_size: int | None = checked(None, ge=1, odd=True)  # matching block side, px (odd, >= 3); None = from the width
    # when block_size is None: block = width / this, as an odd number >= 3
    # (128: 5 px at 640, 15 px at 1920; chosen, with uniqueness 15, on the synthetic study's training
    # sessions, band pixels within 3 mm of the true depth; Middlebury within 2 px 95.8% -> 94.8%: docs/depth.md)
    width_per_block_px: float = checked(128.0, gt=0)
    # block side of plain whole-frame matching (sgbm_disparity: no instrument in view, no mask or an empty one),
    # px; None = block_size when that is given, else 3 (Middlebury within 2 px 96.0% against 94.8% with the
    # width rule's 7 px; synthetic tissue within 3 mm 95.8% against 95.7% with 5 px: docs/depth.md)
    plain_block_size: int | None = checked(None, ge=1, odd=True)
    p1_factor: int = checked(8, gt=0)  # P1 = p1_factor * channels * block^2: penalty for a 1 px disparity change
    p2_factor: int = 32  # P2 = p2_factor * channels * block^2: penalty for larger disparity jumps (> p1_factor)
    uniqueness_ratio: int = 15  # best cost must beat the second best by this margin, %
    speckle_window_size: int = 100  # largest connected speckle region removed, px (0 = no speckle filter)
    speckle_range: int = 2  # largest disparity step inside one connected region, px
    disp12_max_diff: int = 1  # OpenCV's built-in left-right tolerance, px (-1 = off)
    lr_check: bool = True  # run the right-view match and drop pixels failing the left-right check
    lr_max_diff_px: float = checked(1.0, ge=0)  # left-right consistency tolerance, px
    mode: str = checked("sgbm_3way", choices=_MODES)  # OpenCV mode: sgbm, sgbm_3way (fast), hh (full 8-path, slow), hh4
    # match at 1/downscale resolution, then upsample the disparity; None = from match_width_px
    downscale: int | None = checked(None, ge=1)
    # when downscale is None: the smallest downscale that brings the width to at most this, px (741 -> 1,
    # 1280 -> 2, 1920 -> 2). Weak tissue texture then spans enough grey levels per pixel: matched at 1920 px, most
    # pixels beside the tool go unmatched; at 640 px the patch's band (3-11 px of the image) hugs the tool edge
    # (1080p, |distance - rendered| 3.5 mm at 640, 2.0 at 960 px: benchmarks/bench_depth_region.py, docs/depth.md)
    match_width_px: int = checked(960, ge=16)
    # Depth only where the patch reads it (geometry.stereo_region), when the frame's tool mask is known:
    region: bool = True  # match finely only around the tools; elsewhere the coarse pass's disparity
    region_px: int = checked(24, ge=0)  # the fine region: the tools and the background within this of them, px
    coarse_width_px: int = checked(480, ge=16)  # the coarse full-frame pass matches at most this wide, px
    tile_rows_px: int = checked(48, ge=8)  # rows of one fine tile, px at the matching resolution
    range_margin_px: int = checked(4, ge=0)  # a tile's search range: the coarse disparities +- this, matching px
    # ... found in the tile's region; its far end also reaches the farthest coarse disparity this far beside the
    # region along the rows, matching px (None: the whole search range, the widest strip a tool can cast). The
    # coarse pass may have no tissue inside the region: beside a wide half-occluded strip, between two instruments,
    # near the image's edge, its own tool fattened over what is left
    range_context_px: int | None = checked(None, ge=0)
    # a tile whose tool pixels the coarse pass matched fewer of than this share searches up to the nearest depth
    # (min_depth_m): a tool too thin for the coarse pass (a sliver at the image's edge) is matched all the same
    range_tool_seen_min: float = checked(0.5, ge=0, le=1)
    # Mask-aware matching (masked_sgbm_disparity), used when the frame's tool mask is known:
    tool_mask_aware: bool = True  # match the tissue with the tool removed (inpainted) from both views
    tool_margin_px: int = checked(1, ge=0)  # the tool region removed grows by this in both views, px
    occlusion_check: bool = True  # drop left pixels whose match lies behind the tool in the right view
    # no depth on the half-occluded strip left of each tool, which the right camera cannot see, whatever SGBM put
    # there (geometry.occlusion.half_occluded: the tissue's disparity read beyond the strip)
    half_occluded_strip: bool = True
    # also inpaint, right of the tool in the right view, the tissue only the right camera sees (_hidden_strips)
    hidden_strip: bool = True
    # OpenCV's speckle filter once more after the inpainted tool region is taken out: it had joined the tool's
    # disparity dragged onto the tissue to that region (a narrow tip at close range) and kept it
    respeckle: bool = True
    strip_probe_near_px: int = checked(8, ge=1)  # the tissue's disparity beside the tool is read from this far ...
    strip_probe_far_px: int = checked(16, ge=1)  # ... to this far right of the tool, px
    tool_rows_pad_px: int = checked(16, ge=0)  # the tool's disparity is matched on its bbox grown by this, px
    # median of the matched disparity over this square window, px (0 = off; 3 or 5: OpenCV's float median);
    # tool and tissue apart. 5 chosen on the study's training sessions (band within 3 mm 91.0 -> 92.4%)
    median_px: int = checked(5, choices=(0, 3, 5))

    def __post_init__(self) -> None:
        check_fields(self)
        if self.strip_probe_far_px < self.strip_probe_near_px:
            raise ValueError(f"SGBMParams needs strip_probe_near_px <= strip_probe_far_px, got "
                             f"{self.strip_probe_near_px} and {self.strip_probe_far_px}")
        if self.p2_factor <= self.p1_factor:
            raise ValueError(
                f"SGBMParams needs p1_factor < p2_factor, got {self.p1_factor} and {self.p2_factor}"
            )

    def resolve(self, width_px: int, fx_px: float | None = None, baseline_m: float | None = None,
                disparity_offset_px: float = 0.0) -> SGBMParams:
        """These parameters with num_disparities, block_size, plain_block_size and downscale fixed for images
        ``width_px`` wide.

        The sizes refer to the matching resolution (width / downscale). The search range, unless given:
        with the calibration (``fx_px`` at this width and ``baseline_m``; ``disparity_offset_px`` = cx_right -
        cx_left of the rectified cameras), the disparity of a point at ``min_depth_m``, fx * baseline /
        min_depth - offset, scaled to the matching resolution and capped at ``max_disparity_fraction`` of
        its width, the smallest multiple of 16 reaching it from ``min_disparity``; without it,
        ``disparity_range_fraction`` of the matching width.
        """
        downscale = self.downscale if self.downscale is not None else max(1, -(-int(width_px) // self.match_width_px))
        width = max(1, int(width_px) // downscale)
        num = self.num_disparities
        if num is None and (fx_px is None) != (baseline_m is None):
            raise ValueError("SGBMParams.resolve needs both fx_px and baseline_m, or neither")
        if num is None and fx_px is not None:
            if not (np.isfinite(fx_px) and fx_px > 0 and np.isfinite(baseline_m) and baseline_m > 0
                    and np.isfinite(disparity_offset_px)):
                raise ValueError(f"SGBMParams.resolve: fx_px and baseline_m must be positive and the offset finite, "
                                 f"got {fx_px!r}, {baseline_m!r} and {disparity_offset_px!r}")
            largest = (fx_px * baseline_m / self.min_depth_m - disparity_offset_px) / downscale
            largest = min(largest, self.max_disparity_fraction * width)
            num = max(SUBPIXEL, -(-(int(np.floor(largest)) + 1 - self.min_disparity) // SUBPIXEL) * SUBPIXEL)
        elif num is None:
            num = max(SUBPIXEL, -(-int(np.ceil(width * self.disparity_range_fraction)) // SUBPIXEL) * SUBPIXEL)
        block = self.block_size
        if block is None:
            block = max(_MIN_BLOCK, int(round(width / self.width_per_block_px)))
            block += 1 - block % _BLOCK_STEP  # next odd number
        plain = self.plain_block_size
        if plain is None:
            plain = self.block_size if self.block_size is not None else _PLAIN_BLOCK
        if (num + max(self.min_disparity, 0)) * downscale * SUBPIXEL >= _MAX_CODE:
            raise ValueError(
                f"SGBMParams: search range {num} px x downscale {downscale} is too large "
                "(disparities must stay below 4096 px)"
            )
        return replace(self, num_disparities=num, block_size=block, plain_block_size=plain, downscale=downscale)


# --------------------------------------------------------------------------------------------
# Pure functions
# --------------------------------------------------------------------------------------------


def _as_pair(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    left, right = np.asarray(left), np.asarray(right)
    if left.shape != right.shape:
        raise ValueError(f"left and right images must have the same shape, got {left.shape} and {right.shape}")
    if left.dtype != np.uint8 or right.dtype != np.uint8:
        raise ValueError(f"expected uint8 images, got {left.dtype} and {right.dtype}")
    if left.ndim not in (2, 3) or (left.ndim == 3 and left.shape[2] != 3) or min(left.shape[:2]) < 1:
        raise ValueError(f"expected (H, W) grey or (H, W, 3) RGB images, got shape {left.shape}")
    return np.ascontiguousarray(left), np.ascontiguousarray(right)


def _matcher(p: SGBMParams, channels: int, min_disparity: int):
    """OpenCV's StereoSGBM for parameters ``p`` searching ``min_disparity .. + num_disparities - 1``."""
    area = channels * p.block_size * p.block_size
    return cv2.StereoSGBM_create(
        minDisparity=min_disparity,
        numDisparities=p.num_disparities,
        blockSize=p.block_size,
        P1=p.p1_factor * area,
        P2=p.p2_factor * area,
        disp12MaxDiff=p.disp12_max_diff,
        uniquenessRatio=p.uniqueness_ratio,
        speckleWindowSize=p.speckle_window_size,
        speckleRange=p.speckle_range,
        mode=_MODES[p.mode],
    )


def _match(left: np.ndarray, right: np.ndarray, p: SGBMParams) -> np.ndarray:
    """StereoSGBM disparity of ``left`` against ``right`` (H, W) float32 px, NaN = no match.

    The pair is padded on the left by the search range (edge pixels repeated) so that pixels
    near the left border can match; the padding is cropped off the result.
    """
    matcher = _matcher(p, 1 if left.ndim == 2 else left.shape[2], p.min_disparity)
    pad = p.num_disparities + max(p.min_disparity, 0)
    left_p = cv2.copyMakeBorder(left, 0, 0, pad, 0, cv2.BORDER_REPLICATE)
    right_p = cv2.copyMakeBorder(right, 0, 0, pad, 0, cv2.BORDER_REPLICATE)
    fixed = matcher.compute(left_p, right_p)[:, pad:]
    disparity = fixed.astype(np.float32) / np.float32(SUBPIXEL)
    disparity[fixed < p.min_disparity * SUBPIXEL] = np.nan  # OpenCV marks no-match as (min - 1) * 16
    return disparity


def left_right_check(disp_left: np.ndarray, disp_right: np.ndarray, max_diff_px: float) -> np.ndarray:
    """Where the left disparity is confirmed by the right view: (H, W) bool.

    ``disp_left[y, x] = d`` says left pixel x matches right pixel x - d; it passes when that right
    pixel (rounded) exists and ``|disp_right[y, round(x - d)] - d| <= max_diff_px``.
    Both inputs (H, W) float32 px with NaN = no match.
    """
    height, width = disp_left.shape
    finite = np.isfinite(disp_left)
    x_right = np.arange(width, dtype=np.float32)[None, :] - np.where(finite, disp_left, np.float32(width))
    col = np.rint(x_right).astype(np.int64)
    inside = finite & (col >= 0) & (col < width)
    rows = np.broadcast_to(np.arange(height)[:, None], disp_left.shape)
    back = np.full(disp_left.shape, np.nan, dtype=np.float32)
    back[inside] = disp_right[rows[inside], col[inside]]
    with np.errstate(invalid="ignore"):
        return inside & (np.abs(back - disp_left) <= max_diff_px)


def sgbm_disparity(left_rgb: np.ndarray, right_rgb: np.ndarray, params: SGBMParams = SGBMParams()) -> np.ndarray:
    """Disparity of a rectified pair by semi-global matching.

    ``left_rgb``, ``right_rgb``: (H, W, 3) or (H, W) uint8, rectified (corresponding pixels on the
    same row, right pixel = left pixel - disparity); blocks of ``plain_block_size``; ``params`` resolved
    with the calibration (:meth:`SGBMParams.resolve`) search from it, others a share of the width. Returns (H, W) float32 disparity in px
    (multiples of 1/16 px, times ``downscale``), NaN where no reliable match was found; with
    ``median_px``, the median of the matched disparities around each (:func:`median_by_region`).
    """
    left, right = _as_pair(left_rgb, right_rgb)
    p = params.resolve(left.shape[1])
    disparity = _sgbm(left, right, replace(p, block_size=p.plain_block_size))
    return median_by_region(disparity, [np.ones(disparity.shape, bool)], p.median_px)


def median_by_region(disparity_px: np.ndarray, regions: Sequence[np.ndarray], size: int) -> np.ndarray:
    """The median of the finite disparities over a ``size`` x ``size`` window at every finite pixel,
    taken within each of ``regions`` ((H, W) bool each) apart, so that no window mixes two regions
    (the tool and the tissue beside it); NaN stays NaN. ``size`` 0 or 1: unchanged.

    Pixels outside a region or without a match take the value of the nearest matched pixel of the
    region first (so they neither count as values nor pull the median towards 0); away from them
    this is exactly the median of the window (tested against ``np.median``). An odd window's median
    is one of its values, so 1/16 px disparities stay 1/16 px multiples.
    """
    if size <= 1:
        return disparity_px
    out = disparity_px.copy()
    for region in regions:
        known = region & np.isfinite(disparity_px)
        if known.any():
            filled = _fill_nearest(np.where(known, disparity_px, 0).astype(np.float32), known)
            out[known] = cv2.medianBlur(filled, size)[known]
    return out


def _sgbm(left: np.ndarray, right: np.ndarray, p: SGBMParams) -> np.ndarray:
    """:func:`sgbm_disparity` of a checked pair with resolved parameters, without the median."""
    height, width = left.shape[:2]
    n = p.downscale
    if n > 1:
        size = (max(1, width // n), max(1, height // n))
        left = cv2.resize(left, size, interpolation=cv2.INTER_AREA)
        right = cv2.resize(right, size, interpolation=cv2.INTER_AREA)
    disparity = _match(left, right, p)
    if p.lr_check:
        flipped = _match(np.ascontiguousarray(right[:, ::-1]), np.ascontiguousarray(left[:, ::-1]), p)
        disparity[~left_right_check(disparity, flipped[:, ::-1], p.lr_max_diff_px)] = np.nan
    if n > 1:
        disparity = cv2.resize(disparity, (width, height), interpolation=cv2.INTER_NEAREST) * np.float32(n)
    return disparity


def drop_speckles(disparity_px: np.ndarray, window_px: int, range_px: int) -> np.ndarray:
    """``disparity_px`` (H, W) float px, NaN = none, without its speckles: NaN on every 4-connected region
    of at most ``window_px`` pixels whose neighbours differ by at most ``range_px`` (OpenCV's
    filterSpeckles at the matcher's 1/16 px, as StereoSGBM applies it to its own output)."""
    fixed = np.where(np.isfinite(disparity_px), np.rint(disparity_px * SUBPIXEL), -SUBPIXEL)
    fixed = np.clip(fixed, -SUBPIXEL, np.iinfo(np.int16).max).astype(np.int16)
    cv2.filterSpeckles(fixed, -SUBPIXEL, window_px, range_px * SUBPIXEL)
    out = disparity_px.copy()
    out[fixed == -SUBPIXEL] = np.nan
    return out


def _fill_nearest(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """``values`` with every pixel outside ``known`` replaced by the value of its nearest ``known`` pixel."""
    if known.all():
        return values.copy()
    _, labels = cv2.distanceTransformWithLabels(
        (~known).astype(np.uint8), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
    )
    return values[known][labels - 1]  # labels number the known pixels in row-major order, from 1


def right_view_tool_mask(tool_mask: np.ndarray, tool_disparity_px: np.ndarray, margin_px: int = 0) -> np.ndarray:
    """Where the tool of the left view lies in the right view: (H, W) bool.

    ``tool_mask`` (H, W) bool, the left view's tool; ``tool_disparity_px`` (H, W) float, the
    disparity of every tool pixel (other pixels ignored; must be finite on the tool). Each tool
    pixel (y, x) marks (y, floor(x - d)) and (y, ceil(x - d)); the result is closed along rows
    over 1 px gaps and dilated by ``margin_px`` (square).
    """
    tool = np.asarray(tool_mask, dtype=bool)
    height, width = tool.shape
    ys, xs = np.nonzero(tool)
    out = np.zeros((height, width), np.uint8)
    x_right = xs - np.asarray(tool_disparity_px, dtype=np.float64)[ys, xs]
    for col in (np.floor(x_right), np.ceil(x_right)):
        col = col.astype(np.int64)
        keep = (col >= 0) & (col < width)
        out[ys[keep], col[keep]] = 1
    out = cv2.morphologyEx(out, cv2.MORPH_CLOSE, np.ones((1, 3), np.uint8))
    if margin_px > 0:
        out = cv2.dilate(out, np.ones((2 * margin_px + 1, 2 * margin_px + 1), np.uint8))
    return out.astype(bool)


def _tool_disparity(left: np.ndarray, right: np.ndarray, tool: np.ndarray, p: SGBMParams) -> np.ndarray:
    """Plain SGBM disparity around the tool, NaN elsewhere, (H, W) float32.

    Matched on a crop: the tool's rows +- tool_rows_pad_px, and its columns from the search range
    (plus the pad) left of it to the pad right of it, so that every tool pixel sees all its
    candidate matches (about a quarter of the frame instead of all of it on the study's sessions).
    """
    rows = np.flatnonzero(tool.any(axis=1))
    cols = np.flatnonzero(tool.any(axis=0))
    pad = p.tool_rows_pad_px
    reach = (p.num_disparities + max(p.min_disparity, 0)) * p.downscale
    y0, y1 = max(int(rows[0]) - pad, 0), min(int(rows[-1]) + 1 + pad, tool.shape[0])
    x0, x1 = max(int(cols[0]) - reach - pad, 0), min(int(cols[-1]) + 1 + pad, tool.shape[1])
    if p.downscale > 1:  # keep the crop's corner on the matching grid
        y0, x0 = y0 - y0 % p.downscale, x0 - x0 % p.downscale
    out = np.full(tool.shape, np.nan, np.float32)
    out[y0:y1, x0:x1] = _sgbm(*_as_pair(left[y0:y1, x0:x1], right[y0:y1, x0:x1]), p)
    return out


def _hidden_strips(tool: np.ndarray, tool_disparity_px: np.ndarray, around_disparity_px: np.ndarray,
                   margin_px: int, probe_px: tuple[int, int]) -> np.ndarray:
    """Right-view pixels right of the tool that only the right camera sees: (H, W) bool.

    Per row, right of each run of tool pixels a..x: from x - d_tool (the run's end in the right view),
    but not left of a - margin_px - d_bg, to x + margin_px - d_bg, where d_bg is the median finite
    disparity of the non-tool pixels probe_px[0]..probe_px[1] px right of x (rows y-1..y+1) in
    ``around_disparity_px``. These right-view columns show the tissue that lies under the (grown) run in
    the left view. The left view's tool region ends at x + margin_px; with this strip, the right view's
    ends where the tissue next to it lies (at d_bg), so the inpainted regions' edges line up at the
    tissue's disparity instead of the tool's. A run narrower than d_tool - d_bg (an instrument's tip at
    close range) hides only its own width: the tissue left of it that both cameras see stays matchable.
    Runs without a background disparity get no strip.
    """
    height, width = tool.shape
    out = np.zeros((height, width), bool)
    lo_px, hi_px = probe_px
    run_rows, run_firsts, run_lasts = tool_runs(tool)
    for y, a, x in zip(run_rows.tolist(), run_firsts.tolist(), run_lasts.tolist()):
        rows = slice(max(y - 1, 0), y + 2)
        cols = slice(min(x + lo_px, width), min(x + hi_px + 1, width))
        around = around_disparity_px[rows, cols][~tool[rows, cols]]
        around = around[np.isfinite(around)]
        if around.size == 0:
            continue
        background = float(np.median(around))
        start = max(int(np.floor(x - tool_disparity_px[y, x])), int(np.floor(a - margin_px - background)))
        stop = int(np.floor(x + margin_px - background)) + 1
        start, stop = max(start, 0), min(stop, width)
        if stop > start:
            out[y, start:stop] = True
    return out


def _inpaint_pair(left: np.ndarray, right: np.ndarray, left_region: np.ndarray, right_region: np.ndarray):
    """Both views with their tool region filled from the surrounding background (OpenCV's Telea inpainting)."""
    radius = 3  # px of background each filled pixel is drawn from
    return (cv2.inpaint(left, left_region.astype(np.uint8), radius, cv2.INPAINT_TELEA),
            cv2.inpaint(right, right_region.astype(np.uint8), radius, cv2.INPAINT_TELEA))


def masked_sgbm_disparity(
    left_rgb: np.ndarray,
    right_rgb: np.ndarray,
    tool_mask: np.ndarray,
    params: SGBMParams = SGBMParams(),
) -> np.ndarray:
    """Disparity of a rectified pair whose left tool mask is known, without foreground fattening.

    Block matching and the smoothness term of SGBM drag the disparity of a near object (the
    tool) several pixels out over the background next to it, exactly where the contact patch
    reads the tissue. Here the tool is taken out of both views instead: its pixels are inpainted
    from the background around them (in the right view, the tool region is the left mask shifted
    by the tool's own disparity; both grown by ``tool_margin_px``), so that no block beside the
    tool can align with the tool's edge, and the background is matched on its own texture.
    (Filling with noise, independent in the two views, was tried and is worse: OpenCV's
    Birchfield-Tomasi cost finds noise cheap to match; see docs/depth.md.)

    1. The tool's disparity: plain SGBM (:func:`sgbm_disparity` without the median) on a crop around
       the tool (inside the tool it is accurate); holes on the tool are filled from the nearest
       matched tool pixel.
    2. The right-view tool region from it (:func:`right_view_tool_mask`).
    3. Plain SGBM on the pair with both tool regions inpainted; with ``hidden_strip``, the
       right view's region also covers, right of the tool, the tissue that only the right camera sees
       (under the tool in the left view: for a tool narrower than its disparity step, its own width)
       (:func:`_hidden_strips`): otherwise the edges of the two inpainted regions line up at the tool's
       disparity and drag it 2-4 px over the tissue right of the tool (docs/depth.md).
    4. Result: step 1 on the (left) tool, step 3 elsewhere; with ``respeckle``, OpenCV's speckle
       filter once more on step 3 with the left tool region taken out (inside SGBM the tool's disparity
       dragged onto the tissue was joined to the inpainted region and kept: at close range, up to 25 px
       left of a narrow tip); with ``occlusion_check``, a left
       pixel whose match falls in the right view's inpainted region (hidden behind the tool in the
       right view: no depth can be measured there; or in the strip, where it came out too wide) is NaN;
       with ``half_occluded_strip``, so is every pixel of the strip left of the tool that the right
       camera cannot see (:func:`contact_viz.geometry.occlusion.half_occluded`), whatever disparity it
       got (the tool's, or made-up tissue whose match does not fall behind the tool).
    5. The median (``median_px``) of the tool and of the tissue apart (:func:`median_by_region`).
       SGBM's isolated mismatches beside the tool are what the patch's minimum finds; on the
       study's training sessions the median brings the band within 3 mm from 91.0% to 92.4%.

    ``tool_mask`` (H, W) bool or integer (nonzero = tool). Returns (H, W) float32 px, NaN where no
    reliable match. An empty mask gives :func:`sgbm_disparity`.
    """
    left, right = _as_pair(left_rgb, right_rgb)
    tool = np.asarray(tool_mask) != 0
    if tool.shape != left.shape[:2]:
        raise ValueError(f"tool_mask shape {tool.shape} differs from the images' {left.shape[:2]}")
    if not tool.any():
        return sgbm_disparity(left, right, params)
    p = params.resolve(left.shape[1])
    tool_disp = _tool_disparity(left, right, tool, p)
    known = tool & np.isfinite(tool_disp)
    margin = np.ones((2 * p.tool_margin_px + 1,) * 2, np.uint8)
    left_region = cv2.dilate(tool.astype(np.uint8), margin).astype(bool)
    if known.any():
        filled = _fill_nearest(np.where(known, tool_disp, 0).astype(np.float32), known)
        right_region = right_view_tool_mask(tool, filled, p.tool_margin_px)
    else:  # the tool matched nowhere: its right-view place is unknown; only the left view is masked
        right_region = np.zeros_like(tool)
    inpaint_right = right_region
    if p.hidden_strip and known.any():
        inpaint_right = right_region | _hidden_strips(tool, filled, tool_disp, p.tool_margin_px,
                                                      (p.strip_probe_near_px, p.strip_probe_far_px))
    left_m, right_m = _inpaint_pair(left, right, left_region, inpaint_right)
    disparity = _sgbm(left_m, right_m, p)
    disparity[left_region] = np.nan  # the margin beside the tool was inpainted: not measured
    if p.respeckle and p.speckle_window_size > 0:  # the filter again, the inpainted region (its joints) out
        disparity = drop_speckles(disparity, p.speckle_window_size, p.speckle_range)
    disparity[tool] = tool_disp[tool]
    if p.occlusion_check and inpaint_right.any():
        height, width = tool.shape
        outside = ~tool & np.isfinite(disparity)
        ys, xs = np.nonzero(outside)
        col = np.rint(xs - disparity[ys, xs]).astype(np.int64)
        inside = (col >= 0) & (col < width)
        hidden = np.zeros(ys.shape, bool)
        hidden[inside] = inpaint_right[ys[inside], col[inside]]  # behind the tool, or inpainted: not measured
        disparity[ys[hidden], xs[hidden]] = np.nan
    if p.half_occluded_strip:
        disparity[half_occluded(disparity, tool)] = np.nan
    return median_by_region(disparity, [tool, ~tool], p.median_px)


def disparity_to_depth(
    disparity_px: np.ndarray, fx_px: float, baseline_m: float, offset_px: float = 0.0
) -> np.ndarray:
    """Depth of a rectified pair's disparity: ``fx * baseline / (disparity + offset)``.

    ``disparity_px`` (H, W) float px; ``offset_px`` = cx_right - cx_left of the rectified cameras
    (0 for FoundationStereo's K.txt). Returns (H, W) float32 metres, NaN where the disparity is
    not finite or not positive, or disparity + offset is not positive.
    """
    if not (np.isfinite(fx_px) and fx_px > 0 and np.isfinite(baseline_m) and baseline_m > 0):
        raise ValueError(f"fx_px and baseline_m must be positive, got {fx_px!r} and {baseline_m!r}")
    disparity = np.asarray(disparity_px, dtype=np.float32)
    shifted = disparity + np.float32(offset_px)
    valid = np.isfinite(disparity) & (disparity > 0) & (shifted > 0)
    depth = np.full(disparity.shape, np.nan, dtype=np.float32)
    np.divide(np.float32(fx_px * baseline_m), shifted, out=depth, where=valid)
    return depth


