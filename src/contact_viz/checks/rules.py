"""The checks: each compares one measured quantity with its threshold and names the likely cause.

:class:`FrameChecker` runs the per-frame checks causally, frame after frame (it keeps what it
needs of the previous frames), on :class:`~contact_viz.checks.frame.FrameMeasures` and the
frame's patch numbers. Every check also has a *score* = measured value / threshold, oriented so
that > 1 means "fires" (the viewer plots the scores on one axis). Session checks (force lag,
frame times) are in :mod:`contact_viz.checks.session`. Pure Python; no I/O.

Where the depth beside the tool is missing (``beside_valid_fraction`` below
``min_beside_valid_fraction``), ``depth_holes`` fires naming the depth source, not the mask
(:func:`no_depth_beside_cause`: "no depth beside the tool: stereo failed here" for SGBM depth), and
the depth-against-mask checks (``mask_on_tissue``, ``tool_depth_outside``) are skipped: their
shares would rest on the few pixels with depth (``inside_far_fraction`` is not measured either where
the rim's depth is mostly invalid).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np

from contact_viz.checks.frame import FrameMeasures
from contact_viz.checks.params import DiagnosticParams

ENTERING_FRAMES = 5  # a tool's first frames in view (at the border) do not raise no_patch, frames

__all__ = ["CHECKS", "Diagnostic", "DepthSource", "FrameChecker", "PatchNumbers", "SESSION_CHECKS", "fired_ranges",
           "no_depth_beside_cause"]

DepthSource = Literal["depth", "disparity", "sgbm"]  # where a session's depth comes from (io.session.DEPTH_SOURCES)

# code -> (what it measures, likely cause); in the order the viewer stacks them.
CHECKS: dict[str, tuple[str, str]] = {
    "bad_frame": ("frame files could not be read", "a missing or corrupt mask / depth file"),
    "mask_dropout": ("empty tool mask while the tool was in view", "mask dropout (segmenter lost the tool)"),
    "extra_blob": ("extra mask blob away from the tool", "a second object or identity switch in the mask"),
    "mask_area_jump": ("tool mask area jumped (away from the border)", "mask dropout, bleed or identity switch"),
    "mask_image_edges": ("mask edge does not follow an image edge", "mask drift or bleed?"),
    "mask_on_tissue": ("mask rim has depth behind the tool", "mask bleed or drift onto tissue, or depth misregistered"),
    "tool_depth_outside": ("tool depth outside the mask", "depth edge bleeding (flying pixels), or depth "
                                                          "misregistered / mask drift"),
    "depth_holes": ("much invalid depth on and around the tool", "depth holes (specular metal, occlusion)"),
    "tool_width": ("tool's physical width differs from --tool-diameter-mm", "depth scale error (baseline, focal "
                                                                            "length, disparity read as depth) or "
                                                                            "wrong --tool-diameter-mm"),
    "stereo_residual": ("depth does not explain the stereo pair near the tool", "depth scale error, misregistered, "
                                                                                "frozen or bled depth"),
    "frozen_depth": ("depth identical to the previous frame while the image changed", "frozen depth (repeated map)"),
    "no_patch": ("tool present but no valid patch", "depth holes or a mask too thin for the patch"),
    "distance_jump": ("distance jumped while the patch stayed put", "a depth or mask failure at this frame"),
}
NO_DEPTH_BESIDE = "no depth beside the tool"  # depth_holes' cause where the depth beside the tool is missing


def no_depth_beside_cause(depth_source: str) -> str:
    """The likely cause when the depth beside the tool is missing, worded for where the depth came from:
    SGBM stereo (``"sgbm"``), or a depth or disparity file (a learned depth source)."""
    failed = "stereo" if depth_source == "sgbm" else "the depth source"
    return f"{NO_DEPTH_BESIDE}: {failed} failed here"


SESSION_CHECKS: dict[str, tuple[str, str]] = {
    "force_lag": ("force peaks lag the distance signal", "force and frames out of sync (time offset)"),
    "frame_times": ("frame times not increasing or with gaps", "dropped frames or a bad frames.csv"),
}


@dataclass(frozen=True)
class Diagnostic:
    """One check that fired at one frame."""

    code: str  # key of CHECKS
    index: int  # frame index in the session
    message: str  # one line for a log: what, the measured value against the threshold, the likely cause
    value: float  # the measured quantity (units as in the message; NaN when there is none)
    cause: str = ""  # the likely cause the message names; "" = the code's usual one (CHECKS / SESSION_CHECKS)

    @property
    def likely_cause(self) -> str:
        """The likely cause the message names."""
        return self.cause or (CHECKS.get(self.code) or SESSION_CHECKS[self.code])[1]


@dataclass(frozen=True)
class PatchNumbers:
    """What the checks use of a frame's patch (contact_viz.geometry.patch.PatchResult)."""

    distance_m: float  # patch distance, m (NaN = none)
    center_xy: tuple[float, float] | None  # patch centre, px
    reason: str | None  # why no patch (None = found)


