"""Tests of the visual debugger: style, point clouds, diagnostics, and the .rrd it writes (read back with RrdReader)."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
import textwrap
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

rr = pytest.importorskip("rerun")
from rerun.chunk import RrdReader  # noqa: E402

from contact_viz.viz import rerun_log  # noqa: E402
from contact_viz.viz.debugger import DebuggerOptions, run_debugger, select_frames  # noqa: E402
from contact_viz.viz.rerun_log import open_recording  # noqa: E402
from contact_viz.viz.diagnostics import DIAGNOSTIC_CODES, SESSION_DIAGNOSTIC_CODES  # noqa: E402
from contact_viz.errors import SessionWarning  # noqa: E402
from contact_viz.pipeline.extract import BadFrameWarning  # noqa: E402
from contact_viz.model.hmm import LosoEnsemble  # noqa: E402
from contact_viz.model.model_file import ContactModel  # noqa: E402
from contact_viz.params import LabelParams, PatchParams  # noqa: E402
from contact_viz.geometry.patch import (  # noqa: E402
    LAYER_BACKGROUND, LAYER_BAND, LAYER_INTERIOR, LAYER_RING, LAYER_TOOL_EDGE, compute_patch,
)
from contact_viz.geometry.pointcloud import (  # noqa: E402
    FAR_POINT_RADIUS,
    CloudParams,
    backproject,
    decimated_intrinsics,
    depth_cloud,
    depth_preview,
    patch_geometry,
    sample_colors,
    voxel_downsample,
)
from contact_viz.io.session import open_session  # noqa: E402
from contact_viz.viz.style import DIAGNOSTIC_STYLES, LAYER_STYLES, SERIES_STYLES, layer_style  # noqa: E402

H, W = 180, 320  # test image size, px
N_FRAMES = 12
FX = FY = 300.0  # focal length, px
CX, CY = 159.5, 89.5  # principal point, px
BASELINE_M = 0.005
TISSUE_M = 0.10  # tissue depth at the image centre, m
TOOL_COLS = (140, 180)  # tool shaft columns [x0, x1), px
DEPTH_STEP = DebuggerOptions().depth_step  # the default depth decimation, px


def gap_m(t: int) -> float:
    """Tool-tissue gap of frame t: 8 mm closing by 1 mm per frame (negative = pressing in)."""
    return 0.008 - 0.001 * t


def write_session(root: Path, n_frames: int = N_FRAMES, seed: int = 0) -> None:
    """A small session: a tilted textured plane and a tool shaft coming down from the top edge."""
    rng = np.random.default_rng(seed)
    for sub in ("left", "right", "masks", "depth"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    (root / "K.txt").write_text(f"{FX} 0 {CX} 0 {FY} {CY} 0 0 1\n{BASELINE_M}\n")
    (root / "session.json").write_text('{"fps": 30}')
    rows = np.arange(H, dtype=np.float64)[:, None]
    tissue = TISSUE_M + 0.0001 * (CY - rows) + np.zeros((H, W))  # recedes upwards: nearest below the tip
    texture = rng.integers(60, 200, (H // 4 + 1, W // 4 + 1, 3), dtype=np.uint8)
    texture = np.kron(texture, np.ones((4, 4, 1), np.uint8))[:H, :W]
    force_rows = ["frame,fx,fy,fz"]
    for t in range(n_frames):
        stem = f"{t:06d}"
        tip = 70 + 2 * t  # the shaft grows downwards
        mask = np.zeros((H, W), np.uint8)
        mask[:tip, TOOL_COLS[0]:TOOL_COLS[1]] = 255
        depth = tissue.copy()
        depth[mask > 0] = tissue[tip, 160] - gap_m(t)
        depth[rng.random((H, W)) < 0.02] = np.nan  # stereo holes
        np.save(root / "depth" / f"{stem}.npy", depth.astype(np.float32))
        Image.fromarray(mask).save(root / "masks" / f"{stem}.png")
        left = texture.copy()
        left[mask > 0] = (90, 90, 100)
        Image.fromarray(left).save(root / "left" / f"{stem}.jpg", quality=90)
        Image.fromarray(np.roll(left, -8, axis=1)).save(root / "right" / f"{stem}.jpg", quality=90)
        force_z = max(0.0, -gap_m(t)) * 1000.0 + 0.05 * t  # N: 1 N per mm of pressing, plus a drift
        force_rows.append(f"{stem},0.1,{-0.02 * t:.3f},{force_z:.4f}")
    (root / "force.csv").write_text("\n".join(force_rows) + "\n")


@pytest.fixture(scope="module")
def session_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("viewer") / "sess"
    write_session(root)
    return root


def expected_patches(session, indices, params=PatchParams()):
    """compute_patch on each frame, independently of the debugger (frame index -> (frame, patch))."""
    out = {}
    for index in indices:
        frame = session.load_frame(index, ("mask", "depth"))
        out[index] = (frame, compute_patch(frame.depth_m, frame.tool_mask, params))
    return out


# ------------------------------------------------------------------------------------------
# Reading a saved recording back
# ------------------------------------------------------------------------------------------


class Recording:
    """Every row of an .rrd: temporal rows per (entity, component) with their frame, and static values."""

    def __init__(self, path: Path) -> None:
        reader = RrdReader(path)
        self.blueprints = reader.blueprints()
        self.rows: dict[tuple[str, str], list[tuple[int, object]]] = defaultdict(list)
        self.static: dict[tuple[str, str], object] = {}
        static_row: dict[tuple[str, str], bytes] = {}
        self.blueprint_rows: dict[str, list[str]] = {}
        for chunk in reader.stream():
            batch = chunk.to_record_batch()
            entity = chunk.entity_path.lstrip("/")
            components = [n for n in batch.schema.names if ":" in n]
            if chunk.is_static:
                # static data: the last write wins by row id (creation order), whatever the chunks' order in the file
                row_id = batch.column("rerun.controls.RowId")[batch.num_rows - 1].as_py()
                for name in components:
                    if row_id >= static_row.get((entity, name), b""):
                        static_row[(entity, name)] = row_id
                        self.static[(entity, name)] = batch.column(name)[batch.num_rows - 1]
                continue
            frames = batch.column("frame").to_pylist()
            for name in components:
                column = batch.column(name)
                for i, frame in enumerate(frames):
                    if column[i].is_valid:
                        self.rows[(entity, name)].append((frame, column[i]))
        for store in self.blueprints:
            for chunk in reader.stream(store=store):
                batch = chunk.to_record_batch()
                self.blueprint_rows[chunk.entity_path] = [n for n in batch.schema.names if ":" in n]
                for name in batch.schema.names:
                    if name.endswith("class_identifier"):
                        self.blueprint_rows.setdefault("classes", []).extend(
                            v[0] for v in batch.column(name).to_pylist())

    def frames(self, entity: str, component: str) -> list[int]:
        return sorted(f for f, _ in self.rows[(entity, component)])

    def values(self, entity: str, component: str) -> dict[int, object]:
        """frame -> value (the last row of that frame)."""
        return {f: v for f, v in sorted(self.rows[(entity, component)], key=lambda r: r[0])}

    def scalars(self, entity: str) -> dict[int, float]:
        rows = self.values(entity, "Scalars:scalars")
        return {f: v.values.to_numpy(zero_copy_only=False)[0] for f, v in rows.items()}

    def texts(self, entity: str = rerun_log.ENTITY_LOG) -> list[tuple[int, str, str]]:
        texts = self.rows[(entity, "TextLog:text")]
        levels = self.rows[(entity, "TextLog:level")]
        return [(f, t.as_py()[0], lv.as_py()[0]) for (f, t), (_, lv) in zip(texts, levels)]


def image_buffer(value, shape, dtype) -> np.ndarray:
    """The one buffer (blob) of a row: a list of one list of bytes, as an array."""
    raw = value.values[0].values.to_numpy(zero_copy_only=False)
    return np.frombuffer(raw.astype(np.uint8).tobytes(), dtype=dtype).reshape(shape)


def run(session_dir: Path, out: Path, options=DebuggerOptions(), model=None, **kwargs):
    rr.set_strict_mode(True)  # any logging mistake raises instead of being logged and skipped
    session = open_session(session_dir)
    opened = open_recording(save=out, blueprint=rerun_log.default_blueprint(with_model=model is not None))
    summary = run_debugger(session, opened.rec, options, model=model, **kwargs)
    opened.close()
    return session, summary, Recording(out)


# ------------------------------------------------------------------------------------------
# The recording
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def default_run(session_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("rrd") / "view.rrd"
    return run(session_dir, out)


@pytest.fixture(scope="module")
def jpeg_run(session_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("rrd") / "jpeg.rrd"
    return run(session_dir, out, DebuggerOptions(images="jpeg"))


def test_every_entity_once_per_frame_with_the_right_archetype(default_run):
    session, summary, rec = default_run
    frames = list(range(N_FRAMES))
    assert summary.frames == N_FRAMES and summary.bad_frames == 0 and not summary.interrupted
    per_frame = {
        rerun_log.ENTITY_LEFT_IMAGE: "VideoStream:sample",
        rerun_log.ENTITY_RIGHT_IMAGE: "VideoStream:sample",
        rerun_log.ENTITY_LEFT_LAYERS: "SegmentationImage:buffer",
        rerun_log.ENTITY_DEPTH_IMAGE: "DepthImage:buffer",
        rerun_log.ENTITY_DEPTH_LAYERS: "SegmentationImage:buffer",
        rerun_log.ENTITY_LEFT_PATCH: "Boxes2D:half_sizes",
        rerun_log.ENTITY_DEPTH_PATCH: "Boxes2D:half_sizes",
        rerun_log.ENTITY_CLOUD_NEAR: "Points3D:positions",
        rerun_log.ENTITY_CLOUD_FAR: "Points3D:positions",
        rerun_log.ENTITY_PATCH_TISSUE: "Points3D:positions",
        rerun_log.ENTITY_PATCH_TOOL: "Points3D:positions",
        rerun_log.ENTITY_PATCH_GAP: "LineStrips3D:strips",
        rerun_log.ENTITY_PATCH_GAP_LENGTH: "Points3D:labels",
        rerun_log.ENTITY_LEFT_LABELS: "Points2D:labels",
        rerun_log.ENTITY_SERIES_DISTANCE: "Scalars:scalars",
        rerun_log.ENTITY_SERIES_SIGNAL: "Scalars:scalars",
        rerun_log.ENTITY_SERIES_INVALID_DEPTH: "Scalars:scalars",
        rerun_log.ENTITY_SERIES_TRUTH: "Scalars:scalars",
        "series/force/magnitude": "Scalars:scalars",
        "series/force/z": "Scalars:scalars",
    }
    for entity, component in per_frame.items():
        assert rec.frames(entity, component) == frames, entity
    for entity in (rerun_log.ENTITY_LEFT_IMAGE, rerun_log.ENTITY_RIGHT_IMAGE):  # AV1 streams, said statically
        assert rec.static[(entity, "VideoStream:codec")].as_py() == [rr.VideoCodec.AV1.value]
    # the time timeline is the session's time
    times = [f for f, _ in rec.rows[(rerun_log.ENTITY_SERIES_DISTANCE, "Scalars:scalars")]]
    assert sorted(times) == frames

    # static: view coordinates, the layer classes, and the cameras
    assert (rerun_log.ENTITY_WORLD, "ViewCoordinates:xyz") in rec.static
    context = rec.static[(rerun_log.ENTITY_WORLD, "AnnotationContext:context")].as_py()[0]
    labels = {c["class_id"]: c["class_description"]["info"]["label"] for c in context}
    assert labels == {s.class_id: s.name for s in LAYER_STYLES}
    K = np.array(rec.static[(rerun_log.ENTITY_LEFT_CAMERA, "Pinhole:image_from_camera")].as_py()[0]).reshape(3, 3).T
    np.testing.assert_allclose(K, session.calibration.K, rtol=1e-6)
    K_depth = np.array(rec.static[(rerun_log.ENTITY_DEPTH_CAMERA, "Pinhole:image_from_camera")].as_py()[0])
    np.testing.assert_allclose(K_depth.reshape(3, 3).T, decimated_intrinsics(session.calibration.K, DEPTH_STEP),
                               rtol=1e-6)
    assert rec.static[(rerun_log.ENTITY_RIGHT_CAMERA, "Transform3D:translation")].as_py()[0] == pytest.approx(
        [BASELINE_M, 0, 0])
    # the right image is logged at half size: its camera has half the focal length and resolution
    K_right = np.array(rec.static[(rerun_log.ENTITY_RIGHT_CAMERA, "Pinhole:image_from_camera")].as_py()[0])
    np.testing.assert_allclose(K_right.reshape(3, 3).T[:2], np.asarray(session.calibration.K)[:2] / 2, rtol=1e-6)
    assert rec.static[(rerun_log.ENTITY_RIGHT_CAMERA, "Pinhole:resolution")].as_py()[0] == [W / 2, H / 2]
    for entity in (rerun_log.ENTITY_SERIES_DISTANCE, rerun_log.ENTITY_SERIES_TRUTH):
        assert (entity, "SeriesLines:colors") in rec.static
    # the resolved configuration travels with the recording
    config_text = rec.static[(rerun_log.ENTITY_CONFIG, "TextDocument:text")].as_py()[0]
    config = json.loads(config_text.split("```json\n", 1)[1].rsplit("\n```", 1)[0])
    assert config["options"]["patch_params"]["n1"] == 31 and config["session"]["frames"] == len(session)


def test_images_pass_through_and_layers_depth_patch_match_extract(jpeg_run, session_dir):
    session, _, rec = jpeg_run
    expected = expected_patches(session, range(N_FRAMES))
    blobs = rec.values(rerun_log.ENTITY_LEFT_IMAGE, "EncodedImage:blob")
    layers = rec.values(rerun_log.ENTITY_LEFT_LAYERS, "SegmentationImage:buffer")
    depth = rec.values(rerun_log.ENTITY_DEPTH_IMAGE, "DepthImage:buffer")
    depth_layers = rec.values(rerun_log.ENTITY_DEPTH_LAYERS, "SegmentationImage:buffer")
    centers = rec.values(rerun_log.ENTITY_LEFT_PATCH, "Boxes2D:centers")
    halves = rec.values(rerun_log.ENTITY_LEFT_PATCH, "Boxes2D:half_sizes")
    labels = rec.values(rerun_log.ENTITY_LEFT_LABELS, "Points2D:labels")
    distance = rec.scalars(rerun_log.ENTITY_SERIES_DISTANCE)
    signal = rec.scalars(rerun_log.ENTITY_SERIES_SIGNAL)
    tool_points = rec.values(rerun_log.ENTITY_PATCH_TOOL, "Points3D:positions")
    gap = rec.values(rerun_log.ENTITY_PATCH_GAP, "LineStrips3D:strips")
    n_found = 0
    for index, (frame, patch) in expected.items():
        stem = session.stems[index]
        # the JPEG file's own bytes, not re-encoded
        source = (session_dir / "left" / f"{stem}.jpg").read_bytes()
        assert image_buffer(blobs[index], (-1,), np.uint8).tobytes() == source
        np.testing.assert_array_equal(image_buffer(layers[index], (H, W), np.uint8), patch.layer_ids)
        step = DEPTH_STEP
        np.testing.assert_array_equal(image_buffer(depth[index], (-(-H // step), -(-W // step)), np.uint16),
                                      depth_preview(frame.depth_m, step, DebuggerOptions().depth_units_per_m))
        np.testing.assert_array_equal(image_buffer(depth_layers[index], (-(-H // step), -(-W // step)), np.uint8),
                                      patch.layer_ids[::step, ::step])
        assert distance[index] == pytest.approx(1000 * patch.distance_m, rel=1e-12, nan_ok=True)
        assert signal[index] == pytest.approx(patch.signal, rel=1e-12, nan_ok=True)
        if patch.found:
            n_found += 1
            x0, y0, x1, y1 = patch.window_xyxy
            center, half = np.array(centers[index].as_py()[0]), np.array(halves[index].as_py()[0])
            np.testing.assert_allclose(np.concatenate([center - half, center + half]), [x0, y0, x1, y1], atol=1e-4)
            # its label: the distance, marked as the nearest instrument (the only one)
            assert labels[index].as_py() == [f"{1000 * patch.distance_m:.1f} mm ●"]
            # the tool points' mean depth is the patch's tool depth; the gap runs from it over the distance in z
            pts = np.array(tool_points[index].as_py())
            assert pts[:, 2].mean() == pytest.approx(patch.tool_depth_m, rel=1e-5)
            start, end = np.array(gap[index].as_py()[0])
            assert start[2] == pytest.approx(patch.tool_depth_m, rel=1e-5)
            assert end[2] - start[2] == pytest.approx(patch.distance_m, rel=1e-4)
    assert n_found >= N_FRAMES - 2  # the scene is built so that (nearly) every frame has a patch


def test_known_series_blueprint_and_no_model_hint(default_run):
    session, _, rec = default_run
    force = rec.scalars("series/force/magnitude")
    np.testing.assert_allclose([force[i] for i in range(N_FRAMES)], session.force_n, rtol=1e-12)
    truth = rec.scalars(rerun_log.ENTITY_SERIES_TRUTH)
    assert [truth[i] for i in range(N_FRAMES)] == [float(v) for v in session.labels]
    assert set(session.labels.tolist()) == {0, 1}  # the scene has both states
    # no model: no posterior, threshold or prediction, and one hint saying how to get a model
    for entity in (rerun_log.ENTITY_SERIES_POSTERIOR, rerun_log.ENTITY_SERIES_THRESHOLD,
                   rerun_log.ENTITY_SERIES_PREDICTED):
        assert not rec.rows[(entity, "Scalars:scalars")]
    hints = [t for t in rec.texts() if t[1] == rerun_log.MODEL_HINT]
    assert len(hints) == 1 and hints[0][0] == 0 and "contact-viz fit" in hints[0][1] and "--model" in hints[0][1]
    # the blueprint is a store of its own, with the views of the layout
    assert len(rec.blueprints) == 1
    classes = rec.blueprint_rows["classes"]
    assert classes.count("TimeSeries") == 5 and classes.count("2D") == 3 and classes.count("3D") == 1
    assert "TextLog" in classes


def tiny_model(contact: tuple[float, float], free: tuple[float, float], seed: int = 5) -> ContactModel:
    """A tiny ensemble fitted on three random sequences whose contact frames have the signal ``contact``
    (mean, sd) and the others ``free``, in a model with the default patch parameters."""
    rng = np.random.default_rng(seed)
    signals, labels = [], []
    for _ in range(3):
        y = (np.sin(np.arange(300) / 15.0) > 0.3).astype(np.int64)
        signals.append(rng.normal(np.where(y == 1, contact[0], free[0]), np.where(y == 1, contact[1], free[1])))
        labels.append(y)
    return ContactModel(ensemble=LosoEnsemble().fit(signals, labels), patch_params=PatchParams(),
                        label_params=LabelParams(), training_sessions=())


def test_posterior_with_a_model_equals_predict_proba(session_dir, tmp_path):
    model = tiny_model(contact=(3.0, 0.3), free=(2.2, 0.1))
    ensemble = model.ensemble
    options = DebuggerOptions(stride=2, points=False)
    session, summary, rec = run(session_dir, tmp_path / "model.rrd", options, model=model)
    indices = list(range(0, N_FRAMES, 2))
    expected = expected_patches(session, indices)
    signal = np.array([expected[i][1].signal for i in indices])
    want = ensemble.predict_proba(signal)
    posterior = rec.scalars(rerun_log.ENTITY_SERIES_POSTERIOR)
    assert sorted(posterior) == indices
    np.testing.assert_allclose([posterior[i] for i in indices], want, rtol=0, atol=1e-15)
    assert len(set(np.round(want, 3))) > 1  # the posterior actually moves
    predicted = rec.scalars(rerun_log.ENTITY_SERIES_PREDICTED)
    assert [predicted[i] for i in indices] == [float(p >= ensemble.threshold_) for p in want]
    threshold = rec.scalars(rerun_log.ENTITY_SERIES_THRESHOLD)
    assert sorted(threshold) == indices and set(threshold.values()) == {ensemble.threshold_}
    assert not any(t[1] == rerun_log.MODEL_HINT for t in rec.texts())
    assert not rec.rows[(rerun_log.ENTITY_CLOUD_FAR, "Points3D:positions")]  # points=False

    # a model fitted with other patch parameters is refused
    other = ContactModel(ensemble=ensemble, patch_params=PatchParams(n2=15), label_params=LabelParams(),
                         training_sessions=())
    with pytest.raises(ValueError, match="n2"):
        run(session_dir, tmp_path / "refused.rrd", DebuggerOptions(), model=other)


def test_start_end_stride_select_the_frames(session_dir, tmp_path):
    options = DebuggerOptions(start=2, end=11, stride=3, with_right=False)
    session, summary, rec = run(session_dir, tmp_path / "sel.rrd", options)
    assert summary.frames == 3
    for entity, component in ((rerun_log.ENTITY_LEFT_IMAGE, "VideoStream:sample"),
                              (rerun_log.ENTITY_SERIES_DISTANCE, "Scalars:scalars"),
                              ("series/force/magnitude", "Scalars:scalars"),
                              (rerun_log.ENTITY_CLOUD_NEAR, "Points3D:positions")):
        assert rec.frames(entity, component) == [2, 5, 8], entity
    assert not rec.rows[(rerun_log.ENTITY_RIGHT_IMAGE, "VideoStream:sample")]
    expected = expected_patches(session, [2, 5, 8])
    distance = rec.scalars(rerun_log.ENTITY_SERIES_DISTANCE)
    for index, (_, patch) in expected.items():
        assert distance[index] == pytest.approx(1000 * patch.distance_m, rel=1e-12)
    assert list(select_frames(12, 2, 11, 3)) == [2, 5, 8]
    with pytest.raises(ValueError, match="start"):
        select_frames(12, 12)
    with pytest.raises(ValueError, match="end"):
        select_frames(12, 0, 13)
    with pytest.raises(ValueError, match="stride"):
        DebuggerOptions(stride=0)


def test_bad_frames_in_the_middle_are_logged_and_the_run_goes_on(session_dir, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(session_dir, broken)
    (broken / "depth" / "000005.npy").write_bytes(b"not a numpy file")
    (broken / "left" / "000007.jpg").write_bytes(b"\x00garbage, not a JPEG")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        session, summary, rec = run(broken, tmp_path / "bad.rrd", DebuggerOptions())
    assert [(w.category, str(w.message)[:13]) for w in caught] == [(BadFrameWarning, "frame 000005 "),
                                                                   (SessionWarning, "frame 000007:")]
    assert "000007.jpg" in str(caught[1].message)  # an image it cannot show: on the console as well
    assert summary.frames == N_FRAMES and summary.bad_frames == 1
    assert summary.diagnostic_counts["bad_frame"] == 1
    warns = [(f, text) for f, text, level in rec.texts() if level == "WARN"]
    assert any(f == 5 and "depth" in text and "000005.npy" in text for f, text in warns)
    assert any(f == 7 and "left image" in text and "000007.jpg" in text for f, text in warns)
    # frame 5: depth and patch cleared, gaps in the series, its own images shown; later frames are all there
    assert 5 in rec.frames(rerun_log.ENTITY_DEPTH_IMAGE, "Clear:is_recursive")
    assert 5 not in rec.frames(rerun_log.ENTITY_DEPTH_IMAGE, "DepthImage:buffer")
    assert math.isnan(rec.scalars(rerun_log.ENTITY_SERIES_DISTANCE)[5])
    assert rec.scalars(rerun_log.diagnostic_entity("bad_frame")) == {5: rerun_log.marker_height("bad_frame")}
    later = [i for i in range(6, N_FRAMES)]
    assert set(later) <= set(rec.frames(rerun_log.ENTITY_DEPTH_IMAGE, "DepthImage:buffer"))
    # every frame has a video sample: frame 5 its own image, frame 7 (unreadable) a grey one, never the frame before's
    samples = rec.values(rerun_log.ENTITY_LEFT_IMAGE, "VideoStream:sample")
    assert set(samples) == set(range(N_FRAMES))
    # an unreadable left image is only a display problem: frame 7 still has its patch
    assert not math.isnan(rec.scalars(rerun_log.ENTITY_SERIES_DISTANCE)[7])


def test_png_images_are_jpeg_encoded_and_raw_images_logged_as_is(session_dir, tmp_path):
    pngs = tmp_path / "pngs"
    shutil.copytree(session_dir, pngs)
    for jpg in sorted((pngs / "left").glob("*.jpg")):
        Image.open(jpg).save(jpg.with_suffix(".png"))
        jpg.unlink()
    session = open_session(pngs)
    source = np.asarray(Image.open(pngs / "left" / "000003.png"))
    _, _, rec = run(pngs, tmp_path / "png.rrd", DebuggerOptions(end=4, images="jpeg", jpeg_quality=95, with_right=False))
    blob = image_buffer(rec.values(rerun_log.ENTITY_LEFT_IMAGE, "EncodedImage:blob")[3], (-1,), np.uint8)
    assert blob[:3].tobytes() == b"\xff\xd8\xff"  # a JPEG, made from the PNG
    import cv2

    def cv2_jpeg(rgb, quality):
        return cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])[1].tobytes()

    assert blob.tobytes() == cv2_jpeg(source, 95)  # encoded once, at the quality asked for
    _, _, rec30 = run(pngs, tmp_path / "q30.rrd", DebuggerOptions(end=4, images="jpeg", jpeg_quality=30, with_right=False))
    blob30 = image_buffer(rec30.values(rerun_log.ENTITY_LEFT_IMAGE, "EncodedImage:blob")[3], (-1,), np.uint8)
    assert blob30.tobytes() == cv2_jpeg(source, 30) and blob30.size < blob.size
    _, _, rec = run(pngs, tmp_path / "raw.rrd", DebuggerOptions(end=4, images="raw", points=False))
    raw = rec.values(rerun_log.ENTITY_LEFT_IMAGE, "Image:buffer")
    np.testing.assert_array_equal(image_buffer(raw[3], (H, W, 3), np.uint8), source)
    right = rec.values(rerun_log.ENTITY_RIGHT_IMAGE, "Image:buffer")  # raw mode decodes the right JPEGs too
    np.testing.assert_array_equal(image_buffer(right[3], (H, W, 3), np.uint8),
                                  np.asarray(Image.open(pngs / "right" / "000003.jpg").convert("RGB")))
    assert session.has_right


def test_interrupted_run_leaves_a_readable_recording(session_dir, tmp_path):
    def stop_after_five(done, total):
        assert total == N_FRAMES
        if done == 5:
            raise KeyboardInterrupt

    _, summary, rec = run(session_dir, tmp_path / "stopped.rrd", DebuggerOptions(), progress=stop_after_five)
    assert summary.interrupted and summary.frames == 5
    assert rec.frames(rerun_log.ENTITY_LEFT_IMAGE, "VideoStream:sample") == [0, 1, 2, 3, 4]


def test_killed_process_leaves_what_was_flushed(session_dir, tmp_path):
    out = tmp_path / "killed.rrd"
    script = textwrap.dedent(f"""
        import os, signal, warnings
        warnings.simplefilter("ignore")
        from contact_viz.viz.debugger import DebuggerOptions, run_debugger
        from contact_viz.viz.rerun_log import open_recording
        from contact_viz.io.session import open_session
        def kill(done, total):
            if done == 6:
                os.kill(os.getpid(), signal.SIGKILL)
        opened = open_recording(save={str(out)!r})
        run_debugger(open_session({str(session_dir)!r}), opened.rec, DebuggerOptions(flush_every=3, points=False),
                     progress=kill)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode == -9, proc.stderr
    assert not out.exists()  # never a cut-off recording under the name asked for
    (part,) = out.parent.glob(f".{out.name}.*-*.part")  # the staging file, flushed up to frame 5
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # no footer: RrdReader warns and scans the whole file
        rec = Recording(part)
    assert rec.frames(rerun_log.ENTITY_DEPTH_IMAGE, "DepthImage:buffer") == list(range(6))
    opened = open_recording(save=out)  # the next run to that name removes the dead run's staging file
    assert not part.exists()
    opened.close()
    assert out.exists()


