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
    "DEPTH_FINE_EDGE",
    "DEPTH_KIND_DRAW_ORDER",
    "DEPTH_KIND_STYLES",
    "DEPTH_LAYER_OPACITY",
    "DEPTH_NONE",
    "DIAGNOSTIC_STYLES",
    "INSTRUMENT_COLOURS",
    "InstrumentStyle",
    "LAYER_OVERLAY_OPACITY",
    "LAYER_STYLES",
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


# One colour per instrument (SAM2 object id), the same in every pane and on every frame: its interior and edge on the
# images, its patch box and label, its points and gap in 3D, its distance, signal and posterior lines. Instrument k
# takes INSTRUMENT_COLOURS[(k - 1) % 5]. Bright hues that read on red tissue, on the grey tool and on the viewer's
# dark plot background, unlike the excluded ring's yellow and the exterior band's green (the same on every
# instrument: what a class is reads the same everywhere).
LIME: RGBA = (150, 230, 40, 255)
VIOLET: RGBA = (175, 125, 255, 255)
MAGENTA: RGBA = (255, 85, 215, 255)
INSTRUMENT_COLOURS: tuple[tuple[RGBA, str], ...] = (
    (SKY_BLUE, "sky blue"), (ORANGE, "orange"), (MAGENTA, "magenta"), (LIME, "lime"), (VIOLET, "violet"),
)
TOWARDS_WHITE = 0.45  # an instrument's edge and tool points: its colour this far towards white, 0-1


def _lighter(rgba: RGBA, towards_white: float = TOWARDS_WHITE) -> RGBA:
    """``rgba`` mixed with white (the tool edge and tool points of an instrument, lighter than its interior)."""
    return tuple(int(round(c + (255 - c) * towards_white)) for c in rgba[:3]) + (rgba[3],)  # type: ignore[return-value]


def _layer_styles(rgba: RGBA, colour_name: str, prefix: str = "") -> tuple[LayerStyle, ...]:
    """The layer classes of an instrument drawn in ``rgba``: its interior and edge in its colour, the ring and
    the band in theirs."""
    return (
        LayerStyle(LAYER_BACKGROUND, "background", TRANSPARENT),
        LayerStyle(LAYER_INTERIOR, f"{prefix}tool interior", with_alpha(rgba, INTERIOR_ALPHA), colour_name),
        LayerStyle(LAYER_TOOL_EDGE, f"{prefix}tool edge (excluded)", with_alpha(_lighter(rgba), THIN_LAYER_ALPHA),
                   f"light {colour_name}"),
        LayerStyle(LAYER_RING, f"{prefix}excluded ring", with_alpha(YELLOW, THIN_LAYER_ALPHA), "yellow"),
        LayerStyle(LAYER_BAND, f"{prefix}exterior band", with_alpha(BLUISH_GREEN, THIN_LAYER_ALPHA), "green"),
    )


LAYER_STYLES: tuple[LayerStyle, ...] = _layer_styles(*INSTRUMENT_COLOURS[0])  # instrument 1's, and the figures'


# Which kind of depth each pixel of the depth pane is: the fine stereo match (SGBM around the tools) or a depth file
# as it is, SGBM's coarse full-frame pass, or no depth at all. Chosen on the three kinds of a 1080p SGBM session
# seen in the web viewer (benchmarks/check_viewers.py): the fine region reaches only 10-25 px past the tool at 1080p
# (2-4 px of the depth pane), so its edge is drawn in cyan; the coarse depth is dimmed and cooled by a dark blue veil
# (the grey depth still reads under it); no depth is a solid dark red, unlike any depth grey, the veil, or a layer
# or instrument colour.
DEPTH_FINE = 1  # class id: the fine stereo match (the tools and the background around them), or a depth file's depth
DEPTH_COARSE = 2  # class id: the coarse full-frame pass, at reduced resolution
DEPTH_NONE = 3  # class id: no valid depth
DEPTH_FINE_EDGE = 4  # class id: the fine region's outermost pixels
DEPTH_KIND_DRAW_ORDER = -10.0  # over the depth image (Rerun's default -20), under the layer overlay (0) and box (10)
DEPTH_LAYER_OPACITY = 0.5  # the layers on the depth pane: half as opaque as on the image, the depth shows through
DEPTH_KIND_STYLES: tuple[LayerStyle, ...] = (
    LayerStyle(DEPTH_FINE, "fine stereo depth (what the patch reads)", TRANSPARENT),
    LayerStyle(DEPTH_COARSE, "coarse depth (reduced resolution, not read by the patch)", (20, 30, 90, 150), "dim"),
    LayerStyle(DEPTH_NONE, "no depth (invalid)", (150, 0, 30, 255), "red"),
    LayerStyle(DEPTH_FINE_EDGE, "fine stereo depth, its edge", (0, 225, 225, 255), "cyan"),
)


