"""Failure injection: a copy of a session with one realistic failure put into chosen frames.

Used to measure the diagnostics (tests/test_failure_injection.py, benchmarks/bench_diagnostics.py):
each of :data:`FAULT_KINDS` is what really goes wrong with SAM2 masks, learned stereo depth and
recorders. :func:`inject_fault` never touches the source session: unchanged files are hard-linked
(or copied) into the new session, changed ones written fresh there.

Severity (``Fault.severity``) by kind, in the session's own pixels where it is a length:

* ``mask_dropout``: unused (the mask is emptied).
* ``mask_drift``: shift of the mask, px (mostly across the tool's axis, so it leaves the tool).
* ``mask_bleed``: radius of a lobe of tissue added to the mask at its edge, px.
* ``second_object``: radius of an extra blob (another instrument's tip, a wrong object), px.
* ``depth_holes``: share of the tool and the band around it (up to 2 shaft widths) made invalid, 0-1.
* ``edge_bleeding``: how far the tool's depth is smeared past its silhouette onto tissue, px.
* ``depth_scale``: factor the depth is multiplied by (wrong baseline / focal length); 0 = disparity
  read as depth (depth = fx * baseline / depth, in px read as m).
* ``depth_misregistration``: shift of the depth map against image and mask, px.
* ``force_offset``: shift of the force stream, frames (force of frame i is that of frame i - k): the
  whole session.
* ``frozen_depth``: unused (the depth of the frame before the first injected frame is repeated).

Two more need a session of several instruments (:data:`MULTI_FAULT_KINDS`; masks with object ids 1 and
2, e.g. ``SynthParams(tools=2)``); what the segmenter (SAM2) gets wrong there:

* ``id_swap``: unused; the object ids of two instruments (1 and 2) are exchanged in the injected frames
  (the segmenter's identity switch; the ids return after them).
* ``tools_merged``: unused; one instrument takes in the other's pixels in the injected frames (both written
  with one id, the other id gone). Which one (1 or 2) is drawn from the seed; the returned
  ``Fault.severity`` is its id.

The mask faults of one instrument change object id 1 (``target_id``) and leave the others as they are.

One is a failure of the stereo pair (:data:`PAIR_FAULT_KINDS`), usually injected into every frame:

* ``vertical_offset``: the right images moved down by this many px (up when negative; a fraction is
  interpolated bilinearly), the left ones unchanged: the pair is no longer rectified (a wrong or stale
  calibration), which the ``not_rectified`` session check measures.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from contact_viz.io.atomic import atomic_write
from contact_viz.synth.sensors import spread_tool_depth

__all__ = ["ALL_FAULT_KINDS", "FAULT_KINDS", "MULTI_FAULT_KINDS", "PAIR_FAULT_KINDS", "Fault", "inject_fault",
           "perturb_session", "read_mask_ids", "read_truth_phases", "shift_rows"]

FAULT_KINDS = (
    "mask_dropout", "mask_drift", "mask_bleed", "second_object", "depth_holes", "edge_bleeding",
    "depth_scale", "depth_misregistration", "force_offset", "frozen_depth",
)
MULTI_FAULT_KINDS = ("id_swap", "tools_merged")  # failures of masks with several instruments (object ids)
PAIR_FAULT_KINDS = ("vertical_offset",)  # failures of the stereo pair (its rectification), usually on every frame
ALL_FAULT_KINDS = FAULT_KINDS + MULTI_FAULT_KINDS + PAIR_FAULT_KINDS
MASK_FAULTS = ("mask_dropout", "mask_drift", "mask_bleed", "second_object")
DEPTH_FAULTS = ("depth_holes", "edge_bleeding", "depth_scale", "depth_misregistration", "frozen_depth")


@dataclass(frozen=True)
class Fault:
    """One injected failure: its kind, the frames it covers and its size (see the module docstring)."""

    kind: str
    frames: tuple[int, ...]  # injected frame indices (every frame for force_offset)
    severity: float  # kind-specific size, see the module docstring


def read_truth_phases(session_dir: str | Path) -> list[str]:
    """The ``phase`` column of a synthetic session's truth.csv, one entry per frame."""
    with (Path(session_dir) / "truth.csv").open(newline="") as handle:
        return [row["phase"] for row in csv.DictReader(handle)]


