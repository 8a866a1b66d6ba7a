"""The study's steps (paper, Sec. 3): open the sessions of a split, the features and the
leave-one-session-out HMM ensemble, and the RGB baseline under the same protocol.

Each step logs its progress to the ``contact_viz.paper`` logger (:func:`log_to_stderr` shows it).
"""

from __future__ import annotations

import hashlib
import json
import logging
import sys
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from contact_viz.baseline import BaselineEnsemble, BaselineParams, BaselineWarning, FoldEvent, SessionCrops
from contact_viz.io.cache import cache_key, default_cache_dir
from contact_viz.io.session import Session, open_session
from contact_viz.model.hmm import HMMParams, LosoEnsemble
from contact_viz.model.kinds import PAPER_KIND
from contact_viz.model.model_file import ContactModel, save_model
from contact_viz.paper.profiles import StudyProfile
from contact_viz.paper.study import Split, read_split
from contact_viz.paper.synthetic import synthetic_study
from contact_viz.params import LabelParams, PatchParams, to_dict
from contact_viz.pipeline.features import Features, fit_loso, score_features, session_features

log = logging.getLogger(__name__)
HMM_METHOD = "HMM"  # the HMM's method name in the table


def log_to_stderr() -> None:
    """Show the study's progress messages (the ``contact_viz.paper`` logger) on stderr, once."""
    logger = logging.getLogger("contact_viz.paper")
    if not any(getattr(h, "contact_viz_study", False) for h in logger.handlers):
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(message)s"))
        handler.contact_viz_study = True
        logger.addHandler(handler)
    logger.setLevel(logging.INFO)


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


def prepare_study(profile: StudyProfile, label_params: LabelParams, sessions_dir: Path | None = None,
                  split_path: Path | None = None, synthetic_dir: Path | None = None,
                  cache_dir: Path | None = None) -> Study:
    """Open every session of ``split_path`` (names relative to ``sessions_dir``); without them,
    generate (or reuse) the synthetic study of ``profile`` in ``synthetic_dir`` first."""
    synthetic = None
    if sessions_dir is None:
        log.info(f"== synthetic study ({profile.name}: {profile.n_train} train + {len(profile.test_phantoms)} test "
                 f"sessions, {profile.synth_frames} frames at {profile.synth_width}x{profile.synth_height}) "
                 f"in {synthetic_dir}")
        sessions_dir, split_path, specs = synthetic_study(synthetic_dir, profile)
        synthetic = {"directory": str(synthetic_dir.resolve()), "sessions": specs}
    split = read_split(split_path)

    def open_one(rel: str) -> Session:
        return open_session(sessions_dir / rel, label_params=label_params, cache_dir=cache_dir)

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


@dataclass
class HmmRun:
    """The HMM step's result: its held-out output, the fitted ensemble, the test sessions' features."""

    result: MethodResult
    ensemble: LosoEnsemble
    test_features: list[Features]


def _features(session: Session, params: PatchParams, label_params: LabelParams, cache_dir) -> Features:
    start = time.perf_counter()
    features = session_features(session, params, label_params, cache_dir=cache_dir)
    log.info(f"  features {session.name}: {len(features.frames)} frames" + (
        " (cached)" if features.cached else f" in {time.perf_counter() - start:.1f} s"))
    return features


def fit_hmm(study: Study, params: PatchParams, label_params: LabelParams, cache_dir, out: Path) -> HmmRun:
    """Features of every session, the LOSO HMM ensemble (saved as ``out/model.json``), its test posteriors."""
    log.info("== features (minimum-distance patch of every frame)")
    train = [_features(s, params, label_params, cache_dir) for s in study.train]
    test = [_features(s, params, label_params, cache_dir) for s in study.test]
    log.info("== LOSO HMM ensemble")
    # the paper's six-parameter HMM, whatever `contact-viz fit` defaults to; several instruments: one sequence each
    ensemble = fit_loso(train, HMMParams(model_kind=PAPER_KIND))
    model = ContactModel(ensemble=ensemble, patch_params=params, label_params=label_params,
                         training_sessions=tuple({"name": s.name, "path": str(s.root), "frames": len(s)}
                                                 for s in study.train))
    save_model(model, out / "model.json")
    log.info(f"  threshold {ensemble.threshold_:.4f}")
    for s, f in zip(study.test, test):
        if not np.array_equal(np.asarray(s.labels), f.labels):
            raise ValueError(f"{s.root}: the cached features' labels differ from the session's; clear the cache")
    threshold = float(ensemble.threshold_)
    result = MethodResult(HMM_METHOD, threshold,
                          [score_features(ensemble.predict_proba, threshold, f).posterior for f in test])
    return HmmRun(result, ensemble, test)


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


def _fold_progress(event: FoldEvent) -> None:
    loss = "" if event.loss is None else f", loss {event.loss:.4f}"
    log.info(f"  baseline fold {event.fold} (without {event.held_out}): {event.stage} {event.epoch}{loss}")


@dataclass
class BaselineRun:
    """The baseline step's result."""

    result: MethodResult
    ensemble: BaselineEnsemble
    raw: list[np.ndarray]  # per test session, (T,) raw scores (logit differences)
    test_crops: list[SessionCrops]
    checkpoint_dir: Path
    paper_configuration: bool  # the paper's configuration (full profile, ImageNet weights)
    note: str  # one line on the configuration, for the outputs


def fit_baseline(study: Study, profile: StudyProfile, out: Path, weights: Path | None = None,
                 device: str | None = None, cache_dir: Path | None = None, timer: Timer | None = None) -> BaselineRun:
    """Tool-tip crops, the LOSO EfficientNet ensemble (checkpoints in ``out/baseline/<key>``, resumed),
    its test posteriors."""
    from contact_viz.baseline import extract_crops, fit_loso

    method, paper_configuration, note = baseline_label(profile, weights)
    log.info(f"== RGB baseline: {note}")
    crop_cache = cache_dir if cache_dir is not None else default_cache_dir()
    train_crops = [extract_crops(s, profile.baseline.crop_px, cache_dir=crop_cache) for s in study.train]
    test_crops = [extract_crops(s, profile.baseline.crop_px, cache_dir=crop_cache) for s in study.test]
    if timer is not None:
        timer.lap("baseline_crops")
    checkpoint_dir = out / "baseline" / checkpoint_key(profile.baseline, weights, study.train)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BaselineWarning)  # training from scratch: said in every output instead
        ensemble = fit_loso(train_crops, profile.baseline, checkpoint_dir, weights=weights, device=device,
                            progress=_fold_progress)
    if timer is not None:
        timer.lap("baseline_training")
    raw = [ensemble.predict_raw(c) for c in test_crops]
    log.info(f"  threshold {ensemble.threshold_:.4f}")
    result = MethodResult(method, float(ensemble.threshold_), [ensemble.platt_(r) for r in raw])
    return BaselineRun(result, ensemble, raw, test_crops, checkpoint_dir, paper_configuration, note)
