"""Names and colours of everything the viewer and the paper figures draw: the ONE source of both.

Layer classes are the ``LAYER_*`` ids of :class:`contact_viz.geometry.patch.PatchResult.layer_ids`; the
Rerun ``AnnotationContext`` and the figure legends are both built from :data:`LAYER_STYLES`, so a
class is called and coloured the same everywhere. Colours are the colour-blind-safe Okabe-Ito
palette, as 8-bit RGBA tuples; :func:`to_float_rgba` converts one for matplotlib. The alpha of a
layer colour is that class's overlay opacity (the thin exclusion and band layers are drawn more
opaque than the tool interior, so the tool stays visible and the thin rings stay legible). Series
colours are chosen to read on the viewer's dark plot background (no near-black lines).

Pure data: no imports beyond the patch ids.
"""

from __future__ import annotations

from dataclasses import dataclass

from contact_viz.geometry.patch import LAYER_BACKGROUND, LAYER_BAND, LAYER_INTERIOR, LAYER_RING, LAYER_TOOL_EDGE

__all__ = [
    "DEPTH_COARSE",
    "DEPTH_COLORMAP",
    "DEPTH_FINE",
    "DEPTH_KIND_DRAW_ORDER",
    "DEPTH_KIND_STYLES",
    "DIAGNOSTIC_STYLES",
    "INSTRUMENT_COLOURS",
    "InstrumentStyle",
    "LAYER_OVERLAY_OPACITY",
    "LAYER_STYLES",
    "PATCH_COLOUR_NAME",
    "PATCH_STYLES",
    "SERIES_STYLES",
    "LayerStyle",
    "SeriesStyle",
    "instrument_style",
    "layer_style",
    "to_float_rgba",
    "with_alpha",
]

RGBA = tuple[int, int, int, int]

# Okabe-Ito colour-blind-safe palette, 8-bit RGBA.
BLACK: RGBA = (0, 0, 0, 255)
ORANGE: RGBA = (230, 159, 0, 255)
SKY_BLUE: RGBA = (86, 180, 233, 255)
BLUISH_GREEN: RGBA = (0, 158, 115, 255)
YELLOW: RGBA = (240, 228, 66, 255)
BLUE: RGBA = (0, 114, 178, 255)
VERMILLION: RGBA = (213, 94, 0, 255)
REDDISH_PURPLE: RGBA = (204, 121, 167, 255)
GREY: RGBA = (150, 150, 150, 255)
LIGHT_GREY: RGBA = (215, 215, 215, 255)
WHITE: RGBA = (255, 255, 255, 255)
TRANSPARENT: RGBA = (0, 0, 0, 0)

INTERIOR_ALPHA = 110  # overlay alpha of the tool interior (a large area over the tool), 0-255
THIN_LAYER_ALPHA = 235  # overlay alpha of the thin layers (tool edge, excluded ring, exterior band), 0-255

LAYER_OVERLAY_OPACITY = 1.0  # overall opacity of the layer overlay (per class: the alpha of its colour), 0-1
DEPTH_COLORMAP = "Grayscale"  # Rerun colormap of the depth image: grey, so the coloured layer overlay stands out


def with_alpha(rgba: RGBA, alpha: int) -> RGBA:
    """``rgba`` with its alpha replaced by ``alpha`` (0-255)."""
    return (rgba[0], rgba[1], rgba[2], alpha)


@dataclass(frozen=True)
class LayerStyle:
    """One class of the layer image."""

    class_id: int  # LAYER_* id in PatchResult.layer_ids
    name: str  # label shown in the viewer and figure legends
    rgba: RGBA  # colour, 8-bit RGBA (alpha 0 = not drawn)
    colour_name: str = ""  # the colour in words, for legends that cannot show a swatch (view titles)


