"""Detection table of the diagnostics: each failure injected into synthetic sessions, and false alarms.

    python benchmarks/bench_diagnostics.py                       # seeds 100-101, every phantom, 84 frames (one whole contact)
    python benchmarks/bench_diagnostics.py --seeds 100,101,102 --size 320x180 --frames 84
    python benchmarks/bench_diagnostics.py --two-tools 160       # also two-instrument sessions (id swaps, merges)
    python benchmarks/bench_diagnostics.py --elevations 5,8,15   # also clean sessions with shallow shafts

For every phantom and session seed it renders a clean session (`contact-viz synth`), runs
`contact-viz check` on it (false alarms: frames on which any check fired), then injects each of
the ten failures (contact_viz.synth.faults) once while approaching and once in contact (random
window, severity and timing from the seed; contact_viz.synth.fault_study) and prints per kind:
frames flagged / injected in each phase, how many injections met the target (flagged on >= 90% of
the injected frames or within 2 frames of onset) and the checks that fired. The thresholds were
chosen on seed 0 sessions; the default seeds here were not used for that.

``--two-tools FRAMES`` adds a session of two instruments (``SynthParams(tools=2)``, that many frames)
per phantom and seed: its false alarms, and the two failures only such masks have (``id_swap``,
``tools_merged``) injected into it like the others. ``--elevations`` adds clean sessions whose shafts
lie that many degrees above the tissue (``SynthParams(shaft_elevation_deg=...)``) and prints the share
of their frames flagged, per elevation and check (a phantom where the generator finds no pose is
left out and named).
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
from contact_viz.synth.faults import FAULT_KINDS, MULTI_FAULT_KINDS  # noqa: E402
from contact_viz.checks.params import DiagnosticParams  # noqa: E402
from contact_viz.pipeline.check import check_session  # noqa: E402


def _study(args):
    session, work, seed, params, kinds = args
    clean = check_session(session, params=params)
    phantom = PHANTOMS.index(Path(session).name.split("_")[0])
    outcomes = [inject_and_check(session, work, kind, seed=(seed * 10 + phantom) * 100 + k, params=params)
                for k, kind in kinds]
    return session, clean, outcomes


def _make(job):
    """make_session_job, or the reason the generator gave up (a pose it cannot find at that elevation)."""
    try:
        return make_session_job(job), None
    except RuntimeError as exc:
        return None, f"{Path(job[0]).name}: {exc}"


def _false_alarms(results) -> tuple[int, int, dict[str, int]]:
    total = sum(clean.n_frames for _, clean, _ in results)
    false = sum(len(flagged_frames(clean)) for _, clean, _ in results)
    codes: dict[str, int] = {}
    for _, clean, _ in results:
        for code, n in clean.counts.items():
            codes[code] = codes.get(code, 0) + n
    return false, total, codes


def _print_table(outcomes) -> None:
    rows = detection_table(outcomes)
    print("| failure | approach: flagged / injected frames | contact: flagged / injected frames | "
          "injections meeting the target (approach, contact) | checks that fired most |")
    print("|---|---|---|---|---|")
    for r in rows:
        a = f"{r['approach_flagged']} / {r['approach_injected']} ({r['approach_flagged'] / r['approach_injected']:.0%})"
        c = f"{r['contact_flagged']} / {r['contact_injected']} ({r['contact_flagged'] / r['contact_injected']:.0%})"
        print(f"| {r['kind']} | {a} | {c} | {r['approach_detected']}/{r['injections']}, "
              f"{r['contact_detected']}/{r['injections']} | {r['checks']} |")


def _print_false_alarms(label: str, results) -> None:
    false, total, codes = _false_alarms(results)
    print(f"\nfalse alarms on the {label}: {false} of {total} frames ({false / max(total, 1):.1%})"
          + (f"; by check: {', '.join(f'{c} {n}' for c, n in codes.items())}" if codes else ""))
    for session, clean, _ in results:
        if clean.fired:
            print(f"  {Path(session).name}: " + "; ".join(f"{code} at {', '.join(f'{x}-{y}' for x, y in r)}"
                                                         for code, r in clean.fired.items()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="100,101", help="session seeds, comma-separated (not the tuning seed 0)")
    parser.add_argument("--phantoms", default=",".join(PHANTOMS))
    parser.add_argument("--frames", type=int, default=84)
    parser.add_argument("--size", default="320x180")
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--analysis-width", type=int, default=DiagnosticParams().analysis_width_px,
                        help="DiagnosticParams.analysis_width_px: the checks run on every n-th pixel above this width")
    parser.add_argument("--two-tools", type=int, default=0, metavar="FRAMES",
                        help="also two-instrument sessions of this many frames (0 = none): false alarms, id swaps, "
                             "merges")
    parser.add_argument("--elevations", default="", help="also clean sessions with the shafts this many degrees "
                                                         "above the tissue, comma-separated (e.g. 5,8,15)")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    seeds = [int(s) for s in args.seeds.split(",")]
    phantoms = args.phantoms.split(",")
    elevations = [float(e) for e in args.elevations.split(",") if e]
    started = time.perf_counter()
    params = DiagnosticParams(analysis_width_px=args.analysis_width)
    single = list(enumerate(FAULT_KINDS))
    multi = [(len(FAULT_KINDS) + k, kind) for k, kind in enumerate(MULTI_FAULT_KINDS)]
    with tempfile.TemporaryDirectory(prefix="bench_diagnostics_") as tmp:
        jobs = [(Path(tmp) / f"{p}_{s}", p, s, args.frames, width, height) for s in seeds for p in phantoms]
        two_jobs = [(Path(tmp) / f"{p}_{s}_two", p, s, args.two_tools, width, height, 2)
                    for s in seeds for p in phantoms] if args.two_tools else []
        tilt_jobs = [(Path(tmp) / f"{p}_{s}_e{e:g}", p, s, args.frames, width, height, 1, e)
                     for e in elevations for s in seeds for p in phantoms]
        work = Path(tmp) / "work"
        work.mkdir()
        with ProcessPoolExecutor(args.processes) as pool:
            sessions = list(pool.map(make_session_job, jobs))
            results = list(pool.map(_study, [(s, work, job[2], params, single) for s, job in zip(sessions, jobs)]))
            two = list(pool.map(make_session_job, two_jobs))
            two_results = list(pool.map(_study, [(s, work, job[2], params, multi) for s, job in zip(two, two_jobs)]))
            tilted = list(pool.map(_make, tilt_jobs))
            made = [(s, job) for (s, _), job in zip(tilted, tilt_jobs) if s is not None]
            tilt_results = list(pool.map(_study, [(s, work, job[2], params, []) for s, job in made]))
    outcomes = [o for _, _, os_ in results for o in os_]
    print(f"{len(sessions)} sessions ({', '.join(phantoms)}; seeds {args.seeds}; {args.frames} frames at {args.size}; "
          f"checks at 1/{-(-width // args.analysis_width)} resolution), "
          f"{len(outcomes)} injected sessions, {time.perf_counter() - started:.0f} s\n")
    _print_table(outcomes)
    _print_false_alarms("clean sessions", results)
    misses = [o for o in outcomes if any(len(o.flagged[ph]) < 0.9 * len(o.injected[ph])
                                         for ph in ("approach", "contact"))]
    for o in misses[:20]:
        print(f"  below 90%: {o.kind} in {o.session} severity {o.severity:g}: "
              f"approach {len(o.flagged['approach'])}/{len(o.injected['approach'])}, "
              f"contact {len(o.flagged['contact'])}/{len(o.injected['contact'])}")
    if two_results:
        multi_outcomes = [o for _, _, os_ in two_results for o in os_]
        print(f"\n{len(two)} two-instrument sessions ({args.two_tools} frames), {len(multi_outcomes)} injected "
              "sessions\n")
        _print_table(multi_outcomes)
        _print_false_alarms("clean two-instrument sessions", two_results)
    if tilt_jobs:
        print("\nclean sessions with shallow shafts (shaft_elevation_deg): frames flagged")
        print("| elevation | sessions | flagged / frames | by check |")
        print("|---|---|---|---|")
        for e in elevations:
            mine = [r for r, (_, job) in zip(tilt_results, made) if job[7] == e]
            false, total, codes = _false_alarms(mine)
            print(f"| {e:g} deg | {len(mine)} | {false} / {total} ({false / max(total, 1):.1%}) | "
                  f"{', '.join(f'{c} {n}' for c, n in codes.items()) or '-'} |")
        for _, reason in tilted:
            if reason is not None:
                print(f"  not generated: {reason}")


if __name__ == "__main__":
    main()