def test_open_recording_needs_a_sink(tmp_path):
    with pytest.raises(ValueError, match="at least one sink"):
        open_recording()
    with pytest.raises(ValueError, match=".rrd"):
        open_recording(save=tmp_path / "x.txt")


# ------------------------------------------------------------------------------------------
# Point clouds (pure)
# ------------------------------------------------------------------------------------------

K_SKEW = np.array([[400.0, 2.0, 30.5], [0.0, 410.0, 20.25], [0.0, 0.0, 1.0]])


def test_backprojection_against_a_hand_computed_point():
    depth = np.full((40, 60), np.nan, np.float32)
    depth[25, 50] = 0.08
    depth[3, 4] = -1.0  # invalid
    points, yx = backproject(depth, K_SKEW)
    assert yx.tolist() == [[25, 50]]
    # y_n = (25 - 20.25) / 410; x_n = (50 - 30.5 - 2 * y_n) / 400; X = Z * (x_n, y_n, 1)
    y_n = 4.75 / 410.0
    x_n = (19.5 - 2.0 * y_n) / 400.0
    np.testing.assert_allclose(points[0], [0.08 * x_n, 0.08 * y_n, 0.08], rtol=1e-6)
    # and projecting it with K gives the pixel back
    uvw = K_SKEW @ points[0].astype(np.float64)
    np.testing.assert_allclose(uvw[:2] / uvw[2], [50, 25], atol=1e-4)


