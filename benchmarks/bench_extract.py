"""Benchmark: the whole `contact-viz extract` command against merely decoding its inputs once.

Makes (once, cached under --workdir) a 1920x1080 synthetic session of --frames frames, and a
longer one that lists those frames --loops times over (symbolic links, so it costs no disk; the
paper's sessions have about 1,400 frames, and start-up weighs less in a longer session). For each
session it times, over --repeats interleaved runs each, (a) decoding every mask PNG and depth
.npy once in a plain loop (PIL + numpy, one thread, in this process: its own start-up is not
counted), (b) the whole `contact-viz extract` command in a fresh process, start-up included, with
its default processes (one per core), and (c) the same with --processes 1 (one process; decoding
in a thread). Prints the medians and the ratios to (a) (the issue's target: at most about 1.5).
With a warm page cache it also times, in a fresh single-threaded process, the work of one frame
as extract does it (decode the mask, read the depth rows around the tool, compute the patch;
means over the session) and prints the bound it sets: that work spread perfectly over the cores,
before any start-up or output.

--cold drops the page cache before every run (root only; Linux) and then warms the Python
libraries (`contact-viz --help`, numpy, PIL), so the session's files come from disk while the
code does not: the situation of a session recorded earlier, or larger than memory.

--compare SRC [SRC ...] instead A/B-tests versions of the package: the extract command of each
source tree on the longer session, one invocation of each in turn, --repeats rounds (how the
home-made code was weighed against library calls, issue 11).

Run: .venv/bin/python benchmarks/bench_extract.py [--frames 300] [--loops 4] [--repeats 3] [--cold]
     .venv/bin/python benchmarks/bench_extract.py --compare A/src B/src@B/.venv/bin/python [--repeats 5]
         [--extract-options '--processes 1']
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image

CLI = [sys.executable, "-m", "contact_viz.cli"]


def decode_once(session: Path) -> float:
    t0 = time.perf_counter()
    for mask_path in sorted((session / "masks").iterdir()):
        np.asarray(Image.open(mask_path))
        np.load(session / "depth" / f"{mask_path.stem}.npy")
    return time.perf_counter() - t0


def run_extract(session: Path, out: Path, *options: str, src: str | None = None) -> float:
    """Seconds of one `contact-viz extract` in a fresh process; ``src``: "SRC" or "SRC@PYTHON",
    the package's source directory (put on PYTHONPATH) and the interpreter to run it with."""
    cli, env = CLI, None
    if src is not None:
        path, _, python = src.partition("@")
        cli, env = [python or sys.executable, *CLI[1:]], {**os.environ, "PYTHONPATH": path}
    t0 = time.perf_counter()
    subprocess.run([*cli, "extract", str(session), "-o", str(out), *options], check=True, capture_output=True, env=env)
    return time.perf_counter() - t0


def compare_sources(session: Path, sources: list[str], repeats: int, workdir: Path, options: list[str]) -> None:
    """A/B: the whole extract command of each source tree (its ``src`` directory on PYTHONPATH),
    one invocation of each in turn, ``repeats`` rounds (each starting with the next tree); medians of the wall-clock time and of the
    CPU time (user + system, the command and its workers: steadier than wall-clock on a shared
    machine), each tree's gain over the first, and whether all wrote the same features CSV."""
    runs: dict[str, list[tuple[float, float]]] = {src: [] for src in sources}
    outputs: dict[str, bytes] = {}
    for r in range(repeats):
        for src in sources[r % len(sources):] + sources[:r % len(sources)]:  # each round starts elsewhere
            out = workdir / f"ab-{sources.index(src)}.csv"
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            wall = run_extract(session, out, *options, src=src)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu = after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime
            runs[src].append((wall, cpu))
            outputs[src] = out.read_bytes()
            print(f"  run {len(runs[src])}: {src}: wall {wall:.2f} s, cpu {cpu:.2f} s", flush=True)
    print(f"{session.name}: extract {' '.join(options)}, medians of {repeats} interleaved invocations")
    first = [statistics.median(v[i] for v in runs[sources[0]]) for i in (0, 1)]
    for src in sources:
        wall, cpu = (statistics.median(v[i] for v in runs[src]) for i in (0, 1))
        print(f"  {src}: wall {wall:.2f} s ({100 * (first[0] - wall) / first[0]:+.1f}% vs the first), "
              f"cpu {cpu:.2f} s ({100 * (first[1] - cpu) / first[1]:+.1f}%)")
    same = len(set(outputs.values())) == 1
    print(f"  features CSV identical across trees: {same}")


