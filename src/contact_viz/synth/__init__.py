"""Synthetic stereo-endoscope sessions with known truth, rendered by open3d ray casting.

A textured tissue phantom (``cup``, ``kidney``, ``liver`` or ``glove``) and a dVRK-like instrument
(8 mm shaft, dark wrist, two rounded jaws) are seen through a rectified stereo endoscope. The tool
palpates the tissue in repeated cycles (approach with hover, press, hold, retract); on the glove
it grasps the surface and pulls it outward instead. Because the scene is synthetic, the true
tool-tissue gap, indentation, force and contact are known for every frame.

The module is layered; each layer only uses the ones above it:

1. geometry and motion (pure numpy): camera, tissue frame, phantom height fields, closest points,
   tool trajectory and truth (``plan_tool_track``), dent/tent field (``tissue_displacement``);
2. sensor models (pure numpy/cv2): stereo depth noise and holes (``stereo_depth``), force noise
   (``measured_force``), manual-style labels (``manual_labels``);
3. rendering (open3d ray casting + shading) of a stereo pair (``_Renderer``);
4. file writing (``generate_session``).

Coordinates are metres in the left camera frame (OpenCV: x right, y down, z forward). The right
camera sits at (+baseline, 0, 0) with the same orientation, so true disparity = fx * B / Z.
"""

from __future__ import annotations

import math
import shutil
import tempfile
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from contact_viz.io.atomic import atomic_write
from contact_viz.io.jsonfile import write_json
from contact_viz.params import check_fields, checked, to_dict

PHANTOMS: tuple[str, ...] = ("cup", "kidney", "liver", "glove")
PHASES: tuple[str, ...] = ("approach", "press", "hold", "retract", "pull")

REFERENCE_WIDTH_PX = 1920  # image width at which the px-valued noise parameters are given, px

# Independent random streams, each seeded by (seed, stream, phantom[, frame]): changing how much one
# part draws never changes another part.
_STREAM_MOTION, _STREAM_TEXTURE, _STREAM_DEPTH, _STREAM_FORCE, _STREAM_LABELS = 101, 202, 303, 404, 505


def _rng(params: SynthParams, stream: int, *more: int) -> np.random.Generator:
    """The random generator of one stream of a session."""
    return np.random.default_rng([params.seed, stream, PHANTOMS.index(params.phantom), *more])


@dataclass(frozen=True)
class SynthParams:
    """Everything that defines a synthetic session; the same params give the same files.

    Pairs ``(lo, hi)`` are ranges that a value is drawn from uniformly, per cycle or per blob.
    """

    phantom: str = checked("cup", choices=PHANTOMS)  # tissue phantom, one of PHANTOMS ("glove" is a pulling task), -
    frames: int = checked(120, ge=1)  # number of frames, count
    seed: int = checked(0, ge=0)  # seed of every random choice, -
    width: int = checked(1920, ge=32)  # image width, px
    height: int = checked(1080, ge=32)  # image height, px
    fps: int = checked(30, ge=1)  # frame rate, 1/s
    fov_deg: float = checked(80.0, ge=30, le=120)  # horizontal field of view, deg
    baseline_m: float = checked(0.005, gt=0)  # stereo baseline (right camera at +x), m
    tissue_distance_m: float = checked(0.09, gt=0)  # distance from the camera to the tissue base plane along z, m
    # tilt of the base plane about the camera x axis (top recedes), deg
    tissue_tilt_deg: float = checked(30.0, ge=0, lt=60)
    shaft_diameter_m: float = checked(0.008, gt=0)  # instrument shaft diameter, m
    jaw_radius_m: float = checked(0.0018, gt=0)  # radius of each of the two rounded jaws, m
    jaw_length_m: float = checked(0.009, gt=0)  # hinge-to-tip length of the jaws, m
    wrist_radius_m: float = checked(0.0031, gt=0)  # radius of the dark wrist between jaws and shaft, m
    wrist_length_m: float = checked(0.009, gt=0)  # length of the wrist, m
    jaw_open_deg: float = checked(22.0, ge=0)  # opening of each jaw while approaching to grasp (glove), deg
    # tissue stiffness under the tip: force = stiffness x indentation, N/m
    stiffness_n_per_m: float = checked(1400.0, gt=0)
    pull_stiffness_n_per_m: float = checked(150.0, gt=0)  # tension per metre of tenting when pulling the glove, N/m
    force_noise_n: float = checked(0.08, ge=0)  # force sensor noise, standard deviation per axis, N
    press_depth_m: tuple[float, float] = checked((0.0025, 0.0042), ge=0, pair=True)  # indentation of a firm press, m
    # indentation of a light touch, m
    light_press_depth_m: tuple[float, float] = checked((0.0004, 0.0013), ge=0, pair=True)
    light_press_prob: float = checked(0.3, ge=0, le=1)  # chance that a press after the first is a light touch, -
    hover_gap_m: tuple[float, float] = checked((0.002, 0.010), ge=0, pair=True)  # gap while hovering before a press, m
    # gap where an approach starts / a retract ends, m
    start_gap_m: tuple[float, float] = checked((0.012, 0.022), ge=0, pair=True)
    # indentation when the jaws grasp (glove), m
    grasp_squeeze_m: tuple[float, float] = checked((0.0006, 0.0012), ge=0, pair=True)
    # how far the grasped surface is pulled (glove), m
    pull_height_m: tuple[float, float] = checked((0.005, 0.014), ge=0, pair=True)
    dent_sigma_m: float = checked(0.006, gt=0)  # Gaussian width of the dent around the tip, m
    tent_length_m: float = checked(0.005, gt=0)  # decay length of the tent around the grasped point, m
    approach_s: tuple[float, float] = checked((0.5, 0.9), ge=0, pair=True)  # duration of the approach move, s
    hover_s: tuple[float, float] = checked((0.2, 0.5), ge=0, pair=True)  # duration of the hover, s
    # duration of the press (hover to full indentation), s
    press_s: tuple[float, float] = checked((0.25, 0.45), ge=0, pair=True)
    hold_s: tuple[float, float] = checked((0.3, 0.8), ge=0, pair=True)  # duration of the hold, s
    pull_s: tuple[float, float] = checked((0.4, 0.7), ge=0, pair=True)  # duration of the pull (glove), s
    retract_s: tuple[float, float] = checked((0.35, 0.6), ge=0, pair=True)  # duration of the retract, s
    hover_wobble: float = checked(0.2, ge=0)  # amplitude of the slow gap variation while hovering, fraction of the gap
    disparity_noise_px: float = checked(0.25, ge=0)  # stereo disparity noise, std at REFERENCE_WIDTH_PX image width, px
    specular_hole_threshold: float = checked(0.4, gt=0)  # sharp specular radiance above which stereo fails (hole), -
    # mean number of random hole blobs per depth frame (>= 1 if this is >= 1), count
    hole_blob_count: float = checked(5.0, ge=0)
    # radius of a hole blob, fraction of width
    hole_blob_radius_frac: tuple[float, float] = checked((0.005, 0.018), ge=0, pair=True)
    edge_fattening_px: float = checked(2.0, ge=0)  # tool depth bleeding past its silhouette, at REFERENCE_WIDTH_PX, px
    # depth margin for calling a left pixel occluded in the right view, m
    occlusion_tolerance_m: float = checked(0.001, gt=0)
    label_jitter_frames: int = checked(1, ge=0)  # largest shift of a manual label boundary (glove labels.csv), frames
    raycast_step_px: int = checked(4, ge=1)  # adaptive ray caster lattice at REFERENCE_WIDTH_PX (1 = ray per pixel), px
    mesh_cell_px: float = checked(14.0, gt=0)  # tissue mesh cell size as seen at tissue_distance_m (at most 2 mm), px
    jpeg_quality: int = checked(92, ge=0, le=100)  # JPEG quality of the left/right images, 0-100

    def __post_init__(self) -> None:
        check_fields(self)
        if self.hover_gap_m[0] <= 0 or self.start_gap_m[0] < self.hover_gap_m[1]:
            raise ValueError("SynthParams needs 0 < hover_gap_m and start_gap_m >= hover_gap_m (approach moves in)")
        if self.press_depth_m[0] <= 0 or self.light_press_depth_m[0] <= 0 or self.grasp_squeeze_m[0] <= 0:
            raise ValueError("SynthParams.press_depth_m, light_press_depth_m and grasp_squeeze_m must be > 0")

    @property
    def task(self) -> str:
        """``"pulling"`` for the glove, ``"palpation"`` otherwise."""
        return "pulling" if self.phantom == "glove" else "palpation"