def _link_tree(src: Path, dst: Path) -> None:
    for path in src.rglob("*"):
        target = dst / path.relative_to(src)
        if path.is_dir():
            target.mkdir(parents=True, exist_ok=True)
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(path, target)
        except OSError:
            shutil.copy2(path, target)


def without_depth(src: str | Path, dst: str | Path) -> Path:
    """A copy of session ``src`` at ``dst`` without depth/ (hard links where possible): a stereo-only session,
    whose depth contact-viz's SGBM computes. Reused when ``dst`` is a session already; written under a hidden
    name and renamed into place when complete."""
    src, dst = Path(src), Path(dst)
    if (dst / "session.json").is_file():
        return dst
    tmp = dst.with_name(f".{dst.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    for path in sorted(src.rglob("*")):
        rel = path.relative_to(src)
        if rel.parts[0] == "depth" or path.is_dir():
            continue
        target = tmp / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(path, target)
        except OSError:
            shutil.copy2(path, target)
    tmp.rename(dst)
    return dst


def _replace(path: Path, write, mode: str = "wb") -> None:
    """Write a new file at ``path`` (breaking a hard link, never writing through it): ``write(handle)``
    into a staging file that is renamed onto ``path`` (contact_viz.io.atomic.atomic_write)."""
    with atomic_write(path, mode, **({"newline": ""} if "b" not in mode else {})) as handle:
        write(handle)


def _npy_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()  # np.save into a real file reports a full disk without its errno
    np.save(buffer, array)
    return buffer.getvalue()


def read_mask_ids(path: str | Path) -> tuple[np.ndarray, Image.Image]:
    """(object ids (H, W) uint8, the image) of a mask file: palettized / single-channel values as they are
    (0 = background), a binary 0/255 mask as id 1."""
    image = Image.open(path)
    image.load()
    ids = np.asarray(image)
    if ids.ndim == 3:
        ids = ids[..., 0]
    if image.mode != "P" and ids.max() == 255 and np.isin(ids, (0, 255)).all():
        ids = (ids > 0).astype(np.uint8)
    return ids.astype(np.uint8), image


def _read_mask(path: Path, target_id: int = 1) -> tuple[np.ndarray, Image.Image, np.ndarray]:
    """(the target instrument's mask, the image, every object id) of a mask file. With one instrument
    the target is every mask pixel (whatever its value)."""
    ids, image = read_mask_ids(path)
    several = np.unique(ids[ids > 0]).size > 1
    return (ids == target_id) if several else ids > 0, image, ids


def _write_ids(path: Path, ids: np.ndarray, like: Image.Image) -> None:
    values = ids.astype(np.uint8)
    if like.mode != "P" and values.max(initial=0) <= 1:
        values = values * 255  # a binary mask stays 0/255
    out = Image.fromarray(values, mode="L")
    if like.mode == "P":
        out = out.convert("P")
        out.putpalette(like.getpalette())
    _replace(path, lambda handle: out.save(handle, format="PNG"))


def _write_mask(path: Path, mask: np.ndarray, like: Image.Image, ids: np.ndarray | None = None,
                target_id: int = 1) -> None:
    """Write the target instrument's new ``mask`` into the mask file (the other instruments' ids kept)."""
    if ids is None or np.unique(ids[ids > 0]).size <= 1:
        _write_ids(path, mask.astype(np.uint8), like)
        return
    out = np.where(ids == target_id, 0, ids)
    out[mask] = target_id
    _write_ids(path, out, like)


def _write_depth(path: Path, depth: np.ndarray) -> None:
    _replace(path, lambda handle: handle.write(_npy_bytes(depth.astype(np.float32))))


def _shift(array: np.ndarray, dx: int, dy: int, fill) -> np.ndarray:
    out = np.full_like(array, fill)
    h, w = array.shape[:2]
    ys, yd = (slice(0, h - dy), slice(dy, h)) if dy >= 0 else (slice(-dy, h), slice(0, h + dy))
    xs, xd = (slice(0, w - dx), slice(dx, w)) if dx >= 0 else (slice(-dx, w), slice(0, w + dx))
    out[yd, xd] = array[ys, xs]
    return out


def shift_rows(image: np.ndarray, px: float) -> np.ndarray:
    """``image`` moved down by ``px`` rows (up when negative; a fraction is interpolated bilinearly), the rows it
    uncovers repeating the edge row; same shape and dtype."""
    height, width = image.shape[:2]
    move = np.float32([[1, 0, 0], [0, 1, px]])
    return cv2.warpAffine(image, move, (width, height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _jpeg_quality(session: Path) -> int:
    """The JPEG quality a synthetic session was written at (session.json), else 92."""
    try:
        return int(json.loads((session / "session.json").read_text())["generator"]["jpeg_quality"])
    except (OSError, ValueError, KeyError, TypeError):
        return 92


def _write_image(path: Path, image: np.ndarray, quality: int) -> None:
    """Encode ``image`` (as cv2 reads it) into ``path`` by its suffix (JPEG at ``quality``)."""
    jpeg = path.suffix.lower() != ".png"
    ok, data = cv2.imencode(path.suffix, image, [cv2.IMWRITE_JPEG_QUALITY, quality] if jpeg else [])
    if not ok:
        raise RuntimeError(f"{path}: OpenCV could not encode the image again")
    _replace(path, lambda handle: handle.write(data.tobytes()))


def _axis(mask: np.ndarray) -> np.ndarray:
    """Unit vector (x, y) of the mask's main axis (PCA of its pixels)."""
    ys, xs = np.nonzero(mask)
    if xs.size < 3:
        return np.array([1.0, 0.0])
    cov = np.cov(np.stack([xs, ys]).astype(np.float64))
    values, vectors = np.linalg.eigh(cov)
    return vectors[:, int(np.argmax(values))]


def _disc(shape, centre_xy, radius_px: float, aspect: float = 1.0, angle_deg: float = 0.0) -> np.ndarray:
    out = np.zeros(shape, np.uint8)
    axes = (max(1, round(radius_px)), max(1, round(radius_px * aspect)))
    cv2.ellipse(out, (int(round(centre_xy[0])), int(round(centre_xy[1]))), axes, angle_deg, 0, 360, 1, -1)
    return out > 0


def _mask_fault(kind: str, mask: np.ndarray, severity: float, rng: np.random.Generator) -> np.ndarray:
    h, w = mask.shape
    if kind == "mask_dropout":
        return np.zeros_like(mask)
    if kind == "mask_drift":
        across = _axis(mask)[::-1] * np.array([-1.0, 1.0])  # perpendicular to the axis
        angle = rng.uniform(-math.pi / 4, math.pi / 4) + (math.pi if rng.random() < 0.5 else 0.0)
        c, s = math.cos(angle), math.sin(angle)
        direction = np.array([c * across[0] - s * across[1], s * across[0] + c * across[1]])
        dx, dy = (int(round(v)) for v in severity * direction)
        return _shift(mask, dx, dy, False)
    if kind == "mask_bleed":
        edge = mask & ~cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        margin = int(severity) + 2
        edge[:margin], edge[-margin:], edge[:, :margin], edge[:, -margin:] = False, False, False, False
        ys, xs = np.nonzero(edge)
        if xs.size == 0:
            return mask
        k = int(rng.integers(xs.size))
        dist = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5)
        # centre of the lobe: outside the tool, about 0.6 radius beyond the edge point, away from the mask
        gy, gx = np.gradient(dist)
        normal = np.array([gx[ys[k], xs[k]], gy[ys[k], xs[k]]])
        normal = normal / (np.linalg.norm(normal) or 1.0)
        centre = np.array([xs[k], ys[k]]) + 0.6 * severity * normal
        return mask | _disc(mask.shape, centre, severity, rng.uniform(0.6, 1.0), rng.uniform(0, 180))
    if kind == "second_object":
        dist = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5)
        margin = int(severity) + 3
        ok = dist > 2.5 * severity + 6
        ok[:margin], ok[-margin:], ok[:, :margin], ok[:, -margin:] = False, False, False, False
        ys, xs = np.nonzero(ok)
        if xs.size == 0:
            return mask
        k = int(rng.integers(xs.size))
        return mask | _disc(mask.shape, (xs[k], ys[k]), severity, rng.uniform(0.4, 1.0), rng.uniform(0, 180))
    raise ValueError(f"not a mask fault: {kind!r}")


def _depth_fault(kind: str, depth: np.ndarray, mask: np.ndarray, severity: float, fx_b: float,
                 rng: np.random.Generator) -> np.ndarray:
    depth = depth.copy()
    if kind == "depth_holes":
        inside = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 5)
        width = 2 * float(cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 5).max())
        region = inside <= max(2.0 * width, 6.0)
        noise = cv2.GaussianBlur(rng.standard_normal(depth.shape).astype(np.float32), (0, 0), 3)
        cut = np.quantile(noise[region], 1.0 - severity) if region.any() else np.inf
        depth[region & (noise >= cut)] = 0.0
        return depth
    if kind == "edge_bleeding":
        return spread_tool_depth(depth, mask, int(round(severity)))
    if kind == "depth_scale":
        valid = depth > 0
        if severity == 0:  # disparity (px) read as depth (m)
            depth[valid] = fx_b / depth[valid]
        else:
            depth[valid] *= severity
        return depth
    if kind == "depth_misregistration":
        angle = rng.uniform(0, 2 * math.pi)
        dx, dy = int(round(severity * math.cos(angle))), int(round(severity * math.sin(angle)))
        if dx == 0 and dy == 0:
            dx = int(round(severity))
        return _shift(depth, dx, dy, np.float32(0.0))
    raise ValueError(f"not a depth fault: {kind!r}")


