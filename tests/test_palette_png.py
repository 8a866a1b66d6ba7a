"""palette_png: the indices of palettized PNGs through OpenCV, checked against PIL's decoding."""

from __future__ import annotations

import io
import struct

import numpy as np
import pytest
from PIL import Image, PngImagePlugin

from contact_viz.io.palette_png import PNG_SIGNATURE, is_palette_png, palette_indices
from contact_viz.io.session import read_tool_mask


def palette_png(ids: np.ndarray, palette: list[int], **save) -> bytes:
    image = Image.fromarray(ids)
    image.putpalette(palette)
    assert image.mode == "P"
    buffer = io.BytesIO()
    image.save(buffer, format="PNG", **save)
    return buffer.getvalue()


def pil_indices(data: bytes) -> np.ndarray:
    with Image.open(io.BytesIO(data)) as image:
        assert image.mode == "P"
        return np.asarray(image)


def chunk_types(data: bytes) -> list[bytes]:
    types, position = [], len(PNG_SIGNATURE)
    while position < len(data):
        (length,) = struct.unpack_from(">I", data, position)
        types.append(data[position + 4:position + 8])
        position += 12 + length
    return types


DAVIS = [0, 0, 0, 128, 0, 0, 0, 128, 0, 128, 128, 0] + [0] * (256 * 3 - 12)


def test_smoke_equals_pil():
    ids = np.zeros((30, 41), np.uint8)
    ids[3:12, 5:20] = 1
    ids[15:29, 22:40] = 3
    data = palette_png(ids, DAVIS)
    assert is_palette_png(data)
    out = palette_indices(data)
    assert out.dtype == np.uint8 and out.shape == (30, 41)
    np.testing.assert_array_equal(out, pil_indices(data))
    np.testing.assert_array_equal(out, ids)


def test_indices_not_colours():
    # Every palette entry is black: colours cannot tell the objects apart, indices can.
    ids = np.arange(64, dtype=np.uint8).reshape(8, 8)
    data = palette_png(ids, [0] * (256 * 3))
    np.testing.assert_array_equal(palette_indices(data), ids)


def test_many_idat_and_ancillary_chunks():
    rng = np.random.default_rng(0)
    ids = rng.integers(0, 256, (300, 400), dtype=np.uint8)  # incompressible: several IDAT chunks
    info = PngImagePlugin.PngInfo()
    info.add_text("Software", "test")
    data = palette_png(ids, list(rng.integers(0, 256, 768)), transparency=0, pnginfo=info)
    types = chunk_types(data)
    assert types.count(b"IDAT") > 1 and b"tRNS" in types and b"tEXt" in types and b"PLTE" in types
    np.testing.assert_array_equal(palette_indices(data), pil_indices(data))


def test_not_handled_returns_none():
    ids = np.zeros((10, 12), np.uint8)
    ids[2:5, 3:9] = 1
    four_bit = palette_png(ids, DAVIS[:48], bits=4)
    assert is_palette_png(four_bit)
    assert palette_indices(four_bit) is None  # the session reader then uses PIL
    grey = io.BytesIO()
    Image.fromarray(ids * 255).save(grey, format="PNG")
    assert not is_palette_png(grey.getvalue()) and palette_indices(grey.getvalue()) is None
    good = palette_png(ids, DAVIS)
    assert palette_indices(good[: len(good) // 2]) is None  # truncated
    assert palette_indices(b"") is None and palette_indices(b"not a png at all") is None
    # A corrupted IDAT payload (its CRC no longer matches) is not decoded.
    idat = good.index(b"IDAT")
    corrupt = good[: idat + 6] + bytes([good[idat + 6] ^ 0xFF]) + good[idat + 7:]
    assert palette_indices(corrupt) is None


def test_read_tool_mask_uses_it(tmp_path):
    ids = np.zeros((20, 24), np.uint8)
    ids[1:8, 2:9] = 2
    ids[10:18, 12:22] = 5
    for bits, name in ((8, "eight.png"), (4, "four.png")):
        (tmp_path / name).write_bytes(palette_png(ids, DAVIS[:48] if bits == 4 else DAVIS, bits=bits))
        np.testing.assert_array_equal(read_tool_mask(tmp_path / name), ids != 0)
        np.testing.assert_array_equal(read_tool_mask(tmp_path / name, object_ids=(5,)), ids == 5)


@pytest.mark.parametrize("cut", [0.3, 0.9])
def test_read_tool_mask_truncated_is_one_error(tmp_path, cut):
    from contact_viz.errors import SessionError

    ids = np.random.default_rng(1).integers(0, 3, (64, 64), dtype=np.uint8)
    data = palette_png(ids, DAVIS)
    path = tmp_path / "cut.png"
    path.write_bytes(data[: int(len(data) * cut)])
    with pytest.raises(SessionError, match="cut.png"):
        read_tool_mask(path)
