"""No depth beside the tool: the checks name the depth source (SGBM stereo, a depth file), not the mask.

Where the depth source returns (almost) no depth just outside the tool's mask, `depth_holes` fires with
the cause "no depth beside the tool: stereo failed here" (SGBM) or "...: the depth source failed here"
(depth/ or disparity/ files), and the depth-against-mask checks do not blame the mask; a real mask bleed
still fires `mask_on_tissue` with the mask as the cause.
"""

from __future__ import annotations

import json
import math
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from contact_viz.checks.frame import measure_frame
from contact_viz.checks.params import DiagnosticParams
from contact_viz.checks.rules import CHECKS, FrameChecker, no_depth_beside_cause

sys.path.insert(0, str(Path(__file__).parent))
from test_checks import BASELINE, FX, TISSUE_Z, W, scene  # noqa: E402  (the checks' worked example)

STEREO_FAILED = "no depth beside the tool: stereo failed here"
SOURCE_FAILED = "no depth beside the tool: the depth source failed here"
MASK_CAUSE = CHECKS["mask_on_tissue"][1]
PARAMS = DiagnosticParams(tool_diameter_mm=3.5)


def _outside(mask: np.ndarray, r_px: float) -> np.ndarray:
    """Pixels 1 to ``r_px`` px outside the mask (the tool's silhouette)."""
    dist = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5)
    return (dist > 0) & (dist <= r_px)


def _rim(mask: np.ndarray, r_px: float = 2.0) -> np.ndarray:
    """Mask pixels within ``r_px`` px of its edge (the image border is not an edge)."""
    padded = cv2.copyMakeBorder(mask.astype(np.uint8), 1, 1, 1, 1, cv2.BORDER_REPLICATE)
    return mask & (cv2.distanceTransform(padded, cv2.DIST_L2, 5)[1:-1, 1:-1] <= r_px)


def _check(measures, depth_source="sgbm", params=PARAMS):
    fired, scores = FrameChecker(params, W, depth_source).check(0, measures, None)
    return {d.code: d for d in fired}, scores


def test_no_depth_beside_the_tool_names_the_depth_source_not_the_mask():
    mask, depth, left, right = scene()
    gone = depth.copy()
    gone[_outside(mask, 16)] = np.nan  # the mask is clean; no depth 1-16 px beside the tool, tissue valid beyond
    # and, as stereo leaves it at a failed edge, a few of the rim's pixels carry the tissue's depth
    rng = np.random.default_rng(1)
    gone[_rim(mask) & (rng.random(mask.shape) < 0.05)] = TISSUE_Z
    m = measure_frame(mask, gone, left, right, FX, BASELINE, PARAMS)
    assert m.beside_valid_fraction == 0
    assert m.inside_far_fraction > PARAMS.max_inside_far_fraction  # what used to blame the mask

    fired, scores = _check(m, "sgbm")
    assert set(fired) == {"depth_holes"}, fired
    holes = fired["depth_holes"]
    assert holes.likely_cause == STEREO_FAILED and holes.message.endswith(": " + STEREO_FAILED)
    assert "0% valid just outside the mask (< 15%" in holes.message
    assert holes.value == 0 and scores["depth_holes"] > 1 and "mask_on_tissue" not in scores
    assert not any("mask" in d.likely_cause for d in fired.values())
    for source in ("depth", "disparity"):  # a learned depth or disparity file
        assert _check(m, source)[0]["depth_holes"].likely_cause == SOURCE_FAILED
    assert no_depth_beside_cause("sgbm") == STEREO_FAILED

    # the control: without the rule the same frame blames the mask
    old, _ = _check(m, "sgbm", replace(PARAMS, min_beside_valid_fraction=0.0))
    assert old["mask_on_tissue"].likely_cause == MASK_CAUSE and old["depth_holes"].likely_cause != STEREO_FAILED


def test_no_depth_beside_the_tool_needs_a_clear_crossing_and_nan_is_not_missing():
    ok = measure_frame(*scene(), FX, BASELINE, PARAMS)
    assert ok.beside_valid_fraction == 1 and _check(ok)[0] == {}
    t = PARAMS.min_beside_valid_fraction / (1 + PARAMS.margin)  # fires below this (the score t / value above 1 + m)
    assert _check(replace(ok, beside_valid_fraction=t + 1e-3))[0] == {}
    below = _check(replace(ok, beside_valid_fraction=t - 1e-3, inside_far_fraction=0.5, outside_tool_fraction=0.9))[0]
    assert set(below) == {"depth_holes"} and below["depth_holes"].likely_cause == STEREO_FAILED
    assert _check(replace(ok, beside_valid_fraction=math.nan))[0] == {}
    # holes on the tool with depth beside it: the usual cause
    holes = _check(replace(ok, hole_fraction=0.9))[0]["depth_holes"]
    assert holes.likely_cause == CHECKS["depth_holes"][1] and holes.cause == ""


