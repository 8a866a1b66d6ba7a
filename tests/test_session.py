"""Tests for contact_viz.io.session: tiny synthetic sessions written to tmp_path."""

from __future__ import annotations

import json
import math
import os
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from contact_viz.errors import SessionError
from contact_viz.params import LabelParams
from contact_viz.geometry.stereo import SGBMParams
from contact_viz.io.session_files import nearest_indices
from contact_viz.io.session import (
    BadFrame,
    Frame,
    SessionWarning,
    missing_inputs,
    natural_key,
    open_session,
    read_depth_m,
    read_tool_mask,
)

H, W = 24, 32  # synthetic image size, px
K_ROWS = [[300.0, 0.0, 16.5], [0.0, 310.0, 12.25], [0.0, 0.0, 1.0]]  # synthetic K, px
BASELINE_M = 0.0045  # synthetic stereo baseline, m
PALETTE = [0, 0, 0, 255, 0, 0, 0, 255, 0] + [0] * (256 * 3 - 9)  # DAVIS-like: id 1 red, id 2 green


def id_map() -> np.ndarray:
    """(H, W) uint8 object ids: 1 in one rectangle, 2 in another, 0 elsewhere."""
    ids = np.zeros((H, W), np.uint8)
    ids[2:9, 3:11] = 1
    ids[12:21, 15:26] = 2
    return ids


def write_palette_png(path: Path, ids: np.ndarray) -> None:
    image = Image.fromarray(ids)  # mode L
    image.putpalette(PALETTE)  # L + palette -> mode P, pixel values kept as indices
    assert image.mode == "P"
    image.save(path)


