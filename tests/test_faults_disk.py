"""Machine faults on the output side: a full disk, a read-only output or cache place, a process killed
with SIGKILL at any moment, two processes sharing one cache, a cache entry torn by hand.

Every case runs the real console script in a subprocess (``python -m contact_viz.cli``) and asserts
what a user sees and what is left on disk:

* a failing command exits with status 2 within a few seconds, prints no traceback, and its last
  stderr line is ONE ``error: PATH: what happened`` line naming the output the user asked for;
* nothing is left under the output's name, and no staging file (``.NAME.PID-NS.KIND``) beside it;
* the input session is byte-for-byte untouched (every file hashed before and after);
* a cache that cannot be written is a warning, not a failure: the results equal a run without it;
* after a SIGKILL the next run to the same cache and output removes the dead run's staging files
  and gives byte-identical results.

Full and read-only places are small tmpfs mounts (root only; skipped otherwise).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from contact_viz.synth import SynthParams, generate_session

sys.path.insert(0, str(Path(__file__).parent))
from test_importers import make_dvrk  # noqa: E402  (the importer tests' recording builder)

CLI = [sys.executable, "-m", "contact_viz.cli"]
H, W, N_FRAMES = 80, 128, 6  # tiny: every command below runs in well under a second
STAGING = re.compile(r"^\..+\.\d+-\d+\.[A-Za-z0-9_.-]+$")  # contact_viz.io.atomic.staging_path
MAX_SECONDS = 20.0  # "within a few seconds", with room for a loaded test machine


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def run(*args: str | Path, cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess:
    env = {**os.environ, "COLUMNS": "160", "CONTACT_VIZ_CACHE": str(cwd / "default-cache")}
    start = time.monotonic()
    done = subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, cwd=cwd, env=env,
                          start_new_session=True, timeout=timeout)
    done.seconds = time.monotonic() - start
    return done


def start(*args: str | Path, cwd: Path) -> subprocess.Popen:
    env = {**os.environ, "COLUMNS": "160", "CONTACT_VIZ_CACHE": str(cwd / "default-cache")}
    return subprocess.Popen([*CLI, *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=cwd, env=env, start_new_session=True)


def tree_hash(root: Path) -> dict[str, str]:
    """Every entry under ``root``: file bytes hashed, links by their target, folders by name."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in sorted(dirnames + filenames):
            path = Path(dirpath) / name
            rel = str(path.relative_to(root))
            if path.is_symlink():
                out[rel] = f"link:{os.readlink(path)}"
            elif path.is_file():
                out[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
            else:
                out[rel] = "dir"
    return out


def staging_files(root: Path) -> list[str]:
    """Hidden entries (files or folders) anywhere under ``root``: staging files (``STAGING``) or any
    other temporary a writer left (none of the outputs or caches has a hidden file of its own)."""
    found = []
    for dirpath, dirnames, filenames in os.walk(root):
        found += [str(Path(dirpath) / n) for n in dirnames + filenames if n.startswith(".")]
    return found


def error_line(done: subprocess.CompletedProcess, *names: Path) -> str:
    """Exit 2, no traceback, the last stderr line is the only ``error:`` line and names one of ``names``."""
    err = done.stderr
    assert done.returncode == 2, (done.returncode, err[-3000:])
    assert "Traceback" not in err and "Traceback" not in done.stdout, err[-3000:]
    lines = err.strip().splitlines()
    assert lines and lines[-1].startswith("error: "), err[-3000:]
    assert sum(line.startswith("error:") for line in lines) == 1, err[-3000:]
    assert any(str(name) in lines[-1] for name in names), ([str(n) for n in names], lines[-1])
    assert done.seconds < MAX_SECONDS, done.seconds
    return lines[-1]


def _mount(path: Path, options: str) -> None:
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    path.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip() or done.returncode}")


