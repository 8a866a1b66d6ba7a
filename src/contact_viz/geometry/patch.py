"""The minimum-distance patch (paper, Sec. 2.1), as pure functions over arrays.

Given a tool mask and a metric depth map of one rectified frame, :func:`compute_patch` builds
the layers around the tool (eroded interior, excluded ring, exterior surface band), computes
for every band pixel ``p``

    d(p) = Z(p) - mean{ Z(q) : q in N1(p), q interior, Z(q) valid }   (needs >= tau_tool such q)
    s(p) = mean{ |d(q)| : q in N2(p), q a band pixel with d(q) defined } (needs >= tau_patch)

picks ``p* = argmin s`` (first in row-major order on ties) and reports the median of ``d`` over
the valid pixels of ``N2(p*)`` as the frame's tool-tissue distance, and
``-log10(max(|distance|, eps))`` as its signal.

Choices the paper leaves open, fixed here:

* "Tool pixels" of the N1 window are the *interior* pixels (the eroded mask) with valid depth;
  the eroded edge is excluded because both the SAM2 mask and the stereo depth are least
  reliable there.
* The neighbours ``q`` scored in ``N2(p)`` are band pixels (surface pixels) only; a tool or
  ring pixel never contributes a distance.
* Windows are clipped at the image border (pixels outside the image do not exist).
* Layers are defined by exact Euclidean distance to the mask edge: interior = tool pixels
  more than ``erosion_px`` from the background; ring = the rest of the tool plus background
  within ``ring_px`` of the tool; band = background between ``ring_px`` and
  ``ring_px + band_width`` of the tool, band_width = clip(band_scale * shaft width,
  band_min_px, band_max_px). The visible shaft width is ``2 * max(distance to background) - 1``
  over the tool pixels (the diameter of the largest inscribed disc), measured among the pixels
  of even row and even column of the image (a 2 px grid: within 3 px of the
  full-resolution value, so the band width it sets moves by at most 0.3 px, for a quarter of the
  cost). A tool covering none or all of those grid pixels is measured among all pixels.

Speed: every computation runs on the tool's bounding box padded by the band's reach (never the
whole frame; :func:`patch_depth_rows` says which rows of the depth that is), with integral images
gathered only at band pixels. Morphology and the distance transform are OpenCV's; the per-pixel
passes are compiled (contact_viz.geometry._patch_kernels), each checked against the NumPy expression it
replaces, and the whole against the literal formulas (tests).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from contact_viz.geometry import _patch_kernels as _kernels
from contact_viz.params import PatchParams

# Class ids of the layer image (see PatchResult.layer_ids); shared with the viewer and figures.
LAYER_BACKGROUND = 0
LAYER_INTERIOR = 1
LAYER_TOOL_EDGE = 2  # tool pixels eroded away: the inner half of the excluded ring
LAYER_RING = 3  # background pixels of the excluded ring
LAYER_BAND = 4  # exterior surface band (the candidate pixels)

# Why no patch was found (PatchResult.reason).
REASON_EMPTY_MASK = "empty_mask"
REASON_NO_BAND = "no_band"
REASON_NO_TOOL_DEPTH = "too_few_tool_pixels"
REASON_NO_CANDIDATE = "too_few_valid_distances"
REASON_BLEEDING = "depth_bleeding"  # as the two above, but because the bleeding test rejected band pixels
REASON_HIDDEN = "band_hidden"  # as the two above, but the band pixels with depth are all hidden from the right camera

SHAFT_GRID_PX = 2  # the shaft width is measured among every SHAFT_GRID_PX-th row and column, px


@dataclass(frozen=True)
class PatchResult:
    """Everything :func:`compute_patch` found in one frame; every layer a viewer draws.

    Attributes
    ----------
    layer_ids : (H, W) uint8
        ``LAYER_*`` class of every pixel.
    band_yx : (N, 2) int64
        Row, column of every exterior-band pixel, row-major order.
    band_distance_m : (N,) float64
        ``d(p)`` at each band pixel, m; NaN where undefined (invalid depth or < tau_tool).
    band_score_m : (N,) float64
        ``s(p)`` at each band pixel, m; NaN where undefined (< tau_patch valid neighbours).
    center_xy : (x, y) of ``p*`` in pixels, or None.
    window_xyxy : (x0, y0, x1, y1) of ``N2(p*)`` clipped to the image, half-open, or None.
    tool_depth_m : the tool depth behind the patch: mean over the valid pixels ``q`` of ``N2(p*)``
        of their ``N1(q)`` interior depth, m, or NaN. (``p*`` itself may lack a tool depth: it
        only needs ``tau_patch`` valid neighbours.)
    score_m : ``s(p*)``, m, or NaN.
    distance_m : median ``d`` over the valid pixels of ``N2(p*)``, m, or NaN.
    signal : ``-log10(max(|distance_m|, eps))``, or NaN.
    shaft_width_px : visible shaft width, px (0 for an empty mask).
    tool_area_px : tool pixels in the mask, px.
    band_width_px : width of the exterior band used, px.
    n_band, n_valid_distance, n_candidates : band pixels; those with ``d`` defined; those with ``s``.
    invalid_depth_fraction : share of the band pixels the right camera sees (all of them without ``hidden``)
        with invalid depth, in [0, 1] (NaN if no band).
    n_bleeding : band pixels whose d was rejected as depth bled from the tool (``reject_bleeding``;
        see _band_distances); they count neither in n_valid_distance nor in the scores.
    n_hidden : band pixels in ``compute_patch``'s ``hidden`` (seen by the left camera only): no d, no score.
    reason : None when a patch was found, else one of the ``REASON_*`` strings.
    """

    layer_ids: np.ndarray
    band_yx: np.ndarray
    band_distance_m: np.ndarray
    band_score_m: np.ndarray
    center_xy: tuple[int, int] | None
    window_xyxy: tuple[int, int, int, int] | None
    tool_depth_m: float
    score_m: float
    distance_m: float
    signal: float
    shaft_width_px: float
    tool_area_px: int
    band_width_px: float
    n_band: int
    n_valid_distance: int
    n_candidates: int
    invalid_depth_fraction: float
    reason: str | None
    n_bleeding: int = 0
    n_hidden: int = 0

    @property
    def found(self) -> bool:
        """True when a patch was selected."""
        return self.reason is None

    @property
    def interior(self) -> np.ndarray:
        """(H, W) bool: the eroded tool interior."""
        return self.layer_ids == LAYER_INTERIOR

    @property
    def ring(self) -> np.ndarray:
        """(H, W) bool: the excluded ring (eroded tool edge and the background next to it)."""
        return (self.layer_ids == LAYER_TOOL_EDGE) | (self.layer_ids == LAYER_RING)

    @property
    def band(self) -> np.ndarray:
        """(H, W) bool: the exterior surface band."""
        return self.layer_ids == LAYER_BAND

    @property
    def candidates_yx(self) -> np.ndarray:
        """(M, 2) int64: band pixels where the score ``s`` is defined."""
        return self.band_yx[np.isfinite(self.band_score_m)]


def distance_signal(distance_m: np.ndarray | float, eps_m: float) -> np.ndarray | float:
    """The paper's signal ``-log10(max(|d|, eps))``; NaN stays NaN. Units of ``d``/``eps``: m."""
    with np.errstate(invalid="ignore"):
        return -np.log10(np.maximum(np.abs(distance_m), eps_m))


