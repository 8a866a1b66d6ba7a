"""Whether a session's left and right images are rectified: the vertical offset of matched features.

In a rectified pair a point of the scene lies on the same row of both images, so features matched
between them differ only in x. :func:`pair_offsets` matches SIFT features of one left/right pair
(Lowe's ratio test and a cross-check: each is the other's best match) and keeps the matches whose
vertical offset (right y - left y) lies near the pair's median (a MAD filter: wrong matches land
anywhere); :func:`vertical_offset` pools the kept matches of sampled frames (:func:`sample_frames`)
and takes their median: the ``not_rectified`` session check (docs/diagnostics.md) fires when it
exceeds ``DiagnosticParams.max_vertical_offset_px``. Pure: grey arrays in, numbers out (no I/O).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from contact_viz.checks.params import DiagnosticParams

__all__ = ["VerticalOffset", "pair_offsets", "sample_frames", "vertical_offset"]

# SIFT's contrast threshold (OpenCV's default 0.04 finds 20-60 features on a smooth rendered synthetic frame at
# 640x360, 0.01 thousands; the per-frame median then varies by 0.03 px instead of 0.3 px), -
SIFT_CONTRAST = 0.01
# ... keeping the strongest this many of each image (a textured 640x480 endoscope frame has ~6,000: matching them all
# took 1.3 s a pair, 1,000 take 0.04 s and still leave hundreds of matches a pair), features
SIFT_FEATURES = 1000
RATIO = 0.75  # Lowe's ratio test: the best match's descriptor distance below this share of the second best's, -
MAD_FACTOR = 3.0  # a match is kept within this many robust standard deviations (1.4826 x MAD) of the median, -
MIN_BAND_PX = 1.0  # ... or within this of it, whichever is wider (a near-perfect pair has a MAD near 0), px
MIN_FRAME_MATCHES = 8  # a frame with fewer kept matches gives no offset of its own, matches


@dataclass(frozen=True)
class VerticalOffset:
    """The vertical offset between the left and right images of a session's sampled frames."""

    offset_px: float  # median of right y - left y over every kept match, px of the session's images (> 0: right lower)
    frames: tuple[int, ...]  # the frames measured (indices in the session)
    frame_offsets_px: tuple[float, ...]  # each measured frame's median offset, px (NaN: too few matches)
    matches: int  # kept matches over all measured frames
    threshold_px: float  # the check's threshold (DiagnosticParams.max_vertical_offset_px), px

    @property
    def fired(self) -> bool:
        """The pair is not rectified: |offset| above the threshold."""
        return abs(self.offset_px) > self.threshold_px

    @property
    def spread_px(self) -> tuple[float, float]:
        """The smallest and largest per-frame offset, px (NaN, NaN when no frame had enough matches)."""
        finite = [v for v in self.frame_offsets_px if math.isfinite(v)]
        return (min(finite), max(finite)) if finite else (math.nan, math.nan)

    def summary(self) -> str:
        """``3.3 px vertical offset (right image lower; median of 2,345 features matched in 8 frames, 2.6 to
        4.4 px per frame)``."""
        lo, hi = self.spread_px
        side = "right image lower" if self.offset_px > 0 else "right image higher"
        per_frame = f", {lo:.1f} to {hi:.1f} px per frame" if len(self.frames) > 1 and math.isfinite(lo) else ""
        return (f"{abs(self.offset_px):.1f} px vertical offset ({side}; median of {self.matches:,} features matched "
                f"in {len(self.frames)} frame{'s' * (len(self.frames) != 1)}{per_frame})")

    def message(self) -> str:
        """The check's one line: ``left and right not rectified: 3.3 px vertical offset (...)``."""
        return f"left and right not rectified: {self.summary()}; threshold {self.threshold_px:g} px"


def sample_frames(indices: Sequence[int], count: int) -> list[int]:
    """At most ``count`` of ``indices``, evenly spaced from the first to the last (all when there are fewer)."""
    indices = list(indices)
    if len(indices) <= count:
        return indices
    picks = np.linspace(0, len(indices) - 1, count).round().astype(int)
    return [indices[k] for k in sorted(set(picks.tolist()))]


def _features(grey: np.ndarray):
    sift = cv2.SIFT_create(nfeatures=SIFT_FEATURES, contrastThreshold=SIFT_CONTRAST)
    return sift.detectAndCompute(np.ascontiguousarray(grey, dtype=np.uint8), None)


def pair_offsets(left_grey: np.ndarray, right_grey: np.ndarray) -> np.ndarray:
    """Right y - left y of the SIFT features matched between one left and right grey image (uint8, same
    size), px of these images: matches that pass the ratio test both ways and are each other's best
    (cross-check), then those near the median (MAD filter). Empty when fewer than two features match."""
    left_points, left_desc = _features(left_grey)
    right_points, right_desc = _features(right_grey)
    if left_desc is None or right_desc is None or len(left_points) < 2 or len(right_points) < 2:
        return np.zeros(0)
    matcher = cv2.BFMatcher(cv2.NORM_L2)

    def ratio_matches(query, train) -> dict[int, int]:
        pairs = matcher.knnMatch(query, train, k=2)
        return {m[0].queryIdx: m[0].trainIdx for m in pairs if len(m) == 2 and m[0].distance < RATIO * m[1].distance}

    forward, backward = ratio_matches(left_desc, right_desc), ratio_matches(right_desc, left_desc)
    both = [(i, j) for i, j in forward.items() if backward.get(j) == i]
    if len(both) < 2:
        return np.zeros(0)
    dy = np.array([right_points[j].pt[1] - left_points[i].pt[1] for i, j in both], dtype=np.float64)
    median = float(np.median(dy))
    band = max(MAD_FACTOR * 1.4826 * float(np.median(np.abs(dy - median))), MIN_BAND_PX)
    return dy[np.abs(dy - median) <= band]


def vertical_offset(pairs: Iterable[tuple[int, np.ndarray, np.ndarray]], params: DiagnosticParams = DiagnosticParams(),
                    scale_px: float = 1.0) -> VerticalOffset | None:
    """The vertical offset over ``pairs`` of (frame index, left grey, right grey): the median of every kept
    match's right y - left y (:func:`pair_offsets`), times ``scale_px`` (px of the session per px of these
    images: the images may be shrunk). None when fewer than ``params.min_rectification_matches`` matches are
    kept in all (too little texture to tell)."""
    frames, medians, kept = [], [], []
    for index, left, right in pairs:
        dy = pair_offsets(left, right) * scale_px
        frames.append(int(index))
        medians.append(float(np.median(dy)) if dy.size >= MIN_FRAME_MATCHES else math.nan)
        kept.append(dy)
    pooled = np.concatenate(kept) if kept else np.zeros(0)
    if pooled.size < params.min_rectification_matches:
        return None
    return VerticalOffset(float(np.median(pooled)), tuple(frames), tuple(medians), int(pooled.size),
                          params.max_vertical_offset_px)
