"""The paper's figures as matplotlib figures: pure functions from arrays to a ``Figure``.

* :func:`timelines_figure`: for each held-out session, the contact probability of the HMM and of
  the RGB baseline against the ground-truth contact over time, with each method's decision
  threshold (one row per session, one column per method).
* :func:`pipeline_figure`: the minimum-distance patch on one frame: (a) the tool mask over the RGB
  frame, (b) tool interior, tool edge, excluded ring and exterior band over the depth image,
  (c) a zoom on the selected patch with its N2 window and its distance.

Layer class names and colours come from :mod:`contact_viz.viz.style` (``LAYER_STYLES``,
``PATCH_STYLES``), the same source the Rerun debugger's annotation context is built from, so the
figure and the recording call and colour every class the same way. The depth image is drawn in
grey, as in the debugger (``style.DEPTH_COLORMAP``), so the coloured layers stand out.

Figures are built with matplotlib's object API on the Agg canvas (no display, no pyplot state);
:func:`save_figure` writes them atomically. Nothing here reads sessions or files.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from contact_viz.viz import style
from contact_viz.io.atomic import atomic_write
from contact_viz.geometry.patch import LAYER_BACKGROUND, LAYER_INTERIOR, PatchResult
from contact_viz.params import MM_PER_M

__all__ = [
    "FigureStyle",
    "TimelineSession",
    "layer_legend_names",
    "layer_overlay_rgba",
    "pipeline_figure",
    "save_figure",
    "timelines_figure",
]

DEPTH_CMAP = "gray"  # matplotlib colormap of the depth image (the debugger's "Grayscale")
DEPTH_PERCENTILES = (1.0, 99.0)  # depth colour range: these percentiles of the valid depth in view, %
MISSING_DEPTH_RGBA = style.to_float_rgba(style.REDDISH_PURPLE)  # invalid depth pixels (NaN)
SAVE_FORMATS = ("png", "pdf")  # default output formats of save_figure
TIMELINE_EXTRA_IN = 0.7  # height of the timelines figure beyond its session rows (legend, title), in
POINTS_PER_INCH = 72.0
AVERAGE_CHAR_WIDTH_EM = 0.55  # mean character width of the sans-serif font, in font sizes (for wrapping)
LEGEND_COLUMNS = 4  # columns of the pipeline figure's legend

# Method colours of the timelines, from the style module's colour-blind-safe palette; chosen for a
# white page (the debugger's series colours are chosen for its dark plot background).
METHOD_COLORS = (style.BLUE, style.VERMILLION)  # first method (HMM), second method (RGB baseline)
TRUTH_RGBA = style.with_alpha(style.GREY, 90)  # shading of ground-truth contact frames
THRESHOLD_RGBA = style.BLACK  # decision threshold line


@dataclass(frozen=True)
class FigureStyle:
    """Sizes of the paper figures (matplotlib units: inches and points)."""

    width_in: float = 7.16  # figure width: a two-column IEEE/Springer text width, in
    font_pt: float = 8.0  # base font size, pt
    timeline_row_in: float = 1.4  # height of one session row of the timelines figure, in
    pipeline_height_in: float = 2.75  # height of the pipeline figure, in
    line_pt: float = 1.1  # width of the probability lines, pt
    threshold_line_pt: float = 0.8  # width of the threshold lines, pt
    box_line_pt: float = 1.4  # width of the patch window box, pt
    zoom_margin_px: int = 12  # margin around the layers in panel (b), image px
    mask_alpha: float = 0.45  # opacity of the tool mask over the RGB frame in panel (a), -
    marker_pt: float = 7.0  # size of the patch centre marker, pt
    patch_zoom_windows: float = 5.0  # side of panel (c)'s view, in N2 window sides
    dpi: int = 300  # raster resolution of saved PNGs, dots per inch


class TimelineSession(NamedTuple):
    """One held-out session of the timelines figure (a plain tuple in this order works too)."""

    name: str  # session name, the row title
    category: str  # e.g. "same phantom and task", shown after the name
    time_s: np.ndarray  # (T,) float frame times, s
    labels: np.ndarray  # (T,) int ground truth 1 = contact, 0 = no contact, -1 = unknown
    hmm_posterior: np.ndarray  # (T,) float HMM P(contact) in [0, 1]
    hmm_threshold: float  # HMM decision threshold on hmm_posterior
    rgb_posterior: np.ndarray  # (T,) float RGB baseline P(contact) in [0, 1]
    rgb_threshold: float  # RGB baseline decision threshold on rgb_posterior


def _rc(fs: FigureStyle) -> dict[str, object]:
    return {
        "font.size": fs.font_pt,
        "axes.titlesize": fs.font_pt,
        "axes.labelsize": fs.font_pt,
        "xtick.labelsize": fs.font_pt - 1,
        "ytick.labelsize": fs.font_pt - 1,
        "legend.fontsize": fs.font_pt - 1,
        "axes.linewidth": 0.6,
        "pdf.fonttype": 42,  # embed TrueType fonts: text stays editable and searchable in the PDF
        "ps.fonttype": 42,
    }


def _wrap(text: str, fs: FigureStyle) -> str:
    """``text`` broken into lines that fit the figure width at the base font size."""
    import textwrap

    chars_per_line = int(fs.width_in * POINTS_PER_INCH / (fs.font_pt * AVERAGE_CHAR_WIDTH_EM))
    return textwrap.fill(text, chars_per_line)


def _new_figure(width_in: float, height_in: float):
    """A Figure on the Agg canvas with constrained layout (no pyplot, no display)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


