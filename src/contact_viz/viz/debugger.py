"""The visual debugger's run loop: stream a session through the pipeline into a Rerun recording.

:func:`run_debugger` reads the frames one at a time through
:func:`contact_viz.pipeline.extract.iter_frame_results` (the same code path as ``contact-viz extract``, so
every distance, signal and bad frame is the one the features file has), prepares what each
frame shows (point cloud, patch geometry, decimated depth, causal HMM posterior, diagnostics) and
hands it to :mod:`contact_viz.viz.rerun_log`. Nothing is collected across frames: memory stays flat
however long the session is. :func:`contact_viz.viz.rerun_log.open_recording` makes the ``rr.RecordingStream`` with the
chosen sinks (an .rrd file, a viewer to spawn or connect to, or a served web viewer).

Images. The left and right images are read by a second background thread (not by the session
reader), so an unreadable image is a display problem only (a warning at that frame) and never
changes which frames have a patch. A JPEG file is logged as its own bytes (``rr.EncodedImage``,
no re-encoding); its colours for the point cloud come from a reduced-size decode. Other image
files are decoded and JPEG-encoded at ``jpeg_quality``; ``raw_images`` logs decoded RGB instead.

Library code: no typer, no printing.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from contact_viz.viz import rerun_log
from contact_viz.viz.diagnostics import DiagnosticParams, DiagnosticsTracker
from contact_viz.errors import SessionError
from contact_viz.pipeline.extract import iter_frame_results, run_config
from contact_viz.model.hmm import StreamingFilter
from contact_viz.params import PatchParams, check_fields, checked, to_dict
from contact_viz.geometry.pointcloud import CloudParams, decimated_intrinsics, depth_cloud, depth_preview, patch_geometry
from contact_viz.io.prefetch import prefetched
from contact_viz.io.session import Session, read_rgb

__all__ = [
    "DebuggerOptions",
    "RunSummary",
    "run_debugger",
    "select_frames",
]

JPEG_SUFFIXES = (".jpg", ".jpeg")
JPEG_SOI = b"\xff\xd8\xff"  # every JPEG file starts with these bytes
# cv2 flags decoding a JPEG at 1/n size (libjpeg DCT scaling: much faster than a full decode)
_REDUCED_COLOR = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
                  8: cv2.IMREAD_REDUCED_COLOR_8}


@dataclass(frozen=True)
class DebuggerOptions:
    """What ``contact-viz view`` shows and how densely."""

    start: int = checked(0, ge=0)  # first frame index shown (0-based, inclusive)
    end: int | None = checked(None, ge=0)  # stop before this frame index (exclusive); None = the last frame
    stride: int = checked(1, ge=1)  # show every stride-th frame from start, frames
    jpeg_quality: int = checked(85, ge=1, le=100)  # JPEG quality for images that are not JPEG files already, 1-100
    raw_images: bool = False  # log decoded RGB instead of JPEG (about 6 MB per 1080p image)
    with_right: bool = True  # log the right image (when the session has right/)
    depth_step: int = checked(3, ge=1)  # log every depth_step-th depth pixel along rows and columns, px
    depth_units_per_m: float = checked(10000.0, gt=0)  # uint16 depth units per metre (10000: 0.1 mm steps up to 6.5 m)
    points: bool = True  # log the RGB point cloud
    cloud: CloudParams = field(default_factory=CloudParams)  # point cloud density
    # decode left JPEGs at 1/n size for the point colours (1, 2, 4 or 8)
    color_reduction: int = checked(2, choices=_REDUCED_COLOR)
    patch_params: PatchParams = field(default_factory=PatchParams)  # the patch (must match the model's)
    diagnostics: DiagnosticParams = field(default_factory=DiagnosticParams)  # thresholds of the checks
    # flush the recording to its sinks every this many frames (bounds memory and loss), frames
    flush_every: int = checked(15, ge=1)
    prefetch: int = checked(4, ge=1)  # images read ahead of the frame being logged, frames

    def __post_init__(self) -> None:
        check_fields(self)


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
    prepare_s: float  # point cloud, patch geometry, depth preview, posterior, diagnostics, s
    log_s: float  # Rerun calls and flushes, s

    @property
    def frames_per_s(self) -> float:
        return self.frames / self.elapsed_s if self.elapsed_s > 0 else math.nan

    def lines(self) -> list[str]:
        """A short human-readable report."""
        out = [f"{self.frames} frames in {self.elapsed_s:.1f} s ({self.frames_per_s:.1f} frames/s)"
               + (", interrupted" if self.interrupted else "")]
        out.append(f"time: next frame {self.wait_s:.1f} s, images {self.image_wait_s:.1f} s, "
                   f"prepare {self.prepare_s:.1f} s, log {self.log_s:.1f} s")
        fired = {code: n for code, n in self.diagnostic_counts.items() if n}
        if fired:
            out.append("diagnostics: " + ", ".join(f"{code} on {n} frame{'s' * (n != 1)}" for code, n in fired.items()))
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
# Images (read in their own thread)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Images:
    left_jpeg: bytes | None
    left_rgb: np.ndarray | None  # raw mode only
    colors_rgb: np.ndarray | None  # left image (full or reduced size) for the point colours
    right_jpeg: bytes | None
    right_rgb: np.ndarray | None  # raw mode only
    has_right: bool
    notes: tuple[str, ...]


class _ImageReader:
    """Loads what the viewer shows of a frame's left and right images; problems become notes."""

    def __init__(self, session: Session, options: DebuggerOptions, with_right: bool) -> None:
        self.session = session
        self.options = options
        self.with_right = with_right

    def _read(self, side: str, path: Path, want_colors: bool):
        """(jpeg bytes, raw rgb, colour image) of one image; raises SessionError on a problem."""
        height, width = self.session.image_size
        opts = self.options
        rectification = self.session.rectification
        if not opts.raw_images and rectification is None and path.suffix.lower() in JPEG_SUFFIXES:
            try:
                data = path.read_bytes()
            except OSError as exc:
                raise SessionError(path, f"expected a readable JPEG {side} image ({exc})") from exc
            if not data.startswith(JPEG_SOI):
                raise SessionError(path, f"expected a JPEG {side} image, the file does not start like one")
            colors = None
            if want_colors:
                n = opts.color_reduction
                bgr = cv2.imdecode(np.frombuffer(data, np.uint8), _REDUCED_COLOR[n])
                if bgr is None:
                    raise SessionError(path, f"expected a JPEG {side} image, could not decode it")
                if bgr.shape[:2] != (-(-height // n), -(-width // n)):
                    raise SessionError(path, f"expected a {side} image of {height}x{width} px (height x width), "
                                             f"found about {bgr.shape[0] * n}x{bgr.shape[1] * n}")
                colors = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            return data, None, colors
        rgb = read_rgb(path)
        if rectification is not None:  # raw recordings: show the rectified view the depth belongs to
            try:
                rgb = rectification.apply(side, rgb)
            except ValueError as exc:
                raise SessionError(path, str(exc)) from exc
        if rgb.shape[:2] != (height, width):
            raise SessionError(path, f"expected a {side} image of {height}x{width} px (height x width), "
                                     f"found {rgb.shape[0]}x{rgb.shape[1]}")
        if opts.raw_images:
            return None, rgb, rgb
        ok, encoded = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                                   [cv2.IMWRITE_JPEG_QUALITY, opts.jpeg_quality])
        if not ok:
            raise SessionError(path, f"could not JPEG-encode the {side} image")
        return encoded.tobytes(), None, rgb

    def load(self, index: int) -> _Images:
        stem = self.session.stems[index]
        notes = []
        left_jpeg = left_rgb = colors = right_jpeg = right_rgb = None
        try:
            left_path = self.session.image_path("left", index)
            if left_path is None:
                raise SessionError(self.session.root / "left" / f"{stem}.jpg", "missing: expected the left image")
            left_jpeg, left_rgb, colors = self._read("left", left_path, self.options.points)
        except SessionError as exc:
            notes.append(f"frame {index}: left image not shown: {exc}")
        right_path = self.session.image_path("right", index) if self.with_right else None
        if right_path is not None:
            try:
                right_jpeg, right_rgb, _ = self._read("right", right_path, False)
            except SessionError as exc:
                notes.append(f"frame {index}: right image not shown: {exc}")
        return _Images(left_jpeg, left_rgb, colors, right_jpeg, right_rgb, right_path is not None, tuple(notes))


# --------------------------------------------------------------------------------------------
# The run loop
# --------------------------------------------------------------------------------------------


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
                         with_right=with_right, with_model=model is not None)
    config = run_config(session, options=options, model=None if model is None else {
        "threshold": model.threshold, "training_sessions": list(model.training_sessions),
        "label_params": to_dict(model.label_params), "version": model.version})
    config["session"]["depth"] = getattr(session, "depth_note", None)
    rerun_log.log_config(rec, config)
    rerun_log.send_known_series(rec, session, indices, threshold=None if model is None else model.threshold)
    if model is None:
        rerun_log.log_model_hint(rec, indices[0], float(session.timestamps_s[indices[0]]))
    tracker = DiagnosticsTracker(options.diagnostics)
    stream = None if model is None else StreamingFilter(model.ensemble)
    reader = _ImageReader(session, options, with_right)

    results = iter_frame_results(session, options.patch_params, layers=("mask", "depth"), indices=indices)
    images = prefetched(reader.load, indices, options.prefetch, thread_name="contact-viz-images")
    done = bad = 0
    wait_s = image_wait_s = prepare_s = log_s = 0.0
    interrupted = False
    try:
        while True:
            t0 = time.perf_counter()
            result = next(results, None)
            if result is None:
                break
            t1 = time.perf_counter()
            shown = next(images)
            t2 = time.perf_counter()
            frame, patch = result.frame, result.patch
            diagnostics = tracker.update(result)
            posterior = predicted = None
            if stream is not None:
                posterior = stream.update(math.nan if patch is None else patch.signal)
                predicted = posterior >= model.threshold
            if patch is None:
                bad += 1
                t3 = time.perf_counter()
                rerun_log.log_bad_frame(rec, frame, posterior=posterior, predicted=predicted, diagnostics=diagnostics)
            else:
                window = patch.window_xyxy
                view = rerun_log.FrameView(
                    left_jpeg=shown.left_jpeg,
                    left_rgb=shown.left_rgb,
                    right_jpeg=shown.right_jpeg,
                    right_rgb=shown.right_rgb,
                    has_right=shown.has_right,
                    depth_u16=depth_preview(frame.depth_m, step, options.depth_units_per_m),
                    depth_units_per_m=options.depth_units_per_m,
                    depth_layers=np.ascontiguousarray(patch.layer_ids[::step, ::step]),
                    depth_window_xyxy=None if window is None else tuple(v / step for v in window),
                    cloud=depth_cloud(frame.depth_m, K, shown.colors_rgb, center_xy=patch.center_xy,
                                      params=options.cloud) if options.points else None,
                    geometry=patch_geometry(frame.depth_m, K, patch, options.patch_params),
                    posterior=posterior,
                    predicted=predicted,
                    diagnostics=diagnostics,
                    notes=shown.notes,
                )
                t3 = time.perf_counter()
                rerun_log.log_frame(rec, result, view)
            done += 1
            if done % options.flush_every == 0:
                rec.flush()
            t4 = time.perf_counter()
            wait_s += t1 - t0
            image_wait_s += t2 - t1
            prepare_s += t3 - t2
            log_s += t4 - t3
            if progress is not None:
                progress(done, len(indices))
    except KeyboardInterrupt:
        interrupted = True
    finally:
        results.close()
        images.close()
        t5 = time.perf_counter()
        rec.flush()
        log_s += time.perf_counter() - t5
    return RunSummary(
        frames=done,
        bad_frames=bad,
        diagnostic_counts=dict(tracker.counts),
        interrupted=interrupted,
        elapsed_s=time.perf_counter() - started,
        wait_s=wait_s,
        image_wait_s=image_wait_s,
        prepare_s=prepare_s,
        log_s=log_s,
    )