def test_backproject_stride_box_and_exclusion():
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.05, 0.1, (30, 41)).astype(np.float32)
    _, yx = backproject(depth, K_SKEW, stride=4, box_xyxy=(5, 2, 30, 20), exclude_xyxy=(10, 0, 15, 9))
    expected = [(y, x) for y in range(0, 30, 4) for x in range(0, 41, 4)
                if 2 <= y < 20 and 5 <= x < 30 and not (0 <= y < 9 and 10 <= x < 15)]
    assert [tuple(p) for p in yx.tolist()] == expected


def test_decimated_depth_and_its_intrinsics():
    rng = np.random.default_rng(2)
    depth = rng.uniform(0.05, 0.1, (31, 47)).astype(np.float32)
    depth[0, 3] = np.nan
    depth[3, 3] = 7.0  # beyond uint16 at 10000 units/m -> invalid
    preview = depth_preview(depth, 3, 10000.0)
    assert preview.shape == (11, 16) and preview.dtype == np.uint16
    assert preview[0, 1] == 0 and preview[1, 1] == 0
    assert preview[2, 5] == round(float(depth[6, 15]) * 10000)
    # the decimated grid's K back-projects pixel (5, 2) to the same point as the full K does pixel (15, 6)
    full, _ = backproject(np.where(np.arange(47)[None, :] == 15, depth, np.nan)[6:7], K_SKEW)
    K3 = decimated_intrinsics(K_SKEW, 3)
    z = float(depth[6, 15])
    ray = np.linalg.solve(K3, [5.0, 2.0, 1.0])
    ray_full = np.linalg.solve(K_SKEW, [15.0, 6.0, 1.0])
    np.testing.assert_allclose(ray * z, ray_full * z, rtol=1e-12)
    assert full.shape == (1, 3)


