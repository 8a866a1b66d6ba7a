"""Reproduce the paper's study on your sessions with one command: Table 1, the timelines and pipeline figures.

    python recipes/reproduce_paper.py                       # the synthetic study, full configuration
    python recipes/reproduce_paper.py --quick -o /tmp/paper # the synthetic study in a few minutes
    python recipes/reproduce_paper.py SESSIONS SPLIT.json -o results/paper --grid-search --weights b3.pth

Steps: feature extraction (the minimum-distance patch of every frame, cached), optionally the
grid search of N1, N2, tau_tool and tau_patch on the training sessions (recipes/grid_search.py),
the leave-one-session-out HMM ensemble, the RGB EfficientNet baseline under the same LOSO
protocol (contact_viz.baseline; fold checkpoints resume), held-out evaluation of both, and the
figures.

Split file (JSON), session names relative to the SESSIONS folder, test sessions in table order:

    {"train": ["cup_1", "cup_2", "cup_3", "cup_4", "cup_5", "cup_6"],
     "test": [{"session": "cup_7",    "category": "same phantom and task"},
              {"session": "kidney_1", "category": "new phantom"},
              {"session": "liver_1",  "category": "new phantom"},
              {"session": "glove_1",  "category": "new phantom and task"}]}

"train" needs at least two sessions (leave-one-session-out); "category" is one of
contact_viz.paper.study.CATEGORIES (contact_viz.paper.study reads and checks the file).

Without SESSIONS and SPLIT the synthetic study of scripts/demo.sh is generated and run: six ``cup``
training sessions (seeds 0-5) and one test session each on ``cup``, ``kidney``, ``liver`` and
``glove`` (seeds 100-103), into ``<output>/synthetic`` unless --synthetic-dir; sessions already
there with the same generator settings are reused.

Configurations: the default is the paper's (EfficientNet-B3, 234 px crops, 10 epochs; give
``--weights`` an efficientnet-pytorch ImageNet state dict, without it the net trains from scratch
and every output says so; about a day of CPU time on the paper's data). ``--quick`` runs a tiny
baseline (EfficientNet-B0 at a quarter of its width and depth, 64 px crops, 2 epochs) on a
smaller synthetic study; ``--tiny`` is smaller still (for tests). Neither is the paper's
configuration, and table1.*, the timelines figure and config.json say so.

Outputs (``-o``, default results/paper/), each written atomically:
    table1.md, table1.tex, table1.csv  Table 1: both methods side by side, per session and Macro
                                       (the CSV has one row per session and method)
    timelines.png / .pdf               contact probabilities of both methods against ground truth
    pipeline.png / .pdf                (a) tool mask, (b) layers over depth, (c) the selected patch
    per_frame_hmm.csv, per_frame_rgb.csv  every test frame: posterior, decision, label
    config.json                        the resolved configuration, thresholds, versions, timings
    model.json                         the HMM ensemble (contact-viz evaluate / view can use it)
    grid_search.json                   with --grid-search: every grid point's out-of-fold scores
    baseline/<key>/                    the baseline's fold checkpoints and ensemble.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
import sys
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from contact_viz import __version__
from contact_viz.baseline import BaselineParams, BaselineWarning, FoldEvent, extract_crops, fit_loso
from contact_viz.io.cache import cache_key, default_cache_dir
from contact_viz.errors import SessionError
from contact_viz.pipeline.extract import cached_features, feature_arrays
from contact_viz.model.hmm import LosoEnsemble
from contact_viz.io.jsonfile import write_json
from contact_viz.model.metrics import MACRO_ROW, format_table, macro_mean, session_metrics
from contact_viz.model.model_file import ContactModel, save_model
from contact_viz.params import LabelParams, PatchParams, read_patch_params, to_dict
from contact_viz.io.session import BadFrame, Session, open_session
from contact_viz.paper.study import CATEGORIES, HeldOutEntry, Split, read_split, write_split
from contact_viz.paper.tables import write_per_frame, write_table1

RECIPES_DIR = Path(__file__).resolve().parent
sys.path.insert(0, str(RECIPES_DIR))  # recipes/ is not a package
import grid_search  # noqa: E402  (the grid search step and its default grid)
PHANTOM_CATEGORY = {"cup": CATEGORIES[0], "kidney": CATEGORIES[1], "liver": CATEGORIES[1], "glove": CATEGORIES[2]}
TEST_SEED_BASE = 100  # synthetic test seeds: 100 + index of the phantom in synth.PHANTOMS (training: 0..K-1)
HMM_METHOD = "HMM"
SPLIT_FILE = "split.json"  # name of the split file written beside a generated synthetic study
DEFAULT_OUTPUT = Path("results/paper")
PAPER_GRID = grid_search.DEFAULT_GRID  # n1, n2, tau_tool, tau_patch


@dataclass(frozen=True)
class StudyProfile:
    """How big the run is: the synthetic study's size, the baseline's configuration, the grid."""

    name: str  # "full", "quick" or "tiny"
    synth_frames: int  # frames per synthetic session, count
    synth_width: int  # synthetic image width, px
    synth_height: int  # synthetic image height, px
    synth_fps: int  # synthetic frame rate, 1/s
    n_train: int  # synthetic cup training sessions, count
    test_phantoms: tuple[str, ...]  # one synthetic test session per phantom, in table order
    baseline: BaselineParams  # RGB baseline settings
    grid: tuple[tuple[int, ...], ...]  # --grid-search values of n1, n2, tau_tool, tau_patch


TINY_NET = dict(model_name="efficientnet-b0", width_coefficient=0.25, depth_coefficient=0.25)
PROFILES = {
    # The paper's baseline. The synthetic study at 960x540 (about 3 GB, most of it float32 depth) so
    # the 234 px crop is a crop around the tool tip, not the whole frame.
    "full": StudyProfile("full", 150, 960, 540, 30, 6, ("cup", "kidney", "liver", "glove"),
                         BaselineParams(), PAPER_GRID),
    # A few minutes on 2 CPU cores: the demo's study size, a tiny net on 64 px crops.
    "quick": StudyProfile("quick", 150, 480, 270, 30, 6, ("cup", "kidney", "liver", "glove"),
                          BaselineParams(**TINY_NET, bn_momentum=0.1, crop_px=64, epochs=2),
                          ((29, 31), (11, 17), (30,), (8,))),
    # Seconds: for tests and smoke runs. fps 10 so 40 frames hold a full press cycle.
    "tiny": StudyProfile("tiny", 40, 160, 96, 10, 3, ("cup", "glove"),
                         BaselineParams(**TINY_NET, bn_momentum=0.5, crop_px=64, epochs=1, batch_size=8,
                                        eval_batch_size=16),
                         ((31,), (11, 17), (30,), (8,))),
}


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------------------------
# Split and study
# --------------------------------------------------------------------------------------------


def synthetic_study(directory: Path, profile: StudyProfile) -> tuple[Path, Path, list[dict]]:
    """Generate (or reuse) the synthetic study; returns (sessions folder, split file, session specs)."""
    from contact_viz.synth import PHANTOMS, SynthParams, generate_session

    sessions_dir = directory / "sessions"
    specs = [{"session": f"cup_train_{k}", "phantom": "cup", "seed": k} for k in range(profile.n_train)]
    specs += [{"session": f"{phantom}_test", "phantom": phantom, "seed": TEST_SEED_BASE + PHANTOMS.index(phantom),
               "category": PHANTOM_CATEGORY[phantom]} for phantom in profile.test_phantoms]
    for spec in specs:
        params = SynthParams(phantom=spec["phantom"], frames=profile.synth_frames, seed=spec["seed"],
                             width=profile.synth_width, height=profile.synth_height, fps=profile.synth_fps)
        spec["synth_params"] = to_dict(params)
        out = sessions_dir / spec["session"]
        marker = out / "session.json"  # written last by generate_session: the completion marker
        wanted = json.loads(json.dumps(spec["synth_params"]))  # tuples as JSON lists, as session.json holds them
        if marker.is_file() and json.loads(marker.read_text()).get("generator") == wanted:
            continue
        start = time.perf_counter()
        generate_session(out, params, overwrite=True)
        log(f"  generated {out} ({profile.synth_frames} frames, {time.perf_counter() - start:.1f} s)")
    split = Split(train=tuple(s["session"] for s in specs if "category" not in s),
                  test=tuple(HeldOutEntry(s["session"], s["category"]) for s in specs if "category" in s))
    split_path = directory / SPLIT_FILE
    write_split(split_path, split)
    return sessions_dir, split_path, specs


# --------------------------------------------------------------------------------------------
# Steps
# --------------------------------------------------------------------------------------------


def run_grid_search(train_dirs: Sequence[Path], grid_values, cache_dir: Path | None,
                    out: Path) -> tuple[PatchParams, dict]:
    """recipes/grid_search.py's protocol on the training sessions; writes grid_search.json; returns the best params."""
    grid, skipped = grid_search.build_grid(*grid_values, base=PatchParams())
    for note in skipped:
        log(f"  grid point skipped: {note}")
    points = grid_search.score_grid(list(train_dirs), grid, cache_dir, on_skip=lambda note: log(f"  grid point {note}"))
    scored = [{"patch_params": to_dict(r.params), "oof_f1": r.oof_f1, "oof_auprc": r.oof_auprc} for r in points]
    best = points[0].params
    result = {"score": "pooled out-of-fold F1 of the LOSO HMM ensemble, AUPRC as tie-breaker",
              "grid": dict(zip(("n1", "n2", "tau_tool", "tau_patch"), (list(v) for v in grid_values))),
              "best": scored[0], "points": scored}
    write_json(out / "grid_search.json", result)
    return best, result


