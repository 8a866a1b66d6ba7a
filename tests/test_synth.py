"""Tests of the synthetic session generator (contact_viz.synth)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from contact_viz import synth
from contact_viz.params import from_dict
from contact_viz.synth import PHANTOMS, SynthParams, generate_session

SMALL = {"width": 320, "height": 180}
TINY = {"width": 160, "height": 90}
CONTACT_FORCE_N = 2.0  # the paper's force threshold for contact labels


def _read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def _load_depth(session: Path, frame: int) -> np.ndarray:
    return np.load(session / "depth" / f"{frame:06d}.npy")


def _load_mask(session: Path, frame: int) -> np.ndarray:
    return np.array(Image.open(session / "masks" / f"{frame:06d}.png"))


@pytest.fixture(scope="module")
def cup(tmp_path_factory) -> tuple[Path, SynthParams]:
    """A 75-frame cup palpation session: the first cycle (approach, hover, press, hold, retract)."""
    params = SynthParams(phantom="cup", frames=75, seed=0, **SMALL)
    return generate_session(tmp_path_factory.mktemp("cup") / "session", params), params


@pytest.fixture(scope="module")
def glove(tmp_path_factory) -> tuple[Path, SynthParams]:
    params = SynthParams(phantom="glove", frames=80, seed=0, **TINY)
    return generate_session(tmp_path_factory.mktemp("glove") / "session", params), params


# -- files and formats ---------------------------------------------------------------------------


def test_session_files_and_formats(cup):
    session, params = cup
    meta = json.loads((session / "session.json").read_text())
    assert meta["name"] == "session"
    assert (meta["phantom"], meta["task"], meta["fps"]) == ("cup", "palpation", 30)
    assert from_dict(SynthParams, meta["generator"]) == params  # the resolved params round-trip

    lines = (session / "K.txt").read_text().splitlines()
    K = np.array([float(x) for x in lines[0].split()])
    assert K.shape == (9,)
    fx = (params.width / 2) / math.tan(math.radians(params.fov_deg) / 2)
    np.testing.assert_allclose(K, [fx, 0, (params.width - 1) / 2, 0, fx, (params.height - 1) / 2, 0, 0, 1], rtol=1e-9)
    assert float(lines[1]) == pytest.approx(0.005)

    for sub, ext in (("left", "jpg"), ("right", "jpg"), ("masks", "png"), ("depth", "npy")):
        names = sorted(p.name for p in (session / sub).iterdir())
        assert names == [f"{i:06d}.{ext}" for i in range(params.frames)], sub

    left = cv2.imread(str(session / "left" / "000040.jpg"))
    right = cv2.imread(str(session / "right" / "000040.jpg"))
    assert left.shape == right.shape == (params.height, params.width, 3)
    assert np.abs(left.astype(int) - right.astype(int)).mean() > 2.0  # two different views
    # Endoscope look: reddish tissue (R > G, B on average) and darker corners (vignetting, fall-off).
    b, g, r = left.reshape(-1, 3).mean(0)
    assert r > 1.3 * g and r > 1.3 * b

    with Image.open(session / "masks" / "000040.png") as mask:
        assert mask.mode == "P"
        assert mask.getpalette()[:6] == [0, 0, 0, 128, 0, 0]  # DAVIS: 0 black, 1 dark red
        values = np.array(mask)
    assert set(np.unique(values)) == {0, 1}

    for i in range(params.frames):
        depth = _load_depth(session, i)
        assert depth.dtype == np.float32 and depth.shape == (params.height, params.width)
        holes = float(np.mean(depth == 0))
        assert 0.005 <= holes <= 0.15, (i, holes)
        valid = depth[depth > 0]
        assert 0.03 < valid.min() and valid.max() < 0.16  # tool and tissue within a few cm .. ~12 cm

    force = _read_csv(session / "force.csv")
    assert list(force[0]) == ["frame", "fx", "fy", "fz"] and len(force) == params.frames
    truth = _read_csv(session / "truth.csv")
    assert list(truth[0]) == ["frame", "timestamp", "gap_m", "indentation_m", "force_true_n", "contact", "phase"]
    assert [int(r["frame"]) for r in truth] == list(range(params.frames))
    np.testing.assert_allclose([float(r["timestamp"]) for r in truth], np.arange(params.frames) / 30, atol=1e-6)
    assert not (session / "labels.csv").exists()


def test_truth_is_consistent(cup):
    session, params = cup
    truth = _read_csv(session / "truth.csv")
    gap = np.array([float(r["gap_m"]) for r in truth])
    indentation = np.array([float(r["indentation_m"]) for r in truth])
    force_true = np.array([float(r["force_true_n"]) for r in truth])
    contact = np.array([int(r["contact"]) for r in truth])
    phase = [r["phase"] for r in truth]
    assert (gap >= 0).all() and (indentation >= 0).all()
    np.testing.assert_array_equal(gap == 0, indentation > 0)  # gap ~0 exactly when indented
    np.testing.assert_array_equal(contact, indentation > 0)
    assert set(phase) <= set(synth.PHASES) and {"approach", "press", "hold", "retract"} <= set(phase)
    assert all(p in ("press", "hold", "retract") for p, c in zip(phase, contact) if c)
    # Palpation: force = stiffness x indentation (to the 1e-6 m / 1e-6 N rounding of the csv).
    np.testing.assert_allclose(force_true, params.stiffness_n_per_m * indentation, atol=2e-3)
    # The approach hovers at a few mm to ~2 cm.
    assert 0.012 <= gap.max() <= 0.03 and 0.0 < gap[gap > 0].min() < 0.005


def test_force_readings_straddle_the_contact_threshold(cup):
    session, params = cup
    force = np.array([[float(r[k]) for k in ("fx", "fy", "fz")] for r in _read_csv(session / "force.csv")])
    truth = _read_csv(session / "truth.csv")
    contact = np.array([int(r["contact"]) for r in truth], dtype=bool)
    magnitude = np.linalg.norm(force, axis=1)
    assert (magnitude >= CONTACT_FORCE_N).any() and (magnitude < CONTACT_FORCE_N).any()
    assert 3.0 <= magnitude.max() <= 7.0  # a firm press gives 3-6 N
    # Off contact the reading is pure sensor noise: zero mean, std force_noise_n per axis.
    free = force[~contact]
    assert len(free) > 30
    assert np.abs(free.mean(0)).max() < 4 * params.force_noise_n / math.sqrt(len(free))
    assert free.std() == pytest.approx(params.force_noise_n, rel=0.3)


def test_light_touches_stay_below_the_threshold():
    """Over many cycles some contacts are light (true force < 2 N) and presses reach 3-6 N."""
    params = SynthParams(phantom="kidney", frames=900, seed=3)
    track = synth.plan_tool_track(params)  # pure: no rendering
    force = np.linalg.norm(track.force_true_n, axis=1)
    peaks = [force[a:b].max() for a, b in _runs(track.contact)]
    assert len(peaks) >= 8
    assert any(p < CONTACT_FORCE_N for p in peaks) and sum(3.0 <= p <= 6.0 for p in peaks) >= len(peaks) // 2


@pytest.mark.parametrize("phantom", PHANTOMS)
def test_contact_happens_only_in_contact_phases(phantom):
    for seed in (0, 1):
        track = synth.plan_tool_track(SynthParams(phantom=phantom, seed=seed, frames=300))
        assert track.contact.any() and not track.contact.all()
        assert set(track.phase[track.contact]) <= {"press", "hold", "retract", "pull"}
        assert (track.gap_m[track.phase == "hold"] == 0).all()
        # Phases come in order within a cycle: approach -> press -> (pull ->) hold -> retract.
        order = [p for i, p in enumerate(track.phase) if i == 0 or p != track.phase[i - 1]]
        allowed = {("approach", "press"), ("press", "hold"), ("hold", "retract"), ("retract", "approach"),
                   ("press", "pull"), ("pull", "hold")}
        assert set(zip(order, order[1:])) <= allowed


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    edges = np.flatnonzero(np.diff(np.concatenate([[0], flags.astype(int), [0]])))
    return list(zip(edges[0::2], edges[1::2]))


# -- geometry seen in the images -----------------------------------------------------------------


def test_right_view_is_the_left_view_shifted_by_disparity(cup):
    """On the tool, R(u - fx B / Z, v) matches L(u, v); unshifted it does not."""
    session, params = cup
    camera = synth.stereo_camera(params)
    fb = camera.fx * camera.baseline_m
    matched, unshifted = [], []
    for i in range(0, params.frames, 10):
        left = cv2.imread(str(session / "left" / f"{i:06d}.jpg")).astype(np.float32)
        right = cv2.imread(str(session / "right" / f"{i:06d}.jpg")).astype(np.float32)
        tool = cv2.erode(_load_mask(session, i).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        depth = _load_depth(session, i)
        v, u = np.nonzero(tool & (depth > 0))
        u_right = np.round(u - fb / depth[v, u]).astype(int)
        keep = u_right >= 0
        matched.append(np.abs(left[v, u] - right[v[keep], u_right[keep]]).mean())
        unshifted.append(np.abs(left[v, u] - right[v, u]).mean())
    assert np.mean(matched) < 12.0
    assert np.mean(matched) < 0.5 * np.mean(unshifted)


def test_depth_next_to_the_tip_tells_contact_from_hover(cup):
    """In contact the tissue right next to the tip is at about the tip's depth; hovering, deeper."""
    session, params = cup
    camera = synth.stereo_camera(params)
    track = synth.plan_tool_track(params)
    radius_px = 0.04 * params.width
    rows, cols = np.mgrid[: params.height, : params.width]
    step_in_depth = {}
    for i in range(params.frames):
        depth, tool = _load_depth(session, i), _load_mask(session, i) > 0
        tip_px = camera.project(track.jaw_tips_m[i]).mean(axis=0)
        near = np.hypot(cols - tip_px[0], rows - tip_px[1]) < radius_px
        beside = cv2.dilate(tool.astype(np.uint8), np.ones((5, 5), np.uint8)) == 0
        tool_z = depth[near & tool & (depth > 0)]
        tissue_z = depth[(np.hypot(cols - tip_px[0], rows - tip_px[1]) < 1.5 * radius_px) & beside & (depth > 0)]
        step_in_depth[i] = float(np.median(tissue_z) - np.median(tool_z))
    contact = [i for i in range(params.frames) if track.contact[i]]
    hover = [i for i in range(params.frames) if track.gap_m[i] > 0.005]
    assert len(contact) >= 10 and len(hover) >= 10
    in_contact = np.array([step_in_depth[i] for i in contact])
    hovering = np.array([step_in_depth[i] for i in hover])
    gaps = track.gap_m[hover]
    assert np.abs(in_contact).max() < 0.005  # within the tip's own size (3.6 mm jaws)
    assert (hovering > gaps + 0.002).all()  # the tissue behind the tip is more than the gap deeper
    assert hovering.min() > np.abs(in_contact).max() + 0.003


