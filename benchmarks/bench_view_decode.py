"""Benchmark: `contact-viz view` on a 1080p JPEG session with depth given, against decoding its inputs once.

The issue's target (live mode): the whole `contact-viz view SESSION --save out.rrd` (process start-up
included, default options) takes at most 1.2 times as long as decoding its inputs once, and keeps up
with 30 frames/s.

Decoding the inputs once: what `view` must read of every frame, each file decoded in full once with
OpenCV / NumPy, one thread, in a fresh process (its start-up not counted): the left JPEG
(cv2.imread, colour), the right JPEG (the same, full size), the mask PNG (cv2.imread,
IMREAD_UNCHANGED) and the depth .npy (np.load). Each part is printed. The ratio is taken against
this plain decode, as the issue did; two stricter ones are printed beside it: against the decode "at
the size the viewer needs" (the right image at half size, cv2.IMREAD_REDUCED_COLOR_2, as the default
--right-step 2 logs it), and against the plain decode in a process whose allocator keeps freed memory
(contact_viz.pipeline.allocator: no page faults for each new frame buffer, about 4 ms a frame less).

Per round (interleaved: the machine's speed drifts by up to about 25% from one minute to the next):
decode once, then `view` of each source tree (--compare; the order rotates every round) in a fresh
process. Printed, medians over --repeats rounds: frames/s end to end (process wall time), the run's
own frames/s and time split (its summary lines: next frame / images / prepare / log), CPU ms per
frame (user + sys of the process, all its threads), MB of .rrd per frame, and the ratio of the
view's wall time to the same round's decode-once time. --psnr adds the PSNR of the decoded left
and right videos (PyAV, libdav1d) of each tree's last recording against the source images.

The session: --session (default /tmp/s1080), made if missing with `contact-viz synth SESSION --frames
150 --size 1920x1080 --seed 5`. synth writes JPEG files (quality 92) already; a session whose
left/right images are PNG files is first copied to SESSION-jpeg with them re-saved as JPEG (quality
90, same stems, the other directories linked).

--stages instead prints what each stage of `view` costs per frame, CPU ms, one at a time in a fresh process of
each tree (the floor: with everything spread perfectly over the cores, no start-up, wall >= sum / cores), and the
start-up (`view --end 1`, wall).

Run: .venv/bin/python benchmarks/bench_view_decode.py [--session /tmp/s1080] [--repeats 3] [--psnr]
     .venv/bin/python benchmarks/bench_view_decode.py --stages [--compare OLD/src NEW/src]
     .venv/bin/python benchmarks/bench_view_decode.py --compare OLD/src NEW/src --repeats 5 --psnr
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PARTS = ("left JPEG", "right JPEG", "mask PNG", "depth npy")


def make_session(session: Path, frames: int) -> Path:
    """The 1080p JPEG session with depth: ``session`` (synth if missing), or its JPEG copy if its images are PNG."""
    if not (session / "session.json").exists():
        print(f"making {session} with contact-viz synth ...", file=sys.stderr, flush=True)
        subprocess.run([sys.executable, "-m", "contact_viz.cli", "synth", str(session), "--frames", str(frames),
                        "--size", "1920x1080", "--seed", "5"], check=True, stdout=subprocess.DEVNULL)
    if not list((session / "left").glob("*.png")):
        return session
    import cv2

    jpeg = session.with_name(session.name + "-jpeg")
    if not (jpeg / "done").exists():
        jpeg.mkdir(exist_ok=True)
        for entry in session.iterdir():
            if entry.name not in ("left", "right") and not (jpeg / entry.name).exists():
                os.symlink(entry.resolve(), jpeg / entry.name)
        for side in ("left", "right"):
            (jpeg / side).mkdir(exist_ok=True)
            for image in sorted((session / side).glob("*.png")):
                ok = cv2.imwrite(str(jpeg / side / f"{image.stem}.jpg"), cv2.imread(str(image)),
                                 [cv2.IMWRITE_JPEG_QUALITY, 90])
                assert ok, image
        (jpeg / "done").write_text("")
    return jpeg


def _frame_files(session: Path, frames: int) -> list[tuple[Path, Path, Path, Path]]:
    stems = sorted(p.stem for p in (session / "left").iterdir())[:frames]
    right = {p.stem: p for p in (session / "right").iterdir()}
    masks = {p.stem: p for p in (session / "masks").iterdir()}
    depth = {p.stem: p for p in (session / "depth").iterdir()}
    left = {p.stem: p for p in (session / "left").iterdir()}
    return [(left[s], right[s], masks[s], depth[s]) for s in stems]


def _decode_once_here(session: Path, frames: int) -> dict:
    """(in the fresh process) seconds, wall and CPU, of each part of decoding the inputs once, one thread."""
    import cv2
    import numpy as np

    cv2.setNumThreads(1)
    files = _frame_files(session, frames)
    decode = (lambda p: cv2.imread(str(p), cv2.IMREAD_COLOR), lambda p: cv2.imread(str(p), cv2.IMREAD_COLOR),
              lambda p: cv2.imread(str(p), cv2.IMREAD_UNCHANGED), lambda p: np.load(p))
    wall = [0.0] * 4
    cpu = [0.0] * 4
    for paths in files:  # frame by frame, as the viewer reads them
        for k, (step, path) in enumerate(zip(decode, paths)):
            w0, c0 = time.perf_counter(), time.thread_time()
            out = step(path)
            wall[k] += time.perf_counter() - w0
            cpu[k] += time.thread_time() - c0
            assert out is not None and out.size, path
    w0 = time.perf_counter()
    for paths in files:
        cv2.imread(str(paths[1]), cv2.IMREAD_REDUCED_COLOR_2)
    half = time.perf_counter() - w0
    return {"frames": len(files), "wall": wall, "cpu": cpu, "right_half_wall": half}


def _stages_here(session_dir: Path, frames: int) -> dict:
    """(in a fresh process of the tree measured) CPU seconds per frame of each stage of `view`, one at a time
    over every 5th frame (process time: the encoders' own threads count; nothing else runs meanwhile)."""
    import cv2
    import numpy as np

    from contact_viz.geometry.pointcloud import depth_cloud, depth_preview, patch_geometry
    from contact_viz.io.decoders import read_depth_m, read_mask_ids
    from contact_viz.io.session import open_session
    from contact_viz.pipeline.check import grey_step, load_grey
    from contact_viz.pipeline.extract import FrameResult, frame_patches
    from contact_viz.viz.diagnostics import DiagnosticsTracker
    from contact_viz.viz.images import ImageReader
    from contact_viz.viz.options import DebuggerOptions
    from contact_viz.viz.video import VideoEncoder, rgb_to_i420

    session = open_session(session_dir)
    options = DebuggerOptions()
    K = np.asarray(session.calibration.K, dtype=np.float64)
    indices = list(range(0, min(frames, len(session)), 5))
    height, width = session.image_size
    costs: dict[str, float] = {}

    def stage(name, step, items, keep=False):
        """Median over 3 passes of the CPU per item of ``step``; each result is dropped at once (steady state:
        the allocator reuses the memory, as in the viewer's loop), unless ``keep`` (then returned, untimed)."""
        step(items[0])  # warm-up (first allocations, lazy imports)
        passes = []
        for _ in range(3):
            t0 = time.process_time()
            for item in items:
                step(item)
            passes.append((time.process_time() - t0) / len(items))
        costs[name] = statistics.median(passes)
        return [step(item) for item in items] if keep else None

    paths = [(session.image_path("left", i), session.image_path("right", i)) for i in indices]
    stage("read left+right JPEG bytes", lambda p: (np.fromfile(p[0], np.uint8), np.fromfile(p[1], np.uint8)), paths)
    lefts = stage("decode left JPEG, full size, RGB", lambda p: cv2.imread(str(p[0]), cv2.IMREAD_COLOR_RGB), paths,
                  keep=True)
    rights = stage("decode right JPEG at 1/2 (right_step 2)",
                   lambda p: cv2.imread(str(p[1]), cv2.IMREAD_REDUCED_COLOR_2), paths, keep=True)
    stage("checks' greys: left+right JPEG at 1/4, grey", lambda i: [
        load_grey(session, side, i, grey_step(session, options.diagnostics)) for side in ("left", "right")], indices)
    stage("RGB -> I420, left + right", lambda k: (rgb_to_i420(lefts[k]), rgb_to_i420(
        cv2.cvtColor(rights[k], cv2.COLOR_BGR2RGB))), list(range(len(indices))))
    # the encoders on consecutive frames (as in a run; a pass starts again at its first frame, one scene cut)
    first = max(0, min(frames, len(session)) // 2 - 15)
    run = range(first, min(first + 30, len(session)))
    video = [(rgb_to_i420(cv2.imread(str(session.image_path("left", i)), cv2.IMREAD_COLOR_RGB)), rgb_to_i420(
        cv2.cvtColor(cv2.imread(str(session.image_path("right", i)), cv2.IMREAD_REDUCED_COLOR_2),
                     cv2.COLOR_BGR2RGB))) for i in run]
    for side, size, pick in (("left", (width, height), 0), ("right", (-(-width // 2), -(-height // 2)), 1)):
        encoder = VideoEncoder(*size, float(session.fps), options.video)
        stage(f"AV1 encode {side} {size[0]}x{size[1]} (all its threads)",
              lambda k: encoder.encode(video[k][pick], k), list(range(len(video))))
        encoder.flush()
    reader = ImageReader(session, options, True, None)
    reader.modes = {"left": "video", "right": "video"}
    stage("ImageReader.load as the viewer runs it (the rows above but the encodes)", reader.load, indices)
    stage("decode mask PNG (ids)", lambda i: read_mask_ids(session.layer_file("mask", session.stems[i])), indices)
    stage("load depth .npy", lambda i: read_depth_m(session.layer_file("depth", session.stems[i])), indices)
    loaded = [session.load_frame(i) for i in indices]
    results = stage("patch (frame_patches, whole frame)",
                    lambda f: FrameResult(f, *frame_patches(f, options.patch_params, session.object_ids)), loaded,
                    keep=True)
    greys = [[load_grey(session, side, i, grey_step(session, options.diagnostics)) for side in ("left", "right")]
             for i in indices]
    tracker = DiagnosticsTracker(options.diagnostics, fx_px=float(K[0, 0]),
                                 baseline_m=float(session.calibration.baseline_m), image_width=width,
                                 depth_source=session.depth_source)
    stage("checks (DiagnosticsTracker.update)",
          lambda k: tracker.update(results[k], *greys[k], evidence=True), list(range(len(indices))))
    colors = [cv2.cvtColor(cv2.imread(str(p[0]), cv2.IMREAD_REDUCED_COLOR_2), cv2.COLOR_BGR2RGB) for p in paths]
    stage("cloud + depth preview + patch geometry", lambda k: (
        depth_cloud(results[k].frame.depth_m, K, colors[k], center_xy=results[k].patch.center_xy,
                    params=options.cloud),
        depth_preview(results[k].frame.depth_m, options.depth_step, options.depth_units_per_m),
        patch_geometry(results[k].frame.depth_m, K, results[k].patch, options.patch_params)),
        list(range(len(indices))))
    return costs


def stages(session: Path, frames: int, trees: list[Path | None], labels: list[str], workdir: Path) -> None:
    """Each tree's stage costs (a fresh process each) and its start-up (`view --end 1`, median of 3)."""
    table: dict[str, list[float]] = {}
    starts = []
    for k, src in enumerate(trees):
        env = dict(os.environ, **({"PYTHONPATH": str(src)} if src is not None else {}))
        out = subprocess.run([sys.executable, __file__, "--stages-of", str(session), "--frames", str(frames)],
                             check=True, capture_output=True, text=True, env=env)
        for name, value in json.loads(out.stdout.strip().splitlines()[-1]).items():
            table.setdefault(name, [math.nan] * len(trees))[k] = value
        starts.append(statistics.median(run_view(session, workdir / "one.rrd", 1, src, workdir / "cache", [])["wall"]
                                        for _ in range(3)))
    print(f"\n{session}: CPU ms per frame of each stage of `view`, one at a time (every 5th of {frames} frames):")
    print("| stage | " + " | ".join(f"tree {k + 1}" for k in range(len(trees))) + " |")
    print("|---|" + "---|" * len(trees))
    for name, values in table.items():
        print(f"| {name} | " + " | ".join(f"{1000 * v:.2f}" for v in values) + " |")
    reader = "ImageReader.load as the viewer runs it (the rows above but the encodes)"
    summed = [sum(v[k] for name, v in table.items() if name == reader or not (
        name.startswith(("read left", "decode left", "decode right", "checks' greys", "RGB -> I420"))))
        for k in range(len(trees))]
    print("| sum (ImageReader.load in place of its parts; Rerun's logging not included) | "
          + " | ".join(f"{1000 * v:.1f}" for v in summed) + " |")
    cores = os.cpu_count() or 1
    print(f"| floor on {cores} cores, ms/frame wall (sum / {cores}) | "
          + " | ".join(f"{1000 * v / cores:.1f}" for v in summed) + " |")
    print("| start-up + close, `view --end 1`, s wall | " + " | ".join(f"{v:.2f}" for v in starts) + " |")
    for k, label in enumerate(labels):
        print(f"tree {k + 1}: {label}")


def decode_once(session: Path, frames: int, keep_freed: bool = False) -> dict:
    """Decoding the inputs once, in a fresh process; ``keep_freed``: with glibc told to keep freed memory
    (contact_viz.pipeline.allocator, as `extract` runs), which spares the page faults of each new frame buffer."""
    out = subprocess.run([sys.executable, __file__, "--decode-once", str(session), "--frames", str(frames)]
                         + ["--keep-freed"] * keep_freed, check=True, capture_output=True, text=True)
    return json.loads(out.stdout)


def run_view(session: Path, out: Path, frames: int, src: Path | None, cache: Path, extra: list[str]) -> dict:
    """`contact-viz view SESSION --save out --end frames` in a fresh process (``src`` on PYTHONPATH)."""
    env = dict(os.environ, CONTACT_VIZ_CACHE=str(cache))
    if src is not None:
        env["PYTHONPATH"] = str(src)
    cmd = [sys.executable, "-m", "contact_viz.cli", "view", str(session), "--save", str(out), "--end", str(frames),
           *extra]
    before = os.times()
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = os.times()
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{proc.stdout}\n{proc.stderr}")
    text = proc.stdout + proc.stderr
    own = re.search(r"(\d+) frames? in ([\d.]+) s \(([\d.]+) frames/s\)", text)
    split = re.search(r"time: next frame ([\d.]+) s, images ([\d.]+) s, prepare ([\d.]+) s, log ([\d.]+) s", text)
    cpu = (after.children_user - before.children_user) + (after.children_system - before.children_system)
    return {"wall": wall, "cpu": cpu, "frames": int(own.group(1)), "own_s": float(own.group(2)),
            "split": [float(v) for v in split.groups()], "rrd_mb": out.stat().st_size / 1e6}


def psnr_of(rrd: Path, session: Path, src: Path | None) -> dict:
    """Median and minimum PSNR (dB) of the left and right videos of ``rrd`` against the session's images,
    computed in a fresh process with ``src``'s package (bench_viewer.video_psnr)."""
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = str(src)
    code = ("import json, sys, statistics; sys.path.insert(0, sys.argv[1]); from bench_viewer import video_psnr; "
            "from pathlib import Path; out = {}\n"
            "for side in ('left', 'right'):\n"
            "    v = video_psnr(Path(sys.argv[2]), Path(sys.argv[3]), side)\n"
            "    out[side] = [statistics.median(v), min(v), len(v)]\n"
            "print(json.dumps(out))")
    proc = subprocess.run([sys.executable, "-c", code, str(Path(__file__).parent), str(rrd), str(session)],
                          env=env, capture_output=True, text=True, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--session", type=Path, default=Path("/tmp/s1080"))
    parser.add_argument("--frames", type=int, default=150, help="frames of the session made, and shown (--end)")
    parser.add_argument("--repeats", type=int, default=3, help="rounds (medians are printed)")
    parser.add_argument("--compare", nargs="+", type=Path, metavar="SRC",
                        help="source trees (a checkout's src/, put on PYTHONPATH), run interleaved")
    parser.add_argument("--psnr", action="store_true", help="PSNR of each tree's videos against the source images")
    parser.add_argument("--view-options", default="", help="more options for `contact-viz view`, e.g. "
                        "'--video-codec h264'")
    parser.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "bench-view-decode")
    parser.add_argument("--stages", action="store_true", help="instead: each stage's CPU per frame, and start-up")
    parser.add_argument("--decode-once", type=Path, help=argparse.SUPPRESS)  # the fresh decoding process
    parser.add_argument("--stages-of", type=Path, help=argparse.SUPPRESS)  # the fresh process of --stages
    parser.add_argument("--keep-freed", action="store_true", help=argparse.SUPPRESS)  # with --decode-once
    args = parser.parse_args()
    if args.decode_once:
        if args.keep_freed:
            from contact_viz.pipeline.allocator import keep_freed_memory

            keep_freed_memory()
        print(json.dumps(_decode_once_here(args.decode_once, args.frames)))
        return
    if args.stages_of:
        import warnings

        warnings.simplefilter("ignore")
        print(json.dumps(_stages_here(args.stages_of, args.frames)))
        return
    args.workdir.mkdir(parents=True, exist_ok=True)
    session = make_session(args.session, args.frames)
    trees = [p.resolve() for p in args.compare] if args.compare else [None]
    labels = [str(t) if t is not None else "installed" for t in trees]
    extra = args.view_options.split()
    if args.stages:
        stages(session, args.frames, trees, labels, args.workdir)
        return
    decodes: list[dict] = []
    tuned: list[dict] = []
    runs: dict[int, list[dict]] = {k: [] for k in range(len(trees))}
    ratios: dict[int, list[float]] = {k: [] for k in range(len(trees))}
    print("$ " + " ".join([sys.executable, *sys.argv]), flush=True)
    for r in range(args.repeats):
        d = decode_once(session, args.frames)
        decodes.append(d)
        tuned.append(decode_once(session, args.frames, keep_freed=True))
        order = list(range(len(trees)))
        order = order[r % len(order):] + order[:r % len(order)]
        line = [f"round {r + 1}: decode once {sum(d['wall']):.2f} s"]
        for k in order:
            run = run_view(session, args.workdir / f"view-{k}.rrd", args.frames, trees[k], args.workdir / "cache",
                           extra)
            runs[k].append(run)
            ratios[k].append(run["wall"] / sum(d["wall"]))
            line.append(f"tree {k + 1} {run['wall']:.2f} s ({ratios[k][-1]:.2f}x)")
        print("  " + ", ".join(line), flush=True)

    n = decodes[0]["frames"]
    med = statistics.median
    print(f"\n{session}: {n} frames at 1920x1080, JPEG images, depth given; medians of {args.repeats} interleaved "
          "rounds")
    parts_wall = [med(d["wall"][i] for d in decodes) for i in range(4)]
    parts_cpu = [med(d["cpu"][i] for d in decodes) for i in range(4)]
    once = med(sum(d["wall"]) for d in decodes)
    half = med(sum(d["wall"]) - d["wall"][1] + d["right_half_wall"] for d in decodes)
    print(f"decode once (one thread, fresh process, start-up not counted): {once:.2f} s = {1000 * once / n:.1f} "
          f"ms/frame: " + ", ".join(f"{p} {1000 * w / n:.1f} ms (CPU {1000 * c / n:.1f})"
                                    for p, w, c in zip(PARTS, parts_wall, parts_cpu)))
    print(f"  at the size the viewer needs (right JPEG at 1/2): {half:.2f} s = {1000 * half / n:.1f} ms/frame "
          f"(right {1000 * med(d['right_half_wall'] for d in decodes) / n:.1f} ms)")
    kept = med(sum(d["wall"]) for d in tuned)
    print(f"  with glibc keeping freed memory (no page faults for each new frame buffer): {kept:.2f} s = "
          f"{1000 * kept / n:.1f} ms/frame: " + ", ".join(
              f"{p} {1000 * med(d['wall'][i] for d in tuned) / n:.1f} ms" for i, p in enumerate(PARTS)))
    print(f"  frames/s of decoding once: {n / once:.1f}; 1.2x decode once = {1.2 * once:.2f} s = "
          f"{n / (1.2 * once):.1f} frames/s end to end")
    header = ("tree", "frames/s end to end", "wall s", "ratio to decode once (to the 1/2-right decode; to the "
              "decode without page faults)",
              "run's own frames/s", "split s: next frame / images / prepare / log", "CPU ms/frame", "MB/frame")
    print("\n| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for k, label in enumerate(labels):
        rs = runs[k]
        wall = med(r["wall"] for r in rs)
        split = " / ".join(f"{med(r['split'][i] for r in rs):.2f}" for i in range(4))
        row = (f"{k + 1}: {label}", f"{n / wall:.1f}", f"{wall:.2f}",
               f"{med(ratios[k]):.2f} ({wall / half:.2f}; {wall / kept:.2f})",
               f"{med(r['frames'] / r['own_s'] for r in rs):.1f}",
               split, f"{1000 * med(r['cpu'] for r in rs) / n:.1f}", f"{med(r['rrd_mb'] for r in rs) / n:.3f}")
        print("| " + " | ".join(row) + " |")
    if args.psnr:
        print()
        for k, label in enumerate(labels):
            p = psnr_of(args.workdir / f"view-{k}.rrd", session, trees[k])
            print(f"tree {k + 1} video PSNR vs the source images: " + ", ".join(
                f"{side} median {v[0]:.2f} dB, min {v[1]:.2f} dB ({v[2]} frames)" for side, v in p.items()))


if __name__ == "__main__":
    main()
