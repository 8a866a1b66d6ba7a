"""Tests for contact_viz.geometry.stereo: SGBM disparity (synthetic and Middlebury), depth, cache, precompute."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from contact_viz.errors import SessionError
from contact_viz.geometry.stereo import (SGBMParams, disparity_to_depth, left_right_check, median_by_region,
                                         sgbm_disparity)
from contact_viz.io.depth_cache import DisparityCache, _decode, _encode
from contact_viz.pipeline.depth import run_depth_command

# Middlebury 2014 "Motorcycle" as shipped (4x down-sampled) by scikit-image; calibration from
# the docstring of skimage.data.stereo_motorcycle.
MB_FX_PX = 994.978  # focal length, px
MB_CX_PX, MB_CY_PX = 311.193, 254.877  # principal point of the left camera, px
MB_DOFFS_PX = 31.086  # x-difference of the principal points (right - left), px
MB_BASELINE_M = 0.193001  # baseline, m
# Measured with the default SGBMParams (plain matching: 96 disparities, 3 px blocks, uniqueness 15, 3-way, LR
# check): 96.0 % of the pixels valid in both maps are within 2 px of the truth; 88.0 % of pixels valid
# (94.8 % with the 7 px blocks of the width rule; 96.1 % / 87.8 % through a session, 192 disparities).
MB_WITHIN_2PX_MIN = 0.955  # bound the test enforces on the share within 2 px
MB_VALID_MIN = 0.85  # bound on the valid fraction


def random_dot_pair(height: int, width: int, layers, seed: int = 0):
    """A rectified pair of random texture with fronto-parallel layers.

    ``layers`` = [(disparity px, (y0, y1, x0, x1) or None for the whole image)], back to front.
    Returns (left (H, W, 3) uint8, right (H, W, 3) uint8, true left disparity (H, W) float32,
    occluded (H, W) bool: left pixels whose match in the right image is hidden by a nearer layer).
    """
    rng = np.random.default_rng(seed)
    pad = max(d for d, _ in layers) + 1
    textures = [rng.integers(0, 256, (height, width + 2 * pad, 3), dtype=np.uint8) for _ in layers]
    left = np.zeros((height, width, 3), np.uint8)
    right = np.zeros((height, width, 3), np.uint8)
    disp = np.zeros((height, width), np.float32)
    owner_right = np.full((height, width), -1)
    owner_left = np.full((height, width), -1)
    for i, (d, box) in enumerate(layers):
        y0, y1, x0, x1 = box if box is not None else (0, height, 0, width)
        tex = textures[i]
        # The layer's texture is fixed in the world: left pixel x shows tex[x + pad],
        # right pixel x shows tex[x + d + pad].
        left[y0:y1, x0:x1] = tex[y0:y1, x0 + pad:x1 + pad]
        disp[y0:y1, x0:x1] = d
        owner_left[y0:y1, x0:x1] = i
        rx0, rx1 = max(x0 - d, 0), max(x1 - d, 0)
        right[y0:y1, rx0:rx1] = tex[y0:y1, rx0 + d + pad:rx1 + d + pad]
        owner_right[y0:y1, rx0:rx1] = i
    xs = np.arange(width)[None, :] - disp.astype(int)
    rows = np.broadcast_to(np.arange(height)[:, None], disp.shape)
    inside = xs >= 0
    occluded = np.zeros_like(inside)
    occluded[inside] = owner_right[rows[inside], xs[inside]] != owner_left[inside]
    return left, right, disp, occluded


def test_resolve_sizes_from_width():
    # By hand: 741 / 8 = 92.6 -> 96; 741 / 128 = 5.8 -> 6 -> next odd 7.
    p = SGBMParams().resolve(741)
    assert (p.num_disparities, p.block_size) == (96, 7)
    assert p.downscale == 1  # 741 <= match_width_px (960): matched as it is
    # Wider images are matched at the smallest downscale bringing them to <= 960 px:
    # 1920 -> 2 (960 px: 960 / 8 = 120 disparities, 960 / 128 = 7.5 -> 8 -> 9 px blocks); 1280 -> 2 (640 px);
    # 961 -> 2 (480 px); 2880 -> 3.
    for width, downscale in ((1920, 2), (1280, 2), (960, 1), (961, 2), (640, 1), (2880, 3)):
        p = SGBMParams().resolve(width)
        assert p.downscale == downscale
        matched = width // downscale
        block = max(3, round(matched / 128))
        assert (p.num_disparities, p.block_size) == (math.ceil(math.ceil(matched / 8) / 16) * 16,
                                                     block + 1 - block % 2)
    assert (SGBMParams().resolve(1920).num_disparities, SGBMParams().resolve(1920).block_size) == (128, 9)
    # Matched at full size on request: 1920 / 8 = 240 (a multiple of 16); 1920 / 128 = 15 (odd).
    p = SGBMParams(downscale=1).resolve(1920)
    assert (p.num_disparities, p.block_size) == (240, 15)
    p = SGBMParams(downscale=1).resolve(1280)  # 1280 / 8 = 160; 1280 / 128 = 10 -> 11
    assert (p.num_disparities, p.block_size) == (160, 11)
    p = SGBMParams(downscale=2).resolve(1280)
    assert (p.num_disparities, p.block_size) == (80, 5)
    # 160 px (the smallest synth sessions): 160 / 128 = 1.25 -> 1 -> at least 3.
    assert SGBMParams().resolve(160).block_size == 3
    # Explicit values are kept.
    p = SGBMParams(num_disparities=64, block_size=9).resolve(5000)
    assert (p.num_disparities, p.block_size) == (64, 9)


def test_resolve_search_range_from_the_calibration():
    """The range reaches fx * baseline / min_depth_m - offset, at the matching resolution, capped at
    max_disparity_fraction of its width, as the smallest multiple of 16 from min_disparity covering it."""
    # The synthetic camera at 1080p: fx = 960 / tan(40 deg) = 1144.1 px, 5 mm: 1144.1 * 0.005 / 0.015 = 381.4 px;
    # matched at 960 px (downscale 2): 190.7 -> disparities 0..190 -> 191 -> 192 (cap 0.25 * 960 = 240).
    fx_synth = 960 / math.tan(math.radians(40))
    p = SGBMParams().resolve(1920, fx_px=fx_synth, baseline_m=0.005)
    assert (p.downscale, p.num_disparities) == (2, 192)
    # A da Vinci endoscope at 1080p: 1103 * 0.0041 / 0.015 = 301.5 px -> 150.7 at 960 px -> 151 -> 160.
    assert SGBMParams().resolve(1920, fx_px=1103.0, baseline_m=0.0041).num_disparities == 160
    # ... its rectified 1280x960 crop (fx 1227): 335.4 px -> 167.7 at 640 px, capped at 0.25 * 640 = 160 -> 161 -> 176.
    assert SGBMParams().resolve(1280, fx_px=1227.0, baseline_m=0.0041).num_disparities == 176
    # 30 mm nearest: 1227 * 0.0041 / 0.03 = 167.7 full -> 83.8 -> 84 -> 96; at 640x480 as it is: 167.7 -> 168 ->
    # 176 (cap 160 -> 161 -> 176 as well).
    assert SGBMParams(min_depth_m=0.03).resolve(1280, fx_px=1227.0, baseline_m=0.0041).num_disparities == 96
    # Middlebury (0.193 m baseline, doffs 31.1 px): 12,802 - 31 px, capped at 0.25 * 741 = 185.25 -> 186 -> 192.
    p = SGBMParams().resolve(741, fx_px=MB_FX_PX, baseline_m=MB_BASELINE_M, disparity_offset_px=MB_DOFFS_PX)
    assert p.num_disparities == 192
    # With min_disparity 16: disparities 16..190 -> 175 -> 176.
    assert SGBMParams(min_disparity=16).resolve(1920, fx_px=fx_synth, baseline_m=0.005).num_disparities == 176
    # A scene far away (min depth 1 m): 1144.1 * 0.005 = 5.7 px -> 2.9 -> 3 -> at least 16.
    assert SGBMParams(min_depth_m=1.0).resolve(1920, fx_px=fx_synth, baseline_m=0.005).num_disparities == 16
    # An explicit range wins; without a calibration, 1/8 of the matching width (960 / 8 = 120 -> 128).
    assert SGBMParams(num_disparities=64).resolve(1920, fx_px=fx_synth, baseline_m=0.005).num_disparities == 64
    assert SGBMParams().resolve(1920).num_disparities == 128
    # Resolving again keeps the range (the session resolves once, the matchers again).
    assert p.resolve(741).num_disparities == 192
    with pytest.raises(ValueError, match="both fx_px and baseline_m"):
        SGBMParams().resolve(1920, fx_px=1000.0)
    with pytest.raises(ValueError, match="positive"):
        SGBMParams().resolve(1920, fx_px=1000.0, baseline_m=0.0)


def test_plain_block_size():
    """Plain whole-frame matching uses 3 px blocks unless a block size is given (Middlebury: docs/depth.md)."""
    assert SGBMParams().resolve(741).plain_block_size == 3
    assert SGBMParams().resolve(741).block_size == 7  # the width rule, for the matching around the tools
    assert SGBMParams(block_size=9).resolve(741).plain_block_size == 9
    assert SGBMParams(block_size=9, plain_block_size=5).resolve(741).plain_block_size == 5


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"num_disparities": 40}, "multiple of 16"),
        ({"block_size": 4}, "odd"),
        ({"mode": "fast"}, "mode"),
        ({"downscale": 0}, "downscale"),
        ({"disparity_range_fraction": 0.0}, "disparity_range_fraction"),
        ({"min_depth_m": 0.0}, "min_depth_m"),
        ({"max_disparity_fraction": 1.5}, "max_disparity_fraction"),
        ({"plain_block_size": 4}, "odd"),
        ({"p1_factor": 40, "p2_factor": 32}, "p1_factor"),
    ],
)
def test_params_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SGBMParams(**kwargs)


def test_left_right_check_against_loop():
    rng = np.random.default_rng(3)
    height, width = 5, 17
    quarters = rng.choice([0, 0.25, 0.5, 0.75], (height, width)).astype(np.float32)
    disp_left = rng.integers(0, 6, (height, width)).astype(np.float32) + quarters
    disp_left[rng.random((height, width)) < 0.15] = np.nan
    disp_right = disp_left + rng.normal(0, 1.0, (height, width)).astype(np.float32)
    disp_right[rng.random((height, width)) < 0.15] = np.nan
    expected = np.zeros((height, width), bool)
    for y in range(height):
        for x in range(width):
            d = disp_left[y, x]
            if math.isnan(d):
                continue
            xr = int(np.rint(x - d))
            if 0 <= xr < width and not math.isnan(disp_right[y, xr]):
                expected[y, x] = abs(disp_right[y, xr] - d) <= 0.7
    np.testing.assert_array_equal(left_right_check(disp_left, disp_right, 0.7), expected)
    assert 0 < expected.sum() < expected.size  # the example exercises both outcomes


def test_median_by_region_is_the_windows_median_and_keeps_regions_apart():
    """Away from holes and region borders, the median of the finite values of each window (a slow
    literal loop); next to them, values of the pixel's own region only; NaN stays NaN."""
    rng = np.random.default_rng(5)
    height, width, size = 24, 30, 5
    tool = np.zeros((height, width), bool)
    tool[:, 18:] = True  # a near tool (disparity ~20) right of the tissue (disparity ~5) ...
    tool[:, 8:10] = True  # ... and a thin one: a window mixing the regions takes the tissue's value there
    disparity = np.where(tool, 20.0, 5.0) + rng.normal(0, 0.5, (height, width))
    disparity = (np.round(disparity * 16) / 16).astype(np.float32)  # SGBM's 1/16 px
    disparity[rng.random((height, width)) < 0.08] = np.nan
    out = median_by_region(disparity, [tool, ~tool], size)
    np.testing.assert_array_equal(np.isnan(out), np.isnan(disparity))
    half = size // 2
    checked = 0
    for y in range(half, height - half):
        for x in range(half, width - half):
            window = disparity[y - half:y + half + 1, x - half:x + half + 1]
            same = tool[y - half:y + half + 1, x - half:x + half + 1] == tool[y, x]
            if np.isnan(disparity[y, x]):
                continue
            if same.all() and np.isfinite(window).all():
                assert out[y, x] == np.median(window)
                checked += 1
    # next to the border too: never pulled towards the other region's disparity (15 px away)
    finite = np.isfinite(out)
    assert np.abs(out[finite] - np.where(tool, 20.0, 5.0)[finite]).max() < 2.5
    assert checked > 50
    np.testing.assert_array_equal(median_by_region(disparity, [tool, ~tool], 0), disparity)


