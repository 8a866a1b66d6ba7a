"""What is logged to Rerun: static data and every frame (the default layout is in
:mod:`contact_viz.viz.blueprint`, the sinks in :mod:`contact_viz.viz.sinks`, both re-exported here).

Everything here receives an explicit ``rr.RecordingStream`` and objects the pipeline already
computed (the session, :class:`~contact_viz.pipeline.extract.FrameResult`, a :class:`FrameView` of
display-ready arrays, diagnostics); it computes no geometry and no posterior itself.

The entity paths and timelines are in :mod:`contact_viz.viz.entities` (re-exported here).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import rerun as rr
from rerun import RecordingStream

from contact_viz.checks.frame import FrameEvidence
from contact_viz.viz.diagnostics import DIAGNOSTIC_CODES, SESSION_DIAGNOSTIC_CODES, Diagnostic
from contact_viz.geometry.patch import PatchResult
from contact_viz.geometry.pointcloud import Cloud, PatchGeometry
from contact_viz.io.session import BadFrame, Session
from contact_viz.params import MM_PER_M
from contact_viz.viz.blueprint import (  # noqa: F401 (re-exported)
    MARKER_LANE, SCORE_CLIP, default_blueprint)
from contact_viz.viz.entities import *  # noqa: F403  (the entity paths, re-exported for scripts)
from contact_viz.viz.instrument_log import InstrumentLayers, InstrumentView  # noqa: F401 (re-exported)
from contact_viz.viz.sinks import (  # noqa: F401 (re-exported)
    DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT, OpenedRecording, SinkError, open_recording)
from contact_viz.viz.style import (
    DEPTH_COARSE,
    DEPTH_COLORMAP,
    DEPTH_FINE,
    DEPTH_FINE_EDGE,
    DEPTH_KIND_DRAW_ORDER,
    DEPTH_KIND_STYLES,
    DEPTH_NONE,
    DIAGNOSTIC_STYLES,
    KINEMATIC_STYLES,
    LAYER_OVERLAY_OPACITY,
    LAYER_STYLES,
    SERIES_STYLES,
    instrument_style,
)

__all__ = [
    "APPLICATION_ID",
    "CheckLines",
    "ContactEvidenceLines",
    "DepthKindLayer",
    "OpenedRecording",
    "RecordingStream",
    "open_recording",
    "ENTITY_CLOUD_FAR",
    "ENTITY_CONFIG",
    "ENTITY_CONTACT",
    "ENTITY_CLOUD_NEAR",
    "ENTITY_DEPTH_CAMERA",
    "ENTITY_DEPTH_IMAGE",
    "ENTITY_DEPTH_KIND",
    "ENTITY_DEPTH_LAYERS",
    "ENTITY_DEPTH_PATCH",
    "ENTITY_LEFT_CAMERA",
    "ENTITY_LEFT_IMAGE",
    "ENTITY_LEFT_LAYERS",
    "ENTITY_LEFT_PATCH",
    "ENTITY_LOG",
    "ENTITY_PATCH_GAP",
    "ENTITY_PATCH_TISSUE",
    "ENTITY_PATCH_TOOL",
    "ENTITY_RIGHT_CAMERA",
    "ENTITY_RIGHT_IMAGE",
    "ENTITY_SERIES_CONTACT",
    "ENTITY_SERIES_DIAGNOSTICS",
    "ENTITY_SERIES_DISTANCE",
    "ENTITY_SERIES_FORCE",
    "ENTITY_SERIES_INVALID_DEPTH",
    "ENTITY_SERIES_POSTERIOR",
    "ENTITY_SERIES_PREDICTED",
    "ENTITY_SERIES_SIGNAL",
    "ENTITY_SERIES_THRESHOLD",
    "ENTITY_SERIES_TRUTH",
    "ENTITY_WORLD",
    "FORCE_ENTITIES",
    "FrameView",
    "InstrumentLayers",
    "InstrumentView",
    "EMPTY_PNG",
    "MODEL_HINT",
    "TIMELINE_FRAME",
    "TIMELINE_TIME",
    "clear_image",
    "default_blueprint",
    "depth_kind_ids",
    "diagnostic_entity",
    "diagnostic_score_entity",
    "log_session_diagnostics",
    "log_bad_frame",
    "log_frame",
    "log_images",
    "log_model_hint",
    "log_static",
    "log_video_codec",
    "log_video_samples",
    "send_known_series",
    "set_frame_time",
    "tool_entity",
]

IMAGE_PLANE_DISTANCE_M = 0.015  # how far from each camera its image is drawn in the 3D view, m
EVIDENCE_OPACITY = 0.7  # opacity of the stereo-residual image over the left image, 0-1
EVIDENCE_MAX_POINTS = 3000  # contour points drawn at most (evenly subsampled), count
EVIDENCE_CHECKS = ("mask_image_edges", "mask_on_tissue", "tool_depth_outside", "stereo_residual", "frozen_depth",
                   "tool_width", "extra_blob")  # checks whose firing frames get the residual and contour pictures


MODEL_HINT = (
    "No contact model given, so there is no HMM posterior. Fit one on labelled training sessions with "
    "`contact-viz fit TRAIN_SESSION... -o model.json`, then add `--model model.json`."
)

CHECK_LANES = {code: k for k, code in enumerate({**DIAGNOSTIC_CODES, **SESSION_DIAGNOSTIC_CODES})}
SCORE_SHOWN = 0.5  # a check's score line is drawn where it is at least this (far from firing below), ratio


def marker_height(code: str) -> float:
    """Where a firing check's markers sit: in a lane of its own above every score line (two checks firing together
    never hide each other)."""
    return SCORE_CLIP + (CHECK_LANES[code] + 1) * MARKER_LANE


@dataclass(frozen=True)
class FrameView:
    """Display-ready data of one readable frame, prepared by the debugger (see contact_viz.viz.debugger)."""

    left_jpeg: bytes | None  # left image as JPEG bytes, or None
    left_rgb: np.ndarray | None  # left image as (H, W, 3) uint8 RGB (raw mode), or None
    right_jpeg: bytes | None  # right image as JPEG bytes, or None
    right_rgb: np.ndarray | None  # right image as (H, W, 3) uint8 RGB (raw mode), or None
    depth_u16: np.ndarray  # (h, w) uint16 decimated depth, 1 unit = 1 / depth_units_per_m m, 0 = invalid
    depth_units_per_m: float  # units of depth_u16 per metre
    # every instrument in the frame (a frame without any: the frame's patch as the primary instrument's)
    instruments: Sequence[InstrumentView]
    cloud: Cloud | None  # RGB point cloud (None = not logged)
    posterior: float | None  # the scene's causal HMM posterior P(contact) (None = no model)
    predicted: bool | None  # posterior >= threshold (None = no model)
    diagnostics: Sequence[Diagnostic] = ()  # checks that fired at this frame
    diagnostic_scores: dict | None = None  # check code -> measured value / threshold (> 1 fires)
    evidence: FrameEvidence | None = None  # residual image and contour of the frame checks
    has_right: bool = False  # the run shows right images (if this frame's right_* are None the pane is emptied)
    left_in_video: bool = False  # the left image goes to its video stream (log_video_samples), not logged here
    right_in_video: bool = False  # the right image goes to its video stream
    notes: Sequence[str] = ()  # other warnings of this frame (e.g. an unreadable right image)
    contact_tool: int | None = None  # the instrument in contact (with a model) or nearest (without), or None
    contact_text: str | None = None  # the same in words, for ENTITY_CONTACT (None: not logged)


# --------------------------------------------------------------------------------------------
# Static data and the blueprint
# --------------------------------------------------------------------------------------------


def _series_lines(key: str) -> rr.SeriesLines:
    style = SERIES_STYLES[key]
    return rr.SeriesLines(
        colors=[style.rgba], widths=[style.width_px], names=[style.name], visible_series=[style.visible],
        interpolation_mode=rr.components.InterpolationMode.StepAfter if style.step else None,
    )


def log_config(rec: rr.RecordingStream, config: dict) -> None:
    """Save the run's resolved configuration (a JSON-ready dict) in the recording, statically."""
    text = json.dumps(config, indent=2, default=str)
    rec.log(ENTITY_CONFIG, rr.TextDocument(f"```json\n{text}\n```", media_type=rr.MediaType.MARKDOWN), static=True)