def test_visible_shaft_width_matches_a_dvrk_tool_at_1080p(cup):
    session, params = cup
    scale = 1080 / params.height
    widths = []
    for i in range(0, params.frames, 5):
        tool = _load_mask(session, i).astype(np.uint8)
        widths.append(2 * cv2.distanceTransform(tool, cv2.DIST_L2, 5).max() * scale)
    assert 60 <= min(widths) and max(widths) <= 160


def test_each_phantom_has_its_own_shape(tmp_path):
    depths = {}
    for phantom in PHANTOMS:
        params = SynthParams(phantom=phantom, frames=1, disparity_noise_px=0.0, **TINY)
        depths[phantom] = _load_depth(generate_session(tmp_path / phantom, params), 0)
    for i, a in enumerate(PHANTOMS):
        for b in PHANTOMS[i + 1 :]:
            both = (depths[a] > 0) & (depths[b] > 0)
            # The base plane around the phantoms is shared; the phantoms themselves differ.
            assert np.mean(np.abs(depths[a][both] - depths[b][both]) > 0.003) > 0.1, (a, b)


# -- glove: pulling with manual labels -----------------------------------------------------------


def test_glove_is_a_pulling_task_with_manual_labels(glove):
    session, params = glove
    meta = json.loads((session / "session.json").read_text())
    assert (meta["phantom"], meta["task"]) == ("glove", "pulling")
    truth = _read_csv(session / "truth.csv")
    labels = _read_csv(session / "labels.csv")
    assert list(labels[0]) == ["frame", "contact"] and len(labels) == params.frames
    contact = np.array([int(r["contact"]) for r in truth])
    label = np.array([int(r["contact"]) for r in labels])
    phase = np.array([r["phase"] for r in truth])
    assert "pull" in phase and contact[phase == "pull"].all()
    # Manual labels follow contact up to a frame or so at each boundary.
    disagree = np.flatnonzero(label != contact)
    boundaries = np.flatnonzero(np.diff(contact)) + 0.5
    for i in disagree:
        assert np.abs(boundaries - i).min() <= params.label_jitter_frames
    # Grasped and pulled: gap 0, the tissue displaced by more than the squeeze (tenting outward).
    gap = np.array([float(r["gap_m"]) for r in truth])
    indentation = np.array([float(r["indentation_m"]) for r in truth])
    assert (gap[phase == "pull"] == 0).all()
    assert indentation[phase == "hold"].min() >= params.pull_height_m[0] - 1e-6


