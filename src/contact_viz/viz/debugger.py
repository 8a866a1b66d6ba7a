"""The visual debugger's run loop: stream a session through the pipeline into a Rerun recording.

:func:`run_debugger` reads the frames one at a time through
:func:`contact_viz.pipeline.extract.iter_frame_results` (the same code path as ``contact-viz extract``, so
every distance, signal and bad frame is the one the features file has), prepares what each
frame shows (point cloud, patch geometry, decimated depth, causal HMM posterior, diagnostics) and
hands it to :mod:`contact_viz.viz.rerun_log`. Nothing is collected across frames: memory stays flat
however long the session is.

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

import copy
import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from contact_viz.viz import rerun_log
from contact_viz.viz.images import ImageReader, VideoStreams, right_step_of
from contact_viz.viz.sinks import flush
from contact_viz.viz.diagnostics import DiagnosticParams, DiagnosticsTracker
from contact_viz.console import FULL_MASK, no_patch_message, no_patch_problem
from contact_viz.errors import NoPatchWarning, SessionWarning
from contact_viz.pipeline.extract import iter_frame_results, run_config
from contact_viz.model.hmm import StreamingFilter
from contact_viz.params import PatchParams, check_fields, checked, to_dict
from contact_viz.geometry.pointcloud import CloudParams, decimated_intrinsics, depth_cloud, depth_preview, patch_geometry
from contact_viz.io.prefetch import prefetched
from contact_viz.io.decoders import JPEG_REDUCTIONS
from contact_viz.io.session import Session
from contact_viz.viz.video import VideoParams
from contact_viz.geometry.kinematics import frame_samples, kinematic_tip
from contact_viz.geometry.tooltip import tool_tip_xy

__all__ = [
    "DebuggerOptions",
    "InstrumentPosteriors",
    "RunSummary",
    "run_debugger",
    "select_frames",
]

IMAGE_MODES = ("video", "jpeg", "raw")  # how the images are logged: video stream, JPEG, decoded RGB


@dataclass(frozen=True)
class DebuggerOptions:
    """What ``contact-viz view`` shows and how densely."""

    start: int = checked(0, ge=0)  # first frame index shown (0-based, inclusive)
    end: int | None = checked(None, ge=0)  # stop before this frame index (exclusive); None = the last frame
    stride: int = checked(1, ge=1)  # show every stride-th frame from start, frames
    # "video" (AV1/H.264 stream), "jpeg" (exact JPEG files) or "raw" (RGB, 6 MB per 1080p image)
    images: str = checked("video", choices=IMAGE_MODES)
    video: VideoParams = field(default_factory=VideoParams)  # codec, quality and keyframes of images="video"
    # images="jpeg": JPEG quality for images that are not JPEG files already, 1-100
    jpeg_quality: int = checked(85, ge=1, le=100)
    with_right: bool = True  # log the right image (when the session has right/)
    # images="video": the right image at 1/right_step of its size, 1 or 2. 2: the right pane of the default layout
    # shows it at a third of its width anyway, and it halves the image work of a frame pair (JPEG files decode at
    # half size in a quarter of the time; a quarter of the pixels to encode): 21 ms less CPU per 1080p frame
    right_step: int = checked(2, choices=(1, 2))
    # log every depth_step-th depth pixel along rows and columns, px. 6: 320x180 at 1080p, the size of the depth pane
    # of the default layout on a 1080p screen; 51 kB a frame (3: 137 kB, 4: 81 kB, at 0.5 mm)
    depth_step: int = checked(6, ge=1)
    # uint16 depth units per metre. 2000: 0.5 mm steps up to 33 m; coarser steps compress better in the .rrd
    # (per 1080p frame at depth_step 6: 1 mm 39 kB, 0.5 mm 51 kB, 0.25 mm 63 kB, 0.1 mm 84 kB)
    depth_units_per_m: float = checked(2000.0, gt=0)
    points: bool = True  # log the RGB point cloud
    cloud: CloudParams = field(default_factory=CloudParams)  # point cloud density
    # decode left JPEGs at 1/n size for the point colours (1, 2, 4 or 8)
    color_reduction: int = checked(2, choices=JPEG_REDUCTIONS)
    patch_params: PatchParams = field(default_factory=PatchParams)  # the patch (must match the model's)
    diagnostics: DiagnosticParams = field(default_factory=DiagnosticParams)  # thresholds of the checks
    # flush the recording to its sinks every this many frames (bounds memory and loss), frames
    flush_every: int = checked(15, ge=1)
    prefetch: int = checked(4, ge=1)  # images read ahead of the frame being logged, frames
    image_workers: int = checked(2, ge=1)  # threads reading (decoding, converting) the images, one frame each
    hand_eye: tuple[tuple[float, ...], ...] | None = None  # 4x4 camera_T_base (m; io/kinematics.py); None = no tip
    kinematics_max_gap_s: float = checked(0.05, ge=0)  # a pose farther than this from a frame is not drawn there, s

    def __post_init__(self) -> None:
        check_fields(self)
        if self.hand_eye is not None and np.asarray(self.hand_eye, dtype=np.float64).shape != (4, 4):
            raise ValueError(f"DebuggerOptions.hand_eye must be a 4x4 transform, got {self.hand_eye!r}")


@dataclass(frozen=True)
class RunSummary:
    """What a run did, for the command line to print."""

    frames: int  # frames processed (logged), bad ones included
    bad_frames: int  # frames whose mask or depth could not be read
    diagnostic_counts: dict[str, int]  # diagnostic code -> frames it fired on
    interrupted: bool  # stopped early by KeyboardInterrupt (everything up to there is logged)
    elapsed_s: float  # wall time of the run, s
    wait_s: float  # waiting for the next frame: mask + depth decoding (background thread) and the patch, s
    image_wait_s: float  # waiting for the images (read and decoded in their own thread), s
    prepare_s: float  # point cloud, patch geometry, depth preview, posterior, the checks, s
    log_s: float  # Rerun calls and flushes, s
    diagnostic_ranges: dict[str, list[tuple[int, int]]] = field(default_factory=dict)  # code -> (first, last) frame runs
    instrument_frames: dict[int, int] = field(default_factory=dict)  # object id -> readable frames it is in
    nearest_frames: dict[int, int] = field(default_factory=dict)  # object id -> frames it was the nearest instrument
    contact_frames: dict[int, int] = field(default_factory=dict)  # with a model: object id -> frames it was in contact
    closest: tuple[int, float, int] | None = None  # (object id, distance mm, frame): the run's smallest |distance|
    with_model: bool = False  # the run had a model (contact_frames is meaningful)
    stop_signal: int = 0  # the signal that stopped the run (SIGINT 2, SIGTERM 15, SIGHUP 1), 0 if none

    @property
    def nearest_instrument(self) -> int | None:
        """The instrument nearest the tissue on the most frames (ties: the lowest object id); None if no frame
        had an instrument with a distance."""
        if not self.nearest_frames:
            return None
        return min(self.nearest_frames, key=lambda k: (-self.nearest_frames[k], k))

    def instrument_lines(self) -> list[str]:
        """The instruments' part of the report: which were seen, the nearest one, which were in contact."""
        out = []
        if len(self.instrument_frames) > 1:
            out.append("instruments: " + ", ".join(f"{k} on {n} frame{'s' * (n != 1)}"
                                                   for k, n in sorted(self.instrument_frames.items())))
        nearest = self.nearest_instrument
        if nearest is not None:
            others = [f"{k} on {n}" for k, n in sorted(self.nearest_frames.items(), key=lambda kv: (-kv[1], kv[0]))
                      if k != nearest]
            n = self.nearest_frames[nearest]
            text = f"nearest instrument: {nearest} (nearest on {n} frame{'s' * (n != 1)}"
            text += "".join(f", {o}" for o in others) + ")"
            if self.closest is not None:
                tool, distance_mm, frame = self.closest
                who = f"instrument {tool}, " if len(self.instrument_frames) > 1 else ""
                text += f"; closest: {who}{distance_mm:.1f} mm at frame {frame}"
            out.append(text)
        elif self.instrument_frames:
            out.append("nearest instrument: none (no frame had a distance)")
        if self.with_model and self.instrument_frames:
            if self.contact_frames:
                out.append("in contact: " + ", ".join(
                    f"instrument {k} on {n} frame{'s' * (n != 1)}"
                    for k, n in sorted(self.contact_frames.items(), key=lambda kv: (-kv[1], kv[0]))))
            else:
                out.append("in contact: no instrument on any frame (no posterior at or above the threshold)")
        return out

    @property
    def stop_name(self) -> str:
        """How the run was stopped early: "interrupted (Ctrl-C)", "stopped by SIGTERM" ..."""
        import signal

        if self.stop_signal in (0, signal.SIGINT):
            return "interrupted (Ctrl-C)"
        return f"stopped by {signal.Signals(self.stop_signal).name}"

    @property
    def frames_per_s(self) -> float:
        return self.frames / self.elapsed_s if self.elapsed_s > 0 else math.nan

    def lines(self) -> list[str]:
        """A short human-readable report."""
        out = [f"{self.frames} frames in {self.elapsed_s:.1f} s ({self.frames_per_s:.1f} frames/s)"
               + (f", {self.stop_name}: the recording is partial" if self.interrupted else "")]
        out.append(f"time: next frame {self.wait_s:.1f} s, images {self.image_wait_s:.1f} s, "
                   f"prepare {self.prepare_s:.1f} s, log {self.log_s:.1f} s")
        out += self.instrument_lines()
        fired = {code: n for code, n in self.diagnostic_counts.items() if n}
        if fired:
            out.append("diagnostics:")
            for code, n in fired.items():
                runs = self.diagnostic_ranges.get(code, [])
                text = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs[:8])
                more = f", ... ({len(runs)} ranges)" if len(runs) > 8 else ""
                out.append(f"  {code} on {n} frame{'s' * (n != 1)}" + (f": {text}{more}" if text else ""))
        else:
            out.append("diagnostics: none fired")
        return out


