"""The viewer with several instruments (object ids of palettized masks): each instrument's own layers, box, patch
points, gap arrow and series under its own entity paths, in its own stable colours, cleared where it is absent;
the instrument in contact per frame and in the run's summary. Recordings are read back from the .rrd."""

from __future__ import annotations

import math
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

rr = pytest.importorskip("rerun")

from test_viewer import (  # noqa: E402
    CY, H, N_FRAMES, TISSUE_M, W, Recording, image_buffer, tiny_model, write_session)

from contact_viz.geometry.patch import LAYER_BAND, LAYER_INTERIOR, LAYER_RING, LAYER_TOOL_EDGE  # noqa: E402
from contact_viz.io.session import open_session  # noqa: E402
from contact_viz.params import PatchParams  # noqa: E402
from contact_viz.pipeline.extract import frame_patches  # noqa: E402
from contact_viz.viz import rerun_log  # noqa: E402
from contact_viz.viz.debugger import DebuggerOptions, run_debugger  # noqa: E402
from contact_viz.viz.entities import TOOL_ENTITIES, tool_entity  # noqa: E402
from contact_viz.viz.instrument_log import CONTACT_MARK, label_colour  # noqa: E402
from contact_viz.viz.style import LAYER_STYLES, PATCH_STYLES, SERIES_STYLES, instrument_style  # noqa: E402

ABSENT = (4, 5)  # frames without instrument 2
BAD = 9  # a frame whose depth cannot be read
COLS_2 = (40, 80)  # instrument 2's columns [x0, x1), px (instrument 1: test_viewer.TOOL_COLS)
STEP = DebuggerOptions().depth_step


def gap2_m(t: int) -> float:
    """Instrument 2's gap: 3.5 mm closing by 0.2 mm a frame (instrument 1's closes by 1 mm a frame from 8 mm:
    instrument 2 is the nearer one up to frame 5, instrument 1 from frame 6)."""
    return 0.0035 - 0.0002 * t


def tissue_at_row(row: int) -> float:
    return TISSUE_M + 0.0001 * (CY - row)  # test_viewer.write_session's plane


def write_two_instrument_session(root: Path) -> None:
    """test_viewer's session, its masks turned into palettized object ids: its shaft is instrument 1 and a
    second shaft at COLS_2 instrument 2 (absent on ABSENT), whose depth is written into depth/."""
    write_session(root)
    palette = [0, 0, 0, 255, 0, 0, 0, 255, 0] + [0] * (256 * 3 - 9)
    for t in range(N_FRAMES):
        stem = f"{t:06d}"
        ids = (np.array(Image.open(root / "masks" / f"{stem}.png")) > 0).astype(np.uint8)
        if t not in ABSENT:
            tip = 60 + 3 * t
            bar = np.zeros((H, W), bool)
            bar[:tip, COLS_2[0]:COLS_2[1]] = True
            depth = np.load(root / "depth" / f"{stem}.npy")
            depth[bar] = tissue_at_row(tip) - gap2_m(t)
            np.save(root / "depth" / f"{stem}.npy", depth)
            ids[bar] = 2
        image = Image.fromarray(ids, mode="P")
        image.putpalette(palette)
        image.save(root / "masks" / f"{stem}.png")
    (root / "depth" / f"{BAD:06d}.npy").write_bytes(b"not a numpy file")


@pytest.fixture(scope="module")
def two_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("instruments") / "two"
    write_two_instrument_session(root)
    return root


def expected(session) -> dict[int, dict[int, object]]:
    """frame -> {object id: PatchResult} from the pipeline's own frame_patches ({} for the bad frame)."""
    out = {}
    for index in range(N_FRAMES):
        frame = session.load_frame(index, ("mask", "depth")) if index != BAD else None
        out[index] = {} if frame is None else frame_patches(frame, PatchParams())[1]
    return out


def view(session_dir: Path, out: Path, model=None, object_ids=None, **options):
    rr.set_strict_mode(True)
    session = open_session(session_dir, object_ids=object_ids)
    opened = rerun_log.open_recording(save=out, blueprint=rerun_log.default_blueprint(with_model=model is not None))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the bad frame's warning (tested in test_viewer)
        summary = run_debugger(session, opened.rec, DebuggerOptions(**options), model=model)
    opened.close()
    return session, summary, Recording(out)


