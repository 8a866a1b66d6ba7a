"""The paper figures: panels, legends from the style module, layer colours where the layers are, saving."""

from __future__ import annotations

import numpy as np
import pytest

from contact_viz.viz import style
from contact_viz.viz.figures import (
    TimelineSession,
    layer_overlay_rgba,
    pipeline_figure,
    save_figure,
    timelines_figure,
)
from contact_viz.params import PatchParams
from contact_viz.geometry.patch import LAYER_BAND, LAYER_INTERIOR, LAYER_RING, LAYER_TOOL_EDGE, compute_patch

HEIGHT, WIDTH = 60, 80  # px
TISSUE_M, TOOL_M = 0.100, 0.095  # depth of the flat tissue and of the tool, m
PARAMS = PatchParams(band_min_px=4.0, band_max_px=4.0)  # a 4 px band: several screen pixels wide


@pytest.fixture(scope="module")
def frame():
    """A horizontal tool (rows 24-35) entering from the left over flat tissue, and its patch."""
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    mask = np.zeros((HEIGHT, WIDTH), bool)
    mask[24:36, :45] = True
    depth = np.full((HEIGHT, WIDTH), TISSUE_M, np.float32)
    depth[mask] = TOOL_M
    patch = compute_patch(depth, mask, PARAMS)
    assert patch.found
    return rgb, mask, depth, patch


@pytest.fixture(scope="module")
def pipeline(frame):
    fig = pipeline_figure(*frame)
    fig.canvas.draw()
    return fig


def drawn_layer_names() -> list[str]:
    return [s.name for s in style.LAYER_STYLES if s.rgba[3] > 0]


def test_pipeline_has_three_panels_and_a_depth_colour_bar(pipeline):
    assert len(pipeline.axes) == 4
    titles = [ax.get_title(loc="left") for ax in pipeline.axes[:3]]
    assert [t[:3] for t in titles] == ["(a)", "(b)", "(c)"]
    assert pipeline.axes[3].get_ylabel() == "depth (mm)"
    assert all(ax.get_xlabel() == "x (px)" for ax in pipeline.axes[:3])


def test_pipeline_legend_names_and_colours_are_the_style_classes(pipeline):
    (legend,) = pipeline.legends
    texts = [t.get_text() for t in legend.get_texts()]
    names = drawn_layer_names()
    assert texts[: len(names)] == names
    by_name = {s.name: s for s in style.LAYER_STYLES}
    for handle, name in zip(legend.legend_handles, names):
        np.testing.assert_allclose(handle.get_facecolor(), np.array(by_name[name].rgba) / 255.0)
    assert any(t.startswith("patch window N2") for t in texts[len(names):])


def layer_artist(ax):
    (image,) = [im for im in ax.get_images() if im.get_gid() == "layers"]
    return image


def test_layer_image_holds_the_style_colour_of_every_pixel(pipeline, frame):
    patch = frame[3]
    image = layer_artist(pipeline.axes[1])
    data = np.asarray(image.get_array())
    left, _, _, top = image.get_extent()
    x0, y0 = int(left + 0.5), int(top + 0.5)  # image pixel at the crop's corner
    for s in style.LAYER_STYLES:
        ys, xs = np.nonzero(patch.layer_ids == s.class_id)
        inside = (ys >= y0) & (ys < y0 + data.shape[0]) & (xs >= x0) & (xs < x0 + data.shape[1])
        assert inside.any() or s.class_id == 0
        np.testing.assert_allclose(data[ys[inside] - y0, xs[inside] - x0], np.tile(np.array(s.rgba) / 255.0,
                                                                                   (int(inside.sum()), 1)))


def rendered_rgb(fig, ax, x: float, y: float) -> np.ndarray:
    """The rendered canvas colour (RGB in [0, 1]) at image pixel (x, y) of ``ax``."""
    buffer = np.asarray(fig.canvas.buffer_rgba())
    dx, dy = ax.transData.transform((x, y))
    return buffer[int(buffer.shape[0] - dy), int(dx), :3] / 255.0


