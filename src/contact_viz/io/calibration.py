"""Stereo calibration of a session: which file it comes from, what it says, and rectification.

A session holds exactly one of these (looked up in this order; the first found is used):

``K.txt``
    FoundationStereo's format: line 1 = the 9 numbers of the rectified left camera's 3x3 K (px),
    row-major; line 2 = the stereo baseline (m). The images are rectified.
``left.yaml`` + ``right.yaml``
    ROS ``camera_info`` YAML (camera_calibration_parsers): ``image_width``, ``image_height``,
    ``camera_matrix``, ``distortion_coefficients``, ``rectification_matrix`` and
    ``projection_matrix`` (``rows``, ``cols``, ``data``). The rectified left camera is the left
    projection matrix; the baseline comes from the right one, whose Tx = -fx * B (B in metres).
    The images are taken as raw (and rectified on load) unless the distortion is zero and the
    rectification matrix the identity, or either file has ``rectified: 1``.
``stereo.yaml|yml|xml`` or ``calibration.yaml|yml|xml``
    An OpenCV FileStorage stereo calibration (what ``cv2.stereoCalibrate`` gives):
    ``K1``/``M1``/``M_l``/``cameraMatrix1``, ``D1``/``D_l``/``distCoeffs1``, the same with 2 (``_r``),
    ``R`` and ``T`` (right camera from left: x_right = R x_left + T), optional ``P1`` and ``P2`` (rectified
    3x4 projections), ``image_width`` and ``image_height`` (or ``image_size`` = [w, h]),
    ``translation_unit`` (``m`` default, ``cm`` or ``mm``) and ``rectified`` (0/1). With
    ``rectified: 1`` (or no R and T) the images are taken as rectified and P1/P2 (else K1 and
    |T|) give K and the baseline; otherwise they are rectified on load with ``cv2.stereoRectify``
    (zero-disparity principal points, no black border) and ``cv2.initUndistortRectifyMap``.
    Published calibrations often hold an R that is a rotation only to about 1e-3 (printed with few
    digits, or estimated without the constraint): an R whose entries all lie within
    ``ROTATION_TOLERANCE`` of the nearest rotation's is replaced by that rotation (the SVD polar
    factor U V^T), with one warning naming the file and the deviation; a farther one is refused.

Anything wrong (zero or negative baseline, a camera matrix that is not upper-triangular
[fx s cx; 0 fy cy; 0 0 1], a calibration for another image size, left and right rectified
cameras that disagree) is one :class:`SessionError` naming the file.
"""

from __future__ import annotations

import math
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from contact_viz.errors import SessionError, SessionWarning

__all__ = [
    "CALIBRATION_FILES",
    "Calibration",
    "Rectification",
    "StereoCalibration",
    "calibration_files",
    "read_calibration",
    "read_k_txt",
    "read_opencv_stereo",
    "read_ros_camera_info",
    "rotation_deviation",
]

# Calibration file names, in lookup order (a pair for ROS camera_info).
OPENCV_NAMES = ("stereo.yaml", "stereo.yml", "stereo.xml", "calibration.yaml", "calibration.yml", "calibration.xml")
CALIBRATION_FILES = ("K.txt", "left.yaml", "right.yaml") + OPENCV_NAMES
MAX_BASELINE_M = 1.0  # longest plausible stereo baseline, m (longer usually means T was in mm)
RECTIFY_ALPHA = 0.0  # cv2.stereoRectify alpha: 0 keeps only valid pixels (no black border)
_REL_TOL = 1e-6  # relative tolerance when comparing calibration numbers that must be equal
_UNIT_TO_M = {"m": 1.0, "cm": 0.01, "mm": 0.001}  # OpenCV translation units, metres per unit
_TRUE = ("1", "true", "yes", "on")  # spellings of a true ``rectified`` flag
# R's deviation from a rotation = the largest |R - Q| entry, Q the nearest rotation (rotation_deviation):
ROTATION_EXACT = 1e-6  # at most this: R is taken as it is (a rotation written with float32 digits), -
ROTATION_TOLERANCE = 1e-3  # at most this: replaced by Q with one warning (published files: ~1e-3); beyond: refused, -