def test_sample_colors_from_a_reduced_image():
    rgb = np.arange(5 * 8 * 3, dtype=np.uint8).reshape(5, 8, 3)  # a half-size copy of a 10x16 image
    yx = np.array([[0, 0], [9, 15], [4, 7]])
    np.testing.assert_array_equal(sample_colors(rgb, yx, (10, 16)), rgb[[0, 4, 2], [0, 7, 3]])
    assert sample_colors(None, yx, (10, 16)).tolist() == [[128, 128, 128]] * 3


def slow_voxel_downsample(points, colors, voxel):
    """open3d's definition, written out: voxel index floor((p - (min - voxel/2)) / voxel); mean per voxel."""
    origin = points.min(axis=0) - voxel / 2
    groups = defaultdict(list)
    for p, c in zip(points.astype(np.float64), colors.astype(np.float64) / 255.0):
        groups[tuple(np.floor((p - origin) / voxel).astype(int))].append((p, c))
    out_p = np.array([np.mean([g[0] for g in grp], axis=0) for grp in groups.values()])
    out_c = np.array([np.mean([g[1] for g in grp], axis=0) for grp in groups.values()])
    return out_p, out_c


def test_voxel_downsample_matches_the_literal_definition():
    rng = np.random.default_rng(3)
    points = rng.uniform(0, 0.01, (400, 3)).astype(np.float32)
    colors = rng.integers(0, 256, (400, 3), dtype=np.uint8)
    got_p, got_c = voxel_downsample(points, colors, 0.0025)
    want_p, want_c = slow_voxel_downsample(points, colors, 0.0025)
    assert got_p.shape == want_p.shape and got_p.shape[0] < 400
    order_got, order_want = np.lexsort(got_p.T), np.lexsort(want_p.T)
    np.testing.assert_allclose(got_p[order_got], want_p[order_want], atol=1e-7)
    np.testing.assert_allclose(got_c[order_got], np.rint(want_c[order_want] * 255), atol=1)