def test_sgbm_recovers_layers():
    height, width = 60, 128
    left, right, truth, occluded = random_dot_pair(height, width, [(4, None), (12, (15, 45, 50, 95))], seed=1)
    assert occluded.sum() > 200  # an 8 px band left of the square, 30 rows
    disparity = sgbm_disparity(left, right, SGBMParams(num_disparities=16, block_size=5))
    assert disparity.dtype == np.float32 and disparity.shape == (height, width)
    visible = ~occluded
    good = np.isfinite(disparity) & visible
    assert good.sum() / visible.sum() > 0.8
    assert np.mean(np.abs(disparity[good] - truth[good]) <= 0.5) > 0.97
    # Pixels at the left border still get disparities thanks to the padding (true disparity 4 < x).
    assert np.isfinite(disparity[:, 5:16]).mean() > 0.8
    # Occluded pixels have no match in the right image: almost all are left invalid.
    assert np.isfinite(disparity[occluded]).mean() < 0.25
    # Downscaled matching gives the same layers at half the resolution (disparities scaled back).
    coarse = sgbm_disparity(left, right, SGBMParams(num_disparities=16, block_size=3, downscale=2))
    ok = np.isfinite(coarse) & visible
    assert ok.mean() > 0.6 and np.median(np.abs(coarse[ok] - truth[ok])) <= 0.5


