"""The study of issue 13: contact detection with classical stereo (SGBM) depth instead of the rendered one.

    python recipes/sgbm_study.py                        # 640x360, 120 frames (synth's default), into .study/
    python recipes/sgbm_study.py --first-frames 75      # the same sessions, their first 75 frames (faster)
    python recipes/sgbm_study.py --band-sweep           # SGBM settings beside the tool, training sessions only
    python recipes/sgbm_study.py --dir .study-1400 --seed-offset 100 --only-default --bleed-px ""  # another draw
    python recipes/sgbm_study.py --ceiling-draws 100    # the exact gap's F1 on 100 draws (no rendering; minutes)
    python recipes/sgbm_study.py --camera davinci --dir .study-davinci --only-default  # a real endoscope's range

Ten ``contact-viz synth`` sessions (six ``cup`` for training, seeds 1300-1305; one test session
each on ``cup``, ``kidney``, ``liver`` and ``glove``, seeds 1310-1313) are generated once into
``DIR/sessions`` and reused. For each depth source the LOSO HMM ensemble is fitted on the six and
evaluated on the four (what `contact-viz fit` and `evaluate` do), and Table 1 is printed:

* rendered: the session's depth/ (synth's stereo-like depth: disparity noise, the tool's depth
  bled 1 px past its edge at 640 px, holes; the stand-in for FoundationStereo);
* SGBM: depth/ removed (``DIR/stereo/<name>``, hard links of the other files), depth from the
  stereo pair by OpenCV SGBM as before issue 13 (no mask; 3 px blocks at 640 px, uniqueness 10);
* SGBM, mask-aware, 3-way: the same pair matched knowing the tool mask, as issue 13 first did it
  (no hidden strip; 3 px blocks, uniqueness 10);
* SGBM, mask-aware, no median: contact_viz.geometry.stereo.masked_sgbm_disparity with the hidden
  strip, 5 px blocks at 640 px, uniqueness 15 (the default until the median);
* SGBM, mask-aware: the default (the same, then the 5x5 median of the disparity, tool and tissue apart).

Then the exact gap: the signal of the generator's true tool-tissue gap (truth.csv) with the same
labels, what a depth map without error would give; no depth source can be expected above it. The
force labels (>= 2 N) call light touches and the start of each press no contact while the gap is 0,
so on some draws even this ceiling is under the issue's F1 target (``--ceiling-draws`` says how often).

Then the same models scored against the generator's physical contact (truth.csv), and how many
frames are in contact but labelled no contact (touches under 2 N).

Then the band error profile on the test sessions (every ``--profile-step``-th frame): the depth
error of background pixels by their distance from the mask edge (1..15 px; median and 10th
percentile, mm), against the exact depth re-rendered by contact_viz.synth.true_depth, and the
share of the exterior band's valid pixels within 3 mm of the true tissue depth.

Then edge bleeding on a depth file (``--bleed-px``): the rendered depth with the tool's depth
dilated k px further into the tissue, with the patch as before (``reject_bleeding=False``) and
with the bleeding test (the default), Table 1 macro rows.

Everything computed is cached under ``DIR`` (features and disparities in ``DIR/cache``, true depth
in ``DIR/truth``); the printed figures go to ``DIR/results.json`` too.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from contact_viz.geometry.depth_edges import edge_error_profile
from contact_viz.geometry.patch import LAYER_BAND, compute_patch, distance_signal
from contact_viz.geometry.stereo import SGBMParams, disparity_to_depth, masked_sgbm_disparity
from contact_viz.io.decoders import read_rgb
from contact_viz.io.session import BadFrame, open_session
from contact_viz.io.session_files import force_labels
from contact_viz.model.hmm import LosoEnsemble
from contact_viz.model.metrics import format_table, macro_mean, session_metrics, MACRO_ROW
from contact_viz.params import LabelParams, PatchParams
from contact_viz.pipeline.extract import cached_features, extract_features, feature_arrays
from contact_viz.synth.faults import without_depth

TRAIN = [(f"cup_train_{k}", "cup", 1300 + k) for k in range(6)]
TEST = [("cup_test", "cup", 1310), ("kidney_test", "kidney", 1311), ("liver_test", "liver", 1312),
        ("glove_test", "glove", 1313)]
# the mask-aware matcher as issue 13 first had it: 3 px blocks at 640 px, uniqueness 10, no hidden strip
FIRST_SGBM = SGBMParams(width_per_block_px=320.0, uniqueness_ratio=10, hidden_strip=False, median_px=0)
SOURCES = {  # depth source -> SGBM parameters (None = the session's depth/)
    "rendered": None,
    "SGBM": replace(FIRST_SGBM, tool_mask_aware=False),
    "SGBM, mask-aware, 3-way": FIRST_SGBM,
    "SGBM, mask-aware, no median": replace(SGBMParams(), median_px=0),
    "SGBM, mask-aware": SGBMParams(),
}
METHODS = {  # Table 1 row group -> (depth source, patch parameters)
    "rendered depth": ("rendered", PatchParams()),
    "SGBM, as before issue 13": ("SGBM", PatchParams(reject_bleeding=False)),
    "SGBM + the patch's bleeding test": ("SGBM", PatchParams()),
    "SGBM, mask-aware (3-way, 3 px blocks) + bleeding test": ("SGBM, mask-aware, 3-way", PatchParams()),
    "SGBM, mask-aware, no median + bleeding test": ("SGBM, mask-aware, no median", PatchParams()),
    "SGBM, mask-aware + bleeding test (default)": ("SGBM, mask-aware", PatchParams()),
}
EXACT = "exact gap (truth.csv; no depth error: the ceiling of every depth source)"
PROFILE_PX = 15  # band profile: background pixels 1..this far from the mask edge, px
WITHIN_M = 0.003  # band accuracy: within this of the true tissue depth, m


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def make_sessions(directory: Path, frames: int, size: tuple[int, int], camera: str = "default") -> None:
    """Generate the ten sessions into ``directory/sessions`` unless already there with these settings;
    ``camera``: a preset of `contact-viz synth --camera` (contact_viz.synth.camera)."""
    from contact_viz.synth import SynthParams, generate_session
    from contact_viz.synth.camera import camera_fields

    for name, phantom, seed in TRAIN + TEST:
        out = directory / "sessions" / name
        params = SynthParams(phantom=phantom, frames=frames, seed=seed, width=size[0], height=size[1],
                             **camera_fields(camera))
        info = out / "session.json"
        if info.is_file():
            g = json.loads(info.read_text()).get("generator", {})
            if ((g.get("frames"), g.get("width"), g.get("height"), g.get("seed"), g.get("tissue_distance_m"))
                    == (frames, *size, seed, params.tissue_distance_m)):
                continue
            raise SystemExit(f"{out}: a session with other settings is there ({g.get('frames')} frames at "
                             f"{g.get('width')}x{g.get('height')}); choose another --dir")
        log(f"synth {name} ({phantom}, seed {seed}, {frames} frames at {size[0]}x{size[1]})")
        generate_session(out, params)


def stereo_only(src: Path, dst: Path) -> Path:
    """A copy of session ``src`` without depth/ (contact_viz.synth.faults.without_depth)."""
    return without_depth(src, dst)


def source_root(directory: Path, source: str, name: str) -> Path:
    root = directory / "sessions" / name
    return root if SOURCES[source] is None else stereo_only(root, directory / "stereo" / name)


def open_source(directory: Path, source: str, name: str, cache_dir: Path):
    return open_session(source_root(directory, source, name), sgbm_params=SOURCES[source], cache_dir=cache_dir)


def table1(signals: dict[str, tuple[np.ndarray, np.ndarray]], score_labels: dict[str, np.ndarray] | None = None
           ) -> dict[str, dict]:
    """Fit the LOSO ensemble on the training sessions' (signal, labels), score the test sessions (against
    ``score_labels[name]`` instead of their labels when given)."""
    train = [signals[name] for name, _, _ in TRAIN]
    ensemble = LosoEnsemble().fit([s for s, _ in train], [y for _, y in train],
                                  session_names=[name for name, _, _ in TRAIN])
    rows = {}
    for name, _, _ in TEST:
        signal, labels = signals[name]
        if score_labels is not None:
            labels = score_labels[name][: len(signal)]
        rows[name] = session_metrics(labels, ensemble.predict_proba(signal), ensemble.threshold_, name)
    rows[MACRO_ROW] = macro_mean(rows)
    return rows


def truth_column(directory: Path, name: str, column: str) -> np.ndarray:
    """One column of a session's truth.csv per frame, float64 (``contact``: physical contact 0/1;
    ``gap_m``: the true tool-tissue gap, 0 in contact)."""
    import csv

    with (directory / "sessions" / name / "truth.csv").open(newline="") as handle:
        return np.array([float(r[column]) for r in csv.DictReader(handle)], np.float64)


def exact_gap_signals(directory: Path, cache_dir: Path, first: int | None) -> dict:
    """The signal of the generator's true tool-tissue gap (truth.csv ``gap_m``, 0 in contact) with the
    sessions' own labels: what a perfect distance would give the HMM, the ceiling of every depth source."""
    out = {}
    for name, _, _ in TRAIN + TEST:
        gap_m = truth_column(directory, name, "gap_m")
        labels = np.asarray(open_source(directory, "rendered", name, cache_dir).labels)
        count = len(gap_m) if first is None else min(first, len(gap_m))
        out[name] = (distance_signal(gap_m[:count], PatchParams().eps_m), labels[:count])
    return out


