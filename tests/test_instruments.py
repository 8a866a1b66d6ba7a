"""Several instruments in one scene: each instrument's distance against exact answers (fronto-parallel
instruments over flat tissue), with the other instrument nearer the camera or between the instrument and
the tissue, with and without selecting instruments; extract's rows per instrument."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from PIL import Image

from contact_viz.geometry.instruments import instrument_ids, instrument_patches, without_other_instruments
from contact_viz.geometry.patch import compute_patch
from contact_viz.io.session import open_session
from contact_viz.params import PatchParams

H, W = 160, 240
TISSUE_M = 0.100  # flat tissue, fronto-parallel, m
BAR_1 = (slice(0, 110), slice(80, 110))  # instrument 1: rows, columns (30 px wide, ends 50 px above the bottom)
BAR_2 = (slice(0, 90), slice(114, 140))  # instrument 2: 4 px right of instrument 1


def scene(depth_1_m: float, depth_2_m: float | None) -> tuple[np.ndarray, np.ndarray]:
    """(depth (H, W) float32 m, object ids (H, W) uint16): two fronto-parallel bars over flat tissue."""
    depth = np.full((H, W), TISSUE_M, np.float32)
    ids = np.zeros((H, W), np.uint16)
    depth[BAR_1], ids[BAR_1] = depth_1_m, 1
    if depth_2_m is not None:
        depth[BAR_2], ids[BAR_2] = depth_2_m, 2
    return depth, ids


# (instrument 1's depth, instrument 2's depth): 2 nearer the camera than 1; 2 between 1 and the tissue
# (the issue's cases: instrument 1 read -3.0 mm instead of 8 and 3.0 instead of 6 with instrument 2 taken for tissue)
ARRANGEMENTS = {"2 in front": (0.092, 0.089), "2 between 1 and the tissue": (0.094, 0.097)}


@pytest.mark.parametrize("arrangement", ARRANGEMENTS)
def test_each_instrument_measures_its_own_gap(arrangement):
    depth_1, depth_2 = ARRANGEMENTS[arrangement]
    depth, ids = scene(depth_1, depth_2)
    patches = instrument_patches(depth, ids)
    assert set(patches) == {1, 2}
    assert abs(patches[1].distance_m - (TISSUE_M - depth_1)) <= 0.0003
    assert abs(patches[2].distance_m - (TISSUE_M - depth_2)) <= 0.0003
    # Selecting one instrument excludes the other all the same.
    only_1 = instrument_patches(depth, ids, selected=[1])
    assert set(only_1) == {1} and only_1[1].distance_m == patches[1].distance_m
    # Without the exclusion (the other instrument taken for tissue) instrument 1's distance is wrong:
    # the band beside it lies on instrument 2.
    naive = compute_patch(depth, ids == 1)
    assert abs(abs(naive.distance_m) - 0.003) <= 0.0003


def test_one_instrument_is_compute_patch_itself():
    depth, ids = scene(0.095, None)
    rng = np.random.default_rng(3)
    depth += rng.normal(0, 0.0003, depth.shape).astype(np.float32)
    (single,) = instrument_patches(depth, ids).values()
    plain = compute_patch(depth, ids == 1)
    assert single.distance_m == plain.distance_m and single.center_xy == plain.center_xy
    assert without_other_instruments(depth, ids, 1, 3.0) is depth  # no copy when there is no other


def test_the_other_instrument_and_its_safety_ring_are_no_tissue():
    depth, ids = scene(0.092, 0.089)
    out = without_other_instruments(depth, ids, 1, 3.0)
    yy, xx = np.mgrid[0:H, 0:W]
    # distance to the bar of instrument 2 (rows 0..89, columns 114..139), literally
    dy = np.maximum(0, yy - 89)
    dx = np.maximum(0, np.maximum(114 - xx, xx - 139))
    near_2 = dy * dy + dx * dx <= 9
    assert np.array_equal(np.isnan(out), near_2)
    assert np.array_equal(out[~near_2], depth[~near_2])
    assert instrument_ids(ids) == (1, 2) and instrument_ids(ids, [2, 5]) == (2,)


def write_session(root, frames):
    """A session whose frame k has object ids ``frames[k][1]`` (palettized PNG) and depth ``frames[k][0]``."""
    from contact_viz.synth.files import davis_palette

    for sub in ("left", "masks", "depth"):
        (root / sub).mkdir(parents=True)
    (root / "K.txt").write_text(f"500 0 {W / 2} 0 500 {H / 2} 0 0 1\n0.005\n")
    for k, (depth, ids) in enumerate(frames):
        image = Image.fromarray(ids.astype(np.uint8), mode="L")
        image.putpalette(davis_palette())
        image.save(root / "masks" / f"{k}.png")
        np.save(root / "depth" / f"{k}.npy", depth)
        Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(root / "left" / f"{k}.png")


def test_extract_writes_a_row_per_frame_and_instrument(tmp_path):
    from contact_viz.pipeline.extract import extract_features, write_features, run_config

    frames = [scene(0.092, 0.089), scene(0.092, None), scene(0.094, 0.097), (np.full((H, W), TISSUE_M, np.float32),
                                                                             np.zeros((H, W), np.uint16))]
    write_session(tmp_path / "s", frames)
    session = open_session(tmp_path / "s")
    rows = extract_features(session)
    assert [(r["frame"], r["tool"]) for r in rows] == [("0", 1), ("0", 2), ("1", 1), ("2", 1), ("2", 2), ("3", "")]
    gaps = {("0", 1): 0.008, ("0", 2): 0.011, ("1", 1): 0.008, ("2", 1): 0.006, ("2", 2): 0.003}
    for r in rows[:-1]:
        assert abs(float(r["distance_m"]) - gaps[(r["frame"], r["tool"])]) <= 0.0003
    assert rows[-1]["reason"] == "empty_mask"
    path = write_features(rows, tmp_path / "f.csv", run_config(session))
    with path.open(newline="") as handle:
        header = next(csv.reader(handle))
    assert header[:3] == ["frame", "tool", "timestamp"]
    # --object-id 2: only instrument 2's rows, the same distances; instrument 1 is still no tissue
    selected = extract_features(open_session(tmp_path / "s", object_ids=(2,)))
    assert [(r["frame"], r["tool"]) for r in selected] == [("0", 2), ("1", ""), ("2", 2), ("3", "")]
    assert [r["distance_m"] for r in selected if r["tool"] == 2] == [r["distance_m"] for r in rows if r["tool"] == 2]


def test_an_id_swap_swaps_the_rows(tmp_path):
    depth, ids = scene(0.092, 0.089)
    swapped = np.where(ids == 1, 2, np.where(ids == 2, 1, 0)).astype(np.uint16)
    write_session(tmp_path / "s", [(depth, ids), (depth, swapped)])
    rows = extract_features_of(tmp_path / "s")
    by = {(r["frame"], r["tool"]): float(r["distance_m"]) for r in rows}
    assert by[("0", 1)] == by[("1", 2)] and by[("0", 2)] == by[("1", 1)]


def extract_features_of(path):
    from contact_viz.pipeline.extract import extract_features

    return extract_features(open_session(path))