# --------------------------------------------------------------------------------------------
# Data types
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Calibration:
    """Rectified left camera intrinsics and stereo baseline."""

    K: np.ndarray  # (3, 3) float64 camera matrix of the rectified left camera, px
    baseline_m: float  # stereo baseline, m
    disparity_offset_px: float = 0.0  # cx_right - cx_left of the rectified cameras, px (depth = fx*B/(d+offset))

    @property
    def fx(self) -> float:
        """Focal length along x, px."""
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        """Focal length along y, px."""
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        """Principal point x, px."""
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        """Principal point y, px."""
        return float(self.K[1, 2])


@dataclass(frozen=True, eq=False)
class Rectification:
    """Pixel maps from the raw left/right images to the rectified ones (same size as the raw).

    Maps are (H, W) float32 source coordinates for ``cv2.remap``, px.
    """

    image_size: tuple[int, int]  # (height, width) of the raw and rectified images, px
    left_x: np.ndarray  # (H, W) float32 raw left x for each rectified left pixel, px
    left_y: np.ndarray  # (H, W) float32 raw left y, px
    right_x: np.ndarray  # (H, W) float32 raw right x for each rectified right pixel, px
    right_y: np.ndarray  # (H, W) float32 raw right y, px

    def apply(self, side: str, image: np.ndarray, nearest: bool = False) -> np.ndarray:
        """Rectify a raw ``side`` ("left"/"right") image (H, W[, C]); same dtype out.

        ``nearest`` for label-like data (masks, depth); bool images stay bool. Pixels that map
        outside the raw image become 0 (False for bool, NaN for float).
        """
        if side not in ("left", "right"):
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        if image.shape[:2] != self.image_size:
            raise ValueError(
                f"expected an image of {self.image_size[0]}x{self.image_size[1]} px to rectify, "
                f"found {image.shape[0]}x{image.shape[1]}"
            )
        map_x, map_y = (self.left_x, self.left_y) if side == "left" else (self.right_x, self.right_y)
        interpolation = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
        if image.dtype == bool:
            out = cv2.remap(image.view(np.uint8), map_x, map_y, cv2.INTER_NEAREST,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            return out.astype(bool)
        border = float("nan") if image.dtype.kind == "f" else 0
        return cv2.remap(image, map_x, map_y, interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=border)


@dataclass(frozen=True, eq=False)
class StereoCalibration:
    """What a session's calibration file(s) say, and how to rectify its images if needed."""

    calibration: Calibration  # rectified left K (px) and baseline (m)
    files: tuple[Path, ...]  # the file(s) read
    kind: str  # "K.txt", "ros" or "opencv"
    image_size: tuple[int, int] | None  # (height, width) px the calibration declares; None if it does not
    rectification: Rectification | None  # None when the images are already rectified

    def describe(self) -> str:
        """One line for logs: the files, and whether images are rectified on load."""
        names = " + ".join(p.name for p in self.files)
        state = "images rectified on load" if self.rectification is not None else "images already rectified"
        return f"calibration from {names} ({state})"


# --------------------------------------------------------------------------------------------
# Validation shared by all formats
# --------------------------------------------------------------------------------------------


def _check_camera_matrix(path: Path, K: np.ndarray, what: str) -> None:
    """K must be finite, [fx s cx; 0 fy cy; 0 0 1] with fx, fy > 0 (upper-triangular)."""
    ok = (
        K.shape == (3, 3)
        and bool(np.all(np.isfinite(K)))
        and K[0, 0] > 0
        and K[1, 1] > 0
        and K[1, 0] == 0
        and np.array_equal(K[2], [0.0, 0.0, 1.0])
    )
    if not ok:
        shown = np.array2string(np.asarray(K, dtype=np.float64).ravel(), separator=" ", max_line_width=200)
        raise SessionError(
            path, f"expected {what} to be a camera matrix [fx s cx; 0 fy cy; 0 0 1] (upper-triangular) with "
            f"fx, fy > 0, found {shown}"
        )


def _check_baseline(path: Path, baseline_m: float, how: str) -> None:
    if not math.isfinite(baseline_m) or baseline_m <= 0:
        raise SessionError(path, f"expected a positive stereo baseline, found {baseline_m!r} m ({how})")
    if baseline_m > MAX_BASELINE_M:
        raise SessionError(
            path, f"expected a stereo baseline below {MAX_BASELINE_M} m, found {baseline_m:g} m ({how}); "
            "was the translation written in millimetres?"
        )


def _check_image_size(path: Path, declared: tuple[int, int] | None, actual: tuple[int, int] | None) -> None:
    if declared is not None and actual is not None and tuple(declared) != tuple(actual):
        raise SessionError(
            path, f"image size mismatch: the calibration is for {declared[1]}x{declared[0]} px (width x height), "
            f"the left images are {actual[1]}x{actual[0]} px"
        )


def _check_principal_point(path: Path, K: np.ndarray, image_size: tuple[int, int] | None) -> None:
    """The principal point must lie inside the image (else K is for another resolution)."""
    if image_size is None:
        return
    height, width = image_size
    if not (0 <= K[0, 2] <= width and 0 <= K[1, 2] <= height):
        raise SessionError(
            path, f"image size mismatch: the principal point ({K[0, 2]:g}, {K[1, 2]:g}) px lies outside the "
            f"{width}x{height} px left images; is the calibration for another resolution?"
        )


def rotation_deviation(R: np.ndarray) -> tuple[np.ndarray | None, float]:
    """(Q, deviation): the rotation nearest the 3x3 ``R`` in the Frobenius norm (the polar factor U V^T of
    R = U S V^T, with det +1) and the largest |R - Q| entry. Q is None when R's determinant is not positive
    (the nearest orthogonal matrix is a reflection: no rotation is near R)."""
    U, _, Vt = np.linalg.svd(R)
    Q = U @ Vt
    if np.linalg.det(R) <= 0 or np.linalg.det(Q) <= 0:
        return None, math.inf
    return Q, float(np.abs(R - Q).max())


def _check_rotation(path: Path, R: np.ndarray) -> np.ndarray:
    """``R`` if it is a rotation (to ROTATION_EXACT), the nearest rotation (with one warning) if it is within
    ROTATION_TOLERANCE of one, else SessionError naming the file."""
    Q, deviation = rotation_deviation(R)
    orthogonality = float(np.abs(R @ R.T - np.eye(3)).max())
    numbers = (f"its entries differ from the nearest rotation's by up to {deviation:.2g}, R R^T from the identity "
               f"by up to {orthogonality:.2g}, det {np.linalg.det(R):.6g}")
    if Q is None or deviation > ROTATION_TOLERANCE:
        raise SessionError(path, f"expected 'R' to be a rotation matrix (within {ROTATION_TOLERANCE:g} of one), found "
                                 f"{R.ravel().tolist()} ({numbers if Q is not None else 'det <= 0: a reflection'})")
    if deviation <= ROTATION_EXACT:
        return R
    warnings.warn(f"{path}: 'R' is not exactly a rotation ({numbers}; tolerated up to {ROTATION_TOLERANCE:g}): "
                  "the nearest rotation is used", SessionWarning, stacklevel=3)
    return Q


def read_only(array: np.ndarray, dtype: np.dtype | type | None = None) -> np.ndarray:
    """A read-only copy of ``array`` (as ``dtype`` when given): what a calibration or a session hands out."""
    out = np.array(array, dtype=dtype)
    out.flags.writeable = False
    return out


# --------------------------------------------------------------------------------------------
# K.txt
# --------------------------------------------------------------------------------------------


def _parse_number_line(line: str) -> list[float]:
    """Numbers on one line, separated by whitespace and/or commas; raises ValueError naming a bad token."""
    tokens = [t for t in re.split(r"[\s,]+", line.strip()) if t]
    return [float(t) for t in tokens]


def read_k_txt(path: str | Path) -> Calibration:
    """Parse a FoundationStereo K.txt: line 1 = row-major 3x3 K (px), line 2 = baseline (m)."""
    path = Path(path)
    if not path.is_file():
        raise SessionError(
            path, "missing: expected the rectified left camera K.txt (line 1: 9 numbers of the 3x3 K in px; "
            "line 2: the stereo baseline in metres)"
        )
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SessionError(path, f"expected a readable text file, could not read it ({exc})") from exc
    lines = text.splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    if len(lines) != 2:
        raise SessionError(
            path, f"expected 2 lines (9 numbers of K, then the baseline in metres), found {len(lines)}"
        )
    try:
        k_values = _parse_number_line(lines[0])
    except ValueError as exc:
        raise SessionError(
            path, f"expected 9 numbers on line 1 (row-major 3x3 K in px), found {lines[0].strip()!r}"
        ) from exc
    if len(k_values) != 9:
        raise SessionError(path, f"expected 9 numbers on line 1, found {len(k_values)} (row-major 3x3 K in px)")
    K = np.asarray(k_values, dtype=np.float64).reshape(3, 3)
    _check_camera_matrix(path, K, "line 1")
    try:
        b_values = _parse_number_line(lines[1])
    except ValueError as exc:
        raise SessionError(
            path, f"expected one positive number (stereo baseline, m) on line 2, found {lines[1].strip()!r}"
        ) from exc
    if len(b_values) != 1 or not (math.isfinite(b_values[0]) and b_values[0] > 0):
        found = f"{len(b_values)} numbers" if len(b_values) != 1 else f"{b_values[0]!r}"
        raise SessionError(path, f"expected one positive number (stereo baseline, m) on line 2, found {found}")
    _check_baseline(path, b_values[0], "line 2")
    return Calibration(K=read_only(K, np.float64), baseline_m=float(b_values[0]))


# --------------------------------------------------------------------------------------------
# OpenCV FileStorage helpers (also used for ROS YAML, which OpenCV parses given a header)
# --------------------------------------------------------------------------------------------


def _open_storage(path: Path, what: str) -> cv2.FileStorage:
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SessionError(path, f"expected a readable {what}, could not read it ({exc})") from exc
    if path.suffix.lower() in (".yaml", ".yml") and not text.lstrip().startswith("%YAML"):
        text = "%YAML:1.0\n" + text  # OpenCV's YAML reader needs the directive; ROS files lack it
    try:
        storage = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError) as exc:  # the bindings report some parse errors as SystemError
        cause = exc.__cause__ if isinstance(exc, SystemError) and exc.__cause__ is not None else exc
        detail = str(cause).strip().splitlines()[-1] if str(cause).strip() else type(cause).__name__
        raise SessionError(path, f"expected a {what}, could not parse it ({detail})") from exc
    if not storage.isOpened():
        raise SessionError(path, f"expected a {what}, could not parse it")
    return storage


