"""The checks with several instruments (object ids): each measured and checked on its own, with its own
history, and the two failures only multi-instrument masks have (``id_swap``, ``tools_merged``), on worked
examples (contact_viz.checks) and on `contact-viz check`'s table and JSON."""

from __future__ import annotations

import json
import math
import sys
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import pytest

from contact_viz.checks.frame import COVER_SIZE, ToolMeasures, measure_frame, measure_tools
from contact_viz.checks.params import DiagnosticParams
from contact_viz.checks.rules import FrameChecker, PatchNumbers

sys.path.insert(0, str(Path(__file__).parent))
from test_checks import BASELINE, FX, TOOL_Z, W, scene  # noqa: E402  (the checks' worked example)

PARAMS = DiagnosticParams(tool_diameter_mm=3.5)


def two_tools():
    """The worked example's tool (id 1, a bar from the left border, rows 50-70) and a second instrument (id 2)
    from the top border down to 1 px above the first, along it (columns 10-120), at the same depth."""
    mask, depth, left, right = scene()
    ids = mask.astype(np.uint16)
    ids[0:49, 10:121] = 2
    depth = depth.copy()
    depth[ids == 2] = TOOL_Z
    return ids, depth, left, right


def test_each_instrument_is_measured_without_the_others():
    ids, depth, left, right = two_tools()
    tools = measure_tools(ids, depth, left, right, FX, BASELINE, PARAMS)
    assert set(tools.tools) == {1, 2} and tools.tool_area_px == int(np.count_nonzero(ids))
    one = tools.tools[1]
    alone = measure_frame(ids == 1, *scene()[1:], FX, BASELINE, PARAMS)  # the first tool without the second
    assert one.tool_area_px == alone.tool_area_px and one.extra_blob_px == 0
    for name in ("inside_far_fraction", "outside_tool_fraction", "hole_fraction", "width_ratio", "edge_support"):
        assert getattr(one, name) == pytest.approx(getattr(alone, name), abs=0.02), name
    # the other instrument taken for tissue: its depth just beside the first tool reads as that tool's depth
    # bleeding out (the ring outside it at the tool's depth)
    as_tissue = measure_frame(ids == 1, depth, left, right, FX, BASELINE, PARAMS)
    assert as_tissue.outside_tool_fraction > PARAMS.max_outside_tool_fraction >= one.outside_tool_fraction
    # the mask read as one tool (as before): the other instrument is an extra blob of it
    two = ids.copy()
    two[0:49, 10:121] = 0
    two[0:30, 150:171] = 2  # (an instrument away from the first)
    union = measure_frame(two > 0, depth, left, right, FX, BASELINE, PARAMS)
    assert union.extra_blob_px > PARAMS.min_blob_area_fraction * union.tool_area_px
    assert measure_tools(two, depth, left, right, FX, BASELINE, PARAMS).tools[1].extra_blob_px == 0
    # one instrument only: exactly measure_frame of its mask
    single = measure_tools(ids == 1, *scene()[1:], FX, BASELINE, PARAMS).tools[1]
    for f in fields(single):
        a, b = getattr(single, f.name), getattr(alone, f.name)
        assert np.array_equal(a, b) if isinstance(a, np.ndarray) else a == b or (a != a and b != b), f.name
    # selected ids: the others are measured as other instruments only
    assert set(measure_tools(ids, depth, left, right, FX, BASELINE, PARAMS, selected=[2]).tools) == {2}


def test_a_tool_cut_in_two_by_an_instrument_in_front_of_it_is_no_extra_blob():
    mask, depth, left, right = scene()
    ids = mask.astype(np.uint16)
    ids[:, 70:85] = np.where(ids[:, 70:85] > 0, 2, 0)  # tool 2 crosses tool 1 (in front of it), top to bottom
    ids[0:50, 70:85] = 2
    ids[71:, 70:85] = 2
    cut = measure_tools(ids, depth, None, None, FX, BASELINE, PARAMS).tools[1]
    assert cut.extra_blob_px == 0
    # the same two pieces of tool 1 without tool 2 between them: an extra blob
    apart = measure_frame(ids == 1, depth, None, None, FX, BASELINE, PARAMS)
    assert apart.extra_blob_px > PARAMS.min_blob_area_fraction * apart.tool_area_px


