"""The one way the package runs work in parallel: a pool of spawned worker processes.

Threads cannot spread `contact-viz extract` over the cores (between its NumPy and OpenCV calls
the patch holds the GIL), so work is shared by processes, through
:class:`concurrent.futures.ProcessPoolExecutor` with the "spawn" start method (a fresh
interpreter: safe after OpenCV and OpenBLAS have started their threads, unlike "fork").

API
---
``ProcessPool(processes, *, initializer=None, preload=())`` -- a context manager.
    ``processes`` processes share the work, the caller included: ``processes - 1`` worker
    processes, started at once, so that they import (``preload``: module names, e.g. NumPy,
    OpenCV, the patch) while the caller does its own start-up; each runs ``initializer()`` (a
    module-level function) first (the caller runs it itself if it should apply there too).
    ``processes=1`` starts nothing: the work runs in the calling process, by the same
    functions. A pool runs any number of jobs.

``pool.map(fn, items, *, progress=None) -> list``
    ``[fn(item) for item in items]``, one task per item (e.g. one session each); results in
    item order.

``pool.map_chunks(task, n_items, *, chunk_size, progress=None) -> list``
    ``task(lo, hi)`` (a picklable callable returning the results of items ``lo`` to ``hi - 1``,
    e.g. the rows of a session's frames ``lo..hi-1``) over the consecutive chunks of
    ``range(n_items)``; the results of all items, in item order.

``run_chunks(task, n_items, *, chunk_size, processes, progress=None, initializer=None)``
    ``map_chunks`` in a pool of its own (no more processes than chunks).

``fn``/``task`` is pickled once and unpickled once in each worker (not once per item), so it
may carry an opened session. The workers take the items from the front (a few at a time), the caller from the back, so
nobody waits for a worker still starting up. Both ``map`` calls call
``progress(n)`` in the caller with the number of items done so far.
An exception raised by ``fn``/``task`` in a worker is raised again in the caller, as it is
(its worker-side traceback is its ``__cause__``), exactly as with ``processes=1``; a worker
that dies (killed, out of memory) raises :class:`WorkerError`. Either way, and on Ctrl-C,
SIGTERM or SIGHUP (workers ignore all three and leave them to the caller, so a signal sent to
the whole process group stops the command, not a worker), the jobs not started are cancelled
and the pool's processes have exited when the ``with`` block is left: a worker still busy
``STOP_GRACE_S`` after that is killed, so closing never waits long.

Workers never outlive the process that started them, even when it is killed with SIGKILL: on
Linux the kernel kills them (``PR_SET_PDEATHSIG``); everywhere, each worker checks its parent
every ``WATCH_INTERVAL_S`` and exits when it is gone. As with any spawned process, a script
using a pool at import time needs an ``if __name__ == "__main__":`` guard.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import ctypes
import importlib
import multiprocessing
import os
import pickle
import signal
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures.process import BrokenProcessPool
from multiprocessing import resource_tracker
from multiprocessing.connection import wait as wait_ready
from typing import Any, Protocol, TypeVar

T = TypeVar("T")
R = TypeVar("R")

_USABLE_CORES = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
DEFAULT_PROCESSES = min(8, _USABLE_CORES)  # processes sharing the work, the caller included (one per core, at most 8)
STOP_GRACE_S = 1.0  # closing: how long a worker may take to finish its job (or start-up) and exit before it is killed
EXIT_TIMEOUT_S = 5.0  # closing: the longest wait for a killed worker to be gone
WATCH_INTERVAL_S = 0.5  # in a worker: how often it checks that its parent is alive

# concurrent.futures (3.11) does nothing when the parent dies: its workers then wait for jobs forever.
_PR_SET_PDEATHSIG = 1  # prctl option (linux/prctl.h): the signal this process gets when its parent thread exits
_STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))
_HAVE_SIGMASK = hasattr(signal, "pthread_sigmask")


class ChunkTask(Protocol):
    """A picklable callable computing the results of items ``lo`` to ``hi - 1``, in order."""

    def __call__(self, lo: int, hi: int) -> list[Any]: ...


class WorkerError(RuntimeError):
    """A worker process died (killed, out of memory, its start-up failed) before delivering its results."""


def chunk_bounds(n_items: int, chunk_size: int) -> list[tuple[int, int]]:
    """The ``(lo, hi)`` half-open bounds of the consecutive chunks of ``range(n_items)``."""
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1:
        raise ValueError(f"chunk_size must be a positive integer, got {chunk_size!r}")
    if n_items < 0:
        raise ValueError(f"n_items must be >= 0, got {n_items!r}")
    return [(lo, min(lo + chunk_size, n_items)) for lo in range(0, n_items, chunk_size)]


class _Parent:
    """The process starting a worker, as the worker sees it: its pid, and whether the thread
    starting the worker is its main thread. Pickled for each worker as it is started, in the
    thread starting it (the spawn method pickles the initializer's arguments in Process.start):
    the executor does that in ``submit`` (here: in ``ProcessPool()``), or in its manager thread
    when it replaces a worker (only with ``max_tasks_per_child``, not used here)."""

    def __getstate__(self) -> tuple[int, bool]:
        return os.getpid(), threading.current_thread() is threading.main_thread()

    def __setstate__(self, state: tuple[int, bool]) -> None:
        self.pid, self.main_thread = state


def _die_with_parent(parent: _Parent) -> None:
    """Make this worker end when its parent does (even by SIGKILL), at once if it already has."""
    if sys.platform.startswith("linux") and parent.main_thread:
        # The kernel sends the signal when the *thread* that started this process exits, so only
        # when that is the parent's main thread, which lasts as long as the process.
        try:
            ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, ctypes.c_ulong(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):  # no prctl: the watch below does it
            pass
    if os.getppid() != parent.pid:  # the parent died before that (this process now belongs to init)
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(parent.pid,), name="contact-viz-watch-parent", daemon=True).start()


def _watch_parent(pid: int) -> None:
    """In a worker: exit as soon as the parent ``pid`` is gone (where the kernel does not do it,
    or when the parent thread that started this worker was not its main thread)."""
    while os.getppid() == pid:
        time.sleep(WATCH_INTERVAL_S)
    os._exit(1)


def _start_worker(parent: _Parent, initializer: Callable[[], object] | None, preload: Sequence[str]) -> None:
    """First thing in each worker: end with the parent, leave Ctrl-C, SIGTERM and SIGHUP to it
    (they were blocked since this process started), run ``initializer``, import ``preload``."""
    _die_with_parent(parent)
    for signum in _STOP_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)
    if _HAVE_SIGMASK:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, _STOP_SIGNALS)
    if initializer is not None:
        initializer()
    for module in preload:
        importlib.import_module(module)


def _started() -> None:
    """A no-op job: submitting one per worker makes the executor start them all now."""


@contextlib.contextmanager
def _stop_signals_blocked() -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP blocked in this thread meanwhile, so that the processes it starts
    begin with them blocked (the mask is inherited): a signal sent to the whole process group
    cannot kill a worker before it ignores them, nor multiprocessing's resource tracker (started
    here if it is not running; it ignores SIGINT and SIGTERM only). A signal that comes
    meanwhile reaches this process when the block ends."""
    if not _HAVE_SIGMASK:
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS)
    try:
        resource_tracker.ensure_running()  # it unblocks SIGINT and SIGTERM once the tracker has started
        signal.pthread_sigmask(signal.SIG_BLOCK, _STOP_SIGNALS)
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