def _node(storage: cv2.FileStorage, names: tuple[str, ...]):
    """The first present node among ``names`` and its name, else (None, names[0])."""
    for name in names:
        node = storage.getNode(name)
        if not node.isNone():
            return node, name
    return None, names[0]


def _numbers(path: Path, node, name: str) -> np.ndarray:
    """A node holding a matrix (OpenCV !!opencv-matrix, or ROS {rows, cols, data}, or a sequence)."""
    if node.isMap() and not node.getNode("data").isNone() and node.getNode("dt").isNone():
        rows, cols, data = node.getNode("rows"), node.getNode("cols"), node.getNode("data")
        values = np.array([data.at(i).real() for i in range(data.size())], dtype=np.float64)
        if rows.isNone() or cols.isNone() or int(rows.real()) * int(cols.real()) != values.size:
            raise SessionError(path, f"expected {name!r} to have rows x cols numbers in data, found {values.size}")
        return values.reshape(int(rows.real()), int(cols.real()))
    if node.isSeq():
        return np.array([node.at(i).real() for i in range(node.size())], dtype=np.float64)
    mat = node.mat()
    if mat is None:
        raise SessionError(path, f"expected {name!r} to be a matrix, could not read it")
    return np.asarray(mat, dtype=np.float64)


def _matrix(path: Path, storage, names: tuple[str, ...], shape: tuple[int, int] | None, required: bool = True):
    node, name = _node(storage, names)
    if node is None:
        if required:
            raise SessionError(path, f"missing: expected {' or '.join(repr(n) for n in names)}")
        return None
    values = _numbers(path, node, name)
    if shape is not None:
        if values.size != shape[0] * shape[1]:
            raise SessionError(
                path, f"expected {name!r} to be a {shape[0]}x{shape[1]} matrix, found {values.size} numbers"
            )
        values = values.reshape(shape)
    if not np.all(np.isfinite(values)):
        raise SessionError(path, f"expected finite numbers in {name!r}, found {values.ravel().tolist()}")
    return values


