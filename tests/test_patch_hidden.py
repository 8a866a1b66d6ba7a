"""The patch leaves out band pixels the right camera cannot see (compute_patch's ``hidden``), and the pipeline
decides when (PatchParams.hidden_strip: with SGBM depth by default, always, never)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from contact_viz.geometry.occlusion import half_occluded
from contact_viz.geometry.patch import REASON_HIDDEN, compute_patch
from contact_viz.params import PatchParams
from contact_viz.pipeline.extract import hidden_pixels

FX_PX, BASELINE_M = 1100.0, 0.0041  # a da Vinci endoscope at 1080p (CalibrationParameters.xml of issue 33)


def close_range_scene(strip_filled_with_tool: bool = True):
    """A vertical shaft (columns 200-279) 20 mm above flat tissue at 50 mm, seen at 30 mm: 240x320 px. The right
    camera sees the shaft at x - d_tool and cannot see the tissue whose x - d_tissue falls there: left of the
    shaft, the columns from 200 - (d_tool - d_tissue) (60 px) to 199. SGBM fills such a strip with the shaft's
    depth (``strip_filled_with_tool``); the tissue elsewhere has its true depth. Returns the depth, the mask, the
    two depths and the hidden columns, computed here from the projection itself."""
    height, width = 240, 320
    tool_z, tissue_z = 0.030, 0.050
    mask = np.zeros((height, width), bool)
    mask[:, 200:280] = True
    d_tool, d_tissue = FX_PX * BASELINE_M / tool_z, FX_PX * BASELINE_M / tissue_z
    # a tissue column x is hidden when its right-image column x - d_tissue lies within the shaft's, 200..279 - d_tool
    hidden_cols = [x for x in range(200) if 200 - d_tool <= x - d_tissue <= 279 - d_tool]
    depth = np.full((height, width), tissue_z, np.float32)
    depth[mask] = tool_z
    if strip_filled_with_tool:
        depth[:, hidden_cols] = tool_z
    return depth, mask, tool_z, tissue_z, hidden_cols


def disparity_of(depth: np.ndarray) -> np.ndarray:
    return FX_PX * BASELINE_M / depth.astype(np.float64)


def test_the_strip_filled_with_the_tools_depth_reads_zero_without_hidden_and_the_gap_with_it():
    depth, mask, tool_z, tissue_z, hidden_cols = close_range_scene()
    assert hidden_cols == list(range(140, 200))  # 60 px: the two disparities' difference
    plain = compute_patch(depth, mask)
    assert plain.found and abs(plain.distance_m) < 1e-6  # the failure of issue 33: the strip reads as contact
    hidden = half_occluded(disparity_of(depth), mask)
    # the strip found is exactly the hidden columns (its tissue disparity read beyond it), on every row
    assert np.flatnonzero(hidden.any(axis=0)).tolist() == hidden_cols and hidden[:, hidden_cols].all()
    aware = compute_patch(depth, mask, hidden=hidden)
    assert aware.found
    assert aware.distance_m == pytest.approx(tissue_z - tool_z, abs=1e-6)  # the true gap, 20 mm
    assert aware.center_xy[0] >= 280  # the patch moved to the right side of the shaft
    assert aware.n_hidden == int(hidden[aware.band].sum()) > 0


def test_hidden_band_pixels_lose_their_distance_and_nothing_else_changes():
    depth, mask, *_ = close_range_scene(strip_filled_with_tool=False)
    rng = np.random.default_rng(3)
    depth = depth + rng.normal(0, 2e-4, depth.shape).astype(np.float32)
    hidden = np.zeros(depth.shape, bool)
    hidden[:, 170:200] = True
    plain, aware = compute_patch(depth, mask), compute_patch(depth, mask, hidden=hidden)
    in_hidden = hidden[plain.band_yx[:, 0], plain.band_yx[:, 1]]
    assert in_hidden.any() and (~in_hidden).any()
    assert np.isnan(aware.band_distance_m[in_hidden]).all()
    np.testing.assert_array_equal(aware.band_distance_m[~in_hidden], plain.band_distance_m[~in_hidden])
    # the scores are the literal windows over the distances that remain
    d = aware.band_distance_m
    index = {tuple(p): i for i, p in enumerate(aware.band_yx)}
    half = PatchParams().n2 // 2
    for i in rng.choice(np.flatnonzero(np.isfinite(aware.band_score_m)), 20, replace=False):
        y, x = aware.band_yx[i]
        near = [d[index[(yy, xx)]] for yy in range(y - half, y + half + 1) for xx in range(x - half, x + half + 1)
                if (yy, xx) in index and np.isfinite(d[index[(yy, xx)]])]
        assert aware.band_score_m[i] == pytest.approx(np.mean(np.abs(near)), rel=1e-9)
    assert compute_patch(depth, mask, hidden=np.zeros_like(hidden)).distance_m == plain.distance_m
    assert aware.invalid_depth_fraction == 0.0


def test_a_band_wholly_hidden_says_so():
    depth, mask, *_ = close_range_scene()
    hidden = ~mask
    result = compute_patch(depth, mask, hidden=hidden)
    assert not result.found and result.reason == REASON_HIDDEN


def test_hidden_must_match_the_depth():
    depth, mask, *_ = close_range_scene()
    with pytest.raises(ValueError, match="hidden"):
        compute_patch(depth, mask, hidden=np.zeros((3, 3), bool))


@pytest.mark.parametrize("setting, depth_source, used", [
    ("sgbm", "depth", False), ("always", "depth", True), ("never", "depth", False),
    ("sgbm", "sgbm", True), ("never", "sgbm", False)])
def test_the_pipeline_leaves_the_strip_out_when_the_setting_says(tmp_path, setting, depth_source, used):
    depth, mask, *_ = close_range_scene()

    class FakeCalibration:
        fx, baseline_m, disparity_offset_px = FX_PX, BASELINE_M, 0.0

    class FakeSession:
        calibration = FakeCalibration()

    session = FakeSession()
    session.depth_source = depth_source
    frame = _frame(depth, mask)
    hidden = hidden_pixels(session, frame, PatchParams(hidden_strip=setting))
    if used:
        np.testing.assert_array_equal(hidden, half_occluded(disparity_of(depth), mask))
    else:
        assert hidden is None


def _frame(depth, mask):
    from contact_viz.io.session import Frame

    return Frame(index=0, stem="000000", timestamp_s=0.0, tool_mask=mask, depth_m=depth, left_rgb=None,
                 right_rgb=None)


def test_hidden_strip_is_checked():
    with pytest.raises(ValueError, match="hidden_strip"):
        PatchParams(hidden_strip="sometimes")
    assert dataclasses.replace(PatchParams(), hidden_strip="always").hidden_strip == "always"
