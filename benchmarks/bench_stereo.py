"""Benchmark: SGBM depth accuracy on real data (Middlebury) and its speed, incl. how to use 2 cores.

1. Accuracy on the Middlebury 2014 "Motorcycle" pair shipped by scikit-image (741x500, true
   disparity): share of pixels valid in both maps within 2 px of the truth, valid fraction,
   ms per frame: first through `contact-viz depth -o` (a session with the pair's ROS calibration,
   whose principal points differ, and no mask), then for the default SGBMParams (the search range
   from that calibration) beside the matching before plain whole-frame matching had its own block
   size (the width rule's 7 px blocks, 1/8 of the width searched), and a few variants.
2. Speed at endoscope sizes (1280x1024 and 1920x1080; the Middlebury pair resized, so only the
   timing means something).
3. Throughput of many frames on 2 cores: OpenCV's own threads vs 2 worker threads vs 2
   processes (the process timing includes starting them and sending the images).

Run: .venv/bin/python benchmarks/bench_stereo.py [--repeats 5] [--frames 8]
"""

from __future__ import annotations

import argparse
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

import cv2
import numpy as np
from skimage import data

from contact_viz.geometry.stereo import SGBMParams, sgbm_disparity

# The pair's calibration (skimage.data.stereo_motorcycle's docstring): focal length, principal point of the left
# camera (px), the right camera's principal point x minus the left's (doffs, px), baseline (m)
MB_FX_PX, MB_CX_PX, MB_CY_PX, MB_DOFFS_PX, MB_BASELINE_M = 994.978, 311.193, 254.877, 31.086, 0.193001


def within_2px(disparity, truth) -> tuple[float, float]:
    """(share within 2 px of truth over pixels valid in both, valid fraction)."""
    both = np.isfinite(disparity) & np.isfinite(truth)
    return float(np.mean(np.abs(disparity[both] - truth[both]) <= 2.0)), float(np.isfinite(disparity).mean())


def depth_command(left, right, truth) -> str:
    """One line: Motorcycle through `contact-viz depth -o` on a session with a ROS calibration (doffs), no mask."""
    import tempfile
    from pathlib import Path

    from PIL import Image

    from contact_viz.io.session import open_session
    from contact_viz.pipeline.depth import run_depth_command

    height, width = truth.shape

    def ros(p_row0):
        k = f"[{MB_FX_PX}, 0, {MB_CX_PX}, 0, {MB_FX_PX}, {MB_CY_PX}, 0, 0, 1]"
        p = "[" + ", ".join(str(v) for v in p_row0 + [0, MB_FX_PX, MB_CY_PX, 0, 0, 0, 1, 0]) + "]"
        return (f"image_width: {width}\nimage_height: {height}\ncamera_matrix:\n  rows: 3\n  cols: 3\n  data: {k}\n"
                "distortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [0, 0, 0, 0, 0]\n"
                "rectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n"
                f"projection_matrix:\n  rows: 3\n  cols: 4\n  data: {p}\n")

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "motorcycle"
        for sub in ("left", "right"):
            (root / sub).mkdir(parents=True)
        Image.fromarray(left).save(root / "left" / "0.png")
        Image.fromarray(right).save(root / "right" / "0.png")
        (root / "left.yaml").write_text(ros([MB_FX_PX, 0, MB_CX_PX, 0]))
        (root / "right.yaml").write_text(ros([MB_FX_PX, 0, MB_CX_PX + MB_DOFFS_PX, -MB_FX_PX * MB_BASELINE_M]))
        t0 = time.perf_counter()
        run_depth_command(root, cache_dir=Path(tmp) / "cache", output=Path(tmp) / "out", workers=1)
        ms = 1000 * (time.perf_counter() - t0)
        p = open_session(root, cache_dir=Path(tmp) / "cache", require_masks=False).sgbm_cache.params
        depth = np.load(Path(tmp) / "out" / "0.npy")
    within, valid = within_2px(MB_FX_PX * MB_BASELINE_M / depth - MB_DOFFS_PX, truth)
    return (f"  contact-viz depth -o ({p.num_disparities} disp, block {p.plain_block_size}): {within:.2%} within 2 px, "
            f"valid {valid:.1%}, {ms:.0f} ms (the command, once)")


