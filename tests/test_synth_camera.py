"""Synthetic sessions at a real endoscope's range (issue 33): the camera presets, every phantom with one
and two instruments at 25-60 mm, and the default camera unchanged."""

from __future__ import annotations

import filecmp
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from contact_viz import synth
from contact_viz.cli import app
from contact_viz.synth import PHANTOMS, SynthParams, generate_session
from contact_viz.synth.camera import CAMERAS, camera_fields
from contact_viz.synth.motion import nearest_in_view_m

SIZE = {"width": 320, "height": 240}
FRAMES = 24
# (name, camera fields): the da Vinci preset and its lens at the two ends of the range
SETTINGS = {
    "davinci": camera_fields("davinci"),
    "25mm": camera_fields("davinci", working_distance_mm=25),
    "60mm": camera_fields("davinci", working_distance_mm=60),
}
# The nearest an instrument's pixel may be (synth.motion: 20 mm, or 0.4 of the working distance), and
# the farthest one is at these distances, m.
NEAREST_M = {"davinci": 0.020, "25mm": 0.010, "60mm": 0.020}
FARTHEST_M = 0.060
DEPTH_MARGIN_M = 0.0005  # the depth files carry stereo-like noise: a few hundredths of a mm here


def _k_txt(session: Path) -> tuple[np.ndarray, float]:
    lines = (session / "K.txt").read_text().split("\n")
    return np.array([float(x) for x in lines[0].split()]).reshape(3, 3), float(lines[1])


def _mask(session: Path, i: int) -> np.ndarray:
    return np.array(Image.open(session / "masks" / f"{i:06d}.png"))


# -- the presets -----------------------------------------------------------------------------------


def test_davinci_preset_is_the_calibration():
    """fx 1103.43 px at 1920 px wide (M_l[0, 0] of CalibrationParameters.xml) and |T| = 4.11 mm."""
    camera = synth.stereo_camera(SynthParams(width=1920, height=1080, **camera_fields("davinci")))
    assert camera.fx == pytest.approx(1103.4302694252408, rel=1e-12)
    t_mm = (-4.1081855448335531, -0.14437844278862857, 0.0092522573362769783)
    assert camera.baseline_m == pytest.approx(math.sqrt(sum(t * t for t in t_mm)) / 1000, rel=1e-12)
    assert 0.0041 < camera.baseline_m < 0.0042 and 82.0 < CAMERAS["davinci"].fov_deg < 82.1
    assert CAMERAS["davinci"].tissue_distance_m == 0.05 and CAMERAS["close"].tissue_distance_m == 0.03
    default = SynthParams()
    assert camera_fields("default") == {"fov_deg": default.fov_deg, "baseline_m": default.baseline_m,
                                        "tissue_distance_m": default.tissue_distance_m} == \
        {"fov_deg": 80.0, "baseline_m": 0.005, "tissue_distance_m": 0.09}


def test_camera_fields_overrides_and_names():
    fields = camera_fields("davinci", fov_deg=55.1, baseline_mm=4.0, working_distance_mm=42)
    assert fields == {"fov_deg": 55.1, "baseline_m": 0.004, "tissue_distance_m": 0.042}
    with pytest.raises(ValueError, match="--camera must be one of default, davinci, close; got 'dv'"):
        camera_fields("dv")


def test_scales_of_the_scene():
    """The phantom shrinks with the width of tissue the camera sees (below the default's: 90 mm at 80 deg),
    the gaps below the width seen at 50 mm; worked examples. The instruments keep their size."""
    for distance_m, fov_deg, phantom, gaps in ((0.12, 80.0, 1.0, 1.0), (0.09, 80.0, 1.0, 1.0),
                                               (0.06, 80.0, 0.6667, 1.0), (0.025, 80.0, 0.2778, 0.5),
                                               (0.05, 82.047, 0.5760, 1.0),  # davinci: tan 41.02 / tan 40 = 1.037
                                               (0.05, 55.1, 0.3454, 0.6217)):  # tan 27.55 / tan 40 = 0.6217
        params = SynthParams(tissue_distance_m=distance_m, fov_deg=fov_deg)
        assert params.scene_scale == pytest.approx(phantom, abs=1e-4)
        assert params.gap_scale == pytest.approx(gaps, abs=1e-4)
        frame = synth.tissue_frame(params)
        # the cup's top (16 mm high at its centre as designed) stands scene_scale x 16 mm above the plane
        top = synth.surface_points("cup", frame, np.array(0.002), np.array(0.004))
        base = frame.to_camera(np.array(0.002), np.array(0.004), np.array(0.0))
        assert np.linalg.norm(top - base) == pytest.approx(0.016 * phantom, rel=1e-3)
    assert SynthParams(shaft_diameter_m=0.008, tissue_distance_m=0.025).shaft_diameter_m == 0.008


