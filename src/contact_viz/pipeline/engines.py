"""Where `contact-viz batch` runs its tasks: this machine's cores, or a Ray cluster.

An engine takes a list of calls ``(function, args)`` and yields ``(position, result)`` as each call
completes, where ``result`` is the function's return value or the exception it raised (a failing
call never stops the others). Functions must be importable module-level functions and their
arguments and results picklable, because they run in other processes or on other machines.

- :class:`LocalEngine`: ``concurrent.futures.ProcessPoolExecutor`` with spawned processes (one per
  core by default); with one process the calls run in this process, one after the other.
- :class:`RayEngine`: each call is a Ray task (``num_cpus=1``). ``address=None`` starts a local
  Ray on the fly; otherwise it joins an existing cluster (``"auto"``, or ``"ray://HOST:10001"``).
  Ray is imported only here, only when this engine is created (``pip install contact-viz[ray]``).
  Every node needs the same Python environment (contact-viz installed) and must see the session
  folders at the same paths (a shared file system); results travel back to the driver, which
  writes every output file itself.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from typing import Any

Call = tuple[Callable[..., Any], tuple]

__all__ = ["Call", "LocalEngine", "RayEngine", "default_processes"]


def default_processes() -> int:
    """The usable cores of this process (at most 8)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, 8))


class LocalEngine:
    """This machine's cores: spawned worker processes (``processes`` of them; 1 = in this process)."""

    name = "local"

    def __init__(self, processes: int | None = None) -> None:
        self.processes = processes or default_processes()
        self._pool: ProcessPoolExecutor | None = None
        if self.processes > 1:
            self._pool = ProcessPoolExecutor(max_workers=self.processes,
                                             mp_context=multiprocessing.get_context("spawn"))

    def run(self, calls: Sequence[Call]) -> Iterator[tuple[int, Any]]:
        if self._pool is None:
            for position, (function, args) in enumerate(calls):
                try:
                    result = function(*args)
                except Exception as exc:  # reported per call, as the pool does
                    result = exc
                yield position, result
            return
        futures: dict[Future, int] = {self._pool.submit(function, *args): i for i, (function, args) in enumerate(calls)}
        pending = set(futures)
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                exc = future.exception()
                yield futures[future], exc if exc is not None else future.result()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None

    def describe(self) -> str:
        return f"local, {self.processes} process{'es' if self.processes > 1 else ''}"


class RayEngine:
    """Ray tasks: a local Ray started on the fly (``address=None``) or an existing cluster."""

    name = "ray"

    def __init__(self, address: str | None = None, num_cpus: int | None = None) -> None:
        try:
            import ray
        except ImportError as exc:  # the optional extra is missing
            raise RuntimeError("--ray needs Ray: pip install 'contact-viz[ray]'") from exc
        self._ray = ray
        self._started = not ray.is_initialized()
        if self._started:
            kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False,
                                      "configure_logging": False}
            if address is None:
                kwargs["num_cpus"] = num_cpus or default_processes()
            else:
                kwargs["address"] = address
            try:
                ray.init(**kwargs)
            except (ConnectionError, ValueError, RuntimeError) as exc:
                where = address or "a local Ray"
                raise RuntimeError(f"--ray-address {where}: could not start or join Ray ({exc})") from exc
        self.address = address
        self._remote: dict[Callable, Any] = {}

    def run(self, calls: Sequence[Call]) -> Iterator[tuple[int, Any]]:
        ray = self._ray
        refs = {}
        for position, (function, args) in enumerate(calls):
            remote = self._remote.get(function)
            if remote is None:
                remote = self._remote[function] = ray.remote(num_cpus=1, max_retries=0)(function)
            refs[remote.remote(*args)] = position
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                try:
                    result = ray.get(ref)
                except ray.exceptions.RayTaskError as exc:  # the task's own exception, as raised there
                    result = exc.cause if isinstance(exc.cause, BaseException) else RuntimeError(str(exc))
                except ray.exceptions.RayError as exc:  # a worker or node died
                    result = RuntimeError(f"Ray task lost: {type(exc).__name__}: {exc}")
                yield refs[ref], result

    def close(self) -> None:
        if self._started:
            self._ray.shutdown()
            self._started = False

    def describe(self) -> str:
        resources = self._ray.cluster_resources()
        nodes = len([n for n in self._ray.nodes() if n.get("Alive")])
        where = self.address or "local Ray"
        return f"ray ({where}: {nodes} node{'s' if nodes != 1 else ''}, {int(resources.get('CPU', 0))} CPUs)"
