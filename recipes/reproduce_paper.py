"""Reproduce the paper's study on your sessions with one command: Table 1, the timelines and pipeline figures.

    python recipes/reproduce_paper.py                       # the synthetic study, full configuration
    python recipes/reproduce_paper.py --quick -o /tmp/paper # the synthetic study in a few minutes
    python recipes/reproduce_paper.py SESSIONS SPLIT.json -o results/paper --grid-search --weights b3.pth

Without SESSIONS and SPLIT the synthetic study of scripts/demo.sh is generated into
<output>/synthetic (or --synthetic-dir) and run. The steps, the split file's format, the
configurations and the outputs (table1.*, timelines.*, pipeline.*, per_frame_*.csv, config.json,
model.json, grid_search.json, baseline/) are described in contact_viz.paper.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from contact_viz.errors import SessionError
from contact_viz.paper.figures import figure_frame, write_figures
from contact_viz.paper.grid_search import run_grid_search
from contact_viz.paper.profiles import study_profile
from contact_viz.paper.protocol import Timer, fit_baseline, fit_hmm, log_to_stderr, prepare_study
from contact_viz.paper.results import summary_lines, write_config, write_results
from contact_viz.params import LabelParams, PatchParams, read_patch_params


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="See contact_viz.paper for the split file format and the outputs.")
    parser.add_argument("sessions", type=Path, nargs="?",
                        help="folder of session directories (omit for the synthetic study)")
    parser.add_argument("split", type=Path, nargs="?", help="split JSON (train / test with categories)")
    parser.add_argument("-o", "--output", type=Path, default=Path("results/paper"),
                        help="results folder [results/paper]")
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


def run(args: argparse.Namespace, argv: list[str]) -> int:
    timer = Timer()
    profile = study_profile("tiny" if args.tiny else "quick" if args.quick else "full", seed=args.seed)
    out: Path = args.output
    out.mkdir(parents=True, exist_ok=True)
    label_params = LabelParams(contact_force_n=args.contact_force)
    study = prepare_study(profile, label_params, args.sessions, args.split,
                          args.synthetic_dir or out / "synthetic", args.cache_dir)
    timer.lap("study")

    grid_result = None
    if args.grid_search:
        print(f"== grid search on {len(study.train)} training sessions", file=sys.stderr)
        params, grid_result = run_grid_search([s.root for s in study.train], profile.grid, args.cache_dir, out)
        print(f"  best: n1={params.n1} n2={params.n2} tau_tool={params.tau_tool} tau_patch={params.tau_patch} "
              f"(OOF F1 {grid_result['best']['oof_f1']:.4f})", file=sys.stderr)
        timer.lap("grid_search")
    else:
        params = PatchParams() if args.params is None else read_patch_params(args.params)

    hmm = fit_hmm(study, params, label_params, args.cache_dir, out)
    timer.lap("features_and_hmm")
    rgb = fit_baseline(study, profile, out, args.weights, args.device, args.cache_dir, timer)
    timer.lap("baseline_prediction")
    table = write_results(out, study, hmm, rgb)
    timer.lap("evaluation")

    frame_session, frame_index = figure_frame(study, args.figure_frame, hmm.test_features)
    figure_files, frame_info = write_figures(out, study, hmm.result, rgb.result,
                                             None if rgb.paper_configuration else rgb.note,
                                             frame_session, frame_index, params)
    timer.lap("figures")
    source = "grid search" if args.grid_search else str(args.params) if args.params else "defaults"
    write_config(out, ["python", "recipes/reproduce_paper.py", *argv], profile, study, params, label_params, source,
                 grid_result, hmm, rgb, args.weights, frame_info, timer)

    print("\n".join(summary_lines(table, hmm, rgb)))
    written = ["table1.md", "table1.tex", "table1.csv", *(p.name for p in figure_files), "per_frame_hmm.csv",
               "per_frame_rgb.csv", "config.json", "model.json", *(["grid_search.json"] if grid_result else [])]
    print(f"\nwrote to {out}/: {' '.join(written)}  ({timer.total():.0f} s)")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    log_to_stderr()
    try:
        return run(args, list(sys.argv[1:] if argv is None else argv))
    except (ValueError, SessionError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr, flush=True)
        return 1


if __name__ == "__main__":
    sys.exit(main())