@pytest.mark.parametrize("which", ["cup", "glove"])
def test_sensor_streams_are_what_the_session_records(which, request):
    """sensor_streams (used without rendering by recipes/sgbm_study.py --ceiling-draws) gives the
    force.csv readings and labels.csv of the written session, and through them the labels that
    open_session reads."""
    from contact_viz.io.session import open_session
    from contact_viz.io.session_files import force_labels
    from contact_viz.params import LabelParams

    session, params = request.getfixturevalue(which)
    force_n, manual = synth.sensor_streams(params, synth.plan_tool_track(params))
    written = np.array([[float(r[k]) for k in ("fx", "fy", "fz")] for r in _read_csv(session / "force.csv")])
    np.testing.assert_allclose(force_n, written, atol=5e-7)  # force.csv keeps 6 decimals
    read = np.asarray(open_session(session).labels)
    if which == "glove":
        assert manual is not None and (session / "labels.csv").is_file()
        np.testing.assert_array_equal(manual, read)
    else:
        assert manual is None and not (session / "labels.csv").exists()
        np.testing.assert_array_equal(force_labels(np.linalg.norm(force_n, axis=1), LabelParams()), read)
        assert read.min() == 0 and read.max() == 1


def test_pulled_tissue_tents_toward_the_tool():
    params = SynthParams(phantom="glove", frames=80, **TINY)
    track = synth.plan_tool_track(params)
    held = np.flatnonzero(np.linalg.norm(track.pull_m, axis=1) > 0.004)
    assert len(held)
    i = held[-1]
    pull = track.pull_m[i]
    assert pull @ track.dent_normal[i] > 0  # out of the tissue
    assert pull @ track.axis[i] < 0  # back toward the tool
    centre = track.dent_center_m[i]
    far = centre + np.array([0.05, 0.0, 0.0])
    disp = synth.tissue_displacement(np.stack([centre, far]), track, i, params)
    np.testing.assert_allclose(disp[0], -track.press_m[i] * track.dent_normal[i] + pull, atol=1e-12)
    assert np.linalg.norm(disp[1]) < 1e-3 * np.linalg.norm(pull)


