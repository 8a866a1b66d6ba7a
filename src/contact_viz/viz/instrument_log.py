"""What is logged of each instrument, frame by frame: its layers, patch box, label, 3D patch and gap, and series,
in its one colour (:func:`contact_viz.viz.style.instrument_style`); and where the labels go (:func:`place_labels`,
no Rerun: labels kept apart and inside the image).

Entity paths (contact_viz.viz.entities): the *primary* instrument (the lowest selected object id, 1 without a
selection: a binary mask's only instrument) at the single-instrument paths, every other instrument ``k`` one level
down, at ``<entity>/tools/<k>``. The labels of all instruments are one Points2D, ENTITY_LEFT_LABELS.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import rerun as rr

from contact_viz.geometry.patch import PatchResult
from contact_viz.geometry.pointcloud import PatchGeometry
from contact_viz.params import MM_PER_M
from contact_viz.viz.entities import (
    ENTITY_DEPTH_LAYERS,
    ENTITY_DEPTH_PATCH,
    ENTITY_LEFT_LABELS,
    ENTITY_LEFT_LAYERS,
    ENTITY_LEFT_PATCH,
    ENTITY_PATCH_GAP,
    ENTITY_PATCH_GAP_LENGTH,
    ENTITY_PATCH_TISSUE,
    ENTITY_PATCH_TOOL,
    ENTITY_SERIES_DISTANCE,
    ENTITY_SERIES_POSTERIOR,
    ENTITY_SERIES_SIGNAL,
    PATCH_ENTITIES,
    TOOL_ENTITIES,
    TOOL_LAYER_ENTITIES,
    tool_entity,
)
from contact_viz.viz.style import (
    DEPTH_LAYER_OPACITY,
    INSTRUMENT_POSTERIOR_WIDTH_PX,
    LAYER_OVERLAY_OPACITY,
    SERIES_STYLES,
    InstrumentStyle,
    instrument_style,
)

__all__ = ["CONTACT_MARK", "InstrumentLayers", "InstrumentView", "label_colour", "label_text", "place_labels"]

BOX_LINE_RADIUS_PX = 1.5  # half line width of the patch box, UI px (negative radii in Rerun = UI units)
LABEL_POINT_RADIUS_PX = 3.0  # the dot a label hangs on, UI px
GAP_LINE_RADIUS_M = 0.00015  # radius of the gap segment in 3D, m
GAP_END_RADIUS_M = 0.0004  # radius of its two end points (tool, tissue): seen however short the gap, m
CONTACT_MARK = "●"  # after the distance of the instrument in contact (with a model) or nearest (without)
# labels: their text is about this wide per character and this tall, in image pixels per image width (the viewer
# scales the image to its pane, the text not: measured in a 1280x720 window), and kept this far apart
LABEL_CHAR_FRAC, LABEL_HEIGHT_FRAC, LABEL_GAP_FRAC = 0.014, 0.03, 0.006
# the viewer draws a label in its point's colour on a translucent plate below the point, light in the web viewer
# (light theme) and dark in the native one: bright instrument colours vanish on the light plate, dark shades on the
# dark one; this share of each channel keeps a WCAG contrast of 2.4-4.2 on a (225, 225, 225) plate and 2.5-4.4
# on a (45, 45, 50) one for the five colours (0.55: 3.7-5.9 and 1.8-2.9, unreadable in the native viewer)
LABEL_SHADE = 0.7


@dataclass(frozen=True)
class InstrumentView:
    """One instrument's part of a readable frame, display-ready (prepared by the debugger)."""

    tool: int  # object id
    patch: PatchResult  # its patch: layer ids, window, distance, signal
    depth_layers: np.ndarray  # (h, w) uint8 its layer ids on the decimated depth grid
    depth_window_xyxy: tuple[float, float, float, float] | None  # its patch window on the depth grid, px
    geometry: PatchGeometry | None  # its patch in 3D (None = no patch)
    posterior: float | None = None  # its own causal posterior P(contact) (None = no model)


def label_colour(tool: int) -> tuple[int, int, int, int]:
    """The colour of instrument ``tool``'s label: a dark shade of its colour (LABEL_SHADE)."""
    r, g, b, a = instrument_style(tool).window
    return (round(r * LABEL_SHADE), round(g * LABEL_SHADE), round(b * LABEL_SHADE), a)