def ceiling_draws(count: int, frames: int, size: tuple[int, int]) -> np.ndarray:
    """Macro F1 of the exact gap (as ``exact_gap_signals``) on ``count`` draws of the study (seed offsets
    0, 100, 200, ... on top of the current seeds), from the generator's motion and sensors alone: no
    rendering, about 2 s a draw. How often the F1 target is within reach of any depth source."""
    from contact_viz.synth import SynthParams, plan_tool_track, sensor_streams

    f1 = []
    for k in range(count):
        signals = {}
        for name, phantom, seed in TRAIN + TEST:
            params = SynthParams(phantom=phantom, frames=frames, seed=seed + 100 * k, width=size[0], height=size[1])
            track = plan_tool_track(params)
            force_n, manual = sensor_streams(params, track)
            labels = manual if manual is not None else force_labels(np.linalg.norm(force_n, axis=1), LabelParams())
            signals[name] = (distance_signal(track.gap_m, PatchParams().eps_m), np.asarray(labels, np.int8))
        f1.append(table1(signals)[MACRO_ROW]["f1"])
    return np.array(f1)


def source_signals(directory: Path, source: str, params: PatchParams, cache_dir: Path, processes: int,
                   first: int | None) -> dict:
    out = {}
    for name, _, _ in TRAIN + TEST:
        session = open_source(directory, source, name, cache_dir)
        start = time.perf_counter()
        if first is None:
            rows, cached = cached_features(session, params, cache_dir=cache_dir, processes=processes)
        else:
            rows, cached = extract_features(session, params, indices=range(min(first, len(session))),
                                            processes=processes), False
        log(f"  {source}: {name} {'(cached)' if cached else f'in {time.perf_counter() - start:.0f} s'}")
        out[name] = feature_arrays(rows)
    return out