def _umount(path: Path) -> None:
    if subprocess.run(["umount", str(path)], capture_output=True).returncode != 0:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def fill(directory: Path, leave_kb: int = 0) -> Path:
    """Fill the filesystem of ``directory`` until the next write fails, then free ``leave_kb`` kB."""
    filler = directory / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        for size in (65536, 4096, 1):  # big steps, then page by page, then the last bytes
            try:
                while True:
                    os.write(fd, b"\0" * size)
            except OSError as exc:
                assert exc.errno == errno.ENOSPC, exc
    finally:
        os.close(fd)
    if leave_kb:
        os.truncate(filler, max(0, filler.stat().st_size - leave_kb * 1024))
    return directory


@pytest.fixture
def tmpfs(tmp_path):
    """``tmpfs(name, leave_kb=None, ro=False)``: a 1 MB tmpfs at tmp_path/name, filled to the last page
    and then ``leave_kb`` kB freed (None: left empty), or mounted read-only; unmounted afterwards."""
    mounted = []

    def make(name: str, leave_kb: int | None = None, ro: bool = False) -> Path:
        where = tmp_path / name
        _mount(where, "ro,size=1m" if ro else "size=1m")
        mounted.append(where)
        return where if leave_kb is None else fill(where, leave_kb)

    try:
        yield make
    finally:
        for where in reversed(mounted):
            _umount(where)


@pytest.fixture
def full(tmpfs):
    """No space left at all."""
    return tmpfs("full", leave_kb=0)


@pytest.fixture
def nearly_full(tmpfs):
    """40 kB left: the first small files fit, the images do not."""
    return tmpfs("nearly", leave_kb=40)


@pytest.fixture
def three_pages(tmpfs):
    """12 kB left: three small files."""
    return tmpfs("pages", leave_kb=12)


@pytest.fixture
def readonly(tmpfs):
    """An empty tmpfs mounted read-only."""
    return tmpfs("ro", ro=True)


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> dict[str, Path]:
    """The inputs: a session with depth/, the same without (stereo pair only), two features CSVs
    long enough to fit a model, a model, and a dVRK recording to import."""
    root = tmp_path_factory.mktemp("faults")
    base = generate_session(root / "cup", SynthParams(phantom="cup", frames=N_FRAMES, seed=1, width=W, height=H))
    stereo = root / "pair"
    shutil.copytree(base, stereo)
    shutil.rmtree(stereo / "depth")
    train = []
    for seed in (1, 2):
        session = generate_session(root / f"train{seed}",
                                   SynthParams(phantom="cup", frames=80, seed=seed, width=W, height=H))
        csv_path = root / f"train{seed}.csv"
        done = run("extract", session, "-o", csv_path, "--processes", "1", cwd=root)
        assert done.returncode == 0, done.stderr
        train.append(csv_path)
    model = root / "model.json"
    done = run("fit", *train, "-o", model, cwd=root)
    assert done.returncode == 0, done.stderr
    dvrk = root / "recording"
    make_dvrk(dvrk)
    clean = root / "clean_stereo.csv"  # the stereo-only session's features with a fresh cache
    done = run("extract", stereo, "-o", clean, "--cache-dir", root / "clean-cache", "--processes", "1", cwd=root)
    assert done.returncode == 0, done.stderr
    return {"root": root, "base": base, "stereo": stereo, "train1": train[0], "train2": train[1], "model": model,
            "dvrk": dvrk, "clean_stereo": clean}


def _inputs(data) -> dict[str, dict[str, str]]:
    return {k: tree_hash(data[k]) for k in ("base", "stereo", "dvrk")}


