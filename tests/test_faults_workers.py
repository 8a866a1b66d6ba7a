"""Machine faults: the worker processes of a command never outlive it.

Each test runs a real command in a session of its own (``start_new_session``: its own process
group), sends it a signal while its workers are computing, and checks within ``GONE_S`` that no
process of the group (or, for Ray, of the session) is left; a test that fails kills what is left.
``extract`` runs on a synthetic session without depth/, so that its workers compute SGBM depth.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from contact_viz.synth import SynthParams, generate_session

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")

CLI = [sys.executable, "-m", "contact_viz.cli"]
GONE_S = 5.0  # how long the processes of a stopped command may take to be gone
START_S = 60.0  # the longest wait for a command to be at work


@pytest.fixture(scope="module")
def stereo_session(tmp_path_factory) -> Path:
    """240 frames without depth/ (SGBM): about 4 s of work for two processes."""
    root = tmp_path_factory.mktemp("workers") / "stereo"
    generate_session(root, SynthParams(phantom="cup", frames=240, seed=1, width=320, height=180))
    shutil.rmtree(root / "depth")
    return root


def _digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _processes(*, group: int | None = None, session: int | None = None) -> dict[int, str]:
    """The processes (pid -> command line) of a process group or session that have not exited
    (a zombie, waiting to be reaped, does not count)."""
    found = {}
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            state, _, pgrp, sid = (proc / "stat").read_text().rsplit(")", 1)[1].split()[:4]
            cmdline = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
        except (OSError, ValueError):
            continue
        if state != "Z" and (int(pgrp) == group if group is not None else int(sid) == session):
            found[int(proc.name)] = cmdline
    return found


def _kill_all(**which) -> dict[int, str]:
    """SIGKILL every process of the group/session (a failed test leaves none); returns those it found."""
    left = _processes(**which)
    for pid in left:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    return left


def _gone_after(since: float, **which) -> float:
    """Seconds from ``since`` until no process of the group/session is left; fails after GONE_S."""
    while _processes(**which):
        if time.monotonic() - since > GONE_S:
            left = _kill_all(**which)
            pytest.fail(f"still running {GONE_S} s after the signal: {left}")
        time.sleep(0.05)
    return time.monotonic() - since


def _start(args: list[str], ready, what: str) -> subprocess.Popen:
    """Run ``args`` in a session of its own; return once ``ready(run)`` is true (it is at work)."""
    run = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    started = time.monotonic()
    while not ready(run):
        if run.poll() is not None:
            _kill_all(session=run.pid)
            pytest.fail(f"ended before {what}: {run.returncode} {run.communicate()}")
        if time.monotonic() - started > START_S:
            run.kill()
            _kill_all(session=run.pid)
            pytest.fail(f"not {what} after {START_S} s: {run.communicate()}")
        time.sleep(0.02)
    return run


def _start_extract(session: Path, tmp_path: Path) -> tuple[subprocess.Popen, Path]:
    """`contact-viz extract --processes 2` at work: a worker has computed frames (the workers take
    the frames from the front, the caller from the back) and goes on with the next ones."""
    out, cache = tmp_path / "out" / "features.csv", tmp_path / "cache"

    def workers_at_work(run: subprocess.Popen) -> bool:  # SGBM disparities of frames 0..99 cached
        return sum(1 for f in cache.rglob("*.png") if (m := re.match(r"(\d+)-", f.name)) and int(m[1]) < 100) >= 8

    run = _start([*CLI, "extract", str(session), "-o", str(out), "--processes", "2", "--cache-dir", str(cache)],
                 workers_at_work, "computing frames in a worker")
    assert any("spawn_main" in cmd for cmd in _processes(group=run.pid).values())
    return run, out


@pytest.mark.parametrize("signum, to_group", [(signal.SIGTERM, False), (signal.SIGHUP, False),
                                              (signal.SIGTERM, True), (signal.SIGHUP, True)],
                         ids=["SIGTERM", "SIGHUP", "SIGTERM-to-group", "SIGHUP-to-group"])
def test_a_stop_signal_stops_every_process_and_writes_nothing(stereo_session, tmp_path, signum, to_group):
    """SIGTERM / SIGHUP to the command (``kill PID``), or to its whole process group (a closed
    terminal, ``kill -- -PGID``: the workers ignore it and leave it to the command): one line,
    128 + the signal, no features file, and every process gone."""
    before = _digest(stereo_session)
    run, out = _start_extract(stereo_session, tmp_path)
    try:
        sent = time.monotonic()
        (os.killpg if to_group else os.kill)(run.pid, signum)
        _, stderr = run.communicate(timeout=30)
        gone_s = _gone_after(sent, group=run.pid)
    finally:
        run.kill()
        _kill_all(group=run.pid)
    name = signal.Signals(signum).name
    assert run.returncode == 128 + signum, stderr
    assert stderr.strip().splitlines()[-1].startswith(f"stopped by {name}"), stderr
    assert "Traceback" not in stderr and "worker process died" not in stderr, stderr
    assert not out.exists() and not out.with_name("features.csv.json").exists()
    assert gone_s < GONE_S
    assert _digest(stereo_session) == before


def test_sigkill_of_the_command_leaves_no_process(stereo_session, tmp_path):
    """SIGKILL to the command alone (the out-of-memory killer, ``kill -9 PID``): its workers are
    gone too, and with them the last holders of its stdout and stderr (EOF at once)."""
    before = _digest(stereo_session)
    run, out = _start_extract(stereo_session, tmp_path)
    try:
        sent = time.monotonic()
        run.kill()
        run.communicate(timeout=GONE_S)  # EOF: no process holds the pipes any more
        gone_s = _gone_after(sent, group=run.pid)
    finally:
        _kill_all(group=run.pid)
    assert run.returncode == -signal.SIGKILL
    assert gone_s < GONE_S
    assert not out.exists()
    assert _digest(stereo_session) == before


POOL_SCRIPT = textwrap.dedent('''
    import os, sys, threading, time
    from pathlib import Path
    from contact_viz.pipeline.parallel import ProcessPool

    def slow(item):
        Path(sys.argv[2], str(os.getpid())).touch()
        time.sleep(60)
        return item

    if __name__ == "__main__":
        if sys.argv[1] == "thread":  # started by a thread that has ended when the work starts
            pools = []
            starter = threading.Thread(target=lambda: (pools.append(ProcessPool(3)), time.sleep(1.5)))
            starter.start()
            starter.join()
            pool = pools[0]
            time.sleep(0.5)
            assert pool.map(abs, range(-9, 0)) == list(range(9, 0, -1))  # its workers are alive
        else:
            pool = ProcessPool(3)
        pool.map(slow, range(20))
''')


@pytest.mark.parametrize("started_by", ["main", "thread"])
def test_pool_workers_die_with_their_parent(tmp_path, started_by):
    """The parent of a pool is killed (SIGKILL) while its two workers run a slow task: the workers
    are gone at once (PR_SET_PDEATHSIG), or within WATCH_INTERVAL_S when the pool was started by
    another thread than the main one (the kernel would kill them when that thread ends, so the
    workers watch their parent instead) -- and such workers survive the end of that thread."""
    script, marks = tmp_path / "pool.py", tmp_path / "marks"
    script.write_text(POOL_SCRIPT)
    marks.mkdir()

    def both_workers_busy(run: subprocess.Popen) -> bool:
        return len({p.name for p in marks.iterdir()} - {str(run.pid)}) >= 2

    run = _start([sys.executable, str(script), started_by, str(marks)], both_workers_busy,
                 "running the slow task in both workers")
    try:
        assert len(_processes(group=run.pid)) >= 3  # the parent, its workers (and the resource tracker)
        sent = time.monotonic()
        run.kill()
        run.communicate(timeout=GONE_S)
        gone_s = _gone_after(sent, group=run.pid)
    finally:
        _kill_all(group=run.pid)
    assert gone_s < GONE_S


def test_ray_batch_stops_on_sigterm_and_shuts_ray_down(stereo_session, tmp_path):
    """`contact-viz batch --ray` and SIGTERM: the command's own line and status (Ray's init sets a
    SIGTERM handler of its own, and its waits turn the command's stop into a plain Ctrl-C), and
    the local Ray (GCS, raylet, agents, task workers: one session) shut down by RayEngine.close."""
    pytest.importorskip("ray")
    before = _digest(stereo_session)

    def task_running(run: subprocess.Popen) -> bool:
        # a task of ours runs: ray.init has returned (while it runs, Ray's own SIGTERM handlers are in place)
        return any(cmd.startswith("ray::depth_task") for cmd in _processes(session=run.pid).values())

    run = _start([*CLI, "batch", str(stereo_session), "-o", str(tmp_path / "out"), "--ray", "--steps", "depth",
                  "--chunk-frames", "16", "--cache-dir", str(tmp_path / "cache")], task_running, "running a Ray task")
    try:
        sent = time.monotonic()
        run.send_signal(signal.SIGTERM)
        _, stderr = run.communicate(timeout=60)
        gone_s = _gone_after(sent, session=run.pid)
    finally:
        run.kill()
        _kill_all(session=run.pid)
    assert run.returncode == 128 + signal.SIGTERM, stderr
    assert stderr.strip().splitlines()[-1] == "stopped by SIGTERM", stderr
    assert "Traceback" not in stderr and "SIGTERM received" not in stderr, stderr
    assert gone_s < GONE_S
    assert _digest(stereo_session) == before
