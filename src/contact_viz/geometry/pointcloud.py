"""Depth maps to camera-frame 3D points, as pure functions over arrays.

Conventions: points are metres in the rectified left camera frame (OpenCV / Rerun "RDF": x right,
y down, z forward). A pixel at column ``u``, row ``v`` (integers, the pixel's centre, as OpenCV's K
assumes) with depth ``Z`` maps to ``Z * K^-1 [u, v, 1]^T``, skew included. This is also how Rerun
back-projects an ``rr.DepthImage`` under an ``rr.Pinhole`` with the same K, so the explicit cloud
and the viewer's own depth cloud coincide.

A depth value is valid when finite and > 0 (the session reader passes invalid depth on as stored: 0, NaN, inf or negative).

The viewer's cloud (:func:`depth_cloud`) keeps every pixel in a square around the selected patch
(where the gap is measured) and, elsewhere, every ``stride``-th pixel merged into voxels
(:func:`voxel_downsample`: open3d's voxel_down_sample, in NumPy).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from contact_viz.params import PatchParams, check_fields, checked
from contact_viz.geometry.patch import LAYER_INTERIOR, PatchResult

__all__ = [
    "Cloud",
    "CloudParams",
    "PatchGeometry",
    "backproject",
    "camera_rays",
    "decimated_intrinsics",
    "depth_cloud",
    "depth_preview",
    "patch_geometry",
    "sample_colors",
    "voxel_downsample",
]

FAR_SAMPLES_ACROSS = 120  # CloudParams.stride_px=None: the far part samples this many columns across the image
NEAR_POINT_RADIUS_PX = 0.6  # radius of a full-density point, in pixel footprints at its depth (touching discs)
PATCH_POINT_RADIUS_PX = 1.2  # radius of a patch point (drawn over the cloud), in pixel footprints at its depth
UINT16_MAX = np.iinfo(np.uint16).max


@dataclass(frozen=True)
class CloudParams:
    """Density of the viewer's point cloud."""

    # the near part: the square of half-side this around the patch centre, px (0 = none)
    near_radius_px: int = checked(40, ge=0)
    # keep every near_stride-th pixel of the near part along rows and columns, px (1 = all). 2: a quarter of the
    # points (27 kB a frame instead of 105 at the default radius) at 0.1 mm spacing at 10 cm, 1080p
    near_stride_px: int = checked(2, ge=1)
    # elsewhere keep every stride-th pixel along rows and columns, px (0 = no far part; None = the image width /
    # FAR_SAMPLES_ACROSS), then merge those points into voxels of voxel_m edge, m (0 = no merging). At 1080p the default
    # is 16 px / 4 mm: ~1500 points, 22 kB a frame, enough to show the tissue around the tool in 3D (6 px / 1.5 mm:
    # 11700 points, 190 kB; 12 px / 3 mm: 2700 points, 40 kB)
    stride_px: int | None = checked(None, ge=0)
    voxel_m: float = checked(0.004, ge=0)

    def __post_init__(self) -> None:
        check_fields(self)


@dataclass(frozen=True)
class Cloud:
    """A coloured camera-frame point cloud in two parts of different density."""

    near_points_m: np.ndarray  # (N, 3) float32, every valid pixel near the patch, m
    near_colors: np.ndarray  # (N, 3) uint8 RGB
    far_points_m: np.ndarray  # (M, 3) float32, the rest: strided then voxel-merged, m
    far_colors: np.ndarray  # (M, 3) uint8 RGB
    near_radius_m: float  # point radius that makes the near points touch (from their median depth), m
    far_radius_m: float  # point radius that makes the far points touch, m

    @property
    def n_points(self) -> int:
        return int(self.near_points_m.shape[0] + self.far_points_m.shape[0])


@dataclass(frozen=True)
class PatchGeometry:
    """The selected patch in 3D: the points behind its distance and the gap itself."""

    tissue_points_m: np.ndarray  # (N, 3) float32: band pixels of N2(p*) with a distance (their median = distance)
    tool_points_m: np.ndarray  # (M, 3) float32: interior pixels of N1(p*) with valid depth (their mean Z = tool depth)
    gap_origin_m: np.ndarray  # (3,) float64: the patch centre's ray at the tool depth, m
    gap_vector_m: np.ndarray  # (3,) float64: along the same ray, from the tool depth to tool depth + distance, m
    distance_m: float  # the patch distance (z component of gap_vector_m), m
    point_radius_m: float  # radius to draw the tissue and tool points with, m