def _flag(storage, name: str) -> bool:
    node = storage.getNode(name)
    if node.isNone():
        return False
    if node.isString():
        return node.string().strip().lower() in _TRUE
    return bool(node.real())


def _declared_size(path: Path, storage) -> tuple[int, int] | None:
    """(height, width) from image_width/image_height or image_size/imageSize [w, h]; None if absent."""
    width, height = storage.getNode("image_width"), storage.getNode("image_height")
    if not width.isNone() and not height.isNone():
        size = (int(height.real()), int(width.real()))
    else:
        node, name = _node(storage, ("image_size", "imageSize"))
        if node is None:
            return None
        values = _numbers(path, node, name).ravel()
        if values.size != 2:
            raise SessionError(path, f"expected {name!r} to be [width, height] in px, found {values.tolist()}")
        size = (int(values[1]), int(values[0]))
    if size[0] <= 0 or size[1] <= 0:
        raise SessionError(path, f"expected a positive image size, found {size[1]}x{size[0]} px")
    return size


def _close(a: float, b: float) -> bool:
    return abs(a - b) <= _REL_TOL * max(1.0, abs(a), abs(b))


def _maps(K: np.ndarray, D: np.ndarray, R: np.ndarray, P: np.ndarray, size: tuple[int, int]):
    height, width = size
    return cv2.initUndistortRectifyMap(K, D, R, P[:, :3], (width, height), cv2.CV_32FC1)