def command(kind: str, data, out_dir: Path, tmp: Path) -> tuple[list, Path | list[Path]]:
    """The arguments of command ``kind`` writing into ``out_dir``, and the output paths its error may name."""
    cache = tmp / "cache"  # writable: only the output place is faulty here
    if kind == "extract":
        out = out_dir / "features.csv"
        return ["extract", data["base"], "-o", out, "--processes", "1"], out
    if kind == "check":
        out = out_dir / "check.json"
        return ["check", data["base"], "--json", out], out
    if kind == "depth":
        out = out_dir / "depth_out"
        return ["depth", data["stereo"], "-o", out, "--cache-dir", cache], out
    if kind == "batch":
        out = out_dir / "batch"
        return ["batch", data["base"], "-o", out, "--processes", "1", "--cache-dir", cache], out
    if kind == "fit":
        out = out_dir / "model.json"
        return ["fit", data["train1"], data["train2"], "-o", out], out
    if kind == "evaluate":
        out, per_frame = out_dir / "metrics.json", out_dir / "per_frame.csv"
        return ["evaluate", data["model"], data["base"], "--json", out, "--per-frame", per_frame,
                "--cache-dir", cache], [out, per_frame]
    if kind == "predict":
        out = out_dir / "predictions.csv"
        return ["predict", data["model"], data["base"], "-o", out, "--cache-dir", cache], out
    if kind == "import":
        out = out_dir / "imported"
        return ["import", "dvrk", data["dvrk"], out, "--copy"], out
    if kind == "synth":
        out = out_dir / "synth"
        return ["synth", out, "--frames", "4", "--size", f"{W}x{H}", "--seed", "3"], out
    raise AssertionError(kind)


def named(kind: str, data, out_dir: Path, tmp: Path) -> tuple[list, list[Path]]:
    args, out = command(kind, data, out_dir, tmp)
    return args, out if isinstance(out, list) else [out]


ALL = ("extract", "check", "depth", "batch", "fit", "evaluate", "predict", "import", "synth")


def assert_fails_cleanly(kind: str, data, place: Path, tmp_path: Path) -> str:
    args, outs = named(kind, data, place, tmp_path)
    before, inputs = sorted(os.listdir(place)), _inputs(data)
    done = run(*args, cwd=tmp_path)
    line = error_line(done, *outs)
    assert sorted(os.listdir(place)) == before, f"left in {place}: {sorted(set(os.listdir(place)) - set(before))}"
    assert not staging_files(place) and not staging_files(tmp_path / "cache")
    assert _inputs(data) == inputs
    return line


# --------------------------------------------------------------------------------------------
# A full disk, a read-only place: every command stops with one line and leaves nothing
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ALL)
def test_full_disk_output_is_one_line_and_nothing_left(kind, data, full, tmp_path):
    line = assert_fails_cleanly(kind, data, full, tmp_path)
    assert "no space left on the device" in line, line


@pytest.mark.parametrize("kind", ("depth", "import", "synth"))
def test_nearly_full_disk_removes_what_was_written_so_far(kind, data, nearly_full, tmp_path):
    line = assert_fails_cleanly(kind, data, nearly_full, tmp_path)
    assert "no space left on the device" in line, line