def test_cloud_full_density_near_the_patch_and_voxels_elsewhere():
    K = np.array([[300.0, 0, 50], [0, 300.0, 50], [0, 0, 1]])
    depth = np.full((101, 101), 0.1, np.float32)
    params = CloudParams(near_radius_px=10, near_stride_px=1, stride_px=2, voxel_m=0.001)
    cloud = depth_cloud(depth, K, center_xy=(50, 50), params=params)
    # near: every pixel of the 21x21 square, exactly back-projected
    near, _ = backproject(depth, K, box_xyxy=(40, 40, 61, 61))
    np.testing.assert_array_equal(cloud.near_points_m, near)
    assert cloud.near_points_m.shape[0] == 21 * 21
    # far: the stride-2 pixels outside the square (51 x 51 grid minus its 11 x 11 inside), merged into
    # 1 mm voxels; a pixel is 1/3 mm here, so a voxel holds 1.5 x 1.5 of them on average
    far, _ = backproject(depth, K, stride=2, exclude_xyxy=(40, 40, 61, 61))
    assert far.shape[0] == 51 * 51 - 11 * 11
    want, _ = slow_voxel_downsample(far, np.zeros_like(far, dtype=np.uint8), 0.001)
    assert cloud.far_points_m.shape == want.shape
    assert cloud.far_points_m.shape[0] < far.shape[0] / 2
    # point spacing: pixel footprint 0.1 / 300 m; far points are a voxel apart
    assert cloud.near_radius_m == pytest.approx(0.6 * 0.1 / 300)
    assert cloud.far_radius_m == pytest.approx(FAR_POINT_RADIUS * 0.001)
    # no patch: no near part
    assert depth_cloud(depth, K, params=params).near_points_m.shape == (0, 3)
    # every 4th pixel near the patch by default (points four times as large, still touching); stride 0: no far part
    thin = depth_cloud(depth, K, center_xy=(50, 50), params=CloudParams(stride_px=0))
    assert thin.far_points_m.shape == (0, 3) and thin.far_colors.shape == (0, 3)
    # (the default 40 px half-side, clipped, on the image's every-4th-pixel grid: X = (x - cx) Z / fx)
    ys, xs = np.mgrid[12:91:4, 12:91:4]
    want = np.stack([(xs - 50) * 0.1 / 300, (ys - 50) * 0.1 / 300, np.full(xs.shape, 0.1)], -1).reshape(-1, 3)
    np.testing.assert_allclose(thin.near_points_m, want, atol=1e-7)
    assert thin.near_radius_m == pytest.approx(4 * 0.6 * 0.1 / 300)


