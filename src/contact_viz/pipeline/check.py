"""`contact-viz check`: the debugger's diagnostics over whole sessions, without Rerun.

:func:`check_session` reads every frame (mask, whole depth map, grey left and right images),
computes each instrument's patch and measurements (:mod:`contact_viz.checks.frame`), spread over
``processes`` processes, then runs the checks in frame order (:class:`FrameChecker`, the same
object the viewer uses) and the session checks (force lag, frame times, and whether left and right
are rectified: :func:`rectification_offset`). The result is a
:class:`CheckReport`: which checks fired on which frame ranges, and with several instruments (object
ids) on which instrument too (the table gets a ``tool`` column, "-" for a check of the whole frame;
the JSON an ``instruments`` list and per check ``tools``). A session of one instrument (id 1, or a
binary mask) prints as before. Frames are named by their stems (the files' names in left/):
``000020-000022`` for a run of consecutive numbers (:func:`contact_viz.console.frames_text`); the JSON keeps
the frame indices (``ranges``) beside the stems (``stem_ranges``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from dataclasses import dataclass, field, replace

import numpy as np

from contact_viz import __version__
from contact_viz.checks.frame import FrameMeasures, ToolMeasures, analysis_step, measure_tools, shrink_grey
from contact_viz.checks.params import DiagnosticParams
from contact_viz.checks.rules import (CHECKS, SESSION_CHECKS, DepthSource, FrameChecker, PatchNumbers, fired_ranges,
                                     patch_place)
from contact_viz.checks.rectification import VerticalOffset, sample_frames, vertical_offset
from contact_viz.checks.session import ForceLag, force_lag, frame_time_problems
from contact_viz.console import frame_name, frames_text, stem_runs
from contact_viz.errors import SessionError
from contact_viz.io.decoders import JPEG_REDUCTIONS, read_jpeg_reduced
from contact_viz.io.session import JPEG_SUFFIXES, BadFrame, Session, open_session
from contact_viz.params import PatchParams

__all__ = ["CheckReport", "FrameRecord", "check_session", "grey_step", "load_grey", "measure_session_frame",
           "rectification_offset"]

CHUNK_FRAMES = 8  # frames a process claims at a time, frames


def grey_step(session: Session, params: DiagnosticParams) -> int:
    """The analysis step of the session's frames (:func:`contact_viz.checks.frame.analysis_step`)."""
    return analysis_step(session.image_size[1], params)


def load_grey(session: Session, side: str, index: int, step: int = 1, rgb: np.ndarray | None = None
              ) -> np.ndarray | None:
    """Frame ``index``'s ``side`` image as grey uint8 shrunk ``step`` times (rectified like the
    session), or None when the frame has no such image (the image checks are then skipped).
    Raises SessionError, naming the file, when the image cannot be read or has another size.

    JPEG files of unrectified sessions decode straight to the reduced size; other images are decoded
    (or taken from ``rgb``, the image already decoded and rectified by the caller) and go through
    :func:`contact_viz.checks.frame.shrink_grey`, so the viewer and `check` see the same pixels."""
    path = session.image_path(side, index)
    if path is None:
        return None
    if session.rectification is None and path.suffix.lower() in JPEG_SUFFIXES and step in JPEG_REDUCTIONS:
        return read_jpeg_reduced(path, step, session.image_size, side, grey=True)
    height, width = session.image_size
    if rgb is None:
        frame = session.load_frame(index, layers=(side,))
        if isinstance(frame, BadFrame):
            raise frame.error
        rgb = frame.left_rgb if side == "left" else frame.right_rgb
    if rgb.shape[:2] != (height, width):
        raise SessionError(path, f"expected a {side} image of {height}x{width} px (height x width), "
                                 f"found {rgb.shape[0]}x{rgb.shape[1]}")
    return shrink_grey(rgb, step)


