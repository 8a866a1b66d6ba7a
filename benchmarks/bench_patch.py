"""Benchmark: milliseconds per frame of compute_patch at 1920x1080, single-threaded.

Frames are synthetic: a tissue surface with stereo-like noise and holes, and a tool shaft of
60-140 px entering from a random image border at a random angle. Prints the median and the
spread over the frames. As in `contact-viz extract`, OpenCV runs on one thread and glibc keeps
freed memory for the next frame (contact_viz.pipeline.allocator).
Run: .venv/bin/python benchmarks/bench_patch.py [--frames 60]
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np

from contact_viz.pipeline.allocator import keep_freed_memory
from contact_viz.params import PatchParams
from contact_viz.geometry.patch import compute_patch


def synthetic_frame(rng: np.random.Generator, height: int = 1080, width: int = 1920):
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    depth = 0.08 + 0.01 * np.sin(xx / 300.0) * np.cos(yy / 200.0)
    depth += rng.normal(0, 0.0005, (height, width)).astype(np.float32)
    tool = np.zeros((height, width), np.uint8)
    tip = (rng.uniform(0.35, 0.65) * width, rng.uniform(0.35, 0.65) * height)
    angle = rng.uniform(0, 2 * np.pi)
    start = (tip[0] + 3000 * np.cos(angle), tip[1] + 3000 * np.sin(angle))
    cv2.line(tool, (int(start[0]), int(start[1])), (int(tip[0]), int(tip[1])), 1,
             thickness=int(rng.uniform(60, 140)))
    tool = tool.astype(bool)
    depth[tool] -= rng.uniform(0.0, 0.02)
    depth[rng.random((height, width)) < 0.03] = np.nan
    return depth.astype(np.float32), tool


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    keep_freed_memory()
    rng = np.random.default_rng(args.seed)
    frames = [synthetic_frame(rng) for _ in range(args.frames)]
    params = PatchParams()
    compute_patch(*frames[0], params)  # warm-up
    times_ms = []
    found = 0
    for depth, tool in frames:
        t0 = time.perf_counter()
        result = compute_patch(depth, tool, params)
        times_ms.append(1000 * (time.perf_counter() - t0))
        found += result.found
    t = np.array(times_ms)
    print(f"compute_patch 1920x1080, {len(t)} frames, 1 thread: median {np.median(t):.2f} ms/frame "
          f"(p10 {np.percentile(t, 10):.2f}, p90 {np.percentile(t, 90):.2f}, max {t.max():.2f}); "
          f"patch found on {found}/{len(t)}")


if __name__ == "__main__":
    main()