def band_width_px(shaft_width_px: float, params: PatchParams) -> float:
    """Exterior band width for a visible shaft width, px (clipped to the params' range)."""
    return float(np.clip(params.band_scale * shaft_width_px, params.band_min_px, params.band_max_px))


def _check_inputs(depth_m: np.ndarray, tool_mask: np.ndarray) -> None:
    if not isinstance(depth_m, np.ndarray) or depth_m.ndim != 2 or not np.issubdtype(depth_m.dtype, np.floating):
        raise ValueError(
            f"depth_m must be a 2-D float array (H, W) in metres, got "
            f"{getattr(depth_m, 'dtype', type(depth_m))} with shape {getattr(depth_m, 'shape', None)}"
        )
    if not isinstance(tool_mask, np.ndarray) or tool_mask.ndim != 2:
        raise ValueError(f"tool_mask must be a 2-D array (H, W), got shape {getattr(tool_mask, 'shape', None)}")
    if tool_mask.shape != depth_m.shape:
        raise ValueError(f"tool_mask shape {tool_mask.shape} differs from depth_m shape {depth_m.shape}")


@functools.lru_cache(maxsize=64)
def _disc(radius_px: float) -> np.ndarray:
    """Structuring element of the pixel offsets (dy, dx) with sqrt(dy^2 + dx^2) <= radius_px, uint8."""
    r = int(np.floor(radius_px))
    dy, dx = np.mgrid[-r:r + 1, -r:r + 1]
    return (np.sqrt(dy * dy + dx * dx) <= radius_px).astype(np.uint8)


