"""A band of rows of a 2-D .npy array, read without reading the rest of the file.

The patch of a frame needs the depth only in the rows around the tool (about 40% of a 1080p
frame), so `contact-viz extract` reads just those (contact_viz.io.session.Session.load_depth_rows).
The .npy header is parsed with NumPy's own reader (numpy.lib.format); the rows are read with
one positioned read into the output array. A Fortran-ordered file (``np.save`` of a transposed
or ``np.asfortranarray`` array, which ``np.load`` reads) has no contiguous rows: it is read whole.
"""

from __future__ import annotations

import functools
import io
import os
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np

_MAGIC = b"\x93NUMPY"
_HEADER_LENGTH_FORMAT = {1: "<H", 2: "<I", 3: "<I"}  # struct format of the header length, by major version


class TruncatedNpyError(ValueError):
    """The file is shorter than its header announces."""

    def __init__(self, size: int, expected: int) -> None:
        self.size, self.expected = size, expected
        super().__init__(f"truncated: {size} bytes, the header announces {expected}")


def data_end(offset: int, dtype: np.dtype, shape: tuple[int, ...]) -> int:
    """The byte length a .npy file with this header (data at ``offset``) must have at least."""
    count = 1
    for n in shape:
        count *= int(n)
    return offset + count * dtype.itemsize


@functools.lru_cache(maxsize=32)
def _parse_header(prefix: bytes) -> tuple[np.dtype, tuple[int, ...], bool]:
    """(dtype, shape, fortran_order) of the .npy file starting with ``prefix`` (magic + header);
    cached: the frames of a session share one header."""
    handle = io.BytesIO(prefix)
    version = np.lib.format.read_magic(handle)
    read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    shape, fortran_order, dtype = read(handle)
    return dtype, shape, fortran_order


def read_header(handle) -> tuple[int, np.dtype, tuple[int, ...], bool]:
    """(data offset in bytes, dtype, shape, fortran_order) of the open .npy file ``handle``,
    positioned at its start. ValueError when it is not a .npy file."""
    start = handle.read(len(_MAGIC) + 2)
    if len(start) < len(_MAGIC) + 2 or not start.startswith(_MAGIC):
        raise ValueError("not a .npy file (no NUMPY magic)")
    major = start[len(_MAGIC)]
    if major not in _HEADER_LENGTH_FORMAT:
        raise ValueError(f"unsupported .npy format version {major}")
    length_format = _HEADER_LENGTH_FORMAT[major]
    length_bytes = handle.read(struct.calcsize(length_format))
    if len(length_bytes) < struct.calcsize(length_format):
        raise ValueError("truncated .npy header")
    (header_length,) = struct.unpack(length_format, length_bytes)
    header = handle.read(header_length)
    if len(header) < header_length:
        raise ValueError("truncated .npy header")
    prefix = start + length_bytes + header
    dtype, shape, fortran_order = _parse_header(prefix)
    return len(prefix), dtype, shape, fortran_order


def read_npy_rows(
    path: str | Path, row0: int, row1: int, check: Callable[[np.dtype, tuple[int, ...]], None] | None = None,
) -> tuple[np.ndarray, tuple[int, int]]:
    """Rows ``row0`` to ``row1 - 1`` of the 2-D array stored in the .npy file ``path``, as a
    (row1 - row0, W) array of the file's dtype, and the stored array's full (H, W) shape.

    Only those rows are read (all of a Fortran-ordered file). ``check(dtype, shape)``, when
    given, is called with the stored array's dtype and shape as soon as the header is read; what
    it raises propagates. Raises ValueError when the file does not hold a 2-D non-object array or
    when the rows are out of range, TruncatedNpyError (a ValueError) when it is shorter than its
    header says; OSError when it cannot be opened or read.
    """
    with open(path, "rb", buffering=0) as handle:
        offset, dtype, shape, fortran_order = read_header(handle)
        if check is not None:
            check(dtype, shape)
        if len(shape) != 2 or dtype.hasobject:
            raise ValueError(f"expected a 2-D numeric array, found shape {shape}, dtype {dtype}")
        height, width = shape
        row_bytes = width * dtype.itemsize
        size = os.fstat(handle.fileno()).st_size
        end = data_end(offset, dtype, shape)
        if size < end:
            raise TruncatedNpyError(size, end)
        if not 0 <= row0 <= row1 <= height:
            raise ValueError(f"rows {row0}..{row1 - 1} out of range for an array of {height} rows")
        if fortran_order:  # column-major: every row is spread over the whole file
            whole = np.empty((width, height), dtype)
            _read_into(handle, offset, whole, size, end)
            return np.ascontiguousarray(whole.T[row0:row1]), (height, width)
        rows = np.empty((row1 - row0, width), dtype)
        _read_into(handle, offset + row0 * row_bytes, rows, size, end)
    return rows, (height, width)


def _read_into(handle, position: int, out: np.ndarray, size: int, end: int) -> None:
    """Fill the C-contiguous ``out`` with the bytes of ``handle`` from ``position`` on."""
    view = memoryview(out.reshape(-1).view(np.uint8))
    handle.seek(position)
    filled = 0
    while filled < view.nbytes:
        n = handle.readinto(view[filled:])
        if not n:  # the file shrank since its size was taken
            raise TruncatedNpyError(size, end)
        filled += n
