"""The robot's side of a session: ``kinematics.csv``, ``tool_tips.csv`` and hand-eye files.

``kinematics.csv`` (optional; written by ``contact-viz import bag`` from a ``PoseStamped`` or
``TransformStamped`` topic such as the dVRK's ``/PSM1/measured_cp``)::

    timestamp,x_m,y_m,z_m,qx,qy,qz,qw,frame_id
    1737146000.033333333,0.0123,-0.0451,-0.1022,0.0,0.7071068,0.0,0.7071068,PSM1_base

One row per pose sample at the recorder's own rate: ``timestamp`` in seconds on the clock of
``frames.csv``; the tool tip's position in metres and its orientation as a unit quaternion (ROS
order x, y, z, w), both expressed in the frame named by ``frame_id`` (the pose's parent frame,
e.g. the arm's base; may be empty). Rows are matched to frames by nearest timestamp.

``tool_tips.csv`` (optional; written by ``contact-viz import yang2024 --labels``)::

    frame,x_px,y_px
    000045,465.94,266.65

Tool-tip keypoints in left-image pixels (x = column, y = row, origin at the top-left pixel
centre) for the frames that have one; the RGB baseline centres its crop there instead of on the
tip estimated from the mask.

Hand-eye file (``contact-viz view --hand-eye FILE``): the 4x4 rigid transform ``camera_T_base``
taking points in the kinematics frame (``frame_id`` above) to the rectified left camera's frame
(x right, y down, z forward, metres: the frame of K.txt and of the debugger's 3D view). Either a
text file of 16 numbers (4 rows of 4, separated by spaces, tabs or commas; ``#`` starts a
comment) or a ``.npy`` file holding a (4, 4) array. Translation in metres; the last row must be
0 0 0 1 and the rotation orthonormal with determinant +1.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from contact_viz.errors import SessionError
from contact_viz.io.session_files import (
    _check_unique,
    _column_floats,
    _match_stems,
    _read_csv,
    _require_columns,
    _warn_unmatched,
)

__all__ = [
    "KINEMATICS_COLUMNS",
    "KINEMATICS_FILE",
    "TOOL_TIPS_COLUMNS",
    "TOOL_TIPS_FILE",
    "Kinematics",
    "read_hand_eye",
    "read_kinematics",
    "read_tool_tips",
]

KINEMATICS_FILE = "kinematics.csv"
KINEMATICS_COLUMNS = ("timestamp", "x_m", "y_m", "z_m", "qx", "qy", "qz", "qw", "frame_id")
TOOL_TIPS_FILE = "tool_tips.csv"
TOOL_TIPS_COLUMNS = ("frame", "x_px", "y_px")
QUATERNION_NORM_TOLERANCE = 1e-3  # largest accepted | |q| - 1 | before normalising (unitless)
ROTATION_TOLERANCE = 1e-3  # largest accepted deviation of R^T R from I and of det R from 1 (unitless)


@dataclass(frozen=True, eq=False)
class Kinematics:
    """The pose samples of kinematics.csv, in time order (arrays read-only, m = samples)."""

    path: Path  # the file read
    timestamps_s: np.ndarray  # (m,) float64, s, ascending
    position_m: np.ndarray  # (m, 3) float64 tool-tip position in frame_id, m
    quaternion_xyzw: np.ndarray  # (m, 4) float64 unit quaternion (x, y, z, w), tool orientation in frame_id
    frame_ids: tuple[str, ...]  # (m,) the frame each pose is expressed in

    def __len__(self) -> int:
        return len(self.timestamps_s)


def read_kinematics(path: str | Path) -> Kinematics:
    """Read and check ``kinematics.csv`` (see the module docstring); SessionError naming the file."""
    path = Path(path)
    header, body = _read_csv(path)
    _require_columns(path, header, KINEMATICS_COLUMNS[:-1], "timestamp in s, position in m, quaternion x y z w")
    if not body:
        raise SessionError(path, "expected at least one pose row (timestamp, x_m, y_m, z_m, qx, qy, qz, qw)")
    columns = {name: _column_floats(path, header, body, name, unit)
               for name, unit in zip(KINEMATICS_COLUMNS[:-1], ("seconds",) + ("m",) * 3 + ("unitless",) * 4)}
    for name, values in columns.items():
        if np.isnan(values).any():
            line = body[int(np.flatnonzero(np.isnan(values))[0])][0]
            raise SessionError(path, f"line {line}: expected a number in column {name!r}, found nan")
    times = columns["timestamp"]
    position = np.stack([columns[c] for c in ("x_m", "y_m", "z_m")], axis=1)
    quat = np.stack([columns[c] for c in ("qx", "qy", "qz", "qw")], axis=1)
    norm = np.linalg.norm(quat, axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE)
    if bad.size:
        raise SessionError(path, f"line {body[int(bad[0])][0]}: expected a unit quaternion qx, qy, qz, qw, "
                                 f"found norm {norm[bad[0]]:.6g}")
    quat = quat / norm[:, None]
    frame_col = header.index("frame_id") if "frame_id" in header else None
    frames = [cells[frame_col] if frame_col is not None else "" for _, cells in body]
    order = np.argsort(times, kind="stable")
    out = Kinematics(path, times[order], position[order], quat[order], tuple(frames[i] for i in order))
    for array in (out.timestamps_s, out.position_m, out.quaternion_xyzw):
        array.flags.writeable = False
    return out


def read_tool_tips(path: str | Path, stems: Sequence[str]) -> np.ndarray:
    """``tool_tips.csv`` -> (n, 2) float64 (x, y) px per stem of ``stems``, NaN where the file has no row."""
    path = Path(path)
    header, body = _read_csv(path)
    _require_columns(path, header, TOOL_TIPS_COLUMNS, "frame stem, tool tip x and y in px")
    names = [cells[header.index("frame")] for _, cells in body]
    xs = _column_floats(path, header, body, "x_px", "px")
    ys = _column_floats(path, header, body, "y_px", "px")
    matched = _match_stems(path, names, list(stems))
    _check_unique(path, names, matched)
    _warn_unmatched(path, names, matched)
    out = np.full((len(stems), 2), np.nan)
    ok = matched >= 0
    out[matched[ok], 0] = xs[ok]
    out[matched[ok], 1] = ys[ok]
    out.flags.writeable = False
    return out


_NUMBER_SPLIT = re.compile(r"[\s,;]+")


def read_hand_eye(path: str | Path) -> np.ndarray:
    """The 4x4 ``camera_T_base`` of a hand-eye file (text or .npy, see the module docstring), float64.

    Raises SessionError naming the file and what was expected.
    """
    path = Path(path).expanduser()
    what = "a hand-eye file: the 4x4 camera_T_base (16 numbers, 4 rows of 4, metres) as text or .npy"
    if not path.is_file():
        raise SessionError(path, f"missing: expected {what}")
    if path.suffix.lower() == ".npy":
        try:
            matrix = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise SessionError(path, f"expected {what}, could not read it ({exc})") from exc
    else:
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise SessionError(path, f"expected {what}, could not read it ({exc})") from exc
        cells = [c for line in text.splitlines() for c in _NUMBER_SPLIT.split(line.split("#", 1)[0].strip()) if c]
        try:
            matrix = np.array([float(c) for c in cells], dtype=np.float64)
        except ValueError as exc:
            raise SessionError(path, f"expected {what}, found a non-number ({exc})") from None
        if matrix.size != 16:
            raise SessionError(path, f"expected {what}, found {matrix.size} numbers")
        matrix = matrix.reshape(4, 4)
    matrix = np.asarray(matrix)
    if matrix.shape != (4, 4) or not np.issubdtype(matrix.dtype, np.number):
        raise SessionError(path, f"expected {what}, found an array of shape {matrix.shape} dtype {matrix.dtype}")
    matrix = matrix.astype(np.float64)
    if not np.isfinite(matrix).all():
        raise SessionError(path, f"expected {what}, found a non-finite number")
    if not np.allclose(matrix[3], (0.0, 0.0, 0.0, 1.0), atol=1e-9):
        raise SessionError(path, f"expected the last row 0 0 0 1 of a rigid transform, found {matrix[3].tolist()}")
    rotation = matrix[:3, :3]
    orth = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    det = float(np.linalg.det(rotation))
    if orth > ROTATION_TOLERANCE or not math.isclose(det, 1.0, abs_tol=ROTATION_TOLERANCE):
        raise SessionError(path, f"expected a rotation in the upper-left 3x3 (orthonormal, determinant +1), "
                                 f"found max |R^T R - I| = {orth:.3g}, det = {det:.4g}")
    return matrix
