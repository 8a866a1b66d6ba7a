"""Choose N1, N2, tau_tool and tau_patch jointly on the training sessions only (paper, Sec. 2.1).

Every grid point is scored by the pooled out-of-fold F1 of the leave-one-session-out HMM
ensemble (AUPRC breaks ties); see contact_viz.paper.grid_search for how the grid is computed and
cached. The best point is written as a --params file for `fit`, `extract`, `view` and
recipes/reproduce_paper.py.

    python recipes/grid_search.py demo/sessions/cup_train_* -o demo/best_params.json
    contact-viz fit demo/sessions/cup_train_* --params demo/best_params.json -o demo/model.json
"""

from __future__ import annotations

import argparse
from pathlib import Path

from contact_viz.paper.grid_search import DEFAULT_GRID, build_grid, score_grid, write_best_params
from contact_viz.params import PatchParams
from contact_viz.pipeline.engines import LocalEngine, RayEngine


def ints(text: str) -> list[int]:
    return [int(v) for v in text.split(",")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sessions", type=Path, nargs="+", help="training session directories (K >= 2)")
    parser.add_argument("-o", "--output", type=Path, default=Path("best_params.json"))
    n1s, n2s, tau_tools, tau_patches = (list(values) for values in DEFAULT_GRID)
    parser.add_argument("--n1", type=ints, default=n1s, help="N1 window sides, px")
    parser.add_argument("--n2", type=ints, default=n2s, help="N2 window sides, px")
    parser.add_argument("--tau-tool", type=ints, default=tau_tools, help="tau_tool values, pixels")
    parser.add_argument("--tau-patch", type=ints, default=tau_patches, help="tau_patch values, distances")
    parser.add_argument("--cache-dir", type=Path, default=None)
    parser.add_argument("--processes", type=int, default=None, help="local processes [default: one per core]")
    parser.add_argument("--ray", action="store_true", help="spread the work over a local Ray started on the fly")
    parser.add_argument("--ray-address", default=None, help="spread the work over an existing Ray cluster "
                        "(auto, or ray://HOST:10001; the sessions must be at the same path on every node)")
    args = parser.parse_args()
    if len(args.sessions) < 2:
        parser.error("leave-one-session-out needs at least 2 training sessions")

    values = (args.n1, args.n2, args.tau_tool, args.tau_patch)
    grid, skipped = build_grid(*values, base=PatchParams())
    for note in skipped:
        print(f"skipped: {note}")
    try:
        engine = (RayEngine(address=args.ray_address) if args.ray or args.ray_address
                  else LocalEngine(args.processes))
    except RuntimeError as exc:
        raise SystemExit(f"error: {exc}") from None
    try:
        results = score_grid([s.resolve() for s in args.sessions], grid, args.cache_dir, engine=engine)
    except ValueError as exc:
        raise SystemExit(str(exc)) from None
    finally:
        engine.close()

    print(f"\n{'N1':>4} {'N2':>4} {'tau_tool':>8} {'tau_patch':>9} {'OOF F1':>8} {'OOF AUPRC':>10} {'found':>6}")
    for r in results:
        p = r.params
        print(f"{p.n1:>4} {p.n2:>4} {p.tau_tool:>8} {p.tau_patch:>9} {r.oof_f1:>8.4f} {r.oof_auprc:>10.4f} "
              f"{r.found:>6.1%}")
    write_best_params(args.output, results, args.sessions, values, len(grid))
    best = results[0]
    p = best.params
    print(f"\nbest: n1={p.n1} n2={p.n2} tau_tool={p.tau_tool} tau_patch={p.tau_patch} "
          f"(OOF F1 {best.oof_f1:.4f}, AUPRC {best.oof_auprc:.4f}) -> {args.output}")


if __name__ == "__main__":  # the guard spawned worker processes need
    main()