def test_gaps_of_the_motion_at_real_range():
    """At the da Vinci preset the gaps keep their sizes (start 12-22 mm, hover 2-10 mm): across the
    phantoms an instrument approaching the tissue is 25 mm or more above it on some frame, and every
    phantom has hover frames 10 mm or more above it; the instruments stay 20 mm or more from the
    camera (exact ray casts of them alone, every frame)."""
    largest = []
    for phantom in PHANTOMS:
        params = SynthParams(phantom=phantom, frames=300, **SIZE, **camera_fields("davinci"))
        assert params.gap_scale == 1.0
        track = synth.plan_tool_track(params)
        approaching = (track.phase == "approach") & ~track.contact
        largest.append(track.gap_m[approaching].max())
        assert largest[-1] >= 0.01, phantom
        camera = synth.stereo_camera(params)
        for i in range(params.frames):
            _, z = synth.cast_tools([synth.tool_primitives(track, i, params)], camera,
                                    *np.meshgrid(np.arange(0, 320, 2), np.arange(0, 240, 2)))
            assert z.min() >= 0.02 - 1e-4, (phantom, i)
    assert max(largest) >= 0.025, largest


def test_instruments_keep_their_distance_from_the_camera():
    """Where it binds (20 mm; the glove, whose open jaws need more room, at 25 mm), the nearest visible
    part of instrument 1 (``nearest_in_view_m``) is 0.4 of the working distance (8 and 10 mm) or more
    from the camera on every frame, and comes within 1 mm of that; and ``nearest_in_view_m`` is a lower
    bound of the instrument's exact ray casts (every 3rd frame, every 2nd pixel), by a median 5 mm or less
    (measured: 1.6-2.1 mm with closed jaws, 3.9 mm with the glove's open ones)."""
    above = []
    for phantom, distance_mm, limit_m in (("cup", 20, 0.008), ("kidney", 20, 0.008), ("liver", 20, 0.008),
                                          ("glove", 25, 0.010)):
        params = SynthParams(phantom=phantom, frames=120, **SIZE,
                             **camera_fields("davinci", working_distance_mm=distance_mm))
        track = synth.plan_tool_track(params)
        camera = synth.stereo_camera(params)
        bound = nearest_in_view_m(params, camera, track.tip_center_m, track.axis)
        assert bound.min() >= limit_m - 1e-12, phantom
        above.append(bound.min() - limit_m)
        cols, rows = np.meshgrid(np.arange(0, 320, 2), np.arange(0, 240, 2))
        slack = []
        for i in range(0, params.frames, 3):
            _, z = synth.cast_tools([synth.tool_primitives(track, i, params)], camera, cols, rows)
            if np.isfinite(z.min()):
                assert bound[i] - 1e-9 <= z.min(), (phantom, i, bound[i], z.min())
                slack.append(z.min() - bound[i])
        assert len(slack) >= 20 and np.median(slack) < 0.005, (phantom, np.median(slack))
    assert min(above) < 0.001, above


# -- every phantom, one and two instruments, 25-60 mm ------------------------------------------------


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> dict:
    out = {}
    root = tmp_path_factory.mktemp("range")
    for setting, fields in SETTINGS.items():
        for phantom in PHANTOMS:
            for tools in (1, 2):
                params = SynthParams(phantom=phantom, tools=tools, frames=FRAMES, seed=2, **SIZE, **fields)
                out[setting, phantom, tools] = generate_session(root / f"{setting}-{phantom}-{tools}", params), params
    return out


@pytest.mark.parametrize("setting", list(SETTINGS))
def test_every_phantom_and_instrument_count_at_real_range(sessions, setting):
    """Each session is whole; its instruments' depth lies between the near limit and 60 mm, instrument 1
    appears in every session and instrument 2 in most (it starts lifted above its first target and can
    be out of view for a while, as with the default camera), and K.txt and session.json state the camera."""
    second_seen = 0
    for phantom in PHANTOMS:
        for tools in (1, 2):
            session, params = sessions[setting, phantom, tools]
            assert len(list((session / "left").iterdir())) == FRAMES
            K, baseline = _k_txt(session)
            fx = (params.width / 2) / math.tan(math.radians(params.fov_deg) / 2)
            assert K[0, 0] == pytest.approx(fx, rel=1e-9) and K[1, 1] == pytest.approx(fx, rel=1e-9)
            assert baseline == pytest.approx(params.baseline_m, rel=1e-9)
            camera = json.loads((session / "session.json").read_text())["camera"]
            assert camera["preset"] == ("davinci" if setting == "davinci" else "custom")
            assert camera["fx_px"] == pytest.approx(fx, rel=1e-9)
            assert camera["baseline_mm"] == pytest.approx(params.baseline_m * 1000, rel=1e-9)
            assert camera["working_distance_mm"] == pytest.approx(params.tissue_distance_m * 1000, rel=1e-9)
            seen = set()
            for i in range(FRAMES):
                mask = _mask(session, i)
                depth = np.load(session / "depth" / f"{i:06d}.npy")
                on = (mask > 0) & (depth > 0)
                seen |= set(np.unique(mask[on]).tolist())
                if on.any():
                    where = (setting, phantom, tools, i)
                    assert depth[on].min() >= NEAREST_M[setting] - DEPTH_MARGIN_M, where
                    assert depth[on].max() <= FARTHEST_M + DEPTH_MARGIN_M, where
            assert 1 in seen and seen <= set(range(1, tools + 1)), (setting, phantom, tools, seen)
            second_seen += 2 in seen
    assert second_seen >= 3, setting


