"""Tool-tip estimate from a binary tool mask, and zero-padded square crops around a point.

The RGB baseline (``contact_viz.baseline``) centres its crop on the tool tip; Yang et al. used a
DeepLabCut keypoint, we have only the SAM2 tool mask, so the tip is estimated from the mask alone.

The rule (``tool_tip_xy``):

1. Keep the largest 8-connected component of the mask (stray blobs and segmentation specks are
   ignored). Components smaller than ``TipParams.min_area_px`` count as no tool: the result is None.
2. Find where the tool enters the image (the "entry"):

   * if the component touches the image border, the entry is the longest run of component pixels
     along the one-pixel image frame (8-connected along the frame, so a run may turn a corner).
     A tool normally enters with its shaft, which is wider where it crosses the border than a
     jaw that may also graze it;
   * otherwise (the mask is wholly inside the image, e.g. the shaft is not segmented), the entry is
     the set of component pixels nearest to the image border: the shaft side of a tool faces the
     border it comes from.

3. The tip is the part of the component farthest (Euclidean, straight-line) from the entry: the
   centroid of the component pixels whose distance to the nearest entry pixel is within
   ``TipParams.tip_band_px`` of the maximum. The centroid makes the estimate stable against a
   single far pixel; with two open jaws of equal reach it lies between the jaw tips.

Known limits: a tip that itself leaves the image is not found (the crop is then centred on the
farthest in-image part); when the jaws are segmented as a separate, smaller component than the
shaft, the tip is the shaft's end.

Coordinates are pixels: x = column, y = row, origin at the top-left pixel centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from contact_viz.params import check_fields, checked

__all__ = ["TipParams", "crop_centered", "tool_tip_xy"]

_CONNECTIVITY = 8  # pixel connectivity of mask components and of runs along the border


@dataclass(frozen=True)
class TipParams:
    """Settings of the tool-tip estimate (see the module docstring for the rule)."""

    min_area_px: int = checked(20, ge=1)  # smallest largest-component area that counts as a tool, px
    tip_band_px: float = checked(2.0, ge=0)  # pixels this close to the largest entry distance form the tip, px

    def __post_init__(self) -> None:
        check_fields(self)


def _largest_component(mask: np.ndarray) -> np.ndarray | None:
    """The largest 8-connected component of ``mask`` (H, W) bool as a bool mask, None if empty."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=_CONNECTIVITY)
    if n <= 1:
        return None
    areas = stats[1:, cv2.CC_STAT_AREA]
    best = 1 + int(np.argmax(areas))  # ties: the lowest label, i.e. the first in raster order
    return labels == best


def _entry_pixels(component: np.ndarray) -> np.ndarray:
    """(H, W) bool: the entry of ``component`` (non-empty bool mask), see the module docstring."""
    height, width = component.shape
    frame = np.zeros_like(component)
    frame[0, :] = frame[-1, :] = frame[:, 0] = frame[:, -1] = True
    on_border = component & frame
    if on_border.any():
        # Runs along the frame: components of the border pixels alone (8-connected, so the frame's
        # corner pixels join the two sides they belong to).
        n, labels, stats, _ = cv2.connectedComponentsWithStats(on_border.astype(np.uint8), connectivity=_CONNECTIVITY)
        best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        return labels == best
    rows = np.arange(height)[:, None]
    cols = np.arange(width)[None, :]
    border_distance = np.minimum(np.minimum(rows, height - 1 - rows), np.minimum(cols, width - 1 - cols))
    nearest = border_distance[component].min()
    return component & (border_distance == nearest)


def tool_tip_xy(tool_mask: np.ndarray, params: TipParams = TipParams()) -> tuple[float, float] | None:
    """The tool tip (x, y) in px estimated from ``tool_mask`` (H, W) bool; None when there is no tool.

    See the module docstring for the rule. Returns float pixel coordinates (x = column, y = row),
    not necessarily integers (the tip is a centroid) and not necessarily on the mask.
    """
    mask = np.asarray(tool_mask)
    if mask.ndim != 2 or mask.dtype != np.bool_:
        raise ValueError(f"tool_mask: expected a 2-D bool array (H, W), got shape {mask.shape} dtype {mask.dtype}")
    if mask.shape[0] < 1 or mask.shape[1] < 1:
        raise ValueError(f"tool_mask: expected a non-empty image, got shape {mask.shape}")
    component = _largest_component(mask)
    if component is None or int(component.sum()) < params.min_area_px:
        return None
    entry = _entry_pixels(component)
    # Distance of every pixel to the nearest entry pixel (distanceTransform measures to zeros).
    not_entry = np.where(entry, 0, 1).astype(np.uint8)
    distance_px = cv2.distanceTransform(not_entry, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    reach = np.where(component, distance_px, -np.inf)
    tip = reach >= reach.max() - params.tip_band_px
    rows, cols = np.nonzero(tip)
    return float(cols.mean()), float(rows.mean())


def crop_centered(image: np.ndarray, center_xy: tuple[float, float], size: int) -> np.ndarray:
    """The ``size`` x ``size`` window of ``image`` centred on ``center_xy``, zero outside the image.

    Args:
        image: (H, W) or (H, W, C) array of any dtype.
        center_xy: (x, y) in px (x = column, y = row); rounded to the nearest pixel (halves up).
        size: side of the crop, px (>= 1). The centre pixel lands at index ``size // 2`` of the
            crop (for an even size, the crop reaches one pixel further up/left than down/right).

    Returns:
        (size, size) or (size, size, C) array of ``image``'s dtype; a new array, never a view.
    """
    img = np.asarray(image)
    if img.ndim not in (2, 3) or img.shape[0] < 1 or img.shape[1] < 1:
        raise ValueError(f"image: expected a non-empty (H, W) or (H, W, C) array, got shape {img.shape}")
    size = int(size)
    cx, cy = (float(v) for v in center_xy)
    if not (math.isfinite(cx) and math.isfinite(cy)):
        raise ValueError(f"center_xy: expected finite (x, y) px, got {center_xy!r}")
    height, width = img.shape[:2]
    x0 = math.floor(cx + 0.5) - size // 2  # image column of the crop's first column
    y0 = math.floor(cy + 0.5) - size // 2  # image row of the crop's first row
    out = np.zeros((size, size) + img.shape[2:], dtype=img.dtype)
    src_x0, src_x1 = max(x0, 0), min(x0 + size, width)
    src_y0, src_y1 = max(y0, 0), min(y0 + size, height)
    if src_x0 < src_x1 and src_y0 < src_y1:
        out[src_y0 - y0 : src_y1 - y0, src_x0 - x0 : src_x1 - x0] = img[src_y0:src_y1, src_x0:src_x1]
    return out
