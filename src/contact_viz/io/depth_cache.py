"""Per-frame SGBM disparities of a session, cached outside the session directory.

Stored as 16-bit PNGs of the fixed-point (1/16 px) disparity, keyed by the session's path, the sizes
and modification times of the calibration and image files they depend on, and the resolved
parameters, so the second run is fast and a changed input never reuses a stale entry.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import os
import sys
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np

from contact_viz import __version__
from contact_viz.io.atomic import atomic_write, os_reason, staging_path, sweep_stale_in

from contact_viz.geometry.stereo import SUBPIXEL, SGBMParams, sgbm_disparity
from contact_viz.geometry.stereo_region import region_sgbm_disparity


class CacheWarning(UserWarning):
    """The depth cache could not be written; depth is recomputed on every read."""


# --------------------------------------------------------------------------------------------
# Cache
# --------------------------------------------------------------------------------------------


def _stat_key(path: Path) -> list:
    stat = path.stat()
    return [path.name, stat.st_size, stat.st_mtime_ns]


def _encode(disparity: np.ndarray, p: SGBMParams) -> np.ndarray:
    """Disparity px -> uint16 code: 0 = invalid, else (d - min) * 16 + 1 (exact for 1/16 px steps)."""
    code = np.zeros(disparity.shape, dtype=np.uint16)
    valid = np.isfinite(disparity)
    code[valid] = np.rint((disparity[valid] - p.min_disparity * p.downscale) * SUBPIXEL).astype(np.uint32) + 1
    return code


def _decode(code: np.ndarray, p: SGBMParams) -> np.ndarray:
    disparity = (code.astype(np.float32) - 1) / np.float32(SUBPIXEL) + np.float32(p.min_disparity * p.downscale)
    disparity[code == 0] = np.nan
    return disparity


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # the IEND chunk: length 0, type, CRC


def read_entry(path: Path) -> np.ndarray | None:
    """The uint16 (H, W) code of a cache entry, or None if it is absent or not a whole PNG.

    Entries are renamed into place only once written and fsynced, but a filesystem without atomic
    rename, or a crash before the data reached the disk, can leave a file cut short or zero-filled:
    such a file lacks the PNG signature or the IEND chunk that ends every whole PNG, and a wrong byte
    inside fails the CRC of its chunk or the zlib checksum of the image data (libpng refuses both)."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    if len(data) < len(_PNG_SIGNATURE) + len(_PNG_END) or not data.startswith(_PNG_SIGNATURE) \
            or not data.endswith(_PNG_END):
        return None
    code = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if code is None or code.dtype != np.uint16 or code.ndim != 2:
        return None
    return code