def layer_style(class_id: int) -> LayerStyle:
    """The style of layer class ``class_id`` (a LAYER_* id); KeyError naming the known ids otherwise."""
    for style in LAYER_STYLES:
        if style.class_id == class_id:
            return style
    raise KeyError(f"no layer class {class_id!r}; known ids: {[s.class_id for s in LAYER_STYLES]}")


# The selected patch and its 3D evidence, of instrument 1 (every instrument's are in its own colour:
# instrument_style): the box and its label in the instrument's colour, the band points in the band's green.
PATCH_STYLES: dict[str, RGBA] = {
    "window": SKY_BLUE,  # the N2 window of the selected patch (2D box) and its label
    "tissue_points": BLUISH_GREEN,  # band pixels of the N2 window whose distance entered the median (3D)
    "tool_points": _lighter(SKY_BLUE),  # interior pixels of N1 whose depth gave the tool depth (3D)
    "gap": SKY_BLUE,  # the gap: the tool depth to the tissue along the patch centre's ray (3D)
}

# The robot's tool tip (view --hand-eye): white kinematic tip, cyan mask tip (both unlike any layer or instrument
# colour), and the tool frame's axes in the usual x/y/z = red/green/blue.
KINEMATIC_STYLES: dict[str, tuple] = {
    "tip": WHITE,  # the kinematic tool tip (3D point, and its projection on the left image)
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


# Keys are the series' short names, used by the viewer to pick entity paths. The distance, signal and posterior
# lines are instrument 1's colour (every other instrument's are in its own: instrument_style).
# Contact: Rerun draws a plot's series in entity-path order (posterior, predicted, threshold, truth; seen
# on screenshots of Rerun 0.41), so the prediction is a wide translucent band over the thinner posterior, and
# the truth a yellow line on top: where prediction and truth disagree reads at a glance.
SERIES_STYLES: dict[str, SeriesStyle] = {
    "distance_mm": SeriesStyle("distance (mm)", SKY_BLUE, 2.0),
    "signal": SeriesStyle("signal", SKY_BLUE, 2.0),
    "force_n": SeriesStyle("|F| (N)", LIGHT_GREY, 2.0),
    # components hidden at start: with them the plot spans negative and positive newtons, too many unit
    # steps for its height, and the viewer then labels only 0 on the y axis
    "force_x_n": SeriesStyle("Fx (N)", BLUE, 1.0, visible=False),
    "force_y_n": SeriesStyle("Fy (N)", BLUISH_GREEN, 1.0, visible=False),
    "force_z_n": SeriesStyle("Fz (N)", VERMILLION, 1.0, visible=False),
    "contact_truth": SeriesStyle("truth", YELLOW, 2.0, step=True),
    "posterior": SeriesStyle("P(contact)", SKY_BLUE, 3.0),
    # with several instruments the scene's posterior is the max over the instruments: in none of their colours, a
    # grey that reads on the viewer's dark plots and on its light ones (the web viewer in a light-themed browser)
    "scene_posterior": SeriesStyle("P(contact), max", (110, 110, 110, 255), 2.5),
    "threshold": SeriesStyle("threshold", GREY, 1.0),
    "predicted": SeriesStyle("predicted", with_alpha(VERMILLION, 150), 7.0, step=True),
    # the emission log-likelihood ratio the filter adds per frame (each instrument's in its own colour)
    "contact_evidence": SeriesStyle("evidence (log LR)", SKY_BLUE, 2.0),
    "invalid_depth_fraction": SeriesStyle("invalid depth in the band", LIGHT_GREY, 1.5),
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
    "not_rectified": SeriesStyle("left and right not rectified", BLUE, 6.0),
}


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
    """The style of instrument ``tool`` (object id >= 1): INSTRUMENT_COLOURS by id (the same id gets the same
    colour in every frame and session; instrument 1 the single-instrument colours, LAYER_STYLES and PATCH_STYLES)."""
    tool = int(tool)
    if tool < 1:
        raise ValueError(f"tool: expected an object id >= 1 (0 is background), got {tool}")
    rgba, colour_name = INSTRUMENT_COLOURS[(tool - 1) % len(INSTRUMENT_COLOURS)]
    layers = LAYER_STYLES if tool == 1 else _layer_styles(rgba, colour_name, f"instrument {tool}: ")
    return InstrumentStyle(tool, colour_name, layers, rgba, PATCH_STYLES["tissue_points"], _lighter(rgba), rgba,
                           rgba, rgba)


def to_float_rgba(rgba: RGBA) -> tuple[float, float, float, float]:
    """An 8-bit RGBA colour as floats in [0, 1] (matplotlib's form)."""
    return tuple(channel / 255.0 for channel in rgba)  # type: ignore[return-value]
