"""Depth from a rectified stereo pair with OpenCV semi-global matching (SGBM), and its cache.

This is the fallback for sessions that come without depth: a learned stereo network such as
FoundationStereo gives far better depth on endoscopic images (weak texture, specular highlights,
thin tools); feed its output in as ``depth/<stem>.npy`` (float32 m) or ``disparity/<stem>.npy``
(float32 px) and this module is never used.

The matcher (:func:`sgbm_disparity`) runs ``cv2.StereoSGBM`` with the left images padded on the
left (so pixels near the left edge can still be matched), OpenCV's speckle filter and
uniqueness test, then a left-right consistency check of our own (OpenCV's contrib
``ximgproc`` is not used): the right-view disparity is computed by matching the horizontally
flipped pair, and a left pixel is kept only where the right view maps it back within
``lr_max_diff_px``.

Disparities are cached per frame outside the session directory (:class:`DisparityCache`), as
16-bit PNGs of the fixed-point (1/16 px) disparity, keyed by the session's path, the sizes and
modification times of the calibration and image files they depend on, and the resolved
parameters, so the second run is fast and a changed input never reuses a stale entry.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from contact_viz import __version__
from contact_viz.atomic import atomic_write
from contact_viz.errors import SessionError

__all__ = [
    "DEPTH_METHODS",
    "DepthRunSummary",
    "DisparityCache",
    "SGBMParams",
    "disparity_to_depth",
    "precompute_depth",
    "run_depth_command",
    "sgbm_disparity",
]

DEPTH_METHODS = ("sgbm",)  # methods `contact-viz depth` can compute
SUBPIXEL = 16  # StereoSGBM returns disparities in 1/16 px fixed point
_MODES = {
    "sgbm": cv2.STEREO_SGBM_MODE_SGBM,
    "sgbm_3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    "hh": cv2.STEREO_SGBM_MODE_HH,
    "hh4": cv2.STEREO_SGBM_MODE_HH4,
}
_MAX_CODE = np.iinfo(np.uint16).max  # largest value a 16-bit PNG holds
_MIN_BLOCK = 3  # smallest matching block side, px
_BLOCK_STEP = 2  # block sides are odd


class CacheWarning(UserWarning):
    """The depth cache could not be written; depth is recomputed on every read."""


# --------------------------------------------------------------------------------------------
# Parameters
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SGBMParams:
    """Semi-global matching settings; ``None`` fields are sized from the image width by :meth:`resolve`."""

    num_disparities: int | None = None  # disparity search range, px (multiple of 16); None = from the width
    disparity_range_fraction: float = 0.125  # when num_disparities is None: range = this * width (rounded up to 16)
    min_disparity: int = 0  # smallest disparity searched, px
    block_size: int | None = None  # matching block side, px (odd, >= 3); None = from the width
    width_per_block_px: float = 320.0  # when block_size is None: block = width / this, as an odd number >= 3
    p1_factor: int = 8  # P1 = p1_factor * channels * block^2: penalty for a 1 px disparity change
    p2_factor: int = 32  # P2 = p2_factor * channels * block^2: penalty for larger disparity jumps
    uniqueness_ratio: int = 10  # best cost must beat the second best by this margin, %
    speckle_window_size: int = 100  # largest connected speckle region removed, px (0 = no speckle filter)
    speckle_range: int = 2  # largest disparity step inside one connected region, px
    disp12_max_diff: int = 1  # OpenCV's built-in left-right tolerance, px (-1 = off)
    lr_check: bool = True  # run the right-view match and drop pixels failing the left-right check
    lr_max_diff_px: float = 1.0  # left-right consistency tolerance, px
    mode: str = "sgbm_3way"  # OpenCV mode: sgbm, sgbm_3way (fast), hh (full 8-path, slow), hh4
    downscale: int = 1  # match at 1/downscale resolution, then upsample the disparity (faster, coarser)

    def __post_init__(self) -> None:
        if self.mode not in _MODES:
            raise ValueError(f"SGBMParams.mode must be one of {sorted(_MODES)}, got {self.mode!r}")
        if self.num_disparities is not None and (
            self.num_disparities < SUBPIXEL or self.num_disparities % SUBPIXEL
            or self.num_disparities * SUBPIXEL >= _MAX_CODE
        ):
            raise ValueError(
                f"SGBMParams.num_disparities must be a positive multiple of 16 below 4096, got {self.num_disparities}"
            )
        if self.block_size is not None and (self.block_size < 1 or self.block_size % 2 == 0):
            raise ValueError(f"SGBMParams.block_size must be an odd number >= 1, got {self.block_size}")
        if not 0 < self.disparity_range_fraction <= 1:
            raise ValueError(
                f"SGBMParams.disparity_range_fraction must be in (0, 1], got {self.disparity_range_fraction}"
            )
        if not self.width_per_block_px > 0:
            raise ValueError(f"SGBMParams.width_per_block_px must be positive, got {self.width_per_block_px}")
        if not self.lr_max_diff_px >= 0:
            raise ValueError(f"SGBMParams.lr_max_diff_px must be >= 0, got {self.lr_max_diff_px}")
        if isinstance(self.downscale, bool) or not isinstance(self.downscale, int) or self.downscale < 1:
            raise ValueError(f"SGBMParams.downscale must be a positive integer, got {self.downscale!r}")
        if self.p1_factor <= 0 or self.p2_factor <= self.p1_factor:
            raise ValueError(
                f"SGBMParams needs 0 < p1_factor < p2_factor, got {self.p1_factor} and {self.p2_factor}"
            )

    def resolve(self, width_px: int) -> SGBMParams:
        """These parameters with num_disparities and block_size fixed for images ``width_px`` wide.

        The sizes refer to the matching resolution (width / downscale).
        """
        width = max(1, int(width_px) // self.downscale)
        num = self.num_disparities
        if num is None:
            num = max(SUBPIXEL, -(-int(np.ceil(width * self.disparity_range_fraction)) // SUBPIXEL) * SUBPIXEL)
        block = self.block_size
        if block is None:
            block = max(_MIN_BLOCK, int(round(width / self.width_per_block_px)))
            block += 1 - block % _BLOCK_STEP  # next odd number
        if (num + max(self.min_disparity, 0)) * self.downscale * SUBPIXEL >= _MAX_CODE:
            raise ValueError(
                f"SGBMParams: search range {num} px x downscale {self.downscale} is too large "
                "(disparities must stay below 4096 px)"
            )
        return replace(self, num_disparities=num, block_size=block)


# --------------------------------------------------------------------------------------------
# Pure functions
# --------------------------------------------------------------------------------------------


def _as_pair(left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    left, right = np.asarray(left), np.asarray(right)
    if left.shape != right.shape:
        raise ValueError(f"left and right images must have the same shape, got {left.shape} and {right.shape}")
    if left.dtype != np.uint8 or right.dtype != np.uint8:
        raise ValueError(f"expected uint8 images, got {left.dtype} and {right.dtype}")
    if left.ndim not in (2, 3) or (left.ndim == 3 and left.shape[2] != 3) or min(left.shape[:2]) < 1:
        raise ValueError(f"expected (H, W) grey or (H, W, 3) RGB images, got shape {left.shape}")
    return np.ascontiguousarray(left), np.ascontiguousarray(right)


def _match(left: np.ndarray, right: np.ndarray, p: SGBMParams) -> np.ndarray:
    """StereoSGBM disparity of ``left`` against ``right`` (H, W) float32 px, NaN = no match.

    The pair is padded on the left by the search range (edge pixels repeated) so that pixels
    near the left border can match; the padding is cropped off the result.
    """
    channels = 1 if left.ndim == 2 else left.shape[2]
    area = channels * p.block_size * p.block_size
    matcher = cv2.StereoSGBM_create(
        minDisparity=p.min_disparity,
        numDisparities=p.num_disparities,
        blockSize=p.block_size,
        P1=p.p1_factor * area,
        P2=p.p2_factor * area,
        disp12MaxDiff=p.disp12_max_diff,
        uniquenessRatio=p.uniqueness_ratio,
        speckleWindowSize=p.speckle_window_size,
        speckleRange=p.speckle_range,
        mode=_MODES[p.mode],
    )
    pad = p.num_disparities + max(p.min_disparity, 0)
    left_p = cv2.copyMakeBorder(left, 0, 0, pad, 0, cv2.BORDER_REPLICATE)
    right_p = cv2.copyMakeBorder(right, 0, 0, pad, 0, cv2.BORDER_REPLICATE)
    fixed = matcher.compute(left_p, right_p)[:, pad:]
    disparity = fixed.astype(np.float32) / np.float32(SUBPIXEL)
    disparity[fixed < p.min_disparity * SUBPIXEL] = np.nan  # OpenCV marks no-match as (min - 1) * 16
    return disparity


def left_right_check(disp_left: np.ndarray, disp_right: np.ndarray, max_diff_px: float) -> np.ndarray:
    """Where the left disparity is confirmed by the right view: (H, W) bool.

    ``disp_left[y, x] = d`` says left pixel x matches right pixel x - d; it passes when that right
    pixel (rounded) exists and ``|disp_right[y, round(x - d)] - d| <= max_diff_px``.
    Both inputs (H, W) float32 px with NaN = no match.
    """
    height, width = disp_left.shape
    finite = np.isfinite(disp_left)
    x_right = np.arange(width, dtype=np.float32)[None, :] - np.where(finite, disp_left, np.float32(width))
    col = np.rint(x_right).astype(np.int64)
    inside = finite & (col >= 0) & (col < width)
    rows = np.broadcast_to(np.arange(height)[:, None], disp_left.shape)
    back = np.full(disp_left.shape, np.nan, dtype=np.float32)
    back[inside] = disp_right[rows[inside], col[inside]]
    with np.errstate(invalid="ignore"):
        return inside & (np.abs(back - disp_left) <= max_diff_px)


def sgbm_disparity(left_rgb: np.ndarray, right_rgb: np.ndarray, params: SGBMParams = SGBMParams()) -> np.ndarray:
    """Disparity of a rectified pair by semi-global matching.

    ``left_rgb``, ``right_rgb``: (H, W, 3) or (H, W) uint8, rectified (corresponding pixels on the
    same row, right pixel = left pixel - disparity). Returns (H, W) float32 disparity in px
    (multiples of 1/16 px, times ``downscale``), NaN where no reliable match was found.
    """
    left, right = _as_pair(left_rgb, right_rgb)
    height, width = left.shape[:2]
    p = params.resolve(width)
    n = p.downscale
    if n > 1:
        size = (max(1, width // n), max(1, height // n))
        left = cv2.resize(left, size, interpolation=cv2.INTER_AREA)
        right = cv2.resize(right, size, interpolation=cv2.INTER_AREA)
    disparity = _match(left, right, p)
    if p.lr_check:
        flipped = _match(np.ascontiguousarray(right[:, ::-1]), np.ascontiguousarray(left[:, ::-1]), p)
        disparity[~left_right_check(disparity, flipped[:, ::-1], p.lr_max_diff_px)] = np.nan
    if n > 1:
        disparity = cv2.resize(disparity, (width, height), interpolation=cv2.INTER_NEAREST) * np.float32(n)
    return disparity


def disparity_to_depth(
    disparity_px: np.ndarray, fx_px: float, baseline_m: float, offset_px: float = 0.0
) -> np.ndarray:
    """Depth of a rectified pair's disparity: ``fx * baseline / (disparity + offset)``.

    ``disparity_px`` (H, W) float px; ``offset_px`` = cx_right - cx_left of the rectified cameras
    (0 for FoundationStereo's K.txt). Returns (H, W) float32 metres, NaN where the disparity is
    not finite or not positive, or disparity + offset is not positive.
    """
    if not (np.isfinite(fx_px) and fx_px > 0 and np.isfinite(baseline_m) and baseline_m > 0):
        raise ValueError(f"fx_px and baseline_m must be positive, got {fx_px!r} and {baseline_m!r}")
    disparity = np.asarray(disparity_px, dtype=np.float32)
    shifted = disparity + np.float32(offset_px)
    valid = np.isfinite(disparity) & (disparity > 0) & (shifted > 0)
    depth = np.full(disparity.shape, np.nan, dtype=np.float32)
    np.divide(np.float32(fx_px * baseline_m), shifted, out=depth, where=valid)
    return depth


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


class DisparityCache:
    """Per-frame SGBM disparities of one session, stored outside the session directory.

    Entries live in ``<cache_dir>/sgbm/<session name>-<key>/`` where the key hashes the package
    version, the session's absolute path, the name, size and mtime of each calibration file and
    the resolved parameters; each frame's file name adds a hash of its left and right images'
    size and mtime. Writes are atomic, so concurrent readers never see half a file.
    ``directory=None`` disables storage (every read recomputes).
    """

    def __init__(self, directory: Path | None, params: SGBMParams) -> None:
        self.directory = directory
        self.params = params
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
        from contact_viz.cache import default_cache_dir

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
        return cls(base / "sgbm" / f"{root.name}-{key}", params)

    def path(self, stem: str, left_path: Path, right_path: Path) -> Path | None:
        """Where frame ``stem``'s disparity lives (None when caching is off)."""
        if self.directory is None:
            return None
        frame_key = json.dumps([_stat_key(left_path), _stat_key(right_path)])
        digest = hashlib.sha256(frame_key.encode()).hexdigest()[:12]
        return self.directory / f"{stem}-{digest}.png"

    def load(self, path: Path | None) -> np.ndarray | None:
        """The cached disparity (H, W) float32 px (NaN invalid), or None if absent or unreadable."""
        if path is None or not path.is_file():
            return None
        code = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if code is None or code.dtype != np.uint16 or code.ndim != 2:
            return None
        return _decode(code, self.params)

    def save(self, path: Path | None, disparity: np.ndarray) -> None:
        """Store a disparity atomically; a failure only warns (once) and disables nothing else."""
        if path is None:
            return
        ok, data = cv2.imencode(".png", _encode(disparity, self.params), [cv2.IMWRITE_PNG_COMPRESSION, 1])
        try:
            if not ok:
                raise OSError("PNG encoding failed")
            with atomic_write(path, "wb") as handle:
                handle.write(data.tobytes())
        except OSError as exc:
            if not self._warned:
                self._warned = True
                warnings.warn(f"{path.parent}: could not write the depth cache ({exc}); depth is recomputed "
                              "on every read", CacheWarning, stacklevel=2)

    def disparity(
        self, stem: str, left_path: Path, right_path: Path, load_pair: Callable[[], tuple[np.ndarray, np.ndarray]]
    ) -> tuple[np.ndarray, bool]:
        """Frame ``stem``'s disparity from the cache, else computed from ``load_pair()`` and stored.

        Returns (disparity (H, W) float32 px, whether it came from the cache).
        """
        path = self.path(stem, left_path, right_path)
        cached = self.load(path)
        if cached is not None:
            return cached, True
        left, right = load_pair()
        disparity = sgbm_disparity(left, right, self.params)
        self.save(path, disparity)
        return disparity, False


# --------------------------------------------------------------------------------------------
# Whole-session precomputation (`contact-viz depth`)
# --------------------------------------------------------------------------------------------


@dataclass
class DepthRunSummary:
    """What `contact-viz depth` did."""

    session: str  # session name
    source: str  # the session's depth source: depth, disparity or sgbm
    frames: int  # frames handled
    computed: int  # frames whose disparity was computed now
    cached: int  # frames already in the cache
    failed: list[str]  # "<stem>: <reason>" of frames that could not be computed
    valid_fraction: float  # mean share of pixels with a valid depth over the frames handled
    seconds: float  # wall time, s
    cache_dir: Path | None  # where the disparities are cached
    output: Path | None  # where depth .npy files were written, if asked

    def lines(self) -> list[str]:
        """Human-readable report, one line each."""
        out = []
        if self.source != "sgbm":
            out.append(f"{self.session}: depth comes from {self.source}/ (no SGBM needed)")
        per_frame = 1000 * self.seconds / max(self.computed, 1)
        out.append(
            f"{self.session}: {self.frames} frames, {self.computed} computed ({per_frame:.0f} ms/frame), "
            f"{self.cached} from cache, {len(self.failed)} failed; valid depth on {100 * self.valid_fraction:.1f}% "
            "of pixels"
        )
        if self.cache_dir is not None and self.source == "sgbm":
            out.append(f"cache: {self.cache_dir}")
        if self.output is not None:
            out.append(f"depth written to {self.output} (float32 metres, <stem>.npy)")
        out.extend(f"failed: {reason}" for reason in self.failed)
        if self.source == "sgbm":
            out.append("note: a learned stereo network (FoundationStereo) gives far better depth; put its "
                       "depth_meter.npy as depth/<stem>.npy or its disparity as disparity/<stem>.npy")
        return out


def precompute_depth(
    session,
    *,
    output: str | Path | None = None,
    workers: int = 2,
    progress: Callable[[int, int], None] | None = None,
) -> DepthRunSummary:
    """Compute (or load from the cache) the depth of every frame of an opened ``session``.

    SGBM frames run in ``workers`` threads (OpenCV releases the GIL while matching; each match
    also uses OpenCV's own threads). With ``output``, each frame's depth is also written as
    ``<output>/<stem>.npy`` (float32 m, NaN invalid, rectified left view); ``output`` must be new
    or empty and outside the session directory, and is filled through a temporary folder beside
    it that is renamed at the end. ``progress(done, total)`` is called after each frame.
    """
    from contact_viz.session import BadFrame

    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    out_dir = tmp_dir = None
    if output is not None:
        out_dir = Path(output).expanduser().resolve()
        if out_dir == session.root or session.root in out_dir.parents:
            raise ValueError(f"{out_dir}: refusing to write inside the session directory {session.root}; "
                             "choose another output folder")
        if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
            raise ValueError(f"{out_dir}: expected a new or empty folder for the depth files")
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        tmp_dir = out_dir.parent / f".{out_dir.name}.tmp-{os.getpid()}-{time.monotonic_ns()}"
        tmp_dir.mkdir()

    total = len(session)
    failed: list[str] = []
    valid_sum = 0.0
    counts = {"computed": 0, "cached": 0}
    start = time.perf_counter()

    def one(index: int):
        return index, session.load_depth(index, with_origin=True)

    try:
        with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="contact-viz-depth") as pool:
            done = 0
            for index, result in pool.map(one, range(total)):
                stem = session.stems[index]
                if isinstance(result, BadFrame):
                    failed.append(f"{stem}: {result.reason}")
                else:
                    depth_m, origin = result
                    counts[origin] = counts.get(origin, 0) + 1
                    valid_sum += float(np.isfinite(depth_m).mean())
                    if tmp_dir is not None:
                        np.save(tmp_dir / f"{stem}.npy", depth_m)
                done += 1
                if progress is not None:
                    progress(done, total)
        if tmp_dir is not None:
            if out_dir.exists():
                out_dir.rmdir()
            os.replace(tmp_dir, out_dir)
            tmp_dir = None
    finally:
        if tmp_dir is not None:
            for child in tmp_dir.iterdir():
                child.unlink()
            tmp_dir.rmdir()
    handled = total - len(failed)
    return DepthRunSummary(
        session=session.name,
        source=session.depth_source,
        frames=total,
        computed=counts["computed"],
        cached=counts["cached"],
        failed=failed,
        valid_fraction=valid_sum / handled if handled else 0.0,
        seconds=time.perf_counter() - start,
        cache_dir=session.depth_cache_dir,
        output=out_dir,
    )


def run_depth_command(
    session_dir: str | Path,
    *,
    method: str = "sgbm",
    output: str | Path | None = None,
    cache_dir: str | Path | None = None,
    params: SGBMParams | None = None,
    workers: int = 2,
    progress: Callable[[int, int], None] | None = None,
) -> list[str]:
    """`contact-viz depth SESSION [--method sgbm] [-o OUT] [--cache-dir DIR]`: returns the lines to print.

    Opens the session (masks not required), fills the depth cache, optionally writes depth
    files to ``output``. Raises SessionError / ValueError with a message for the user.
    """
    from contact_viz.session import open_session

    if method not in DEPTH_METHODS:
        raise ValueError(f"--method must be one of {', '.join(DEPTH_METHODS)}, got {method!r}")
    session = open_session(session_dir, cache_dir=cache_dir, depth_method=method, sgbm_params=params,
                           require_masks=False)
    summary = precompute_depth(session, output=output, workers=workers, progress=progress)
    lines = [session.depth_note] + summary.lines()
    if summary.frames and len(summary.failed) == summary.frames:
        raise SessionError(session.root, "no frame's depth could be computed:\n" + "\n".join(summary.failed[:5]))
    return lines
