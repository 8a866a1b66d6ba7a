"""Benchmark: the visual debugger (`contact-viz view SESSION --save out.rrd`) on 1920x1080 synthetic sessions.

Targets (2-core machine, default options): at least 30 frames/s end to end (process start
included) for a session whose frames are JPEG files and for one whose frames are PNG files, 150
frames or more; at most 0.15 MB of .rrd per frame (aim 0.1); memory flat in the session length.

Makes (once, cached under --workdir) a 1080p synthetic session of N frames (JPEG images, as
`contact-viz synth` writes them) and a copy whose left/right images are PNG files. Then, for each
session and each --images mode asked for, runs the CLI in a fresh process, the runs of the modes
interleaved (the machine's speed drifts; medians of --repeats), and prints: frames/s end to end,
CPU time per frame (user + sys of the process: less sensitive than wall time to other processes
on a shared machine), MB of .rrd per frame, the split of the run loop's time, peak RSS, and the
same for half the frames (memory flat in the length). For --images video it decodes the left video
back with PyAV and prints its PSNR against the source images, and on the Middlebury motorcycle
pair (skimage.data.stereo_motorcycle, upscaled to 1920x1080 and panned 2 px a frame).

Run: .venv/bin/python benchmarks/bench_viewer.py [--frames 150] [--repeats 3] [--images video jpeg]
     .venv/bin/python benchmarks/bench_viewer.py --compare OLD/src NEW/src --repeats 3   # trees side by side
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def make_sessions(workdir: Path, frames: int) -> tuple[Path, Path]:
    """The 1080p JPEG session (synth) and its PNG copy (masks, depth, ... linked), cached."""
    import cv2

    from contact_viz.synth import SynthParams, generate_session

    jpeg = workdir / f"cup-1080p-{frames}"
    if not (jpeg / "truth.csv").exists():
        print(f"generating {jpeg} ...", flush=True)
        t0 = time.perf_counter()
        generate_session(jpeg, SynthParams(phantom="cup", frames=frames, seed=0), overwrite=True)
        print(f"  synth: {(time.perf_counter() - t0) / frames:.2f} s/frame at 1920x1080", flush=True)
    png = workdir / f"cup-1080p-{frames}-png"
    if not (png / "done").exists():
        png.mkdir(parents=True, exist_ok=True)
        for entry in jpeg.iterdir():
            if entry.name not in ("left", "right") and not (png / entry.name).exists():
                os.symlink(entry.resolve(), png / entry.name)
        for side in ("left", "right"):
            (png / side).mkdir(exist_ok=True)
            for image in sorted((jpeg / side).glob("*.jpg")):
                cv2.imwrite(str(png / side / f"{image.stem}.png"), cv2.imread(str(image)))
        (png / "done").write_text("")
    return jpeg, png


def run_view(session: Path, out: Path, frames: int, images: str, cache: Path, src: Path | None = None) -> dict:
    """`contact-viz view` in a fresh process: wall s, CPU s (user + sys), peak RSS MB, .rrd MB, its time split.

    ``src``: import contact_viz from this source tree (another checkout's src/) instead."""
    env = dict(os.environ, CONTACT_VIZ_CACHE=str(cache))
    if src is not None:
        env["PYTHONPATH"] = str(src)
    cmd = [sys.executable, "-m", "contact_viz.cli", "view", str(session), "--save", str(out), "--end", str(frames),
           "--images", images]
    t0 = time.perf_counter()
    out_file = tempfile.TemporaryFile(mode="w+")
    proc = subprocess.Popen(cmd, stdout=out_file, stderr=subprocess.STDOUT, text=True, env=env)
    # peak RSS: the child's VmHWM (high-water mark since its exec), polled; the rusage of wait4 would count the
    # copy of this (large) process that the child was before its exec
    peak_kb = 0
    status_path = Path(f"/proc/{proc.pid}/status")
    while True:
        try:
            match = re.search(r"VmHWM:\s+(\d+) kB", status_path.read_text())
            peak_kb = max(peak_kb, int(match.group(1))) if match else peak_kb
        except (OSError, ValueError):
            pass
        if os.waitid(os.P_PID, proc.pid, os.WEXITED | os.WNOHANG | os.WNOWAIT) is not None:
            break
        time.sleep(0.05)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = status
    wall = time.perf_counter() - t0
    out_file.seek(0)
    text = out_file.read()
    if status != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{text}")
    split = re.search(r"time: next frame ([\d.]+) s, images ([\d.]+) s, prepare ([\d.]+) s, log ([\d.]+) s", text)
    return {"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime, "peak_rss_mb": peak_kb / 1024,
            "rrd_mb": out.stat().st_size / 1e6, "split": [float(v) for v in split.groups()]}


def video_psnr(rrd: Path, session: Path, side: str = "left") -> list[float]:
    """PSNR (dB) of every logged frame of the ``side`` video, decoded with PyAV, against the session's image
    (shrunk by pixel averaging to the video's size: the right image is logged at half size)."""
    entity = f"world/camera/{side}/image"
    import av
    import cv2
    from rerun.chunk import RrdReader

    from contact_viz.io.session import open_session
    from contact_viz.viz.video import i420_to_rgb, psnr_db

    samples = []
    for chunk in RrdReader(rrd).stream():
        if chunk.entity_path.lstrip("/") != entity or chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        if "VideoStream:sample" not in batch.schema.names:
            continue
        column = batch.column("VideoStream:sample")
        for frame, value in zip(batch.column("frame").to_pylist(), column):
            if value.is_valid:
                samples.append((frame, value.values[0].values.to_numpy(zero_copy_only=False).tobytes()))
    samples.sort()
    decoder = av.CodecContext.create("libdav1d", "r")
    decoded = []
    for _, data in samples:
        decoded += decoder.decode(av.Packet(data))
    decoded += decoder.decode(None)
    opened = open_session(session)
    out = []
    for (f, _), d in zip(samples, decoded):
        rgb = i420_to_rgb(d.to_ndarray())
        source = cv2.cvtColor(cv2.imread(str(opened.image_path(side, f))), cv2.COLOR_BGR2RGB)
        if source.shape != rgb.shape:
            source = cv2.resize(source, rgb.shape[1::-1], interpolation=cv2.INTER_AREA)
        out.append(psnr_db(rgb, source))
    return out


def middlebury_psnr(n: int = 30) -> tuple[float, float, float]:
    """Median and minimum PSNR (dB) and kB per frame of the default video encoding on the Middlebury
    motorcycle left image, upscaled to 1920x1080 and panned 2 px a frame."""
    import cv2
    from skimage import data

    from contact_viz.viz.video import VideoEncoder, i420_to_rgb, psnr_db, rgb_to_i420

    left = data.stereo_motorcycle()[0]
    wide = cv2.resize(left, (1920 + 2 * n, 1080), interpolation=cv2.INTER_AREA)
    frames = [np.ascontiguousarray(wide[:, 2 * i:2 * i + 1920]) for i in range(n)]
    encoder = VideoEncoder(1920, 1080, 30.0)
    samples = [s for i, f in enumerate(frames) for s in encoder.encode(rgb_to_i420(f), i)] + encoder.flush()
    import av

    decoder = av.CodecContext.create("libdav1d", "r")
    decoded = [d for s in samples for d in decoder.decode(av.Packet(s.data))] + decoder.decode(None)
    psnrs = [psnr_db(i420_to_rgb(d.to_ndarray()), f) for d, f in zip(decoded, frames)]
    return float(np.median(psnrs)), float(min(psnrs)), sum(len(s.data) for s in samples) / len(samples) / 1e3


def cost_per_image(jpeg: Path, png: Path, n: int = 20) -> dict[str, float]:
    """CPU ms per 1080p image of each image step, one at a time (what the 2 cores must share per frame)."""
    import cv2

    from contact_viz.viz.video import VideoEncoder, VideoParams, rgb_to_i420

    def cpu_ms(step, items):
        t0 = time.process_time()
        out = [step(item) for item in items]
        return 1000 * (time.process_time() - t0) / len(items), out

    jpegs = sorted((jpeg / "left").glob("*.jpg"))[:n]
    pngs = sorted((png / "left").glob("*.png"))[:n]
    costs = {}
    costs["decode JPEG"], rgbs = cpu_ms(lambda p: cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB), jpegs)
    costs["decode PNG"], _ = cpu_ms(lambda p: cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB), pngs)
    costs["RGB -> I420"], frames = cpu_ms(rgb_to_i420, rgbs)
    costs["encode JPEG q85"], _ = cpu_ms(lambda f: cv2.imencode(".jpg", f, [cv2.IMWRITE_JPEG_QUALITY, 85]), rgbs)
    for codec in ("av1", "h264"):
        encoder = VideoEncoder(1920, 1080, 30.0, VideoParams(codec=codec))
        costs[f"encode {codec}"], _ = cpu_ms(lambda item: encoder.encode(item[1], item[0]), list(enumerate(frames)))
        encoder.flush()
    return costs