def test_sgbm_on_middlebury_motorcycle():
    skdata = pytest.importorskip("skimage.data")
    left, right, truth = skdata.stereo_motorcycle()
    disparity = sgbm_disparity(left, right, SGBMParams())
    valid = np.isfinite(disparity)
    both = valid & np.isfinite(truth)
    within = np.abs(disparity[both] - truth[both]) <= 2.0
    assert within.mean() >= MB_WITHIN_2PX_MIN, f"only {within.mean():.4f} within 2 px"
    assert valid.mean() >= MB_VALID_MIN, f"valid fraction {valid.mean():.4f}"
    # The left-right check removes more wrong matches than right ones (measured 94.6 % without it).
    unchecked = sgbm_disparity(left, right, SGBMParams(lr_check=False))
    both_u = np.isfinite(unchecked) & np.isfinite(truth)
    within_u = np.abs(unchecked[both_u] - truth[both_u]) <= 2.0
    assert within.mean() > within_u.mean() + 0.005


def write_middlebury_session(root: Path, empty_masks: bool) -> np.ndarray:
    """The Motorcycle pair as a session with a ROS calibration whose principal points differ (doffs), with or
    without an empty mask per frame; returns the true disparity."""
    left, right, truth = pytest.importorskip("skimage.data").stereo_motorcycle()
    for sub in ("left", "right") + (("masks",) if empty_masks else ()):
        (root / sub).mkdir(parents=True)
    Image.fromarray(left).save(root / "left" / "0.png")
    Image.fromarray(right).save(root / "right" / "0.png")
    if empty_masks:
        Image.fromarray(np.zeros(truth.shape, np.uint8)).save(root / "masks" / "0.png")
    height, width = truth.shape

    def ros(p_row0):
        k = f"[{MB_FX_PX}, 0, {MB_CX_PX}, 0, {MB_FX_PX}, {MB_CY_PX}, 0, 0, 1]"
        p = "[" + ", ".join(str(v) for v in p_row0 + [0, MB_FX_PX, MB_CY_PX, 0, 0, 0, 1, 0]) + "]"
        return (f"image_width: {width}\nimage_height: {height}\ncamera_matrix:\n  rows: 3\n  cols: 3\n  data: {k}\n"
                "distortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [0, 0, 0, 0, 0]\n"
                "rectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n"
                f"projection_matrix:\n  rows: 3\n  cols: 4\n  data: {p}\n")

    (root / "left.yaml").write_text(ros([MB_FX_PX, 0, MB_CX_PX, 0]))
    (root / "right.yaml").write_text(ros([MB_FX_PX, 0, MB_CX_PX + MB_DOFFS_PX, -MB_FX_PX * MB_BASELINE_M]))
    return truth


