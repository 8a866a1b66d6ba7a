"""A synthetic session written in real time, as a recorder writes one (``write_live``).

``write_live(out, params, fps)`` writes exactly the files ``generate_session(out, params)`` writes
(byte-identical once it has finished), but frame by frame: frame k is written at ``t0 + k / fps``.
It is the recorder that the live viewer (``contact-viz SESSION --follow``) is tested, measured and
shown with.

Rendering is slower than most frame rates (one core renders about 7 frames/s at 1280x720 and 3.5
at 1920x1080), so frames are rendered ahead by worker processes (``workers``, one per core by
default; processes, because a rendering thread would hold the GIL and delay the writer's wake-ups
by milliseconds) into a hidden folder beside the session (``.OUT.PID-NS.live``,
:func:`contact_viz.io.atomic.staging_path`, removed at the end), and played from there at the
given rate: playback starts as soon as the frames rendered so far and the measured rendering rate
let every later frame be ready in time (``prerender=True``: only once all are rendered, so that no
rendering competes with a reader being measured). A frame that is not rendered in time is written
late (``LiveStats``); the schedule is kept, so the frames after it catch up. As with any spawned
process, a script calling ``write_live`` at import time needs an ``if __name__ == "__main__":`` guard.

What appears in ``out`` (created at once, empty; removed again if the run stops before step 1), in
this order (the recorder contract):

1. at ``t0 - 1 / fps``: the folders left/, right/, masks/, depth/; K.txt; the header lines of
   force.csv, truth.csv and (glove) labels.csv; session.json last;
2. per frame k, from ``t0 + k / fps``: right/STEM.jpg, masks/STEM.png, depth/STEM.npy, then
   left/STEM.jpg (the left image is the frame list, so when it appears the frame's other files are
   there), then its force.csv row (with ``force_delay_frames = d``: instead, the rows of frame k - d,
   and after the last frame those still owed), its truth.csv row and its labels.csv row, each
   appended with one write of whole lines (``os.write`` on an ``O_APPEND`` descriptor: no buffer
   to flush);
3. nothing at the end: the session is complete when the last frame's rows are there. No file is
   fsynced (a recorder at 30 frames/s would not either).

With ``rename=True`` (the default) every file is written under a hidden temporary name in its own
folder (``left/.000012.jpg.PID-NS.tmp``: starts with '.', ends with '.tmp') and renamed into
place, so a file under its own name is always complete. With ``rename=False`` every file is
written in place, in ``CHUNKS`` pieces with short sleeps between them (together ``IN_PLACE_SHARE``
of a frame interval per frame), and every CSV append in two writes (half a line, a sleep, the
rest), so that a reader sees half-written files and lines (the case its "the size has stopped
changing and it decodes completely" rule is for).

Stopping: the ``stop`` event (checked before each frame and while waiting for it), Ctrl-C or
SIGTERM (``console.Stopped``, a KeyboardInterrupt). A frame interrupted before its left image is in
place is removed; one interrupted after it gets its rows; the force rows still owed are written.
So a stopped run leaves a valid session of the frames it completed (session.json still describes
the whole planned session). A KeyboardInterrupt is raised again after this cleanup.
"""

from __future__ import annotations

import collections
import concurrent.futures as cf
import contextlib
import os
import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from contact_viz.io.atomic import reported_as, staging_path, sweep_stale
from contact_viz.io.jsonfile import write_json
from contact_viz.synth.files import (
    _SESSION_DIRS,
    _SESSION_FILES,
    _check_target,
    _frame_scene,
    _write_frame,
    _write_tables,
    davis_palette,
    session_description,
)
from contact_viz.synth.params import STREAM_DEPTH, STREAM_TEXTURE, SynthParams, stream_rng
from contact_viz.synth.render import Renderer
from contact_viz.synth.scene import stereo_camera, tissue_frame
from contact_viz.synth.second import plan_tracks
from contact_viz.synth.sensors import stereo_depth

