"""How SGBM settings do beside the tool, on the study's TRAINING sessions (issue 13): how the defaults were chosen.

    python recipes/sgbm_band_sweep.py    # after recipes/sgbm_study.py made its sessions in .study/

For each variant of :class:`SGBMParams` (mask-aware matching), on the frames of the six training
sessions: the share of the patch's exterior-band pixels (on the true depth) whose SGBM depth is within
3 mm of the exact depth (``contact_viz.synth.true_depth``), the share of band pixels with a depth, the
10th percentile of the depth error 2, 3 and 4 px from the mask edge (mm; the tool's depth dragged over
the tissue shows as -10 to -40 mm there), and the matching time per frame. The test sessions are not
read: the defaults are picked here, and sgbm_study.py reports the test sessions after.
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import sgbm_study as study  # noqa: E402

from contact_viz.geometry.depth_edges import edge_error_profile  # noqa: E402
from contact_viz.geometry.patch import compute_patch  # noqa: E402
from contact_viz.geometry.stereo import SGBMParams, disparity_to_depth, masked_sgbm_disparity  # noqa: E402
from contact_viz.io.decoders import read_rgb  # noqa: E402
from contact_viz.io.session import open_session  # noqa: E402

FIRST = study.FIRST_SGBM
VARIANTS = {
    "3-way, 3 px blocks, uniqueness 10 (issue 13's first)": FIRST,
    "... 5 px blocks": replace(FIRST, block_size=5),
    "... uniqueness 20": replace(FIRST, uniqueness_ratio=20),
    "... no left-right check, disp12MaxDiff off": replace(FIRST, lr_check=False, disp12_max_diff=-1),
    "... mode HH (8 paths; O(W H D) memory)": replace(FIRST, mode="hh"),
    "hidden strip, 3 px blocks, uniqueness 10": replace(FIRST, hidden_strip=True),
    "hidden strip, 5 px blocks, uniqueness 15 (default)": SGBMParams(),
    "hidden strip, 7 px blocks, uniqueness 15": replace(SGBMParams(), block_size=7),
}
NEAR_PX = (2, 3, 4)  # the profile's distances from the mask edge printed, px


def frame_figures(job):
    """Counts and errors of one training session's frames for every variant."""
    directory, name, indices = job
    root = directory / "sessions" / name
    session = open_session(root)
    truth = study.truth_depth(directory, name, indices)
    stems = sorted(p.name for p in (root / "left").iterdir())
    out = {v: {"within": 0, "valid": 0, "band": 0, "near": [[] for _ in NEAR_PX], "seconds": 0.0} for v in VARIANTS}
    for i in indices:
        tool = session.load_frame(i, ("mask",)).tool_mask != 0
        left, right = read_rgb(root / "left" / stems[i]), read_rgb(root / "right" / stems[i])
        true_m = np.where(truth[i] > 0, truth[i], np.nan).astype(np.float32)
        band = compute_patch(true_m, tool).band
        for name_v, params in VARIANTS.items():
            start = time.perf_counter()
            disparity = masked_sgbm_disparity(left, right, tool, params)
            out[name_v]["seconds"] += time.perf_counter() - start
            depth = disparity_to_depth(disparity, session.calibration.fx, session.calibration.baseline_m)
            with np.errstate(invalid="ignore"):
                valid = band & np.isfinite(depth) & np.isfinite(true_m)
                out[name_v]["within"] += int((np.abs(depth - true_m)[valid] < study.WITHIN_M).sum())
            out[name_v]["valid"] += int(valid.sum())
            out[name_v]["band"] += int(band.sum())
            profile = edge_error_profile(depth, true_m, tool, max(NEAR_PX))
            for k, px in enumerate(NEAR_PX):
                out[name_v]["near"][k].append(profile[px - 1])
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dir", type=Path, default=Path(".study"), help="the study's folder (sgbm_study.py)")
    parser.add_argument("--step", type=int, default=15, help="every n-th frame ...")
    parser.add_argument("--start", type=int, default=7, help="... from this one")
    parser.add_argument("--processes", type=int, default=2)
    args = parser.parse_args(argv)
    directory = args.dir.resolve()
    if not all((directory / "sessions" / n / "session.json").is_file() for n, _, _ in study.TRAIN):
        raise SystemExit(f"{directory}/sessions: the training sessions are missing; run recipes/sgbm_study.py first")
    frames = len(open_session(directory / "sessions" / study.TRAIN[0][0]))
    jobs = [(directory, n, list(range(args.start, frames, args.step))) for n, _, _ in study.TRAIN]
    total = {v: {"within": 0, "valid": 0, "band": 0, "near": [[] for _ in NEAR_PX], "seconds": 0.0} for v in VARIANTS}
    with ProcessPoolExecutor(args.processes) as pool:
        for part in pool.map(frame_figures, jobs):
            for v in VARIANTS:
                for key in ("within", "valid", "band", "seconds"):
                    total[v][key] += part[v][key]
                for k in range(len(NEAR_PX)):
                    total[v]["near"][k] += part[v]["near"][k]
    n_frames = sum(len(j[2]) for j in jobs)
    print(f"{n_frames} frames of the six training sessions (every {args.step}th from {args.start}); band = the patch's "
          "exterior band on the true depth")
    print(f"{'variant':55s} {'within 3 mm':>11s} {'valid':>6s}  p10 error at " + "/".join(map(str, NEAR_PX))
          + f" px, mm {'ms/frame':>9s}")
    for v, t in total.items():
        near = "/".join(f"{1000 * np.percentile(np.concatenate(e), 10):.1f}" if sum(map(len, e)) else "-"
                        for e in t["near"])
        print(f"{v:55s} {100 * t['within'] / max(t['valid'], 1):10.1f}% {100 * t['valid'] / max(t['band'], 1):5.1f}%  "
              f"{near:>22s} {1000 * t['seconds'] / n_frames:9.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
