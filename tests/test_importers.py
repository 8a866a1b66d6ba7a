"""Tests for contact_viz.io.importers: small dVRK data_collection and Yang et al. 2024 layouts in tmp_path."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from contact_viz.errors import SessionError
from contact_viz.io.importers import import_dvrk, import_yang2024, run_import_command
from contact_viz.io.session import open_session

H, W = 24, 40  # image size, px
T0_NS = 1_737_146_000_000_000_000  # an epoch time, ns
FRAME_NS = 33_333_333  # ~30 Hz frame period, ns
FORCE_NS = 10_000_000  # 100 Hz force period, ns
FX_PX, BASELINE_M = 60.0, 0.005  # rectified camera of the synthetic CameraInfo topics


def listing(root: Path) -> dict[str, tuple[int, int, int]]:
    """Every file and folder under root: relative path -> (size, mtime_ns, inode)."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            path = Path(dirpath) / name
            st = path.stat()
            out[str(path.relative_to(root))] = (st.st_size if path.is_file() else 0, st.st_mtime_ns, st.st_ino)
    return out


def image(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8)


def seconds_text(ns: int) -> str:
    """The extractor's file-name time: f"{ns / 1e9:.9f}" (exact here since ns < 2**53 is not needed)."""
    return f"{ns // 10**9}.{ns % 10**9:09d}"


def write_topic(path: Path, topic: str, msg_type: str, header: list[str], rows: list[list[object]]) -> None:
    with open(path, "w", newline="") as handle:
        handle.write(f"# Topic: {topic}\n# Type: {msg_type}\n")
        writer = csv.writer(handle)
        writer.writerow(header)
        writer.writerows(rows)


def camera_info_row(cx_right_offset: float, tx: float) -> tuple[list[str], list[object]]:
    k = [FX_PX, 0, W / 2, 0, FX_PX, H / 2, 0, 0, 1]
    p = [FX_PX, 0, W / 2 + cx_right_offset, tx, 0, FX_PX, H / 2, 0, 0, 0, 1, 0]
    r = [1, 0, 0, 0, 1, 0, 0, 0, 1]
    header = (["timestamp"] + [f"d.{i}" for i in range(5)] + ["distortion_model", "header.frame_id", "height"]
              + [f"k.{i}" for i in range(9)] + [f"p.{i}" for i in range(12)] + [f"r.{i}" for i in range(9)] + ["width"])
    row = [T0_NS] + [0.0] * 5 + ["plumb_bob", "cam", H] + k + p + r + [W]
    return header, row


