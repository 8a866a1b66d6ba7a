"""Process-level parallelism over chunks of items, shared between the caller and spawned workers.

Threads cannot spread the per-frame work of `contact-viz extract` over the cores: between its
NumPy and OpenCV calls the patch holds the GIL, and so does the PNG decoder's Python side.
:class:`WorkerPool` (or :func:`run_chunks`, which makes one) splits ``range(n_items)`` into
chunks that the calling process and the pool's spawned worker processes claim from one shared
counter, so

* nobody waits for work another process has not started: a worker still importing NumPy
  when the caller has claimed the last chunk is simply stopped, so short runs pay nothing
  for it (and a pool started early imports while the caller is busy elsewhere);
* the task (e.g. an opened session) is pickled once per worker, not once per chunk;
* a worker that dies (killed, out of memory) leaves its chunk to the caller, which computes
  it itself; an exception raised by the task in a worker is raised again in the caller.

Workers are started with the "spawn" method (a fresh interpreter: safe after OpenCV and
OpenBLAS have started their threads, unlike "fork"). As with any spawned process, a script
calling this at import time needs an ``if __name__ == "__main__":`` guard.
"""

from __future__ import annotations

import importlib
import multiprocessing
import os
import pickle
import queue
import signal
import threading
import traceback
from collections.abc import Callable, Sequence
from typing import Any, Protocol

_USABLE_CORES = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
DEFAULT_PROCESSES = min(8, _USABLE_CORES)  # processes to share work over, the caller included
WORKER_POLL_S = 0.05  # how often the caller checks on its workers while waiting, s
WORKER_STOP_TIMEOUT_S = 5.0  # how long a worker gets to exit before it is terminated, s


class ChunkTask(Protocol):
    """A picklable callable computing the results of items ``lo`` to ``hi - 1`` in order."""

    def __call__(self, lo: int, hi: int) -> list[Any]: ...


class WorkerError(RuntimeError):
    """A task raised in a worker process; the message carries the worker's traceback."""


def chunk_bounds(n_items: int, chunk_size: int) -> list[tuple[int, int]]:
    """The ``(lo, hi)`` half-open bounds of the consecutive chunks of ``range(n_items)``."""
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1:
        raise ValueError(f"chunk_size must be a positive integer, got {chunk_size!r}")
    if n_items < 0:
        raise ValueError(f"n_items must be >= 0, got {n_items!r}")
    return [(lo, min(lo + chunk_size, n_items)) for lo in range(0, n_items, chunk_size)]


def _claim(counter) -> int:
    with counter.get_lock():
        index = counter.value
        counter.value += 1
    return index


def _send_job(connection, job_bytes: bytes) -> None:
    """Send the pickled job down a worker's pipe (in a thread: it blocks until the worker reads)."""
    try:
        connection.send_bytes(job_bytes)
    except OSError:
        pass  # the worker was stopped before it read its job: it is not needed any more
    finally:
        connection.close()


