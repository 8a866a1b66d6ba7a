"""Tests for contact_viz.io.calibration: K.txt, ROS camera_info YAML, OpenCV FileStorage, rectification."""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from contact_viz.io.calibration import (
    Rectification,
    read_calibration,
    read_k_txt,
    read_opencv_stereo,
    read_ros_camera_info,
    rotation_deviation,
)
from contact_viz.errors import SessionError, SessionWarning

W, H = 160, 120  # raw image size of the synthetic rig, px
K1 = np.array([[150.0, 0.0, 82.0], [0.0, 152.0, 58.0], [0.0, 0.0, 1.0]])  # raw left camera, px
K2 = np.array([[148.0, 0.0, 79.0], [0.0, 149.0, 61.0], [0.0, 0.0, 1.0]])  # raw right camera, px
D1 = np.array([-0.12, 0.03, 0.001, -0.0015, 0.0])  # left distortion (plumb bob)
D2 = np.array([-0.10, 0.02, -0.001, 0.001, 0.0])  # right distortion
R_RL = cv2.Rodrigues(np.array([0.01, -0.02, 0.006]))[0]  # rotation right-from-left
T_RL_M = np.array([-0.05, 0.0008, 0.0015])  # translation right-from-left, m (x_right = R x_left + T)


def ros_yaml(K, D, R, P, size=(W, H), extra: str = "") -> str:
    """A camera_info YAML as camera_calibration_parsers writes it."""
    def block(name, m):
        m = np.asarray(m, dtype=float)
        rows, cols = (1, m.size) if m.ndim == 1 else m.shape
        data = ", ".join(f"{v:.12g}" for v in m.ravel())
        return f"{name}:\n  rows: {rows}\n  cols: {cols}\n  data: [{data}]\n"
    return (f"image_width: {size[0]}\nimage_height: {size[1]}\ncamera_name: cam\n" + block("camera_matrix", K)
            + "distortion_model: plumb_bob\n" + block("distortion_coefficients", D)
            + block("rectification_matrix", R) + block("projection_matrix", P) + extra)


def write_ros_pair(root: Path, rectified_images: bool = False, **overrides) -> None:
    """left.yaml/right.yaml of the synthetic rig, rectified by OpenCV (as ROS's calibrator does)."""
    R1, R2, P1, P2, *_ = cv2.stereoRectify(K1, D1, K2, D2, (W, H), R_RL, T_RL_M.reshape(3, 1),
                                           flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0)
    left = dict(K=K1, D=D1, R=R1, P=P1)
    right = dict(K=K2, D=D2, R=R2, P=P2)
    if rectified_images:  # camera_info of already-rectified images: no distortion, identity R
        left = dict(K=P1[:, :3], D=np.zeros(5), R=np.eye(3), P=P1)
        right = dict(K=P2[:, :3], D=np.zeros(5), R=np.eye(3), P=P2)
    left.update(overrides.get("left", {}))
    right.update(overrides.get("right", {}))
    root.mkdir(parents=True, exist_ok=True)
    (root / "left.yaml").write_text(ros_yaml(**left, size=overrides.get("left_size", (W, H))))
    (root / "right.yaml").write_text(ros_yaml(**right, size=overrides.get("right_size", (W, H))))