# The files of a frame, in the order they are written: (folder, suffix); left last.
FRAME_FILES: tuple[tuple[str, str], ...] = (("right", ".jpg"), ("masks", ".png"), ("depth", ".npy"), ("left", ".jpg"))
CHUNKS = 4  # rename=False: each file is written in this many pieces, count
IN_PLACE_SHARE = 0.75  # rename=False: the sleeps between the pieces of a frame's files, fraction of 1/fps
LOOKAHEAD = 4  # once playing, frames rendered ahead of the one played, per render worker, count
RATE_MARGIN = 0.5  # playback starts when the frames would be rendered in time at this fraction of the measured rate
_POLL_S = 0.05  # longest single wait (for a rendered frame, or for the schedule) between looks at ``stop``, s


@dataclass(frozen=True)
class LiveStats:
    """How a live run went.

    frames: frames written completely; total: frames of the session; fps: the rate asked for.
    achieved_fps: frames per second between the starts of the first and the last frame written
    (None for fewer than 2 frames). max_late_s: the largest lateness of a frame, the time its first
    file was started after its scheduled time ``t0 + k / fps``, s; late_frames: frames started more
    than one frame interval late. lead_s: from the call to frame 0's time ``t0`` (rendering ahead), s.
    stopped: ended early (``stop``, Ctrl-C, SIGTERM).
    """

    frames: int
    total: int
    fps: float
    achieved_fps: float | None
    max_late_s: float
    late_frames: int
    lead_s: float
    stopped: bool

    def line(self, out_dir: str | Path) -> str:
        """The one line the `synth --live` command ends with."""
        rate = f"{self.achieved_fps:.2f}" if self.achieved_fps is not None else "-"
        what = f"{self.frames} frames" if not self.stopped else f"stopped after {self.frames} of {self.total} frames"
        return (f"{out_dir}: {what} written at {rate} frames/s (asked {self.fps:g}), largest lateness "
                f"{self.max_late_s * 1000:.1f} ms, {self.late_frames} frames over 1/fps late; "
                f"rendered ahead for {self.lead_s:.1f} s")


_WORKER_STATE: dict = {}  # in a render worker: {params: (renderer, camera, tracks, palette)}, built on its first frame


def _render_into(stage: str, params: SynthParams, i: int) -> float | None:
    """In a render worker: frame ``i``'s files into ``stage``, encoded as ``generate_session`` does.
    The seconds it took (None for the worker's first frame, which also built its renderer)."""
    start = time.perf_counter()
    state = _WORKER_STATE.get(params)
    first = state is None
    if first:
        _WORKER_STATE.clear()
        camera, frame = stereo_camera(params), tissue_frame(params)
        renderer = Renderer(params, camera, frame, stream_rng(params, STREAM_TEXTURE))
        state = _WORKER_STATE[params] = (renderer, camera, plan_tracks(params), davis_palette())
    renderer, camera, tracks, palette = state
    views = renderer.render(*_frame_scene(renderer, tracks, i, params))
    left = views["left"]
    depth = stereo_depth(left["z"], views["right"]["z"], left["tool"], left["specular"], camera, params,
                         stream_rng(params, STREAM_DEPTH, i))
    _write_frame(Path(stage), f"{i:06d}", views, depth, params.jpeg_quality, palette)
    return None if first else time.perf_counter() - start


