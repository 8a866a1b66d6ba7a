"""Process-level parallelism over chunks of items, shared between the caller and spawned workers.

Threads cannot spread the per-frame work of `contact-viz extract` over the cores: between its
NumPy and OpenCV calls the patch holds the GIL, and so does the PNG decoder's Python side.
:func:`run_chunks` splits ``range(n_items)`` into chunks that the calling process and
``processes - 1`` spawned worker processes claim from one shared counter, so

* nobody waits for work another process has not started: a worker still importing NumPy
  when the caller has claimed the last chunk is simply stopped, so short runs pay nothing
  for it;
* the task (e.g. an opened session) is pickled once per worker, not once per chunk;
* a worker that dies (killed, out of memory) leaves its chunk to the caller, which computes
  it itself; an exception raised by the task in a worker is raised again in the caller.

Workers are started with the "spawn" method (a fresh interpreter: safe after OpenCV and
OpenBLAS have started their threads, unlike "fork"). As with any spawned process, a script
calling this at import time needs an ``if __name__ == "__main__":`` guard.
"""

from __future__ import annotations

import multiprocessing
import pickle
import queue
import threading
import traceback
from collections.abc import Callable, Sequence
from typing import Any, Protocol

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


def _send_task(connection, task_bytes: bytes) -> None:
    """Send the pickled task down a worker's pipe (in a thread: it blocks until the worker reads)."""
    try:
        connection.send_bytes(task_bytes)
    except OSError:
        pass  # the worker was stopped before it read its task: it is not needed any more
    finally:
        connection.close()


def _worker_main(task_connection, bounds: Sequence[tuple[int, int]], counter, results,
                 setup: Callable[[], object] | None) -> None:
    """Body of a worker process: run ``setup``, read the task from its pipe, claim chunks until
    none is left, put ``(chunk, ok, payload)`` on ``results``."""
    if setup is not None:
        setup()
    task = pickle.loads(task_connection.recv_bytes())
    task_connection.close()
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

    ``processes`` counts the caller: 1 runs everything here, without starting a process.
    ``progress`` is called in the caller with the number of items done so far. Each worker calls
    ``worker_setup`` (a module-level function, or None) once before its first chunk.
    Raises :class:`WorkerError` when the task raised in a worker (the caller's own exceptions
    propagate as they are); the workers are stopped in every case.
    """
    if isinstance(processes, bool) or not isinstance(processes, int) or processes < 1:
        raise ValueError(f"processes must be a positive integer, got {processes!r}")
    bounds = chunk_bounds(n_items, chunk_size)
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

    n_workers = min(processes - 1, len(bounds) - 1)
    if n_workers <= 0:
        for chunk, (lo, hi) in enumerate(bounds):
            store(chunk, task(lo, hi))
        return [item for chunk in range(len(bounds)) for item in done[chunk]]

    context = multiprocessing.get_context("spawn")
    counter = context.Value("q", 0)
    results = context.Queue()
    # The task travels through a pipe written by a thread, not through the process arguments:
    # Process.start() writes those itself and would block until the new interpreter has
    # imported everything that unpickling them needs, while the caller could be computing.
    task_bytes = pickle.dumps(task, protocol=pickle.HIGHEST_PROTOCOL)
    pipes = [context.Pipe(duplex=False) for _ in range(n_workers)]
    workers = [
        context.Process(target=_worker_main, args=(receiver, bounds, counter, results, worker_setup), daemon=True,
                        name=f"contact-viz-worker-{k}")
        for k, (receiver, _) in enumerate(pipes)
    ]
    senders = [threading.Thread(target=_send_task, args=(sender, task_bytes), daemon=True) for _, sender in pipes]

    def collect(block: bool) -> None:
        while True:
            try:
                chunk, ok, payload = results.get(block=block, timeout=WORKER_POLL_S if block else None)
            except queue.Empty:
                return
            if not ok:
                raise WorkerError(f"a worker process failed on items {bounds[chunk][0]}..{bounds[chunk][1] - 1}:\n"
                                  f"{payload}")
            store(chunk, payload)
            block = False

    try:
        for worker, (receiver, _), sender in zip(workers, pipes, senders):
            worker.start()
            receiver.close()  # the worker holds its own end now
            sender.start()
        while (chunk := _claim(counter)) < len(bounds):
            store(chunk, task(*bounds[chunk]))
            collect(block=False)
        # Every chunk is claimed; wait for the workers' last ones. A chunk claimed by a worker
        # that has exited without delivering it (killed) is computed here.
        while len(done) < len(bounds):
            collect(block=True)
            if len(done) < len(bounds) and not any(w.is_alive() for w in workers):
                collect(block=False)  # anything a worker put just before exiting
                for chunk in range(len(bounds)):
                    if chunk not in done:
                        store(chunk, task(*bounds[chunk]))
    finally:
        for worker in workers:
            if worker.is_alive():
                worker.terminate()
        for worker in workers:
            if worker.pid is not None:  # started
                worker.join(WORKER_STOP_TIMEOUT_S)
        for sender in senders:
            if sender.is_alive():
                sender.join(WORKER_STOP_TIMEOUT_S)
        results.close()
        results.join_thread()
    return [item for chunk in range(len(bounds)) for item in done[chunk]]
