"""Tool-tip crops of a session (``extract_crops``), cached as a memory-mapped ``.npy`` outside it."""

from __future__ import annotations

import errno
import os
import warnings
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from contact_viz.baseline.params import CONTACT, NO_CONTACT, UNKNOWN_LABEL
from contact_viz.geometry.tooltip import TipParams, crop_centered, tool_tip_xy
from contact_viz.io.atomic import atomic_write, staging_path, sweep_stale
from contact_viz.params import to_dict as _params_to_dict


# center_source codes of SessionCrops
TIP_FOUND, LAST_TIP, IMAGE_CENTER, TIP_FILE = 0, 1, 2, 3


@dataclass(frozen=True, eq=False)
class SessionCrops:
    """The tool-tip crops of one session (T frames), ready for training or prediction."""

    name: str  # session name (unique within a LOSO run)
    crops: np.ndarray  # (T, S, S, 3) uint8 RGB crops (in memory or a read-only memory map)
    labels: np.ndarray  # (T,) int8 1 = contact, 0 = no contact, -1 = unknown
    center_xy: np.ndarray  # (T, 2) float64 crop centre (x = column, y = row) in the left image, px
    center_source: np.ndarray  # (T,) uint8 TIP_FOUND (0) / LAST_TIP (1) / IMAGE_CENTER (2) / TIP_FILE (3)
    readable: np.ndarray  # (T,) bool, False where the left image could not be read (never trained on)

    def __post_init__(self) -> None:
        crops = self.crops
        if crops.ndim != 4 or crops.shape[3] != 3 or crops.shape[1] != crops.shape[2] or crops.dtype != np.uint8:
            raise ValueError(
                f"SessionCrops {self.name!r}: crops: expected (T, S, S, 3) uint8, "
                f"got shape {crops.shape} dtype {crops.dtype}"
            )
        n = crops.shape[0]
        for attr, shape in (("labels", (n,)), ("center_xy", (n, 2)), ("center_source", (n,)), ("readable", (n,))):
            value = getattr(self, attr)
            if value.shape != shape:
                raise ValueError(f"SessionCrops {self.name!r}: {attr}: expected shape {shape}, got {value.shape}")
        if not np.isin(self.labels, (UNKNOWN_LABEL, NO_CONTACT, CONTACT)).all():
            raise ValueError(f"SessionCrops {self.name!r}: labels: expected values in {{-1, 0, 1}}")

    def __len__(self) -> int:
        return int(self.crops.shape[0])

    @property
    def trainable(self) -> np.ndarray:
        """(T,) bool: frames labelled 0 or 1 whose left image was read."""
        return (self.labels != UNKNOWN_LABEL) & self.readable


def _crop_cache_paths(session: Any, crop_px: int, tip_params: TipParams, cache_dir: Path) -> tuple[Path, Path]:
    from contact_viz.io.cache import cache_path

    key_params = {"crop_px": crop_px, "tip": _params_to_dict(tip_params)}
    crops_path = cache_path(session.root, "baseline-crops", key_params, ".npy", cache_dir)
    return crops_path, crops_path.with_suffix(".meta.npz")


def _load_cached(crops_path: Path, meta_path: Path, shape: tuple[int, ...]):
    """(crops as a read-only memory map, the SessionCrops fields of the meta file) of a cache entry, or
    None if absent or not whole (a file cut short by a crash on a filesystem without atomic rename)."""
    if not (crops_path.is_file() and meta_path.is_file()):
        return None
    try:
        crops = np.load(crops_path, mmap_mode="r")
        with np.load(meta_path) as meta:
            fields = {k: meta[k] for k in ("center_xy", "center_source", "readable")}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile):  # not whole: computed again
        return None
    if crops.shape != shape or crops.dtype != np.uint8 or any(len(v) != shape[0] for v in fields.values()):
        return None
    return crops, fields


def _cache_warning(crops_path: Path, exc: OSError) -> None:
    from contact_viz.io.atomic import os_reason

    warnings.warn(f"{crops_path.parent}: could not write the crops cache ({os_reason(exc)}); the crops are held "
                  "in memory", stacklevel=3)


def _staged_memmap(path: Path, shape: tuple[int, ...]) -> np.memmap:
    """A new ``.npy`` memory map at ``path`` whose blocks are allocated up front: on a full disk that is
    an OSError now, where writing through the map into a sparse file would kill the process (SIGBUS)."""
    try:
        crops = np.lib.format.open_memmap(path, mode="w+", dtype=np.uint8, shape=shape)
        fd = os.open(path, os.O_RDWR)
        try:
            os.posix_fallocate(fd, 0, os.fstat(fd).st_size)
        except OSError as exc:
            if exc.errno not in (errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):  # no fallocate here: as before
                raise OSError(exc.errno, exc.strerror, str(path)) from exc
        finally:
            os.close(fd)
    except BaseException:
        path.unlink(missing_ok=True)
        raise
    return crops