def truth_depth(directory: Path, name: str, indices: list[int]) -> dict[int, np.ndarray]:
    """The exact depth of frames ``indices`` of session ``name``, re-rendered once and kept in DIR/truth."""
    from contact_viz.synth import SynthParams, true_depth

    path = directory / "truth" / f"{name}.npz"
    if path.is_file():
        data = np.load(path)
        if all(f"f{i}" in data.files for i in indices):
            return {i: data[f"f{i}"] for i in indices}
    g = json.loads((directory / "sessions" / name / "session.json").read_text())["generator"]
    params = SynthParams(**{k: tuple(v) if isinstance(v, list) else v for k, v in g.items()})
    depth = true_depth(params, indices)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **{f"f{i}": d for i, d in depth.items()})
    return depth


def band_profile(directory: Path, cache_dir: Path, step: int, first: int | None) -> dict[str, dict]:
    """Per source: median and 10th percentile of the depth error (m) at 1..PROFILE_PX px from the mask
    edge, and the share of valid exterior-band pixels within WITHIN_M of the true depth."""
    errors = {s: [[] for _ in range(PROFILE_PX)] for s in SOURCES}
    band = {s: [0, 0, 0] for s in SOURCES}  # within, valid, band pixels
    for name, _, _ in TEST:
        sessions = {s: open_source(directory, s, name, cache_dir) for s in SOURCES}
        indices = list(range(0, min(first or len(sessions["rendered"]), len(sessions["rendered"])), step))
        truth = truth_depth(directory, name, indices)
        for i in indices:
            frame = sessions["rendered"].load_frame(i, ("mask",))
            if isinstance(frame, BadFrame):
                continue
            true_m = np.where(truth[i] > 0, truth[i], np.nan).astype(np.float32)
            in_band = compute_patch(true_m, frame.tool_mask).layer_ids == LAYER_BAND
            for s, session in sessions.items():
                depth = session.load_depth(i)
                if isinstance(depth, BadFrame):
                    continue
                for k, e in enumerate(edge_error_profile(depth, true_m, frame.tool_mask, PROFILE_PX)):
                    errors[s][k].append(e)
                with np.errstate(invalid="ignore"):
                    valid = in_band & np.isfinite(depth) & (depth > 0) & np.isfinite(true_m)
                    band[s][0] += int((np.abs(depth - true_m)[valid] < WITHIN_M).sum())
                band[s][1] += int(valid.sum())
                band[s][2] += int(in_band.sum())
    out = {}
    for s in SOURCES:
        pooled = [np.concatenate(e) if e else np.zeros(0) for e in errors[s]]
        out[s] = {
            "median_m": [float(np.median(e)) if e.size else None for e in pooled],
            "p10_m": [float(np.percentile(e, 10)) if e.size else None for e in pooled],
            "band_within_3mm": band[s][0] / max(band[s][1], 1),
            "band_valid": band[s][1] / max(band[s][2], 1),
        }
    return out


