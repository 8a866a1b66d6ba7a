"""The not_rectified check: the vertical offset of features matched between left and right, from the pure
measurement (checks.rectification) through `contact-viz check` and the debugger, and the vertical_offset fault."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

pytest.importorskip("rerun")

from test_viewer import Recording  # noqa: E402  (reads a saved recording back)

from contact_viz.checks.params import DiagnosticParams  # noqa: E402
from contact_viz.checks.rectification import pair_offsets, sample_frames, vertical_offset  # noqa: E402


def textured(height: int = 240, width: int = 320, seed: int = 0) -> np.ndarray:
    """A grey image with texture at several scales (blurred noise), uint8."""
    rng = np.random.default_rng(seed)
    out = np.zeros((height, width), np.float32)
    for sigma, weight in ((1.0, 0.5), (3.0, 1.0), (8.0, 1.5)):
        noise = cv2.GaussianBlur(rng.standard_normal((height, width)).astype(np.float32), (0, 0), sigma)
        out += weight * noise / noise.std()
    return np.clip(128 + 30 * out, 0, 255).astype(np.uint8)


def moved(image: np.ndarray, down_px: int, left_px: int) -> np.ndarray:
    """``image`` moved ``down_px`` rows down and ``left_px`` columns left (numpy slicing; edges repeated)."""
    out = np.roll(image, (down_px, -left_px), axis=(0, 1))
    if down_px > 0:
        out[:down_px] = out[down_px]
    elif down_px < 0:
        out[down_px:] = out[down_px - 1]
    if left_px > 0:
        out[:, -left_px:] = out[:, [-left_px - 1]]
    return out


@pytest.mark.parametrize("down_px", [3, -2, 0])
def test_a_known_vertical_shift_is_measured(down_px):
    left = textured()
    right = moved(left, down_px, 9)  # a stereo pair: everything 9 px of disparity, and the vertical shift
    dy = pair_offsets(left, right)
    assert dy.size >= 100
    assert abs(float(np.median(dy)) - down_px) <= 0.3
    offset = vertical_offset([(0, left, right)])
    assert offset is not None and abs(offset.offset_px - down_px) <= 0.3
    assert offset.fired == (down_px != 0) and offset.matches == dy.size
    # images shrunk twice, read in px of the full size (scale_px), as `check` reads 1080p frames
    small = [(0, cv2.resize(left, (160, 120), interpolation=cv2.INTER_AREA),
              cv2.resize(right, (160, 120), interpolation=cv2.INTER_AREA))]
    shrunk = vertical_offset(small, DiagnosticParams(min_rectification_matches=10), scale_px=2.0)
    assert shrunk is not None and abs(shrunk.offset_px - down_px) <= 0.3


def test_too_little_texture_measures_nothing():
    flat = np.full((120, 160), 128, np.uint8)
    assert pair_offsets(flat, flat).size == 0
    assert vertical_offset([(0, flat, flat)]) is None


def test_frames_are_sampled_evenly():
    assert sample_frames(range(30), 8) == [0, 4, 8, 12, 17, 21, 25, 29]  # round(k * 29 / 7): 12.4 -> 12
    assert sample_frames([5, 7, 9], 8) == [5, 7, 9]
    assert sample_frames(range(100, 200), 1) == [100]


def test_the_message_names_the_offset():
    offset = vertical_offset([(0, textured(), moved(textured(), 3, 9)), (1, textured(seed=1),
                                                                          moved(textured(seed=1), 3, 9))])
    assert offset.message().startswith("left and right not rectified: 3.0 px vertical offset (right image lower; ")
    assert "in 2 frames" in offset.message() and offset.message().endswith("threshold 0.6 px")


# ------------------------------------------------------------------------------------------
# Synthetic sessions: rectified, and with the right images moved (the vertical_offset fault)
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    from contact_viz.synth import SynthParams, generate_session
    from contact_viz.synth.faults import inject_fault

    root = tmp_path_factory.mktemp("rectification")
    clean = generate_session(root / "cup_r", SynthParams(phantom="cup", frames=20, seed=4, width=320, height=180))
    shifted = root / "shifted"
    fault = inject_fault(clean, shifted, "vertical_offset", range(20), 2.0)
    half = root / "half"
    inject_fault(clean, half, "vertical_offset", [3], 0.5)
    return {"clean": clean, "shifted": shifted, "half": half, "fault": fault}


def test_the_fault_moves_the_right_images_only(sessions):
    clean, shifted, half = sessions["clean"], sessions["shifted"], sessions["half"]
    assert sessions["fault"].kind == "vertical_offset" and sessions["fault"].frames == tuple(range(20))
    assert sessions["fault"].severity == 2.0
    for stem in ("000000", "000011"):
        assert (shifted / "left" / f"{stem}.jpg").read_bytes() == (clean / "left" / f"{stem}.jpg").read_bytes()
        before = cv2.imread(str(clean / "right" / f"{stem}.jpg"), cv2.IMREAD_GRAYSCALE).astype(float)
        after = cv2.imread(str(shifted / "right" / f"{stem}.jpg"), cv2.IMREAD_GRAYSCALE).astype(float)
        assert np.abs(after[2:] - before[:-2]).mean() < 2.0  # two rows down, up to JPEG's re-encoding
        assert np.abs(after[2:] - before[2:]).mean() > 2 * np.abs(after[2:] - before[:-2]).mean()
    # half a pixel: each row the mean of itself and the one above; frames not injected untouched
    before = cv2.imread(str(clean / "right" / "000003.jpg"), cv2.IMREAD_GRAYSCALE).astype(float)
    after = cv2.imread(str(half / "right" / "000003.jpg"), cv2.IMREAD_GRAYSCALE).astype(float)
    assert np.abs(after[1:] - (before[1:] + before[:-1]) / 2).mean() < 2.0
    assert (half / "right" / "000004.jpg").read_bytes() == (clean / "right" / "000004.jpg").read_bytes()


def test_a_rectified_synthetic_pair_reads_zero(sessions):
    from contact_viz.io.session import open_session
    from contact_viz.pipeline.check import rectification_offset

    offset = rectification_offset(open_session(sessions["clean"]))
    assert offset is not None and abs(offset.offset_px) < 0.1 and not offset.fired
    assert offset.frames == (0, 3, 5, 8, 11, 14, 16, 19) and offset.matches >= 200
    moved_offset = rectification_offset(open_session(sessions["shifted"]))
    assert abs(moved_offset.offset_px - 2.0) < 0.2 and moved_offset.fired


def test_check_names_a_pair_that_is_not_rectified(sessions, tmp_path):
    from contact_viz.cli import app

    out = tmp_path / "checks.json"
    result = CliRunner().invoke(app, ["check", str(sessions["clean"]), str(sessions["shifted"]), "--json", str(out)])
    assert result.exit_code == 0, result.output
    clean_table, shifted_table = result.output.split("cup_r")[1], result.output.split("shifted")[1]
    assert "not_rectified" not in clean_table and "not rectified" not in clean_table
    row = next(line for line in shifted_table.splitlines() if line.strip().startswith("not_rectified"))
    assert row.split()[1] == "20" and "all (2.0 px vertical offset)" in row
    assert row.rstrip().endswith("the pair is not rectified, or rectified with a wrong or stale calibration")
    said = [line.strip() for line in shifted_table.splitlines() if "left and right not rectified" in line]
    assert len(said) == 1 and said[0].startswith("left and right not rectified: 2.0 px vertical offset (right "
                                                 "image lower; median of ")
    clean, shifted = json.loads(out.read_text())["sessions"]
    assert clean["rectification"]["fired"] is False and abs(clean["rectification"]["vertical_offset_px"]) < 0.1
    assert clean["checks"]["not_rectified"]["frames"] == 0
    rect = shifted["rectification"]
    assert rect["fired"] is True and abs(rect["vertical_offset_px"] - 2.0) < 0.2
    assert rect["frames"] == ["000000", "000003", "000005", "000008", "000011", "000014", "000016", "000019"]
    assert all(abs(v - 2.0) < 0.3 for v in rect["frame_offsets_px"])
    check = shifted["checks"]["not_rectified"]
    assert check["frames"] == 20 and check["stem_ranges"] == [["000000", "000019"]]
    assert check["first_message"].startswith("left and right not rectified: 2.0 px vertical offset")
    assert shifted["params"]["max_vertical_offset_px"] == DiagnosticParams().max_vertical_offset_px
    strict = CliRunner().invoke(app, ["check", str(sessions["shifted"]), "--strict"])
    assert strict.exit_code == 1


def test_the_debugger_says_it_in_its_summary_and_recording(sessions, tmp_path):
    from contact_viz.io.session import open_session
    from contact_viz.viz.debugger import DebuggerOptions, run_debugger
    from contact_viz.viz.rerun_log import ENTITY_LOG, open_recording

    for name, fires in (("shifted", True), ("clean", False)):
        out = tmp_path / f"{name}.rrd"
        opened = open_recording(save=out)
        summary = run_debugger(open_session(sessions[name]), opened.rec, DebuggerOptions(points=False))
        opened.close()
        lines = [line for line in summary.lines() if "not_rectified" in line]
        texts = [t for _, t, _ in Recording(out).texts(ENTITY_LOG) if "not rectified" in t]
        if not fires:
            assert lines == [] and texts == [], (lines, texts)
            continue
        assert len(lines) == 1 and lines[0].startswith("  not_rectified on 20 frames: left and right not rectified: "
                                                       "2.0 px vertical offset"), summary.lines()
        assert summary.diagnostic_ranges["not_rectified"] == [(0, 19)]
        assert len(texts) == 1 and texts[0].startswith("session: left and right not rectified: 2.0 px"), texts
        assert texts[0].endswith("the pair is not rectified, or rectified with a wrong or stale calibration")
        assert math.isfinite(summary.elapsed_s)
