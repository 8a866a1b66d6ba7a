"""Tests of the viewer's cloud with the instruments' mask: the dense part over every instrument and the tissue
beside it, their ids and radii, the far part of tissue only, and the cloud without a mask."""

from __future__ import annotations

import numpy as np
import pytest

from contact_viz.geometry.pointcloud import (  # noqa: I001
    FAR_POINT_RADIUS,
    FAR_SAMPLES_ACROSS,
    NEAR_POINT_RADIUS_PX,
    TOOL_SAMPLES_ACROSS,
    CloudParams,
    backproject,
    depth_cloud,
    near_box,
    sample_colors,
    tool_region,
    voxel_downsample,
)

H, W = 120, 200  # image size, px
FX, FY, CX, CY = 300.0, 310.0, 99.5, 60.25  # camera, px
K = np.array([[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]])
FOCAL = float(np.sqrt(FX * FY))
STRIP_ID, BLOCK_ID = 1, 7  # the two instruments' object ids
STRIP_Z, BLOCK_Z = 0.06, 0.08  # their depths, m


def scene() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A tilted tissue plane (8.5-10.5 cm), a shaft-like strip (id 1) coming in from the top with a rounded
    tip, a block (id 7) in the lower left, and invalid depth on both the tissue and the strip.
    Returns depth (H, W) float32 m, ids (H, W) uint16 and an RGB image (H, W, 3) uint8."""
    ys, xs = np.mgrid[0:H, 0:W]
    depth = (0.085 + 0.0001 * xs).astype(np.float32)
    ids = np.zeros((H, W), np.uint16)
    # the strip: a cylinder of radius 9 px about column 120, rows 0..70, seen side on
    across = (xs - 120) / 9.0
    strip = (np.abs(across) <= 1) & (ys <= 70)
    strip |= (xs - 120) ** 2 + (ys - 70) ** 2 <= 81
    ids[strip] = STRIP_ID
    depth[strip] = (STRIP_Z - 0.004 * np.sqrt(np.clip(1 - across[strip] ** 2, 0, 1))).astype(np.float32)
    block = (ys >= 90) & (ys < 104) & (xs >= 20) & (xs < 45)
    ids[block] = BLOCK_ID
    depth[block] = BLOCK_Z
    depth[10:14, 30:60] = np.nan  # tissue without depth
    depth[20:22, 110:130] = 0.0  # strip pixels without depth
    depth[0, 0] = -1.0
    rgb = np.stack([(xs * 255 // W), (ys * 255 // H), ((xs + ys) % 256)], axis=-1).astype(np.uint8)
    return depth, ids, rgb


def valid(depth: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.isfinite(depth) & (depth > 0)


def pixels_of(points: np.ndarray) -> np.ndarray:
    """(N, 2) int (row, column) of camera-frame points, by projecting them with K (no skew)."""
    z = points[:, 2].astype(np.float64)
    return np.stack([np.rint(points[:, 1] / z * FY + CY), np.rint(points[:, 0] / z * FX + CX)], axis=1).astype(int)


def backprojected(yx: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """The points of pixels ``yx``, computed directly: X = (x - cx) Z / fx, Y = (y - cy) Z / fy."""
    y, x = yx[:, 0].astype(np.float64), yx[:, 1].astype(np.float64)
    z = depth[yx[:, 0], yx[:, 1]].astype(np.float64)
    return np.stack([(x - CX) * z / FX, (y - CY) * z / FY, z], axis=1)


def in_margin(ids: np.ndarray, depth: np.ndarray, stride: int, margin_m: float) -> np.ndarray:
    """(H, W) bool, brute force: pixels on the stride grid within margin_m * f / Z_k (px, Euclidean) of a
    grid pixel of instrument k, Z_k the median valid depth of k's grid pixels."""
    out = np.zeros((H, W), bool)
    gy, gx = np.mgrid[0:H:stride, 0:W:stride]
    for tool in (STRIP_ID, BLOCK_ID):
        on = ids[gy, gx] == tool
        z = depth[gy[on], gx[on]]
        reach = margin_m * FOCAL / float(np.median(z[valid(z)]))
        ty, tx = gy[on], gx[on]
        d2 = (gy[..., None] - ty) ** 2 + (gx[..., None] - tx) ** 2
        out[gy, gx] |= d2.min(axis=-1) <= reach * reach
    return out