@functools.lru_cache(maxsize=64)
def _disc_rectangles(radius_px: float) -> tuple[np.ndarray, ...]:
    """All-ones kernels whose union is ``_disc(radius_px)``: one (2h+1, 2w+1) rectangle per corner
    of the disc's staircase (row h of the disc is 2w+1 px wide, and row h+1 narrower)."""
    disc = _disc(radius_px)
    r = disc.shape[0] // 2
    half_widths = disc[r:].sum(axis=1) // 2  # w(h) for h = 0..r, non-increasing
    return tuple(
        np.ones((2 * h + 1, 2 * int(w) + 1), np.uint8)
        for h, w in enumerate(half_widths)
        if h == r or half_widths[h + 1] < w
    )


def _dilate_disc(mask_u8: np.ndarray, radius_px: float) -> np.ndarray:
    """Exact dilation of a uint8 0/1 mask by ``_disc(radius_px)``, (h, w) uint8 0/1.

    A disc is the union of the rectangles of its staircase, and OpenCV dilates by a rectangle
    separably, so this is about twice as fast as dilating by the disc kernel itself.
    """
    out = None
    for rectangle in _disc_rectangles(radius_px):
        dilated = cv2.dilate(mask_u8, rectangle)
        out = dilated if out is None else cv2.bitwise_or(out, dilated, dst=out)
    return out


def _max_distance_to_background(tool_u8: np.ndarray) -> float:
    """Largest exact Euclidean distance from a tool pixel of ``tool_u8`` (uint8 0/1) to a
    background pixel of it, in its pixels; outside the array is not background.

    OpenCV's exact transform returns float32 whose last bits depend on the buffer's memory
    alignment; the distance is the square root of an integer (a sum of two squares), which
    rounding the float32 value's square recovers exactly up to distances of 2,000 px.
    """
    distance = cv2.minMaxLoc(cv2.distanceTransform(tool_u8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE))[1]
    return math.sqrt(round(distance * distance))


def _shaft_width_px(tool_u8: np.ndarray, row_phase: int, col_phase: int) -> float:
    """Visible shaft width, px: ``2 * max(distance to background) - 1`` over the tool pixels.

    ``tool_u8`` is the (h, w) uint8 0/1 tool crop, framed by at least 2 px of background wherever
    it does not meet the image border; ``row_phase``/``col_phase`` are the crop row and column
    of the first image row and column that are multiples of ``SHAFT_GRID_PX``. The distance is
    measured among those grid pixels (``SHAFT_GRID_PX`` apart), or among all pixels when the tool
    covers none or all of them.
    """
    grid = np.ascontiguousarray(tool_u8[row_phase::SHAFT_GRID_PX, col_phase::SHAFT_GRID_PX])
    if grid.any() and not grid.all():
        return 2.0 * SHAFT_GRID_PX * _max_distance_to_background(grid) - 1.0
    return 2.0 * _max_distance_to_background(tool_u8) - 1.0


def _empty_result(shape: tuple[int, int], reason: str, layer_ids: np.ndarray | None = None,
                  shaft_width_px: float = 0.0, band_w: float = 0.0, tool_area_px: int = 0) -> PatchResult:
    empty_i = np.zeros((0, 2), np.int64)
    empty_f = np.zeros(0, np.float64)
    return PatchResult(
        layer_ids=np.zeros(shape, np.uint8) if layer_ids is None else layer_ids,
        band_yx=empty_i, band_distance_m=empty_f, band_score_m=empty_f,
        center_xy=None, window_xyxy=None, tool_depth_m=float("nan"), score_m=float("nan"),
        distance_m=float("nan"), signal=float("nan"), shaft_width_px=shaft_width_px, tool_area_px=tool_area_px,
        band_width_px=band_w,
        n_band=0, n_valid_distance=0, n_candidates=0, invalid_depth_fraction=float("nan"), reason=reason,
    )


