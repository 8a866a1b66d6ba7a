"""The debugger on a session that is being recorded: every frame is logged as soon as its files are
complete (:class:`contact_viz.io.live.SessionFollower`), through the same per-frame path as a
finished session (:class:`contact_viz.viz.frame_log.FrameLogger`), with the causal posterior.

With ``from_start``, the frames there at the start are shown whole, one after another (a replay;
they are not counted in the latency). Falling behind: when several new frames are complete while the
one before them is read and logged, the newest is shown whole and the older ones only in the series
(distance, signal, posterior): the causal filter sees every frame. With SGBM depth (no depth/ in the
session) a frame shown only in the series is not matched either: the filter then steps over it without
an observation, and the summary counts it. The lag (a frame's last file completed -> its data logged,
ms) is a series of its own (``series/lag_ms``).
"""

from __future__ import annotations

import math
import threading
import time
import warnings
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import rerun as rr

from contact_viz.io.live import FollowParams, SessionFollower
from contact_viz.io.session import BadFrame
from contact_viz.pipeline.extract import BadFrameWarning, FrameResult, session_frame_patches
from contact_viz.viz import rerun_log
from contact_viz.viz.entities import ENTITY_SERIES_LAG
from contact_viz.viz.frame_log import FrameLogger
from contact_viz.viz.options import DebuggerOptions, RunSummary
from contact_viz.viz.sinks import flush

_LATENCY_WINDOW = 100_000  # latencies kept for the percentiles (the most recent), frames


@dataclass(frozen=True)
class FollowSummary:
    """What a follow run did: the debugger's summary, plus how it kept up."""

    run: RunSummary
    frames_series_only: int  # frames shown only in the series (the follower was behind)
    frames_unfiltered: int  # of those, frames without a distance (SGBM not run): the filter stepped over them
    frames_timed_out: int  # frames whose files never completed (skipped with a warning)
    frames_replayed: int  # --from-start: frames there at the start, logged whole (not in the latency)
    latency_ms: tuple[float, float, float]  # median, 95th percentile, max of complete -> logged (whole frames), ms
    stop: str  # "idle" (no new frame for --idle-timeout), "interrupted", or "" (stopped by the caller)

    def lines(self) -> list[str]:
        p50, p95, worst = self.latency_ms
        out = self.run.lines()
        latency = ("none (no frame arrived after the start)" if math.isnan(p50) else
                   f"median {p50:.0f} ms, 95th percentile {p95:.0f} ms, max {worst:.0f} ms")
        out.insert(1, f"latency (files complete -> logged): {latency}; frames shown only in the series: "
                      f"{self.frames_series_only} ({self.frames_unfiltered} without a distance); "
                      f"timed out: {self.frames_timed_out}")
        if self.frames_replayed:
            n = self.frames_replayed
            out.insert(1, f"replayed {n} frame{'' if n == 1 else 's'} there at the start (--from-start)")
        if self.stop == "idle":
            out.insert(1, "stopped: no new frame within --idle-timeout")
        return out


