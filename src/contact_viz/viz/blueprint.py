"""The default layout sent with every recording (Rerun blueprint), in its own module as Rerun's examples keep it."""

from __future__ import annotations

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
    ENTITY_SERIES_FORCE,
    ENTITY_SERIES_LAG,
    ENTITY_SERIES_SIGNAL,
    ENTITY_SERIES_TIP,
    ENTITY_WORLD,
    TIMELINE_FRAME,
)
from contact_viz.viz.style import DEPTH_KIND_STYLES, LAYER_STYLES, PATCH_COLOUR_NAME

__all__ = ["SCORE_CLIP", "default_blueprint", "depth_kind_legend", "layer_legend"]

SCORE_CLIP = 3.0  # diagnostic scores (value / threshold) are drawn clipped at this, ratio

# Default 3D camera of the blueprint, in the world (= left camera) frame, RDF, m: above, to the left of and
# slightly behind the stereo camera, looking at a point on the optical axis at a typical endoscopic working
# distance, so the tool, the tissue under it, the gap arrow and the camera frustums are all in view, seen from
# the side rather than along the camera's own ray. A fixed pose (the blueprint is made before any data is
# read): for scenes much nearer or farther, the user moves the eye.
EYE_POSITION_M = (-0.085, -0.07, -0.005)  # eye position, m
EYE_TARGET_M = (0.0, 0.0, 0.085)  # point the eye looks at, m
EYE_UP = (0.0, -1.0, 0.0)  # up direction of the eye (-y in RDF)


def layer_legend() -> str:
    """The drawn layer classes in words ("blue: tool interior · ..."), for a view title.

    Rerun shows no legend for a SegmentationImage (a class's name appears only on hover), so the
    left image's title carries it, built from the same styles as the AnnotationContext.
    """
    return " · ".join(f"{s.colour_name}: {s.name}" for s in LAYER_STYLES if s.rgba[3] > 0)


def depth_kind_legend() -> str:
    """The drawn depth kinds in words ("purple tint: coarse depth"), for the depth view's title (the full
    names, with what the patch reads, show on hover)."""
    return " · ".join(f"{s.colour_name}: {s.name.split(' (')[0]}" for s in DEPTH_KIND_STYLES if s.rgba[3] > 0)