def test_patch_geometry_reproduces_the_patch_numbers(session_dir):
    session = open_session(session_dir)
    frame = session.load_frame(4, ("mask", "depth"))
    params = PatchParams()
    patch = compute_patch(frame.depth_m, frame.tool_mask, params)
    assert patch.found
    geometry = patch_geometry(frame.depth_m, session.calibration.K, patch, params)
    assert geometry.tool_points_m[:, 2].mean() == pytest.approx(patch.tool_depth_m, rel=1e-6)
    # the distance is the median over the window of (tissue depth - tool depth at each pixel's N1);
    # on this scene the tool is flat, so it is the median tissue z minus the tool depth
    assert np.median(geometry.tissue_points_m[:, 2]) - patch.tool_depth_m == pytest.approx(patch.distance_m, abs=1e-6)
    assert geometry.gap_vector_m[2] == pytest.approx(patch.distance_m)
    assert geometry.gap_origin_m[2] == pytest.approx(patch.tool_depth_m)
    # the gap starts on the ray through the patch centre
    uvw = session.calibration.K @ geometry.gap_origin_m
    np.testing.assert_allclose(uvw[:2] / uvw[2], patch.center_xy, atol=1e-9)
    # every tool point is an interior pixel, every tissue point a band pixel
    for pts, layer in ((geometry.tool_points_m, LAYER_INTERIOR), (geometry.tissue_points_m, LAYER_BAND)):
        uvw = (session.calibration.K @ pts.T.astype(np.float64))
        u, v = np.rint(uvw[:2] / uvw[2]).astype(int)
        assert (patch.layer_ids[v, u] == layer).all()
    empty = compute_patch(frame.depth_m, np.zeros_like(frame.tool_mask), params)
    assert patch_geometry(frame.depth_m, session.calibration.K, empty, params) is None


