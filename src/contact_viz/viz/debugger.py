"""The visual debugger's run loop: stream a session through the pipeline into a Rerun recording.

:func:`run_debugger` reads the frames one at a time through
:func:`contact_viz.pipeline.extract.iter_frame_results` (the same code path as ``contact-viz extract``, so
every distance, signal and bad frame is the one the features file has) and logs each with a
:class:`contact_viz.viz.frame_log.FrameLogger` (what a frame shows: point cloud, patch geometry,
decimated depth, causal HMM posterior, diagnostics). Nothing is collected across frames: memory stays
flat however long the session is. The options and the summary are in :mod:`contact_viz.viz.options`.

Several instruments (object ids of the masks): every instrument in a frame
(``FrameResult.tool_patches``) gets its own layers, box, patch points, gap arrow and series
(:class:`contact_viz.viz.rerun_log.InstrumentLayers`; the entity paths are in
:mod:`contact_viz.viz.entities`), and with a model its own causal posterior; the scene's posterior is
the max over the instruments in the frame. Each frame names the instrument in contact (the largest
posterior at or above the threshold; without a model the nearest instrument, the one
``FrameResult.patch`` is), and the summary the nearest instrument of the run.

:func:`contact_viz.viz.rerun_log.open_recording` makes the ``rr.RecordingStream`` with the
chosen sinks (an .rrd file, a viewer to spawn or connect to, or a served web viewer).

Images. The left and right images are read by background threads of their own (not by the
session reader), so an unreadable image is a display problem only (a warning at that frame) and
never changes which frames have a patch. ``images``: "video" (default) decodes them and
video-encodes each stream on the fly (:mod:`contact_viz.viz.video`, one encoder thread per
stream); "jpeg" logs a JPEG file as its own bytes (``rr.EncodedImage``, no re-encoding; the point
colours come from a reduced-size decode) and JPEG-encodes other files at ``jpeg_quality``; "raw"
logs decoded RGB. A stream whose video encoder cannot be opened (images smaller or larger than the
codec takes, a codec missing from the FFmpeg build) is logged as in "jpeg" instead, with one warning.

Library code: no typer, no printing.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from contact_viz.io.prefetch import prefetched
from contact_viz.io.session import Session
from contact_viz.pipeline.extract import iter_frame_results
from contact_viz.viz.frame_log import (  # noqa: F401 (re-exported)
    FrameLogger, InstrumentPosteriors, contact_instrument, contact_text, nearest_instrument)
from contact_viz.viz.options import IMAGE_MODES, DebuggerOptions, RunSummary, select_frames  # noqa: F401
from contact_viz.viz.rooted import rooted
from contact_viz.viz.sinks import flush

__all__ = [
    "DebuggerOptions",
    "InstrumentPosteriors",
    "RunSummary",
    "log_session",
    "run_debugger",
    "select_frames",
]


def run_debugger(
    session: Session,
    rec,
    options: DebuggerOptions = DebuggerOptions(),
    model=None,
    progress: Callable[[int, int], None] | None = None,
    *,
    keep_partial: bool = True,
) -> RunSummary:
    """Log the frames of ``session`` selected by ``options`` to ``rec`` (an ``rr.RecordingStream``),
    streaming, and summarise.

    ``model`` (a :class:`contact_viz.model.model_file.ContactModel`, optional) adds the causal HMM
    posterior, computed frame by frame over the shown frames (equal to
    ``model.predict_proba`` on their signals), its threshold and the predicted contact; its patch
    parameters must equal ``options.patch_params`` (ValueError otherwise). Without a model the
    recording says how to get one. ``progress(done, total)`` is called after each frame.
    A KeyboardInterrupt (Ctrl-C, SIGTERM, SIGHUP) stops the run cleanly: what was logged is flushed
    and the summary says so; without ``keep_partial`` (a step of a larger command, which must stop too) it
    is raised again after the flush.
    """
    indices = select_frames(len(session), options.start, options.end, options.stride)
    started = time.perf_counter()
    logger = FrameLogger(session, rec, options, model, indices=indices)
    results = iter_frame_results(session, options.patch_params, layers=("mask", "depth"), indices=indices)
    images = prefetched(logger.reader.load, indices, options.prefetch, workers=options.image_workers,
                        thread_name="contact-viz-images")
    wait_s = image_wait_s = 0.0
    interrupted, stop_signal = False, 0
    try:
        while True:
            t0 = time.perf_counter()
            result = next(results, None)
            if result is None:
                break
            t1 = time.perf_counter()
            shown = next(images)
            wait_s += t1 - t0
            image_wait_s += time.perf_counter() - t1
            logger.log(result, shown)
            if logger.done % options.flush_every == 0:
                t3 = time.perf_counter()
                flush(rec)
                logger.log_s += time.perf_counter() - t3
            if progress is not None:
                progress(logger.done, len(indices))
    except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM, SIGHUP (contact_viz.console.Stopped)
        interrupted, stop_signal = True, getattr(exc, "signum", 2)
        if not keep_partial:
            raise
    finally:
        results.close()
        images.close()
        summary = logger.finish(indices[:logger.done], started=started, interrupted=interrupted,
                                stop_signal=stop_signal, wait_s=wait_s, image_wait_s=image_wait_s)
        flush(rec)
    return summary


def log_session(
    rec,
    session: Session,
    *,
    model=None,
    options: DebuggerOptions = DebuggerOptions(),
    root: str | None = None,
    progress: Callable[[int, int], None] | None = None,
    keep_partial: bool = True,
) -> RunSummary:
    """:func:`run_debugger` into the caller's ``rec`` with every entity under ``root`` (None: the debugger's own
    paths, as `contact-viz SESSION` records them); the one logging path of the debugger, the CLI's included."""
    return run_debugger(session, rooted(rec, root), options, model=model, progress=progress,
                        keep_partial=keep_partial)