def inject_fault(src: str | Path, dst: str | Path, kind: str, frames, severity: float = 0.0,
                 seed: int = 0) -> Fault:
    """Copy the session ``src`` to ``dst`` (which must not exist) with ``kind`` injected into ``frames``.

    ``frames``: frame indices (positions in the sorted stems). ``severity``: see the module docstring.
    Returns the :class:`Fault`; for ``force_offset`` its frames are all frames of the session.
    """
    if kind not in ALL_FAULT_KINDS:
        raise ValueError(f"kind must be one of {ALL_FAULT_KINDS}, got {kind!r}")
    src, dst = Path(src), Path(dst)
    if dst.exists():
        raise ValueError(f"{dst}: already exists")
    stems = sorted((p.stem for p in (src / "left").iterdir() if not p.name.startswith(".")), key=int)
    frames = tuple(sorted(int(i) for i in frames))
    rng = np.random.default_rng(seed)
    _link_tree(src, dst)
    K_line, baseline_line = (src / "K.txt").read_text().splitlines()[:2]
    fx_b = float(K_line.split()[0]) * float(baseline_line)
    if kind == "force_offset":
        shift = int(round(severity))
        with (src / "force.csv").open(newline="") as handle:
            rows = list(csv.DictReader(handle))
        by_frame = {int(row["frame"]): row for row in rows}  # force.csv names frames by number
        out_rows = []
        for i, stem in enumerate(stems):
            j = min(max(i - shift, 0), len(stems) - 1)
            source = by_frame[int(stems[j])]
            out_rows.append({**source, "frame": by_frame[int(stem)]["frame"]})
        fields = list(rows[0].keys())

        def write(handle) -> None:
            writer = csv.DictWriter(handle, fieldnames=fields)
            writer.writeheader()
            writer.writerows(out_rows)

        _replace(dst / "force.csv", write, "w")
        return Fault(kind, tuple(range(len(stems))), float(shift))
    if kind == "frozen_depth":
        base = max(frames[0] - 1, 0)
        frozen = np.load(src / "depth" / f"{stems[base]}.npy")
        for i in frames:
            _write_depth(dst / "depth" / f"{stems[i]}.npy", frozen)
        return Fault(kind, frames, severity)
    if kind in MULTI_FAULT_KINDS:
        return _inject_ids(src, dst, kind, frames, stems, rng)
    if kind == "vertical_offset":
        quality = _jpeg_quality(src)
        right = {p.stem: p for p in (src / "right").iterdir() if not p.name.startswith(".")}
        for i in frames:
            image = cv2.imread(str(right[stems[i]]), cv2.IMREAD_UNCHANGED)
            _write_image(dst / "right" / right[stems[i]].name, shift_rows(image, severity), quality)
        return Fault(kind, frames, severity)
    for i in frames:
        mask, like, ids = _read_mask(src / "masks" / f"{stems[i]}.png")
        if kind in MASK_FAULTS:
            _write_mask(dst / "masks" / f"{stems[i]}.png", _mask_fault(kind, mask, severity, rng), like, ids)
        else:
            depth = np.load(src / "depth" / f"{stems[i]}.npy")
            _write_depth(dst / "depth" / f"{stems[i]}.npy", _depth_fault(kind, depth, mask, severity, fx_b, rng))
    return Fault(kind, frames, severity)


