"""Thresholds of the diagnostics (frame and session checks), one frozen, typed config."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

__all__ = ["DiagnosticParams"]

# Fields that are fractions in [0, 1] and fields that must be > 0.
_FRACTIONS = (
    "mask_area_jump", "min_edge_support", "max_inside_far_fraction", "max_outside_tool_fraction",
    "max_hole_fraction", "image_change_grey", "force_level", "signal_level",
)
_POSITIVE = (
    "distance_jump_m", "tool_diameter_mm", "max_width_ratio", "max_residual_ratio", "blob_gap_frac",
    "ring_frac_lo", "ring_frac_hi", "same_depth_m", "same_depth_rel", "far_depth_m", "far_depth_rel",
    "image_edge_grey", "pad_frac", "distance_jump_rel", "frame_gap_factor", "max_lag_s", "min_lag_correlation",
)


@dataclass(frozen=True)
class DiagnosticParams:
    """Thresholds of the per-frame and per-session checks (contact_viz.checks; docs/diagnostics.md).

    Lengths in pixels are given as fractions of the image width (``*_frac``) so that one setting
    fits every resolution; depths in metres with a relative part (fraction of the tool's depth).
    A check fires when its measured value is strictly beyond its threshold.
    """

    # ---- mask ----
    min_tool_area_px: int = 1  # fewer tool-mask pixels than this = no tool, px
    dropout_memory_frames: int = 30  # an empty mask is a dropout if a tool was seen within this many frames, frames
    exit_area_fraction: float = 0.35  # ... unless the last mask touched the border and was below this share of the typical area (the tool left), 0-1
    mask_area_jump: float = 0.5  # relative mask-area change that fires, |dA| / max(A_t, A_prev), 0-1 (not at the border)
    min_blob_area_fraction: float = 0.008  # an extra mask blob counts from this share of the main blob's area, 0-1
    blob_gap_frac: float = 0.01  # ... when farther than this from the main blob (fragments nearer are the same tool), x image width
    min_edge_support: float = 0.5  # share of the mask contour on an image edge below which it fires, 0-1
    image_edge_grey: float = 8.0  # an image edge: grey-level gradient (Sobel / 8) at least this, grey levels/px
    # ---- depth against the mask ----
    max_inside_far_fraction: float = 0.008  # share of the mask's inner rim whose depth lies behind the tool that fires, 0-1
    max_outside_tool_fraction: float = 0.3  # share of the ring just outside the mask at the tool's depth that fires, 0-1
    ring_frac_lo: float = 0.006  # that ring starts this far outside the mask, x image width (natural edge fattening lies inside)
    ring_frac_hi: float = 0.012  # ... and ends this far out, x image width
    same_depth_m: float = 0.002  # "at the tool's depth": within this of the nearby tool depth, m ...
    same_depth_rel: float = 0.02  # ... or this share of it, whichever is larger, fraction
    far_depth_m: float = 0.004  # "behind the tool": farther than the nearby tool depth by this, m ...
    far_depth_rel: float = 0.05  # ... or this share of it, whichever is larger, fraction
    max_hole_fraction: float = 0.4  # share of invalid depth on the tool and the band around it that fires, 0-1
    # ---- scale and stereo ----
    tool_diameter_mm: float = 8.0  # the instrument's shaft diameter (--tool-diameter-mm; da Vinci 8 mm, many 5 mm), mm
    max_width_ratio: float = 1.45  # physical shaft width / diameter above this (or below its inverse) fires, ratio
    max_residual_ratio: float = 1.1  # stereo residual at the depth's disparity / at a 15% different one, above this fires, ratio
    # ---- time ----
    image_change_grey: float = 0.5  # the image changed: mean |grey difference| of a thumbnail above this (0-1 of 255 = grey/255), fraction
    distance_jump_m: float = 0.005  # change of the patch distance between frames that fires, m ...
    distance_jump_rel: float = 0.2  # ... plus this share of the smaller |distance| (far away it is noisy and harmless), fraction
    patch_move_frac: float = 0.01  # ... unless the patch centre moved more than this (another part of the tool), x image width
    pad_frac: float = 0.05  # margin around the tool's bounding box the frame checks look at, x image width
    # ---- session ----
    frame_gap_factor: float = 1.8  # a frame interval longer than this x the median interval is a gap, ratio
    max_lag_s: float = 0.5  # force-to-signal lags searched, +- s
    force_level: float = 0.1  # force "on" above this share of its range (20th to 95th percentile), 0-1
    signal_level: float = 0.85  # signal "on" above this share of its range (5th to 95th percentile), 0-1
    min_lag_frames: int = 3  # a force lag of at least this many frames fires (the on/off edges agree within 1), frames
    min_lag_correlation: float = 0.3  # ... when its cross-correlation peak is at least this, -1..1

    def __post_init__(self) -> None:
        for name in ("min_tool_area_px", "dropout_memory_frames", "min_lag_frames"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"DiagnosticParams.{name} must be an integer >= 1, got {value!r}")
        for name in _FRACTIONS:
            value = getattr(self, name)
            low_ok = value > 0 if name == "mask_area_jump" else value >= 0
            if not (isinstance(value, (int, float)) and low_ok and value <= 1):
                raise ValueError(f"DiagnosticParams.{name} must be in {'(0' if name == 'mask_area_jump' else '[0'}, 1], "
                                 f"got {value!r}")
        for name in ("exit_area_fraction", "min_blob_area_fraction", "patch_move_frac"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0 <= value <= 1):
                raise ValueError(f"DiagnosticParams.{name} must be in [0, 1], got {value!r}")
        for name in _POSITIVE:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
                    and value > 0):
                raise ValueError(f"DiagnosticParams.{name} must be > 0, got {value!r}")
        if not self.ring_frac_lo < self.ring_frac_hi:
            raise ValueError("DiagnosticParams needs ring_frac_lo < ring_frac_hi")
        if not self.max_width_ratio > 1:
            raise ValueError(f"DiagnosticParams.max_width_ratio must be > 1, got {self.max_width_ratio!r}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)