class _Producer:
    """Render workers (spawned processes: rendering holds the GIL, which would make a thread delay
    the player by milliseconds at every sleep) filling the stage ahead of the player, in frame order.

    They render as fast as they can, except when they are comfortably faster than the playback
    (``RATE_MARGIN``): then at most ``LOOKAHEAD`` frames per worker beyond the frame being played
    are in the stage or on the way (the stage holds about 9 MB per 1080p frame)."""

    def __init__(self, stage: Path, params: SynthParams, fps: float, workers: int) -> None:
        from contact_viz.pipeline.parallel import ProcessPool

        self.stage, self.params, self.fps, self.workers = stage, params, fps, workers
        # ProcessPool: the package's spawned workers (they ignore Ctrl-C/SIGTERM, die with this process,
        # are killed on close); jobs go to its executor directly, to get them back one by one, in order.
        self.pool = ProcessPool(workers + 1, preload=("contact_viz.synth.live",))
        self.futures: list[cf.Future] = []
        self.seconds: list[float] = []  # how long each job took (but each worker's first), in the order they ended
        self.ended: list[float] = []  # when each of those ended (monotonic), s
        self.playing: int | None = None  # the frame being played (None: playback has not started)
        self._ready = 0

    def _done(self, future: cf.Future) -> None:  # in the executor's thread
        if not future.cancelled() and future.exception() is None and future.result() is not None:
            self.seconds.append(future.result())
            self.ended.append(time.monotonic())

    @property
    def ready(self) -> int:
        """Frames 0 .. ready-1 are in the stage."""
        while self._ready < len(self.futures) and self.futures[self._ready].done():
            self._check(self._ready)
            self._ready += 1
        return self._ready

    def rate(self) -> float | None:
        """The frames/s the workers render (recently), times ``RATE_MARGIN``; None before it is known.

        The smaller of the rate of their jobs (how long each took) and that of the jobs ending (which
        counts what the jobs do not time, and is lower while they wait for the lookahead)."""
        window = max(3, 4 * self.workers)
        took, ended = self.seconds[-window:], self.ended[-window:]
        if len(took) < 3:
            return None
        busy = self.workers * len(took) / max(sum(took), 1e-9)
        seen = (len(ended) - 1) / max(ended[-1] - ended[0], 1e-9)
        return RATE_MARGIN * min(busy, seen)

    def feed(self) -> None:
        """Hand out jobs, ``2 x workers`` in flight; once playing, within the lookahead when rendering is fast."""
        total = self.params.frames
        limit = total
        if self.playing is not None and (rate := self.rate()) is not None and rate >= self.fps:
            limit = min(total, self.playing + 1 + LOOKAHEAD * self.workers)
        in_flight = sum(not f.done() for f in self.futures[self._ready:])
        while len(self.futures) < limit and in_flight < 2 * self.workers:
            future = self.pool._executor.submit(_render_into, str(self.stage), self.params, len(self.futures))
            self.futures.append(future)
            future.add_done_callback(self._done)
            in_flight += 1

    def _check(self, k: int) -> None:
        """Raise the error of job ``k`` if it failed."""
        from concurrent.futures.process import BrokenProcessPool

        from contact_viz.pipeline.parallel import WorkerError

        future = self.futures[k]
        if future.done() and not future.cancelled() and future.exception() is not None:
            try:
                future.result()
            except BrokenProcessPool as exc:
                raise WorkerError(f"a render worker died (killed, out of memory, or its start-up failed) "
                                  f"while rendering frame {k}") from exc

    def can_start(self, prerender: bool) -> bool:
        """Whether playback from now lets every later frame be rendered in time."""
        total, ready, rate = self.params.frames, self.ready, self.rate()
        if ready >= total:
            return True
        if prerender or ready < 1 or rate is None:
            return False
        # frame k (k >= ready) is rendered by now + (k - ready + 1) / rate and played at now + k / fps
        return all((k - ready + 1) / rate <= k / self.fps for k in (ready, total - 1))

    def wait(self, predicate: Callable[[], bool], stop: threading.Event) -> bool:
        """Wait until ``predicate()`` (True) or ``stop`` (False), feeding the workers; raise a job's error."""
        while True:
            self.feed()
            for k in range(self.ready, len(self.futures)):  # a failed job stops the run at once
                self._check(k)
            if predicate():
                return True
            if stop.is_set():
                return False
            pending = [f for f in self.futures[self._ready:] if not f.done()]
            if pending:
                cf.wait(pending, timeout=_POLL_S, return_when=cf.FIRST_COMPLETED)
            else:
                stop.wait(_POLL_S)

    def close(self) -> None:
        for future in self.futures:
            future.cancel()
        self.pool.close()