def rectification_offset(session: Session, params: DiagnosticParams = DiagnosticParams(),
                         indices=None) -> VerticalOffset | None:
    """The vertical offset between the left and right images of ``params.rectification_frames`` frames evenly
    spaced over ``indices`` (default: every frame), read as the checks read them (rectified like the session)
    and shrunk to at most ``params.rectification_width_px`` wide (:mod:`contact_viz.checks.rectification`).
    None without right images, or with too few features matched; a frame whose image cannot be read is left
    out (its own check reports it)."""
    if not session.has_right:
        return None
    height, width = session.image_size
    step = max(1, -(-width // params.rectification_width_px))
    pairs = []
    for index in sample_frames(range(len(session)) if indices is None else indices, params.rectification_frames):
        (left, _), (right, _) = (_grey_or_problem(session, side, index, step) for side in ("left", "right"))
        if left is not None and right is not None:
            pairs.append((index, left, right))
    if not pairs:
        return None
    return vertical_offset(pairs, params, scale_px=height / pairs[0][1].shape[0])


def _grey_or_problem(session: Session, side: str, index: int, step: int) -> tuple[np.ndarray | None, str | None]:
    try:
        return load_grey(session, side, index, step), None
    except SessionError as exc:
        return None, str(exc)


@dataclass(frozen=True)
class FrameRecord:
    """One frame as the checks see it: its measurements and patch numbers, or why it could not be read."""

    index: int
    measures: ToolMeasures | FrameMeasures | None  # every instrument's (measure_tools); None = bad frame
    patch: Mapping[int, PatchNumbers] | PatchNumbers | None  # {object id: its patch numbers}
    signal: float  # -log10(max(|d|, eps)) of the instrument nearest the tissue, NaN = no patch
    bad_reason: str | None = None
    image_problem: str | None = None  # an image that could not be read (its checks skipped), naming the file


def measure_session_frame(session: Session, index: int, patch_params: PatchParams, params: DiagnosticParams,
                          evidence: bool = False) -> FrameRecord:
    """Read frame ``index`` of ``session`` and measure it (every instrument's patch and measurements)."""
    from contact_viz.pipeline.extract import session_frame_patches

    frame = session.load_frame(index, layers=("mask", "depth"))
    if isinstance(frame, BadFrame):
        return FrameRecord(index, None, None, math.nan, frame.reason)
    step = grey_step(session, params)
    (left, left_problem), (right, right_problem) = (_grey_or_problem(session, side, index, step)
                                                    for side in ("left", "right"))
    patch, patches = session_frame_patches(session, frame, patch_params)
    record = measure_loaded_frame(session, frame, patch, left, right, params, evidence, tool_patches=patches)
    problem = left_problem or right_problem
    return record if problem is None else replace(record, image_problem=problem)


def patch_numbers(patch, params: DiagnosticParams = DiagnosticParams()) -> PatchNumbers:
    """What the checks use of a :class:`contact_viz.geometry.patch.PatchResult`."""
    place = None if patch.center_xy is None or not params.patch_place else patch_place(
        patch.band_yx[:, ::-1], patch.band_score_m, float(patch.score_m))
    return PatchNumbers(float(patch.distance_m), None if patch.center_xy is None else
                        (float(patch.center_xy[0]), float(patch.center_xy[1])), patch.reason, place)


def measure_frame_tools(frame, tool_patches, left_grey, right_grey, fx_px: float, baseline_m: float,
                        params: DiagnosticParams, evidence: bool = False) -> ToolMeasures:
    """The checks' measurements of every instrument of a decoded frame (:func:`measure_tools`): those with a
    patch in ``tool_patches`` ({object id: PatchResult}; None: every instrument of ``frame.tool_mask``)."""
    ids = frame.tool_ids if frame.tool_ids is not None else frame.tool_mask
    selected = None if tool_patches is None else tuple(tool_patches)
    return measure_tools(ids, frame.depth_m, left_grey, right_grey, fx_px, baseline_m, params, selected=selected,
                         evidence=evidence)


def measure_loaded_frame(session: Session, frame, patch, left_grey, right_grey, params: DiagnosticParams,
                         evidence: bool = False, *, tool_patches=None) -> FrameRecord:
    """The :class:`FrameRecord` of a decoded frame, its patch(es) and its grey images (as load_grey reads
    them). ``tool_patches``: {object id: PatchResult} of every instrument (pipeline.extract.frame_patches);
    None: ``patch`` is the only instrument's (id 1)."""
    K = session.calibration.K
    if tool_patches is None:
        tool_patches = {1: patch} if frame.tool_mask is not None and frame.tool_mask.any() else {}
    measures = measure_frame_tools(frame, tool_patches, left_grey, right_grey, float(K[0][0]),
                                   float(session.calibration.baseline_m), params, evidence)
    numbers = {k: patch_numbers(p, params) for k, p in tool_patches.items()}
    return FrameRecord(frame.index, measures, numbers, float(patch.signal))


@dataclass(frozen=True)
class _MeasureTask:
    """Frame records of positions lo..hi-1 (a contact_viz.pipeline.parallel.ChunkTask)."""

    session: Session
    patch_params: PatchParams
    params: DiagnosticParams

    def __call__(self, lo: int, hi: int) -> list[FrameRecord]:
        return [measure_session_frame(self.session, i, self.patch_params, self.params) for i in range(lo, hi)]


@dataclass
class CheckReport:
    """What `contact-viz check` found in one session."""

    session: str  # session name
    path: str  # session directory
    n_frames: int  # frames in the session
    fired: dict[str, list[tuple[int, int]]]  # check code -> (first_frame, last_frame) ranges it fired on
    counts: dict[str, int]  # check code -> frames it fired on
    force_lag: ForceLag | None  # the force-to-signal lag estimate (None = no force)
    params: DiagnosticParams
    elapsed_s: float  # wall time, s
    messages: dict[str, str] = field(default_factory=dict)  # check code -> first message (with the likely cause)
    # frames with an image that could not be read (their image checks skipped), and the first one's message
    unreadable_images: tuple[list[int], str] | None = None
    # frame check code -> likely cause -> frames it fired on naming that cause (most frames first); a check can
    # name another cause than its usual one (depth_holes: "no depth beside the tool: stereo failed here")
    causes: dict[str, dict[str, int]] = field(default_factory=dict)
    # the instruments (object ids) the checks saw; with several (or one other than 1) the frame checks are
    # also reported per instrument: check code -> object id -> (first, last) frame ranges it fired on
    instruments: tuple[int, ...] = ()
    tool_fired: dict[str, dict[int, list[tuple[int, int]]]] = field(default_factory=dict)
    stems: tuple[str, ...] = ()  # the session's frame stems (frame index -> stem); () = name frames by index
    rectification: VerticalOffset | None = None  # left against right (not_rectified); None = not measured

    @property
    def several(self) -> bool:
        """The session has several instruments, or one other than id 1: reported per instrument."""
        return several_instruments(self.instruments)

    def likely_causes(self, code: str) -> list[str]:
        """The likely causes check ``code`` named in this session, most frames first (its usual one if it
        named none)."""
        named = list(self.causes.get(code, {}))
        return named or [(CHECKS.get(code) or SESSION_CHECKS[code])[1]]

    @property
    def flagged_frames(self) -> int:
        """Frames on which any check fired."""
        frames = set()
        for ranges in self.fired.values():
            for a, b in ranges:
                frames.update(range(a, b + 1))
        return len(frames)

    def frames_text(self, ranges: list[tuple[int, int]], max_runs: int) -> str:
        """(first, last) frame index ranges as stems: ``000020-000022, 000024`` (console.frames_text)."""
        return frames_text(ranges, self.stems, max_runs)

    def _stem_ranges(self, ranges) -> list[list[str]]:
        return [list(run) for run in stem_runs(ranges, self.stems)]

    def to_dict(self) -> dict:
        rect = self.rectification
        lag = None if self.force_lag is None else {
            "lag_frames": self.force_lag.lag_frames, "lag_s": round(self.force_lag.lag_s, 4),
            "correlation": round(self.force_lag.correlation, 4),
            "zero_lag_correlation": None if math.isnan(self.force_lag.zero_lag_correlation)
            else round(self.force_lag.zero_lag_correlation, 4),
            "fired": self.force_lag.fired}
        return {
            "session": self.session, "path": self.path, "n_frames": self.n_frames,
            "flagged_frames": self.flagged_frames,
            "checks": {code: {"frames": self.counts.get(code, 0), "ranges": [list(r) for r in self.fired.get(code, [])],
                              "stem_ranges": self._stem_ranges(self.fired.get(code, [])),
                              "measures": (CHECKS.get(code) or SESSION_CHECKS[code])[0],
                              "likely_cause": self.likely_causes(code)[0],
                              **({"causes": self.causes[code]} if len(self.causes.get(code, {})) > 1 else {}),
                              **({"first_message": self.messages[code]} if code in self.messages else {}),
                              **({"tools": {str(k): {"frames": sum(b - a + 1 for a, b in r),
                                                     "ranges": [list(x) for x in r],
                                                     "stem_ranges": self._stem_ranges(r)}
                                            for k, r in self.tool_fired[code].items()}}
                                 if self.several and code in self.tool_fired else {})}
                       for code in (*CHECKS, *SESSION_CHECKS)},
            **({"instruments": list(self.instruments)} if self.several else {}),
            "force_lag": lag,
            "rectification": None if rect is None else {
                "vertical_offset_px": round(rect.offset_px, 3), "matches": rect.matches,
                "frames": [frame_name(i, self.stems) for i in rect.frames],
                "frame_offsets_px": [None if math.isnan(v) else round(v, 3) for v in rect.frame_offsets_px],
                "fired": rect.fired},
            "unreadable_images": None if self.unreadable_images is None else {
                "frames": len(self.unreadable_images[0]),
                "ranges": [list(r) for r in fired_ranges(self.unreadable_images[0])],
                "stem_ranges": self._stem_ranges(fired_ranges(self.unreadable_images[0])),
                "first_message": self.unreadable_images[1]},
            "params": self.params.to_dict(),
            "contact_viz_version": __version__,
            "elapsed_s": round(self.elapsed_s, 3),
        }


def check_session(session_dir, *, params: DiagnosticParams | None = None, cache_dir=None, processes: int = 1,
                  patch_params: PatchParams | None = None,
                  object_ids: Sequence[int] | None = None) -> CheckReport:
    """Run every check on the session at ``session_dir``; see :class:`CheckReport`.

    ``cache_dir``: where SGBM depth is cached for sessions without depth (as everywhere).
    ``processes`` counts this one (1 = no worker process). Raises SessionError on a session-wide
    problem; an unreadable frame is a ``bad_frame`` and the run goes on.
    """
    from contact_viz.pipeline.parallel import run_chunks

    started = time.perf_counter()
    params = params or DiagnosticParams()
    patch_params = patch_params or PatchParams()
    session = open_session(session_dir, cache_dir=cache_dir, object_ids=object_ids)
    task = _MeasureTask(session, patch_params, params)
    n = len(session)
    if processes == 1:
        records = task(0, n)
    else:
        records = run_chunks(task, n, chunk_size=CHUNK_FRAMES, processes=processes)
    instruments = record_instruments(records)
    stems = tuple(session.stems)
    frames, causes, by_tool = fired_frames(records, params, session.image_size[1], session.depth_source,
                                           several=several_instruments(instruments), stems=stems)
    signal = np.array([r.signal for r in records], dtype=np.float64)
    suspect = np.zeros(n, bool)
    for idx, _ in frames.values():
        suspect[idx] = True
    lag = force_lag(session.force_n, signal, session.timestamps_s, params, suspect=suspect)
    if lag is not None and lag.fired:
        frames["force_lag"] = (list(range(n)), f"force lags the signal by {lag.lag_frames} frames "
                                               f"({lag.lag_s:+.3f} s; correlation {lag.correlation:.2f} vs "
                                               f"{lag.zero_lag_correlation:.2f} at 0)")
    gaps = frame_time_problems(session.timestamps_s, params)
    if gaps:
        frames["frame_times"] = (gaps, f"{len(gaps)} frame(s) with a time step <= 0 or a gap, first at frame "
                                       f"{frame_name(gaps[0], stems)}")
    rectification = rectification_offset(session, params)
    if rectification is not None and rectification.fired:
        frames["not_rectified"] = (list(range(n)), rectification.message())
    return CheckReport(
        session=session.name, path=str(session.root), n_frames=n,
        fired={code: fired_ranges(idx) for code, (idx, _) in frames.items()},
        counts={code: len(idx) for code, (idx, _) in frames.items()},
        force_lag=lag, params=params, elapsed_s=time.perf_counter() - started,
        messages={code: msg for code, (_, msg) in frames.items()},
        unreadable_images=_unreadable_images(records, stems),
        causes=causes,
        instruments=instruments,
        tool_fired={code: {k: fired_ranges(idx) for k, idx in sorted(tools.items())}
                    for code, tools in by_tool.items()},
        stems=stems,
        rectification=rectification,
    )


def several_instruments(instruments: Sequence[int]) -> bool:
    """Whether a session with these instruments (object ids) is reported per instrument: several, or one
    that is not id 1 (a binary mask reads as id 1)."""
    return len(instruments) > 1 or any(k != 1 for k in instruments)


def record_instruments(records: list[FrameRecord]) -> tuple[int, ...]:
    """The object ids measured with mask pixels in any of ``records``, ascending."""
    ids: set[int] = set()
    for r in records:
        if isinstance(r.measures, ToolMeasures):
            ids.update(k for k, m in r.measures.tools.items() if m.tool_area_px > 0)
        elif r.measures is not None and r.measures.tool_area_px > 0:
            ids.add(1)
    return tuple(sorted(ids))


def _unreadable_images(records: list[FrameRecord], stems: tuple[str, ...] = ()) -> tuple[list[int], str] | None:
    """The frames with an unreadable image and the first one's message (CheckReport.unreadable_images)."""
    bad = [r for r in records if r.image_problem]
    return None if not bad else ([r.index for r in bad],
                                 f"frame {frame_name(bad[0].index, stems)}: {bad[0].image_problem}")


def fired_frames(records: list[FrameRecord], params: DiagnosticParams, image_width: int,
                 depth_source: DepthSource = "depth", several: bool | None = None, stems: tuple[str, ...] = ()
                 ) -> tuple[dict, dict[str, dict[str, int]], dict[str, dict[int, list[int]]]]:
    """Run the frame checks over ``records`` in order: (code -> (frame indices, first message),
    code -> likely cause -> frames, most frames first, code -> object id -> frame indices).
    ``depth_source``: the session's (``Session.depth_source``), for the wording of the causes;
    ``several``: the messages name the instrument (FrameChecker); ``stems``: the messages name frames by them."""
    checker = FrameChecker(params, image_width, depth_source, several=several, stems=stems)
    out: dict[str, tuple[list[int], str]] = {}
    causes: dict[str, dict[str, int]] = {}
    by_tool: dict[str, dict[int, list[int]]] = {}
    for record in records:
        if record.measures is None:
            out.setdefault("bad_frame", ([], f"frame {frame_name(record.index, stems)}: {record.bad_reason}")
                           )[0].append(record.index)
            checker.reset_previous()
            continue
        fired, _ = checker.check(record.index, record.measures, record.patch)
        for diagnostic in fired:
            frames = out.setdefault(diagnostic.code, ([], f"frame {frame_name(diagnostic.index, stems)}: "
                                                          f"{diagnostic.message}"))[0]
            if not frames or frames[-1] != diagnostic.index:  # several instruments: a frame counts once
                frames.append(diagnostic.index)
                named = causes.setdefault(diagnostic.code, {})
                named[diagnostic.likely_cause] = named.get(diagnostic.likely_cause, 0) + 1
            if diagnostic.tool is not None:
                tool_frames = by_tool.setdefault(diagnostic.code, {}).setdefault(diagnostic.tool, [])
                if not tool_frames or tool_frames[-1] != diagnostic.index:
                    tool_frames.append(diagnostic.index)
    return (out, {code: dict(sorted(named.items(), key=lambda kv: -kv[1])) for code, named in causes.items()},
            by_tool)


def report_table(report: CheckReport, max_ranges: int = 6) -> list[str]:
    """The per-session table `contact-viz check` prints: one line per check that fired (its frames by stem), and
    the line of a pair that is not rectified."""
    name = report.session if Path(report.path).name == report.session else f"{report.session} ({report.path})"
    head = (f"{name}: {report.n_frames} frames, {report.flagged_frames} flagged "
            f"({report.elapsed_s:.1f} s)")
    if report.several:
        head += f"; instruments {', '.join(str(k) for k in report.instruments)}"
    lines = [head]
    if report.unreadable_images is not None:
        frames, first = report.unreadable_images
        lines.append(f"  warning: {len(frames)} frame(s) with an unreadable image, their image checks skipped; {first}")
    fired = [c for c in (*CHECKS, *SESSION_CHECKS) if report.counts.get(c)]
    if not fired:
        lines.append("  no check fired")
        return lines
    width = max(len(c) for c in fired)
    if report.several:
        lines += _tool_table(report, fired, width, max_ranges)
    else:
        texts = {code: _ranges_text(report, code, report.fired[code], max_ranges) for code in fired}
        column = max(30, *(len(t) for t in texts.values()))
        lines.append(f"  {'check':{width}s}  frames  {'ranges':{column}s}  likely cause")
        for code in fired:
            lines.append(f"  {code:{width}s}  {report.counts[code]:6d}  {texts[code]:{column}s}  {_cause(report, code)}")
    if "not_rectified" in fired:
        lines.append(f"  {report.messages['not_rectified']}")
    return lines


def _cause(report: CheckReport, code: str) -> str:
    named = report.likely_causes(code)
    return named[0] if len(named) == 1 else "; ".join(f"{c} ({report.causes[code][c]} frame(s))" for c in named)


def _ranges_text(report: CheckReport, code: str, ranges: list[tuple[int, int]], max_ranges: int) -> str:
    """The ranges column: the frames by stem, or for a check of the whole session what it measured."""
    if code == "force_lag" and report.force_lag is not None:
        return f"all ({report.force_lag.lag_frames:+d} frames, {report.force_lag.lag_s:+.3f} s)"
    if code == "not_rectified" and report.rectification is not None:
        return f"all ({abs(report.rectification.offset_px):.1f} px vertical offset)"
    return report.frames_text(ranges, max_ranges)


def _tool_table(report: CheckReport, fired: list[str], width: int, max_ranges: int) -> list[str]:
    """report_table's rows for a session of several instruments: one per check and instrument it fired on
    (tool "-": a check of the whole frame or session)."""
    rows = []  # (code, tool, frames, ranges text)
    for code in fired:
        per_tool = report.tool_fired.get(code)
        if not per_tool:
            rows.append((code, "-", report.counts[code], _ranges_text(report, code, report.fired[code], max_ranges)))
        for tool, ranges in (per_tool or {}).items():
            rows.append((code, str(tool), sum(b - a + 1 for a, b in ranges),
                         _ranges_text(report, code, ranges, max_ranges)))
    column = max(30, *(len(row[3]) for row in rows))
    lines = [f"  {'check':{width}s}  tool  frames  {'ranges':{column}s}  likely cause"]
    for code, tool, frames, text in rows:
        lines.append(f"  {code:{width}s}  {tool:>4s}  {frames:6d}  {text:{column}s}  {_cause(report, code)}")
    return lines


def run_check(session_dirs, *, params: DiagnosticParams | None = None, cache_dir=None, processes: int = 1,
              json_path=None, on_report=None, on_error=None,
              object_ids: Sequence[int] | None = None) -> tuple[list[CheckReport], list[str]]:
    """`contact-viz check`: :func:`check_session` on each of ``session_dirs`` in turn (``object_ids``: only those
    instruments).

    ``on_report(report)`` / ``on_error(message)`` are called as each session finishes (the CLI prints
    there). A session that cannot be opened is an error line naming it; the others go on. With
    ``json_path`` the reports (``{"sessions": [report.to_dict(), ...], "errors": [...]}``) are written
    there atomically at the end. Returns (reports, errors).
    """
    from contact_viz.io.jsonfile import write_json

    reports: list[CheckReport] = []
    errors: list[str] = []
    for session_dir in session_dirs:
        try:
            report = check_session(session_dir, params=params, cache_dir=cache_dir, processes=processes,
                                   object_ids=object_ids)
        except (SessionError, ValueError) as exc:
            errors.append(str(exc))
            if on_error is not None:
                on_error(str(exc))
            continue
        reports.append(report)
        if on_report is not None:
            on_report(report)
    if json_path is not None:
        write_json(json_path, {"sessions": [r.to_dict() for r in reports], "errors": errors,
                               "contact_viz_version": __version__})
    return reports, errors