def label_text(distance_m: float, marked: bool) -> str:
    """An instrument's label: its distance ("2.0 mm"), and CONTACT_MARK when it is the frame's instrument in contact
    (with a model) or nearest (without). The instrument is told by the label's colour."""
    return f"{distance_m * MM_PER_M:.1f} mm" + (f" {CONTACT_MARK}" if marked else "")


def place_labels(windows: Sequence[tuple[float, float, float, float]], texts: Sequence[str],
                 image_size: tuple[int, int]) -> np.ndarray:
    """Where each label's point goes, (n, 2) x, y px (the viewer draws the text centred below its point): the text
    just above its patch box (below it at the image's top edge), moved right or left so that it stays inside the
    image, and down past any label placed before it that it would cover (boxes in order; the first keeps its
    place).

    Text sizes are estimated from the image width (the viewer scales images to their pane but draws text at a
    fixed size): LABEL_CHAR_FRAC of the width per character, LABEL_HEIGHT_FRAC high."""
    height, width = image_size
    char_w, text_h, gap = LABEL_CHAR_FRAC * width, LABEL_HEIGHT_FRAC * width, LABEL_GAP_FRAC * width
    placed: list[tuple[float, float, float, float]] = []  # x0, y0, x1, y1 of the labels placed
    out = np.zeros((len(windows), 2))
    for k, ((x0, y0, x1, y1), text) in enumerate(zip(windows, texts)):
        w = char_w * len(text)
        x = min(max(0.5 * (x0 + x1), w / 2), width - w / 2)
        y = y0 - gap - text_h / 2 if y0 - gap - text_h >= 0 else y1 + gap + text_h / 2
        for _ in range(len(placed) + 1):
            clash = [b for b in placed if abs(b[0] + b[2] - 2 * x) < (b[2] - b[0]) + w + 2 * gap
                     and abs(b[1] + b[3] - 2 * y) < (b[3] - b[1]) + text_h + 2 * gap]
            if not clash:
                break
            y = max(b[3] for b in clash) + gap + text_h / 2
        y = min(y, height - text_h / 2)
        placed.append((x - w / 2, y - text_h / 2, x + w / 2, y + text_h / 2))
        out[k] = (x, y - text_h / 2)
    return out


