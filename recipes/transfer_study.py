"""The transfer study of issue 34: train the contact model in one domain, test it in others.

    python recipes/transfer_study.py                     # 3 draws, into .transfer/ (about 35 min on 2 cores)
    python recipes/transfer_study.py --draws 1 --frames 60 --hd-frames 60   # a quick look
    python recipes/transfer_study.py --dir .transfer --json results.json     # the figures as JSON too

Domains (one `contact-viz synth` group each, four sessions per draw: cup, kidney, liver, glove):

* ``640 rendered`` (the training domain): 640x360, synth's default camera (80 deg, 5 mm baseline,
  tissue at 90 mm), one instrument, the session's rendered depth/;
* ``640 SGBM``: the same sessions copied without depth/ (hard links), depth from the stereo pair;
* ``1080p rendered`` and ``1080p SGBM``: 1920x1080 (``--hd-frames`` frames);
* ``da Vinci rendered`` and ``da Vinci SGBM``: 640x360, ``--camera davinci`` (4.11 mm baseline, tissue
  at 50 mm: the close range of a real endoscope);
* ``2 instruments``: 640x360, ``--tools 2``, rendered depth (scored on the scene posterior).

For every model kind (contact_viz.model.emission.MODEL_KINDS) the LOSO ensemble is fitted as
`contact-viz fit --model-kind KIND` fits it (contact_viz.pipeline.features.fit_loso) and scored as
`contact-viz evaluate` scores (score_features, metrics_table). Leave one phantom out: each test
session (one phantom) is scored by the ensemble fitted on the training domain's sessions of the
three other phantoms (same draw), and by the oracle, the same kind fitted on the *test* domain's
sessions of those three phantoms: both see three sessions of the same phantoms, so the oracle
differs only in its domain. The training domain's own cell is its oracle. Per cell: the macro F1
and AUPRC over the four test sessions, mean and spread (min-max) over the draws.

Sessions and features are cached under ``--dir`` (sessions/, cache/), so a second run only fits.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from contact_viz.io.session import open_session
from contact_viz.synth.faults import without_depth
from contact_viz.model.emission import MODEL_KINDS, MONOTONE_KINDS
from contact_viz.model.evaluation import metrics_table
from contact_viz.model.hmm import HMMParams
from contact_viz.params import LabelParams, PatchParams
from contact_viz.pipeline.features import Features, fit_loso, score_features, session_features

PHANTOMS = ("cup", "kidney", "liver", "glove")  # one session of each per domain and draw
SEED_BASE = 3400  # synth seed = SEED_BASE + 100 * draw + 10 * group + phantom index


@dataclass(frozen=True)
class Group:
    """A set of synthetic sessions: what `contact-viz synth` is given."""

    name: str  # folder under DIR/sessions
    index: int  # its place in the seed
    hd: bool  # 1920x1080 (--hd-frames frames) instead of 640x360 (--frames frames)
    camera: str  # synth --camera preset
    tools: int  # synth --tools


@dataclass(frozen=True)
class Domain:
    """A test (or training) domain: a group's sessions with one depth source."""

    name: str  # column / row label
    group: Group
    sgbm: bool  # depth/ removed: depth from the stereo pair by SGBM


GROUPS = {g.name: g for g in (Group("640", 0, False, "default", 1), Group("1080p", 1, True, "default", 1),
                              Group("davinci", 2, False, "davinci", 1), Group("tools2", 3, False, "default", 2))}
DOMAINS = (
    Domain("640 rendered", GROUPS["640"], False),
    Domain("640 SGBM", GROUPS["640"], True),
    Domain("1080p rendered", GROUPS["1080p"], False),
    Domain("1080p SGBM", GROUPS["1080p"], True),
    Domain("da Vinci rendered", GROUPS["davinci"], False),
    Domain("da Vinci SGBM", GROUPS["davinci"], True),
    Domain("2 instruments", GROUPS["tools2"], False),
)
TRAIN_DOMAIN = DOMAINS[0].name


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def session_dir(directory: Path, group: Group, draw: int, phantom: str) -> Path:
    return directory / "sessions" / group.name / f"{group.name}_d{draw}_{phantom}"