def test_dent_profile_worked_example():
    """Dent: full depth in the flat bottom, Gaussian flank beyond it, along -normal."""
    params = SynthParams(dent_sigma_m=0.005)
    track = synth.plan_tool_track(SynthParams(frames=75, **SMALL))
    i = int(np.argmax(track.press_m))
    press, n, c, flat = track.press_m[i], track.dent_normal[i], track.dent_center_m[i], track.dent_flat_m[i]
    tangent = np.cross(n, [0.0, 0.0, 1.0])
    tangent /= np.linalg.norm(tangent)
    points = np.stack([c, c + 0.5 * flat * tangent, c + (flat + 0.005) * tangent, c + (flat + 0.01) * tangent])
    disp = synth.tissue_displacement(points, track, i, params)
    expected = press * np.array([1.0, 1.0, math.exp(-0.5), math.exp(-2.0)])
    np.testing.assert_allclose(disp, -expected[:, None] * n, atol=1e-12)


# -- pure pieces checked against independent computations ---------------------------------------


def test_closest_surface_points_match_brute_force():
    params = SynthParams(phantom="kidney")
    frame = synth.tissue_frame(params)
    rng = np.random.default_rng(7)
    uv = rng.uniform(-0.015, 0.015, (5, 2))
    points = synth.surface_points("kidney", frame, uv[:, 0], uv[:, 1]) + rng.normal(0, 0.004, (5, 3))
    closest, normals, signed, _ = synth.closest_surface_points("kidney", frame, points)
    for k, p in enumerate(points):
        u, v, w = frame.to_tissue(p)
        half = abs(w - synth.phantom_height("kidney", u, v)) + 0.001
        grid_u, grid_v = np.meshgrid(np.arange(u - half, u + half, 2e-5), np.arange(v - half, v + half, 2e-5))
        surface = synth.surface_points("kidney", frame, grid_u, grid_v).reshape(-1, 3)
        brute = np.linalg.norm(surface - p, axis=1).min()
        assert abs(signed[k]) == pytest.approx(brute, abs=3e-6)
        assert np.sign(signed[k]) == np.sign(w - synth.phantom_height("kidney", u, v))
        np.testing.assert_allclose(np.linalg.norm(normals[k]), 1.0)
        assert abs((p - closest[k]) @ normals[k]) == pytest.approx(abs(signed[k]), rel=1e-3)