@dataclass
class Features:
    """Features of one session."""

    name: str
    frames: list[str]
    signal: np.ndarray  # (T,) float64, NaN = no patch
    labels: np.ndarray  # (T,) int8, -1 = unknown
    rows: list[dict]


def session_features(session: Session, params: PatchParams, label_params: LabelParams, cache_dir) -> Features:
    start = time.perf_counter()
    rows, cached = cached_features(session, params, label_params=label_params, cache_dir=cache_dir)
    signal, labels = feature_arrays(rows)
    log(f"  features {session.name}: {len(rows)} frames" + (" (cached)" if cached else
                                                             f" in {time.perf_counter() - start:.1f} s"))
    return Features(session.name, [str(r["frame"]) for r in rows], signal, labels, rows)


def baseline_label(profile: StudyProfile, weights: Path | None) -> tuple[str, bool, str]:
    """(method name in the table, whether it is the paper's configuration, a one-line note)."""
    p = profile.baseline
    what = (f"{p.model_name}" + (f" at width x{p.width_coefficient:g}, depth x{p.depth_coefficient:g}"
                                 if p.width_coefficient or p.depth_coefficient else "")
            + f", {p.crop_px} px crops, epochs {p.epochs}, "
            + ("ImageNet init" if weights is not None else "trained from scratch"))
    if profile.name != "full":
        return (f"EfficientNet [{profile.name}]", False,
                f"RGB baseline in the --{profile.name} configuration ({what}): NOT the paper's configuration")
    if weights is None:
        return ("EfficientNet [scratch]", False,
                f"RGB baseline: the paper's architecture ({what}); no --weights given, so it is NOT "
                "the paper's ImageNet fine-tuning")
    return "EfficientNet", True, f"RGB baseline: the paper's configuration ({what})"