# --------------------------------------------------------------------------------------------
# ROS camera_info YAML
# --------------------------------------------------------------------------------------------


def _ros_camera(path: Path) -> dict:
    storage = _open_storage(path, "ROS camera_info YAML")
    cam = {
        "size": _declared_size(path, storage),
        "K": _matrix(path, storage, ("camera_matrix",), (3, 3)),
        "P": _matrix(path, storage, ("projection_matrix",), (3, 4)),
        "R": _matrix(path, storage, ("rectification_matrix",), (3, 3), required=False),
        "D": _matrix(path, storage, ("distortion_coefficients",), None, required=False),
        "rectified": _flag(storage, "rectified"),
    }
    model = storage.getNode("distortion_model")
    if not model.isNone() and model.string() not in ("plumb_bob", "rational_polynomial", ""):
        raise SessionError(
            path, f"expected distortion_model plumb_bob or rational_polynomial, found {model.string()!r}"
        )
    if cam["R"] is None:
        cam["R"] = np.eye(3)
    cam["D"] = np.zeros(5) if cam["D"] is None else cam["D"].ravel()
    _check_camera_matrix(path, cam["K"], "camera_matrix")
    _check_camera_matrix(path, cam["P"][:, :3], "the left 3x3 block of projection_matrix")
    return cam


def read_ros_camera_info(
    left_path: str | Path, right_path: str | Path, image_size: tuple[int, int] | None = None
) -> StereoCalibration:
    """A stereo calibration from ROS ``camera_info`` YAML files of the left and right cameras.

    ``image_size`` (height, width) px of the left images, checked against the files' size.
    """
    left_path, right_path = Path(left_path), Path(right_path)
    left, right = _ros_camera(left_path), _ros_camera(right_path)
    if left["size"] is None:
        raise SessionError(left_path, "missing: expected image_width and image_height (px)")
    if right["size"] != left["size"]:
        raise SessionError(
            right_path, f"expected the same image size as {left_path.name} "
            f"({left['size'][1]}x{left['size'][0]} px), found {right['size']}"
        )
    _check_image_size(left_path, left["size"], image_size)
    P_left, P_right = left["P"], right["P"]
    if not _close(P_left[0, 3], 0.0):
        raise SessionError(
            left_path, f"expected Tx = 0 in the left projection_matrix (the left camera is the reference), "
            f"found {P_left[0, 3]:g}; are left.yaml and right.yaml swapped?"
        )
    for (r, c), name in (((0, 0), "fx"), ((1, 1), "fy"), ((1, 2), "cy")):
        if not _close(P_left[r, c], P_right[r, c]):
            raise SessionError(
                right_path, f"inconsistent calibration: the rectified right camera's {name} ({P_right[r, c]:g}) "
                f"differs from the left one's ({P_left[r, c]:g}) in {left_path.name}; both projection matrices "
                "must come from one stereo rectification"
            )
    tx = P_right[0, 3]
    if tx == 0:
        raise SessionError(
            right_path, "expected the right projection_matrix Tx = -fx * baseline, found a baseline of zero"
        )
    if tx > 0:
        raise SessionError(
            right_path, f"expected Tx = -fx * baseline < 0 in the right projection_matrix, found {tx:g}; "
            "are left.yaml and right.yaml swapped?"
        )
    baseline_m = -tx / P_right[0, 0]
    _check_baseline(right_path, baseline_m, "-Tx / fx of the right projection_matrix")
    calibration = Calibration(
        K=read_only(P_left[:, :3], np.float64), baseline_m=float(baseline_m),
        disparity_offset_px=float(P_right[0, 2] - P_left[0, 2]),
    )
    identity = all(np.allclose(c["R"], np.eye(3)) and not np.any(c["D"]) for c in (left, right))
    rectification = None
    if not (identity or left["rectified"] or right["rectified"]):
        lx, ly = _maps(left["K"], left["D"], left["R"], P_left, left["size"])
        rx, ry = _maps(right["K"], right["D"], right["R"], P_right, left["size"])
        rectification = Rectification(left["size"], lx, ly, rx, ry)
    return StereoCalibration(calibration, (left_path, right_path), "ros", left["size"], rectification)