# ------------------------------------------------------------------------------------------
# Styles
# ------------------------------------------------------------------------------------------


def test_styles_cover_every_class_series_and_diagnostic():
    # one style per layer class of the patch, in class order
    assert [s.class_id for s in LAYER_STYLES] == sorted({LAYER_BACKGROUND, LAYER_INTERIOR, LAYER_TOOL_EDGE,
                                                          LAYER_RING, LAYER_BAND})
    assert layer_style(LAYER_BAND).name == "exterior band"
    assert len({s.rgba for s in LAYER_STYLES}) == len(LAYER_STYLES)
    assert set(DIAGNOSTIC_STYLES) == set(DIAGNOSTIC_CODES) | set(SESSION_DIAGNOSTIC_CODES)
    assert {"distance_mm", "signal", "force_n", "contact_truth", "posterior", "threshold", "predicted"} <= set(
        SERIES_STYLES)
    with pytest.raises(KeyError):
        layer_style(9)


# ------------------------------------------------------------------------------------------
# The video streams, decoded back
# ------------------------------------------------------------------------------------------


def decode_logged_video(rec: Recording, entity: str) -> dict[int, np.ndarray]:
    """Decode the VideoStream samples of ``entity`` in frame order with PyAV: frame -> RGB (BT.601 limited)."""
    import av

    from test_video import bt601_i420_to_rgb

    codec = rec.static[(entity, "VideoStream:codec")].as_py()[0]
    decoder = av.CodecContext.create({rr.VideoCodec.AV1.value: "libdav1d", rr.VideoCodec.H264.value: "h264"}[codec],
                                     "r")
    samples = sorted(rec.rows[(entity, "VideoStream:sample")], key=lambda r: r[0])
    frames = []
    for _, value in samples:
        frames += decoder.decode(av.Packet(value.values[0].values.to_numpy(zero_copy_only=False).tobytes()))
    frames += decoder.decode(None)
    assert len(frames) == len(samples)  # one frame per sample, in order
    return {f: bt601_i420_to_rgb(d.to_ndarray()) for (f, _), d in zip(samples, frames)}


@pytest.mark.parametrize("codec", ["av1", "h264"])
def test_logged_video_decodes_back_to_the_synthetic_session_images(tmp_path, codec):
    from contact_viz.synth import SynthParams, generate_session
    from contact_viz.viz.video import VideoParams, psnr_db

    root = tmp_path / "synth"
    generate_session(root, SynthParams(phantom="cup", frames=14, seed=3, width=320, height=180, fps=10))
    # right_step=1: both streams at the session's size (the half-size right stream: test_right_video_at_half_size)
    options = DebuggerOptions(video=VideoParams(codec=codec, keyframe_interval_s=0.5), right_step=1)
    session, summary, rec = run(root, tmp_path / "video.rrd", options)
    keyframes = rec.values(rerun_log.ENTITY_LEFT_IMAGE, "VideoStream:is_keyframe")
    assert sorted(f for f, v in keyframes.items() if v.as_py()[0]) == [0, 5, 10]  # every 0.5 s at 10 frames/s
    import cv2

    for side, entity in (("left", rerun_log.ENTITY_LEFT_IMAGE), ("right", rerun_log.ENTITY_RIGHT_IMAGE)):
        decoded = decode_logged_video(rec, entity)
        assert sorted(decoded) == list(range(14))
        sources = [cv2.imread(str(session.image_path(side, i)))[:, :, ::-1] for i in range(14)]
        assert decoded[0].shape == sources[0].shape
        psnrs = [psnr_db(decoded[i], sources[i]) for i in range(14)]
        # at this tiny size a frame of fast motion costs a few dB; 1080p sessions: 41 dB and more on every frame
        # (benchmarks/bench_viewer.py prints it)
        assert np.median(psnrs) >= 38.0 and min(psnrs) >= 34.0, (side, psnrs)