def checkpoint_key(params: BaselineParams, weights: Path | None, train: Sequence[Session]) -> str:
    """Name of the checkpoint folder of one baseline run: a digest of the params, the init and the
    training sessions' names and files (a changed session never resumes a stale checkpoint)."""
    payload = json.dumps({"params": to_dict(params), "weights": None if weights is None else weights.name,
                          "train": [[s.name, cache_key(s.root, "baseline-run", {})] for s in train]}, sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()[:12]


def fold_progress(event: FoldEvent) -> None:
    loss = "" if event.loss is None else f", loss {event.loss:.4f}"
    log(f"  baseline fold {event.fold} (without {event.held_out}): {event.stage} {event.epoch}{loss}")


def pick_figure_frame(features: Features) -> int:
    """The frame of the smallest |distance| among frames with a patch (the tool at the tissue), else 0."""
    distance = np.array([abs(float(r["distance_m"])) if r["distance_m"] != "" else np.inf for r in features.rows])
    return int(np.argmin(distance)) if np.isfinite(distance).any() else 0


# --------------------------------------------------------------------------------------------
# Outputs
# --------------------------------------------------------------------------------------------


HMM_COLUMNS = ("session", "category", "frame", "timestamp_s", "signal", "posterior", "predicted", "label")
RGB_COLUMNS = ("session", "category", "frame", "timestamp_s", "raw_score", "posterior", "predicted", "label",
               "crop_x", "crop_y")


# --------------------------------------------------------------------------------------------
# Main
# --------------------------------------------------------------------------------------------


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="See the module docstring for the split file format and the outputs.")
    parser.add_argument("sessions", type=Path, nargs="?",
                        help="folder of session directories (omit for the synthetic study)")
    parser.add_argument("split", type=Path, nargs="?", help="split JSON (train / test with categories)")
    parser.add_argument("-o", "--output", type=Path, default=DEFAULT_OUTPUT, help="results folder [results/paper]")
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--quick", action="store_true", help="tiny baseline and smaller synthetic study (minutes)")
    size.add_argument("--tiny", action="store_true", help="smallest run, for tests (seconds)")
    parser.add_argument("--grid-search", action="store_true",
                        help="choose N1, N2, tau_tool, tau_patch on the training sessions")
    parser.add_argument("--params", type=Path, help="JSON of PatchParams fields (or grid_search.py's output)")
    parser.add_argument("--weights", type=Path, help="efficientnet-pytorch ImageNet state dict (.pth) for the baseline")
    parser.add_argument("--contact-force", type=float, default=LabelParams().contact_force_n,
                        help="contact label threshold on the force magnitude, N [2.0]")
    parser.add_argument("--seed", type=int, default=0, help="seed of the baseline's training [0]")
    parser.add_argument("--device", default=None, help="torch device of the baseline [cuda if available, else cpu]")
    parser.add_argument("--cache-dir", type=Path, default=None, help="feature / crop cache [~/.cache/contact-viz]")
    parser.add_argument("--synthetic-dir", type=Path, default=None,
                        help="where the synthetic study goes [OUTPUT/synthetic]")
    parser.add_argument("--figure-frame", default=None, metavar="SESSION:INDEX",
                        help="frame of the pipeline figure [first test session, frame of the smallest distance]")
    args = parser.parse_args(argv)
    if (args.sessions is None) != (args.split is None):
        parser.error("give both SESSIONS and SPLIT, or neither (the synthetic study)")
    if args.grid_search and args.params is not None:
        parser.error("--grid-search and --params both set the patch parameters; give one")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    try:
        return run(args)
    except (ValueError, SessionError, FileNotFoundError) as exc:
        log(f"error: {exc}")
        return 1