class InstrumentLayers:
    """Every instrument's own entities, frame by frame (module docstring).

    Each instrument is drawn in its colours (instrument_style: instrument 1's layer classes are the world's
    AnnotationContext, the others' an AnnotationContext on their layer entities, static, the first time they
    appear). An instrument that leaves the frame (or a bad frame) gets its entities cleared and its series broken
    by a NaN, once: a stale layer never shows.

    The session counts as one of several instruments from the first frame with an instrument other than the
    primary (or from the start, ``several``: the selection names several); from then on the series are named
    after the instruments, with a model each instrument's own posterior is logged too
    (``tool_entity(ENTITY_SERIES_POSTERIOR, k)``, the primary's included) and the scene's posterior (the max over
    the instruments) is drawn in a colour of no instrument. A session of one instrument records what it did
    before there were several.
    """

    def __init__(self, primary: int = 1, *, with_model: bool = False, several: bool = False,
                 image_size: tuple[int, int] = (1080, 1920)) -> None:
        self.primary = int(primary)
        self.with_model = with_model
        self.several = several
        self.image_size = image_size
        self.styled: set[int] = set()  # instruments whose static styles are logged
        self.shown: set[int] = set()  # instruments whose entities hold data at the current time
        self.labelled = False  # ENTITY_LEFT_LABELS holds labels at the current time

    def entity(self, entity: str, tool: int) -> str:
        """Where instrument ``tool`` logs its ``entity`` (one of TOOL_ENTITIES, or the distance / signal series)."""
        return entity if tool == self.primary else tool_entity(entity, tool)

    # -- static styles -------------------------------------------------------------------------

    def _series_styles(self, rec: rr.RecordingStream, style: InstrumentStyle) -> None:
        tool = style.tool
        named = self.several or tool != self.primary
        for entity, key, colour, name in (
                (ENTITY_SERIES_DISTANCE, "distance_mm", style.line, f"{style.name} (mm)"),
                (ENTITY_SERIES_SIGNAL, "signal", style.signal, style.name)):
            base = SERIES_STYLES[key]
            rec.log(self.entity(entity, tool), rr.SeriesLines(colors=[colour], widths=[base.width_px],
                                                              names=[name if named else base.name]), static=True)
        if self.with_model and self.several:
            rec.log(tool_entity(ENTITY_SERIES_POSTERIOR, tool),
                    rr.SeriesLines(colors=[style.line], widths=[INSTRUMENT_POSTERIOR_WIDTH_PX],
                                   names=[f"P {style.name}"]), static=True)
        elif self.with_model and tool == self.primary:  # one instrument: its posterior is the scene's
            base = SERIES_STYLES["posterior"]
            rec.log(ENTITY_SERIES_POSTERIOR, rr.SeriesLines(colors=[style.line], widths=[base.width_px],
                                                            names=[base.name]), static=True)

    def _style(self, rec: rr.RecordingStream, tool: int) -> None:
        if tool in self.styled:
            return
        self.styled.add(tool)
        style = instrument_style(tool)
        if tool != 1:  # (instrument 1's classes are the world's AnnotationContext, LAYER_STYLES)
            context = rr.AnnotationContext([rr.AnnotationInfo(id=s.class_id, label=s.name, color=s.rgba)
                                            for s in style.layers])
            for entity in TOOL_LAYER_ENTITIES:
                rec.log(self.entity(entity, tool), context, static=True)
        self._series_styles(rec, style)

    def _become_several(self, rec: rr.RecordingStream) -> None:
        self.several = True
        for tool in sorted(self.styled):  # the series named after their instruments, and their posteriors
            self._series_styles(rec, instrument_style(tool))
        if self.with_model:  # (the max over the instruments: it runs along one of their lines, hidden at first)
            scene = SERIES_STYLES["scene_posterior"]
            rec.log(ENTITY_SERIES_POSTERIOR, rr.SeriesLines(colors=[scene.rgba], widths=[scene.width_px],
                                                            names=[scene.name], visible_series=[False]), static=True)

    # -- per frame -----------------------------------------------------------------------------

    def log(self, rec: rr.RecordingStream, views: Sequence[InstrumentView], contact_tool: int | None = None) -> None:
        """Log the instruments of a readable frame (at the recording's current time); clear those gone."""
        present = {v.tool for v in views}
        if not self.several and any(tool != self.primary for tool in present):
            self._become_several(rec)
        for view in views:
            self._style(rec, view.tool)
            self._log_one(rec, view)
        for tool in sorted(self.shown - present):
            self._clear(rec, tool)
        self.shown = present
        self._log_labels(rec, views, contact_tool)

    def _log_labels(self, rec: rr.RecordingStream, views: Sequence[InstrumentView], contact_tool: int | None) -> None:
        """Every instrument's label (its distance, CONTACT_MARK on the one in contact) on a dot above its patch box,
        in its colour, kept apart (place_labels): one Points2D."""
        shown = [v for v in views if v.patch.window_xyxy is not None and v.geometry is not None]
        if not shown:
            if self.labelled:
                rec.log(ENTITY_LEFT_LABELS, rr.Clear(recursive=False))
                self.labelled = False
            return
        texts = [label_text(v.patch.distance_m, v.tool == contact_tool) for v in shown]
        xy = place_labels([v.patch.window_xyxy for v in shown], texts, self.image_size)
        rec.log(ENTITY_LEFT_LABELS, rr.Points2D(xy, labels=texts, colors=[label_colour(v.tool) for v in shown],
                                                radii=[-LABEL_POINT_RADIUS_PX], show_labels=True))
        self.labelled = True

    def bad_frame(self, rec: rr.RecordingStream) -> None:
        """A frame that could not be read: every instrument's entities cleared (log_bad_frame clears the
        primary's single-instrument paths itself)."""
        for tool in sorted(self.shown - {self.primary}):
            self._clear(rec, tool)
        if self.several and self.with_model and self.primary in self.shown:
            rec.log(tool_entity(ENTITY_SERIES_POSTERIOR, self.primary), rr.Scalars(math.nan))
        self.shown = set()
        rec.log(ENTITY_LEFT_LABELS, rr.Clear(recursive=False))
        self.labelled = False

    def clear_layers(self, rec: rr.RecordingStream) -> None:
        """Every instrument's layers, boxes, labels and 3D patch cleared, its series left as they are (a frame shown
        only in the series; the primary's single-instrument paths are cleared by the caller)."""
        for tool in sorted(self.shown - {self.primary}):
            for entity in TOOL_ENTITIES:
                rec.log(self.entity(entity, tool), rr.Clear(recursive=False))
        self.shown = set()
        rec.log(ENTITY_LEFT_LABELS, rr.Clear(recursive=False))
        self.labelled = False

    def _log_one(self, rec: rr.RecordingStream, view: InstrumentView) -> None:
        tool, patch, geometry = view.tool, view.patch, view.geometry
        style = instrument_style(tool)
        at = self.entity
        rec.log(at(ENTITY_LEFT_LAYERS, tool), rr.SegmentationImage(patch.layer_ids, opacity=LAYER_OVERLAY_OPACITY))
        rec.log(at(ENTITY_DEPTH_LAYERS, tool), rr.SegmentationImage(view.depth_layers, opacity=DEPTH_LAYER_OPACITY))
        if patch.window_xyxy is not None and geometry is not None:
            rec.log(at(ENTITY_LEFT_PATCH, tool), _box(patch.window_xyxy, style.window))
            if view.depth_window_xyxy is not None:
                rec.log(at(ENTITY_DEPTH_PATCH, tool), _box(view.depth_window_xyxy, style.window))
            else:
                rec.log(at(ENTITY_DEPTH_PATCH, tool), rr.Clear(recursive=False))
            radii = [geometry.point_radius_m]
            rec.log(at(ENTITY_PATCH_TISSUE, tool), rr.Points3D(geometry.tissue_points_m,
                                                               colors=[style.tissue_points], radii=radii))
            rec.log(at(ENTITY_PATCH_TOOL, tool), rr.Points3D(geometry.tool_points_m, colors=[style.tool_points],
                                                             radii=radii))
            start = np.asarray(geometry.gap_origin_m, dtype=np.float64)
            end = start + np.asarray(geometry.gap_vector_m, dtype=np.float64)
            # the gap as a segment between its two ends, with its length: seen in contact too, where it is short
            rec.log(at(ENTITY_PATCH_GAP, tool), rr.LineStrips3D([np.stack([start, end])], colors=[style.gap],
                                                                radii=[GAP_LINE_RADIUS_M]),
                    rr.Points3D(np.stack([start, end]), colors=[style.tool_points, style.tissue_points],
                                radii=[GAP_END_RADIUS_M]))
            rec.log(at(ENTITY_PATCH_GAP_LENGTH, tool), rr.Points3D([0.5 * (start + end)], colors=[label_colour(tool)],
                                                                   radii=[GAP_LINE_RADIUS_M],
                                                                   labels=[label_text(geometry.distance_m, False)],
                                                                   show_labels=True))
        else:
            for entity in PATCH_ENTITIES:
                rec.log(at(entity, tool), rr.Clear(recursive=False))
        rec.log(at(ENTITY_SERIES_DISTANCE, tool), rr.Scalars(patch.distance_m * MM_PER_M))
        rec.log(at(ENTITY_SERIES_SIGNAL, tool), rr.Scalars(patch.signal))
        if self.several and view.posterior is not None:
            rec.log(tool_entity(ENTITY_SERIES_POSTERIOR, tool), rr.Scalars(view.posterior))

    def _clear(self, rec: rr.RecordingStream, tool: int) -> None:
        for entity in TOOL_ENTITIES:
            rec.log(self.entity(entity, tool), rr.Clear(recursive=False))
        for entity in (ENTITY_SERIES_DISTANCE, ENTITY_SERIES_SIGNAL):
            rec.log(self.entity(entity, tool), rr.Scalars(math.nan))
        if self.several and self.with_model:
            rec.log(tool_entity(ENTITY_SERIES_POSTERIOR, tool), rr.Scalars(math.nan))


def _box(window: tuple[float, float, float, float], colour) -> rr.Boxes2D:
    x0, y0, x1, y1 = window
    return rr.Boxes2D(mins=[[x0, y0]], sizes=[[x1 - x0, y1 - y0]], colors=[colour], radii=[-BOX_LINE_RADIUS_PX])
