"""The minimum-distance patch: fast implementation against a slow, literal one."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

from contact_viz.params import PatchParams
from contact_viz.geometry.patch import (
    LAYER_BAND,
    LAYER_INTERIOR,
    LAYER_RING,
    LAYER_TOOL_EDGE,
    REASON_EMPTY_MASK,
    REASON_NO_BAND,
    REASON_NO_CANDIDATE,
    REASON_NO_TOOL_DEPTH,
    compute_patch,
    patch_depth_rows,
    tool_bbox,
)

SMALL = PatchParams(n1=11, n2=5, tau_tool=5, tau_patch=3, erosion_px=1.0, ring_px=1.0,
                    band_scale=0.25, band_min_px=1.0, band_max_px=2.0)


# ----------------------------------------------------------------------------------------------
# The literal version: the paper's formulas with loops, written for clarity, not speed.
# Layers come from scipy's exact Euclidean distance transform (a peer library, not cv2).
# ----------------------------------------------------------------------------------------------
def literal_patch(depth, tool, p: PatchParams):
    height, width = depth.shape
    tool = tool.astype(bool)
    if not tool.any():
        return {"reason": REASON_EMPTY_MASK}
    if tool.all():
        return {"reason": REASON_NO_BAND}
    valid = np.isfinite(depth) & (depth > 0)
    dist_in = distance_transform_edt(tool)
    dist_out = distance_transform_edt(~tool)
    # The shaft width is measured among the image's even-row, even-column pixels (2 px apart),
    # or among all pixels when the tool covers none or all of those.
    grid = tool[::2, ::2]
    if grid.any() and not grid.all():
        shaft = 2 * distance_transform_edt(grid, sampling=2).max() - 1
    else:
        shaft = 2 * dist_in.max() - 1
    band_w = min(max(p.band_scale * shaft, p.band_min_px), p.band_max_px)
    interior = tool & (dist_in > p.erosion_px)
    ring = (tool & ~interior) | (~tool & (dist_out <= p.ring_px))
    band = ~tool & (dist_out > p.ring_px) & (dist_out <= p.ring_px + band_w)

    def window(y, x, half):
        for qy in range(max(y - half, 0), min(y + half + 1, height)):
            for qx in range(max(x - half, 0), min(x + half + 1, width)):
                yield qy, qx

    band_pixels = [(int(y), int(x)) for y, x in zip(*np.nonzero(band))]  # row-major
    # The bleeding test: the tissue beyond = background within bleed_beyond_px of the band's outer edge.
    outer = tool | (dist_out <= p.ring_px + band_w)  # the tool, its ring and its band
    beyond = ~outer & (distance_transform_edt(~outer) <= p.bleed_beyond_px)
    d, z_tool, bled = {}, {}, set()
    for y, x in band_pixels:
        if not valid[y, x]:
            continue
        tool_depths = [float(depth[q]) for q in window(y, x, p.n1 // 2) if interior[q] and valid[q]]
        if len(tool_depths) >= p.tau_tool:
            z_tool[(y, x)] = sum(tool_depths) / len(tool_depths)
            d[(y, x)] = float(depth[y, x]) - z_tool[(y, x)]
            tissue = [float(depth[q]) for q in window(y, x, p.n1 // 2) if beyond[q] and valid[q]]
            if p.reject_bleeding and tissue:
                step = sum(tissue) / len(tissue) - z_tool[(y, x)]
                if step >= p.bleed_step_m and d[(y, x)] < step / 2:  # nearer the tool's depth: bled
                    del d[(y, x)]
                    bled.add((y, x))
    s = {}
    for y, x in band_pixels:
        near = [abs(d[q]) for q in window(y, x, p.n2 // 2) if q in d]
        if len(near) >= p.tau_patch:
            s[(y, x)] = sum(near) / len(near)
    out = {"interior": interior, "ring": ring, "band": band, "d": d, "s": s, "band_w": band_w, "shaft": shaft,
           "bled": bled}
    if not band_pixels:
        out["reason"] = REASON_NO_BAND
    elif not d:
        out["reason"] = "depth_bleeding" if bled else REASON_NO_TOOL_DEPTH
    elif not s:
        out["reason"] = "depth_bleeding" if bled else REASON_NO_CANDIDATE
    else:
        best = min(s, key=lambda q: s[q])  # first minimum in row-major order
        in_window = [q for q in window(*best, p.n2 // 2) if q in d]
        out.update(reason=None, best=best, score=s[best], distance=float(np.median([d[q] for q in in_window])),
                   tool_depth=sum(z_tool[q] for q in in_window) / len(in_window))
    return out


def random_frame(rng, height, width):
    """A random small frame: tissue depth, 0-3 tool blobs (some touching the border), holes."""
    yy, xx = np.mgrid[0:height, 0:width]
    tissue = 0.08 + 0.01 * np.sin(xx / 7.0) * np.cos(yy / 5.0) + rng.normal(0, 0.002, (height, width))
    depth = tissue.copy()
    tool = np.zeros((height, width), bool)
    for _ in range(rng.integers(0, 4)):
        cy, cx = rng.uniform(-3, height + 3), rng.uniform(-3, width + 3)
        ry, rx = rng.uniform(2, height / 2.5), rng.uniform(2, width / 2.5)
        angle = rng.uniform(0, np.pi)
        u = (xx - cx) * np.cos(angle) + (yy - cy) * np.sin(angle)
        v = -(xx - cx) * np.sin(angle) + (yy - cy) * np.cos(angle)
        blob = (u / rx) ** 2 + (v / ry) ** 2 <= 1
        tool |= blob
        depth[blob] = tissue[blob] - rng.uniform(0.0, 0.02) + rng.normal(0, 0.001, blob.sum())
    holes = rng.random((height, width)) < rng.uniform(0, 0.3)
    depth[holes] = rng.choice([0.0, np.nan, np.inf, -1.0], size=holes.sum())
    return depth.astype(np.float32), tool


def assert_matches_literal(depth, tool, params):
    fast = compute_patch(depth, tool, params)
    slow = literal_patch(depth.astype(np.float64), tool, params)
    assert fast.reason == slow["reason"]
    assert fast.tool_area_px == int(np.count_nonzero(tool))
    if slow["reason"] == REASON_EMPTY_MASK:
        assert not fast.layer_ids.any()
        return
    if "band" in slow:
        np.testing.assert_array_equal(fast.interior, slow["interior"])
        np.testing.assert_array_equal(fast.ring, slow["ring"])
        np.testing.assert_array_equal(fast.band, slow["band"])
        assert fast.band_width_px == pytest.approx(slow["band_w"], abs=1e-6)
        assert fast.shaft_width_px == pytest.approx(slow["shaft"], abs=1e-9)
        # d and s at every band pixel, NaN exactly where the literal version has none.
        for (y, x), d, s in zip(fast.band_yx, fast.band_distance_m, fast.band_score_m):
            key = (int(y), int(x))
            assert (key in slow["d"]) == np.isfinite(d)
            assert (key in slow["s"]) == np.isfinite(s)
            if key in slow["d"]:
                assert d == pytest.approx(slow["d"][key], abs=1e-9)
            if key in slow["s"]:
                assert s == pytest.approx(slow["s"][key], abs=1e-9)
        assert fast.n_band == len(fast.band_yx) == int(slow["band"].sum())
        assert fast.n_valid_distance == len(slow["d"])
        assert fast.n_bleeding == len(slow["bled"])
        assert fast.n_candidates == len(slow["s"])
    if slow["reason"] is None:
        assert fast.distance_m == pytest.approx(slow["distance"], abs=1e-6)
        assert fast.score_m == pytest.approx(slow["score"], abs=1e-9)
        assert fast.tool_depth_m == pytest.approx(slow["tool_depth"], abs=1e-9)
        # The chosen centre is a minimiser of the literal score (ties may break either way
        # only when scores agree to rounding; then the windows hold the same distances).
        cx, cy = fast.center_xy
        assert slow["s"][(cy, cx)] == pytest.approx(slow["score"], abs=1e-9)
        assert fast.signal == pytest.approx(-math.log10(max(abs(slow["distance"]), params.eps_m)), abs=1e-9)
    else:
        assert math.isnan(fast.distance_m) and math.isnan(fast.signal)
        assert fast.center_xy is None and fast.window_xyxy is None


# ----------------------------------------------------------------------------------------------
# Feature: agreement with the literal formulas
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(40))
def test_fast_matches_literal_small_params(seed):
    rng = np.random.default_rng(seed)
    depth, tool = random_frame(rng, int(rng.integers(20, 36)), int(rng.integers(20, 44)))
    assert_matches_literal(depth, tool, SMALL)


@pytest.mark.parametrize("seed", range(6))
def test_fast_matches_literal_paper_params(seed):
    rng = np.random.default_rng(1000 + seed)
    depth, tool = random_frame(rng, 48, 64)
    assert_matches_literal(depth, tool, PatchParams())


def test_reasons_are_all_reachable():
    """Each failure reason appears on a frame built to cause it, and agrees with the literal code."""
    depth = np.full((30, 30), 0.1, np.float32)
    empty = np.zeros((30, 30), bool)
    full = np.ones((30, 30), bool)
    tiny = empty.copy()
    tiny[14:16, 14:16] = True  # no interior survives erosion: no tool depth
    holes = depth.copy()
    blob = empty.copy()
    blob[10:20, 10:20] = True
    holes[~blob] = np.nan  # tool depth fine, but no surface depth
    for d, m, reason in [(depth, empty, REASON_EMPTY_MASK), (depth, full, REASON_NO_BAND),
                         (depth, tiny, REASON_NO_TOOL_DEPTH), (holes, blob, REASON_NO_TOOL_DEPTH)]:
        result = compute_patch(d, m, SMALL)
        assert result.reason == reason
        assert_matches_literal(d, m, SMALL)
    # Surface depth valid only on isolated pixels: d exists but never tau_patch of them together.
    sparse = depth.copy()
    sparse[~blob] = np.nan
    sparse[0, 0] = 0.1
    sparse[29, 29] = 0.1
    sparse[blob] = 0.1
    strict = PatchParams(n1=11, n2=5, tau_tool=5, tau_patch=2, erosion_px=1.0, ring_px=1.0,
                         band_scale=0.25, band_min_px=1.0, band_max_px=2.0)
    sparse[8, 8] = 0.1  # one band pixel near the tool with a valid depth
    result = compute_patch(sparse, blob, strict)
    assert result.reason == REASON_NO_CANDIDATE and result.n_valid_distance == 1
    assert_matches_literal(sparse, blob, strict)


# ----------------------------------------------------------------------------------------------
# Feature: worked examples with known answers
# ----------------------------------------------------------------------------------------------
def test_flat_tool_above_flat_tissue_gives_the_gap():
    """A tool 12 mm in front of a flat tissue plane: d = 0.012 m everywhere, signal = -log10(0.012)."""
    depth = np.full((120, 160), 0.100, np.float32)
    tool = np.zeros((120, 160), bool)
    tool[50:70, 0:90] = True  # a 20 px shaft entering from the left border
    depth[tool] = 0.088
    result = compute_patch(depth, tool)
    assert result.found
    assert result.distance_m == pytest.approx(0.012, abs=1e-6)
    assert result.signal == pytest.approx(-math.log10(0.012), abs=1e-4)
    assert result.shaft_width_px == pytest.approx(20.0, abs=1.0)
    assert result.tool_depth_m == pytest.approx(0.088, abs=1e-6)
    # All scores tie on this frame, so the first band pixel in row-major order wins, and its
    # 17x17 window is clipped at the left image border.
    cx, cy = result.center_xy
    assert result.window_xyxy == (max(cx - 8, 0), max(cy - 8, 0), min(cx + 9, 160), min(cy + 9, 120))
    assert result.invalid_depth_fraction == 0.0


def test_patch_goes_where_the_tissue_is_closest():
    """Tissue slopes away from the tool except near its tip, where it touches: distance ~ 0."""
    height, width = 120, 160
    yy, xx = np.mgrid[0:height, 0:width]
    depth = (0.10 + 0.0002 * np.abs(xx - 100)).astype(np.float32)  # closest at x = 100
    tool = np.zeros((height, width), bool)
    tool[50:70, 0:95] = True
    depth[tool] = 0.10  # tool surface at tissue depth at its tip
    result = compute_patch(depth, tool)
    cx, cy = result.center_xy
    assert cx >= 90  # beyond the tip, not along the shaft
    assert abs(result.distance_m) < 1e-3
    assert result.signal > 3.0
    touching = compute_patch(np.full((120, 160), 0.1, np.float32), tool)
    assert touching.distance_m == 0.0
    assert touching.signal == pytest.approx(4.0)  # -log10(eps) with eps = 1e-4


@pytest.mark.parametrize("seed", range(30))
def test_shaft_width_matches_literal_on_grid_edge_cases(seed):
    """Shaft width against scipy on masks that probe the 2 px grid: 1-2 px lines on odd or even
    rows and columns, shapes at odd offsets and against the image border, and full masks."""
    rng = np.random.default_rng(5000 + seed)
    height, width = int(rng.integers(9, 40)), int(rng.integers(9, 40))
    tool = np.zeros((height, width), bool)
    kind = seed % 5
    if kind == 0:  # a thin horizontal line, 1 or 2 px, on an odd or even row
        y = int(rng.integers(0, height - 2))
        tool[y:y + int(rng.integers(1, 3)), int(rng.integers(0, width // 2)):] = True
    elif kind == 1:  # a thin vertical line
        x = int(rng.integers(0, width - 2))
        tool[int(rng.integers(0, height // 2)):, x:x + int(rng.integers(1, 3))] = True
    elif kind == 2:  # a rectangle at random offsets, possibly touching the borders
        y0, x0 = int(rng.integers(0, height - 2)), int(rng.integers(0, width - 2))
        tool[y0:y0 + int(rng.integers(2, height)), x0:x0 + int(rng.integers(2, width))] = True
    elif kind == 3:  # random speckle
        tool = rng.random((height, width)) < rng.uniform(0.05, 0.95)
    else:  # everything but a few pixels
        tool[:] = True
        tool[rng.integers(0, height, 3), rng.integers(0, width, 3)] = False
    if not tool.any() or tool.all():
        tool[0, 0], tool[-1, -1] = True, False
    depth = np.full((height, width), 0.1, np.float32)
    fast = compute_patch(depth, tool, SMALL)
    assert fast.shaft_width_px == pytest.approx(literal_patch(depth.astype(np.float64), tool, SMALL)["shaft"], abs=1e-9)


def test_shaft_width_worked_example():
    """A shaft on rows 30-50 (21 px). On the 2 px grid its rows are 30, 32, ..., 50 and the nearest
    background grid rows are 28 and 52, so grid row 40 is 12 px from the background: width
    2 * 12 - 1 = 23 px (the full-resolution value is 2 * 11 - 1 = 21 px)."""
    tool = np.zeros((80, 120), bool)
    tool[30:51, 10:110] = True
    result = compute_patch(np.full((80, 120), 0.1, np.float32), tool)
    assert result.shaft_width_px == 23.0


def test_band_reach_scales_with_shaft_width():
    narrow, wide = np.zeros((200, 200), bool), np.zeros((200, 200), bool)
    narrow[95:105, :120] = True  # 10 px shaft
    wide[70:130, :120] = True  # 60 px shaft
    depth = np.full((200, 200), 0.1, np.float32)
    p = PatchParams()
    rn, rw = compute_patch(depth, narrow, p), compute_patch(depth, wide, p)
    assert rn.band_width_px == pytest.approx(p.band_min_px)
    assert rw.band_width_px == pytest.approx(min(p.band_scale * 60, p.band_max_px), abs=0.2)
    assert rw.n_band > rn.n_band


# ----------------------------------------------------------------------------------------------
# Shape, dtype and exceptions
# ----------------------------------------------------------------------------------------------
def test_output_shapes_and_dtypes():
    rng = np.random.default_rng(7)
    depth, tool = random_frame(rng, 40, 50)
    tool[10:25, 0:30] = True
    result = compute_patch(depth, tool.astype(np.uint8) * 255, SMALL)
    assert result.layer_ids.shape == (40, 50) and result.layer_ids.dtype == np.uint8
    assert set(np.unique(result.layer_ids)) <= {0, LAYER_INTERIOR, LAYER_TOOL_EDGE, LAYER_RING, LAYER_BAND}
    assert result.band_yx.shape == (result.n_band, 2)
    assert result.band_distance_m.shape == result.band_score_m.shape == (result.n_band,)
    assert result.candidates_yx.shape == (result.n_candidates, 2)
    # Integer masks mean the same as boolean ones.
    same = compute_patch(depth, tool, SMALL)
    assert same.distance_m == result.distance_m or (math.isnan(same.distance_m) and math.isnan(result.distance_m))


@pytest.mark.parametrize(
    "depth, mask, message",
    [
        (np.zeros((4, 4), np.uint16), np.zeros((4, 4), bool), "depth_m must be a 2-D float array"),
        (np.zeros((4, 4, 1), np.float32), np.zeros((4, 4), bool), "depth_m must be a 2-D float array"),
        (np.zeros((4, 4), np.float32), np.zeros((4, 5), bool), "differs from depth_m shape"),
        (np.zeros((4, 4), np.float32), np.zeros((4,), bool), "tool_mask must be a 2-D array"),
    ],
)
def test_bad_inputs_raise_naming_the_argument(depth, mask, message):
    with pytest.raises(ValueError, match=message):
        compute_patch(depth, mask)


def test_params_validation():
    with pytest.raises(ValueError, match="n1 must be an odd integer"):
        PatchParams(n1=30)
    with pytest.raises(ValueError, match="out of reach"):
        PatchParams(n1=15)
    with pytest.raises(ValueError, match="tau_patch"):
        PatchParams(tau_patch=17 * 17 + 1)


@pytest.mark.parametrize("seed", range(8))
def test_distance_grid_equals_one_call_per_parameter_set(seed):
    from itertools import product

    from contact_viz.geometry.patch import patch_distance_grid

    rng = np.random.default_rng(500 + seed)
    depth, tool = random_frame(rng, 40, 52)
    grid = [PatchParams(n1=n1, n2=n2, tau_tool=tt, tau_patch=tp, erosion_px=1.0, ring_px=1.0,
                        band_scale=0.25, band_min_px=1.0, band_max_px=2.0)
            for n1, tt, n2, tp in product((11, 15), (3, 8), (3, 5), (2, 5))]
    expected = [compute_patch(depth, tool, p).distance_m for p in grid]
    np.testing.assert_array_equal(patch_distance_grid(depth, tool, grid), expected)


@pytest.mark.parametrize("radius_px", [0.0, 1.0, 1.5, 2.0, 3.0, 4.7, 8.0, 11.0, 13.25])
def test_disc_dilation_by_rectangles_equals_disc_kernel(radius_px):
    """The staircase-of-rectangles dilation is exactly the dilation by the disc kernel."""
    import cv2

    from contact_viz.geometry.patch import _dilate_disc, _disc

    rng = np.random.default_rng(int(radius_px * 100))
    mask = (rng.random((60, 70)) < 0.02).astype(np.uint8)
    mask[20:30, 0:40] = 1  # a shaft touching the border
    np.testing.assert_array_equal(_dilate_disc(mask, radius_px), cv2.dilate(mask, _disc(radius_px)))


# ----------------------------------------------------------------------------------------------
# patch_depth_rows: the patch reads depth only in those rows (extract reads no others)


@pytest.mark.parametrize("seed", range(40))
def test_patch_on_its_depth_rows_equals_patch_on_the_frame(seed):
    rng = np.random.default_rng(seed)
    params = SMALL if seed % 2 else PatchParams()
    height, width = int(rng.integers(40, 90)), int(rng.integers(40, 90))
    depth, tool = random_frame(rng, height, width)
    whole = compute_patch(depth, tool, params)
    row0, row1 = patch_depth_rows(tool, params)
    assert row0 % 2 == 0 and 0 <= row0 <= row1 <= height
    if not tool.any():
        assert (row0, row1) == (0, 0)
    else:
        rows = np.flatnonzero(tool.any(axis=1))
        assert row0 <= rows[0] and row1 > rows[-1]
    # Depth outside the rows is never read: garbage there changes nothing.
    scrambled = depth.copy()
    scrambled[:row0] = rng.normal(size=(row0, width))
    scrambled[row1:] = np.nan
    assert compute_patch(scrambled, tool, params).distance_m == whole.distance_m or (
        math.isnan(whole.distance_m) and math.isnan(compute_patch(scrambled, tool, params).distance_m))
    band = compute_patch(depth[row0:row1], tool[row0:row1], params)
    assert band.reason == whole.reason
    for name in ("shaft_width_px", "band_width_px", "tool_area_px", "n_band", "n_valid_distance", "n_candidates", "n_bleeding",
                 "invalid_depth_fraction", "distance_m", "score_m", "tool_depth_m", "signal"):
        a, b = getattr(band, name), getattr(whole, name)
        assert a == b or (math.isnan(a) and math.isnan(b)), name
    np.testing.assert_array_equal(band.layer_ids, whole.layer_ids[row0:row1])
    assert not whole.layer_ids[:row0].any() and not whole.layer_ids[row1:].any()
    np.testing.assert_array_equal(band.band_yx + [row0, 0], whole.band_yx)
    if whole.found:
        assert (band.center_xy[0], band.center_xy[1] + row0) == whole.center_xy


def test_tool_bbox_against_numpy():
    """The tool's bounding box (cv2.boundingRect) equals the slow first/last nonzero row and column."""
    rng = np.random.default_rng(0)
    for trial in range(200):
        shape = (int(rng.integers(1, 40)), int(rng.integers(1, 150)))
        tool = (rng.random(shape) < rng.uniform(0, 0.05)).astype(np.uint8) * (1 + trial % 255)
        rows, cols = np.flatnonzero(tool.any(axis=1)), np.flatnonzero(tool.any(axis=0))
        expected = None if rows.size == 0 else (rows[0], rows[-1], cols[0], cols[-1])
        assert tool_bbox(tool) == expected
    for width in (1, 8, 65, 1920):  # a lone pixel at the first, middle and last column
        for x in {0, width // 2, width - 1}:
            tool = np.zeros((5, width), np.uint8)
            tool[3, x] = 1
            assert tool_bbox(tool) == (3, 3, x, x)
    assert tool_bbox(np.zeros((10, 70), np.uint8)) is None
