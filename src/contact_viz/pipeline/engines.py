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
  writes every output file itself. Ctrl-C, SIGTERM and SIGHUP stop the command as with the local
  engine (the caller's SIGTERM handler, which ``ray.init`` replaces, is put back) and ``close``
  shuts a local Ray down. If the command is killed (SIGKILL), Ray's own fate sharing ends the
  local Ray's GCS and raylet at once and its task workers within seconds; its two agents
  (dashboard, runtime env) wait about a minute for the gone GCS before they exit.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from contact_viz.errors import SessionError
from contact_viz.pipeline.parallel import DEFAULT_PROCESSES, ProcessPool

Call = tuple[Callable[..., Any], tuple]

_STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))

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


def _keep_sigterm_handler(handler: Any) -> None:
    """Put back the caller's own SIGTERM handler (the CLI's: stop as Ctrl-C does, exit 143), which
    ``ray.init`` replaces by ``sys.exit(15)`` (and its core worker by a stack dump on stderr); a
    default handler is left to Ray."""
    if callable(handler) and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, handler)


@contextlib.contextmanager
def _handlers_exceptions_kept() -> Iterator[None]:
    """While Ray waits, it runs the signal handlers itself and raises a plain KeyboardInterrupt in
    place of the exception a handler raised (the CLI's console.Stopped, which names SIGTERM or
    SIGHUP: exit 128 + the signal): raise the handler's own exception instead."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    handlers = {signum: handler for signum in _STOP_SIGNALS if callable(handler := signal.getsignal(signum))}
    raised: list[BaseException] = []

    def run_handler(signum: int, frame: Any) -> None:
        try:
            handlers[signum](signum, frame)
        except BaseException as exc:
            raised.append(exc)
            raise

    for signum in handlers:
        signal.signal(signum, run_handler)
    try:
        yield
    except KeyboardInterrupt as exc:
        if raised and raised[-1] is not exc:
            raise raised[-1] from None
        raise
    finally:
        for signum, handler in handlers.items():
            signal.signal(signum, handler)


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
            on_sigterm = signal.getsignal(signal.SIGTERM)
            try:
                ray.init(**kwargs)
            except (ConnectionError, ValueError, RuntimeError) as exc:
                where = address or "a local Ray"
                raise RuntimeError(f"--ray-address {where}: could not start or join Ray ({exc})") from exc
            finally:
                _keep_sigterm_handler(on_sigterm)
        self.address = address
        self._remote: dict[Callable, Any] = {}

    def run(self, calls: Sequence[Call], progress: Callable[[int], None] | None = None) -> Iterator[tuple[int, Any]]:
        ray = self._ray
        refs = {}
        with _handlers_exceptions_kept():
            for position, (function, args) in enumerate(calls):
                remote = self._remote.get(function)
                if remote is None:
                    remote = self._remote[function] = ray.remote(num_cpus=1, max_retries=0)(function)
                refs[remote.remote(*args)] = position
        pending = list(refs)
        finished = 0
        while pending:
            with _handlers_exceptions_kept():
                done, pending = ray.wait(pending, num_returns=1)
                results = [(refs[ref], self._result(ref)) for ref in done]
            for position, result in results:
                finished += 1
                if progress is not None:
                    progress(finished)
                yield position, result

    def _result(self, ref: Any) -> Any:
        """The return value of a finished task, or the exception it raised (or that lost it)."""
        ray = self._ray
        try:
            return ray.get(ref)
        except ray.exceptions.RayTaskError as exc:  # the task's own exception, as raised there
            return exc.cause if isinstance(exc.cause, BaseException) else RuntimeError(str(exc))
        except ray.exceptions.RayError as exc:  # a worker or node died
            return RuntimeError(f"Ray task lost: {type(exc).__name__}: {exc}")

    def close(self) -> None:
        if self._started:
            self._ray.shutdown()
            self._started = False

    def describe(self) -> str:
        resources = self._ray.cluster_resources()
        nodes = len([n for n in self._ray.nodes() if n.get("Alive")])
        where = self.address or "local Ray"
        return f"ray ({where}: {nodes} node{'s' if nodes != 1 else ''}, {int(resources.get('CPU', 0))} CPUs)"