def select_frames(n_frames: int, start: int = 0, end: int | None = None, stride: int = 1) -> range:
    """Frames ``start, start + stride, ...`` below ``end`` (default ``n_frames``); ValueError if none / out of range."""
    stop = n_frames if end is None else end
    if start >= n_frames:
        raise ValueError(f"start: frame {start} is past the last frame ({n_frames - 1}) of this session")
    if stop > n_frames:
        raise ValueError(f"end: {stop} is past the end of this session ({n_frames} frames; end is exclusive)")
    if stop <= start:
        raise ValueError(f"end ({stop}) must be greater than start ({start})")
    return range(start, stop, stride)


# --------------------------------------------------------------------------------------------
# Recording sinks
# --------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------
# Several instruments
# --------------------------------------------------------------------------------------------


class InstrumentPosteriors:
    """Causal HMM posteriors of every instrument and of the scene, frame by frame.

    (contact_viz.model has no streaming per-instrument filter yet, so the debugger runs one
    :class:`~contact_viz.model.hmm.StreamingFilter` per instrument id and combines them with the max over the
    instruments present, the rule of the scene posterior.) Each instrument's posterior is ``forward_filter`` on
    its own signal over every frame shown, NaN where it is absent or the frame could not be read (a
    filter started on the frame an instrument first appears copies a filter that has run on NaN since the first
    frame: the same recursion bit for bit). The scene's posterior is the max over the instruments in the frame;
    in a frame without any, the max over every instrument seen so far (their one-step predictions), or the
    no-instrument filter's before the first. With one instrument it is that instrument's posterior: exactly
    the single StreamingFilter on ``FrameResult.patch.signal`` that the debugger ran before.
    """

    def __init__(self, ensemble) -> None:
        self._unseen = StreamingFilter(ensemble)  # fed NaN on every frame: an instrument not seen yet
        self.filters: dict[int, StreamingFilter] = {}

    def update(self, signals: dict[int, float]) -> tuple[float, dict[int, float]]:
        """Add one frame: ``signals`` {object id: signal} of the instruments in it ({} for none, or a bad
        frame). Returns (scene posterior, {object id: posterior} of every instrument seen so far)."""
        for tool in sorted(signals.keys() - self.filters.keys()):
            self.filters[tool] = copy.deepcopy(self._unseen)
        each = {tool: f.update(signals.get(tool, math.nan)) for tool, f in self.filters.items()}
        unseen = self._unseen.update(math.nan)
        present = [each[tool] for tool in signals]
        scene = max(present) if present else max(each.values()) if each else unseen
        return scene, each