def make_dvrk(root: Path, n: int = 5, *, two_force_topics: bool = False) -> dict:
    """A recording folder with extracted/full_session/ as data_collection writes it."""
    folder = root / "extracted" / "full_session"
    folder.mkdir(parents=True)
    times = [T0_NS + i * FRAME_NS + (i % 2) * 1234 for i in range(n)]
    for i, t in enumerate(times):
        ext = "png" if i % 2 == 0 else "jpg"  # a mix, as -f png / -f jpg runs might leave
        Image.fromarray(image(i)).save(folder / f"stereo_left_{seconds_text(t)}.{ext}")
        Image.fromarray(image(100 + i)).save(folder / f"stereo_right_{seconds_text(t)}.{ext}")
    # A right image with no left one, and a mono video that must be ignored.
    Image.fromarray(image(999)).save(folder / f"stereo_right_{seconds_text(T0_NS + 99 * FRAME_NS)}.png")
    Image.fromarray(image(998)).save(folder / f"overview_{seconds_text(T0_NS)}.jpg")
    # Force at 100 Hz from before the first frame to after the last.
    force_t = [T0_NS - 3 * FORCE_NS + i * FORCE_NS for i in range(n * 4 + 6)]
    force = [[t, "", 0, i % 1_000_000, (t // 10**9), 0.1 * i, -0.05 * i, 1.5 + 0.2 * i, 0, 0, 0]
             for i, t in enumerate(force_t)]
    header = ["timestamp", "header.frame_id", "header.stamp.nanosec", "header.stamp.nsec_dummy", "header.stamp.sec",
              "wrench.force.x", "wrench.force.y", "wrench.force.z", "wrench.torque.x", "wrench.torque.y",
              "wrench.torque.z"]
    write_topic(folder / "force_sensor_measured_cf.csv", "/force_sensor/measured_cf",
                "geometry_msgs/msg/WrenchStamped", header, force)
    if two_force_topics:
        write_topic(folder / "PSM1_body_measured_cf.csv", "/PSM1/body/measured_cf", "geometry_msgs/msg/Wrench",
                    ["timestamp", "force.x", "force.y", "force.z"], [[T0_NS, 9, 9, 9]])
    write_topic(folder / "PSM1_measured_js.csv", "/PSM1/measured_js", "sensor_msgs/msg/JointState",
                ["timestamp", "position.0", "position.1"], [[T0_NS, 0.1, 0.2]])
    left_header, left_row = camera_info_row(0.0, 0.0)
    right_header, right_row = camera_info_row(2.0, -FX_PX * BASELINE_M)
    write_topic(folder / "camera_left_camera_info.csv", "/camera/left/camera_info", "sensor_msgs/msg/CameraInfo",
                left_header, [left_row, left_row])
    write_topic(folder / "camera_right_camera_info.csv", "/camera/right/camera_info", "sensor_msgs/msg/CameraInfo",
                right_header, [right_row])
    return {"folder": folder, "times": times, "force_t": force_t, "force": force}


def read_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def test_dvrk_import(tmp_path):
    src = tmp_path / "rec"
    made = make_dvrk(src)
    before = listing(src)
    out = tmp_path / "sessions" / "run1"
    lines = run_import_command("dvrk", src, out)
    assert listing(src) == before  # the source is untouched
    assert [p.name for p in out.parent.iterdir()] == ["run1"]  # no leftover staging folder
    folder = made["folder"]
    # Stems in time order; each links to the source file of that time.
    stems = [f"{i:06d}" for i in range(5)]
    for i, (stem, t) in enumerate(zip(stems, made["times"])):
        ext = "png" if i % 2 == 0 else "jpg"
        left = out / "left" / f"{stem}.{ext}"
        assert left.read_bytes() == (folder / f"stereo_left_{seconds_text(t)}.{ext}").read_bytes()
        assert os.path.samefile(left, folder / f"stereo_left_{seconds_text(t)}.{ext}")  # linked, not copied
        assert os.path.samefile(out / "right" / f"{stem}.{ext}", folder / f"stereo_right_{seconds_text(t)}.{ext}")
    assert sorted(p.name for p in (out / "left").iterdir()) == [f"{s}.{'png' if i % 2 == 0 else 'jpg'}"
                                                                 for i, s in enumerate(stems)]
    frames = read_rows(out / "frames.csv")
    assert [r["frame"] for r in frames] == stems
    assert [r["timestamp"] for r in frames] == [seconds_text(t) for t in made["times"]]  # exact text
    force = read_rows(out / "force.csv")
    assert len(force) == len(made["force"])  # the sensor's own rate
    assert [r["timestamp"] for r in force] == [seconds_text(t) for t in made["force_t"]]
    np.testing.assert_allclose([float(r["fz"]) for r in force], [row[7] for row in made["force"]])
    text = "\n".join(lines)
    assert "5 frames imported" in text and ("10 hardlinked" in text or "10 symlinked" in text)
    assert "1 right image(s) without a left image" in text and "/force_sensor/measured_cf" in text
    assert "still to fill" in text and "masks/<stem>.png" in text and "FoundationStereo" in text
    assert "left.yaml + right.yaml" in text
    # The new session opens; its force per frame is the nearest sample (brute force reference).
    s = open_session(out, require_masks=False, cache_dir=tmp_path / "cache")
    assert s.stems == stems and s.depth_source == "sgbm"
    assert s.calibration.baseline_m == pytest.approx(BASELINE_M) and s.calibration.disparity_offset_px == 2.0
    frame_s = np.array([t / 1e9 for t in made["times"]])
    sample_s = np.array([t / 1e9 for t in made["force_t"]])
    nearest = [int(np.argmin(np.abs(sample_s - t))) for t in frame_s]
    np.testing.assert_allclose(s.force_xyz_n[:, 2], [made["force"][j][7] for j in nearest])
    np.testing.assert_allclose(s.timestamps_s, frame_s)
    # The reader's error for the missing masks says what the importer said.
    with pytest.raises(SessionError, match="SAM2"):
        open_session(out)


def test_dvrk_force_topic_choice_and_errors(tmp_path):
    src = tmp_path / "rec"
    make_dvrk(src, two_force_topics=True)
    expected = r"several.*/PSM1/body/measured_cf.*/force_sensor/measured_cf.*--force-topic"
    with pytest.raises(SessionError, match=expected):
        import_dvrk(src, tmp_path / "a")
    assert not (tmp_path / "a").exists()
    result = import_dvrk(src, tmp_path / "b", force_topic="/PSM1/body/measured_cf")
    assert result.force_samples == 1
    assert read_rows(tmp_path / "b" / "force.csv") == [{"timestamp": seconds_text(T0_NS), "fx": "9.0", "fy": "9.0",
                                                        "fz": "9.0"}]
    # By CSV file name too.
    assert import_dvrk(src, tmp_path / "c", force_topic="force_sensor_measured_cf.csv").force_samples == 26
    with pytest.raises(SessionError, match=r"topic '/nope'.*found topics"):
        import_dvrk(src, tmp_path / "d", force_topic="/nope")
    with pytest.raises(SessionError, match=r"PSM1_measured_js.csv.*force columns"):
        import_dvrk(src, tmp_path / "e", force_topic="/PSM1/measured_js")


def test_dvrk_bad_inputs_leave_nothing_behind(tmp_path):
    src = tmp_path / "rec"
    made = make_dvrk(src)
    folder = made["folder"]
    # Several videos need --video.
    Image.fromarray(image(5)).save(folder / f"other_left_{seconds_text(T0_NS)}.png")
    with pytest.raises(SessionError, match=r"other, stereo.*--video"):
        import_dvrk(src, tmp_path / "out")
    assert import_dvrk(folder, tmp_path / "ok", video="stereo").frames == 5  # SRC may be the folder itself
    (folder / f"other_left_{seconds_text(T0_NS)}.png").unlink()
    # OUT must be new or empty, and not inside SRC.
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(ValueError, match="new or empty"):
        run_import_command("dvrk", src, tmp_path / "full")
    with pytest.raises(ValueError, match="inside the source"):
        run_import_command("dvrk", src, src / "session")
    # A malformed force value names the file and line; OUT is not created.
    text = (folder / "force_sensor_measured_cf.csv").read_text().splitlines()
    text[5] = text[5].replace(",0.2,", ",abc,", 1)
    (folder / "force_sensor_measured_cf.csv").write_text("\n".join(text) + "\n")
    with pytest.raises(SessionError, match=r"force_sensor_measured_cf.csv: line 6: expected a number"):
        import_dvrk(src, tmp_path / "out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["full", "ok", "rec"]
    with pytest.raises(ValueError, match="KIND"):
        run_import_command("scared", src, tmp_path / "x")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(SessionError, match=r"empty.*<video>_left_<t>"):
        import_dvrk(empty, tmp_path / "x")


def test_dvrk_copy_and_given_calibration(tmp_path):
    src = tmp_path / "rec"
    made = make_dvrk(src, n=3)
    for info in made["folder"].glob("camera_*_camera_info.csv"):
        info.unlink()
    k_txt = tmp_path / "K.txt"
    k_txt.write_text(f"{FX_PX} 0 20 0 {FX_PX} 12 0 0 1\n0.0042\n")
    result = import_dvrk(src, tmp_path / "out", calibration=[k_txt], copy=True)
    assert result.placed == {"hardlink": 0, "symlink": 0, "copy": 6}
    assert not os.path.samefile(tmp_path / "out" / "left" / "000000.png",
                                next(made["folder"].glob("stereo_left_*.png")))
    assert (tmp_path / "out" / "K.txt").read_text() == k_txt.read_text()
    assert not any("K.txt" in line for line in result.to_fill)
    bad = tmp_path / "cal" / "K.txt"
    bad.parent.mkdir()
    bad.write_text(f"{FX_PX} 0 20 0 {FX_PX} 12 0 0 1\n0\n")
    with pytest.raises(SessionError, match=r"K.txt.*positive"):
        import_dvrk(src, tmp_path / "out2", calibration=[bad])
    with pytest.raises(ValueError, match="must be named"):
        import_dvrk(src, tmp_path / "out3", calibration=[tmp_path / "cal"])
    assert not (tmp_path / "out2").exists() and not (tmp_path / "out3").exists()


def make_yang(root: Path, n: int = 4, rows: int = 5) -> np.ndarray:
    """img_<n>.jpg, right_img/img_<n>.jpg and labels_30hz.txt (np.savetxt, 104 columns as the recorder)."""
    (root / "right_img").mkdir(parents=True)
    for i in range(n):
        Image.fromarray(image(i)).save(root / f"img_{i}.jpg")
        Image.fromarray(image(50 + i)).save(root / "right_img" / f"img_{i}.jpg")
    rng = np.random.default_rng(7)
    data = rng.normal(0, 1, (rows, 104))
    data[:, 0] = np.arange(rows) * 0.0333 + 0.0121  # time, s
    with open(root / "labels_30hz.txt", "w") as handle:
        for row in data:
            np.savetxt(handle, row.reshape(1, -1), delimiter=",")
    return data


def test_yang2024_import(tmp_path):
    src = tmp_path / "R1_M1_T1_1"
    data = make_yang(src)
    before = listing(src)
    lines = run_import_command("yang2024", src, tmp_path / "s")
    assert "K.txt" in "\n".join(lines)  # no calibration given: still to fill
    k_txt = tmp_path / "K.txt"
    k_txt.write_text("60 0 20 0 60 12 0 0 1\n0.005\n")
    lines = run_import_command("yang2024", src, tmp_path / "s2", calibration=[k_txt])
    assert listing(src) == before
    out = tmp_path / "s2"
    stems = [f"{i:06d}" for i in range(4)]
    assert sorted(p.name for p in (out / "left").iterdir()) == [f"{s}.jpg" for s in stems]
    assert os.path.samefile(out / "right" / "000002.jpg", src / "right_img" / "img_2.jpg")
    s = open_session(out, require_masks=False, cache_dir=tmp_path / "cache")
    assert s.stems == stems
    np.testing.assert_allclose(s.timestamps_s, data[:4, 0])
    np.testing.assert_allclose(s.force_xyz_n, data[:4, 1:4])
    text = "\n".join(lines)
    assert "4 frames imported" in text and "1 row(s) of labels_30hz.txt have no left image" in text
    assert "masks/<stem>.png" in text and "K.txt" not in text
    with pytest.raises(ValueError, match="only apply to dvrk"):
        run_import_command("yang2024", src, tmp_path / "t", force_topic="/x")


def test_yang2024_errors(tmp_path):
    src = tmp_path / "rec"
    make_yang(src, n=4, rows=3)
    with pytest.raises(SessionError, match=r"labels_30hz.txt.*3 rows.*img_3.*row 4"):
        import_yang2024(src, tmp_path / "out")
    (src / "labels_30hz.txt").write_text("0.1,1,2\n")
    with pytest.raises(SessionError, match=r"labels_30hz.txt: line 1: expected at least 4"):
        import_yang2024(src, tmp_path / "out")
    (src / "labels_30hz.txt").unlink()
    with pytest.raises(SessionError, match=r"labels_30hz.txt: missing"):
        import_yang2024(src, tmp_path / "out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"]
