"""The half-occluded strip (contact_viz.geometry.occlusion): against a literal loop, a worked row, and the
true visibility of scenes whose strip carries the tool's disparity or none."""

from __future__ import annotations

import math

import numpy as np
import pytest

from contact_viz.geometry.occlusion import OcclusionParams, half_occluded, tool_runs


def literal_half_occluded(disparity: np.ndarray, tool: np.ndarray, params: OcclusionParams) -> np.ndarray:
    """The definition of half_occluded written out: every row, every run, every pixel, one at a time."""
    height, width = tool.shape
    out = np.zeros((height, width), bool)
    for y in range(height):
        x = 0
        while x < width:
            if not tool[y, x]:
                x += 1
                continue
            a = x
            while x < width and tool[y, x]:
                x += 1
            b = x - 1
            right_cols = [c - disparity[y, c] for c in range(a, b + 1) if math.isfinite(disparity[y, c])]
            if not right_cols:
                continue
            m, big_m = min(right_cols), max(right_cols)
            nearest = max(disparity[y, c] for c in range(a, b + 1) if math.isfinite(disparity[y, c]))
            tissue = [c for c in range(a) if not tool[y, c] and math.isfinite(disparity[y, c])]
            d_s, found = 0.0, False
            if tissue:
                for _ in range(params.iterations):
                    first_strip_col = math.ceil(m + d_s)
                    beyond = [c for c in tissue if c <= first_strip_col - 1 - params.probe_gap_px]
                    chosen = [c for c in beyond[-params.probe_count:]  # in front of the tool: not read
                              if disparity[y, c] <= nearest * (1 + params.nearer_fraction)]
                    found = bool(chosen)
                    new = float(np.median([disparity[y, c] for c in chosen])) if chosen else 0.0
                    if new == d_s:
                        break
                    d_s = new
            last = min(a - 1, math.floor(big_m + d_s)) if found else a - 1  # unknown tissue: all it could hide
            for c in range(max(math.ceil(m + d_s), 0), last + 1):
                out[y, c] = not tool[y, c]
    return out


def test_worked_row():
    """Tool at columns 100-140 with disparity 80, tissue at 40: the tool covers right columns 20-60, where
    tissue pixels 60-99 would land (x - 40): the strip is columns 60-99, 40 px = 80 - 40, whatever the strip
    carries (the tool's disparity dragged over it, a made-up disparity, nothing)."""
    width = 200
    tool = np.zeros((4, width), bool)
    tool[:, 100:141] = True
    disparity = np.full((4, width), 40.0)
    disparity[:, 100:141] = 80.0
    disparity[1, 60:100] = 80.0  # the tool's disparity carried into the strip (SGBM, a network's bleeding)
    disparity[2, 60:100] = np.nan  # nothing there (SGBM's left-right check)
    disparity[3, 60:100] = 55.0  # a made-up tissue
    expected = np.zeros((4, width), bool)
    expected[:, 60:100] = True
    got = half_occluded(disparity, tool)
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(literal_half_occluded(disparity, tool, OcclusionParams()), expected)


def test_a_fold_nearer_than_the_tool_is_not_the_tissue_behind_it():
    """Tool at columns 100-140, disparity 80; the tissue behind it at 40. Row 0: only a fold of tissue nearer
    than the tool (disparity 90, columns 0-39) has depth left of the strip, and the strip carries the tool's
    disparity (SGBM's drag). Read as the tissue, the fold put the edge at 20 + 90 = 110, past the tool: no
    strip, the dragged pixels kept as tissue at the tool's depth. Not read, nothing behind the tool is known:
    all that it could hide, 20-99. Row 1: the far tissue next to the widest edge (10-17), the fold beyond
    it (0-9): the strip is 60-99."""
    width = 200
    tool = np.zeros((2, width), bool)
    tool[:, 100:141] = True
    disparity = np.full((2, width), np.nan)
    disparity[:, 100:141] = 80.0
    disparity[0, 0:40] = 90.0  # the fold, in front of the tool
    disparity[1, 0:10], disparity[1, 10:18] = 90.0, 40.0
    disparity[:, 60:100] = 80.0  # the tool's disparity dragged into the strip
    got = half_occluded(disparity, tool)
    np.testing.assert_array_equal(np.flatnonzero(got[0]), np.arange(20, 100))
    np.testing.assert_array_equal(np.flatnonzero(got[1]), np.arange(60, 100))
    np.testing.assert_array_equal(literal_half_occluded(disparity, tool, OcclusionParams()), got)
    assert not half_occluded(disparity, tool, OcclusionParams(nearer_fraction=1.0))[0].any()  # read: no strip