LAYER_STYLES: tuple[LayerStyle, ...] = (
    LayerStyle(LAYER_BACKGROUND, "background", TRANSPARENT),
    LayerStyle(LAYER_INTERIOR, "tool interior", with_alpha(BLUE, INTERIOR_ALPHA), "blue"),
    LayerStyle(LAYER_TOOL_EDGE, "tool edge (excluded)", with_alpha(SKY_BLUE, THIN_LAYER_ALPHA), "sky blue"),
    LayerStyle(LAYER_RING, "excluded ring", with_alpha(YELLOW, THIN_LAYER_ALPHA), "yellow"),
    LayerStyle(LAYER_BAND, "exterior band", with_alpha(BLUISH_GREEN, THIN_LAYER_ALPHA), "green"),
)


# Which kind of depth each pixel of the depth pane is (SGBM depth with masks: contact_viz.io.session.Frame.depth_fine).
# The fine match is left as it is; the coarse pass's (reduced resolution, read by nothing the patch measures) is
# tinted, lightly enough that the depth under it still reads.
DEPTH_FINE = 1  # class id: the fine stereo match (the tools and the background around them)
DEPTH_COARSE = 2  # class id: the coarse full-frame pass, at reduced resolution
COARSE_DEPTH_ALPHA = 90  # overlay alpha of the coarse depth's tint, 0-255
DEPTH_KIND_DRAW_ORDER = -10.0  # over the depth image (Rerun's default -20), under the layer overlay (0) and box (10)
DEPTH_KIND_STYLES: tuple[LayerStyle, ...] = (
    LayerStyle(DEPTH_FINE, "fine stereo depth (what the patch reads)", TRANSPARENT),
    LayerStyle(DEPTH_COARSE, "coarse depth (reduced resolution, not read by the patch)",
               with_alpha(REDDISH_PURPLE, COARSE_DEPTH_ALPHA), "purple tint"),
)


def layer_style(class_id: int) -> LayerStyle:
    """The style of layer class ``class_id`` (a LAYER_* id); KeyError naming the known ids otherwise."""
    for style in LAYER_STYLES:
        if style.class_id == class_id:
            return style
    raise KeyError(f"no layer class {class_id!r}; known ids: {[s.class_id for s in LAYER_STYLES]}")


# The selected patch and its 3D evidence. White: it must read on red tissue, on the grey depth image
# and over the coloured layers alike (vermillion vanished on tissue), and its label text takes its colour.
PATCH_COLOUR_NAME = "white"  # PATCH_STYLES["window"] in words, for the view title
PATCH_STYLES: dict[str, RGBA] = {
    "window": WHITE,  # the N2 window of the selected patch (2D box)
    "tissue_points": BLUISH_GREEN,  # band pixels of the N2 window whose distance entered the median (3D)
    "tool_points": SKY_BLUE,  # interior pixels of N1 whose depth gave the tool depth (3D)
    "gap": WHITE,  # arrow from the tool depth to the tissue along the patch centre's ray (3D)
}

# The robot's tool tip (view --hand-eye): magenta kinematic tip, cyan mask tip (both unlike any layer
# colour), and the tool frame's axes in the usual x/y/z = red/green/blue.
KINEMATIC_STYLES: dict[str, tuple] = {
    "tip": (255, 0, 255, 255),  # the kinematic tool tip (3D point, and its projection on the left image)
    "mask": (0, 255, 255, 255),  # the tip estimated from the mask (left image)
    "axes": ((255, 0, 0, 255), (0, 200, 0, 255), (0, 80, 255, 255)),  # tool frame x, y, z (3D arrows)
}


@dataclass(frozen=True)
class SeriesStyle:
    """How one time series is drawn."""

    name: str  # legend name
    rgba: RGBA  # line / marker colour, 8-bit RGBA
    width_px: float  # line width (or marker size for point series), UI px
    step: bool = False  # drawn as a step function (0/1 states) instead of a straight-line interpolation
    visible: bool = True  # shown when the viewer opens (False: listed in the legend, one click shows it)