_SHARED: dict[str, Any] = {}  # in a worker: the functions of the jobs it has seen, unpickled once each


class _Shared:
    """A function (or task) pickled once in the caller and unpickled once per worker, not once
    per call: an opened session takes longer to unpickle (its file paths) than a chunk of frames
    takes to compute on a loaded machine."""

    def __init__(self, fn: Callable[..., Any]) -> None:
        self.fn: Callable[..., Any] | None = fn
        self.key = uuid.uuid4().hex
        self.payload = pickle.dumps(fn, protocol=pickle.HIGHEST_PROTOCOL)

    def __getstate__(self) -> tuple[str, bytes]:
        return self.key, self.payload

    def __setstate__(self, state: tuple[str, bytes]) -> None:
        self.key, self.payload = state
        self.fn = None

    def __call__(self, *args: Any) -> Any:
        fn = self.fn
        if fn is None:
            fn = _SHARED.get(self.key)
            if fn is None:
                _SHARED.clear()  # the previous job's function is not needed any more
                fn = _SHARED[self.key] = pickle.loads(self.payload)
        return fn(*args)


class _Chunk:
    """``task(lo, hi)`` as a one-argument function of the chunk's bounds, checked for length."""

    def __init__(self, task: ChunkTask) -> None:
        self.task = task

    def __call__(self, bounds: tuple[int, int]) -> list[Any]:
        lo, hi = bounds
        items = self.task(lo, hi)
        if len(items) != hi - lo:
            raise ValueError(f"task returned {len(items)} results for items {lo}..{hi - 1}, expected {hi - lo}")
        return items