def test_a_tip_entering_the_view_shows_its_jaws_at_the_border_as_one_tool():
    mask, depth, left, right = scene()
    tip = np.zeros_like(mask)
    tip[0:8, 100:112] = True  # the jaws of a tool peeking in at the top border: two pieces a few px apart
    tip[0:3, 116:121] = True
    m = measure_frame(tip, depth, None, None, FX, BASELINE, PARAMS)
    assert m.extra_blob_px == 0
    far = tip.copy()
    far[0:3, 160:165] = True  # a piece farther along the border than the tip is wide: another object
    assert measure_frame(far, depth, None, None, FX, BASELINE, PARAMS).extra_blob_px > 0
    # a tool reaching well into the view: a piece beside it at the border is no jaw of a tip entering
    deep = tip.copy()
    deep[0:40, 100:112] = True
    assert measure_frame(deep, depth, None, None, FX, BASELINE, PARAMS).extra_blob_px > 0


def _cover(x0, x1, y0=10, y1=20):
    grid = np.zeros(COVER_SIZE[::-1], np.float32)
    grid[y0:y1, x0:x1] = 1.0
    return grid


@pytest.fixture(scope="module")
def base():
    return measure_frame(*scene(), FX, BASELINE, PARAMS)


def frame(base, index, **tools):
    """ToolMeasures of tools given as name=(x0, x1[, area[, touches_border]]) on the coverage grid."""
    out = {}
    for name, spec in tools.items():
        x0, x1, *more = spec
        area = more[0] if more else 2500
        touches = more[1] if len(more) > 1 else True
        out[int(name[1:])] = replace(base, tool_area_px=area, touches_border=touches, coverage=_cover(x0, x1),
                                     depth_digest=bytes([index]))
    return ToolMeasures(out, bytes([index]), base.thumb, sum(m.tool_area_px for m in out.values()))


def run(checker, frames):
    """{frame index: {(code, tool)}} of the checks fired."""
    out = {}
    for i, (measures, patches) in enumerate(frames):
        fired, _ = checker.check(i, measures, patches)
        out[i] = {(d.code, d.tool) for d in fired}
    return out


def test_each_instrument_has_its_own_history_and_is_named(base):
    checker = FrameChecker(PARAMS, W)
    near, far = PatchNumbers(0.004, (40.0, 60.0), None), PatchNumbers(0.010, (150.0, 30.0), None)
    frames = [(frame(base, i, t1=(5, 15), t2=(40, 50)), {1: near, 2: far}) for i in range(4)]
    # tool 2 only jumps (the patch stayed put): only tool 2's distance_jump fires
    frames.append((frame(base, 4, t1=(5, 15), t2=(40, 50)), {1: near, 2: PatchNumbers(0.030, (151.0, 30.0), None)}))
    fired = run(checker, frames)
    assert all(not fired[i] for i in range(4)), fired  # 4 mm and 10 mm in one frame: each its own distance
    assert fired[4] == {("distance_jump", 2)}
    # the message names the instrument; a single-instrument session's does not
    msg = checker.check(5, frame(base, 5, t1=(5, 15), t2=(40, 50)), {1: near, 2: PatchNumbers(0.08, (151.0, 30.0),
                                                                                                  None)})[0][0].message
    assert msg.startswith("tool 2: distance jumped while the patch stayed put: 30.0 -> 80.0 mm")
    single = FrameChecker(PARAMS, W)
    single.check(0, replace(base, depth_digest=b"a"), near)
    [jump] = single.check(1, replace(base, depth_digest=b"b"), PatchNumbers(0.03, (40.0, 60.0), None))[0]
    assert jump.message.startswith("distance jumped") and jump.tool == 1
    # one instrument other than id 1 is named too
    other = FrameChecker(PARAMS, W)
    other.check(0, frame(base, 0, t3=(5, 15)), {3: near})
    [jump] = other.check(1, frame(base, 1, t3=(5, 15)), {3: PatchNumbers(0.03, (40.0, 60.0), None)})[0]
    assert jump.message.startswith("tool 3: distance jumped")
    # a dropout is the instrument's own: tool 2 gone mid-view fires for tool 2
    checker = FrameChecker(PARAMS, W)
    fired = run(checker, [(frame(base, i, t1=(5, 15), t2=(40, 50, 2500, False)), None) for i in range(3)]
                + [(frame(base, 3, t1=(5, 15)), None)])
    assert fired[3] == {("mask_dropout", 2)}