def nearest_instrument(tool_patches: dict) -> int | None:
    """The instrument nearest the tissue: the smallest |distance| (ties: the lowest object id), as
    :func:`contact_viz.pipeline.extract.frame_patches` picks ``FrameResult.patch``; None if none has a distance."""
    finite = {k: abs(p.distance_m) for k, p in tool_patches.items() if math.isfinite(p.distance_m)}
    return min(finite, key=lambda k: (finite[k], k)) if finite else None


def contact_instrument(posteriors: dict[int, float], threshold: float) -> tuple[int | None, int | None]:
    """(the instrument in contact, the instrument with the largest posterior) among ``posteriors`` {object id:
    posterior} of the instruments in a frame: in contact = the largest posterior, if at or above ``threshold``
    (ties: the lowest object id)."""
    if not posteriors:
        return None, None
    top = min(posteriors, key=lambda k: (-posteriors[k], k))
    return (top if posteriors[top] >= threshold else None), top


def contact_text(tool_patches: dict, posteriors: dict[int, float] | None, threshold: float | None,
                 contact: int | None, top: int | None) -> str:
    """The frame's ENTITY_CONTACT text: the instrument in contact (with a model) or nearest (without),
    then each instrument's distance (and posterior)."""
    if not tool_patches:
        return "no instrument in this frame"
    if posteriors is not None:
        if contact is not None:
            head = f"in contact: instrument {contact} (P {posteriors[contact]:.2f} >= threshold {threshold:.2f})"
        else:
            head = (f"no instrument in contact (largest P: instrument {top}, {posteriors[top]:.2f} < threshold "
                    f"{threshold:.2f})")
    elif contact is not None:
        head = f"nearest instrument: {contact} ({tool_patches[contact].distance_m * 1000:.1f} mm)"
    else:
        head = "nearest instrument: none (no instrument has a distance in this frame)"
    lines = [head]
    for tool, patch in sorted(tool_patches.items()):
        d = patch.distance_m
        text = f"instrument {tool}: " + (f"{d * 1000:.1f} mm" if math.isfinite(d) else "no distance")
        if posteriors is not None:
            text += f", P {posteriors[tool]:.2f}"
        lines.append(text)
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# The run loop
# --------------------------------------------------------------------------------------------