def bleed(depth_m: np.ndarray, tool: np.ndarray, px: int) -> np.ndarray:
    """``depth_m`` with the tool's depth spread ``px`` px out over the tissue: each background pixel with a
    valid depth within ``px`` of the tool takes the nearest (smallest) tool depth within that disc."""
    if px <= 0 or not tool.any():
        return depth_m
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * px + 1, 2 * px + 1))
    far = np.float32(1e30)  # "no tool depth here" (OpenCV's erode pads with FLT_MAX, not inf)
    tool_depth = np.where(tool & (depth_m > 0), depth_m, far).astype(np.float32)
    spread = cv2.erode(tool_depth, kernel)
    take = ~tool & (spread < far) & (depth_m > 0)  # the tissue's depth is replaced; holes stay holes
    out = depth_m.copy()
    out[take] = spread[take]
    return out


def bleeding_study(directory: Path, cache_dir: Path, widths: list[int], first: int | None):
    """Macro Table-1 rows with the rendered depth bled k px, patch without and with the bleeding test."""
    variants = {"as before": PatchParams(reject_bleeding=False), "bleeding test": PatchParams()}
    signals = {(k, v): {} for k in widths for v in variants}
    for name, _, _ in TRAIN + TEST:
        session = open_source(directory, "rendered", name, cache_dir)
        count = min(first or len(session), len(session))
        labels = np.asarray(session.labels)[:count]
        sig = {key: np.full(count, np.nan) for key in signals}
        for frame in session.iter_frames(("mask", "depth"), indices=range(count)):
            if isinstance(frame, BadFrame):
                continue
            tool = frame.tool_mask != 0
            for k in widths:
                depth = bleed(np.asarray(frame.depth_m), tool, k)
                for v, params in variants.items():
                    sig[(k, v)][frame.index] = compute_patch(depth, tool, params).signal
        for key in signals:
            signals[key][name] = (sig[key], labels)
        log(f"  bleeding: {name}")
    changed = {k: sum(int(np.sum(~np.isclose(signals[(k, "as before")][n][0], signals[(k, "bleeding test")][n][0],
                                             rtol=0, atol=1e-12, equal_nan=True))) for n in signals[(k, "as before")])
               for k in widths}
    for k in widths:
        log(f"  bled {k} px: the bleeding test changed the signal of {changed[k]} frames")
    return {f"bled {k} px, {v}": table1(signals[(k, v)])[MACRO_ROW] for k in widths for v in variants}, changed


