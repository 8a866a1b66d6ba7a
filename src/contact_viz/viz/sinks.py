"""Where a recording goes: an .rrd file, a running viewer, a spawned one, a served web viewer.

The file is written under a temporary name beside the one asked for (``.NAME.PID-NS.part``) and
renamed into place by :meth:`OpenedRecording.close`, so a run that fails or is killed never
leaves a truncated recording under the user's name. Every flush has a deadline
(:data:`FLUSH_TIMEOUT_S`): a full disk, a vanished viewer or a stuck writer becomes a
:class:`SinkError` naming the file or address, never a hang.
"""

from __future__ import annotations

import errno
import os
import shutil
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import quote

import rerun as rr

from contact_viz.io.atomic import staging_path, sweep_stale
from contact_viz.viz.entities import APPLICATION_ID

DEFAULT_GRPC_PORT = 9876  # Rerun's default gRPC port
DEFAULT_WEB_PORT = 9090  # Rerun's default web viewer port
FLUSH_TIMEOUT_S = 20.0  # longest wait for one flush of the recording to its sinks, s
CLOSE_TIMEOUT_S = 5.0  # longest wait for the sinks to close after the last flush, s
_LOW_SPACE_BYTES = 1 << 20  # a device with less free space than this is called full, bytes
_STUCK: list[str] = []  # sinks that missed a deadline: the SDK's exit-time flush would wait for them forever


class SinkError(OSError):
    """A recording could not be written or sent (full disk, the viewer went away, a stuck writer);
    ``detail``: the SDK's own words."""

    detail: str = ""


@dataclass
class OpenedRecording:
    """A recording stream and where it goes; :meth:`close` it (the .rrd appears then)."""

    rec: rr.RecordingStream
    web_viewer_url: str | None  # with serve: open this in a browser (keep the process alive)
    grpc_url: str | None  # with serve or spawn: the gRPC address viewers connect to
    save: Path | None = None  # the .rrd asked for (written by close())
    part: Path | None = None  # the file being written, renamed onto ``save`` by close()
    targets: tuple[str, ...] = ()  # the viewer addresses streamed to, for messages
    closed: bool = field(default=False, init=False)

    def flush(self, timeout_s: float = FLUSH_TIMEOUT_S) -> None:
        """Flush to every sink within ``timeout_s``; SinkError (naming the file or viewer) otherwise."""
        flush(self.rec, timeout_s, where=self.where)

    def close(self, keep: bool = True) -> None:
        """Flush, close the sinks and, with ``keep``, rename the written file onto ``save``;
        without (or when the flush fails) remove it. Each step has a deadline; idempotent."""
        if self.closed:
            return
        self.closed = True
        try:
            if keep:
                self.flush()
        except BaseException:
            keep = False
            raise
        finally:
            _disconnect(self.rec, CLOSE_TIMEOUT_S)
            if self.part is not None:
                if keep:
                    os.replace(self.part, self.save)
                else:
                    self.part.unlink(missing_ok=True)

    def explain(self, exc: SinkError) -> SinkError:
        """``exc`` (raised by a flush that did not know where the recording goes) told about this recording."""
        return _sink_error(RuntimeError(exc.detail), self.where, FLUSH_TIMEOUT_S)

    @property
    def where(self) -> str:
        """The file (or else the viewer addresses) this recording goes to, for messages."""
        return str(self.save) if self.save is not None else ", ".join(self.targets) or "the recording"


def flush(rec: rr.RecordingStream, timeout_s: float = FLUSH_TIMEOUT_S, *, where: str = "the recording") -> None:
    """``rec.flush`` with a deadline; its failure as a SinkError naming ``where`` (a file or viewer)."""
    try:
        rec.flush(timeout_sec=timeout_s)
    except RuntimeError as exc:
        _STUCK.append(where)
        raise _sink_error(exc, where, timeout_s) from None


def exit_would_hang() -> bool:
    """Whether a sink missed a deadline in this process: Rerun's at-exit shutdown (an unbounded flush of
    every recording) would then never return, so the command must leave with ``os._exit``."""
    return bool(_STUCK)


def _sink_error(exc: RuntimeError, where: str, timeout_s: float) -> SinkError:
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    error = _classify(text, where, timeout_s)
    error.detail = text
    return error


def _classify(text: str, where: str, timeout_s: float) -> SinkError:
    if where.endswith((".rrd", ".part")):
        try:
            free = shutil.disk_usage(Path(where).parent).free
        except OSError:
            free = None
        if free is not None and free < _LOW_SPACE_BYTES:
            return SinkError(errno.ENOSPC, "no space left on the device", where)
        return SinkError(errno.EIO, f"writing the recording failed ({text})", where)
    if "timeout" in text.lower() or "timed out" in text.lower():
        return SinkError(errno.ETIMEDOUT, f"the viewer took more than {timeout_s:g} s to take the data; "
                         "expected a running viewer (or --save out.rrd)", where)
    return SinkError(errno.EIO, f"sending to the viewer failed ({text}); expected a running viewer "
                     "(or --save out.rrd)", where)


