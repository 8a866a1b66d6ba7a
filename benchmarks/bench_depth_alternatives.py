"""Benchmark: ways of computing SGBM depth where the patch reads it, side by side (how the default was chosen).

On the near-contact frames (truth.csv gap_m <= 5 mm) of bench_depth_region.py's synthetic sessions (made
there first), per variant: median |distance - distance from the rendered depth| (mm) and the median wall
ms of the depth of one frame (2 cores), all variants on each frame in turn (so machine drift hits all alike):

* tiles, range from the coarse pass (the default): geometry.stereo_region.region_sgbm_disparity, the whole
  search range from the calibration (SGBMParams.min_depth_m);
* before: the same with the whole search range 1/8 of the matching width and the half-occluded strip left
  as matched (half_occluded_strip off): the matching before the range came from the calibration;
* tiles, the whole search range: the same with range_margin_px so large that no tile's range is narrowed;
* whole frame at the matching resolution (region=False): no coarse pass, no tiles;
* StereoBM per tile: the default with OpenCV's block matcher (grey, 9 px blocks, uniqueness 15,
  texture threshold 10) in place of SGBM, in the tiles and the coarse pass.

Run: .venv/bin/python benchmarks/bench_depth_alternatives.py [--sizes 640x360,1280x720,1920x1080] [--step 3]
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

import contact_viz.geometry.stereo as stereo
from contact_viz.geometry.patch import compute_patch
from contact_viz.geometry.stereo import SGBMParams, disparity_to_depth
from contact_viz.geometry.stereo_region import region_sgbm_disparity
from contact_viz.io.session import open_session

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_real_range as real_range  # noqa: E402
from bench_depth_region import SEEDS, parse_size, session_dirs  # noqa: E402


class _BlockMatcher:
    """StereoBM behind StereoSGBM's interface (grey images, the same search range)."""

    def __init__(self, p: SGBMParams, min_disparity: int) -> None:
        self.bm = cv2.StereoBM_create(numDisparities=p.num_disparities, blockSize=9)
        self.bm.setMinDisparity(min_disparity)
        self.bm.setUniquenessRatio(p.uniqueness_ratio)
        self.bm.setTextureThreshold(10)
        self.bm.setSpeckleWindowSize(p.speckle_window_size)
        self.bm.setSpeckleRange(p.speckle_range)
        self.bm.setDisp12MaxDiff(p.disp12_max_diff)

    def compute(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        grey = lambda image: cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
        return self.bm.compute(grey(left), grey(right))


@contextlib.contextmanager
def block_matching():
    original = stereo._matcher
    stereo._matcher = lambda p, channels, min_disparity: _BlockMatcher(p, min_disparity)
    try:
        yield
    finally:
        stereo._matcher = original


DEFAULT = "tiles, range from the coarse pass (default)"
BEFORE = "before: range 1/8 of the width, strip kept"
VARIANTS = {  # name: (SGBMParams, matcher context, search range from the calibration)
    DEFAULT: (SGBMParams(), contextlib.nullcontext, True),
    BEFORE: (SGBMParams(half_occluded_strip=False), contextlib.nullcontext, False),
    "tiles, whole search range": (SGBMParams(range_margin_px=100_000), contextlib.nullcontext, True),
    "whole frame at the matching resolution": (SGBMParams(region=False), contextlib.nullcontext, True),
    "StereoBM per tile": (SGBMParams(), block_matching, True),
}


def resolved(params: SGBMParams, width: int, cal, calibrated: bool) -> SGBMParams:
    """``params`` for images ``width`` wide, the search range from the calibration (as a session resolves them)
    or, not ``calibrated``, from the width."""
    if not calibrated:
        return params.resolve(width)
    return params.resolve(width, fx_px=cal.fx, baseline_m=cal.baseline_m, disparity_offset_px=cal.disparity_offset_px)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="640x360,1280x720,1920x1080")
    parser.add_argument("--phantoms", help="default: all four (with --real-range: cup)")
    parser.add_argument("--frames", type=int, help="frames per session (bench_depth_region's 45, bench_real_range's 60)")
    parser.add_argument("--step", type=int, default=3, help="every K-th near-contact frame")
    parser.add_argument("--workdir", type=Path, help="default: /tmp/cv-depth-bench (--real-range: /tmp/cv-real-range-bench)")
    parser.add_argument("--before-after", action="store_true", help="only the default and the matching before")
    parser.add_argument("--real-range", action="store_true", help="bench_real_range.py's sessions (its camera, "
                        "phantoms and seeds, --frames 60, --workdir /tmp/cv-real-range-bench) instead")
    args = parser.parse_args()
    args.phantoms = args.phantoms or ("cup" if args.real_range else ",".join(SEEDS))
    args.frames = args.frames or (60 if args.real_range else 45)
    args.workdir = args.workdir or Path("/tmp/cv-real-range-bench" if args.real_range else "/tmp/cv-depth-bench")
    print("$ " + " ".join([sys.executable, *sys.argv]))
    variants = {k: v for k, v in VARIANTS.items() if not args.before_after or k in (DEFAULT, BEFORE)}
    for size in args.sizes.split(","):
        errors = {k: [] for k in variants}
        times = {k: [] for k in variants}
        for phantom in args.phantoms.split(","):
            if args.real_range:
                full = real_range.session_dir(args.workdir.resolve(), phantom, parse_size(size), args.frames,
                                              real_range.CAMERA)
            else:
                full, _ = session_dirs(args.workdir.resolve(), phantom, parse_size(size), args.frames)
            session = open_session(full)
            cal = session.calibration
            with (full / "truth.csv").open(newline="") as handle:
                near = [i for i, row in enumerate(csv.DictReader(handle)) if float(row["gap_m"]) <= 0.005]
            for i in near[::args.step]:
                frame = session.load_frame(i, ("mask", "depth", "left", "right"))
                reference = compute_patch(frame.depth_m, frame.tool_mask).distance_m
                for name, (params, context, calibrated) in variants.items():
                    params = resolved(params, frame.left_rgb.shape[1], cal, calibrated)
                    with context():
                        start = time.perf_counter()
                        result = region_sgbm_disparity(frame.left_rgb, frame.right_rgb, frame.tool_mask, params)
                        times[name].append(1000 * (time.perf_counter() - start))
                    depth = disparity_to_depth(result.disparity_px, cal.fx, cal.baseline_m, cal.disparity_offset_px)
                    distance = compute_patch(depth, frame.tool_mask).distance_m
                    errors[name].append(1000 * abs(distance - reference))
        print(f"\n{size}, {len(times[DEFAULT])} near-contact frames "
              f"({args.phantoms})")
        print(f"{'variant':46s}{'|d - rendered| mm':>20s}{'no distance':>13s}{'wall ms':>9s}")
        for name in variants:
            e = np.asarray(errors[name])
            print(f"{name:46s}{np.nanmedian(e):20.2f}{int(np.isnan(e).sum()):13d}{np.median(times[name]):9.0f}")


if __name__ == "__main__":
    main()
