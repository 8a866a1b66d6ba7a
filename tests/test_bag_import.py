"""`contact-viz import bag`: real ROS 1, ROS 2 (sqlite3) and MCAP bags written with rosbags' own writers."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from bag_writers import FORCE_BETWEEN_N, RIGHT_DELAY_NS, poses, session_tables, write_bag
from contact_viz.errors import SessionError
from contact_viz.io.importers import run_import_command
from contact_viz.io.importers.bag import import_bag, list_lines
from contact_viz.io.importers.ros_messages import MessageError, image_message
from contact_viz.io.kinematics import read_kinematics
from contact_viz.io.session import open_session, read_rgb
from contact_viz.pipeline.extract import extract_features
from contact_viz.synth import SynthParams, generate_session

N_FRAMES = 8


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("bag") / "orig"
    generate_session(root, SynthParams(phantom="cup", frames=N_FRAMES, seed=3, width=96, height=64))
    return root


def listing(root: Path) -> dict[str, tuple[int, int]]:
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in filenames:
            st = (Path(dirpath) / name).stat()
            out[str((Path(dirpath) / name).relative_to(root))] = (st.st_size, st.st_mtime_ns)
    return out if root.is_dir() else {root.name: (root.stat().st_size, root.stat().st_mtime_ns)}


FLAVOURS = {
    # ROS 1 bag with the dVRK's topic names (found by the defaults), rgb8 images, PoseStamped
    "ros1": dict(),
    # ROS 2 sqlite3 bag with other names (found by type and side), bgr8, frame 3 without a right image
    "ros2": dict(encoding="bgr8", left="/camera/left/image_rect_color", right="/camera/right/image_rect_color",
                 left_info="/camera/left/camera_info", right_info="/camera/right/camera_info", force="/ati/wrench",
                 pose="/PSM2/measured_cp", skip_right=(3,)),
    # MCAP with JPEG CompressedImage (bytes kept) and TransformStamped
    "mcap": dict(compressed=True, pose_type="TransformStamped"),
}


@pytest.mark.parametrize("flavour", sorted(FLAVOURS))
def test_imported_bag_gives_the_same_extract_rows(synth, tmp_path, flavour):
    bag = write_bag(synth, tmp_path / ("rec.bag" if flavour == "ros1" else "rec"), flavour, **FLAVOURS[flavour])
    before = listing(bag)
    out = tmp_path / "imported"
    lines = run_import_command("bag", bag, out)
    assert listing(bag) == before  # the bag is never modified
    text = "\n".join(lines)
    assert f"{N_FRAMES} frames imported" in text
    assert "1 right image(s) have no left image" in text  # the extra right image: reported, not silently dropped
    if flavour == "ros2":
        assert "1 left frame(s) have no right image" in text and not (out / "right" / "000003.png").exists()
    # masks and depth are not in bags: take them from the original session
    shutil.copytree(synth / "masks", out / "masks")
    shutil.copytree(synth / "depth", out / "depth")
    original = open_session(synth, cache_dir=tmp_path / "cache")
    imported = open_session(out, cache_dir=tmp_path / "cache")
    assert imported.stems == original.stems
    np.testing.assert_allclose(imported.calibration.K, original.calibration.K)
    assert imported.calibration.baseline_m == pytest.approx(original.calibration.baseline_m)
    assert imported.rectification is None
    np.testing.assert_array_equal(imported.force_xyz_n, original.force_xyz_n)  # the frame's own sample, N
    assert sum(1 for _ in open(out / "force.csv")) - 1 == 3 * N_FRAMES  # force keeps its own rate
    rows_a = extract_features(original)
    rows_b = extract_features(imported)
    assert len(rows_a) == len(rows_b) == N_FRAMES
    for a, b in zip(rows_a, rows_b):
        assert float(b["timestamp"]) == pytest.approx(float(a["timestamp"]), abs=1e-9)
        assert {k: v for k, v in a.items() if k != "timestamp"} == {k: v for k, v in b.items() if k != "timestamp"}
    assert all(r["label_source"] == "force" for r in rows_b)  # every frame got its force sample's label
    # images: the same pixels (JPEG bytes kept as they are for CompressedImage)
    for stem in original.stems:
        src = synth / "left" / f"{stem}.jpg"
        if flavour == "mcap":
            assert (out / "left" / f"{stem}.jpg").read_bytes() == src.read_bytes()
        else:
            np.testing.assert_array_equal(read_rgb(out / "left" / f"{stem}.png"), read_rgb(src))
    # the pose: kinematics.csv
    kin = read_kinematics(out / "kinematics.csv")
    position, quat = poses(N_FRAMES)
    np.testing.assert_array_equal(kin.position_m, position)
    np.testing.assert_allclose(kin.quaternion_xyzw, quat, atol=1e-12)
    np.testing.assert_allclose(kin.timestamps_s, np.arange(N_FRAMES) / 30.0, atol=1e-9)
    assert set(kin.frame_ids) == {"PSM1_base"}
    assert imported.kinematics is not None and len(imported.kinematics) == N_FRAMES


def test_list_prints_topics_types_counts_rates_and_default_roles(synth, tmp_path):
    bag = write_bag(synth, tmp_path / "rec.bag", "ros1")
    lines = list_lines(bag)
    assert lines[0].startswith(f"{bag}: ROS 1 bag")
    rows = {line.split()[0]: line.split() for line in lines[2:]}
    expected = {"/jhu_daVinci/left/image_raw": ("sensor_msgs/msg/Image", N_FRAMES, "left"),
                "/jhu_daVinci/right/image_raw": ("sensor_msgs/msg/Image", N_FRAMES + 1, "right"),
                "/jhu_daVinci/left/camera_info": ("sensor_msgs/msg/CameraInfo", 1, "left-info"),
                "/jhu_daVinci/right/camera_info": ("sensor_msgs/msg/CameraInfo", 1, "right-info"),
                "/force_sensor/measured_cf": ("geometry_msgs/msg/WrenchStamped", 3 * N_FRAMES, "force"),
                "/PSM1/measured_cp": ("geometry_msgs/msg/PoseStamped", N_FRAMES, "pose")}
    assert set(rows) == set(expected)
    tables = session_tables(synth)
    duration_s = (N_FRAMES - 1 + 2 / 3) / tables["fps"]  # first left image to the last force sample
    for topic, (msgtype, count, role) in expected.items():
        assert rows[topic][1] == msgtype and int(rows[topic][2]) == count and rows[topic][4] == role
        assert float(rows[topic][3]) == pytest.approx(count / duration_s, abs=0.01)


def test_topic_options_override_the_defaults(synth, tmp_path):
    bag = write_bag(synth, tmp_path / "rec", "mcap", left="/a/cam1/image", right="/a/cam2/image",
                    left_info="/a/cam1/info", right_info="/a/cam2/info", force="/ft", pose="/tool")
    mcap = next(bag.parent.glob("*.mcap")) if bag.is_file() else bag
    with pytest.raises(SessionError, match="expected a left image topic.*--left"):
        import_bag(mcap, tmp_path / "x")
    result = import_bag(mcap, tmp_path / "s", left="/a/cam1/image", right="/a/cam2/image", left_info="/a/cam1/info",
                        right_info="/a/cam2/info", pose="none")
    assert result.frames == N_FRAMES and (tmp_path / "s" / "force.csv").is_file()  # the only wrench topic
    assert not (tmp_path / "s" / "kinematics.csv").exists()
    with pytest.raises(SessionError, match=r"topic /nope: --left: expected a topic of the bag"):
        import_bag(mcap, tmp_path / "y", left="/nope")
    with pytest.raises(SessionError, match=r"topic /ft: --left: expected a topic of type sensor_msgs/msg/Image"):
        import_bag(mcap, tmp_path / "y", left="/ft")


def test_given_calibration_replaces_camera_info(synth, tmp_path):
    bag = write_bag(synth, tmp_path / "rec.bag", "ros1", with_info=False)
    with pytest.raises(SessionError, match=r"rec.bag: expected a sensor_msgs/CameraInfo topic for the left camera"):
        import_bag(bag, tmp_path / "x")
    import_bag(bag, tmp_path / "s", calibration=[synth / "K.txt"])
    assert (tmp_path / "s" / "K.txt").read_text() == (synth / "K.txt").read_text()


def remains(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir())


@pytest.mark.parametrize("case", ["no_images", "sizes", "encoding", "truncated", "no_camera_info"])
def test_bad_bags_get_one_line_naming_the_topic_or_file(synth, tmp_path, case):
    if case == "no_images":
        bag = write_bag(synth, tmp_path / "rec.bag", "ros1", left="/x/image", right="/y/image")
        # no image topic has 'left' in its name: as if the bag had no left images
        expected = r"rec.bag: expected a left image topic .* found image topics /x/image, /y/image"
    elif case == "sizes":
        bag = write_bag(synth, tmp_path / "rec.bag", "ros1", sizes={4: (48, 32)})
        expected = r"rec.bag: topic /jhu_daVinci/(left|right)/image_raw: message at 0.13\d+ s: expected a 96x64 image"
    elif case == "encoding":
        bag = write_bag(synth, tmp_path / "rec.bag", "ros1", encoding="32FC1")
        expected = r"topic /jhu_daVinci/left/image_raw: message at 0.000000000 s: expected an image encoding"
    elif case == "truncated":
        whole = write_bag(synth, tmp_path / "whole.bag", "ros1")
        bag = tmp_path / "rec.bag"
        bag.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
        whole.unlink()
        expected = r"rec.bag: expected a (readable|complete) ROS bag"
    else:
        bag = write_bag(synth, tmp_path / "rec.bag", "ros1", with_info=False)
        expected = r"rec.bag: expected a sensor_msgs/CameraInfo topic for the left camera"
    before = remains(tmp_path)
    with pytest.raises(SessionError, match=expected):
        import_bag(bag, tmp_path / "out")
    assert remains(tmp_path) == before  # nothing that looks like a session, no staging folder
    proc = subprocess.run([sys.executable, "-m", "contact_viz.cli", "import", "bag", str(bag), str(tmp_path / "out")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    error_lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(error_lines) == 1 and error_lines[0].startswith("error: ") and "Traceback" not in proc.stderr


def test_truncated_mcap_and_damaged_sqlite(synth, tmp_path):
    bag = write_bag(synth, tmp_path / "m", "mcap")
    data = bag.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(SessionError, match=r"cut.mcap: expected a (readable|complete) ROS bag"):
        import_bag(cut, tmp_path / "out")
    db = write_bag(synth, tmp_path / "d", "ros2")
    db3 = next(db.glob("*.db3"))
    db3.write_bytes(db3.read_bytes()[:4096])
    with pytest.raises(SessionError, match=r"expected a (readable|complete) ROS bag"):
        import_bag(db, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_an_interrupted_import_leaves_nothing(synth, tmp_path):
    bag = write_bag(synth, tmp_path / "rec.bag", "ros1")
    seen = []

    def progress(done, total):
        seen.append(done)
        if done >= total // 2:
            raise KeyboardInterrupt

    before = remains(tmp_path)
    with pytest.raises(KeyboardInterrupt):
        import_bag(bag, tmp_path / "out", progress=progress)
    assert seen and remains(tmp_path) == before


def test_pairing_tolerance(synth, tmp_path):
    bag = write_bag(synth, tmp_path / "rec.bag", "ros1")
    result = import_bag(bag, tmp_path / "s", pair_tolerance_s=RIGHT_DELAY_NS / 2e9)  # tighter than the 1 ms offset
    assert any(f"{N_FRAMES} left frame(s) have no right image" in n for n in result.notes)
    assert any(f"{N_FRAMES + 1} right image(s) have no left image" in n for n in result.notes)
    assert not (tmp_path / "s" / "right").exists() or not any((tmp_path / "s" / "right").iterdir())


def test_wrench_between_frames_is_kept_at_its_own_rate(synth, tmp_path):
    bag = write_bag(synth, tmp_path / "rec.bag", "ros1")
    import_bag(bag, tmp_path / "s")
    rows = [line.split(",") for line in (tmp_path / "s" / "force.csv").read_text().splitlines()[1:]]
    between = [r for r in rows if float(r[1]) == FORCE_BETWEEN_N]
    assert len(between) == 2 * N_FRAMES


# ---- image messages ----


class Msg:
    def __init__(self, **fields):
        self.__dict__.update(fields)


def test_image_encodings():
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (6, 10, 3), dtype=np.uint8)
    padded = np.zeros((6, 32), dtype=np.uint8)  # step 32 > 30 bytes per row
    padded[:, :30] = rgb.reshape(6, 30)
    out = image_message(Msg(encoding="rgb8", height=6, width=10, step=32, is_bigendian=0, data=padded.ravel()))
    decoded = cv2.imdecode(np.frombuffer(out.data, np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(decoded[:, :, ::-1], rgb)
    assert out.shape == (6, 10) and out.suffix == ".png"
    # mono16 big-endian stays 16-bit
    mono = rng.integers(0, 65536, (4, 5), dtype=np.uint16)
    out = image_message(Msg(encoding="mono16", height=4, width=5, step=10, is_bigendian=1,
                            data=np.frombuffer(mono.astype(">u2").tobytes(), np.uint8)))
    np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(out.data, np.uint8), cv2.IMREAD_UNCHANGED), mono)
    # bayer_rggb8: a flat colour comes back as that colour away from the border
    colour = np.array([200, 90, 30])  # R, G, B
    mosaic = np.empty((8, 8), dtype=np.uint8)
    mosaic[0::2, 0::2], mosaic[0::2, 1::2] = colour[0], colour[1]  # R G
    mosaic[1::2, 0::2], mosaic[1::2, 1::2] = colour[1], colour[2]  # G B
    out = image_message(Msg(encoding="bayer_rggb8", height=8, width=8, step=8, is_bigendian=0, data=mosaic.ravel()))
    bgr = cv2.imdecode(np.frombuffer(out.data, np.uint8), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(bgr[2:6, 2:6].reshape(-1, 3), np.tile(colour[::-1], (16, 1)))
    with pytest.raises(MessageError, match="expected an image encoding .* found '32FC1'"):
        image_message(Msg(encoding="32FC1", height=1, width=1, step=4, is_bigendian=0, data=np.zeros(4, np.uint8)))
    with pytest.raises(MessageError, match="found 20 bytes"):
        image_message(Msg(encoding="rgb8", height=2, width=4, step=12, is_bigendian=0, data=np.zeros(20, np.uint8)))


def test_cli_list_and_import(synth, tmp_path):
    from typer.testing import CliRunner

    from contact_viz.cli import app

    bag = write_bag(synth, tmp_path / "rec.bag", "ros1")
    runner = CliRunner()
    listed = runner.invoke(app, ["import", "bag", str(bag), "--list"])
    assert listed.exit_code == 0 and listed.output.splitlines() == list_lines(bag)
    missing = runner.invoke(app, ["import", "bag", str(bag)])
    assert missing.exit_code == 2 and "OUT_SESSION: expected the new session directory" in missing.output
    wrong = runner.invoke(app, ["import", "dvrk", str(tmp_path), "--list"])
    assert wrong.exit_code == 2 and "--list only applies to bag imports" in wrong.output
    done = runner.invoke(app, ["import", "bag", str(bag), str(tmp_path / "s"), "--force", "none", "--pose", "none"])
    assert done.exit_code == 0, done.output
    assert f"{N_FRAMES} frames imported" in done.output and "no force topic" in done.output
    assert not (tmp_path / "s" / "force.csv").exists() and not (tmp_path / "s" / "kinematics.csv").exists()