def make_session(root: Path, stems=("10", "1", "2"), *, seed: int = 0, right: bool = True, json_data=None) -> dict:
    """Write a valid session with palettized masks and float32 npy depth; return what was written."""
    rng = np.random.default_rng(seed)
    for sub in ("left", "right", "masks", "depth") if right else ("left", "masks", "depth"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    (root / "K.txt").write_text(" ".join(f"{v:g}" for row in K_ROWS for v in row) + f"\n{BASELINE_M}\n")
    if json_data is not None:
        (root / "session.json").write_text(json.dumps(json_data))
    written = {}
    for stem in stems:
        left = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        Image.fromarray(left).save(root / "left" / f"{stem}.png")  # PIL writes RGB order
        right_img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        if right:
            Image.fromarray(right_img).save(root / "right" / f"{stem}.png")
        write_palette_png(root / "masks" / f"{stem}.png", id_map())
        depth = rng.uniform(0.05, 0.2, (H, W)).astype(np.float32)
        np.save(root / "depth" / f"{stem}.npy", depth)
        written[stem] = {"left": left, "right": right_img, "depth": depth}
    return written


def listing(root: Path) -> dict[str, tuple[int, int]]:
    """Every file and directory under root: relative path -> (size, mtime_ns)."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            path = Path(dirpath) / name
            st = path.stat()
            out[str(path.relative_to(root))] = (st.st_size if path.is_file() else 0, st.st_mtime_ns)
    return out


def write_csv(path: Path, text: str) -> None:
    path.write_text(text.strip() + "\n")


# ------------------------------------------------------------------------------------------
# Happy path
# ------------------------------------------------------------------------------------------


def test_open_session_basic_metadata(tmp_path):
    root = tmp_path / "sess_a"
    make_session(root, json_data={"phantom": "liver", "task": "palpation", "fps": 10})
    s = open_session(root)
    assert s.stems == ["1", "2", "10"]
    assert len(s) == 3
    assert s.name == "sess_a" and s.phantom == "liver" and s.task == "palpation"
    assert s.fps == 10.0
    np.testing.assert_array_equal(s.calibration.K, np.array(K_ROWS))
    assert s.calibration.K.dtype == np.float64
    assert (s.calibration.fx, s.calibration.fy, s.calibration.cx, s.calibration.cy) == (300.0, 310.0, 16.5, 12.25)
    assert s.calibration.baseline_m == BASELINE_M
    assert s.image_size == (H, W)
    np.testing.assert_allclose(s.timestamps_s, [0.0, 0.1, 0.2])
    assert s.has_right
    # No force.csv: force unknown, labels unknown.
    assert np.isnan(s.force_xyz_n).all() and s.force_xyz_n.shape == (3, 3)
    assert np.isnan(s.force_n).all()
    np.testing.assert_array_equal(s.labels, [-1, -1, -1])
    assert s.labels.dtype == np.int8
    assert list(s.label_source) == ["none"] * 3


def test_defaults_without_session_json(tmp_path):
    make_session(tmp_path / "plain")
    s = open_session(tmp_path / "plain")
    assert s.name == "plain" and s.phantom is None and s.task is None and s.fps == 30.0
    np.testing.assert_allclose(s.timestamps_s, np.arange(3) / 30.0)


def test_natural_key_order():
    stems = ["frame_10", "frame_000012", "frame_2", "b", "a", "10", "2", "1"]
    assert sorted(stems, key=natural_key) == ["1", "2", "10", "a", "b", "frame_2", "frame_10", "frame_000012"]


def test_frames_decoded(tmp_path):
    written = make_session(tmp_path / "s")
    s = open_session(tmp_path / "s")
    frames = list(s.iter_frames(layers=("mask", "depth", "left", "right")))
    assert [f.stem for f in frames] == ["1", "2", "10"]
    assert [f.index for f in frames] == [0, 1, 2]
    for f in frames:
        assert isinstance(f, Frame)
        assert f.tool_mask.dtype == bool and f.tool_mask.shape == (H, W)
        np.testing.assert_array_equal(f.tool_mask, id_map() != 0)
        assert f.depth_m.dtype == np.float32
        np.testing.assert_array_equal(f.depth_m, written[f.stem]["depth"])
        assert f.left_rgb.dtype == np.uint8
        np.testing.assert_array_equal(f.left_rgb, written[f.stem]["left"])  # RGB order, not BGR
        np.testing.assert_array_equal(f.right_rgb, written[f.stem]["right"])


def test_object_id_selects_one_palette_index(tmp_path):
    make_session(tmp_path / "s")
    s = open_session(tmp_path / "s", object_ids=(2,))
    frame = next(s.iter_frames(layers=("mask",)))
    np.testing.assert_array_equal(frame.tool_mask, id_map() == 2)
    assert frame.tool_mask.sum() == 9 * 11
    with pytest.raises(ValueError, match="object_ids"):
        open_session(tmp_path / "s", object_ids=(0,))


def test_mask_formats(tmp_path):
    ids = id_map()
    binary = tmp_path / "binary.png"
    Image.fromarray((ids != 0).astype(np.uint8) * 255).save(binary)
    with Image.open(binary) as image:
        assert image.mode == "L"
    np.testing.assert_array_equal(read_tool_mask(binary), ids != 0)
    rgb = tmp_path / "rgb.png"
    colours = np.zeros((H, W, 3), np.uint8)
    colours[ids == 1] = (0, 0, 128)  # nonzero only in the blue channel
    colours[ids == 2] = (200, 0, 0)
    Image.fromarray(colours).save(rgb)
    np.testing.assert_array_equal(read_tool_mask(rgb), ids != 0)
    with pytest.raises(SessionError, match="rgb.png.*object-id"):
        read_tool_mask(rgb, object_ids=(1,))
    pal = tmp_path / "pal.png"
    write_palette_png(pal, ids)
    np.testing.assert_array_equal(read_tool_mask(pal, object_ids=(1,)), ids == 1)


@pytest.mark.parametrize("dtype", [np.float32, np.float64, ">f4"])
def test_depth_npy_read_as_stored_and_read_only(tmp_path, dtype):
    """Values (invalid ones included) come back as float32 exactly as stored; the array is
    read-only, and reading it leaves the file unchanged."""
    depth = np.full((2, 4), 0.1, np.float64)
    depth[0, :] = [0.0, np.nan, np.inf, -0.5]
    depth[1, :] = [0.125, 0.25, -np.inf, 1.5]
    path = tmp_path / "d.npy"
    np.save(path, depth.astype(dtype))
    before = path.read_bytes()
    out = read_depth_m(path)
    assert out.dtype == np.float32 and out.shape == (2, 4) and type(out) is np.ndarray
    np.testing.assert_array_equal(out, depth.astype(np.float32))  # NaN positions must match too
    with pytest.raises(ValueError):
        out[0, 0] = 1.0
    del out
    assert path.read_bytes() == before


def test_depth_png_millimetres_to_metres(tmp_path):
    mm = np.array([[0, 1000, 1234], [65535, 5, 0]], np.uint16)
    path = tmp_path / "d.png"
    cv2.imwrite(str(path), mm)
    out = read_depth_m(path)
    assert out.dtype == np.float32
    expected = np.array([[0.0, 1.0, 1.234], [65.535, 0.005, 0.0]], np.float32)  # 0 = invalid, kept
    np.testing.assert_allclose(out, expected, rtol=1e-7)
    assert not out.flags.writeable


def test_depth_png_in_session(tmp_path):
    root = tmp_path / "s"
    make_session(root)
    os.remove(root / "depth" / "2.npy")
    mm = np.full((H, W), 150, np.uint16)
    mm[0, 0] = 0
    cv2.imwrite(str(root / "depth" / "2.png"), mm)
    s = open_session(root)
    frame = s.load_frame(1, layers=("depth",))
    assert isinstance(frame, Frame)
    assert frame.depth_m[0, 0] == 0.0  # invalid, as stored
    assert frame.depth_m[1, 1] == np.float32(0.15)


def test_load_depth_rows_equals_the_whole_map_cut(tmp_path):
    root = tmp_path / "s"
    written = make_session(root)
    os.remove(root / "depth" / "2.npy")
    mm = np.arange(H * W, dtype=np.uint16).reshape(H, W)
    cv2.imwrite(str(root / "depth" / "2.png"), mm)  # a PNG frame: decoded whole, then cut
    np.save(root / "depth" / "10.npy", written["10"]["depth"].astype(">f8"))  # big-endian float64
    s = open_session(root)
    for index in range(len(s)):
        whole = s.load_frame(index, layers=("depth",)).depth_m
        for row0, row1 in [(0, H), (3, 9), (0, 0), (H - 1, H)]:
            rows = s.load_depth_rows(index, row0, row1)
            assert rows.dtype == np.float32 and rows.shape == (row1 - row0, W) and not rows.flags.writeable
            np.testing.assert_array_equal(rows, whole[row0:row1])
    with pytest.raises(ValueError, match="out of range"):
        s.load_depth_rows(0, 5, H + 1)
    with pytest.raises(IndexError):
        s.load_depth_rows(3, 0, 1)


def test_load_depth_rows_bad_files_are_bad_frames(tmp_path):
    root = tmp_path / "s"
    make_session(root)
    np.save(root / "depth" / "1.npy", np.zeros((H + 1, W), np.float32))  # wrong shape
    np.save(root / "depth" / "2.npy", np.zeros((H, W), np.int32))  # wrong dtype
    data = (root / "depth" / "10.npy").read_bytes()
    (root / "depth" / "10.npy").write_bytes(data[:-100])  # truncated
    s = open_session(root)
    expected = {0: f"{H + 1}x{W}", 1: "int32", 2: "truncated"}
    for index, message in expected.items():
        bad = s.load_depth_rows(index, 2, 5)
        assert isinstance(bad, BadFrame), index
        assert str(root / "depth" / f"{s.stems[index]}.npy") in bad.reason and message in bad.reason
    # The same problems, found by the whole-frame reader too.
    for index in expected:
        assert isinstance(s.load_frame(index, layers=("depth",)), BadFrame)
    # A map shorter than the rows asked for: still the shape, not the rows, is what is wrong.
    np.save(root / "depth" / "1.npy", np.zeros((3, W), np.float32))
    bad = open_session(root).load_depth_rows(0, 2, H)
    assert isinstance(bad, BadFrame) and f"expected a depth map of {H}x{W} px" in bad.reason and f"found 3x{W}" in bad.reason
    os.remove(root / "depth" / "1.npy")
    bad = open_session(root).load_depth_rows(0, 0, 3)
    assert isinstance(bad, BadFrame) and "missing" in bad.reason


def test_force_by_frame_and_labels(tmp_path):
    root = tmp_path / "s"
    make_session(root, stems=("1", "2", "10", "11"))
    # "001" and "0010" are the same frames as stems "1" and "10" written with zero padding.
    write_csv(root / "force.csv", "frame,fx,fy,fz\n001,0.6,0,0.8\n2,1.2,1.6,0\n0010,0,0,-3\n99,5,5,5")
    with pytest.warns(SessionWarning, match="99"):
        s = open_session(root, label_params=LabelParams(contact_force_n=2.0))
    np.testing.assert_array_equal(s.force_xyz_n[:3], [[0.6, 0, 0.8], [1.2, 1.6, 0], [0, 0, -3]])
    assert np.isnan(s.force_xyz_n[3]).all()
    expected_n = [math.sqrt(0.6**2 + 0.8**2), math.sqrt(1.2**2 + 1.6**2), 3.0, math.nan]
    np.testing.assert_allclose(s.force_n, expected_n, equal_nan=True)
    # 1.0 N < 2 N; 2.0 N >= 2 N (boundary counts as contact); 3 N; unknown.
    np.testing.assert_array_equal(s.labels, [0, 1, 1, -1])
    assert list(s.label_source) == ["force", "force", "force", "none"]

    write_csv(root / "labels.csv", "frame,contact\n2,0\n11,1")
    write_csv(root / "force.csv", "frame,fx,fy,fz\n001,0.6,0,0.8\n2,1.2,1.6,0\n0010,0,0,-3")
    s2 = open_session(root, label_params=LabelParams(contact_force_n=2.0))
    np.testing.assert_array_equal(s2.labels, [0, 0, 1, 1])
    assert list(s2.label_source) == ["force", "manual", "force", "manual"]
    s3 = open_session(root, label_params=LabelParams(contact_force_n=0.5))
    np.testing.assert_array_equal(s3.labels, [1, 0, 1, 1])


def test_force_by_timestamp_nearest(tmp_path):
    root = tmp_path / "s"
    make_session(root, stems=("1", "2", "10", "11"))
    write_csv(root / "frames.csv", "frame,timestamp\n1,0.0\n2,0.1\n10,0.26\n11,5.0")
    # Samples written out of time order; the reader must sort them.
    write_csv(
        root / "force.csv",
        "timestamp,fx,fy,fz\n0.13,0,0,3\n0.02,0,0,1\n0.3,0,0,5\n0.09,0,0,2\n0.2,0,0,4",
    )
    s = open_session(root)
    np.testing.assert_array_equal(s.timestamps_s, [0.0, 0.1, 0.26, 5.0])
    # By hand: 0.0 -> 0.02 (fz 1); 0.1 -> 0.09 (0.01 away, vs 0.13 at 0.03) (fz 2);
    # 0.26 -> 0.3 (0.04, vs 0.2 at 0.06) (fz 5); 5.0 is far past the last sample -> unknown.
    np.testing.assert_array_equal(s.force_xyz_n[:3, 2], [1.0, 2.0, 5.0])
    assert np.isnan(s.force_xyz_n[3]).all()
    np.testing.assert_array_equal(s.labels, [0, 1, 1, -1])


def test_nearest_indices_ties_and_edges():
    samples = np.array([0.0, 1.0, 2.0, 4.0])
    queries = np.array([-3.0, 0.5, 0.75, 2.9, 3.0, 3.1, 10.0])
    # Slow literal reference: argmin of |difference|, first index on ties.
    expected = [int(np.argmin(np.abs(samples - q))) for q in queries]
    assert expected == [0, 0, 1, 2, 2, 3, 3]
    np.testing.assert_array_equal(nearest_indices(samples, queries), expected)


def test_only_requested_layers(tmp_path, monkeypatch):
    make_session(tmp_path / "s")
    s = open_session(tmp_path / "s")
    import contact_viz.io.session as session_module

    calls = []
    real = session_module.read_rgb
    monkeypatch.setattr(session_module, "read_rgb", lambda p: calls.append(Path(p).parent.name) or real(p))
    frame = next(s.iter_frames(indices=[0]))  # default layers: mask + depth
    assert frame.tool_mask is not None and frame.depth_m is not None
    assert frame.left_rgb is None and frame.right_rgb is None
    assert calls == []  # the left/right images were never decoded
    frame = next(s.iter_frames(layers=("left",), indices=[0]))
    assert frame.left_rgb is not None
    assert frame.tool_mask is None and frame.depth_m is None and frame.right_rgb is None
    assert calls == ["left"]
    with pytest.raises(ValueError, match="layers"):
        s.iter_frames(layers=("mask", "normals"))


def test_no_right_dir(tmp_path):
    make_session(tmp_path / "s", right=False)
    s = open_session(tmp_path / "s")
    assert not s.has_right
    frame = next(s.iter_frames(layers=("right", "mask")))
    assert isinstance(frame, Frame) and frame.right_rgb is None and frame.tool_mask is not None


def test_indices_order_and_workers(tmp_path):
    make_session(tmp_path / "s", stems=[str(i) for i in range(6)])
    s = open_session(tmp_path / "s")
    got = [f.stem for f in s.iter_frames(indices=[5, 0, 3, 3], prefetch=2, workers=2)]
    assert got == ["5", "0", "3", "3"]
    with pytest.raises(IndexError):
        s.iter_frames(indices=[6])


# ------------------------------------------------------------------------------------------
# Session-wide errors
# ------------------------------------------------------------------------------------------


def _k_text(line1: str, line2: str = str(BASELINE_M)) -> str:
    return f"{line1}\n{line2}\n"


K9 = "300 0 16.5 0 310 12.25 0 0 1"

ERROR_CASES = {
    "no_left_dir": (lambda r: _rmtree(r / "left"), ["left", "rectified left frames"]),
    "empty_left": (lambda r: [p.unlink() for p in (r / "left").iterdir()], ["left", "found none"]),
    "missing_k": (lambda r: (r / "K.txt").unlink(), ["K.txt", "9 numbers", "baseline"]),
    "k_8_numbers": (lambda r: (r / "K.txt").write_text(_k_text("300 0 16.5 0 310 12.25 0 0")), ["K.txt", "expected 9 numbers on line 1, found 8"]),
    "k_text": (lambda r: (r / "K.txt").write_text(_k_text("300 0 16.5 0 310 x 0 0 1")), ["K.txt", "expected 9 numbers on line 1", "x"]),
    "k_not_camera": (lambda r: (r / "K.txt").write_text(_k_text("300 0 16.5 0 310 12.25 0 0 2")), ["K.txt", "0 0 1"]),
    "baseline_negative": (lambda r: (r / "K.txt").write_text(_k_text(K9, "-0.004")), ["K.txt", "one positive number", "line 2", "-0.004"]),
    "baseline_two": (lambda r: (r / "K.txt").write_text(_k_text(K9, "0.004 0.005")), ["K.txt", "line 2", "found 2 numbers"]),
    "baseline_missing": (lambda r: (r / "K.txt").write_text(K9 + "\n"), ["K.txt", "expected 2 lines", "found 1"]),
    "json_invalid": (lambda r: (r / "session.json").write_text("{name: oops"), ["session.json", "valid JSON"]),
    "json_fps_zero": (lambda r: (r / "session.json").write_text('{"fps": 0}'), ["session.json", "fps", "positive"]),
    "json_fps_text": (lambda r: (r / "session.json").write_text('{"fps": "30"}'), ["session.json", "fps", "positive"]),
    "no_masks": (lambda r: _rmtree(r / "masks"), ["masks", "masks/<stem>.png", "SAM2"]),
    # Without depth/ a session with right/ falls back to SGBM (tested below); without right/ too, nothing is left.
    "no_depth": (
        lambda r: (_rmtree(r / "depth"), _rmtree(r / "right")),
        ["depth", "FoundationStereo", "depth_meter.npy", "depth/<stem>.npy", "uint16", "disparity/<stem>.npy",
         "right/", "SGBM", "recommended"],
    ),
    "force_missing_fz": (
        lambda r: write_csv(r / "force.csv", "frame,fx,fy,force_z\n1,0,0,0"),
        ["force.csv", "missing fz", "found columns", "force_z"],
    ),
    "force_no_index": (
        lambda r: write_csv(r / "force.csv", "t,fx,fy,fz\n1,0,0,0"),
        ["force.csv", "missing frame or timestamp", "'t'"],
    ),
    "force_non_numeric": (
        lambda r: write_csv(r / "force.csv", "frame,fx,fy,fz\n1,0,0,0\n2,0,abc,0"),
        ["force.csv", "line 3", "number", "'fy'", "abc"],
    ),
    "force_timestamp_no_frames_csv": (
        lambda r: write_csv(r / "force.csv", "timestamp,fx,fy,fz\n0.0,0,0,1"),
        ["frames.csv", "missing", "timestamp"],
    ),
    "frames_csv_missing_column": (
        lambda r: write_csv(r / "frames.csv", "frame,time\n1,0\n2,1\n10,2"),
        ["frames.csv", "missing timestamp", "found columns"],
    ),
    "frames_csv_missing_stem": (
        lambda r: write_csv(r / "frames.csv", "frame,timestamp\n1,0\n2,1"),
        ["frames.csv", "every frame", "10"],
    ),
    "frames_csv_bad_number": (
        lambda r: write_csv(r / "frames.csv", "frame,timestamp\n1,0\n2,soon\n10,2"),
        ["frames.csv", "line 3", "soon"],
    ),
    "labels_bad_contact": (
        lambda r: write_csv(r / "labels.csv", "frame,contact\n1,0\n2,2"),
        ["labels.csv", "line 3", "contact 0 or 1", "'2'"],
    ),
    "labels_missing_column": (
        lambda r: write_csv(r / "labels.csv", "frame,label\n1,0"),
        ["labels.csv", "missing contact", "found columns"],
    ),
    "labels_duplicate": (
        lambda r: write_csv(r / "labels.csv", "frame,contact\n1,0\n01,1"),
        ["labels.csv", "one row per frame"],
    ),
    "duplicate_left_stem": (
        lambda r: Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(r / "left" / "2.jpg"),
        ["left", "2.png", "2.jpg", "one file per frame"],
    ),
    "first_left_corrupt": (
        lambda r: (r / "left" / "1.png").write_bytes(b"not an image"),
        ["1.png", "left image"],
    ),
}


def _rmtree(path: Path) -> None:
    for child in path.iterdir():
        child.unlink()
    path.rmdir()


@pytest.mark.parametrize("case", sorted(ERROR_CASES))
def test_session_errors(tmp_path, case):
    root = tmp_path / "s"
    make_session(root)
    mutate, expected = ERROR_CASES[case]
    mutate(root)
    with pytest.raises(SessionError) as info:
        open_session(root)
    message = str(info.value)
    for part in expected:
        assert part in message, f"{part!r} not in {message!r}"


def test_missing_or_file_session_path(tmp_path):
    with pytest.raises(SessionError, match="nowhere.*missing.*session directory"):
        open_session(tmp_path / "nowhere")
    (tmp_path / "afile").write_text("x")
    with pytest.raises(SessionError, match="afile.*session directory.*found a file"):
        open_session(tmp_path / "afile")


def test_unknown_stems_in_csv_only_warn(tmp_path):
    root = tmp_path / "s"
    make_session(root)
    write_csv(root / "frames.csv", "frame,timestamp\n1,0\n2,0.5\n10,1.5\n77,9")
    write_csv(root / "labels.csv", "frame,contact\n2,1\n88,0")
    with pytest.warns(SessionWarning) as record:
        s = open_session(root)
    messages = " ".join(str(w.message) for w in record)
    assert "frames.csv" in messages and "77" in messages and "labels.csv" in messages and "88" in messages
    np.testing.assert_array_equal(s.timestamps_s, [0.0, 0.5, 1.5])
    np.testing.assert_array_equal(s.labels, [-1, 1, -1])


# ------------------------------------------------------------------------------------------
# Per-frame problems
# ------------------------------------------------------------------------------------------


def test_bad_frames_are_yielded_and_iteration_continues(tmp_path):
    root = tmp_path / "s"
    make_session(root, stems=[str(i) for i in range(7)])
    (root / "depth" / "1.npy").unlink()
    (root / "masks" / "2.png").write_bytes(os.urandom(200))  # garbage bytes
    np.save(root / "depth" / "3.npy", np.ones((H - 1, W), np.float32))
    (root / "depth" / "4.npy").unlink()
    cv2.imwrite(str(root / "depth" / "4.png"), np.full((H, W), 100, np.uint8))  # 8-bit depth PNG
    np.save(root / "depth" / "5.npy", np.ones((H, W), np.int32))  # integer depth
    s = open_session(root)
    out = list(s.iter_frames(prefetch=2))
    assert [type(f).__name__ for f in out] == ["Frame", "BadFrame", "BadFrame", "BadFrame", "BadFrame", "BadFrame", "Frame"]
    assert [f.stem for f in out] == [str(i) for i in range(7)]
    reasons = {f.stem: f.reason for f in out if isinstance(f, BadFrame)}
    assert "1.npy" in reasons["1"] and "missing" in reasons["1"] and "depth" in reasons["1"]
    assert "masks" in reasons["2"] and "2.png" in reasons["2"] and "tool mask" in reasons["2"]
    assert "3.npy" in reasons["3"] and "24x32" in reasons["3"] and "found 23x32" in reasons["3"]
    assert "4.png" in reasons["4"] and "16-bit single-channel" in reasons["4"] and "8-bit" in reasons["4"]
    assert "5.npy" in reasons["5"] and "float32" in reasons["5"] and "int32" in reasons["5"]
    bad = out[1]
    assert bad.index == 1 and bad.timestamp_s == pytest.approx(1 / 30) and isinstance(bad.error, SessionError)
    # The mask-only pass does not touch depth, so frame 1 is fine there.
    assert isinstance(s.load_frame(1, layers=("mask",)), Frame)


def test_bad_left_and_mask_shapes(tmp_path):
    root = tmp_path / "s"
    make_session(root, stems=("1", "2", "3"))
    (root / "left" / "2.png").write_bytes(b"")  # empty left image
    write_palette_png(root / "masks" / "3.png", np.zeros((H, W + 1), np.uint8))
    s = open_session(root)
    out = list(s.iter_frames(layers=("left", "mask")))
    assert isinstance(out[0], Frame)
    assert isinstance(out[1], BadFrame) and "2.png" in out[1].reason and "empty file" in out[1].reason
    assert isinstance(out[2], BadFrame) and "3.png" in out[2].reason and "tool mask of 24x32" in out[2].reason


def test_session_directory_unchanged(tmp_path):
    root = tmp_path / "s"
    make_session(root)
    write_csv(root / "frames.csv", "frame,timestamp\n1,0\n2,0.5\n10,1.5")
    write_csv(root / "force.csv", "timestamp,fx,fy,fz\n0,0,0,1\n1,0,0,3")
    write_csv(root / "labels.csv", "frame,contact\n2,1")
    (root / "masks" / "2.png").write_bytes(b"junk")
    before = listing(root)
    time.sleep(0.01)
    s = open_session(root)
    frames = list(s.iter_frames(layers=("mask", "depth", "left", "right")))
    assert any(isinstance(f, BadFrame) for f in frames)
    assert listing(root) == before
    assert sorted(os.listdir(tmp_path)) == ["s"]


def _decode_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("contact-viz-decode")]


def test_early_break_does_not_hang(tmp_path):
    make_session(tmp_path / "s", stems=[str(i) for i in range(12)])
    s = open_session(tmp_path / "s")
    done = threading.Event()

    def consume():
        for frame in s.iter_frames(layers=("mask", "depth", "left"), prefetch=3, workers=2):
            assert isinstance(frame, Frame)
            break
        gen = s.iter_frames(prefetch=2)
        next(gen)
        gen.close()
        done.set()

    consumer = threading.Thread(target=consume)
    consumer.start()
    consumer.join(timeout=10)
    assert done.is_set(), "iteration did not stop after an early break"
    assert _decode_threads() == []
    # An unstarted generator creates no threads at all.
    unstarted = s.iter_frames()
    assert _decode_threads() == []
    del unstarted


def test_empty_indices(tmp_path):
    make_session(tmp_path / "s")
    s = open_session(tmp_path / "s")
    assert list(s.iter_frames(indices=[])) == []


def test_jpeg_left_is_rgb(tmp_path):
    root = tmp_path / "s"
    make_session(root)
    (root / "left" / "2.png").unlink()
    colour = (10, 200, 60)  # distinct R, G, B so a BGR/RGB swap would show
    Image.fromarray(np.full((H, W, 3), colour, np.uint8)).save(root / "left" / "2.jpg", quality=95)
    s = open_session(root)
    frame = s.load_frame(1, layers=("left",))
    assert isinstance(frame, Frame) and frame.left_rgb.shape == (H, W, 3)
    np.testing.assert_allclose(frame.left_rgb.reshape(-1, 3).mean(axis=0), colour, atol=3)


# ------------------------------------------------------------------------------------------
# Depth sources: depth/, disparity/, SGBM; calibration that needs rectification
# ------------------------------------------------------------------------------------------

SH, SW = 40, 96  # size of the stereo sessions, px
SFX = 200.0  # their focal length, px
SBASE_M = 0.005  # their baseline, m


def make_stereo_session(root: Path, disparities=(6, 7, 8), *, masks: bool = True, seed: int = 0) -> None:
    """left/ + right/ of a textured fronto-parallel plane per frame (constant disparity), K.txt, masks/."""
    rng = np.random.default_rng(seed)
    for sub in ("left", "right") + (("masks",) if masks else ()):
        (root / sub).mkdir(parents=True, exist_ok=True)
    (root / "K.txt").write_text(f"{SFX} 0 {SW / 2} 0 {SFX} {SH / 2} 0 0 1\n{SBASE_M}\n")
    for i, d in enumerate(disparities):
        texture = rng.integers(0, 256, (SH, SW + d, 3), dtype=np.uint8)
        Image.fromarray(texture[:, :SW]).save(root / "left" / f"{i}.png")  # left x shows texture x
        Image.fromarray(texture[:, d:d + SW]).save(root / "right" / f"{i}.png")  # right x shows texture x + d
        if masks:
            Image.fromarray(np.zeros((SH, SW), np.uint8)).save(root / "masks" / f"{i}.png")


def test_sgbm_fallback_is_cached_outside_the_session(tmp_path, caplog):
    root = tmp_path / "s"
    make_stereo_session(root)
    cache = tmp_path / "cache"
    before = listing(root)
    with caplog.at_level("INFO", logger="contact_viz.io.session"):
        s = open_session(root, cache_dir=cache)
    assert s.depth_source == "sgbm" and "SGBM" in s.depth_note and "FoundationStereo" in s.depth_note
    assert s.depth_note in caplog.text
    # the search range from the calibration: fx 200 px x 5 mm / 15 mm = 66.7 px, capped at 96 / 4 = 24 -> 25 -> 32
    assert s.depth_config["source"] == "sgbm" and s.depth_config["sgbm"]["num_disparities"] == 32
    assert s.depth_cache_dir is not None and cache in s.depth_cache_dir.parents
    frames = list(s.iter_frames(layers=("mask", "depth", "left", "right"), workers=2, prefetch=3))
    assert all(isinstance(f, Frame) for f in frames)
    for frame, d in zip(frames, (6, 7, 8)):
        valid = np.isfinite(frame.depth_m)
        assert valid.mean() > 0.8  # the padding lets even the left border match
        np.testing.assert_allclose(np.median(frame.depth_m[valid]), SFX * SBASE_M / d, rtol=1e-6)
        assert np.mean(np.abs(frame.depth_m[valid] - SFX * SBASE_M / d) < 1e-4) > 0.95
    assert len(list(s.depth_cache_dir.glob("*.png"))) == 3
    assert listing(root) == before  # nothing written into the session
    # A second session object reads the cache; the depth is identical.
    again = open_session(root, cache_dir=cache)
    depth, origin = again.load_depth(0, with_origin=True)
    assert origin == "cached"
    np.testing.assert_array_equal(depth, frames[0].depth_m)
    # Other SGBM parameters are another cache entry.
    other = open_session(root, cache_dir=cache, sgbm_params=SGBMParams(block_size=5))
    assert other.depth_cache_dir != s.depth_cache_dir
    assert other.load_depth(0, with_origin=True)[1] == "computed"


def test_sgbm_frame_without_right_image_is_a_bad_frame(tmp_path):
    root = tmp_path / "s"
    make_stereo_session(root)
    (root / "right" / "1.png").unlink()
    s = open_session(root, cache_dir=tmp_path / "cache")
    out = list(s.iter_frames())
    assert [type(f).__name__ for f in out] == ["Frame", "BadFrame", "Frame"]
    assert "right" in out[1].reason and "1.png" in out[1].reason and "SGBM" in out[1].reason


def test_disparity_source_and_preference_order(tmp_path):
    root = tmp_path / "s"
    make_stereo_session(root)
    (root / "disparity").mkdir()
    for i in range(3):
        disparity = np.full((SH, SW), 4.0 + i, np.float32)
        disparity[0, :4] = [0.0, -1.0, np.nan, np.inf]
        np.save(root / "disparity" / f"{i}.npy", disparity)
    s = open_session(root, cache_dir=tmp_path / "cache")
    assert s.depth_source == "disparity" and s.depth_cache_dir is None and "disparity/" in s.depth_note
    depth = s.load_frame(2, layers=("depth",)).depth_m
    assert not depth.flags.writeable  # a frame's depth is read-only whatever its source
    # depth = fx * B / d = 200 * 0.005 / 6 m; zero, negative, NaN and inf disparities are invalid.
    assert depth[5, 5] == pytest.approx(1.0 / 6.0, rel=1e-6)
    assert np.isnan(depth[0, :4]).all() and np.isfinite(depth[1:]).all()
    # depth/ wins over disparity/.
    (root / "depth").mkdir()
    for i in range(3):
        np.save(root / "depth" / f"{i}.npy", np.full((SH, SW), 0.3, np.float32))
    s = open_session(root)
    assert s.depth_source == "depth"
    assert s.load_frame(0, layers=("depth",)).depth_m[0, 0] == np.float32(0.3)


def test_depth_method_none_turns_sgbm_off(tmp_path):
    root = tmp_path / "s"
    make_stereo_session(root)
    with pytest.raises(SessionError, match=r"depth.*depth_method=None.*FoundationStereo"):
        open_session(root, depth_method=None)
    with pytest.raises(ValueError, match="depth_method"):
        open_session(root, depth_method="raft")


def test_missing_masks_says_what_to_fill(tmp_path):
    root = tmp_path / "s"
    make_stereo_session(root, masks=False)
    assert missing_inputs(root) == [
        line for line in missing_inputs(root) if line.startswith(("masks/", "depth/"))
    ] and len(missing_inputs(root)) == 2
    with pytest.raises(SessionError) as info:
        open_session(root)
    message = str(info.value)
    for part in ("masks", "masks/<stem>.png", "SAM2", "depth/<stem>.npy", "disparity/<stem>.npy", "SGBM"):
        assert part in message, part
    s = open_session(root, require_masks=False, cache_dir=tmp_path / "cache")
    bad = s.load_frame(0, layers=("mask",))
    assert isinstance(bad, BadFrame) and "masks" in bad.reason
    assert isinstance(s.load_depth(0), np.ndarray)
    (root / "K.txt").unlink()
    assert any("K.txt" in line for line in missing_inputs(root))


def write_raw_rig(root: Path) -> None:
    """stereo.yaml of a raw (distorted, slightly rotated) rig of SW x SH images, in OpenCV FileStorage."""
    fs = cv2.FileStorage(str(root / "stereo.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("K1", np.array([[80.0, 0, 47], [0, 81, 19], [0, 0, 1]]))
    fs.write("D1", np.array([-0.2, 0.05, 0.001, 0.0, 0.0]))
    fs.write("K2", np.array([[79.0, 0, 49], [0, 80, 21], [0, 0, 1]]))
    fs.write("D2", np.array([-0.15, 0.03, 0.0, 0.001, 0.0]))
    fs.write("R", cv2.Rodrigues(np.array([0.02, -0.03, 0.01]))[0])
    fs.write("T", np.array([-0.005, 0.0002, 0.0001]))
    fs.write("image_width", SW)
    fs.write("image_height", SH)
    fs.release()


def test_raw_images_are_rectified_on_load(tmp_path):
    root = tmp_path / "s"
    make_stereo_session(root)
    (root / "K.txt").unlink()
    write_raw_rig(root)
    ids = np.zeros((SH, SW), np.uint8)
    ids[10:30, 20:70] = 1
    write_palette_png(root / "masks" / "0.png", ids)
    (root / "depth").mkdir()
    raw_depth = np.linspace(0.05, 0.15, SH * SW, dtype=np.float32).reshape(SH, SW)
    np.save(root / "depth" / "0.npy", raw_depth)
    s = open_session(root)
    assert s.rectification is not None and "rectified on load" in s.depth_note
    assert s.calibration.baseline_m == pytest.approx(math.sqrt(0.005**2 + 0.0002**2 + 0.0001**2))
    frame = s.load_frame(0, layers=("mask", "depth", "left", "right"))
    assert isinstance(frame, Frame)
    raw_left = np.asarray(Image.open(root / "left" / "0.png"))
    raw_right = np.asarray(Image.open(root / "right" / "0.png"))
    rect = s.rectification
    np.testing.assert_array_equal(frame.left_rgb, rect.apply("left", raw_left))
    np.testing.assert_array_equal(frame.right_rgb, rect.apply("right", raw_right))
    assert not np.array_equal(frame.left_rgb, raw_left)  # the maps are not the identity
    # Masks and depth are resampled with nearest neighbour: no new values appear.
    assert frame.tool_mask.dtype == bool
    expected_mask = cv2.remap(ids, rect.left_x, rect.left_y, cv2.INTER_NEAREST) == 1
    np.testing.assert_array_equal(frame.tool_mask, expected_mask)
    assert 0 < frame.tool_mask.sum() < SH * SW
    values = frame.depth_m[np.isfinite(frame.depth_m)]
    assert np.isin(values, raw_depth).all()
    # disparity/ cannot be used with raw images.
    for path in (root / "depth").iterdir():
        path.unlink()
    (root / "depth").rmdir()
    (root / "disparity").mkdir()
    np.save(root / "disparity" / "0.npy", np.ones((SH, SW), np.float32))
    with pytest.raises(SessionError, match=r"disparity.*rectified.*raw"):
        open_session(root)


def test_calibration_errors_reach_open_session(tmp_path):
    root = tmp_path / "s"
    make_stereo_session(root)
    (root / "K.txt").write_text(f"{SFX} 0 {SW * 4} 0 {SFX} {SH / 2} 0 0 1\n{SBASE_M}\n")
    with pytest.raises(SessionError, match=r"K.txt.*image size mismatch"):
        open_session(root)
    (root / "K.txt").unlink()
    with pytest.raises(SessionError, match=r"K.txt.*left.yaml.*stereo.yaml"):
        open_session(root)


def test_middlebury_session_with_ros_calibration(tmp_path):
    """SGBM depth of the Middlebury Motorcycle pair through a session with a ROS calibration whose
    rectified principal points differ (doffs): depth = f B / (d + doffs) against the true disparity."""
    skdata = pytest.importorskip("skimage.data")
    left, right, truth = skdata.stereo_motorcycle()
    root = tmp_path / "mb"
    for sub in ("left", "right"):
        (root / sub).mkdir(parents=True)
    Image.fromarray(left).save(root / "left" / "0.png")
    Image.fromarray(right).save(root / "right" / "0.png")
    fx, cx, cy, doffs, baseline = 994.978, 311.193, 254.877, 31.086, 0.193001
    height, width = truth.shape

    def ros(p_row0):
        k = f"[{fx}, 0, {cx}, 0, {fx}, {cy}, 0, 0, 1]"
        p = "[" + ", ".join(str(v) for v in p_row0 + [0, fx, cy, 0, 0, 0, 1, 0]) + "]"
        return (f"image_width: {width}\nimage_height: {height}\ncamera_matrix:\n  rows: 3\n  cols: 3\n  data: {k}\n"
                "distortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [0, 0, 0, 0, 0]\n"
                "rectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n"
                f"projection_matrix:\n  rows: 3\n  cols: 4\n  data: {p}\n")

    (root / "left.yaml").write_text(ros([fx, 0, cx, 0]))
    (root / "right.yaml").write_text(ros([fx, 0, cx + doffs, -fx * baseline]))
    s = open_session(root, require_masks=False, cache_dir=tmp_path / "cache")
    assert s.rectification is None and s.calibration.disparity_offset_px == pytest.approx(doffs)
    depth = s.load_depth(0)
    both = np.isfinite(depth) & np.isfinite(truth)  # truth is inf where unknown
    true_depth = fx * baseline / (truth + doffs)
    relative = np.abs(depth[both] / true_depth[both] - 1)
    # Measured: 95.7 % within 2 px of disparity; disparities + doffs are 38-91 px, so 2 px <= 5.3 %.
    assert np.mean(relative <= 0.053) >= 0.94
    assert np.median(relative) < 0.01