def sorted_rows(a: np.ndarray) -> np.ndarray:
    return a[np.lexsort(a.T[::-1])]


# ------------------------------------------------------------------------------------------
# The dense part
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("stride, margin_m", [(2, 0.003), (3, 0.005), (4, 0.0)])
def test_dense_part_is_every_instrument_and_the_tissue_within_the_margin(stride, margin_m):
    depth, ids, rgb = scene()
    params = CloudParams(near_radius_px=0, tool_stride_px=stride, tool_margin_m=margin_m, stride_px=0)
    cloud = depth_cloud(depth, K, rgb, tool_ids=ids, params=params)
    grid = np.zeros((H, W), bool)
    grid[::stride, ::stride] = True
    want = grid & valid(depth) & ((ids != 0) | in_margin(ids, depth, stride, margin_m))
    got = pixels_of(cloud.near_points_m)
    assert len(np.unique(got, axis=0)) == len(got)  # no pixel twice
    np.testing.assert_array_equal(sorted_rows(got), np.argwhere(want))
    # every instrument pixel on the grid with a depth is there, and the margin is tissue around them
    assert (ids[got[:, 0], got[:, 1]] != 0).sum() == (grid & valid(depth) & (ids != 0)).sum()
    if margin_m:
        assert 0 < (ids[got[:, 0], got[:, 1]] == 0).sum() < (grid & valid(depth) & (ids == 0)).sum() / 2
    else:
        assert (ids[got[:, 0], got[:, 1]] != 0).all()
    # positions are the back-projection of their pixels, colours the image's there
    np.testing.assert_allclose(cloud.near_points_m, backprojected(got, depth), rtol=1e-6, atol=0)
    np.testing.assert_array_equal(cloud.near_colors, rgb[got[:, 0], got[:, 1]])
    assert cloud.near_points_m.dtype == np.float32 and cloud.near_colors.dtype == np.uint8


def test_ids_name_the_instrument_of_each_point_and_zero_the_tissue():
    depth, ids, rgb = scene()
    cloud = depth_cloud(depth, K, rgb, center_xy=(120, 78), tool_ids=ids,
                        params=CloudParams(tool_stride_px=2, near_radius_px=12))
    assert cloud.near_ids.dtype == np.uint16 and cloud.near_ids.shape == (cloud.near_points_m.shape[0],)
    got = pixels_of(cloud.near_points_m)
    np.testing.assert_array_equal(cloud.near_ids, ids[got[:, 0], got[:, 1]])
    assert set(np.unique(cloud.near_ids).tolist()) == {0, STRIP_ID, BLOCK_ID}
    # the instruments' points at their depths, the tissue's behind them
    z = cloud.near_points_m[:, 2]
    assert np.all(z[cloud.near_ids == BLOCK_ID] == np.float32(BLOCK_Z))
    strip_z = z[cloud.near_ids == STRIP_ID]
    assert np.all((strip_z < STRIP_Z + 1e-6) & (strip_z > STRIP_Z - 0.0041))
    assert np.all(z[cloud.near_ids == 0] > 0.0849)
    # any integer mask type gives the same ids
    again = depth_cloud(depth, K, rgb, center_xy=(120, 78), tool_ids=ids.astype(np.int32),
                        params=CloudParams(tool_stride_px=2, near_radius_px=12))
    np.testing.assert_array_equal(again.near_ids, cloud.near_ids)
    np.testing.assert_array_equal(again.near_points_m, cloud.near_points_m)


def test_margin_is_measured_at_each_instruments_depth():
    depth, ids, _ = scene()
    region = tool_region(ids, depth, FOCAL, 1, 0.002)
    # 2 mm at the strip's median depth (5.7 cm) is 10.7 px; at the block's 8 cm 7.6 px
    strip_z = depth[(ids == STRIP_ID) & valid(depth)]
    reach = int(0.002 * FOCAL / float(np.median(strip_z)))
    assert reach == 10
    row = region[40]  # across the strip (columns 111..129)
    assert row[129 + reach] and not row[129 + reach + 1] and row[111 - reach] and not row[111 - reach - 1]
    column = region[:, 30]  # above and below the block (rows 90..103)
    assert column[103 + 7] and not column[103 + 8] and column[90 - 7] and not column[90 - 8]
    assert region[ids != 0].all()
    # nearer the camera, a wider band in pixels for the same margin in millimetres
    shallow = ids.copy()
    deep = depth.copy()
    deep[ids == STRIP_ID] = 0.03
    assert tool_region(shallow, deep, FOCAL, 1, 0.002).sum() > region.sum()