def _pose_samples(session: Session, options: DebuggerOptions) -> np.ndarray | None:
    """Index of the kinematics.csv row drawn at each frame (-1: none within the gap); None without a hand-eye."""
    if options.hand_eye is None:
        return None
    if session.kinematics is None:
        raise ValueError(f"--hand-eye: the session {session.root} has no kinematics.csv to place with it "
                         "(import a bag with a pose topic)")
    return frame_samples(session.kinematics.timestamps_s, session.timestamps_s, options.kinematics_max_gap_s)


def _kinematic_tip(session: Session, frame, pose_of: np.ndarray, options: DebuggerOptions, K: np.ndarray):
    """The frame's KinematicTip (checked against the mask tip when the mask was read), or None without a pose."""
    row = pose_of[frame.index]
    if row < 0:
        return None
    kin = session.kinematics
    tool_mask = getattr(frame, "tool_mask", None)
    mask_tip = tool_tip_xy(tool_mask) if tool_mask is not None else None
    return kinematic_tip(np.asarray(options.hand_eye), kin.position_m[row], kin.quaternion_xyzw[row], K,
                         mask_tip, getattr(frame, "depth_m", None))


def _instrument_view(tool: int, patch, depth_m: np.ndarray, K: np.ndarray, step: int, options: DebuggerOptions,
                     posterior: float | None = None) -> rerun_log.InstrumentView:
    """What the viewer shows of one instrument's patch: its layers on the depth grid, its box there, its 3D
    geometry."""
    window = patch.window_xyxy
    return rerun_log.InstrumentView(
        tool=tool,
        patch=patch,
        depth_layers=np.ascontiguousarray(patch.layer_ids[::step, ::step]),
        depth_window_xyxy=None if window is None else tuple(v / step for v in window),
        geometry=patch_geometry(depth_m, K, patch, options.patch_params),
        posterior=posterior,
    )


