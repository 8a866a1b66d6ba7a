"""The checks: each compares one measured quantity with its threshold and names the likely cause.

:class:`FrameChecker` runs the per-frame checks causally, frame after frame (it keeps what it
needs of the previous frames), on :class:`~contact_viz.checks.frame.FrameMeasures` and the
frame's patch numbers. Every check also has a *score* = measured value / threshold, oriented so
that > 1 means "fires" (the viewer plots the scores on one axis). Session checks (force lag,
frame times) are in :mod:`contact_viz.checks.session`. Pure Python; no I/O.

With several instruments (object ids) every instrument has its own history (a track: previous
measures and patch, typical area, dropout memory), and two checks compare them: ``id_swap`` (the
masks of two ids continue each other's of the frame before: the segmenter exchanged them; it fires
while they stay exchanged) and ``tools_merged`` (one id gone while another grew by about its area
over its place). An instrument gone behind another (its place covered by it), or leaving through
the border (its mask shrinking there), is no dropout.

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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from itertools import permutations
from typing import Literal

import numpy as np

from contact_viz.checks.frame import FrameMeasures, ToolMeasures
from contact_viz.checks.params import DiagnosticParams

ENTERING_FRAMES = 5  # a tool's first frames in view (at the border) do not raise no_patch, frames
MAX_SWAP_TOOLS = 6  # id swaps are looked for among at most this many instruments (every permutation is tried)

__all__ = ["CHECKS", "Diagnostic", "DepthSource", "FrameChecker", "PatchNumbers", "SESSION_CHECKS", "fired_ranges",
           "no_depth_beside_cause", "patch_place"]

DepthSource = Literal["depth", "disparity", "sgbm"]  # where a session's depth comes from (io.session.DEPTH_SOURCES)

# code -> (what it measures, likely cause); in the order the viewer stacks them.
CHECKS: dict[str, tuple[str, str]] = {
    "bad_frame": ("frame files could not be read", "a missing or corrupt mask / depth file"),
    "mask_dropout": ("empty tool mask while the tool was in view", "mask dropout (segmenter lost the tool)"),
    "extra_blob": ("extra mask blob away from the tool", "a second object or identity switch in the mask"),
    "mask_area_jump": ("tool mask area jumped (away from the border)", "mask dropout, bleed or identity switch"),
    "id_swap": ("instrument ids exchanged between frames", "the segmenter swapped two instruments' object ids "
                                                           "(identity switch)"),
    "tools_merged": ("one instrument's id took in another instrument", "the segmenter merged two instruments "
                                                                       "into one object id"),
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
    "not_rectified": ("vertical offset between features matched in the left and right images",
                      "the pair is not rectified, or rectified with a wrong or stale calibration"),
}


@dataclass(frozen=True)
class Diagnostic:
    """One check that fired at one frame."""

    code: str  # key of CHECKS
    index: int  # frame index in the session
    message: str  # one line for a log: what, the measured value against the threshold, the likely cause
    value: float  # the measured quantity (units as in the message; NaN when there is none)
    cause: str = ""  # the likely cause the message names; "" = the code's usual one (CHECKS / SESSION_CHECKS)
    tool: int | None = None  # the instrument's object id (None: a check of the whole frame or session)

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
    # (K, 2) x, y of the band pixels scoring within a hair of the patch's (patch_place): where the patch could as
    # well be. The centre is their argmin, which a tiny change of the depth moves among them; None = the centre only
    place_xy: np.ndarray | None = None


PLACE_M = 2e-5  # a band pixel is at the patch's place when its score is within this of the patch's, m
PLACE_MAX = 512  # at most this many pixels of the place (the best-scored), px


def patch_place(band_xy: np.ndarray, band_score_m: np.ndarray, score_m: float) -> np.ndarray | None:
    """The patch's place: the x, y (K, 2) of the band pixels whose score s is within ``PLACE_M`` of the patch's
    s* (at most ``PLACE_MAX``, the best-scored); None without a patch. A change of the depth by 1e-5 (another
    processor's renderer, or more) changes s by about a micrometre, a twentieth of that tolerance."""
    if not math.isfinite(score_m):
        return None
    near = np.flatnonzero(band_score_m <= score_m + PLACE_M)
    if len(near) > PLACE_MAX:
        near = near[np.argsort(band_score_m[near], kind="stable")[:PLACE_MAX]]
    return np.asarray(band_xy, dtype=np.float64)[near]


def _moved(now: PatchNumbers, before: PatchNumbers) -> float:
    """How far the patch moved between two frames, px: the distance between the nearest pixels of their places
    (0 when they share one), or between their centres where a place is not known."""
    if now.place_xy is not None and before.place_xy is not None and len(now.place_xy) and len(before.place_xy):
        gaps = now.place_xy[:, None, :] - before.place_xy[None, :, :]
        return float(np.sqrt((gaps ** 2).sum(axis=-1).min()))
    if now.center_xy is None or before.center_xy is None:
        return math.inf
    return math.dist(now.center_xy, before.center_xy)


def fired_ranges(frames: list[int]) -> list[tuple[int, int]]:
    """Sorted frame indices as (first, last) runs of consecutive indices."""
    out: list[tuple[int, int]] = []
    for i in sorted(frames):
        if out and i == out[-1][1] + 1:
            out[-1] = (out[-1][0], i)
        else:
            out.append((i, i))
    return out


MIN_COVER_CELLS = 1.0  # instruments are paired between frames (id_swap) when their masks cover this many grid cells


def _overlap(a: np.ndarray, b: np.ndarray) -> float:
    """Overlap of two coverage grids (FrameMeasures.coverage): their intersection over the smaller one, 0-1
    (a tool entering the view, its mask growing fast, still overlaps its mask of the frame before)."""
    smaller = min(float(a.sum()), float(b.sum()))
    return float(np.minimum(a, b).sum()) / smaller if smaller > 0 else 0.0


def _covered(a: np.ndarray, by: np.ndarray) -> float:
    """Share of coverage grid ``a`` that ``by`` covers, 0-1."""
    total = float(a.sum())
    return float(np.minimum(a, by).sum()) / total if total > 0 else 0.0


class _Decisions:
    """Each check's decision per instrument with a margin (DiagnosticParams.margin): a score (> 1 = beyond the
    threshold) fires above ``1 + margin`` and stops below ``1 - margin``; in between the decision of the frame
    before stands (unfired when the check was not decided at the frame before: absent tool, skipped check)."""

    def __init__(self, margin: float) -> None:
        self.margin = margin
        self._before: dict[tuple[int, str], bool] = {}
        self._now: dict[tuple[int, str], bool] = {}

    def next_frame(self) -> None:
        self._before, self._now = self._now, {}

    def forget(self) -> None:
        self._before, self._now = {}, {}

    def decide(self, key: tuple[int, str], score: float) -> bool:
        fired = score > (1.0 - self.margin if self._before.get(key, False) else 1.0 + self.margin)
        self._now[key] = fired
        return fired


@dataclass
class _Merge:
    """An instrument whose id took in another instrument (tools_merged), while it lasts."""

    other: int  # the track (key) taken in
    other_id: int  # its object id then
    base_area_px: int  # this instrument's area the frame before, px
    other_area_px: int  # the other's area the frame before, px
    since: int  # frame index it began


@dataclass
class _Track:
    """What the checks keep of one instrument between frames. Its object id may change (an id swap the checks
    recognised moves the track to the new id); ``key`` is the id it was first seen with."""

    key: int
    prev: FrameMeasures | None = None  # its measures at the previous frame (None: absent, or after a bad frame)
    prev_patch: PatchNumbers | None = None
    last_seen: FrameMeasures | None = None  # the last measures with a mask of at least min_tool_area_px
    last_seen_index: int = -10 ** 9
    areas: deque = field(default_factory=lambda: deque(maxlen=31))  # recent nonzero areas, for the typical area
    merged: _Merge | None = None  # it holds another instrument's pixels (tools_merged)
    swapped_at: int | None = None  # the frame its object id changed (id_swap), None = it has its own id


class FrameChecker:
    """Runs the per-frame checks in frame order; ``check`` returns (diagnostics fired, scores).

    ``check(index, measures, patch)`` takes one instrument's :class:`FrameMeasures` and
    :class:`PatchNumbers` (a mask read as one tool, object id 1), or a frame's :class:`ToolMeasures` and
    {object id: PatchNumbers}: then every instrument is checked on its own, with its own history (area,
    previous distance, dropout memory), and the instruments against each other (``id_swap``: two ids
    exchanged between frames; ``tools_merged``: one id took in another instrument). A score is the
    largest over the instruments. The messages name the instrument ("tool 2: ...") when the session has
    several (``several``; None = from the object ids seen so far: more than one, or one other than 1).

    ``depth_source``: where the session's depth comes from (``Session.depth_source``); it words the
    cause when the depth beside the tool is missing (:func:`no_depth_beside_cause`)."""

    def __init__(self, params: DiagnosticParams = DiagnosticParams(), image_width: int = 1920,
                 depth_source: DepthSource = "depth", *, several: bool | None = None,
                 stems: Sequence[str] = ()) -> None:
        self.params = params
        self.stems = tuple(stems)  # the session's frame stems: messages name a frame by its stem (index without)
        self.width = image_width
        self.depth_source = depth_source
        self.several = several
        self._tracks: dict[int, _Track] = {}  # track key -> track
        self._track_of: dict[int, int] = {}  # object id -> track key
        self._ids_seen: set[int] = set()
        self._prev_frame: tuple[bytes, np.ndarray, int] | None = None  # depth digest, thumb, area of the last frame
        self._decisions = _Decisions(params.margin)

    def reset_previous(self) -> None:
        """Forget the previous frame (after a bad frame the next one has no predecessor for frozen depth)."""
        self._prev_frame = None
        self._decisions.forget()
        for track in self._tracks.values():
            track.prev = None

    def _track(self, tool: int) -> _Track:
        key = self._track_of.get(tool)
        if key is None:
            key = tool if tool not in self._tracks else max(self._tracks) + 1
            self._tracks[key] = _Track(key)
            self._track_of[tool] = key
        return self._tracks[key]

    def check(self, index: int, m: FrameMeasures | ToolMeasures,
              patch: PatchNumbers | Mapping[int, PatchNumbers] | None) -> tuple[list[Diagnostic], dict]:
        p = self.params
        if isinstance(m, ToolMeasures):
            tools = dict(m.tools)
            digest, thumb, frame_area = m.depth_digest, m.thumb, m.tool_area_px
            if isinstance(patch, PatchNumbers):
                if len(tools) != 1:
                    raise ValueError(f"FrameChecker.check: one PatchNumbers for {len(tools)} instruments; "
                                     "give {object id: PatchNumbers}")
                patch = {next(iter(tools)): patch}
            patches = patch
        else:
            tools = {1: m}  # one mask, one tool (as a binary mask reads: id 1), even when empty
            digest, thumb, frame_area = m.depth_digest, m.thumb, m.tool_area_px
            patches = None if patch is None else {1: patch}
        fired: list[Diagnostic] = []
        scores: dict[str, float] = {}
        self._decisions.next_frame()
        self._ids_seen.update(k for k, t in tools.items() if t.tool_area_px > 0)
        several = self.several if self.several is not None else (len(self._ids_seen) > 1
                                                                  or bool(self._ids_seen - {1}))

        def fire(code: str, text: str, value: float, cause: str = "", tool: int | None = None) -> None:
            prefix = f"tool {tool}: " if several and tool is not None else ""
            fired.append(Diagnostic(code, index, f"{prefix}{CHECKS[code][0]}: {text}: {cause or CHECKS[code][1]}",
                                    float(value), cause, tool))

        def score(code: str, value: float, threshold: float, above: bool = True, *, key: int,
                  decision: str | None = None) -> bool:
            """Plot the score of ``code`` (the largest over the instruments) and decide it for the instrument of
            track ``key`` with the margin (``decision``: the name of the decision when it is not the code's)."""
            if not math.isfinite(value):
                return False
            s = value / threshold if above else (threshold / value if value > 0 else math.inf if threshold > 0 else 0.0)
            scores[code] = max(scores.get(code, 0.0), float(min(s, 10.0)))
            return self._decisions.decide((key, decision or code), s)

        def present(t: FrameMeasures | None) -> bool:
            return t is not None and t.tool_area_px >= p.min_tool_area_px

        for k in sorted(tools):
            if tools[k].tool_area_px > 0 or k in self._track_of or not isinstance(m, ToolMeasures):
                self._track(k)
        swaps = self._identify(index, tools, present)
        # every instrument known: (object id, track, its measures now or None when absent), by object id
        id_of = {key: k for k, key in self._track_of.items()}
        rows = sorted(((id_of[key], track, tools.get(id_of[key])) for key, track in self._tracks.items()
                       if key in id_of), key=lambda r: r[0])
        merges = self._merges(index, rows, present)

        for k, track, t in rows:
            if t is not None and t.tool_area_px > 0 and track.swapped_at is not None:
                if index == track.swapped_at:
                    new_overlap, own_overlap, before = swaps[k]
                    fire("id_swap", f"this mask continues tool {before}'s of the frame before "
                                    f"(overlap {new_overlap:.2f}; with its own {own_overlap:.2f})", new_overlap, tool=k)
                else:
                    at = track.swapped_at
                    fire("id_swap", f"still tool {track.key}'s instrument (ids exchanged at frame "
                                    f"{self.stems[at] if at < len(self.stems) else at})", math.nan, tool=k)
                scores["id_swap"] = 2.0
            merge = track.merged
            if merge is not None and t is not None:
                if index == merge.since:
                    fire("tools_merged", f"took in tool {merge.other_id}'s {merge.other_area_px} px ("
                                         f"{merge.base_area_px} -> {t.tool_area_px} px; tool {merge.other_id} gone, "
                                         f"its mask {merges[k]:.0%} covered)", t.tool_area_px, tool=k)
                else:
                    fire("tools_merged", f"still holds tool {merge.other_id} ({t.tool_area_px} px; since frame "
                                         f"{merge.since})", t.tool_area_px, tool=k)
                scores["tools_merged"] = 2.0
        absorbed = {track.merged.other for _, track, _ in rows if track.merged is not None}
        others_now = [t.coverage for _, _, t in rows if present(t) and t.coverage is not None]

        typicals = {track.key: float(np.median(track.areas)) if track.areas else 0.0 for _, track, _ in rows}
        for k, track, t in rows:
            area = 0 if t is None else t.tool_area_px
            typical = typicals[track.key]
            if area < p.min_tool_area_px:
                last = track.last_seen
                recent = index - track.last_seen_index <= p.dropout_memory_frames
                # it left the view: its last mask touched the border and was small, or shrinking fast (moving out)
                before_last = track.areas[-2] if len(track.areas) >= 2 else 0
                left_view = last is not None and last.touches_border and (
                    last.tool_area_px < p.exit_area_fraction * typical
                    or last.tool_area_px < p.exit_shrink_fraction * before_last)
                # gone into another instrument's id (tools_merged), or hidden behind another instrument
                hidden = track.key in absorbed or (last is not None and last.coverage is not None and others_now
                                                   and _covered(last.coverage, np.maximum.reduce(others_now))
                                                   >= p.hidden_cover_fraction)
                scores["mask_dropout"] = max(scores.get("mask_dropout", 0.0), 2.0 if (
                    last is not None and recent and not left_view and not hidden) else 0.0)
                if last is not None and recent and not left_view and not hidden:
                    fire("mask_dropout", f"{area} px, {last.tool_area_px} px {index - track.last_seen_index} "
                                         f"frame(s) before", area, tool=k)
            else:
                self._check_present(k, track, t, fire, score)
                track.last_seen, track.last_seen_index = t, index
                track.areas.append(t.tool_area_px)
        prev = self._prev_frame
        if prev is not None and digest == prev[0]:
            changed = frame_area != prev[2]
            if thumb.size and prev[1].size:
                diff = float(np.abs(thumb - prev[1]).mean()) / 255.0
                changed = changed or diff > p.image_change_grey / 255.0
            scores["frozen_depth"] = 2.0 if changed else 0.0
            if changed:
                fire("frozen_depth", "same depth bytes as the previous frame", 1.0)
        if patches is not None:
            for k, track, t in rows:
                self._check_patch(index, k, track, t, patches.get(k), typicals[track.key], fire, score)
        for k, track, t in rows:
            track.prev = t
        self._prev_frame = (digest, thumb, frame_area)
        return fired, scores

    def _identify(self, index: int, tools: dict[int, FrameMeasures], present
                  ) -> dict[int, tuple[float, float, int]]:
        """Recognise an id swap: the instruments present now and the frame before, paired by the overlap of
        their masks' coverage; where another pairing than their ids' overlaps much better, the tracks follow
        it (the checks compare each instrument with its own past). Returns {object id: (overlap with the
        track it now continues, overlap with its own id's, that track's object id the frame before)} of the ids
        that changed track at this frame."""
        p = self.params

        def pairable(m: FrameMeasures | None) -> bool:
            return present(m) and m.coverage is not None and float(m.coverage.sum()) >= MIN_COVER_CELLS

        ids = [k for k in sorted(tools) if pairable(tools[k]) and k in self._track_of
               and pairable(self._tracks[self._track_of[k]].prev)]
        if len(ids) < 2 or len(ids) > MAX_SWAP_TOOLS:
            return {}
        keys = [self._track_of[k] for k in ids]
        overlap = np.array([[_overlap(tools[k].coverage, self._tracks[key].prev.coverage) for key in keys]
                            for k in ids])
        n = len(ids)
        keep = float(np.trace(overlap))
        best, best_perm = keep, tuple(range(n))
        for perm in permutations(range(n)):
            total = float(sum(overlap[i, perm[i]] for i in range(n)))
            if total > best + 1e-9:
                best, best_perm = total, perm
        moved = [i for i in range(n) if best_perm[i] != i]
        if not moved:
            return {}
        # an id that changes track continues that track's mask clearly better than its own id's, and none of
        # them overlaps its own id's mask better (an instrument that moved off its place, entering fast or
        # passing behind another, gives no evidence either way: the pairing is one-to-one)
        clear = [i for i in moved if overlap[i, best_perm[i]] >= p.swap_min_overlap
                 and overlap[i, best_perm[i]] - overlap[i, i] >= p.swap_margin]
        if not clear or any(overlap[i, best_perm[i]] < overlap[i, i] for i in moved):
            return {}
        out = {}
        before = {key: k for k, key in self._track_of.items()}
        for i in moved:
            k, key = ids[i], keys[best_perm[i]]
            self._track_of[k] = key
            track = self._tracks[key]
            track.swapped_at = None if key == k else index  # back to its own id: the swap is undone
            out[k] = (float(overlap[i, best_perm[i]]), float(overlap[i, i]), before[key])
        return out

    def _merges(self, index: int, rows, present) -> dict[int, float]:
        """Recognise and follow tools_merged: an instrument present the frame before is gone, and another one
        grew by at least merge_min_growth of its area and covers at least merge_min_cover of its mask.
        Returns {object id: covered share} of the merges that begin at this frame."""
        p = self.params
        out: dict[int, float] = {}
        # those that go on: until the other instrument is back or this one shrinks back
        by_key = {track.key: (k, track, t) for k, track, t in rows}
        for k, track, t in rows:
            merge = track.merged
            if merge is None:
                continue
            other = by_key.get(merge.other)
            if (other is not None and present(other[2])) or not present(t) or \
                    t.tool_area_px < merge.base_area_px + p.merge_min_growth * merge.other_area_px:
                track.merged = None
        for j, gone, tj in rows:
            before = gone.prev
            if present(tj) or not present(before) or before.coverage is None:
                continue
            best = None
            for k, track, t in rows:
                if track is gone or not present(t) or not present(track.prev) or t.coverage is None \
                        or track.merged is not None:
                    continue
                growth = t.tool_area_px - track.prev.tool_area_px
                cover = _covered(before.coverage, t.coverage)
                if growth >= p.merge_min_growth * before.tool_area_px and cover >= p.merge_min_cover:
                    if best is None or cover > best[2]:
                        best = (k, track, cover)
            if best is not None:
                k, track, cover = best
                track.merged = _Merge(gone.key, j, track.prev.tool_area_px, before.tool_area_px, index)
                out[k] = cover
        return out

    def _check_present(self, k: int, track: _Track, m: FrameMeasures, fire, score) -> None:
        """The checks of one instrument's mask and depth (its mask has at least min_tool_area_px)."""
        p = self.params
        score = partial(score, key=track.key)
        if score("extra_blob", m.extra_blob_px, p.min_blob_area_fraction * m.tool_area_px):
            fire("extra_blob", f"{m.extra_blob_px} px blob at ({m.extra_blob_xy[0]:.0f}, {m.extra_blob_xy[1]:.0f})",
                 m.extra_blob_px, tool=k)
        prev = track.prev
        if prev is not None and prev.tool_area_px >= p.min_tool_area_px:
            change = abs(m.tool_area_px - prev.tool_area_px) / max(m.tool_area_px, prev.tool_area_px)
            at_border = m.touches_border or prev.touches_border
            if not at_border and score("mask_area_jump", change, p.mask_area_jump):
                fire("mask_area_jump", f"{prev.tool_area_px} -> {m.tool_area_px} px (change {change:.0%} > "
                                       f"{p.mask_area_jump:.0%})", change, tool=k)
        if score("mask_image_edges", m.edge_support, p.min_edge_support, above=False):
            fire("mask_image_edges", f"{m.edge_support:.0%} of the contour on an image edge "
                                     f"(< {p.min_edge_support:.0%})", m.edge_support, tool=k)
        # no depth beside the tool (NaN = not measured: not missing): the depth source failed there, and the
        # depth-against-mask shares would rest on the few pixels with depth (the mask is not to blame)
        beside = m.beside_valid_fraction
        # (depth_holes' score is the larger of its two measures'; NaN = not measured: never missing)
        no_beside = score("depth_holes", beside, p.min_beside_valid_fraction, above=False, decision="no_beside")
        if not no_beside and score("mask_on_tissue", m.inside_far_fraction, p.max_inside_far_fraction):
            fire("mask_on_tissue", f"{m.inside_far_fraction:.1%} of the rim (> {p.max_inside_far_fraction:.1%})",
                 m.inside_far_fraction, tool=k)
        if not no_beside and score("tool_depth_outside", m.outside_tool_fraction, p.max_outside_tool_fraction):
            fire("tool_depth_outside", f"{m.outside_tool_fraction:.0%} of the ring outside "
                                       f"(> {p.max_outside_tool_fraction:.0%})", m.outside_tool_fraction, tool=k)
        holes = score("depth_holes", m.hole_fraction, p.max_hole_fraction)
        if no_beside:
            fire("depth_holes", f"{beside:.0%} valid just outside the mask (< {p.min_beside_valid_fraction:.0%}; "
                                f"{m.hole_fraction:.0%} invalid on and around the tool)", beside,
                 no_depth_beside_cause(self.depth_source), tool=k)
        elif holes:
            fire("depth_holes", f"{m.hole_fraction:.0%} invalid (> {p.max_hole_fraction:.0%})", m.hole_fraction,
                 tool=k)
        if math.isfinite(m.width_ratio) and m.width_ratio > 0:
            off = max(m.width_ratio, 1.0 / m.width_ratio)
            if score("tool_width", off, p.max_width_ratio):
                fire("tool_width", f"{m.width_ratio * p.tool_diameter_mm:.1f} mm wide vs "
                                   f"{p.tool_diameter_mm:g} mm (ratio {m.width_ratio:.2f})", m.width_ratio, tool=k)
        if score("stereo_residual", m.residual_ratio, p.max_residual_ratio):
            fire("stereo_residual", f"residual ratio {m.residual_ratio:.2f} (> {p.max_residual_ratio:g}; "
                                    f"{m.residual_grey:.1f} grey levels)", m.residual_ratio, tool=k)

    def _check_patch(self, index: int, k: int, track: _Track, m: FrameMeasures | None, patch: PatchNumbers | None,
                     typical: float, fire, score) -> None:
        """no_patch and distance_jump of one instrument (``patch`` None: it is absent); ``typical``: its typical
        area before this frame, px."""
        p = self.params
        if patch is None:
            track.prev_patch = None
            return
        area = 0 if m is None else m.tool_area_px
        touches = m is not None and m.touches_border
        # a small mask at the border while the tool enters (its first frames) or leaves the view
        passing = touches and (len(track.areas) <= ENTERING_FRAMES or area < p.exit_area_fraction * typical)
        if patch.reason is not None and area >= p.min_tool_area_px and not passing:
            fire("no_patch", f"({patch.reason})", math.nan, tool=k)
        pp = track.prev_patch
        if pp is not None and math.isfinite(patch.distance_m) and math.isfinite(pp.distance_m):
            jump = abs(patch.distance_m - pp.distance_m)
            moved = _moved(patch, pp)
            limit = p.distance_jump_m + p.distance_jump_rel * min(abs(patch.distance_m), abs(pp.distance_m))
            if moved <= p.patch_move_frac * self.width and score("distance_jump", jump, limit, key=track.key):
                fire("distance_jump", f"{1000 * pp.distance_m:.1f} -> {1000 * patch.distance_m:.1f} mm "
                                      f"(jump {1000 * jump:.1f} mm > {1000 * limit:.1f} mm, patch "
                                      f"moved {moved:.0f} px)", jump, tool=k)
        track.prev_patch = patch
