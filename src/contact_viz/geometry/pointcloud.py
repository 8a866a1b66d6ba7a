"""Depth maps to camera-frame 3D points, as pure functions over arrays.

Conventions: points are metres in the rectified left camera frame (OpenCV / Rerun "RDF": x right,
y down, z forward). A pixel at column ``u``, row ``v`` (integers, the pixel's centre, as OpenCV's K
assumes) with depth ``Z`` maps to ``Z * K^-1 [u, v, 1]^T``, skew included. This is also how Rerun
back-projects an ``rr.DepthImage`` under an ``rr.Pinhole`` with the same K, so the explicit cloud
and the viewer's own depth cloud coincide.

A depth value is valid when finite and > 0 (the session reader passes invalid depth on as stored: 0, NaN, inf or negative).

The viewer's cloud (:func:`depth_cloud`) has a dense part and a far part. The dense part keeps every
``near_stride_px``-th pixel in a square around each selected patch (where the gap is measured) and, given the
instruments' mask, every ``tool_stride_px``-th pixel of every instrument and of the tissue within
``tool_margin_m`` of it, each point labelled with its instrument's id (0 = tissue). The far part takes every
``stride``-th pixel of the rest of the tissue and merges them into voxels (:func:`voxel_downsample`: open3d's
voxel_down_sample, in NumPy).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
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
    "tool_region",
    "voxel_downsample",
]

FAR_SAMPLES_ACROSS = 120  # CloudParams.stride_px=None: the far part samples this many columns across the image
TOOL_SAMPLES_ACROSS = 120  # CloudParams.tool_stride_px=None: the instruments and their margins, columns across
NEAR_POINT_RADIUS_PX = 0.6  # radius of a dense point, in strides of pixel footprints at its depth (touching discs)
# the far points' radius, in their spacing: 0.5 made them touch, a wall of large dark spheres in the viewer's 3D view;
# smaller, the far tissue reads as a sampled surface behind the dense part near the instruments
FAR_POINT_RADIUS = 0.3
PATCH_POINT_RADIUS_PX = 1.2  # radius of a patch point (drawn over the cloud), in pixel footprints at its depth
UINT16_MAX = np.iinfo(np.uint16).max


@dataclass(frozen=True)
class CloudParams:
    """Density of the viewer's point cloud."""

    # the squares of the dense part: half-side around each patch centre, px (0 = none)
    near_radius_px: int = checked(40, ge=0)
    # keep every near_stride-th pixel of the squares along rows and columns, px (1 = all). 4: with a square per
    # instrument and the instruments' region, 55 kB a frame on the two-instrument synthetic sessions at 1080p (2: 101
    # kB; the cloud around the patch alone, before the instruments' region: 43 kB), points 0.2 mm apart at 10 cm
    near_stride_px: int = checked(4, ge=1)
    # with the instruments' mask: the tissue within this distance of an instrument joins the dense part, m, measured
    # in the image at the instrument's depth (the median over its pixels): the tissue beside it that the patch compares
    # its depth with, at the same physical width at every resolution and camera distance (3 mm: 57 px at 6 cm,
    # 1080p; 0 = the instruments only)
    tool_margin_m: float = checked(0.003, ge=0)
    # keep every tool_stride-th pixel of the instruments and their margins along rows and columns, px (None = the image
    # width / TOOL_SAMPLES_ACROSS: 16 px at 1080p, 0.8 mm apart on an instrument at 6 cm). On the synthetic sessions
    # (2 instruments; 640x360 to 1920x1080 alike) ~650 instrument and ~480 tissue points, 22-25 kB a frame with ids
    # and radii (width / 160: 1870 points, 39 kB; width / 240 at 1080p: 4270 points, 90 kB)
    tool_stride_px: int | None = checked(None, ge=1)
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

    near_points_m: np.ndarray  # (N, 3) float32, the dense part: the valid pixels on its strides, m
    near_colors: np.ndarray  # (N, 3) uint8 RGB
    far_points_m: np.ndarray  # (M, 3) float32, the rest: strided then voxel-merged, m
    far_colors: np.ndarray  # (M, 3) uint8 RGB
    # one radius for every near point: that of the coarsest stride among them at their median depth, m (0 = none)
    near_radius_m: float
    far_radius_m: float  # point radius that makes the far points touch, m (see depth_cloud)
    near_ids: np.ndarray  # (N,) uint16 object id of the instrument at each near point, 0 = tissue (or no mask)
    near_radii_m: np.ndarray  # (N,) float32 radius of each near point: touching its neighbours at its depth, m

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


