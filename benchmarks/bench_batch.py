"""Benchmark: `contact-viz batch` over a 4-session dataset on local processes and on a local Ray.

Makes (once, cached under --workdir) four synthetic sessions (cup, kidney, liver, glove) of
--frames frames at --size, and copies of them without depth/ (symbolic links to the other
folders), so that the batch has to compute SGBM depth, the dataset work that costs most. Then
times, over --repeats interleaved runs each, the whole command in a fresh process (start-up,
and for Ray its start and shutdown, included), each run with an empty cache:

    contact-viz batch DATASET -o OUT --steps depth,extract [--ray]

and prints the medians, the per-step wall times of the last run of each engine, and checks that
both engines wrote identical features files.

Run: .venv/bin/python benchmarks/bench_batch.py [--frames 60] [--size 640x360] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CLI = [sys.executable, "-m", "contact_viz.cli"]
PHANTOMS = ("cup", "kidney", "liver", "glove")


def make_dataset(workdir: Path, frames: int, size: str) -> Path:
    rendered = workdir / f"rendered-{frames}-{size}"
    for seed, phantom in enumerate(PHANTOMS):
        if not (rendered / phantom / "session.json").exists():
            subprocess.run([*CLI, "synth", str(rendered / phantom), "--phantom", phantom, "--seed", str(seed),
                            "--frames", str(frames), "--size", size, "--overwrite"], check=True,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    stereo_only = workdir / f"stereo-only-{frames}-{size}"
    if not stereo_only.exists():
        for phantom in PHANTOMS:
            (stereo_only / phantom).mkdir(parents=True)
            for item in (rendered / phantom).iterdir():
                if item.name != "depth":
                    (stereo_only / phantom / item.name).symlink_to(item.resolve())
    return stereo_only


def run(dataset: Path, out: Path, ray: bool) -> float:
    cache = Path(tempfile.mkdtemp(prefix="bench-batch-cache-"))
    try:
        start = time.perf_counter()
        subprocess.run([*CLI, "batch", str(dataset), "-o", str(out), "--steps", "depth,extract",
                        "--cache-dir", str(cache), *(["--ray"] if ray else [])], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        return time.perf_counter() - start
    finally:
        shutil.rmtree(cache, ignore_errors=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "contact-viz-bench-batch")
    args = parser.parse_args()
    dataset = make_dataset(args.workdir, args.frames, args.size)
    times: dict[str, list[float]] = {"local": [], "ray": []}
    outs = {}
    for _ in range(args.repeats):
        for engine in ("local", "ray"):
            out = Path(tempfile.mkdtemp(prefix=f"bench-batch-{engine}-"))
            times[engine].append(run(dataset, out, engine == "ray"))
            if engine in outs:
                shutil.rmtree(outs[engine], ignore_errors=True)
            outs[engine] = out
    frames = args.frames * len(PHANTOMS)
    print(f"4-session batch (--steps depth,extract; SGBM depth; {frames} frames at {args.size}), "
          f"median of {args.repeats} interleaved runs, start-up included:")
    for engine, values in times.items():
        median = statistics.median(values)
        wall = json.loads((outs[engine] / "summary.json").read_text())["wall_s"]
        split = ", ".join(f"{step} {t:.1f} s" for step, t in wall.items())
        print(f"  {engine:<6} {median:6.1f} s  ({frames / median:5.1f} frames/s; runs {', '.join(f'{v:.1f}' for v in values)};"
              f" last run: {split})")
    same = all((outs["local"] / p / "features.csv").read_bytes() == (outs["ray"] / p / "features.csv").read_bytes()
               for p in PHANTOMS)
    print(f"  features identical on both engines: {'yes' if same else 'NO'}")
    for out in outs.values():
        shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
    main()