class _Appender:
    """A CSV file that rows are appended to, each append one ``os.write`` (or two, in place)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.fd = os.open(path, os.O_WRONLY | os.O_APPEND | getattr(os, "O_CLOEXEC", 0))
        self.pending = b""  # the rest of an append that was interrupted

    def append(self, data: bytes, pause: Callable[[], None] | None) -> None:
        """Append ``data`` (whole lines); with ``pause``: in two writes with ``pause()`` between (in place)."""
        self.pending = data
        if pause is not None and len(data) > 1:
            half = len(data) // 2
            self._write(data[:half])
            self.pending = data[half:]
            pause()
        self._write(self.pending)
        self.pending = b""

    def finish(self) -> None:
        """Write what an interrupted ``append`` left (so the file ends with whole lines)."""
        if self.pending:
            data, self.pending = self.pending, b""
            self._write(data)

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self.fd, view):]

    def close(self) -> None:
        os.close(self.fd)


def _write_renamed(path: Path, data: bytes) -> None:
    """``data`` under a hidden ``.NAME.PID-NS.tmp`` beside ``path``, renamed onto ``path``."""
    tmp = staging_path(path, "tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
        finally:
            os.close(fd)
        os.rename(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _write_in_place(path: Path, data: bytes, pause: Callable[[], None]) -> None:
    """``data`` written into ``path`` itself in ``CHUNKS`` pieces, with ``pause()`` between them."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_CLOEXEC", 0), 0o666)
    try:
        bounds = [round(len(data) * j / CHUNKS) for j in range(CHUNKS + 1)]
        for j in range(CHUNKS):
            if j:
                pause()
            view = memoryview(data)[bounds[j]:bounds[j + 1]]
            while view:
                view = view[os.write(fd, view):]
    finally:
        os.close(fd)


def _rows(data: bytes, total: int, path: Path) -> tuple[bytes, list[bytes]]:
    """A CSV file's header line and its rows, one per frame."""
    lines = data.splitlines(keepends=True)
    if len(lines) != total + 1:
        raise RuntimeError(f"{path}: expected a header and {total} rows, found {len(lines)} lines")
    return lines[0], lines[1:]


def write_live(
    out_dir: str | Path,
    params: SynthParams = SynthParams(),
    fps: float | None = None,
    *,
    rename: bool = True,
    stop: threading.Event | None = None,
    on_frame: Callable[[int, float], None] | None = None,
    force_delay_frames: int = 0,
    prerender: bool = False,
    overwrite: bool = False,
    on_start: Callable[[], None] | None = None,
    workers: int | None = None,
) -> LiveStats:
    """Write the session ``generate_session(out_dir, params)`` writes, frame k at ``t0 + k / fps``.

    ``fps``: the playback rate, frames/s (default ``params.fps``; the files do not depend on it).
    ``rename``: each file under a hidden temporary name, then renamed into place; False: written in
    place, slowly (see the module docstring for the order and both modes). ``stop``: an event that
    ends the run before the next frame (from another thread). ``on_frame(k, late_s)``: called after
    frame k is written, with how late it started. ``on_start()``: called before the first file,
    one frame interval before ``t0``. ``force_delay_frames``: frame k's force.csv row is written
    after frame k + that (and the last ones after the last frame). ``prerender``: render every
    frame before writing any. ``overwrite``: as ``generate_session`` (the previous session's files
    are removed just before the new ones are written). ``workers``: render processes (default: one
    per core, at most 8).

    Raises FileExistsError for a non-empty ``out_dir`` unless ``overwrite``; a KeyboardInterrupt
    (Ctrl-C, SIGTERM) is raised again once the frames written so far form a valid session.
    """
    if not isinstance(params, SynthParams):
        raise TypeError(f"params must be a SynthParams, got {type(params).__name__}")
    fps = float(params.fps if fps is None else fps)
    if not fps > 0 or fps == float("inf"):
        raise ValueError(f"fps must be a positive number of frames per second, got {fps}")
    if isinstance(force_delay_frames, bool) or not isinstance(force_delay_frames, int) or force_delay_frames < 0:
        raise ValueError(f"force_delay_frames must be an int >= 0, got {force_delay_frames!r}")
    if workers is None:
        from contact_viz.pipeline.parallel import DEFAULT_PROCESSES

        workers = DEFAULT_PROCESSES
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be an int >= 1, got {workers!r}")
    stop = stop if stop is not None else threading.Event()
    called = time.monotonic()
    out_dir = Path(out_dir)
    _check_target(out_dir, overwrite)
    created = not out_dir.exists()
    with reported_as(out_dir):
        out_dir.mkdir(parents=True, exist_ok=True)
        sweep_stale(out_dir)
        stage = staging_path(out_dir, "live")
        stage.mkdir()
    producer = None
    try:
        with reported_as(out_dir, stage):
            for sub in _SESSION_DIRS:
                (stage / sub).mkdir()
            camera, tracks = stereo_camera(params), plan_tracks(params)
            _write_tables(stage, params, camera, tracks)
            write_json(stage / "session.json", session_description(out_dir.resolve().name, params))
            player = _Player(out_dir, stage, params, fps, rename, force_delay_frames)
            producer = player.producer = _Producer(stage, params, fps, min(workers, params.frames))
            if not producer.wait(lambda: producer.can_start(prerender), stop):
                return player.stats(called, stopped=True)
            if overwrite:
                _remove_session(out_dir)
            player.play(stop, on_frame, on_start)
            return player.stats(called, stopped=player.written < params.frames)
    finally:
        if producer is not None:
            producer.close()
        shutil.rmtree(stage, ignore_errors=True)
        if created:  # stopped before writing anything: as before the call
            with contextlib.suppress(OSError):
                out_dir.rmdir()  # only if empty


