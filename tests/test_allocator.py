"""The allocator tuning: freed frame-sized blocks are reused instead of being faulted in again."""

from __future__ import annotations

import subprocess
import sys

import pytest

from contact_viz.allocator import retain_freed_memory

# A child process decodes "frames" the way the session reader does: a background thread allocates
# and fills an 8 MB depth map and a 2 MB mask per frame, a few frames are alive at once, and the
# consumer drops them. It prints the minor page faults of 20 rounds of 3 frames.
CHILD = r"""
import resource, sys
from concurrent.futures import ThreadPoolExecutor
import numpy as np
from contact_viz.allocator import retain_freed_memory
if sys.argv[1] == "retain":
    assert retain_freed_memory()
def decode(_):
    return np.ones((1080, 1920), np.float32), np.ones((1080, 1920), bool)
with ThreadPoolExecutor(1) as reader:
    for _ in range(5):  # warm-up: the first rounds fault pages in whatever the setting
        list(reader.map(decode, range(3)))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(20):
        frames = list(reader.map(decode, range(3)))
        del frames
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", CHILD, mode], check=True, capture_output=True, text=True)
    return int(out.stdout.strip())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt")
def test_retained_blocks_are_reused_without_page_faults():
    default, retained = _faults("default"), _faults("retain")
    pages_per_frame = 1080 * 1920 * (4 + 1) // 4096
    # By default glibc gives the thread's blocks back and faults them in again (about a page
    # fault per page per frame); retained, the rounds reuse the same pages.
    assert default > 10 * pages_per_frame, (default, retained)
    assert retained < pages_per_frame, (default, retained)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt")
def test_retain_freed_memory_is_idempotent():
    assert retain_freed_memory() and retain_freed_memory()