# Keys are the series' short names, used by the viewer to pick entity paths.
# Contact: Rerun draws a plot's series in entity-path order (posterior, predicted, threshold, truth; seen
# on screenshots of Rerun 0.41), so the prediction is a wide band over the thinner posterior, which shows
# wherever it is not within the band's half-width of 0 or 1, and the truth is a hairline on top: where
# prediction and truth disagree reads at a glance, and the posterior's ramps around each switch stay visible.
SERIES_STYLES: dict[str, SeriesStyle] = {
    "distance_mm": SeriesStyle("distance (mm)", ORANGE, 2.0),
    "signal": SeriesStyle("signal -log10 max(|d|, eps), d in m", REDDISH_PURPLE, 2.0),
    "force_n": SeriesStyle("|F| (N)", LIGHT_GREY, 2.0),
    # components hidden at start: with them the plot spans negative and positive newtons, too many unit
    # steps for its height, and the viewer then labels only 0 on the y axis
    "force_x_n": SeriesStyle("Fx (N)", SKY_BLUE, 1.0, visible=False),
    "force_y_n": SeriesStyle("Fy (N)", BLUISH_GREEN, 1.0, visible=False),
    "force_z_n": SeriesStyle("Fz (N)", ORANGE, 1.0, visible=False),
    "contact_truth": SeriesStyle("ground truth contact (0/1)", WHITE, 1.5, step=True),
    "posterior": SeriesStyle("HMM posterior P(contact)", SKY_BLUE, 3.0),
    "threshold": SeriesStyle("decision threshold", GREY, 1.0),
    "predicted": SeriesStyle("predicted contact (0/1)", VERMILLION, 7.0, step=True),
    "invalid_depth_fraction": SeriesStyle("invalid depth in band (fraction)", LIGHT_GREY, 1.5),
}

# One colour per diagnostic code (contact_viz.checks.rules), for its score line and its markers where it fires.
DIAGNOSTIC_STYLES: dict[str, SeriesStyle] = {
    "bad_frame": SeriesStyle("bad frame", WHITE, 6.0),
    "mask_dropout": SeriesStyle("mask dropout", SKY_BLUE, 6.0),
    "extra_blob": SeriesStyle("extra mask blob", BLUE, 6.0),
    "mask_area_jump": SeriesStyle("mask area jump", ORANGE, 6.0),
    "id_swap": SeriesStyle("instrument ids swapped", YELLOW, 6.0),
    "tools_merged": SeriesStyle("instruments merged", SKY_BLUE, 6.0),
    "mask_image_edges": SeriesStyle("mask off image edges", YELLOW, 6.0),
    "mask_on_tissue": SeriesStyle("mask rim on tissue depth", BLUISH_GREEN, 6.0),
    "tool_depth_outside": SeriesStyle("tool depth outside mask", REDDISH_PURPLE, 6.0),
    "depth_holes": SeriesStyle("depth holes at the tool", GREY, 6.0),
    "tool_width": SeriesStyle("tool width vs diameter", LIGHT_GREY, 6.0),
    "stereo_residual": SeriesStyle("stereo residual", VERMILLION, 6.0),
    "frozen_depth": SeriesStyle("frozen depth", WHITE, 6.0),
    "no_patch": SeriesStyle("no valid patch", REDDISH_PURPLE, 6.0),
    "distance_jump": SeriesStyle("distance jump", VERMILLION, 6.0),
    "force_lag": SeriesStyle("force out of sync", ORANGE, 6.0),
    "frame_times": SeriesStyle("frame time gaps", GREY, 6.0),
}