def drop_page_cache() -> None:
    """Empty the page cache, then read the Python code back in (it is not what is measured)."""
    os.sync()
    Path("/proc/sys/vm/drop_caches").write_text("3\n")
    subprocess.run([*CLI, "--help"], check=True, capture_output=True)
    subprocess.run([sys.executable, "-c", "import numpy, PIL.Image, cv2"], check=True)


def looped_session(source: Path, loops: int) -> Path:
    """A session that lists the frames of ``source`` ``loops`` times (symbolic links), with its force."""
    target = source.with_name(f"{source.name}x{loops}")
    if (target / "force.csv").exists():
        return target
    stems = sorted(p.stem for p in (source / "masks").iterdir())
    left = {p.stem: p.suffix for p in (source / "left").iterdir()}
    force = dict(line.split(",", 1) for line in (source / "force.csv").read_text().splitlines()[1:])
    for sub in ("masks", "depth", "left"):
        (target / sub).mkdir(parents=True, exist_ok=True)
    (target / "K.txt").write_text((source / "K.txt").read_text())
    rows = ["frame,fx,fy,fz"]
    for n in range(loops * len(stems)):
        stem = stems[n % len(stems)]
        for sub, suffix in (("masks", ".png"), ("depth", ".npy"), ("left", left[stem])):
            link = target / sub / f"{n:06d}{suffix}"
            if not link.is_symlink():
                link.symlink_to(source / sub / f"{stem}{suffix}")
        rows.append(f"{n},{force[str(int(stem))]}")
    (target / "force.csv").write_text("\n".join(rows) + "\n")
    return target


def parts_per_frame(session_dir: Path) -> tuple[float, float, float]:
    """Mean seconds per frame, one thread, in a fresh process, of extract's three steps: decode
    the mask, read the depth rows around the tool, compute the patch."""
    out = subprocess.run([sys.executable, __file__, "--parts-of", str(session_dir)],
                         check=True, capture_output=True, text=True)
    mask_s, depth_s, patch_s = (float(v) for v in out.stdout.split())
    return mask_s, depth_s, patch_s


def _print_parts(session_dir: Path) -> None:
    import cv2

    from contact_viz.pipeline.allocator import keep_freed_memory
    from contact_viz.params import PatchParams
    from contact_viz.geometry.patch import compute_patch, patch_depth_rows
    from contact_viz.io.session import open_session

    cv2.setNumThreads(1)
    keep_freed_memory()  # as `contact-viz extract` does
    session, params = open_session(session_dir), PatchParams()
    mask_s, depth_s, patch_s = [], [], []
    for index in range(len(session)):
        t0 = time.perf_counter()
        tool = session.load_frame(index, layers=("mask",)).tool_mask
        t1 = time.perf_counter()
        row0, row1 = patch_depth_rows(tool, params)
        depth = session.load_depth_rows(index, row0, row1)
        t2 = time.perf_counter()
        compute_patch(depth, tool[row0:row1], params)
        t3 = time.perf_counter()
        mask_s.append(t1 - t0)
        depth_s.append(t2 - t1)
        patch_s.append(t3 - t2)
    print(statistics.fmean(mask_s), statistics.fmean(depth_s), statistics.fmean(patch_s))


