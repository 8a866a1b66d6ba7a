"""Tests of the instruments of the synthetic generator: a second instrument in the scene
(``SynthParams.tools = 2``, contact_viz.synth.second) and a set shaft elevation
(``SynthParams.shaft_elevation_deg``); with neither, every file is the same as before they existed."""

from __future__ import annotations

import csv
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
from contact_viz.params import from_dict
from contact_viz.synth import PHANTOMS, SynthParams, generate_session

# A cup session with two contact runs of instrument 1 (near miss in the first, crossing in the second).
PAIR = {"phantom": "cup", "seed": 0, "frames": 135, "width": 256, "height": 144}
NOISELESS = {"disparity_noise_px": 0.0, "edge_fattening_px": 0.0, "hole_blob_count": 0.0}


def _read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def _mask(session: Path, i: int) -> np.ndarray:
    return np.array(Image.open(session / "masks" / f"{i:06d}.png"))


def _depth(session: Path, i: int) -> np.ndarray:
    return np.load(session / "depth" / f"{i:06d}.npy")


def _column(rows: list[dict[str, str]], name: str, kind=float) -> np.ndarray:
    return np.array([kind(r[name]) for r in rows])


def _image_gap(mask: np.ndarray) -> float:
    """Smallest distance, px, from an instrument-2 pixel to an instrument-1 pixel (inf: one is missing)."""
    if not ((mask == 1).any() and (mask == 2).any()):
        return math.inf
    to_first = cv2.distanceTransform((mask != 1).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return float(to_first[mask == 2].min())


def _analytic(track, i: int, params: SynthParams) -> tuple[np.ndarray, np.ndarray]:
    """Exact silhouette (H, W) bool and z-depth (H, W) (inf off the tool) of one instrument alone."""
    camera = synth.stereo_camera(params)
    rows, cols = np.mgrid[: params.height, : params.width]
    ids, z = synth.cast_tools([synth.tool_primitives(track, i, params)], camera, cols.ravel(), rows.ravel())
    return ids.reshape(rows.shape) > 0, z.reshape(rows.shape)


# -- one instrument: the defaults make the session they always made (tests/test_synth_reference.py) ------


def test_the_defaults_are_one_instrument_and_no_set_elevation(tmp_path):
    params = SynthParams(phantom="cup", seed=5, frames=4, width=160, height=90)
    assert params.tools == 1 and params.shaft_elevation_deg is None
    generator = json.loads((generate_session(tmp_path / "s", params) / "session.json").read_text())["generator"]
    assert (generator["tools"], generator["shaft_elevation_deg"]) == (1, None)


@pytest.mark.parametrize("phantom", PHANTOMS)
def test_instrument_1_moves_the_same_with_a_second_one(phantom):
    """Instrument 2 draws from its own stream: instrument 1's motion and truth are those of the
    one-instrument session (its gap is measured to the tissue as instrument 2 deforms it: a dent next
    to it lowers the tissue, adding to the gap; far from the dent the change is below a micrometre)."""
    one = synth.plan_tool_track(SynthParams(phantom=phantom, seed=1, frames=160, width=160, height=90))
    first, second = synth.plan_tracks(SynthParams(phantom=phantom, seed=1, frames=160, width=160, height=90, tools=2))
    for name in one.__dataclass_fields__:
        if name != "gap_m":
            np.testing.assert_array_equal(getattr(first, name), getattr(one, name), err_msg=name)
    assert (first.gap_m >= one.gap_m - 1e-6).all()
    np.testing.assert_array_equal(first.gap_m == 0, one.gap_m == 0)
    assert second.frames == one.frames
    assert not np.allclose(second.tip_center_m, first.tip_center_m)


# -- two instruments: what a session shows -------------------------------------------------------


@pytest.fixture(scope="module")
def pair(tmp_path_factory) -> tuple[Path, SynthParams]:
    params = SynthParams(tools=2, **PAIR)
    return generate_session(tmp_path_factory.mktemp("pair") / "session", params), params


@pytest.fixture(scope="module")
def solo(tmp_path_factory) -> tuple[Path, SynthParams]:
    """The same session with instrument 1 alone."""
    params = SynthParams(**PAIR)
    return generate_session(tmp_path_factory.mktemp("solo") / "session", params), params


def test_two_instruments_files(pair):
    session, params = pair
    meta = json.loads((session / "session.json").read_text())
    assert meta["generator"]["tools"] == 2
    assert from_dict(SynthParams, meta["generator"]) == params
    with Image.open(session / "masks" / "000040.png") as mask:
        assert mask.mode == "P"
        assert mask.getpalette()[:9] == [0, 0, 0, 128, 0, 0, 0, 128, 0]  # DAVIS: 0 black, 1 dark red, 2 green
    ids = [set(np.unique(_mask(session, i)).tolist()) for i in range(params.frames)]
    assert all(s <= {0, 1, 2} for s in ids)
    assert sum(s == {0, 1, 2} for s in ids) >= 0.8 * params.frames  # both instruments in view most of the time
    truth = _read_csv(session / "truth.csv")
    assert list(truth[0]) == ["frame", "timestamp", "gap_m", "indentation_m", "force_true_n", "contact", "phase",
                              "gap_m_1", "contact_1", "gap_m_2", "contact_2"]
    assert len(truth) == params.frames


def test_a_near_miss_of_a_few_pixels(pair):
    """Instrument 2 hovers 2-6 px from instrument 1 in the image (masks apart, nothing between but a few
    background pixels) for a stretch of frames, while instrument 1 is in contact."""
    session, params = pair
    truth = _read_csv(session / "truth.csv")
    contact_1 = _column(truth, "contact_1", int).astype(bool)
    gaps = np.array([_image_gap(_mask(session, i)) for i in range(params.frames)])
    near = np.flatnonzero((gaps >= 2) & (gaps <= 6))
    assert len(near) >= 8, gaps
    assert contact_1[near].mean() > 0.7
    # One stretch of consecutive frames (the hold), not scattered passes.
    assert np.max(np.diff(np.concatenate([[0], np.flatnonzero(np.diff(near) != 1) + 1, [len(near)]]))) >= 6


def test_instrument_2_crosses_in_front_of_instrument_1(pair, solo):
    """Where instrument 2 overlaps instrument 1 in the image the mask shows 2 (it is nearer): pixels that
    are instrument 1 alone (the one-instrument session) read 2 there; instrument 1 never hides 2."""
    session, params = pair
    solo_session, _ = solo
    first, second = synth.plan_tracks(params)
    covered = []
    for i in range(params.frames):
        mask, alone = _mask(session, i), _mask(solo_session, i)
        hidden = (alone == 1) & (mask == 2)  # instrument 1's pixels now showing instrument 2
        covered.append(int(hidden.sum()))
        # Everywhere else instrument 1 looks the same as alone (the second tool changes nothing of it).
        assert np.mean((alone == 1) != ((mask == 1) | hidden)) < 0.002, i
        if hidden.sum() >= 20:
            two, z2 = _analytic(second, i, params)
            one, z1 = _analytic(first, i, params)
            both = two & one
            assert (z2[both] < z1[both]).all()  # exact geometry: instrument 2 nearer wherever both are
            assert np.mean(mask[both] == 2) > 0.98  # and the renderer shows it
    crossing = np.flatnonzero(np.array(covered) >= 20)
    assert len(crossing) >= 3, covered


def test_each_instrument_touches_while_the_other_hovers(pair):
    session, params = pair
    truth = _read_csv(session / "truth.csv")
    c1, c2 = (_column(truth, f"contact_{k}", int).astype(bool) for k in (1, 2))
    g1, g2 = _column(truth, "gap_m_1"), _column(truth, "gap_m_2")
    only_2 = c2 & ~c1
    only_1 = c1 & ~c2
    assert only_2.sum() >= 8 and only_1.sum() >= 8
    assert (g1[only_2] > 0.001).mean() > 0.8  # instrument 1 hovers (above 1 mm) while instrument 2 presses
    assert (g2[only_1] > 0.001).all()  # and the other way round
    assert not (c1 & c2).any()  # the plan never has both in contact


def test_truth_columns_agree(pair):
    """Scene columns from the instruments' (gap = the smaller gap, contact = either, force = the total),
    each instrument's gap 0 exactly in contact, instrument 1's phase; force.csv is the scene sensor."""
    session, params = pair
    truth = _read_csv(session / "truth.csv")
    gap, g1, g2 = (_column(truth, n) for n in ("gap_m", "gap_m_1", "gap_m_2"))
    contact, c1, c2 = (_column(truth, n, int).astype(bool) for n in ("contact", "contact_1", "contact_2"))
    np.testing.assert_array_equal(gap, np.minimum(g1, g2))
    np.testing.assert_array_equal(contact, c1 | c2)
    for g, c in ((g1, c1), (g2, c2)):
        assert (g[c] == 0).all() and (g[~c] > 0).all() and (g >= 0).all()
    tracks = synth.plan_tracks(params)
    np.testing.assert_allclose(g1, tracks[0].gap_m, atol=5e-7)
    np.testing.assert_allclose(g2, tracks[1].gap_m, atol=5e-7)
    total = tracks[0].force_true_n + tracks[1].force_true_n
    np.testing.assert_allclose(_column(truth, "force_true_n"), np.linalg.norm(total, axis=1), atol=5e-7)
    indentation = _column(truth, "indentation_m")
    np.testing.assert_allclose(indentation, np.maximum(tracks[0].indentation_m, tracks[1].indentation_m), atol=5e-7)
    np.testing.assert_allclose(_column(truth, "force_true_n"), params.stiffness_n_per_m * indentation, atol=2e-3)
    assert [r["phase"] for r in truth] == list(tracks[0].phase)
    force = np.array([[float(r[k]) for k in ("fx", "fy", "fz")] for r in _read_csv(session / "force.csv")])
    np.testing.assert_allclose(force, synth.sensor_streams(params, tracks)[0], atol=5e-7)
    assert np.abs(force[c2 & ~c1]).max() > 1.0  # instrument 2's presses reach the sensor


def test_contact_columns_agree_with_the_images(pair):
    """Each instrument in contact: the tissue right beside its tip (in the image) lies at about the tip's
    depth; hovering more than 5 mm up, the tissue behind its tip is deeper by more than its gap. (Frames
    where the other instrument hides the tip or much of the tissue around it are left out.)"""
    session, params = pair
    camera = synth.stereo_camera(params)
    tracks = synth.plan_tracks(params)
    truth = _read_csv(session / "truth.csv")
    radius_px = 0.04 * params.width
    rows, cols = np.mgrid[: params.height, : params.width]
    for k, track in enumerate(tracks, start=1):
        contact = _column(truth, f"contact_{k}", int).astype(bool)
        gap = _column(truth, f"gap_m_{k}")
        steps, gaps, touching = [], [], []
        for i in np.flatnonzero(contact | (gap > 0.005)):
            depth, mask = _depth(session, i), _mask(session, i)
            tips = camera.project(track.jaw_tips_m[i])
            at = np.round(tips).astype(int)
            inside = (at >= 0).all() and (at[:, 0] < params.width).all() and (at[:, 1] < params.height).all()
            if not inside or not (mask[at[:, 1], at[:, 0]] == k).all():
                continue  # the tip hidden by the other instrument (crossing) or out of the image
            tip = tips.mean(axis=0)
            dist = np.hypot(cols - tip[0], rows - tip[1])
            around = dist < 1.5 * radius_px
            if np.sum(around & (mask == 3 - k)) > 0.15 * np.sum(around):
                continue  # the other instrument covers much of the tissue around the tip (crossing)
            tool_z = depth[(dist < radius_px) & (mask == k) & (depth > 0)]
            beside = cv2.dilate((mask > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) == 0
            tissue_z = depth[around & beside & (depth > 0)]
            if len(tool_z) < 5 or len(tissue_z) < 5:
                continue
            steps.append(float(np.median(tissue_z) - np.median(tool_z)))
            gaps.append(gap[i])
            touching.append(contact[i])
        steps, gaps, touching = np.array(steps), np.array(gaps), np.array(touching)
        assert touching.sum() >= 8 and (~touching).sum() >= 8, k
        assert np.abs(steps[touching]).max() < 0.005, k
        assert (steps[~touching] > gaps[~touching]).all(), k


def test_depth_at_instrument_pixels_is_the_rendered_instrument(tmp_path):
    """Without noise, depth/ at each instrument's mask pixels is the renderer's depth there
    (true_depth), which is that instrument's exact geometry (ray casts of its primitives)."""
    params = SynthParams(tools=2, phantom="cup", seed=0, frames=24, width=160, height=90, **NOISELESS)
    session = generate_session(tmp_path / "s", params)
    tracks = synth.plan_tracks(params)
    frames = [i for i in (0, 12, 23) if (_mask(session, i) == 2).sum() >= 30]
    assert frames
    rendered = synth.true_depth(params, frames)
    for i in frames:
        depth, mask = _depth(session, i), _mask(session, i)
        for k, track in enumerate(tracks, start=1):
            on = (mask == k) & (depth > 0)
            assert on.sum() >= 30
            np.testing.assert_allclose(depth[on], rendered[i][on], rtol=1e-5)
            _, z = _analytic(track, i, params)
            error = np.abs(depth[on] - z[on])
            assert np.quantile(error, 0.98) < 2e-4 and np.median(error) < 5e-5, (i, k)


def test_two_instruments_plan_on_every_phantom():
    """Pure plan checks (no rendering) on every phantom: the instruments keep apart in 3D, are never
    in contact together, each touches while the other does not, and both visits happen: a near miss
    of 2-6 px and a crossing where instrument 2 is nearer (exact silhouettes)."""
    for phantom in PHANTOMS:
        params = SynthParams(phantom=phantom, seed=0, frames=200, width=160, height=90, tools=2)
        first, second = synth.plan_tracks(params)
        assert synth.tool_distance(first, second, params).min() >= 0.001, phantom
        assert not (first.contact & second.contact).any(), phantom
        assert (first.contact & ~second.contact).sum() >= 10 and (second.contact & ~first.contact).sum() >= 10
        near = crossing = 0
        for i in np.flatnonzero(first.contact):
            one, z1 = _analytic(first, i, params)
            two, z2 = _analytic(second, i, params)
            both = one & two
            if both.any():
                crossing += int((z2[both] < z1[both]).all())
            elif two.any():
                to_first = cv2.distanceTransform((~one).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
                near += int(2 <= to_first[two].min() <= 6)
        assert near >= 5 and crossing >= 3, (phantom, near, crossing)


def test_short_sessions_with_two_instruments():
    for frames in (1, 7, 30):
        first, second = synth.plan_tracks(SynthParams(phantom="kidney", frames=frames, tools=2, width=160, height=90))
        assert first.frames == second.frames == frames


# -- shaft elevation -----------------------------------------------------------------------------


@pytest.mark.parametrize("phantom", ["cup", "kidney", "glove"])
def test_shaft_elevation_sets_every_frame(phantom):
    params = SynthParams(phantom=phantom, frames=200, shaft_elevation_deg=8.0, tools=2, width=160, height=90)
    normal = synth.tissue_frame(params).normal
    for track in synth.plan_tracks(params):
        elevation = np.degrees(np.arcsin(-(track.axis @ normal)))
        np.testing.assert_allclose(elevation, 8.0, atol=1e-9)
    default = synth.plan_tool_track(SynthParams(phantom=phantom, frames=200))
    assert np.degrees(np.arcsin(-(default.axis @ normal))).min() > 20.0


def test_liver_has_no_target_for_a_flat_shaft():
    with pytest.raises(RuntimeError, match="deg above the tissue plane"):
        synth.plan_tool_track(SynthParams(phantom="liver", shaft_elevation_deg=8.0))


def _shaft_elevation_seen(session: Path, params: SynthParams, frames) -> list[tuple[float, float, float]]:
    """Per frame, from the depth map alone (back-projected shaft pixels): the angle of their principal
    axis above the tissue base plane (deg), their visible length (m) and how much their height above the
    base plane changes over it (m). Shaft pixels: instrument 1's, farther from its tip than jaws and wrist."""
    camera = synth.stereo_camera(params)
    frame = synth.tissue_frame(params)
    track = synth.plan_tool_track(params)
    out = []
    for i in frames:
        depth, mask = _depth(session, i), _mask(session, i)
        v, u = np.nonzero((mask == 1) & (depth > 0))
        z = depth[v, u].astype(np.float64)
        points = np.stack([(u - camera.K[0, 2]) * z / camera.K[0, 0], (v - camera.K[1, 2]) * z / camera.K[1, 1], z], 1)
        reach = params.jaw_length_m + params.wrist_length_m + 0.004
        shaft = points[np.linalg.norm(points - track.tip_center_m[i], axis=1) > reach]
        centred = shaft - shaft.mean(axis=0)
        direction = np.linalg.svd(centred, full_matrices=False)[2][0]
        along = centred @ direction
        height = (shaft - frame.origin_m) @ frame.normal
        angle = math.degrees(math.asin(abs(direction @ frame.normal)))
        out.append((angle, float(np.ptp(along)), float(np.ptp(height))))
    return out


def test_a_flat_shaft_is_flat_in_the_depth_map(tmp_path):
    """--shaft-elevation-deg 8: while the tool holds a press (the most shaft in view), the shaft's points
    (from depth/) lie along a line 8 deg above the tissue plane, rising less than L sin(11 deg) + its
    diameter over its visible length L; without the option the same session's shaft rises at 25 deg or more."""
    flat = SynthParams(phantom="cup", seed=0, frames=56, width=256, height=144, shaft_elevation_deg=8.0, **NOISELESS)
    usual = SynthParams(phantom="cup", seed=0, frames=56, width=256, height=144, **NOISELESS)
    holding = (45, 55)
    assert all(synth.plan_tool_track(p).phase[i] == "hold" for p in (flat, usual) for i in holding)
    for angle, length, rise in _shaft_elevation_seen(generate_session(tmp_path / "flat", flat), flat, holding):
        assert length > 0.03  # a few cm of shaft in view
        assert angle == pytest.approx(8.0, abs=1.5)
        assert rise < length * math.sin(math.radians(11.0)) + flat.shaft_diameter_m
    for angle, length, rise in _shaft_elevation_seen(generate_session(tmp_path / "usual", usual), usual, holding):
        assert length > 0.015
        assert angle > 25.0
        assert rise > length * math.sin(math.radians(20.0))


def test_cli_tools_and_shaft_elevation(tmp_path):
    out = tmp_path / "s"
    result = CliRunner().invoke(app, ["synth", str(out), "--phantom", "kidney", "--frames", "3", "--size", "96x54",
                                      "--tools", "2", "--shaft-elevation-deg", "8"])
    assert result.exit_code == 0, result.output
    assert "with 2 instruments" in result.output
    generator = json.loads((out / "session.json").read_text())["generator"]
    assert (generator["tools"], generator["shaft_elevation_deg"]) == (2, 8.0)
    assert len(_read_csv(out / "truth.csv")[0]) == 11
    bad = CliRunner().invoke(app, ["synth", str(tmp_path / "t"), "--tools", "3", "--frames", "2", "--size", "64x36"])
    assert bad.exit_code != 0 and not (tmp_path / "t").exists()
    flat_liver = CliRunner().invoke(app, ["synth", str(tmp_path / "u"), "--phantom", "liver", "--frames", "2",
                                          "--size", "64x36", "--shaft-elevation-deg", "8"])
    assert flat_liver.exit_code != 0 and "30 deg" in flat_liver.output