def test_contact_and_thin_tool():
    """Tissue rising to the tool's disparity at its edge (contact, one continuous surface): no pixel is
    hidden, so at most the few px the probe's offset adds; a tool thinner than the disparity step hides
    only the columns its footprint covers; a tool farther than all the tissue of its row (tissue more than
    nearer_fraction in front of it is not read) leaves the tissue behind it unknown: all it could hide."""
    width = 200
    tool = np.zeros((3, width), bool)
    tool[:, 100:141] = True
    x = np.arange(width, dtype=np.float64)
    disparity = np.where(tool, 80.0, 40.0)
    disparity[0, :100] = 80.0 - 0.1 * (99 - x[:100])  # rising to 80 at column 99: x - d = 0.9 x - 70.1 < 20
    strip = half_occluded(disparity, tool)[0]
    assert strip[:100].sum() <= 2  # the probe reads 2 + 4 px out: 0.1 px/px x 6 px / 0.9 -> at most 1 px
    thin = np.zeros((1, width), bool)
    thin[0, 100:111] = True  # 11 px wide, disparity 80, tissue 40: footprint 20-30, strip 60-70
    flat = np.where(thin, 80.0, 40.0)
    np.testing.assert_array_equal(np.flatnonzero(half_occluded(flat, thin)[0]), np.arange(60, 71))
    unknown = np.where(thin, 80.0, np.nan)  # no tissue depth left of it: all it could hide, 20-99
    np.testing.assert_array_equal(np.flatnonzero(half_occluded(unknown, thin)[0]), np.arange(20, 100))
    behind = np.where(thin, 30.0, 40.0)  # farther than all the tissue of the row: what lies behind it is not
    np.testing.assert_array_equal(np.flatnonzero(half_occluded(behind, thin)[0]), np.arange(70, 100))  # known
    assert not half_occluded(np.where(thin, 39.0, 40.0), thin).any()  # within 5%: read, and nothing is hidden


def random_scene(rng, height=12, width=160):
    """Tissue of one disparity per row (plus noise), one or two tool runs per row nearer than it, the strip
    filled with the tool's disparity, NaN or noise; returns (disparity, tool, true strip of the row geometry)."""
    disparity = np.empty((height, width))
    tool = np.zeros((height, width), bool)
    truth = np.zeros((height, width), bool)
    for y in range(height):
        d_tissue = rng.uniform(10, 30)
        disparity[y] = d_tissue + rng.normal(0, 0.2, width)
        a = int(rng.integers(80, 120))  # the widest strip (tissue at infinity) ends right of column 10
        b = min(a + int(rng.integers(5, 40)), width - 1)
        d_tool = d_tissue + rng.uniform(0, 40)
        tool[y, a:b + 1] = True
        disparity[y, a:b + 1] = d_tool + rng.normal(0, 0.2, b + 1 - a)
        right = (np.arange(a, b + 1) - disparity[y, a:b + 1])
        for c in range(a):  # the true strip, from the tissue's disparity without noise
            truth[y, c] = right.min() <= c - d_tissue <= right.max()
        strip = np.flatnonzero(truth[y])
        fill = rng.integers(0, 3)
        if strip.size and fill == 0:
            disparity[y, strip] = d_tool
        elif strip.size and fill == 1:
            disparity[y, strip] = np.nan
        elif strip.size:
            disparity[y, strip] = rng.uniform(0, 80, strip.size)
        if rng.random() < 0.3:  # a second tool left of the first, on some rows, 5 px nearer: a 5 px strip
            c0 = int(rng.integers(45, 55))  # with tissue left of its strip
            tool[y, c0:c0 + 4] = True
            disparity[y, c0:c0 + 4] = d_tissue + 5
            truth[y, c0 - 5:c0] = True
        disparity[y, rng.random(width) < 0.1] = np.nan  # holes everywhere, tool included
    return disparity, tool, truth


@pytest.mark.parametrize("seed", range(6))
def test_against_literal_loop_on_random_scenes(seed):
    rng = np.random.default_rng(seed)
    disparity, tool, truth = random_scene(rng)
    params = OcclusionParams(probe_count=int(rng.integers(1, 10)), probe_gap_px=int(rng.integers(0, 4)))
    got = half_occluded(disparity, tool, params)
    np.testing.assert_array_equal(got, literal_half_occluded(disparity, tool, params))
    assert not (got & tool).any()
    # against the true geometry (one tissue depth per row, its noise 0.2 px): all but the edges' pixels
    hidden_truth = truth & ~tool
    assert (got ^ hidden_truth).sum() <= 2 * tool.shape[0]  # a strip of 15-40 px per row
    assert got.sum() > 0


def test_tool_runs_and_input_checks():
    tool = np.array([[0, 1, 1, 0, 1], [1, 0, 0, 0, 0], [0, 0, 0, 0, 0]], bool)
    rows, firsts, lasts = tool_runs(tool)
    assert rows.tolist() == [0, 0, 1] and firsts.tolist() == [1, 4, 0] and lasts.tolist() == [2, 4, 0]
    assert not half_occluded(np.full((3, 5), np.nan), tool).any()  # no tool disparity: no strip
    assert not half_occluded(np.zeros((3, 5)), np.zeros((3, 5), bool)).any()
    with pytest.raises(ValueError, match="same"):
        half_occluded(np.zeros((3, 4)), tool)
    with pytest.raises(ValueError, match="probe_count"):
        OcclusionParams(probe_count=0)