# Several instruments (SAM2 object ids): each has a colour of its own, the same on every frame, picked by object
# id. Instrument 1 keeps the single-instrument colours above (blue interior, white box and gap arrow, orange
# distance line); instrument k >= 2 is drawn in INSTRUMENT_COLOURS[(k - 2) % 5]: its interior, tool edge, tool
# points, box, gap arrow and series. The excluded ring and the exterior band keep their yellow and green on every
# instrument (what a class is reads the same everywhere; hovering names the instrument). Bright hues unlike
# instrument 1's colours and the ring / band, readable on red tissue, the grey tool and the dark plot background.
LIME: RGBA = (150, 230, 40, 255)
VIOLET: RGBA = (175, 125, 255, 255)
MAGENTA: RGBA = (255, 85, 215, 255)
CYAN: RGBA = (0, 225, 225, 255)
SALMON: RGBA = (255, 130, 100, 255)
INSTRUMENT_COLOURS: tuple[tuple[RGBA, str], ...] = (
    (LIME, "lime"), (VIOLET, "violet"), (MAGENTA, "magenta"), (CYAN, "cyan"), (SALMON, "salmon"),
)
INSTRUMENT_POSTERIOR_WIDTH_PX = 1.5  # an instrument's own posterior line, over the scene's (SERIES_STYLES)


@dataclass(frozen=True)
class InstrumentStyle:
    """How one instrument (object id) is drawn, on every frame."""

    tool: int  # object id
    colour_name: str  # its colour in words (instrument 1: its interior's)
    layers: tuple[LayerStyle, ...]  # its layer classes (LAYER_STYLES' ids; instrument 1: LAYER_STYLES itself)
    window: RGBA  # the patch box (2D)
    tissue_points: RGBA  # band pixels of the patch (3D)
    tool_points: RGBA  # interior pixels behind the tool depth (3D)
    gap: RGBA  # the gap arrow (3D)
    line: RGBA  # its distance line and its own posterior line
    signal: RGBA  # its signal line

    @property
    def name(self) -> str:
        return f"instrument {self.tool}"


def instrument_style(tool: int) -> InstrumentStyle:
    """The style of instrument ``tool`` (object id >= 1): instrument 1 in the single-instrument colours,
    the others in INSTRUMENT_COLOURS by id (the same id gets the same colour in every frame and session)."""
    tool = int(tool)
    if tool < 1:
        raise ValueError(f"tool: expected an object id >= 1 (0 is background), got {tool}")
    if tool == 1:
        return InstrumentStyle(1, "blue", LAYER_STYLES, PATCH_STYLES["window"], PATCH_STYLES["tissue_points"],
                               PATCH_STYLES["tool_points"], PATCH_STYLES["gap"], SERIES_STYLES["distance_mm"].rgba,
                               SERIES_STYLES["signal"].rgba)
    rgba, colour_name = INSTRUMENT_COLOURS[(tool - 2) % len(INSTRUMENT_COLOURS)]
    light = _lighter(rgba)
    own = {LAYER_INTERIOR: with_alpha(rgba, INTERIOR_ALPHA), LAYER_TOOL_EDGE: with_alpha(light, THIN_LAYER_ALPHA)}
    layers = tuple(LayerStyle(s.class_id, s.name if s.class_id == LAYER_BACKGROUND else f"instrument {tool}: {s.name}",
                              own.get(s.class_id, s.rgba),
                              colour_name if s.class_id in own else s.colour_name) for s in LAYER_STYLES)
    return InstrumentStyle(tool, colour_name, layers, rgba, PATCH_STYLES["tissue_points"], light, rgba, rgba, rgba)


def _lighter(rgba: RGBA, towards_white: float = 0.45) -> RGBA:
    """``rgba`` mixed with white (the tool edge and tool points of an instrument, lighter than its interior)."""
    return tuple(int(round(c + (255 - c) * towards_white)) for c in rgba[:3]) + (rgba[3],)  # type: ignore[return-value]


def to_float_rgba(rgba: RGBA) -> tuple[float, float, float, float]:
    """An 8-bit RGBA colour as floats in [0, 1] (matplotlib's form)."""
    return tuple(channel / 255.0 for channel in rgba)  # type: ignore[return-value]