SWEEP = {  # --band-sweep: mask-aware SGBM variants compared on the training sessions
    "3-way, 3 px blocks, uniqueness 10 (issue 13's first)": FIRST_SGBM,
    "... 5 px blocks": replace(FIRST_SGBM, block_size=5),
    "... uniqueness 20": replace(FIRST_SGBM, uniqueness_ratio=20),
    "... no left-right check, disp12MaxDiff off": replace(FIRST_SGBM, lr_check=False, disp12_max_diff=-1),
    "... mode HH (8 paths; O(W H D) memory)": replace(FIRST_SGBM, mode="hh"),
    "hidden strip, 3 px blocks, uniqueness 10": replace(FIRST_SGBM, hidden_strip=True),
    "hidden strip, 5 px blocks, uniqueness 15 (no median)": replace(SGBMParams(), median_px=0),
    "hidden strip, 7 px blocks, uniqueness 15 (no median)": replace(SGBMParams(), block_size=7, median_px=0),
    "... 5 px blocks, tool margin 2 px (no median)": replace(SGBMParams(), tool_margin_px=2, median_px=0),
    "... 5 px blocks, tool margin 3 px (no median)": replace(SGBMParams(), tool_margin_px=3, median_px=0),
    "... 5 px blocks, median 3 px": replace(SGBMParams(), median_px=3),
    "... 5 px blocks, median 5 px (default)": SGBMParams(),
}
SWEEP_NEAR_PX = (2, 3, 4)  # the profile's distances from the mask edge printed, px


def sweep_frames(job):
    """Counts and errors of one training session's frames for every variant."""
    directory, name, indices = job
    root = directory / "sessions" / name
    session = open_session(root)
    truth = truth_depth(directory, name, indices)
    stems = sorted(p.name for p in (root / "left").iterdir())
    out = {v: {"within": 0, "valid": 0, "band": 0, "near": [[] for _ in SWEEP_NEAR_PX], "seconds": 0.0} for v in SWEEP}
    for i in indices:
        tool = session.load_frame(i, ("mask",)).tool_mask != 0
        left, right = read_rgb(root / "left" / stems[i]), read_rgb(root / "right" / stems[i])
        true_m = np.where(truth[i] > 0, truth[i], np.nan).astype(np.float32)
        band = compute_patch(true_m, tool).band
        for name_v, params in SWEEP.items():
            start = time.perf_counter()
            disparity = masked_sgbm_disparity(left, right, tool, params)
            out[name_v]["seconds"] += time.perf_counter() - start
            depth = disparity_to_depth(disparity, session.calibration.fx, session.calibration.baseline_m)
            with np.errstate(invalid="ignore"):
                valid = band & np.isfinite(depth) & np.isfinite(true_m)
                out[name_v]["within"] += int((np.abs(depth - true_m)[valid] < WITHIN_M).sum())
            out[name_v]["valid"] += int(valid.sum())
            out[name_v]["band"] += int(band.sum())
            profile = edge_error_profile(depth, true_m, tool, max(SWEEP_NEAR_PX))
            for k, px in enumerate(SWEEP_NEAR_PX):
                out[name_v]["near"][k].append(profile[px - 1])
    return out


