"""Benchmark: stereo-only (SGBM) depth at the paper's resolution, against the rendered depth.

For each image size (--sizes) and phantom (--phantoms), and over all phantoms per size, on `contact-viz
synth` sessions opened through their stereo-only copy (no depth/, so `open_session(depth_method="sgbm")`
computes the depth from the pair):

* accuracy, on the frames within 5 mm of contact (truth.csv gap_m <= 5 mm): |distance from SGBM depth -
  distance from the rendered depth| (compute_patch, default PatchParams), median and 90th percentile in
  mm, over the frames with both distances; "NaN": frames with a distance from the rendered depth but
  none from SGBM; "bad": frames measured (either kind) whose SGBM depth was a BadFrame, taken as all NaN;
* valid depth near the tool, pixels pooled over every K-th frame: the share of exterior pixels 1..16 px
  from the tool mask with SGBM depth; the ceiling, the share of them both cameras see (from the rendered
  depth: disparity fx*B/z, a pixel is hidden when a pixel of its row lands on the same right column with
  a disparity larger by more than 0.75 px; the rendered depth's holes, mostly the right view's
  occlusions, count as hidden); valid / ceiling; the share of tool pixels with SGBM depth;
* speed, every K-th frame, in a fresh cache (nothing cached): wall and CPU ms (process time, OpenCV's
  threads included) of one frame's SGBM depth, medians; distance frames/s end to end (depth, mask,
  patch), 1 / median.

The sessions (--frames, a fixed seed per phantom) are made once under --workdir with the installed
`contact-viz synth` and reused; each one's stereo-only copy beside it links all but depth/.

Run: .venv/bin/python benchmarks/bench_depth_region.py [--frames 45] [--step 1] [--sizes 640x360,1280x720,1920x1080]
     .venv/bin/python benchmarks/bench_depth_region.py --sizes 640x360 --frames 20 --phantoms kidney   # quick
     .venv/bin/python benchmarks/bench_depth_region.py --sgbm-params '{"block_size": 7}'   # an SGBM variant
     .venv/bin/python benchmarks/bench_depth_region.py --compare OLD/src NEW/src   # trees side by side
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SEEDS = {"cup": 6062, "kidney": 6061, "liver": 6063, "glove": 6064}
NEAR_M = 0.005  # "within 5 mm of contact": truth.csv gap_m at most this, m
BAND_PX = 16  # exterior pixels at most this far from the tool mask, px
SEEN_TOL_PX = 0.75  # a pixel landing on an occupied right column is hidden if its disparity is smaller by more, px
COUNTS = ("near", "missed", "bad", "band", "valid", "seen", "tool", "tool_valid")
LISTS = ("diff_mm", "wall_ms", "cpu_ms", "e2e_ms", "coarse_ms", "exact_mm", "rendered_exact_mm", "tool_bias_mm",
         "exact_tool_mm")


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def session_dirs(workdir: Path, phantom: str, size: tuple[int, int], frames: int) -> tuple[Path, Path]:
    """The synthetic session (made with `contact-viz synth` unless there with these settings) and its
    stereo-only copy (symbolic links to everything but depth/)."""
    w, h = size
    full = workdir / f"{phantom}-{w}x{h}-{frames}f"
    want = {"phantom": phantom, "seed": SEEDS[phantom], "frames": frames, "width": w, "height": h}
    info = full / "session.json"
    have = json.loads(info.read_text()).get("generator", {}) if info.is_file() else {}
    if not (full / "truth.csv").is_file() or any(have.get(k) != v for k, v in want.items()):
        log(f"generating {full} ...")
        subprocess.run([sys.executable, "-m", "contact_viz.cli", "synth", str(full), "--phantom", phantom,
                        "--seed", str(SEEDS[phantom]), "--frames", str(frames), "--size", f"{w}x{h}", "--overwrite"],
                       check=True, stdout=subprocess.DEVNULL)
    stereo = workdir / f"{full.name}-stereo"
    stereo.mkdir(exist_ok=True)
    for entry in full.iterdir():
        if entry.name != "depth" and not (stereo / entry.name).is_symlink():
            os.symlink(entry.resolve(), stereo / entry.name)
    return full, stereo


def seen_by_both(depth_m: np.ndarray, fx: float, baseline_m: float) -> np.ndarray:
    """(H, W) bool: left pixels that the right camera sees too. Pixel (y, x) of disparity d lands on right
    column x - d (rounded); it is seen if that column is in the image and no pixel of row y landing there
    has a disparity larger by more than SEEN_TOL_PX (one z-buffer per row, all rows in one np.maximum.at).
    Pixels without depth are not seen."""
    h, w = depth_m.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        disparity = np.where(depth_m > 0, fx * baseline_m / depth_m, np.nan)
    ys, xs = np.nonzero(np.isfinite(disparity))
    d = disparity[ys, xs]
    col = np.rint(xs - d).astype(np.int64)
    inside = col >= 0
    ys, xs, d, cell = ys[inside], xs[inside], d[inside], ys[inside] * w + col[inside]
    front = np.full(h * w, -np.inf)
    np.maximum.at(front, cell, d)
    seen = np.zeros((h, w), bool)
    seen[ys, xs] = d >= front[cell] - SEEN_TOL_PX
    return seen


def exact_depth(full: Path, indices: list[int]) -> dict[int, np.ndarray]:
    """The generator's exact depth (no noise, bleeding or holes; NaN = no surface) of frames ``indices``,
    re-rendered once (contact_viz.synth.true_depth) and kept beside the session."""
    from contact_viz.synth import SynthParams, true_depth

    path = full.parent / f"{full.name}-exact.npz"
    if path.is_file():
        data = np.load(path)
        if all(f"f{i}" in data.files for i in indices):
            return {i: data[f"f{i}"] for i in indices}
    g = json.loads((full / "session.json").read_text())["generator"]
    depth = true_depth(SynthParams(**{k: tuple(v) if isinstance(v, list) else v for k, v in g.items()}), indices)
    depth = {i: np.where(d > 0, d, np.nan).astype(np.float32) for i, d in depth.items()}
    np.savez_compressed(path, **{f"f{i}": d for i, d in depth.items()})
    return depth


def coarse_ms(sgbm, index: int) -> float:
    """Wall ms of the coarse full-frame pass alone (geometry.stereo_region; NaN in a tree without it)."""
    try:
        from contact_viz.geometry.stereo_region import _shrink, coarse_disparity
    except ImportError:
        return float("nan")
    from contact_viz.geometry.stereo import SGBMParams

    frame = sgbm.load_frame(index, layers=("left", "right"))
    p = SGBMParams(**sgbm.depth_config["sgbm"])  # resolved for the session's width
    start = time.perf_counter()
    left, right = _shrink(frame.left_rgb, p.downscale), _shrink(frame.right_rgb, p.downscale)
    coarse_disparity(left, right, p)
    return 1000 * (time.perf_counter() - start)


def measure_session(full: Path, stereo: Path, step: int, sgbm_params) -> dict:
    """The raw figures of one session (counts and per-frame lists; the tables pool them)."""
    import cv2

    from contact_viz.geometry.patch import compute_patch
    from contact_viz.io.session import BadFrame, open_session
    from contact_viz.params import PatchParams

    with (full / "truth.csv").open(newline="") as handle:
        gap_m = [float(row["gap_m"]) for row in csv.DictReader(handle)]
    near = [i for i, g in enumerate(gap_m) if g <= NEAR_M][::step]
    timed = list(range(0, len(gap_m), step))
    out = {k: 0 for k in COUNTS} | {k: [] for k in LISTS}
    out["near"] = len(near)
    exact = exact_depth(full, near)
    with tempfile.TemporaryDirectory() as cache:
        sgbm = open_session(stereo, cache_dir=cache, depth_method="sgbm", sgbm_params=sgbm_params)
        rendered = open_session(full, cache_dir=cache)
        fx, baseline_m = sgbm.calibration.fx, sgbm.calibration.baseline_m
        for i in sorted(set(near) | set(timed)):
            wall0, cpu0 = time.perf_counter(), time.process_time()
            depth = sgbm.load_depth(i)
            wall1, cpu1 = time.perf_counter(), time.process_time()
            tool = sgbm.load_frame(i, layers=("mask",)).tool_mask != 0
            if isinstance(depth, BadFrame):
                out["bad"] += 1
                depth = np.full(tool.shape, np.nan, np.float32)
            distance = compute_patch(depth, tool, PatchParams()).distance_m
            wall2 = time.perf_counter()
            truth = rendered.load_depth(i)
            if i in near:
                true_distance = compute_patch(truth, tool, PatchParams()).distance_m
                if np.isfinite(true_distance) and np.isfinite(distance):
                    out["diff_mm"].append(1000 * abs(distance - true_distance))
                out["missed"] += int(np.isfinite(true_distance) and not np.isfinite(distance))
                # against the exact depth: SGBM's and the rendered depth's own errors, SGBM's error on the
                # tool's interior, and SGBM's distance with the exact depth on the tool (its tissue's share)
                patch = compute_patch(exact[i], tool, PatchParams())
                interior = patch.interior & np.isfinite(depth) & np.isfinite(exact[i])
                exact_tool = np.where(tool, exact[i], depth).astype(np.float32)
                for key, value in (("exact_mm", distance), ("rendered_exact_mm", true_distance),
                                   ("exact_tool_mm", compute_patch(exact_tool, tool, PatchParams()).distance_m)):
                    if np.isfinite(value) and np.isfinite(patch.distance_m):
                        out[key].append(1000 * abs(value - patch.distance_m))
                if interior.any():
                    out["tool_bias_mm"].append(1000 * float(np.median((depth - exact[i])[interior])))
            if i in timed:
                out["coarse_ms"].append(coarse_ms(sgbm, i))
                out["wall_ms"].append(1000 * (wall1 - wall0))
                out["cpu_ms"].append(1000 * (cpu1 - cpu0))
                out["e2e_ms"].append(1000 * (wall2 - wall0))
                outside = cv2.distanceTransform((~tool).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
                band = (outside > 0) & (outside <= BAND_PX)
                has_depth = np.isfinite(depth) & (depth > 0)
                out["band"] += int(band.sum())
                out["valid"] += int((band & has_depth).sum())
                out["seen"] += int((band & seen_by_both(truth, fx, baseline_m)).sum())
                out["tool"] += int(tool.sum())
                out["tool_valid"] += int((tool & has_depth).sum())
    return out


def measure(args, sizes: list[str]) -> dict:
    """{size: {phantom: figures}} measured with the contact_viz imported here; "contact_viz": its directory."""
    import contact_viz
    from contact_viz.geometry.stereo import SGBMParams

    sgbm_params = SGBMParams(**json.loads(args.sgbm_params))
    results: dict = {"contact_viz": str(Path(contact_viz.__file__).parent)}
    for size in sizes:
        for phantom in args.phantoms:
            full, stereo = session_dirs(args.workdir, phantom, parse_size(size), args.frames)
            start = time.perf_counter()
            results.setdefault(size, {})[phantom] = measure_session(full, stereo, args.step, sgbm_params)
            log(f"  {size} {phantom}: {time.perf_counter() - start:.0f} s")
    return results


def measure_tree(args, src: Path, size: str) -> dict:
    """``measure`` for one size in a subprocess importing contact_viz from source tree ``src``."""
    with tempfile.NamedTemporaryFile(suffix=".json") as out:
        cmd = [sys.executable, __file__, "--sizes", size, "--phantoms", ",".join(args.phantoms), "--frames",
               str(args.frames), "--step", str(args.step), "--workdir", str(args.workdir), "--sgbm-params",
               args.sgbm_params, "--worker", out.name]
        log(f"{size}, {src}:")
        if subprocess.run(cmd, env=dict(os.environ, PYTHONPATH=str(src))).returncode:
            raise SystemExit(f"{src}: the measurement failed (see above)")
        return json.loads(Path(out.name).read_text())


def pooled(parts: list[dict]) -> dict:
    return {k: sum(p[k] for p in parts) for k in COUNTS} | {k: [v for p in parts for v in p[k]] for k in LISTS}


def median(values: list[float]) -> float:
    return float(np.median(values)) if values else float("nan")


def share(part: int, whole: int) -> float:
    return 100 * part / whole if whole else float("nan")


TABLES = {  # title -> columns (header, figure of the pooled figures, format)
    f"Accuracy, frames within {1000 * NEAR_M:.0f} mm of contact: |SGBM - rendered| distance": [
        ("frames", lambda f: f["near"], "d"), ("median mm", lambda f: median(f["diff_mm"]), ".2f"),
        ("p90 mm", lambda f: float(np.percentile(f["diff_mm"], 90)) if f["diff_mm"] else float("nan"), ".2f"),
        ("NaN", lambda f: f["missed"], "d"), ("bad", lambda f: f["bad"], "d")],
    "Against the exact depth (same frames), median mm: |SGBM - exact|, |rendered - exact|, SGBM's tool interior "
    "- exact (+ = too far), |SGBM with the exact tool depth - exact|": [
        ("SGBM", lambda f: median(f["exact_mm"]), ".2f"), ("rendered", lambda f: median(f["rendered_exact_mm"]), ".2f"),
        ("tool bias", lambda f: median(f["tool_bias_mm"]), ".2f"),
        ("exact tool", lambda f: median(f["exact_tool_mm"]), ".2f")],
    f"Valid depth near the tool (exterior 1-{BAND_PX} px; ceiling: seen by both cameras), % of pixels": [
        ("valid", lambda f: share(f["valid"], f["band"]), ".1f"),
        ("ceiling", lambda f: share(f["seen"], f["band"]), ".1f"),
        ("valid/ceil", lambda f: share(f["valid"], f["seen"]), ".1f"),
        ("tool", lambda f: share(f["tool_valid"], f["tool"]), ".1f")],
    "Speed per frame (medians): SGBM depth wall and CPU ms, its coarse pass alone, distance end to end frames/s": [
        ("wall ms", lambda f: median(f["wall_ms"]), ".0f"), ("CPU ms", lambda f: median(f["cpu_ms"]), ".0f"),
        ("coarse ms", lambda f: median(f["coarse_ms"]), ".0f"),
        ("dist fps", lambda f: 1000 / median(f["e2e_ms"]) if f["e2e_ms"] else float("nan"), ".2f")],
}


def print_tables(results: dict[str, dict], sizes: list[str], phantoms: list[str]) -> None:
    """One table per group of TABLES: a row per size and phantom (and all phantoms), a column group per tree."""
    for label, tree in results.items():
        print(f"{label}: contact_viz from {tree['contact_viz']}", flush=True)
    for title, columns in TABLES.items():
        width = 11 * len(columns)
        print(f"\n{title}\n{'':18s}" + "".join(f" | {label:^{width}s}" for label in results))
        print(f"{'size':10s}{'phantom':8s}" + (" | " + "".join(f"{h:>11s}" for h, _, _ in columns)) * len(results))
        for size in sizes:
            for phantom in phantoms + ["all"]:
                cells = []
                for tree in results.values():
                    f = pooled([tree[size][p] for p in phantoms] if phantom == "all" else [tree[size][phantom]])
                    cells.append("".join(f"{fn(f):11{spec}}" for _, fn, spec in columns))
                print(f"{size:10s}{phantom:8s}" + "".join(f" | {c}" for c in cells))


def parse_size(text: str) -> tuple[int, int]:
    w, h = (int(v) for v in text.lower().split("x"))
    return w, h


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="640x360,1280x720,1920x1080", help="image sizes WxH, comma-separated")
    parser.add_argument("--phantoms", default=",".join(SEEDS), help="phantoms, comma-separated")
    parser.add_argument("--frames", type=int, default=45, help="frames per session")
    parser.add_argument("--step", type=int, default=1, help="every K-th near-contact frame, every K-th frame")
    parser.add_argument("--sgbm-params", default="{}", metavar="JSON", help="SGBMParams overrides, e.g. "
                        "'{\"block_size\": 7}'")
    parser.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "cv-depth-bench")
    parser.add_argument("--compare", nargs="+", type=Path, metavar="SRC",
                        help="measure each SRC tree (another checkout's src/) in a subprocess, interleaved per size")
    parser.add_argument("--worker", type=Path, help=argparse.SUPPRESS)  # --compare's subprocess: figures to this JSON
    args = parser.parse_args()
    args.phantoms = [p.strip() for p in args.phantoms.split(",") if p.strip()]
    unknown = set(args.phantoms) - set(SEEDS)
    if unknown:
        parser.error(f"unknown phantoms {sorted(unknown)}; choose from {list(SEEDS)}")
    sizes = [s.strip() for s in args.sizes.split(",") if s.strip()]
    args.workdir = args.workdir.resolve()
    args.workdir.mkdir(parents=True, exist_ok=True)

    import warnings

    warnings.simplefilter("ignore")
    if args.worker:
        args.worker.write_text(json.dumps(measure(args, sizes)))
        return
    print("$ " + shlex.join([sys.executable, *sys.argv]), flush=True)
    if not args.compare:
        print_tables({"installed": measure(args, sizes)}, sizes, args.phantoms)
        return
    for size in sizes:  # made once, before any tree is timed
        for phantom in args.phantoms:
            session_dirs(args.workdir, phantom, parse_size(size), args.frames)
    labels = [f"tree {k + 1}" for k in range(len(args.compare))]
    results: dict[str, dict] = {label: {} for label in labels}
    for size in sizes:  # interleaved: every tree on one size before the next size
        for label, src in zip(labels, args.compare):
            results[label] |= measure_tree(args, src.resolve(), size)
    print_tables(results, sizes, args.phantoms)


if __name__ == "__main__":
    main()
