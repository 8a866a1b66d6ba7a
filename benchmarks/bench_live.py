"""`contact-viz SESSION --follow` on a session recorded in real time: latency and keeping up.

A finished synthetic session (rendered once, cached under --dir) is played into a new folder at
--fps by a player process (the recorder contract: each file under a hidden temporary name, then
renamed; right, mask, depth, left, then its force.csv line), while the real command follows it:

    contact-viz view LIVE --follow --from-start --idle-timeout 3 --save OUT.rrd

and its summary is read: the latency from a frame's files being complete to its data being logged
(median, 95th percentile, max; frames logged whole) and how many frames it showed only in the
series (behind: the newest frame is shown whole, the older ones as series only; with SGBM those
get no distance). Keeping up = every frame after the first few logged whole.

    python benchmarks/bench_live.py                       # the three cases of the README
    python benchmarks/bench_live.py --case 720p-depth --frames 300 --repeats 3
    python benchmarks/bench_live.py --memory 12000     # the follower's memory over a long session
    python benchmarks/bench_live.py --compare OLD/src NEW/src --repeats 3   # two source trees side by side
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

CASES = {  # name -> (size, keep depth/, frames/s the recorder writes)
    "720p-depth": ("1280x720", True, 30.0),
    "1080p-depth": ("1920x1080", True, 30.0),
    "720p-stereo": ("1280x720", False, 10.0),
}
PLAYER = r"""
import os, shutil, sys, time
from pathlib import Path
src, dst, fps = Path(sys.argv[1]), Path(sys.argv[2]), float(sys.argv[3])
total = int(sys.argv[4]) if len(sys.argv) > 4 else 0  # > 0: play this many frames, cycling over the source's
folders = [d for d in ("right", "masks", "depth", "left") if (src / d).is_dir()]
stems = sorted(p.stem for p in (src / "left").iterdir() if not p.name.startswith("."))
for name in ("K.txt", "session.json"):
    shutil.copy(src / name, dst / name)
force = (src / "force.csv").read_bytes().splitlines(keepends=True)
data = [{d: [(p.name, p.read_bytes()) for p in (src / d).glob(stem + ".*")][0] for d in folders} for stem in stems]
for d in folders:
    (dst / d).mkdir()
fd = os.open(dst / "force.csv", os.O_WRONLY | os.O_CREAT | os.O_APPEND)
os.write(fd, force[0])
print("ready", flush=True)
sys.stdin.readline()
t0 = time.monotonic() + 0.2
late = 0.0
for k in range(total or len(data)):
    files = data[k % len(data)]
    wait = t0 + k / fps - time.monotonic()
    if wait > 0:
        time.sleep(wait)
    late = max(late, -wait)
    for d in folders:
        name, content = files[d]
        name = f"{k:06d}" + name[name.index("."):]
        tmp = dst / d / f".{name}.tmp"
        tmp.write_bytes(content)
        os.rename(tmp, dst / d / name)
    os.write(fd, f"{k}".encode() + force[k % len(data) + 1][force[k % len(data) + 1].index(b","):])