def test_depth_command_on_middlebury_matches_the_whole_frame(tmp_path):
    """`contact-viz depth -o` on Motorcycle, without masks and with an empty mask (no instrument in view): the
    whole frame matched plainly at the matching resolution, the same depth both ways, 96.1 % within 2 px."""
    depths = []
    for empty_masks in (False, True):
        root = tmp_path / f"mb{int(empty_masks)}"
        truth = write_middlebury_session(root, empty_masks)
        run_depth_command(root, cache_dir=tmp_path / "cache", output=tmp_path / f"out{int(empty_masks)}", workers=1)
        depths.append(np.load(tmp_path / f"out{int(empty_masks)}" / "0.npy"))
    np.testing.assert_array_equal(depths[0], depths[1])
    disparity = MB_FX_PX * MB_BASELINE_M / depths[0] - MB_DOFFS_PX  # the matcher's disparity back from depth
    both = np.isfinite(disparity) & np.isfinite(truth)
    assert np.mean(np.abs(disparity[both] - truth[both]) <= 2.0) >= MB_WITHIN_2PX_MIN
    assert np.isfinite(disparity).mean() >= MB_VALID_MIN


def test_disparity_to_depth_worked_example():
    disparity = np.array([[10.0, 0.0, -2.0], [np.nan, 4.0, 1.0]], np.float32)
    depth = disparity_to_depth(disparity, fx_px=500.0, baseline_m=0.004)
    # 500 * 0.004 = 2 (px m): 2 / 10 = 0.2 m, 2 / 4 = 0.5 m, 2 / 1 = 2 m; 0, negative and NaN invalid.
    np.testing.assert_allclose(depth, [[0.2, np.nan, np.nan], [np.nan, 0.5, 2.0]], rtol=1e-6)
    assert depth.dtype == np.float32
    # Middlebury's doffs: Z = f B / (d + doffs).
    shifted = disparity_to_depth(np.array([[40.0]], np.float32), MB_FX_PX, MB_BASELINE_M, MB_DOFFS_PX)
    assert shifted[0, 0] == pytest.approx(MB_FX_PX * MB_BASELINE_M / (40.0 + MB_DOFFS_PX), rel=1e-6)
    # A negative offset makes small positive disparities invalid.
    assert np.isnan(disparity_to_depth(np.array([[1.0]]), 500.0, 0.004, offset_px=-2.0)[0, 0])
    with pytest.raises(ValueError, match="baseline_m"):
        disparity_to_depth(disparity, 500.0, 0.0)


