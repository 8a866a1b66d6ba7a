"""The default layout sent with every recording (Rerun blueprint), in its own module as Rerun's examples keep it."""

from __future__ import annotations

from functools import partial

import rerun.blueprint as rrb

from contact_viz.viz.entities import (
    ENTITY_CONTACT,
    ENTITY_DEPTH_CAMERA,
    ENTITY_DEPTH_IMAGE,
    ENTITY_DEPTH_KIND,
    ENTITY_DEPTH_LAYERS,
    ENTITY_DEPTH_PATCH,
    ENTITY_LEFT_CAMERA,
    ENTITY_LEFT_LAYERS,
    ENTITY_LEFT_PATCH,
    ENTITY_LOG,
    ENTITY_RIGHT_CAMERA,
    ENTITY_SERIES_CONTACT,
    ENTITY_SERIES_DIAGNOSTICS,
    ENTITY_SERIES_DISTANCE,
    ENTITY_SERIES_EVIDENCE,
    ENTITY_SERIES_FORCE,
    ENTITY_SERIES_LAG,
    ENTITY_SERIES_SIGNAL,
    ENTITY_SERIES_TIP,
    ENTITY_WORLD,
    TIMELINE_FRAME,
)
from contact_viz.viz.rooted import root_path
from contact_viz.viz.style import LAYER_STYLES

__all__ = ["DEPTH_LEGEND", "DIAGNOSTICS_RANGE", "DISTANCE_RANGE", "EVIDENCE_RANGE", "MARKER_LANE", "SCORE_CLIP", "SIGNAL_RANGE", "default_blueprint",
           "layer_legend"]

SCORE_CLIP = 3.0  # diagnostic scores (value / threshold) are drawn clipped at this, ratio
MARKER_LANE = 0.15  # the markers of the k-th check sit at SCORE_CLIP + (k + 1) x this, above every score line, -
DIAGNOSTICS_RANGE = (-0.05, SCORE_CLIP + 18 * MARKER_LANE)  # the checks plot's y range (lines, then marker lanes)
SIGNAL_RANGE = (0.8, 4.2)  # the signal plot's y range: 160 mm to the cap at 0.1 mm (4), -log10 m
# the distance plot's y range: contact to a 40 mm hover. The viewer labels its y axis only where 10 mm steps are
# 20 px apart or more (at 1280x720 a range of 60 mm left only "0"); farther distances leave the top, mm
DISTANCE_RANGE = (-3.0, 40.0)
# the evidence plot's y range: the log-likelihood ratio, 0 (no evidence either way) in the middle; a hovering tool
# reads -5 to -20 with the paper's model, nats
EVIDENCE_RANGE = (-12.0, 12.0)

# Default 3D camera of the blueprint, in the world (= left camera) frame, RDF, m: above, to the left of and
# slightly behind the stereo camera, looking at a point on the optical axis at a typical endoscopic working
# distance, so the tool, the tissue under it, the gap arrow and the camera frustums are all in view, seen from
# the side rather than along the camera's own ray. A fixed pose (the blueprint is made before any data is
# read): for scenes much nearer or farther, the user moves the eye.
EYE_POSITION_M = (-0.085, -0.07, -0.005)  # eye position, m
EYE_TARGET_M = (0.0, 0.0, 0.085)  # point the eye looks at, m
EYE_UP = (0.0, -1.0, 0.0)  # up direction of the eye (-y in RDF)


def layer_legend() -> str:
    """The layer classes and the patch in words, for every instrument at once ("fill: the instrument's colour ·
    yellow: excluded ring · ..."): Rerun shows no legend for a SegmentationImage (a class's name appears only on
    hover), so the contact pane carries it, built from the same styles as the AnnotationContext."""
    ring_and_band = [f"{s.colour_name}: {s.name.split()[-1]}" for s in LAYER_STYLES[3:] if s.rgba[3] > 0]
    return " · ".join(["tool: its colour, edge lighter", *ring_and_band, "box: patch"])


DEPTH_LEGEND = "depth: red = none; SGBM fine inside cyan, coarse dimmed"


