"""What the patch, the checks and the timings do on real da Vinci stereo pairs, frame by frame.

Data: the public repository LauraCruciani/DaVinci_project (no licence stated: use it on your own machine, commit
neither its frames nor pictures of them). Bring it and unpack it where ``--data`` points:

    # e.g. with the project's fetch tool, or `git clone https://github.com/LauraCruciani/DaVinci_project`
    .venv/bin/python benchmarks/bench_real_pairs.py --data DIR [--compare SRC_BEFORE SRC_AFTER]

``DIR`` holds ``Offline/frame_decenti/frame/{left,right}/*.jpg`` (30 pairs, 1280x960 crops ``[20:980, 310:1590]``
of 1920x1080 frames, not rectified) and ``CalibrationParameters.xml`` (M_l, M_r, D_l, D_r, R, T in mm, for the
1080p frames). The script makes a session of its own under ``--workdir`` (the data is never written):

- the images copied; ``stereo.xml``: the published calibration with the principal points moved by the crop (cx -
  310, cy - 20), T in mm, R as published (``--nearest-rotation``: replaced by its nearest rotation first, for a
  tree that refuses it), not rectified (contact-viz rectifies on load);
- ``masks/``: the tool mask by a colour rule (CIELab chroma below ``MASK_CHROMA`` on the unrectified left image,
  opened, closed, the ``MASK_MAX_TOOLS`` largest components of at least ``MASK_MIN_AREA`` px, each an instrument
  of its own, object id 1 the leftmost): the instruments are grey metal and black plastic on red tissue. A rule, not a segmentation network: it
  also takes the few grey reflections, and two touching instruments are one.

It runs ``contact-viz extract`` (depth from the package's SGBM, since the session has none) and ``contact-viz
check --json`` with each source tree (``--compare``: PYTHONPATH=SRC; default: the installed package), and prints,
per frame: the tool's depth (median over the patch's N1 window: the features' ``tool_depth_m``), the distance,
whether it is within ``ZERO_MM`` of zero, whether the patch's centre lies in the half-occluded strip
(contact_viz.pipeline.extract.hidden_pixels on the installed package's SGBM depth), and the checks that fired; then per tree: the patches within
``ZERO_MM`` of zero, at the signal's cap (|d| <= 1e-4 m), the frames flagged per check, and the wall time of
each command.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

CROP_X0, CROP_Y0 = 310, 20  # where the 1280x960 crops start in the 1920x1080 frames, px
MASK_CHROMA = 10.0  # a pixel is tool when its CIELab chroma (8-bit a, b around 128) is below this, -
MASK_MIN_AREA = 20000  # smallest connected tool component kept, px (1.6% of the image; reflections are smaller)
MASK_MAX_TOOLS = 2  # the largest components kept, each an instrument, px
MASK_KERNEL = 9  # side of the opening and closing kernel, px
ZERO_MM = 0.33  # a distance within this of zero "reads zero", mm
CAP_M = 1e-4  # the signal's floor eps: |d| at or below it reads at the cap, m
DATA_SUBDIR = Path("Offline/frame_decenti/frame")


def read_opencv_matrix(path: Path, name: str) -> np.ndarray:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        node = fs.getNode(name)
        if node.empty():
            raise SystemExit(f"error: {path}: no {name!r}")
        return node.mat().astype(np.float64)
    finally:
        fs.release()


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(R)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def write_calibration(src: Path, dst: Path, size: tuple[int, int], fix_rotation: bool, right_cy_px: float = 0.0
                      ) -> None:
    """stereo.xml for the crops: the 1080p calibration with the principal points moved by the crop (and the right
    camera's cy by ``right_cy_px`` more: an experiment on the pairs' vertical offset)."""
    K1, K2 = read_opencv_matrix(src, "M_l"), read_opencv_matrix(src, "M_r")
    for K in (K1, K2):
        K[0, 2] -= CROP_X0
        K[1, 2] -= CROP_Y0
    K2[1, 2] += right_cy_px
    R = read_opencv_matrix(src, "R")
    fs = cv2.FileStorage(str(dst), cv2.FILE_STORAGE_WRITE)
    fs.write("K1", K1)
    fs.write("D1", read_opencv_matrix(src, "D_l"))
    fs.write("K2", K2)
    fs.write("D2", read_opencv_matrix(src, "D_r"))
    fs.write("R", nearest_rotation(R) if fix_rotation else R)
    fs.write("T", read_opencv_matrix(src, "T"))
    fs.write("translation_unit", "mm")
    fs.write("image_width", size[0])
    fs.write("image_height", size[1])
    fs.release()


def tool_mask(image_bgr: np.ndarray) -> np.ndarray:
    """The colour rule: low CIELab chroma, opened and closed, the largest components only; uint8 object ids, one
    per component (an instrument each), 1 the leftmost."""
    lab = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2LAB).astype(np.float32)
    chroma = np.hypot(lab[..., 1] - 128.0, lab[..., 2] - 128.0)
    mask = (chroma < MASK_CHROMA).astype(np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (MASK_KERNEL, MASK_KERNEL))
    mask = cv2.morphologyEx(cv2.morphologyEx(mask, cv2.MORPH_OPEN, kernel), cv2.MORPH_CLOSE, kernel)
    n, labels, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    ids = np.zeros(n, np.uint8)
    large = [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] >= MASK_MIN_AREA]
    kept = sorted(large, key=lambda i: -stats[i, cv2.CC_STAT_AREA])[:MASK_MAX_TOOLS]
    for k, i in enumerate(sorted(kept, key=lambda i: centroids[i][0])):  # 1 = the leftmost, as seen
        ids[i] = k + 1
    return ids[labels]


def make_session(data: Path, root: Path, fix_rotation: bool, right_cy_px: float = 0.0, dilate_px: int = 0) -> Path:
    session = root / (("session_fixed_r" if fix_rotation else "session") + (f"_cy{right_cy_px:g}" if right_cy_px else "")
                      + (f"_dilate{dilate_px}" if dilate_px else ""))
    if (session / "complete").exists():
        return session
    shutil.rmtree(session, ignore_errors=True)
    frames = data / DATA_SUBDIR
    for side in ("left", "right"):
        (session / side).mkdir(parents=True)
        for f in sorted((frames / side).iterdir()):
            stem = f.stem.removesuffix("_r")  # one right image is named 023300_r.jpg
            shutil.copyfile(f, session / side / f"{stem}{f.suffix}")
    (session / "masks").mkdir()
    size = None
    for f in sorted((session / "left").iterdir()):
        image = cv2.imread(str(f), cv2.IMREAD_COLOR)
        size = (image.shape[1], image.shape[0])
        ids = tool_mask(image)
        if dilate_px:  # every instrument grown by dilate_px (the larger id wins where two meet)
            ids = cv2.dilate(ids, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilate_px + 1,) * 2))
        cv2.imwrite(str(session / "masks" / f"{f.stem}.png"), ids)
    write_calibration(data / "CalibrationParameters.xml", session / "stereo.xml", size, fix_rotation, right_cy_px)
    (session / "complete").write_text("made by benchmarks/bench_real_pairs.py\n")
    return session


def run_tree(src: Path | None, session: Path, out: Path) -> dict:
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = str(src)
    out.mkdir(parents=True, exist_ok=True)
    cli = [sys.executable, "-c", "import sys; from contact_viz.cli import main; sys.exit(main())"]
    result: dict = {}
    for name, args in (("extract", ["extract", str(session), "-o", str(out / "features.csv"),
                                    "--cache-dir", str(out / "cache")]),
                       ("check", ["check", str(session), "--json", str(out / "checks.json"),
                                  "--cache-dir", str(out / "cache")])):
        start = time.perf_counter()
        proc = subprocess.run(cli + args, env=env, capture_output=True, text=True, timeout=3600)
        result[f"{name}_s"] = time.perf_counter() - start
        result[f"{name}_out"] = proc.stdout + proc.stderr
        if name == "extract" and proc.returncode != 0:
            raise SystemExit(f"error: extract with {src or 'the installed package'} failed:\n{proc.stderr}")
    with open(out / "features.csv", newline="") as f:
        result["rows"] = list(csv.DictReader(f))
    checks = out / "checks.json"
    result["checks"] = json.loads(checks.read_text()) if checks.exists() else None
    return result


def flagged_by_frame(checks: dict | None, stems: list[str]) -> dict[str, list[str]]:
    """{stem: [checks that fired]} from check's JSON (its "ranges": [first, last] pairs, inclusive, of frame
    indices or of stems; a stem range covers the stems between them in sorted order)."""
    fired: dict[str, list[str]] = {s: [] for s in stems}
    position = {s: i for i, s in enumerate(stems)}
    for sess in (checks or {}).get("sessions", []):
        for name, entry in (sess.get("checks") or {}).items():
            for first, last in entry.get("ranges", []):
                lo = first if isinstance(first, int) else position.get(str(first), len(stems))
                hi = last if isinstance(last, int) else position.get(str(last), -1)
                for i in range(lo, hi + 1):
                    fired[stems[i]].append(name)
    return fired


def strip_of_frames(session: Path, cache: Path) -> dict[str, np.ndarray]:
    """{stem: (H, W) bool}: the half-occluded strips beside the instruments (contact_viz.pipeline.extract.
    hidden_pixels on the installed package's SGBM depth, cached in ``cache``), to say where each tree's patch lies."""
    import warnings

    from contact_viz.io.session import open_session
    from contact_viz.params import PatchParams
    from contact_viz.pipeline.extract import hidden_pixels

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = open_session(session, cache_dir=cache)
        out = {}
        for frame in s.iter_frames(layers=("mask", "depth")):
            hidden = hidden_pixels(s, frame, PatchParams(hidden_strip="always")) if hasattr(frame, "depth_m") else None
            if hidden is not None:
                out[frame.stem] = hidden
    return out


def report(label: str, result: dict, strips: dict[str, np.ndarray] | None = None) -> None:
    rows = result["rows"]  # one per frame and instrument
    stems = sorted({r["frame"] for r in rows})
    fired = flagged_by_frame(result["checks"], stems)
    print(f"\n== {label}: extract {result['extract_s']:.1f} s ({1000 * result['extract_s'] / max(len(rows), 1):.0f} "
          f"ms/frame, start-up included), check {result['check_s']:.1f} s")
    print("| frame | instrument | tool depth mm | distance mm | reads zero | patch in the strip | checks fired |")
    print("|---|---|---|---|---|---|---|")
    zero = cap = found = in_strip = 0
    for r in rows:
        d = float(r["distance_m"]) if r["distance_m"] else float("nan")
        tool = float(r["tool_depth_m"]) * 1000 if r.get("tool_depth_m") else float("nan")
        is_zero = np.isfinite(d) and abs(d) * 1000 <= ZERO_MM
        found += np.isfinite(d)
        zero += is_zero
        cap += np.isfinite(d) and abs(d) <= CAP_M
        strip = strips.get(r["frame"]) if strips else None
        hit = strip is not None and r["patch_x"] != "" and bool(strip[int(float(r["patch_y"])), int(float(r["patch_x"]))])
        in_strip += hit
        print(f"| {r['frame']} | {r.get('tool', '')} | {tool:.1f} | {d * 1000:.2f} | {'yes' if is_zero else ''} | "
              f"{'yes' if hit else ''} | "
              f"{', '.join(sorted(set(fired.get(r['frame'], []))))} |")
    per_check: dict[str, int] = {}
    for names in fired.values():
        for n in set(names):
            per_check[n] = per_check.get(n, 0) + 1
    flagged = sum(1 for names in fired.values() if names)
    print(f"{label}: patch found on {found} of {len(rows)} (frame, instrument); within {ZERO_MM} mm of zero {zero}; at the "
          f"signal's cap {cap}; the patch in the half-occluded strip {in_strip}; frames flagged {flagged} of {len(stems)}: "
          + (", ".join(f"{k} {v}" for k, v in sorted(per_check.items(), key=lambda kv: -kv[1])) or "none"))
    tail = [line for line in result["check_out"].splitlines() if "rectif" in line.lower() or "warning" in line.lower()]
    for line in tail[:5]:
        print(f"  check says: {line.strip()}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=Path("/tmp/dv"), help="the unpacked DaVinci_project")
    parser.add_argument("--compare", nargs="+", type=Path, metavar="SRC", help="source trees (PYTHONPATH) to run")
    parser.add_argument("--nearest-rotation", action="store_true",
                        help="write R's nearest rotation into stereo.xml (for a tree that refuses R as published)")
    parser.add_argument("--right-cy-px", type=float, default=0.0,
                        help="move the right camera's principal point down by this, px (to undo a vertical offset)")
    parser.add_argument("--dilate-px", type=int, default=0, help="grow every instrument's mask by this, px")
    parser.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "contact-viz-real-pairs")
    args = parser.parse_args(argv)
    if not (args.data / DATA_SUBDIR / "left").is_dir() or not (args.data / "CalibrationParameters.xml").is_file():
        print(f"error: --data {args.data}: expected {DATA_SUBDIR}/left and CalibrationParameters.xml (see the "
              "docstring)", file=sys.stderr)
        return 2
    session = make_session(args.data, args.workdir, args.nearest_rotation, args.right_cy_px, args.dilate_px)
    trees = args.compare or [None]
    results = []
    for i, src in enumerate(trees):
        out = args.workdir / f"run_{i}"
        shutil.rmtree(out, ignore_errors=True)
        results.append(run_tree(src, session, out))
    strips = strip_of_frames(session, args.workdir / "strip_cache")
    for i, (src, result) in enumerate(zip(trees, results)):
        report(f"tree {i + 1}: {src or 'installed'}", result, strips)
    return 0


if __name__ == "__main__":
    sys.exit(main())
