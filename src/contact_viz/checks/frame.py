"""Per-frame measurements for the diagnostics: pure functions over one frame's arrays.

:func:`measure_frame` takes the tool mask, the depth, the grey left and right images and the
calibration of one rectified frame and returns :class:`FrameMeasures`, the quantities the checks
(:mod:`contact_viz.checks.rules`) compare with their thresholds:

* mask blobs: the main connected component and the largest extra one that is not a fragment of
  the tool cut by the image border (it does not touch the border, or lies far from the main blob);
* edge support: share of the mask contour (off the image border) that lies on an image edge (a grey
  gradient of image_edge_grey, or in dim light edge_texture_factor x the tissue's texture around);
* depth against the mask: with ``ref`` = the tool depth nearby (mean valid interior depth in a
  window, carried outwards to every pixel from its nearest interior pixel),
  ``inside_far_fraction`` = share of the mask's inner rim whose depth lies behind the tool's surface
  continued to it (the plane fitted to the window's interior depth, its slope bounded by what a
  shaft can have: a receding shaft deepens along its axis, a round one towards its silhouette) by
  more than far_depth_m / far_depth_rel and than a round shaft's silhouette relief there (one
  radius seen straight on, up to 1.4 radii off the optical axis) (the mask covers tissue, or the
  depth is shifted), ``outside_tool_fraction`` = share of a ring just outside the mask whose depth
  equals ``ref`` (the tool's depth bleeds onto tissue, or is shifted);
* ``hole_fraction``: invalid depth on the tool and in the band around it (two shaft widths);
* ``beside_valid_fraction``: valid depth in the band just outside the mask (out to the outer end of
  that ring): where it is low the depth source failed beside the tool (and the depth-against-mask
  shares rest on a few pixels). ``inside_far_fraction`` is NaN where the rim's depth is mostly
  invalid (valid on less than ``RIM_MIN_VALID`` of it): its share would rest on a minority of the rim;
* ``width_ratio``: physical shaft width (inscribed-disc diameter in px x depth of the shaft axis /
  fx) over the instrument's diameter (depth scale error; wrong mask). Below 1 it is NaN where the
  widest disc may not lie on the shaft: the disc is cut by the image border, or the mask fills more
  than ``max_shaft_fill`` x the disc's width x its reach from the border (the jaws side by side, the
  shaft out of view; the tip is narrower than the shaft);
* ``residual_ratio``: photometric residual of the right image warped into the left view by the
  depth's disparity fx B / Z near the tool, over the residual at a disparity 15% off (the better
  of +- 15%): well below 1 when the depth explains the stereo pair, near or above 1 when not;
* a digest of the depth and a grey thumbnail, for frozen-depth and image-change tests;
* where the mask is (centroid, coverage of a coarse grid), to tell instruments apart between frames.

:func:`measure_tools` measures every instrument (object id) of a frame on its own: the other
instruments are no tissue (out of its rings, bands and residual region), no contour of it, and a
piece of it seen beyond one of them is no extra blob.

Everything runs on the tool's bounding box padded by ``pad_frac`` x width, and at a reduced
resolution on large frames: every n-th pixel of the mask and the depth (nearest sampling: no depth
is mixed across the tool's edge) and the grey images shrunk n times by pixel averaging
(:func:`shrink_grey`), n = :func:`analysis_step` (4 at 1080p with the default
``analysis_width_px`` 480). Areas, positions and widths are reported in pixels of the full image.
No I/O.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from contact_viz.checks.params import DiagnosticParams

__all__ = ["COVER_SIZE", "FrameEvidence", "FrameMeasures", "ToolMeasures", "analysis_step", "measure_frame",
           "measure_tools", "merge_evidence", "shrink_grey", "THUMB_SIZE"]

THUMB_SIZE = (32, 18)  # (width, height) of the grey thumbnail kept per frame, px
RESIDUAL_DELTA = 0.15  # the alternative disparities are (1 +- this) x the depth's, fraction
RESIDUAL_BOX = 5  # side of the box filter over the absolute residual, px
SOBEL_NORM = 8.0  # Sobel 3x3 output / this = grey levels per px
RIM_MIN_VALID = 0.5  # inside_far_fraction is measured where at least this share of the rim has valid depth, 0-1
COVER_SIZE = (64, 36)  # (width, height) of the coarse coverage grid of a mask kept per frame and instrument, cells
OTHERS_MARGIN = 2.0  # pixels this close to another instrument (analysis px) are neither tissue nor contour, px


@dataclass(frozen=True)
class FrameEvidence:
    """Pictures of what the checks measured, for the viewer.

    The pictures are at the analysis resolution: one of their pixels is ``step`` x ``step`` pixels of
    the image; the contour is in full-image pixels."""

    residual_xywh: tuple[int, int, int, int]  # where the residual image lies in the shrunk left image, px / step
    residual: np.ndarray  # (h, w) uint8: |left - warped right| (grey levels, clipped to 255), 0 outside the region
    contour_xy: np.ndarray  # (n, 2) float32 mask contour pixels (x, y), full-image px
    contour_on_edge: np.ndarray  # (n,) bool: on an image edge
    region: np.ndarray  # (h, w) bool: where the residual was measured (valid depth near the tool)
    left_grey: np.ndarray | None  # (ceil(H/step), ceil(W/step)) the shrunk left image, grey (the picture's background)
    step: int = 1  # image pixels per picture pixel along each axis


@dataclass(frozen=True)
class FrameMeasures:
    """What :func:`measure_frame` measured on one frame; NaN where a quantity could not be measured."""

    tool_area_px: int  # tool-mask pixels, px
    touches_border: bool  # the mask reaches the image border
    extra_blob_px: int  # area of the largest extra blob that is not a border fragment of the tool, px (0 = none)
    extra_blob_xy: tuple[float, float] | None  # its centroid, px
    edge_support: float  # share of the contour (off the border) on an image edge, 0-1
    inside_far_fraction: float  # share of the mask's inner rim with depth behind the nearby tool depth, 0-1
    outside_tool_fraction: float  # share of the outside ring with depth at the nearby tool depth, 0-1
    hole_fraction: float  # share of invalid depth on the tool and the band around it, 0-1
    # share of valid depth in the band just outside the mask (0 < distance <= the ring's outer end), 0-1
    beside_valid_fraction: float = field(default=math.nan, kw_only=True)
    shaft_width_px: float  # diameter of the largest disc inside the mask, px
    width_ratio: float  # physical shaft width / tool diameter, ratio
    residual_ratio: float  # stereo residual at the depth / at a 15% different disparity, ratio
    residual_grey: float  # mean stereo residual near the tool, grey levels
    depth_digest: bytes  # hash of the depth map's bytes
    thumb: np.ndarray = field(repr=False)  # (18, 32) float32 grey thumbnail of the left image, 0-255 (empty if none)
    evidence: FrameEvidence | None = field(default=None, repr=False)
    # where the mask is, for telling instruments apart between frames (id swaps, merges): its centroid, px, and
    # the share of each cell of a COVER_SIZE grid over the image that it covers, (36, 64) float32 0-1 (None = empty)
    centroid_xy: tuple[float, float] | None = field(default=None, kw_only=True)
    coverage: np.ndarray | None = field(default=None, repr=False, kw_only=True)


@dataclass(frozen=True)
class ToolMeasures:
    """What :func:`measure_tools` measured on one frame: each instrument's :class:`FrameMeasures` (the
    instruments present, by object id, ascending) and what belongs to the frame (depth digest, thumbnail,
    the instruments' total mask area)."""

    tools: dict[int, FrameMeasures]  # object id -> its measures (only ids with mask pixels)
    depth_digest: bytes  # hash of the depth map's bytes
    thumb: np.ndarray = field(repr=False)  # (18, 32) float32 grey thumbnail of the left image (empty if none)
    tool_area_px: int = 0  # mask pixels of every instrument measured, px
    evidence: FrameEvidence | None = field(default=None, repr=False)  # every instrument's, one picture


DIGEST_STRIDE = 3  # the depth digest hashes every 3rd row and column of the analysed depth (a repeated map matches,
# a new one differs by its noise everywhere): at 1080p every 6th, 1/36 of the bytes, 0.35 ms (every 3rd: 1.3)
BLOB_STEP = 2  # extra blobs are found on every 2nd row and column of the mask (a quarter of the cost), px


def analysis_step(width_px: int, params: DiagnosticParams = DiagnosticParams()) -> int:
    """n: the checks of a frame ``width_px`` wide look at every n-th pixel, the smallest n with
    ``width_px / n <= params.analysis_width_px``."""
    return max(1, -(-int(width_px) // params.analysis_width_px))


def shrink_grey(image: np.ndarray, step: int) -> np.ndarray:
    """The grey image the checks read: (H, W, 3) uint8 RGB or (H, W) grey, shrunk ``step`` times by
    pixel averaging to (ceil(H/step), ceil(W/step))."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    if step == 1:
        return grey
    height, width = grey.shape
    return cv2.resize(grey, (-(-width // step), -(-height // step)), interpolation=cv2.INTER_AREA)


def _digest(depth_m: np.ndarray) -> bytes:
    sample = np.ascontiguousarray(depth_m[::DIGEST_STRIDE, ::DIGEST_STRIDE])
    return hashlib.blake2b(sample.view(np.uint8), digest_size=16).digest()


def _thumb(grey: np.ndarray | None) -> np.ndarray:
    if grey is None:
        return np.zeros((0, 0), np.float32)
    return cv2.resize(np.asarray(grey), THUMB_SIZE, interpolation=cv2.INTER_AREA).astype(np.float32)


def _blobs(mask: np.ndarray, gap_px: float, others: np.ndarray | None = None) -> tuple[int, tuple[float, float] | None]:
    """(area, centroid) of the largest extra blob that is not a fragment of the tool, or (0, None).

    Found on the mask sampled every BLOB_STEP px (areas and positions scaled back). ``others``: the other
    instruments' pixels (same size as ``mask``); a blob joined to the main one by them is the tool seen on
    both sides of an instrument that crosses in front of it, no extra blob."""
    step = BLOB_STEP
    small = np.ascontiguousarray(mask[::step, ::step]).view(np.uint8)
    n, labels, stats, centroids = cv2.connectedComponentsWithStats(small, connectivity=8)
    if n <= 2:
        return 0, None
    gap_px = gap_px / step
    areas = stats[1:, cv2.CC_STAT_AREA]
    main = 1 + int(np.argmax(areas))
    height, width = small.shape
    bridged = None
    if others is not None:
        near = cv2.dilate(np.ascontiguousarray(others[::step, ::step]).view(np.uint8), np.ones((3, 3), np.uint8))
        if near.any():
            _, joined = cv2.connectedComponents(small | near, connectivity=8)
            bridged = joined
            main_joined = joined[labels == main][0]
    gap = None
    best, best_xy = 0, None
    mx, my, mw, mh, _ = stats[main]
    # how far the main blob reaches into the image from the border it touches (inf: it touches none)
    reach = min([mh for touching in (my == 0, my + mh == height) if touching]
                + [mw for touching in (mx == 0, mx + mw == width) if touching], default=math.inf)
    border_gap = None
    for k in range(1, n):
        if k == main:
            continue
        x, y, w, h, area = stats[k]
        if area <= best:
            continue
        if bridged is not None and bridged[labels == k][0] == main_joined:
            continue  # the same tool on the far side of another instrument
        at_border = x == 0 or y == 0 or x + w == width or y + h == height
        if gap is None:
            gap = cv2.distanceTransform((labels != main).view(np.uint8), cv2.DIST_L2, 3)
        limit = gap_px
        if at_border and math.isfinite(reach):
            # a tool tip just entering the view (reaching in no more than twice its width) shows its parts at the
            # border (its jaws) up to about its own width apart
            if border_gap is None:
                inside = cv2.distanceTransform((labels == main).view(np.uint8), cv2.DIST_L2, 3)
                diameter = 2.0 * float(inside.max())
                border_gap = max(gap_px, diameter) if reach <= 2.0 * diameter else gap_px
            limit = border_gap
        far = float(gap[labels == k].min()) > limit
        if far or not at_border:
            if far or float(gap[labels == k].min()) > 1.5:  # touching fragments are one blob really
                best, best_xy = int(area), (float(centroids[k][0]) * step, float(centroids[k][1]) * step)
    return best * step * step, best_xy


def measure_frame(
    tool_mask: np.ndarray,
    depth_m: np.ndarray,
    left_grey: np.ndarray | None,
    right_grey: np.ndarray | None,
    fx_px: float,
    baseline_m: float,
    params: DiagnosticParams = DiagnosticParams(),
    *,
    evidence: bool = False,
    others: np.ndarray | None = None,
) -> FrameMeasures:
    """The diagnostics' measurements of one frame (see the module docstring).

    tool_mask (H, W) bool; depth_m (H, W) float, m, invalid where not finite or <= 0; fx_px of the
    full image; left_grey / right_grey the grey images shrunk to the analysis size,
    ``shrink_grey(image, analysis_step(W, params))`` (the full (H, W) images when the step is 1), uint8
    or float, or None (then the image checks are NaN). ``others`` (H, W) bool: other instruments' pixels
    (:func:`measure_tools`): they and a margin of OTHERS_MARGIN analysis px around them are no tissue (left
    out of the rings, the band of the holes, the residual's region) and no mask contour of this tool.
    """
    full = np.asarray(tool_mask, dtype=bool)
    step = analysis_step(full.shape[1], params)
    area = int(np.count_nonzero(full))
    touches = bool(area and (full[0].any() or full[-1].any() or full[:, 0].any() or full[:, -1].any()))
    others_a = None if others is None else np.ascontiguousarray(np.asarray(others, dtype=bool)[::step, ::step])
    return _measure(area, touches, np.ascontiguousarray(full[::step, ::step]), step, depth_m, left_grey, right_grey,
                    fx_px, baseline_m, params, evidence, others_a, _digest(depth_m[::step, ::step]),
                    _thumb(left_grey))


def _coverage(mask: np.ndarray) -> np.ndarray:
    """The share of each cell of a COVER_SIZE grid that ``mask`` covers, (36, 64) float32."""
    return cv2.resize(mask.view(np.uint8).astype(np.float32), COVER_SIZE, interpolation=cv2.INTER_AREA)


def _measure(area: int, touches: bool, mask: np.ndarray, step: int, depth_m, left_grey, right_grey, fx_px, baseline_m,
             params, evidence, others_a, digest, thumb) -> FrameMeasures:
    """measure_frame of a mask given as its full-image area, whether it touches the image border and its pixels
    at the analysis resolution (every ``step``-th); ``others_a``: the other instruments there, or None."""
    nan = math.nan
    if area == 0:
        return FrameMeasures(0, False, 0, None, nan, nan, nan, nan, 0.0, nan, nan, nan, digest, thumb)
    depth_m = depth_m[::step, ::step]
    fx_px = fx_px / step
    height, width = mask.shape
    principal = ((width - 1) / 2.0, (height - 1) / 2.0)  # the view rays' angles are taken from the image centre
    for name, grey in (("left_grey", left_grey), ("right_grey", right_grey)):
        if grey is not None and np.shape(grey)[:2] != mask.shape:
            raise ValueError(f"measure_frame: {name} must be {height}x{width} px (the image shrunk {step} times), "
                             f"got {np.shape(grey)}")
    if not mask.any():  # a sliver the sampling misses: nothing to measure at this resolution
        return FrameMeasures(area, touches, 0, None, nan, nan, nan, nan, 0.0, nan, nan, nan, digest, thumb)
    ys, xs = np.nonzero(mask)
    where = dict(centroid_xy=(float(xs.mean()) * step, float(ys.mean()) * step), coverage=_coverage(mask))
    extra_px, extra_xy = _blobs(mask, params.blob_gap_frac * width, others_a)
    extra_px *= step * step
    extra_xy = None if extra_xy is None else (extra_xy[0] * step, extra_xy[1] * step)

    bx, by, bw, bh = cv2.boundingRect(mask.view(np.uint8))
    pad = int(math.ceil(params.pad_frac * width)) + 2
    y0, y1 = max(by - pad, 0), min(by + bh + pad, height)
    x0, x1 = max(bx - pad, 0), min(bx + bw + pad, width)
    m = mask[y0:y1, x0:x1]
    m8 = m.view(np.uint8)
    z = np.asarray(depth_m[y0:y1, x0:x1], dtype=np.float32)
    valid = np.isfinite(z) & (z > 0)
    z0 = np.where(valid, z, np.float32(0))
    # pixels away from the image border (a contour there is the frame's edge, not the tool's)
    off = np.zeros_like(m)
    off[max(2 - y0, 0):max(min(height - 2 - y0, m.shape[0]), 0), max(2 - x0, 0):max(min(width - 2 - x0, m.shape[1]), 0)] = True
    near_others = None
    if others_a is not None:
        o = np.ascontiguousarray(others_a[y0:y1, x0:x1])
        if o.any():
            near_others = cv2.distanceTransform((~o).view(np.uint8), cv2.DIST_L2, 5) <= OTHERS_MARGIN
            off &= ~near_others  # another instrument is no tissue, and its edge is no edge of this tool

    # inside distances (the image border counts as background: every disc lies inside the image)
    dt_in = cv2.distanceTransform(cv2.copyMakeBorder(m8, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0), cv2.DIST_L2,
                                  5)[1:-1, 1:-1]
    dt_out = cv2.distanceTransform((~m).view(np.uint8), cv2.DIST_L2, 5)
    radius = float(dt_in.max())
    shaft_px = max(2.0 * radius - 1.0, 1.0)
    cy, cx = np.unravel_index(int(np.argmax(dt_in)), dt_in.shape)
    r = max(int(radius), 1)
    disc = z[max(cy - r, 0):cy + r + 1, max(cx - r, 0):cx + r + 1]
    disc = disc[np.isfinite(disc) & (disc > 0)]
    diameter_m = params.tool_diameter_mm / 1000.0
    width_ratio = nan
    if disc.size:
        axis_depth = float(np.median(disc)) + diameter_m / 2  # the shaft's axis lies a radius behind its surface
        width_ratio = shaft_px * axis_depth / fx_px / diameter_m
        gy, gx = cy + y0, cx + x0
        if width_ratio < 1 and (min(gy, gx, height - 1 - gy, width - 1 - gx) <= radius + 1
                                or _tip_only(m, (y0, y1, x0, x1), (height, width), near_others, shaft_px, params)):
            # the widest disc is cut by the image border (a tool entering or leaving), or lies on the jaws with the
            # shaft out of view: no shaft to measure, and the tip is narrower than the shaft
            width_ratio = nan

    # holes on the tool and in the band around it
    region = dt_out <= 2.0 * shaft_px
    if near_others is not None:
        region &= ~near_others
    hole_fraction = float(1.0 - valid[region].mean())

    # depth against the mask: the nearby tool depth, carried outwards
    lo, hi = max(params.ring_frac_lo * width, 1.5), max(params.ring_frac_hi * width, 3.5)
    beside = (dt_out > 0) & (dt_out <= hi) & off
    beside_valid = float(valid[beside].mean()) if beside.any() else nan
    inside_far = outside_tool = nan
    interior = (dt_in > 2.5) & valid
    k = max(3, int(round(0.03 * width)) | 1)
    num = cv2.boxFilter(z0 * interior, -1, (k, k), normalize=False)
    den = cv2.boxFilter(interior.astype(np.float32), -1, (k, k), normalize=False)
    source = interior & (den > 0)
    if source.any():
        _, labels = cv2.distanceTransformWithLabels((~source).view(np.uint8), cv2.DIST_L2, 5,
                                                    labelType=cv2.DIST_LABEL_PIXEL)
        lut = np.zeros(int(labels.max()) + 1, np.float32)
        lut[labels[source]] = num[source] / den[source]
        ring = (dt_out > lo) & (dt_out <= hi) & valid & off
        if ring.any():
            ref = lut[labels[ring]]
            same = np.abs(z0[ring] - ref) < np.maximum(params.same_depth_m, params.same_depth_rel * ref)
            outside_tool = float(same.mean())
        rim_all = m & (dt_in <= max(lo, 2.5) + 1) & off
        rim = rim_all & valid
        if rim.any() and rim.sum() >= RIM_MIN_VALID * rim_all.sum():
            ref = _surface_at(rim, labels, source, interior, z0, k, m, fx_px, diameter_m / 2, radius)
            ry, rx = np.nonzero(rim)
            relief = _silhouette_relief(rx + x0, ry + y0, fx_px, principal, diameter_m / 2, dt_in[rim], radius)
            far = z0[rim] - ref > np.maximum(np.maximum(params.far_depth_m, params.far_depth_rel * ref), relief)
            inside_far = float(far.mean())

    # mask contour against image edges
    edge_support = nan
    contour = m & ~cv2.erode(m8, np.ones((3, 3), np.uint8)).view(bool) & off
    mag = None
    left_c = None if left_grey is None else np.asarray(left_grey[y0:y1, x0:x1], dtype=np.float32)
    if left_c is not None:
        # smoothed once against noise: a 3x3 Gaussian at full size; shrinking's pixel averaging did it otherwise
        grey = cv2.GaussianBlur(left_c, (3, 3), 0) if step == 1 else left_c
        mag = cv2.magnitude(cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3))
        edge_grey = _edge_threshold(mag / SOBEL_NORM, (dt_out > hi) & (dt_out <= max(2.0 * shaft_px, 2.0 * hi)) & off,
                                    params)
        mag = cv2.dilate(mag, np.ones((3, 3), np.uint8)) / SOBEL_NORM
        if contour.any():
            edge_support = float((mag[contour] >= edge_grey).mean())

    # stereo photometric residual near the tool
    residual_ratio = residual_grey = nan
    residual_img = None
    near = None
    if left_c is not None and right_grey is not None and baseline_m > 0:
        near = (dt_out <= max(hi if source.any() else 3.5, 3.5) * 2) & valid
        if near_others is not None:
            near &= ~near_others
        if near.any():
            right = np.asarray(right_grey)
            disparity = np.where(valid, fx_px * baseline_m / np.where(valid, z, 1), 0).astype(np.float32)
            cols = np.arange(x0, x1, dtype=np.float32)[None, :]
            rows = np.broadcast_to(np.arange(y0, y1, dtype=np.float32)[:, None], m.shape)
            res = []
            for factor in (1.0, 1.0 - RESIDUAL_DELTA, 1.0 + RESIDUAL_DELTA):
                warped = cv2.remap(right, cols - factor * disparity, np.ascontiguousarray(rows), cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_REPLICATE).astype(np.float32)
                diff = np.abs(left_c - warped)
                if factor == 1.0:
                    residual_img = diff
                res.append(cv2.boxFilter(diff, -1, (RESIDUAL_BOX, RESIDUAL_BOX)))
            r0 = float(res[0][near].mean())
            alt = float(np.minimum(res[1], res[2])[near].mean())
            residual_grey = r0
            residual_ratio = r0 / max(alt, 1e-3)
            residual_img = np.where(near, residual_img, 0)

    ev = None
    if evidence:
        cys, cxs = np.nonzero(contour)
        on_edge = (mag[cys, cxs] >= edge_grey) if mag is not None else np.zeros(cys.size, bool)
        res_u8 = (np.zeros(m.shape, np.uint8) if residual_img is None
                  else np.clip(residual_img, 0, 255).astype(np.uint8))
        ev = FrameEvidence((x0, y0, x1 - x0, y1 - y0), res_u8,
                           (step * np.stack([cxs + x0, cys + y0], axis=1)).astype(np.float32), on_edge,
                           near if residual_img is not None else np.zeros(m.shape, bool),
                           None if left_grey is None else np.asarray(left_grey), step)
    return FrameMeasures(area, touches, extra_px, extra_xy, edge_support, inside_far, outside_tool, hole_fraction,
                         shaft_px * step, width_ratio, residual_ratio, residual_grey, digest, thumb, ev,
                         beside_valid_fraction=beside_valid, **where)


def _tip_only(m: np.ndarray, box: tuple[int, int, int, int], shape: tuple[int, int], near_others: np.ndarray | None,
              width_px: float, params: DiagnosticParams) -> bool:
    """Whether the mask ``m`` (the window y0:y1, x0:x1 = ``box`` of an image of ``shape``) may show an instrument's
    tip alone: its area exceeds max_shaft_fill x its widest disc's width ``width_px`` x its reach into the view (the
    farthest a mask pixel lies from where the mask is cut: its pixels on the image border, or where it touches no
    border those next to another instrument, ``near_others``). One shaft fills about its width x its reach; the
    jaws side by side, each as wide as the widest disc on them, about twice that. A mask cut nowhere is not."""
    y0, y1, x0, x1 = box
    cut = np.zeros_like(m)
    if y0 == 0:
        cut[0] |= m[0]
    if y1 == shape[0]:
        cut[-1] |= m[-1]
    if x0 == 0:
        cut[:, 0] |= m[:, 0]
    if x1 == shape[1]:
        cut[:, -1] |= m[:, -1]
    if not cut.any() and near_others is not None:
        cut = m & near_others
    if not cut.any():
        return False
    reach = float(cv2.distanceTransform((~cut).view(np.uint8), cv2.DIST_L2, 5)[m].max()) + 1.0  # px, the cut's own too
    return float(np.count_nonzero(m)) > params.max_shaft_fill * width_px * reach


EDGE_TEXTURE_MIN_PX = 20  # the tissue's texture is measured on at least this many pixels (else the fixed threshold)


def _edge_threshold(gradient: np.ndarray, band: np.ndarray, params: DiagnosticParams) -> float:
    """The gradient (grey levels / px) from which a mask contour pixel lies on an image edge: image_edge_grey,
    or less where the light is dim: edge_texture_factor x the tissue's median gradient in ``band`` (around the
    tool), at least min_image_edge_grey. Image gradients scale with the light, the tissue's texture and the
    tool's silhouette alike: a shaft that recedes from the camera (lying along tissue that tilts away) turns
    its surface from the endoscope's light and shows a dim, low-contrast silhouette that is still an edge
    several times the texture around it."""
    if np.count_nonzero(band) < EDGE_TEXTURE_MIN_PX:
        return params.image_edge_grey
    texture = float(np.median(gradient[band]))
    return float(min(params.image_edge_grey, max(params.min_image_edge_grey, params.edge_texture_factor * texture)))


SILHOUETTE_SLACK_PX = 1.5  # rim pixels this close to the mask's edge are taken at the silhouette (the depth map's
# silhouette may sit a pixel off the mask's), px


def _silhouette_relief(xs: np.ndarray, ys: np.ndarray, fx_px: float, principal: tuple[float, float],
                       radius_m: float, inset_px: np.ndarray, half_width_px: float) -> np.ndarray:
    """How far behind its front surface a round shaft of ``radius_m`` can lie at pixels (x, y) of its rim, where
    the view ray runs psi off the optical axis and the pixel lies ``inset_px`` inside the mask (distance to its
    edge) of a shaft ``half_width_px`` wide: radius x ((1 - e) sin psi + (1 - sqrt(2 e - e^2)) cos psi), with
    e = (inset - SILHOUETTE_SLACK_PX) / half_width (0 at the silhouette: radius x (sin psi + cos psi)), with psi
    at most 45 deg (beyond it the circle's whole depth span, radius x sqrt 2), m.

    (In the plane across the shaft, the ray grazes its circle at the silhouette and meets it first at its front;
    their depths differ by at most sin psi + cos psi radii: a shaft seen straight on shows its silhouette one
    radius behind its front, one seen obliquely, near the image's border, up to 1.4. A pixel e half-widths
    inside the silhouette sees the circle's surface there, nearer the front.)"""
    tan2 = ((xs - principal[0]) ** 2 + (ys - principal[1]) ** 2) / (fx_px * fx_px)
    cos = 1.0 / np.sqrt(1.0 + tan2)
    sin = np.minimum(np.sqrt(tan2) * cos, math.sqrt(0.5))  # beyond 45 deg the circle's whole depth span, sqrt 2
    cos = np.maximum(cos, math.sqrt(0.5))
    e = np.clip((inset_px - SILHOUETTE_SLACK_PX) / max(half_width_px, 1.0), 0.0, 1.0)
    return (radius_m * ((1.0 - e) * sin + (1.0 - np.sqrt(2.0 * e - e * e)) * cos)).astype(np.float32)


PLANE_RIDGE_PX2 = 0.5  # added to the variances of the pixel positions in the local plane fit (a thin window), px^2


MAX_AXIS_SLOPE = 1.0  # the steepest depth slope along a shaft that the rim test follows: tan(45 deg), a shaft
# pointing 45 deg away from the image plane; x (depth / fx) per px
MAX_RELIEF_SLOPE = 1.0  # ... across it: this x its radius (m) / its half-width (px) per px (a round shaft deepens
# by its radius from its axis to its silhouette: this is its mean slope there)


def _surface_at(where: np.ndarray, labels: np.ndarray, source: np.ndarray, interior: np.ndarray, z0: np.ndarray,
                k: int, mask: np.ndarray, fx_px: float, radius_m: float, half_width_px: float) -> np.ndarray:
    """The tool's depth at the pixels ``where``, continued from its interior: around each pixel's nearest source
    pixel (``labels``), the plane fitted by least squares to the interior depth in a k x k window, evaluated at
    the pixel. Unlike the window's mean, the plane follows the tool's own shape: a shaft that recedes from the
    camera (lying along tissue that tilts away) deepens along its axis, and a round shaft deepens across it
    towards its silhouette, by up to its radius; its rim lies behind the window's mean there without being
    tissue. The plane's slope is bounded by what a shaft can have: along its axis (the mask's main direction)
    MAX_AXIS_SLOPE x depth / fx per px, across it MAX_RELIEF_SLOPE x radius / half-width per px; a steeper slope
    is a depth step in the window (tissue inside the mask), which must not explain itself away.
    (n,) float32, m."""
    height, width = interior.shape
    moments = cv2.moments(mask.view(np.uint8), binaryImage=True)
    theta = 0.5 * math.atan2(2.0 * moments["mu11"], moments["mu20"] - moments["mu02"])
    ax, ay = math.cos(theta), math.sin(theta)
    weight = interior.astype(np.float64)
    ys, xs = np.mgrid[0:height, 0:width]
    xs = xs - width / 2.0  # about the middle: smaller moments
    ys = ys - height / 2.0
    zs = z0.astype(np.float64)

    def box(a):
        return cv2.boxFilter(a * weight, cv2.CV_64F, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)

    n = np.maximum(box(np.ones_like(weight)), 1.0)
    mx, my, mz = box(xs) / n, box(ys) / n, box(zs) / n
    cxx = box(xs * xs) / n - mx * mx + PLANE_RIDGE_PX2
    cyy = box(ys * ys) / n - my * my + PLANE_RIDGE_PX2
    cxy = box(xs * ys) / n - mx * my
    cxz = box(xs * zs) / n - mx * mz
    cyz = box(ys * zs) / n - my * mz
    det = cxx * cyy - cxy * cxy
    index = np.zeros(int(labels.max()) + 1, np.int64)
    index[labels[source]] = np.flatnonzero(source.ravel())
    at = index[labels[where]]

    def pick(a):
        return a.ravel()[at]

    cxx, cyy, cxy, cxz, cyz, det = pick(cxx), pick(cyy), pick(cxy), pick(cxz), pick(cyz), pick(det)
    gx = (cyy * cxz - cxy * cyz) / det
    gy = (cxx * cyz - cxy * cxz) / det
    mz = pick(mz)
    along_limit = MAX_AXIS_SLOPE * np.abs(mz) / fx_px
    across_limit = MAX_RELIEF_SLOPE * radius_m / max(half_width_px, 1.0)
    g_along = np.clip(gx * ax + gy * ay, -along_limit, along_limit)
    g_across = np.clip(-gx * ay + gy * ax, -across_limit, across_limit)
    dx, dy = xs[where] - pick(mx), ys[where] - pick(my)
    return (mz + g_along * (dx * ax + dy * ay) + g_across * (-dx * ay + dy * ax)).astype(np.float32)


def measure_tools(
    tool_ids: np.ndarray,
    depth_m: np.ndarray,
    left_grey: np.ndarray | None,
    right_grey: np.ndarray | None,
    fx_px: float,
    baseline_m: float,
    params: DiagnosticParams = DiagnosticParams(),
    *,
    selected=None,
    evidence: bool = False,
) -> ToolMeasures:
    """:func:`measure_frame` of every instrument of a frame, each with the others taken out of its tissue.

    ``tool_ids`` (H, W) integer object ids, 0 = background (``Frame.tool_ids``; a bool mask is one
    instrument, id 1). ``selected``: the object ids to measure (default every id present); ids not
    selected are still other instruments, never tissue. A frame whose only instrument is measured gets
    exactly ``measure_frame`` of its mask.
    """
    ids = np.asarray(tool_ids)
    if ids.dtype == bool:
        ids = ids.view(np.uint8)
    step = analysis_step(ids.shape[1], params)
    digest, thumb = _digest(depth_m[::step, ::step]), _thumb(left_grey)
    keys, areas = np.unique(ids[ids != 0], return_counts=True)  # tool pixels only: 0.6 ms, bincount 2.6
    counts = dict(zip(keys.tolist(), areas.tolist()))
    present = list(counts)
    measured = present if selected is None else [k for k in present if k in set(int(i) for i in selected)]
    tools: dict[int, FrameMeasures] = {}
    small = np.ascontiguousarray(ids[::step, ::step])
    edges = np.concatenate([ids[0], ids[-1], ids[:, 0], ids[:, -1]])
    for k in measured:
        area = int(counts[k]) if counts is not None else int(np.count_nonzero(ids == k))
        mask_a = small == k
        others_a = (small != 0) & ~mask_a if len(present) > 1 else None
        tools[k] = _measure(area, bool((edges == k).any()), mask_a, step, depth_m, left_grey, right_grey, fx_px,
                            baseline_m, params, evidence, others_a, digest, thumb)
    area = sum(m.tool_area_px for m in tools.values())
    shown = [m.evidence for m in tools.values() if m.evidence is not None]
    return ToolMeasures(tools, digest, thumb, area, merge_evidence(shown) if shown else None)


def merge_evidence(pictures: list[FrameEvidence]) -> FrameEvidence:
    """One :class:`FrameEvidence` of several instruments': the residual pictures pasted into their joint
    box (the largest residual where they overlap), the contours and regions joined."""
    if len(pictures) == 1:
        return pictures[0]
    x0 = min(e.residual_xywh[0] for e in pictures)
    y0 = min(e.residual_xywh[1] for e in pictures)
    x1 = max(e.residual_xywh[0] + e.residual_xywh[2] for e in pictures)
    y1 = max(e.residual_xywh[1] + e.residual_xywh[3] for e in pictures)
    residual = np.zeros((y1 - y0, x1 - x0), np.uint8)
    region = np.zeros((y1 - y0, x1 - x0), bool)
    for e in pictures:
        x, y, w, h = e.residual_xywh
        window = (slice(y - y0, y - y0 + h), slice(x - x0, x - x0 + w))
        residual[window] = np.maximum(residual[window], e.residual)
        region[window] |= e.region
    first = pictures[0]
    return FrameEvidence((x0, y0, x1 - x0, y1 - y0), residual,
                         np.concatenate([e.contour_xy for e in pictures]),
                         np.concatenate([e.contour_on_edge for e in pictures]), region, first.left_grey, first.step)