def default_blueprint(*, with_right: bool = True, with_model: bool = True,
                      with_kinematics: bool = False, with_depth_kind: bool = True,
                      with_lag: bool = False) -> rrb.Blueprint:
    """The layout sent with every recording: images over the 3D scene on the left, stacked time series on the right.

    Left column, top: the left image with the layer overlay and the patch box (large; its title
    names the layer colours), and beside it the right image over the depth image with the same
    overlay (each a quarter of the left image's area, so the three images fill their panes with
    little letterboxing); every instrument's layers and box are drawn, each in its own colours
    (contact_viz.viz.style.instrument_style). Below: the 3D scene (RGB cloud, patch points, gap
    arrows, camera frustums; the depth image's own back-projection is in the scene but hidden until
    toggled on), seen from the side (EYE_*). Where SGBM depth was computed in two parts, the depth
    image's coarse part is tinted (:class:`DepthKindLayer`; the depth view's title names the tint unless ``with_depth_kind``
    is False). Right column: distance, signal, force, contact (truth / posterior / threshold
    / prediction) and diagnostics, all on the global ``frame`` axis, the text log and the instrument in
    contact (ENTITY_CONTACT) in tabs beside the diagnostics. The distance, signal and contact plots show
    every instrument's series (children of their origin: entities.tool_entity), the contact plot the
    scene's posterior with each instrument's own as a thin line in its colour. The plots' legends (which
    name the instruments) sit in a corner that the approach phase mostly leaves free. ``with_lag``
    (--follow): a tab with the lag of each frame (files complete -> logged, ms).
    """
    linked = rrb.TimeAxis(link=rrb.components.LinkAxis.LinkToGlobal)
    left = rrb.Spatial2DView(name=f"left · {layer_legend()}", origin=ENTITY_LEFT_CAMERA)
    depth_name = f"depth + layers · {PATCH_COLOUR_NAME} box: patch"
    if with_depth_kind:
        depth_name += f" · {depth_kind_legend()}"
    # (its contents, everything under the depth camera, take the depth kinds of ENTITY_DEPTH_KIND too)
    depth = rrb.Spatial2DView(name=depth_name, origin=ENTITY_DEPTH_CAMERA)
    scene = rrb.Spatial3DView(
        name="3D: cloud, patch points, gap",
        origin=ENTITY_WORLD,
        # (/**: every instrument's layers and boxes too, under <entity>/tools/<id>)
        contents=["+ $origin/**", f"- {ENTITY_LEFT_LAYERS}/**", f"- {ENTITY_LEFT_PATCH}/**",
                  f"- {ENTITY_DEPTH_LAYERS}/**", f"- {ENTITY_DEPTH_PATCH}/**", f"- {ENTITY_DEPTH_KIND}"],
        # the depth image's own back-projection duplicates the RGB cloud: there, but hidden until toggled on
        overrides={ENTITY_DEPTH_IMAGE: rrb.EntityBehavior(visible=False)},
        line_grid=rrb.LineGrid3D(visible=False),
        eye_controls=rrb.EyeControls3D(position=EYE_POSITION_M, look_target=EYE_TARGET_M, eye_up=EYE_UP),
    )
    if with_right:
        right = rrb.Spatial2DView(name="right image", origin=ENTITY_RIGHT_CAMERA)
        images = rrb.Horizontal(left, rrb.Vertical(right, depth), column_shares=[2, 1])
    else:
        images = rrb.Horizontal(left, depth, column_shares=[1, 1])
    contact_name = ("contact (0/1): truth, HMM posterior, threshold, prediction · thin: each instrument's posterior"
                    if with_model else "contact (0/1): ground truth")
    diagnostics_top = SCORE_CLIP + 0.1
    series = [
        # the legends name the instruments (a session of one has a single entry, "distance (mm)")
        rrb.TimeSeriesView(name="distance (mm)", origin=ENTITY_SERIES_DISTANCE, axis_x=linked,
                           plot_legend=rrb.PlotLegend(rrb.components.Corner2D.RightTop)),
        rrb.TimeSeriesView(name="signal -log10 max(|d|, eps), d in m", origin=ENTITY_SERIES_SIGNAL, axis_x=linked,
                           plot_legend=rrb.PlotLegend(rrb.components.Corner2D.LeftTop)),
        rrb.TimeSeriesView(name="force (N)", origin=ENTITY_SERIES_FORCE, axis_x=linked,
                           plot_legend=rrb.PlotLegend(rrb.components.Corner2D.LeftTop)),
        rrb.TimeSeriesView(name=contact_name, origin=ENTITY_SERIES_CONTACT, axis_x=linked,
                           axis_y=rrb.ScalarAxis(range=(-0.05, 1.05)),
                           plot_legend=rrb.PlotLegend(rrb.components.Corner2D.LeftTop)),
        # the log shares a tab with the diagnostics plot: a sixth row would leave the plots too low for
        # the viewer to label their y axes
        rrb.Tabs(
            rrb.TimeSeriesView(name="diagnostics: score = measured / threshold (> 1 fires; markers), invalid depth",
                               origin=ENTITY_SERIES_DIAGNOSTICS, axis_x=linked,
                               axis_y=rrb.ScalarAxis(range=(-0.05, diagnostics_top)),
                               # 2 series per check: a legend would cover the plot; hover names them, `log` says why
                               plot_legend=rrb.PlotLegend(visible=False)),
            rrb.TextLogView(name="log", origin=ENTITY_LOG),
            rrb.TextDocumentView(name="instrument in contact", origin=ENTITY_CONTACT),
            *([rrb.TimeSeriesView(name="tool tip: kinematic vs mask (px, mm)", origin=ENTITY_SERIES_TIP,
                                  axis_x=linked)] if with_kinematics else []),
            *([rrb.TimeSeriesView(name="lag: files complete -> logged (ms)", origin=ENTITY_SERIES_LAG,
                                  axis_x=linked)] if with_lag else []),
            active_tab=0,
        ),
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(images, scene, row_shares=[0.47, 0.53]),
            rrb.Vertical(*series, row_shares=[1.0, 0.9, 1.2, 1.1, 1.0]),
            column_shares=[3, 2],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=TIMELINE_FRAME),
    )