@pytest.fixture(scope="module")
def two_run(two_dir, tmp_path_factory):
    return view(two_dir, tmp_path_factory.mktemp("rrd") / "two.rrd", images="jpeg")


def layers_at(rec: Recording, entity: str, frame: int, shape: tuple[int, int]) -> np.ndarray:
    return image_buffer(rec.values(entity, "SegmentationImage:buffer")[frame], shape, np.uint8)


def context_colours(rec: Recording, entity: str) -> dict[int, int]:
    """class id -> packed RGBA of the AnnotationContext logged (statically) on ``entity``."""
    context = rec.static[(entity, "AnnotationContext:context")].as_py()[0]
    return {c["class_id"]: c["class_description"]["info"]["color"] for c in context}


def packed(rgba) -> int:
    r, g, b, a = rgba
    return (r << 24) | (g << 16) | (b << 8) | a


def test_each_instrument_has_its_own_layers_where_it_is_present(two_run):
    session, summary, rec = two_run
    want = expected(session)
    present_2 = [i for i in range(N_FRAMES) if i not in ABSENT and i != BAD]
    readable = [i for i in range(N_FRAMES) if i != BAD]
    assert summary.bad_frames == 1 and summary.instrument_frames == {1: len(readable), 2: len(present_2)}
    small = (-(-H // STEP), -(-W // STEP))
    # instrument 1 (the primary): the single-instrument paths, on every readable frame; instrument 2: tools/2
    for tool, frames in ((1, readable), (2, present_2)):
        at = (lambda e: e) if tool == 1 else (lambda e, k=tool: tool_entity(e, k))
        assert rec.frames(at(rerun_log.ENTITY_LEFT_LAYERS), "SegmentationImage:buffer") == frames, tool
        assert rec.frames(at(rerun_log.ENTITY_DEPTH_LAYERS), "SegmentationImage:buffer") == frames, tool
        distance = rec.scalars(at(rerun_log.ENTITY_SERIES_DISTANCE))
        signal = rec.scalars(at(rerun_log.ENTITY_SERIES_SIGNAL))
        n_boxes = 0
        for i in frames:
            patch = want[i][tool]
            np.testing.assert_array_equal(layers_at(rec, at(rerun_log.ENTITY_LEFT_LAYERS), i, (H, W)), patch.layer_ids)
            np.testing.assert_array_equal(layers_at(rec, at(rerun_log.ENTITY_DEPTH_LAYERS), i, small),
                                          patch.layer_ids[::STEP, ::STEP])
            assert (patch.layer_ids == LAYER_INTERIOR).any()  # each instrument's own interior
            assert distance[i] == pytest.approx(1000 * patch.distance_m, rel=1e-12)
            assert signal[i] == pytest.approx(patch.signal, rel=1e-12)
            if patch.found:
                n_boxes += 1
                # its label, in its colour (a dark shade, readable on the viewer's light label plate)
                labels = rec.values(rerun_log.ENTITY_LEFT_LABELS, "Points2D:labels")[i].as_py()
                colours = rec.values(rerun_log.ENTITY_LEFT_LABELS, "Points2D:colors")[i].as_py()
                mine = [t for t, c in zip(labels, colours) if c == packed(label_colour(tool))]
                assert len(mine) == 1 and mine[0].startswith(f"{1000 * patch.distance_m:.1f} mm"), (i, labels)
                start, end = rec.values(at(rerun_log.ENTITY_PATCH_GAP), "LineStrips3D:strips")[i].as_py()[0]
                assert end[2] - start[2] == pytest.approx(patch.distance_m, rel=1e-4)
                assert rec.values(at(rerun_log.ENTITY_PATCH_TOOL), "Points3D:positions")[i].as_py()
        assert n_boxes >= len(frames) - 2, tool
    # the two instruments' layers differ (each is its own patch, not the frame's nearest one)
    assert not np.array_equal(layers_at(rec, rerun_log.ENTITY_LEFT_LAYERS, 0, (H, W)),
                              layers_at(rec, tool_entity(rerun_log.ENTITY_LEFT_LAYERS, 2), 0, (H, W)))


def test_an_absent_instrument_is_cleared(two_run):
    _, _, rec = two_run
    # frame 4: instrument 2 left the frame: every one of its entities cleared, its series broken; back at 6
    for entity in TOOL_ENTITIES:
        cleared = rec.frames(tool_entity(entity, 2), "Clear:is_recursive")
        assert ABSENT[0] in cleared and BAD in cleared, entity
        assert 0 not in cleared and 6 not in cleared, entity
    for entity in (rerun_log.ENTITY_SERIES_DISTANCE, rerun_log.ENTITY_SERIES_SIGNAL):
        series = rec.scalars(tool_entity(entity, 2))
        assert math.isnan(series[ABSENT[0]]) and math.isnan(series[BAD]) and not math.isnan(series[6])
    layers_2 = tool_entity(rerun_log.ENTITY_LEFT_LAYERS, 2)
    assert not set(ABSENT) & set(rec.frames(layers_2, "SegmentationImage:buffer"))
    # instrument 1, present throughout, is never cleared but at the bad frame (log_bad_frame, as before)
    assert rec.frames(rerun_log.ENTITY_LEFT_LAYERS, "Clear:is_recursive") == [BAD]


def test_each_instrument_has_one_colour_in_every_pane(two_run):
    _, _, rec = two_run
    one, two = instrument_style(1), instrument_style(2)
    # instrument 1: the world's classes (no context of its own), its interior and edge in its colour
    world = context_colours(rec, rerun_log.ENTITY_WORLD)
    assert world == {s.class_id: packed(s.rgba) for s in LAYER_STYLES}
    assert (rerun_log.ENTITY_LEFT_LAYERS, "AnnotationContext:context") not in rec.static
    # instrument 2: its own classes on its layer entities, the interior and edge in its colour, ring and band alike
    for entity in (rerun_log.ENTITY_LEFT_LAYERS, rerun_log.ENTITY_DEPTH_LAYERS):
        own = context_colours(rec, tool_entity(entity, 2))
        assert own == {s.class_id: packed(s.rgba) for s in two.layers}
        assert own[LAYER_INTERIOR] != world[LAYER_INTERIOR] and own[LAYER_TOOL_EDGE] != world[LAYER_TOOL_EDGE]
        assert own[LAYER_RING] == world[LAYER_RING] and own[LAYER_BAND] == world[LAYER_BAND]
    # the interior, box, gap, distance, signal and posterior of an instrument: one hue, its own
    for style in (one, two):
        interior = dict((s.class_id, s.rgba) for s in style.layers)[LAYER_INTERIOR]
        assert interior[:3] == style.window[:3] == style.gap[:3] == style.line[:3] == style.signal[:3]
    for entity, component, colour_1, colour_2 in (
            (rerun_log.ENTITY_LEFT_PATCH, "Boxes2D:colors", one.window, two.window),
            (rerun_log.ENTITY_PATCH_GAP, "LineStrips3D:colors", one.gap, two.gap)):
        assert {tuple(v.as_py()) for v in rec.values(entity, component).values()} == {(packed(colour_1),)}
        assert {tuple(v.as_py()) for v in rec.values(tool_entity(entity, 2), component).values()} == {
            (packed(colour_2),)}
    for entity in (rerun_log.ENTITY_SERIES_DISTANCE, rerun_log.ENTITY_SERIES_SIGNAL):
        assert rec.static[(entity, "SeriesLines:colors")].as_py() == [packed(one.line)]
        assert rec.static[(tool_entity(entity, 2), "SeriesLines:colors")].as_py() == [packed(two.line)]
    # the legend names the instruments
    assert rec.static[(rerun_log.ENTITY_SERIES_DISTANCE, "SeriesLines:names")].as_py() == ["instrument 1 (mm)"]
    assert rec.static[(tool_entity(rerun_log.ENTITY_SERIES_DISTANCE, 2), "SeriesLines:names")].as_py() == [
        "instrument 2 (mm)"]
    # a fixed palette: every id its colour, always the same; instrument 1's are the single-instrument styles
    assert one.window == PATCH_STYLES["window"] and one.layers == LAYER_STYLES and one.line == (
        SERIES_STYLES["distance_mm"].rgba) == SERIES_STYLES["signal"].rgba == SERIES_STYLES["posterior"].rgba
    interiors = [dict((s.class_id, s.rgba) for s in instrument_style(k).layers)[LAYER_INTERIOR] for k in range(1, 6)]
    assert len(set(interiors)) == 5 and len({instrument_style(k).window for k in range(1, 6)}) == 5
    assert instrument_style(2) == two and instrument_style(7).window == two.window  # (5 colours, then again)
    # no instrument in the ring's, band's or truth's colour
    taken = {world[LAYER_RING] >> 8, world[LAYER_BAND] >> 8, packed(SERIES_STYLES["contact_truth"].rgba) >> 8}
    assert not {packed(instrument_style(k).window) >> 8 for k in range(1, 6)} & taken


def test_the_nearest_instrument_per_frame_and_in_the_summary(two_run):
    session, summary, rec = two_run
    want = expected(session)
    texts = {f: v.as_py()[0] for f, v in rec.values(rerun_log.ENTITY_CONTACT, "TextDocument:text").items()}
    assert sorted(texts) == list(range(N_FRAMES))
    nearest = {}
    for i, tools in want.items():
        if not tools:
            assert "could not be read" in texts[i]
            continue
        k = min(tools, key=lambda t: abs(tools[t].distance_m))
        nearest[i] = k
        name = f"instrument {k} ({instrument_style(k).colour_name})"
        assert texts[i].startswith(f"**nearest: {name}, "), (i, texts[i])
        for tool, patch in tools.items():
            assert f"instrument {tool} ({instrument_style(tool).colour_name}): {1000 * patch.distance_m:.1f} mm" in \
                texts[i]
        # the nearest instrument's label is marked, the other's not; each label in its instrument's colour
        labels = rec.values(rerun_log.ENTITY_LEFT_LABELS, "Points2D:labels")[i].as_py()
        colours = rec.values(rerun_log.ENTITY_LEFT_LABELS, "Points2D:colors")[i].as_py()
        for label, colour in zip(labels, colours):
            tool = next(t for t in tools if packed(label_colour(t)) == colour)
            assert label.endswith(CONTACT_MARK) == (tool == k), (i, tool, label)
    assert {nearest[i] for i in (0, 1, 2, 3)} == {2} and {nearest[i] for i in (6, 7, 8, 10, 11)} == {1}
    counts = {k: list(nearest.values()).count(k) for k in (1, 2)}
    assert summary.nearest_frames == counts and summary.nearest_instrument == max(counts, key=counts.get)
    line = [t for t in summary.lines() if t.startswith("nearest instrument:")]
    assert line and line[0].startswith(f"nearest instrument: {summary.nearest_instrument} (nearest on "
                                       f"{counts[summary.nearest_instrument]} frames")
    assert "instruments: 1 on 11 frames, 2 on 9 frames" in summary.lines()
    # the blueprint has the contact text in a view of its own
    assert "TextDocument" in rec.blueprint_rows["classes"]


def test_with_a_model_each_instrument_has_its_posterior_and_the_scene_the_max(two_dir, tmp_path):
    model = tiny_model(contact=(2.6, 0.2), free=(2.2, 0.1))
    ensemble = model.ensemble
    session, summary, rec = view(two_dir, tmp_path / "model.rrd", model=model, points=False, images="jpeg")
    want = expected(session)
    columns = {k: np.array([want[i][k].signal if k in want[i] else np.nan for i in range(N_FRAMES)]) for k in (1, 2)}
    each = {k: ensemble.predict_proba(x) for k, x in columns.items()}  # forward_filter, NaN where absent
    for k in (1, 2):
        logged = rec.scalars(tool_entity(rerun_log.ENTITY_SERIES_POSTERIOR, k))
        present = [i for i in range(N_FRAMES) if k in want[i]]
        np.testing.assert_allclose([logged[i] for i in present], each[k][present], rtol=0, atol=1e-15)
        assert all(math.isnan(logged[i]) for i in set(range(N_FRAMES)) - set(present) if i in logged)
        assert BAD in logged and math.isnan(logged[BAD])
    scene = rec.scalars(rerun_log.ENTITY_SERIES_POSTERIOR)
    threshold = ensemble.threshold_
    contact_frames = {}
    texts = {f: v.as_py()[0] for f, v in rec.values(rerun_log.ENTITY_CONTACT, "TextDocument:text").items()}
    for i in range(N_FRAMES):
        present = list(want[i]) or [1, 2]  # no instrument (the bad frame): the max over all
        assert scene[i] == max(each[k][i] for k in present)
        if not want[i]:
            continue
        top = max(want[i], key=lambda k: (each[k][i], -k))
        if each[top][i] >= threshold:
            contact_frames[top] = contact_frames.get(top, 0) + 1
            name = f"instrument {top} ({instrument_style(top).colour_name})"
            assert texts[i].startswith(f"**in contact: {name}, P {each[top][i]:.2f} >= threshold"), (i, texts[i])
        else:
            assert texts[i].startswith(f"**no contact: largest P {each[top][i]:.2f} (instrument {top}"), (i, texts[i])
    assert len(set(np.round(each[1], 2))) > 2 and len(set(np.round(each[2], 2))) > 2  # the posteriors move
    assert contact_frames and summary.contact_frames == contact_frames
    assert any(t.startswith("in contact: instrument ") for t in summary.lines())
    assert rec.static[(tool_entity(rerun_log.ENTITY_SERIES_POSTERIOR, 2), "SeriesLines:colors")].as_py() == [
        packed(instrument_style(2).line)]


def test_one_selected_instrument_keeps_the_single_instrument_paths(two_dir, tmp_path):
    # --object-id 2 alone: a session of one instrument, recorded at today's paths, in instrument 2's colours
    session, summary, rec = view(two_dir, tmp_path / "only2.rrd", object_ids=[2], points=False, images="jpeg")
    want = expected(session)
    assert summary.instrument_frames == {2: N_FRAMES - len(ABSENT) - 1}
    assert not [e for e, _ in rec.rows if "/tools/" in e] and not [e for e, _ in rec.static if "/tools/" in e]
    for i in range(N_FRAMES):
        if 2 in want[i]:
            np.testing.assert_array_equal(layers_at(rec, rerun_log.ENTITY_LEFT_LAYERS, i, (H, W)), want[i][2].layer_ids)
            if want[i][2].found:  # its label, in its colour: the distance, marked as the nearest (the only one)
                assert rec.values(rerun_log.ENTITY_LEFT_LABELS, "Points2D:labels")[i].as_py() == [
                    f"{1000 * want[i][2].distance_m:.1f} mm {CONTACT_MARK}"]
                assert rec.values(rerun_log.ENTITY_LEFT_LABELS, "Points2D:colors")[i].as_py() == [
                    packed(label_colour(2))]
    own = context_colours(rec, rerun_log.ENTITY_LEFT_LAYERS)
    assert own == {s.class_id: packed(s.rgba) for s in instrument_style(2).layers}
    assert rec.static[(rerun_log.ENTITY_SERIES_DISTANCE, "SeriesLines:names")].as_py() == [
        SERIES_STYLES["distance_mm"].name]


def test_a_binary_mask_session_records_no_instrument_paths(tmp_path):
    root = tmp_path / "one"
    write_session(root, n_frames=4)
    session, summary, rec = view(root, tmp_path / "one.rrd", points=False, images="jpeg")
    assert not [e for e, _ in rec.rows if "/tools/" in e] and not [e for e, _ in rec.static if "/tools/" in e]
    assert rec.static[(rerun_log.ENTITY_SERIES_DISTANCE, "SeriesLines:names")].as_py() == [
        SERIES_STYLES["distance_mm"].name]
    assert summary.instrument_frames == {1: 4} and summary.nearest_instrument == 1
    distances = [frame_patches(session.load_frame(i, ("mask", "depth")), PatchParams())[0].distance_m
                 for i in range(4)]
    frame = int(np.argmin(np.abs(distances)))
    line = f"nearest instrument: 1 (nearest on 4 frames); closest: {1000 * distances[frame]:.1f} mm at frame {frame:06d}"
    assert line in summary.lines()
    assert not [t for t in summary.lines() if t.startswith("instruments:")]
    shutil.rmtree(root)