def test_batch_on_a_disk_that_fills_keeps_the_finished_steps_and_resumes(data, three_pages, tmp_path):
    """batch is resumable by design: a step's files appear whole (atomically) and are recorded in
    batch.json; the disk filling up in a later step stops the run with one line, leaves those whole
    files and no staging file, and the run after space is freed reuses them."""
    clean = tmp_path / "clean"
    assert run("batch", data["base"], "-o", clean, "--processes", "1", "--cache-dir", tmp_path / "cache",
               cwd=tmp_path).returncode == 0
    args, (out,) = named("batch", data, three_pages, tmp_path)
    inputs = _inputs(data)
    error_line(run(*args, cwd=tmp_path), out)
    assert not staging_files(three_pages)
    left = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    assert left == ["cup/batch.json", "cup/features.csv", "cup/features.csv.json"], left
    assert (out / "cup" / "features.csv").read_bytes() == (clean / "cup" / "features.csv").read_bytes()
    (three_pages / "filler").unlink()
    done = run(*args, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "reused" in done.stdout, done.stdout
    assert (out / "cup" / "features.csv").read_bytes() == (clean / "cup" / "features.csv").read_bytes()
    assert json.loads((out / "cup" / "check.json").read_text())["checks"].keys() == \
        json.loads((clean / "cup" / "check.json").read_text())["checks"].keys()
    assert not staging_files(out)
    assert _inputs(data) == inputs


@pytest.mark.parametrize("kind", ("check", "depth", "batch", "evaluate", "import", "synth"))  # one per writer kind
def test_read_only_output_place_is_one_line_and_nothing_left(kind, data, readonly, tmp_path):
    line = assert_fails_cleanly(kind, data, readonly, tmp_path)
    assert "read-only file system" in line.lower(), line


def test_evaluate_writes_both_outputs_or_neither(data, full, tmp_path):
    """--per-frame fits on a writable disk, --json does not: the per-frame file must not stay either."""
    per_frame, metrics = tmp_path / "per_frame.csv", full / "metrics.json"
    done = run("evaluate", data["model"], data["base"], "--per-frame", per_frame, "--json", metrics,
               "--cache-dir", tmp_path / "cache", cwd=tmp_path)
    error_line(done, metrics)
    assert not per_frame.exists() and not metrics.exists()
    assert not staging_files(tmp_path) and not staging_files(full)


# --------------------------------------------------------------------------------------------
# Caches: a cache that cannot be written only warns; results equal a run without it
# --------------------------------------------------------------------------------------------


def assert_cache_only_warns(data, cache_dir: Path, tmp_path: Path, what: str = "depth") -> None:
    out = tmp_path / "features.csv"
    inputs = _inputs(data)
    done = run("extract", data["stereo"], "-o", out, "--cache-dir", cache_dir, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    warned = [line for line in done.stderr.splitlines() if "could not write the" in line]
    assert len(warned) == 1 and warned[0].startswith("warning: ") and f"{what} cache" in warned[0], done.stderr
    assert str(cache_dir) in warned[0], warned[0]
    assert out.read_bytes() == data["clean_stereo"].read_bytes()
    assert not staging_files(cache_dir) and not staging_files(tmp_path)
    assert _inputs(data) == inputs


def test_depth_cache_on_a_full_disk_only_warns(data, full, tmp_path):
    assert_cache_only_warns(data, full / "cache", tmp_path)


def test_depth_cache_on_a_read_only_mount_only_warns(data, readonly, tmp_path):
    assert_cache_only_warns(data, readonly / "cache", tmp_path)


def test_depth_cache_filling_up_during_the_run_warns_once(long_stereo, tmpfs, tmp_path):
    """72 kB left: the cache takes its probe and a few entries, then the disk is full."""
    cache = tmpfs("filling", leave_kb=72) / "cache"
    out = tmp_path / "features.csv"
    done = run("extract", long_stereo["session"], "-o", out, "--cache-dir", cache, "--processes", "1", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    warned = [line for line in done.stderr.splitlines() if "could not write the" in line]
    assert len(warned) == 1 and warned[0].startswith("warning: ") and "no space left" in warned[0], done.stderr
    assert 0 < len(cache_entries(cache)) < 40
    assert out.read_bytes() == long_stereo["clean"].read_bytes()
    assert not staging_files(cache.parent)


def test_depth_command_whose_only_output_is_the_cache_fails_on_a_full_disk(data, full, tmp_path):
    """`depth` without -o only fills the cache: a cache that cannot be written is its error (one line);
    with -o the depth files are its output and the cache is a warning."""
    inputs = _inputs(data)
    done = run("depth", data["stereo"], "--cache-dir", full / "cache", cwd=tmp_path)
    line = error_line(done, full / "cache")
    assert "no space left on the device" in line and "warning:" not in done.stderr, done.stderr
    out = tmp_path / "depth_out"
    done = run("depth", data["stereo"], "--cache-dir", full / "cache", "-o", out, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert sum("could not write the depth cache" in line for line in done.stderr.splitlines()) == 1, done.stderr
    assert len(list(out.glob("*.npy"))) == N_FRAMES
    assert not staging_files(full) and not staging_files(tmp_path)
    assert _inputs(data) == inputs


def test_depth_command_whose_cache_fills_up_during_the_run_stops_with_one_line(long_stereo, tmpfs, tmp_path):
    """`depth` without -o on a cache with room for its probe and a few entries: the run stops when the
    disk fills (one error line naming the cache, no warning first), it does not report the frames as done;
    the entries stored before are whole, and the next run with room reuses them."""
    cache = tmpfs("filling", leave_kb=72) / "cache"
    inputs = tree_hash(long_stereo["session"])
    done = run("depth", long_stereo["session"], "--cache-dir", cache, cwd=tmp_path)
    line = error_line(done, cache)
    assert "no space left on the device" in line and "warning:" not in done.stderr, done.stderr
    assert "computed" not in done.stdout, done.stdout
    stored = cache_entries(cache)
    assert 0 < len(stored) < 40 and not staging_files(cache.parent)
    roomy = tmp_path / "roomy"
    shutil.copytree(cache, roomy)
    done = run("depth", long_stereo["session"], "--cache-dir", roomy, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert f"{40 - len(stored)} computed" in done.stdout and f"{len(stored)} from cache" in done.stdout, done.stdout
    assert tree_hash(long_stereo["session"]) == inputs


def test_features_cache_on_a_full_disk_only_warns(data, full, tmp_path):
    """predict's features cache (kept for fit / evaluate / predict) on a full disk: a warning, the same output."""
    clean = tmp_path / "clean.csv"
    done = run("predict", data["model"], data["base"], "-o", clean, "--cache-dir", tmp_path / "cache", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    out = tmp_path / "predictions.csv"
    done = run("predict", data["model"], data["base"], "-o", out, "--cache-dir", full / "cache", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    warned = [line for line in done.stderr.splitlines() if "could not write the" in line]
    assert len(warned) == 1 and warned[0].startswith("warning: ") and "features cache" in warned[0], done.stderr
    assert out.read_bytes() == clean.read_bytes()
    assert not staging_files(full) and not staging_files(tmp_path)


# --------------------------------------------------------------------------------------------
# Caches survive anything: SIGKILL at any moment, two processes at once, a torn entry
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def long_stereo(data) -> dict[str, Path]:
    """A stereo-only session long enough (40 frames at 320x180) to be killed in the middle, and its
    clean features."""
    root = data["root"]
    full = generate_session(root / "long_full", SynthParams(phantom="cup", frames=40, seed=4, width=320, height=180))
    pair = root / "long_pair"
    shutil.copytree(full, pair)
    shutil.rmtree(pair / "depth")
    clean = root / "long_clean.csv"
    done = run("extract", pair, "-o", clean, "--cache-dir", root / "long-clean-cache", "--processes", "1", cwd=root)
    assert done.returncode == 0, done.stderr
    return {"session": pair, "clean": clean}


def cache_entries(cache: Path) -> list[Path]:
    return sorted(p for p in cache.rglob("*.png") if not p.name.startswith("."))


def kill_group(proc: subprocess.Popen) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=30)


@pytest.mark.parametrize("moment", ["0.3s", "0.8s", "1.5s", "1 entry", "20 entries"])
def test_sigkill_at_any_moment_then_the_next_run_is_identical(long_stereo, tmp_path, moment):
    cache, out = tmp_path / "cache", tmp_path / "out" / "features.csv"
    args = ("extract", long_stereo["session"], "-o", out, "--cache-dir", cache, "--processes", "2")
    proc = start(*args, cwd=tmp_path)
    try:
        value, unit = moment.split(" ", 1) if " " in moment else (moment[:-1], "s")
        deadline = time.monotonic() + 60
        if unit == "s":
            time.sleep(float(value))
        else:
            while len(cache_entries(cache)) < int(value) and proc.poll() is None and time.monotonic() < deadline:
                time.sleep(0.002)
    finally:
        kill_group(proc)
    done = run(*args, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert out.read_bytes() == long_stereo["clean"].read_bytes()
    assert not staging_files(cache), staging_files(cache)
    assert not staging_files(out.parent), staging_files(out.parent)
    assert len(cache_entries(cache)) == 40


def test_a_dead_processes_staging_files_are_swept_by_the_next_writer(long_stereo, tmp_path):
    """Staging files as a SIGKILL leaves them, made on purpose (a dead pid): the next run removes them."""
    cache, out = tmp_path / "cache", tmp_path / "out" / "features.csv"
    args = ("extract", long_stereo["session"], "-o", out, "--cache-dir", cache, "--processes", "1")
    assert run(*args, cwd=tmp_path).returncode == 0
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    entries = cache_entries(cache)
    planted = [entries[0].with_name(f".{entries[0].name}.{dead.pid}-123.tmp"),
               out.with_name(f".{out.name}.{dead.pid}-456.tmp")]
    for path in planted:
        path.write_bytes(b"half a file")
    done = run(*args, cwd=tmp_path)  # opening the cache sweeps it; writing features.csv sweeps beside it
    assert done.returncode == 0, done.stderr
    assert not any(p.exists() for p in planted), [p for p in planted if p.exists()]
    assert out.read_bytes() == long_stereo["clean"].read_bytes()


def test_two_extracts_share_one_cache(long_stereo, tmp_path):
    cache = tmp_path / "cache"
    outs = [tmp_path / f"out{k}" / "features.csv" for k in (1, 2)]
    procs = [start("extract", long_stereo["session"], "-o", out, "--cache-dir", cache, "--processes", "2",
                   cwd=tmp_path) for out in outs]
    for proc in procs:
        try:
            _, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                kill_group(proc)
        assert proc.returncode == 0, err
    for out in outs:
        assert out.read_bytes() == long_stereo["clean"].read_bytes()
    assert not staging_files(cache)
    assert len(cache_entries(cache)) == 40


@pytest.mark.parametrize("damage", ["half", "empty", "no end", "flipped byte"])
def test_a_torn_cache_entry_is_detected_and_recomputed(data, tmp_path, damage):
    """An entry damaged as a crash on a filesystem without atomic rename could leave it (cut short,
    empty, or with wrong bytes): it is not used, and is written again."""
    cache, out = tmp_path / "cache", tmp_path / "features.csv"
    args = ("extract", data["stereo"], "-o", out, "--cache-dir", cache, "--processes", "1")
    assert run(*args, cwd=tmp_path).returncode == 0
    entries = cache_entries(cache)
    assert len(entries) == N_FRAMES
    victim = entries[2]
    good = victim.read_bytes()
    if damage == "half":
        victim.write_bytes(good[: len(good) // 2])
    elif damage == "empty":
        victim.write_bytes(b"")
    elif damage == "no end":
        victim.write_bytes(good[:-12])  # everything but the IEND chunk
    else:
        data_at = good.index(b"IDAT") + 20
        victim.write_bytes(good[:data_at] + bytes([good[data_at] ^ 0x40]) + good[data_at + 1:])
    out.unlink()
    done = run(*args, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert out.read_bytes() == data["clean_stereo"].read_bytes()
    assert victim.read_bytes() == good  # recomputed and stored again


@pytest.mark.parametrize("damage", ["half", "rows lost"])
def test_a_torn_features_cache_entry_is_recomputed(data, tmp_path, damage):
    """The features cache (fit / evaluate / predict): an entry cut short, mid-row or at a row's end."""
    cache, out = tmp_path / "cache", tmp_path / "predictions.csv"
    args = ("predict", data["model"], data["base"], "-o", out, "--cache-dir", cache)
    assert run(*args, cwd=tmp_path).returncode == 0
    clean = out.read_bytes()
    (entry,) = (cache / "features").glob("*.csv")
    good = entry.read_bytes()
    lines = good.splitlines(keepends=True)
    entry.write_bytes(good[: len(good) // 2] if damage == "half" else b"".join(lines[:-2]))
    out.unlink()
    done = run(*args, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert out.read_bytes() == clean
    assert entry.read_bytes() == good


def test_a_torn_entry_is_refused_by_the_cache_itself(tmp_path):
    from contact_viz.geometry.stereo import SGBMParams
    from contact_viz.io.depth_cache import DisparityCache

    cache = DisparityCache(tmp_path, SGBMParams().resolve(W))
    disparity = np.full((H, W), 7.5, dtype=np.float32)
    disparity[:, :10] = np.nan
    path = tmp_path / "000000-abc.png"
    cache.save(path, disparity)
    good = path.read_bytes()
    np.testing.assert_array_equal(cache.load(path), disparity)
    for cut in (0, 8, 33, len(good) // 2, len(good) - 12, len(good) - 1):
        path.write_bytes(good[:cut])
        assert cache.load(path) is None, cut


# --------------------------------------------------------------------------------------------
# The pieces (in-process): naming, all-or-nothing, sweeping
# --------------------------------------------------------------------------------------------


def test_atomic_write_on_a_full_disk_names_the_file_and_leaves_nothing(full):
    from contact_viz.io.atomic import atomic_write

    target = full / "out.csv"
    with pytest.raises(OSError) as caught:
        with atomic_write(target) as handle:
            handle.write("x" * 100_000)
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(target)
    assert sorted(os.listdir(full)) == ["filler"]


def test_all_or_nothing_discards_every_file_of_the_block(tmp_path):
    from contact_viz.io.atomic import all_or_nothing, atomic_write

    first, second = tmp_path / "a.csv", tmp_path / "b.json"
    first.write_text("old")
    with pytest.raises(OSError):
        with all_or_nothing():
            with atomic_write(first) as handle:
                handle.write("new")
            assert first.read_text() == "old"  # not yet in place
            raise OSError(errno.ENOSPC, "No space left on device")
    assert first.read_text() == "old" and not second.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv"]
    with all_or_nothing():
        for path in (first, second):
            with atomic_write(path) as handle:
                handle.write("new")
    assert first.read_text() == second.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv", "b.json"]


def test_reported_as_names_the_output_only_for_its_own_files(tmp_path):
    from contact_viz.io.atomic import reported_as

    out, staging = tmp_path / "session", tmp_path / ".session.1-2.import"
    with pytest.raises(OSError) as caught, reported_as(out, staging):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "source.png"), None, str(staging / "x"))
    assert caught.value.filename == str(out)
    with pytest.raises(OSError) as caught, reported_as(out, staging):
        raise OSError(errno.ENOENT, "No such file or directory", str(tmp_path / "source.png"))
    assert caught.value.filename == str(tmp_path / "source.png")  # about an input: as it was


def test_sweep_stale_in_removes_only_dead_processes_staging(tmp_path):
    from contact_viz.io.atomic import staging_path, sweep_stale_in

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f".a.png.{dead.pid}-1.tmp"
    stale_dir = tmp_path / f".b.{dead.pid}-2.partial"
    live = staging_path(tmp_path / "c.png")
    assert STAGING.match(live.name) and STAGING.match(stale.name) and STAGING.match(stale_dir.name)
    other = tmp_path / ".hidden.txt"
    for path in (stale, live, other):
        path.write_text("x")
    stale_dir.mkdir()
    (stale_dir / "f").write_text("x")
    assert sorted(sweep_stale_in(tmp_path)) == sorted([stale, stale_dir])
    assert live.exists() and other.exists()
