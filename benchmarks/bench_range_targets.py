"""Benchmark: the stereo path, the patch and the checks at a real endoscope's range, through the commands a user runs.

For each camera (``--cameras``: presets of `contact-viz synth --camera`; default ``davinci``, the measured da Vinci
endoscope at 50 mm, and ``default``, the synthetic sessions' 90 mm camera), image size, phantom and number of
instruments, a clean session is made with `contact-viz synth` (once, under ``--workdir``) with a stereo-only copy
(depth/ removed: depth from contact-viz's SGBM), and for each source tree (``--compare OLD/src NEW/src``: each run
as ``PYTHONPATH=SRC``; default the installed package) it runs `contact-viz extract` and `contact-viz check` on both
and prints per cell and over all cells:

* hover read as contact: of the (frame, instrument) rows whose true gap (truth.csv ``gap_m``, ``gap_m_<id>`` with
  two instruments) is at least HOVER_MM, those whose distance reads below CONTACT_MM (target: at most 2% with
  SGBM);
* near error: the median of |SGBM distance - rendered distance| over the rows whose true gap is at most NEAR_MM
  (target: no worse than at the 90 mm camera, 1.9 mm at 1080p);
* false flags: the share of frames where `check` fired any check, on these clean sessions (targets: under 3% with
  the rendered depth, under 5% with SGBM);
* the wall time of `extract` per frame (SGBM computed; the depth cache is per tree and run).

    .venv/bin/python benchmarks/bench_range_targets.py [--sizes 1280x960,1920x1080] [--phantoms cup,kidney,liver,glove]
        [--tools 1,2] [--frames 40] [--cameras davinci,default] [--compare OLD/src NEW/src]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HOVER_MM, CONTACT_MM, NEAR_MM = 3.0, 1.0, 5.0  # a hover (true gap >= ...), read as contact (< ...), near contact
SEEDS = {"cup": 21, "kidney": 22, "liver": 23, "glove": 24}  # the sessions' seeds (+ 100 x two instruments)
CLI = [sys.executable, "-c", "import sys; from contact_viz.cli import main; sys.exit(main())"]


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def run(args: list[str], env: dict | None = None, timeout: float = 7200) -> subprocess.CompletedProcess:
    proc = subprocess.run(CLI + args, env=env, capture_output=True, text=True, timeout=timeout)
    if proc.returncode not in (0, 1):
        raise SystemExit(f"error: contact-viz {' '.join(args)} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    return proc


def make_session(root: Path, camera: str, size: str, phantom: str, tools: int, frames: int) -> tuple[Path, Path]:
    """The rendered session and its stereo-only copy (made once)."""
    name = f"{camera}-{size}-{phantom}-{tools}"
    rendered, stereo = root / "sessions" / name, root / "sessions" / f"{name}-sgbm"
    if not (stereo / "session.json").is_file():
        shutil.rmtree(rendered, ignore_errors=True)
        shutil.rmtree(stereo, ignore_errors=True)
        log(f"synth {name}")
        seed = SEEDS[phantom] + 100 * (tools - 1)
        run(["synth", str(rendered), "--phantom", phantom, "--tools", str(tools), "--frames", str(frames),
             "--size", size, "--seed", str(seed), "--camera", camera])
        partial = stereo.with_name(stereo.name + ".partial")
        shutil.rmtree(partial, ignore_errors=True)
        shutil.copytree(rendered, partial, ignore=lambda d, names: ["depth"] if Path(d) == rendered else [])
        partial.rename(stereo)
    return rendered, stereo


def truth_gaps(session: Path) -> dict[tuple[str, str], float]:
    """{(stem, tool id or ''), true gap mm} from truth.csv (frame numbers as the stems synth writes)."""
    stems = sorted(p.stem for p in (session / "left").iterdir())
    out = {}
    with open(session / "truth.csv", newline="") as f:
        for row in csv.DictReader(f):
            stem = stems[int(row["frame"])]
            ids = [k.removeprefix("gap_m_") for k in row if k.startswith("gap_m_")]
            if ids:
                for k in ids:
                    out[(stem, k)] = 1000 * float(row[f"gap_m_{k}"])
            else:
                out[(stem, "")] = 1000 * float(row["gap_m"])
                out[(stem, "1")] = out[(stem, "")]
    return out


def distances(features: Path) -> dict[tuple[str, str], float]:
    with open(features, newline="") as f:
        return {(r["frame"], r.get("tool", "")): (1000 * float(r["distance_m"]) if r["distance_m"] else float("nan"))
                for r in csv.DictReader(f)}


def flagged_share(checks_json: Path) -> float:
    data = json.loads(checks_json.read_text())
    sess = data["sessions"][0]
    return sess["flagged_frames"] / sess["n_frames"]


def measure(src: Path | None, rendered: Path, stereo: Path, out: Path) -> dict:
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = str(src)
    out.mkdir(parents=True, exist_ok=True)
    cache = out / "cache"
    result = {}
    for kind, session in (("rendered", rendered), ("sgbm", stereo)):
        start = time.perf_counter()
        run(["extract", str(session), "-o", str(out / f"{kind}.csv"), "--cache-dir", str(cache)], env)
        result[f"{kind}_extract_s"] = time.perf_counter() - start
        proc = run(["check", str(session), "--json", str(out / f"{kind}.json"), "--cache-dir", str(cache)], env)
        if not (out / f"{kind}.json").is_file():
            raise SystemExit(f"error: contact-viz check {session} wrote no JSON:\n{proc.stdout[-1000:]}{proc.stderr[-2000:]}")
        result[f"{kind}_flagged"] = flagged_share(out / f"{kind}.json")
        result[kind] = distances(out / f"{kind}.csv")
    gaps = truth_gaps(rendered)
    keys = [k for k in result["sgbm"] if k in gaps]
    hovers = [k for k in keys if gaps[k] >= HOVER_MM]
    result["hover_n"] = len(hovers)
    result["hover_contact_sgbm"] = sum(1 for k in hovers if result["sgbm"][k] < CONTACT_MM)
    result["hover_contact_rendered"] = sum(1 for k in hovers if result["rendered"].get(k, float("nan")) < CONTACT_MM)
    near = [abs(result["sgbm"][k] - result["rendered"][k]) for k in keys
            if gaps[k] <= NEAR_MM and k in result["rendered"] and result["sgbm"][k] == result["sgbm"][k]
            and result["rendered"][k] == result["rendered"][k]]
    result["near_diffs"] = near
    result["frames"] = len({k[0] for k in keys})
    del result["sgbm"], result["rendered"]
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default="1280x960,1920x1080")
    parser.add_argument("--phantoms", default="cup,kidney,liver,glove")
    parser.add_argument("--tools", default="1,2")
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--cameras", default="davinci,default")
    parser.add_argument("--compare", nargs="+", type=Path, metavar="SRC")
    parser.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "cv-range-targets")
    args = parser.parse_args(argv)
    trees = args.compare or [None]
    cells = [(c, s, p, int(t)) for c in args.cameras.split(",") for s in args.sizes.split(",")
             for p in args.phantoms.split(",") for t in args.tools.split(",")]
    totals = {i: {} for i in range(len(trees))}
    print("| camera | size | phantom | tools | tree | hover read < 1 mm, SGBM (rendered) | median abs(SGBM - rendered) "
          "near contact, mm | false flags rendered / SGBM | extract ms/frame rendered / SGBM |")
    print("|---|---|---|---|---|---|---|---|---|")
    for camera, size, phantom, tools in cells:
        rendered, stereo = make_session(args.workdir, camera, size, phantom, tools, args.frames)
        for i, src in enumerate(trees):
            r = measure(src, rendered, stereo, args.workdir / "runs" / f"{rendered.name}-{i}")
            t = totals[i].setdefault(camera, {"hover": 0, "sgbm": 0, "rendered": 0, "near": [], "flag_r": [],
                                              "flag_s": []})
            t["hover"] += r["hover_n"]
            t["sgbm"] += r["hover_contact_sgbm"]
            t["rendered"] += r["hover_contact_rendered"]
            t["near"] += r["near_diffs"]
            t["flag_r"].append(r["rendered_flagged"])
            t["flag_s"].append(r["sgbm_flagged"])
            near = f"{statistics.median(r['near_diffs']):.2f}" if r["near_diffs"] else "-"
            print(f"| {camera} | {size} | {phantom} | {tools} | {i + 1} | {r['hover_contact_sgbm']} of {r['hover_n']} "
                  f"({r['hover_contact_rendered']}) | {near} | {r['rendered_flagged']:.0%} / {r['sgbm_flagged']:.0%} | "
                  f"{1000 * r['rendered_extract_s'] / r['frames']:.0f} / {1000 * r['sgbm_extract_s'] / r['frames']:.0f} |",
                  flush=True)
    for i, src in enumerate(trees):
        for camera, t in totals[i].items():
            near = f"{statistics.median(t['near']):.2f} mm" if t["near"] else "-"
            print(f"tree {i + 1} ({src or 'installed'}), camera {camera}: hovers read below {CONTACT_MM:g} mm with SGBM "
                  f"{t['sgbm']} of {t['hover']} ({t['sgbm'] / max(t['hover'], 1):.1%}; rendered {t['rendered']}); "
                  f"median abs(SGBM - rendered) within {NEAR_MM:g} mm of contact {near}; frames flagged on clean "
                  f"sessions rendered {statistics.mean(t['flag_r']):.1%}, SGBM {statistics.mean(t['flag_s']):.1%} "
                  f"(cell means)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
