"""parallel.ProcessPool / run_chunks: work shared by spawned worker processes, results in order."""

from __future__ import annotations

import multiprocessing
import os
import pickle
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

import pytest

from contact_viz.pipeline.parallel import STOP_GRACE_S, ProcessPool, WorkerError, _Parent, chunk_bounds, run_chunks


@dataclass(frozen=True)
class Squares:
    """Results of items lo..hi-1: (item, item**2, pid of the process that computed it)."""

    offset: int = 0

    def __call__(self, lo: int, hi: int) -> list[tuple[int, int, int]]:
        return [(i, (i + self.offset) ** 2, os.getpid()) for i in range(lo, hi)]


@dataclass(frozen=True)
class CallerFails:
    caller_pid: int

    def __call__(self, lo: int, hi: int) -> list[int]:
        if os.getpid() == self.caller_pid:
            raise KeyError("the caller's own error")
        return list(range(lo, hi))


@dataclass(frozen=True)
class SlowSquares(Squares):
    def __call__(self, lo: int, hi: int):
        time.sleep(0.01)
        return super().__call__(lo, hi)


@dataclass(frozen=True)
class FailsInWorker:
    """Raises in a worker process (never in the caller)."""

    caller_pid: int

    def __call__(self, lo: int, hi: int) -> list[int]:
        if os.getpid() != self.caller_pid:
            raise ArithmeticError(f"items {lo}..{hi - 1} are bad")
        time.sleep(0.01)
        return list(range(lo, hi))


@dataclass(frozen=True)
class DiesInWorker:
    """Kills its own process in a worker."""

    caller_pid: int

    def __call__(self, lo: int, hi: int) -> list[int]:
        if os.getpid() != self.caller_pid:
            os.kill(os.getpid(), signal.SIGKILL)
        time.sleep(0.01)
        return [i * 10 for i in range(lo, hi)]


@dataclass(frozen=True)
class CallerFailsWhileWorkersHang:
    """The workers start jobs that last a minute; then the caller fails."""

    caller_pid: int
    error: type[BaseException]

    def __call__(self, lo: int, hi: int) -> list[int]:
        if os.getpid() == self.caller_pid:
            time.sleep(0.5)  # the workers have started their jobs
            raise self.error("the caller's own error")
        time.sleep(60)
        return list(range(lo, hi))


def square(x: int) -> int:
    return x * x


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def signal_state(_) -> tuple[int, list, list]:
    """The pid, the handlers of SIGINT, SIGTERM, SIGHUP and the blocked signals of the process running it."""
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    return os.getpid(), [signal.getsignal(s) for s in STOP_SIGNALS], sorted(blocked)


def test_chunk_bounds():
    assert chunk_bounds(10, 4) == [(0, 4), (4, 8), (8, 10)]
    assert chunk_bounds(8, 4) == [(0, 4), (4, 8)]
    assert chunk_bounds(0, 4) == []
    with pytest.raises(ValueError, match="chunk_size"):
        chunk_bounds(10, 0)
    with pytest.raises(ValueError, match="n_items"):
        chunk_bounds(-1, 3)


@pytest.mark.parametrize("processes, n_items, chunk", [(1, 23, 4), (2, 23, 4), (3, 50, 3), (2, 3, 8), (2, 0, 4)])
def test_results_in_item_order(processes, n_items, chunk):
    done = []
    out = run_chunks(Squares(offset=1), n_items, chunk_size=chunk, processes=processes, progress=done.append)
    assert [(i, sq) for i, sq, _ in out] == [(i, (i + 1) ** 2) for i in range(n_items)]
    assert done == sorted(done) and (done[-1] == n_items if n_items else done == [])
    assert multiprocessing.active_children() == []  # every worker was stopped and joined


def test_work_is_shared_by_the_caller_and_the_workers():
    out = run_chunks(SlowSquares(), 200, chunk_size=2, processes=3)
    pids = [pid for _, _, pid in out]
    assert len(set(pids)) >= 2 and pids[-1] == os.getpid()  # the caller takes the chunks from the back


def test_single_process_starts_nothing():
    out = run_chunks(Squares(), 10, chunk_size=3, processes=1)
    assert {pid for _, _, pid in out} == {os.getpid()}
    with ProcessPool(1) as pool:
        assert pool.map(square, range(5)) == [0, 1, 4, 9, 16]
    assert multiprocessing.active_children() == []


def test_pool_runs_several_jobs_then_stops():
    """One pool, several jobs (as `contact-viz batch` runs sessions, then frame chunks)."""
    with ProcessPool(2) as pool:
        done = []
        assert pool.map(square, range(7), progress=done.append) == [k * k for k in range(7)]
        assert done == list(range(1, 8))
        assert [sq for _, sq, _ in pool.map_chunks(Squares(), 9, chunk_size=4)] == [k * k for k in range(9)]
        assert len(multiprocessing.active_children()) == 1  # the caller is the second process
    assert multiprocessing.active_children() == []