def test_cache_code_roundtrip_is_exact():
    rng = np.random.default_rng(0)
    for params in (SGBMParams().resolve(640), SGBMParams(min_disparity=-8, downscale=2).resolve(640)):
        low = params.min_disparity * params.downscale
        steps = rng.integers(0, params.num_disparities * SUBPIXEL_STEPS, (7, 9))
        disparity = (low + steps / SUBPIXEL_STEPS * params.downscale).astype(np.float32)
        disparity[0, :3] = np.nan
        code = _encode(disparity, params)
        assert code.dtype == np.uint16 and (code[0, :3] == 0).all() and (code[1:] > 0).all()
        np.testing.assert_array_equal(_decode(code, params), disparity)


SUBPIXEL_STEPS = 16  # StereoSGBM's 1/16 px fixed point


def write_stereo_session(root: Path, n: int = 3, height: int = 48, width: int = 96, masks: bool = False) -> dict:
    """A session with only left/, right/ and K.txt (plus masks/ if asked); returns truth."""
    for sub in ("left", "right") + (("masks",) if masks else ()):
        (root / sub).mkdir(parents=True, exist_ok=True)
    fx, baseline = 200.0, 0.005
    (root / "K.txt").write_text(f"{fx} 0 {width / 2} 0 {fx} {height / 2} 0 0 1\n{baseline}\n")
    truth = {}
    for i in range(n):
        left, right, disp, occluded = random_dot_pair(height, width, [(5 + i, None), (11, (10, 35, 40, 80))], seed=i)
        Image.fromarray(left).save(root / "left" / f"{i}.png")
        Image.fromarray(right).save(root / "right" / f"{i}.png")
        if masks:
            Image.fromarray(np.zeros((height, width), np.uint8)).save(root / "masks" / f"{i}.png")
        truth[str(i)] = (disp, occluded, fx * baseline / disp)
    return truth


