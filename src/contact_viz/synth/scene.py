"""Scene geometry (pure numpy): the stereo camera, the tissue base plane, the phantoms' height
fields and closest points on their surfaces."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from contact_viz.synth.params import PHANTOMS, SynthParams


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
    """Frame of the tissue base plane: a point is origin + scale (u e_u + v e_v + w normal).

    Tissue coordinates (u, v, w) are phantom units: metres of the phantom as designed (its height
    field, where the tool works); ``scale`` (``SynthParams.scene_scale``) makes them camera-frame metres.
    """

    origin_m: np.ndarray  # (3,) phantom centre on the base plane, m
    e_u: np.ndarray  # (3,) in-plane unit vector along image x
    e_v: np.ndarray  # (3,) in-plane unit vector roughly along image y (down)
    normal: np.ndarray  # (3,) unit normal of the base plane, toward the camera
    scale: float = 1.0  # camera-frame metres per phantom unit, -

    def to_camera(self, u: np.ndarray, v: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Camera-frame points (..., 3), m, of tissue coordinates u, v, w (phantom units)."""
        u, v, w = (self.scale * np.asarray(a, dtype=np.float64)[..., None] for a in (u, v, w))
        return self.origin_m + u * self.e_u + v * self.e_v + w * self.normal

    def to_tissue(self, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Tissue coordinates (u, v, w) (phantom units), each (...), of camera-frame points (..., 3), m."""
        d = np.asarray(points_m, dtype=np.float64) - self.origin_m
        return d @ self.e_u / self.scale, d @ self.e_v / self.scale, d @ self.normal / self.scale


_PHANTOM_CENTRE_HEIGHT_M = 0.015  # the point this high above the phantom centre is on the optical axis, phantom units


def tissue_frame(params: SynthParams) -> TissueFrame:
    """Base plane at ``tissue_distance_m`` along the optical axis, tilted so the image top recedes,
    with the phantom at ``params.scene_scale``.

    The origin (the phantom centre) is placed so that the point ``_PHANTOM_CENTRE_HEIGHT_M`` above
    it lies on the optical axis: the top of the phantom appears near the image centre.
    """
    tilt = math.radians(params.tissue_tilt_deg)
    normal = np.array([0.0, -math.sin(tilt), -math.cos(tilt)])
    scale = params.scene_scale
    centre_height_m = scale * _PHANTOM_CENTRE_HEIGHT_M
    on_axis_z = params.tissue_distance_m + centre_height_m / normal[2]
    return TissueFrame(
        origin_m=np.array([0.0, 0.0, on_axis_z]) - centre_height_m * normal,
        e_u=np.array([1.0, 0.0, 0.0]),
        e_v=np.array([0.0, math.cos(tilt), -math.sin(tilt)]),
        normal=normal,
        scale=scale,
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
    """Height (>= 0) of the phantom above its base plane at tissue coordinates (u, v), all in phantom
    units (metres as designed; ``TissueFrame.scale`` makes them camera-frame metres).

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


_GRAD_STEP_M = 1e-5  # central-difference step for height gradients, phantom units


def height_gradient(phantom: str, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(dh/du, dh/dv) of the phantom height, central differences, dimensionless."""
    step = _GRAD_STEP_M
    dh_du = (phantom_height(phantom, u + step, v) - phantom_height(phantom, u - step, v)) / (2 * step)
    dh_dv = (phantom_height(phantom, u, v + step) - phantom_height(phantom, u, v - step)) / (2 * step)
    return dh_du, dh_dv


def surface_points(phantom: str, frame: TissueFrame, u_m: np.ndarray, v_m: np.ndarray) -> np.ndarray:
    """Camera-frame points (..., 3), m, of the undeformed phantom surface at (u, v) (phantom units)."""
    return frame.to_camera(u_m, v_m, phantom_height(phantom, u_m, v_m))


def surface_normals(phantom: str, frame: TissueFrame, u_m: np.ndarray, v_m: np.ndarray) -> np.ndarray:
    """Unit normals (..., 3) of the undeformed surface at (u, v), pointing out of the tissue."""
    dh_du, dh_dv = height_gradient(phantom, np.asarray(u_m, float), np.asarray(v_m, float))
    n = frame.normal - dh_du[..., None] * frame.e_u - dh_dv[..., None] * frame.e_v
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


_CLOSEST_GRID = 25  # samples per side of each grid-search window, count
_CLOSEST_ROUNDS = 5  # refinement rounds of the grid search, count


def closest_surface_points(
    phantom: str, frame: TissueFrame, points_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Closest points of the undeformed surface to camera-frame points (M, 3), m.

    Returns (closest (M, 3) m, their unit normals (M, 3), signed distance (M,) m: positive
    outside the tissue, (u, v) of the closest points (M, 2) in phantom units). The closest point lies
    within the vertical distance |w - h(u, v)| of (u, v) in the base plane, so a grid search over that window,
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
