"""Benchmark: the whole `contact-viz extract` command against merely decoding its inputs once.

Makes (once, cached under --workdir) a 1920x1080 synthetic session, then times, over --repeats
runs each, (a) decoding every mask PNG and depth .npy once in a plain loop (PIL + numpy, one
thread) and (b) the whole `contact-viz extract` command in a fresh process, start-up included.
Prints the medians and their ratio (target: at most about 1.5).

Run: .venv/bin/python benchmarks/bench_extract.py [--frames 60] [--repeats 3]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image


def decode_once(session: Path) -> float:
    t0 = time.perf_counter()
    for mask_path in sorted((session / "masks").iterdir()):
        np.asarray(Image.open(mask_path))
        np.load(session / "depth" / f"{mask_path.stem}.npy")
    return time.perf_counter() - t0


def run_extract(session: Path, out: Path) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "contact_viz.cli", "extract", str(session), "-o", str(out)],
                   check=True, capture_output=True)
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "contact-viz-bench")
    args = parser.parse_args()

    from contact_viz.synth import SynthParams, generate_session

    session = args.workdir / f"cup-1080p-{args.frames}"
    if not (session / "truth.csv").exists():
        print(f"generating {session} ...", flush=True)
        t0 = time.perf_counter()
        generate_session(session, SynthParams(phantom="cup", frames=args.frames, seed=0), overwrite=True)
        print(f"  synth: {(time.perf_counter() - t0) / args.frames:.3f} s/frame at 1920x1080")
    decode_s = [decode_once(session) for _ in range(args.repeats)]
    extract_s = [run_extract(session, args.workdir / "features.csv") for _ in range(args.repeats)]
    d, e = statistics.median(decode_s), statistics.median(extract_s)
    n = args.frames
    print(f"decode mask+depth once: median {d:.2f} s ({1000 * d / n:.1f} ms/frame)")
    print(f"contact-viz extract (whole command, start-up included): median {e:.2f} s "
          f"({1000 * e / n:.1f} ms/frame, {n / e:.1f} frames/s)")
    print(f"ratio extract / decode: {e / d:.2f}")


if __name__ == "__main__":
    main()