def default_blueprint(*, with_right: bool = True, with_model: bool = True,
                      with_kinematics: bool = False, with_lag: bool = False, root: str | None = None) -> rrb.Blueprint:
    """The layout sent with every recording: images over the 3D scene and the contact pane on the left, stacked time
    series on the right. Readable in a 1280x720 window: short titles, one colour per instrument everywhere.

    Left column, top: the left image with every instrument's layers, patch box and label (large), and beside it
    the right image over the depth image with the same layers (each a quarter of the left image's area, so the
    three images fill their panes with little letterboxing). Where SGBM depth was computed in two parts, the
    depth image's pixels without depth are red and, with SGBM depth, the coarse part is dimmed and the fine region
    outlined in cyan (rerun_log.DepthKindLayer; the contact pane names the colours). Below: the 3D scene (RGB cloud, patch points, gap segments, camera
    frustums; the depth image's own back-projection is in the scene but hidden until toggled on), seen from the
    side (EYE_*), and beside it the contact pane (ENTITY_CONTACT: which instrument is in contact, each one's
    distance and posterior, and the legend of the colours). Right column, on the global ``frame`` axis:
    distance, signal (its whole range, the cap at 4 included), force, contact (truth, posterior, threshold,
    prediction; each instrument's posterior in its colour), with a model the evidence for contact beneath it
    (each instrument's log-likelihood ratio: why the posterior moves) and, in tabs, the diagnostics (each check's score and
    markers, with a legend), the text log, and with ``with_kinematics`` the tool-tip error, with ``with_lag``
    (--follow) the lag of each frame (files complete -> logged, ms). ``root``: the entity root the session was
    logged under (``contact_viz.log_session(..., root=...)``; None: the debugger's own paths).
    """
    at = partial(root_path, root)
    linked = rrb.TimeAxis(link=rrb.components.LinkAxis.LinkToGlobal)
    left = rrb.Spatial2DView(name="left image", origin=at(ENTITY_LEFT_CAMERA))
    # (a quarter of the window wide: its colours are named in the contact pane)
    depth = rrb.Spatial2DView(name="depth", origin=at(ENTITY_DEPTH_CAMERA))
    scene = rrb.Spatial3DView(
        name="3D: cloud, patch, gap",
        origin=at(ENTITY_WORLD),
        # (/**: every instrument's layers and boxes too, under <entity>/tools/<id>)
        contents=["+ $origin/**", f"- {at(ENTITY_LEFT_LAYERS)}/**", f"- {at(ENTITY_LEFT_PATCH)}/**",
                  f"- {at(ENTITY_DEPTH_LAYERS)}/**", f"- {at(ENTITY_DEPTH_PATCH)}/**", f"- {at(ENTITY_DEPTH_KIND)}",
                  f"- {at(ENTITY_LEFT_CAMERA)}/labels/**"],
        # the depth image's own back-projection duplicates the RGB cloud: there, but hidden until toggled on
        overrides={at(ENTITY_DEPTH_IMAGE): rrb.EntityBehavior(visible=False)},
        line_grid=rrb.LineGrid3D(visible=False),
        eye_controls=rrb.EyeControls3D(position=EYE_POSITION_M, look_target=EYE_TARGET_M, eye_up=EYE_UP),
    )
    if with_right:
        right = rrb.Spatial2DView(name="right image", origin=at(ENTITY_RIGHT_CAMERA))
        images = rrb.Horizontal(left, rrb.Vertical(right, depth), column_shares=[2, 1])
    else:
        images = rrb.Horizontal(left, depth, column_shares=[1, 1])
    contact = rrb.TextDocumentView(name="contact", origin=at(ENTITY_CONTACT))
    # (no legend: a short plot shows the first three entries of its legend only, and the truth came last)
    contact_name = "contact · yellow: truth · band: predicted · P per instrument" if with_model else \
        "contact · yellow: ground truth"
    series = [
        # the legends name the instruments (a session of one has a single entry, "distance (mm)")
        rrb.TimeSeriesView(name=f"distance (mm; the axis ends at {DISTANCE_RANGE[1]:g})", origin=at(ENTITY_SERIES_DISTANCE),
                           axis_x=linked, axis_y=rrb.ScalarAxis(range=DISTANCE_RANGE),
                           plot_legend=rrb.PlotLegend(rrb.components.Corner2D.RightTop)),
        rrb.TimeSeriesView(name="signal -log10 max(|d|, 1e-4 m)", origin=at(ENTITY_SERIES_SIGNAL), axis_x=linked,
                           axis_y=rrb.ScalarAxis(range=SIGNAL_RANGE),
                           plot_legend=rrb.PlotLegend(rrb.components.Corner2D.LeftTop)),
        # (the magnitude only: a short plot shows three legend entries; the components are in the recording)
        rrb.TimeSeriesView(name="force |F| (N)", origin=at(ENTITY_SERIES_FORCE), axis_x=linked,
                           contents=[f"+ {at(ENTITY_SERIES_FORCE)}/magnitude"], plot_legend=rrb.PlotLegend(visible=False)),
        rrb.TimeSeriesView(name=contact_name, origin=at(ENTITY_SERIES_CONTACT), axis_x=linked,
                           axis_y=rrb.ScalarAxis(range=(-0.05, 1.05)), plot_legend=rrb.PlotLegend(visible=False)),
        *([rrb.TimeSeriesView(name="evidence for contact: log LR (> 0: contact)", origin=at(ENTITY_SERIES_EVIDENCE),
                              axis_x=linked, axis_y=rrb.ScalarAxis(range=EVIDENCE_RANGE),
                              plot_legend=rrb.PlotLegend(visible=False))] if with_model else []),
        rrb.Tabs(
            rrb.TimeSeriesView(name="checks: score (> 1 fires), markers where fired", origin=at(ENTITY_SERIES_DIAGNOSTICS),
                               axis_x=linked, axis_y=rrb.ScalarAxis(range=DIAGNOSTICS_RANGE),
                               plot_legend=rrb.PlotLegend(rrb.components.Corner2D.LeftTop)),
            rrb.TextLogView(name="log", origin=at(ENTITY_LOG)),
            *([rrb.TimeSeriesView(name="tool tip: kinematic vs mask (px, mm)", origin=at(ENTITY_SERIES_TIP),
                                  axis_x=linked)] if with_kinematics else []),
            *([rrb.TimeSeriesView(name="lag: files complete -> logged (ms)", origin=at(ENTITY_SERIES_LAG),
                                  axis_x=linked)] if with_lag else []),
            active_tab=0,
        ),
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(images, rrb.Horizontal(scene, contact, column_shares=[3, 1]), row_shares=[0.5, 0.5]),
            rrb.Vertical(*series, row_shares=[1.2, 0.9, 0.8, 1.1, *([0.8] if with_model else []), 1.2]),
            column_shares=[3, 2],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        # a finished session opens paused at its first frame (a followed one follows its newest frame)
        rrb.TimePanel(state="collapsed", timeline=TIMELINE_FRAME, play_state=None if with_lag else "paused"),
    )