def test_truth_gap_is_the_distance_of_the_jaw_tips():
    params = SynthParams(phantom="liver", frames=60)
    track = synth.plan_tool_track(params)
    frame = synth.tissue_frame(params)
    free = np.flatnonzero(~track.contact)
    _, _, signed, _ = synth.closest_surface_points("liver", frame, track.jaw_tips_m[free].reshape(-1, 3))
    expected = signed.reshape(-1, 2).min(axis=1) - params.jaw_radius_m
    np.testing.assert_allclose(track.gap_m[free], expected, atol=1e-9)
    assert (track.tip_center_m[:, 2] > 0.05).all() and (track.tip_center_m[:, 2] < 0.12).all()


def test_disparity_noise_grows_with_depth_squared():
    params = SynthParams(hole_blob_count=0.0, edge_fattening_px=0.0, **SMALL)
    camera = synth.stereo_camera(params)
    scale = params.width / synth.REFERENCE_WIDTH_PX
    stds = []
    for z_m in (0.06, 0.12):
        z = np.full((params.height, params.width), z_m, np.float32)
        none = np.zeros(z.shape, bool)
        depth = synth.stereo_depth(z, z, none, np.zeros(z.shape, np.float32), camera, params, np.random.default_rng(1))
        assert (depth > 0).all()
        stds.append(depth.std())
        # first order: sigma_z = z^2 / (fx B) sigma_d
        predicted = z_m**2 / (camera.fx * camera.baseline_m) * params.disparity_noise_px * scale
        assert depth.std() == pytest.approx(predicted, rel=0.15)
    assert stds[1] / stds[0] == pytest.approx(4.0, rel=0.1)