@dataclass(frozen=True)
class _Layers:
    """The layers of one frame on the padded tool crop (see compute_patch); internal."""

    shape: tuple[int, int]  # full frame (H, W)
    origin_yx: tuple[int, int]  # crop's top-left corner in the frame, px
    crop_shape: tuple[int, int]
    layer_ids: np.ndarray  # (H, W) uint8, full frame
    depth_c: np.ndarray  # (h, w) float32 or float64 crop (a view) of the depth, m
    band_flat: np.ndarray  # (N,) int64 flat crop indices of the band pixels, row-major order
    by: np.ndarray  # (N,) band pixel rows in the crop
    bx: np.ndarray  # (N,) band pixel columns in the crop
    band_valid: np.ndarray  # (N,) uint8: 1 where the band pixel's depth is valid
    tool_sum_int: np.ndarray  # (h+1, w+1) integral of valid interior depth, m
    tool_cnt_int: np.ndarray  # (h+1, w+1) integral of the valid interior count
    shaft_width_px: float
    tool_area_px: int
    band_width_px: float
    beyond_sum_int: np.ndarray | None = None  # (h+1, w+1) integral of the valid depth beyond the band, m
    beyond_cnt_int: np.ndarray | None = None  # (h+1, w+1) integral of its count; None = no bleeding test
    bleed_step_m: float = 0.0  # PatchParams.bleed_step_m


def _tool_u8(tool_mask: np.ndarray) -> np.ndarray:
    """The tool mask as a C-contiguous uint8 0/1 array (a view when it already is bool)."""
    tool = tool_mask if tool_mask.dtype == np.bool_ else tool_mask != 0
    return np.ascontiguousarray(tool).view(np.uint8)


