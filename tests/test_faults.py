"""Faults of the machine under `view` and `batch`: a full disk, SIGTERM/SIGHUP/SIGINT mid-run, a viewer
that stops taking data.

Each command runs as the console script in a subprocess of its own process group, with a hard
timeout; each case asserts the exit status, the one line, no traceback, nothing partial under
the name asked for (an interrupted recording is kept only flushed, readable and said to be
partial), no process of the group left running, and the session byte-for-byte untouched.
(Workers under SIGKILL: tests/test_faults_workers.py; full and read-only disks under the other
commands and the caches: tests/test_faults_disk.py.)
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest

from contact_viz.synth import SynthParams, generate_session
from contact_viz.viz import rerun_log
from test_bad_inputs import tree_hash
from test_viewer import Recording

FRAMES = 120  # long enough that a signal after the first frames lands mid-run (~70 frames/s at this size)


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("faults") / "cup"
    generate_session(out, SynthParams(phantom="cup", frames=FRAMES, seed=2, width=320, height=180))
    return out


@pytest.fixture
def tmpfs(tmp_path):
    """A 2 MB filesystem (root only), unmounted afterwards."""
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    where = tmp_path / "small"
    where.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(where)], capture_output=True).returncode:
        pytest.skip("mount -t tmpfs failed here")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], capture_output=True)


def start(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "contact_viz.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)


def finish(proc: subprocess.Popen, timeout_s: float = 120) -> tuple[str, str]:
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        pytest.fail(f"still running after {timeout_s} s:\n{out}\n{err}")
    return out, err


def group_alive(pgid: int) -> list[int]:
    """The processes of group ``pgid`` still running (zombies excluded)."""
    alive = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            alive.append(int(entry.name))
    return alive


def assert_group_gone(pgid: int, within_s: float = 5.0) -> None:
    deadline = time.monotonic() + within_s
    while group_alive(pgid) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = group_alive(pgid)
    if left:
        os.killpg(pgid, signal.SIGKILL)
    assert not left, f"processes of the run still running: {left}"


def wait_for_frames(proc: subprocess.Popen, path_glob: tuple[Path, str], timeout_s: float = 60) -> None:
    """Wait until the run has written something (its staging file exists and grows)."""
    folder, pattern = path_glob
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"ended before the signal: {proc.communicate()}")
        parts = list(folder.glob(pattern))
        if parts and parts[0].stat().st_size > 200_000:
            return
        time.sleep(0.05)
    pytest.fail("the run wrote nothing")


def staged(folder: Path) -> list[Path]:
    return [p for p in folder.iterdir() if p.name.startswith(".")]


# --------------------------------------------------------------------------------------------
# view --save
# --------------------------------------------------------------------------------------------


def test_full_disk_under_view_save_is_one_line_and_leaves_nothing(session, tmpfs):
    before = tree_hash(session)
    out = tmpfs / "view.rrd"
    proc = start(["view", str(session), "--save", str(out)])
    stdout, stderr = finish(proc)
    assert proc.returncode == 2, (stdout, stderr)
    assert stderr.strip().splitlines()[-1] == f"error: {out}: no space left on the device"
    assert "Traceback" not in stderr + stdout and "File-writer" not in stderr
    assert list(tmpfs.iterdir()) == []  # neither view.rrd nor its staging file
    assert_group_gone(proc.pid)
    assert tree_hash(session) == before


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT], ids=lambda s: s.name)
def test_a_signal_mid_view_keeps_a_flushed_partial_recording_and_says_so(session, tmp_path, signum):
    before = tree_hash(session)
    out = tmp_path / "out" / "view.rrd"
    proc = start(["view", str(session), "--save", str(out)])
    wait_for_frames(proc, (out.parent, ".view.rrd.*.part"))
    os.kill(proc.pid, signum)
    stdout, stderr = finish(proc, 30)
    assert proc.returncode == 128 + signum, (stdout, stderr)
    name = "interrupted (Ctrl-C)" if signum == signal.SIGINT else f"stopped by {signal.Signals(signum).name}"
    (line,) = [x for x in stdout.splitlines() if "frames/s)" in x]
    assert line.endswith(f", {name}: the recording is partial"), line
    n_done = int(line.split()[0])
    assert 0 < n_done < FRAMES
    assert "Traceback" not in stderr + stdout
    assert staged(out.parent) == []
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a complete file: RrdReader warns on a missing footer
        rec = Recording(out)
    logged = rec.frames(rerun_log.ENTITY_DEPTH_IMAGE, "DepthImage:buffer")
    # every counted frame, and perhaps the one the signal cut short (logged, not yet counted)
    assert logged in (list(range(n_done)), list(range(n_done + 1)))
    assert_group_gone(proc.pid)
    assert tree_hash(session) == before


def test_sigkill_mid_view_leaves_nothing_under_the_name_and_the_next_run_cleans_up(session, tmp_path):
    out = tmp_path / "view.rrd"
    proc = start(["view", str(session), "--save", str(out)])
    wait_for_frames(proc, (tmp_path, ".view.rrd.*.part"))
    os.kill(proc.pid, signal.SIGKILL)
    finish(proc, 30)
    assert not out.exists() and len(staged(tmp_path)) == 1
    assert_group_gone(proc.pid)
    proc = start(["view", str(session), "--save", str(out), "--end", "3"])
    finish(proc)
    assert proc.returncode == 0 and out.exists() and staged(tmp_path) == []


def test_a_flush_to_a_viewer_that_stopped_taking_data_has_a_deadline(tmp_path):
    """A gRPC viewer frozen with SIGSTOP: the flush gives up after its deadline with a SinkError naming the
    address, and the process still exits at once (Rerun's own exit-time flush would wait forever)."""
    server = subprocess.Popen([sys.executable, "-c", (
        "import rerun as rr, sys, time\n"
        "rr.init('frozen')\n"
        "print(rr.serve_grpc(grpc_port=0 or 9931), flush=True)\n"
        "time.sleep(300)\n")], stdout=subprocess.PIPE, text=True, start_new_session=True)
    try:
        url = server.stdout.readline().strip()
        os.kill(server.pid, signal.SIGSTOP)
        script = (
            "import sys, time, numpy as np, rerun as rr\n"
            "from contact_viz.viz.sinks import SinkError, open_recording, exit_would_hang\n"
            f"opened = open_recording(connect={url!r})\n"
            "for i in range(10):  # more than the gRPC client buffers without the viewer taking it\n"
            "    opened.rec.log('img', rr.Image(np.random.default_rng(i).integers(0, 255, (512, 512, 3), np.uint8)))\n"
            "t = time.monotonic()\n"
            "try:\n"
            "    opened.flush(timeout_s=2)\n"
            "except SinkError as exc:\n"
            "    print(f'{time.monotonic() - t:.1f}', exc.filename, exc.strerror, exit_would_hang(), flush=True)\n"
            "import os; os._exit(0) if exit_would_hang() else None\n")
        started = time.monotonic()
        proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60,
                              env={**os.environ, "RUST_LOG": "off"})
        assert time.monotonic() - started < 30
        waited, where, *rest = proc.stdout.split(" ", 2)
        assert 1.5 <= float(waited) < 10, proc.stdout
        assert where == url and rest[0].endswith(" True\n"), proc.stdout
        assert "the viewer took more than 2 s" in rest[0]
    finally:
        os.killpg(server.pid, signal.SIGKILL)
        server.wait()