def test_squares_around_each_patch_centre_join_the_dense_part_at_their_stride():
    depth, ids, rgb = scene()
    params = CloudParams(near_radius_px=6, near_stride_px=1, tool_stride_px=4, tool_margin_m=0.002)
    centres = [(120, 80), (150, 20)]
    cloud = depth_cloud(depth, K, rgb, center_xy=centres[0], centers_xy=[centres[1], None], tool_ids=ids,
                        params=params)
    boxes = [near_box(c, 6, (H, W)) for c in centres]
    square = np.zeros((H, W), bool)
    for x0, y0, x1, y1 in boxes:
        square[y0:y1, x0:x1] = True
    grid = np.zeros((H, W), bool)
    grid[::4, ::4] = True
    want = (square | (grid & ((ids != 0) | in_margin(ids, depth, 4, 0.002)))) & valid(depth)
    got = pixels_of(cloud.near_points_m)
    assert len(np.unique(got, axis=0)) == len(got)
    np.testing.assert_array_equal(sorted_rows(got), np.argwhere(want))
    # the squares' points first (both squares, row-major over them), then the rest
    n_square = int((square & valid(depth)).sum())
    np.testing.assert_array_equal(got[:n_square], np.argwhere(square & valid(depth)))
    np.testing.assert_array_equal(cloud.near_ids, ids[got[:, 0], got[:, 1]])
    assert (cloud.near_ids[:n_square] == STRIP_ID).any()  # the square at the tip holds strip pixels, with their id
    # radii: each point touches its neighbours on its own stride at its own depth
    strides = np.where(np.arange(len(got)) < n_square, 1, 4)
    np.testing.assert_allclose(cloud.near_radii_m,
                               NEAR_POINT_RADIUS_PX * strides * cloud.near_points_m[:, 2] / FOCAL, rtol=1e-6)
    assert cloud.near_radii_m.dtype == np.float32
    assert cloud.near_radius_m == pytest.approx(NEAR_POINT_RADIUS_PX * 4 * np.median(cloud.near_points_m[:, 2]) / FOCAL)


# ------------------------------------------------------------------------------------------
# The far part
# ------------------------------------------------------------------------------------------


