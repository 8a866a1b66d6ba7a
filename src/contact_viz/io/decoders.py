"""Decoders of one frame's files: tool masks, depth (.npy / uint16 PNG), disparity, RGB images.

Each raises one :class:`SessionError` naming the file and what was expected.
"""

from __future__ import annotations

import contextlib
import io
import os
import zlib
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from contact_viz.errors import SessionError, SessionFormatError
from contact_viz.io.npy_rows import TruncatedNpyError, data_end, read_header, read_npy_rows
from contact_viz.io.palette_png import is_palette_png, palette_indices
from contact_viz.params import MM_PER_M


# Exceptions that mean "this file could not be decoded" (PIL raises SyntaxError for some broken PNGs).
DECODE_ERRORS = (OSError, ValueError, EOFError, SyntaxError, zlib.error, cv2.error)

# --------------------------------------------------------------------------------------------


def _read_bytes(path: Path, what: str) -> np.ndarray:
    """The file's bytes as (k,) uint8; a missing, unreadable or empty file is a SessionError."""
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise SessionError(path, f"expected {what}, could not read the file ({exc.strerror or exc})") from exc
    if data.size == 0:
        raise SessionError(path, f"expected {what}, found an empty file")
    return data


JPEG_SOI = b"\xff\xd8\xff"  # every JPEG file starts with these bytes
_JPEG_EOI = b"\xff\xd9"  # ... and ends with this marker, which entropy-coded data cannot contain
_JPEG_TAIL = 1024  # the end-of-image marker is looked for in this many last bytes (some writers pad), bytes


def check_jpeg_complete(path: Path, data: bytes | np.ndarray, what: str) -> None:
    """A SessionError when ``data`` is a JPEG cut short (no end-of-image marker near its end): libjpeg
    would print a warning on stderr and fill the missing rows with grey instead of failing."""
    head = bytes(data[:3])
    if head == JPEG_SOI and _JPEG_EOI not in bytes(data[-_JPEG_TAIL:]):
        raise SessionError(path, f"expected {what}, found a JPEG cut short (no end-of-image marker: truncated?)")


def read_jpeg_bytes(path: Path, what: str) -> np.ndarray:
    """A JPEG file's bytes, (k,) uint8, checked to start and end like a whole JPEG; a missing, empty,
    other or truncated file is one SessionError naming the file and ``what`` was expected."""
    data = _read_bytes(path, what)
    if bytes(data[:3]) != JPEG_SOI:
        raise SessionError(path, f"expected {what}, the file does not start like a JPEG")
    check_jpeg_complete(path, data, what)
    return data


# cv2 flags decoding a JPEG straight to 1/n of its size, colour (BGR) or grey: libjpeg's DCT scaling,
# much faster than a full decode (a 1080p pair in grey: 13 -> 7 ms of CPU at n = 2)
_REDUCED = {False: {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
                    8: cv2.IMREAD_REDUCED_COLOR_8},
            True: {1: cv2.IMREAD_GRAYSCALE, 2: cv2.IMREAD_REDUCED_GRAYSCALE_2, 4: cv2.IMREAD_REDUCED_GRAYSCALE_4,
                   8: cv2.IMREAD_REDUCED_GRAYSCALE_8}}
JPEG_REDUCTIONS = (1, 2, 4, 8)  # the n a JPEG decodes to 1/n of its size at


