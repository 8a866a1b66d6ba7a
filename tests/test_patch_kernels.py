"""The compiled kernels of patch.py, each against the NumPy/OpenCV expression it replaces.

(compute_patch as a whole is checked against the literal formulas in test_patch.py.)
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from contact_viz.geometry import _patch_kernels as kernels
from contact_viz.geometry.patch import (LAYER_BACKGROUND, LAYER_BAND, LAYER_INTERIOR, LAYER_RING, LAYER_TOOL_EDGE, _dilate_disc,
                               _disc)

IDS = (LAYER_BACKGROUND, LAYER_INTERIOR, LAYER_TOOL_EDGE, LAYER_RING, LAYER_BAND)


def random_mask(rng, shape, p=0.5, blobs=True):
    if blobs:
        mask = np.zeros(shape, np.uint8)
        for _ in range(rng.integers(1, 4)):
            y, x = rng.integers(0, shape[0]), rng.integers(0, shape[1])
            cv2.circle(mask, (int(x), int(y)), int(rng.integers(1, max(2, min(shape) // 3))), 1, -1)
        return mask
    return (rng.random(shape) < p).astype(np.uint8)


# --------------------------------------------------------------------------------------- fuse_layers


def layers_by_numpy(tool, depth, ring=3.0, outer=7.0, erosion=2.0):
    """The masks and the NumPy/OpenCV form of everything fuse_layers returns."""
    interior = cv2.erode(tool, _disc(erosion))
    near = _dilate_disc(tool, ring)
    far = _dilate_disc(tool, outer)
    layer = np.zeros(tool.shape, np.uint8)
    layer[far == 1] = LAYER_BAND
    layer[near == 1] = LAYER_RING
    layer[tool == 1] = LAYER_TOOL_EDGE
    layer[interior == 1] = LAYER_INTERIOR
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(depth) & (depth > 0)
    band = (far == 1) & (near == 0)
    taken = (interior == 1) & valid
    expected = dict(
        layer=layer,
        band_flat=np.flatnonzero(band),
        band_valid=valid.ravel()[np.flatnonzero(band)].astype(np.uint8),
        tool_sum=cv2.integral(np.where(taken, depth, 0).astype(np.float64), sdepth=cv2.CV_64F),
        tool_cnt=cv2.integral(taken.astype(np.uint8), sdepth=cv2.CV_32S),
    )
    return (interior, near, far), expected


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_fuse_layers_against_numpy(dtype):
    rng = np.random.default_rng(1)
    for _ in range(30):
        shape = (int(rng.integers(5, 60)), int(rng.integers(5, 80)))
        tool = random_mask(rng, shape)
        depth = rng.uniform(0.05, 0.1, shape).astype(dtype)
        depth[rng.random(shape) < 0.1] = np.nan
        depth[rng.random(shape) < 0.05] = 0
        depth[rng.random(shape) < 0.02] = -np.inf
        (interior, near, far), expected = layers_by_numpy(tool, depth)
        layer = np.full(shape, 99, np.uint8)
        band_flat, band_valid, tool_sum, tool_cnt, area = kernels.fuse_layers(tool, interior, near, far, depth,
                                                                             layer, *IDS)
        assert area == tool.sum()
        np.testing.assert_array_equal(layer, expected["layer"])
        np.testing.assert_array_equal(band_flat, expected["band_flat"])
        np.testing.assert_array_equal(band_valid, expected["band_valid"])
        np.testing.assert_array_equal(tool_cnt, expected["tool_cnt"])
        np.testing.assert_allclose(tool_sum, expected["tool_sum"], rtol=0, atol=1e-12)
        assert band_flat.dtype == np.int64 and tool_sum.shape == (shape[0] + 1, shape[1] + 1)


def test_fuse_layers_writes_into_strided_views():
    # The depth crop and the layer image are views into full frames (rows contiguous).
    rng = np.random.default_rng(2)
    tool = random_mask(rng, (30, 40))
    full_depth = rng.uniform(0.05, 0.1, (50, 70)).astype(np.float32)
    full_layer = np.zeros((50, 70), np.uint8)
    depth = full_depth[10:40, 20:60]
    (interior, near, far), expected = layers_by_numpy(tool, depth)
    kernels.fuse_layers(tool, interior, near, far, depth, full_layer[10:40, 20:60], *IDS)
    np.testing.assert_array_equal(full_layer[10:40, 20:60], expected["layer"])
    assert full_layer[:10].sum() == 0 and full_layer[:, :20].sum() == 0


def test_fuse_layers_errors():
    m = np.zeros((6, 8), np.uint8)
    d = np.ones((6, 8), np.float32)
    with pytest.raises(ValueError, match="same"):
        kernels.fuse_layers(m, m, m, np.zeros((6, 9), np.uint8), d, m.copy(), *IDS)
    with pytest.raises(ValueError, match="contiguous along their rows"):
        kernels.fuse_layers(m, m, m, m, np.ones((6, 16), np.float32)[:, ::2], m.copy(), *IDS)
    with pytest.raises(TypeError):
        kernels.fuse_layers(m, m, m, m, d.astype(np.float16), m.copy(), *IDS)


# ---------------------------------------------------------------------------- band_distances / sums


def test_band_distances_against_brute_force():
    rng = np.random.default_rng(3)
    for half, tau in ((1, 1), (3, 5), (15, 30)):
        shape = (40, 50)
        tool = random_mask(rng, shape)
        depth = rng.uniform(0.05, 0.1, shape)
        depth[rng.random(shape) < 0.1] = np.nan
        (interior, near, far), _ = layers_by_numpy(tool, depth)
        layer = np.zeros(shape, np.uint8)
        band_flat, band_valid, tool_sum, tool_cnt, _ = kernels.fuse_layers(tool, interior, near, far, depth, layer,
                                                                          *IDS)
        band_d, tool_mean = kernels.band_distances(tool_sum, tool_cnt, band_flat, band_valid, depth, half, tau)
        taken = (interior == 1) & np.isfinite(depth)
        for i, flat in enumerate(band_flat):
            y, x = divmod(int(flat), shape[1])
            window = (slice(max(y - half, 0), y + half + 1), slice(max(x - half, 0), x + half + 1))
            values = depth[window][taken[window]]
            if values.size < tau:
                assert np.isnan(tool_mean[i]) and np.isnan(band_d[i])
                continue
            assert tool_mean[i] == pytest.approx(values.mean(), abs=1e-12)
            expected = depth[y, x] - values.mean() if band_valid[i] else np.nan
            np.testing.assert_allclose(band_d[i], expected, atol=1e-12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_ring_depth_integrals_against_opencv(dtype):
    """Bit-equal to what patch.py did before the kernel: subtract, mask the valid depth, two cv2.integral."""
    rng = np.random.default_rng(8)
    for _ in range(20):
        shape = (int(rng.integers(3, 50)), int(rng.integers(3, 70)))
        inner = random_mask(rng, shape)
        outer = _dilate_disc(inner, float(rng.uniform(1, 6)))
        depth = rng.uniform(0.02, 0.2, shape).astype(dtype)
        depth[rng.random(shape) < 0.1] = np.nan
        depth[rng.random(shape) < 0.05] = 0.0
        depth[rng.random(shape) < 0.05] = -np.inf
        ring = cv2.subtract(outer, inner)
        with np.errstate(invalid="ignore"):
            ok = (ring != 0) & np.isfinite(depth) & (depth > 0)
        sums, counts = kernels.ring_depth_integrals(outer, inner, depth)
        np.testing.assert_array_equal(sums, cv2.integral(np.where(ok, depth, dtype(0)), sdepth=cv2.CV_64F))
        np.testing.assert_array_equal(counts, cv2.integral(ok.view(np.uint8), sdepth=cv2.CV_32S))
    with pytest.raises(ValueError):
        kernels.ring_depth_integrals(np.zeros((4, 5), np.uint8), np.zeros((4, 6), np.uint8), np.ones((4, 5)))


def test_reject_bled_against_numpy():
    """The bleeding test's rule, per band pixel, against its NumPy form (window means from a brute-force loop)."""
    rng = np.random.default_rng(9)
    shape = (30, 40)
    for half, step_m in ((1, 0.004), (4, 0.01), (15, 0.004)):
        beyond = (rng.random(shape) < 0.3).astype(np.uint8)
        depth = rng.uniform(0.05, 0.1, shape)
        sums, counts = kernels.ring_depth_integrals(beyond, np.zeros(shape, np.uint8), depth)
        band_flat = np.flatnonzero(rng.random(shape) < 0.4).astype(np.int64)
        n = band_flat.size
        tool_mean = rng.uniform(0.03, 0.08, n)
        tool_mean[rng.random(n) < 0.1] = np.nan
        band_d = rng.uniform(-0.01, 0.05, n)
        band_d[rng.random(n) < 0.1] = np.nan
        beyond_mean = np.full(n, np.nan)
        for i, flat in enumerate(band_flat):
            y, x = divmod(int(flat), shape[1])
            window = (slice(max(y - half, 0), y + half + 1), slice(max(x - half, 0), x + half + 1))
            if beyond[window].any():
                beyond_mean[i] = depth[window][beyond[window] == 1].mean()
        step = beyond_mean - tool_mean
        with np.errstate(invalid="ignore"):
            bled = (step >= step_m) & (band_d < step / 2)
        expected = np.where(bled, np.nan, band_d)
        got = band_d.copy()
        assert kernels.reject_bled(sums, counts, band_flat, got, tool_mean, half, step_m) == bled.sum() > 0
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-15)
        np.testing.assert_array_equal(np.isnan(got), np.isnan(expected))