class ProcessPool:
    """``processes - 1`` spawned worker processes and the caller; see the module docstring."""

    def __init__(self, processes: int, *, initializer: Callable[[], object] | None = None,
                 preload: Sequence[str] = ()) -> None:
        if isinstance(processes, bool) or not isinstance(processes, int) or processes < 1:
            raise ValueError(f"processes must be a positive integer, got {processes!r}")
        self.processes = processes
        self._executor: cf.ProcessPoolExecutor | None = None
        if processes > 1:
            try:
                with _stop_signals_blocked():  # the executor's locks start multiprocessing's resource tracker
                    self._executor = cf.ProcessPoolExecutor(
                        processes - 1, mp_context=multiprocessing.get_context("spawn"),
                        initializer=_start_worker, initargs=(_Parent(), initializer, tuple(preload)))
                    for _ in range(processes - 1):  # the executor starts a process for each job no idle one takes
                        self._executor.submit(_started)
            except BaseException:  # e.g. Ctrl-C, delivered when the signals are unblocked
                self.close()
                raise

    def __enter__(self) -> ProcessPool:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        """Cancel the jobs not started and let the workers exit; kill those still busy (a job, their
        start-up) after ``STOP_GRACE_S``. Returns within seconds, whatever the workers do."""
        executor, self._executor = self._executor, None
        if executor is None:
            return
        # The executor's own shutdown waits for the running jobs however long they take, and its
        # terminate() of a broken pool's workers sends SIGTERM, which they ignore: so its private
        # lists of processes and of its manager thread are taken, to kill and wait with deadlines.
        workers = {p.sentinel: p for p in (executor._processes or {}).values()}
        manager = executor._executor_manager_thread
        executor.shutdown(wait=False, cancel_futures=True)
        try:
            deadline = time.monotonic() + STOP_GRACE_S
            while workers and (left := deadline - time.monotonic()) > 0:
                for sentinel in wait_ready(list(workers), left):
                    del workers[sentinel]
        finally:  # also when a second Ctrl-C interrupts the wait
            for worker in workers.values():
                worker.kill()
            gone_by = time.monotonic() + EXIT_TIMEOUT_S  # one deadline for both waits: close() takes at most
            if workers:  # STOP_GRACE_S + EXIT_TIMEOUT_S (it took up to 1 + 5 + 5 s)
                wait_ready(list(workers), EXIT_TIMEOUT_S)
            if manager is not None:
                manager.join(max(gone_by - time.monotonic(), 0.0))  # it reaps the workers

    def map(self, fn: Callable[[T], R], items: Iterable[T], *,
            progress: Callable[[int], None] | None = None) -> list[R]:
        """``[fn(item) for item in items]``, shared by the workers; see the module docstring."""
        items = list(items)
        return self._run(fn, items, [1] * len(items), progress, lambda k: f"item {k} ({_short(items[k])})")

    def map_chunks(self, task: ChunkTask, n_items: int, *, chunk_size: int,
                   progress: Callable[[int], None] | None = None) -> list[Any]:
        """``task(lo, hi)`` over the chunks of ``range(n_items)``; see the module docstring."""
        bounds = chunk_bounds(n_items, chunk_size)
        results = self._run(_Chunk(task), bounds, [hi - lo for lo, hi in bounds], progress,
                            lambda k: f"items {bounds[k][0]}..{bounds[k][1] - 1}")
        return [item for items in results for item in items]

    def _run(self, fn: Callable[[Any], Any], items: list[Any], sizes: list[int],
             progress: Callable[[int], None] | None, describe: Callable[[int], str]) -> list[Any]:
        """``fn`` over ``items`` (by the workers and this process), results in order;
        ``progress`` gets the running total of the ``sizes`` of the items done."""
        done = 0
        if self._executor is None:
            if self.processes > 1:
                raise RuntimeError("this ProcessPool is closed")
            results = []
            for item, size in zip(items, sizes):
                results.append(fn(item))
                done += size
                if progress is not None:
                    progress(done)
            return results
        results = [None] * len(items)
        in_flight: dict[cf.Future, int] = {}
        queued = 2 * (self.processes - 1)  # jobs handed to the workers at a time (one running, one ready each)
        front, back = 0, len(items)  # items[front:back] are not handed out yet
        k = None

        def finished(j: int, result: Any) -> None:
            nonlocal done
            results[j] = result
            done += sizes[j]
            if progress is not None:
                progress(done)

        try:
            shared = _Shared(fn)
            while front < back or in_flight:
                while front < back and len(in_flight) < queued:
                    in_flight[self._executor.submit(shared, items[front])] = front
                    front += 1
                if front < back:  # this process works too, from the back
                    back -= 1
                    finished(back, fn(items[back]))
                    ready = [future for future in in_flight if future.done()]
                else:
                    ready = cf.wait(in_flight, return_when=cf.FIRST_COMPLETED).done
                for future in ready:
                    k = in_flight.pop(future)
                    finished(k, future.result())
        except BrokenProcessPool as exc:
            self._stop(in_flight)
            where = "" if k is None else f" while computing {describe(k)}"
            raise WorkerError(f"a worker process died (killed, out of memory, or its start-up failed){where}; "
                              "the pool was stopped") from exc
        except BaseException:
            self._stop(in_flight)
            raise
        return results

    def _stop(self, futures) -> None:
        """After a failure: cancel what has not started and close (a failed pool is not reused)."""
        for future in futures:
            future.cancel()
        self.close()


def _short(item: object) -> str:
    text = repr(item)
    return text if len(text) <= 60 else text[:57] + "..."


def run_chunks(task: ChunkTask, n_items: int, *, chunk_size: int, processes: int,
               progress: Callable[[int], None] | None = None,
               initializer: Callable[[], object] | None = None) -> list[Any]:
    """``task(lo, hi)`` over the chunks of ``range(n_items)`` in a pool of its own of at most
    ``processes`` processes, this one included (no more than there are chunks; ``processes=1``:
    in this process only)."""
    if isinstance(processes, bool) or not isinstance(processes, int) or processes < 1:
        raise ValueError(f"processes must be a positive integer, got {processes!r}")
    n_chunks = len(chunk_bounds(n_items, chunk_size))
    with ProcessPool(max(1, min(processes, n_chunks)), initializer=initializer) as pool:
        return pool.map_chunks(task, n_items, chunk_size=chunk_size, progress=progress)
