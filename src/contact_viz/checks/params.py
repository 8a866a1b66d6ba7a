"""Thresholds of the diagnostics (frame and session checks), one frozen, typed config."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from contact_viz.params import check_fields, checked

__all__ = ["DiagnosticParams"]


@dataclass(frozen=True)
class DiagnosticParams:
    """Thresholds of the per-frame and per-session checks (contact_viz.checks; docs/diagnostics.md).

    Lengths in pixels are given as fractions of the image width (``*_frac``) so that one setting
    fits every resolution; depths in metres with a relative part (fraction of the tool's depth).
    A check's score is its measured value over its threshold, oriented so that > 1 means beyond it;
    a check fires once its score clearly crosses 1 (by ``margin``) and stops once it clearly falls back.
    """

    # ---- decisions ----
    # a score within this share of 1 is no clear crossing: the check keeps its decision of the frame before for
    # the same instrument (fires above 1 + margin, stops below 1 - margin; a frame after a gap starts unfired), so
    # that the input's last bits (another processor's) cannot flip it. Measured: a 1e-5 relative change of the
    # depth and +-1 grey level on 2% of the pixels moves scores by at most 0.025 (bench_diagnostics --perturb), ratio
    margin: float = checked(0.05, ge=0, lt=1)

    # ---- mask ----
    min_tool_area_px: int = checked(1, ge=1)  # fewer tool-mask pixels than this = no tool, px
    # an empty mask is a dropout if a tool was seen within this many frames, frames
    dropout_memory_frames: int = checked(30, ge=1)
    # ... unless the last mask touched the border and was below this share of the typical area (it left), 0-1
    exit_area_fraction: float = checked(0.35, ge=0, le=1)
    # ... or had shrunk below this share of its area the frame it was seen before (moving out fast), 0-1
    exit_shrink_fraction: float = checked(0.8, ge=0, le=1)
    # relative mask-area change that fires, |dA| / max(A_t, A_prev), 0-1 (not when a mask touches the border)
    mask_area_jump: float = checked(0.5, gt=0, le=1)
    # an extra mask blob counts from this share of the main blob's area, 0-1
    min_blob_area_fraction: float = checked(0.008, ge=0, le=1)
    # ... when farther than this from the main blob (fragments nearer are the same tool), x image width
    blob_gap_frac: float = checked(0.01, gt=0, le=1)
    # ---- several instruments (object ids), compared by the overlap of their masks on a coarse grid ----
    # id_swap: an id whose mask overlaps (intersection over the smaller of the two) another id's mask of the
    # frame before at least this much ...
    swap_min_overlap: float = checked(0.3, gt=0, le=1)
    # ... and by at least this much more than its own id's mask of the frame before, 0-1
    swap_margin: float = checked(0.25, gt=0, le=1)
    # tools_merged: an instrument gone while another grew by at least this share of its area ...
    merge_min_growth: float = checked(0.5, gt=0, le=2)
    # ... and covers at least this share of its mask of the frame before, 0-1
    merge_min_cover: float = checked(0.5, gt=0, le=1)
    # an instrument gone whose last mask other instruments now cover at least this much is hidden behind them
    # (no mask_dropout), 0-1
    hidden_cover_fraction: float = checked(0.5, gt=0, le=1)
    min_edge_support: float = checked(0.5, ge=0, le=1)  # share of the mask contour on an image edge below which it fires, 0-1
    image_edge_grey: float = checked(8.0, gt=0)  # an image edge: grey gradient (Sobel / 8) at least this, grey levels/px
    # ... or, where the light is dim, at least this many times the median gradient of the tissue around the tool
    # (its texture: gradients scale with the light on tissue and silhouette alike), ratio ...
    edge_texture_factor: float = checked(5.0, gt=0)
    min_image_edge_grey: float = checked(2.0, gt=0)  # ... and never below this, grey levels/px
    # ---- depth against the mask ----
    # share of the mask's inner rim whose depth lies behind the tool that fires, 0-1
    max_inside_far_fraction: float = checked(0.008, ge=0, le=1)
    # share of the ring just outside the mask at the tool's depth that fires, 0-1
    max_outside_tool_fraction: float = checked(0.3, ge=0, le=1)
    ring_frac_lo: float = checked(0.006, gt=0, le=1)  # that ring starts this far outside the mask, x image width
    ring_frac_hi: float = checked(0.012, gt=0, le=1)  # ... and ends this far out, x image width
    same_depth_m: float = checked(0.002, gt=0)  # "at the tool's depth": within this of the nearby tool depth, m ...
    same_depth_rel: float = checked(0.02, gt=0)  # ... or this share of it, whichever is larger, fraction
    # "behind the tool": farther than the tool's surface continued to the rim by this, m ...
    far_depth_m: float = checked(0.004, gt=0)
    # ... or this share of it, or a round shaft's silhouette relief there (tool_diameter_mm / 2 x (sin + cos) of
    # the view ray's angle off the optical axis), whichever is larger, fraction
    far_depth_rel: float = checked(0.05, gt=0)
    max_hole_fraction: float = checked(0.4, ge=0, le=1)  # share of invalid depth on and around the tool that fires, 0-1
    # "no depth beside the tool" (depth_holes, the depth source failed there, not the mask): valid depth on less than
    # this share of the band just outside the mask (out to ring_frac_hi); mask_on_tissue and tool_depth_outside
    # are then skipped (their shares would rest on the few pixels with depth), 0-1.
    # (SGBM on synthetic sessions 160-640 px wide: 20-60% there, its usual gap at the tool's edge; failed: 4-7%)
    min_beside_valid_fraction: float = checked(0.15, ge=0, le=1)
    # ---- scale and stereo ----
    # the instrument's shaft diameter (--tool-diameter-mm; da Vinci 8 mm, many others 5 mm), mm
    tool_diameter_mm: float = checked(8.0, gt=0)
    # a mask whose area exceeds this x its widest disc's width x its reach from the image border is wider on average
    # than that disc: parts side by side (the two jaws) with the shaft out of view, the disc on a jaw; tool_width's
    # lower bound is not measured on it. Clean synthetic sessions, 320x180 to 1920x1080, where the disc reads
    # narrower than the shaft and lies inside the image: 0.89-1.05 with the disc on the shaft, 1.33-1.86 on the jaws
    # with the shaft out of view, ratio
    max_shaft_fill: float = checked(1.2, gt=0)
    # physical shaft width / diameter above this (or below its inverse) fires, ratio
    max_width_ratio: float = checked(1.45, gt=1)
    # stereo residual at the depth's disparity / at a 15% different one above this fires, ratio
    max_residual_ratio: float = checked(1.1, gt=0)
    # ---- time ----
    # the image changed: mean |grey difference| of a 32x18 thumbnail above this, grey levels
    image_change_grey: float = checked(0.5, ge=0)
    distance_jump_m: float = checked(0.005, gt=0)  # change of the patch distance between frames that fires, m ...
    # ... plus this share of the smaller |distance| (far away it is noisy and harmless: the tissue seen beside a tool
    # hovering 15-30 mm above it moves by up to 15 mm between frames of clean synthetic sessions), fraction
    distance_jump_rel: float = checked(0.6, ge=0)
    # ... unless the patch moved more than this (another part of the tool), x image width: measured between the
    # patch's places (the band pixels scoring within a hair of the patch, checks.rules.patch_place), not its
    # centres, an argmin that a 1e-5 change of the depth moved by 3-7 px on a flat score (bench_diagnostics --perturb)
    patch_move_frac: float = checked(0.01, ge=0, le=1)
    patch_place: bool = True  # False: measure it between the patch centres (strict, for comparison), -
    pad_frac: float = checked(0.05, gt=0, le=1)  # margin around the tool's box the frame checks look at, x image width
    # the frame checks look at every n-th pixel of the mask and depth, and at the images shrunk n times, n the
    # smallest integer that brings the width to at most this, px. The thresholds were chosen at 320 px; measured
    # at 640x360, full resolution raised false alarms from 0.4% to 3.9% (image edges are softer per pixel). 1080p:
    # n = 4 (480x270; JPEG files decode straight to it), 47 -> 4 ms of CPU a frame for the measurements
    analysis_width_px: int = checked(480, ge=16)
    # ---- session ----
    frame_gap_factor: float = checked(1.8, gt=1)  # a frame interval longer than this x the median is a gap, ratio
    max_lag_s: float = checked(0.5, gt=0)  # force-to-signal lags searched, +- s
    force_level: float = checked(0.1, gt=0, lt=1)  # force "on" above this share of its range (20th-95th percentile), 0-1
    signal_level: float = checked(0.85, gt=0, lt=1)  # signal "on" above this share of its range (5th-95th pct.), 0-1
    min_lag_frames: int = checked(3, ge=1)  # a force lag of at least this many frames fires, frames
    min_lag_correlation: float = checked(0.3, ge=-1, le=1)  # ... when its correlation peak is at least this, -1..1
    # a force whose swing (95th minus 20th percentile) is below this never left its sensor noise: no contact to time,
    # no lag measured (synthetic noise 0.1 N: a 30-frame session without contact swung 0.26 N and read a 6-frame
    # lag; contacts reach 2 N and more), N
    min_force_swing_n: float = checked(0.5, ge=0)
    # not_rectified (checks.rectification): |median vertical offset| of SIFT features matched between left and right
    # above this fires, px of the session's images. Measured (bench_rectification.py): rectified pairs 0.00-0.03
    # (synth, four phantoms, 640x360 and 1280x720), 0.06 (Middlebury motorcycle), 0.35 (the SCARED keyframe); with
    # 1 px shifted in 0.92-1.04 (0.64 on SCARED); da Vinci pairs rectified with their published calibration 3.3.
    # 0.6 is about the geometric mean of 0.35 and 0.92: 1.7x the largest rectified offset, 1/1.5 of the smallest
    # 1 px shift on a pair rectified to 0.06 px, px
    max_vertical_offset_px: float = checked(0.6, gt=0)
    rectification_frames: int = checked(8, ge=1)  # ... measured on this many frames, evenly spaced, frames
    # ... on images shrunk n times, n the smallest integer that brings the width to at most this. SIFT on this machine
    # (loaded): 1.3 s an image at 1920x1080, 0.16 s at 640x360, 0.09 s at 320x180; the offsets measured at 320 px are
    # those at 640 px within 0.03 px (synth, Middlebury, SCARED, da Vinci), px
    rectification_width_px: int = checked(320, ge=16)
    # ... and only with at least this many matches kept over those frames (fewer: too little texture to tell), matches
    min_rectification_matches: int = checked(30, ge=1)

    def __post_init__(self) -> None:
        check_fields(self)
        if not self.ring_frac_lo < self.ring_frac_hi:
            raise ValueError(f"DiagnosticParams needs ring_frac_lo < ring_frac_hi, got {self.ring_frac_lo!r}, "
                             f"{self.ring_frac_hi!r}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)