def test_band_window_sums_against_brute_force():
    rng = np.random.default_rng(4)
    shape = (25, 33)
    for half in (0, 2, 8):
        band_flat = np.flatnonzero(rng.random(shape) < 0.3)
        band_d = rng.normal(0, 0.01, band_flat.size)
        band_d[rng.random(band_flat.size) < 0.2] = np.nan
        count, total = kernels.band_window_sums(band_flat, band_d, *shape, half)
        image_abs = np.zeros(shape)
        image_has = np.zeros(shape, int)
        ys, xs = np.divmod(band_flat, shape[1])
        ok = np.isfinite(band_d)
        image_abs[ys[ok], xs[ok]] = np.abs(band_d[ok])
        image_has[ys[ok], xs[ok]] = 1
        for i, (y, x) in enumerate(zip(ys, xs)):
            window = (slice(max(y - half, 0), y + half + 1), slice(max(x - half, 0), x + half + 1))
            assert count[i] == image_has[window].sum()
            assert total[i] == pytest.approx(image_abs[window].sum(), abs=1e-12)


def test_band_window_sums_errors():
    with pytest.raises(ValueError, match="increasing"):
        kernels.band_window_sums(np.array([3, 1], np.int64), np.zeros(2), 4, 4, 1)
    with pytest.raises(ValueError, match="values for"):
        kernels.band_window_sums(np.array([1, 3], np.int64), np.zeros(3), 4, 4, 1)
    with pytest.raises(ValueError, match="4x4"):
        kernels.band_window_sums(np.array([1, 16], np.int64), np.zeros(2), 4, 4, 1)
    count, total = kernels.band_window_sums(np.zeros(0, np.int64), np.zeros(0), 4, 4, 1)
    assert count.shape == (0,) and total.shape == (0,)


def test_window_members_against_brute_force():
    rng = np.random.default_rng(5)
    shape = (30, 41)
    for half in (0, 1, 4, 8):
        band_flat = np.flatnonzero(rng.random(shape) < 0.4)
        band_d = rng.normal(0, 0.01, band_flat.size)
        band_d[rng.random(band_flat.size) < 0.2] = np.nan
        ys, xs = np.divmod(band_flat, shape[1])
        for center in range(band_flat.size):
            expected = np.flatnonzero(np.isfinite(band_d) & (np.abs(ys - ys[center]) <= half)
                                      & (np.abs(xs - xs[center]) <= half))
            np.testing.assert_array_equal(kernels.window_members(band_flat, band_d, shape[1], center, half), expected)


def test_window_members_errors():
    flat = np.array([1, 5, 9], np.int64)
    with pytest.raises(IndexError):
        kernels.window_members(flat, np.zeros(3), 4, 3, 1)
    with pytest.raises(ValueError, match="values for"):
        kernels.window_members(flat, np.zeros(2), 4, 0, 1)