def run_debugger(
    session: Session,
    rec: rerun_log.RecordingStream,
    options: DebuggerOptions = DebuggerOptions(),
    model=None,
    progress: Callable[[int, int], None] | None = None,
) -> RunSummary:
    """Log the frames of ``session`` selected by ``options`` to ``rec``, streaming, and summarise.

    ``model`` (a :class:`contact_viz.model.model_file.ContactModel`, optional) adds the causal HMM
    posterior, computed frame by frame over the shown frames (equal to
    ``model.predict_proba`` on their signals), its threshold and the predicted contact; its patch
    parameters must equal ``options.patch_params`` (ValueError otherwise). Without a model the
    recording says how to get one. ``progress(done, total)`` is called after each frame.
    A KeyboardInterrupt stops the run cleanly: what was logged is flushed and the summary says so.
    """
    indices = select_frames(len(session), options.start, options.end, options.stride)
    if model is not None:
        from contact_viz.model.model_file import check_params

        check_params(model.patch_params, options.patch_params, "contact-viz view")
    started = time.perf_counter()
    K = np.asarray(session.calibration.K, dtype=np.float64)
    step = options.depth_step
    with_right = options.with_right and session.has_right
    rerun_log.log_static(rec, session, depth_step=step, depth_K=decimated_intrinsics(K, step),
                         with_right=with_right, with_model=model is not None,
                         right_step=right_step_of(session, options))
    config = run_config(session, options=options, model=None if model is None else {
        "threshold": model.threshold, "training_sessions": list(model.training_sessions),
        "label_params": to_dict(model.label_params), "version": model.version})
    config["session"]["depth"] = getattr(session, "depth_note", None)
    rerun_log.log_config(rec, config)
    rerun_log.send_known_series(rec, session, indices, threshold=None if model is None else model.threshold)
    if model is None:
        rerun_log.log_model_hint(rec, indices[0], float(session.timestamps_s[indices[0]]))
    tracker = DiagnosticsTracker(options.diagnostics, fx_px=float(K[0, 0]),
                                 baseline_m=float(session.calibration.baseline_m), image_width=session.image_size[1],
                                 depth_source=session.depth_source)
    pose_of = _pose_samples(session, options)  # (n,) pose row per frame (-1 none), or None without --hand-eye
    stream = None if model is None else InstrumentPosteriors(model.ensemble)
    selected = getattr(session, "object_ids", None)
    # the primary instrument (single-instrument entity paths): the lowest selected id, else 1 (a binary mask's)
    instruments = rerun_log.InstrumentLayers(min(selected) if selected else 1, with_model=model is not None,
                                             several=bool(selected) and len(selected) > 1)
    instrument_frames: dict[int, int] = {}
    nearest_frames: dict[int, int] = {}
    contact_frames: dict[int, int] = {}
    closest: tuple[int, float, int] | None = None
    # the encoders first: a stream they refuse is read as JPEG images
    videos = VideoStreams(session, rec, options, with_right) if options.images == "video" else None
    reader = ImageReader(session, options, with_right, videos)

    results = iter_frame_results(session, options.patch_params, layers=("mask", "depth"), indices=indices)
    images = prefetched(reader.load, indices, options.prefetch, workers=options.image_workers,
                        thread_name="contact-viz-images")
    depth_kind = rerun_log.DepthKindLayer()  # fine / coarse SGBM depth on the depth pane (frames with depth_fine)
    done = bad = 0
    wait_s = image_wait_s = prepare_s = log_s = 0.0
    interrupted = False
    stop_signal = 0
    try:
        while True:
            t0 = time.perf_counter()
            result = next(results, None)
            if result is None:
                break
            t1 = time.perf_counter()
            shown = next(images)
            for note in shown.notes:  # an image the viewer cannot show: on the console too, not only in the log
                warnings.warn(note, SessionWarning, stacklevel=2)
            t2 = time.perf_counter()
            frame, patch = result.frame, result.patch
            # (in this thread: one frame ahead in a thread of its own, the checks, cloud and depth preview were
            # slower, 20.4 against 22.5 frames/s, 1080p JPEG session, --images jpeg: the threads contend for the GIL)
            diag = tracker.update(result, shown.left_grey, shown.right_grey, evidence=True)
            diagnostics = diag.fired
            tools = dict(result.tool_patches or {}) if patch is not None else {}  # {object id: PatchResult}
            posterior = predicted = each = None
            nearest = contact = top = nearest_instrument(tools)  # without a model: the nearest one is named
            if stream is not None:
                posterior, each = stream.update({k: p.signal for k, p in tools.items()})
                predicted = posterior >= model.threshold
                contact, top = contact_instrument({k: each[k] for k in tools}, model.threshold)
            for tool, tool_patch in tools.items():
                instrument_frames[tool] = instrument_frames.get(tool, 0) + 1
                d = tool_patch.distance_m
                if math.isfinite(d) and (closest is None or abs(d) * 1000 < abs(closest[1])):
                    closest = (tool, d * 1000, frame.index)
            if nearest is not None:
                nearest_frames[nearest] = nearest_frames.get(nearest, 0) + 1
            if stream is not None and contact is not None:
                contact_frames[contact] = contact_frames.get(contact, 0) + 1
            if patch is None:
                bad += 1
                t3 = time.perf_counter()
                rerun_log.log_bad_frame(rec, frame, posterior=posterior, predicted=predicted, diagnostics=diagnostics,
                                        instruments=instruments, contact_text="this frame could not be read")
                depth_kind.log(rec, None)
            else:
                problem = no_patch_problem(patch.reason, patch.invalid_depth_fraction)
                if problem is not None:  # the frame was read, but its input gives nothing to measure
                    layer = "mask" if problem == FULL_MASK else "depth"
                    warnings.warn(no_patch_message(frame.stem, problem, session.layer_file(layer, frame.stem)),
                                  NoPatchWarning, stacklevel=2)
                kind_ids = rerun_log.depth_kind_ids(frame.depth_fine, step)
                # each instrument's layers; a frame without any shows its (empty) patch as the primary's
                views = [_instrument_view(tool, tool_patch, frame.depth_m, K, step, options,
                                          None if each is None else each[tool])
                         for tool, tool_patch in sorted(tools.items())] or [
                    _instrument_view(instruments.primary, patch, frame.depth_m, K, step, options)]
                view = rerun_log.FrameView(
                    left_jpeg=shown.left_jpeg,
                    left_rgb=shown.left_rgb,
                    right_jpeg=shown.right_jpeg,
                    right_rgb=shown.right_rgb,
                    left_in_video=shown.left_i420 is not None,
                    right_in_video=shown.right_i420 is not None,
                    has_right=shown.has_right,
                    depth_u16=depth_preview(frame.depth_m, step, options.depth_units_per_m),
                    depth_units_per_m=options.depth_units_per_m,
                    instruments=views,
                    cloud=depth_cloud(frame.depth_m, K, shown.colors_rgb, center_xy=patch.center_xy,
                                      params=options.cloud) if options.points else None,
                    posterior=posterior,
                    predicted=predicted,
                    diagnostics=diagnostics,
                    diagnostic_scores=diag.scores,
                    evidence=diag.evidence,
                    notes=shown.notes,
                    contact_tool=contact,
                    contact_text=contact_text(tools, None if each is None else {k: each[k] for k in tools},
                                              None if model is None else model.threshold, contact, top),
                )
                t3 = time.perf_counter()
                rerun_log.log_frame(rec, result, view, instruments)
                depth_kind.log(rec, kind_ids)
                if videos is not None:
                    videos.feed(frame.index, shown)
            if pose_of is not None:
                rerun_log.log_kinematic_tip(rec, _kinematic_tip(session, frame, pose_of, options, K))
            done += 1
            if done % options.flush_every == 0:
                flush(rec)
            t4 = time.perf_counter()
            wait_s += t1 - t0
            image_wait_s += t2 - t1
            prepare_s += t3 - t2
            log_s += t4 - t3
            if progress is not None:
                progress(done, len(indices))
    except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM, SIGHUP (contact_viz.console.Stopped)
        interrupted = True
        stop_signal = getattr(exc, "signum", 2)
    finally:
        results.close()
        images.close()
        t5 = time.perf_counter()
        if videos is not None:
            videos.close()
        session_checks = tracker.finish(session, indices[:done])
        if session_checks:
            last = indices[max(done - 1, 0)]
            rerun_log.log_session_diagnostics(rec, session_checks, float(session.timestamps_s[last]))
        flush(rec)
        log_s += time.perf_counter() - t5
    return RunSummary(
        frames=done,
        bad_frames=bad,
        diagnostic_counts=dict(tracker.counts),
        diagnostic_ranges=tracker.ranges(),
        interrupted=interrupted,
        stop_signal=stop_signal,
        elapsed_s=time.perf_counter() - started,
        wait_s=wait_s,
        image_wait_s=image_wait_s,
        prepare_s=prepare_s,
        log_s=log_s,
        instrument_frames=dict(sorted(instrument_frames.items())),
        nearest_frames=dict(sorted(nearest_frames.items())),
        contact_frames=dict(sorted(contact_frames.items())),
        closest=closest,
        with_model=model is not None,
    )
