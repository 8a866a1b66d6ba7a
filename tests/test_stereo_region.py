"""SGBM depth only where the patch reads it (contact_viz.geometry.stereo_region): the region, the tiles'
search ranges, the coarse pass, and the depth at 1280x720 and 1920x1080 against the exact depth."""

from __future__ import annotations

import numpy as np
import pytest

from contact_viz.geometry.occlusion import half_occluded
from contact_viz.geometry.patch import compute_patch
from contact_viz.geometry.stereo import SGBMParams, disparity_to_depth, sgbm_disparity
from contact_viz.geometry.stereo_region import _search_range, _tiles, coarse_disparity, fine_region, region_sgbm_disparity
from contact_viz.params import PatchParams


def test_fine_region_against_brute_force():
    rng = np.random.default_rng(4)
    tool = np.zeros((40, 60), bool)
    tool[rng.integers(0, 40, 6), rng.integers(0, 60, 6)] = True
    tool[10:14, 20:35] = True
    ys, xs = np.nonzero(tool)
    yy, xx = np.mgrid[0:40, 0:60]
    nearest = np.min((yy[..., None] - ys) ** 2 + (xx[..., None] - xs) ** 2, axis=-1)
    for radius in (0, 1, 3, 7):
        assert np.array_equal(fine_region(tool, radius), nearest <= radius * radius)
    assert not fine_region(np.zeros((5, 5), bool), 3).any()


def test_search_range_worked_example():
    p = SGBMParams(range_margin_px=4).resolve(640)  # 80 disparities from 0
    # 40.2 .. 47.9 -> floor 40 - 4 = 36 .. ceil 48 + 4 = 52: 17 disparities, rounded up to 32.
    assert _search_range(np.array([47.9, np.nan, 40.2, 44.0]), p) == (36, 32)
    assert _search_range(np.array([np.nan]), p) == (0, 80)  # nothing known: the whole range
    assert _search_range(np.array([1.0, 78.5]), p) == (0, 80)  # clipped to the whole range
    # The whole range from the calibration (the synthetic camera at 1080p: 192 disparities at 960 px) caps it:
    # 150.0 .. 190.0 -> 146 .. min(194, 191) = 191: 46 disparities -> 48.
    p = SGBMParams(range_margin_px=4).resolve(1920, fx_px=960 / np.tan(np.radians(40)), baseline_m=0.005)
    assert p.num_disparities == 192
    assert _search_range(np.array([150.0, 190.0]), p) == (146, 48)