def test_occlusion_and_fattening_near_a_tool_edge():
    """A flat tool strip in front of a flat wall: holes beside it on the occluded side, depth bleeding on the edges."""
    params = SynthParams(hole_blob_count=0.0, disparity_noise_px=0.0, **SMALL)
    camera = synth.stereo_camera(params)
    fb = camera.fx * camera.baseline_m
    h, w = params.height, params.width
    z_tool, z_wall = 0.06, 0.09
    tool_l = np.zeros((h, w), bool)
    tool_l[:, 150:180] = True
    shift = round(fb / z_tool)  # the strip sits shift px further left in the right view
    tool_r = np.zeros((h, w), bool)
    tool_r[:, 150 - shift : 180 - shift] = True
    z_l = np.where(tool_l, z_tool, z_wall).astype(np.float32)
    z_r = np.where(tool_r, z_tool, z_wall).astype(np.float32)
    depth = synth.stereo_depth(z_l, z_r, tool_l, np.zeros((h, w), np.float32), camera, params, np.random.default_rng(0))
    wall_shift = fb / z_wall
    # Wall pixels left of the strip whose match falls on the strip in the right view are holes.
    occluded = [u for u in range(120, 150) if 150 - shift <= u - wall_shift < 180 - shift]
    assert occluded and (depth[:, occluded] == 0).all()
    fatten = max(1, round(params.edge_fattening_px * params.width / synth.REFERENCE_WIDTH_PX))
    np.testing.assert_allclose(depth[:, 180 : 180 + fatten], z_tool, rtol=1e-5)
    np.testing.assert_allclose(depth[:, 180 + fatten + 1 :], z_wall, rtol=1e-5)


def test_adaptive_ray_caster_matches_one_ray_per_pixel(tmp_path):
    """The lattice caster (step 4 px at 1920 px, so 2 px here) against one exact ray per pixel."""
    base = {"phantom": "glove", "frames": 1, "disparity_noise_px": 0.0, "width": 960, "height": 540}
    exact = generate_session(tmp_path / "exact", SynthParams(raycast_step_px=1, **base))
    adaptive = generate_session(tmp_path / "adaptive", SynthParams(raycast_step_px=4, **base))
    a, b = _load_depth(exact, 0), _load_depth(adaptive, 0)
    assert np.mean((a > 0) != (b > 0)) < 0.001  # specular holes may flip right at the threshold
    both = (a > 0) & (b > 0)
    assert np.mean(np.abs(a - b)[both] > 1e-4) < 0.002 and np.abs(a - b)[both].max() < 5e-4
    assert np.mean(_load_mask(exact, 0) != _load_mask(adaptive, 0)) < 0.001


# -- reproducibility and the output directory ----------------------------------------------------


def test_same_seed_same_files_other_seed_other_files(tmp_path):
    params = SynthParams(phantom="kidney", frames=4, seed=5, **TINY)
    a = generate_session(tmp_path / "a", params)
    b = generate_session(tmp_path / "b", params)
    c = generate_session(tmp_path / "c", SynthParams(phantom="kidney", frames=4, seed=6, **TINY))
    for name in ("K.txt", "force.csv", "truth.csv"):
        assert (a / name).read_bytes() == (b / name).read_bytes()
    for i in range(4):
        for sub, ext in (("depth", "npy"), ("masks", "png"), ("left", "jpg"), ("right", "jpg")):
            assert (a / sub / f"{i:06d}.{ext}").read_bytes() == (b / sub / f"{i:06d}.{ext}").read_bytes()
    assert (a / "truth.csv").read_bytes() != (c / "truth.csv").read_bytes()
    assert (a / "force.csv").read_bytes() != (c / "force.csv").read_bytes()
    assert not np.array_equal(_load_depth(a, 0), _load_depth(c, 0))


def test_refuses_a_non_empty_directory(tmp_path):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    params = SynthParams(frames=2, **TINY)
    with pytest.raises(FileExistsError, match="busy"):
        generate_session(out, params)
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    generate_session(out, params, overwrite=True)
    assert (out / "notes.txt").read_text() == "keep me"
    # Overwriting a longer session leaves no stale frames behind.
    generate_session(out, SynthParams(frames=1, **TINY), overwrite=True)
    assert sorted(p.name for p in (out / "depth").iterdir()) == ["000000.npy"]
    empty = tmp_path / "empty"
    empty.mkdir()
    generate_session(empty, params)  # an existing empty directory is fine


