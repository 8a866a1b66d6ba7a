"""Keep freed memory for the next frame (glibc malloc tuning for frame loops).

Every frame allocates and frees arrays of a few megabytes (the decoded mask and depth, the
crops and integral images of the patch) whose sizes change with the tool's bounding box. By
default glibc serves such blocks with mmap, or trims them off the heap when they are freed,
and the next frame then faults the same pages back in: on a 1080p session about 460 page
faults per frame, a quarter of `contact-viz extract`'s time on one core
(benchmarks/bench_extract.py). :func:`keep_freed_memory` raises both thresholds so that
freed blocks stay in the heap and are reused. The process keeps up to
``TRIM_THRESHOLD_BYTES`` of freed memory; nothing else changes.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools

MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024  # blocks smaller than this come from the heap, B (glibc's maximum)
TRIM_THRESHOLD_BYTES = 256 * 1024 * 1024  # freed memory the heap keeps before returning it to the OS, B
_M_TRIM_THRESHOLD = -1  # mallopt parameter numbers, from glibc's <malloc.h>
_M_MMAP_THRESHOLD = -3


# Kept: extract 18.5% faster wall-clock, 11.9% less CPU than without (bench_extract --compare, 1,200 frames).
@functools.lru_cache(maxsize=1)
def keep_freed_memory() -> bool:
    """Ask glibc's malloc to keep freed blocks of up to ``MMAP_THRESHOLD_BYTES`` in the heap
    (see the module docstring). Returns whether it applied: False where the C library is not
    glibc (macOS, musl), where nothing is changed. Safe to call more than once."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
        libc.gnu_get_libc_version  # noqa: B018 - present in glibc only
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