print(f"played {total or len(data)} frames, at most {late * 1000:.1f} ms late", flush=True)
"""
SUMMARY = re.compile(r"latency \(files complete -> logged\): median (\S+) ms, 95th percentile (\S+) ms, max (\S+) ms; "
                     r"frames shown only in the series: (\d+) \((\d+) without a distance\); timed out: (\d+)")


def source(cache: Path, case: str, frames: int) -> Path:
    size, keep_depth, _ = CASES[case]
    out = cache / f"{case}-{frames}"
    if not out.is_dir():
        tmp = cache / f".{out.name}.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        subprocess.run([sys.executable, "-m", "contact_viz.cli", "synth", str(tmp), "--frames", str(frames),
                        "--size", size, "--seed", "11", "--phantom", "kidney"], check=True, capture_output=True)
        if not keep_depth:
            shutil.rmtree(tmp / "depth")
        os.rename(tmp, out)
    return out


def run_once(src: Path, work: Path, fps: float, cache_dir: Path, tree: Path | None = None) -> dict:
    """One follow of ``src`` played at ``fps``; ``tree``: the source tree (its src/) the follower runs from."""
    env = dict(os.environ)
    if tree is not None:
        env["PYTHONPATH"] = str(tree)
    live = work / "live"
    shutil.rmtree(live, ignore_errors=True)
    live.mkdir(parents=True)
    player = subprocess.Popen([sys.executable, "-c", PLAYER, str(src), str(live), str(fps)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    assert player.stdout.readline().strip() == "ready"
    follower = subprocess.Popen([sys.executable, "-m", "contact_viz.cli", "view", str(live), "--follow",
                                 "--from-start", "--idle-timeout", "3", "--save", str(work / "out.rrd"),
                                 "--cache-dir", str(cache_dir)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    time.sleep(2.0)  # the follower's start-up (imports) before the first frame
    player.stdin.write("go\n")
    player.stdin.flush()
    played = player.stdout.readline().strip()
    player.wait(timeout=600)
    stdout, stderr = follower.communicate(timeout=600)
    match = SUMMARY.search(stdout)
    if follower.returncode != 0 or match is None:
        raise SystemExit(f"follower failed ({follower.returncode}):\n{stdout}\n{stderr}")
    whole = int(re.search(r"^(\d+) frames? in", stdout, re.MULTILINE).group(1))
    p50, p95, worst = (float(v) for v in match.groups()[:3])
    return {"whole": whole, "series_only": int(match.group(4)), "no_distance": int(match.group(5)),
            "timed_out": int(match.group(6)), "p50_ms": p50, "p95_ms": p95, "max_ms": worst, "player": played}


def memory(cache: Path, total: int, fps: float = 100.0) -> None:
    """The follower's resident memory while a 160x96 session of ``total`` frames is played at ``fps``."""
    src = cache / "memory-source"
    if not src.is_dir():
        subprocess.run([sys.executable, "-m", "contact_viz.cli", "synth", str(src), "--frames", "40", "--size",
                        "160x96", "--seed", "3"], check=True, capture_output=True)
    live = cache / "work" / "memory"
    shutil.rmtree(live, ignore_errors=True)
    live.mkdir(parents=True)
    player = subprocess.Popen([sys.executable, "-c", PLAYER, str(src), str(live), str(fps), str(total)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert player.stdout.readline().strip() == "ready"
    follower = subprocess.Popen([sys.executable, "-m", "contact_viz.cli", "view", str(live), "--follow", "--from-start",
                                 "--idle-timeout", "3", "--save", str(cache / "work" / "memory.rrd")],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(2.0)
    player.stdin.write("go\n")
    player.stdin.flush()
    print(f"{'s':>5} {'frames written':>14} {'follower RSS MB':>15}")
    started = time.monotonic()
    while player.poll() is None:
        time.sleep(5.0)
        written = len(os.listdir(live / "left"))
        try:
            rss = next(int(line.split()[1]) for line in open(f"/proc/{follower.pid}/status") if line.startswith("VmRSS"))
        except (OSError, StopIteration):
            break
        print(f"{time.monotonic() - started:5.0f} {written:14d} {rss / 1024:15.1f}", flush=True)
    stdout, _ = follower.communicate(timeout=600)
    print(stdout.splitlines()[0] if stdout else "")
    print(next((line for line in stdout.splitlines() if line.startswith("latency")), ""))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--case", choices=sorted(CASES), action="append")
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--dir", type=Path, default=Path("/tmp/contact-viz-bench-live"))
    parser.add_argument("--work", type=Path, default=Path("/dev/shm/contact-viz-bench-live") if Path("/dev/shm").is_dir()
                        else None, help="where the live session is written [default: a tmpfs, /dev/shm: at 1080p the "
                        "recorder writes 250 MB/s (8 MB of depth a frame), more than this machine's disk takes "
                        "without stalling it; else under --dir]")
    parser.add_argument("--json", type=Path, help="also write the figures here")
    parser.add_argument("--compare", type=Path, nargs="+", metavar="TREE/src",
                        help="follow with each of these source trees in turn (interleaved runs, the order rotating "
                        "every round), side by side; default: the installed package")
    parser.add_argument("--memory", type=int, metavar="FRAMES", help="only measure the follower's memory over a "
                        "160x96 session of FRAMES frames played at 100 frames/s")
    args = parser.parse_args()
    args.dir.mkdir(parents=True, exist_ok=True)
    if args.memory:
        memory(args.dir, args.memory)
        return
    work = args.work or args.dir / "work"
    print(f"the live session is written to {work}")
    figures = {}
    trees = [tree.resolve() for tree in args.compare] if args.compare else [None]
    names = [f"{k + 1}: {tree}" if tree is not None else "installed" for k, tree in enumerate(trees)]
    print(f"{'case':<13} {'tree':<6} {'fps':>4} {'frames':>6} {'whole':>6} {'series only':>11} {'no distance':>11} "
          f"{'median ms':>9} {'p95 ms':>7} {'max ms':>7}")
    for case in args.case or list(CASES):
        _, _, fps = CASES[case]
        src = source(args.dir, case, args.frames)
        runs: dict[int, list[dict]] = {k: [] for k in range(len(trees))}
        for round_ in range(args.repeats):  # interleaved: the machine's speed drifts
            for k in (round_ + j for j in range(len(trees))):
                k %= len(trees)
                runs[k].append(run_once(src, work, fps, args.dir / "cache", trees[k]))
        for k, name in enumerate(names):
            med = {key: statistics.median(r[key] for r in runs[k]) for key in runs[k][0] if key != "player"}
            figures.setdefault(case, {})[name] = {"fps": fps, "frames": args.frames, "runs": runs[k], "median": med}
            print(f"{case:<13} {k + 1:<6} {fps:>4.0f} {args.frames:>6} {med['whole']:>6.0f} "
                  f"{med['series_only']:>11.0f} {med['no_distance']:>11.0f} {med['p50_ms']:>9.0f} "
                  f"{med['p95_ms']:>7.0f} {med['max_ms']:>7.0f}")
            for r in runs[k]:
                print(f"    run: {r['whole']} whole, {r['series_only']} series only, median {r['p50_ms']:.0f} ms, "
                      f"p95 {r['p95_ms']:.0f} ms; player: {r['player']}")
    for k, name in enumerate(names):
        print(f"tree {k + 1}: {name}")
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2))


if __name__ == "__main__":
    main()
