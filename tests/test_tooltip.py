"""Tests of the tool-tip estimate and the zero-padded crop."""

from __future__ import annotations

import math

import numpy as np
import pytest

from contact_viz.geometry.tooltip import TipParams, crop_centered, tool_tip_xy

HEIGHT, WIDTH = 96, 160  # px


def capsule(start_xy, end_xy, radius_px, shape=(HEIGHT, WIDTH)) -> np.ndarray:
    """(H, W) bool: pixels within ``radius_px`` of the segment start-end (a shaft with a round tip)."""
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    p = np.stack([cols, rows], axis=-1)
    a, b = np.asarray(start_xy, float), np.asarray(end_xy, float)
    t = np.clip(((p - a) @ (b - a)) / np.dot(b - a, b - a), 0.0, 1.0)
    nearest = a + t[..., None] * (b - a)
    return np.linalg.norm(p - nearest, axis=-1) <= radius_px


def apex(start_xy, end_xy, radius_px) -> np.ndarray:
    """The far point of the capsule's round end: end + radius along the shaft direction."""
    a, b = np.asarray(start_xy, float), np.asarray(end_xy, float)
    return b + radius_px * (b - a) / np.linalg.norm(b - a)


@pytest.mark.parametrize(
    ("start", "end"),
    [
        ((-30.0, 40.0), (95.0, 62.0)),  # enters from the left border
        ((70.0, -20.0), (88.0, 70.0)),  # enters from the top border
        ((175.0, 110.0), (60.0, 30.0)),  # enters across the bottom-right corner
    ],
)
def test_tip_of_a_shaft_entering_from_the_border(start, end):
    radius = 6.0
    mask = capsule(start, end, radius)
    tip = tool_tip_xy(mask)
    assert tip is not None
    assert np.linalg.norm(np.array(tip) - apex(start, end, radius)) <= 2.0


def test_largest_blob_wins_over_a_farther_speck():
    start, end, radius = (-30.0, 40.0), (80.0, 50.0), 6.0
    mask = capsule(start, end, radius)
    mask[85:90, 150:155] = True  # a 25 px speck farther from the entry than the real tip
    tip = tool_tip_xy(mask)
    assert np.linalg.norm(np.array(tip) - apex(start, end, radius)) <= 2.0


def test_shaft_touching_two_borders_uses_the_longer_run():
    # A wide shaft from the left (about 17 px on the border) whose round end grazes the bottom
    # border over a few px only: the entry must be the left run, not both runs.
    start, end, radius = (-30.0, 30.0), (120.0, 88.0), 8.0
    mask = capsule(start, end, radius)
    assert 0 < mask[-1].sum() < mask[:, 0].sum()
    tip = tool_tip_xy(mask)
    assert np.linalg.norm(np.array(tip) - apex(start, end, radius)) <= 2.0


def test_mask_inside_the_image_takes_the_end_nearest_the_border_as_entry():
    # Fully inside: the upper-left end is 14 px from the top border, the lower-right end farther
    # from every border, so the entry is the upper-left end and the tip the lower-right one.
    start, end, radius = (40.0, 20.0), (100.0, 55.0), 6.0
    mask = capsule(start, end, radius)
    assert not (mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())
    tip = tool_tip_xy(mask)
    assert np.linalg.norm(np.array(tip) - apex(start, end, radius)) <= 2.0


def test_empty_and_tiny_masks_have_no_tip():
    mask = np.zeros((HEIGHT, WIDTH), dtype=bool)
    assert tool_tip_xy(mask) is None
    mask[10:13, 10:13] = True  # 9 px < min_area_px
    assert tool_tip_xy(mask) is None
    assert tool_tip_xy(mask, TipParams(min_area_px=9)) == (pytest.approx(11.0), pytest.approx(11.0))


def test_tip_band_centroid_is_the_mean_of_the_farthest_pixels():
    # A 5-row bar from the left border to column 30: distances from the entry (column 0, rows
    # 10..14) are exact; with band 1.5 the tip pixels are those with distance >= max - 1.5.
    mask = np.zeros((30, 40), dtype=bool)
    mask[10:15, 0:31] = True
    rows, cols = np.nonzero(mask)
    entry = [(0, r) for r in range(10, 15)]
    dist = np.array([min(math.hypot(c - ex, r - ey) for ex, ey in entry) for r, c in zip(rows, cols)])
    keep = dist >= dist.max() - 1.5
    expected = (cols[keep].mean(), rows[keep].mean())
    tip = tool_tip_xy(mask, TipParams(tip_band_px=1.5))
    assert tip == (pytest.approx(expected[0], abs=1e-3), pytest.approx(expected[1], abs=1e-3))


def test_tip_rejects_bad_input():
    with pytest.raises(ValueError, match="tool_mask: expected a 2-D bool"):
        tool_tip_xy(np.zeros((4, 4), dtype=np.uint8))
    with pytest.raises(ValueError, match="min_area_px"):
        TipParams(min_area_px=0)


def slow_crop(image, center_xy, size):
    """Pixel-by-pixel reference of crop_centered."""
    out = np.zeros((size, size) + image.shape[2:], dtype=image.dtype)
    cx, cy = math.floor(center_xy[0] + 0.5), math.floor(center_xy[1] + 0.5)
    for i in range(size):
        for j in range(size):
            y, x = cy - size // 2 + i, cx - size // 2 + j
            if 0 <= y < image.shape[0] and 0 <= x < image.shape[1]:
                out[i, j] = image[y, x]
    return out


@pytest.mark.parametrize(
    ("center", "size"), [((0.0, 0.0), 5), ((11.0, 9.0), 6), ((5.4, 4.6), 7), ((30.0, 30.0), 4), ((6.0, 5.0), 25)]
)
def test_crop_centered_matches_a_pixel_loop(center, size):
    image = np.arange(10 * 12 * 3, dtype=np.uint16).reshape(10, 12, 3) + 1  # no zeros inside the image
    out = crop_centered(image, center, size)
    assert out.shape == (size, size, 3) and out.dtype == image.dtype
    np.testing.assert_array_equal(out, slow_crop(image, center, size))


def test_crop_at_the_corner_pads_with_zeros():
    image = np.full((10, 12, 3), 7, dtype=np.uint8)
    out = crop_centered(image, (0, 0), 5)
    assert out.shape == (5, 5, 3)
    assert (out[:2] == 0).all() and (out[:, :2] == 0).all()
    assert (out[2:, 2:] == 7).all()
    gray = crop_centered(image[..., 0], (11, 9), 4)  # 2-D in, 2-D out
    assert gray.shape == (4, 4) and gray[2, 2] == 7 and gray[3, 3] == 0


def test_crop_rejects_bad_arguments():
    with pytest.raises(ValueError, match="center_xy"):
        crop_centered(np.zeros((4, 4)), (np.nan, 1), 3)
    with pytest.raises(ValueError, match="image"):
        crop_centered(np.zeros(4), (1, 1), 3)