class Timer:
    """Wall-clock time of each step, s."""

    def __init__(self) -> None:
        self.start = self.last = time.perf_counter()
        self.steps: dict[str, float] = {}

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.steps[name] = round(now - self.last, 2)
        self.last = now

    def total(self) -> float:
        return round(time.perf_counter() - self.start, 2)


@dataclass
class Study:
    """The sessions of one run, opened."""

    sessions_dir: Path
    split_path: Path
    split: Split
    train: list[Session]
    test: list[Session]
    categories: dict[str, str]  # test session name -> category
    synthetic: dict | None  # the generated study's description, None for the user's sessions


def prepare_study(args: argparse.Namespace, profile: StudyProfile, label_params: LabelParams) -> Study:
    """Generate the synthetic study if no sessions were given, read the split, open every session."""
    synthetic = None
    if args.sessions is None:
        synth_dir = args.synthetic_dir or args.output / "synthetic"
        log(f"== synthetic study ({profile.name}: {profile.n_train} train + {len(profile.test_phantoms)} test "
            f"sessions, {profile.synth_frames} frames at {profile.synth_width}x{profile.synth_height}) in {synth_dir}")
        sessions_dir, split_path, specs = synthetic_study(synth_dir, profile)
        synthetic = {"directory": str(synth_dir.resolve()), "sessions": specs}
    else:
        sessions_dir, split_path = args.sessions, args.split
    split = read_split(split_path)

    def open_one(rel: str) -> Session:
        return open_session(sessions_dir / rel, label_params=label_params, cache_dir=args.cache_dir)

    train, test = [open_one(s) for s in split.train], [open_one(e.session) for e in split.test]
    names = [s.name for s in train + test]
    if len(set(names)) != len(names):
        raise ValueError(f"{split_path}: session names (session.json \"name\", else the folder name) must be "
                         f"distinct, got {names}")
    categories = {s.name: e.category for s, e in zip(test, split.test)}
    return Study(Path(sessions_dir), Path(split_path), split, train, test, categories, synthetic)


