"""The diagnostics' measurements and rules on worked examples (contact_viz.checks), and `contact-viz check`."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from contact_viz.checks.frame import measure_frame
from contact_viz.checks.params import DiagnosticParams
from contact_viz.checks.rules import FrameChecker, PatchNumbers, fired_ranges
from contact_viz.checks.session import force_lag, frame_time_problems

FX = 300.0  # px
BASELINE = 0.005  # m
H, W = 120, 200  # px
TOOL_Z, TISSUE_Z = 0.05, 0.09  # m


def scene(shift_depth=0, bleed_px=0, scale=1.0, seed=0):
    """A bar-shaped tool entering from the left border at TOOL_Z over a textured plane at TISSUE_Z.

    Returns (mask, depth, left, right): the right image is the left scene seen with disparity
    fx B / Z (a pure horizontal shift per depth), so the true depth explains the pair exactly.
    """
    rng = np.random.default_rng(seed)
    mask = np.zeros((H, W), bool)
    mask[50:71, :120] = True  # 21 px wide shaft
    depth = np.where(mask, TOOL_Z, TISSUE_Z).astype(np.float32)
    texture_far = cv2.GaussianBlur(rng.uniform(0, 255, (H, W + 40)).astype(np.float32), (0, 0), 1.5)
    texture_tool = cv2.GaussianBlur(rng.uniform(0, 80, (H, W + 40)).astype(np.float32), (0, 0), 1.5)
    cols = np.arange(W)
    d_far, d_tool = FX * BASELINE / TISSUE_Z, FX * BASELINE / TOOL_Z
    left = np.where(mask, texture_tool[:, cols + 20], texture_far[:, cols + 20])
    right = np.empty_like(left)
    for y in range(H):  # right(x) = left scene at x + d: sample the textures at the shifted column
        x_far = np.interp(cols + d_far + 20, np.arange(W + 40), texture_far[y])
        x_tool = np.interp(cols + d_tool + 20, np.arange(W + 40), texture_tool[y])
        on_tool = mask[y, np.clip(np.round(cols + d_tool).astype(int), 0, W - 1)]
        right[y] = np.where(on_tool, x_tool, x_far)
    # a strong silhouette: the tool is much darker than the tissue
    if bleed_px:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * bleed_px + 1, 2 * bleed_px + 1))
        grown = cv2.dilate(mask.astype(np.uint8), k).astype(bool)
        depth = np.where(grown, TOOL_Z, TISSUE_Z).astype(np.float32)
    if shift_depth:
        depth = np.roll(depth, shift_depth, axis=0)
    return mask, depth * scale, left.astype(np.float32), right.astype(np.float32)


def test_clean_scene_measures_as_expected_by_hand():
    mask, depth, left, right = scene()
    m = measure_frame(mask, depth, left, right, FX, BASELINE, DiagnosticParams(tool_diameter_mm=3.5))
    assert m.tool_area_px == 21 * 120 and m.touches_border
    assert m.extra_blob_px == 0
    # shaft 21 px at 5 cm + radius behind: 2 r - 1 with r the largest inscribed disc
    assert abs(m.shaft_width_px - 21) <= 1.5
    expected_ratio = m.shaft_width_px * (TOOL_Z + 0.00175) / FX / 0.0035
    assert m.width_ratio == pytest.approx(expected_ratio, rel=1e-6)
    assert m.inside_far_fraction == 0 and m.outside_tool_fraction == 0 and m.hole_fraction == 0
    assert m.edge_support > 0.9
    assert m.residual_ratio < 0.8


def test_each_failure_moves_its_measure():
    params = DiagnosticParams(tool_diameter_mm=3.5)
    clean = measure_frame(*scene(), FX, BASELINE, params)
    bled = measure_frame(*scene(bleed_px=4), FX, BASELINE, params)
    assert bled.outside_tool_fraction > 0.9 > clean.outside_tool_fraction  # tool depth 4 px onto tissue
    shifted = measure_frame(*scene(shift_depth=5), FX, BASELINE, params)
    assert shifted.inside_far_fraction > 0.2 and shifted.outside_tool_fraction > 0.2
    scaled = measure_frame(*scene(scale=1.3), FX, BASELINE, params)
    assert scaled.width_ratio == pytest.approx(clean.width_ratio * 1.3, rel=0.05)
    assert scaled.residual_ratio > 1.1 > clean.residual_ratio
    mask, depth, left, right = scene()
    holes = depth.copy()
    holes[40:81, 60:140] = np.nan
    assert measure_frame(mask, holes, left, right, FX, BASELINE, params).hole_fraction > 0.3
    blob = mask.copy()
    blob[10:20, 160:175] = True  # 150 px away from the tool, not at the border
    assert measure_frame(blob, depth, left, right, FX, BASELINE, params).extra_blob_px == pytest.approx(150, rel=0.1)  # sampled every 2 px
    fragment = mask.copy()
    fragment[100:120, 0:10] = True  # at the border and far: another instrument
    assert measure_frame(fragment, depth, left, right, FX, BASELINE, params).extra_blob_px == pytest.approx(200, rel=0.1)
    drifted = np.roll(mask, 6, axis=0)  # mask off the tool: contour on texture, tool depth left outside it
    d = measure_frame(drifted, depth, left, right, FX, BASELINE, params)
    assert d.edge_support < 0.5 < clean.edge_support and d.outside_tool_fraction > 0.3


def _doubled(mask, depth, left, right):
    """The same scene at twice the resolution: every pixel repeated 2 x 2 (so shrinking it back is exact)."""
    up = lambda a: np.repeat(np.repeat(a, 2, axis=0), 2, axis=1)  # noqa: E731
    return up(mask), up(depth), up(left), up(right)


@pytest.mark.parametrize("case", [{}, {"bleed_px": 4}, {"shift_depth": 5}, {"scale": 1.3}, {"drift": 6}])
def test_checks_at_half_resolution_measure_what_full_resolution_measures(case):
    """A frame twice the analysis width is measured on every 2nd pixel: on a scene doubled by repeating
    pixels, the measures equal those of the original scene at full resolution (areas in the doubled
    image's pixels), and the contour evidence lands on the doubled image's pixels."""
    from contact_viz.checks.frame import analysis_step, shrink_grey

    params = DiagnosticParams(tool_diameter_mm=3.5)
    drift = case.pop("drift", 0)
    mask, depth, left, right = scene(**case)
    if drift:
        mask = np.roll(mask, drift, axis=0)
    ref = measure_frame(mask, depth, left, right, FX, BASELINE, params, evidence=True)
    big = _doubled(mask, depth, left, right)
    half = replace(params, analysis_width_px=W)  # 2 W px wide: every 2nd pixel
    assert analysis_step(2 * W, half) == 2 and analysis_step(W, half) == 1
    m = measure_frame(big[0], big[1], shrink_grey(big[2], 2), shrink_grey(big[3], 2), 2 * FX, BASELINE, half,
                      evidence=True)
    assert m.tool_area_px == 4 * ref.tool_area_px and m.touches_border == ref.touches_border
    assert m.shaft_width_px == 2 * ref.shaft_width_px and m.extra_blob_px == 4 * ref.extra_blob_px
    for name in ("inside_far_fraction", "outside_tool_fraction", "hole_fraction", "beside_valid_fraction",
                 "width_ratio", "residual_ratio"):
        assert getattr(m, name) == pytest.approx(getattr(ref, name), rel=1e-5, abs=1e-6), name
    # the image gradient is smoothed by the shrinking there, by a 3x3 Gaussian at full size: same verdict
    assert (m.edge_support < params.min_edge_support) == (ref.edge_support < params.min_edge_support)
    assert m.edge_support == pytest.approx(ref.edge_support, abs=0.1)
    assert m.evidence.step == 2 and m.evidence.residual.shape == ref.evidence.residual.shape
    np.testing.assert_array_equal(m.evidence.contour_xy, 2 * ref.evidence.contour_xy)
    assert big[0][m.evidence.contour_xy[:, 1].astype(int), m.evidence.contour_xy[:, 0].astype(int)].all()
    with pytest.raises(ValueError, match="left_grey must be 120x200 px"):
        measure_frame(*big, 2 * FX, BASELINE, half)


def _measures(**kw):
    mask, depth, left, right = scene()
    base = measure_frame(mask, depth, left, right, FX, BASELINE, DiagnosticParams(tool_diameter_mm=3.5))
    return replace(base, **kw)


def codes(checker, index, measures, patch=None):
    return [d.code for d in checker.check(index, measures, patch)[0]]


def test_rules_fire_on_their_case_only_and_thresholds_are_strict():
    p = DiagnosticParams(tool_diameter_mm=3.5)
    checker = FrameChecker(p, W)
    ok = _measures()
    assert codes(checker, 0, ok) == []
    assert codes(checker, 1, replace(ok, depth_digest=b"x")) == []
    assert codes(checker, 2, replace(ok, inside_far_fraction=p.max_inside_far_fraction, depth_digest=b"y")) == []
    assert codes(checker, 3, replace(ok, inside_far_fraction=0.5, depth_digest=b"z")) == ["mask_on_tissue"]
    assert codes(checker, 4, replace(ok, outside_tool_fraction=0.9, depth_digest=b"a")) == ["tool_depth_outside"]
    assert codes(checker, 5, replace(ok, hole_fraction=0.9, depth_digest=b"b")) == ["depth_holes"]
    assert codes(checker, 6, replace(ok, residual_ratio=2.0, depth_digest=b"c")) == ["stereo_residual"]
    assert codes(checker, 7, replace(ok, edge_support=0.1, depth_digest=b"d")) == ["mask_image_edges"]
    assert codes(checker, 8, replace(ok, width_ratio=2.0, depth_digest=b"e")) == ["tool_width"]
    assert codes(checker, 9, replace(ok, width_ratio=0.5, depth_digest=b"f")) == ["tool_width"]
    assert codes(checker, 10, replace(ok, extra_blob_px=500, extra_blob_xy=(1.0, 2.0), depth_digest=b"g")) == \
        ["extra_blob"]
    # frozen: same bytes as the previous frame while the image changed; not when nothing changed
    assert codes(checker, 11, replace(ok, depth_digest=b"g", thumb=ok.thumb + 10)) == ["frozen_depth"]
    assert codes(checker, 12, replace(ok, depth_digest=b"g", thumb=ok.thumb + 10)) == []


def test_border_entry_and_exit_and_patch_moves_are_not_failures():
    p = DiagnosticParams()
    checker = FrameChecker(p, 200)
    ok = _measures()
    # the tool enters at the border: the area grows fast, but the mask touches the border
    for i, area in enumerate((50, 200, 800, 2000, 2500, 2500, 2500, 2500)):
        assert codes(checker, i, replace(ok, tool_area_px=area, depth_digest=bytes([i]))) == []
    # it leaves: shrinking at the border, then gone: no dropout
    for i, area in enumerate((1500, 600, 150), start=8):
        assert codes(checker, i, replace(ok, tool_area_px=area, depth_digest=bytes([i]))) == []
    assert codes(checker, 11, replace(ok, tool_area_px=0, depth_digest=b"q")) == []
    # a dropout: a full-size mask, then nothing
    checker = FrameChecker(p, 200)
    for i in range(3):
        codes(checker, i, replace(ok, depth_digest=bytes([i])))
    assert codes(checker, 3, replace(ok, tool_area_px=0, touches_border=False, depth_digest=b"r")) == \
        ["mask_dropout"]
    # away from the border an area jump fires
    checker = FrameChecker(p, 200)
    codes(checker, 0, replace(ok, touches_border=False, depth_digest=b"1"))
    assert "mask_area_jump" in codes(checker, 1, replace(ok, touches_border=False, tool_area_px=ok.tool_area_px * 3,
                                                          depth_digest=b"2"))
    # distance jumps: explained when the patch moved (another part of the tool), not otherwise
    checker = FrameChecker(p, 200)
    codes(checker, 0, replace(ok, depth_digest=b"a"), PatchNumbers(0.010, (50.0, 50.0), None))
    assert codes(checker, 1, replace(ok, depth_digest=b"b"), PatchNumbers(0.005, (90.0, 50.0), None)) == []
    assert codes(checker, 2, replace(ok, depth_digest=b"c"), PatchNumbers(0.015, (91.0, 50.0), None)) == \
        ["distance_jump"]
    # far away the allowed jump grows with the distance (5 mm + 60%: 10 mm at 15 mm is within 14 mm)
    assert codes(checker, 3, replace(ok, depth_digest=b"d"), PatchNumbers(0.025, (91.0, 50.0), None)) == []


def test_a_check_fires_on_a_clear_crossing_and_stops_on_a_clear_return():
    """The margin (DiagnosticParams.margin): a score must pass 1 + margin to fire, then stays fired until it falls
    below 1 - margin; a score in between keeps the decision of the frame before."""
    p = DiagnosticParams(margin=0.05)
    checker = FrameChecker(p, 200)
    ok = _measures()
    steps = [(1.02, []), (1.06, ["tool_width"]), (0.97, ["tool_width"]), (1.02, ["tool_width"]), (0.94, []),
             (1.04, []), (1.051, ["tool_width"])]
    for i, (score, expected) in enumerate(steps):
        measures = replace(ok, width_ratio=score * p.max_width_ratio, depth_digest=bytes([i]))
        assert codes(checker, i, measures) == expected, (i, score)
    # a frame the check is not decided at (here: a bad frame) starts the next one unfired
    checker.reset_previous()
    assert codes(checker, 9, replace(ok, width_ratio=1.02 * p.max_width_ratio, depth_digest=b"z")) == []
    # margin 0: the threshold itself decides
    strict = FrameChecker(replace(p, margin=0.0), 200)
    assert codes(strict, 0, replace(ok, width_ratio=1.02 * p.max_width_ratio)) == ["tool_width"]


def test_the_patch_moved_is_measured_between_its_places():
    """The centre is the argmin of a score that can be flat; where two frames' places (the band pixels within
    PLACE_M of the best score) touch, the patch stayed, however far its centre went."""
    from contact_viz.checks.rules import PLACE_M, patch_place

    band_xy = np.array([[10.0, 50.0], [11.0, 50.0], [40.0, 50.0], [41.0, 50.0]])
    place = patch_place(band_xy, np.array([0.002, 0.002 + PLACE_M / 2, 0.002 + 2 * PLACE_M, np.nan]), 0.002)
    np.testing.assert_array_equal(place, band_xy[:2])
    assert patch_place(band_xy, np.full(4, np.nan), float("nan")) is None
    ok = _measures()
    near = np.array([[10.0, 50.0], [30.0, 50.0]])  # a flat score: two places 20 px apart score alike
    for centres, expected in (((10.0, 30.0), ["distance_jump"]), ((30.0, 10.0), ["distance_jump"])):
        checker = FrameChecker(DiagnosticParams(), 200)
        codes(checker, 0, replace(ok, depth_digest=b"a"), PatchNumbers(0.004, (centres[0], 50.0), None, near))
        assert codes(checker, 1, replace(ok, depth_digest=b"b"),
                     PatchNumbers(0.016, (centres[1], 50.0), None, near[::-1])) == expected
    # the same centres without places: the patch moved 20 px (more than 1% of 200 px), no failure
    checker = FrameChecker(DiagnosticParams(), 200)
    codes(checker, 0, replace(ok, depth_digest=b"a"), PatchNumbers(0.004, (10.0, 50.0), None))
    assert codes(checker, 1, replace(ok, depth_digest=b"b"), PatchNumbers(0.016, (30.0, 50.0), None)) == []


def test_force_lag_finds_an_injected_offset_and_not_a_clean_one():
    rng = np.random.default_rng(0)
    n = 120
    t = np.arange(n) / 30.0
    contact = np.zeros(n, bool)
    for a in (20, 60, 95):
        contact[a:a + 15] = True
    signal = np.where(contact, 3.0, 1.5) + 0.05 * rng.standard_normal(n)
    force = np.where(contact, 4.0, 0.0) + 0.1 * rng.standard_normal(n)
    clean = force_lag(force, signal, t)
    assert clean is not None and not clean.fired and abs(clean.lag_frames) <= 1
    late = force_lag(np.roll(force, 6), signal, t)
    assert late.fired and late.lag_frames == 6 and late.lag_s == pytest.approx(0.2)
    early = force_lag(np.roll(force, -5), signal, t)
    assert early.fired and early.lag_frames == -5
    assert force_lag(np.full(n, np.nan), signal, t) is None


def test_force_lag_needs_a_force_above_its_noise():
    """A 30-frame session without contact (the tool approaching, the force only sensor noise of 0.1 N): the
    noise's crossings of its own 20th-95th percentile range paired with the approaching signal read as a lag
    (min_force_swing_n 0: it fires); below a 0.5 N swing no lag is measured. A real contact of 3 N in the same
    noise, 6 frames late, still fires."""
    rng = np.random.default_rng(3)
    n = 30
    t = np.arange(n) / 30.0
    signal = np.linspace(1.3, 2.3, n) + 0.03 * rng.standard_normal(n)  # nearing the tissue, never touching it
    hits = 0
    for seed in range(20):
        noise = 0.1 * np.random.default_rng(seed).standard_normal(n)
        assert force_lag(noise, signal, t) is None
        loose = force_lag(noise, signal, t, DiagnosticParams(min_force_swing_n=0.0))
        hits += loose is not None and loose.fired
    assert hits >= 3  # without the swing rule the noise alone fires: 4 of these 20 draws
    contact = np.zeros(n, bool)
    contact[8:20] = True
    force = np.roll(np.where(contact, 3.0, 0.0), 6) + 0.1 * rng.standard_normal(n)
    stepped = np.where(contact, 3.0, 1.5) + 0.03 * rng.standard_normal(n)
    late = force_lag(force, stepped, t)
    assert late is not None and late.fired and late.lag_frames == 6


def test_frame_time_problems_and_ranges():
    t = np.array([0, 1, 2, 3, 4, 4, 5, 6, 13, 14]) / 30.0  # frame 5 repeats a time; 6 frames missing before 8
    assert frame_time_problems(t) == [5, 8]
    assert fired_ranges([3, 1, 2, 7, 9, 8]) == [(1, 3), (7, 9)]


def test_params_are_checked():
    with pytest.raises(ValueError, match="tool_diameter_mm"):
        DiagnosticParams(tool_diameter_mm=0)
    with pytest.raises(ValueError, match="mask_area_jump"):
        DiagnosticParams(mask_area_jump=0)
    with pytest.raises(ValueError, match="min_tool_area_px"):
        DiagnosticParams(min_tool_area_px=0)
    with pytest.raises(ValueError, match="max_width_ratio"):
        DiagnosticParams(max_width_ratio=0.9)


@pytest.fixture(scope="module")
def small_session(tmp_path_factory):
    from contact_viz.synth import SynthParams, generate_session

    return generate_session(tmp_path_factory.mktemp("check") / "cup_s", SynthParams(
        phantom="cup", frames=24, seed=3, width=160, height=90))


def test_check_command_table_json_and_exit_status(small_session, tmp_path):
    from contact_viz.cli import app
    from contact_viz.pipeline.check import check_session
    from contact_viz.synth.faults import inject_fault

    broken = tmp_path / "broken"
    inject_fault(small_session, broken, "mask_dropout", range(10, 14))
    runner = CliRunner()
    out = tmp_path / "checks.json"
    result = runner.invoke(app, ["check", str(small_session), str(broken), "--json", str(out)])
    assert result.exit_code == 0, result.output
    row = next(line for line in result.output.splitlines() if line.strip().startswith("mask_dropout"))
    assert row.split()[1:3] == ["4", "000010-000013"], result.output  # frames named by stem, as in left/
    data = json.loads(out.read_text())
    assert [s["n_frames"] for s in data["sessions"]] == [24, 24]
    dropout = data["sessions"][1]["checks"]["mask_dropout"]
    assert dropout["ranges"] == [[10, 13]] and dropout["stem_ranges"] == [["000010", "000013"]]
    assert dropout["first_message"].startswith("frame 000010: ")
    assert data["sessions"][1] == json.loads(json.dumps(check_session(broken).to_dict() | {
        "elapsed_s": data["sessions"][1]["elapsed_s"]}))
    strict = runner.invoke(app, ["check", str(broken), "--strict"])
    assert strict.exit_code == 1
    missing = runner.invoke(app, ["check", str(tmp_path / "nope"), "--json", str(tmp_path / "x.json")])
    assert missing.exit_code == 2 and "nope" in missing.output
    assert not list(small_session.rglob("*.json.tmp"))


def test_check_session_interface_and_processes_agree(small_session):
    from contact_viz.pipeline.check import check_session

    one = check_session(small_session)
    two = check_session(small_session, params=None, cache_dir=None, processes=2)
    assert one.n_frames == 24 and one.fired == two.fired
    assert isinstance(one.fired, dict) and all(isinstance(r, tuple) for v in one.fired.values() for r in v)
    assert math.isfinite(json.loads(json.dumps(one.to_dict()))["elapsed_s"])


# ------------------------------------------------------------------------------------------
# Frames named as the user named them: by stem
# ------------------------------------------------------------------------------------------


def test_frame_ranges_read_as_stems():
    from contact_viz.console import frame_name, frames_text, stem_runs

    stems = ["000020", "000021", "000022", "000024", "000025", "x1"]
    assert stem_runs([(0, 2), (3, 5)], stems) == [("000020", "000022"), ("000024", "000025"), ("x1", "x1")]
    assert frames_text([(0, 5)], stems, 8) == "000020-000022, 000024-000025, x1"  # runs of consecutive numbers
    real = ["021300", "022225", "022650", "023125"]  # a clip's frame numbers, far apart: one by one
    assert frames_text([(0, 3)], real, 8) == "021300, 022225, 022650, 023125"
    assert frames_text([(0, 3)], real, 2) == "021300, 022225, ... (4 ranges)"
    assert frames_text([(0, 2), (4, 4)], None, 8) == "0-2, 4"  # no stems known: indices
    assert frame_name(3, stems) == "000024" and frame_name(3, ()) == "3"


def test_check_names_frames_by_stems_that_skip_numbers(small_session, tmp_path):
    """A session whose stems are frame numbers 25 apart (as a clip's frames sampled from a video): every
    flagged frame is named by its stem, in the table, the JSON and the first message."""
    from contact_viz.cli import app
    from contact_viz.synth.faults import inject_fault

    broken = tmp_path / "broken"
    inject_fault(small_session, broken, "mask_dropout", range(10, 14))
    sampled = tmp_path / "sampled"
    for sub in ("left", "right", "masks", "depth"):
        (sampled / sub).mkdir(parents=True)
        for path in (broken / sub).iterdir():
            (sampled / sub / f"{25 * int(path.stem):06d}{path.suffix}").write_bytes(path.read_bytes())
    (sampled / "K.txt").write_bytes((broken / "K.txt").read_bytes())
    out = tmp_path / "checks.json"
    result = CliRunner().invoke(app, ["check", str(sampled), "--json", str(out)])
    assert result.exit_code == 0, result.output
    row = next(line for line in result.output.splitlines() if line.strip().startswith("mask_dropout"))
    assert "000250, 000275, 000300, 000325" in row, result.output
    dropout = json.loads(out.read_text())["sessions"][0]["checks"]["mask_dropout"]
    assert dropout["ranges"] == [[10, 13]]  # indices, as before
    assert dropout["stem_ranges"] == [["000250", "000250"], ["000275", "000275"], ["000300", "000300"],
                                      ["000325", "000325"]]
    assert dropout["first_message"].startswith("frame 000250: ")


def test_the_debugger_summary_names_frames_by_stem():
    from contact_viz.viz.options import RunSummary

    summary = RunSummary(frames=30, bad_frames=0, diagnostic_counts={"mask_on_tissue": 4, "not_rectified": 30},
                         interrupted=False, elapsed_s=1.0, wait_s=0.0, image_wait_s=0.0, prepare_s=0.0, log_s=0.0,
                         diagnostic_ranges={"mask_on_tissue": [(20, 22), (24, 24)], "not_rectified": [(0, 29)]},
                         nearest_frames={1: 30}, closest=(1, 0.8, 21), instrument_frames={1: 30},
                         frame_stems=tuple(f"{k:06d}" for k in range(30)),
                         session_messages={"not_rectified": "left and right not rectified: 3.3 px vertical offset"})
    lines = summary.lines()
    assert "  mask_on_tissue on 4 frames: 000020-000022, 000024" in lines
    assert "  not_rectified on 30 frames: left and right not rectified: 3.3 px vertical offset" in lines
    assert "nearest instrument: 1 (nearest on 30 frames); closest: 0.8 mm at frame 000021" in lines
    unnamed = replace(summary, frame_stems=())  # a summary made without stems: indices, as before
    assert "  mask_on_tissue on 4 frames: 20-22, 24" in unnamed.lines()
