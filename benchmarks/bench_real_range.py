"""Benchmark: stereo-only (SGBM) depth at a real endoscope's range, against the rendered and the exact depth.

A da Vinci endoscope (fx 1103 px at 1920x1080, baseline 4.1 mm) sees instruments 25-50 mm away and tissue at
40-150 mm: disparities up to 200 px, and beside a shaft 20 mm above the tissue a strip of tissue 60-70 px wide
that the right camera cannot see (the half-occluded strip). The synthetic sessions here put the camera there
(--camera: SynthParams fields, by default fov 55.1 deg at 1280 px, as the rectified 1280x960 crop of those
frames, fx 1227 px; baseline 4.1 mm; tissue base 60 mm away) and are made once under --workdir.

Per tree (--compare OLD/src NEW/src: each in a subprocess importing contact_viz from there), on every K-th
frame, with SGBM computed by geometry.stereo_region.region_sgbm_disparity (its search range from the
calibration where the tree's SGBMParams.resolve takes one, else from the width) and turned into depth:

* valid: the share of exterior pixels 1-16 px from the tool with SGBM depth, and of those the right camera
  sees (from the exact depth) the share with depth;
* strip with depth: of the exterior pixels 1-16 px from the tool (the patch's reach) that the tool hides
  from the right camera (the exact depth's z-buffer: a tool pixel of the row lands on the same right column
  with a disparity larger by more than 0.75 px), the share that carries SGBM depth (nobody observed it), and
  the share whose depth is within 3 mm of the tool's (the depth that makes a hover read as contact);
* found / false: geometry.occlusion.half_occluded (where the tree has it) on the rendered depth (as a
  FoundationStereo-like source: noise, 1 px bleeding, holes): the share of the strip pixels above it marks,
  and the share of the band pixels it marks that the tool does not hide;
* tool: the share of tool pixels with depth;
* the patch (geometry.patch.compute_patch, default PatchParams) on SGBM and on the rendered depth: frames
  with a true gap (truth.csv) of 3 mm or more reading below 1 mm (false contact); median |SGBM - rendered|
  distance on frames within 5 mm of contact; every hover frame (true gap >= 3 mm) listed with its gap, the
  rendered and the SGBM distance with --list;
* wall ms per frame of the SGBM depth (2 cores, medians).

Run: .venv/bin/python benchmarks/bench_real_range.py [--sizes 1280x960] [--phantoms cup] [--frames 60] [--step 2]
     .venv/bin/python benchmarks/bench_real_range.py --compare OLD/src NEW/src   # trees side by side
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_depth_region import exact_depth, parse_size, seen_by_both  # noqa: E402

CAMERA = {"fov_deg": 55.1, "baseline_m": 0.0041, "tissue_distance_m": 0.06}  # the rectified da Vinci crop
SEEDS = {"cup": 11, "kidney": 12, "liver": 13, "glove": 14}
BAND_PX = 16  # exterior pixels at most this far from the tool, px
HOVER_M, FALSE_CONTACT_M, NEAR_M = 0.003, 0.001, 0.005  # true gap >= this is a hover; reads < this: contact; near
HIDDEN_TOL_PX = 0.75  # a tool pixel hides a left pixel landing on its right column when nearer by more, px
TOOL_DEPTH_TOL_M = 0.003  # a strip pixel within this of the tool's depth carries the tool's depth, m
COUNTS = ("band", "valid", "seen", "seen_valid", "strip", "strip_depth", "strip_tooldepth", "tool", "tool_valid",
          "hover", "false_contact", "frames", "marked", "marked_hidden")
LISTS = ("wall_ms", "near_diff_mm")


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def session_dir(workdir: Path, phantom: str, size: tuple[int, int], frames: int, camera: dict, draw: int = 0) -> Path:
    """The synthetic session at the real-range camera (seed: the phantom's + 100 x ``draw``), made unless there
    with these settings."""
    from contact_viz.synth import SynthParams, generate_session

    w, h = size
    tag = "-".join(f"{v:g}" for v in camera.values())
    seed = SEEDS[phantom] + 100 * draw
    path = workdir / f"{phantom}-{w}x{h}-{frames}f-{tag}" if draw == 0 else workdir / f"{phantom}{seed}-{w}x{h}-{frames}f-{tag}"
    want = {"phantom": phantom, "seed": seed, "frames": frames, "width": w, "height": h} | camera
    info = path / "session.json"
    have = json.loads(info.read_text()).get("generator", {}) if info.is_file() else {}
    if not (path / "truth.csv").is_file() or any(have.get(k) != v for k, v in want.items()):
        log(f"generating {path} ...")
        generate_session(path, SynthParams(**want), overwrite=True)
    return path


def hidden_by_tool(depth_m: np.ndarray, tool: np.ndarray, fx: float, baseline_m: float) -> np.ndarray:
    """(H, W) bool: non-tool left pixels whose right column a nearer tool pixel of the row covers (the tool's
    right-view footprint: each tool pixel marks floor and ceil of x - d, as geometry.stereo.right_view_tool_mask)."""
    h, w = depth_m.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        disparity = np.where(depth_m > 0, fx * baseline_m / depth_m, np.nan)
    front = np.full(h * w, -np.inf)
    ys, xs = np.nonzero(tool & np.isfinite(disparity))
    d = disparity[ys, xs]
    for col in (np.floor(xs - d), np.ceil(xs - d)):
        inside = (col >= 0) & (col < w)
        np.maximum.at(front, ys[inside] * w + col[inside].astype(np.int64), d[inside])
    ys, xs = np.nonzero(~tool & np.isfinite(disparity))
    d = disparity[ys, xs]
    col = np.rint(xs - d).astype(np.int64)
    inside = (col >= 0) & (col < w)
    out = np.zeros((h, w), bool)
    out[ys[inside], xs[inside]] = front[ys[inside] * w + col[inside]] > d[inside] + HIDDEN_TOL_PX
    return out


def sgbm_depth(frame, cal) -> tuple[np.ndarray, float]:
    """(SGBM depth (H, W) float32 m, wall ms) with the tree's defaults, its range from the calibration if it can."""
    from contact_viz.geometry.stereo import SGBMParams, disparity_to_depth
    from contact_viz.geometry.stereo_region import region_sgbm_disparity

    width = frame.left_rgb.shape[1]
    try:
        params = SGBMParams().resolve(width, fx_px=cal.fx, baseline_m=cal.baseline_m,
                                      disparity_offset_px=cal.disparity_offset_px)
    except TypeError:  # a tree whose range comes from the width alone
        params = SGBMParams().resolve(width)
    start = time.perf_counter()
    disparity = region_sgbm_disparity(frame.left_rgb, frame.right_rgb, frame.tool_mask != 0, params).disparity_px
    ms = 1000 * (time.perf_counter() - start)
    return disparity_to_depth(disparity, cal.fx, cal.baseline_m, cal.disparity_offset_px), ms


def strip_found(depth_m: np.ndarray, tool: np.ndarray, cal) -> np.ndarray | None:
    """geometry.occlusion.half_occluded on a depth (the rendered one), None in a tree without it."""
    try:
        from contact_viz.geometry.occlusion import half_occluded
    except ImportError:
        return None
    with np.errstate(divide="ignore", invalid="ignore"):
        disparity = np.where(depth_m > 0, cal.fx * cal.baseline_m / depth_m - cal.disparity_offset_px, np.nan)
    return half_occluded(disparity, tool)


def measure_session(path: Path, step: int) -> dict:
    import cv2

    from contact_viz.geometry.patch import compute_patch
    from contact_viz.io.session import open_session

    with (path / "truth.csv").open(newline="") as handle:
        gap_m = [float(row["gap_m"]) for row in csv.DictReader(handle)]
    indices = list(range(0, len(gap_m), step))
    exact = exact_depth(path, indices)
    session = open_session(path)
    cal = session.calibration
    out = {k: 0 for k in COUNTS} | {k: [] for k in LISTS} | {"hover_frames": []}
    for i in indices:
        frame = session.load_frame(i, ("left", "right", "mask", "depth"))
        tool = frame.tool_mask != 0
        depth, ms = sgbm_depth(frame, cal)
        outside = cv2.distanceTransform((~tool).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        band = (outside > 0) & (outside <= BAND_PX)
        has = np.isfinite(depth) & (depth > 0)
        seen = seen_by_both(exact[i], cal.fx, cal.baseline_m)
        strip = band & hidden_by_tool(exact[i], tool, cal.fx, cal.baseline_m)
        tool_depth = float(np.nanmedian(np.where(tool, exact[i], np.nan))) if tool.any() else np.nan
        out["frames"] += 1
        out["wall_ms"].append(ms)
        out["band"] += int(band.sum())
        out["valid"] += int((band & has).sum())
        out["seen"] += int((band & seen).sum())
        out["seen_valid"] += int((band & seen & has).sum())
        out["strip"] += int(strip.sum())
        out["strip_depth"] += int((strip & has).sum())
        with np.errstate(invalid="ignore"):
            out["strip_tooldepth"] += int((strip & has & (np.abs(depth - tool_depth) <= TOOL_DEPTH_TOL_M)).sum())
        marked = strip_found(frame.depth_m, tool, cal)
        if marked is not None:
            out["marked"] += int((marked & band).sum())
            out["marked_hidden"] += int((marked & strip).sum())
        out["tool"] += int(tool.sum())
        out["tool_valid"] += int((tool & has).sum())
        sgbm_mm = 1000 * compute_patch(depth, tool).distance_m
        rendered_mm = 1000 * compute_patch(frame.depth_m, tool).distance_m
        if gap_m[i] <= NEAR_M and np.isfinite(sgbm_mm) and np.isfinite(rendered_mm):
            out["near_diff_mm"].append(abs(sgbm_mm - rendered_mm))
        if gap_m[i] >= HOVER_M:
            out["hover"] += 1
            out["false_contact"] += int(np.isfinite(sgbm_mm) and sgbm_mm < 1000 * FALSE_CONTACT_M)
            out["hover_frames"].append((i, 1000 * gap_m[i], rendered_mm, sgbm_mm))
    return out


def measure(args) -> dict:
    import contact_viz

    results = {"contact_viz": str(Path(contact_viz.__file__).parent)}
    for size in args.sizes:
        for phantom in args.phantoms:
            parts = []
            for draw in range(args.draws):
                path = session_dir(args.workdir, phantom, parse_size(size), args.frames, args.camera, draw)
                start = time.perf_counter()
                parts.append(measure_session(path, args.step))
                log(f"  {size} {path.name}: {time.perf_counter() - start:.0f} s")
            results.setdefault(size, {})[phantom] = pooled(parts) | {
                "hover_frames": [(draw, *h) for draw, part in enumerate(parts) for h in part["hover_frames"]]}
    return results


def share(part: int, whole: int) -> float:
    return 100 * part / whole if whole else float("nan")


COLUMNS = [  # header, figure of the pooled figures, format
    ("valid %", lambda f: share(f["valid"], f["band"]), ".1f"),
    ("of seen %", lambda f: share(f["seen_valid"], f["seen"]), ".1f"),
    ("strip px", lambda f: f["strip"], "d"),
    ("w/ depth %", lambda f: share(f["strip_depth"], f["strip"]), ".1f"),
    ("tool's %", lambda f: share(f["strip_tooldepth"], f["strip"]), ".1f"),
    ("found %", lambda f: share(f["marked_hidden"], f["strip"]) if f["marked"] else float("nan"), ".1f"),
    ("false %", lambda f: share(f["marked"] - f["marked_hidden"], f["marked"]), ".2f"),
    ("tool %", lambda f: share(f["tool_valid"], f["tool"]), ".1f"),
    ("hover<1mm", lambda f: f"{f['false_contact']}/{f['hover']}", "s"),
    ("near |d| mm", lambda f: float(np.median(f["near_diff_mm"])) if f["near_diff_mm"] else float("nan"), ".2f"),
    ("ms/frame", lambda f: float(np.median(f["wall_ms"])) if f["wall_ms"] else float("nan"), ".0f"),
]


def pooled(parts: list[dict]) -> dict:
    return {k: sum(p[k] for p in parts) for k in COUNTS} | {k: [v for p in parts for v in p[k]] for k in LISTS}


def print_tables(results: dict, args) -> None:
    for label, tree in results.items():
        print(f"{label}: contact_viz from {tree['contact_viz']}")
    print(f"\nvalid: exterior 1-{BAND_PX} px with SGBM depth (of seen: of those both cameras see); strip: those the "
          f"tool hides from the right camera, w/ depth: carrying SGBM depth, tool's: within "
          f"{1000 * TOOL_DEPTH_TOL_M:.0f} mm of the tool's depth; found: share of the strip that "
          f"geometry.occlusion.half_occluded finds on the rendered depth, false: share of what it marks there that "
          f"the tool does not hide; tool: tool pixels with depth; hover<1mm: frames "
          f"with a true gap >= {1000 * HOVER_M:.0f} mm whose SGBM distance reads < {1000 * FALSE_CONTACT_M:.0f} mm; "
          f"near |d|: median |SGBM - rendered| distance, true gap <= {1000 * NEAR_M:.0f} mm")
    width = 11 * len(COLUMNS)
    print(f"{'':18s}" + "".join(f" | {label:^{width}s}" for label in results))
    print(f"{'size':10s}{'phantom':8s}" + (" | " + "".join(f"{h:>11s}" for h, _, _ in COLUMNS)) * len(results))
    for size in args.sizes:
        for phantom in args.phantoms + (["all"] if len(args.phantoms) > 1 else []):
            cells = []
            for tree in results.values():
                f = pooled([tree[size][p] for p in args.phantoms] if phantom == "all" else [tree[size][phantom]])
                cells.append("".join(f"{fn(f):>11{spec}}" for _, fn, spec in COLUMNS))
            print(f"{size:10s}{phantom:8s}" + "".join(f" | {c}" for c in cells))
    if args.list:
        print("\nhover frames (true gap >= 3 mm): frame, true gap, rendered distance, SGBM distance per tree (mm)")
        for size in args.sizes:
            for phantom in args.phantoms:
                rows = [tree[size][phantom]["hover_frames"] for tree in results.values()]
                for entries in zip(*rows):
                    draw, i, gap, rendered, _ = entries[0]
                    seed = SEEDS[phantom] + 100 * draw
                    print(f"{size:10s}{phantom:8s} seed {seed:4d} frame {i:3d}: gap {gap:5.1f}, rendered "
                          f"{rendered:6.1f}, SGBM " + ", ".join(f"{e[4]:6.1f}" for e in entries))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1280x960", help="image sizes WxH, comma-separated")
    parser.add_argument("--phantoms", default="cup", help=f"phantoms, comma-separated, of {', '.join(SEEDS)}")
    parser.add_argument("--frames", type=int, default=60, help="frames per session")
    parser.add_argument("--step", type=int, default=2, help="every K-th frame")
    parser.add_argument("--draws", type=int, default=1, help="sessions per phantom (seeds + 0, 100, ...)")
    parser.add_argument("--camera", default=json.dumps(CAMERA), metavar="JSON", help="SynthParams camera fields")
    parser.add_argument("--list", action="store_true", help="list every hover frame's distances")
    parser.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "cv-real-range-bench")
    parser.add_argument("--compare", nargs="+", type=Path, metavar="SRC", help="measure each SRC tree (another "
                        "checkout's src/) in a subprocess")
    parser.add_argument("--worker", type=Path, help=argparse.SUPPRESS)  # --compare's subprocess: figures to this JSON
    args = parser.parse_args()
    args.sizes = [s.strip() for s in args.sizes.split(",") if s.strip()]
    args.phantoms = [p.strip() for p in args.phantoms.split(",") if p.strip()]
    if set(args.phantoms) - set(SEEDS):
        parser.error(f"unknown phantoms {sorted(set(args.phantoms) - set(SEEDS))}; choose from {list(SEEDS)}")
    args.camera = json.loads(args.camera)
    args.workdir = args.workdir.resolve()
    args.workdir.mkdir(parents=True, exist_ok=True)

    import warnings

    warnings.simplefilter("ignore")
    if args.worker:
        args.worker.write_text(json.dumps(measure(args)))
        return
    print("$ " + shlex.join([sys.executable, *sys.argv]), flush=True)
    if not args.compare:
        print_tables({"installed": measure(args)}, args)
        return
    for size in args.sizes:  # made once, before any tree is timed
        for phantom in args.phantoms:
            for draw in range(args.draws):
                session_dir(args.workdir, phantom, parse_size(size), args.frames, args.camera, draw)
    results = {}
    for k, src in enumerate(args.compare):
        with tempfile.NamedTemporaryFile(suffix=".json") as out:
            cmd = [sys.executable, __file__, "--sizes", ",".join(args.sizes), "--phantoms", ",".join(args.phantoms),
                   "--frames", str(args.frames), "--step", str(args.step), "--draws", str(args.draws),
                   "--camera", json.dumps(args.camera),
                   "--workdir", str(args.workdir), "--worker", out.name]
            log(f"{src}:")
            if subprocess.run(cmd, env=dict(os.environ, PYTHONPATH=str(src.resolve()))).returncode:
                raise SystemExit(f"{src}: the measurement failed (see above)")
            results[f"tree {k + 1}"] = json.loads(Path(out.name).read_text())
    print_tables(results, args)


if __name__ == "__main__":
    main()