@dataclass
class MethodResult:
    """One method's held-out output."""

    name: str  # method name in the table
    threshold: float  # decision threshold on the posterior
    posteriors: list[np.ndarray]  # per test session, (T,) float64 P(contact)


def fit_hmm(study: Study, params: PatchParams, label_params: LabelParams, cache_dir, out: Path):
    """Features of every session, the LOSO HMM ensemble (saved as model.json), its test posteriors."""
    log("== features (minimum-distance patch of every frame)")
    train = [session_features(s, params, label_params, cache_dir) for s in study.train]
    test = [session_features(s, params, label_params, cache_dir) for s in study.test]
    log("== LOSO HMM ensemble")
    ensemble = LosoEnsemble().fit([f.signal for f in train], [f.labels for f in train],
                                  session_names=[f.name for f in train])
    model = ContactModel(ensemble=ensemble, patch_params=params, label_params=label_params,
                         training_sessions=tuple({"name": s.name, "path": str(s.root), "frames": len(s)}
                                                 for s in study.train))
    save_model(model, out / "model.json")
    log(f"  threshold {ensemble.threshold_:.4f}")
    for s, f in zip(study.test, test):
        if not np.array_equal(np.asarray(s.labels), f.labels):
            raise ValueError(f"{s.root}: the cached features' labels differ from the session's; clear the cache")
    result = MethodResult(HMM_METHOD, float(ensemble.threshold_), [ensemble.predict_proba(f.signal) for f in test])
    return result, ensemble, test


def fit_baseline(study: Study, profile: StudyProfile, args: argparse.Namespace, method: str, timer: Timer):
    """Tool-tip crops, the LOSO EfficientNet ensemble (resuming its checkpoints), its test posteriors."""
    crop_cache = args.cache_dir if args.cache_dir is not None else default_cache_dir()
    train_crops = [extract_crops(s, profile.baseline.crop_px, cache_dir=crop_cache) for s in study.train]
    test_crops = [extract_crops(s, profile.baseline.crop_px, cache_dir=crop_cache) for s in study.test]
    timer.lap("baseline_crops")
    checkpoint_dir = args.output / "baseline" / checkpoint_key(profile.baseline, args.weights, study.train)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BaselineWarning)  # training from scratch: said in every output instead
        ensemble = fit_loso(train_crops, profile.baseline, checkpoint_dir, weights=args.weights,
                            device=args.device, progress=fold_progress)
    timer.lap("baseline_training")
    raw = [ensemble.predict_raw(c) for c in test_crops]
    log(f"  threshold {ensemble.threshold_:.4f}")
    result = MethodResult(method, float(ensemble.threshold_), [ensemble.platt_(r) for r in raw])
    return result, ensemble, raw, test_crops, checkpoint_dir


def metrics_rows(study: Study, methods: Sequence[MethodResult]) -> dict[str, dict[str, dict]]:
    """Table 1: test session -> method -> session_metrics, then the Macro row."""
    table: dict[str, dict[str, dict]] = {}
    for i, s in enumerate(study.test):
        labels = np.asarray(s.labels, dtype=np.int64)
        table[s.name] = {m.name: session_metrics(labels, m.posteriors[i], m.threshold, name=s.name) for m in methods}
    table[MACRO_ROW] = {m.name: macro_mean({n: row[m.name] for n, row in table.items()}) for m in methods}
    return table