def test_precompute_fills_cache_and_writes_depth(tmp_path):
    root = tmp_path / "sess"
    truth = write_stereo_session(root)
    cache = tmp_path / "cache"
    out = tmp_path / "depth_out"
    seen = []
    lines = run_depth_command(root, cache_dir=cache, output=out, workers=2, progress=lambda d, t: seen.append((d, t)))
    text = "\n".join(lines)
    assert "3 computed" in text and "0 from cache" in text and "SGBM" in text and "FoundationStereo" in text
    assert seen[-1] == (3, 3)
    for stem, (disp, occluded, depth_true) in truth.items():
        depth = np.load(out / f"{stem}.npy")
        good = np.isfinite(depth) & ~occluded
        assert good.mean() > 0.7
        # Within 5 %, except a few pixels at the layer edges (SGBM fattens the nearer layer).
        assert np.mean(np.abs(depth[good] / depth_true[good] - 1) <= 0.05) > 0.98
    cached = sorted(p.name for p in (cache / "sgbm").rglob("*.png"))
    assert len(cached) == 3
    lines = run_depth_command(root, cache_dir=cache, workers=1)
    assert "0 computed" in "\n".join(lines) and "3 from cache" in "\n".join(lines)
    # Touching one right image recomputes only that frame.
    os.utime(root / "right" / "1.png", ns=(1, 1))
    lines = run_depth_command(root, cache_dir=cache, workers=1)
    assert "1 computed" in "\n".join(lines) and "2 from cache" in "\n".join(lines)
    # Nothing was written into the session.
    assert sorted(p.name for p in root.iterdir()) == ["K.txt", "left", "right"]


def test_precompute_refuses_output_inside_session_and_nonempty(tmp_path):
    root = tmp_path / "sess"
    write_stereo_session(root, n=1)
    with pytest.raises(ValueError, match="inside the session"):
        run_depth_command(root, cache_dir=tmp_path / "c", output=root / "depth")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(ValueError, match="new or empty"):
        run_depth_command(root, cache_dir=tmp_path / "c", output=tmp_path / "full")
    with pytest.raises(ValueError, match="inside the session"):
        run_depth_command(root, cache_dir=root / "cache")
    with pytest.raises(ValueError, match="--method"):
        run_depth_command(root, method="raft")
    assert not (root / "depth").exists() and not (root / "cache").exists()


def test_run_depth_command_no_source(tmp_path):
    root = tmp_path / "sess"
    write_stereo_session(root, n=1)
    for path in (root / "right").iterdir():
        path.unlink()
    (root / "right").rmdir()
    with pytest.raises(SessionError, match="FoundationStereo"):
        run_depth_command(root, cache_dir=tmp_path / "c")