def test_cli_images_options(session_dir, tmp_path):
    from typer.testing import CliRunner

    from contact_viz.cli import app

    runner = CliRunner()
    bad = runner.invoke(app, ["view", str(session_dir), "--images", "gif", "--save", str(tmp_path / "x.rrd")])
    assert bad.exit_code == 2 and "--images" in bad.output and "video, jpeg, raw" in bad.output
    assert not (tmp_path / "x.rrd").exists()
    bad = runner.invoke(app, ["view", str(session_dir), "--video-codec", "vp9", "--save", str(tmp_path / "x.rrd")])
    assert bad.exit_code == 2 and "--video-codec" in bad.output
    out = tmp_path / "h264.rrd"
    ok = runner.invoke(app, ["view", str(session_dir), "--video-codec", "h264", "--end", "3", "--save", str(out)])
    assert ok.exit_code == 0, ok.output
    rec = Recording(out)
    assert rec.static[(rerun_log.ENTITY_LEFT_IMAGE, "VideoStream:codec")].as_py() == [rr.VideoCodec.H264.value]
    assert rec.frames(rerun_log.ENTITY_LEFT_IMAGE, "VideoStream:sample") == [0, 1, 2]
    out = tmp_path / "jpeg.rrd"
    ok = runner.invoke(app, ["view", str(session_dir), "--images", "jpeg", "--end", "2", "--save", str(out)])
    assert ok.exit_code == 0, ok.output
    assert Recording(out).frames(rerun_log.ENTITY_LEFT_IMAGE, "EncodedImage:blob") == [0, 1]


def test_right_video_at_half_size(default_run, session_dir):
    import cv2

    from contact_viz.viz.video import psnr_db

    session, _, rec = default_run
    decoded = decode_logged_video(rec, rerun_log.ENTITY_RIGHT_IMAGE)
    assert sorted(decoded) == list(range(N_FRAMES))
    for index, rgb in decoded.items():
        half = cv2.imread(str(session.image_path("right", index)), cv2.IMREAD_REDUCED_COLOR_2)[:, :, ::-1]
        assert rgb.shape == half.shape == (H // 2, W // 2, 3)
        # 160x90 px of random 2 px colour blocks is the worst case of 4:2:0 video (1080p: benchmarks/bench_viewer.py)
        assert psnr_db(rgb, half) >= 28.0


def test_view_with_no_readable_frame_fails_and_leaves_no_recording(session_dir, tmp_path):
    """Every mask unreadable (a per-frame fault on every frame): one error line, exit 2, no .rrd."""
    broken = tmp_path / "sess"
    shutil.copytree(session_dir, broken)
    for mask in (broken / "masks").iterdir():
        mask.write_bytes(b"not a png")
    out = tmp_path / "out.rrd"
    proc = subprocess.run([sys.executable, "-m", "contact_viz.cli", "view", str(broken), "--save", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == f"error: {broken}: no frame could be read (see the warnings above); no recording written"
    assert not out.exists()


@pytest.mark.parametrize("image_format", ["jpg", "png"])
def test_viewer_flags_what_check_flags_and_shows_the_evidence_at_the_image_size(image_format, tmp_path):
    """The viewer and `contact-viz check` run the checks on the same pixels, here at half resolution
    (analysis width 160 px on 320 px images; JPEG files decode to it, PNG images are decoded and
    shrunk), so they flag the same frames; on frames where a check with evidence fired the recording
    holds the residual picture at the image's size and the mask contour on the image's pixels."""
    import cv2

    from contact_viz.checks.params import DiagnosticParams
    from contact_viz.pipeline.check import check_session
    from contact_viz.synth import SynthParams, generate_session
    from contact_viz.synth.faults import inject_fault

    clean = generate_session(tmp_path / "clean", SynthParams(phantom="cup", frames=24, seed=3, width=320, height=180))
    broken = tmp_path / "broken"
    inject_fault(clean, broken, "mask_drift", range(8, 14), severity=8)
    if image_format == "png":
        for side in ("left", "right"):
            for jpg in (broken / side).glob("*.jpg"):
                cv2.imwrite(str(jpg.with_suffix(".png")), cv2.imread(str(jpg)))
                jpg.unlink()
    params = DiagnosticParams(analysis_width_px=160)
    report = check_session(broken, params=params)
    session, summary, rec = run(broken, tmp_path / "view.rrd", DebuggerOptions(diagnostics=params, points=False))
    assert summary.diagnostic_ranges == report.fired
    evidence_frames = sorted({f for code in rerun_log.EVIDENCE_CHECKS for a, b in report.fired.get(code, [])
                              for f in range(a, b + 1)})
    assert set(range(9, 14)) <= set(evidence_frames)  # the drifted mask is caught
    blobs = rec.values(rerun_log.ENTITY_EVIDENCE_RESIDUAL, "EncodedImage:blob")
    assert sorted(blobs) == list(range(24))  # every frame: the picture where a check fired, else an empty image
    empty = {f for f, blob in blobs.items() if image_buffer(blob, (-1,), np.uint8).tobytes() == rerun_log.EMPTY_PNG}
    assert sorted(set(range(24)) - empty) == evidence_frames
    picture = cv2.imdecode(image_buffer(blobs[evidence_frames[0]], (-1,), np.uint8), cv2.IMREAD_COLOR)
    assert picture.shape == (180, 320, 3)
    contour = rec.values(rerun_log.ENTITY_EVIDENCE_CONTOUR, "Points2D:positions")[evidence_frames[0]]
    xy = np.asarray(contour.values.flatten().to_numpy(zero_copy_only=False)).reshape(-1, 2)
    assert len(xy) > 10 and np.all((xy - 0.5) % 2 == 0)  # every 2nd pixel, drawn at pixel centres