def test_progress_and_bad_input(tmp_path):
    calls = []
    generate_session(tmp_path / "p", SynthParams(frames=3, **TINY), progress=lambda *args: calls.append(args))
    assert calls == [(1, 3), (2, 3), (3, 3)]
    with pytest.raises(ValueError, match="phantom"):
        SynthParams(phantom="heart")
    with pytest.raises(ValueError, match="press_depth_m"):
        SynthParams(press_depth_m=(0.005, 0.002))
    with pytest.raises(TypeError, match="SynthParams"):
        generate_session(tmp_path / "q", {"phantom": "cup"})


def test_an_interrupted_run_leaves_no_partial_session(tmp_path):
    def stop_after_two(done, total):
        if done == 2:
            raise KeyboardInterrupt

    new = tmp_path / "new"
    with pytest.raises(KeyboardInterrupt):
        generate_session(new, SynthParams(frames=5, **TINY), progress=stop_after_two)
    assert list(tmp_path.iterdir()) == []  # neither the session nor its hidden work folder
    # Interrupting an overwrite leaves the previous session whole.
    old = tmp_path / "old"
    generate_session(old, SynthParams(frames=3, **TINY))
    before = sorted((p.relative_to(old), p.stat().st_size) for p in old.rglob("*"))
    with pytest.raises(KeyboardInterrupt):
        generate_session(old, SynthParams(frames=5, seed=9, **TINY), overwrite=True, progress=stop_after_two)
    assert sorted((p.relative_to(old), p.stat().st_size) for p in old.rglob("*")) == before
    assert [p.name for p in tmp_path.iterdir()] == ["old"]


def test_true_depth_is_the_noiseless_depth_of_the_session(tmp_path):
    """synth.true_depth re-renders the exact z-depth: without disparity noise, edge fattening and hole
    blobs, the session's depth/ equals it wherever depth/ has a value (holes: occlusion, highlights)."""
    params = SynthParams(phantom="cup", frames=40, seed=2, disparity_noise_px=0.0, edge_fattening_px=0.0,
                         hole_blob_count=0.0, **TINY)
    session = generate_session(tmp_path / "s", params)
    truth = synth.true_depth(params, [0, 39])
    for i in (0, 39):
        depth = _load_depth(session, i)
        assert truth[i].shape == depth.shape and truth[i].dtype == np.float32
        seen = depth > 0
        assert seen.mean() > 0.8
        np.testing.assert_allclose(depth[seen], truth[i][seen], rtol=1e-5)
        assert np.all(truth[i][_load_mask(session, i) > 0] > 0)  # the tool is there in the truth too


def test_spread_tool_depth_against_a_literal_loop_and_at_the_image_border():
    """The tool's depth bled px past its edge: each background pixel with a tool pixel that has depth within
    the disc takes the smallest such depth (a literal loop); a pixel at the image border whose tool
    neighbours are all holes keeps its depth (cv2.erode pads with FLT_MAX: it used to get 3.4e38 m)."""
    from contact_viz.synth.sensors import spread_tool_depth

    rng = np.random.default_rng(3)
    depth = rng.uniform(0.08, 0.1, (24, 30)).astype(np.float32)
    tool = np.zeros(depth.shape, bool)
    tool[0:14, 10:17] = True  # a shaft entering from the top border
    depth[tool] = rng.uniform(0.05, 0.06, int(tool.sum()))
    depth[0:5, 10:17] = 0.0  # its end at the border has no depth
    depth[20, 3] = 0.0  # a hole in the tissue, far from the tool
    px = 3
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * px + 1, 2 * px + 1)).astype(bool)
    expected = depth.copy()
    for y, x in zip(*np.nonzero(~tool)):
        near = []
        for dy in range(-px, px + 1):
            for dx in range(-px, px + 1):
                v, u = y + dy, x + dx
                if disc[dy + px, dx + px] and 0 <= v < 24 and 0 <= u < 30 and tool[v, u] and depth[v, u] > 0:
                    near.append(depth[v, u])
        if near:
            expected[y, x] = min(near)
    out = spread_tool_depth(depth, tool, px)
    np.testing.assert_array_equal(out, expected)
    assert out.max() < 0.2  # no 3.4e38
    np.testing.assert_array_equal(out[0, 5:8], depth[0, 5:8])  # border pixels next to the tool's holes keep theirs
