"""What the debugger logs of each frame, shared by a run over a finished session
(:func:`contact_viz.viz.debugger.run_debugger`) and one that follows a session being recorded
(:func:`contact_viz.viz.follow.follow_session`): :class:`FrameLogger`.

Per frame it prepares what the frame shows (point cloud, patch geometry, decimated depth, causal
HMM posterior, diagnostics) and hands it to :mod:`contact_viz.viz.rerun_log`. Nothing is collected
across frames but counters: memory stays flat however long the session is.
"""

from __future__ import annotations

import copy
import math
import time
import warnings

import numpy as np

from contact_viz.console import FULL_MASK, no_patch_message, no_patch_problem
from contact_viz.errors import NoPatchWarning, SessionWarning
from contact_viz.geometry.kinematics import frame_samples, kinematic_tip
from contact_viz.geometry.pointcloud import decimated_intrinsics, depth_cloud, depth_preview, patch_geometry
from contact_viz.geometry.tooltip import tool_tip_xy
from contact_viz.io.session import Session
from contact_viz.model.hmm import StreamingFilter
from contact_viz.params import to_dict
from contact_viz.pipeline.extract import run_config
from contact_viz.viz import rerun_log
from contact_viz.viz.blueprint import DEPTH_LEGEND, layer_legend
from contact_viz.viz.diagnostics import DiagnosticsTracker
from contact_viz.viz.images import ImageReader, ShownImages, VideoStreams, right_step_of
from contact_viz.viz.options import DebuggerOptions, RunSummary
from contact_viz.viz.style import instrument_style


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
    a single StreamingFilter on ``FrameResult.patch.signal``. After an update, ``evidence`` holds each instrument
    in the frame's emission log-likelihood ratio ({object id: nats}, NaN without a patch): what its filter added.
    """

    def __init__(self, ensemble) -> None:
        self._unseen = StreamingFilter(ensemble)  # fed NaN on every frame: an instrument not seen yet
        self.filters: dict[int, StreamingFilter] = {}
        self.evidence: dict[int, float] = {}

    def update(self, signals: dict[int, float]) -> tuple[float, dict[int, float]]:
        """Add one frame: ``signals`` {object id: signal} of the instruments in it ({} for none, or a bad
        frame). Returns (scene posterior, {object id: posterior} of every instrument seen so far)."""
        for tool in sorted(signals.keys() - self.filters.keys()):
            self.filters[tool] = copy.deepcopy(self._unseen)
        each = {tool: f.update(signals.get(tool, math.nan)) for tool, f in self.filters.items()}
        self.evidence = {tool: self.filters[tool].evidence for tool in signals}
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
                 contact: int | None, top: int | None, evidence: dict[int, float] | None = None) -> str:
    """The frame's ENTITY_CONTACT document (markdown): the contact state as a heading (the instrument in contact
    with a model, or the nearest without), then each instrument's distance (and posterior, and the evidence for
    contact its signal gave: the log-likelihood ratio, ``evidence``) under its colour's name, then the legend of
    the colours (blueprint.layer_legend)."""
    def name(tool: int) -> str:
        return f"instrument {tool} ({instrument_style(tool).colour_name})"

    if not tool_patches:
        head = "no instrument in this frame"
    elif posteriors is not None:
        if contact is not None:
            head = f"in contact: {name(contact)}, P {posteriors[contact]:.2f} >= threshold {threshold:.2f}"
        else:
            head = f"no contact: largest P {posteriors[top]:.2f} ({name(top)}) < threshold {threshold:.2f}"
    elif contact is not None:
        head = f"nearest: {name(contact)}, {tool_patches[contact].distance_m * 1000:.1f} mm"
    else:
        head = "nearest: none (no instrument has a distance in this frame)"
    lines = [f"**{head}**", ""]
    for tool, patch in sorted(tool_patches.items()):
        d = patch.distance_m
        text = f"- {name(tool)}: " + (f"{d * 1000:.1f} mm" if math.isfinite(d) else "no distance")
        if posteriors is not None:
            text += f", P {posteriors[tool]:.2f}"
        if evidence is not None and math.isfinite(evidence.get(tool, math.nan)):
            text += f", evidence {evidence[tool]:+.1f}"
        lines.append(text)
    return "\n".join([*lines, "", f"*{layer_legend()}*", "", f"*{DEPTH_LEGEND}*"])


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


class _ImagesOf:
    """The image fields of :class:`rerun_log.FrameView` from a frame's ShownImages (for a bad frame); ``video``:
    the image entities that are video streams (their frames, grey where unreadable, go to the encoders)."""

    def __init__(self, shown: ShownImages, video: frozenset[str], with_right: bool) -> None:
        self.left_jpeg, self.left_rgb = shown.left_jpeg, shown.left_rgb
        self.right_jpeg, self.right_rgb = shown.right_jpeg, shown.right_rgb
        self.left_in_video = rerun_log.ENTITY_LEFT_IMAGE in video
        self.right_in_video = rerun_log.ENTITY_RIGHT_IMAGE in video
        self.has_right = with_right


class FrameLogger:
    """A run's logging state: static data at the start, then :meth:`log` per frame, :meth:`finish` at the end.

    ``indices``: the frames a run over a finished session shows (their force, truth and threshold are
    sent up front as columns); None when they are not known yet (a session being recorded: the
    follower logs force as it arrives). ``model`` (a ContactModel, optional) adds the causal posterior;
    its patch parameters must equal ``options.patch_params`` (ValueError otherwise).
    """

    def __init__(self, session: Session, rec, options: DebuggerOptions, model=None, indices=None) -> None:
        if model is not None:
            from contact_viz.model.model_file import check_params

            check_params(model.patch_params, options.patch_params, "contact-viz view")
        self.session, self.rec, self.options, self.model = session, rec, options, model
        self.K = np.asarray(session.calibration.K, dtype=np.float64)
        self.step = options.depth_step
        with_right = self.with_right = options.with_right and session.has_right
        rerun_log.log_static(rec, session, depth_step=self.step, depth_K=decimated_intrinsics(self.K, self.step),
                             with_right=with_right, with_model=model is not None,
                             right_step=right_step_of(session, options))
        config = run_config(session, options=options, model=None if model is None else {
            "model_kind": model.model_kind, "threshold": model.threshold,
            "training_sessions": list(model.training_sessions),
            "label_params": to_dict(model.label_params), "version": model.version})
        config["session"]["depth"] = getattr(session, "depth_note", None)
        rerun_log.log_config(rec, config)
        if indices is not None:
            rerun_log.send_known_series(rec, session, indices,
                                        threshold=None if model is None else model.threshold)
        self._hint_logged = model is not None
        self.tracker = DiagnosticsTracker(options.diagnostics, fx_px=float(self.K[0, 0]),
                                          baseline_m=float(session.calibration.baseline_m),
                                          image_width=session.image_size[1], depth_source=session.depth_source,
                                          stems=tuple(session.stems))
        self.pose_of = _pose_samples(session, options)  # (n,) pose row per frame (-1 none), or None
        self.stream = None if model is None else InstrumentPosteriors(model.ensemble)
        selected = getattr(session, "object_ids", None)
        # the primary instrument (single-instrument entity paths): the lowest selected id, else 1 (a binary mask's)
        self.instruments = rerun_log.InstrumentLayers(min(selected) if selected else 1, with_model=model is not None,
                                                      several=bool(selected) and len(selected) > 1,
                                                      image_size=session.image_size)
        # each instrument's evidence for contact beside the posterior (with a model)
        self.evidence_lines = None if model is None else rerun_log.ContactEvidenceLines(self.instruments)
        self.check_lines = rerun_log.CheckLines()  # the checks' score lines, drawn where near firing
        self.instrument_frames: dict[int, int] = {}
        self.nearest_frames: dict[int, int] = {}
        self.contact_frames: dict[int, int] = {}
        self.closest: tuple[int, float, int] | None = None
        # the encoders first: a stream they refuse is read as JPEG images
        self.videos = VideoStreams(session, rec, options, with_right) if options.images == "video" else None
        self.reader = ImageReader(session, options, with_right, self.videos)
        self.video_entities = frozenset(self.videos.encoders if self.videos is not None else ())
        self.depth_kind = rerun_log.DepthKindLayer()  # fine / coarse SGBM depth on the depth pane
        self.done = self.bad = 0
        self.prepare_s = self.log_s = 0.0
        self.last_index: int | None = None

    def _contact(self, result):
        """The frame's instruments, posteriors and named instrument, and the run's counters updated."""
        tools = dict(result.tool_patches or {}) if result.patch is not None else {}  # {object id: PatchResult}
        posterior = predicted = each = None
        nearest = contact = top = nearest_instrument(tools)  # without a model: the nearest one is named
        if self.stream is not None:
            posterior, each = self.stream.update({k: p.signal for k, p in tools.items()})
            predicted = posterior >= self.model.threshold
            contact, top = contact_instrument({k: each[k] for k in tools}, self.model.threshold)
        for tool, tool_patch in tools.items():
            self.instrument_frames[tool] = self.instrument_frames.get(tool, 0) + 1
            d = tool_patch.distance_m
            if math.isfinite(d) and (self.closest is None or abs(d) * 1000 < abs(self.closest[1])):
                self.closest = (tool, d * 1000, result.frame.index)
        if nearest is not None:
            self.nearest_frames[nearest] = self.nearest_frames.get(nearest, 0) + 1
        if self.stream is not None and contact is not None:
            self.contact_frames[contact] = self.contact_frames.get(contact, 0) + 1
        return tools, posterior, predicted, each, contact, top

    def log(self, result, shown: ShownImages) -> None:
        """Log one frame: ``result`` its FrameResult (the pipeline's), ``shown`` its images (ImageReader.load)."""
        t2 = time.perf_counter()
        rec, options, session, K, step = self.rec, self.options, self.session, self.K, self.step
        for note in shown.notes:  # an image the viewer cannot show: on the console too, not only in the log
            warnings.warn(note, SessionWarning, stacklevel=2)
        frame, patch = result.frame, result.patch
        if not self._hint_logged:
            rerun_log.log_model_hint(rec, frame.index, float(frame.timestamp_s))
            self._hint_logged = True
        # (in this thread: one frame ahead in a thread of its own, the checks, cloud and depth preview were
        # slower, 20.4 against 22.5 frames/s, 1080p JPEG session, --images jpeg: the threads contend for the GIL)
        diag = self.tracker.update(result, shown.left_grey, shown.right_grey, evidence=True)
        diagnostics = diag.fired
        tools, posterior, predicted, each, contact, top = self._contact(result)
        if patch is None:
            self.bad += 1
            t3 = time.perf_counter()
            rerun_log.log_bad_frame(rec, frame, posterior=posterior, predicted=predicted, diagnostics=diagnostics,
                                    instruments=self.instruments, contact_text="this frame could not be read",
                                    lines=self.check_lines)
            rerun_log.log_images(rec, _ImagesOf(shown, self.video_entities, self.with_right))  # its own, or none
            self._log_contact_evidence()
            self.depth_kind.log(rec, None)
            if self.videos is not None:
                self.videos.feed(frame.index, shown)
        else:
            problem = no_patch_problem(patch.reason, patch.invalid_depth_fraction)
            if problem is not None:  # the frame was read, but its input gives nothing to measure
                layer = "mask" if problem == FULL_MASK else "depth"
                warnings.warn(no_patch_message(frame.stem, problem, session.layer_file(layer, frame.stem)),
                              NoPatchWarning, stacklevel=2)
            depth_u16 = depth_preview(frame.depth_m, step, options.depth_units_per_m)
            kind_ids = rerun_log.depth_kind_ids(frame.depth_fine, step, depth_u16)
            # each instrument's layers; a frame without any shows its (empty) patch as the primary's
            views = [_instrument_view(tool, tool_patch, frame.depth_m, K, step, options,
                                      None if each is None else each[tool])
                     for tool, tool_patch in sorted(tools.items())] or [
                _instrument_view(self.instruments.primary, patch, frame.depth_m, K, step, options)]
            view = rerun_log.FrameView(
                left_jpeg=shown.left_jpeg,
                left_rgb=shown.left_rgb,
                right_jpeg=shown.right_jpeg,
                right_rgb=shown.right_rgb,
                left_in_video=rerun_log.ENTITY_LEFT_IMAGE in self.video_entities,
                right_in_video=rerun_log.ENTITY_RIGHT_IMAGE in self.video_entities,
                has_right=self.with_right,  # (a frame without its right image: the pane is emptied)
                depth_u16=depth_u16,
                depth_units_per_m=options.depth_units_per_m,
                instruments=views,
                cloud=depth_cloud(frame.depth_m, K, shown.colors_rgb, center_xy=patch.center_xy,
                                  centers_xy=[p.center_xy for p in tools.values()], tool_ids=frame.tool_ids,
                                  params=options.cloud) if options.points else None,
                posterior=posterior,
                predicted=predicted,
                diagnostics=diagnostics,
                diagnostic_scores=diag.scores,
                evidence=diag.evidence,
                notes=shown.notes,
                contact_tool=contact,
                contact_text=contact_text(tools, None if each is None else {k: each[k] for k in tools},
                                          None if self.model is None else self.model.threshold, contact, top,
                                          None if self.stream is None else self.stream.evidence),
            )
            t3 = time.perf_counter()
            rerun_log.log_frame(rec, result, view, self.instruments, self.check_lines)
            self._log_contact_evidence()
            self.depth_kind.log(rec, kind_ids)
            if self.videos is not None:
                self.videos.feed(frame.index, shown)
        if self.pose_of is not None:
            rerun_log.log_kinematic_tip(rec, _kinematic_tip(session, frame, self.pose_of, options, K))
        self.done += 1
        self.last_index = frame.index
        self.prepare_s += t3 - t2
        self.log_s += time.perf_counter() - t3

    def _log_contact_evidence(self) -> None:
        """The frame's evidence for contact per instrument (after its posterior was computed by ``_contact``; a bad
        frame: none, each line breaks)."""
        if self.evidence_lines is not None:
            self.evidence_lines.log(self.rec, self.stream.evidence)

    def log_series_only(self, result) -> None:
        """A frame shown only in the series (a follower catching up): its distances and posterior (the
        causal filter sees every frame), no images, layers or checks."""
        frame = result.frame
        rerun_log.set_frame_time(self.rec, frame.index, frame.timestamp_s)
        tools, posterior, predicted, each, _, _ = self._contact(result)
        rerun_log.log_series_only(self.rec, tools, posterior, predicted, each, self.instruments, self.video_entities)
        self._log_contact_evidence()
        self.depth_kind.log(self.rec, None)
        if self.videos is not None:  # a grey frame: the video must not show the frame before as this one
            self.videos.feed(frame.index, ShownImages(None, None, None, None, None, None, None, self.with_right, ()))
        self.last_index = frame.index

    def finish(self, indices_done, *, started: float, interrupted: bool = False, stop_signal: int = 0,
               wait_s: float = 0.0, image_wait_s: float = 0.0) -> RunSummary:
        """Encode what is queued, log the session checks over ``indices_done`` and summarise the run."""
        t5 = time.perf_counter()
        if self.videos is not None:
            self.videos.close()
        session_checks = self.tracker.finish(self.session, indices_done)
        if session_checks and self.last_index is not None:
            rerun_log.log_session_diagnostics(self.rec, session_checks,
                                              float(self.session.timestamps_s[self.last_index]))
        self.log_s += time.perf_counter() - t5
        return RunSummary(
            frames=self.done,
            bad_frames=self.bad,
            diagnostic_counts=dict(self.tracker.counts),
            diagnostic_ranges=self.tracker.ranges(),
            interrupted=interrupted,
            stop_signal=stop_signal,
            elapsed_s=time.perf_counter() - started,
            wait_s=wait_s,
            image_wait_s=image_wait_s,
            prepare_s=self.prepare_s,
            log_s=self.log_s,
            instrument_frames=dict(sorted(self.instrument_frames.items())),
            nearest_frames=dict(sorted(self.nearest_frames.items())),
            contact_frames=dict(sorted(self.contact_frames.items())),
            closest=self.closest,
            with_model=self.model is not None,
            frame_stems=tuple(self.session.stems),
            session_messages={d.code: d.message for d in session_checks},
        )