def follow_session(
    root,
    rec,
    options: DebuggerOptions = DebuggerOptions(),
    model=None,
    params: FollowParams = FollowParams(),
    *,
    open_kwargs: dict | None = None,
    progress: Callable[[int], None] | None = None,
    stop: Callable[[], bool] | None = None,
) -> FollowSummary:
    """Follow the session at ``root`` as it is recorded, logging to ``rec`` (an ``rr.RecordingStream``).

    Runs until ``params.idle_timeout_s`` passes without a new frame, ``stop()`` is true, or a
    KeyboardInterrupt (Ctrl-C, SIGTERM, SIGHUP): what was logged is flushed either way.
    ``progress(frames)`` is called after each frame logged whole.

    Three stages overlap: this thread polls the folders and decides how each new frame is shown, two
    worker threads read it (its patch, as `extract` computes it, beside its images), and a logging
    thread logs the frames in order (:class:`_FrameLog`). One frame is read while the one before it is
    logged; the frames that complete meanwhile are taken together: the newest whole, the older ones in
    the series only.
    """
    if options.hand_eye is not None:
        raise ValueError("--hand-eye: not available with --follow (kinematics.csv is read whole)")
    started = last_new = time.monotonic()
    try:
        waited = _wait_for_session(Path(root), params, stop, started)
    except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM, SIGHUP before the session appeared
        return _no_frame(started, "interrupted", getattr(exc, "signum", 2))
    if waited not in ("there", "made"):  # no session appeared: stopped as if idle (or by the caller)
        return _no_frame(started, waited)
    # a session made after the start: its frames are all new (none to start after, none to replay)
    follower = SessionFollower(root, params, new=waited == "made", **(open_kwargs or {}))
    readers = ThreadPoolExecutor(max_workers=2, thread_name_prefix="contact-viz-follow-read")
    log: _FrameLog | None = None
    waiting: deque[tuple[int, float, bool]] = deque()  # complete, not handed on: (index, completed, replay)
    held_force: list[dict[str, str]] = []  # force.csv rows of frames not there yet
    interrupted, stop_signal, why = False, 0, ""
    try:
        while True:
            arrived = follower.poll()
            now = time.monotonic()
            session = follower.session
            if arrived:
                last_new = now
                if log is None:
                    logger = FrameLogger(session, rec, replace(options, start=0, end=None, stride=1), model)
                    log = _FrameLog(logger, rec, progress)
                waiting.extend((index, completed, follower.from_backlog(session.stems[index]))
                               for index, completed in arrived)
            if log is not None:
                log.raise_error()
                _hand_on(waiting, log, readers, session, options)
                rows = follower.take_force_rows()
                if rows or (held_force and arrived):  # at their frames (this thread's time on the timelines)
                    held_force = _log_force(rec, session, held_force + rows)
                follower.prune()
            if not arrived:
                if params.idle_timeout_s is not None and now - last_new > params.idle_timeout_s:
                    why = "idle"
                    break
                if stop is not None and stop():
                    break
                time.sleep(params.poll_s)
        if log is not None:  # the frames taken so far are logged before the end
            _hand_on(waiting, log, readers, session, options, everything=True)
            log.close(wait=True)
            log.raise_error()
    except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM, SIGHUP (contact_viz.console.Stopped)
        interrupted, stop_signal, why = True, getattr(exc, "signum", 2), "interrupted"
    finally:
        summary = None
        if log is not None:
            log.close(wait=False)  # a stop: the frame being logged is finished, those queued are dropped
            readers.shutdown(wait=True, cancel_futures=True)
            done = log.logger.last_index + 1 if log.logger.last_index is not None else 0
            summary = log.logger.finish(range(done), started=started, interrupted=interrupted,
                                        stop_signal=stop_signal)
        else:
            readers.shutdown(wait=True, cancel_futures=True)
        flush(rec)
    if log is not None:
        log.raise_error()
    if summary is None:
        summary = _empty_run(started, interrupted, stop_signal)
    counts = log.counts if log is not None else {}
    lat = np.asarray(log.latencies if log is not None else [], dtype=np.float64)
    figures = (float(np.median(lat)), float(np.percentile(lat, 95)), float(lat.max())) if lat.size else (
        math.nan, math.nan, math.nan)
    return FollowSummary(run=summary, frames_series_only=counts.get("series", 0),
                         frames_unfiltered=counts.get("unfiltered", 0), frames_replayed=counts.get("replayed", 0),
                         frames_timed_out=len(follower.skipped), latency_ms=figures, stop=why)


@dataclass
class _Job:
    """What the logging thread logs next: a frame, shown whole or in the series only."""

    kind: str  # "whole" or "series"
    index: int = -1  # the frame's index in the session
    completed: float = math.nan  # when its last file was completed (time.monotonic), s
    replay: bool = False  # --from-start: there at the start (shown whole, not in the latency)
    result: Future | None = None  # its FrameResult (None: SGBM depth not matched for a series-only frame)
    images: Future | None = None  # its ShownImages (whole frames)


def _hand_on(waiting: deque, log: _FrameLog, readers: ThreadPoolExecutor, session, options: DebuggerOptions,
             everything: bool = False) -> None:
    """Start reading the frames waiting, in order, while no whole frame is queued for logging (or
    ``everything``): a frame there at the start, or the newest, is shown whole; an older one only in
    the series (the follower is behind), its patch read unless the depth comes from SGBM."""
    while waiting and (everything or not log.whole_queued()):
        index, completed, replay = waiting.popleft()
        if replay or not waiting:
            log.put(_Job("whole", index, completed, replay, readers.submit(_result, session, index, options),
                         readers.submit(log.logger.reader.load, index)))
        else:
            log.put(_Job("series", index, completed, result=None if session.depth_source == "sgbm" else
                         readers.submit(_result, session, index, options)))


