"""The debugger on a session that is being recorded: every frame is logged as soon as its files are
complete (:class:`contact_viz.io.live.SessionFollower`), through the same per-frame path as a
finished session (:class:`contact_viz.viz.frame_log.FrameLogger`), with the causal posterior.

With ``from_start``, the frames there at the start are shown whole, one after another (a replay;
they are not counted in the latency). Falling behind: when several new frames are complete at once,
the newest is shown whole and the older ones only in the series (distance, signal, posterior): the causal filter sees every frame. With SGBM
depth (no depth/ in the session) a frame shown only in the series is not matched either: the filter
then steps over it without an observation, and the summary counts it. The lag (a frame's files
complete -> its data logged, ms) is a series of its own (``series/lag_ms``).
"""

from __future__ import annotations

import math
import time
import warnings
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import rerun as rr

from contact_viz.io.live import FollowParams, SessionFollower
from contact_viz.io.session import BadFrame
from contact_viz.pipeline.extract import BadFrameWarning, FrameResult, frame_patches
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
    """
    if options.hand_eye is not None:
        raise ValueError("--hand-eye: not available with --follow (kinematics.csv is read whole)")
    started = last_new = time.monotonic()
    try:
        waited = _wait_for_session(Path(root), params, stop, started)
    except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM, SIGHUP before the session appeared
        return _no_frame(started, "interrupted", getattr(exc, "signum", 2))
    if waited is not None:  # no session appeared: stopped as if idle (or by the caller) before any frame
        return _no_frame(started, waited)
    follower = SessionFollower(root, params, **(open_kwargs or {}))
    logger: FrameLogger | None = None
    latencies: deque[float] = deque(maxlen=_LATENCY_WINDOW)
    series_only = unfiltered = replayed = 0
    interrupted, stop_signal, why = False, 0, ""
    try:
        while True:
            arrived = follower.poll()
            now = time.monotonic()
            if not arrived:
                if params.idle_timeout_s is not None and now - last_new > params.idle_timeout_s:
                    why = "idle"
                    break
                if stop is not None and stop():
                    break
                _log_force(rec, follower, logger)
                time.sleep(params.poll_s)
                continue
            last_new = now
            session = follower.session
            if logger is None:
                logger = FrameLogger(session, rec, replace(options, start=0, end=None, stride=1), model)
            for index, _ in arrived[:-1]:
                if follower.from_backlog(session.stems[index]):  # --from-start: there at the start, shown whole
                    replayed += 1
                    logger.log(_result(session, index, options), logger.reader.load(index))
                    continue
                series_only += 1  # behind: shown in the series only
                result = _result(session, index, options) if session.depth_source != "sgbm" else None
                if result is None:
                    unfiltered += 1
                    result = FrameResult(BadFrame(index, session.stems[index], float(session.timestamps_s[index]),
                                                  None), None)
                logger.log_series_only(result)
            index, complete_at = arrived[-1]
            logger.log(_result(session, index, options), logger.reader.load(index))
            if follower.from_backlog(session.stems[index]):  # its files completed before the run: no latency
                replayed += 1
            else:
                lag_ms = (time.monotonic() - complete_at) * 1000
                latencies.append(lag_ms)
                rec.log(ENTITY_SERIES_LAG, rr.Scalars(lag_ms))
            _log_force(rec, follower, logger)
            if logger.done % options.flush_every == 0:
                flush(rec)
            follower.prune()
            if progress is not None:
                progress(logger.done)
    except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM, SIGHUP (contact_viz.console.Stopped)
        interrupted, stop_signal, why = True, getattr(exc, "signum", 2), "interrupted"
    finally:
        summary = None
        if logger is not None:
            summary = logger.finish(range(follower.session and len(follower.session) or 0), started=started,
                                    interrupted=interrupted, stop_signal=stop_signal)
        flush(rec)
    if summary is None:
        summary = _empty_run(started, interrupted, stop_signal)
    lat = np.asarray(latencies, dtype=np.float64)
    figures = (float(np.median(lat)), float(np.percentile(lat, 95)), float(lat.max())) if lat.size else (
        math.nan, math.nan, math.nan)
    return FollowSummary(run=summary, frames_series_only=series_only, frames_unfiltered=unfiltered,
                         frames_replayed=replayed,
                         frames_timed_out=len(follower.skipped), latency_ms=figures, stop=why)


def _wait_for_session(root: Path, params: FollowParams, stop: Callable[[], bool] | None,
                      started: float) -> str | None:
    """Wait for the recorder to make the session (its left/ folder): None once it has, else the stop
    reason of a run that took no frame: "idle" (--idle-timeout passed) or "" (``stop()``)."""
    while not (root / "left").is_dir():
        if params.idle_timeout_s is not None and time.monotonic() - started > params.idle_timeout_s:
            return "idle"
        if stop is not None and stop():
            return ""
        time.sleep(max(params.poll_s, 0.05))
    return None


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
    return FrameResult(frame, *frame_patches(frame, options.patch_params, session.object_ids))


def _log_force(rec, follower: SessionFollower, logger: FrameLogger | None) -> None:
    """The force rows read so far, at their frame (``frame`` column) or nearest frame time (``timestamp``)."""
    session = follower.session
    if logger is None or session is None or not len(session):
        return
    rows = follower.take_force_rows()
    held = []
    times = session.timestamps_s
    recent = enumerate(session.stems[-256:], start=max(len(session) - 256, 0))
    index_of = {key: i for i, stem in recent for key in ((stem, str(int(stem))) if stem.isdigit() else (stem,))}
    for row in rows:
        try:
            force = [float(row[k]) for k in ("fx", "fy", "fz")]
        except (KeyError, ValueError):
            continue
        if "frame" in row:  # a stem, or its number ("7" for 000007), as open_session matches them
            frame = row["frame"]
            index = index_of.get(str(int(frame)) if frame.isdigit() else frame)
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
    follower.force_rows[:0] = held[-10_000:]  # rows of frames that never came are not kept forever
