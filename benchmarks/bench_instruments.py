"""Benchmark: the debugger's time per frame with two instruments against one, in one run.

A `contact-viz synth --tools 2` session, and its copy with instrument 2 taken out of the masks (the
same images and depth: one instrument), each logged by the debugger to an .rrd in this process,
interleaved --repeats times; prints the median wall and CPU ms per frame and their ratio.

Run: .venv/bin/python benchmarks/bench_instruments.py [--size 1920x1080] [--frames 150] [--repeats 3]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from PIL import Image


def one_instrument_copy(src: Path, dst: Path) -> None:
    """``src`` with every mask's id 2 set to background (palette kept); other files linked."""
    dst.mkdir()
    for entry in src.iterdir():
        if entry.name != "masks":
            (dst / entry.name).symlink_to(entry.resolve())
    (dst / "masks").mkdir()
    for mask in sorted((src / "masks").iterdir()):
        with Image.open(mask) as image:
            ids = np.array(image)
            out = Image.fromarray(np.where(ids == 2, 0, ids).astype(np.uint8), mode="L")
            out.putpalette(image.getpalette())
            out.save(dst / "masks" / mask.name)


def run(session: Path, out: Path) -> tuple[float, float, int]:
    from contact_viz.io.session import open_session
    from contact_viz.viz import rerun_log
    from contact_viz.viz.debugger import DebuggerOptions, run_debugger

    opened = rerun_log.open_recording(save=out, blueprint=rerun_log.default_blueprint())
    s = open_session(session)
    wall, cpu = time.perf_counter(), time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run_debugger(s, opened.rec, DebuggerOptions())
    opened.rec.flush(timeout_sec=60)
    return time.perf_counter() - wall, time.process_time() - cpu, len(s)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="1920x1080")
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--seed", type=int, default=70)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print("$ " + " ".join([sys.executable, *sys.argv]))
    with tempfile.TemporaryDirectory() as tmp:
        two, one = Path(tmp) / "two", Path(tmp) / "one"
        subprocess.run([sys.executable, "-m", "contact_viz.cli", "synth", str(two), "--tools", "2", "--size", args.size,
                        "--frames", str(args.frames), "--seed", str(args.seed)], check=True, stdout=subprocess.DEVNULL)
        one_instrument_copy(two, one)
        times: dict[str, list[tuple[float, float]]] = {"one instrument": [], "two instruments": []}
        for _ in range(args.repeats):
            for name, session in (("one instrument", one), ("two instruments", two)):
                wall, cpu, n = run(session, Path(tmp) / "out.rrd")
                times[name].append((1000 * wall / n, 1000 * cpu / n))
        med = {k: (statistics.median(w for w, _ in v), statistics.median(c for _, c in v)) for k, v in times.items()}
        for name, (wall, cpu) in med.items():
            print(f"{name:16s} wall {wall:6.1f} ms/frame  CPU {cpu:6.1f} ms/frame")
        print(f"two / one: wall {med['two instruments'][0] / med['one instrument'][0]:.2f}x, "
              f"CPU {med['two instruments'][1] / med['one instrument'][1]:.2f}x")
        shutil.rmtree(two, ignore_errors=True)


if __name__ == "__main__":
    main()