def extract_crops(
    session: Any,
    crop_px: int,
    tip_params: TipParams = TipParams(),
    cache_dir: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> SessionCrops:
    """The tool-tip crops of every frame of an opened ``session`` (``contact_viz.io.session.Session``).

    Decodes the mask and left image of each frame once. Crop centres follow the package docstring
    of ``contact_viz.baseline`` (tip, else last known tip, else image centre). With ``cache_dir``
    the crops are written to a ``.npy`` file there (keyed by the session's files, ``crop_px`` and
    ``tip_params``, see ``contact_viz.io.cache``) and returned as a read-only memory map; a later call with unchanged
    inputs reads it back without decoding anything. Without it they are held in memory
    (crop_px**2 * 3 bytes per frame: 164 kB at 234 px). ``progress(done, total)`` after each frame.
    """
    n_frames = len(session)
    height, width = session.image_size
    labels = np.array(session.labels, dtype=np.int8)
    shape = (n_frames, crop_px, crop_px, 3)
    staged = None  # the staging .npy the crops are written into, when they are cached
    if cache_dir is not None:
        crops_path, meta_path = _crop_cache_paths(session, crop_px, tip_params, Path(cache_dir))
        cached = _load_cached(crops_path, meta_path, shape)
        if cached is not None:
            crops, meta = cached
            return SessionCrops(name=session.name, crops=crops, labels=labels, **meta)
        try:
            crops_path.parent.mkdir(parents=True, exist_ok=True)
            sweep_stale(crops_path)  # the staging file of a killed run
            staged = staging_path(crops_path, "tmp.npy")
            crops = _staged_memmap(staged, shape)
        except OSError as exc:  # a full disk, a read-only cache: the crops are held in memory
            _cache_warning(crops_path, exc)
            staged = None
    if staged is None:
        crops = np.zeros(shape, dtype=np.uint8)
    center_xy = np.empty((n_frames, 2), dtype=np.float64)
    center_source = np.empty(n_frames, dtype=np.uint8)
    readable = np.ones(n_frames, dtype=bool)
    last_tip: tuple[float, float] | None = None
    file_tips = getattr(session, "tool_tips_xy", None)  # (T, 2) px from tool_tips.csv, NaN where absent
    image_center = ((width - 1) / 2.0, (height - 1) / 2.0)
    try:
        for frame in session.iter_frames(layers=("mask", "left")):
            i = frame.index
            tool_mask = getattr(frame, "tool_mask", None)
            left_rgb = getattr(frame, "left_rgb", None)
            if left_rgb is None:  # a BadFrame: the mask or the image is unreadable; try each alone
                tool_mask = getattr(session.load_frame(i, ("mask",)), "tool_mask", None)
                left_rgb = getattr(session.load_frame(i, ("left",)), "left_rgb", None)
            file_tip = None if file_tips is None or not np.isfinite(file_tips[i]).all() else file_tips[i]
            tip = tool_tip_xy(tool_mask, tip_params) if tool_mask is not None and file_tip is None else None
            if file_tip is not None:  # the session's tool_tips.csv (e.g. Yang et al.'s keypoints) wins
                last_tip, center_source[i] = (float(file_tip[0]), float(file_tip[1])), TIP_FILE
            elif tip is not None:
                last_tip, center_source[i] = tip, TIP_FOUND
            else:
                center_source[i] = LAST_TIP if last_tip is not None else IMAGE_CENTER
            center_xy[i] = last_tip if last_tip is not None else image_center
            if left_rgb is not None:
                crops[i] = crop_centered(left_rgb, center_xy[i], crop_px)
            else:
                readable[i] = False
                if i > 0:
                    crops[i] = crops[i - 1]  # hold the previous crop (zeros before the first readable frame)
            if progress is not None:
                progress(i + 1, n_frames)
        if staged is not None:
            try:
                crops.flush()
                with atomic_write(meta_path, "wb") as handle:
                    np.savez(handle, center_xy=center_xy, center_source=center_source, readable=readable)
                os.replace(staged, crops_path)  # the crops file appears last: both present = complete
                del crops
                crops = np.load(crops_path, mmap_mode="r")
            except OSError as exc:  # the crops computed are right: keep them in memory
                _cache_warning(crops_path, exc)
                crops = np.array(crops)
                staged.unlink(missing_ok=True)
    except BaseException:
        if staged is not None:
            staged.unlink(missing_ok=True)
        raise
    return SessionCrops(
        name=session.name,
        crops=crops,
        labels=labels,
        center_xy=center_xy,
        center_source=center_source,
        readable=readable,
    )