def cost_of_checks(session_dir: Path, n: int = 20) -> dict[str, float]:
    """CPU ms per 1080p frame of the diagnostics: reading the grey pair and measuring, at the default analysis
    resolution and at full resolution (contact_viz.checks)."""
    from contact_viz.checks.frame import measure_frame
    from contact_viz.checks.params import DiagnosticParams
    from contact_viz.io.session import open_session
    from contact_viz.pipeline.check import grey_step, load_grey

    session = open_session(session_dir)
    K = session.calibration.K
    indices = range(0, min(len(session), 5 * n), 5)
    frames = [session.load_frame(i) for i in indices]
    costs = {}
    full = DiagnosticParams(analysis_width_px=1 << 16)
    for label, params in (("default", DiagnosticParams()), ("full resolution", full)):
        step = grey_step(session, params)
        t0 = time.process_time()
        greys = [(load_grey(session, "left", i, step), load_grey(session, "right", i, step)) for i in indices]
        t1 = time.process_time()
        for frame, (left, right) in zip(frames, greys):
            measure_frame(frame.tool_mask, frame.depth_m, left, right, float(K[0][0]),
                          float(session.calibration.baseline_m), params, evidence=True)
        t2 = time.process_time()
        costs[f"grey pair ({label}, 1/{step})"] = 1000 * (t1 - t0) / len(frames)
        costs[f"measurements ({label})"] = 1000 * (t2 - t1) / len(frames)
    return costs


