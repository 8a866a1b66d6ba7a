"""Detection table of the diagnostics: each failure injected into synthetic sessions, and false alarms.

    python benchmarks/bench_diagnostics.py                       # seeds 100-101, every phantom, 84 frames (one whole contact)
    python benchmarks/bench_diagnostics.py --seeds 100,101,102 --size 320x180 --frames 84

For every phantom and session seed it renders a clean session (`contact-viz synth`), runs
`contact-viz check` on it (false alarms: frames on which any check fired), then injects each of
the ten failures (contact_viz.synth.faults) once while approaching and once in contact (random
window, severity and timing from the seed; contact_viz.synth.fault_study) and prints per kind:
frames flagged / injected in each phase, how many injections met the target (flagged on >= 90% of
the injected frames or within 2 frames of onset) and the checks that fired. The thresholds were
chosen on seed 0 sessions; the default seeds here were not used for that.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from contact_viz.synth import PHANTOMS  # noqa: E402
from contact_viz.synth.fault_study import (detection_table, flagged_frames, inject_and_check,  # noqa: E402
                                           make_session_job)
from contact_viz.synth.faults import FAULT_KINDS  # noqa: E402
from contact_viz.checks.params import DiagnosticParams  # noqa: E402
from contact_viz.pipeline.check import check_session  # noqa: E402


def _study(args):
    session, work, seed, params = args
    clean = check_session(session, params=params)
    phantom = PHANTOMS.index(Path(session).name.split("_")[0])
    outcomes = [inject_and_check(session, work, kind, seed=(seed * 10 + phantom) * 100 + k, params=params)
                for k, kind in enumerate(FAULT_KINDS)]
    return session, clean, outcomes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="100,101", help="session seeds, comma-separated (not the tuning seed 0)")
    parser.add_argument("--phantoms", default=",".join(PHANTOMS))
    parser.add_argument("--frames", type=int, default=84)
    parser.add_argument("--size", default="320x180")
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--analysis-width", type=int, default=DiagnosticParams().analysis_width_px,
                        help="DiagnosticParams.analysis_width_px: the checks run on every n-th pixel above this width")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    seeds = [int(s) for s in args.seeds.split(",")]
    phantoms = args.phantoms.split(",")
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_diagnostics_") as tmp:
        jobs = [(Path(tmp) / f"{p}_{s}", p, s, args.frames, width, height) for s in seeds for p in phantoms]
        with ProcessPoolExecutor(args.processes) as pool:
            sessions = list(pool.map(make_session_job, jobs))
            work = Path(tmp) / "work"
            work.mkdir()
            params = DiagnosticParams(analysis_width_px=args.analysis_width)
            results = list(pool.map(_study, [(s, work, job[2], params) for s, job in zip(sessions, jobs)]))
    outcomes = [o for _, _, os_ in results for o in os_]
    print(f"{len(sessions)} sessions ({', '.join(phantoms)}; seeds {args.seeds}; {args.frames} frames at {args.size}; "
          f"checks at 1/{-(-width // args.analysis_width)} resolution), "
          f"{len(outcomes)} injected sessions, {time.perf_counter() - started:.0f} s\n")
    rows = detection_table(outcomes)
    print("| failure | approach: flagged / injected frames | contact: flagged / injected frames | "
          "injections meeting the target (approach, contact) | checks that fired most |")
    print("|---|---|---|---|---|")
    for r in rows:
        a = f"{r['approach_flagged']} / {r['approach_injected']} ({r['approach_flagged'] / r['approach_injected']:.0%})"
        c = f"{r['contact_flagged']} / {r['contact_injected']} ({r['contact_flagged'] / r['contact_injected']:.0%})"
        print(f"| {r['kind']} | {a} | {c} | {r['approach_detected']}/{r['injections']}, "
              f"{r['contact_detected']}/{r['injections']} | {r['checks']} |")
    total = sum(clean.n_frames for _, clean, _ in results)
    false = sum(len(flagged_frames(clean)) for _, clean, _ in results)
    codes: dict[str, int] = {}
    for _, clean, _ in results:
        for code, n in clean.counts.items():
            codes[code] = codes.get(code, 0) + n
    print(f"\nfalse alarms on the clean sessions: {false} of {total} frames ({false / total:.1%})"
          + (f"; by check: {', '.join(f'{c} {n}' for c, n in codes.items())}" if codes else ""))
    for session, clean, _ in results:
        if clean.fired:
            print(f"  {Path(session).name}: " + "; ".join(f"{code} at {', '.join(f'{x}-{y}' for x, y in r)}"
                                                         for code, r in clean.fired.items()))
    misses = [o for o in outcomes if any(len(o.flagged[ph]) < 0.9 * len(o.injected[ph])
                                         for ph in ("approach", "contact"))]
    for o in misses[:20]:
        print(f"  below 90%: {o.kind} in {o.session} severity {o.severity:g}: "
              f"approach {len(o.flagged['approach'])}/{len(o.injected['approach'])}, "
              f"contact {len(o.flagged['contact'])}/{len(o.injected['contact'])}")


if __name__ == "__main__":
    main()