def _remove_session(out_dir: Path) -> None:
    """The previous session's own files in ``out_dir`` (others are left alone)."""
    for name in _SESSION_FILES:
        (out_dir / name).unlink(missing_ok=True)
    for name in _SESSION_DIRS:
        if (out_dir / name).is_dir():
            shutil.rmtree(out_dir / name)


class _Player:
    """Moves the rendered frames from the stage into the session on schedule."""

    def __init__(self, out_dir: Path, stage: Path, params: SynthParams, fps: float, rename: bool,
                 force_delay: int) -> None:
        self.out, self.stage, self.params, self.fps, self.rename = out_dir, stage, params, fps, rename
        self.force_delay = force_delay
        self.producer: _Producer | None = None
        self.tables = {name: (stage / name).read_bytes() for name in _SESSION_FILES if (stage / name).is_file()}
        self.csv = {}  # name: (header, rows)
        for name in ("force.csv", "truth.csv", "labels.csv"):
            if name in self.tables:
                self.csv[name] = _rows(self.tables[name], params.frames, stage / name)
        self.appenders: dict[str, _Appender] = {}
        self.force_owed: collections.deque[int] = collections.deque()
        self.deadline, self.gaps = 0.0, 1  # in place: the sleeps of a frame end by ``deadline``; ``gaps`` to go
        self.written = 0
        self.t0 = None
        self.starts: list[float] = []
        self.late: list[float] = []

    def _pace(self, gaps: int) -> None:
        """In place: spread the next ``gaps`` sleeps over ``IN_PLACE_SHARE`` of a frame interval from now."""
        self.deadline, self.gaps = time.monotonic() + IN_PLACE_SHARE / self.fps, max(1, gaps)

    def _pause(self) -> None:
        """One of those sleeps: an equal share of the time left (none once the frame is behind)."""
        left = self.deadline - time.monotonic()
        if left > 0:
            time.sleep(left / self.gaps)
        self.gaps = max(1, self.gaps - 1)

    def _put(self, path: Path, data: bytes) -> None:
        if self.rename:
            _write_renamed(path, data)
        else:
            _write_in_place(path, data, self._pause)

    def _append(self, name: str, data: bytes) -> None:
        if data:
            self.appenders[name].append(data, None if self.rename else self._pause)

    def _begin(self) -> None:
        """The session-wide files: the folders, K.txt, the CSV headers, session.json last."""
        for sub in _SESSION_DIRS:
            (self.out / sub).mkdir()
        self._pace(2 * (CHUNKS - 1) + len(self.csv))
        self._put(self.out / "K.txt", self.tables["K.txt"])
        for name, (header, _) in self.csv.items():
            path = self.out / name
            if self.rename:
                _write_renamed(path, header)
                self.appenders[name] = _Appender(path)
            else:
                path.touch(exist_ok=False)
                self.appenders[name] = _Appender(path)
                self._append(name, header)
        self._put(self.out / "session.json", self.tables["session.json"])

    def play(self, stop: threading.Event, on_frame, on_start) -> None:
        total = self.params.frames
        self.t0 = time.monotonic() + 1.0 / self.fps  # frame 0; the session-wide files one interval before
        if on_start is not None:
            on_start()
        try:
            try:
                self._begin()
            except BaseException:  # no half set of session-wide files
                self._close()
                _remove_session(self.out)
                raise
            for k in range(total):
                self.producer.playing = k
                if not self.producer.wait(lambda: self.producer.ready > k, stop):
                    break
                due = self.t0 + k / self.fps
                while (wait := due - time.monotonic()) > 0:
                    if stop.wait(min(wait, _POLL_S)):
                        break
                if stop.is_set():
                    break
                started = time.monotonic()
                self._frame(k)
                self.written = k + 1
                self.starts.append(started)
                self.late.append(max(0.0, started - due))
                if on_frame is not None:
                    on_frame(k, self.late[-1])
        finally:
            try:
                self._pay_force(self.written)
            finally:
                self._close()

    def _close(self) -> None:
        for appender in self.appenders.values():
            appender.close()
        self.appenders.clear()

    def _frame(self, k: int) -> None:
        stem = f"{k:06d}"
        placed: list[Path] = []
        self._pace(len(FRAME_FILES) * (CHUNKS - 1) + len(self.csv))
        try:
            for sub, suffix in FRAME_FILES:
                source = self.stage / sub / f"{stem}{suffix}"
                data = source.read_bytes()
                target = self.out / sub / source.name
                placed.append(target)
                self._put(target, data)
                source.unlink()
        except BaseException:  # not yet a frame of the session (no left image): none of its files stays
            for path in placed:
                path.unlink(missing_ok=True)
            raise
        self.force_owed.append(k)
        due = []
        while self.force_owed and self.force_owed[0] <= k - self.force_delay:
            due.append(self.force_owed.popleft())
        rows = [("force.csv", b"".join(self.csv["force.csv"][1][j] for j in due))]
        rows += [(name, self.csv[name][1][k]) for name in ("truth.csv", "labels.csv") if name in self.csv]
        done = 0
        try:
            for name, data in rows:
                self._append(name, data)
                done += 1
        except BaseException:  # the left image is there: the frame keeps its rows
            self.written = k + 1
            self.appenders[rows[done][0]].finish()
            for name, data in rows[done + 1:]:
                self.appenders[name].append(data, None)
            raise

    def _pay_force(self, written: int) -> None:
        """The force rows still owed of the frames written (one write)."""
        owed = [j for j in self.force_owed if j < written]
        self.force_owed.clear()
        if "force.csv" in self.appenders:
            self.appenders["force.csv"].finish()
            if owed:
                self.appenders["force.csv"].append(b"".join(self.csv["force.csv"][1][j] for j in owed), None)

    def stats(self, called: float, stopped: bool) -> LiveStats:
        n = len(self.starts)
        achieved = (n - 1) / (self.starts[-1] - self.starts[0]) if n > 1 and self.starts[-1] > self.starts[0] else None
        return LiveStats(
            frames=self.written,
            total=self.params.frames,
            fps=self.fps,
            achieved_fps=achieved,
            max_late_s=max(self.late, default=0.0),
            late_frames=sum(1 for s in self.late if s > 1.0 / self.fps),
            lead_s=(self.t0 if self.t0 is not None else time.monotonic()) - called,
            stopped=stopped,
        )
