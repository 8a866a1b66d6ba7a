"""The viewer's diagnostics: the checks of contact_viz.checks run frame by frame on the stream of results.

Each check has a code (the keys of :data:`DIAGNOSTIC_CODES`, documented in docs/diagnostics.md):
mask checks (``mask_dropout``, ``extra_blob``, ``mask_area_jump``, ``mask_image_edges``), depth-
against-mask checks (``mask_on_tissue``, ``tool_depth_outside``, ``depth_holes``), scale and
stereo checks (``tool_width``, ``stereo_residual``), ``frozen_depth``, and the patch's own
(``bad_frame``, ``no_patch``, ``distance_jump``); with several instruments each is checked on its own
(its messages start "tool <id>: ") and against the others (``id_swap``, ``tools_merged``). Session
checks (``force_lag``, ``frame_times``, ``not_rectified``: the vertical offset between left and right,
measured on frames sampled from those shown) run once at the end (:meth:`DiagnosticsTracker.finish`) and
are logged at the last frame shown. The same :class:`FrameChecker` and measurements serve
``contact-viz check``, so the viewer and the command flag the same frames.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from contact_viz.checks.frame import FrameEvidence
from contact_viz.checks.params import DiagnosticParams
from contact_viz.checks.rules import CHECKS, SESSION_CHECKS, DepthSource, Diagnostic, FrameChecker, fired_ranges
from contact_viz.checks.session import force_lag, frame_time_problems

__all__ = ["DIAGNOSTIC_CODES", "SESSION_DIAGNOSTIC_CODES", "Diagnostic", "DiagnosticParams", "DiagnosticsTracker",
           "FrameDiagnostics"]

DIAGNOSTIC_CODES: dict[str, str] = {code: what for code, (what, _) in CHECKS.items()}
SESSION_DIAGNOSTIC_CODES: dict[str, str] = {code: what for code, (what, _) in SESSION_CHECKS.items()}


@dataclass(frozen=True)
class FrameDiagnostics:
    """The checks of one frame: those that fired, every check's score (value / threshold, > 1 fires), evidence."""

    fired: list[Diagnostic]
    scores: dict[str, float]
    evidence: FrameEvidence | None


class DiagnosticsTracker:
    """Runs the checks frame by frame and keeps the frames each fired on.

    ``update(frame_result, left_grey, right_grey)`` takes a
    :class:`contact_viz.pipeline.extract.FrameResult` (``patch`` None = bad frame) and the frame's
    grey images shrunk for the checks (:func:`contact_viz.pipeline.check.load_grey`), or None.
    ``counts`` maps every code to the number of frames it fired on; ``ranges()`` gives (first, last)
    frame runs; ``frames`` is the number of frames seen. ``depth_source``: the session's
    (``Session.depth_source``), for the wording of a cause (no depth beside the tool: stereo failed).
    """

    def __init__(self, params: DiagnosticParams = DiagnosticParams(), *, fx_px: float = math.nan,
                 baseline_m: float = math.nan, image_width: int = 1920, depth_source: DepthSource = "depth",
                 stems: Sequence[str] = ()) -> None:
        self.params = params
        self.fx_px = fx_px
        self.baseline_m = baseline_m
        self.checker = FrameChecker(params, image_width, depth_source, stems=stems)
        self.counts: dict[str, int] = dict.fromkeys({**DIAGNOSTIC_CODES, **SESSION_DIAGNOSTIC_CODES}, 0)
        self.fired_frames: dict[str, list[int]] = {}
        self.frames = 0
        self._signal: dict[int, float] = {}

    def update(self, frame_result, left_grey=None, right_grey=None, *, evidence: bool = False) -> FrameDiagnostics:
        frame, patch = frame_result.frame, frame_result.patch
        if patch is None:
            fired = [Diagnostic("bad_frame", frame.index, f"frame {frame.stem}: {frame.reason}", math.nan)]
            scores, ev = {}, None
            self.checker.reset_previous()
        else:
            from contact_viz.pipeline.check import measure_frame_tools, patch_numbers

            tool_patches = frame_result.tool_patches
            if tool_patches is None:  # a FrameResult of one tool
                tool_patches = {1: patch} if frame.tool_mask is not None and frame.tool_mask.any() else {}
            measures = measure_frame_tools(frame, tool_patches, left_grey, right_grey, self.fx_px, self.baseline_m,
                                           self.params, evidence)
            numbers = {k: patch_numbers(p, self.params) for k, p in tool_patches.items()}
            fired, scores = self.checker.check(frame.index, measures, numbers)
            ev = measures.evidence
            self._signal[frame.index] = float(patch.signal)
        self.frames += 1
        for diagnostic in fired:
            frames = self.fired_frames.setdefault(diagnostic.code, [])
            if not frames or frames[-1] != diagnostic.index:  # several instruments: a frame counts once
                self.counts[diagnostic.code] += 1
                frames.append(diagnostic.index)
        return FrameDiagnostics(fired, scores, ev)

    def finish(self, session, indices) -> list[Diagnostic]:
        """The session checks over the frames seen (force lag needs force; frame times; left and right
        rectified, which needs right images), at the last frame."""
        from contact_viz.console import frame_name
        from contact_viz.pipeline.check import rectification_offset

        out: list[Diagnostic] = []
        idx = np.asarray(list(indices), dtype=np.int64)
        if idx.size == 0:
            return out
        last = int(idx[-1])
        signal = np.array([self._signal.get(int(i), math.nan) for i in idx], dtype=np.float64)
        times = np.asarray(session.timestamps_s, dtype=np.float64)[idx]
        position = {int(i): k for k, i in enumerate(idx)}
        suspect = np.zeros(idx.size, bool)
        for frames in self.fired_frames.values():
            suspect[[position[i] for i in frames if i in position]] = True
        lag = force_lag(np.asarray(session.force_n, dtype=np.float64)[idx], signal, times, self.params,
                        suspect=suspect)
        if lag is not None and lag.fired:
            out.append(Diagnostic("force_lag", last, f"force lags the distance signal by {lag.lag_frames:+d} frames "
                                                     f"({lag.lag_s:+.3f} s; correlation {lag.correlation:.2f}, "
                                                     f"{lag.zero_lag_correlation:.2f} at lag 0): "
                                                     f"{SESSION_CHECKS['force_lag'][1]}", lag.lag_s))
            self.fired_frames["force_lag"] = [int(i) for i in idx]
        gaps = frame_time_problems(times, self.params)
        if gaps:
            first = frame_name(int(idx[gaps[0]]), session.stems)
            out.append(Diagnostic("frame_times", last, f"{len(gaps)} frame(s) with a time step <= 0 or a gap, first at "
                                                       f"frame {first}: {SESSION_CHECKS['frame_times'][1]}",
                                  float(len(gaps))))
            self.fired_frames["frame_times"] = [int(idx[g]) for g in gaps]
        offset = rectification_offset(session, self.params, [int(i) for i in idx])
        if offset is not None and offset.fired:
            out.append(Diagnostic("not_rectified", last, f"{offset.message()}: {SESSION_CHECKS['not_rectified'][1]}",
                                  offset.offset_px))
            self.fired_frames["not_rectified"] = [int(i) for i in idx]
        for diagnostic in out:
            self.counts[diagnostic.code] = len(self.fired_frames[diagnostic.code])
        return out

    def ranges(self) -> dict[str, list[tuple[int, int]]]:
        """Check code -> (first, last) frame runs it fired on (only codes that fired)."""
        return {code: fired_ranges(frames) for code, frames in self.fired_frames.items() if frames}