# --------------------------------------------------------------------------------------------
# batch
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def dataset(session, tmp_path_factory) -> Path:
    """Three copies of the session, named apart."""
    sessions = tmp_path_factory.mktemp("dataset") / "sessions"
    sessions.mkdir()
    for k in range(3):
        shutil.copytree(session, sessions / f"s{k}")
        meta = json.loads((sessions / f"s{k}" / "session.json").read_text())
        (sessions / f"s{k}" / "session.json").write_text(json.dumps({**meta, "name": f"s{k}"}))
    return sessions


def test_a_signal_at_any_moment_of_batch_under_load_stops_it_with_its_line(dataset, tmp_path):
    """SIGHUP and SIGTERM at moments spread over a whole `batch` run (the pool starting, extract, between the
    steps, view in the caller and in a worker, the results written), with two CPU hogs beside it: each run
    stops within 10 s with its one line, or had finished; nothing is left running. (A signal in view used to
    be taken by the recording as the end of a partial recording: the batch went on and exited 0.)"""
    inputs = tree_hash(dataset)
    hogs = [subprocess.Popen([sys.executable, "-c", "while 1: pass"]) for _ in range(2)]
    try:
        def run(out: Path) -> subprocess.Popen:
            return start(["batch", str(dataset), "-o", str(out), "--steps", "extract,view", "--processes", "2",
                          "--cache-dir", str(out.with_name(out.name + "_cache"))])

        began = time.monotonic()
        whole = run(tmp_path / "whole")
        finish(whole, 120)
        assert whole.returncode == 0
        length = time.monotonic() - began
        moments = [0.5, 0.2 * length, 0.35 * length, 0.5 * length, 0.65 * length, 0.8 * length]
        for k, delay in enumerate(moments):
            signum = (signal.SIGHUP, signal.SIGTERM)[k % 2]
            out = tmp_path / f"out{k}"
            proc = run(out)
            time.sleep(delay)
            running = proc.poll() is None
            if running:
                os.kill(proc.pid, signum)
            stdout, stderr = finish(proc, 10)
            stopped = f"stopped by {signal.Signals(signum).name}" + (
                " (the terminal closed)" if signum == signal.SIGHUP else "")
            if running:  # (a run that had finished before the signal had nothing to stop)
                assert (proc.returncode, stderr.strip().splitlines()[-1]) == (128 + signum, stopped), (delay, stderr)
                assert not (out / "summary.json").exists()
            assert "Traceback" not in stderr + stdout, (delay, stderr)
            assert [p for p in out.rglob(".*")] == [] if out.exists() else True
            assert_group_gone(proc.pid)
    finally:
        for hog in hogs:
            hog.kill()
    assert tree_hash(dataset) == inputs


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP], ids=lambda s: s.name)
def test_a_signal_mid_batch_stops_it_with_one_line_and_no_process_left(session, tmp_path, signum):
    before = tree_hash(session)
    sessions = tmp_path / "sessions"
    sessions.mkdir()
    for k in range(3):  # three copies, named apart
        shutil.copytree(session, sessions / f"s{k}")
        meta = json.loads((sessions / f"s{k}" / "session.json").read_text())
        (sessions / f"s{k}" / "session.json").write_text(json.dumps({**meta, "name": f"s{k}"}))
    inputs = {k: tree_hash(sessions / f"s{k}") for k in range(3)}
    out = tmp_path / "results"
    proc = start(["batch", str(sessions), "-o", str(out), "--steps", "extract,view", "--processes", "2"])
    deadline = time.monotonic() + 60
    while not list(out.glob("*/features.csv")) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
    os.kill(proc.pid, signum)
    stdout, stderr = finish(proc, 30)
    assert proc.returncode == 128 + signum, (stdout, stderr)
    assert stderr.strip().splitlines()[-1] == f"stopped by {signal.Signals(signum).name}" + (
        " (the terminal closed)" if signum == signal.SIGHUP else "")
    assert "Traceback" not in stderr + stdout
    assert not (out / "summary.json").exists()
    assert [p for p in out.rglob(".*")] == []  # no staging file anywhere in the results
    assert_group_gone(proc.pid)
    assert tree_hash(session) == before
    assert all(tree_hash(sessions / f"s{k}") == inputs[k] for k in range(3))
