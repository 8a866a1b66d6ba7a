"""The viewer marks the kinds of depth: the depth-kind layer (ENTITY_DEPTH_KIND) of a stereo-only session (SGBM's
fine match, its outline, the coarse pass, no depth), read back from the .rrd it writes; with depth files, the pixels
without depth."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

rr = pytest.importorskip("rerun")
from rerun.chunk import RrdReader  # noqa: E402

from test_stereo import random_dot_pair  # noqa: E402  (the stereo tests' synthetic pair)
from test_viewer import Recording, image_buffer, write_session  # noqa: E402  (the viewer tests' helpers)

from contact_viz.geometry.stereo import SGBMParams  # noqa: E402
from contact_viz.io.session import open_session  # noqa: E402
from contact_viz.viz import rerun_log  # noqa: E402
from contact_viz.viz.debugger import DebuggerOptions, run_debugger  # noqa: E402
from contact_viz.viz.style import (DEPTH_COARSE, DEPTH_FINE, DEPTH_FINE_EDGE, DEPTH_KIND_STYLES, DEPTH_NONE,  # noqa: E402
                                   LAYER_STYLES)

H, W = 96, 192  # image size, px
N = 4  # frames
STEP = 4  # depth decimation of the runs here, px (not a divisor of W - 2: the last column counts)
KIND = rerun_log.ENTITY_DEPTH_KIND


def tool_rows(i: int) -> int:
    return 40 + 6 * i  # the tool comes down from the top edge, px


def write_stereo_masked_session(root: Path, n: int = N) -> None:
    """left/, right/, masks/ and K.txt, no depth/: SGBM depth, the fine match around the tool (a nearer layer)."""
    for sub in ("left", "right", "masks"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    (root / "K.txt").write_text(f"200 0 {W / 2} 0 200 {H / 2} 0 0 1\n0.005\n")
    for i in range(n):
        box = (0, tool_rows(i), 90, 120)
        left, right, _, _ = random_dot_pair(H, W, [(6, None), (14, box)], seed=i)
        Image.fromarray(left).save(root / "left" / f"{i}.png")
        Image.fromarray(right).save(root / "right" / f"{i}.png")
        mask = np.zeros((H, W), np.uint8)
        mask[box[0]:box[1], box[2]:box[3]] = 255
        Image.fromarray(mask).save(root / "masks" / f"{i}.png")


def view(root: Path, out: Path, cache: Path, **kwargs):
    """Run the viewer on ``root`` into ``out`` (strict mode) and read the recording back."""
    rr.set_strict_mode(True)
    session = open_session(root, cache_dir=cache)
    opened = rerun_log.open_recording(save=out, blueprint=rerun_log.default_blueprint())
    options = DebuggerOptions(images="jpeg", depth_step=STEP, **kwargs)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # (a frame without a patch may warn; not what is tested here)
        summary = run_debugger(session, opened.rec, options)
    opened.close()
    rec = Recording(out)
    rec.path = out
    return session, summary, rec


@pytest.fixture(scope="module")
def stereo_run(tmp_path_factory):
    base = tmp_path_factory.mktemp("coarse")
    write_stereo_masked_session(base / "sess")
    return view(base / "sess", base / "stereo.rrd", base / "cache")


def test_stereo_session_marks_fine_and_coarse_depth_on_the_depth_grid(stereo_run):
    session, summary, rec = stereo_run
    assert summary.frames == N and summary.bad_frames == 0
    assert SGBMParams().region and SGBMParams().tool_mask_aware  # what makes the frames carry depth_fine
    grid = (-(-H // STEP), -(-W // STEP))
    layers = rec.values(KIND, "SegmentationImage:buffer")
    depth = rec.values(rerun_log.ENTITY_DEPTH_IMAGE, "DepthImage:buffer")
    assert sorted(layers) == list(range(N))  # one layer per frame
    for index in range(N):
        frame = session.load_frame(index)
        assert frame.depth_fine is not None and frame.depth_fine.shape == (H, W)
        ids = image_buffer(layers[index], grid, np.uint8)  # same grid as the decimated depth image
        assert image_buffer(depth[index], grid, np.uint16).shape == ids.shape
        np.testing.assert_array_equal(ids, expected_kinds(frame.depth_fine[::STEP, ::STEP],
                                                          image_buffer(depth[index], grid, np.uint16)))
        assert {DEPTH_FINE, DEPTH_COARSE, DEPTH_FINE_EDGE} <= set(np.unique(ids))
        # the tool is fine depth (its edge in the fine region's outline); away from it, the coarse pass
        tool = np.zeros((H, W), bool)
        tool[:tool_rows(index), 90:120] = True
        assert np.isin(ids[tool[::STEP, ::STEP]], (DEPTH_FINE, DEPTH_FINE_EDGE, DEPTH_NONE)).all()
        assert np.isin(ids[:, :10 // STEP], (DEPTH_COARSE, DEPTH_NONE)).all()
    # drawn over the depth image, under the layer overlay
    draw_order = rec.values(KIND, "SegmentationImage:draw_order")
    assert {v.as_py()[0] for v in draw_order.values()} == {-10.0}

    # its classes: its own AnnotationContext (static), found before the layer classes on world (the ids overlap)
    context = rec.static[(KIND, "AnnotationContext:context")].as_py()[0]
    info = {c["class_id"]: c["class_description"]["info"] for c in context}
    assert set(info) == {DEPTH_FINE, DEPTH_COARSE, DEPTH_NONE, DEPTH_FINE_EDGE}
    assert "fine" in info[DEPTH_FINE]["label"] and "coarse" in info[DEPTH_COARSE]["label"]
    assert info[DEPTH_FINE]["color"] & 0xFF == 0  # fine: left as it is
    assert 0 < info[DEPTH_COARSE]["color"] & 0xFF < 255  # coarse: a translucent veil, the depth still shows under it
    assert info[DEPTH_NONE]["color"] & 0xFF == 255 and info[DEPTH_FINE_EDGE]["color"] & 0xFF == 255  # opaque
    assert len({info[k]["color"] for k in info}) == 4  # four kinds, four looks
    assert [(s.class_id, s.name) for s in DEPTH_KIND_STYLES] == [(k, info[k]["label"]) for k in
                                                                 (DEPTH_FINE, DEPTH_COARSE, DEPTH_NONE,
                                                                  DEPTH_FINE_EDGE)]
    world = rec.static[(rerun_log.ENTITY_WORLD, "AnnotationContext:context")].as_py()[0]
    assert {c["class_id"] for c in world} == {s.class_id for s in LAYER_STYLES}  # unchanged

    # the default layout: the depth view (everything under the depth camera) shows it, the 3D view leaves it out
    queries, names = {}, {}
    reader = RrdReader(rec.path)
    for store in reader.blueprints():
        for chunk in reader.stream(store=store):
            batch = chunk.to_record_batch()
            view_id = chunk.entity_path.split("/ViewContents")[0]
            for name in batch.schema.names:
                if name == "ViewContents:query":
                    queries[view_id] = batch.column(name).to_pylist()[-1]
                if name == "ViewBlueprint:space_origin":
                    names[view_id] = batch.column(name).to_pylist()[-1][0]
    depth_view = [v for v, origin in names.items() if origin == rerun_log.ENTITY_DEPTH_CAMERA]
    assert len(depth_view) == 1 and queries[depth_view[0]] == ["$origin/**"]
    assert KIND.startswith(rerun_log.ENTITY_DEPTH_CAMERA + "/")
    scene = [v for v, origin in names.items() if origin == rerun_log.ENTITY_WORLD]
    assert f"- {KIND}" in queries[scene[0]]


def test_a_bad_frame_clears_the_layer_and_the_next_good_frame_brings_it_back(tmp_path):
    root = tmp_path / "sess"
    write_stereo_masked_session(root)
    (root / "masks" / "1.png").write_bytes(b"not a PNG")  # frame 1 cannot be read
    _, summary, rec = view(root, tmp_path / "bad.rrd", tmp_path / "cache", with_right=False)
    assert summary.bad_frames == 1
    assert rec.frames(KIND, "SegmentationImage:buffer") == [0, 2, 3]
    assert rec.frames(KIND, "Clear:is_recursive") == [1]  # no stale layer at the bad frame, and cleared once


def test_depth_kind_layer_logs_classes_once_and_clears_only_after_a_shown_layer(tmp_path):
    out = tmp_path / "unit.rrd"
    rr.set_strict_mode(True)
    opened = rerun_log.open_recording(save=out)
    layer = rerun_log.DepthKindLayer()
    fine = np.zeros((10, 13), bool)
    fine[2:5, 3:9] = True
    for index, mask in enumerate([None, fine, fine, None, None, fine]):
        rerun_log.set_frame_time(opened.rec, index, index / 30)
        layer.log(opened.rec, rerun_log.depth_kind_ids(mask, 3))
    opened.close()
    rec = Recording(out)
    assert rec.frames(KIND, "SegmentationImage:buffer") == [1, 2, 5]
    assert rec.frames(KIND, "Clear:is_recursive") == [3]
    ids = image_buffer(rec.values(KIND, "SegmentationImage:buffer")[1], (4, 5), np.uint8)
    np.testing.assert_array_equal(ids, expected_kinds(fine[::3, ::3], None))
    assert rerun_log.depth_kind_ids(None, 3) is None
    assert rerun_log.depth_kind_ids(fine, 3).dtype == np.uint8
    # a worked example: a 3x4 fine block inside a 5x6 grid, one pixel without depth
    block = np.zeros((5, 6), bool)
    block[1:4, 1:5] = True
    depth_u16 = np.ones((5, 6), np.uint16)
    depth_u16[0, 0] = 0
    F, C, N_, E = DEPTH_FINE, DEPTH_COARSE, DEPTH_NONE, DEPTH_FINE_EDGE
    np.testing.assert_array_equal(rerun_log.depth_kind_ids(block, 1, depth_u16), [
        [N_, C, C, C, C, C], [C, E, E, E, E, C], [C, E, F, F, E, C], [C, E, E, E, E, C], [C, C, C, C, C, C]])
    # depth files: only the pixels without depth are marked
    np.testing.assert_array_equal(rerun_log.depth_kind_ids(None, 1, depth_u16), np.where(depth_u16 == 0, N_, F))


def expected_kinds(fine: np.ndarray, depth_u16: np.ndarray | None) -> np.ndarray:
    """The depth kinds, literally: fine, its pixels with a coarse 8-neighbour on the edge, coarse, none."""
    h, w = fine.shape
    out = np.where(fine, DEPTH_FINE, DEPTH_COARSE).astype(np.uint8)
    for y in range(h):
        for x in range(w):
            near = fine[max(y - 1, 0):y + 2, max(x - 1, 0):x + 2]
            if fine[y, x] and not near.all():
                out[y, x] = DEPTH_FINE_EDGE
    if depth_u16 is not None:
        out[depth_u16 == 0] = DEPTH_NONE
    return out


def test_a_depth_files_session_marks_only_the_pixels_without_depth(tmp_path):
    root = tmp_path / "sess"
    write_session(root, n_frames=3)  # depth/ files with 2% holes: no fine or coarse, but pixels without depth
    session, summary, rec = view(root, tmp_path / "files.rrd", tmp_path / "cache", with_right=False)
    assert summary.frames == 3 and session.load_frame(0).depth_fine is None
    height, width = session.image_size  # (test_viewer's session)
    grid = (-(-height // STEP), -(-width // STEP))
    depth = rec.values(rerun_log.ENTITY_DEPTH_IMAGE, "DepthImage:buffer")
    for index, value in rec.values(KIND, "SegmentationImage:buffer").items():
        ids = image_buffer(value, grid, np.uint8)
        none = image_buffer(depth[index], grid, np.uint16) == 0
        assert none.any() and set(np.unique(ids)) == {DEPTH_FINE, DEPTH_NONE}
        np.testing.assert_array_equal(ids == DEPTH_NONE, none)