def test_right_view_is_the_left_view_shifted_by_the_disparity(sessions):
    """At 25 mm (disparities of 30-40 px at 320 px wide), R(u - fx B / Z, v) matches L(u, v) on the
    tissue, with fx and B read from K.txt and Z from depth/: of the shifts -4..4 px from there, 0 matches
    best, and 3 px off matches clearly worse. (High-passed images: each view is lit by a light at its own
    centre, so the two differ in brightness by more than the texture's contrast at this range.)"""
    shifts = range(-4, 5)
    for phantom in PHANTOMS:
        session, params = sessions["25mm", phantom, 1]
        K, baseline = _k_txt(session)
        errors = {shift: [] for shift in shifts}
        disparities = []
        for i in (0, FRAMES - 1):
            left, right = (cv2.imread(str(session / side / f"{i:06d}.jpg")).astype(np.float32)
                           for side in ("left", "right"))
            left, right = (image - cv2.GaussianBlur(image, (0, 0), 3) for image in (left, right))
            depth = np.load(session / "depth" / f"{i:06d}.npy")
            tool = cv2.dilate((_mask(session, i) > 0).astype(np.uint8), np.ones((15, 15), np.uint8)) > 0
            v, u = np.nonzero(~tool & (depth > 0))
            disparity = K[0, 0] * baseline / depth[v, u]
            disparities.append(disparity)
            for shift in shifts:
                u_right = np.round(u - disparity + shift).astype(int)
                keep = (u_right >= 0) & (u_right < params.width)
                errors[shift].append(np.abs(left[v[keep], u[keep]] - right[v[keep], u_right[keep]]).mean())
        assert 25 < np.median(np.concatenate(disparities)) < 60, phantom
        mean = {shift: np.mean(e) for shift, e in errors.items()}
        assert min(mean, key=mean.get) == 0, (phantom, mean)
        assert mean[0] < 0.7 * min(mean[3], mean[-3]), (phantom, mean)


# -- the default camera ------------------------------------------------------------------------------


def _same_tree(a: Path, b: Path) -> list[str]:
    names = sorted(p.relative_to(a).as_posix() for p in a.rglob("*") if p.is_file())
    assert names == sorted(p.relative_to(b).as_posix() for p in b.rglob("*") if p.is_file())
    return [n for n in names if not filecmp.cmp(a / n, b / n, shallow=False)]


def test_default_camera_is_no_camera_options(tmp_path):
    runner = CliRunner()
    common = ["--phantom", "kidney", "--frames", "3", "--size", "160x120", "--seed", "4"]
    plain = runner.invoke(app, ["synth", str(tmp_path / "a" / "s"), *common])
    named = runner.invoke(app, ["synth", str(tmp_path / "b" / "s"), *common, "--camera", "default",
                                "--fov-deg", "80", "--baseline-mm", "5", "--working-distance-mm", "90"])
    assert plain.exit_code == 0 and named.exit_code == 0, (plain.output, named.output)
    assert ", camera" not in plain.output and ", camera" not in named.output
    assert _same_tree(tmp_path / "a" / "s", tmp_path / "b" / "s") == []
    meta = json.loads((tmp_path / "a" / "s" / "session.json").read_text())
    assert meta["camera"]["preset"] == "default" and meta["camera"]["working_distance_mm"] == pytest.approx(90)


def test_cli_camera_options(tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["synth", str(tmp_path / "s"), "--frames", "2", "--size", "160x120",
                                 "--camera", "davinci", "--working-distance-mm", "40", "--tools", "2"])
    assert result.exit_code == 0, result.output
    assert "camera 82.05 deg, baseline 4.11 mm, tissue at 40 mm" in result.output
    generator = json.loads((tmp_path / "s" / "session.json").read_text())["generator"]
    assert (generator["fov_deg"], generator["baseline_m"], generator["tissue_distance_m"]) == (
        CAMERAS["davinci"].fov_deg, CAMERAS["davinci"].baseline_m, 0.04)
    for args, message in ((["--camera", "dv"], "--camera must be one of default, davinci, close; got 'dv'"),
                          (["--baseline-mm", "0"], "--baseline-mm must be a number > 0, got 0"),
                          (["--working-distance-mm", "-5"], "--working-distance-mm must be a number > 0, got -5"),
                          (["--fov-deg", "10"], "--fov-deg must be a finite number in [30, 120], got 10")):
        bad = runner.invoke(app, ["synth", str(tmp_path / "bad"), "--frames", "2", *args])
        assert bad.exit_code == 2 and message in bad.output, (args, bad.output)
        assert not (tmp_path / "bad").exists()
    help_text = runner.invoke(app, ["synth", "--help"], terminal_width=200).output
    davinci = synth.stereo_camera(SynthParams(width=1920, **camera_fields("davinci")))
    figures = f"fx {davinci.fx:.1f} px at 1920 px wide = {CAMERAS['davinci'].fov_deg:.2f} deg"
    assert figures in " ".join(help_text.split())