def test_an_id_swap_fires_while_the_ids_are_exchanged(base):
    a, b = (5, 15), (40, 50)
    frames = [frame(base, i, t1=a, t2=b) for i in range(3)]
    frames += [frame(base, i, t1=b, t2=a) for i in range(3, 6)]  # the segmenter exchanged the ids
    frames += [frame(base, i, t1=a, t2=b) for i in range(6, 9)]  # and back
    checker = FrameChecker(PARAMS, W)
    fired = run(checker, [(f, None) for f in frames])
    swapped = {i for i, codes in fired.items() if ("id_swap", 1) in codes and ("id_swap", 2) in codes}
    assert swapped == {3, 4, 5}, fired
    assert all(codes <= {("id_swap", 1), ("id_swap", 2)} for codes in fired.values()), fired
    checker = FrameChecker(PARAMS, W)
    for i in range(3):
        checker.check(i, frames[i], None)
    messages = sorted(d.message for d in checker.check(3, frames[3], None)[0])
    assert messages[0].startswith("tool 1: instrument ids exchanged between frames: this mask continues tool 2's "
                                  "of the frame before (overlap 1.00; with its own 0.00)")
    assert messages[0].endswith("the segmenter swapped two instruments' object ids (identity switch)")
    later = sorted(d.message for d in checker.check(4, frames[4], None)[0])
    assert later[1].startswith("tool 2: instrument ids exchanged between frames: still tool 1's instrument (ids "
                               "exchanged at frame 3)")
    # the instruments moving on their own (each overlapping its own past) is no swap, nor crossing paths
    checker = FrameChecker(PARAMS, W)
    moving = [frame(base, i, t1=(5 + 2 * i, 15 + 2 * i), t2=(40 - 2 * i, 50 - 2 * i)) for i in range(9)]
    assert not any(run(checker, [(f, None) for f in moving]).values())
    # the margin is a real one: a pairing only a little better than the ids' (overlap 0.7 against 0.6) does not
    # move them, a clearly better one (0.8 against 0.5) does
    for moved, (t1, t2) in ((False, ((9, 19), (8, 18))), (True, ((10, 20), (7, 17)))):
        checker = FrameChecker(PARAMS, W)
        pair = [frame(base, 0, t1=(5, 15), t2=(12, 22)), frame(base, 1, t1=t1, t2=t2)]
        assert bool(run(checker, [(f, None) for f in pair])[1]) == moved, (t1, t2)