def accuracy(left, right, truth, params: SGBMParams, repeats: int) -> tuple[float, float, float]:
    """(share within 2 px of truth over pixels valid in both, valid fraction, median ms/frame)."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        disparity = sgbm_disparity(left, right, params)
        times.append(1000 * (time.perf_counter() - t0))
    within, valid = within_2px(disparity, truth)
    return within, valid, float(np.median(times))


def _one(pair) -> float:
    left, right = pair
    return float(np.isfinite(sgbm_disparity(left, right, SGBMParams())).mean())


def _init_worker(threads: int) -> None:
    cv2.setNumThreads(threads)


def throughput(pairs, mode: str) -> float:
    """ms per frame over ``pairs`` with one parallel strategy."""
    t0 = time.perf_counter()
    if mode == "1 thread, OpenCV 2 threads":
        cv2.setNumThreads(2)
        [_one(p) for p in pairs]
    elif mode == "1 thread, OpenCV 1 thread":
        cv2.setNumThreads(1)
        [_one(p) for p in pairs]
    elif mode == "2 threads, OpenCV 2 threads":
        cv2.setNumThreads(2)
        with ThreadPoolExecutor(2) as pool:
            list(pool.map(_one, pairs))
    elif mode == "2 threads, OpenCV 1 thread":
        cv2.setNumThreads(1)
        with ThreadPoolExecutor(2) as pool:
            list(pool.map(_one, pairs))
    elif mode == "2 processes, OpenCV 1 thread":
        # spawn: forking after OpenCV has started its thread pool can deadlock the children
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(2, mp_context=context, initializer=_init_worker, initargs=(1,)) as pool:
            list(pool.map(_one, pairs))
    cv2.setNumThreads(2)
    return 1000 * (time.perf_counter() - t0) / len(pairs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--frames", type=int, default=8)
    args = parser.parse_args()
    left, right, truth = data.stereo_motorcycle()
    print(f"Middlebury Motorcycle {left.shape[1]}x{left.shape[0]} (skimage.data.stereo_motorcycle), "
          f"{np.isfinite(truth).mean():.1%} of pixels with true disparity; OpenCV {cv2.__version__}, "
          f"{cv2.getNumThreads()} threads")
    print(depth_command(left, right, truth), flush=True)
    variants = {
        "before: 7 px blocks, 96 disp": SGBMParams(plain_block_size=7, num_disparities=96),
        "default (LR check, 3-way, median 5)": SGBMParams(),
        "no median": SGBMParams(median_px=0),
        "no LR check": SGBMParams(lr_check=False),
        "block 5": SGBMParams(block_size=5),
        "mode hh (8 paths)": SGBMParams(mode="hh"),
        "downscale 2": SGBMParams(downscale=2),
    }
    for name, params in variants.items():
        params = params.resolve(left.shape[1], fx_px=MB_FX_PX, baseline_m=MB_BASELINE_M,
                                disparity_offset_px=MB_DOFFS_PX)  # as a session with this calibration
        p = params
        within, valid, ms = accuracy(left, right, truth, params, args.repeats)
        print(f"  {name:35s} ({p.num_disparities} disp, block {p.plain_block_size}): {within:.2%} within 2 px, "
              f"valid {valid:.1%}, {ms:.0f} ms/frame")

    for width, height in ((1280, 1024), (1920, 1080)):
        big_l = cv2.resize(left, (width, height), interpolation=cv2.INTER_CUBIC)
        big_r = cv2.resize(right, (width, height), interpolation=cv2.INTER_CUBIC)
        davinci = SGBMParams().resolve(width, fx_px=1103.0 * width / 1920, baseline_m=0.0041)  # 15 mm nearest
        for name, params in (("default", SGBMParams()), ("no median", SGBMParams(median_px=0)),
                             ("downscale 2", SGBMParams(downscale=2)), ("da Vinci", davinci)):
            p = params.resolve(width)
            times = []
            for _ in range(max(1, args.repeats // 2)):
                t0 = time.perf_counter()
                sgbm_disparity(big_l, big_r, params)
                times.append(1000 * (time.perf_counter() - t0))
            print(f"  {width}x{height} {name:12s} ({p.num_disparities} disp, block {p.plain_block_size} at 1/{p.downscale}): "
                  f"{np.median(times):.0f} ms/frame")

    width, height = 1280, 1024
    pairs = [(cv2.resize(left, (width, height)), cv2.resize(right, (width, height)))] * args.frames
    print(f"{args.frames} frames of {width}x{height} on {cv2.getNumberOfCPUs()} CPUs:")
    for mode in ("1 thread, OpenCV 1 thread", "1 thread, OpenCV 2 threads", "2 threads, OpenCV 1 thread",
                 "2 threads, OpenCV 2 threads", "2 processes, OpenCV 1 thread"):
        print(f"  {mode:30s}: {throughput(pairs, mode):.0f} ms/frame")


if __name__ == "__main__":
    main()
