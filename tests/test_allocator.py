"""allocator.keep_freed_memory: frame-sized blocks are reused instead of faulted back in."""

from __future__ import annotations

import platform
import resource
import subprocess
import sys

import cv2
import numpy as np
import pytest

from contact_viz.pipeline.allocator import keep_freed_memory

# Runs extract's per-frame work (read, patch, features row) over a session in a fresh process
# and prints the median minor page faults per frame.
LOOP = """
import resource, sys
import numpy as np
if sys.argv[2] == "keep":
    from contact_viz.pipeline.allocator import keep_freed_memory
    assert keep_freed_memory()
from contact_viz.pipeline.extract import FeatureRows
from contact_viz.params import PatchParams
from contact_viz.io.session import open_session
session = open_session(sys.argv[1])
task = FeatureRows(session, PatchParams(), tuple(range(len(session))))
faults = []
for index in range(len(session)):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    task(index, index + 1)
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(int(np.median(faults[2:])))
"""


def write_session(root, frames=12, height=1080, width=1920):
    """A 1080p session whose tool (a thick line) moves and changes width from frame to frame."""
    rng = np.random.default_rng(0)
    for sub in ("left", "masks", "depth"):
        (root / sub).mkdir(parents=True)
    (root / "K.txt").write_text("1000 0 960 0 1000 540 0 0 1\n0.005\n")
    (root / "force.csv").write_text("frame,fx,fy,fz\n" + "".join(f"{i},0,0,{i % 3}\n" for i in range(frames)))
    left = np.zeros((height, width, 3), np.uint8)
    for i in range(frames):
        tool = np.zeros((height, width), np.uint8)
        tip = (int(rng.integers(500, 1400)), int(rng.integers(200, 900)))
        cv2.line(tool, (0, int(rng.integers(0, height))), tip, 1, int(rng.integers(40, 160)))
        cv2.imwrite(str(root / "masks" / f"{i}.png"), tool * 255)
        depth = rng.uniform(0.07, 0.09, (height, width)).astype(np.float32)
        depth[tool == 1] -= 0.01
        np.save(root / "depth" / f"{i}.npy", depth)
        cv2.imwrite(str(root / "left" / f"{i}.png"), left)


def faults_per_frame(session, mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", LOOP, str(session), mode], check=True, capture_output=True, text=True)
    return int(out.stdout)


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_frame_loop_stops_faulting(tmp_path):
    assert keep_freed_memory() is True and keep_freed_memory() is True  # idempotent
    write_session(tmp_path / "s", height=1080, width=1920)
    depth_pages = 1080 * 1920 * 4 // resource.getpagesize()  # pages of one float32 depth map
    default, kept = faults_per_frame(tmp_path / "s", "default"), faults_per_frame(tmp_path / "s", "keep")
    # By default glibc hands the frame-sized blocks back and faults them in again every frame
    # (about 1.5 depth maps' worth); kept, they are reused: under 1% of a depth map per frame.
    assert default > depth_pages / 2
    assert kept < depth_pages / 100
