"""The robot's pose: kinematics.csv, hand-eye files, the tip geometry, and the debugger's kinematic tip (.rrd)."""

from __future__ import annotations

import math
import shutil
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from contact_viz.errors import SessionError
from contact_viz.geometry.kinematics import (
    frame_samples,
    kinematic_tip,
    project_points,
    quaternion_to_matrix,
    transform_points,
)
from contact_viz.geometry.tooltip import tool_tip_xy
from contact_viz.io.kinematics import read_hand_eye, read_kinematics, read_tool_tips
from contact_viz.io.session import open_session
from contact_viz.synth import SynthParams, generate_session

N_FRAMES = 8


# ---- pure geometry, against scipy and OpenCV ----


def test_quaternions_and_transforms_match_scipy():
    rng = np.random.default_rng(1)
    quats = rng.normal(size=(20, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    np.testing.assert_allclose(quaternion_to_matrix(quats), Rotation.from_quat(quats).as_matrix(), atol=1e-12)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix()
    T[:3, 3] = [0.01, -0.02, 0.03]
    points = rng.normal(size=(5, 3))
    expected = Rotation.from_matrix(T[:3, :3]).apply(points) + T[:3, 3]
    np.testing.assert_allclose(transform_points(T, points), expected, atol=1e-12)


def test_projection_matches_opencv():
    K = np.array([[500.0, 0, 320], [0, 480, 240], [0, 0, 1]])
    points = np.array([[0.01, -0.02, 0.1], [-0.03, 0.01, 0.2], [0.0, 0.0, -0.1]])
    uv = project_points(K, points)
    expected, _ = cv2.projectPoints(points[:2], np.zeros(3), np.zeros(3), K, None)
    np.testing.assert_allclose(uv[:2], expected.reshape(-1, 2), atol=1e-9)
    assert np.isnan(uv[2]).all()  # behind the camera


def test_frame_samples_nearest_within_gap():
    samples = np.array([0.0, 0.1, 0.2])
    frames = np.array([-0.2, 0.04, 0.05, 0.16, 0.26, 0.3])
    np.testing.assert_array_equal(frame_samples(samples, frames, 0.06), [-1, 0, 0, 2, 2, -1])
    np.testing.assert_array_equal(frame_samples(np.array([]), frames, 1.0), [-1] * 6)


def test_kinematic_tip_worked_example():
    # camera 10 cm in front of the base, looking along the base's z; tip at base (0.01, 0, 0)
    T = np.eye(4)
    T[2, 3] = 0.1
    K = np.array([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]])
    depth = np.full((80, 100), 0.1, dtype=np.float32)
    tip = kinematic_tip(T, [0.01, 0.0, 0.0], [0, 0, 0, 1], K, mask_tip_xy=(63.0, 40.0), depth_m=depth)
    np.testing.assert_allclose(tip.tip_m, [0.01, 0, 0.1])
    np.testing.assert_allclose(tip.tip_xy_px, [60.0, 40.0])  # 50 + 100 * 0.01 / 0.1
    assert tip.error_px == pytest.approx(3.0)
    np.testing.assert_allclose(tip.mask_tip_m, [0.013, 0.0, 0.1])  # (63 - 50) / 100 * 0.1
    assert tip.error_mm == pytest.approx(3.0)
    np.testing.assert_allclose(tip.axes, np.eye(3))
    none = kinematic_tip(T, [0.01, 0.0, 0.0], [0, 0, 0, 1], K)
    assert math.isnan(none.error_px) and math.isnan(none.error_mm) and none.mask_tip_xy_px is None


# ---- files ----


def test_read_kinematics_and_errors(tmp_path):
    path = tmp_path / "kinematics.csv"
    path.write_text("timestamp,x_m,y_m,z_m,qx,qy,qz,qw,frame_id\n"
                    "0.2,0.1,0.2,0.3,0,0,0,1,base\n0.1,0.4,0.5,0.6,0,0,0.7071068,0.7071068,base\n")
    kin = read_kinematics(path)
    np.testing.assert_array_equal(kin.timestamps_s, [0.1, 0.2])  # sorted by time
    np.testing.assert_array_equal(kin.position_m, [[0.4, 0.5, 0.6], [0.1, 0.2, 0.3]])
    np.testing.assert_allclose(np.linalg.norm(kin.quaternion_xyzw, axis=1), 1.0, atol=1e-15)
    assert kin.frame_ids == ("base", "base")
    path.write_text("timestamp,x_m,y_m,z_m,qx,qy,qz,qw\n0.1,0,0,0,0,0,0,2\n")
    with pytest.raises(SessionError, match=r"kinematics.csv: line 2: expected a unit quaternion"):
        read_kinematics(path)
    path.write_text("timestamp,x,y,z,qx,qy,qz,qw\n0.1,0,0,0,0,0,0,1\n")
    with pytest.raises(SessionError, match=r"kinematics.csv: expected columns .* missing x_m, y_m, z_m"):
        read_kinematics(path)


def test_read_hand_eye_text_npy_and_errors(tmp_path):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    T[:3, 3] = [0.01, 0.02, 0.03]
    text = tmp_path / "he.txt"
    text.write_text("# camera_T_base\n" + "\n".join(", ".join(repr(float(v)) for v in row) for row in T) + "\n")
    np.testing.assert_array_equal(read_hand_eye(text), T)
    np.save(tmp_path / "he.npy", T)
    np.testing.assert_array_equal(read_hand_eye(tmp_path / "he.npy"), T)
    text.write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n")
    with pytest.raises(SessionError, match=r"he.txt: expected a hand-eye file.* found 12 numbers"):
        read_hand_eye(text)
    text.write_text("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(SessionError, match=r"he.txt: expected a rotation"):
        read_hand_eye(text)
    with pytest.raises(SessionError, match=r"nope.txt: missing"):
        read_hand_eye(tmp_path / "nope.txt")


def test_read_tool_tips(tmp_path):
    path = tmp_path / "tool_tips.csv"
    path.write_text("frame,x_px,y_px\n000002,10.5,20.25\n")
    tips = read_tool_tips(path, ["000000", "000001", "000002"])
    assert np.isnan(tips[:2]).all() and tips[2].tolist() == [10.5, 20.25]


# ---- the debugger ----


@pytest.fixture(scope="module")
def session_with_pose(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("kin") / "s"
    generate_session(root, SynthParams(phantom="cup", frames=N_FRAMES, seed=5, width=96, height=64))
    rows = ["timestamp,x_m,y_m,z_m,qx,qy,qz,qw,frame_id"]
    for i in range(6):  # poses for frames 0-5 only: frame 6 takes frame 5's (33 ms), frame 7 none (67 ms)
        q = [float(v) for v in Rotation.from_euler("y", 5 * i, degrees=True).as_quat()]
        rows.append(f"{i / 30:.9f},{0.002 * i - 0.005},{0.001 * i},{0.01 + 0.001 * i},{q[0]!r},{q[1]!r},{q[2]!r},"
                    f"{q[3]!r},PSM1_base")
    (root / "kinematics.csv").write_text("\n".join(rows) + "\n")
    return root


def rrd_rows(path: Path) -> dict[tuple[str, str], dict[int, object]]:
    from rerun.chunk import RrdReader

    rows: dict[tuple[str, str], dict[int, object]] = defaultdict(dict)
    for chunk in RrdReader(path).stream():
        if chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        frames = batch.column("frame").to_pylist()
        for name in (n for n in batch.schema.names if ":" in n):
            column = batch.column(name)
            for i, frame in enumerate(frames):
                if column[i].is_valid:
                    rows[(chunk.entity_path.lstrip("/"), name)][frame] = column[i].as_py()
    return rows


def test_debugger_draws_the_kinematic_tip_for_a_known_hand_eye(session_with_pose, tmp_path):
    rr = pytest.importorskip("rerun")
    from contact_viz.viz import rerun_log
    from contact_viz.viz.debugger import DebuggerOptions, run_debugger

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("x", 20, degrees=True).as_matrix()
    T[:3, 3] = [0.004, -0.003, 0.07]
    session = open_session(session_with_pose)
    options = DebuggerOptions(points=False, hand_eye=tuple(map(tuple, T)))
    out = tmp_path / "view.rrd"
    rr.set_strict_mode(True)
    opened = rerun_log.open_recording(save=out, blueprint=rerun_log.default_blueprint(with_kinematics=True))
    run_debugger(session, opened.rec, options)
    opened.close()
    rows = rrd_rows(out)
    kin = read_kinematics(session_with_pose / "kinematics.csv")
    K = session.calibration.K
    tips = rows[(rerun_log.ENTITY_KINEMATIC_TIP, "Points3D:positions")]
    projected = rows[(rerun_log.ENTITY_LEFT_KINEMATIC_TIP, "Points2D:positions")]
    error_px = rows[(f"{rerun_log.ENTITY_SERIES_TIP}/error_px", "Scalars:scalars")]
    error_mm = rows[(f"{rerun_log.ENTITY_SERIES_TIP}/error_mm", "Scalars:scalars")]
    axes = rows[(rerun_log.ENTITY_KINEMATIC_AXES, "Arrows3D:vectors")]
    assert sorted(tips) == list(range(7))  # frame 7: no pose within 50 ms
    assert (rerun_log.ENTITY_KINEMATIC_TIP, "Points3D:positions") in rows
    assert math.isnan(error_px[7][0])
    for frame in range(7):
        row = min(frame, 5)
        expected = Rotation.from_matrix(T[:3, :3]).apply(kin.position_m[row].copy()) + T[:3, 3]  # independent of ours
        np.testing.assert_allclose(tips[frame][0], expected, atol=1e-6)  # Points3D are float32
        uv, _ = cv2.projectPoints(kin.position_m[row][None], cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K, None)
        np.testing.assert_allclose(projected[frame][0], uv.ravel(), atol=1e-3)
        tool_axes = Rotation.from_matrix(T[:3, :3]) * Rotation.from_quat(kin.quaternion_xyzw[row].copy())
        np.testing.assert_allclose(np.array(axes[frame]), tool_axes.as_matrix().T * rerun_log.KINEMATIC_AXIS_M,
                                   atol=1e-6)
        loaded = session.load_frame(frame, ("mask", "depth"))
        mask_tip = tool_tip_xy(loaded.tool_mask)
        assert mask_tip is not None
        assert error_px[frame][0] == pytest.approx(math.dist(uv.ravel(), mask_tip), abs=1e-6)
        u, v = (math.floor(c + 0.5) for c in mask_tip)
        window = loaded.depth_m[max(v - 3, 0):v + 4, max(u - 3, 0):u + 4]
        z = float(np.median(window[np.isfinite(window) & (window > 0)]))
        back = np.array([(mask_tip[0] - K[0, 2]) / K[0, 0] * z, (mask_tip[1] - K[1, 2]) / K[1, 1] * z, z])
        assert error_mm[frame][0] == pytest.approx(np.linalg.norm(expected - back) * 1000, abs=1e-4)


def test_hand_eye_without_kinematics_is_one_line(session_with_pose, tmp_path):
    from typer.testing import CliRunner

    from contact_viz.cli import app

    plain = tmp_path / "plain"
    shutil.copytree(session_with_pose, plain)
    (plain / "kinematics.csv").unlink()
    he = tmp_path / "he.txt"
    he.write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    result = CliRunner().invoke(app, ["view", str(plain), "--hand-eye", str(he), "--save", str(tmp_path / "v.rrd")])
    assert result.exit_code == 2
    assert "kinematics.csv: missing: --hand-eye needs the robot's pose" in result.output