def make_session(directory: Path, group: Group, draw: int, phantom: str, frames: int, hd_frames: int) -> Path:
    """Generate one session unless it is there with these settings (another setting is an error)."""
    from contact_viz.synth import SynthParams, generate_session
    from contact_viz.synth.camera import camera_fields

    out = session_dir(directory, group, draw, phantom)
    width, height, count = (1920, 1080, hd_frames) if group.hd else (640, 360, frames)
    seed = SEED_BASE + 100 * draw + 10 * group.index + PHANTOMS.index(phantom)
    params = SynthParams(phantom=phantom, frames=count, seed=seed, width=width, height=height, tools=group.tools,
                         **camera_fields(group.camera))
    info = out / "session.json"
    if info.is_file():
        g = json.loads(info.read_text()).get("generator", {})
        if (g.get("frames"), g.get("width"), g.get("height"), g.get("seed"), g.get("tools")) == (
                count, width, height, seed, group.tools):
            return out
        raise SystemExit(f"{out}: a session with other settings is there ({g.get('frames')} frames at "
                         f"{g.get('width')}x{g.get('height')}); choose another --dir")
    log(f"synth {out.name} ({phantom}, seed {seed}, {count} frames at {width}x{height}, camera {group.camera}, "
        f"{group.tools} instrument(s))")
    generate_session(out, params)
    return out


def stereo_only(src: Path, dst: Path) -> Path:
    """A copy of session ``src`` without depth/ (contact_viz.synth.faults.without_depth)."""
    return without_depth(src, dst)


def domain_sessions(directory: Path, domain: Domain, draw: int, frames: int, hd_frames: int) -> list[Path]:
    """The four session directories of ``domain`` in draw ``draw`` (generated / copied when missing)."""
    out = []
    for phantom in PHANTOMS:
        root = make_session(directory, domain.group, draw, phantom, frames, hd_frames)
        if domain.sgbm:
            root = stereo_only(root, directory / "stereo" / domain.group.name / root.name)
        out.append(root)
    return out


def domain_features(directory: Path, domain: Domain, draw: int, frames: int, hd_frames: int) -> list[Features]:
    """The features of a domain's four sessions in one draw (extracted once, cached in DIR/cache)."""
    out = []
    for root in domain_sessions(directory, domain, draw, frames, hd_frames):
        session = open_session(root, label_params=LabelParams(), cache_dir=directory / "cache")
        started = time.perf_counter()
        features = session_features(session, PatchParams(), LabelParams(), cache_dir=directory / "cache")
        if not features.cached:
            log(f"extract {domain.name}: {root.name}, {len(features.frames)} frames in "
                f"{time.perf_counter() - started:.0f} s")
        out.append(features)
    return out


SKIPPED: list[str] = []  # the fits that failed (a fold whose sessions never leave contact), one line each


def held_out(train: Sequence[Features], test: Sequence[Features], kind: str) -> dict[str, float]:
    """Macro F1 and AUPRC over the sessions of ``test``, session k scored by the LOSO ensemble of ``kind``
    fitted on every session of ``train`` but session k (the same phantom). A session whose ensemble cannot be
    fitted (`contact-viz fit` would refuse it: e.g. no transition out of contact in a fold) is left out of the
    mean and noted in SKIPPED."""
    scores = []
    for k, session in enumerate(test):
        try:
            ensemble = fit_loso([f for i, f in enumerate(train) if i != k], HMMParams(model_kind=kind))
        except ValueError as exc:
            SKIPPED.append(f"{kind}, {session.name} held out: {str(exc).split(': ', 1)[-1][:110]}")
            continue
        scores.append(metrics_table([score_features(ensemble.predict_proba, ensemble.threshold_, session)],
                                    ensemble.threshold_)[session.name])
    return {key: _mean([s[key] for s in scores if s[key] is not None]) for key in ("f1", "auprc")}