def per_frame_rows(study: Study, hmm: MethodResult, hmm_signals: list[Features], rgb: MethodResult,
                   rgb_raw: list[np.ndarray], crops: list) -> tuple[list[dict], list[dict]]:
    """Rows of per_frame_hmm.csv and per_frame_rgb.csv (floats as repr: they read back exactly)."""
    hmm_rows, rgb_rows = [], []
    for i, (s, f) in enumerate(zip(study.test, hmm_signals)):
        for t, stem in enumerate(s.stems):
            common = {"session": s.name, "category": study.categories[s.name], "frame": stem,
                      "timestamp_s": repr(float(s.timestamps_s[t])),
                      "label": "" if s.labels[t] < 0 else int(s.labels[t])}
            p_hmm, p_rgb = float(hmm.posteriors[i][t]), float(rgb.posteriors[i][t])
            hmm_rows.append({**common, "signal": "" if np.isnan(f.signal[t]) else repr(float(f.signal[t])),
                             "posterior": repr(p_hmm), "predicted": int(p_hmm >= hmm.threshold)})
            rgb_rows.append({**common, "raw_score": repr(float(rgb_raw[i][t])), "posterior": repr(p_rgb),
                             "predicted": int(p_rgb >= rgb.threshold),
                             "crop_x": repr(float(crops[i].center_xy[t, 0])),
                             "crop_y": repr(float(crops[i].center_xy[t, 1]))})
    return hmm_rows, rgb_rows


def figure_frame(study: Study, spec: str | None, test_features: list[Features]) -> tuple[Session, int]:
    """The session and frame index of the pipeline figure (``SESSION:INDEX``, or the default)."""
    if spec is None:
        return study.test[0], pick_figure_frame(test_features[0])
    name, _, index = spec.rpartition(":")
    by_name = {s.name: s for s in study.train + study.test}
    if name not in by_name or not index.isdigit() or int(index) >= len(by_name[name]):
        raise ValueError(f"--figure-frame {spec!r}: expected SESSION:INDEX with SESSION one of {sorted(by_name)} "
                         "and INDEX a frame number of that session")
    return by_name[name], int(index)


def write_figures(out: Path, study: Study, hmm: MethodResult, rgb: MethodResult, title: str | None,
                  frame_session: Session, frame_index: int, params: PatchParams) -> tuple[list[Path], dict]:
    """timelines.png/.pdf and pipeline.png/.pdf; returns the files and a description of the figure frame."""
    from contact_viz.viz.figures import TimelineSession, pipeline_figure, save_figure, timelines_figure
    from contact_viz.geometry.patch import compute_patch

    timeline = [TimelineSession(s.name, study.categories[s.name], np.asarray(s.timestamps_s), np.asarray(s.labels),
                                hmm.posteriors[i], hmm.threshold, rgb.posteriors[i], rgb.threshold)
                for i, s in enumerate(study.test)]
    files = save_figure(timelines_figure(timeline, method_names=(hmm.name, rgb.name), title=title), out / "timelines")
    frame = next(iter(frame_session.iter_frames(layers=("mask", "depth", "left"), indices=[frame_index])))
    if isinstance(frame, BadFrame):
        raise ValueError(f"pipeline figure: frame {frame_index} of {frame_session.name} is unreadable: {frame.reason}")
    patch = compute_patch(frame.depth_m, frame.tool_mask, params)
    files += save_figure(pipeline_figure(frame.left_rgb, frame.tool_mask, frame.depth_m, patch), out / "pipeline")
    described = {"session": frame_session.name, "index": frame_index, "stem": frame.stem,
                 "distance_m": patch.distance_m if patch.found else None, "no_patch_reason": patch.reason}
    return files, described