def test_unwritable_cache_warns_and_still_computes(tmp_path):
    blocked = tmp_path / "blocked"
    blocked.write_text("a file where the cache folder should be")
    cache = DisparityCache(blocked / "sgbm", SGBMParams().resolve(96))
    left, right, _, _ = random_dot_pair(32, 96, [(6, None)])
    left_path, right_path = tmp_path / "l.png", tmp_path / "r.png"
    Image.fromarray(left).save(left_path)
    Image.fromarray(right).save(right_path)
    with pytest.warns(UserWarning, match="could not write the depth cache"):
        disparity, cached = cache.disparity("0", left_path, right_path, lambda: (left, right))
    assert not cached and np.isfinite(disparity).mean() > 0.5


def test_depth_command_line_full_frame_and_min_depth(tmp_path):
    """`contact-viz depth --full-frame --min-depth-mm`: the whole frame matched and said so; a depth that is not
    > 0 is refused in one line."""
    from typer.testing import CliRunner

    from contact_viz.cli import app

    root = tmp_path / "sess"
    write_stereo_session(root, n=1, masks=True)
    result = CliRunner().invoke(app, ["depth", str(root), "--full-frame", "--min-depth-mm", "50", "-o",
                                      str(tmp_path / "out"), "--cache-dir", str(tmp_path / "cache")])
    assert result.exit_code == 0, result.output
    assert "SGBM: whole frames at 1/1 scale" in result.output
    assert (tmp_path / "out" / "0.npy").is_file()
    bad = CliRunner().invoke(app, ["depth", str(root), "--min-depth-mm", "0"])
    assert bad.exit_code == 2 and "--min-depth-mm: expected a depth > 0 mm, got 0" in bad.output


@pytest.mark.parametrize("seed", range(3))
def test_drop_speckles_against_flood_fill(seed):
    """drop_speckles (OpenCV's filterSpeckles at 1/16 px) against a literal flood fill: 4-connected regions of
    finite disparities whose neighbours differ by at most the range (in 1/16 px), of at most window pixels, go."""
    from collections import deque

    from contact_viz.geometry.stereo import SUBPIXEL, drop_speckles

    rng = np.random.default_rng(seed)
    height, width, window, spread = 30, 40, 12, 2
    levels = rng.choice([10.0, 10.5, 14.0, 30.0], size=(height // 3, width // 4))
    disparity = np.kron(levels, np.ones((3, 4))) + rng.choice([0, 0.0625, 0.125, 3.0], (height, width), p=[.6, .2, .15, .05])
    disparity[rng.random((height, width)) < 0.15] = np.nan
    fixed = np.where(np.isfinite(disparity), np.rint(disparity * SUBPIXEL), np.nan)
    label = np.full((height, width), -1)
    expected = disparity.copy()
    for y0 in range(height):
        for x0 in range(width):
            if label[y0, x0] >= 0 or not np.isfinite(fixed[y0, x0]):
                continue
            label[y0, x0] = 1
            members, queue = [], deque([(y0, x0)])
            while queue:
                y, x = queue.popleft()
                members.append((y, x))
                for v, u in ((y - 1, x), (y + 1, x), (y, x - 1), (y, x + 1)):
                    if (0 <= v < height and 0 <= u < width and label[v, u] < 0 and np.isfinite(fixed[v, u])
                            and abs(fixed[v, u] - fixed[y, x]) <= spread * SUBPIXEL):
                        label[v, u] = 1
                        queue.append((v, u))
            if len(members) <= window:
                for y, x in members:
                    expected[y, x] = np.nan
    got = drop_speckles(disparity.astype(np.float32), window, spread)
    assert np.isnan(expected).sum() > np.isnan(disparity).sum() + 10  # some speckles went
    np.testing.assert_array_equal(np.isnan(got), np.isnan(expected))
    np.testing.assert_array_equal(got[np.isfinite(got)], disparity.astype(np.float32)[np.isfinite(got)])