# --------------------------------------------------------------------------------------------
# OpenCV FileStorage stereo calibration
# --------------------------------------------------------------------------------------------


def read_opencv_stereo(path: str | Path, image_size: tuple[int, int] | None = None) -> StereoCalibration:
    """A stereo calibration from an OpenCV FileStorage file (see the module docstring for keys).

    ``image_size`` (height, width) px of the left images: checked against the file's size, and
    used for rectification when the file gives none.
    """
    path = Path(path)
    storage = _open_storage(path, "OpenCV FileStorage stereo calibration (YAML or XML)")
    declared = _declared_size(path, storage)
    _check_image_size(path, declared, image_size)
    size = declared or image_size
    K1 = _matrix(path, storage, ("K1", "M1", "M_l", "cameraMatrix1"), (3, 3))
    K2 = _matrix(path, storage, ("K2", "M2", "M_r", "cameraMatrix2"), (3, 3), required=False)
    _check_camera_matrix(path, K1, "K1")
    if K2 is not None:
        _check_camera_matrix(path, K2, "K2")
    D1 = _matrix(path, storage, ("D1", "D_l", "distCoeffs1"), None, required=False)
    D2 = _matrix(path, storage, ("D2", "D_r", "distCoeffs2"), None, required=False)
    R = _matrix(path, storage, ("R",), (3, 3), required=False)
    T = _matrix(path, storage, ("T",), None, required=False)
    P1 = _matrix(path, storage, ("P1",), (3, 4), required=False)
    P2 = _matrix(path, storage, ("P2",), (3, 4), required=False)
    unit_node = storage.getNode("translation_unit")
    unit = unit_node.string().strip().lower() if not unit_node.isNone() else "m"
    if unit not in _UNIT_TO_M:
        raise SessionError(path, f"expected translation_unit to be one of {sorted(_UNIT_TO_M)}, found {unit!r}")
    metres = _UNIT_TO_M[unit]
    if T is not None and T.size != 3:
        raise SessionError(path, f"expected 'T' to hold 3 numbers (right camera from left), found {T.size}")
    raw = (R is not None and T is not None) and not _flag(storage, "rectified")

    if not raw:  # images already rectified
        if P1 is not None and P2 is not None:
            _check_camera_matrix(path, P1[:, :3], "the left 3x3 block of P1")
            for (r, c), name in (((0, 0), "fx"), ((1, 1), "fy"), ((1, 2), "cy")):
                if not _close(P1[r, c], P2[r, c]):
                    raise SessionError(
                        path, f"inconsistent calibration: P2's {name} ({P2[r, c]:g}) differs from P1's "
                        f"({P1[r, c]:g}); both must come from one stereo rectification"
                    )
            if P2[0, 3] == 0:
                raise SessionError(path, "expected P2[0, 3] = -fx * baseline, found a baseline of zero")
            baseline_m = -P2[0, 3] / P2[0, 0] * metres
            _check_baseline(path, baseline_m, "-P2[0, 3] / P2[0, 0]")
            K, offset = P1[:, :3], P2[0, 2] - P1[0, 2]
        elif T is not None:
            baseline_m = float(np.linalg.norm(T)) * metres
            _check_baseline(path, baseline_m, "|T|")
            K, offset = K1, (K2[0, 2] - K1[0, 2]) if K2 is not None else 0.0
        else:
            raise SessionError(
                path, "missing: expected R and T (raw stereo calibration, rectified on load) or P1 and P2 "
                "(rectified cameras), or K1 with T and rectified: 1"
            )
        _check_principal_point(path, K, size)
        calibration = Calibration(K=read_only(K, np.float64), baseline_m=float(baseline_m),
                                  disparity_offset_px=float(offset))
        return StereoCalibration(calibration, (path,), "opencv", declared, None)

    if K2 is None:
        raise SessionError(path, "missing: expected 'K2' (or 'M2', 'M_r', 'cameraMatrix2') to rectify the right images")
    if size is None:
        raise SessionError(path, "missing: expected image_width and image_height (px) to rectify the images")
    baseline_m = float(np.linalg.norm(T)) * metres
    _check_baseline(path, baseline_m, "|T|")
    R = _check_rotation(path, R)
    D1 = np.zeros(5) if D1 is None else D1.ravel()
    D2 = np.zeros(5) if D2 is None else D2.ravel()
    height, width = size
    try:
        R1, R2, P1r, P2r, _, _, _ = cv2.stereoRectify(
            K1, D1, K2, D2, (width, height), R, T.reshape(3, 1) * metres,
            flags=cv2.CALIB_ZERO_DISPARITY, alpha=RECTIFY_ALPHA,
        )
    except cv2.error as exc:
        raise SessionError(path, f"expected a stereo calibration OpenCV can rectify ({str(exc).strip()})") from exc
    if abs(P2r[1, 3]) > abs(P2r[0, 3]):
        raise SessionError(
            path, "expected a horizontal stereo rig (right camera beside the left one along x); "
            "T is mostly vertical"
        )
    if P2r[0, 3] >= 0:
        raise SessionError(
            path, f"expected the right camera to the right of the left one (T[0] < 0 for x_right = R x_left + T), "
            f"found T = {T.ravel().tolist()}; are the cameras swapped?"
        )
    lx, ly = _maps(K1, D1, R1, P1r, size)
    rx, ry = _maps(K2, D2, R2, P2r, size)
    calibration = Calibration(K=read_only(P1r[:, :3], np.float64), baseline_m=float(-P2r[0, 3] / P2r[0, 0]))
    return StereoCalibration(calibration, (path,), "opencv", declared, Rectification(size, lx, ly, rx, ry))


