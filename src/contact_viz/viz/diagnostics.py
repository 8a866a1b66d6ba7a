"""Per-frame sanity checks on the stream of patch results, for the viewer and its end-of-run summary.

Each check has a code (the keys of :data:`DIAGNOSTIC_CODES`):

* ``bad_frame``: the frame's files could not be read (the session reader's BadFrame).
* ``no_tool``: the tool mask has fewer than ``min_tool_area_px`` pixels.
* ``mask_area_jump``: the tool mask area changed by more than ``mask_area_jump`` (relative) since
  the previous readable frame: |A_t - A_prev| / max(A_t, A_prev); checked when both are nonzero.
* ``invalid_depth``: more than ``max_invalid_depth_fraction`` of the exterior band has invalid depth.
* ``no_patch``: the tool is there (nonempty mask) but no patch was found (PatchResult.reason set).
* ``distance_jump``: |d_t - d_prev| > ``distance_jump_m`` against the previous readable frame,
  when both have a distance.

"Previous" means the previous frame that was processed and readable (bad frames are skipped, so a
jump across a bad frame is still caught). Pure Python over the results; no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from contact_viz.geometry.patch import REASON_EMPTY_MASK
from contact_viz.params import check_fields, checked

__all__ = ["DIAGNOSTIC_CODES", "Diagnostic", "DiagnosticParams", "DiagnosticsTracker"]

DIAGNOSTIC_CODES: dict[str, str] = {
    "bad_frame": "frame files could not be read",
    "no_tool": "no tool in the mask",
    "mask_area_jump": "tool mask area jumped",
    "invalid_depth": "much invalid depth in the exterior band",
    "no_patch": "no valid patch",
    "distance_jump": "distance jumped",
}


@dataclass(frozen=True)
class DiagnosticParams:
    """Thresholds of the per-frame checks."""

    min_tool_area_px: int = checked(1, ge=1)  # fewer tool-mask pixels than this = no tool, px
    # relative mask-area change that fires, |dA| / max(A_t, A_prev), fraction in (0, 1]
    mask_area_jump: float = checked(0.5, gt=0, le=1)
    # share of band pixels with invalid depth above which it fires, 0-1
    max_invalid_depth_fraction: float = checked(0.5, ge=0, lt=1)
    distance_jump_m: float = checked(0.005, gt=0)  # change of the patch distance between frames that fires, m

    def __post_init__(self) -> None:
        check_fields(self)


@dataclass(frozen=True)
class Diagnostic:
    """One check that fired at one frame."""

    code: str  # key of DIAGNOSTIC_CODES
    index: int  # frame index in the session
    message: str  # one line for a log, with the measured value and the threshold
    value: float  # the measured quantity (units as in the message; NaN for bad_frame / no_patch)


class DiagnosticsTracker:
    """Runs the checks frame by frame and counts how often each fired.

    ``update(frame_result)`` takes a :class:`contact_viz.pipeline.extract.FrameResult` (or anything with
    ``frame`` and ``patch``; ``patch`` None = bad frame). ``counts`` maps every code to the number
    of frames it fired on; ``frames`` is the number of frames seen.
    """

    def __init__(self, params: DiagnosticParams = DiagnosticParams()) -> None:
        self.params = params
        self.counts: dict[str, int] = dict.fromkeys(DIAGNOSTIC_CODES, 0)
        self.frames = 0
        self._prev_area: int | None = None
        self._prev_distance_m = math.nan

    def update(self, frame_result) -> list[Diagnostic]:
        """The checks that fire at this frame (in DIAGNOSTIC_CODES order); updates the counts."""
        frame, patch = frame_result.frame, frame_result.patch
        if patch is None:
            fired = [Diagnostic("bad_frame", frame.index, f"frame {frame.stem}: {frame.reason}", math.nan)]
        else:
            area = int(np.count_nonzero(frame.tool_mask))
            fired = self.check(frame.index, area, patch.distance_m, patch.invalid_depth_fraction, patch.reason)
        self.frames += 1
        for diagnostic in fired:
            self.counts[diagnostic.code] += 1
        return fired

    def check(
        self, index: int, tool_area_px: int, distance_m: float, invalid_depth_fraction: float, reason: str | None
    ) -> list[Diagnostic]:
        """The checks of one readable frame from its numbers; advances the previous-frame state.

        Does not touch ``counts`` / ``frames`` (``update`` does).
        """
        p = self.params
        fired: list[Diagnostic] = []
        if tool_area_px < p.min_tool_area_px:
            fired.append(Diagnostic("no_tool", index, f"tool mask has {tool_area_px} px "
                                    f"(< {p.min_tool_area_px} px)", float(tool_area_px)))
        prev_area = self._prev_area
        if prev_area and tool_area_px:
            change = abs(tool_area_px - prev_area) / max(tool_area_px, prev_area)
            if change > p.mask_area_jump:
                fired.append(Diagnostic("mask_area_jump", index, f"tool mask area {prev_area} -> {tool_area_px} px "
                                        f"(change {change:.0%} > {p.mask_area_jump:.0%})", change))
        if math.isfinite(invalid_depth_fraction) and invalid_depth_fraction > p.max_invalid_depth_fraction:
            fired.append(Diagnostic("invalid_depth", index, f"{invalid_depth_fraction:.0%} of the exterior band has "
                                    f"invalid depth (> {p.max_invalid_depth_fraction:.0%})", invalid_depth_fraction))
        if reason is not None and reason != REASON_EMPTY_MASK:
            fired.append(Diagnostic("no_patch", index, f"no valid patch ({reason})", math.nan))
        prev_d = self._prev_distance_m
        if math.isfinite(distance_m) and math.isfinite(prev_d) and abs(distance_m - prev_d) > p.distance_jump_m:
            jump = abs(distance_m - prev_d)
            fired.append(Diagnostic("distance_jump", index, f"distance {1000 * prev_d:.1f} -> "
                                    f"{1000 * distance_m:.1f} mm (jump {1000 * jump:.1f} mm > "
                                    f"{1000 * p.distance_jump_m:.1f} mm)", jump))
        self._prev_area = tool_area_px
        self._prev_distance_m = float(distance_m)
        return fired