def read_jpeg_reduced(path: Path, step: int, image_size: tuple[int, int], side: str, *, grey: bool = False,
                      data: np.ndarray | None = None) -> np.ndarray:
    """The ``side`` JPEG image of ``image_size`` (H, W) decoded straight to 1/``step`` of it
    (``step`` in JPEG_REDUCTIONS): (ceil(H/step), ceil(W/step), 3) BGR, or grey. ``data``: its bytes
    from :func:`read_jpeg_bytes`, else the file is read. A missing, empty, truncated or undecodable
    file, or one of another size, is one SessionError naming the file."""
    what = f"a JPEG {side} image"
    data = read_jpeg_bytes(path, what) if data is None else data
    image = _decode_bytes(path, what, data, lambda d: cv2.imdecode(d, _REDUCED[grey][step]))
    height, width = image_size
    if image.shape[:2] != (-(-height // step), -(-width // step)):
        raise SessionError(path, f"expected a {side} image of {height}x{width} px (height x width), "
                                 f"found about {image.shape[0] * step}x{image.shape[1] * step}")
    return image


def _decode(path: Path, what: str, decode: Callable[[np.ndarray], np.ndarray | None]) -> np.ndarray:
    """``decode`` applied to the file's bytes; a missing, unreadable, empty, truncated (JPEG) or
    undecodable file is one SessionError naming the file and ``what`` was expected."""
    return _decode_bytes(path, what, _read_bytes(path, what), decode)


def _decode_bytes(path: Path, what: str, data: np.ndarray, decode: Callable[[np.ndarray], np.ndarray | None]
                  ) -> np.ndarray:
    check_jpeg_complete(path, data, what)
    try:
        image = decode(data)
    except DECODE_ERRORS as exc:
        raise SessionError(path, f"expected {what}, could not decode it ({type(exc).__name__}: {exc})") from exc
    if image is None or image.size == 0:
        raise SessionError(path, f"expected {what}, could not decode it")
    return image


def _imdecode_unchanged(data: np.ndarray) -> np.ndarray | None:
    return cv2.imdecode(data, cv2.IMREAD_UNCHANGED)


def _mask_ids(data: np.ndarray) -> np.ndarray | None:
    """A mask file's pixel values: palette indices of a palettized PNG, else OpenCV's decode."""
    raw = data.tobytes()
    if not is_palette_png(raw):
        return _imdecode_unchanged(data)
    # palette_png, not PIL: 4.2 vs 5.4 ms per 1080p mask, about 15% of extract's CPU per frame (micro A/B)
    ids = palette_indices(raw)
    if ids is None:
        with Image.open(io.BytesIO(raw)) as image:
            ids = np.asarray(image)
    return ids


BINARY_MASK_VALUE = 255  # a single-channel mask whose only nonzero value is this is binary: one instrument, id 1


def read_mask_ids(path: Path, object_ids: Sequence[int] | None = None) -> np.ndarray:
    """Decode a tool mask PNG to (H, W) uint16 object ids, 0 = background: one id per instrument.

    Palettized (SAM2/DAVIS) and single-channel masks: pixel value = object id; a single-channel
    mask whose only nonzero value is 255 (8-bit 0/255) is binary, one instrument with id 1.
    Multi-channel masks: one instrument, id 1 where any colour channel is nonzero (``object_ids``
    is then an error: there are no ids to select). Palettized PNGs are decoded to their palette
    indices (contact_viz.io.palette_png; PIL for bit depths other than 8), the rest by OpenCV.
    """
    what = "a tool mask PNG (palettized object ids, or 8-bit 0/255)"
    ids = _decode(path, what, _mask_ids)
    if ids.ndim == 2:
        out = ids.astype(np.uint16)
        if out.max(initial=0) == BINARY_MASK_VALUE and not np.any((out != 0) & (out != BINARY_MASK_VALUE)):
            out = (out != 0).astype(np.uint16)
        return out
    if ids.ndim == 3 and ids.shape[2] in (3, 4):
        if object_ids:
            raise SessionFormatError(
                path,
                f"expected a palettized or single-channel mask to select --object-id {object_ids[0]}, "
                f"found {ids.shape[2]} channels",
            )
        return np.any(ids[:, :, :3] != 0, axis=2).astype(np.uint16)
    raise SessionFormatError(path, f"expected {what}, found an array of shape {ids.shape}")


def read_tool_mask(path: Path, object_ids: Sequence[int] | None = None) -> np.ndarray:
    """Decode a tool mask PNG to (H, W) bool, True = tool: every instrument, or those of ``object_ids``."""
    ids = read_mask_ids(path, object_ids)
    return np.isin(ids, object_ids) if object_ids else ids != 0


def _invalid_to_nan(depth_m: np.ndarray) -> np.ndarray:
    """In place: NaN wherever depth is not a finite positive number. Returns ``depth_m``."""
    valid = depth_m > 0
    valid &= depth_m < np.inf
    np.copyto(depth_m, np.float32(np.nan), where=~valid)
    return depth_m


@contextlib.contextmanager
def _loading(path: Path, what: str) -> Iterator[None]:
    """Turn a failure to open or parse ``path`` inside the block into one SessionError naming it."""
    try:
        yield
    except SessionError:
        raise  # already names the file
    except FileNotFoundError as exc:
        raise SessionError(path, f"expected {what}, file missing") from exc
    except TruncatedNpyError as exc:
        raise SessionError(path, f"expected {what}, found a truncated file ({exc.size} bytes, its header "
                                 f"announces {exc.expected})") from exc
    except DECODE_ERRORS as exc:
        raise SessionError(path, f"expected {what}, could not load it ({type(exc).__name__}: {exc})") from exc


def _check_float_2d(path: Path, what: str, dtype: object, shape: object) -> None:
    """SessionError unless ``dtype``/``shape`` describe a 2-D float32 or float64 array."""
    is_float = isinstance(dtype, np.dtype) and dtype.kind == "f" and dtype.itemsize in (4, 8)
    if not is_float or not isinstance(shape, tuple) or len(shape) != 2:
        raise SessionFormatError(path, f"expected {what} (float32 or float64), found dtype {dtype} with shape {shape}")


def _check_image_shape(path: Path, shape: tuple[int, ...], image_size: tuple[int, int], what: str) -> None:
    """SessionError unless ``shape`` (an array's, channels ignored) is ``image_size`` (H, W),
    the left images' size."""
    if tuple(shape[:2]) != tuple(image_size):
        raise SessionFormatError(
            path,
            f"expected a {what} of {image_size[0]}x{image_size[1]} px (height x width, as the left images), "
            f"found {shape[0]}x{shape[1]}",
        )


def _load_float_npy(path: Path, what: str) -> np.ndarray:
    """A 2-D float32/float64 .npy as a writable, C-contiguous float32 array; SessionError naming ``what``.

    The header and the file's length are checked by the same code as the row reader's
    (read_depth_rows_m), so both accept and refuse the same files with the same message."""
    with _loading(path, what), open(path, "rb") as handle:
        offset, dtype, shape, _ = read_header(handle)
        _check_float_2d(path, what, dtype, shape)
        end = data_end(offset, dtype, shape)
        size = os.fstat(handle.fileno()).st_size
        if size < end:
            raise TruncatedNpyError(size, end)
        handle.seek(0)
        raw = np.load(handle, allow_pickle=False)
    return np.ascontiguousarray(raw, dtype=np.float32)


def read_depth_m(path: Path) -> np.ndarray:
    """Read a depth file as (H, W) float32 metres, read-only, values as stored.

    ``.npy``: 2-D float32/float64 metres (FoundationStereo depth_meter.npy).
    ``.png``: 16-bit single-channel millimetres.
    Invalid depth (0, NaN, inf or negative in the file) is left as it is: every consumer treats a
    value as valid only when it is a finite number > 0, so no pass over the frame is spent on it.
    """
    suffix = path.suffix.lower()
    if suffix == ".npy":
        depth = _load_float_npy(path, "a 2-D float32 depth array in metres (.npy)")
        depth.flags.writeable = False
        return depth
    if suffix == ".png":
        what = "a 16-bit single-channel depth PNG in millimetres"
        raw = _decode(path, what, _imdecode_unchanged)
        if raw.dtype != np.uint16 or raw.ndim != 2:
            channels = 1 if raw.ndim == 2 else raw.shape[2]
            raise SessionFormatError(
                path, f"expected {what}, found {raw.dtype.itemsize * 8}-bit {channels}-channel ({raw.dtype})"
            )
        depth = raw.astype(np.float32)
        depth /= np.float32(MM_PER_M)
        depth.flags.writeable = False
        return depth
    raise SessionFormatError(path, "expected a depth file ending in .npy (float32 m) or .png (uint16 mm)")


def read_depth_rows_m(path: Path, row0: int, row1: int, image_size: tuple[int, int]) -> np.ndarray:
    """Rows ``row0`` to ``row1 - 1`` of a depth .npy of ``image_size`` (H, W), as a writable
    (row1 - row0, W) float32 array in metres, values as stored; only those rows are read.
    SessionError naming the file for a missing, malformed or truncated file, a dtype other than
    float32/float64, or another shape (checked from the header, before any row is read)."""
    what = "a 2-D float32 depth array in metres (.npy)"

    def check(dtype: np.dtype, shape: tuple[int, ...]) -> None:
        _check_float_2d(path, what, dtype, shape)
        _check_image_shape(path, shape, image_size, "depth map")

    with _loading(path, what):
        # read_npy_rows, not np.load(mmap_mode="r")[row0:row1]: extract 14.7% faster (bench_extract --compare)
        rows, _ = read_npy_rows(path, row0, row1, check=check)
    return np.ascontiguousarray(rows, dtype=np.float32)


def read_disparity_px(path: Path) -> np.ndarray:
    """Decode a disparity .npy (FoundationStereo's raw output) to (H, W) float32 px.

    NaN where the disparity is not a finite positive number.
    """
    return _invalid_to_nan(_load_float_npy(path, "a 2-D float32 disparity array in pixels (.npy)"))


_IMREAD_RGB = getattr(cv2, "IMREAD_COLOR_RGB", None)  # OpenCV >= 4.10 decodes straight to RGB


def _imdecode_rgb(data: np.ndarray) -> np.ndarray | None:
    if _IMREAD_RGB is not None:
        return cv2.imdecode(data, _IMREAD_RGB)
    bgr = cv2.imdecode(data, cv2.IMREAD_COLOR)
    return None if bgr is None else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def read_rgb(path: Path) -> np.ndarray:
    """Decode a colour image to (H, W, 3) uint8 RGB (grey images are expanded, alpha dropped)."""
    rgb = _decode(path, "a colour image (PNG or JPEG)", _imdecode_rgb)
    if rgb.dtype != np.uint8:  # 16-bit colour PNGs: keep the high byte
        rgb = (rgb >> 8).astype(np.uint8)
    return rgb


# --------------------------------------------------------------------------------------------


def read_image_size(path: Path) -> tuple[int, int]:
    """(height, width) px of a left image from its header (no full decode); the session reader and the
    importers take the session's image size from it."""
    try:
        with Image.open(path) as image:
            width, height = image.size
    except DECODE_ERRORS as exc:
        raise SessionError(
            path,
            f"expected a readable PNG/JPEG left image to take the image size from ({type(exc).__name__}: {exc})",
        ) from exc
    if width <= 0 or height <= 0:
        raise SessionError(path, f"expected a non-empty left image, found {width}x{height} px")
    return height, width