def band_sweep(directory: Path, step: int, start: int, processes: int) -> None:
    """How the SWEEP variants do beside the tool on every ``step``-th frame from ``start`` of the six training
    sessions (the defaults are chosen here; the test sessions are not read): share of the exterior band's
    valid pixels within 3 mm of the exact depth, share of band pixels with depth, 10th percentile of the
    error 2, 3 and 4 px from the mask edge (the tool's depth dragged over the tissue shows as -10 to
    -40 mm there), matching time per frame."""
    if not all((directory / "sessions" / n / "session.json").is_file() for n, _, _ in TRAIN):
        raise SystemExit(f"{directory}/sessions: the training sessions are missing; run recipes/sgbm_study.py first")
    frames = len(open_session(directory / "sessions" / TRAIN[0][0]))
    jobs = [(directory, n, list(range(start, frames, step))) for n, _, _ in TRAIN]
    total = {v: {"within": 0, "valid": 0, "band": 0, "near": [[] for _ in SWEEP_NEAR_PX], "seconds": 0.0} for v in SWEEP}
    with ProcessPoolExecutor(processes) as pool:
        for part in pool.map(sweep_frames, jobs):
            for v in SWEEP:
                for key in ("within", "valid", "band", "seconds"):
                    total[v][key] += part[v][key]
                for k in range(len(SWEEP_NEAR_PX)):
                    total[v]["near"][k] += part[v]["near"][k]
    n_frames = sum(len(j[2]) for j in jobs)
    print(f"{n_frames} frames of the six training sessions (every {step}th from {start}); band = the patch's "
          "exterior band on the true depth")
    print(f"{'variant':55s} {'within 3 mm':>11s} {'valid':>6s}  p10 error at " + "/".join(map(str, SWEEP_NEAR_PX))
          + f" px, mm {'ms/frame':>9s}")
    for v, t in total.items():
        near = "/".join(f"{1000 * np.percentile(np.concatenate(e), 10):.1f}" if sum(map(len, e)) else "-"
                        for e in t["near"])
        print(f"{v:55s} {100 * t['within'] / max(t['valid'], 1):10.1f}% {100 * t['valid'] / max(t['band'], 1):5.1f}%  "
              f"{near:>22s} {1000 * t['seconds'] / n_frames:9.0f}")