@pytest.mark.parametrize("class_id", [LAYER_INTERIOR, LAYER_TOOL_EDGE, LAYER_RING, LAYER_BAND])
def test_rendered_panel_b_shows_each_layer_colour_over_the_grey_depth(pipeline, frame, class_id):
    _, _, depth, patch = frame
    ax = pipeline.axes[1]
    depth_image = [im for im in ax.get_images() if im.get_gid() != "layers"][0]
    vmin, vmax = depth_image.norm.vmin, depth_image.norm.vmax
    rgba = np.array(style.layer_style(class_id).rgba) / 255.0
    ys, xs = np.nonzero(patch.layer_ids == class_id)
    checked = 0
    # Lines drawn over the image (the axes frame, panel (c)'s view box) hide the pixels they cross.
    edges_x, edges_y = [*ax.get_xlim()], [*ax.get_ylim()]
    for rect in ax.patches:
        left, bottom, width, height = rect.get_bbox().bounds
        edges_x += [left, left + width]
        edges_y += [bottom, bottom + height]
    for y, x in list(zip(ys, xs))[:: max(len(ys) // 7, 1)]:
        if min(abs(x - np.array(edges_x))) < 1.5 or min(abs(y - np.array(edges_y))) < 1.5:
            continue
        grey = np.clip((depth[y, x] * 1000.0 - vmin) / (vmax - vmin), 0, 1)  # the "gray" colormap is linear
        expected = rgba[3] * rgba[:3] + (1 - rgba[3]) * grey
        np.testing.assert_allclose(rendered_rgb(pipeline, ax, x, y), expected, atol=0.02)
        checked += 1
    assert checked >= 2


def test_rendered_background_in_panel_b_is_plain_grey(pipeline, frame):
    _, _, depth, patch = frame
    ax = pipeline.axes[1]
    x0, x1 = ax.get_xlim()
    y1, y0 = ax.get_ylim()
    ys, xs = np.nonzero(patch.layer_ids == 0)
    keep = (xs > x0 + 1) & (xs < x1 - 1) & (ys > y0 + 1) & (ys < y1 - 1)
    y, x = ys[keep][0], xs[keep][0]
    rgb = rendered_rgb(pipeline, ax, x, y)
    assert np.ptp(rgb) < 0.02  # grey: no layer colour on the background


def test_pipeline_without_a_patch_says_why(frame):
    rgb, _, depth, _ = frame
    empty = np.zeros(depth.shape, bool)
    fig = pipeline_figure(rgb, empty, depth, compute_patch(depth, empty, PARAMS))
    texts = [t.get_text() for t in fig.axes[2].texts]
    assert any("empty_mask" in t for t in texts)


def test_pipeline_rejects_mismatched_inputs(frame):
    rgb, mask, depth, patch = frame
    with pytest.raises(ValueError, match="depth_m: expected shape"):
        pipeline_figure(rgb, mask, depth[:-1], patch)
    with pytest.raises(ValueError, match="left_rgb"):
        pipeline_figure(rgb[..., 0], mask, depth, patch)


def test_layer_overlay_rejects_unknown_ids():
    with pytest.raises(ValueError, match="LAYER_"):
        layer_overlay_rgba(np.full((2, 2), 9, np.uint8))


def timeline_sessions():
    t = np.arange(12) / 10.0
    labels = np.array([0, 0, 1, 1, 1, 0, 0, 1, -1, 0, 1, 1])  # contact runs: [2, 5), [7, 8), [10, 12)
    hmm = np.linspace(0, 1, 12)
    rgb = np.linspace(1, 0, 12)
    return [
        TimelineSession("cup_test", "same phantom and task", t, labels, hmm, 0.4, rgb, 0.6),
        ("glove_test", "new phantom and task", t, np.zeros(12, int), hmm[::-1], 0.5, rgb[::-1], 0.7),
    ]


def test_timelines_have_one_axes_per_session_and_method_with_the_data():
    sessions = timeline_sessions()
    fig = timelines_figure(sessions, method_names=("HMM", "RGB"))
    assert len(fig.axes) == 2 * len(sessions)
    for row, s in enumerate(sessions):
        s = TimelineSession(*s)
        for col, (posterior, threshold) in enumerate(((s.hmm_posterior, s.hmm_threshold),
                                                      (s.rgb_posterior, s.rgb_threshold))):
            ax = fig.axes[2 * row + col]
            curve, level = ax.get_lines()
            np.testing.assert_array_equal(curve.get_xdata(), s.time_s)
            np.testing.assert_array_equal(curve.get_ydata(), posterior)
            assert list(level.get_ydata()) == [threshold, threshold]
            assert ax.get_figure(root=False).get_suptitle() == f"{s.name} ({s.category})"
            assert ax.get_title(loc="left") == f"{('HMM', 'RGB')[col]} (threshold {threshold:.2f})"
            runs = [(i, j) for i, j in [(2, 5), (7, 8), (10, 12)]] if row == 0 else []
            spans = [p.get_x() for p in ax.patches]
            # frame edges are midpoints between frame times (0.1 s apart)
            np.testing.assert_allclose(sorted(spans), [i / 10.0 - 0.05 for i, _ in runs])
    (legend,) = fig.legends
    assert [t.get_text() for t in legend.get_texts()] == [
        "ground-truth contact", "HMM P(contact)", "RGB P(contact)", "decision threshold"]
    assert fig.axes[-1].get_xlabel() == "time (s)" and fig.axes[0].get_ylabel() == "P(contact)"


def test_timelines_reject_bad_input():
    t = np.arange(5) / 10.0
    with pytest.raises(ValueError, match=r"sessions\[0\].*rgb_posterior: expected shape"):
        timelines_figure([("s", "c", t, np.zeros(5, int), np.zeros(5), 0.5, np.zeros(4), 0.5)])
    with pytest.raises(ValueError, match="at least one session"):
        timelines_figure([])


def test_save_figure_writes_png_and_pdf_atomically(tmp_path, frame):
    fig = timelines_figure(timeline_sessions())
    written = save_figure(fig, tmp_path / "timelines")
    assert written == [tmp_path / "timelines.png", tmp_path / "timelines.pdf"]
    assert (tmp_path / "timelines.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "timelines.pdf").read_bytes()[:5] == b"%PDF-"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["timelines.pdf", "timelines.png"]

    class Broken(RuntimeError):
        pass

    def half_written(handle, **kwargs):
        handle.write(b"\x89PNG partial")
        raise Broken("disk full")

    fig.savefig = half_written
    before = (tmp_path / "timelines.png").read_bytes()
    with pytest.raises(Broken):
        save_figure(fig, tmp_path / "timelines")
    assert (tmp_path / "timelines.png").read_bytes() == before  # the old file is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["timelines.pdf", "timelines.png"]  # no temp file left
