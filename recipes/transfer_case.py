"""Issue 34's out-of-domain case: a model fitted on three 640x360 cup sessions with rendered depth, run on
a 1080p kidney session whose depth comes from SGBM (`synth --phantom kidney --size 1920x1080 --frames 40
--seed 8`, depth/ removed). Its contact frames read about 0.1 mm (the signal's cap, 4.0): the paper's
model, whose contact state has the smaller variance, calls that evidence of no contact.

    python recipes/transfer_case.py                  # into .transfer_case/ (about 4 min on 2 cores)
    python recipes/transfer_case.py --dir /tmp/case  # sessions and features cached there

Prints, per model kind: the contact frames called in contact, the frames called in contact without
contact, the session's F1, the threshold, the posterior on the contact frames and the evidence there (log-likelihood ratio).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from contact_viz.io.session import open_session
from contact_viz.model.hmm import HMMParams
from contact_viz.model.kinds import MODEL_KINDS
from contact_viz.params import LabelParams, PatchParams
from contact_viz.pipeline.features import fit_loso, session_features
from contact_viz.synth import SynthParams, generate_session
from contact_viz.synth.faults import without_depth

TRAIN_SEEDS = (1, 2, 3)  # the three 640x360 cup sessions (rendered depth, 90 frames each)
TEST = dict(phantom="kidney", frames=40, seed=8, width=1920, height=1080)  # the shifted session, as the issue


def session(directory: Path, name: str, params: SynthParams) -> Path:
    out = directory / "sessions" / name
    if not (out / "session.json").is_file():
        print(f"synth {name}", file=sys.stderr, flush=True)
        generate_session(out, params)
    return out


def features(root: Path, cache: Path):
    opened = open_session(root, label_params=LabelParams(), cache_dir=cache)
    return session_features(opened, PatchParams(), LabelParams(), cache_dir=cache)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dir", type=Path, default=Path(".transfer_case"), help="sessions and caches")
    args = parser.parse_args(argv)
    cache = args.dir / "cache"
    train = [features(session(args.dir, f"cup640_s{s}", SynthParams(phantom="cup", frames=90, seed=s, width=640,
                                                                     height=360)), cache) for s in TRAIN_SEEDS]
    rendered = session(args.dir, "kidney1080_s8", SynthParams(**TEST))
    test = features(without_depth(rendered, args.dir / "stereo" / "kidney1080_s8"), cache)
    contact = test.labels == 1
    print(f"kidney 1920x1080 seed 8, SGBM depth: {int(contact.sum())} contact frames of {len(test.labels)}; "
          f"median signal there {np.nanmedian(test.signal[contact]):.2f} (cap 4.0)")
    print("| model | contact frames called | false calls | F1 | threshold | posterior on contact frames (min, median) "
          "| evidence there (median) |")
    print("|---|---|---|---|---|---|---|")
    for kind in MODEL_KINDS:
        ensemble = fit_loso(train, HMMParams(model_kind=kind))
        called = ensemble.predict(test.signal)
        hits, false = int((called & contact).sum()), int((called & (test.labels == 0)).sum())
        f1 = 2 * hits / (2 * hits + false + int((~called & contact).sum()))
        evidence = np.nanmedian(ensemble.log_likelihood_ratio(test.signal)[contact])
        posterior = ensemble.predict_proba(test.signal)[contact]
        print(f"| {kind} | {hits} of {int(contact.sum())} | {false} | {f1:.3f} | {ensemble.threshold_:.3f} | "
              f"{posterior.min():.3f}, {np.median(posterior):.3f} | {evidence:+.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
