# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled inner loops of the minimum-distance patch (contact_viz.patch).

Each kernel does in one pass over its pixels what would otherwise be a chain of whole-array
NumPy passes (compare, mask, scatter, integral, gather), each allocating a crop-sized
temporary. They are pure functions over arrays, called by contact_viz.patch only; the
formulas are documented there, and tests/test_patch_kernels.py checks each kernel against
the NumPy/OpenCV expression it replaces.

Integral images use OpenCV's layout and summation order (cv2.integral): shape (h+1, w+1),
row 0 and column 0 zero, I[y+1, x+1] = I[y, x+1] + (sum of row y up to column x).
"""

import numpy as np

from libc.math cimport NAN, isfinite

ctypedef fused depth_t:
    float
    double


def fuse_layers(
    const unsigned char[:, ::1] tool,
    const unsigned char[:, ::1] interior,
    const unsigned char[:, ::1] near,
    const unsigned char[:, ::1] far,
    const depth_t[:, :] depth_m,
    unsigned char[:, :] layer_ids,
    unsigned char id_background,
    unsigned char id_interior,
    unsigned char id_tool_edge,
    unsigned char id_ring,
    unsigned char id_band,
):
    """One pass over the (h, w) crop that labels the layers and integrates the tool depth.

    Inputs are 0/1 uint8 masks (tool, eroded interior, tool dilated by the ring, tool dilated
    by ring + band) and the depth crop ``depth_m`` (float32/float64, m; valid = finite and > 0;
    rows contiguous). Writes the layer id of every pixel into ``layer_ids`` (rows contiguous):
    interior, tool edge (tool but not interior), ring (near but not tool), band (far but not
    near) or background. The masks must nest (interior in tool in near in far).

    Returns ``(band_flat, band_valid, tool_sum_int, tool_cnt_int, tool_area)``: (N,) int64
    row-major flat crop indices of the band pixels; (N,) uint8 1 where their depth is valid;
    the (h+1, w+1) float64 integral of the valid interior depth, m; the (h+1, w+1) int32
    integral of the valid interior count; the number of tool pixels.
    """
    cdef Py_ssize_t height = tool.shape[0], width = tool.shape[1]
    cdef Py_ssize_t y, x, n_band = 0, n_tool = 0
    cdef double d, row_sum
    cdef int row_cnt, valid, take, code
    cdef unsigned char ids[5]
    cdef const unsigned char *tool_row
    cdef const unsigned char *interior_row
    cdef const unsigned char *near_row
    cdef const unsigned char *far_row
    cdef const depth_t *depth_row
    cdef unsigned char *layer_row
    cdef double *sum_above
    cdef double *sum_row
    cdef int *cnt_above
    cdef int *cnt_row
    _check_same_shape(tool, interior, near, far, depth_m, layer_ids)
    ids[0], ids[1], ids[2], ids[3], ids[4] = id_background, id_band, id_ring, id_tool_edge, id_interior
    if depth_m.strides[1] != sizeof(depth_t) or layer_ids.strides[1] != 1:
        raise ValueError("depth_m and layer_ids must be contiguous along their rows")
    band_flat_arr = np.empty(height * width, np.int64)
    band_valid_arr = np.empty(height * width, np.uint8)
    tool_sum_arr = np.empty((height + 1, width + 1), np.float64)
    tool_cnt_arr = np.empty((height + 1, width + 1), np.int32)
    cdef long long[::1] band_flat = band_flat_arr
    cdef unsigned char[::1] band_valid = band_valid_arr
    cdef double[:, ::1] tool_sum = tool_sum_arr
    cdef int[:, ::1] tool_cnt = tool_cnt_arr
    with nogil:
        for x in range(width + 1):
            tool_sum[0, x] = 0.0
            tool_cnt[0, x] = 0
        for y in range(height):
            tool_row = &tool[y, 0]
            interior_row = &interior[y, 0]
            near_row = &near[y, 0]
            far_row = &far[y, 0]
            depth_row = &depth_m[y, 0]
            layer_row = &layer_ids[y, 0]
            sum_above = &tool_sum[y, 0]
            sum_row = &tool_sum[y + 1, 0]
            cnt_above = &tool_cnt[y, 0]
            cnt_row = &tool_cnt[y + 1, 0]
            sum_row[0] = 0.0
            cnt_row[0] = 0
            row_sum = 0.0
            row_cnt = 0
            for x in range(width):
                # The masks nest (interior in tool in near in far), so their sum is the layer.
                code = interior_row[x] + tool_row[x] + near_row[x] + far_row[x]
                layer_row[x] = ids[code]
                n_tool += code >= 3
                d = depth_row[x]
                valid = isfinite(d) and d > 0.0
                take = valid and code == 4
                row_sum += d if take else 0.0
                row_cnt += take
                if code == 1:
                    band_flat[n_band] = y * width + x
                    band_valid[n_band] = valid
                    n_band += 1
                sum_row[x + 1] = sum_above[x + 1] + row_sum
                cnt_row[x + 1] = cnt_above[x + 1] + row_cnt
    return band_flat_arr[:n_band].copy(), band_valid_arr[:n_band].copy(), tool_sum_arr, tool_cnt_arr, int(n_tool)


def _check_same_shape(*arrays):
    shapes = {(a.shape[0], a.shape[1]) for a in arrays}
    if len(shapes) != 1:
        raise ValueError(f"the arrays must all have the same (h, w) shape, got {sorted(shapes)}")


cdef struct _Corners:
    # Flat offsets into an (h+1, w+1) integral image of a window's corners (y1, x1), (y0, x1),
    # (y1, x0), (y0, x0): the window's sum is I[a] - I[b] - I[c] + I[d].
    Py_ssize_t a, b, c, d


cdef inline _Corners _window_corners(long long flat, Py_ssize_t height, Py_ssize_t width,
                                     Py_ssize_t half) noexcept nogil:
    """Corners of the (2*half+1)^2 window around flat crop index ``flat``, clipped to the
    (height, width) crop."""
    cdef Py_ssize_t y = flat // width, x = flat - (flat // width) * width, stride = width + 1
    cdef Py_ssize_t y0 = y - half if y > half else 0
    cdef Py_ssize_t y1 = y + half + 1 if y + half + 1 < height else height
    cdef Py_ssize_t x0 = x - half if x > half else 0
    cdef Py_ssize_t x1 = x + half + 1 if x + half + 1 < width else width
    cdef _Corners corners
    corners.a = y1 * stride + x1
    corners.b = y0 * stride + x1
    corners.c = y1 * stride + x0
    corners.d = y0 * stride + x0
    return corners


cdef inline double _window_sum(const double* integral, _Corners k) noexcept nogil:
    return integral[k.a] - integral[k.b] - integral[k.c] + integral[k.d]


cdef inline int _window_count(const int* integral, _Corners k) noexcept nogil:
    return integral[k.a] - integral[k.b] - integral[k.c] + integral[k.d]


def band_distances(
    const double[:, ::1] tool_sum_int,
    const int[:, ::1] tool_cnt_int,
    const long long[::1] band_flat,
    const unsigned char[::1] band_valid,
    const depth_t[:, :] depth_m,
    Py_ssize_t half,
    int tau_tool,
):
    """``d(p)`` and the mean valid interior depth of ``N1(p)`` at every band pixel.

    ``tool_sum_int``/``tool_cnt_int``: the (h+1, w+1) integrals of :func:`fuse_layers`;
    ``band_flat``/``band_valid``: its band pixels; ``depth_m``: the (h, w) depth crop, m;
    ``half``: N1 // 2 (windows are clipped to the crop); ``tau_tool``: fewest interior pixels.
    Returns ``(band_d, tool_mean)``, (N,) float64 m each: tool_mean is NaN where N1(p) holds
    fewer than ``tau_tool`` valid interior pixels, band_d also where p's own depth is invalid.
    """
    cdef Py_ssize_t height = tool_sum_int.shape[0] - 1, width = tool_sum_int.shape[1] - 1
    cdef Py_ssize_t n = band_flat.shape[0], i, y
    cdef int count
    cdef double mean
    cdef _Corners corners
    band_d_arr = np.empty(n, np.float64)
    tool_mean_arr = np.empty(n, np.float64)
    cdef double[::1] band_d = band_d_arr
    cdef double[::1] tool_mean = tool_mean_arr
    with nogil:
        for i in range(n):
            corners = _window_corners(band_flat[i], height, width, half)
            count = _window_count(&tool_cnt_int[0, 0], corners)
            if count < tau_tool:
                tool_mean[i] = NAN
                band_d[i] = NAN
                continue
            mean = _window_sum(&tool_sum_int[0, 0], corners) / count
            tool_mean[i] = mean
            y = band_flat[i] // width
            band_d[i] = <double>depth_m[y, band_flat[i] - y * width] - mean if band_valid[i] else NAN
    return band_d_arr, tool_mean_arr


def band_window_sums(
    const long long[::1] band_flat,
    const double[::1] band_d,
    Py_ssize_t height,
    Py_ssize_t width,
    Py_ssize_t half,
):
    """Sums over the (2*half+1)^2 window around every band pixel (clipped to the (height, width)
    crop) of ``|d|`` and of the count of defined (finite) ``d``, over the band pixels.

    ``band_flat``: (N,) int64 flat crop indices; ``band_d``: (N,) float64 m, NaN = undefined.
    Returns ``(count, total)``: (N,) int32 and (N,) float64 m.
    """
    cdef Py_ssize_t n = band_flat.shape[0], i, y, x, next_flat
    cdef double row_sum, value
    cdef _Corners corners
    cdef int row_cnt
    cdef double *abs_above
    cdef double *abs_row
    cdef int *cnt_above
    cdef int *cnt_row
    if band_d.shape[0] != n:
        raise ValueError(f"band_d has {band_d.shape[0]} values for {n} band pixels")
    for i in range(1, n):
        if band_flat[i] <= band_flat[i - 1]:
            raise ValueError("band_flat must be strictly increasing (row-major order)")
    if n and (band_flat[0] < 0 or band_flat[n - 1] >= height * width):
        raise ValueError(f"band_flat must index a {height}x{width} crop")
    abs_int_arr = np.empty((height + 1, width + 1), np.float64)
    cnt_int_arr = np.empty((height + 1, width + 1), np.int32)
    count_arr = np.empty(n, np.int32)
    total_arr = np.empty(n, np.float64)
    cdef double[:, ::1] abs_int = abs_int_arr
    cdef int[:, ::1] cnt_int = cnt_int_arr
    cdef int[::1] count = count_arr
    cdef double[::1] total = total_arr
    with nogil:
        # Integrate |d| and the count of defined d (cv2.integral's order), taking each band
        # pixel's value as the row-major sweep reaches it (band_flat is sorted).
        for x in range(width + 1):
            abs_int[0, x] = 0.0
            cnt_int[0, x] = 0
        i = 0
        next_flat = band_flat[0] if n else -1
        for y in range(height):
            abs_above = &abs_int[y, 0]
            abs_row = &abs_int[y + 1, 0]
            cnt_above = &cnt_int[y, 0]
            cnt_row = &cnt_int[y + 1, 0]
            abs_row[0] = 0.0
            cnt_row[0] = 0
            row_sum = 0.0
            row_cnt = 0
            for x in range(width):
                if y * width + x == next_flat:
                    value = band_d[i]
                    if isfinite(value):
                        row_sum += value if value >= 0.0 else -value
                        row_cnt += 1
                    i += 1
                    next_flat = band_flat[i] if i < n else -1
                abs_row[x + 1] = abs_above[x + 1] + row_sum
                cnt_row[x + 1] = cnt_above[x + 1] + row_cnt
        for i in range(n):
            corners = _window_corners(band_flat[i], height, width, half)
            count[i] = _window_count(&cnt_int[0, 0], corners)
            total[i] = _window_sum(&abs_int[0, 0], corners)
    return count_arr, total_arr


def window_members(
    const long long[::1] band_flat,
    const double[::1] band_d,
    Py_ssize_t width,
    Py_ssize_t center,
    Py_ssize_t half,
):
    """Indices, in band order, of the band pixels with a defined (finite) ``d`` in the
    (2*half+1)^2 window around band pixel ``center``.

    ``band_flat``: (N,) int64 flat indices into a crop of ``width`` columns, strictly increasing
    (row-major), so the window's rows are one contiguous run of band pixels, found by bisection;
    ``band_d``: (N,) float64. Returns (M,) int64.
    """
    cdef Py_ssize_t n = band_flat.shape[0], lo, hi, mid, i, m = 0, cy, cx, x
    cdef long long first
    if band_d.shape[0] != n:
        raise ValueError(f"band_d has {band_d.shape[0]} values for {n} band pixels")
    if not 0 <= center < n:
        raise IndexError(f"center {center} out of range for {n} band pixels")
    members_arr = np.empty((2 * half + 1) * (2 * half + 1), np.int64)
    cdef long long[::1] members = members_arr
    with nogil:
        cy = band_flat[center] // width
        cx = band_flat[center] - cy * width
        first = (cy - half) * width if cy > half else 0
        lo, hi = 0, center  # the first band pixel at or after row cy - half
        while lo < hi:
            mid = (lo + hi) // 2
            if band_flat[mid] < first:
                lo = mid + 1
            else:
                hi = mid
        i = lo
        while i < n and band_flat[i] // width <= cy + half:
            x = band_flat[i] - (band_flat[i] // width) * width
            if cx - half <= x <= cx + half and isfinite(band_d[i]):
                members[m] = i
                m += 1
            i += 1
    return members_arr[:m].copy()


def ring_depth_integrals(
    const unsigned char[:, ::1] outer,
    const unsigned char[:, ::1] inner,
    const depth_t[:, :] depth_m,
):
    """Integrals of the valid depth and of its count over the pixels in ``outer`` but not in ``inner``.

    ``outer``, ``inner``: (h, w) uint8 0/1 masks; ``depth_m``: the (h, w) depth crop (float32 or
    float64, m; valid = finite and > 0; rows contiguous). Returns ``(sum_int, cnt_int)``: the
    (h+1, w+1) float64 and int32 integral images (cv2.integral's layout and order) of
    ``where(outer & ~inner & valid, depth, 0)`` and of ``outer & ~inner & valid``: in one pass
    what patch.py's bleeding test did with a subtraction, three comparisons, a select and two
    cv2.integral calls.
    """
    cdef Py_ssize_t height = outer.shape[0], width = outer.shape[1]
    cdef Py_ssize_t y, x
    cdef double d, row_sum
    cdef int row_cnt, take
    cdef const unsigned char *outer_row
    cdef const unsigned char *inner_row
    cdef const depth_t *depth_row
    cdef double *sum_above
    cdef double *sum_row
    cdef int *cnt_above
    cdef int *cnt_row
    _check_same_shape(outer, inner, depth_m)
    if depth_m.strides[1] != sizeof(depth_t):
        raise ValueError("depth_m must be contiguous along its rows")
    sum_arr = np.empty((height + 1, width + 1), np.float64)
    cnt_arr = np.empty((height + 1, width + 1), np.int32)
    cdef double[:, ::1] sums = sum_arr
    cdef int[:, ::1] cnts = cnt_arr
    with nogil:
        for x in range(width + 1):
            sums[0, x] = 0.0
            cnts[0, x] = 0
        for y in range(height):
            outer_row = &outer[y, 0]
            inner_row = &inner[y, 0]
            depth_row = &depth_m[y, 0]
            sum_above = &sums[y, 0]
            sum_row = &sums[y + 1, 0]
            cnt_above = &cnts[y, 0]
            cnt_row = &cnts[y + 1, 0]
            sum_row[0] = 0.0
            cnt_row[0] = 0
            row_sum = 0.0
            row_cnt = 0
            for x in range(width):
                d = depth_row[x]
                take = outer_row[x] != 0 and inner_row[x] == 0 and isfinite(d) and d > 0.0
                row_sum += d if take else 0.0
                row_cnt += take
                sum_row[x + 1] = sum_above[x + 1] + row_sum
                cnt_row[x + 1] = cnt_above[x + 1] + row_cnt
    return sum_arr, cnt_arr


def reject_bled(
    const double[:, ::1] beyond_sum_int,
    const int[:, ::1] beyond_cnt_int,
    const long long[::1] band_flat,
    double[::1] band_d,
    const double[::1] tool_mean,
    Py_ssize_t half,
    double step_m,
):
    """The patch's bleeding test in one pass over the band pixels; returns how many it rejected.

    For band pixel i with a window (2*half+1)^2 around it (clipped to the crop) holding at least one
    pixel of the integrals ``beyond_*_int`` (:func:`ring_depth_integrals`): ``step = beyond mean -
    tool_mean[i]``; ``band_d[i]`` is set to NaN (in place) when ``step >= step_m`` and
    ``band_d[i] < step / 2``. NaN never passes a comparison (as in NumPy).
    """
    cdef Py_ssize_t height = beyond_sum_int.shape[0] - 1, width = beyond_sum_int.shape[1] - 1
    cdef Py_ssize_t n = band_flat.shape[0], i
    cdef int count, rejected = 0
    cdef double step
    cdef _Corners corners
    if band_d.shape[0] != n or tool_mean.shape[0] != n:
        raise ValueError(f"band_d and tool_mean must have one value per band pixel ({n})")
    with nogil:
        for i in range(n):
            corners = _window_corners(band_flat[i], height, width, half)
            count = _window_count(&beyond_cnt_int[0, 0], corners)
            if count < 1:
                continue
            step = _window_sum(&beyond_sum_int[0, 0], corners) / count - tool_mean[i]
            if step >= step_m and band_d[i] < step / 2:
                band_d[i] = NAN
                rejected += 1
    return rejected