def test_worker_exception_is_raised_in_caller_as_it_is():
    with pytest.raises(ArithmeticError, match=r"items \d+\.\.\d+ are bad") as caught:
        run_chunks(FailsInWorker(os.getpid()), 200, chunk_size=2, processes=2)
    assert "Traceback" in str(caught.value.__cause__)  # the worker's traceback
    assert multiprocessing.active_children() == []


def test_killed_worker_is_reported_and_the_pool_stopped():
    with pytest.raises(WorkerError, match=r"worker process died .* items \d+\.\.\d+; the pool was stopped"):
        run_chunks(DiesInWorker(os.getpid()), 300, chunk_size=2, processes=2)
    assert multiprocessing.active_children() == []


def test_caller_exception_stops_workers():
    with pytest.raises(KeyError, match="caller's own error"):
        run_chunks(CallerFails(os.getpid()), 100, chunk_size=2, processes=3)
    assert multiprocessing.active_children() == []


def test_bad_arguments():
    with pytest.raises(ValueError, match="processes"):
        run_chunks(Squares(), 5, chunk_size=2, processes=0)
    with pytest.raises(ValueError, match="processes"):
        ProcessPool(True)
    with pytest.raises(ValueError, match="expected 2"):
        run_chunks(lambda lo, hi: [0], 4, chunk_size=2, processes=1)


def test_workers_ignore_the_stop_signals():
    """SIGINT, SIGTERM and SIGHUP sent to the whole process group (Ctrl-C, a closed terminal) are
    left to the caller, which stops the pool; none stays blocked in the workers."""
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    with ProcessPool(2) as pool:
        states = pool.map(signal_state, range(60))
    workers = [(handlers, blocked) for pid, handlers, blocked in states if pid != os.getpid()]
    assert workers and all(handlers == [signal.SIG_IGN] * 3 and blocked == [] for handlers, blocked in workers)
    assert signal.pthread_sigmask(signal.SIG_BLOCK, []) == mask  # the caller's mask is as it was


@pytest.mark.parametrize("error", [KeyError, KeyboardInterrupt])
def test_closing_does_not_wait_for_the_running_jobs(error):
    """A failure or Ctrl-C in the caller while the workers run long jobs: the workers still busy
    STOP_GRACE_S later are killed (they ignore SIGTERM), so the pool is gone in seconds, not a minute."""
    started = time.monotonic()
    with pytest.raises(error, match="caller's own error"):
        run_chunks(CallerFailsWhileWorkersHang(os.getpid(), error), 100, chunk_size=2, processes=3)
    assert time.monotonic() - started < 0.5 + STOP_GRACE_S + 10  # start-up on a loaded machine included
    assert multiprocessing.active_children() == []


def test_a_worker_knows_the_process_and_thread_that_started_it():
    """The kernel's parent-death signal follows the thread that started a worker: the worker is
    told whether that was the main thread (pickled as it is started, in the starting thread)."""
    parent = pickle.loads(pickle.dumps(_Parent()))
    assert (parent.pid, parent.main_thread) == (os.getpid(), True)
    seen = []
    starter = threading.Thread(target=lambda: seen.append(pickle.loads(pickle.dumps(_Parent()))))
    starter.start()
    starter.join()
    assert (seen[0].pid, seen[0].main_thread) == (os.getpid(), False)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_worker_dies_with_its_parent_or_at_once_if_it_is_gone():
    """In a worker, _die_with_parent asks the kernel for SIGKILL when the parent dies, and exits at
    once when its parent is not the expected one (it died before that: this process was adopted)."""
    script = """if True:
        import ctypes, os, sys
        from contact_viz.pipeline.parallel import _Parent, _die_with_parent
        parent = _Parent.__new__(_Parent)
        parent.__setstate__((int(sys.argv[1]) if sys.argv[1] != "me" else os.getppid(), True))
        _die_with_parent(parent)
        signum = ctypes.c_int()
        ctypes.CDLL(None).prctl(2, ctypes.byref(signum), 0, 0, 0)  # PR_GET_PDEATHSIG
        print(signum.value)
    """
    alive = subprocess.run([sys.executable, "-c", script, "me"], capture_output=True, text=True, timeout=60)
    assert (alive.returncode, alive.stdout.strip()) == (0, str(int(signal.SIGKILL))), alive.stderr
    orphan = subprocess.run([sys.executable, "-c", script, "-1"], capture_output=True, text=True, timeout=60)
    assert (orphan.returncode, orphan.stdout) == (1, ""), orphan.stderr
