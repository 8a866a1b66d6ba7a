"""tool_width reads the instrument's shaft: the widest disc inside the mask, where the shaft is in view.

An instrument entering or leaving the view tip first shows its two jaws side by side at the image border, each
narrower than the shaft (the synthetic jaws are 3.6 mm wide, the shaft 8 mm): the widest disc then lies on a jaw
and its width says nothing of the depth's scale, so the width's lower bound is not measured there (the mask fills
about twice its widest disc's width x its reach from the border; one shaft about once). A depth too small or too
large on a shaft in view is still caught.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from contact_viz.checks.frame import measure_frame, measure_tools
from contact_viz.checks.params import DiagnosticParams
from contact_viz.checks.rules import FrameChecker

PARAMS = DiagnosticParams()  # an 8 mm shaft, as the synthetic instruments'
FX = 300.0  # px
H, W = 120, 200  # px
TOOL_Z, TISSUE_Z = 0.05, 0.09  # m
BAR_PX = 21  # px: at TOOL_Z, (21 px x 54 mm / 300 px) = 3.8 mm, 0.47 of the 8 mm shaft


def fired(measures, params: DiagnosticParams = PARAMS, width: int = W) -> list[str]:
    """The checks fired on one frame's measures by a fresh checker (no frame before)."""
    return [d.code for d in FrameChecker(params, width).check(0, measures, None)[0]]


