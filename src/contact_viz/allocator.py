"""Process-wide tuning of the C memory allocator for long frame loops (glibc only).

Every frame decodes a 1080p depth map (8 MB) and a mask (2 MB) and drops them a few ms later.
glibc serves blocks that large with a fresh ``mmap`` and gives them back with ``munmap``, so
each frame pays for thousands of page faults and for the kernel zeroing the pages again; in
`contact-viz extract` that churn cost about 3.5 ms of a 9 ms frame (see the README,
"Performance"). :func:`retain_freed_memory` makes glibc keep freed blocks and reuse them.

This changes the whole process, so the library never calls it by itself: the command-line
entry point does, and a script that loops over many frames may too.
"""

from __future__ import annotations

import ctypes
import sys

# mallopt(3) parameter numbers, from glibc's <malloc.h>.
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3

HEAP_BLOCK_MAX_BYTES = 128 << 20  # blocks up to this size come from the reusable heap, not mmap, B
KEEP_FREE_BYTES = 1 << 30  # free heap kept for reuse before any is returned to the system, B


def retain_freed_memory() -> bool:
    """Make glibc keep and reuse freed blocks of up to ``HEAP_BLOCK_MAX_BYTES``.

    Returns True when the settings took effect, False where they do not apply (not Linux, not
    glibc, e.g. musl or macOS); calling it again is harmless. The cost is that the process keeps
    up to ``KEEP_FREE_BYTES`` of freed memory instead of returning it to the system at once.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, HEAP_BLOCK_MAX_BYTES)) and bool(mallopt(M_TRIM_THRESHOLD, KEEP_FREE_BYTES))