def measure(session: Path, frames: int, repeats: int, cold: bool, workdir: Path) -> None:
    decode_s, extract_s, one_s = [], [], []
    for _ in range(repeats):
        for runs, run in ((decode_s, lambda: decode_once(session)),
                          (extract_s, lambda: run_extract(session, workdir / "features.csv")),
                          (one_s, lambda: run_extract(session, workdir / "features.csv", "--processes", "1"))):
            if cold:
                drop_page_cache()
            runs.append(run())
    d, e, one = statistics.median(decode_s), statistics.median(extract_s), statistics.median(one_s)
    cores = os.cpu_count() or 1
    cache = "cold" if cold else "warm"
    print(f"{session.name}: {frames} frames, page cache {cache}, medians of {repeats} interleaved runs")
    print(f"  decode mask+depth once: {d:.2f} s ({1000 * d / frames:.2f} ms/frame)")
    print(f"  contact-viz extract (whole command, start-up included, {min(cores, 8)} processes): {e:.2f} s "
          f"({1000 * e / frames:.2f} ms/frame, {frames / e:.0f} frames/s); ratio to decode {e / d:.2f}")
    print(f"  contact-viz extract --processes 1: {one:.2f} s; ratio to decode {one / d:.2f}")
    print("  runs, s: decode " + " ".join(f"{v:.2f}" for v in decode_s) + " | extract " + " ".join(
        f"{v:.2f}" for v in extract_s) + " | --processes 1 " + " ".join(f"{v:.2f}" for v in one_s))
    if not cold:
        mask_s, depth_s, patch_s = parts_per_frame(session)
        work = mask_s + depth_s + patch_s
        bound = work / cores * frames
        print(f"  work per frame, one thread, means: mask {1000 * mask_s:.2f} ms + depth rows {1000 * depth_s:.2f} ms "
              f"+ patch {1000 * patch_s:.2f} ms = {1000 * work:.2f} ms; spread perfectly over {cores} cores, no "
              f"start-up: {bound:.2f} s = {bound / d:.2f}x decode")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300, help="frames synthesized")
    parser.add_argument("--loops", type=int, default=4, help="the longer session lists the frames this often")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--cold", action="store_true", help="drop the page cache before every run (root)")
    parser.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "contact-viz-bench")
    parser.add_argument("--compare", nargs="+", metavar="SRC[@PYTHON]",
                        help="instead: A/B the extract command of these source trees (each a src/ directory put "
                        "on PYTHONPATH, run by PYTHON if given) on the longer session, interleaved, --repeats rounds")
    parser.add_argument("--extract-options", default="", help="with --compare: options passed to extract, "
                        "e.g. '--processes 1'")
    parser.add_argument("--parts-of", type=Path, help=argparse.SUPPRESS)  # the child of parts_per_frame
    args = parser.parse_args()
    if args.parts_of is not None:
        _print_parts(args.parts_of)
        return

    from contact_viz.synth import SynthParams, generate_session

    session = args.workdir / f"cup-1080p-{args.frames}"
    if not (session / "truth.csv").exists():
        print(f"generating {session} ...", flush=True)
        t0 = time.perf_counter()
        generate_session(session, SynthParams(phantom="cup", frames=args.frames, seed=0), overwrite=True)
        print(f"  synth: {(time.perf_counter() - t0) / args.frames:.3f} s/frame at 1920x1080")
    if args.compare:
        longer = looped_session(session, args.loops) if args.loops > 1 else session
        compare_sources(longer, args.compare, args.repeats, args.workdir, args.extract_options.split())
        return
    measure(session, args.frames, args.repeats, args.cold, args.workdir)
    if args.loops > 1 and not args.cold:  # linked frames are read from disk once, then cached
        measure(looped_session(session, args.loops), args.loops * args.frames, args.repeats, False, args.workdir)


if __name__ == "__main__":
    main()