class DisparityCache:
    """Per-frame SGBM disparities of one session, stored outside the session directory.

    Entries live in ``<cache_dir>/sgbm/<session name>-<key>/`` where the key hashes the package
    version, the session's absolute path, the name, size and mtime of each calibration file and
    the resolved parameters; each frame's file name adds a hash of its left and right images'
    size and mtime. Writes are atomic, so concurrent readers never see half a file; an entry that
    is not a whole PNG (a torn write on a filesystem without atomic rename, a crash before the data
    reached the disk) is never used, but computed and written again (:func:`read_entry`).
    ``directory=None`` disables storage (every read recomputes).

    A cache that cannot be written (a full disk, a read-only place) is one warning, and every entry
    missing from it is computed on each read; :meth:`for_session` finds out when the session is
    opened (:meth:`probe`), so that worker processes given the opened session do not each warn.
    """

    PROBE_BYTES = 64 * 1024  # written and removed by probe(): the size of a small entry

    def __init__(self, directory: Path | None, params: SGBMParams) -> None:
        self.directory = directory
        self.params = params
        self.writable = directory is not None
        self.problem: OSError | None = None  # why the cache cannot be written (probe, or a write), as an error about the folder
        self._warned = False

    @classmethod
    def for_session(
        cls,
        root: Path,
        calibration_files: Sequence[Path],
        params: SGBMParams,
        cache_dir: str | Path | None = None,
    ) -> DisparityCache:
        """The cache of session ``root`` for resolved ``params`` (``cache_dir`` default: the package cache)."""
        from contact_viz.io.cache import default_cache_dir

        root = Path(root).resolve()
        base = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
        base = base.resolve()
        if base == root or root in base.parents:
            raise ValueError(f"cache_dir {base} is inside the session directory {root}; choose a folder outside it")
        payload = json.dumps(
            {"version": __version__, "root": str(root), "params": asdict(params),
             "calibration": [_stat_key(Path(f)) for f in calibration_files]},
            sort_keys=True,
        )
        key = hashlib.sha256(payload.encode()).hexdigest()[:24]
        cache = cls(base / "sgbm" / f"{root.name}-{key}", params)
        cache.probe()
        return cache

    def probe(self) -> bool:
        """Whether the cache folder takes new entries: make it, remove the staging files of dead
        processes (killed while writing an entry), write and remove a small file. If not, warn once;
        entries already there are still read. Returns ``self.writable``."""
        if self.directory is None:
            return False
        probe = staging_path(self.directory / "probe", "probe")
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            sweep_stale_in(self.directory)
            fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            try:
                written = 0
                while written < self.PROBE_BYTES:
                    written += os.write(fd, bytes(self.PROBE_BYTES - written))
            finally:
                os.close(fd)
                probe.unlink(missing_ok=True)
        except OSError as exc:
            self.writable = False
            self._failed(exc)
        return self.writable

    def _failed(self, exc: OSError) -> None:
        """A write failed: keep why, as an error about the folder (:attr:`problem`), and warn once:
        ``DIR: could not write the depth cache (what went wrong); ...``."""
        if self.problem is None:
            self.problem = OSError(exc.errno, exc.strerror, str(self.directory)) if exc.errno else exc
        if self._warned:
            return
        self._warned = True
        message = (f"{self.directory}: could not write the depth cache ({os_reason(exc)}); depth missing from "
                   "it is computed on every read")
        if multiprocessing.parent_process() is not None:  # a worker: one line, as the command's own warnings
            print(f"warning: {message}", file=sys.stderr, flush=True)
        else:
            warnings.warn(message, CacheWarning, stacklevel=3)

    def path(self, stem: str, left_path: Path, right_path: Path, mask_key: list | None = None) -> Path | None:
        """Where frame ``stem``'s disparity lives (None when caching is off).

        ``mask_key``: for mask-aware matching, what identifies the tool mask used (see
        :meth:`disparity`); None for plain matching.
        """
        if self.directory is None:
            return None
        frame_key = json.dumps([_stat_key(left_path), _stat_key(right_path)]
                               + ([] if mask_key is None else [mask_key]))
        digest = hashlib.sha256(frame_key.encode()).hexdigest()[:12]
        return self.directory / f"{stem}-{digest}.png"

    def load(self, path: Path | None) -> np.ndarray | None:
        """The cached disparity (H, W) float32 px (NaN invalid), or None if absent or unreadable."""
        if path is None:
            return None
        code = read_entry(path)
        return None if code is None else _decode(code, self.params)

    def save(self, path: Path | None, disparity: np.ndarray) -> None:
        """Store a disparity atomically; a failure only warns (once), is kept in :attr:`problem` and disables
        nothing else."""
        if path is None or not self.writable:
            return
        ok, data = cv2.imencode(".png", _encode(disparity, self.params), [cv2.IMWRITE_PNG_COMPRESSION, 1])
        try:
            if not ok:
                raise OSError("PNG encoding failed")
            # The folder's dead staging files were swept by probe(): one listing per run, not per entry.
            with atomic_write(path, "wb", sweep=False) as handle:
                handle.write(data.tobytes())
        except OSError as exc:
            self._failed(exc)

    def disparity(
        self,
        stem: str,
        left_path: Path,
        right_path: Path,
        load_pair: Callable[[], tuple[np.ndarray, np.ndarray]],
        mask_path: Path | None = None,
        load_mask: Callable[[], np.ndarray] | None = None,
    ) -> tuple[np.ndarray, bool]:
        """Frame ``stem``'s disparity from the cache, else computed from ``load_pair()`` and stored.

        With ``mask_path`` and ``load_mask`` (and ``params.tool_mask_aware``), the disparity is
        matched knowing the tool mask (:func:`region_sgbm_disparity`: fine around the tools, the
        coarse pass elsewhere; ``load_mask`` gives every instrument of the frame) and the cache entry is
        keyed by the mask file's name, size and mtime too.
        Returns (disparity (H, W) float32 px, whether it came from the cache).
        """
        use_mask = self.params.tool_mask_aware and mask_path is not None and load_mask is not None
        mask_key = _stat_key(mask_path) if use_mask else None
        path = self.path(stem, left_path, right_path, mask_key)
        cached = self.load(path)
        if cached is not None:
            return cached, True
        left, right = load_pair()
        if use_mask:
            disparity = region_sgbm_disparity(left, right, load_mask(), self.params).disparity_px
        else:
            disparity = sgbm_disparity(left, right, self.params)
        self.save(path, disparity)
        return disparity, False


# --------------------------------------------------------------------------------------------
# Whole-session precomputation (`contact-viz depth`)