def compare(trees: list[Path], sessions: dict[str, Path], modes: list[str], frames: int, repeats: int,
            workdir: Path, cache: Path) -> None:
    """Each tree on each session and --images mode, every case once per round (the machine's speed drifts)."""
    runs: dict[tuple, list[dict]] = {}
    for _ in range(repeats):
        for name, session in sessions.items():
            for images in modes:
                for k, src in enumerate(trees):
                    out = workdir / f"compare-{k}.rrd"
                    runs.setdefault((name, images, k), []).append(run_view(session, out, frames, images, cache, src))
    print(f"{frames} frames at 1920x1080, `contact-viz view SESSION --save out.rrd --images MODE`, medians of {repeats}"
          " interleaved runs:")
    for (name, images, k), rs in runs.items():
        wall = statistics.median(r["wall_s"] for r in rs)
        cpu = statistics.median(r["cpu_s"] for r in rs)
        print(f"  {name} session, --images {images}, {trees[k]}: {frames / wall:.1f} frames/s, "
              f"CPU {1000 * cpu / frames:.0f} ms/frame, {statistics.median(r['rrd_mb'] for r in rs) / frames:.3f} MB/frame")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=150, help="frames of the session (and runs on half of them)")
    parser.add_argument("--repeats", type=int, default=1, help="runs of each case (medians are reported)")
    parser.add_argument("--images", nargs="+", default=["video", "jpeg"], choices=["video", "jpeg", "raw"])
    parser.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "contact-viz-bench")
    parser.add_argument("--compare", nargs="+", type=Path, metavar="SRC",
                        help="instead: frames/s and CPU of each SRC tree (another checkout's src/), interleaved")
    args = parser.parse_args()

    import warnings

    warnings.simplefilter("ignore")
    args.workdir.mkdir(parents=True, exist_ok=True)
    jpeg, png = make_sessions(args.workdir, args.frames)
    cache = args.workdir / "cache"
    n = args.frames
    if args.compare:
        compare(args.compare, {"JPEG": jpeg, "PNG": png}, args.images, n, args.repeats, args.workdir, cache)
        return
    costs = cost_per_image(jpeg, png)
    print("CPU per 1080p image, one at a time (a frame has two): "
          + ", ".join(f"{k} {v:.1f} ms" for k, v in costs.items()))
    print("CPU per 1080p frame of the diagnostics (JPEG session): "
          + ", ".join(f"{k} {v:.1f} ms" for k, v in cost_of_checks(jpeg).items()))
    for frames in (n, n // 2):
        cases = [(name, session, images) for name, session in (("JPEG", jpeg), ("PNG", png))
                 for images in args.images]
        runs: dict[tuple, list[dict]] = {case[::2]: [] for case in cases}
        for _ in range(args.repeats):  # interleaved: every case once per round
            for name, session, images in cases:
                out = args.workdir / f"view-{name}-{images}-{frames}.rrd"
                runs[(name, images)].append(run_view(session, out, frames, images, cache))
        print(f"\n{frames} frames at 1920x1080, `contact-viz view SESSION --save out.rrd --images MODE`, "
              f"medians of {args.repeats}:")
        for (name, images), rs in runs.items():
            med = {k: statistics.median(r[k] for r in rs) for k in ("wall_s", "cpu_s", "peak_rss_mb", "rrd_mb")}
            split = [statistics.median(r["split"][i] for r in rs) * 1000 / frames for i in range(4)]
            print(f"  {name} session, --images {images}: {frames / med['wall_s']:.1f} frames/s end to end "
                  f"({med['wall_s']:.1f} s), CPU {1000 * med['cpu_s'] / frames:.0f} ms/frame, "
                  f"{med['rrd_mb'] / frames:.3f} MB/frame, peak RSS {med['peak_rss_mb']:.0f} MB")
            print(f"    run loop ms/frame: next frame {split[0]:.1f}, images {split[1]:.1f}, "
                  f"prepare {split[2]:.1f}, log {split[3]:.1f}")
            if images == "video" and frames == n:
                session = jpeg if name == "JPEG" else png
                for side in ("left", "right"):
                    psnrs = video_psnr(args.workdir / f"view-{name}-{images}-{frames}.rrd", session, side)
                    print(f"    {side} video PSNR vs the source images: median {np.median(psnrs):.1f} dB, "
                          f"min {min(psnrs):.1f} dB over {len(psnrs)} frames")
    median, low, kb = middlebury_psnr()
    print(f"\nMiddlebury motorcycle (left, 1920x1080, panned 2 px/frame), default AV1: PSNR median {median:.1f} dB, "
          f"min {low:.1f} dB, {kb:.1f} kB/frame")


if __name__ == "__main__":
    main()