# Built once at import: its conversion imports 51 ms of Rerun's modules, which a followed session's
# first frame would otherwise wait for (bench_live.py).
_LAYER_CLASSES = rr.AnnotationContext([rr.AnnotationInfo(id=s.class_id, label=s.name, color=s.rgba) for s in LAYER_STYLES])


def log_static(
    rec: rr.RecordingStream,
    session: Session,
    *,
    depth_step: int,
    depth_K: np.ndarray,
    with_right: bool,
    with_model: bool,
    right_step: int = 1,
) -> None:
    """Log what never changes: view coordinates, layer classes, cameras and the series' styles.

    ``depth_K`` is the camera matrix of the decimated depth grid (every ``depth_step``-th pixel);
    the right image is logged at 1 / ``right_step`` of the left image's size (its camera says so).
    """
    rec.send_recording_name(session.name)
    rec.log(
        ENTITY_WORLD,
        rr.ViewCoordinates.RDF,
        _LAYER_CLASSES,
        static=True,
    )
    height, width = session.image_size
    K = np.asarray(session.calibration.K, dtype=np.float64)
    pinhole = dict(camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=IMAGE_PLANE_DISTANCE_M)
    rec.log(ENTITY_LEFT_CAMERA, rr.Pinhole(image_from_camera=K, resolution=[width, height], **pinhole), static=True)
    depth_h, depth_w = -(-height // depth_step), -(-width // depth_step)
    rec.log(ENTITY_DEPTH_CAMERA, rr.Pinhole(image_from_camera=depth_K, resolution=[depth_w, depth_h], **pinhole),
            static=True)
    if with_right:
        rec.log(
            ENTITY_RIGHT_CAMERA,
            rr.Transform3D(translation=[session.calibration.baseline_m, 0.0, 0.0]),
            rr.Pinhole(image_from_camera=_scaled_K(K, right_step),
                       resolution=[-(-width // right_step), -(-height // right_step)], **pinhole),
            static=True,
        )
    rec.log(ENTITY_SERIES_DISTANCE, _series_lines("distance_mm"), static=True)
    rec.log(ENTITY_SERIES_SIGNAL, _series_lines("signal"), static=True)
    for entity, key in FORCE_ENTITIES.items():
        rec.log(entity, _series_lines(key), static=True)
    rec.log(ENTITY_SERIES_TRUTH, _series_lines("contact_truth"), static=True)
    if with_model:
        rec.log(ENTITY_SERIES_POSTERIOR, _series_lines("posterior"), static=True)
        rec.log(ENTITY_SERIES_THRESHOLD, _series_lines("threshold"), static=True)
        rec.log(ENTITY_SERIES_PREDICTED, _series_lines("predicted"), static=True)
    rec.log(ENTITY_SERIES_INVALID_DEPTH, _series_lines("invalid_depth_fraction"), static=True)
    markers = list(rr.components.MarkerShape)
    for k, code in enumerate({**DIAGNOSTIC_CODES, **SESSION_DIAGNOSTIC_CODES}):
        style = DIAGNOSTIC_STYLES[code]
        rec.log(
            diagnostic_entity(code),
            rr.SeriesPoints(colors=[style.rgba], names=[f"{style.name}: fired"], markers=[markers[k % len(markers)]],
                            marker_sizes=[style.width_px]),
            static=True,
        )
        rec.log(diagnostic_score_entity(code), rr.SeriesLines(colors=[style.rgba], widths=[1.5],
                                                              names=[style.name]), static=True)


def _scaled_K(K: np.ndarray, step: int) -> np.ndarray:
    """K of the image downscaled by ``step`` (fx, fy, cx, cy / step; the sub-pixel offset of the pixel centres,
    under half a pixel of the small image, does not show)."""
    K = np.array(K, dtype=np.float64)
    K[:2] /= float(step)
    return K


def send_known_series(
    rec: rr.RecordingStream, session: Session, indices: Sequence[int], *, threshold: float | None = None
) -> None:
    """Send the series known before any frame is read, as columns over the frames ``indices``.

    Force magnitude and components (N; skipped when the session has no force), ground-truth
    contact (0/1, NaN where unknown) and, with a model, its decision ``threshold``.
    """
    idx = np.asarray(indices, dtype=np.int64)
    if idx.size == 0:
        return
    times = [
        rr.TimeColumn(TIMELINE_FRAME, sequence=idx),
        rr.TimeColumn(TIMELINE_TIME, duration=np.asarray(session.timestamps_s, dtype=np.float64)[idx]),
    ]
    force = np.asarray(session.force_xyz_n, dtype=np.float64)[idx]
    if np.isfinite(force).any():
        columns = {
            "series/force/magnitude": np.asarray(session.force_n, dtype=np.float64)[idx],
            "series/force/x": force[:, 0],
            "series/force/y": force[:, 1],
            "series/force/z": force[:, 2],
        }
        for entity, values in columns.items():
            rec.send_columns(entity, indexes=times, columns=rr.Scalars.columns(scalars=values))
    labels = np.asarray(session.labels)[idx]
    if (labels >= 0).any():
        truth = np.where(labels >= 0, labels, np.nan).astype(np.float64)
        rec.send_columns(ENTITY_SERIES_TRUTH, indexes=times, columns=rr.Scalars.columns(scalars=truth))
    if threshold is not None:
        rec.send_columns(ENTITY_SERIES_THRESHOLD, indexes=times,
                         columns=rr.Scalars.columns(scalars=np.full(idx.size, float(threshold))))


def log_model_hint(rec: rr.RecordingStream, index: int, timestamp_s: float) -> None:
    """Say (TextLog, at frame ``index``) that there is no model and how to get one."""
    set_frame_time(rec, index, timestamp_s)
    rec.log(ENTITY_LOG, rr.TextLog(MODEL_HINT, level=rr.TextLogLevel.INFO))


# --------------------------------------------------------------------------------------------
# Per frame
# --------------------------------------------------------------------------------------------


def set_frame_time(rec: rr.RecordingStream, index: int, timestamp_s: float) -> None:
    """Put the recording at frame ``index`` (``frame`` timeline) and ``timestamp_s`` (``time`` timeline)."""
    rec.set_time(TIMELINE_FRAME, sequence=int(index))
    rec.set_time(TIMELINE_TIME, duration=float(timestamp_s))


def _empty_png() -> bytes:
    import cv2

    ok, data = cv2.imencode(".png", np.zeros((1, 1, 4), np.uint8))
    assert ok
    return data.tobytes()


# A fully transparent 1x1 PNG (67 bytes). The viewer ignores rr.Clear on encoded images (rerun-io/rerun#12793,
# Rerun 0.41): an encoded image's entity without an image at a frame gets this one instead, after the Clear.
EMPTY_PNG = _empty_png()


def clear_image(rec: rr.RecordingStream, entity: str, recursive: bool = False) -> None:
    """Nothing at ``entity`` from now on: a Clear, and an empty encoded image (the viewer keeps showing the last
    encoded image through a Clear)."""
    rec.log(entity, rr.Clear(recursive=recursive))
    rec.log(entity, rr.EncodedImage(contents=EMPTY_PNG, media_type="image/png"))


def _log_image(rec: rr.RecordingStream, entity: str, jpeg: bytes | None, rgb: np.ndarray | None,
               in_video: bool = False) -> None:
    if in_video:
        return  # its sample is logged by log_video_samples when the encoder has it
    if jpeg is not None:
        rec.log(entity, rr.EncodedImage(contents=jpeg, media_type="image/jpeg"))
    elif rgb is not None:
        rec.log(entity, rr.Image(rgb, color_model="RGB"))
    else:
        clear_image(rec, entity)


def log_images(rec: rr.RecordingStream, view) -> None:
    """A frame's left and right images (a :class:`FrameView`, or anything with its image fields): each is the
    frame's own or absent, never the frame before's."""
    _log_image(rec, ENTITY_LEFT_IMAGE, view.left_jpeg, view.left_rgb, view.left_in_video)
    if view.has_right:
        _log_image(rec, ENTITY_RIGHT_IMAGE, view.right_jpeg, view.right_rgb, view.right_in_video)


VIDEO_CODECS = {"av1": rr.VideoCodec.AV1, "h264": rr.VideoCodec.H264}  # VideoParams.codec -> Rerun's codec


def log_video_codec(rec: rr.RecordingStream, entities: Sequence[str], codec: str) -> None:
    """Say (statically) that the images of ``entities`` are video streams of ``codec`` ("av1" or "h264")."""
    for entity in entities:
        rec.log(entity, rr.VideoStream(codec=VIDEO_CODECS[codec]), static=True)


def log_video_samples(rec: rr.RecordingStream, entity: str, samples: Sequence, timestamps_s: np.ndarray) -> None:
    """Log encoded video ``samples`` (contact_viz.viz.video.EncodedSample, tagged with their frame index) of
    ``entity`` at their frames; ``timestamps_s`` maps a frame index to its session time (s)."""
    if not samples:
        return
    index = np.array([s.tag for s in samples], dtype=np.int64)
    times = [rr.TimeColumn(TIMELINE_FRAME, sequence=index),
             rr.TimeColumn(TIMELINE_TIME, duration=np.asarray(timestamps_s, dtype=np.float64)[index])]
    rec.send_columns(entity, indexes=times,
                     columns=rr.VideoStream.columns(sample=[s.data for s in samples],
                                                    is_keyframe=[s.is_keyframe for s in samples]))


def _log_series(rec: rr.RecordingStream, entity: str, value: float) -> None:
    rec.log(entity, rr.Scalars(float(value)))


def _log_contact(rec: rr.RecordingStream, posterior: float | None, predicted: bool | None) -> None:
    if posterior is not None:
        _log_series(rec, ENTITY_SERIES_POSTERIOR, posterior)
    if predicted is not None:
        _log_series(rec, ENTITY_SERIES_PREDICTED, 1.0 if predicted else 0.0)


class ContactEvidenceLines:
    """Each instrument's evidence for contact, frame by frame (with a model): the emission log-likelihood ratio of
    its signal that the causal filter adds (ENTITY_SERIES_EVIDENCE; the primary instrument's at that path, every
    other one's under it, at ``tools/<k>``), a line in the instrument's colour. An instrument without evidence at a
    frame (absent, no patch, a bad frame) gets a NaN, once: its line breaks there. The lines are named after
    their instruments once the session has several (``instruments.several``)."""

    def __init__(self, instruments: InstrumentLayers) -> None:
        self.instruments = instruments
        self.styled: dict[int, bool] = {}  # instrument -> whether its line's style names it
        self.shown: set[int] = set()  # instruments whose line holds a value at the current time

    def _style(self, rec: rr.RecordingStream, tool: int) -> None:
        named = self.instruments.several
        if self.styled.get(tool) == named:
            return
        self.styled[tool] = named
        base, style = SERIES_STYLES["contact_evidence"], instrument_style(tool)
        rec.log(self.instruments.entity(ENTITY_SERIES_EVIDENCE, tool),
                rr.SeriesLines(colors=[style.line], widths=[base.width_px],
                               names=[f"{base.name}, {style.name}" if named else base.name]), static=True)

    def log(self, rec: rr.RecordingStream, evidence: dict[int, float]) -> None:
        """Log ``evidence`` {object id: log-likelihood ratio, nats (NaN: no observation)} at the current time."""
        for tool in sorted(evidence):
            self._style(rec, tool)
            _log_series(rec, self.instruments.entity(ENTITY_SERIES_EVIDENCE, tool), evidence[tool])
        for tool in sorted(self.shown - evidence.keys()):
            _log_series(rec, self.instruments.entity(ENTITY_SERIES_EVIDENCE, tool), math.nan)
        self.shown = {tool for tool, value in evidence.items() if math.isfinite(value)}


class CheckLines:
    """The checks' score lines over a run: a check's score is drawn where it is at least SCORE_SHOWN (a NaN breaks
    its line where it falls below), so that the plot and its legend hold the checks that came near firing."""

    def __init__(self) -> None:
        self.up: set[str] = set()  # checks whose line is drawn at the current frame

    def log(self, rec: rr.RecordingStream, scores: dict | None) -> None:
        scores = scores or {}
        for code, score in scores.items():
            if math.isfinite(score) and score >= SCORE_SHOWN:
                _log_series(rec, diagnostic_score_entity(code), min(score, SCORE_CLIP))
                self.up.add(code)
        for code in sorted(self.up - {c for c, v in scores.items() if math.isfinite(v) and v >= SCORE_SHOWN}):
            _log_series(rec, diagnostic_score_entity(code), math.nan)
            self.up.discard(code)


def _log_diagnostics(rec: rr.RecordingStream, diagnostics: Sequence[Diagnostic], notes: Sequence[str],
                     scores: dict | None = None, lines: CheckLines | None = None, stem: str = "") -> None:
    (lines or CheckLines()).log(rec, scores)
    for diagnostic in diagnostics:
        _log_series(rec, diagnostic_entity(diagnostic.code), marker_height(diagnostic.code))
        if diagnostic.code != "bad_frame":  # log_bad_frame writes that one's text
            rec.log(ENTITY_LOG, rr.TextLog(f"frame {stem or diagnostic.index}: {diagnostic.message}",
                                           level=rr.TextLogLevel.WARN))
    for note in notes:
        rec.log(ENTITY_LOG, rr.TextLog(note, level=rr.TextLogLevel.WARN))


def log_frame(rec: rr.RecordingStream, result, view: FrameView, instruments: InstrumentLayers,
              lines: CheckLines | None = None) -> None:
    """Log one readable frame: ``result`` is its FrameResult (frame + patch), ``view`` its display data,
    ``instruments`` the per-instrument entities and ``lines`` the checks' score lines of the run (one of each for
    all its frames)."""
    frame, patch = result.frame, result.patch
    if patch is None:
        raise ValueError(f"log_frame: frame {frame.index} has no patch result (a bad frame); use log_bad_frame")
    set_frame_time(rec, frame.index, frame.timestamp_s)

    log_images(rec, view)
    rec.log(ENTITY_DEPTH_IMAGE, rr.DepthImage(view.depth_u16, meter=view.depth_units_per_m, colormap=DEPTH_COLORMAP))
    instruments.log(rec, view.instruments, view.contact_tool)

    if view.cloud is not None:
        cloud = view.cloud
        rec.log(ENTITY_CLOUD_NEAR, rr.Points3D(cloud.near_points_m, colors=cloud_colours(cloud),
                                               radii=cloud.near_radii_m))
        if len(cloud.far_points_m):  # (stride_px=0: no far part)
            rec.log(ENTITY_CLOUD_FAR, rr.Points3D(cloud.far_points_m, colors=cloud.far_colors,
                                                  radii=[cloud.far_radius_m]))

    _log_series(rec, ENTITY_SERIES_INVALID_DEPTH, patch.invalid_depth_fraction)
    _log_contact(rec, view.posterior, view.predicted)
    if view.contact_text is not None:
        rec.log(ENTITY_CONTACT, rr.TextDocument(view.contact_text, media_type=rr.MediaType.MARKDOWN))
    _log_diagnostics(rec, view.diagnostics, view.notes, view.diagnostic_scores, lines, frame.stem)
    _log_evidence(rec, view.evidence if any(d.code in EVIDENCE_CHECKS for d in view.diagnostics) else None,
                  frame.tool_mask.shape)


def cloud_colours(cloud: Cloud) -> np.ndarray:
    """The near cloud's colours: the image's on the tissue, each instrument's own colour on its points."""
    colours = np.array(cloud.near_colors, dtype=np.uint8, copy=True)
    for tool in np.unique(cloud.near_ids[cloud.near_ids > 0]):
        colours[cloud.near_ids == tool] = instrument_style(int(tool)).window[:3]
    return colours


def log_force_sample(rec: rr.RecordingStream, force_xyz_n) -> None:
    """One force sample (N, x y z) at the recording's current time: its magnitude and components."""
    fx, fy, fz = (float(v) for v in force_xyz_n)
    for entity, value in zip(FORCE_ENTITIES, (math.sqrt(fx * fx + fy * fy + fz * fz), fx, fy, fz)):
        _log_series(rec, entity, value)


def log_series_only(rec: rr.RecordingStream, tools: dict, posterior: float | None, predicted: bool | None,
                    posteriors: dict[int, float] | None, instruments: InstrumentLayers,
                    images_in_video: frozenset[str] = frozenset()) -> None:
    """A frame shown only in the series (at the recording's current time): each instrument's distance and
    signal (``tools``: object id -> PatchResult), the scene's posterior and decision and, with several
    instruments, each one's posterior. No images, layers or checks (a follower catching up): those of the frame
    before are cleared, so that none shows at this frame (``images_in_video``: the image entities that are video
    streams, which get a grey frame from their encoder instead)."""
    for tool, patch in tools.items():
        _log_series(rec, instruments.entity(ENTITY_SERIES_DISTANCE, tool), patch.distance_m * MM_PER_M)
        _log_series(rec, instruments.entity(ENTITY_SERIES_SIGNAL, tool), patch.signal)
        if instruments.several and posteriors is not None:
            _log_series(rec, tool_entity(ENTITY_SERIES_POSTERIOR, tool), posteriors[tool])
    _log_contact(rec, posterior, predicted)
    for entity in PER_FRAME_ENTITIES:
        if entity in (ENTITY_LEFT_IMAGE, ENTITY_RIGHT_IMAGE):
            if entity not in images_in_video:
                clear_image(rec, entity)
        else:
            rec.log(entity, rr.Clear(recursive=False))
    instruments.clear_layers(rec)
    _log_evidence(rec, None, (0, 0))


def depth_kind_ids(depth_fine: np.ndarray | None, step: int, depth_u16: np.ndarray | None = None
                   ) -> np.ndarray | None:
    """The depth-kind classes on the decimated depth grid: (h, w) uint8, DEPTH_FINE where ``depth_fine``
    ((H, W) bool, :attr:`contact_viz.io.session.Frame.depth_fine`) is True (DEPTH_FINE_EDGE on its outermost pixels),
    DEPTH_COARSE elsewhere, DEPTH_NONE where
    ``depth_u16`` (the depth image, :func:`contact_viz.geometry.pointcloud.depth_preview`) is 0; the same
    ``[::step, ::step]`` pixels as the depth image, so it lies on it. Without ``depth_fine`` (depth files) only the
    pixels without depth are marked (the rest DEPTH_FINE, not drawn); None when there is neither."""
    if depth_fine is None and depth_u16 is None:
        return None
    if depth_fine is not None:
        import cv2

        fine = np.asarray(depth_fine, dtype=bool)[::step, ::step]
        ids = np.where(fine, np.uint8(DEPTH_FINE), np.uint8(DEPTH_COARSE))
        edge = fine & ~cv2.erode(fine.astype(np.uint8), np.ones((3, 3), np.uint8), borderValue=1).astype(bool)
        ids[edge] = DEPTH_FINE_EDGE
    else:
        ids = np.full(np.shape(depth_u16), DEPTH_FINE, np.uint8)  # (a class of its own: Rerun colours unknown ids)
    if depth_u16 is not None:
        ids[np.asarray(depth_u16) == 0] = DEPTH_NONE
    return ids


class DepthKindLayer:
    """The fine / coarse / no-depth layer of the depth pane (ENTITY_DEPTH_KIND), frame by frame.

    Its classes (an AnnotationContext on the entity itself, which Rerun finds before the layer classes
    on ``world``: the ids overlap) are logged statically with the first frame that has the layer; a frame
    without it (a depth file, SGBM without a mask, a bad frame) logs nothing, and clears the entity if the
    previous frame showed it, so a stale layer never shows. A session without the layer never has the entity.
    """

    def __init__(self) -> None:
        self.classes_logged = False
        self.shown = False  # the entity holds a layer at the current time

    def log(self, rec: rr.RecordingStream, ids: np.ndarray | None) -> None:
        """Log ``ids`` (from :func:`depth_kind_ids`, or None) at the recording's current time."""
        if ids is None:
            if self.shown:
                rec.log(ENTITY_DEPTH_KIND, rr.Clear(recursive=False))
                self.shown = False
            return
        if not self.classes_logged:
            rec.log(ENTITY_DEPTH_KIND, rr.AnnotationContext(
                [rr.AnnotationInfo(id=s.class_id, label=s.name, color=s.rgba) for s in DEPTH_KIND_STYLES]),
                static=True)
            self.classes_logged = True
        rec.log(ENTITY_DEPTH_KIND, rr.SegmentationImage(ids, opacity=LAYER_OVERLAY_OPACITY,
                                                        draw_order=DEPTH_KIND_DRAW_ORDER))
        self.shown = True


def _log_evidence(rec: rr.RecordingStream, evidence: FrameEvidence | None, shape: tuple[int, int]) -> None:
    """The pictures behind the frame checks, on frames where one fired; cleared on the others.

    The stereo residual (JPEG, inferno colours x4: black = the depth explains the pair, yellow = 64+
    grey levels off) where it was measured near the tool, over the grey left image, and the mask contour: green where it lies on an image edge, red where not.
    """
    if evidence is None:
        clear_image(rec, ENTITY_EVIDENCE_RESIDUAL)
        rec.log(ENTITY_EVIDENCE_CONTOUR, rr.Clear(recursive=False))
        return
    import cv2

    x, y, w, h = evidence.residual_xywh
    # grey left image everywhere, the residual in colour where it was measured (at the checks' resolution,
    # then brought to the image's size so that it lies over the left image)
    step = evidence.step
    grey = evidence.left_grey if evidence.left_grey is not None else np.zeros(
        (-(-shape[0] // step), -(-shape[1] // step)), np.uint8)
    colour = cv2.cvtColor(np.asarray(grey, dtype=np.uint8), cv2.COLOR_GRAY2BGR)
    heat = cv2.applyColorMap(np.clip(evidence.residual.astype(np.float32) * 4.0, 0, 255).astype(np.uint8),
                             cv2.COLORMAP_INFERNO)
    crop = colour[y:y + h, x:x + w]
    crop[evidence.region] = heat[evidence.region]
    if colour.shape[:2] != tuple(shape):
        colour = cv2.resize(colour, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)
    ok, jpeg = cv2.imencode(".jpg", colour, [cv2.IMWRITE_JPEG_QUALITY, 70])
    if ok:
        rec.log(ENTITY_EVIDENCE_RESIDUAL, rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg",
                                                          opacity=EVIDENCE_OPACITY, draw_order=0.5))
    points = evidence.contour_xy
    on_edge = evidence.contour_on_edge
    if len(points) > EVIDENCE_MAX_POINTS:
        keep = np.linspace(0, len(points) - 1, EVIDENCE_MAX_POINTS).astype(np.int64)
        points, on_edge = points[keep], on_edge[keep]
    colours = np.where(on_edge[:, None], np.array([[0, 158, 115, 255]], np.uint8),
                       np.array([[213, 94, 0, 255]], np.uint8))
    rec.log(ENTITY_EVIDENCE_CONTOUR, rr.Points2D(points + 0.5, colors=colours, radii=[-1.5], draw_order=40.0))


def log_session_diagnostics(rec: rr.RecordingStream, diagnostics: Sequence[Diagnostic], timestamp_s: float) -> None:
    """The session checks (force lag, frame times), at the frame each names: a marker and a log warning."""
    for diagnostic in diagnostics:
        set_frame_time(rec, diagnostic.index, timestamp_s)
        _log_series(rec, diagnostic_entity(diagnostic.code), marker_height(diagnostic.code))
        rec.log(ENTITY_LOG, rr.TextLog(f"session: {diagnostic.message}", level=rr.TextLogLevel.WARN))


KINEMATIC_AXIS_M = 0.005  # drawn length of the tool frame's axes, m


def log_kinematic_tip(rec: rr.RecordingStream, tip) -> None:
    """Log a frame's :class:`contact_viz.geometry.kinematics.KinematicTip` (None: no pose near the frame)."""
    entities = (ENTITY_KINEMATIC_TIP, ENTITY_KINEMATIC_AXES, ENTITY_LEFT_KINEMATIC_TIP, ENTITY_LEFT_MASK_TIP)
    if tip is None:
        for entity in entities:
            rec.log(entity, rr.Clear(recursive=False))
        error_px = error_mm = math.nan
    else:
        rec.log(ENTITY_KINEMATIC_TIP, rr.Points3D([tip.tip_m], colors=[KINEMATIC_STYLES["tip"]], radii=[0.0008],
                                                  labels=["kinematic tip"]))
        rec.log(ENTITY_KINEMATIC_AXES, rr.Arrows3D(origins=[tip.tip_m] * 3, vectors=tip.axes.T * KINEMATIC_AXIS_M,
                                                   colors=list(KINEMATIC_STYLES["axes"])))
        for entity, xy, key in ((ENTITY_LEFT_KINEMATIC_TIP, tip.tip_xy_px, "tip"),
                                (ENTITY_LEFT_MASK_TIP, tip.mask_tip_xy_px, "mask")):
            if xy is not None and np.isfinite(xy).all():
                rec.log(entity, rr.Points2D([xy], colors=[KINEMATIC_STYLES[key]], radii=[-4.0]))
            else:
                rec.log(entity, rr.Clear(recursive=False))
        error_px, error_mm = tip.error_px, tip.error_mm
    _log_series(rec, f"{ENTITY_SERIES_TIP}/error_px", error_px)
    _log_series(rec, f"{ENTITY_SERIES_TIP}/error_mm", error_mm)


def log_bad_frame(
    rec: rr.RecordingStream,
    frame: BadFrame,
    *,
    posterior: float | None = None,
    predicted: bool | None = None,
    diagnostics: Sequence[Diagnostic] = (),
    instruments: InstrumentLayers | None = None,
    contact_text: str | None = None,
    lines: CheckLines | None = None,
) -> None:
    """Log a frame that could not be read: a warning naming the file, cleared images (every instrument's
    layers, with ``instruments``), gaps in the series.

    The posterior (a prediction step, with a model) is still logged: the filter runs on.
    """
    set_frame_time(rec, frame.index, frame.timestamp_s)
    rec.log(ENTITY_LOG, rr.TextLog(f"frame {frame.index} ({frame.stem}) could not be read and was skipped: "
                                   f"{frame.reason}", level=rr.TextLogLevel.WARN))
    for entity in PER_FRAME_ENTITIES:  # (its images, when they could be read, are logged by log_images)
        if entity not in (ENTITY_LEFT_IMAGE, ENTITY_RIGHT_IMAGE):
            rec.log(entity, rr.Clear(recursive=False))
    _log_evidence(rec, None, (0, 0))
    for entity in (ENTITY_SERIES_DISTANCE, ENTITY_SERIES_SIGNAL, ENTITY_SERIES_INVALID_DEPTH):
        _log_series(rec, entity, math.nan)
    if instruments is not None:
        instruments.bad_frame(rec)
    _log_contact(rec, posterior, predicted)
    if contact_text is not None:
        rec.log(ENTITY_CONTACT, rr.TextDocument(f"**{contact_text}**", media_type=rr.MediaType.MARKDOWN))
    _log_diagnostics(rec, diagnostics, (), None, lines, frame.stem)
