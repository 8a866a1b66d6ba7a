"""Benchmark: the visual debugger (`run_debugger` into an .rrd file) on a 1920x1080 synthetic session.

Budgets (2-core machine, default options): at least 15 frames/s end to end (read, compute, log,
save) and at most 1.5 MB of .rrd per frame; memory flat in the number of frames.

Makes (once, cached under --workdir, shared with bench_extract.py) a 1080p synthetic session of
2N frames, then runs, each in a fresh process: the debugger on the first N frames and on all 2N
frames. Prints frames/s (run loop, and whole process with start-up), MB of .rrd per frame, the
split of the run loop's time (waiting for the next frame = mask/depth decoding overlapped with the
patch; waiting for images; preparing cloud/geometry/posterior; Rerun logging and flushes), the
time per frame of decoding mask+depth alone and of the patch alone (single-threaded, for
reference), and the peak RSS of both runs.

Run: .venv/bin/python benchmarks/bench_viewer.py [--frames 60] [--repeats 1]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CHILD = r"""
import json, resource, sys, time, warnings
t_start = time.perf_counter()
from contact_viz.viz.debugger import DebuggerOptions, run_debugger
from contact_viz.viz.rerun_log import open_recording
from contact_viz.viz.rerun_log import default_blueprint
from contact_viz.io.session import open_session
warnings.simplefilter("ignore")
session_dir, out, frames = sys.argv[1], sys.argv[2], int(sys.argv[3])
session = open_session(session_dir)
opened = open_recording(save=out, blueprint=default_blueprint(with_right=session.has_right, with_model=False))
summary = run_debugger(session, opened.rec, DebuggerOptions(end=frames))
opened.rec.disconnect()
total_s = time.perf_counter() - t_start
print(json.dumps({"frames": summary.frames, "elapsed_s": summary.elapsed_s, "total_s": total_s,
                  "wait_s": summary.wait_s, "image_wait_s": summary.image_wait_s,
                  "prepare_s": summary.prepare_s, "log_s": summary.log_s,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def run_child(session: Path, out: Path, frames: int) -> dict:
    proc = subprocess.run([sys.executable, "-c", CHILD, str(session), str(out), str(frames)],
                          check=True, capture_output=True, text=True)
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    result["rrd_mb"] = out.stat().st_size / 1e6
    return result


def decode_and_patch_times(session_dir: Path, frames: int) -> tuple[float, float]:
    """Seconds per frame of decoding mask + depth (one thread) and of compute_patch alone."""
    from contact_viz.geometry.patch import compute_patch
    from contact_viz.io.session import open_session

    session = open_session(session_dir)
    decode_s = patch_s = 0.0
    for index in range(frames):
        t0 = time.perf_counter()
        frame = session.load_frame(index, ("mask", "depth"))
        t1 = time.perf_counter()
        compute_patch(frame.depth_m, frame.tool_mask)
        t2 = time.perf_counter()
        decode_s += t1 - t0
        patch_s += t2 - t1
    return decode_s / frames, patch_s / frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60, help="N: the runs use N and 2N frames")
    parser.add_argument("--repeats", type=int, default=1, help="runs of each size (medians are reported)")
    parser.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "contact-viz-bench")
    args = parser.parse_args()

    import warnings

    from contact_viz.synth import SynthParams, generate_session

    warnings.simplefilter("ignore")
    n = args.frames
    session = args.workdir / f"cup-1080p-{2 * n}"
    if not (session / "truth.csv").exists():
        print(f"generating {session} ...", flush=True)
        t0 = time.perf_counter()
        generate_session(session, SynthParams(phantom="cup", frames=2 * n, seed=0), overwrite=True)
        print(f"  synth: {(time.perf_counter() - t0) / (2 * n):.3f} s/frame at 1920x1080")

    decode_s, patch_s = decode_and_patch_times(session, min(n, 30))
    print(f"reference, one thread: decode mask+depth {1000 * decode_s:.1f} ms/frame, "
          f"patch {1000 * patch_s:.1f} ms/frame")
    for frames in (n, 2 * n):
        runs = [run_child(session, args.workdir / f"view-{frames}.rrd", frames) for _ in range(args.repeats)]
        med = {key: statistics.median(r[key] for r in runs) for key in runs[0]}
        per = 1000.0 / frames
        print(f"\n{frames} frames at 1920x1080, default options:")
        print(f"  run loop: {med['elapsed_s']:.2f} s = {frames / med['elapsed_s']:.1f} frames/s "
              f"(whole process with imports and start-up: {frames / med['total_s']:.1f} frames/s)")
        print(f"  .rrd: {med['rrd_mb']:.1f} MB = {med['rrd_mb'] / frames:.2f} MB/frame")
        print(f"  run loop split, ms/frame: next frame (mask+depth read, overlapped, + patch) "
              f"{med['wait_s'] * per:.1f}, images {med['image_wait_s'] * per:.1f}, "
              f"prepare (cloud, geometry, depth, HMM, diagnostics) {med['prepare_s'] * per:.1f}, "
              f"log + flush {med['log_s'] * per:.1f}")
        print(f"  peak RSS: {med['peak_rss_mb']:.0f} MB")


if __name__ == "__main__":
    main()
