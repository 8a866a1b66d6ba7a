"""Palette indices of a palettized PNG (SAM2/DAVIS masks), decoded by OpenCV.

OpenCV expands a palettized PNG to colours, and PIL, which returns the indices, spends about
as long again copying them out through ``tobytes`` while holding the GIL. For the common case,
8 bits per index, the compressed image data of a palettized PNG is byte for byte that of an
8-bit greyscale PNG whose grey levels are the indices (PNG spec, Sec. 11.2.2: colour types 0
and 3 both store one byte per pixel at bit depth 8, filtered and compressed alike). So
:func:`palette_indices` rewrites the header (IHDR colour type 3 -> 0, new CRC), keeps only
the IHDR, IDAT and IEND chunks (the palette and the ancillary chunks describe colours, not
indices) and decodes that with OpenCV. Anything else (other bit depths, a malformed or
truncated file) returns None, and the caller falls back to PIL, which then reports the error.
"""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_IHDR_LENGTH = 13  # bytes of IHDR data
_IHDR_BIT_DEPTH = 8  # offset of the bit depth within the IHDR data
_IHDR_COLOR_TYPE = 9  # offset of the colour type within the IHDR data
_COLOR_GREY = 0  # IHDR colour type of a greyscale PNG
_COLOR_PALETTE = 3  # IHDR colour type of a palettized PNG
_KEPT_CHUNKS = (b"IDAT", b"IEND")  # chunks kept after IHDR: the image data and the end marker


def is_palette_png(data: bytes) -> bool:
    """Whether the PNG bytes ``data`` declare a palettized image (IHDR colour type 3)."""
    offset = len(PNG_SIGNATURE) + 8 + _IHDR_COLOR_TYPE
    return len(data) > offset and data.startswith(PNG_SIGNATURE) and data[offset] == _COLOR_PALETTE


def _chunks(data: bytes):
    """(type, start, end) of each chunk of a PNG after its signature; ValueError when truncated."""
    position = len(PNG_SIGNATURE)
    while position < len(data):
        if position + 12 > len(data):
            raise ValueError("truncated chunk header")
        (length,) = struct.unpack_from(">I", data, position)
        end = position + 12 + length
        if end > len(data):
            raise ValueError("truncated chunk")
        yield data[position + 4:position + 8], position, end
        position = end


def palette_indices(data: bytes) -> np.ndarray | None:
    """The (H, W) uint8 palette indices of the 8-bit palettized PNG ``data``, or None when
    ``data`` is not a well-formed 8-bit palettized PNG (see the module docstring)."""
    if not is_palette_png(data):
        return None
    try:
        chunks = list(_chunks(data))
    except ValueError:
        return None
    if not chunks or chunks[0][0] != b"IHDR" or chunks[0][2] - chunks[0][1] != 12 + _IHDR_LENGTH:
        return None
    ihdr_start = chunks[0][1]
    ihdr = bytearray(data[ihdr_start + 8:ihdr_start + 8 + _IHDR_LENGTH])
    if ihdr[_IHDR_BIT_DEPTH] != 8 or chunks[-1][0] != b"IEND":
        return None
    ihdr[_IHDR_COLOR_TYPE] = _COLOR_GREY
    grey = [PNG_SIGNATURE, struct.pack(">I", _IHDR_LENGTH), b"IHDR", ihdr,
            struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))]
    grey += [data[start:end] for kind, start, end in chunks[1:] if kind in _KEPT_CHUNKS]
    indices = cv2.imdecode(np.frombuffer(b"".join(grey), np.uint8), cv2.IMREAD_UNCHANGED)
    if indices is None or indices.ndim != 2 or indices.dtype != np.uint8:
        return None
    return indices