# --------------------------------------------------------------------------------------------
# Basic back-projection
# --------------------------------------------------------------------------------------------


def _check_K(K: np.ndarray) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K must be a finite 3x3 camera matrix with fx, fy > 0 (px), got {K.tolist()}")
    return K


def _check_depth(depth_m: np.ndarray) -> None:
    if not isinstance(depth_m, np.ndarray) or depth_m.ndim != 2 or depth_m.dtype.kind != "f":
        raise ValueError(
            f"depth_m must be a 2-D float array (H, W) in metres, got {getattr(depth_m, 'dtype', type(depth_m))} "
            f"with shape {getattr(depth_m, 'shape', None)}"
        )


def camera_rays(K: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """K^-1 [u, v, 1] for pixel columns ``xs`` and rows ``ys`` (N,): (N, 3) float64 rays with z = 1."""
    K = _check_K(K)
    fx, skew, cx = K[0]
    fy, cy = K[1, 1], K[1, 2]
    y_n = (np.asarray(ys, dtype=np.float64) - cy) / fy
    x_n = (np.asarray(xs, dtype=np.float64) - cx - skew * y_n) / fx
    return np.stack([x_n, y_n, np.ones_like(x_n)], axis=-1)


def backproject(
    depth_m: np.ndarray,
    K: np.ndarray,
    *,
    stride: int = 1,
    box_xyxy: tuple[int, int, int, int] | None = None,
    exclude_xyxy: tuple[int, int, int, int] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points of the valid pixels on a stride grid.

    Args:
        depth_m: (H, W) float depth, m; valid = finite and > 0.
        K: (3, 3) camera matrix of the depth map, px.
        stride: keep pixels whose row and column are multiples of ``stride``.
        box_xyxy: only pixels with x0 <= x < x1 and y0 <= y < y1 (half-open, clipped to the image).
        exclude_xyxy: leave out the pixels of this half-open box.

    Returns:
        points_m (N, 3) float32 and yx (N, 2) int64 (row, column of each point), row-major order.
    """
    _check_depth(depth_m)
    height, width = depth_m.shape
    x0, y0, x1, y1 = (0, 0, width, height) if box_xyxy is None else _clip_box(box_xyxy, width, height)
    # first multiple of stride at or after the box start
    gy0, gx0 = -(-y0 // stride) * stride, -(-x0 // stride) * stride
    sub = depth_m[gy0:y1:stride, gx0:x1:stride]
    with np.errstate(invalid="ignore"):
        keep = np.isfinite(sub) & (sub > 0)
    if exclude_xyxy is not None:
        ex0, ey0, ex1, ey1 = _clip_box(exclude_xyxy, width, height)
        rows = np.arange(gy0, y1, stride)
        cols = np.arange(gx0, x1, stride)
        in_rows = (rows >= ey0) & (rows < ey1)
        in_cols = (cols >= ex0) & (cols < ex1)
        keep &= ~(in_rows[:, None] & in_cols[None, :])
    ry, rx = np.nonzero(keep)
    z = sub[ry, rx].astype(np.float64)
    ys = ry * stride + gy0
    xs = rx * stride + gx0
    points = camera_rays(K, xs, ys) * z[:, None]
    return points.astype(np.float32), np.stack([ys, xs], axis=1).astype(np.int64)


def _clip_box(box, width: int, height: int) -> tuple[int, int, int, int]:
    x0, y0, x1, y1 = (int(v) for v in box)
    return max(x0, 0), max(y0, 0), min(max(x1, 0), width), min(max(y1, 0), height)


def sample_colors(rgb: np.ndarray | None, yx: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """RGB of full-resolution pixels ``yx`` (N, 2) from ``rgb``, which may be a reduced copy of the image.

    ``rgb`` is (h, w, 3) uint8 of an image of ``image_size`` = (H, W) px, decoded at full or reduced
    size (e.g. cv2.IMREAD_REDUCED_COLOR_2); pixel (y, x) takes ``rgb[y * h // H, x * w // W]``.
    None gives mid grey. Returns (N, 3) uint8.
    """
    if rgb is None:
        return np.full((yx.shape[0], 3), 128, dtype=np.uint8)
    if rgb.ndim != 3 or rgb.shape[2] < 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be an (h, w, 3) uint8 image, got {rgb.dtype} with shape {rgb.shape}")
    height, width = image_size
    h, w = rgb.shape[:2]
    return rgb[yx[:, 0] * h // height, yx[:, 1] * w // width, :3]


def voxel_downsample(points_m: np.ndarray, colors: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge points into cubic voxels of edge ``voxel_m``: mean position and mean colour per voxel.

    open3d's ``PointCloud.voxel_down_sample``, written in NumPy with the same arithmetic (the same points and
    colours, bit for bit, in another order: by voxel): a point's voxel is ``floor((p - (min - voxel_m / 2)) /
    voxel_m)`` per axis, in float64; a voxel's point is the mean of its points, its colour the mean of their
    colours / 255, times 255, rounded. points_m (N, 3) float, m; colors (N, 3) uint8. Returns (M, 3) float32
    and (M, 3) uint8, M <= N, ordered by voxel. ``voxel_m`` <= 0 or no points returns the input (as float32 /
    uint8).
    """
    # NumPy, not open3d: importing open3d took 0.45-0.65 s of every `contact-viz view` (10% of a 150-frame 1080p
    # run; issue: live mode); the merge itself takes 0.27 ms a 1080p frame (8,000 points), as open3d's 0.28
    points_m = np.asarray(points_m)
    if voxel_m <= 0 or points_m.shape[0] == 0:
        return points_m.astype(np.float32, copy=False), np.asarray(colors, dtype=np.uint8)
    xyz = np.array(points_m.T, dtype=np.float64, order="C")  # (3, N): NumPy reduces (N, 3) along axis 0 slowly
    cells = np.floor((xyz - (xyz.min(axis=1) - voxel_m / 2)[:, None]) / voxel_m).astype(np.int64)
    dims = cells.max(axis=1) + 1
    if int(dims[0]) * int(dims[1]) * int(dims[2]) < 1 << 62:  # one int64 key per voxel
        _, inverse, counts = np.unique(np.ravel_multi_index(cells, dims), return_inverse=True, return_counts=True)
    else:
        _, inverse, counts = np.unique(cells.T, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    n = counts.shape[0]
    shades = np.array(np.asarray(colors).T, dtype=np.float64, order="C") / 255.0
    means = np.empty((6, n), np.float64)
    for axis in range(3):  # bincount adds in input order, as open3d does
        means[axis] = np.bincount(inverse, weights=xyz[axis], minlength=n)
        means[3 + axis] = np.bincount(inverse, weights=shades[axis], minlength=n)
    means /= counts
    colours = np.clip(np.rint(means[3:].T * 255.0), 0, 255)
    return np.ascontiguousarray(means[:3].T, dtype=np.float32), np.ascontiguousarray(colours, dtype=np.uint8)


# --------------------------------------------------------------------------------------------
# What the viewer draws
# --------------------------------------------------------------------------------------------


def near_box(center_xy: tuple[int, int] | None, radius_px: int, image_size: tuple[int, int]):
    """Half-open box (x0, y0, x1, y1) of half-side ``radius_px`` around ``center_xy``, clipped; None if none."""
    if center_xy is None or radius_px <= 0:
        return None
    height, width = image_size
    cx, cy = center_xy
    return _clip_box((cx - radius_px, cy - radius_px, cx + radius_px + 1, cy + radius_px + 1), width, height)


def depth_cloud(
    depth_m: np.ndarray,
    K: np.ndarray,
    rgb: np.ndarray | None = None,
    *,
    center_xy: tuple[int, int] | None = None,
    params: CloudParams = CloudParams(),
) -> Cloud:
    """The viewer's coloured cloud of one depth map.

    The valid pixels within ``params.near_radius_px`` (square) of ``center_xy`` (the selected
    patch; None = no near part) are kept every ``params.near_stride_px`` px; the other valid pixels
    are taken every ``params.stride_px`` px (0 = none, None = width / FAR_SAMPLES_ACROSS) and merged into ``params.voxel_m`` voxels. Colours come from ``rgb``
    (full or reduced size, see :func:`sample_colors`; None = grey).
    """
    _check_depth(depth_m)
    K = _check_K(K)
    box = near_box(center_xy, params.near_radius_px, depth_m.shape)
    none = np.zeros((0, 3), np.float32), np.zeros((0, 2), np.int64)
    near_points, near_yx = (backproject(depth_m, K, stride=params.near_stride_px, box_xyxy=box) if box is not None
                            else none)
    stride = params.stride_px if params.stride_px is not None else max(1, depth_m.shape[1] // FAR_SAMPLES_ACROSS)
    far_points, far_yx = backproject(depth_m, K, stride=stride, exclude_xyxy=box) if stride else none
    far_points, far_colors = voxel_downsample(far_points, sample_colors(rgb, far_yx, depth_m.shape), params.voxel_m)
    focal_px = float(np.sqrt(K[0, 0] * K[1, 1]))
    near_depth = float(np.median(near_points[:, 2])) if near_points.shape[0] else 0.0
    far_depth = float(np.median(far_points[:, 2])) if far_points.shape[0] else 0.0
    far_spacing_m = max(params.voxel_m, stride * far_depth / focal_px)
    return Cloud(
        near_points_m=near_points,
        near_colors=sample_colors(rgb, near_yx, depth_m.shape),
        far_points_m=far_points,
        far_colors=far_colors,
        near_radius_m=NEAR_POINT_RADIUS_PX * params.near_stride_px * near_depth / focal_px,
        far_radius_m=0.5 * far_spacing_m,
    )


def patch_geometry(
    depth_m: np.ndarray, K: np.ndarray, patch: PatchResult, params: PatchParams = PatchParams()
) -> PatchGeometry | None:
    """The 3D evidence behind a frame's patch distance; None when the frame has no patch.

    tissue points: the band pixels of N2(p*) whose distance d is defined (the distance is their
    median d); tool points: the interior pixels of N1(p*) with valid depth (the tool depth is
    their mean Z). The gap runs along the ray through p* from Z = tool depth to
    Z = tool depth + distance, i.e. exactly the depth difference the paper measures.
    ``params`` must be the PatchParams that produced ``patch``.
    """
    _check_depth(depth_m)
    if patch.window_xyxy is None or patch.center_xy is None:
        return None
    K = _check_K(K)
    height, width = depth_m.shape
    wx0, wy0, wx1, wy1 = patch.window_xyxy
    by, bx = patch.band_yx[:, 0], patch.band_yx[:, 1]
    in_window = np.isfinite(patch.band_distance_m) & (by >= wy0) & (by < wy1) & (bx >= wx0) & (bx < wx1)
    ty, tx = by[in_window], bx[in_window]
    tissue = camera_rays(K, tx, ty) * depth_m[ty, tx].astype(np.float64)[:, None]

    cx, cy = patch.center_xy
    half1 = params.n1 // 2
    y0, y1 = max(cy - half1, 0), min(cy + half1 + 1, height)
    x0, x1 = max(cx - half1, 0), min(cx + half1 + 1, width)
    depth_w = depth_m[y0:y1, x0:x1]
    with np.errstate(invalid="ignore"):
        tool_w = (patch.layer_ids[y0:y1, x0:x1] == LAYER_INTERIOR) & np.isfinite(depth_w) & (depth_w > 0)
    ry, rx = np.nonzero(tool_w)
    tool = camera_rays(K, rx + x0, ry + y0) * depth_w[ry, rx].astype(np.float64)[:, None]

    ray = camera_rays(K, np.array([cx]), np.array([cy]))[0]
    focal_px = float(np.sqrt(K[0, 0] * K[1, 1]))
    return PatchGeometry(
        tissue_points_m=tissue.astype(np.float32),
        tool_points_m=tool.astype(np.float32),
        gap_origin_m=ray * patch.tool_depth_m,
        gap_vector_m=ray * patch.distance_m,
        distance_m=float(patch.distance_m),
        point_radius_m=PATCH_POINT_RADIUS_PX * float(patch.tool_depth_m) / focal_px,
    )


def depth_preview(depth_m: np.ndarray, step: int, units_per_m: float) -> np.ndarray:
    """Every ``step``-th depth pixel as uint16 in 1/``units_per_m`` m (0 = invalid), for compact logging.

    Decimation by slicing (``depth_m[::step, ::step]``, no averaging, so no mixed depths at tool
    edges); use :func:`decimated_intrinsics` for its K. Values that do not fit in uint16 become 0.
    Returns (ceil(H / step), ceil(W / step)) uint16.
    """
    _check_depth(depth_m)
    scaled = depth_m[::step, ::step] * np.float32(units_per_m)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(scaled) & (scaled > 0) & (scaled <= UINT16_MAX)
    out = np.zeros(scaled.shape, dtype=np.uint16)
    out[valid] = np.rint(scaled[valid]).astype(np.uint16)
    return out


def decimated_intrinsics(K: np.ndarray, step: int) -> np.ndarray:
    """K of an image decimated as ``image[::step, ::step]``: pixel (u, v) there is (step u, step v) here.

    (step u - cx) / fx = (u - cx / step) / (fx / step), so the first two rows of K divide by ``step``.
    """
    K = _check_K(K).copy()
    K[:2] /= float(step)
    return K