def _inject_ids(src: Path, dst: Path, kind: str, frames: tuple[int, ...], stems: list[str],
                rng: np.random.Generator) -> Fault:
    """id_swap / tools_merged between object ids 1 and 2 in ``frames`` (module docstring)."""
    seen = set()
    for i in frames:
        seen.update(int(k) for k in np.unique(read_mask_ids(src / "masks" / f"{stems[i]}.png")[0]))
    if not {1, 2} <= seen:
        raise ValueError(f"{kind} needs instruments 1 and 2 in the masks of the injected frames; "
                         f"{src / 'masks'} has object ids {sorted(seen - {0})} there")
    keep = int(rng.integers(1, 3))  # tools_merged: the id that takes in the other
    for i in frames:
        ids, like = read_mask_ids(src / "masks" / f"{stems[i]}.png")
        out = ids.copy()
        if kind == "id_swap":
            out[ids == 1], out[ids == 2] = 2, 1
        else:
            out[(ids == 1) | (ids == 2)] = keep
        _write_ids(dst / "masks" / f"{stems[i]}.png", out, like)
    return Fault(kind, frames, float(keep) if kind == "tools_merged" else 0.0)


def perturb_session(src: str | Path, dst: str | Path, *, depth_rel: float = 1e-5, grey_share: float = 0.02,
                    seed: int = 0) -> None:
    """Copy the session ``src`` to ``dst`` (which must not exist) with its inputs changed as much as another
    processor changes a synthetic session, or more: every depth value (.npy) times 1 + u, u uniform in
    +-``depth_rel``; ``grey_share`` of the pixels of every left and right image one grey level up or down (a JPEG
    image is encoded again at the session's quality, which changes it a little more). Not a failure: a check
    whose decisions it changes decides on a knife's edge (benchmarks/bench_diagnostics.py --perturb)."""
    src, dst = Path(src), Path(dst)
    if dst.exists():
        raise ValueError(f"{dst}: already exists")
    _link_tree(src, dst)

    def rng_for(data: bytes) -> np.random.Generator:  # files alike are changed alike (a repeated depth map stays so)
        return np.random.default_rng([seed, int.from_bytes(hashlib.blake2b(data, digest_size=8).digest(), "little")])

    quality = _jpeg_quality(src)
    for path in sorted((src / "depth").glob("*.npy")) if (src / "depth").is_dir() else []:
        depth = np.load(path)
        rng = rng_for(depth.tobytes())
        _write_depth(dst / "depth" / path.name, depth * (1.0 + rng.uniform(-depth_rel, depth_rel, depth.shape)))
    for side in ("left", "right"):
        for path in sorted((src / side).iterdir()) if (src / side).is_dir() else []:
            if path.name.startswith(".") or path.suffix.lower() not in (".png", ".jpg", ".jpeg"):
                continue
            image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            rng = rng_for(image.tobytes())
            step = (rng.random(image.shape[:2]) < grey_share) * rng.choice(np.array([-1, 1], np.int16), image.shape[:2])
            image = np.clip(image.astype(np.int16) + (step[..., None] if image.ndim == 3 else step), 0, 255)
            _write_image(dst / side / path.name, image.astype(np.uint8), quality)