# --------------------------------------------------------------------------------------------
# Lookup
# --------------------------------------------------------------------------------------------


def calibration_files(root: str | Path) -> list[Path]:
    """The calibration files present in session ``root`` (any of CALIBRATION_FILES), sorted by name."""
    root = Path(root)
    return sorted(root / name for name in CALIBRATION_FILES if (root / name).is_file())


def read_calibration(root: str | Path, image_size: tuple[int, int] | None = None) -> StereoCalibration:
    """The calibration of session ``root``: K.txt, else left.yaml + right.yaml, else an OpenCV file.

    ``image_size`` (height, width) px of the left images; a calibration made for another size is
    an error. Raises SessionError when none is found or the one found is wrong.
    """
    root = Path(root)
    k_txt = root / "K.txt"
    if k_txt.is_file():
        calibration = read_k_txt(k_txt)
        _check_principal_point(k_txt, calibration.K, image_size)
        return StereoCalibration(calibration, (k_txt,), "K.txt", None, None)
    left, right = root / "left.yaml", root / "right.yaml"
    if left.is_file() or right.is_file():
        if not (left.is_file() and right.is_file()):
            present, absent = (left, right) if left.is_file() else (right, left)
            raise SessionError(absent, f"missing: ROS camera_info calibration needs both left.yaml and right.yaml "
                                       f"(found only {present.name})")
        stereo = read_ros_camera_info(left, right, image_size)
        _check_principal_point(left, stereo.calibration.K, image_size)
        return stereo
    for name in OPENCV_NAMES:
        if (root / name).is_file():
            return read_opencv_stereo(root / name, image_size)
    raise SessionError(
        k_txt, "missing: expected a stereo calibration: K.txt (line 1: 9 numbers of the rectified left 3x3 K in px; "
        "line 2: the baseline in metres), or ROS camera_info left.yaml + right.yaml, or an OpenCV stereo "
        f"calibration ({', '.join(OPENCV_NAMES)})"
    )