def test_tiles_cover_the_region_row_by_row():
    region = np.zeros((100, 80), bool)
    for y in range(10, 90):  # a diagonal band
        region[y, y // 2:y // 2 + 12] = True
    tiles = _tiles(region, 16)
    assert [t[:2] for t in tiles] == [(y, min(y + 16, 100)) for y in range(10, 90, 16)]
    covered = np.zeros_like(region)
    for y0, y1, x0, x1 in tiles:
        rows = region[y0:y1]
        cols = np.flatnonzero(rows.any(axis=0))
        assert (x0, x1) == (cols[0], cols[-1] + 1)
        covered[y0:y1, x0:x1] = True
    assert not (region & ~covered).any()


D_BG, D_BOX = 20, 52  # disparities of the plane and the box at full resolution, px


def box_pair(height=360, width=1280, seed=0, d_bg=D_BG, d_box=D_BOX, box=(100, 260, 500, 700)):
    """A textured plane (disparity d_bg) and a textured box in front of it (d_box) on rows y0..y1-1 and columns
    x0..x1-1 of the left view (``box``); texture in 2x2 px cells so that it survives matching at half size.
    Returns (left, right, box mask)."""
    rng = np.random.default_rng(seed)
    pad = d_box + 2
    cells = lambda lo: np.repeat(np.repeat(rng.integers(lo, 256, (height // 2 + 1, (width + 2 * pad) // 2 + 1, 3),
                                                        dtype=np.uint8), 2, 0), 2, 1)[:height, :width + 2 * pad]
    plane, box_tex = cells(0), cells(150)
    y0, y1, x0, x1 = box
    left = plane[:, pad:pad + width].copy()
    right = plane[:, pad + d_bg:pad + d_bg + width].copy()
    left[y0:y1, x0:x1] = box_tex[y0:y1, pad + x0:pad + x1]
    right[y0:y1, x0 - d_box:x1 - d_box] = box_tex[y0:y1, pad + x0:pad + x1]
    tool = np.zeros((height, width), bool)
    tool[y0:y1, x0:x1] = True
    return left, right, tool


def test_region_disparity_on_a_box_at_half_size():
    left, right, tool = box_pair()
    params = SGBMParams(region_px=24)
    assert params.resolve(1280).downscale == 2
    result = region_sgbm_disparity(left, right, tool, params)
    disparity, fine = result.disparity_px, result.fine
    assert np.array_equal(fine, fine_region(tool, 24))
    # On the box: its own disparity; beside it, right of it and above/below, the plane's, not the box's.
    inner = np.zeros_like(tool)
    inner[110:250, 510:690] = True
    assert np.isfinite(disparity[inner]).mean() > 0.9
    assert np.nanmedian(np.abs(disparity[inner] - D_BOX)) <= 0.5
    beside = fine & ~tool
    beside[:, :500] = False  # left of the box the plane is hidden behind it in the right view (32 px)
    valid = beside & np.isfinite(disparity)
    assert valid.sum() > 0.6 * beside.sum()
    assert np.mean(np.abs(disparity[valid] - D_BG) <= 1.0) > 0.98
    # Outside the region: the coarse pass (the plane, 1/16 px steps of the coarse scale).
    outside = ~fine & np.isfinite(disparity)
    assert outside.sum() > 0.8 * (~fine).sum()
    assert np.mean(np.abs(disparity[outside] - D_BG) <= 2.0) > 0.95


def test_a_near_box_beyond_the_width_rule_is_found_with_the_calibrated_range():
    """A box at disparity 200 px over a plane at 40 (1280 px wide, matched at 640: 100 and 20 px). The width rule
    searches 1/8 of 640 = 80 px and misses it; the calibration (fx 1000 px, baseline 4 mm, nearest 15 mm: 266.7
    px, 133.3 at 640 -> 144 disparities) reaches it, in the coarse pass and the tiles. Left of the box the plane
    is hidden from the right camera over 200 - 40 = 160 px (columns 340-499): no depth there."""
    left, right, tool = box_pair(d_bg=40, d_box=200)
    inner = np.zeros_like(tool)
    inner[110:250, 510:690] = True
    calibrated = SGBMParams().resolve(1280, fx_px=1000.0, baseline_m=0.004)
    assert calibrated.num_disparities == 144 and SGBMParams().resolve(1280).num_disparities == 80
    found = {}
    for name, params in (("calibrated", calibrated), ("width", SGBMParams())):
        disparity = region_sgbm_disparity(left, right, tool, params).disparity_px
        found[name] = np.mean(np.abs(disparity[inner] - 200) <= 2)  # NaN counts as not found
        if name == "calibrated":
            strip = np.zeros_like(tool)
            strip[100:260, 340:500] = True
            assert np.isfinite(disparity[strip]).mean() < 0.02
            strips = half_occluded(disparity, tool)  # the strip found from the result itself: all but its
            assert (np.isfinite(disparity) & strips).sum() <= 0.01 * strips.sum()  # edges (coarse pixels) empty
            right_of = np.zeros_like(tool)
            right_of[110:250, 705:724] = True  # visible to both: the plane
            assert np.nanmedian(np.abs(disparity[right_of] - 40)) <= 1.0
    assert found["calibrated"] > 0.9 and found["width"] < 0.1


def test_no_instrument_in_view_matches_the_whole_frame():
    """An empty mask, or region off, skips the coarse pass and the tiles: plain SGBM over the whole frame."""
    left, right, tool = (a[:, 320:960].copy() for a in box_pair())  # 640 px: matched as it is
    assert tool.any()
    empty = np.zeros_like(tool)
    result = region_sgbm_disparity(left, right, empty, SGBMParams())
    assert result.fine.all()
    np.testing.assert_array_equal(result.disparity_px, sgbm_disparity(left, right, SGBMParams()))
    assert region_sgbm_disparity(left, right, tool, SGBMParams(region=False)).fine.all()


def test_coarse_pass_scales_the_search_range():
    left, right, _ = box_pair()
    small_params = SGBMParams().resolve(1280)  # matching at 640 px, 80 disparities
    disparity, n = coarse_disparity(left[::2, ::2].copy(), right[::2, ::2].copy(), small_params)
    assert n == 2  # 640 px matched at <= 480 px: halved
    assert disparity.shape == (90, 320)
    plane = np.isfinite(disparity[:, :200])
    assert np.median(np.abs(disparity[:, :200][plane] - D_BG / 2)) <= 1.0  # in the pixels of the 640 px pair


@pytest.fixture(scope="module", params=[(1280, 720), (1920, 1080)], ids=["720p", "1080p"])
def synth_frame(request, tmp_path_factory):
    """One frame of a seeded synthetic session at 720p or 1080p (tool hovering over the cup) and its exact depth."""
    from contact_viz.io.decoders import read_rgb
    from contact_viz.io.session import open_session
    from contact_viz.synth import SynthParams, generate_session, true_depth

    width, height = request.param
    params = SynthParams(phantom="cup", frames=1, seed=3, width=width, height=height)
    root = generate_session(tmp_path_factory.mktemp("synth") / "s", params)
    session = open_session(root)
    tool = session.load_frame(0, ("mask",)).tool_mask != 0
    truth = true_depth(params, [0])[0]
    left, right = read_rgb(next((root / "left").iterdir())), read_rgb(next((root / "right").iterdir()))
    return left, right, tool, np.where(truth > 0, truth, np.nan).astype(np.float32), session.calibration


def test_band_depth_at_the_papers_resolution(synth_frame):
    """The exterior band against the exact depth at 720p and 1080p: matched at full size (the default
    before the matching width), most of the band went unmatched at 1080p; now it is measured as at
    640x360, and the patch reads no coarse pixel."""
    left, right, tool, truth, calibration = synth_frame
    band = compute_patch(truth, tool).band

    def depth_of(params):
        result = region_sgbm_disparity(left, right, tool, params)
        return disparity_to_depth(result.disparity_px, calibration.fx, calibration.baseline_m), result.fine

    # Measured (band valid / both cameras see it / valid within 3 mm): 640x360 0.53 / 0.57 / 0.994;
    # 1280x720 0.46 / 0.54 / 0.980 (full size: 0.25 valid); 1920x1080 0.35 / 0.53 / 0.995 (full size: 0.18).
    depth, fine = depth_of(SGBMParams())
    valid = band & np.isfinite(depth) & np.isfinite(truth)
    assert valid.sum() > 0.3 * band.sum()
    assert np.mean(np.abs((depth - truth)[valid]) < 0.003) >= 0.95
    # Everything the patch reads lies in the fine region: the same result with the coarse pixels blanked.
    blanked = np.where(fine, depth, np.nan).astype(np.float32)
    full, only_fine = compute_patch(depth, tool), compute_patch(blanked, tool)
    assert np.array_equal(full.band_distance_m, only_fine.band_distance_m, equal_nan=True)
    assert full.distance_m == only_fine.distance_m or (np.isnan(full.distance_m) and np.isnan(only_fine.distance_m))
    reach = PatchParams().outer_reach_px + PatchParams().bleed_beyond_px
    assert SGBMParams().region_px >= reach
    if left.shape[1] == 1920:  # matched at full size, the band was mostly unmatched (validity collapsed)
        full_size, _ = depth_of(SGBMParams(downscale=1, region=False))
        assert (band & np.isfinite(full_size)).sum() < 0.6 * valid.sum()


def narrow_box_pair(box_width, d_bg, d_box, seed, height=360, width=1280):
    """:func:`box_pair` with a box only ``box_width`` px wide, narrower than d_box - d_bg, as an instrument's
    tip at close range. Left of the box the plane is hidden from the right camera on the columns
    x0 - (d_box - d_bg) .. x0 - (d_box - d_bg) + box_width - 1 only: between there and the box both cameras
    see it. Returns (left, right, box mask, x0)."""
    x0 = width * 15 // 32  # 600 at 1280 px
    return (*box_pair(height, width, seed, d_bg, d_box, box=(100, 260, x0, x0 + box_width)), x0)


@pytest.mark.parametrize("width, height", [(1280, 360), (1920, 1080)])
@pytest.mark.parametrize("box_width, d_bg, d_box, seed", [(40, 40, 120, 0), (24, 40, 120, 1), (60, 40, 160, 2),
                                                          (30, 30, 100, 3)])
def test_the_plane_beside_a_narrow_tool_stays_matched(box_width, d_bg, d_box, seed, width, height):
    """Beside a tool narrower than its disparity step (a tip at close range) both cameras see the plane
    between the half-occluded strip and the tool. The right view's hidden strip used to inpaint the whole step
    right of the tool, and that plane went unmatched; now only the tissue under the tool in the left view (its
    own width). Measured share of the plane matched there, before / now: 1280x360 0.28-0.55 / 0.81-0.92,
    1920x1080 0.12-0.52 / 0.60-0.86; every match within 3 px of the plane's disparity, before and now.
    (640x360, matched at full size: 0.36-0.70 either way; a tile's crop there holds no tissue left of the
    widest strip, and the strip test takes everything the tool could hide.)"""
    left, right, tool, x0 = narrow_box_pair(box_width, d_bg, d_box, seed, height=height, width=width)
    params = SGBMParams().resolve(width, fx_px=1000.0 * width / 1280, baseline_m=0.004)
    disparity = region_sgbm_disparity(left, right, tool, params).disparity_px
    visible = disparity[105:255, x0 - (d_box - d_bg) + box_width + 2:x0]
    assert np.isfinite(visible).mean() > 0.55
    assert np.all(np.abs(visible[np.isfinite(visible)] - d_bg) <= 3)


def test_a_tiles_search_range_reaches_the_tissue_beside_its_region(monkeypatch):
    """When the coarse pass has no tissue inside a tile's region (beside a wide half-occluded strip its
    fattened tool covers the rest), the far end of the tile's search range reaches the coarse disparities
    beside the region (``range_context_px``, by default as far as the whole search range): the tissue there is
    then matched at its own disparity, not the tool's (with no context, the range holds only the box's
    disparity and the plane beside the box reads it)."""
    import contact_viz.geometry.stereo_region as stereo_region

    left, right, tool = box_pair()
    real = stereo_region.coarse_disparity

    def no_tissue_in_region(small_l, small_r, params):  # the coarse pass with the region's tissue unmatched
        coarse, n = real(small_l, small_r, params)
        # the region (grown by a coarse pixel's width, so that every matching pixel of it is covered)
        region = fine_region(tool, SGBMParams().region_px + 4 * n)[::2 * n, ::2 * n][:coarse.shape[0], :coarse.shape[1]]
        box = tool[::2 * n, ::2 * n][:coarse.shape[0], :coarse.shape[1]]
        return np.where(region & ~box, np.nan, np.where(box, D_BOX / 2, coarse)).astype(np.float32), n

    monkeypatch.setattr(stereo_region, "coarse_disparity", no_tissue_in_region)
    right_of = np.zeros_like(tool)
    right_of[110:250, 708:724] = True  # right of the box: both cameras see the plane
    read = {}
    for context in (None, 32, 0):  # None: the default, the whole search range
        disparity = region_sgbm_disparity(left, right, tool, SGBMParams(range_context_px=context)).disparity_px
        read[context] = np.mean(np.abs(disparity[right_of] - D_BG) <= 1.0)  # NaN counts as not read
    assert read[None] > 0.9 and read[32] > 0.9 and read[0] < 0.1


@pytest.mark.parametrize("width, height, rows", [(1280, 720, 6), (1280, 720, 10), (1920, 1080, 6)])
def test_a_sliver_of_a_tool_at_the_image_edge_gets_its_own_depth(width, height, rows):
    """An instrument showing only its last few rows at the top of the image (here a textured box, disparity
    140 px at 1280 over a plane at 40) is too thin for the coarse pass, whose disparities set each tile's
    search range: the tile searched only the plane's and gave the tool the plane's depth. A tile whose tool
    pixels the coarse pass mostly missed searches up to the nearest depth. Measured share of the sliver
    within 2 px of its disparity, with / without (range_tool_seen_min 0): 1280 px, 6 rows 0.81 / 0.00; 10 rows
    0.89 / 0.00; 1920 px, 6 rows 0.66 / 0.00 (640 px: 0.90 either way; 14 rows and more: the same either way)."""
    d_bg, d_box = 40 * width // 1280, 140 * width // 1280
    x0 = width * 15 // 32
    left, right, tool = box_pair(height, width, 0, d_bg, d_box, box=(0, rows, x0, x0 + width // 8))
    found = {}
    for seen in (SGBMParams().range_tool_seen_min, 0.0):
        params = SGBMParams(range_tool_seen_min=seen).resolve(width, fx_px=1000.0 * width / 1280, baseline_m=0.004)
        disparity = region_sgbm_disparity(left, right, tool, params).disparity_px
        found[seen] = np.mean(np.abs(disparity[tool] - d_box) <= 2)  # NaN counts as not found
    assert found[SGBMParams().range_tool_seen_min] > 0.6 and found[0.0] < 0.1