def _worker_main(job_connection, counter, results, setup: Callable[[], object] | None,
                 preload: Sequence[str]) -> None:
    """Body of a worker process: run ``setup``, import ``preload``, then read the job (task,
    chunk bounds) from its pipe, claim chunks until none is left, put ``(chunk, ok, payload)``
    on ``results``. Ctrl-C is left to the caller, which stops its workers."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if setup is not None:
        setup()
    for module in preload:
        importlib.import_module(module)
    try:
        task, bounds = pickle.loads(job_connection.recv_bytes())
    except EOFError:
        return  # the pool was closed without a job
    finally:
        job_connection.close()
    while True:
        chunk = _claim(counter)
        if chunk >= len(bounds):
            return
        try:
            payload, ok = task(*bounds[chunk]), True
        except BaseException:  # noqa: BLE001 - everything is reported to the caller
            payload, ok = traceback.format_exc(), False
        results.put((chunk, ok, payload))
        if not ok:
            return


class WorkerPool:
    """``n_workers`` worker processes, spawned at once, that share the chunks of one
    :meth:`run` with the calling process.

    Start the pool before the work is ready (e.g. before opening a session): each worker
    spends its start-up, a fresh interpreter importing ``preload`` (NumPy, OpenCV, ...), while
    the caller does its own. A pool runs one job and its workers then exit; use it as a
    context manager (or call :meth:`close`) so that they are stopped whatever happens.
    ``setup`` (a module-level function, or None) runs first in each worker.
    """

    def __init__(self, n_workers: int, *, setup: Callable[[], object] | None = None,
                 preload: Sequence[str] = ()) -> None:
        if isinstance(n_workers, bool) or not isinstance(n_workers, int) or n_workers < 0:
            raise ValueError(f"n_workers must be an integer >= 0, got {n_workers!r}")
        context = multiprocessing.get_context("spawn")
        self._counter = context.Value("q", 0)
        self._results = context.Queue()
        self._senders: list[threading.Thread] = []
        self._used = False
        pipes = [context.Pipe(duplex=False) for _ in range(n_workers)]
        self._job_connections = [sender for _, sender in pipes]
        self._workers = [
            context.Process(target=_worker_main, args=(receiver, self._counter, self._results, setup, tuple(preload)),
                            daemon=True, name=f"contact-viz-worker-{k}")
            for k, (receiver, _) in enumerate(pipes)
        ]
        try:
            for worker, (receiver, _) in zip(self._workers, pipes):
                worker.start()
                receiver.close()  # the worker holds its own end now
        except BaseException:
            self.close()
            raise

    @property
    def n_workers(self) -> int:
        """Number of worker processes (the caller is not counted)."""
        return len(self._workers)

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def run(self, task: ChunkTask, n_items: int, *, chunk_size: int,
            progress: Callable[[int], None] | None = None) -> list[Any]:
        """``task(lo, hi)`` over the chunks of ``range(n_items)``, shared by the caller and the
        workers; the results of all items, in item order. ``progress`` is called in the caller
        with the number of items done so far. Raises :class:`WorkerError` when the task raised
        in a worker (the caller's own exceptions propagate as they are). Closes the pool."""
        if self._used:
            raise RuntimeError("a WorkerPool runs one job; start a new pool for the next")
        self._used = True
        try:
            return self._run(task, chunk_bounds(n_items, chunk_size), progress)
        finally:
            self.close()

    def _run(self, task: ChunkTask, bounds: list[tuple[int, int]], progress) -> list[Any]:
        done: dict[int, list[Any]] = {}
        n_done = 0

        def store(chunk: int, items: list[Any]) -> None:
            nonlocal n_done
            lo, hi = bounds[chunk]
            if len(items) != hi - lo:
                raise ValueError(f"task returned {len(items)} results for items {lo}..{hi - 1}, expected {hi - lo}")
            done[chunk] = items
            n_done += hi - lo
            if progress is not None:
                progress(n_done)

        def collect(block: bool) -> None:
            while True:
                try:
                    chunk, ok, payload = self._results.get(block=block, timeout=WORKER_POLL_S if block else None)
                except queue.Empty:
                    return
                if not ok:
                    lo, hi = bounds[chunk]
                    raise WorkerError(f"a worker process failed on items {lo}..{hi - 1}:\n{payload}")
                store(chunk, payload)
                block = False

        if self._workers and len(bounds) > 1:
            # The job travels through pipes written by threads: a pipe write blocks until the
            # worker reads, and a worker still starting up reads late, while the caller computes.
            job_bytes = pickle.dumps((task, bounds), protocol=pickle.HIGHEST_PROTOCOL)
            self._senders = [threading.Thread(target=_send_job, args=(connection, job_bytes), daemon=True)
                             for connection in self._job_connections]
            self._job_connections = []
            for sender in self._senders:
                sender.start()
        while (chunk := _claim(self._counter)) < len(bounds):
            store(chunk, task(*bounds[chunk]))
            collect(block=False)
        # Every chunk is claimed; wait for the workers' last ones. A chunk claimed by a worker
        # that has exited without delivering it (killed) is computed here.
        while len(done) < len(bounds):
            collect(block=True)
            if len(done) < len(bounds) and not any(w.is_alive() for w in self._workers):
                collect(block=False)  # anything a worker put just before exiting
                for chunk in range(len(bounds)):
                    if chunk not in done:
                        store(chunk, task(*bounds[chunk]))
        return [item for chunk in range(len(bounds)) for item in done[chunk]]

    def close(self) -> None:
        """Stop the workers (those still busy or idle are terminated) and release the pipes."""
        for connection in self._job_connections:
            connection.close()  # a worker waiting for a job sees EOF and exits
        self._job_connections = []
        for worker in self._workers:
            if worker.is_alive():
                worker.terminate()
        for worker in self._workers:
            if worker.pid is not None:  # started
                worker.join(WORKER_STOP_TIMEOUT_S)
        for sender in self._senders:
            sender.join(WORKER_STOP_TIMEOUT_S)
        self._results.close()
        self._results.join_thread()


def run_chunks(
    task: ChunkTask,
    n_items: int,
    *,
    chunk_size: int,
    processes: int,
    progress: Callable[[int], None] | None = None,
    worker_setup: Callable[[], object] | None = None,
) -> list[Any]:
    """``task(lo, hi)`` over the chunks of ``range(n_items)``, in ``processes`` processes; the
    results of all items, in item order.

    ``processes`` counts the caller: 1 runs everything here, without starting a process; more
    start a :class:`WorkerPool` of ``processes - 1`` workers (no more than there are chunks to
    share), each running ``worker_setup`` first. ``progress`` is called in the caller with the
    number of items done so far. Raises :class:`WorkerError` when the task raised in a worker.
    """
    if isinstance(processes, bool) or not isinstance(processes, int) or processes < 1:
        raise ValueError(f"processes must be a positive integer, got {processes!r}")
    n_workers = min(processes - 1, max(len(chunk_bounds(n_items, chunk_size)) - 1, 0))
    with WorkerPool(n_workers, setup=worker_setup) as pool:
        return pool.run(task, n_items, chunk_size=chunk_size, progress=progress)