def test_mask_on_tissue_is_not_measured_where_the_rims_depth_is_mostly_invalid():
    mask, depth, left, right = scene()
    rim = _rim(mask, 4.0)  # the measured rim: 3.5 px deep here
    rng = np.random.default_rng(2)
    draw = rng.random(mask.shape)
    for invalid_share, measured in ((0.3, True), (0.7, False)):
        z = depth.copy()
        z[rim & (draw < invalid_share)] = np.nan
        z[rim & (draw >= invalid_share) & (draw < invalid_share + 0.05)] = TISSUE_Z  # a few far pixels
        m = measure_frame(mask, z, left, right, FX, BASELINE, PARAMS)
        assert m.beside_valid_fraction == 1
        assert (m.inside_far_fraction > PARAMS.max_inside_far_fraction) if measured else math.isnan(
            m.inside_far_fraction), (invalid_share, m.inside_far_fraction)
        assert ("mask_on_tissue" in _check(m)[0]) == measured


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    """A small synthetic session (depth files) and copies: stereo only (SGBM), stereo failing beside the
    tool (the images made flat grey 1-8 px around the mask), depth files with no depth 1-16 px around it."""
    from contact_viz.synth import SynthParams, generate_session

    root = tmp_path_factory.mktemp("stereo_checks")
    full = generate_session(root / "cup_s", SynthParams(phantom="cup", frames=24, seed=3, width=160, height=90))
    out = {"full": full}
    for name in ("sgbm", "sgbm_failed", "holes"):
        out[name] = root / name
        shutil.copytree(full, out[name])
    for name in ("sgbm", "sgbm_failed"):
        shutil.rmtree(out[name] / "depth")
    for path in sorted((full / "masks").glob("*.png")):
        mask = np.asarray(Image.open(path)) > 0
        for side in ("left", "right"):  # no texture beside the tool: SGBM finds no match there
            image_path = out["sgbm_failed"] / side / f"{path.stem}.jpg"
            image = np.array(Image.open(image_path))
            image[_outside(mask, 8)] = 128
            Image.fromarray(image).save(image_path, quality=95)
        depth_path = out["holes"] / "depth" / f"{path.stem}.npy"
        depth = np.load(depth_path)
        depth[_outside(mask, 16)] = np.nan
        np.save(depth_path, depth)
    return out


def test_mask_bleed_still_blames_the_mask(sessions, tmp_path):
    from contact_viz.pipeline.check import check_session
    from contact_viz.synth.faults import inject_fault

    bled = tmp_path / "bled"
    inject_fault(sessions["full"], bled, "mask_bleed", range(4, 12), severity=4.5, seed=0)  # 9 px at 320 px
    report = check_session(bled)
    hit = {i for a, b in report.fired.get("mask_on_tissue", []) for i in range(a, b + 1)}
    assert len(hit & set(range(4, 12))) >= 4, report.fired
    assert report.likely_causes("mask_on_tissue") == [MASK_CAUSE]
    assert MASK_CAUSE in report.messages["mask_on_tissue"]
    assert "depth_holes" not in report.fired
    assert "no depth beside the tool" not in json.dumps(report.to_dict())


def test_check_command_says_no_depth_beside_the_tool(sessions, tmp_path):
    from contact_viz.cli import app
    from contact_viz.pipeline.check import check_session

    cache = tmp_path / "cache"
    out = tmp_path / "checks.json"
    result = CliRunner().invoke(app, ["check", str(sessions["sgbm_failed"]), str(sessions["holes"]),
                                      str(sessions["sgbm"]), "--cache-dir", str(cache), "--json", str(out)])
    assert result.exit_code == 0, result.output
    tables = result.output.split("cup_s (")[1:]  # one table per session, in the order given
    assert len(tables) == 3, result.output
    failed, holes, clean = tables
    row = next(line for line in failed.splitlines() if line.strip().startswith("depth_holes"))
    assert row.rstrip().endswith(STEREO_FAILED) and " 24 " in row and "000000-000023" in row, result.output
    assert "mask_on_tissue" not in failed and "mask bleed" not in failed, failed
    row = next(line for line in holes.splitlines() if line.strip().startswith("depth_holes"))
    assert row.rstrip().endswith(SOURCE_FAILED) and "000000-000023" in row, result.output
    assert "mask_on_tissue" not in holes and "mask bleed" not in holes, holes
    assert "no depth beside the tool" not in clean, clean  # SGBM's usual gap at the tool's edge is no failure
    data = json.loads(out.read_text())["sessions"]
    assert data[0]["checks"]["depth_holes"]["likely_cause"] == STEREO_FAILED
    assert data[0]["checks"]["depth_holes"]["first_message"].endswith(STEREO_FAILED)
    assert data[1]["checks"]["depth_holes"]["likely_cause"] == SOURCE_FAILED
    assert data[0] == json.loads(json.dumps(check_session(sessions["sgbm_failed"], cache_dir=cache).to_dict() | {
        "elapsed_s": data[0]["elapsed_s"]}))
