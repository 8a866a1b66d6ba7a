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

``--compare-strict`` measures every session twice: with the checks as they are, and strict, as they
decided before they had margins (DiagnosticParams margin 0: each check decides at its threshold;
patch_place False: the patch's move measured between its centres; distance_jump at 5 mm + 20%), and
prints both tables. ``--perturb REL`` also checks a copy of every clean and injected
session whose depth is changed by up to REL relative and 2% of whose image pixels move one grey level
(contact_viz.synth.faults.perturb_session: what another processor does to a synthetic session, or more),
and prints how many decisions (check, instrument, frame) that flips: a decision on a knife's edge.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from contact_viz.synth import PHANTOMS  # noqa: E402
from contact_viz.synth.fault_study import (decisions, detection_table, flagged_frames, inject,  # noqa: E402
                                           make_session_job, outcome)
from contact_viz.synth.faults import FAULT_KINDS, MULTI_FAULT_KINDS, perturb_session  # noqa: E402
from contact_viz.checks.params import DiagnosticParams  # noqa: E402
from contact_viz.pipeline.check import check_session  # noqa: E402


def _flips(path: Path, reports, variants, perturb: float) -> list[tuple[int, int, dict[str, int]]]:
    """Per variant: (decisions the perturbed copy of ``path`` changes, decisions, the changed ones per check), or []
    without ``perturb``."""
    if not perturb:
        return []
    copy = path.with_name(path.name + "_perturbed")
    perturb_session(path, copy, depth_rel=perturb, seed=len(path.name))
    try:
        again = [check_session(copy, params=params) for params in variants]
    finally:
        shutil.rmtree(copy, ignore_errors=True)
    out = []
    for a, b in zip(reports, again):
        changed = decisions(a) ^ decisions(b)
        out.append((len(changed), len(decisions(a) | decisions(b)), dict(Counter(code for code, _, _ in changed))))
    return out


def _study(args):
    """Per variant of the parameters: the clean session's report and the outcomes of the injections; the
    decisions a perturbation flips, clean and injected sessions pooled, per variant."""
    session, work, seed, variants, kinds, perturb = args
    clean = [check_session(session, params=params) for params in variants]
    flips = [_flips(Path(session), clean, variants, perturb)]
    phantom = PHANTOMS.index(Path(session).name.split("_")[0])
    outcomes = [[] for _ in variants]
    for k, kind in kinds:
        injection = inject(session, work, kind, seed=(seed * 10 + phantom) * 100 + k)
        try:
            reports = [check_session(injection.path, params=params) for params in variants]
            flips.append(_flips(injection.path, reports, variants, perturb))
        finally:
            shutil.rmtree(injection.path, ignore_errors=True)
        for mine, report in zip(outcomes, reports):
            mine.append(outcome(injection, report))
    pooled = [(sum(f[v][0] for f in flips), sum(f[v][1] for f in flips),
               sum((Counter(f[v][2]) for f in flips), Counter())) for v in range(len(variants))] if perturb else []
    return session, clean, outcomes, pooled


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


def _variant(results, v: int) -> list:
    """(session, clean report, outcomes) of parameter variant ``v`` from _study's results."""
    return [(session, clean[v], outcomes[v]) for session, clean, outcomes, _ in results]


def _print_flips(label: str, results, v: int) -> None:
    pooled = [flips[v] for _, _, _, flips in results if flips]
    if pooled:
        changed, total = sum(f[0] for f in pooled), sum(f[1] for f in pooled)
        codes = sum((Counter(f[2]) for f in pooled), Counter())
        print(f"decisions (check, instrument, frame) flipped by the perturbation ({label} and their injected copies): "
              f"{changed} of {total}" + (f"; by check: {', '.join(f'{c} {n}' for c, n in codes.most_common())}"
                                         if codes else ""))


def _report(label: str, results, v: int, title: str) -> None:
    mine = _variant(results, v)
    outcomes = [o for _, _, os_ in mine for o in os_]
    if outcomes:
        print(f"{title}\n")
        _print_table(outcomes)
    _print_false_alarms(label, mine)
    _print_flips(label, results, v)
    return outcomes


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
    parser.add_argument("--compare-strict", action="store_true",
                        help="also measure the checks without their margins (as they decided before), side by side")
    parser.add_argument("--perturb", type=float, default=0.0, metavar="REL",
                        help="also check copies with the depth changed by up to REL relative and 2%% of the image "
                             "pixels by one grey level; print the decisions that flips (e.g. 1e-5)")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    seeds = [int(s) for s in args.seeds.split(",")]
    phantoms = args.phantoms.split(",")
    elevations = [float(e) for e in args.elevations.split(",") if e]
    started = time.perf_counter()
    params = DiagnosticParams(analysis_width_px=args.analysis_width)
    strict = replace(params, margin=0.0, patch_place=False, distance_jump_m=0.005, distance_jump_rel=0.2)
    variants = [params] + ([strict] if args.compare_strict else [])
    labels = ["with margins" if args.compare_strict else "", "strict"]
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

        def study(made, kinds):
            return list(pool.map(_study, [(s, work, job[2], variants, kinds, args.perturb) for s, job in made]))

        with ProcessPoolExecutor(args.processes) as pool:
            sessions = list(pool.map(make_session_job, jobs))
            results = study(zip(sessions, jobs), single)
            two = list(pool.map(make_session_job, two_jobs))
            two_results = study(zip(two, two_jobs), multi)
            tilted = list(pool.map(_make, tilt_jobs))
            made = [(s, job) for (s, _), job in zip(tilted, tilt_jobs) if s is not None]
            tilt_results = study(made, [])
    print(f"{len(sessions)} sessions ({', '.join(phantoms)}; seeds {args.seeds}; {args.frames} frames at {args.size}; "
          f"checks at 1/{-(-width // args.analysis_width)} resolution), "
          f"{len(results[0][2][0]) * len(results) if results else 0} injected sessions"
          f"{f', perturbed by {args.perturb:g}' if args.perturb else ''}, {time.perf_counter() - started:.0f} s\n")
    for v, label in enumerate(labels[:len(variants)]):
        if label:
            p = variants[v]
            print(f"\n## {label}: margin {p.margin:g}, patch_place {p.patch_place}, distance_jump "
                  f"{1000 * p.distance_jump_m:g} mm + {p.distance_jump_rel:.0%}\n")
        outcomes = _report("clean sessions", results, v, "")
        misses = [o for o in outcomes if any(len(o.flagged[ph]) < 0.9 * len(o.injected[ph])
                                             for ph in ("approach", "contact"))]
        for o in misses[:20]:
            print(f"  below 90%: {o.kind} in {o.session} severity {o.severity:g}: "
                  f"approach {len(o.flagged['approach'])}/{len(o.injected['approach'])}, "
                  f"contact {len(o.flagged['contact'])}/{len(o.injected['contact'])}")
        if two_results:
            print(f"\n{len(two)} two-instrument sessions ({args.two_tools} frames)")
            _report("clean two-instrument sessions", two_results, v, "")
        if tilt_jobs:
            print("\nclean sessions with shallow shafts (shaft_elevation_deg): frames flagged")
            print("| elevation | sessions | flagged / frames | by check |")
            print("|---|---|---|---|")
            for e in elevations:
                mine = [r for r, (_, job) in zip(_variant(tilt_results, v), made) if job[7] == e]
                false, total, codes = _false_alarms(mine)
                print(f"| {e:g} deg | {len(mine)} | {false} / {total} ({false / max(total, 1):.1%}) | "
                      f"{', '.join(f'{c} {n}' for c, n in codes.items()) or '-'} |")
            _print_flips("shallow shafts", tilt_results, v)
            for _, reason in tilted:
                if reason is not None:
                    print(f"  not generated: {reason}")


if __name__ == "__main__":
    main()