def _crop_bounds(bbox: tuple[int, int, int, int], shape: tuple[int, int], params: PatchParams) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1), half-open: the tool's bounding box ``bbox`` (row0, row1, col0, col1,
    inclusive) padded by the reach of the band (and of the bleeding test's tissue beyond it) and
    clipped to the frame. Every interior, ring and band pixel lies inside it, so windows clipped to
    it lose nothing that could contribute; the pad is at least 2 px, so that an even row and column of background frame the tool (see
    _shaft_width_px)."""
    row0, row1, col0, col1 = bbox
    pad = max(int(np.ceil(params.depth_reach_px)) + 1, SHAFT_GRID_PX)
    return max(row0 - pad, 0), min(row1 + pad + 1, shape[0]), max(col0 - pad, 0), min(col1 + pad + 1, shape[1])


def tool_bbox(tool_u8: np.ndarray) -> tuple[int, int, int, int] | None:
    """Inclusive bounds ``(row0, row1, col0, col1)`` of the nonzero pixels of the (H, W) uint8
    ``tool_u8``, or None when there are none."""
    x, y, w, h = cv2.boundingRect(tool_u8)
    return None if w == 0 else (y, y + h - 1, x, x + w - 1)


def patch_depth_rows(tool_mask: np.ndarray, params: PatchParams = PatchParams()) -> tuple[int, int]:
    """Rows ``(row0, row1)``, half-open, outside which :func:`compute_patch` never reads the
    depth for this ``tool_mask`` ((H, W) bool or integer); ``(0, 0)`` for an empty mask.

    ``row0`` is even, so ``compute_patch(depth_m[row0:row1], tool_mask[row0:row1], params)``
    equals ``compute_patch(depth_m, tool_mask, params)`` with every row coordinate less
    ``row0`` (the shaft width is measured on the image's even rows). `contact-viz extract`
    reads only these rows of each depth map.
    """
    if not isinstance(tool_mask, np.ndarray) or tool_mask.ndim != 2:
        raise ValueError(f"tool_mask must be a 2-D array (H, W), got shape {getattr(tool_mask, 'shape', None)}")
    bbox = tool_bbox(_tool_u8(tool_mask))
    if bbox is None:
        return 0, 0
    y0, y1, _, _ = _crop_bounds(bbox, tool_mask.shape, params)
    return y0 - y0 % SHAFT_GRID_PX, y1


def _build_layers(depth_m: np.ndarray, tool_mask: np.ndarray, params: PatchParams) -> _Layers | PatchResult:
    """Interior, ring and band of one frame, or the empty PatchResult when there is no band."""
    _check_inputs(depth_m, tool_mask)
    shape = depth_m.shape
    tool_full_u8 = _tool_u8(tool_mask)
    bbox = tool_bbox(tool_full_u8)
    if bbox is None:
        return _empty_result(shape, REASON_EMPTY_MASK)
    y0, y1, x0, x1 = _crop_bounds(bbox, shape, params)
    tool_u8 = np.ascontiguousarray(tool_full_u8[y0:y1, x0:x1])
    depth_c = depth_m[y0:y1, x0:x1]
    if depth_c.dtype not in (np.float32, np.float64):
        depth_c = depth_c.astype(np.float64)
    layer_ids = np.zeros(shape, np.uint8)
    if tool_u8.all():
        # No background anywhere near the tool: nothing to erode against and no band.
        layer_ids[y0:y1, x0:x1] = LAYER_INTERIOR
        return _empty_result(shape, REASON_NO_BAND, layer_ids, tool_area_px=tool_u8.size)

    shaft_width = _shaft_width_px(tool_u8, -y0 % SHAFT_GRID_PX, -x0 % SHAFT_GRID_PX)
    band_w = band_width_px(shaft_width, params)
    # Thresholds of the Euclidean distance to the mask edge are morphology with exact discs:
    # erosion keeps tool pixels with no background within erosion_px (outside the image is not
    # background: erode's default border), dilation adds background within a radius of the tool.
    interior_u8 = cv2.erode(tool_u8, _disc(params.erosion_px))
    near_u8 = _dilate_disc(tool_u8, params.ring_px)  # tool + excluded ring outside it
    far_u8 = _dilate_disc(tool_u8, params.ring_px + band_w)  # ... + exterior band
    band_flat, band_valid, tool_sum_int, tool_cnt_int, tool_area = _kernels.fuse_layers(
        tool_u8, interior_u8, near_u8, far_u8, depth_c, layer_ids[y0:y1, x0:x1],
        LAYER_BACKGROUND, LAYER_INTERIOR, LAYER_TOOL_EDGE, LAYER_RING, LAYER_BAND,
    )
    if band_flat.size == 0:
        return _empty_result(shape, REASON_NO_BAND, layer_ids, shaft_width, band_w, tool_area)
    beyond_sum_int = beyond_cnt_int = None
    if params.reject_bleeding:
        # The tissue beyond the band: background pixels within bleed_beyond_px of the band's outer edge
        # (dilating the small disc, not the tool by the whole reach: 3x cheaper at 1080p).
        # One compiled pass for both integrals, and the test itself in another (reject_bled): the test's
        # own work 0.60 instead of 1.05 ms CPU per 1080p frame (bench_patch frames, interleaved, median).
        beyond_sum_int, beyond_cnt_int = _kernels.ring_depth_integrals(
            _dilate_disc(far_u8, params.bleed_beyond_px), far_u8, depth_c)
    by, bx = np.divmod(band_flat, tool_u8.shape[1])
    return _Layers(
        shape=shape, origin_yx=(y0, x0), crop_shape=tool_u8.shape, layer_ids=layer_ids, depth_c=depth_c,
        band_flat=band_flat, by=by, bx=bx, band_valid=band_valid,
        tool_sum_int=tool_sum_int, tool_cnt_int=tool_cnt_int,
        shaft_width_px=shaft_width, tool_area_px=tool_area, band_width_px=band_w,
        beyond_sum_int=beyond_sum_int, beyond_cnt_int=beyond_cnt_int, bleed_step_m=params.bleed_step_m,
    )


def _band_distances(layers: _Layers, n1: int, tau_tool: int) -> tuple[np.ndarray, np.ndarray, int]:
    """d(p) at every band pixel and the mean interior depth of N1(p) behind it, (N,) each, NaN where
    undefined, and how many band pixels the bleeding test rejected.

    The bleeding test (PatchParams.reject_bleeding): with ``z_beyond`` the mean valid depth of the
    tissue beyond the band in N1(p) (at least one pixel), ``step = z_beyond - z_tool``:
    p's depth bled from the tool when ``step >= bleed_step_m`` and ``d(p) < step / 2`` (p lies
    nearer the tool's depth than the tissue's next to it: a depth step beside the tool, which a
    surface touching the tool does not make). Its d(p) is then undefined.
    """
    half = n1 // 2
    band_d, tool_mean = _kernels.band_distances(layers.tool_sum_int, layers.tool_cnt_int, layers.band_flat,
                                                layers.band_valid, layers.depth_c, half, tau_tool)
    if layers.beyond_sum_int is None:
        return band_d, tool_mean, 0
    n_bled = _kernels.reject_bled(layers.beyond_sum_int, layers.beyond_cnt_int, layers.band_flat, band_d,
                                  tool_mean, half, layers.bleed_step_m)
    return band_d, tool_mean, n_bled


class _Scores:
    """Window sums of |d| and of the count of defined d around every band pixel, for one N2; internal."""

    def __init__(self, layers: _Layers, band_d: np.ndarray, n2: int) -> None:
        self.half2 = n2 // 2
        self.count, self.total = _kernels.band_window_sums(layers.band_flat, band_d, *layers.crop_shape, self.half2)

    def score(self, tau_patch: int) -> np.ndarray:
        """s(p) at every band pixel, (N,), NaN where fewer than ``tau_patch`` distances are defined."""
        ok = self.count >= tau_patch
        band_s = np.full(self.count.shape, np.nan)
        band_s[ok] = self.total[ok] / self.count[ok]
        return band_s


def _patch_window(layers: _Layers, band_d: np.ndarray, band_s: np.ndarray, half2: int) -> tuple[int, np.ndarray]:
    """Index of p* (first minimum of s in row-major order) and the indices (M,) of the band
    pixels with a defined d in its N2 window, in band order."""
    best = int(np.nanargmin(band_s))
    return best, _kernels.window_members(layers.band_flat, band_d, layers.crop_shape[1], best, half2)


def compute_patch(depth_m: np.ndarray, tool_mask: np.ndarray, params: PatchParams = PatchParams(),
                  hidden: np.ndarray | None = None) -> PatchResult:
    """Find the minimum-distance patch of one frame.

    Parameters
    ----------
    depth_m : (H, W) float32 or float64
        Metric depth of the rectified left view, m. Non-finite or non-positive values are invalid.
    tool_mask : (H, W) bool or integer
        Tool segmentation; nonzero = tool. Several blobs are all tool.
    params : PatchParams
    hidden : (H, W) bool, optional
        Pixels the right camera cannot see (the half-occluded strips beside the instruments,
        ``geometry.occlusion.half_occluded``): their depth was observed by nobody, so a band pixel there
        has no ``d`` and is neither a candidate nor in any score. None (the paper): every band pixel counts.

    Returns
    -------
    PatchResult
        With ``reason`` set (and NaN distance) when no patch could be found.
    """
    if hidden is not None and hidden.shape != depth_m.shape:
        raise ValueError(f"hidden has shape {hidden.shape}, expected the depth's {depth_m.shape}")
    layers = _build_layers(depth_m, tool_mask, params)
    if isinstance(layers, PatchResult):
        return layers
    height, width = layers.shape
    y0, x0 = layers.origin_yx
    by, bx = layers.by, layers.bx
    n_band = int(by.size)
    band_yx = np.stack([by + y0, bx + x0], axis=1).astype(np.int64)
    band_d, tool_mean, n_bleeding = _band_distances(layers, params.n1, params.tau_tool)
    seen = np.ones(n_band, bool) if hidden is None else ~hidden[by + y0, bx + x0]
    band_d[~seen] = np.nan
    n_valid = int(np.isfinite(band_d).sum())

    def _result(reason, center=None, window=None, tool_depth=np.nan, score=np.nan, distance=np.nan,
                band_s=None, n_cand=0):
        return PatchResult(
            layer_ids=layers.layer_ids, band_yx=band_yx, band_distance_m=band_d,
            band_score_m=np.full(n_band, np.nan) if band_s is None else band_s,
            center_xy=center, window_xyxy=window, tool_depth_m=float(tool_depth), score_m=float(score),
            distance_m=float(distance), signal=float(distance_signal(distance, params.eps_m)),
            shaft_width_px=layers.shaft_width_px, tool_area_px=layers.tool_area_px,
            band_width_px=layers.band_width_px, n_band=n_band,
            n_valid_distance=n_valid, n_candidates=n_cand,
            invalid_depth_fraction=float(1.0 - layers.band_valid[seen].mean()) if seen.any() else 0.0,
            n_bleeding=n_bleeding, n_hidden=n_band - int(seen.sum()), reason=reason,
        )

    n_hidden = n_band - int(seen.sum())
    if n_valid == 0:
        return _result(REASON_BLEEDING if n_bleeding else REASON_HIDDEN if n_hidden else REASON_NO_TOOL_DEPTH)
    scores = _Scores(layers, band_d, params.n2)
    band_s = scores.score(params.tau_patch)
    n_cand = int(np.isfinite(band_s).sum())
    if n_cand == 0:
        return _result(REASON_BLEEDING if n_bleeding else REASON_HIDDEN if n_hidden else REASON_NO_CANDIDATE,
                       band_s=band_s)
    best, in_window = _patch_window(layers, band_d, band_s, scores.half2)
    distance = float(np.median(band_d[in_window]))
    cx, cy = int(bx[best]) + x0, int(by[best]) + y0
    half2 = scores.half2
    return _result(
        None,
        center=(cx, cy),
        window=(max(cx - half2, 0), max(cy - half2, 0), min(cx + half2 + 1, width), min(cy + half2 + 1, height)),
        tool_depth=float(np.mean(tool_mean[in_window])), score=band_s[best], distance=distance, band_s=band_s,
        n_cand=n_cand,
    )


def patch_distance_grid(
    depth_m: np.ndarray,
    tool_mask: np.ndarray,
    grid: Sequence[PatchParams],
) -> np.ndarray:
    """The frame's distance (m, NaN = no patch) for every parameter set of ``grid``, shape (len(grid),).

    Equal to ``[compute_patch(depth_m, tool_mask, p).distance_m for p in grid]`` but computes the
    layers once per distinct (erosion, ring, band) setting, ``d`` once per (N1, tau_tool) and the
    N2 box sums once per (N1, tau_tool, N2): the grid search's cost grows with the number of
    window sizes, not with the number of grid points.
    """
    out = np.full(len(grid), np.nan)
    layer_cache: dict[tuple, _Layers | PatchResult] = {}
    d_cache: dict[tuple, np.ndarray] = {}
    score_cache: dict[tuple, _Scores] = {}
    for i, p in enumerate(grid):
        layer_key = (p.erosion_px, p.ring_px, p.band_scale, p.band_min_px, p.band_max_px,
                     p.reject_bleeding, p.bleed_step_m, p.bleed_beyond_px)
        if layer_key not in layer_cache:
            layer_cache[layer_key] = _build_layers(depth_m, tool_mask, p)
        layers = layer_cache[layer_key]
        if isinstance(layers, PatchResult):
            continue
        d_key = (*layer_key, p.n1, p.tau_tool)
        if d_key not in d_cache:
            d_cache[d_key] = _band_distances(layers, p.n1, p.tau_tool)[0]
        band_d = d_cache[d_key]
        if not np.isfinite(band_d).any():
            continue
        s_key = (*d_key, p.n2)
        if s_key not in score_cache:
            score_cache[s_key] = _Scores(layers, band_d, p.n2)
        scores = score_cache[s_key]
        band_s = scores.score(p.tau_patch)
        if np.isfinite(band_s).any():
            out[i] = np.median(band_d[_patch_window(layers, band_d, band_s, scores.half2)[1]])
    return out