def fired_ranges(frames: list[int]) -> list[tuple[int, int]]:
    """Sorted frame indices as (first, last) runs of consecutive indices."""
    out: list[tuple[int, int]] = []
    for i in sorted(frames):
        if out and i == out[-1][1] + 1:
            out[-1] = (out[-1][0], i)
        else:
            out.append((i, i))
    return out


class FrameChecker:
    """Runs the per-frame checks in frame order; ``check`` returns (diagnostics fired, scores).

    ``depth_source``: where the session's depth comes from (``Session.depth_source``); it words the
    cause when the depth beside the tool is missing (:func:`no_depth_beside_cause`)."""

    def __init__(self, params: DiagnosticParams = DiagnosticParams(), image_width: int = 1920,
                 depth_source: DepthSource = "depth") -> None:
        self.params = params
        self.width = image_width
        self.depth_source = depth_source
        self._prev: FrameMeasures | None = None
        self._prev_patch: PatchNumbers | None = None
        self._last_seen: FrameMeasures | None = None
        self._last_seen_index = -10 ** 9
        self._areas: deque[int] = deque(maxlen=31)  # recent nonzero areas, for the typical area

    def reset_previous(self) -> None:
        """Forget the previous frame (after a bad frame the next one has no predecessor for frozen depth)."""
        self._prev = None

    def check(self, index: int, m: FrameMeasures, patch: PatchNumbers | None) -> tuple[list[Diagnostic], dict]:
        p = self.params
        fired: list[Diagnostic] = []
        scores: dict[str, float] = {}

        def fire(code: str, text: str, value: float, cause: str = "") -> None:
            fired.append(Diagnostic(code, index, f"{CHECKS[code][0]}: {text}: {cause or CHECKS[code][1]}",
                                    float(value), cause))

        def score(code: str, value: float, threshold: float, above: bool = True) -> bool:
            if not math.isfinite(value):
                return False
            s = value / threshold if above else (threshold / value if value > 0 else math.inf)
            scores[code] = float(min(s, 10.0))
            return value > threshold if above else value < threshold

        typical = float(np.median(self._areas)) if self._areas else 0.0
        if m.tool_area_px < p.min_tool_area_px:
            last = self._last_seen
            recent = index - self._last_seen_index <= p.dropout_memory_frames
            left_view = last is not None and last.touches_border and last.tool_area_px < p.exit_area_fraction * typical
            scores["mask_dropout"] = 2.0 if (last is not None and recent and not left_view) else 0.0
            if scores["mask_dropout"] > 1:
                fire("mask_dropout", f"{m.tool_area_px} px, {last.tool_area_px} px {index - self._last_seen_index} "
                                     f"frame(s) before", m.tool_area_px)
        else:
            if score("extra_blob", m.extra_blob_px, p.min_blob_area_fraction * m.tool_area_px):
                fire("extra_blob", f"{m.extra_blob_px} px blob at ({m.extra_blob_xy[0]:.0f}, {m.extra_blob_xy[1]:.0f})",
                     m.extra_blob_px)
            prev = self._prev
            if prev is not None and prev.tool_area_px >= p.min_tool_area_px:
                change = abs(m.tool_area_px - prev.tool_area_px) / max(m.tool_area_px, prev.tool_area_px)
                at_border = m.touches_border or prev.touches_border
                if not at_border and score("mask_area_jump", change, p.mask_area_jump):
                    fire("mask_area_jump", f"{prev.tool_area_px} -> {m.tool_area_px} px (change {change:.0%} > "
                                           f"{p.mask_area_jump:.0%})", change)
            if score("mask_image_edges", m.edge_support, p.min_edge_support, above=False):
                fire("mask_image_edges", f"{m.edge_support:.0%} of the contour on an image edge "
                                         f"(< {p.min_edge_support:.0%})", m.edge_support)
            # no depth beside the tool (NaN = not measured: not missing): the depth source failed there, and the
            # depth-against-mask shares would rest on the few pixels with depth (the mask is not to blame)
            beside = m.beside_valid_fraction
            no_beside = beside < p.min_beside_valid_fraction  # False for NaN
            if not no_beside and score("mask_on_tissue", m.inside_far_fraction, p.max_inside_far_fraction):
                fire("mask_on_tissue", f"{m.inside_far_fraction:.1%} of the rim (> {p.max_inside_far_fraction:.1%})",
                     m.inside_far_fraction)
            if not no_beside and score("tool_depth_outside", m.outside_tool_fraction, p.max_outside_tool_fraction):
                fire("tool_depth_outside", f"{m.outside_tool_fraction:.0%} of the ring outside "
                                           f"(> {p.max_outside_tool_fraction:.0%})", m.outside_tool_fraction)
            holes = score("depth_holes", m.hole_fraction, p.max_hole_fraction)
            if no_beside:
                missing = p.min_beside_valid_fraction / beside if beside > 0 else math.inf
                scores["depth_holes"] = float(min(max(missing, scores.get("depth_holes", 0.0)), 10.0))
                fire("depth_holes", f"{beside:.0%} valid just outside the mask (< {p.min_beside_valid_fraction:.0%}; "
                                    f"{m.hole_fraction:.0%} invalid on and around the tool)", beside,
                     no_depth_beside_cause(self.depth_source))
            elif holes:
                fire("depth_holes", f"{m.hole_fraction:.0%} invalid (> {p.max_hole_fraction:.0%})", m.hole_fraction)
            if math.isfinite(m.width_ratio) and m.width_ratio > 0:
                off = max(m.width_ratio, 1.0 / m.width_ratio)
                if score("tool_width", off, p.max_width_ratio):
                    fire("tool_width", f"{m.width_ratio * p.tool_diameter_mm:.1f} mm wide vs "
                                       f"{p.tool_diameter_mm:g} mm (ratio {m.width_ratio:.2f})", m.width_ratio)
            if score("stereo_residual", m.residual_ratio, p.max_residual_ratio):
                fire("stereo_residual", f"residual ratio {m.residual_ratio:.2f} (> {p.max_residual_ratio:g}; "
                                        f"{m.residual_grey:.1f} grey levels)", m.residual_ratio)
            self._last_seen, self._last_seen_index = m, index
            self._areas.append(m.tool_area_px)
        prev = self._prev
        if prev is not None and m.depth_digest == prev.depth_digest:
            changed = m.tool_area_px != prev.tool_area_px
            if m.thumb.size and prev.thumb.size:
                diff = float(np.abs(m.thumb - prev.thumb).mean()) / 255.0
                changed = changed or diff > p.image_change_grey / 255.0
            scores["frozen_depth"] = 2.0 if changed else 0.0
            if changed:
                fire("frozen_depth", "same depth bytes as the previous frame", 1.0)
        if patch is not None:
            # a small mask at the border while the tool enters (its first frames) or leaves the view
            passing = m.touches_border and (len(self._areas) <= ENTERING_FRAMES
                                            or m.tool_area_px < p.exit_area_fraction * typical)
            if patch.reason is not None and m.tool_area_px >= p.min_tool_area_px and not passing:
                fire("no_patch", f"({patch.reason})", math.nan)
            pp = self._prev_patch
            if pp is not None and math.isfinite(patch.distance_m) and math.isfinite(pp.distance_m):
                jump = abs(patch.distance_m - pp.distance_m)
                moved = math.inf if patch.center_xy is None or pp.center_xy is None else math.dist(
                    patch.center_xy, pp.center_xy)
                limit = p.distance_jump_m + p.distance_jump_rel * min(abs(patch.distance_m), abs(pp.distance_m))
                if moved <= p.patch_move_frac * self.width and score("distance_jump", jump, limit):
                    fire("distance_jump", f"{1000 * pp.distance_m:.1f} -> {1000 * patch.distance_m:.1f} mm "
                                          f"(jump {1000 * jump:.1f} mm > {1000 * limit:.1f} mm, patch "
                                          f"moved {moved:.0f} px)", jump)
            self._prev_patch = patch
        self._prev = m
        return fired, scores
