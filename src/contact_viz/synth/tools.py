"""The instruments as primitives (pure numpy): the cylinders and spheres a tool is made of
(``tool_primitives``, what the renderer meshes), exact ray casting of them without the tissue
(``cast_tools``: per-pixel tool id and z-depth), and the 3D distance between two tools
(``tool_distance``). Used to place the second instrument (``synth.second``) and by the tests."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from contact_viz.synth.motion import SHAFT_LENGTH_M, ToolTrack
from contact_viz.synth.params import SynthParams
from contact_viz.synth.scene import StereoCamera


@dataclass(frozen=True, eq=False)
class Primitive:
    """One primitive of a tool: a solid cylinder a->b (flat caps) or a sphere at a."""

    kind: str  # "cylinder" or "sphere"
    a: np.ndarray  # cylinder start or sphere centre, m
    b: np.ndarray | None  # cylinder end, m
    radius: float  # m
    material: int  # 0 shaft, 1 wrist, 2 jaw (the renderer's material index)


def tool_primitives(track: ToolTrack, index: int, params: SynthParams) -> list[Primitive]:
    """The tool of frame ``index`` as primitives: shaft, wrist and two capsule jaws (cylinder + tip sphere)."""
    axis, hinge = track.axis[index], track.hinge_m[index]
    wrist_end = hinge - axis * params.wrist_length_m
    parts = [
        Primitive("cylinder", wrist_end, wrist_end - axis * SHAFT_LENGTH_M, params.shaft_diameter_m / 2, 0),
        Primitive("cylinder", hinge + axis * 0.0015, wrist_end, params.wrist_radius_m, 1),
    ]
    for base, tip in zip(track.jaw_bases_m[index], track.jaw_tips_m[index]):
        parts.append(Primitive("cylinder", base, tip, params.jaw_radius_m, 2))
        parts.append(Primitive("sphere", tip, None, params.jaw_radius_m, 2))
    return parts


def _ray_cylinder(origin: np.ndarray, d: np.ndarray, a: np.ndarray, b: np.ndarray, r: float) -> np.ndarray:
    """Ray parameter (M,) of the first hit of rays origin + t d (d (M, 3)) with the solid cylinder a->b of
    radius r (flat caps); inf = miss."""
    ba = b - a
    length = float(np.linalg.norm(ba))
    u = ba / length
    oc = origin - a
    d_par = d @ u
    oc_par = float(oc @ u)
    d_perp = d - d_par[:, None] * u
    oc_perp = oc - oc_par * u
    qa = np.einsum("ij,ij->i", d_perp, d_perp)
    qb = d_perp @ oc_perp
    qc = float(oc_perp @ oc_perp) - r * r
    disc = qb * qb - qa * qc
    parallel = qa < 1e-18
    with np.errstate(divide="ignore", invalid="ignore"):
        root = np.sqrt(np.maximum(disc, 0.0))
        t_in = np.where(parallel, -np.inf, (-qb - root) / qa)
        t_out = np.where(parallel, np.inf, (-qb + root) / qa)
        s0, s1 = (0.0 - oc_par) / d_par, (length - oc_par) / d_par
    inside_slab = 0.0 <= oc_par <= length
    flat = np.abs(d_par) < 1e-18
    lo = np.where(flat, -np.inf if inside_slab else np.inf, np.minimum(s0, s1))
    hi = np.where(flat, np.inf if inside_slab else -np.inf, np.maximum(s0, s1))
    enter, leave = np.maximum(t_in, lo), np.minimum(t_out, hi)
    hit = np.where(parallel, qc <= 0, disc >= 0) & (enter <= leave) & (leave > 0)
    return np.where(hit, np.where(enter > 0, enter, leave), np.inf)


def _ray_sphere(origin: np.ndarray, d: np.ndarray, c: np.ndarray, r: float) -> np.ndarray:
    """Ray parameter (M,) of the first hit of rays origin + t d with the sphere (c, r); inf = miss."""
    oc = origin - c
    qa = np.einsum("ij,ij->i", d, d)
    qb = d @ oc
    qc = float(oc @ oc) - r * r
    disc = qb * qb - qa * qc
    root = np.sqrt(np.maximum(disc, 0.0))
    t0, t1 = (-qb - root) / qa, (-qb + root) / qa
    return np.where((disc >= 0) & (t1 > 0), np.where(t0 > 0, t0, t1), np.inf)


def cast_tools(
    tools: Sequence[Sequence[Primitive]], camera: StereoCamera, cols: np.ndarray, rows: np.ndarray,
    origin: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact ray casting of the tools alone (no tissue) through the pixels (``rows[k]``, ``cols[k]``)
    (1-D arrays of equal length, pixel centres) of a view with centre ``origin`` (default: the left one).

    Returns the id (M,) uint8 of the nearest tool hit (k + 1 for ``tools[k]``, 0 = none) and its
    z-depth (M,) float64, m (inf = none). The renderer meshes the same primitives (48-gon cylinders,
    a UV sphere), so its silhouettes lie within a few micrometres of these.
    """
    origin = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
    cols = np.asarray(cols, dtype=np.float64).ravel()
    rows = np.asarray(rows, dtype=np.float64).ravel()
    d = np.stack([(cols - camera.K[0, 2]) / camera.K[0, 0], (rows - camera.K[1, 2]) / camera.K[1, 1],
                  np.ones_like(cols)], axis=1)
    best = np.full(len(cols), np.inf)
    ids = np.zeros(len(cols), np.uint8)
    for k, parts in enumerate(tools):
        for part in parts:
            if part.kind == "cylinder":
                t = _ray_cylinder(origin, d, part.a, part.b, part.radius)
            else:
                t = _ray_sphere(origin, d, part.a, part.radius)
            nearer = t < best
            best = np.where(nearer, t, best)
            ids[nearer] = k + 1
    return ids, best  # d has z = 1: the ray parameter is the z-depth


