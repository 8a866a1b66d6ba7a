"""The robot's tool-tip pose seen by the camera: rigid transforms, projection, and the tip check.

Pure functions over arrays (no I/O, no Rerun). Conventions: quaternions in ROS order (x, y, z, w);
``camera_T_base`` is the 4x4 hand-eye transform taking points of the kinematics frame to the
rectified left camera's frame (x right, y down, z forward, metres); pixels x = column, y = row,
origin at the top-left pixel centre; K the rectified left camera matrix (px).

The tip check compares the kinematic tool tip with the tip estimated from the tool mask
(:func:`contact_viz.geometry.tooltip.tool_tip_xy`): in the image (px, the projected kinematic tip
against the mask tip) and in 3D (mm, the kinematic tip against the mask tip back-projected at the
median valid depth around it). A large value means the mask, the depth or the hand-eye
registration is off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "KinematicTip",
    "frame_samples",
    "kinematic_tip",
    "project_points",
    "quaternion_to_matrix",
    "transform_points",
]


def quaternion_to_matrix(quaternion_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4) in (x, y, z, w) order (normalised first)."""
    q = np.asarray(quaternion_xyzw, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)


def transform_points(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``transform`` (4, 4) applied to ``points`` (n, 3) -> (n, 3) float64."""
    T = np.asarray(transform, dtype=np.float64)
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return p @ T[:3, :3].T + T[:3, 3]


def project_points(K: np.ndarray, points_m: np.ndarray) -> np.ndarray:
    """Pixels (n, 2) of camera-frame points (n, 3) through K (3, 3); NaN for points not in front (z <= 0)."""
    p = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
    uvw = p @ np.asarray(K, dtype=np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = uvw[:, :2] / uvw[:, 2:3]
    uv[p[:, 2] <= 0] = np.nan
    return uv


def frame_samples(sample_t_s: np.ndarray, frame_t_s: np.ndarray, max_gap_s: float) -> np.ndarray:
    """Index of the nearest sample (ascending ``sample_t_s``) to each frame time; -1 when farther than ``max_gap_s``.

    Ties go to the earlier sample. Returns (n,) int64.
    """
    samples = np.asarray(sample_t_s, dtype=np.float64)
    frames = np.asarray(frame_t_s, dtype=np.float64)
    if samples.size == 0:
        return np.full(frames.shape, -1, dtype=np.int64)
    last = samples.size - 1
    after = np.searchsorted(samples, frames, side="left")
    hi = np.clip(after, 0, last)
    lo = np.clip(after - 1, 0, last)
    nearest = np.where(np.abs(frames - samples[lo]) <= np.abs(samples[hi] - frames), lo, hi)
    return np.where(np.abs(samples[nearest] - frames) <= max_gap_s, nearest, -1).astype(np.int64)


@dataclass(frozen=True)
class KinematicTip:
    """The kinematic tool tip of one frame, in the left camera, and its check against the mask tip."""

    tip_m: np.ndarray  # (3,) tip position in the left camera frame, m
    axes: np.ndarray  # (3, 3) tool frame axes in the camera frame, columns x, y, z (unit vectors)
    tip_xy_px: np.ndarray  # (2,) projection on the left image, px (NaN when behind the camera)
    mask_tip_xy_px: np.ndarray | None  # (2,) tip estimated from the mask, px; None when there is none
    mask_tip_m: np.ndarray | None  # (3,) mask tip back-projected at the depth around it, m; None without depth
    error_px: float  # |projected kinematic tip - mask tip|, px (NaN when either is missing)
    error_mm: float  # |kinematic tip - back-projected mask tip|, mm (NaN when either is missing)


def _depth_around(depth_m: np.ndarray, xy: np.ndarray, radius_px: int) -> float:
    """Median of the valid (finite, > 0) depths within ``radius_px`` of pixel ``xy``; NaN if none."""
    height, width = depth_m.shape
    cx, cy = math.floor(xy[0] + 0.5), math.floor(xy[1] + 0.5)
    window = depth_m[max(cy - radius_px, 0):min(cy + radius_px + 1, height),
                     max(cx - radius_px, 0):min(cx + radius_px + 1, width)]
    valid = window[np.isfinite(window) & (window > 0)]
    return float(np.median(valid)) if valid.size else math.nan


def kinematic_tip(
    camera_T_base: np.ndarray,
    position_m: np.ndarray,
    quaternion_xyzw: np.ndarray,
    K: np.ndarray,
    mask_tip_xy: tuple[float, float] | None = None,
    depth_m: np.ndarray | None = None,
    depth_radius_px: int = 3,
) -> KinematicTip:
    """The tip pose (``position_m``, ``quaternion_xyzw`` in the kinematics frame) in the left camera.

    ``mask_tip_xy``: the mask's tool tip (px) to compare with; ``depth_m`` (H, W) the frame's depth
    (m) to back-project it at the median valid depth within ``depth_radius_px`` of it.
    """
    T = np.asarray(camera_T_base, dtype=np.float64)
    tip = transform_points(T, np.asarray(position_m, dtype=np.float64))[0]
    axes = T[:3, :3] @ quaternion_to_matrix(quaternion_xyzw)
    Kf = np.asarray(K, dtype=np.float64)
    tip_xy = project_points(Kf, tip)[0]
    mask_xy = None if mask_tip_xy is None else np.asarray(mask_tip_xy, dtype=np.float64)
    mask_m = None
    error_px = error_mm = math.nan
    if mask_xy is not None:
        if np.isfinite(tip_xy).all():
            error_px = float(np.hypot(*(tip_xy - mask_xy)))
        if depth_m is not None:
            z = _depth_around(np.asarray(depth_m), mask_xy, depth_radius_px)
            if math.isfinite(z):
                mask_m = np.linalg.solve(Kf, np.array([mask_xy[0], mask_xy[1], 1.0])) * z
                error_mm = float(np.linalg.norm(tip - mask_m) * 1000.0)
    return KinematicTip(tip, axes, tip_xy, mask_xy, mask_m, error_px, error_mm)