def run(args: argparse.Namespace) -> int:
    timer = Timer()
    profile = PROFILES["tiny" if args.tiny else "quick" if args.quick else "full"]
    profile = replace(profile, baseline=replace(profile.baseline, seed=args.seed))
    out: Path = args.output
    out.mkdir(parents=True, exist_ok=True)
    label_params = LabelParams(contact_force_n=args.contact_force)
    study = prepare_study(args, profile, label_params)
    timer.lap("study")

    grid_result = None
    if args.grid_search:
        log(f"== grid search on {len(study.train)} training sessions")
        params, grid_result = run_grid_search([s.root for s in study.train], profile.grid, args.cache_dir, out)
        log(f"  best: n1={params.n1} n2={params.n2} tau_tool={params.tau_tool} tau_patch={params.tau_patch} "
            f"(OOF F1 {grid_result['best']['oof_f1']:.4f})")
        timer.lap("grid_search")
    else:
        params = PatchParams() if args.params is None else read_patch_params(args.params)

    hmm, hmm_ensemble, test_features = fit_hmm(study, params, label_params, args.cache_dir, out)
    timer.lap("features_and_hmm")
    rgb_method, paper_config, baseline_note = baseline_label(profile, args.weights)
    log(f"== RGB baseline: {baseline_note}")
    rgb, rgb_ensemble, rgb_raw, test_crops, checkpoint_dir = fit_baseline(study, profile, args, rgb_method, timer)
    timer.lap("baseline_prediction")

    methods = (hmm, rgb)
    thresholds = {m.name: m.threshold for m in methods}
    notes = [] if paper_config else [baseline_note]
    table = metrics_rows(study, methods)
    write_table1(out, table, [m.name for m in methods], thresholds, study.categories,
                 {s.name: str(s.root) for s in study.test}, notes)
    hmm_rows, rgb_rows = per_frame_rows(study, hmm, test_features, rgb, rgb_raw, test_crops)
    write_per_frame(out / "per_frame_hmm.csv", HMM_COLUMNS, hmm_rows)
    write_per_frame(out / "per_frame_rgb.csv", RGB_COLUMNS, rgb_rows)
    timer.lap("evaluation")

    frame_session, frame_index = figure_frame(study, args.figure_frame, test_features)
    figure_files, frame_info = write_figures(out, study, hmm, rgb, None if paper_config else baseline_note,
                                             frame_session, frame_index, params)
    timer.lap("figures")

    import matplotlib
    import torch

    config = {
        "contact_viz_version": __version__,
        "command": ["python", "recipes/reproduce_paper.py", *args.argv],
        "profile": profile.name, "quick": profile.name == "quick", "tiny": profile.name == "tiny",
        "sessions_dir": str(study.sessions_dir.resolve()), "split_file": str(study.split_path.resolve()),
        "split": {"train": list(study.split.train),
                  "test": [{"session": e.session, "category": e.category} for e in study.split.test]},
        "synthetic_study": study.synthetic,
        "patch_params": to_dict(params), "label_params": to_dict(label_params),
        "patch_params_source": "grid search" if args.grid_search else str(args.params) if args.params else "defaults",
        "grid_search": None if grid_result is None else {k: v for k, v in grid_result.items() if k != "points"},
        "hmm": {"method": hmm.name, "params": to_dict(hmm_ensemble.params), "threshold": hmm.threshold,
                "training_sessions": list(hmm_ensemble.session_names_), "model": str((out / "model.json").resolve())},
        "baseline": {"method": rgb.name, "paper_configuration": paper_config, "note": baseline_note,
                     "params": to_dict(profile.baseline), "init": rgb_ensemble.init_,
                     "weights": None if args.weights is None else str(args.weights.resolve()),
                     "device": str(rgb_ensemble.device), "threshold": rgb.threshold,
                     "platt": {"slope": rgb_ensemble.platt_.slope, "intercept": rgb_ensemble.platt_.intercept},
                     "checkpoints": str(checkpoint_dir.resolve())},
        "seeds": {"baseline": profile.baseline.seed,
                  "synthetic": None if study.synthetic is None else
                  {s["session"]: s["seed"] for s in study.synthetic["sessions"]}},
        "thresholds": thresholds,
        "pipeline_figure_frame": frame_info,
        "versions": {"python": platform.python_version(), "numpy": np.__version__, "torch": torch.__version__,
                     "matplotlib": matplotlib.__version__},
        "timings_s": {**timer.steps, "total": timer.total()},
    }
    write_json(out / "config.json", config)

    for m in methods:
        print(f"Table 1, {m.name} (threshold {m.threshold:.4f})")
        print(format_table({name: row[m.name] for name, row in table.items()}, style="text"))
    for note in notes + [n for row in table.values() for m in row.values() for n in m.get("notes", [])]:
        print(f"note: {note}")
    written = ["table1.md", "table1.tex", "table1.csv", *(p.name for p in figure_files), "per_frame_hmm.csv",
               "per_frame_rgb.csv", "config.json", "model.json", *(["grid_search.json"] if grid_result else [])]
    print(f"\nwrote to {out}/: {' '.join(written)}  ({timer.total():.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