def prongs(count: int, top: int = 0, length: int = 60) -> np.ndarray:
    """A mask of ``count`` bars side by side, 3 px apart and joined over their first 3 rows, ``length`` long from
    row ``top`` down: BAR_PX wide on their far half, 2 px narrower on the half at ``top`` (so that their widest
    disc lies inside the image)."""
    mask = np.zeros((H, W), bool)
    for k in range(count):
        x = 70 + k * (BAR_PX + 3)
        mask[top:top + length // 2, x + 1:x + BAR_PX - 1] = True
        mask[top + length // 2:top + length, x:x + BAR_PX] = True
    mask[top:top + 3, 71:70 + count * (BAR_PX + 3) - 4] = True
    return mask


def depth_of(mask: np.ndarray, scale: float = 1.0) -> np.ndarray:
    return (np.where(mask, TOOL_Z, TISSUE_Z) * scale).astype(np.float32)


def test_two_prongs_side_by_side_at_the_border_are_not_read_as_a_shaft():
    """Two bars entering from the top border, each as narrow as a jaw at the tool's depth: the widest disc lies
    on one of them, no shaft's, and the width's lower bound is not measured; one bar of that width (a shaft
    whose depth reads half the truth) is measured and fires."""
    jaws = prongs(2)
    m = measure_frame(jaws, depth_of(jaws), None, None, FX, 0.005, PARAMS)
    assert m.touches_border and abs(m.shaft_width_px - BAR_PX) <= 1.5
    assert math.isnan(m.width_ratio) and "tool_width" not in fired(m)
    shaft = prongs(1)
    s = measure_frame(shaft, depth_of(shaft), None, None, FX, 0.005, PARAMS)
    assert s.width_ratio == pytest.approx(BAR_PX * (TOOL_Z + 0.004) / FX / 0.008, rel=0.05)
    assert fired(s) == ["tool_width"]
    # the same two prongs beyond another instrument that hides the shaft (the mask reaches no image border)
    hidden = prongs(2, top=30)
    other = np.zeros((H, W), bool)
    other[10:29, :] = True
    h = measure_frame(hidden, depth_of(hidden | other), None, None, FX, 0.005, PARAMS, others=other)
    assert not h.touches_border and math.isnan(h.width_ratio)
    # a wider width is measured on them: the jaws are never wider than the shaft
    wide = measure_frame(jaws, depth_of(jaws, 4.0), None, None, FX, 0.005, PARAMS)
    assert wide.width_ratio > PARAMS.max_width_ratio and fired(wide) == ["tool_width"]


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """Synthetic sessions (contact_viz.synth) whose frames show what the check met on clean data:

    * ``jaws_1280``: cup, seed 7, 1280x720, frame 9, the frame of `contact-viz synth S --tools 2 --frames 120
      --size 1280x720 --seed 7` where tool 1 (the same instrument, at the same place, as in the one-instrument
      session, whose first 10 frames are rendered here) read "4.0 mm wide vs 8 mm": it enters the view from
      the top tip first, its two jaws in view, the shaft and the wrist beyond the border; measured at a third
      of the resolution;
    * ``jaws_320``: glove, seed 101, 320x180, frame 1 (bench_diagnostics' session glove_101): the open jaws
      and a sliver of the wrist at the top border;
    * ``shaft_320``: glove, seed 7, 320x180, frame 3: the shaft in view, its widest disc on it, inside the image.
    """
    from contact_viz.synth import SynthParams, generate_session

    root = tmp_path_factory.mktemp("width")
    specs = {"jaws_1280": (SynthParams(phantom="cup", frames=10, seed=7, width=1280, height=720), 9),
             "jaws_320": (SynthParams(phantom="glove", frames=2, seed=101, width=320, height=180), 1),
             "shaft_320": (SynthParams(phantom="glove", frames=4, seed=7, width=320, height=180), 3)}
    return {name: (generate_session(root / name, params), params, index) for name, (params, index) in specs.items()}


def _frame(rendered, name: str):
    from contact_viz.io.session import open_session

    path, params, index = rendered[name]
    session = open_session(path)
    frame = session.load_frame(index, layers=("mask", "depth"))
    return frame, float(session.calibration.K[0][0]), float(session.calibration.baseline_m), params, index


def _shaft_pixels_in_view(params, index: int) -> int:
    """Pixels of the left view where the ray-cast instrument shows its shaft (its other parts and the tissue
    left out: an upper bound on what the mask holds of it)."""
    from contact_viz.synth.scene import stereo_camera
    from contact_viz.synth.second import plan_tracks
    from contact_viz.synth.tools import cast_tools_image, tool_primitives

    shaft = [p for p in tool_primitives(plan_tracks(params)[0], index, params) if p.material == 0]
    ids, _ = cast_tools_image([shaft], stereo_camera(params))
    return int(np.count_nonzero(ids))


@pytest.mark.parametrize("name", ["jaws_1280", "jaws_320"])
def test_the_jaws_alone_entering_the_view_raise_no_tool_width(rendered, name):
    frame, fx, baseline, params, index = _frame(rendered, name)
    assert _shaft_pixels_in_view(params, index) == 0  # the shaft is beyond the image border
    measures = measure_tools(frame.tool_ids, frame.depth_m, None, None, fx, baseline, PARAMS)
    m = measures.tools[1]
    assert m.touches_border
    # its widest disc, on the jaws, is about half as wide as the shaft at the tool's depth (what read 4 mm)
    z = float(np.median(frame.depth_m[frame.tool_ids == 1]))
    assert m.shaft_width_px < 0.65 * params.shaft_diameter_m * fx / (z + params.shaft_diameter_m / 2)
    assert math.isnan(m.width_ratio)
    assert "tool_width" not in fired(measures, width=params.width)


@pytest.mark.parametrize("scale, fires", [(1.0, False), (0.5, True), (0.6, True), (1.6, True)])
def test_a_depth_scale_error_on_a_shaft_in_view_is_caught(rendered, scale, fires):
    frame, fx, baseline, params, index = _frame(rendered, "shaft_320")
    assert _shaft_pixels_in_view(params, index) > 500
    measures = measure_tools(frame.tool_ids, frame.depth_m * scale, None, None, fx, baseline, PARAMS)
    m = measures.tools[1]
    assert m.touches_border
    # measured on the shaft: about 1 at the true depth, and about the scale of the depth off it (the shaft's axis
    # is taken a radius behind the surface read)
    assert abs(m.width_ratio - scale) < 0.15 * scale
    assert ("tool_width" in fired(measures, width=params.width)) == fires
