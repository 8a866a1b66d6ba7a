"""Sensor models (pure numpy/cv2): stereo depth noise and holes, force noise, manual-style labels."""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from contact_viz.synth.motion import ToolTrack
from contact_viz.synth.params import REFERENCE_WIDTH_PX, SynthParams, STREAM_FORCE, stream_rng
from contact_viz.synth.scene import StereoCamera


def scene_force(tracks: ToolTrack | Sequence[ToolTrack]) -> np.ndarray:
    """The true contact force (F, 3), N, on all the instruments together (one track: its own)."""
    if isinstance(tracks, ToolTrack):
        return tracks.force_true_n
    total = tracks[0].force_true_n
    for track in tracks[1:]:
        total = total + track.force_true_n
    return total


def measured_force(tracks: ToolTrack | Sequence[ToolTrack], params: SynthParams) -> np.ndarray:
    """Force sensor readings (F, 3), N: the true force plus Gaussian noise per axis.

    The sensor is the scene's: given every instrument's track it reads the total contact force of
    all of them (``scene_force``; with two instruments, the sum of both).
    """
    force = scene_force(tracks)
    rng = stream_rng(params, STREAM_FORCE)
    return force + rng.normal(0.0, params.force_noise_n, force.shape)


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


_NO_TOOL_DEPTH = np.float32(np.finfo(np.float32).max)  # "no tool depth here"; also what cv2.erode pads with


def spread_tool_depth(depth_m: np.ndarray, tool: np.ndarray, px: int) -> np.ndarray:
    """``depth_m`` (H, W) float m, 0 = hole, with the tool's depth bled ``px`` px past its silhouette:
    every background pixel within ``px`` (elliptic disc) of a tool pixel with depth takes the smallest
    such tool depth; pixels with no tool depth within reach keep theirs. Returns a new array.

    (cv2.erode pads the image with FLT_MAX, not inf: with inf as "no tool depth", a pixel at the image
    border whose tool neighbours are all holes took 3.4e38 m.)
    """
    out = np.array(depth_m, copy=True)
    tool = np.asarray(tool, dtype=bool)
    if px <= 0 or not tool.any():
        return out
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * px + 1, 2 * px + 1))
    tool_depth = np.where(tool & (out > 0), out, _NO_TOOL_DEPTH).astype(np.float32)
    spread = cv2.erode(tool_depth, kernel)
    take = ~tool & (spread < _NO_TOOL_DEPTH)
    out[take] = spread[take]
    return out


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
        depth = spread_tool_depth(depth, tool_left, fatten)

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