def _mean(values: Sequence[float]) -> float:
    """The mean of the finite ``values``; NaN when there is none."""
    finite = [float(v) for v in values if v is not None and np.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def run_study(features: dict[tuple[str, int], list[Features]], draws: int, kinds: Sequence[str]) -> dict:
    """{kind: {domain: {"transfer"|"oracle": {"f1"|"auprc": [value per draw]}}}}, leave one phantom out
    (``held_out``); the training domain's "transfer" is its oracle."""
    out: dict = {}
    for kind in kinds:
        out[kind] = {}
        for domain in DOMAINS:
            cell = {"transfer": {"f1": [], "auprc": []}, "oracle": {"f1": [], "auprc": []}}
            for draw in range(draws):
                test = features[domain.name, draw]
                oracle = held_out(test, test, kind)
                transfer = oracle if domain.name == TRAIN_DOMAIN else held_out(
                    features[TRAIN_DOMAIN, draw], test, kind)
                for what, values in (("transfer", transfer), ("oracle", oracle)):
                    for key in ("f1", "auprc"):
                        cell[what][key].append(values[key])
            out[kind][domain.name] = cell
    return out


def spread(values: Sequence[float]) -> str:
    """mean [min-max] over the draws with a value, 3 decimals (one draw: the value; fewer draws than given:
    "(k of n)"; none: "n/a")."""
    finite = [v for v in values if np.isfinite(v)]
    if not finite:
        return "n/a"
    text = f"{finite[0]:.3f}" if len(finite) == 1 else f"{np.mean(finite):.3f} [{min(finite):.2f}-{max(finite):.2f}]"
    return text if len(finite) == len(values) else f"{text} ({len(finite)} of {len(values)})"


def print_tables(results: dict, kinds: Sequence[str], draws: int) -> None:
    """Per metric a table: rows the model kinds, columns the domains; each cell "transfer" (trained in
    the training domain) and, below, the oracle (trained in the cell's domain); then the summary."""
    for key, title in (("f1", "macro F1"), ("auprc", "AUPRC")):
        print(f"\n{title}, trained on {TRAIN_DOMAIN} (leave one phantom out); "
              f"mean [min-max] over {draws} draw(s), 4 sessions each\n")
        print("| model | " + " | ".join(d.name for d in DOMAINS) + " |")
        print("|---" * (len(DOMAINS) + 1) + "|")
        for kind in kinds:
            print(f"| {kind} | " + " | ".join(spread(results[kind][d.name]["transfer"][key]) for d in DOMAINS) + " |")
        for kind in kinds:
            print(f"| oracle, {kind} | " + " | ".join(
                "(the column above)" if d.name == TRAIN_DOMAIN else spread(results[kind][d.name]["oracle"][key])
                for d in DOMAINS) + " |")
    print("\nsummary (means over the draws): training-domain F1; over the shifted cells: the mean F1, and the worst "
          "cell's F1 minus the paper's, minus its oracle's (same kind) and minus the best oracle's (any kind)\n")
    print("| model | monotone | training F1 | mean shifted F1 | min (F1 - paper's) | min (F1 - oracle's) "
          "| min (F1 - best oracle's) |")
    print("|---|---|---|---|---|---|---|")
    shifted = [d.name for d in DOMAINS if d.name != TRAIN_DOMAIN]

    def mean(kind: str, name: str, what: str = "transfer") -> float:
        return _mean(results[kind][name][what]["f1"])

    for kind in kinds:
        paper = "paper" if "paper" in results else kind
        vs_paper = np.nanmin([mean(kind, n) - mean(paper, n) for n in shifted])
        vs_oracle = np.nanmin([mean(kind, n) - mean(kind, n, "oracle") for n in shifted])
        vs_best = np.nanmin([mean(kind, n) - np.nanmax([mean(k, n, "oracle") for k in kinds]) for n in shifted])
        print(f"| {kind} | {'yes' if kind in MONOTONE_KINDS else 'no'} | {mean(kind, TRAIN_DOMAIN):.3f} | "
              f"{np.mean([mean(kind, n) for n in shifted]):.3f} | {vs_paper:+.3f} | {vs_oracle:+.3f} | "
              f"{vs_best:+.3f} |")


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dir", type=Path, default=Path(".transfer"), help="sessions and caches [.transfer]")
    parser.add_argument("--draws", type=int, default=3, help="draws (seeds) of every domain's sessions [3]")
    parser.add_argument("--frames", type=int, default=90, help="frames of a 640x360 session [90]")
    parser.add_argument("--hd-frames", type=int, default=90, help="frames of a 1920x1080 session [90]")
    parser.add_argument("--kinds", default=",".join(MODEL_KINDS),
                        help=f"model kinds, comma-separated [{','.join(MODEL_KINDS)}]")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = parser.parse_args(argv)
    kinds = [k.strip() for k in args.kinds.split(",") if k.strip()]
    unknown = [k for k in kinds if k not in MODEL_KINDS]
    if unknown or not kinds:
        parser.error(f"--kinds: expected some of {','.join(MODEL_KINDS)}, got {args.kinds!r}")
    if args.draws < 1 or args.frames < 30 or args.hd_frames < 30:
        parser.error("--draws must be >= 1 and --frames, --hd-frames >= 30")
    args.kinds = kinds
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    started = time.perf_counter()
    features = {}
    for draw in range(args.draws):
        for domain in DOMAINS:
            features[domain.name, draw] = domain_features(args.dir, domain, draw, args.frames, args.hd_frames)
    log(f"sessions and features ready in {time.perf_counter() - started:.0f} s")
    fitted = time.perf_counter()
    results = run_study(features, args.draws, args.kinds)
    log(f"fits and scores in {time.perf_counter() - fitted:.0f} s")
    print(f"transfer study: {args.draws} draw(s); 640x360 sessions {args.frames} frames, 1920x1080 "
          f"{args.hd_frames} frames; phantoms {', '.join(PHANTOMS)} per domain and draw")
    print_tables(results, args.kinds, args.draws)
    if SKIPPED:
        print(f"\n{len(SKIPPED)} held-out session(s) left out of their cell's mean, their ensemble not fittable:")
        for line in sorted(set(SKIPPED)):
            print(f"  {line}")
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