# --------------------------------------------------------------------------------------------
# Timelines
# --------------------------------------------------------------------------------------------


def _check_timeline(i: int, s: TimelineSession) -> TimelineSession:
    who = f"sessions[{i}] ({s.name!r})"
    t = np.asarray(s.time_s, dtype=np.float64)
    if t.ndim != 1 or t.size == 0:
        raise ValueError(f"{who}: time_s: expected a non-empty 1-D array of seconds, got shape {t.shape}")
    arrays = {}
    for field in ("labels", "hmm_posterior", "rgb_posterior"):
        a = np.asarray(getattr(s, field))
        if a.shape != t.shape:
            raise ValueError(f"{who}: {field}: expected shape {t.shape} (one value per frame), got {a.shape}")
        arrays[field] = a
    if not np.isin(arrays["labels"], (-1, 0, 1)).all():
        raise ValueError(f"{who}: labels: expected values in {{-1, 0, 1}}")
    for field in ("hmm_threshold", "rgb_threshold"):
        if not np.isfinite(float(getattr(s, field))):
            raise ValueError(f"{who}: {field}: expected a finite number, got {getattr(s, field)!r}")
    return TimelineSession(str(s.name), str(s.category), t, arrays["labels"].astype(np.int64),
                           arrays["hmm_posterior"].astype(np.float64), float(s.hmm_threshold),
                           arrays["rgb_posterior"].astype(np.float64), float(s.rgb_threshold))


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Half-open index runs [start, stop) where ``mask`` is True."""
    padded = np.concatenate([[False], mask, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return list(zip(edges[0::2].tolist(), edges[1::2].tolist()))


def _frame_edges(t: np.ndarray) -> np.ndarray:
    """(T+1,) frame boundaries, s: midpoints between frame times, half a step beyond the ends."""
    if t.size == 1:
        return np.array([t[0] - 0.5, t[0] + 0.5])
    mid = (t[:-1] + t[1:]) / 2.0
    return np.concatenate([[2 * t[0] - mid[0]], mid, [2 * t[-1] - mid[-1]]])


def timelines_figure(
    sessions: Sequence[TimelineSession | tuple],
    method_names: tuple[str, str] = ("HMM", "EfficientNet"),
    fig_style: FigureStyle = FigureStyle(),
    title: str | None = None,
):
    """Contact probability of both methods against ground truth, one row per session.

    Args:
        sessions: :class:`TimelineSession` (or equal tuples), one per held-out session, in row
            order; arrays are (T,) per session: time_s (s), labels (1/0/-1), posteriors in [0, 1].
        method_names: legend / column names of the two methods (HMM first, RGB baseline second).
        fig_style: sizes. title: optional figure title (e.g. a note on the configuration).

    Returns:
        matplotlib Figure with one subfigure per session (titled with its name and category) and
        ``2 * len(sessions)`` axes in ``fig.axes`` (row-major: session i's HMM axes, then its RGB
        axes, each titled with the method and its threshold). Ground-truth contact frames are
        shaded grey; each method's posterior is a line in its colour and its threshold a dashed
        black line; frames labelled -1 (unknown) are left unshaded.
    """
    import matplotlib

    if len(sessions) == 0:
        raise ValueError("sessions: expected at least one session, got none")
    checked = [_check_timeline(i, TimelineSession(*s)) for i, s in enumerate(sessions)]
    fs = fig_style
    with matplotlib.rc_context(_rc(fs)):
        fig = _new_figure(fs.width_in, fs.timeline_row_in * len(checked) + TIMELINE_EXTRA_IN)
        rows = fig.subfigures(len(checked), 1, squeeze=False)[:, 0]
        truth_color = style.to_float_rgba(TRUTH_RGBA)
        found: dict[str, object] = {}
        for row, (subfig, s) in enumerate(zip(rows, checked)):
            subfig.suptitle(f"{s.name} ({s.category})", x=0.0, ha="left", fontweight="bold",
                            fontsize=fs.font_pt)
            axes = subfig.subplots(1, 2, sharex=True, sharey=True)
            edges = _frame_edges(s.time_s)
            series = ((s.hmm_posterior, s.hmm_threshold), (s.rgb_posterior, s.rgb_threshold))
            for col, (ax, (posterior, threshold)) in enumerate(zip(axes, series)):
                for start, stop in _runs(s.labels == 1):
                    ax.axvspan(edges[start], edges[stop], color=truth_color, lw=0, label="ground-truth contact")
                ax.plot(s.time_s, posterior, color=style.to_float_rgba(METHOD_COLORS[col]), lw=fs.line_pt,
                        label=f"{method_names[col]} P(contact)")
                ax.axhline(threshold, color=style.to_float_rgba(THRESHOLD_RGBA), lw=fs.threshold_line_pt,
                           ls=(0, (4, 2)), label="decision threshold")
                ax.set_xlim(edges[0], edges[-1])
                ax.set_ylim(-0.04, 1.04)
                ax.set_yticks([0.0, 0.5, 1.0])
                ax.grid(axis="y", lw=0.3, alpha=0.5)
                ax.set_title(f"{method_names[col]} (threshold {threshold:.2f})", loc="left",
                             color=style.to_float_rgba(METHOD_COLORS[col]))
                if col == 0:
                    ax.set_ylabel("P(contact)")
                if row == len(checked) - 1:
                    ax.set_xlabel("time (s)")
                for h, lab in zip(*ax.get_legend_handles_labels()):
                    found.setdefault(lab, h)
        order = ["ground-truth contact", *(f"{m} P(contact)" for m in method_names), "decision threshold"]
        labels = [lab for lab in order if lab in found]
        fig.legend([found[lab] for lab in labels], labels, loc="outside lower center", ncol=len(labels),
                   frameon=False)
        if title:
            fig.suptitle(_wrap(title, fs), fontsize=fs.font_pt)
    return fig


# --------------------------------------------------------------------------------------------
# Pipeline
# --------------------------------------------------------------------------------------------


def layer_overlay_rgba(layer_ids: np.ndarray) -> np.ndarray:
    """(H, W, 4) float RGBA in [0, 1] of a ``PatchResult.layer_ids`` image: each class in its
    ``style.LAYER_STYLES`` colour (alpha = the class's overlay opacity; background transparent)."""
    ids = np.asarray(layer_ids)
    if ids.ndim != 2:
        raise ValueError(f"layer_ids: expected an (H, W) array of LAYER_* ids, got shape {ids.shape}")
    lut = np.zeros((256, 4), dtype=np.float64)
    for s in style.LAYER_STYLES:
        lut[s.class_id] = style.to_float_rgba(s.rgba)
    known = [s.class_id for s in style.LAYER_STYLES]
    if not np.isin(ids, known).all():
        raise ValueError(f"layer_ids: expected LAYER_* ids {known}, found {sorted(set(np.unique(ids)) - set(known))}")
    return lut[ids.astype(np.intp)]


def layer_legend_names() -> list[str]:
    """Names of the drawn layer classes (every LAYER_STYLES class with a visible colour), in style order."""
    return [s.name for s in style.LAYER_STYLES if s.rgba[3] > 0 and s.class_id != LAYER_BACKGROUND]


def _square_view(cx: float, cy: float, side: int, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1), half-open: a view ``side`` px wide centred on (cx, cy), shifted (and, for a
    small image, shrunk) to lie inside the image of ``shape`` (H, W)."""
    height, width = shape
    side_x, side_y = min(side, width), min(side, height)
    x0 = int(np.clip(round(cx - side_x / 2), 0, width - side_x))
    y0 = int(np.clip(round(cy - side_y / 2), 0, height - side_y))
    return x0, y0, x0 + side_x, y0 + side_y


def _zoom_box(layer_ids: np.ndarray, margin_px: int) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1), half-open: a square view around every non-background layer pixel plus ``margin_px``."""
    height, width = layer_ids.shape
    rows = np.flatnonzero((layer_ids != LAYER_BACKGROUND).any(axis=1))
    if rows.size == 0:
        return 0, 0, width, height
    cols = np.flatnonzero((layer_ids != LAYER_BACKGROUND).any(axis=0))
    side = max(cols[-1] - cols[0], rows[-1] - rows[0]) + 1 + 2 * margin_px
    return _square_view((cols[0] + cols[-1] + 1) / 2.0, (rows[0] + rows[-1] + 1) / 2.0, int(side), (height, width))


def _patch_view(window: tuple[int, int, int, int], shape: tuple[int, int], windows: float,
                max_side: int) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) of a square view ``windows`` window sides (at most ``max_side`` px) wide
    around the patch, in the image."""
    x0, y0, x1, y1 = window
    side = min(int(round(windows * max(x1 - x0, y1 - y0))), max_side)
    return _square_view((x0 + x1) / 2.0, (y0 + y1) / 2.0, side, shape)


def _extent(box: tuple[int, int, int, int]) -> tuple[float, float, float, float]:
    """imshow extent (left, right, bottom, top) placing a crop at its image pixel coordinates."""
    x0, y0, x1, y1 = box
    return (x0 - 0.5, x1 - 0.5, y1 - 0.5, y0 - 0.5)


def _outlined(artist, width_pt: float = 2.0) -> None:
    """Give a white line or text a dark outline so it reads on any background."""
    from matplotlib import patheffects

    artist.set_path_effects([patheffects.Stroke(linewidth=width_pt, foreground="black"), patheffects.Normal()])


def _check_frame(left_rgb, tool_mask, depth_m, patch_result) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rgb = np.asarray(left_rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"left_rgb: expected an (H, W, 3) uint8 RGB image, got shape {rgb.shape} dtype {rgb.dtype}")
    shape = rgb.shape[:2]
    mask = np.asarray(tool_mask)
    depth = np.asarray(depth_m, dtype=np.float64)
    for name, a in (("tool_mask", mask), ("depth_m", depth)):
        if a.shape != shape:
            raise ValueError(f"{name}: expected shape {shape} (the left image's), got {a.shape}")
    if not isinstance(patch_result, PatchResult):
        raise ValueError(f"patch_result: expected a contact_viz.geometry.patch.PatchResult, got {type(patch_result).__name__}")
    if patch_result.layer_ids.shape != shape:
        raise ValueError(f"patch_result.layer_ids: expected shape {shape}, got {patch_result.layer_ids.shape}")
    return rgb, mask != 0, depth


def pipeline_figure(
    left_rgb: np.ndarray,
    tool_mask: np.ndarray,
    depth_m: np.ndarray,
    patch_result: PatchResult,
    fig_style: FigureStyle = FigureStyle(),
    title: str | None = None,
):
    """The minimum-distance patch of one frame in three panels.

    Args:
        left_rgb: (H, W, 3) uint8 rectified left image.
        tool_mask: (H, W) bool or int, nonzero = tool.
        depth_m: (H, W) float depth in m, NaN / <= 0 = invalid.
        patch_result: ``compute_patch(depth_m, tool_mask, params)`` of this frame.
        fig_style: sizes. title: optional figure title.

    Returns:
        matplotlib Figure with four axes: (a) the tool mask over the RGB frame (the dashed box is
        panel (b)'s view); (b) the layers over the grey depth image, cropped around the tool, with
        a legend of the layer classes (names and colours from ``style.LAYER_STYLES``); (c) a zoom
        on the selected patch over the RGB frame with the same layer colours, its N2 window
        (``style.PATCH_STYLES["window"]``), its centre and its distance; the fourth axes is the
        depth colour bar, mm. Panels (b) and (c) keep image pixel coordinates on their axes.
        Layer overlays are ``AxesImage`` artists with ``gid`` "layers" (panels b and c).
    """
    import matplotlib
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch, Rectangle

    rgb, mask, depth = _check_frame(left_rgb, tool_mask, depth_m, patch_result)
    fs = fig_style
    layers = patch_result.layer_ids
    overlay = layer_overlay_rgba(layers)
    zoom = _zoom_box(layers, fs.zoom_margin_px)
    zx0, zy0, zx1, zy1 = zoom
    depth_mm = np.where(np.isfinite(depth) & (depth > 0), depth * MM_PER_M, np.nan)
    in_view = depth_mm[zy0:zy1, zx0:zx1]
    valid = in_view[np.isfinite(in_view)]
    if valid.size:
        vmin, vmax = (float(v) for v in np.percentile(valid, DEPTH_PERCENTILES))
    else:
        vmin, vmax = 0.0, 1.0
    if not vmax > vmin:
        vmin, vmax = vmin - 0.5, vmax + 0.5
    cmap = matplotlib.colormaps[DEPTH_CMAP].with_extremes(bad=MISSING_DEPTH_RGBA)
    mask_rgba = style.to_float_rgba(style.layer_style(LAYER_INTERIOR).rgba)  # the tool mask: the interior's colour
    window_rgba = style.to_float_rgba(style.PATCH_STYLES["window"])

    with matplotlib.rc_context(_rc(fs)):
        fig = _new_figure(fs.width_in, fs.pipeline_height_in)
        # (b) and (c) are square views: widths in proportion to the aspect ratios give equal heights.
        ax_a, ax_b, ax_c = fig.subplots(1, 3, width_ratios=[rgb.shape[1] / rgb.shape[0], 1.0, 1.0])

        # (a) tool mask over the RGB frame
        ax_a.imshow(rgb, interpolation="antialiased")
        mask_overlay = np.zeros(mask.shape + (4,))
        mask_overlay[mask] = (*mask_rgba[:3], fs.mask_alpha)
        ax_a.imshow(mask_overlay, interpolation="nearest")
        if mask.any():
            ax_a.contour(mask.astype(np.float32), levels=[0.5], colors=[mask_rgba[:3]], linewidths=0.8)
        zoom_rect = Rectangle((zx0 - 0.5, zy0 - 0.5), zx1 - zx0, zy1 - zy0, fill=False, ec=window_rgba, lw=0.9, ls="--")
        ax_a.add_patch(zoom_rect)
        _outlined(zoom_rect, 1.8)
        ax_a.set_title("(a) tool mask on the RGB frame", loc="left")
        ax_a.legend(handles=[Patch(facecolor=(*mask_rgba[:3], fs.mask_alpha), edgecolor=mask_rgba[:3],
                                   label="tool mask")], loc="lower left", framealpha=0.85)

        # (b) interior, ring and band over the depth image
        im = ax_b.imshow(depth_mm[zy0:zy1, zx0:zx1], cmap=cmap, vmin=vmin, vmax=vmax, extent=_extent(zoom),
                         interpolation="nearest")
        ax_b.imshow(overlay[zy0:zy1, zx0:zx1], extent=_extent(zoom), interpolation="nearest", gid="layers")
        ax_b.set_title("(b) layers on the depth", loc="left")
        handles = [Patch(facecolor=style.to_float_rgba(s.rgba), edgecolor="none", label=s.name)
                   for s in style.LAYER_STYLES if s.name in layer_legend_names()]
        if valid.size < in_view.size:
            handles.append(Patch(facecolor=MISSING_DEPTH_RGBA, edgecolor="none", label="invalid depth"))
        bar = fig.colorbar(im, ax=ax_b, fraction=0.06, pad=0.02)
        bar.set_label("depth (mm)")
        bar.ax.tick_params(labelsize=fs.font_pt - 1)

        # (c) the selected patch
        ax_c.set_title("(c) selected patch", loc="left")
        if patch_result.found and patch_result.window_xyxy is not None:
            view = _patch_view(patch_result.window_xyxy, mask.shape, fs.patch_zoom_windows, max(zx1 - zx0, zy1 - zy0))
            vx0, vy0, vx1, vy1 = view
            ax_c.imshow(rgb[vy0:vy1, vx0:vx1], extent=_extent(view), interpolation="nearest")
            ax_c.imshow(overlay[vy0:vy1, vx0:vx1], extent=_extent(view), interpolation="nearest", gid="layers")
            x0, y0, x1, y1 = patch_result.window_xyxy
            box = Rectangle((x0 - 0.5, y0 - 0.5), x1 - x0, y1 - y0, fill=False, ec=window_rgba, lw=fs.box_line_pt)
            ax_c.add_patch(box)
            _outlined(box, fs.box_line_pt + 1.6)
            cx, cy = patch_result.center_xy
            (centre,) = ax_c.plot([cx], [cy], marker="+", ms=fs.marker_pt, mew=fs.box_line_pt, color=window_rgba,
                                  ls="none")
            _outlined(centre, 3.0)
            text = ax_c.text(0.03, 0.97, f"d = {patch_result.distance_m * MM_PER_M:.1f} mm",
                             transform=ax_c.transAxes, va="top", ha="left", color=window_rgba,
                             fontsize=fs.font_pt + 1, fontweight="bold")
            _outlined(text, 2.2)
            handles.append(Patch(facecolor="none", edgecolor="black", lw=fs.box_line_pt,
                                 label=f"patch window N2 ({x1 - x0}x{y1 - y0} px)"))
            handles.append(Line2D([], [], color="black", lw=0.9, label="view of (c)"))
            for ax, rect_box in ((ax_a, view), (ax_b, view)):
                r = Rectangle((rect_box[0] - 0.5, rect_box[1] - 0.5), rect_box[2] - rect_box[0],
                              rect_box[3] - rect_box[1], fill=False, ec=window_rgba, lw=0.9)
                ax.add_patch(r)
                _outlined(r, 1.8)
        else:
            ax_c.text(0.5, 0.5, f"no patch in this frame\n({patch_result.reason})", transform=ax_c.transAxes,
                      ha="center", va="center")
            ax_c.set_xticks([])
            ax_c.set_yticks([])
        handles.insert(len(handles) - 1 if patch_result.found else len(handles),
                       Line2D([], [], color="black", lw=0.9, ls="--", label="view of (b)"))
        for ax in (ax_a, ax_b, ax_c):
            ax.set_xlabel("x (px)")
        ax_a.set_ylabel("y (px)")
        ax_b.set_xlim(zx0 - 0.5, zx1 - 0.5)
        ax_b.set_ylim(zy1 - 0.5, zy0 - 0.5)
        fig.legend(handles=handles, loc="outside lower center", ncol=LEGEND_COLUMNS, frameon=False)
        if title:
            fig.suptitle(_wrap(title, fs), fontsize=fs.font_pt)
    return fig


# --------------------------------------------------------------------------------------------
# Saving
# --------------------------------------------------------------------------------------------


def save_figure(fig, path_stem: str | Path, formats: Sequence[str] = SAVE_FORMATS,
                dpi: int | None = None) -> list[Path]:
    """Write ``fig`` to ``<path_stem>.<format>`` for each format, each atomically.

    Each file is rendered into a temporary file beside its final name and renamed onto it only
    when complete (``contact_viz.io.atomic.atomic_write``): a reader never sees a half-written figure.
    ``dpi`` (raster formats) defaults to ``FigureStyle().dpi``. Returns the written paths.
    """
    stem = Path(path_stem)
    dpi = FigureStyle().dpi if dpi is None else dpi
    written = []
    for fmt in formats:
        path = stem.with_name(f"{stem.name}.{fmt}")
        with atomic_write(path, "wb") as handle:
            fig.savefig(handle, format=fmt, dpi=dpi, metadata=_metadata(fmt))
        written.append(path)
    return written


def _metadata(fmt: str) -> dict[str, str | None] | None:
    """Reproducible file metadata: no creation date (same inputs give the same PDF bytes)."""
    if fmt == "pdf":
        return {"CreationDate": None, "Creator": "contact-viz"}
    if fmt == "png":
        return {"Software": "contact-viz"}
    return None