def _disconnect(rec: rr.RecordingStream, timeout_s: float) -> None:
    """Close the sinks, waiting at most ``timeout_s`` (a sink stuck on a dead peer is abandoned)."""
    closer = threading.Thread(target=rec.disconnect, name="contact-viz-close-sinks", daemon=True)
    closer.start()
    closer.join(timeout_s)
    if closer.is_alive():
        _STUCK.append("disconnect")


def part_path(save: Path) -> Path:
    """The temporary name ``save`` is written under (hidden, beside it); stale ones of killed runs are
    removed first (contact_viz.io.atomic.sweep_stale)."""
    sweep_stale(save)
    return staging_path(save, "part")


def open_recording(
    *,
    save: str | Path | None = None,
    connect: str | None = None,
    spawn: bool = False,
    serve: bool = False,
    grpc_port: int = DEFAULT_GRPC_PORT,
    web_port: int = DEFAULT_WEB_PORT,
    blueprint=None,
    recording_id: str | None = None,
    streamed: bool = False,
) -> OpenedRecording:
    """A recording stream that writes to every chosen sink (at least one); ``close()`` it.

    save: an .rrd file (replaced by close(); written until then under :func:`part_path`).
    connect: the gRPC URL of a running viewer, e.g. ``rerun+http://127.0.0.1:9876/proxy``.
    spawn: start a native viewer (needs a display) on ``grpc_port`` and stream to it.
    serve: host a gRPC server on ``grpc_port`` and a web viewer on ``web_port`` in this process.
    ``blueprint`` (default: none) is sent to every sink as the default layout.
    ``streamed`` (save only, no other sink): a file without Rerun's footer. The footer's index of every
    chunk is kept in memory until the end, about 10 kB per debugger frame (1 GB an hour at 30
    frames/s; ``benchmarks/bench_live.py --memory``); without it the memory stays flat and a viewer
    reads the file whole, as it does a recording cut short.
    """
    if streamed and save is not None and not (spawn or connect or serve):
        save = Path(save)
        if save.suffix != ".rrd":
            raise ValueError(f"save: expected a path ending in .rrd, got {str(save)!r}")
        if not save.parent.is_dir():
            raise ValueError(f"save: directory {str(save.parent)!r} does not exist")
        rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
        part = part_path(save)
        rec.save(part, default_blueprint=blueprint, write_footer=False)
        return OpenedRecording(rec=rec, web_viewer_url=None, grpc_url=None, save=save, part=part)
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
    sinks = []
    targets = []
    web_url = grpc_url = part = None
    if save is not None:
        save = Path(save)
        if save.suffix != ".rrd":
            raise ValueError(f"save: expected a path ending in .rrd, got {str(save)!r}")
        if not save.parent.is_dir():
            raise ValueError(f"save: directory {str(save.parent)!r} does not exist")
        part = part_path(save)
        sinks.append(rr.FileSink(part))
    if spawn:
        # The viewer binary ships with rerun-sdk beside this interpreter; PATH may not include it.
        beside = Path(sys.executable).with_name("rerun")
        try:
            rr.spawn(port=grpc_port, connect=False, hide_welcome_screen=True, recording=rec,
                     executable_path=str(beside) if beside.exists() else None)
        except RuntimeError as exc:
            raise ValueError(f"spawn: could not start the Rerun viewer ({str(exc).splitlines()[0]}); "
                             "use --save out.rrd instead") from None
        grpc_url = f"rerun+http://127.0.0.1:{grpc_port}/proxy"
        sinks.append(rr.GrpcSink(grpc_url))
        targets.append(grpc_url)
    if connect is not None:
        sinks.append(rr.GrpcSink(connect))
        targets.append(connect)
    if serve:
        server = rr.GrpcServerSink(port=grpc_port)
        sinks.append(server)
        grpc_url = server.uri.replace("0.0.0.0", "127.0.0.1")  # the server binds every interface
    if not sinks:
        raise ValueError("open_recording: choose at least one sink (save, connect, spawn or serve)")
    rec.set_sinks(*sinks, default_blueprint=blueprint)
    if serve:
        rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=grpc_url)
        web_url = f"http://localhost:{web_port}/?url={quote(grpc_url, safe='')}"
    return OpenedRecording(rec=rec, web_viewer_url=web_url, grpc_url=grpc_url, save=save, part=part,
                           targets=tuple(targets))
