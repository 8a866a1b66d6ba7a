"""npy_rows.read_npy_rows: a band of rows of a .npy file equals np.load(...)[rows]."""

from __future__ import annotations

import numpy as np
import pytest

from contact_viz.io.npy_rows import read_npy_rows


@pytest.mark.parametrize("dtype", ["<f4", ">f4", "<f8", "<u2"])
def test_rows_equal_np_load(tmp_path, dtype):
    rng = np.random.default_rng(0)
    array = rng.normal(size=(37, 23)).astype(dtype) if dtype[1] == "f" else rng.integers(0, 999, (37, 23)).astype(dtype)
    path = tmp_path / "a.npy"
    np.save(path, array)
    for row0, row1 in [(0, 37), (0, 0), (5, 6), (10, 30), (36, 37), (37, 37)]:
        rows, shape = read_npy_rows(path, row0, row1)
        assert shape == (37, 23) and rows.dtype == np.dtype(dtype)
        np.testing.assert_array_equal(rows, np.load(path)[row0:row1])


def test_version_2_header(tmp_path):
    array = np.arange(60, dtype=np.float32).reshape(6, 10)
    path = tmp_path / "v2.npy"
    with path.open("wb") as handle:
        np.lib.format.write_array(handle, array, version=(2, 0))
    np.testing.assert_array_equal(read_npy_rows(path, 2, 5)[0], array[2:5])


def test_only_the_rows_are_read(tmp_path):
    # Corrupt every byte outside rows 3..5: the band read is unaffected.
    array = np.arange(80, dtype=np.float32).reshape(8, 10)
    path = tmp_path / "a.npy"
    np.save(path, array)
    data = bytearray(path.read_bytes())
    offset = len(data) - array.nbytes
    for i in range(offset, len(data)):
        if not offset + 3 * 40 <= i < offset + 6 * 40:
            data[i] = 0xFF
    path.write_bytes(bytes(data))
    np.testing.assert_array_equal(read_npy_rows(path, 3, 6)[0], array[3:6])


@pytest.mark.parametrize("array, message", [
    (np.zeros((3, 4, 2), np.float32), "2-D"),
    (np.array([[None, 1]], dtype=object), "numeric"),
])
def test_unsupported_arrays(tmp_path, array, message):
    path = tmp_path / "bad.npy"
    np.save(path, array, allow_pickle=True)
    with pytest.raises(ValueError, match=message):
        read_npy_rows(path, 0, 1)


def test_malformed_files(tmp_path):
    path = tmp_path / "a.npy"
    np.save(path, np.zeros((10, 10), np.float32))
    data = path.read_bytes()
    (tmp_path / "short.npy").write_bytes(data[:-5])
    with pytest.raises(ValueError, match="truncated"):
        read_npy_rows(tmp_path / "short.npy", 0, 2)
    (tmp_path / "text.npy").write_bytes(b"hello, world, not an array")
    with pytest.raises(ValueError, match="magic"):
        read_npy_rows(tmp_path / "text.npy", 0, 1)
    (tmp_path / "cut_header.npy").write_bytes(data[:20])
    with pytest.raises(ValueError, match="header"):
        read_npy_rows(tmp_path / "cut_header.npy", 0, 1)
    with pytest.raises(ValueError, match="out of range"):
        read_npy_rows(path, 5, 11)
    with pytest.raises(FileNotFoundError):
        read_npy_rows(tmp_path / "missing.npy", 0, 1)


def test_check_sees_the_header_before_any_row(tmp_path):
    path = tmp_path / "a.npy"
    np.save(path, np.zeros((4, 6), np.float32))
    seen = []
    rows, shape = read_npy_rows(path, 1, 3, check=lambda dtype, shape: seen.append((dtype, shape)))
    assert seen == [(np.dtype(np.float32), (4, 6))] and rows.shape == (2, 6)

    def refuse(dtype, shape):
        raise LookupError(f"not {shape}")

    with pytest.raises(LookupError, match=r"not \(4, 6\)"):
        read_npy_rows(path, 0, 9, check=refuse)  # before the rows are found out of range


def test_fortran_order_rows_equal_np_load(tmp_path):
    """A column-major file (np.save of a transposed array) is read as np.load reads it."""
    array = np.arange(7 * 5, dtype=np.float32).reshape(5, 7).T  # (7, 5), Fortran order
    path = tmp_path / "f.npy"
    np.save(path, array)
    assert np.lib.format.read_array_header_1_0(_after_magic(path))[1]  # the file is Fortran-ordered
    rows, shape = read_npy_rows(path, 2, 6)
    assert shape == (7, 5)
    np.testing.assert_array_equal(rows, np.load(path)[2:6])
    assert rows.flags.c_contiguous


def _after_magic(path):
    import io

    handle = io.BytesIO(path.read_bytes())
    np.lib.format.read_magic(handle)
    return handle