def write_opencv(path: Path, **entries) -> None:
    """An OpenCV FileStorage file with the given matrices / numbers / strings."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for name, value in entries.items():
        if isinstance(value, str):
            fs.write(name, value)
        elif np.ndim(value) == 0:
            fs.write(name, float(value) if isinstance(value, float) else int(value))
        else:
            fs.write(name, np.asarray(value, dtype=np.float64))
    fs.release()


def blob(u: float, v: float, sigma: float = 1.5) -> np.ndarray:
    """(H, W, 3) uint8 image of one Gaussian dot centred at (u, v) px."""
    yy, xx = np.mgrid[0:H, 0:W]
    grey = 255 * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma**2))
    return np.repeat(np.rint(grey).astype(np.uint8)[:, :, None], 3, axis=2)


def centroid(image: np.ndarray) -> tuple[float, float]:
    grey = image[:, :, 0].astype(np.float64)
    grey[grey < 8] = 0
    yy, xx = np.mgrid[0:grey.shape[0], 0:grey.shape[1]]
    return float((grey * xx).sum() / grey.sum()), float((grey * yy).sum() / grey.sum())


def check_rectification_geometry(stereo) -> None:
    """Render dots of known 3D points into the raw pair (cv2.projectPoints, with distortion), rectify
    them with the calibration's maps and triangulate with its K and baseline: the rows must agree
    and the distances from the left camera centre must be the true ones (rectification only rotates)."""
    rect, cal = stereo.rectification, stereo.calibration
    assert rect is not None
    points = np.array(
        [[0.0, 0.0, 0.6], [0.05, -0.03, 0.5], [-0.06, 0.04, 0.8], [0.03, 0.05, 0.7], [-0.04, -0.05, 0.55]]
    )
    rvec = cv2.Rodrigues(R_RL)[0]
    left_px = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K1, D1)[0].reshape(-1, 2)
    right_px = cv2.projectPoints(points, rvec, T_RL_M, K2, D2)[0].reshape(-1, 2)
    for point, (ul, vl), (ur, vr) in zip(points, left_px, right_px):
        xl, yl = centroid(rect.apply("left", blob(ul, vl)))
        xr, yr = centroid(rect.apply("right", blob(ur, vr)))
        assert abs(yl - yr) < 0.15, f"rows differ: {yl:.3f} vs {yr:.3f}"
        z = cal.fx * cal.baseline_m / (xl - xr + cal.disparity_offset_px)
        x = (xl - cal.cx) * z / cal.fx
        y = (yl - cal.cy) * z / cal.fy
        assert np.linalg.norm([x, y, z]) == pytest.approx(np.linalg.norm(point), rel=0.01)
    assert cal.baseline_m == pytest.approx(np.linalg.norm(T_RL_M), rel=1e-9)


def test_rectification_apply_worked_example():
    # Maps that read each output pixel from one column to the left: a shift right by 1 px.
    map_x = np.tile(np.arange(5, dtype=np.float32) - 1, (4, 1))
    map_y = np.tile(np.arange(4, dtype=np.float32)[:, None], (1, 5))
    rect = Rectification((4, 5), map_x, map_y, map_x + 0.5, map_y)
    depth = np.arange(20, dtype=np.float32).reshape(4, 5)
    depth[1, 1] = np.nan
    out = rect.apply("left", depth, nearest=True)
    expected = np.full((4, 5), np.nan, np.float32)  # column 0 reads outside the image: NaN
    expected[:, 1:] = depth[:, :4]
    np.testing.assert_array_equal(out, expected)
    mask = depth > 7
    out_mask = rect.apply("left", mask, nearest=True)
    assert out_mask.dtype == bool
    np.testing.assert_array_equal(out_mask[:, 1:], mask[:, :4])
    assert not out_mask[:, 0].any()
    # Bilinear on the right map (half a pixel): the mean of two neighbours.
    grey = np.tile(np.array([0, 10, 20, 30, 40], np.uint8), (4, 1))
    np.testing.assert_array_equal(rect.apply("right", grey)[:, 1:], np.tile([5, 15, 25, 35], (4, 1)))
    with pytest.raises(ValueError, match="4x5"):
        rect.apply("left", np.zeros((3, 5)))


# ------------------------------------------------------------------------------------------
# K.txt
# ------------------------------------------------------------------------------------------


def test_k_txt_and_lookup_order(tmp_path):
    (tmp_path / "K.txt").write_text("300 0 16.5 0 310 12.25 0 0 1\n0.0045\n")
    write_ros_pair(tmp_path)  # K.txt wins over the YAML pair
    stereo = read_calibration(tmp_path, (24, 32))
    assert stereo.kind == "K.txt" and stereo.rectification is None and stereo.files == (tmp_path / "K.txt",)
    np.testing.assert_array_equal(stereo.calibration.K, [[300, 0, 16.5], [0, 310, 12.25], [0, 0, 1]])
    assert stereo.calibration.baseline_m == 0.0045 and stereo.calibration.disparity_offset_px == 0.0
    assert not stereo.calibration.K.flags.writeable
    assert read_k_txt(tmp_path / "K.txt").fx == 300.0
    (tmp_path / "K.txt").unlink()
    assert read_calibration(tmp_path, (H, W)).kind == "ros"


def test_k_txt_not_upper_triangular(tmp_path):
    (tmp_path / "K.txt").write_text("300 0 16.5 2 310 12.25 0 0 1\n0.0045\n")
    with pytest.raises(SessionError, match=r"K.txt.*upper-triangular"):
        read_calibration(tmp_path)


def test_k_txt_for_another_resolution(tmp_path):
    (tmp_path / "K.txt").write_text("1000 0 960 0 1000 540 0 0 1\n0.005\n")
    with pytest.raises(SessionError, match=r"K.txt.*image size mismatch.*principal point"):
        read_calibration(tmp_path, (540, 640))
    assert read_calibration(tmp_path, (1080, 1920)).calibration.cx == 960


# ------------------------------------------------------------------------------------------
# ROS camera_info
# ------------------------------------------------------------------------------------------


def test_ros_rectified_images(tmp_path):
    write_ros_pair(tmp_path, rectified_images=True)
    stereo = read_calibration(tmp_path, (H, W))
    assert stereo.kind == "ros" and stereo.rectification is None and stereo.image_size == (H, W)
    _, _, P1, P2, *_ = cv2.stereoRectify(K1, D1, K2, D2, (W, H), R_RL, T_RL_M.reshape(3, 1),
                                         flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0)
    np.testing.assert_allclose(stereo.calibration.K, P1[:, :3], rtol=1e-10)
    # Tx = -fx * B: B = -P2[0, 3] / P2[0, 0] = |T| for a zero-disparity rectification.
    assert stereo.calibration.baseline_m == pytest.approx(np.linalg.norm(T_RL_M), rel=1e-9)
    assert stereo.calibration.disparity_offset_px == pytest.approx(0.0, abs=1e-9)


def test_ros_raw_images_are_rectified(tmp_path):
    write_ros_pair(tmp_path)
    stereo = read_ros_camera_info(tmp_path / "left.yaml", tmp_path / "right.yaml", (H, W))
    check_rectification_geometry(stereo)
    # rectified: 1 says the images are already rectified despite the distortion.
    write_ros_pair(tmp_path)
    text = (tmp_path / "left.yaml").read_text() + "rectified: 1\n"
    (tmp_path / "left.yaml").write_text(text)
    assert read_calibration(tmp_path, (H, W)).rectification is None


def test_ros_principal_point_offset(tmp_path):
    # Middlebury-style rectified cameras whose principal points differ by doffs = 31.086 px.
    fx, cx, cy, doffs, baseline = 994.978, 311.193, 254.877, 31.086, 0.193001
    K = np.array([[fx, 0, cx], [0, fx, cy], [0, 0, 1]])
    P_left = np.hstack([K, np.zeros((3, 1))])
    P_right = np.array([[fx, 0, cx + doffs, -fx * baseline], [0, fx, cy, 0], [0, 0, 1, 0]])
    (tmp_path / "left.yaml").write_text(ros_yaml(K, np.zeros(5), np.eye(3), P_left, size=(741, 500)))
    (tmp_path / "right.yaml").write_text(ros_yaml(K, np.zeros(5), np.eye(3), P_right, size=(741, 500)))
    cal = read_calibration(tmp_path, (500, 741)).calibration
    assert cal.baseline_m == pytest.approx(baseline, rel=1e-9)
    assert cal.disparity_offset_px == pytest.approx(doffs, rel=1e-9)


def _ros_case(name: str):
    R1, R2, P1, P2, *_ = cv2.stereoRectify(K1, D1, K2, D2, (W, H), R_RL, T_RL_M.reshape(3, 1),
                                           flags=cv2.CALIB_ZERO_DISPARITY, alpha=0.0)
    zero_tx = P2.copy()
    zero_tx[0, 3] = 0
    bad_k = K1.copy()
    bad_k[2, 0] = 0.5
    other_fy = P2.copy()
    other_fy[1, 1] += 3
    swapped = P2.copy()
    swapped[0, 3] = -swapped[0, 3]
    return {
        "zero_baseline": ({"right": {"P": zero_tx}}, ["right.yaml", "baseline of zero"]),
        "swapped": ({"right": {"P": swapped}}, ["right.yaml", "swapped"]),
        "not_upper_triangular": ({"left": {"K": bad_k}}, ["left.yaml", "camera_matrix", "upper-triangular"]),
        "inconsistent_fy": ({"right": {"P": other_fy}}, ["right.yaml", "inconsistent", "fy"]),
        "size_mismatch": ({"left_size": (320, 240), "right_size": (320, 240)},
                          ["left.yaml", "image size mismatch", "320x240", "160x120"]),
        "sizes_differ": ({"right_size": (320, 240)}, ["right.yaml", "same image size"]),
    }[name]


@pytest.mark.parametrize(
    "case", ["zero_baseline", "swapped", "not_upper_triangular", "inconsistent_fy", "size_mismatch", "sizes_differ"]
)
def test_ros_errors(tmp_path, case):
    overrides, expected = _ros_case(case)
    write_ros_pair(tmp_path, **overrides)
    with pytest.raises(SessionError) as info:
        read_calibration(tmp_path, (H, W))
    for part in expected:
        assert part in str(info.value), f"{part!r} not in {info.value}"


def test_ros_needs_both_files_and_valid_yaml(tmp_path):
    write_ros_pair(tmp_path)
    (tmp_path / "right.yaml").unlink()
    with pytest.raises(SessionError, match=r"right.yaml.*both left.yaml and right.yaml"):
        read_calibration(tmp_path, (H, W))
    (tmp_path / "right.yaml").write_text("camera_matrix: [1, 2\n  oops: {")
    with pytest.raises(SessionError, match=r"right.yaml.*(could not parse|camera_matrix)"):
        read_calibration(tmp_path, (H, W))


# ------------------------------------------------------------------------------------------
# OpenCV FileStorage
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["stereo.yaml", "calibration.xml"])
def test_opencv_raw_calibration_is_rectified(tmp_path, name):
    write_opencv(tmp_path / name, K1=K1, D1=D1, K2=K2, D2=D2, R=R_RL, T=T_RL_M, image_width=W, image_height=H)
    stereo = read_calibration(tmp_path, (H, W))
    assert stereo.kind == "opencv" and stereo.files == (tmp_path / name,)
    check_rectification_geometry(stereo)


def test_opencv_millimetres_and_aliases(tmp_path):
    # M1/M2 (stereo_calib.cpp's names), T in mm, image size from the left images.
    write_opencv(tmp_path / "stereo.yml", M1=K1, D1=D1, M2=K2, D2=D2, R=R_RL, T=T_RL_M * 1000,
                 translation_unit="mm")
    stereo = read_calibration(tmp_path, (H, W))
    assert stereo.calibration.baseline_m == pytest.approx(np.linalg.norm(T_RL_M), rel=1e-9)
    check_rectification_geometry(stereo)
    # The same file without the unit reads T as metres: a 50 m baseline is refused.
    write_opencv(tmp_path / "stereo.yml", M1=K1, D1=D1, M2=K2, D2=D2, R=R_RL, T=T_RL_M * 1000)
    with pytest.raises(SessionError, match=r"stereo.yml.*below 1.0 m.*millimetres"):
        read_calibration(tmp_path, (H, W))


def test_opencv_rectified_projections(tmp_path):
    fx, baseline = 500.0, 0.0042
    P1 = np.array([[fx, 0, 80, 0], [0, fx, 60, 0], [0, 0, 1, 0]])
    P2 = np.array([[fx, 0, 84, -fx * baseline], [0, fx, 60, 0], [0, 0, 1, 0]])
    write_opencv(tmp_path / "stereo.yaml", K1=K1, K2=K2, R=R_RL, T=T_RL_M, P1=P1, P2=P2, rectified=1)
    stereo = read_opencv_stereo(tmp_path / "stereo.yaml", (H, W))
    assert stereo.rectification is None
    np.testing.assert_allclose(stereo.calibration.K, P1[:, :3])
    assert stereo.calibration.baseline_m == pytest.approx(baseline)
    assert stereo.calibration.disparity_offset_px == pytest.approx(4.0)


@pytest.mark.parametrize(
    "entries, expected",
    [
        ({"K1": K1, "D1": D1, "K2": K2, "D2": D2, "R": R_RL, "T": np.zeros(3), "image_width": W, "image_height": H},
         ["positive stereo baseline"]),
        ({"K1": np.array([[150.0, 0, 82], [3, 152, 58], [0, 0, 1]]), "K2": K2, "R": R_RL, "T": T_RL_M},
         ["K1", "upper-triangular"]),
        ({"K1": K1, "K2": K2, "R": R_RL, "T": T_RL_M, "image_width": 640, "image_height": 480},
         ["image size mismatch", "640x480", "160x120"]),
        ({"K1": K1, "K2": K2, "R": R_RL, "T": -T_RL_M, "image_width": W, "image_height": H}, ["swapped"]),
        ({"K1": K1, "K2": K2, "R": R_RL * 2, "T": T_RL_M}, ["rotation matrix"]),
        ({"K1": K1, "K2": K2}, ["R and T", "P1 and P2"]),
        ({"K2": K2, "R": R_RL, "T": T_RL_M}, ["missing", "K1"]),
        ({"K1": K1, "K2": K2, "R": R_RL, "T": T_RL_M, "translation_unit": "inch"}, ["translation_unit", "inch"]),
    ],
    ids=["zero_T", "K_lower", "size", "swapped", "not_rotation", "no_extrinsics", "no_K1", "unit"],
)
def test_opencv_errors(tmp_path, entries, expected):
    write_opencv(tmp_path / "calibration.yaml", **entries)
    with pytest.raises(SessionError) as info:
        read_calibration(tmp_path, (H, W))
    message = str(info.value)
    assert "calibration.yaml" in message
    for part in expected:
        assert part in message, f"{part!r} not in {message!r}"


def test_no_calibration_lists_the_accepted_files(tmp_path):
    with pytest.raises(SessionError) as info:
        read_calibration(tmp_path)
    message = str(info.value)
    for part in ("K.txt", "left.yaml", "right.yaml", "stereo.yaml", "calibration.xml"):
        assert part in message


# ------------------------------------------------------------------------------------------
# R that is a rotation only to about 1e-3, as in published calibrations
# ------------------------------------------------------------------------------------------

# A symmetric perturbation: R = Q (I + E) with E symmetric and I + E positive definite has the polar
# decomposition Q (I + E), so its nearest rotation is exactly Q (worked example, no SVD needed).
S_UNIT = np.array([[1.0, 0.5, -0.3], [0.5, -0.8, 0.2], [-0.3, 0.2, 0.4]])  # symmetric, largest entry 1


def perturbed(Q: np.ndarray, size: float) -> np.ndarray:
    return Q @ (np.eye(3) + size * S_UNIT)


def read_warnings(read, *args):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = read(*args)
    return result, [w for w in caught if issubclass(w.category, SessionWarning)]


def test_nearest_rotation_worked_example():
    from scipy.linalg import polar
    from scipy.spatial.transform import Rotation

    R = perturbed(R_RL, 4e-4)
    Q, deviation = rotation_deviation(R)
    np.testing.assert_allclose(Q, R_RL, atol=1e-12)  # the worked example's answer
    np.testing.assert_allclose(Q, polar(R)[0], atol=1e-12)  # SciPy's polar factor
    np.testing.assert_allclose(Q, Rotation.from_matrix(R).as_matrix(), atol=1e-9)  # SciPy's nearest rotation
    assert deviation == pytest.approx(np.abs(R - R_RL).max(), rel=1e-9)
    assert rotation_deviation(-R_RL)[0] is None  # det -1: a reflection, no rotation near it


def test_opencv_near_rotation_is_replaced_with_one_warning(tmp_path):
    R = perturbed(R_RL, 8e-4)
    deviation = np.abs(R - R_RL).max()
    assert 1e-6 < deviation < 1e-3
    write_opencv(tmp_path / "calibration.xml", K1=K1, D1=D1, K2=K2, D2=D2, R=R, T=T_RL_M * 1000,
                 translation_unit="mm", image_width=W, image_height=H)
    stereo, warned = read_warnings(read_calibration, tmp_path, (H, W))
    assert len(warned) == 1, [str(w.message) for w in warned]
    message = str(warned[0].message)
    assert message.startswith(f"{tmp_path / 'calibration.xml'}: 'R' is not exactly a rotation")
    assert f"{deviation:.2g}" in message and "nearest rotation is used" in message
    check_rectification_geometry(stereo)  # rectified as with R_RL itself
    exact_dir = tmp_path / "exact"
    exact_dir.mkdir()
    write_opencv(exact_dir / "calibration.xml", K1=K1, D1=D1, K2=K2, D2=D2, R=R_RL, T=T_RL_M * 1000,
                 translation_unit="mm", image_width=W, image_height=H)
    exact, none = read_warnings(read_calibration, exact_dir, (H, W))
    assert none == []  # a rotation to the last digits: no warning
    np.testing.assert_allclose(stereo.rectification.left_y, exact.rectification.left_y, atol=1e-3)
    np.testing.assert_allclose(stereo.calibration.K, exact.calibration.K, atol=1e-9)


def test_opencv_beyond_the_tolerance_is_refused(tmp_path):
    R = perturbed(R_RL, 3e-3)
    write_opencv(tmp_path / "calibration.xml", K1=K1, D1=D1, K2=K2, D2=D2, R=R, T=T_RL_M, image_width=W,
                 image_height=H)
    with pytest.raises(SessionError, match=r"calibration.xml: expected 'R' to be a rotation matrix \(within 0.001"):
        read_calibration(tmp_path, (H, W))


def published_like_R() -> tuple[np.ndarray, np.ndarray]:
    """(R, its nearest rotation Q): an R like a published da Vinci calibration's, a small rotation times a
    symmetric stretch of singular values 1 + 9.3e-4, 1, 1 - 1.0e-3 (det 0.99993, R R^T off the identity by
    about 1.9e-3, its entries within 9.6e-4 of Q's)."""
    Q = cv2.Rodrigues(np.array([-0.00178, -0.00096, 0.00014]))[0]
    V = cv2.Rodrigues(np.array([0.0, np.pi / 4, 0.0]))[0]  # stretched along (1, 0, 1) and (1, 0, -1)
    return Q @ V @ np.diag([1 + 9.3e-4, 1.0, 1 - 1.0e-3]) @ V.T, Q


def test_a_published_calibration_loads_with_one_warning(tmp_path):
    """The names and units of a published 1080p da Vinci calibration (M_l, D_l, ..., T in mm)."""
    R, Q = published_like_R()
    assert 1.5e-3 < np.abs(R @ R.T - np.eye(3)).max() < 2.5e-3 and abs(np.linalg.det(R) - 0.99993) < 2e-5
    assert 9e-4 < np.abs(R - Q).max() < 1e-3  # within the tolerance, as the published file's 9.6e-4
    M_l = np.array([[1103.4, 0.0, 921.7], [0.0, 1101.5, 545.8], [0.0, 0.0, 1.0]])
    M_r = np.array([[1102.8, 0.0, 1018.5], [0.0, 1100.5, 544.7], [0.0, 0.0, 1.0]])
    write_opencv(tmp_path / "calibration.xml", M_l=M_l, M_r=M_r, D_l=np.array([-0.031, 0.18, -0.0014, -0.001, -0.3]),
                 D_r=np.array([-0.027, 0.11, -0.0011, -0.0008, -0.28]), R=R, T=np.array([-4.108, -0.144, 0.0093]),
                 translation_unit="mm")
    stereo, warned = read_warnings(read_calibration, tmp_path, (1080, 1920))
    assert len(warned) == 1 and "not exactly a rotation" in str(warned[0].message)
    assert stereo.rectification is not None and stereo.calibration.baseline_m == pytest.approx(0.004111, rel=1e-3)


REAL_CALIBRATION = Path("/tmp/dv/CalibrationParameters.xml")  # a published calibration, on this machine only


@pytest.mark.skipif(not REAL_CALIBRATION.is_file(), reason="the published da Vinci calibration is not here")
def test_the_real_published_calibration_loads_with_one_warning(tmp_path):
    # as published, but its T is in mm: the one line a user adds
    text = REAL_CALIBRATION.read_text().replace("</opencv_storage>", "<translation_unit>mm</translation_unit>\n"
                                                                       "</opencv_storage>")
    (tmp_path / "calibration.xml").write_text(text)
    stereo, warned = read_warnings(read_calibration, tmp_path, (1080, 1920))
    assert len(warned) == 1 and "not exactly a rotation" in str(warned[0].message), warned
    assert stereo.calibration.baseline_m == pytest.approx(0.00411, rel=1e-3)