def cast_tools_image(tools: Sequence[Sequence[Primitive]], camera: StereoCamera) -> tuple[np.ndarray, np.ndarray]:
    """``cast_tools`` over the whole left image: ids (H, W) uint8 and z (H, W) float64 (inf = none)."""
    rows, cols = np.mgrid[: camera.height, : camera.width]
    ids, z = cast_tools(tools, camera, cols.ravel(), rows.ravel())
    return ids.reshape(camera.height, camera.width), z.reshape(camera.height, camera.width)


def capsules(track: ToolTrack, params: SynthParams) -> tuple[np.ndarray, np.ndarray]:
    """The tool of every frame as 4 capsules containing it (shaft, wrist, two jaws with their tip
    spheres): segment ends (F, 4, 2, 3), m, and radii (4,), m."""
    axis, hinge = track.axis, track.hinge_m
    wrist_end = hinge - axis * params.wrist_length_m
    ends = np.empty((track.frames, 4, 2, 3))
    ends[:, 0, 0], ends[:, 0, 1] = wrist_end, wrist_end - axis * SHAFT_LENGTH_M
    ends[:, 1, 0], ends[:, 1, 1] = hinge + axis * 0.0015, wrist_end
    ends[:, 2:, 0], ends[:, 2:, 1] = track.jaw_bases_m, track.jaw_tips_m
    radii = np.array([params.shaft_diameter_m / 2, params.wrist_radius_m, params.jaw_radius_m, params.jaw_radius_m])
    return ends, radii


def segment_distance(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Distance (...) between the segments p1-q1 and p2-q2 (each (..., 3), non-degenerate)
    (Ericson, Real-Time Collision Detection, 5.1.9)."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a = np.sum(d1 * d1, -1)
    e = np.sum(d2 * d2, -1)
    f = np.sum(d2 * r, -1)
    c = np.sum(d1 * r, -1)
    b = np.sum(d1 * d2, -1)
    denom = a * e - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 1e-30 * a * e, np.clip((b * f - c * e) / denom, 0.0, 1.0), 0.0)
        t = (b * s + f) / e
        s = np.where(t < 0, np.clip(-c / a, 0.0, 1.0), np.where(t > 1, np.clip((b - c) / a, 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    return np.linalg.norm(p1 + d1 * s[..., None] - (p2 + d2 * t[..., None]), axis=-1)


def tool_distance(first: ToolTrack, second: ToolTrack, params: SynthParams,
                  frames: np.ndarray | slice = slice(None)) -> np.ndarray:
    """Lower bound (F,) of the 3D distance between the surfaces of two tools in each frame, m
    (between the capsules that contain them; <= 0 means they may touch)."""
    e1, r1 = capsules(first, params)
    e2, r2 = capsules(second, params)
    e1, e2 = e1[frames], e2[frames]
    p1, q1 = e1[:, :, None, 0], e1[:, :, None, 1]
    p2, q2 = e2[:, None, :, 0], e2[:, None, :, 1]
    gaps = segment_distance(p1, q1, p2, q2) - r1[None, :, None] - r2[None, None, :]
    return gaps.reshape(len(gaps), -1).min(axis=1)