def test_two_instruments_merged_into_one_id(base):
    a, b = (5, 15), (40, 50)
    frames = [frame(base, i, t1=(*a, 2500), t2=(*b, 2000)) for i in range(3)]
    merged = ToolMeasures({1: replace(base, tool_area_px=4500, coverage=np.maximum(_cover(*a), _cover(*b)),
                                      depth_digest=b"m")}, b"m", base.thumb, 4500)
    frames += [merged, replace(merged, depth_digest=b"n")]
    frames += [frame(base, i, t1=(*a, 2500), t2=(*b, 2000)) for i in range(5, 7)]  # apart again
    checker = FrameChecker(PARAMS, W)
    fired = run(checker, [(f, None) for f in frames])
    assert fired[3] == {("tools_merged", 1)} and fired[4] == {("tools_merged", 1)}, fired  # no dropout of tool 2
    assert not fired[5] and not fired[6] and not any(fired[i] for i in range(3)), fired
    checker = FrameChecker(PARAMS, W)
    for i in range(3):
        checker.check(i, frames[i], None)
    [onset] = checker.check(3, frames[3], None)[0]
    assert onset.message == ("tool 1: one instrument's id took in another instrument: took in tool 2's 2000 px "
                             "(2500 -> 4500 px; tool 2 gone, its mask 100% covered): the segmenter merged two "
                             "instruments into one object id")
    # tool 2 leaving through the border (its mask shrinking there) is no merge and no dropout
    checker = FrameChecker(PARAMS, W)
    leaving = [frame(base, i, t1=(*a, 2500), t2=(*b, area)) for i, area in enumerate((2000, 2000, 1500, 900))]
    leaving.append(frame(base, 4, t1=(*a, 2500)))
    assert not any(run(checker, [(f, None) for f in leaving]).values())
    # tool 2 hidden behind tool 1 (tool 1 now covers its place, without growing by its area): no dropout
    checker = FrameChecker(PARAMS, W)
    hidden = [frame(base, i, t1=(*a, 2500), t2=((20, 30, 2000, False))) for i in range(3)]
    hidden.append(frame(base, 3, t1=(14, 31, 2600)))
    assert not any(run(checker, [(f, None) for f in hidden]).values())
    # ... while tool 2 gone with nothing at its place is a dropout
    checker = FrameChecker(PARAMS, W)
    gone = hidden[:3] + [frame(base, 3, t1=(*a, 2500))]
    assert run(checker, [(f, None) for f in gone])[3] == {("mask_dropout", 2)}


@pytest.fixture(scope="module")
def two_tool_session(tmp_path_factory):
    """A small session with two instruments: the worked example's masks of a synthetic session with a second
    instrument (id 2) written in (masks only: enough for the table and the JSON)."""
    from PIL import Image

    from contact_viz.synth import SynthParams, generate_session
    from contact_viz.synth.faults import inject_fault

    root = tmp_path_factory.mktemp("two_tools")
    src = generate_session(root / "cup_s", SynthParams(phantom="cup", frames=24, seed=3, width=160, height=90))
    merged = root / "merged"
    inject_fault(src, merged, "frozen_depth", [5])  # a copy with fresh files to write into
    for path in sorted((merged / "masks").glob("*.png")):
        image = Image.open(path)
        ids = np.array(image)
        ids[0:30, 5:15] = 2  # a second instrument down from the top border, away from the first
        out = Image.fromarray(ids, mode="L").convert("P")
        out.putpalette(image.getpalette())
        path.unlink()
        out.save(path)
    return merged


def test_check_reports_per_instrument(two_tool_session):
    from contact_viz.pipeline.check import check_session, report_table

    report = check_session(two_tool_session)
    assert report.instruments == (1, 2) and report.several
    data = json.loads(json.dumps(report.to_dict()))
    assert data["instruments"] == [1, 2]
    assert data["checks"]["frozen_depth"]["ranges"] == [[5, 5]] and "tools" not in data["checks"]["frozen_depth"]
    lines = report_table(report)
    assert lines[0].endswith("; instruments 1, 2")
    assert lines[1].split() == ["check", "tool", "frames", "ranges", "likely", "cause"]
    row = next(line for line in lines if line.strip().startswith("frozen_depth"))
    assert row.split()[1:4] == ["-", "1", "000005"]  # a check of the whole frame: no instrument; frames by stem
    for code, tools in report.tool_fired.items():  # per-instrument rows name the instrument
        for tool, ranges in tools.items():
            assert any(line.split()[:2] == [code, str(tool)] for line in lines), (code, tool, lines)
            assert data["checks"][code]["tools"][str(tool)]["ranges"] == [list(r) for r in ranges]
    # the frames a check fired on count once however many instruments it fired for
    assert all(report.counts[c] == sum(b - a + 1 for a, b in report.fired[c]) for c in report.counts)
    assert math.isfinite(report.elapsed_s)
