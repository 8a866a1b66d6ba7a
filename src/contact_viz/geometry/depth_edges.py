"""Depth at the tool's edge: how wrong it is, as pure functions over arrays.

Any depth source can smear the tool's depth a few pixels out over the tissue next to it: block
matching fattens the foreground (SGBM), learned networks interpolate across the occlusion
boundary (flying pixels). Those pixels lie exactly in the exterior band, where the
minimum-distance patch reads the tissue, and a tissue pixel that shows the tool's depth is what
the patch looks for. :func:`edge_error_profile` measures it against a true depth map: the
depth error of the background pixels by their distance from the mask edge (the band error
profile). The patch's own defence is its bleeding test (``PatchParams.reject_bleeding``,
contact_viz.geometry.patch); SGBM's is mask-aware matching (geometry.stereo).
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["edge_distance_px", "edge_error_profile"]


def edge_distance_px(tool_mask: np.ndarray) -> np.ndarray:
    """(H, W) float32: exact Euclidean distance of every background pixel to the nearest tool pixel, px
    (0 on the tool). An empty mask gives +inf everywhere."""
    tool = np.asarray(tool_mask) != 0
    if not tool.any():
        return np.full(tool.shape, np.inf, np.float32)
    return cv2.distanceTransform((~tool).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def edge_error_profile(
    depth_m: np.ndarray, true_depth_m: np.ndarray, tool_mask: np.ndarray, max_px: int = 15
) -> list[np.ndarray]:
    """The depth errors of the background pixels by distance from the mask edge.

    Returns ``max_px`` arrays; entry k - 1 holds ``depth - true`` (m) of the background pixels
    whose distance to the tool rounds to k px (k = 1..max_px) and where both depths are valid
    (finite, > 0). Negative = nearer than the truth (the tool's depth bled out is negative).
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    truth = np.asarray(true_depth_m, dtype=np.float64)
    if depth.shape != truth.shape or depth.shape != np.shape(tool_mask):
        raise ValueError(f"shapes differ: depth {depth.shape}, truth {truth.shape}, mask {np.shape(tool_mask)}")
    ring = np.rint(edge_distance_px(tool_mask))
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(depth) & (depth > 0) & np.isfinite(truth) & (truth > 0)
    return [(depth - truth)[valid & (ring == k)] for k in range(1, max_px + 1)]