# ----------------------------------------------------------------------------------------------
# 1. Geometry and motion (pure functions)
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class StereoCamera:
    """A rectified stereo pair: both views share ``K``; the right one is at (+baseline, 0, 0)."""

    K: np.ndarray  # (3, 3) float64 intrinsics, px
    baseline_m: float  # distance between the two optical centres along +x, m
    width: int  # image width, px
    height: int  # image height, px

    @property
    def fx(self) -> float:
        """Focal length, px."""
        return float(self.K[0, 0])

    def project(self, points_m: np.ndarray) -> np.ndarray:
        """Left-view pixel coordinates (..., 2) float64 of camera-frame points (..., 3), m."""
        p = np.asarray(points_m, dtype=np.float64)
        z = p[..., 2]
        return np.stack(
            [self.K[0, 0] * p[..., 0] / z + self.K[0, 2], self.K[1, 1] * p[..., 1] / z + self.K[1, 2]], axis=-1
        )

    def pixel_rays(self, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Ray directions (len(rows), len(cols), 3) float32 with z = 1, through pixel centres."""
        x = ((np.asarray(cols, dtype=np.float64) - self.K[0, 2]) / self.K[0, 0]).astype(np.float32)
        y = ((np.asarray(rows, dtype=np.float64) - self.K[1, 2]) / self.K[1, 1]).astype(np.float32)
        dirs = np.empty((len(y), len(x), 3), dtype=np.float32)
        dirs[..., 0] = x[None, :]
        dirs[..., 1] = y[:, None]
        dirs[..., 2] = 1.0
        return dirs


def stereo_camera(params: SynthParams) -> StereoCamera:
    """The endoscope of ``params``: square pixels, principal point at the image centre."""
    fx = (params.width / 2.0) / math.tan(math.radians(params.fov_deg) / 2.0)
    K = np.array(
        [[fx, 0.0, (params.width - 1) / 2.0], [0.0, fx, (params.height - 1) / 2.0], [0.0, 0.0, 1.0]],
        dtype=np.float64,
    )
    return StereoCamera(K=K, baseline_m=float(params.baseline_m), width=params.width, height=params.height)


@dataclass(frozen=True, eq=False)
class TissueFrame:
    """Orthonormal frame of the tissue base plane: a point is origin + u e_u + v e_v + w normal."""

    origin_m: np.ndarray  # (3,) phantom centre on the base plane, m
    e_u: np.ndarray  # (3,) in-plane unit vector along image x
    e_v: np.ndarray  # (3,) in-plane unit vector roughly along image y (down)
    normal: np.ndarray  # (3,) unit normal of the base plane, toward the camera

    def to_camera(self, u: np.ndarray, v: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Camera-frame points (..., 3) of tissue coordinates u, v, w (m)."""
        u, v, w = (np.asarray(a, dtype=np.float64)[..., None] for a in (u, v, w))
        return self.origin_m + u * self.e_u + v * self.e_v + w * self.normal

    def to_tissue(self, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Tissue coordinates (u, v, w), each (...), of camera-frame points (..., 3), m."""
        d = np.asarray(points_m, dtype=np.float64) - self.origin_m
        return d @ self.e_u, d @ self.e_v, d @ self.normal


_PHANTOM_CENTRE_HEIGHT_M = 0.015  # the point this high above the phantom centre is on the optical axis, m


def tissue_frame(params: SynthParams) -> TissueFrame:
    """Base plane at ``tissue_distance_m`` along the optical axis, tilted so the image top recedes.

    The origin (the phantom centre) is placed so that the point ``_PHANTOM_CENTRE_HEIGHT_M`` above
    it lies on the optical axis: the top of the phantom appears near the image centre.
    """
    tilt = math.radians(params.tissue_tilt_deg)
    normal = np.array([0.0, -math.sin(tilt), -math.cos(tilt)])
    on_axis_z = params.tissue_distance_m + _PHANTOM_CENTRE_HEIGHT_M / normal[2]
    return TissueFrame(
        origin_m=np.array([0.0, 0.0, on_axis_z]) - _PHANTOM_CENTRE_HEIGHT_M * normal,
        e_u=np.array([1.0, 0.0, 0.0]),
        e_v=np.array([0.0, math.cos(tilt), -math.sin(tilt)]),
        normal=normal,
    )


def _softplus(x: np.ndarray, sharpness: float) -> np.ndarray:
    """Smooth max(x, 0) with a corner of width ~1/sharpness."""
    return np.logaddexp(0.0, sharpness * x) / sharpness


def _dome(rho2: np.ndarray, height_m: float, sharpness: float) -> np.ndarray:
    """Ellipsoid-like cap height_m * sqrt(1 - rho2) with a smooth foot (rho2 = normalized radius^2)."""
    return height_m * np.sqrt(_softplus(1.0 - rho2, sharpness))


def _smooth_max(values: list[np.ndarray], scale_m: float) -> np.ndarray:
    """Log-sum-exp blend of heights >= 0: the largest wins, with creases of width ~scale_m where
    they meet; offset so that all-zero heights give exactly 0 (the result is >= 0)."""
    stacked = np.stack(values) / scale_m
    return scale_m * (np.logaddexp.reduce(stacked, axis=0) - math.log(len(values)))


def _capsule_rho2(u, v, u0, v0, u1, v1, radius_m):
    """Squared normalized distance to the segment (u0, v0)-(u1, v1), for ridge-like shapes."""
    du, dv = u1 - u0, v1 - v0
    t = np.clip(((u - u0) * du + (v - v0) * dv) / (du * du + dv * dv), 0.0, 1.0)
    return ((u - u0 - t * du) ** 2 + (v - v0 - t * dv) ** 2) / radius_m**2


def phantom_height(phantom: str, u_m: np.ndarray, v_m: np.ndarray) -> np.ndarray:
    """Height (m, >= 0) of the phantom above its base plane at tissue coordinates (u, v) (m).

    cup: a silicone dome with a raised rim at its foot; kidney: a bean-shaped blob with a hilum
    notch; liver: a broad surface of three lobes meeting in creases; glove: an upright column
    (running along the image vertical) ending in four finger ridges and a thumb.
    """
    u, v = np.broadcast_arrays(np.asarray(u_m, dtype=np.float64), np.asarray(v_m, dtype=np.float64))
    if phantom == "cup":
        radius, height = 0.026, 0.016  # dome radius and height, m
        r = np.hypot(u - 0.002, v - 0.004)
        rim = 0.0025 * np.exp(-(((r - 1.08 * radius) / 0.0025) ** 2))  # lip at the foot, m
        return _dome((r / radius) ** 2, height, 25.0) + rim
    if phantom == "kidney":
        angle = math.radians(25.0)  # long axis rotated from image x
        x = math.cos(angle) * (u + 0.002) + math.sin(angle) * (v - 0.002)
        y = -math.sin(angle) * (u + 0.002) + math.cos(angle) * (v - 0.002)
        y_bent = y - 9.0 * x * x  # banana bend, 1/m
        half_len, half_wid = 0.036, 0.021  # semi-axes of the bean, m
        body = _dome((x / half_len) ** 2 + (y_bent / half_wid) ** 2, 0.02, 12.0)
        notch = 0.011 * np.exp(-((x / 0.008) ** 2) - ((y_bent - 0.9 * half_wid) / 0.007) ** 2)  # hilum, m
        return np.maximum(body - notch, 0.0)
    if phantom == "liver":
        lobes = [
            _dome(((u - 0.022) / 0.058) ** 2 + ((v + 0.004) / 0.05) ** 2, 0.018, 8.0),  # right lobe
            _dome(((u + 0.038) / 0.042) ** 2 + ((v + 0.01) / 0.04) ** 2, 0.015, 8.0),  # left lobe
            _dome(((u + 0.004) / 0.02) ** 2 + ((v - 0.03) / 0.016) ** 2, 0.011, 8.0),  # caudate lobe
        ]
        return _smooth_max(lobes, 0.0012)
    if phantom == "glove":
        top = -0.012  # v of the column top (fingers go further up, toward -v), m
        parts = [_dome(_capsule_rho2(u, v, 0.0, top, 0.0, 0.2, 0.019), 0.024, 10.0)]  # palm / wrist column
        for finger_u, length in ((-0.0135, 0.026), (-0.0045, 0.034), (0.0045, 0.031), (0.0135, 0.022)):
            parts.append(_dome(_capsule_rho2(u, v, finger_u, top + 0.006, finger_u, top - length, 0.0047), 0.019, 10.0))
        parts.append(_dome(_capsule_rho2(u, v, 0.014, 0.004, 0.033, -0.012, 0.0055), 0.017, 10.0))  # thumb
        return _smooth_max(parts, 0.0015)
    raise ValueError(f"phantom must be one of {PHANTOMS}, got {phantom!r}")


_GRAD_STEP_M = 1e-5  # central-difference step for height gradients, m


def _height_gradient(phantom: str, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(dh/du, dh/dv) of the phantom height, central differences, dimensionless."""
    step = _GRAD_STEP_M
    dh_du = (phantom_height(phantom, u + step, v) - phantom_height(phantom, u - step, v)) / (2 * step)
    dh_dv = (phantom_height(phantom, u, v + step) - phantom_height(phantom, u, v - step)) / (2 * step)
    return dh_du, dh_dv


def surface_points(phantom: str, frame: TissueFrame, u_m: np.ndarray, v_m: np.ndarray) -> np.ndarray:
    """Camera-frame points (..., 3), m, of the undeformed phantom surface at (u, v)."""
    return frame.to_camera(u_m, v_m, phantom_height(phantom, u_m, v_m))


def surface_normals(phantom: str, frame: TissueFrame, u_m: np.ndarray, v_m: np.ndarray) -> np.ndarray:
    """Unit normals (..., 3) of the undeformed surface at (u, v), pointing out of the tissue."""
    dh_du, dh_dv = _height_gradient(phantom, np.asarray(u_m, float), np.asarray(v_m, float))
    n = frame.normal - dh_du[..., None] * frame.e_u - dh_dv[..., None] * frame.e_v
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


_CLOSEST_GRID = 25  # samples per side of each grid-search window, count
_CLOSEST_ROUNDS = 5  # refinement rounds of the grid search, count


def closest_surface_points(
    phantom: str, frame: TissueFrame, points_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Closest points of the undeformed surface to camera-frame points (M, 3), m.

    Returns (closest (M, 3) m, their unit normals (M, 3), signed distance (M,) m: positive
    outside the tissue, (u, v) of the closest points (M, 2) m). The closest point lies within the
    vertical distance |w - h(u, v)| of (u, v) in the base plane, so a grid search over that window,
    refined ``_CLOSEST_ROUNDS`` times, finds it (to well below a micrometre for smooth shapes).
    """
    p = np.atleast_2d(np.asarray(points_m, dtype=np.float64))
    u, v, w = frame.to_tissue(p)
    vertical = w - phantom_height(phantom, u, v)
    half = np.abs(vertical) + 1e-4
    best_u, best_v = u.copy(), v.copy()
    offsets = np.linspace(-1.0, 1.0, _CLOSEST_GRID)
    for _ in range(_CLOSEST_ROUNDS):
        cu = best_u[:, None, None] + half[:, None, None] * offsets[None, None, :]
        cv = best_v[:, None, None] + half[:, None, None] * offsets[None, :, None]
        cu, cv = np.broadcast_arrays(cu, cv)
        s = surface_points(phantom, frame, cu, cv)
        d2 = np.sum((s - p[:, None, None, :]) ** 2, axis=-1).reshape(len(p), -1)
        k = np.argmin(d2, axis=1)
        best_u = cu.reshape(len(p), -1)[np.arange(len(p)), k]
        best_v = cv.reshape(len(p), -1)[np.arange(len(p)), k]
        half = half * 2.0 / (_CLOSEST_GRID - 1) * 1.5
    q = surface_points(phantom, frame, best_u, best_v)
    n = surface_normals(phantom, frame, best_u, best_v)
    dist = np.linalg.norm(p - q, axis=-1)
    signed = np.where(vertical >= 0, dist, -dist)
    return q, n, signed, np.stack([best_u, best_v], axis=-1)


@dataclass(frozen=True)
class _PhantomLayout:
    """Where the tool works on a phantom and how its tissue looks."""

    target_box_m: tuple[float, float, float, float]  # (u_min, u_max, v_min, v_max) of press targets, m
    target_min_height_m: float  # targets must be at least this high above the base plane, m
    tool_axis: tuple[float, float, float]  # mean shaft direction toward the tip, camera frame, -
    tissue_rgb: tuple[float, float, float]  # base albedo of the phantom, linear RGB
    tray_rgb: tuple[float, float, float]  # albedo of the base plane around it, linear RGB
    vessel_rgb: tuple[float, float, float]  # albedo factor at a vessel's core, per RGB channel
    vessel_count: int  # number of main vessels drawn, count


_LAYOUTS: dict[str, _PhantomLayout] = {
    "cup": _PhantomLayout(
        (-0.016, 0.02, -0.014, 0.022), 0.006, (-0.5, 0.84, 0.2),
        (0.66, 0.24, 0.23), (0.55, 0.10, 0.08), (0.55, 0.22, 0.28), 6,
    ),
    "kidney": _PhantomLayout(
        (-0.022, 0.018, -0.016, 0.02), 0.008, (-0.5, 0.84, 0.2),
        (0.50, 0.13, 0.10), (0.55, 0.10, 0.08), (0.5, 0.2, 0.25), 7,
    ),
    "liver": _PhantomLayout(
        (-0.03, 0.03, -0.022, 0.022), 0.006, (-0.5, 0.84, 0.2),
        (0.34, 0.07, 0.045), (0.55, 0.10, 0.08), (0.5, 0.2, 0.25), 8,
    ),
    "glove": _PhantomLayout(
        (0.006, 0.017, -0.01, 0.025), 0.008, (-0.62, 0.74, 0.2),
        (0.70, 0.42, 0.36), (0.55, 0.10, 0.08), (0.6, 0.35, 0.38), 3,
    ),
}


@dataclass(frozen=True, eq=False)
class ToolTrack:
    """Per-frame tool pose, tissue deformation and truth of a session; arrays over F frames.

    Points and vectors are in the left camera frame, m. The tool tip is two rounded jaws; the
    tip spheres (radius ``jaw_radius_m``) are centred at ``jaw_tips_m``.
    """

    timestamp_s: np.ndarray  # (F,) float64 frame times, s
    tip_center_m: np.ndarray  # (F, 3) hinge + jaw length along the axis (= mid jaw tip when closed), m
    axis: np.ndarray  # (F, 3) unit shaft axis, pointing from the shaft toward the tip
    hinge_m: np.ndarray  # (F, 3) jaw hinge on the axis, m
    jaw_bases_m: np.ndarray  # (F, 2, 3) base points of the two jaw capsules, m
    jaw_tips_m: np.ndarray  # (F, 2, 3) centres of the jaw-tip spheres, m
    dent_center_m: np.ndarray  # (F, 3) centre of the deformation, at the undeformed surface below the tip, m
    dent_normal: np.ndarray  # (F, 3) unit surface normal there
    dent_flat_m: np.ndarray  # (F,) radius of the flat bottom of the dent (covers both jaws), m
    press_m: np.ndarray  # (F,) depth of the dent along -dent_normal, m (0 = none)
    pull_m: np.ndarray  # (F, 3) displacement of the grasped point when pulling, m (0 = none)
    gap_m: np.ndarray  # (F,) distance of the tip surface to the undeformed tissue, 0 in contact, m
    indentation_m: np.ndarray  # (F,) tissue displacement under the tip (dent depth or tent height), m
    force_true_n: np.ndarray  # (F, 3) true contact force on the tool, N
    contact: np.ndarray  # (F,) bool, tool touching (or grasping) the tissue
    phase: np.ndarray  # (F,) str, one of PHASES

    @property
    def frames(self) -> int:
        """Number of frames F."""
        return len(self.timestamp_s)


@dataclass
class _State:
    """A keyframe of the tool motion (see ``_tool_centres`` for the meaning of h and pull)."""

    u: float  # target on the tissue, m
    v: float  # target on the tissue, m
    h: float  # > 0: gap along the target normal; < 0: press depth, m
    pull: float  # distance pulled out along the pull direction, m
    jaw: float  # opening of each jaw, rad
    axis: np.ndarray  # (3,) unit shaft axis toward the tip


@dataclass
class _Segment:
    phase: str  # phase label (approach segments also carry the hover)
    frames: int  # length, frames
    start: _State
    end: _State
    attached: bool  # the jaws hold the tissue (glove grasp)
    wobble: float  # amplitude of a slow h variation that vanishes at both ends, m
    wobble_hz: float  # frequency of that variation, 1/s
    wobble_phase: float  # its phase, rad


def _ease(t: np.ndarray) -> np.ndarray:
    """Smoothstep 3t^2 - 2t^3: zero velocity at both ends."""
    return t * t * (3.0 - 2.0 * t)


def _tool_centres(
    phantom: str, frame: TissueFrame, params: SynthParams, u, v, h, pull, axis
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Tip centre (N, 3) for motion states (arrays of N), plus surface point, normal, pull direction.

    The tool touches the target point q (normal n) when h = 0. For h > 0 it backs off along its
    own axis until the gap along n is h; for h < 0 it presses along -n by |h|. ``pull`` moves it
    along the pull direction normalize(n - axis) (out of the tissue and back along the shaft).
    """
    q = surface_points(phantom, frame, u, v)
    n = surface_normals(phantom, frame, u, v)
    cos_theta = np.maximum(-np.sum(axis * n, axis=-1), _MIN_COS_AXIS)
    h = np.asarray(h, dtype=np.float64)[..., None]
    back = np.where(h >= 0, -axis * h / cos_theta[..., None], h * n)
    pull_dir = n - axis
    pull_dir /= np.linalg.norm(pull_dir, axis=-1, keepdims=True)
    c = q + n * params.jaw_radius_m + back + np.asarray(pull, dtype=np.float64)[..., None] * pull_dir
    return c, q, n, pull_dir


def _jaw_geometry(params: SynthParams, c: np.ndarray, axis: np.ndarray, n: np.ndarray, jaw: np.ndarray):
    """Hinge (N, 3), jaw bases (N, 2, 3) and jaw-tip sphere centres (N, 2, 3).

    The two jaws are capsules of radius ``jaw_radius_m`` side by side (touching when closed, with
    the tips at c -/+ jaw_radius_m along the spread direction, which is parallel to the tissue), each
    turning by ``jaw`` (rad) about its base to open.
    """
    spread = np.cross(axis, n)
    spread /= np.linalg.norm(spread, axis=-1, keepdims=True)
    hinge = c - axis * params.jaw_length_m
    bases, tips = [], []
    for side in (-1.0, 1.0):
        base = hinge + side * params.jaw_radius_m * spread
        beta = side * np.asarray(jaw, dtype=np.float64)[..., None]
        bases.append(base)
        tips.append(base + params.jaw_length_m * (np.cos(beta) * axis + np.sin(beta) * spread))
    return hinge, np.stack(bases, axis=-2), np.stack(tips, axis=-2)


def _tool_samples(params: SynthParams, c: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points along the wrist and shaft axis behind the jaws (S, 3) and the tool radius there (S,), m."""
    start = params.jaw_length_m - 0.0015
    end = params.jaw_length_m + params.wrist_length_m + _SHAFT_LENGTH_M
    s = np.linspace(start, end, 80)
    on_wrist = s < params.jaw_length_m + params.wrist_length_m
    radius = np.where(on_wrist, params.wrist_radius_m, params.shaft_diameter_m / 2)
    return c - s[:, None] * axis, radius


_SHAFT_LENGTH_M = 0.14  # rendered shaft length (reaches past the image border), m
_CLEARANCE_M = 0.001  # smallest allowed gap between wrist/shaft and the undeformed tissue, m
_JAW_CLEARANCE_M = 0.0005  # smallest gap of any jaw tip while hovering (h > 0), m
_MIN_COS_AXIS = 0.35  # tool axis at most ~70 deg from the surface normal at the target, -
_MIN_COS_VIEW = 0.4  # the target surface faces the camera: at most ~66 deg between normal and view ray, -
_TIP_VIEW_MARGIN = 0.2  # the tip stays this fraction of the image size away from the border, -
_MAX_TARGET_TRIES = 400  # attempts to draw a reachable target, count
_AXIS_JITTER = 0.08  # per-cycle random change of the tool axis (std per component of a unit vector), -
_WOBBLE_HZ = (0.6, 1.4)  # range of the frequency of the slow hover / hold variation, 1/s
_HOLD_TREMOR = 0.05  # amplitude of the indentation variation while holding, fraction of the depth


def _height_clearance(phantom: str, frame: TissueFrame, points: np.ndarray) -> np.ndarray:
    """First-order signed distance (m) of points (..., 3) above the undeformed surface."""
    u, v, w = frame.to_tissue(points)
    du, dv = _height_gradient(phantom, u, v)
    return (w - phantom_height(phantom, u, v)) / np.sqrt(1.0 + du * du + dv * dv)


def _placement_ok(phantom, frame, camera, params, u, v, axis, checks) -> bool:
    """Whether the tool at target (u, v) with this axis is clear of the tissue in every checked state.

    The target surface must face the camera. ``checks`` is a list of (h, pull, jaw, in_view):
    while hovering (h > 0) no jaw tip comes within ``_JAW_CLEARANCE_M`` of the tissue; in every
    state the wrist and shaft keep ``_CLEARANCE_M`` from the tissue (the undeformed surface,
    lowered by the dent when pressing) and the far end of the shaft lies outside the image; states
    with in_view also keep the tip inside the central image region and, when not pressing, in the
    camera's line of sight.
    """
    n = surface_normals(phantom, frame, u, v)
    if -float(axis @ n) < _MIN_COS_AXIS:
        return False
    q = surface_points(phantom, frame, u, v)
    if -float(n @ q) / float(np.linalg.norm(q)) < _MIN_COS_VIEW:
        return False
    size = np.array([camera.width, camera.height])
    for h, pull, jaw, in_view in checks:
        c, q, _, _ = _tool_centres(phantom, frame, params, np.array(u), np.array(v), np.array(h), np.array(pull), axis)
        if h > 0:  # not touching yet: no jaw (open or not) may reach the tissue
            _, _, tips = _jaw_geometry(params, c, axis, n, np.array(jaw))
            if np.any(_height_clearance(phantom, frame, tips) < params.jaw_radius_m + _JAW_CLEARANCE_M):
                return False
        pts, radius = _tool_samples(params, c, axis)
        clearance = _height_clearance(phantom, frame, pts)
        if h < 0:  # the dent lowers the tissue around the tip
            rel = pts - q
            lateral = np.linalg.norm(rel - np.outer(rel @ n, n), axis=1)
            beyond = np.maximum(lateral - params.jaw_radius_m, 0.0)
            clearance = clearance + (-h) * np.exp(-0.5 * (beyond / params.dent_sigma_m) ** 2)
        if np.any(clearance < radius + _CLEARANCE_M):
            return False
        far_end = pts[-1]
        if far_end[2] > 0.01:
            end_px = camera.project(far_end)
            if np.all(end_px >= 0) and np.all(end_px < size):
                return False
        if in_view:
            px = camera.project(c)
            if np.any(px < _TIP_VIEW_MARGIN * size) or np.any(px > (1 - _TIP_VIEW_MARGIN) * size):
                return False
            if h >= 0:
                sight = np.linspace(0.0, 1.0 - 0.004 / np.linalg.norm(c), 40)[1:, None] * c  # camera -> tip
                if np.any(_height_clearance(phantom, frame, sight) < 0):
                    return False
    return True


def _draw_target(rng, phantom, frame, camera, params, checks):
    """A reachable target (u, v) and tool axis for one cycle."""
    layout = _LAYOUTS[phantom]
    mean_axis = np.asarray(layout.tool_axis, dtype=np.float64)
    mean_axis /= np.linalg.norm(mean_axis)
    u_min, u_max, v_min, v_max = layout.target_box_m
    for _ in range(_MAX_TARGET_TRIES):
        u = float(rng.uniform(u_min, u_max))
        v = float(rng.uniform(v_min, v_max))
        axis = mean_axis + rng.normal(0.0, _AXIS_JITTER, 3)
        axis /= np.linalg.norm(axis)
        if phantom_height(phantom, np.array(u), np.array(v)) < layout.target_min_height_m:
            continue
        if _placement_ok(phantom, frame, camera, params, u, v, axis, checks):
            return u, v, axis
    raise RuntimeError(f"synth: found no reachable tool target on phantom {phantom!r} in {_MAX_TARGET_TRIES} tries")


def _plan_segments(params: SynthParams, rng: np.random.Generator) -> list[_Segment]:
    """Motion segments (cycles of approach/hover/press/hold/[pull]/retract) covering all frames."""
    phantom, fps = params.phantom, params.fps
    frame, camera = tissue_frame(params), stereo_camera(params)
    grasping = params.task == "pulling"
    open_rad = math.radians(params.jaw_open_deg) if grasping else 0.0

    def frames_of(span: tuple[float, float]) -> int:
        return max(1, round(rng.uniform(*span) * fps))

    def wobble_args(amplitude: float) -> dict:
        hz, phase = float(rng.uniform(*_WOBBLE_HZ)), float(rng.uniform(0, 2 * np.pi))
        return {"wobble": amplitude, "wobble_hz": hz, "wobble_phase": phase}

    segments: list[_Segment] = []
    total, cycle, prev = 0, 0, None
    while total < params.frames:
        start_gap = float(rng.uniform(*params.start_gap_m))
        hover = float(rng.uniform(*params.hover_gap_m))
        if grasping:
            depth = float(rng.uniform(*params.grasp_squeeze_m))
            pull = float(rng.uniform(*params.pull_height_m))
            squeezed = -params.grasp_squeeze_m[1]
            checks = [
                (start_gap, 0.0, open_rad, False),
                (hover, 0.0, open_rad, True),
                (squeezed, 0.0, 0.0, True),
                (0.0, pull, 0.0, True),
            ]
        else:
            light = cycle > 0 and rng.uniform() < params.light_press_prob
            depth = float(rng.uniform(*(params.light_press_depth_m if light else params.press_depth_m)))
            pull = 0.0
            checks = [(start_gap, 0.0, 0.0, False), (hover, 0.0, 0.0, True), (-params.press_depth_m[1], 0.0, 0.0, True)]
        u, v, axis = _draw_target(rng, phantom, frame, camera, params, checks)
        if prev is None:
            prev = _State(u, v, start_gap, 0.0, open_rad, axis)
        hover_state = _State(u, v, hover, 0.0, open_rad, axis)
        pressed = _State(u, v, -depth, 0.0, 0.0, axis)
        segs = [
            _Segment("approach", frames_of(params.approach_s), prev, hover_state, False, 0.0, 0.0, 0.0),
            _Segment("approach", frames_of(params.hover_s), hover_state, hover_state, False,
                     **wobble_args(params.hover_wobble * hover)),
            _Segment("press", frames_of(params.press_s), hover_state, pressed, grasping, 0.0, 0.0, 0.0),
        ]
        if grasping:
            pulled = _State(u, v, 0.0, pull, 0.0, axis)
            segs += [
                _Segment("pull", frames_of(params.pull_s), pressed, pulled, True, 0.0, 0.0, 0.0),
                _Segment("hold", frames_of(params.hold_s), pulled, pulled, True, 0.0, 0.0, 0.0),
            ]
            last = pulled
        else:
            hold_frames = frames_of(params.hold_s)
            segs.append(_Segment("hold", hold_frames, pressed, pressed, False, **wobble_args(_HOLD_TREMOR * depth)))
            last = pressed
        retracted = _State(u, v, float(rng.uniform(*params.start_gap_m)), 0.0, open_rad, axis)
        segs.append(_Segment("retract", frames_of(params.retract_s), last, retracted, False, 0.0, 0.0, 0.0))
        segments += segs
        total += sum(s.frames for s in segs)
        prev, cycle = retracted, cycle + 1
    return segments


def _sample_segments(segments: list[_Segment], frames: int, fps: int) -> dict[str, np.ndarray]:
    """Per-frame motion state arrays from the segments (first ``frames`` frames)."""
    keys = ("u", "v", "h", "pull", "jaw")
    out: dict[str, list] = {k: [] for k in (*keys, "axis", "attached", "phase")}
    for seg in segments:
        tau = np.arange(seg.frames) / seg.frames
        s = _ease(tau)
        for k in keys:
            a, b = getattr(seg.start, k), getattr(seg.end, k)
            out[k].append(a + (b - a) * s)
        out["h"][-1] = out["h"][-1] + seg.wobble * np.sin(np.pi * tau) * np.sin(
            2 * np.pi * seg.wobble_hz * tau * seg.frames / fps + seg.wobble_phase
        )
        axis = seg.start.axis[None, :] * (1 - s[:, None]) + seg.end.axis[None, :] * s[:, None]
        out["axis"].append(axis / np.linalg.norm(axis, axis=1, keepdims=True))
        out["attached"].append(np.full(seg.frames, seg.attached))
        out["phase"].append(np.full(seg.frames, seg.phase, dtype=object))
    return {k: np.concatenate(v)[:frames] for k, v in out.items()}


def plan_tool_track(params: SynthParams) -> ToolTrack:
    """The tool motion, tissue deformation and truth of every frame (pure: depends on params only).

    Truth: the gap is the distance from the lower jaw-tip sphere to the undeformed surface; the
    indentation is how far the tip sits below it (palpation), or the tissue displacement while
    grasped (pulling, where the tissue follows the jaws and the gap is 0). Contact is
    indentation > 0, and then the gap is exactly 0.
    """
    rng = _rng(params, _STREAM_MOTION)
    phantom, frame = params.phantom, tissue_frame(params)
    st = _sample_segments(_plan_segments(params, rng), params.frames, params.fps)
    axis = st["axis"]
    c, q, n, pull_dir = _tool_centres(phantom, frame, params, st["u"], st["v"], st["h"], st["pull"], axis)
    hinge, bases, tips = _jaw_geometry(params, c, axis, n, st["jaw"])

    # Geometry of contact: where the tool would be without the pull (the grasped tissue moves with it).
    attached = st["attached"]
    pull_vec = np.where(attached[:, None], st["pull"][:, None] * pull_dir, 0.0)
    tips_rest = tips - pull_vec[:, None, :]
    closest, normals, signed, _ = closest_surface_points(phantom, frame, tips_rest.reshape(-1, 3))
    signed = signed.reshape(-1, 2)
    low = np.argmin(signed, axis=1)
    rows = np.arange(len(low))
    sd = signed[rows, low]
    q_low = closest.reshape(-1, 2, 3)[rows, low]
    n_low = normals.reshape(-1, 2, 3)[rows, low]
    press = np.maximum(params.jaw_radius_m - sd, 0.0)
    gap_geo = np.maximum(sd - params.jaw_radius_m, 0.0)

    # Centre the dent below the midpoint of the jaws so both tips sit in its flat bottom.
    offset = (c - pull_vec) - tips_rest[rows, low]
    offset -= np.sum(offset * n_low, axis=1, keepdims=True) * n_low
    dent_center = q_low + offset
    dent_flat = np.linalg.norm(offset, axis=1) + 0.5 * params.jaw_radius_m

    held = attached & ((press > 0) | (st["pull"] > 0))
    pull_vec = np.where(held[:, None], pull_vec, 0.0)
    contact = (press > 0) | held
    disp = -press[:, None] * n_low + pull_vec
    indentation = np.where(contact, np.linalg.norm(disp, axis=1), 0.0)
    gap = np.where(contact, 0.0, gap_geo)
    force = params.stiffness_n_per_m * press[:, None] * n_low - params.pull_stiffness_n_per_m * pull_vec

    phase = st["phase"].copy()
    phase[(phase == "press") & ~contact] = "approach"
    return ToolTrack(
        timestamp_s=np.arange(params.frames, dtype=np.float64) / params.fps,
        tip_center_m=c,
        axis=axis,
        hinge_m=hinge,
        jaw_bases_m=bases,
        jaw_tips_m=tips,
        dent_center_m=dent_center,
        dent_normal=n_low,
        dent_flat_m=dent_flat,
        press_m=press,
        pull_m=pull_vec,
        gap_m=gap,
        indentation_m=indentation,
        force_true_n=force,
        contact=contact,
        phase=phase.astype(str),
    )


def tissue_displacement(points_m: np.ndarray, track: ToolTrack, index: int, params: SynthParams) -> np.ndarray:
    """Displacement (N, 3), m, of undeformed tissue points (N, 3) in frame ``index``.

    Pressing: a dent along -normal with a flat bottom (radius ``dent_flat_m``, holding both jaws)
    and a Gaussian flank of width ``dent_sigma_m``. Pulling: a tent along the pull vector,
    (1 + x) exp(-x) with x = distance beyond the flat bottom / ``tent_length_m``.
    """
    p = np.asarray(points_m, dtype=np.float64)
    press = float(track.press_m[index])
    pull = track.pull_m[index]
    out = np.zeros_like(p)
    if press <= 0 and not np.any(pull):
        return out
    rho = np.linalg.norm(p - track.dent_center_m[index], axis=-1)
    beyond = np.maximum(rho - track.dent_flat_m[index], 0.0)
    if press > 0:
        out -= (press * np.exp(-0.5 * (beyond / params.dent_sigma_m) ** 2))[:, None] * track.dent_normal[index]
    if np.any(pull):
        x = beyond / params.tent_length_m
        out += ((1.0 + x) * np.exp(-x))[:, None] * pull
    return out


# ----------------------------------------------------------------------------------------------
# 2. Sensor models
# ----------------------------------------------------------------------------------------------


def measured_force(track: ToolTrack, params: SynthParams) -> np.ndarray:
    """Force sensor readings (F, 3), N: the true force plus Gaussian noise per axis."""
    rng = _rng(params, _STREAM_FORCE)
    return track.force_true_n + rng.normal(0.0, params.force_noise_n, track.force_true_n.shape)


def manual_labels(contact: np.ndarray, jitter_frames: int, rng: np.random.Generator) -> np.ndarray:
    """Manual-style contact labels (F,) int: each contact run's ends shifted by up to ±jitter frames."""
    contact = np.asarray(contact, dtype=bool)
    labels = np.zeros(len(contact), dtype=np.int64)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], contact.astype(np.int8), [0]])))
    for start, stop in zip(edges[0::2], edges[1::2]):
        a = start + int(rng.integers(-jitter_frames, jitter_frames + 1))
        b = stop + int(rng.integers(-jitter_frames, jitter_frames + 1))
        a, b = max(a, 0), min(b, len(contact))
        if b <= a:
            a, b = start, stop
        labels[a:b] = 1
    return labels