def _in_boxes(rows: np.ndarray, cols: np.ndarray, boxes: Sequence[tuple[int, int, int, int]]) -> np.ndarray:
    """(len(rows), len(cols)) bool: grid pixel (rows[i], cols[j]) lies in one of the half-open ``boxes``."""
    inside = np.zeros((rows.shape[0], cols.shape[0]), dtype=bool)
    for x0, y0, x1, y1 in boxes:
        inside |= ((rows >= y0) & (rows < y1))[:, None] & ((cols >= x0) & (cols < x1))[None, :]
    return inside


def _grid(depth_m: np.ndarray, stride: int, box: tuple[int, int, int, int]):
    """Rows, columns, depth and validity of the pixels on the ``stride`` grid (multiples of it) within ``box``."""
    x0, y0, x1, y1 = box
    gy0, gx0 = -(-y0 // stride) * stride, -(-x0 // stride) * stride  # first multiples at or after the start
    sub = depth_m[gy0:y1:stride, gx0:x1:stride]
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(sub) & (sub > 0)
    return np.arange(gy0, y1, stride), np.arange(gx0, x1, stride), sub, valid


def _grid_points(K: np.ndarray, rows: np.ndarray, cols: np.ndarray, sub: np.ndarray, keep: np.ndarray):
    """Camera-frame points (N, 3) float32 and yx (N, 2) int64 of the grid pixels where ``keep``, row-major."""
    ry, rx = np.nonzero(keep)
    ys, xs = rows[ry], cols[rx]
    points = camera_rays(K, xs, ys) * sub[ry, rx].astype(np.float64)[:, None]
    return points.astype(np.float32), np.stack([ys, xs], axis=1).astype(np.int64)


def _check_tool_ids(tool_ids: np.ndarray | None, image_size: tuple[int, int]) -> np.ndarray | None:
    if tool_ids is None:
        return None
    if not isinstance(tool_ids, np.ndarray) or tool_ids.shape != tuple(image_size) or tool_ids.dtype.kind not in "ui":
        raise ValueError(
            f"tool_ids must be an integer array of the depth map's shape {tuple(image_size)} (object ids, 0 = "
            f"background), got {getattr(tool_ids, 'dtype', type(tool_ids))} with shape "
            f"{getattr(tool_ids, 'shape', None)}"
        )
    return tool_ids


def _as_ids(values: np.ndarray) -> np.ndarray:
    """Object ids as uint16; ValueError for ids outside 0..65535."""
    if values.size and values.dtype != np.uint16 and (int(values.min()) < 0 or int(values.max()) > UINT16_MAX):
        raise ValueError(
            f"tool_ids must be object ids in 0..{UINT16_MAX}, got {int(values.min())}..{int(values.max())}"
        )
    return values.astype(np.uint16)


def tool_region(
    tool_ids: np.ndarray, depth_m: np.ndarray, focal_px: float, stride: int, margin_m: float
) -> np.ndarray:
    """The instruments and their margins on the ``stride`` grid: (ceil(H / stride), ceil(W / stride)) bool.

    Grid cell (i, j) is pixel (stride i, stride j). A cell is in the region when an instrument is there
    (``tool_ids`` != 0) or when it lies within ``margin_m`` of a cell of an instrument, measured in the image
    (Euclidean, px) and converted at that instrument's depth: ``margin_m * focal_px / Z``, Z the median valid
    depth of its cells (of every valid cell when it has none).
    """
    grid = tool_ids[::stride, ::stride]
    region = grid != 0
    if margin_m <= 0 or not region.any():
        return region
    depth = depth_m[::stride, ::stride]
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(depth) & (depth > 0)
    if not valid.any():
        return region
    fallback_z = None
    for tool in np.unique(grid[region]):
        cells = grid == tool
        z = depth[cells & valid]
        if z.size:
            tool_z = float(np.median(z))
        else:
            fallback_z = float(np.median(depth[valid])) if fallback_z is None else fallback_z
            tool_z = fallback_z
        reach = margin_m * focal_px / tool_z / stride  # the margin, in cells
        # the cells of this instrument's bounding box widened by its margin: the distance transform's window
        ri, rj = np.nonzero(cells)
        pad = int(np.ceil(reach)) + 1
        i0, i1 = max(int(ri.min()) - pad, 0), min(int(ri.max()) + pad + 1, grid.shape[0])
        j0, j1 = max(int(rj.min()) - pad, 0), min(int(rj.max()) + pad + 1, grid.shape[1])
        far_from_tool = (~cells[i0:i1, j0:j1]).astype(np.uint8)
        cells_away = cv2.distanceTransform(far_from_tool, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)  # exact Euclidean
        region[i0:i1, j0:j1] |= cells_away <= reach
    return region


def depth_cloud(
    depth_m: np.ndarray,
    K: np.ndarray,
    rgb: np.ndarray | None = None,
    *,
    center_xy: tuple[int, int] | None = None,
    centers_xy: Sequence[tuple[int, int] | None] = (),
    tool_ids: np.ndarray | None = None,
    params: CloudParams = CloudParams(),
) -> Cloud:
    """The viewer's coloured cloud of one depth map.

    The dense part (``near_*``):

    - the valid pixels within ``params.near_radius_px`` (square) of ``center_xy`` and of each of
      ``centers_xy`` (the selected patches; None = no square), every ``params.near_stride_px`` px;
    - with ``tool_ids`` ((H, W) integer object ids, 0 = background; every id an instrument): outside the
      squares, the valid pixels of the :func:`tool_region` (every instrument and the tissue within
      ``params.tool_margin_m`` of it) every ``params.tool_stride_px`` px (None = width / TOOL_SAMPLES_ACROSS).

    The squares' points come first, then the tool region's, each row-major. Each near point carries the id of
    the instrument at its pixel (``near_ids``, 0 = tissue; all 0 without ``tool_ids``) and the radius that
    makes it touch its neighbours on its stride at its depth (``near_radii_m``: NEAR_POINT_RADIUS_PX x stride
    x Z / focal, with focal = sqrt(fx fy)).

    The far part: the other valid pixels every ``params.stride_px`` px (0 = none, None = width /
    FAR_SAMPLES_ACROSS) merged into ``params.voxel_m`` voxels. With ``tool_ids`` it holds tissue only: a far
    pixel on an instrument, or whose nearest tool-grid cell is in the tool region, is left out, so no voxel
    mixes an instrument's depth with the tissue's. ``far_radius_m`` is half the far points' spacing: the larger
    of the voxel edge and the stride's pixel footprint at their median depth.

    Colours come from ``rgb`` (full or reduced size, see :func:`sample_colors`; None = grey).
    """
    _check_depth(depth_m)
    K = _check_K(K)
    ids = _check_tool_ids(tool_ids, depth_m.shape)
    height, width = depth_m.shape
    focal_px = float(np.sqrt(K[0, 0] * K[1, 1]))
    boxes = [box for box in (near_box(c, params.near_radius_px, depth_m.shape) for c in (center_xy, *centers_xy))
             if box is not None]
    none = np.zeros((0, 3), np.float32), np.zeros((0, 2), np.int64)

    # the squares, row-major over the box around them all
    near_points, near_yx = none
    if boxes:
        x0s, y0s, x1s, y1s = zip(*boxes)
        around = (min(x0s), min(y0s), max(x1s), max(y1s))
        rows, cols, sub, keep = _grid(depth_m, params.near_stride_px, around)
        if len(boxes) > 1:
            keep &= _in_boxes(rows, cols, boxes)
        near_points, near_yx = _grid_points(K, rows, cols, sub, keep)
    near_strides = [(near_points.shape[0], params.near_stride_px)]

    # the instruments and their margins, outside the squares
    region = None
    if ids is not None:
        tool_stride = (params.tool_stride_px if params.tool_stride_px is not None
                       else max(1, width // TOOL_SAMPLES_ACROSS))
        region = tool_region(ids, depth_m, focal_px, tool_stride, params.tool_margin_m)
        rows, cols, sub, keep = _grid(depth_m, tool_stride, (0, 0, width, height))
        keep &= region
        if boxes:
            keep &= ~_in_boxes(rows, cols, boxes)
        tool_points, tool_yx = _grid_points(K, rows, cols, sub, keep)
        near_points = np.concatenate([near_points, tool_points])
        near_yx = np.concatenate([near_yx, tool_yx])
        near_strides.append((tool_points.shape[0], tool_stride))
    near_ids = (_as_ids(ids[near_yx[:, 0], near_yx[:, 1]]) if ids is not None
                else np.zeros(near_points.shape[0], np.uint16))

    # the far part
    stride = params.stride_px if params.stride_px is not None else max(1, width // FAR_SAMPLES_ACROSS)
    far_points, far_yx = none
    if stride:
        rows, cols, sub, keep = _grid(depth_m, stride, (0, 0, width, height))
        if boxes:
            keep &= ~_in_boxes(rows, cols, boxes)
        if ids is not None:
            keep &= ids[::stride, ::stride] == 0
            tool_stride = near_strides[-1][1]
            cell_rows = np.minimum((rows + tool_stride // 2) // tool_stride, region.shape[0] - 1)
            cell_cols = np.minimum((cols + tool_stride // 2) // tool_stride, region.shape[1] - 1)
            keep &= ~region[np.ix_(cell_rows, cell_cols)]
        far_points, far_yx = _grid_points(K, rows, cols, sub, keep)
    far_points, far_colors = voxel_downsample(far_points, sample_colors(rgb, far_yx, depth_m.shape), params.voxel_m)

    point_strides = np.repeat([s for _, s in near_strides], [n for n, _ in near_strides])
    near_radii = NEAR_POINT_RADIUS_PX * point_strides * near_points[:, 2].astype(np.float64) / focal_px
    coarsest = max((s for n, s in near_strides if n), default=params.near_stride_px)
    near_depth = float(np.median(near_points[:, 2])) if near_points.shape[0] else 0.0
    far_depth = float(np.median(far_points[:, 2])) if far_points.shape[0] else 0.0
    # voxel-merged points lie 0.9-1.0 voxel edge apart at their density (sqrt(surface area / points), measured on the
    # synthetic sessions at 3-4 mm voxels), so half the voxel edge makes them just touch
    far_spacing_m = max(params.voxel_m, stride * far_depth / focal_px)
    return Cloud(
        near_points_m=near_points,
        near_colors=sample_colors(rgb, near_yx, depth_m.shape),
        far_points_m=far_points,
        far_colors=far_colors,
        near_radius_m=NEAR_POINT_RADIUS_PX * coarsest * near_depth / focal_px,
        far_radius_m=FAR_POINT_RADIUS * far_spacing_m,
        near_ids=near_ids,
        near_radii_m=near_radii.astype(np.float32),
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
