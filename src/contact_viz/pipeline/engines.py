"""Where `contact-viz batch` runs its tasks: this machine's cores, or a Ray cluster.

An engine takes a list of calls ``(function, args)`` and yields ``(position, result)`` as each call
completes, where ``result`` is the function's return value or the exception it raised (a failing
call never stops the others). Functions must be importable module-level functions and their
arguments and results picklable, because they run in other processes or on other machines.

- :class:`LocalEngine`: the process pool of `contact-viz extract` (:mod:`contact_viz.pipeline.parallel`:
  spawned processes, one per core by default, this one included); with one process the calls run
  in this process, one after the other.
- :class:`RayEngine`: each call is a Ray task (``num_cpus=1``). ``address=None`` starts a local
  Ray on the fly; otherwise it joins an existing cluster (``"auto"``, or ``"ray://HOST:10001"``).
  Ray is imported only here, only when this engine is created (``pip install contact-viz[ray]``).
  Every node needs the same Python environment (contact-viz installed) and must see the session
  folders at the same paths (a shared file system); results travel back to the driver, which
  writes every output file itself.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any

from contact_viz.errors import SessionError
from contact_viz.pipeline.parallel import DEFAULT_PROCESSES, ProcessPool

Call = tuple[Callable[..., Any], tuple]

__all__ = ["Call", "LocalEngine", "RayEngine", "default_processes"]


def default_processes() -> int:
    """The usable cores of this process (at most 8), as `contact-viz extract` uses them."""
    return DEFAULT_PROCESSES


def _capture(call: Call) -> Any:
    """Run one call; its exception is returned as its result (a failing call never stops the others)."""
    function, args = call
    try:
        return function(*args)
    except SessionError as exc:  # its (path, expected) constructor does not survive pickling: keep type and text
        return ValueError(str(exc))
    except Exception as exc:
        return exc


class LocalEngine:
    """This machine's cores: the pool `contact-viz extract` uses (:class:`contact_viz.pipeline.parallel.ProcessPool`,
    ``processes`` processes, this one included; 1 = in this process)."""

    name = "local"

    def __init__(self, processes: int | None = None) -> None:
        self.processes = processes or default_processes()
        self._pool = ProcessPool(self.processes)

    def run(self, calls: Sequence[Call], progress: Callable[[int], None] | None = None) -> Iterator[tuple[int, Any]]:
        yield from enumerate(self._pool.map(_capture, list(calls), progress=progress))

    def close(self) -> None:
        self._pool.close()

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

    def run(self, calls: Sequence[Call], progress: Callable[[int], None] | None = None) -> Iterator[tuple[int, Any]]:
        ray = self._ray
        refs = {}
        for position, (function, args) in enumerate(calls):
            remote = self._remote.get(function)
            if remote is None:
                remote = self._remote[function] = ray.remote(num_cpus=1, max_retries=0)(function)
            refs[remote.remote(*args)] = position
        pending = list(refs)
        finished = 0
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                try:
                    result = ray.get(ref)
                except ray.exceptions.RayTaskError as exc:  # the task's own exception, as raised there
                    result = exc.cause if isinstance(exc.cause, BaseException) else RuntimeError(str(exc))
                except ray.exceptions.RayError as exc:  # a worker or node died
                    result = RuntimeError(f"Ray task lost: {type(exc).__name__}: {exc}")
                finished += 1
                if progress is not None:
                    progress(finished)
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