_NOISE_COARSE_DIV = 8  # the smooth part of the disparity noise varies over this many px, px
_NOISE_FINE_DIV = 2  # the fine part of the disparity noise varies over this many px, px
_NOISE_COARSE_WEIGHT, _NOISE_FINE_WEIGHT = 0.8, 0.6  # relative std of the two parts (normalized to 1 in total)
_SPECULAR_GROW_PX = 2.0  # specular holes grow by this much at REFERENCE_WIDTH_PX (glare halo), px


def stereo_depth(
    z_left: np.ndarray,
    z_right: np.ndarray,
    tool_left: np.ndarray,
    specular_left: np.ndarray,
    camera: StereoCamera,
    params: SynthParams,
    rng: np.random.Generator,
) -> np.ndarray:
    """Stereo-like depth (H, W) float32, m, 0 = hole, from true z-depths of both views (0 = miss).

    Disparity fx*B/z gets smooth plus fine Gaussian noise (std ``disparity_noise_px`` at the
    reference width), so the depth error grows as z^2 / (fx B). The tool's depth bleeds
    ``edge_fattening_px`` past its silhouette. Holes: misses, pixels occluded in the right view,
    specular highlights (sharp specular radiance above ``specular_hole_threshold``, dilated), and
    random elliptic blobs (1 + Poisson(count - 1) of them: a mean count >= 1 gives at least one).
    """
    height, width = z_left.shape
    scale = width / REFERENCE_WIDTH_PX
    fb = camera.fx * camera.baseline_m
    hit = z_left > 0
    disparity = np.where(hit, fb / np.where(hit, z_left, 1.0), 0.0).astype(np.float32)

    sigma = params.disparity_noise_px * scale
    if sigma > 0:
        noise = np.zeros((height, width), np.float32)
        for div, weight in ((_NOISE_COARSE_DIV, _NOISE_COARSE_WEIGHT), (_NOISE_FINE_DIV, _NOISE_FINE_WEIGHT)):
            small = rng.standard_normal((height // div + 2, width // div + 2)).astype(np.float32)
            field = cv2.resize(small, (width + 2 * div, height + 2 * div), interpolation=cv2.INTER_CUBIC)
            field = field[div : div + height, div : div + width]
            noise += weight * field / max(float(field.std()), 1e-6)
        noise *= sigma / math.hypot(_NOISE_COARSE_WEIGHT, _NOISE_FINE_WEIGHT)
        disparity = disparity + noise
    depth = np.where(hit & (disparity > 0), fb / np.maximum(disparity, 1e-6), 0.0).astype(np.float32)

    # Edge fattening: the nearer tool surface spreads a little over the background.
    fatten = max(1, round(params.edge_fattening_px * scale)) if params.edge_fattening_px > 0 else 0
    if fatten:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * fatten + 1, 2 * fatten + 1))
        ring = (cv2.dilate(tool_left.astype(np.uint8), kernel) > 0) & ~tool_left
        tool_depth = np.where(tool_left & (depth > 0), depth, np.float32(np.inf)).astype(np.float32)
        spread = cv2.erode(tool_depth, kernel)
        take = ring & np.isfinite(spread)
        depth[take] = spread[take]

    holes = ~hit
    # Left-right occlusion: a left pixel's scene point is hidden behind something nearer in the right view.
    cols = np.arange(width, dtype=np.float32)[None, :] - np.where(hit, fb / np.where(hit, z_left, 1.0), 0.0)
    rows = np.broadcast_to(np.arange(height, dtype=np.float32)[:, None], (height, width))
    z_r = cv2.remap(z_right.astype(np.float32), cols.astype(np.float32), np.ascontiguousarray(rows),
                    cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    holes |= hit & (z_r > 0) & (z_r < z_left - params.occlusion_tolerance_m)
    # Specular highlights saturate both views: no match.
    spec = (specular_left > params.specular_hole_threshold).astype(np.uint8)
    grow = max(1, round(_SPECULAR_GROW_PX * scale))
    holes |= cv2.dilate(spec, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow + 1, 2 * grow + 1))) > 0
    # Random blobs (texture-less or mismatched patches).
    blob_mask = np.zeros((height, width), np.uint8)
    count = params.hole_blob_count
    blobs = 1 + int(rng.poisson(count - 1)) if count >= 1 else int(rng.poisson(count))
    for _ in range(blobs):
        centre = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        axes = tuple(max(1, round(rng.uniform(*params.hole_blob_radius_frac) * width)) for _ in range(2))
        cv2.ellipse(blob_mask, centre, axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
    holes |= blob_mask > 0
    depth[holes] = 0.0
    return depth


# ----------------------------------------------------------------------------------------------
# 3. Rendering (open3d ray casting)
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Material:
    albedo: tuple[float, float, float]  # diffuse reflectance, linear RGB
    gloss: float  # broad specular weight, -
    gloss_squarings: int  # broad specular exponent = 2**gloss_squarings
    shine: float  # sharp specular weight, -
    shine_squarings: int  # sharp specular exponent = 2**shine_squarings


_SHAFT = _Material((0.26, 0.27, 0.29), 0.7, 4, 0.9, 6)  # brushed steel
_WRIST = _Material((0.05, 0.05, 0.055), 0.3, 5, 0.6, 7)  # dark anodized wrist
_JAW = _Material((0.085, 0.085, 0.09), 0.35, 5, 0.7, 7)  # dark jaws
_TOOL_MATERIALS = (_SHAFT, _WRIST, _JAW)
_TISSUE = _Material((0.0, 0.0, 0.0), 0.10, 4, 1.3, 8)  # moist tissue; albedo comes from the texture, weights x wetness
_BUMP_SLOPE = 0.05  # std of the micro-relief slope that breaks highlights into wet glints, -
_BUMP_CELL_M = 0.0012  # size of the micro-relief bumps, m
_AMBIENT = 0.03  # ambient light, fraction of the light at the tissue distance
_EXPOSURE = 0.8  # gain before the tone curve, -
_SHOULDER = 0.6  # tone curve y = (1 + s) x / (1 + s x): soft roll-off of bright tissue, s
_VIGNETTE = 0.45  # vignetting (1 + a r^2/f^2)^-2, a
_MAX_CELL_M = 0.002  # coarsest tissue mesh cell (resolves the dent at small image sizes), m
_TEXEL_PX = 1.5  # texture texel size as seen at the tissue distance, px
_MAX_TEXTURE_PX = 4096  # largest texture side, texels
_GRAZING_SLOPE = 4.0  # depth slope (dz per lateral m) beyond which a lattice cell counts as a depth edge, -
_CYL_SEGMENTS = 48  # facets around a cylinder, count
_SPHERE_RES = 16  # open3d sphere resolution, count


@dataclass(frozen=True, eq=False)
class _Part:
    """One primitive of the tool: a cylinder a->b or a sphere at a."""

    kind: str  # "cylinder" or "sphere"
    a: np.ndarray  # cylinder start or sphere centre, m
    b: np.ndarray | None  # cylinder end, m
    radius: float  # m
    material: int  # index into _TOOL_MATERIALS


def tool_parts(track: ToolTrack, index: int, params: SynthParams) -> list[_Part]:
    """The tool of frame ``index`` as primitives: shaft, wrist and two capsule jaws."""
    axis, hinge = track.axis[index], track.hinge_m[index]
    wrist_end = hinge - axis * params.wrist_length_m
    parts = [
        _Part("cylinder", wrist_end, wrist_end - axis * _SHAFT_LENGTH_M, params.shaft_diameter_m / 2, 0),
        _Part("cylinder", hinge + axis * 0.0015, wrist_end, params.wrist_radius_m, 1),
    ]
    for base, tip in zip(track.jaw_bases_m[index], track.jaw_tips_m[index]):
        parts.append(_Part("cylinder", base, tip, params.jaw_radius_m, 2))
        parts.append(_Part("sphere", tip, None, params.jaw_radius_m, 2))
    return parts


def _value_noise(rng, shape, cell_texels: float) -> np.ndarray:
    """Smooth random field (shape) float32 of unit std varying over ~cell_texels."""
    h, w = shape
    gh, gw = max(2, int(h / cell_texels) + 3), max(2, int(w / cell_texels) + 3)
    small = rng.standard_normal((gh, gw)).astype(np.float32)
    field = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    return field / max(float(field.std()), 1e-6)


def _vessel_map(rng, shape, texel_m: float, count: int) -> np.ndarray:
    """Vessel density (shape) float32 in [0, 1]: branching tapered random walks plus capillaries."""
    h, w = shape
    canvas = np.zeros((h, w), np.float32)
    step_m = 0.001  # walk step, m
    sub = 4  # cv2 sub-pixel factor (shift = 2 bits)
    stack = []
    for _ in range(count):
        stack.append((rng.uniform(0, w), rng.uniform(0, h), rng.uniform(0, 2 * np.pi),
                      rng.uniform(0.0006, 0.0012), rng.uniform(0.05, 0.1), 1.0))
    for _ in range(count * 10):  # capillaries
        stack.append((rng.uniform(0, w), rng.uniform(0, h), rng.uniform(0, 2 * np.pi),
                      rng.uniform(0.0001, 0.0002), rng.uniform(0.006, 0.02), 0.55))
    while stack:
        x, y, heading, width_m, length_m, strength = stack.pop()
        steps = max(2, int(length_m / step_m))
        for k in range(steps):
            heading += rng.normal(0.0, 0.15)
            nx = x + math.cos(heading) * step_m / texel_m
            ny = y + math.sin(heading) * step_m / texel_m
            taper = width_m * (1.0 - 0.5 * k / steps)
            thick = max(1, round(taper / texel_m))
            start, end = (round(x * sub), round(y * sub)), (round(nx * sub), round(ny * sub))
            cv2.line(canvas, start, end, strength, thick, cv2.LINE_AA, 2)
            x, y = nx, ny
            if width_m > 0.0003 and rng.uniform() < 0.06:
                stack.append((x, y, heading + rng.choice([-1, 1]) * rng.uniform(0.4, 1.0),
                              taper * 0.6, length_m * 0.5, strength * 0.9))
    blur = max(0.5, 0.00012 / texel_m)
    return np.clip(cv2.GaussianBlur(canvas, (0, 0), blur), 0.0, 1.0)


def _tissue_texture(phantom: str, u_grid: np.ndarray, v_grid: np.ndarray, rng):
    """Surface maps over the (u, v) texel grid (T, S): albedo (T, S, 3) float32 linear RGB,
    wetness (T, S) float32 in [0, 1], and micro-relief slopes (dh/du, dh/dv) (T, S, 2) float32."""
    layout = _LAYOUTS[phantom]
    texel_m = float(u_grid[1] - u_grid[0])
    shape = (len(v_grid), len(u_grid))
    height = phantom_height(phantom, u_grid[None, :], v_grid[:, None])
    on_phantom = np.clip((height - 0.0005) / 0.0025, 0.0, 1.0).astype(np.float32)[..., None]
    blotch = _value_noise(rng, shape, 0.012 / texel_m)
    mottle = _value_noise(rng, shape, 0.003 / texel_m)
    grain = _value_noise(rng, shape, 0.0008 / texel_m)
    tint = np.clip(_value_noise(rng, shape, 0.02 / texel_m), -1.5, 1.5)[..., None]
    vessels = _vessel_map(rng, shape, texel_m, layout.vessel_count)
    shade = (1.0 + 0.14 * blotch + 0.06 * mottle + 0.025 * grain)[..., None]
    redder = np.array([0.04, -0.10, -0.08], np.float32)  # tint toward deeper red per unit of tint noise
    phantom_rgb = np.asarray(layout.tissue_rgb, np.float32) * (1.0 + redder * tint)
    tray_rgb = np.asarray(layout.tray_rgb, np.float32) * (1.0 + 2 * redder * tint)
    albedo = (phantom_rgb * on_phantom + tray_rgb * (1 - on_phantom)) * shade
    darken = np.asarray(layout.vessel_rgb, np.float32)  # albedo factor at a vessel's core
    albedo *= 1.0 - (1.0 - darken) * (0.85 * vessels)[..., None]
    wet = np.clip(0.6 + 0.35 * _value_noise(rng, shape, 0.004 / texel_m), 0.05, 1.0).astype(np.float32)
    bump = _value_noise(rng, shape, _BUMP_CELL_M / texel_m)
    slopes = np.stack(np.gradient(bump, texel_m)[::-1], axis=-1)
    slopes *= _BUMP_SLOPE / max(float(slopes.std()), 1e-9)
    return np.clip(albedo, 0.0, 1.0).astype(np.float32), wet, slopes.astype(np.float32)


class _Renderer:
    """Ray casts and shades the stereo pair of one frame; built once per session.

    Shading: each view is lit by a point light at its own centre (the endoscope's light guide),
    so light, view and half vectors coincide: radiance = (albedo (n.v) + broad + sharp specular)
    x (d0 / distance)^2 x vignetting, then a soft tone curve and gamma 2.
    """

    def __init__(self, params: SynthParams, camera: StereoCamera, frame: TissueFrame, rng: np.random.Generator):
        import open3d as o3d  # this module's job needs it; imported lazily to keep import cheap

        self.o3d = o3d
        self.params, self.camera, self.frame = params, camera, frame
        phantom = params.phantom
        h, w = camera.height, camera.width
        px_per_m = camera.fx / params.tissue_distance_m

        # Tissue grid: covers the base-plane footprint of both views' corners, with margin.
        corners = camera.pixel_rays(np.array([0, w - 1]), np.array([0, h - 1])).reshape(-1, 3).astype(np.float64)
        uv = []
        for origin in (np.zeros(3), np.array([camera.baseline_m, 0, 0])):
            t = ((frame.origin_m - origin) @ frame.normal) / (corners @ frame.normal)
            pu, pv, _ = frame.to_tissue(origin + t[:, None] * corners)
            uv.append(np.stack([pu, pv], 1))
        uv = np.concatenate(uv)
        margin = 0.012  # m
        (u0, v0), (u1, v1) = uv.min(0) - margin, uv.max(0) + margin
        cell = min(params.mesh_cell_px / px_per_m, _MAX_CELL_M)
        nu, nv = int(math.ceil((u1 - u0) / cell)) + 1, int(math.ceil((v1 - v0) / cell)) + 1
        self.u_grid, self.v_grid = np.linspace(u0, u1, nu), np.linspace(v0, v1, nv)
        self.nu, self.nv = nu, nv
        self.rest = surface_points(phantom, frame, self.u_grid[None, :], self.v_grid[:, None]).reshape(-1, 3)
        idx = np.arange(nu * nv, dtype=np.int64).reshape(nv, nu)
        a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel()
        self.triangles = np.stack([np.stack([a, b, c], 1), np.stack([d, c, b], 1)], 1).reshape(-1, 3).astype(np.uint32)

        # Surface maps over the same (u, v) rectangle.
        texel = _TEXEL_PX / px_per_m
        tw = min(_MAX_TEXTURE_PX, int(math.ceil((u1 - u0) / texel)) + 1)
        th = min(_MAX_TEXTURE_PX, int(math.ceil((v1 - v0) / texel)) + 1)
        albedo, wet, slopes = _tissue_texture(phantom, np.linspace(u0, u1, tw), np.linspace(v0, v1, th), rng)
        # Material maps: albedo BGR; broad and sharp specular weights; bump offsets of the normal (3D).
        self.albedo = np.ascontiguousarray(albedo[..., ::-1])
        self.specular = np.dstack([wet * _TISSUE.gloss, wet * _TISSUE.shine]).astype(np.float32)
        self.bump = (-(slopes[..., :1] * frame.e_u) - slopes[..., 1:] * frame.e_v).astype(np.float32)
        self.tex_scale = ((tw - 1) / (nu - 1), (th - 1) / (nv - 1))

        # Unit primitives for the tool.
        angles = np.linspace(0, 2 * np.pi, _CYL_SEGMENTS, endpoint=False)
        ring = np.stack([np.cos(angles), np.sin(angles)], 1)
        m = _CYL_SEGMENTS
        self.cyl_vertices = np.concatenate([np.c_[ring, np.zeros(m)], np.c_[ring, np.ones(m)], [[0, 0, 0], [0, 0, 1]]])
        k = np.arange(m)
        k1 = (k + 1) % m
        self.cyl_triangles = np.concatenate(
            [
                np.c_[k, k1, k + m],
                np.c_[k1, k1 + m, k + m],
                np.c_[np.full(m, 2 * m), k1, k],
                np.c_[np.full(m, 2 * m + 1), k + m, k1 + m],
            ]
        ).astype(np.uint32)
        sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=_SPHERE_RES)
        self.sphere_vertices = np.asarray(sphere.vertices, dtype=np.float64)
        self.sphere_triangles = np.asarray(sphere.triangles, dtype=np.uint32)

        # Rays, per-pixel view vectors and the coarse lattice of the adaptive tracer.
        self.dirs = camera.pixel_rays(np.arange(w), np.arange(h))
        inv_len = 1.0 / np.linalg.norm(self.dirs, axis=-1)
        self.to_eye = (-self.dirs * inv_len[..., None]).astype(np.float32)
        r2 = self.dirs[..., 0] ** 2 + self.dirs[..., 1] ** 2
        vignette = (1.0 + _VIGNETTE * r2) ** -2
        # Irradiance factor without the depth: (d0 / (z |dir|))^2 x vignetting = light_gain / z^2.
        self._rest_cache = None  # (scene, normal grid) of the undeformed tissue, built on first use
        self._ray_cache: dict = {}  # ray tensors of the full pixel grid / lattice, per view
        self.light_gain = (params.tissue_distance_m**2 * inv_len**2 * vignette * _EXPOSURE).astype(np.float32)
        # The lattice keeps its angular size: coarser images get a finer step (320 px wide: one ray per pixel).
        self.step = max(1, round(params.raycast_step_px * w / REFERENCE_WIDTH_PX))
        if self.step > 1:
            s = self.step
            ny, nx = (h - 1) // s + 2, (w - 1) // s + 2
            self.coarse_dirs = camera.pixel_rays(np.arange(nx) * s, np.arange(ny) * s)
            map_x = np.broadcast_to(np.arange(w, dtype=np.float32)[None, :] / s, (h, w))
            map_y = np.broadcast_to(np.arange(h, dtype=np.float32)[:, None] / s, (h, w))
            self.coarse_maps = cv2.convertMaps(np.ascontiguousarray(map_x), np.ascontiguousarray(map_y), cv2.CV_16SC2)

    # -- scene --------------------------------------------------------------------------------
    def _tissue_scene(self, vertices: np.ndarray):
        """Ray casting scene of the tissue mesh with these vertices (N, 3), m."""
        o3d = self.o3d
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(self.triangles))
        return scene

    def _tool_scene(self, parts: list[_Part]):
        """Ray casting scene of the tool; geometry k is parts[k]."""
        o3d = self.o3d
        scene = o3d.t.geometry.RaycastingScene()
        for part in parts:
            if part.kind == "cylinder":
                axis = part.b - part.a
                length = float(np.linalg.norm(axis))
                z = axis / length
                x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
                x /= np.linalg.norm(x)
                y = np.cross(z, x)
                local = self.cyl_vertices * np.array([part.radius, part.radius, length])
                verts = part.a + local @ np.stack([x, y, z])
                tris = self.cyl_triangles
            else:
                verts = part.a + self.sphere_vertices * part.radius
                tris = self.sphere_triangles
            scene.add_triangles(o3d.core.Tensor(verts.astype(np.float32)), o3d.core.Tensor(tris))
        return scene

    def _rays(self, origin: np.ndarray, dirs: np.ndarray, cache_key: str | None = None):
        """open3d ray tensor (M, 6) from one origin along dirs (M, 3); cached per (view, lattice)."""
        key = (cache_key, float(origin[0]))
        if cache_key is not None and key in self._ray_cache:
            return self._ray_cache[key]
        rays = np.empty((len(dirs), 6), np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = dirs
        tensor = self.o3d.core.Tensor.from_numpy(rays)
        if cache_key is not None:
            self._ray_cache[key] = (tensor, rays)  # keep the numpy buffer alive with its view
            return self._ray_cache[key]
        return tensor, rays

    def _cast(self, scenes, origin: np.ndarray, dirs: np.ndarray, cache_key: str | None = None):
        """Cast rays (M, 3) from origin into the (tissue, tool) scenes.

        Returns z-depth (M,) (inf = miss), geometry id (M,) (-1 miss, 0 tissue, k + 1 tool part k)
        and the tissue grid coordinates (i, j) of each hit (0 off the tissue).
        """
        tissue_scene, tool_scene = scenes
        rays_t, _ = self._rays(origin, dirs, cache_key)
        out = tissue_scene.cast_rays(rays_t)
        t = out["t_hit"].numpy()
        tool = tool_scene.cast_rays(rays_t)
        t_tool = tool["t_hit"].numpy()
        on_tool = t_tool < t
        gid = np.where(np.isfinite(t), 0, -1)
        gid[on_tool] = tool["geometry_ids"].numpy()[on_tool].astype(np.int64) + 1
        t = np.where(on_tool, t_tool, t)
        gi = np.zeros(len(t), np.float32)
        gj = np.zeros(len(t), np.float32)
        tissue = np.flatnonzero(gid == 0)
        # Grid triangles 2k and 2k+1 split cell k = (ci, cj); see the triangle list in __init__.
        prim = out["primitive_ids"].numpy()[tissue].astype(np.int32)
        bary = out["primitive_uvs"].numpy()[tissue]
        cell, second = prim // 2, (prim % 2) == 1
        ci, cj = cell // (self.nu - 1), cell % (self.nu - 1)
        gi[tissue] = np.where(second, ci + 1 - bary[:, 0], ci + bary[:, 0])
        gj[tissue] = np.where(second, cj + 1 - bary[:, 1], cj + bary[:, 1])
        return t, gid, gi, gj

    def _trace(self, scenes, origin: np.ndarray):
        """Per-pixel z-depth (H, W) float32 (0 = miss), geometry id (H, W) int64, grid coordinates.

        Adaptive: rays on a lattice every ``raycast_step_px`` px; a lattice cell whose four corners hit
        the same geometry at nearly the same inverse depth is filled by bilinear interpolation of
        inverse depth (exact on planes) and grid coordinates; every other pixel gets its own ray.
        """
        h, w = self.camera.height, self.camera.width
        if self.step == 1:
            t, gid, gi, gj = self._cast(scenes, origin, self.dirs.reshape(-1, 3), "full")
            z = np.where(np.isfinite(t), t, 0).astype(np.float32)
            return z.reshape(h, w), gid.reshape(h, w), gi.reshape(h, w), gj.reshape(h, w)
        s = self.step
        ny, nx = self.coarse_dirs.shape[:2]
        t, gid, gi, gj = self._cast(scenes, origin, self.coarse_dirs.reshape(-1, 3), "lattice")
        inv = np.where(np.isfinite(t), 1.0 / t, 0).astype(np.float32).reshape(ny, nx)
        g, gi, gj = gid.reshape(ny, nx), gi.reshape(ny, nx), gj.reshape(ny, nx)
        c00, c10, c01, c11 = g[:-1, :-1], g[1:, :-1], g[:-1, 1:], g[1:, 1:]
        same = (c00 == c10) & (c00 == c01) & (c00 == c11)
        i4 = np.stack([inv[:-1, :-1], inv[1:, :-1], inv[:-1, 1:], inv[1:, 1:]])
        # Inverse depth is linear in the image on a plane; a cell's relative spread above what a surface
        # at slope _GRAZING_SLOPE gives over the cell's width marks a depth edge (self-occlusion).
        tol = _GRAZING_SLOPE * s / self.camera.fx
        smooth = (i4.max(0) - i4.min(0)) <= tol * i4.max(0)
        # Trace cells next to a traced cell too: catches thin protrusions (a jaw tip) between lattice rays.
        ok = cv2.erode((same & smooth).astype(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE) > 0
        ok_px = np.repeat(np.repeat(ok, s, 0), s, 1)[:h, :w]
        gid_px = np.repeat(np.repeat(c00, s, 0), s, 1)[:h, :w].copy()
        map1, map2 = self.coarse_maps
        inv_px = cv2.remap(inv, map1, map2, cv2.INTER_LINEAR)
        gi_px = cv2.remap(gi, map1, map2, cv2.INTER_LINEAR)
        gj_px = cv2.remap(gj, map1, map2, cv2.INTER_LINEAR)
        bad = np.flatnonzero(~ok_px)
        if len(bad):
            tb, gb, gib, gjb = self._cast(scenes, origin, self.dirs.reshape(-1, 3)[bad])
            inv_px.reshape(-1)[bad] = np.where(np.isfinite(tb), 1.0 / tb, 0)
            gid_px.reshape(-1)[bad] = gb
            gi_px.reshape(-1)[bad] = gib
            gj_px.reshape(-1)[bad] = gjb
        hit = (gid_px >= 0) & (inv_px > 0)
        z = np.zeros((h, w), np.float32)
        np.divide(1.0, inv_px, out=z, where=hit)
        gid_px[~hit] = -1
        return z, gid_px, gi_px, gj_px

    # -- shading --------------------------------------------------------------------------------
    def _shade(self, origin, z, gid, gi, gj, normal_grid, parts):
        """BGR uint8 image (H, W, 3) and sharp specular radiance (H, W) float32 of one view."""
        grid_maps = cv2.convertMaps(gj, gi, cv2.CV_16SC2)
        tex_maps = cv2.convertMaps(gj * np.float32(self.tex_scale[0]), gi * np.float32(self.tex_scale[1]), cv2.CV_16SC2)
        normals = cv2.add(
            cv2.remap(normal_grid, *grid_maps, cv2.INTER_LINEAR), cv2.remap(self.bump, *tex_maps, cv2.INTER_LINEAR)
        )
        albedo = cv2.remap(self.albedo, *tex_maps, cv2.INTER_LINEAR)
        weights = cv2.remap(self.specular, *tex_maps, cv2.INTER_LINEAR)  # broad, sharp
        channel_sum = np.ones((1, 3), np.float32)
        cos_v = cv2.transform(cv2.multiply(normals, self.to_eye), channel_sum)
        length = cv2.sqrt(cv2.transform(cv2.multiply(normals, normals), channel_sum))
        cos_v = np.abs(cv2.divide(cos_v, length))  # two-sided
        broad = cos_v.copy()
        for _ in range(_TISSUE.gloss_squarings):
            broad *= broad
        sharp = broad.copy()
        for _ in range(_TISSUE.shine_squarings - _TISSUE.gloss_squarings):
            sharp *= sharp
        broad *= weights[..., 0]
        sharp *= weights[..., 1]

        # Tool pixels: analytic normals of the primitives, tool materials.
        tool_px = np.flatnonzero(gid > 0)
        tool_gid = gid.reshape(-1)[tool_px]
        flat_dirs, flat_eye = self.dirs.reshape(-1, 3), self.to_eye.reshape(-1, 3)
        for k, part in enumerate(parts):
            sel = tool_px[tool_gid == k + 1]
            if not len(sel):
                continue
            p = origin + flat_dirs[sel].astype(np.float64) * z.reshape(-1)[sel, None]
            if part.kind == "cylinder":
                d = part.b - part.a
                length = np.linalg.norm(d)
                d = d / length
                rel = p - part.a
                along = rel @ d
                radial = rel - along[:, None] * d
                rad = np.linalg.norm(radial, axis=1)
                nrm = radial / np.maximum(rad, 1e-9)[:, None]
                cap = rad < 0.97 * part.radius
                nrm[cap] = np.where((along[cap] < length / 2)[:, None], -d, d)
            else:
                nrm = (p - part.a) / np.linalg.norm(p - part.a, axis=1, keepdims=True)
            mat = _TOOL_MATERIALS[part.material]
            c = np.abs(np.sum(nrm * flat_eye[sel], axis=1)).astype(np.float32)
            cos_v.reshape(-1)[sel] = c
            broad.reshape(-1)[sel] = mat.gloss * c ** (2**mat.gloss_squarings)
            sharp.reshape(-1)[sel] = mat.shine * c ** (2**mat.shine_squarings)
            albedo.reshape(-1, 3)[sel] = mat.albedo[::-1]

        light = np.zeros_like(z)
        np.divide(self.light_gain, cv2.multiply(z, z), out=light, where=z > 0)  # 0 where nothing is hit
        sharp *= light
        diffuse = (cos_v + _AMBIENT) * light
        glints = (broad * cos_v) * light + sharp
        linear = cv2.add(cv2.multiply(albedo, cv2.merge([diffuse] * 3)), cv2.merge([glints] * 3))
        # Soft shoulder y = (1 + s) x / (1 + s x) (maps 1 to 1), then gamma 2 and 8 bits (saturating).
        toned = cv2.divide(linear, cv2.addWeighted(linear, _SHOULDER, linear, 0.0, 1.0), scale=1.0 + _SHOULDER)
        bgr = cv2.convertScaleAbs(cv2.sqrt(toned), alpha=255.0)
        return bgr, sharp

    def _normal_grid(self, vertices: np.ndarray) -> np.ndarray:
        """Unit vertex normals (nv, nu, 3) float32 of the tissue grid, pointing out of the tissue."""
        grid = vertices.reshape(self.nv, self.nu, 3)
        normal_grid = np.cross(np.gradient(grid, axis=0), np.gradient(grid, axis=1))
        normal_grid /= np.linalg.norm(normal_grid, axis=-1, keepdims=True)
        return normal_grid.astype(np.float32)

    def render(self, displacement: np.ndarray | None, parts: list[_Part]) -> dict[str, dict[str, np.ndarray]]:
        """Both views of one frame: BGR uint8 image, z-depth (0 = miss), tool mask, specular radiance.

        ``displacement`` (N, 3) moves the tissue vertices ``rest`` (m); None = undeformed, which
        reuses a cached scene (building the acceleration structure is a large part of a frame).
        """
        if displacement is None:
            if self._rest_cache is None:
                self._rest_cache = (self._tissue_scene(self.rest), self._normal_grid(self.rest))
            tissue_scene, normal_grid = self._rest_cache
        else:
            vertices = self.rest + displacement
            tissue_scene, normal_grid = self._tissue_scene(vertices), self._normal_grid(vertices)
        scenes = (tissue_scene, self._tool_scene(parts))
        views = {}
        for name, origin in (("left", np.zeros(3)), ("right", np.array([self.camera.baseline_m, 0.0, 0.0]))):
            z, gid, gi, gj = self._trace(scenes, origin)
            bgr, specular = self._shade(origin, z, gid, gi, gj, normal_grid, parts)
            views[name] = {"image": bgr, "z": z, "tool": gid > 0, "specular": specular}
        return views


# ----------------------------------------------------------------------------------------------
# 4. Files
# ----------------------------------------------------------------------------------------------


def davis_palette() -> list[int]:
    """The DAVIS / PASCAL VOC palette (768 ints): index 0 black, 1 dark red (the tool), ..."""
    palette = []
    for index in range(256):
        r = g = b = 0
        c = index
        for bit in range(8):
            r |= ((c >> 0) & 1) << (7 - bit)
            g |= ((c >> 1) & 1) << (7 - bit)
            b |= ((c >> 2) & 1) << (7 - bit)
            c >>= 3
        palette += [r, g, b]
    return palette


_SESSION_FILES = ("session.json", "K.txt", "force.csv", "truth.csv", "labels.csv")
_SESSION_DIRS = ("left", "right", "masks", "depth")


def _check_target(out_dir: Path, overwrite: bool) -> None:
    """Refuse a file, or a non-empty directory unless ``overwrite``; changes nothing."""
    if out_dir.exists() and not out_dir.is_dir():
        raise FileExistsError(f"{out_dir}: expected a directory (or a new path), found a file")
    if out_dir.exists() and any(out_dir.iterdir()) and not overwrite:
        raise FileExistsError(
            f"{out_dir}: expected an empty or new directory; pass overwrite=True to replace a session there"
        )


def _install(work: Path, out_dir: Path) -> None:
    """Move the finished session from ``work`` to ``out_dir``, session.json last.

    A new or empty ``out_dir`` is replaced by a rename; in an existing one (overwrite) the previous
    session's own files are removed first and other files are left alone.
    """
    if out_dir.is_dir() and not any(out_dir.iterdir()):
        out_dir.rmdir()
    if not out_dir.exists():
        work.rename(out_dir)
        return
    for name in _SESSION_FILES:
        (out_dir / name).unlink(missing_ok=True)
    for name in _SESSION_DIRS:
        if (out_dir / name).is_dir():
            shutil.rmtree(out_dir / name)
    for entry in sorted(work.iterdir(), key=lambda e: e.name == "session.json"):
        entry.rename(out_dir / entry.name)
    work.rmdir()


def _write_frame(out_dir: Path, stem: str, views, depth: np.ndarray, jpeg_quality: int, palette: list[int]) -> None:
    for name in ("left", "right"):
        path = out_dir / name / f"{stem}.jpg"
        if not cv2.imwrite(str(path), views[name]["image"], [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality]):
            raise OSError(f"{path}: could not write the JPEG image")
    mask = Image.fromarray(views["left"]["tool"].astype(np.uint8))
    mask.putpalette(palette)
    mask.save(out_dir / "masks" / f"{stem}.png", compress_level=1)
    np.save(out_dir / "depth" / f"{stem}.npy", depth.astype(np.float32))


def _write_tables(out_dir: Path, params: SynthParams, camera: StereoCamera, track: ToolTrack) -> None:
    with atomic_write(out_dir / "K.txt") as f:
        f.write(" ".join(f"{x:.10g}" for x in camera.K.ravel()) + "\n")
        f.write(f"{camera.baseline_m:.10g}\n")
    force = measured_force(track, params)
    with atomic_write(out_dir / "force.csv") as f:
        f.write("frame,fx,fy,fz\n")
        for i, (fx, fy, fz) in enumerate(force):
            f.write(f"{i},{fx:.6f},{fy:.6f},{fz:.6f}\n")
    magnitude = np.linalg.norm(track.force_true_n, axis=1)
    with atomic_write(out_dir / "truth.csv") as f:
        f.write("frame,timestamp,gap_m,indentation_m,force_true_n,contact,phase\n")
        for i in range(track.frames):
            f.write(
                f"{i},{track.timestamp_s[i]:.6f},{track.gap_m[i]:.6f},{track.indentation_m[i]:.6f},"
                f"{magnitude[i]:.6f},{int(track.contact[i])},{track.phase[i]}\n"
            )
    if params.task == "pulling":
        labels = manual_labels(track.contact, params.label_jitter_frames, _rng(params, _STREAM_LABELS))
        with atomic_write(out_dir / "labels.csv") as f:
            f.write("frame,contact\n")
            for i, label in enumerate(labels):
                f.write(f"{i},{label}\n")


def generate_session(
    out_dir: str | Path,
    params: SynthParams = SynthParams(),
    *,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Render a synthetic session into ``out_dir`` (created) and return its path.

    Writes session.json, K.txt (9 numbers of K row-major, then the baseline in m), left/ and
    right/ JPEGs, masks/ (palettized PNG, 1 = tool in the left view), depth/ (float32 z-depth in m,
    0 = hole, left view), force.csv (frame,fx,fy,fz in N), truth.csv
    (frame,timestamp,gap_m,indentation_m,force_true_n,contact,phase) and, for the glove (pulling
    task), labels.csv (frame,contact). Frame stems are 000000, 000001, ... ``progress(done, total)``
    is called after each frame. Raises FileExistsError for a non-empty ``out_dir`` unless
    ``overwrite`` (then the session files there are replaced; other files are left alone).
    """
    if not isinstance(params, SynthParams):
        raise TypeError(f"params must be a SynthParams, got {type(params).__name__}")
    out_dir = Path(out_dir)
    _check_target(out_dir, overwrite)
    # Everything is written into a hidden sibling folder and moved into place when complete, so
    # an interrupted run never leaves a partial session that reads like a whole one.
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.partial-", dir=out_dir.parent))
    try:
        _render_session(work, out_dir.resolve().name, params, progress)
        _install(work, out_dir)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    return out_dir


def true_depth(params: SynthParams, indices: Sequence[int]) -> dict[int, np.ndarray]:
    """The exact left-view z-depth (H, W) float32 m, 0 = miss, of frames ``indices`` of the session
    ``params`` makes (re-rendered: depth/ holds the stereo-like depth, with noise, bled tool edges
    and holes). For measuring a depth source against the truth (recipes/sgbm_study.py)."""
    camera, frame = stereo_camera(params), tissue_frame(params)
    track = plan_tool_track(params)
    renderer = _Renderer(params, camera, frame, _rng(params, _STREAM_TEXTURE))
    out = {}
    for i in indices:
        i = int(i)
        deformed = track.press_m[i] > 0 or bool(np.any(track.pull_m[i]))
        displacement = tissue_displacement(renderer.rest, track, i, params) if deformed else None
        out[i] = renderer.render(displacement, tool_parts(track, i, params))["left"]["z"].astype(np.float32)
    return out


def _render_session(out_dir: Path, name: str, params: SynthParams,
                    progress: Callable[[int, int], None] | None) -> None:
    """Write the whole session into the (new, empty) folder ``out_dir``."""
    for sub in _SESSION_DIRS:
        (out_dir / sub).mkdir()
    camera, frame = stereo_camera(params), tissue_frame(params)
    track = plan_tool_track(params)
    renderer = _Renderer(params, camera, frame, _rng(params, _STREAM_TEXTURE))
    palette = davis_palette()
    _write_tables(out_dir, params, camera, track)

    pending: list[Future] = []
    with ThreadPoolExecutor(max_workers=1) as writer:
        for i in range(params.frames):
            deformed = track.press_m[i] > 0 or bool(np.any(track.pull_m[i]))
            displacement = tissue_displacement(renderer.rest, track, i, params) if deformed else None
            views = renderer.render(displacement, tool_parts(track, i, params))
            left = views["left"]
            depth = stereo_depth(
                left["z"], views["right"]["z"], left["tool"], left["specular"], camera, params,
                _rng(params, _STREAM_DEPTH, i),
            )
            pending.append(writer.submit(_write_frame, out_dir, f"{i:06d}", views, depth, params.jpeg_quality, palette))
            while pending and pending[0].done():
                pending.pop(0).result()
            if len(pending) > 2:  # bound memory: wait for the writer
                pending.pop(0).result()
            if progress is not None:
                progress(i + 1, params.frames)
        for fut in pending:
            fut.result()

    session = {
        "name": name,
        "phantom": params.phantom,
        "task": params.task,
        "fps": params.fps,
        "generator": to_dict(params),
    }
    write_json(out_dir / "session.json", session)
