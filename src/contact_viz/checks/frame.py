"""Per-frame measurements for the diagnostics: pure functions over one frame's arrays.

:func:`measure_frame` takes the tool mask, the depth, the grey left and right images and the
calibration of one rectified frame and returns :class:`FrameMeasures`, the quantities the checks
(:mod:`contact_viz.checks.rules`) compare with their thresholds:

* mask blobs: the main connected component and the largest extra one that is not a fragment of
  the tool cut by the image border (it does not touch the border, or lies far from the main blob);
* edge support: share of the mask contour (off the image border) that lies on an image edge;
* depth against the mask: with ``ref`` = the tool depth nearby (mean valid interior depth in a
  window, carried outwards to every pixel from its nearest interior pixel),
  ``inside_far_fraction`` = share of the mask's inner rim whose depth lies behind ``ref`` (the mask
  covers tissue, or the depth is shifted), ``outside_tool_fraction`` = share of a ring just
  outside the mask whose depth equals ``ref`` (the tool's depth bleeds onto tissue, or is shifted);
* ``hole_fraction``: invalid depth on the tool and in the band around it (two shaft widths);
* ``beside_valid_fraction``: valid depth in the band just outside the mask (out to the outer end of
  that ring): where it is low the depth source failed beside the tool (and the depth-against-mask
  shares rest on a few pixels). ``inside_far_fraction`` is NaN where the rim's depth is mostly
  invalid (valid on less than ``RIM_MIN_VALID`` of it): its share would rest on a minority of the rim;
* ``width_ratio``: physical shaft width (inscribed-disc diameter in px x depth of the shaft axis /
  fx) over the instrument's diameter (depth scale error; wrong mask);
* ``residual_ratio``: photometric residual of the right image warped into the left view by the
  depth's disparity fx B / Z near the tool, over the residual at a disparity 15% off (the better
  of +- 15%): well below 1 when the depth explains the stereo pair, near or above 1 when not;
* a digest of the depth and a grey thumbnail, for frozen-depth and image-change tests.

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

__all__ = ["FrameEvidence", "FrameMeasures", "analysis_step", "measure_frame", "shrink_grey", "THUMB_SIZE"]

THUMB_SIZE = (32, 18)  # (width, height) of the grey thumbnail kept per frame, px
RESIDUAL_DELTA = 0.15  # the alternative disparities are (1 +- this) x the depth's, fraction
RESIDUAL_BOX = 5  # side of the box filter over the absolute residual, px
SOBEL_NORM = 8.0  # Sobel 3x3 output / this = grey levels per px
RIM_MIN_VALID = 0.5  # inside_far_fraction is measured where at least this share of the rim has valid depth, 0-1


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


def _blobs(mask: np.ndarray, gap_px: float) -> tuple[int, tuple[float, float] | None]:
    """(area, centroid) of the largest extra blob that is not a fragment of the tool, or (0, None).

    Found on the mask sampled every BLOB_STEP px (areas and positions scaled back)."""
    step = BLOB_STEP
    small = np.ascontiguousarray(mask[::step, ::step]).view(np.uint8)
    n, labels, stats, centroids = cv2.connectedComponentsWithStats(small, connectivity=8)
    if n <= 2:
        return 0, None
    gap_px = gap_px / step
    areas = stats[1:, cv2.CC_STAT_AREA]
    main = 1 + int(np.argmax(areas))
    height, width = small.shape
    gap = None
    best, best_xy = 0, None
    for k in range(1, n):
        if k == main:
            continue
        x, y, w, h, area = stats[k]
        if area <= best:
            continue
        at_border = x == 0 or y == 0 or x + w == width or y + h == height
        if gap is None:
            gap = cv2.distanceTransform((labels != main).view(np.uint8), cv2.DIST_L2, 3)
        far = float(gap[labels == k].min()) > gap_px
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
) -> FrameMeasures:
    """The diagnostics' measurements of one frame (see the module docstring).

    tool_mask (H, W) bool; depth_m (H, W) float, m, invalid where not finite or <= 0; fx_px of the
    full image; left_grey / right_grey the grey images shrunk to the analysis size,
    ``shrink_grey(image, analysis_step(W, params))`` (the full (H, W) images when the step is 1), uint8
    or float, or None (then the image checks are NaN).
    """
    full = np.asarray(tool_mask, dtype=bool)
    step = analysis_step(full.shape[1], params)
    digest = _digest(depth_m[::step, ::step])
    thumb = _thumb(left_grey)
    area = int(np.count_nonzero(full))
    nan = math.nan
    if area == 0:
        return FrameMeasures(0, False, 0, None, nan, nan, nan, nan, 0.0, nan, nan, nan, digest, thumb)
    touches = bool(full[0].any() or full[-1].any() or full[:, 0].any() or full[:, -1].any())
    mask = np.ascontiguousarray(full[::step, ::step])
    depth_m = depth_m[::step, ::step]
    fx_px = fx_px / step
    height, width = mask.shape
    for name, grey in (("left_grey", left_grey), ("right_grey", right_grey)):
        if grey is not None and np.shape(grey)[:2] != mask.shape:
            raise ValueError(f"measure_frame: {name} must be {height}x{width} px (the image shrunk {step} times), "
                             f"got {np.shape(grey)}")
    if not mask.any():  # a sliver the sampling misses: nothing to measure at this resolution
        return FrameMeasures(area, touches, 0, None, nan, nan, nan, nan, 0.0, nan, nan, nan, digest, thumb)
    extra_px, extra_xy = _blobs(mask, params.blob_gap_frac * width)
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
        if min(gy, gx, height - 1 - gy, width - 1 - gx) <= radius + 1 and width_ratio < 1:
            width_ratio = nan  # the widest disc is cut by the image border: a tool entering or leaving

    # holes on the tool and in the band around it
    region = dt_out <= 2.0 * shaft_px
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
            ref = lut[labels[rim]]
            far = z0[rim] - ref > np.maximum(params.far_depth_m, params.far_depth_rel * ref)
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
        mag = cv2.dilate(mag, np.ones((3, 3), np.uint8)) / SOBEL_NORM
        if contour.any():
            edge_support = float((mag[contour] >= params.image_edge_grey).mean())

    # stereo photometric residual near the tool
    residual_ratio = residual_grey = nan
    residual_img = None
    near = None
    if left_c is not None and right_grey is not None and baseline_m > 0:
        near = (dt_out <= max(hi if source.any() else 3.5, 3.5) * 2) & valid
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
        on_edge = (mag[cys, cxs] >= params.image_edge_grey) if mag is not None else np.zeros(cys.size, bool)
        res_u8 = (np.zeros(m.shape, np.uint8) if residual_img is None
                  else np.clip(residual_img, 0, 255).astype(np.uint8))
        ev = FrameEvidence((x0, y0, x1 - x0, y1 - y0), res_u8,
                           (step * np.stack([cxs + x0, cys + y0], axis=1)).astype(np.float32), on_edge,
                           near if residual_img is not None else np.zeros(m.shape, bool),
                           None if left_grey is None else np.asarray(left_grey), step)
    return FrameMeasures(area, touches, extra_px, extra_xy, edge_support, inside_far, outside_tool, hole_fraction,
                         shaft_px * step, width_ratio, residual_ratio, residual_grey, digest, thumb, ev,
                         beside_valid_fraction=beside_valid)