def test_far_part_is_strided_tissue_outside_the_dense_part():
    depth, ids, rgb = scene()
    params = CloudParams(near_radius_px=5, tool_stride_px=3, tool_margin_m=0.002, stride_px=5, voxel_m=0.0)
    cloud = depth_cloud(depth, K, rgb, center_xy=(60, 60), tool_ids=ids, params=params)
    # a far pixel is left out when the tool-grid pixel nearest it is in the region (instrument or margin)
    ys, xs = np.mgrid[0:H, 0:W]
    ny, nx = np.minimum((ys + 1) // 3 * 3, (H - 1) // 3 * 3), np.minimum((xs + 1) // 3 * 3, (W - 1) // 3 * 3)
    nearest = (ids[ny, nx] != 0) | in_margin(ids, depth, 3, 0.002)[ny, nx]
    x0, y0, x1, y1 = near_box((60, 60), 5, (H, W))
    square = (ys >= y0) & (ys < y1) & (xs >= x0) & (xs < x1)
    grid = (ys % 5 == 0) & (xs % 5 == 0)
    want = grid & valid(depth) & (ids == 0) & ~nearest & ~square
    got = pixels_of(cloud.far_points_m)
    np.testing.assert_array_equal(got, np.argwhere(want))  # row-major, without merging
    np.testing.assert_allclose(cloud.far_points_m, backprojected(got, depth), rtol=1e-6, atol=0)
    np.testing.assert_array_equal(cloud.far_colors, rgb[got[:, 0], got[:, 1]])
    assert (ids[got[:, 0], got[:, 1]] == 0).all()  # no instrument pixel in the far part
    # no pixel both near and far
    near = {tuple(p) for p in pixels_of(cloud.near_points_m).tolist()}
    assert not near & {tuple(p) for p in got.tolist()}
    # merged into voxels: the same strided points, voxel-merged
    merged = depth_cloud(depth, K, rgb, center_xy=(60, 60), tool_ids=ids,
                         params=CloudParams(near_radius_px=5, tool_stride_px=3, tool_margin_m=0.002, stride_px=5,
                                            voxel_m=0.004))
    want_p, want_c = voxel_downsample(cloud.far_points_m, cloud.far_colors, 0.004)
    np.testing.assert_array_equal(merged.far_points_m, want_p)
    np.testing.assert_array_equal(merged.far_colors, want_c)
    assert merged.far_points_m.shape[0] < cloud.far_points_m.shape[0] / 2
    # FAR_POINT_RADIUS of the spacing: the voxel edge here (a 5 px stride is 1.5 mm at 9 cm)
    assert merged.far_radius_m == pytest.approx(FAR_POINT_RADIUS * 0.004)
    z = float(np.median(cloud.far_points_m[:, 2]))
    assert cloud.far_radius_m == pytest.approx(FAR_POINT_RADIUS * 5 * z / FOCAL)


@pytest.mark.parametrize("width", [480, 1000])
def test_default_strides_scale_with_the_image_width(width):
    depth = np.full((H, width), 0.09, np.float32)
    ids = np.zeros((H, width), np.uint16)
    ids[30:70, 100:160] = 2
    depth[ids == 2] = 0.06
    K_wide = np.array([[FX, 0.0, width / 2], [0.0, FY, CY], [0.0, 0.0, 1.0]])
    cloud = depth_cloud(depth, K_wide, tool_ids=ids, params=CloudParams(tool_margin_m=0.0, voxel_m=0.0))
    stride, far_stride = width // TOOL_SAMPLES_ACROSS, width // FAR_SAMPLES_ACROSS
    assert stride > 1 and far_stride > 1
    z = cloud.near_points_m[:, 2].astype(np.float64)
    xs = np.rint(cloud.near_points_m[:, 0] / z * FX + width / 2).astype(int)
    ys = np.rint(cloud.near_points_m[:, 1] / z * FY + CY).astype(int)
    assert sorted(zip(ys.tolist(), xs.tolist())) == [(y, x) for y in range(30, 70) for x in range(100, 160)
                                                     if y % stride == 0 and x % stride == 0]
    assert (cloud.near_ids == 2).all()
    z = cloud.far_points_m[:, 2].astype(np.float64)
    far_x = np.rint(cloud.far_points_m[:, 0] / z * FX + width / 2).astype(int)
    assert (far_x % far_stride == 0).all() and np.all(z == np.float32(0.09))


# ------------------------------------------------------------------------------------------
# Without a mask, and bad input
# ------------------------------------------------------------------------------------------


def todays_cloud(depth, K, rgb, center_xy, params):
    """The cloud without a mask, written out from the building blocks: the square every near_stride_px px,
    the rest every stride px merged into voxels; radii from the median depths."""
    box = near_box(center_xy, params.near_radius_px, depth.shape)
    empty = np.zeros((0, 3), np.float32), np.zeros((0, 2), np.int64)
    near, near_yx = backproject(depth, K, stride=params.near_stride_px, box_xyxy=box) if box else empty
    stride = params.stride_px if params.stride_px is not None else max(1, depth.shape[1] // FAR_SAMPLES_ACROSS)
    far, far_yx = backproject(depth, K, stride=stride, exclude_xyxy=box) if stride else empty
    far, far_colors = voxel_downsample(far, sample_colors(rgb, far_yx, depth.shape), params.voxel_m)
    focal = float(np.sqrt(K[0, 0] * K[1, 1]))
    near_z = float(np.median(near[:, 2])) if len(near) else 0.0
    far_z = float(np.median(far[:, 2])) if len(far) else 0.0
    return dict(near_points_m=near, near_colors=sample_colors(rgb, near_yx, depth.shape), far_points_m=far,
                far_colors=far_colors, near_radius_m=NEAR_POINT_RADIUS_PX * params.near_stride_px * near_z / focal,
                far_radius_m=FAR_POINT_RADIUS * max(params.voxel_m, stride * far_z / focal))


@pytest.mark.parametrize("params", [
    CloudParams(),
    CloudParams(near_radius_px=10, near_stride_px=1, stride_px=2, voxel_m=0.001),
    CloudParams(near_radius_px=0),
    CloudParams(stride_px=0),
    CloudParams(near_stride_px=3, stride_px=7, voxel_m=0.0),
])
@pytest.mark.parametrize("center_xy", [(120, 78), None, (3, 2), (W - 1, H + 5)])
def test_without_a_mask_the_cloud_is_the_square_and_the_voxels(params, center_xy):
    depth, ids, rgb = scene()
    cloud = depth_cloud(depth, K, rgb[::2, ::2], center_xy=center_xy, params=params)
    want = todays_cloud(depth, K, rgb[::2, ::2], center_xy, params)
    for name, value in want.items():
        got = getattr(cloud, name)
        if isinstance(value, np.ndarray):
            assert got.dtype == value.dtype and got.shape == value.shape, name
            np.testing.assert_array_equal(got, value, err_msg=name)
        else:
            assert got == value, name
    assert cloud.near_ids.dtype == np.uint16 and not cloud.near_ids.any()
    assert cloud.near_ids.shape == (cloud.near_points_m.shape[0],)
    np.testing.assert_allclose(cloud.near_radii_m, NEAR_POINT_RADIUS_PX * params.near_stride_px
                               * cloud.near_points_m[:, 2] / FOCAL, rtol=1e-6)


def test_a_frame_without_instruments_or_without_depth():
    depth, ids, rgb = scene()
    none = np.zeros_like(ids)
    with_empty_mask = depth_cloud(depth, K, rgb, center_xy=(60, 60), tool_ids=none)
    plain = depth_cloud(depth, K, rgb, center_xy=(60, 60))
    np.testing.assert_array_equal(with_empty_mask.near_points_m, plain.near_points_m)
    np.testing.assert_array_equal(with_empty_mask.far_points_m, plain.far_points_m)
    no_depth = depth_cloud(np.full((H, W), np.nan, np.float32), K, rgb, center_xy=(60, 60), tool_ids=ids)
    assert no_depth.n_points == 0 and no_depth.near_ids.shape == (0,) and no_depth.near_radii_m.shape == (0,)
    assert no_depth.near_radius_m == 0.0


def test_bad_masks_are_refused():
    depth, ids, _ = scene()
    with pytest.raises(ValueError, match="tool_ids must be an integer array of the depth map's shape"):
        depth_cloud(depth, K, tool_ids=ids[:-1])
    with pytest.raises(ValueError, match="tool_ids must be an integer array"):
        depth_cloud(depth, K, tool_ids=ids.astype(np.float32))
    big = ids.astype(np.int32)
    big[ids == BLOCK_ID] = 70000
    with pytest.raises(ValueError, match="tool_ids must be object ids in 0..65535"):
        depth_cloud(depth, K, tool_ids=big)


def test_no_instrument_pixel_is_ever_far():
    depth, ids, rgb = scene()
    # without a margin the tool grid's cells leave instrument pixels between them: those are left out too
    cloud = depth_cloud(depth, K, rgb, tool_ids=ids,
                        params=CloudParams(tool_stride_px=6, tool_margin_m=0.0, stride_px=1, voxel_m=0.0))
    far = pixels_of(cloud.far_points_m)
    assert (ids[far[:, 0], far[:, 1]] == 0).all()
    # and the tissue there is all far, but for the pixels nearest a tool-grid cell on an instrument
    ys, xs = np.mgrid[0:H, 0:W]
    ny, nx = np.minimum((ys + 3) // 6 * 6, (H - 1) // 6 * 6), np.minimum((xs + 3) // 6 * 6, (W - 1) // 6 * 6)
    np.testing.assert_array_equal(far, np.argwhere(valid(depth) & (ids == 0) & (ids[ny, nx] == 0)))