def summarize(directories: list[Path]) -> None:
    """The draws side by side, from each directory's results.json."""
    default = next(k for k in METHODS if "default" in k)
    head = ("draw (test seeds)", "frames", "exact gap", "rendered", "SGBM", "SGBM vs physical contact",
            "band within 3 mm", "test frames in contact labelled 0")
    print("| " + " | ".join(head) + " |\n|" + "---|" * len(head))
    for directory in directories:
        results = json.loads((directory / "results.json").read_text())
        tables, seeds = results["tables"], results["seeds"]
        f1 = [f"{tables[k][MACRO_ROW]['f1']:.3f}" if k in tables else "-" for k in (EXACT, "rendered depth", default)]
        tests = [name for name, _, _ in TEST]
        light = sum(results["contact_labelled_0"][name] for name in tests)
        band = results["band_profile"]["SGBM, mask-aware"]["band_within_3mm"]
        print(f"| {min(seeds[n] for n in tests)}-{max(seeds[n] for n in tests)} | "
              f"{results['first_frames'] or results['frames']} | {' | '.join(f1)} | "
              f"{results['tables_physical_contact'][default]['f1']:.3f} | {100 * band:.1f}% | {light} |")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dir", type=Path, default=Path(".study"), help="where sessions and caches go")
    parser.add_argument("--frames", type=int, default=None,
                        help="frames per session (default: contact-viz synth's, 120, as in the issue)")
    parser.add_argument("--size", default="640x360", help="image size WIDTHxHEIGHT")
    parser.add_argument("--camera", default="default", help="synth's camera preset (default, davinci, close)")
    parser.add_argument("--processes", type=int, default=2, help="processes for feature extraction")
    parser.add_argument("--profile-step", type=int, default=5, help="band profile on every n-th test frame")
    parser.add_argument("--bleed-px", default="0,2,4,6", help="bleeding widths to test, px (comma-separated)")
    parser.add_argument("--first-frames", type=int, default=None,
                        help="use only the first N frames of each session (all sessions and methods alike)")
    parser.add_argument("--seed-offset", type=int, default=0,
                        help="add this to every session seed (another draw of the same study: 100 = seeds 1400-1413)")
    parser.add_argument("--only-default", action="store_true",
                        help="only the rendered depth and the default SGBM path (no earlier matchers; faster)")
    parser.add_argument("--ceiling-draws", type=int, default=0, metavar="N",
                        help="instead: macro F1 of the exact gap on N draws (seed offsets 0, 100, ...; no "
                        "rendering): how often any depth source could reach the F1 target")
    parser.add_argument("--summarize", type=Path, nargs="+", metavar="DIR",
                        help="instead: one line per study directory already run (its results.json): the exact "
                        "gap's, the rendered depth's and the default SGBM's held-out macro F1, and the band accuracy")
    parser.add_argument("--variant", metavar="JSON", default=None,
                        help='one more SGBM row: the default with these SGBMParams fields, e.g. \'{"match_width_px": 640}\'')
    parser.add_argument("--band-sweep", action="store_true",
                        help="instead: compare SGBM settings beside the tool on the training sessions (how the "
                        "defaults were chosen), on every 15th frame from frame 7")
    args = parser.parse_args(argv)
    global TRAIN, TEST, SOURCES, METHODS  # the study's sessions and rows, as the options choose them
    TRAIN = [(name, phantom, seed + args.seed_offset) for name, phantom, seed in TRAIN]
    TEST = [(name, phantom, seed + args.seed_offset) for name, phantom, seed in TEST]
    if args.only_default:
        SOURCES = {k: v for k, v in SOURCES.items() if k in ("rendered", "SGBM, mask-aware")}
        METHODS = {k: v for k, v in METHODS.items() if v[0] in SOURCES and (k == "rendered depth" or "default" in k)}
    if args.variant:
        SOURCES[f"SGBM {args.variant}"] = SGBMParams(**json.loads(args.variant))
        METHODS[f"SGBM {args.variant} + bleeding test"] = (f"SGBM {args.variant}", PatchParams())
    if args.summarize:
        summarize(args.summarize)
        return 0
    size = tuple(int(v) for v in args.size.lower().split("x"))
    if args.frames is None:
        from contact_viz.synth import SynthParams

        args.frames = SynthParams().frames
    if args.ceiling_draws:
        f1 = ceiling_draws(args.ceiling_draws, args.frames, size)
        print(f"Exact gap, {args.ceiling_draws} draws of {args.frames} frames at {args.size}: held-out macro F1 "
              f"median {np.median(f1):.3f}, 10th percentile {np.percentile(f1, 10):.3f}, "
              f"at least 0.90 on {np.mean(f1 >= 0.90):.0%} of draws")
        print("first draws (seed offset: F1): " + ", ".join(
            f"{args.seed_offset + 100 * k}: {v:.3f}" for k, v in enumerate(f1[:10])))
        return 0
    directory = args.dir.resolve()
    cache_dir = directory / "cache"
    make_sessions(directory, args.frames, size, args.camera)
    if args.band_sweep:
        band_sweep(directory, 15, 7, args.processes)
        return 0
    results: dict = {"frames": args.frames, "first_frames": args.first_frames, "size": args.size,
                     "seeds": {name: seed for name, _, seed in TRAIN + TEST}, "tables": {}}
    if args.first_frames:
        print(f"(only the first {args.first_frames} of the {args.frames} frames of each session are used)")
    signals = {}
    for method, (source, params) in METHODS.items():
        log(f"== {method}")
        signals[method] = source_signals(directory, source, params, cache_dir, args.processes, args.first_frames)
        results["tables"][method] = table1(signals[method])
    signals[EXACT] = exact_gap_signals(directory, cache_dir, args.first_frames)
    results["tables"][EXACT] = table1(signals[EXACT])
    for method, rows in results["tables"].items():
        print(f"\nTable 1, {method}")
        print(format_table(rows))
    # The force labels (>= 2 N; the glove's manual labels) miss touches under 2 N, which the distance sees as
    # contact: the same models scored against the generator's physical contact, and how many such frames.
    truth = {name: truth_column(directory, name, "contact").astype(np.int64) for name, _, _ in TRAIN + TEST}
    light = {}
    for name, _, _ in TRAIN + TEST:
        contact = truth[name]
        count = len(contact) if args.first_frames is None else min(args.first_frames, len(contact))
        labels = np.asarray(open_source(directory, "rendered", name, cache_dir).labels)[:count]
        light[name] = int(np.sum((contact[:count] == 1) & (labels == 0)))
    results["contact_labelled_0"] = light
    print("\nFrames in physical contact (truth.csv) but labelled no contact (force under 2 N; glove: manual "
          "labels' edges): " + ", ".join(f"{n} {k}" for n, k in light.items()))
    physical = {name: truth[name] for name, _, _ in TEST}
    results["tables_physical_contact"] = {}
    for method in signals:
        results["tables_physical_contact"][method] = table1(signals[method], physical)[MACRO_ROW]
    print("\nThe same models scored against physical contact (truth.csv; macro rows)")
    print(format_table(results["tables_physical_contact"]))
    log("== band error profile")
    profile = results["band_profile"] = band_profile(directory, cache_dir, args.profile_step, args.first_frames)
    print(f"\nBand error profile (test sessions, every {args.profile_step}th frame): depth - true depth, mm, "
          "by distance from the mask edge")
    print("px    " + "".join(f"{s + ' med':>22s}{'p10':>8s}" for s in SOURCES))
    for k in range(PROFILE_PX):
        mm = {s: [1000 * (profile[s][q][k] if profile[s][q][k] is not None else np.nan) for q in ("median_m", "p10_m")]
              for s in SOURCES}
        cells = "".join(f"{mm[s][0]:22.2f}{mm[s][1]:8.2f}" for s in SOURCES)
        print(f"{k + 1:<6d}{cells}")
    for s in SOURCES:
        print(f"{s}: exterior band pixels within 3 mm of the true depth: {100 * profile[s]['band_within_3mm']:.1f}% "
              f"of valid ones ({100 * profile[s]['band_valid']:.1f}% of band pixels valid)")
    widths = [int(v) for v in args.bleed_px.split(",") if v.strip()]
    if widths:
        log("== edge bleeding on the rendered depth")
        bled, changed = bleeding_study(directory, cache_dir, widths, args.first_frames)
        results["bleeding"], results["bleeding_frames_changed"] = bled, changed
        print("\nEdge bleeding: rendered depth with the tool's depth spread k px into the tissue (macro rows)")
        print(format_table(bled))
        print("frames (all ten sessions) whose signal the bleeding test changed: "
              + ", ".join(f"{changed[k]} at {k} px" for k in widths))
    (directory / "results.json").write_text(json.dumps(results, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