class _FrameLog(threading.Thread):
    """The logging thread: logs the jobs in order (a frame's data through its :class:`FrameLogger`, and
    its lag), flushes every ``flush_every`` frames and keeps the counts."""

    def __init__(self, logger: FrameLogger, rec, progress: Callable[[int], None] | None) -> None:
        super().__init__(name="contact-viz-follow-log", daemon=True)
        self.logger, self.rec, self.progress = logger, rec, progress
        self.jobs: deque[_Job] = deque()
        self.changed = threading.Condition()
        self.closing = self.dropping = False
        self.error: BaseException | None = None
        self.latencies: deque[float] = deque(maxlen=_LATENCY_WINDOW)
        self.counts = {"series": 0, "unfiltered": 0, "replayed": 0}
        self.start()

    def put(self, job: _Job) -> None:
        with self.changed:
            self.jobs.append(job)
            self.changed.notify()

    def whole_queued(self) -> bool:
        """Whether a frame to show whole waits in the queue (not the one being logged)."""
        with self.changed:
            return any(job.kind == "whole" for job in self.jobs)

    def raise_error(self) -> None:
        """Raise, in the caller's thread, what stopped the logging thread (a sink error, a bug)."""
        if self.error is not None:
            raise self.error

    def close(self, wait: bool) -> None:
        """Stop after the jobs queued (``wait``) or after the job being logged, and join."""
        with self.changed:
            self.closing = True
            self.dropping = self.dropping or not wait
            self.changed.notify()
        self.join()

    def run(self) -> None:
        while True:
            with self.changed:
                while not self.jobs and not self.closing:
                    self.changed.wait()
                if self.dropping or not self.jobs:
                    return
                job = self.jobs.popleft()
            try:
                self._log(job)
            except BaseException as exc:  # noqa: BLE001 - handed to the polling thread (raise_error)
                self.error = exc
                return

    def _log(self, job: _Job) -> None:
        logger, session = self.logger, self.logger.session
        if job.kind == "series":
            self.counts["series"] += 1
            result = job.result.result() if job.result is not None else None
            if result is None:
                self.counts["unfiltered"] += 1
                result = FrameResult(BadFrame(job.index, session.stems[job.index],
                                              float(session.timestamps_s[job.index]), None), None)
            logger.log_series_only(result)
        else:
            logger.log(job.result.result(), job.images.result())
            if job.replay:
                self.counts["replayed"] += 1
            else:
                lag_ms = (time.monotonic() - job.completed) * 1000
                self.latencies.append(lag_ms)
                self.rec.log(ENTITY_SERIES_LAG, rr.Scalars(lag_ms))
            if logger.done % logger.options.flush_every == 0:
                flush(self.rec)
            if self.progress is not None:
                self.progress(logger.done)


def _wait_for_session(root: Path, params: FollowParams, stop: Callable[[], bool] | None,
                      started: float) -> str:
    """Wait for the recorder to make the session (its left/ folder): "there" (it was there at the start) or
    "made" (made since), else the stop reason of a run that took no frame: "idle" (--idle-timeout passed)
    or "" (``stop()``)."""
    made = "there"
    while not (root / "left").is_dir():
        made = "made"
        if params.idle_timeout_s is not None and time.monotonic() - started > params.idle_timeout_s:
            return "idle"
        if stop is not None and stop():
            return ""
        time.sleep(max(params.poll_s, 0.05))
    return made


def _empty_run(started: float, interrupted: bool, stop_signal: int) -> RunSummary:
    """The summary of a run that logged no frame."""
    return RunSummary(frames=0, bad_frames=0, diagnostic_counts={}, interrupted=interrupted,
                      stop_signal=stop_signal, elapsed_s=time.monotonic() - started,
                      wait_s=0.0, image_wait_s=0.0, prepare_s=0.0, log_s=0.0)


def _no_frame(started: float, why: str, stop_signal: int = 0) -> FollowSummary:
    """A follow that stopped (``why``) before the recorder made the session."""
    return FollowSummary(run=_empty_run(started, why == "interrupted", stop_signal), frames_series_only=0,
                         frames_unfiltered=0, frames_timed_out=0, frames_replayed=0,
                         latency_ms=(math.nan,) * 3, stop=why)


def _result(session, index: int, options: DebuggerOptions) -> FrameResult:
    """The frame's FrameResult, as `extract` computes it (contact_viz.pipeline.extract.frame_patches)."""
    frame = session.load_frame(index)
    if isinstance(frame, BadFrame):
        warnings.warn(f"frame {frame.stem} skipped: {frame.reason}", BadFrameWarning, stacklevel=2)
        return FrameResult(frame, None)
    return FrameResult(frame, *session_frame_patches(session, frame, options.patch_params))


def _log_force(rec, session, rows: list[dict[str, str]]) -> list[dict[str, str]]:
    """Log force rows at their frame (``frame`` column; among the last 256) or nearest frame time
    (``timestamp``); returns the rows whose frame is not there yet (the last 10 000). A numbered row of a
    frame older than the newest one but not among the last 256 (skipped, or long past) is dropped."""
    if not len(session):
        return rows[-10_000:]
    held = []
    times = session.timestamps_s
    recent = enumerate(session.stems[-256:], start=max(len(session) - 256, 0))
    index_of = {key: i for i, stem in recent for key in ((stem, str(int(stem))) if stem.isdigit() else (stem,))}
    newest = int(session.stems[-1]) if session.stems[-1].isdigit() else None
    for row in rows:
        try:
            force = [float(row[k]) for k in ("fx", "fy", "fz")]
        except (KeyError, ValueError):
            continue
        if "frame" in row:  # a stem, or its number ("7" for 000007), as open_session matches them
            frame = row["frame"]
            index = index_of.get(str(int(frame)) if frame.isdigit() else frame)
            if index is None and newest is not None and frame.isdigit() and int(frame) <= newest:
                continue  # its frame was skipped, or passed long ago
        else:
            t = float(row.get("timestamp", "nan"))
            index = int(np.searchsorted(times, t)) if t <= times[-1] else None
            if index is not None and index > 0 and abs(times[index - 1] - t) <= abs(times[min(index, len(times) - 1)] - t):
                index -= 1
        if index is None:  # its frame is not there yet
            held.append(row)
            continue
        rerun_log.set_frame_time(rec, index, float(times[index]))
        rerun_log.log_force_sample(rec, force)
    return held[-10_000:]
