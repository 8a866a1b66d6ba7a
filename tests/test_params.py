"""The one way config fields are checked (params.checked + check_fields), on every config class."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import pytest

from contact_viz.geometry.pointcloud import CloudParams
from contact_viz.geometry.stereo import SGBMParams
from contact_viz.geometry.tooltip import TipParams
from contact_viz.model.hmm import HMMParams
from contact_viz.params import LabelParams, PatchParams, check_fields, checked, from_dict, to_dict
from contact_viz.viz.debugger import DebuggerOptions
from contact_viz.viz.video import VideoParams
from contact_viz.viz.diagnostics import DiagnosticParams

# (class, field, bad value, the whole message it must give)
BAD = [
    (PatchParams, "n1", 30, "PatchParams.n1 must be an odd integer >= 3, got 30"),
    (PatchParams, "n1", True, "PatchParams.n1 must be an odd integer >= 3, got True"),
    (PatchParams, "tau_tool", 2.0, "PatchParams.tau_tool must be an integer >= 1, got 2.0"),
    (PatchParams, "eps_m", math.inf, "PatchParams.eps_m must be a finite number > 0, got inf"),
    (PatchParams, "ring_px", "3", "PatchParams.ring_px must be a finite number >= 0, got '3'"),
    (LabelParams, "contact_force_n", 0, "LabelParams.contact_force_n must be a finite number > 0, got 0"),
    (SGBMParams, "num_disparities", 40,
     "SGBMParams.num_disparities must be None or a multiple of 16 in [16, 4096), got 40"),
    (SGBMParams, "num_disparities", 4096,
     "SGBMParams.num_disparities must be None or a multiple of 16 in [16, 4096), got 4096"),
    (SGBMParams, "block_size", 4, "SGBMParams.block_size must be None or an odd integer >= 1, got 4"),
    (SGBMParams, "mode", "fast", "SGBMParams.mode must be one of ['sgbm', 'sgbm_3way', 'hh', 'hh4'], got 'fast'"),
    (SGBMParams, "disparity_range_fraction", 0.0,
     "SGBMParams.disparity_range_fraction must be a finite number in (0, 1], got 0.0"),
    (SGBMParams, "lr_check", 1, "SGBMParams.lr_check must be True or False, got 1"),
    (CloudParams, "stride_px", -1, "CloudParams.stride_px must be None or an integer >= 0, got -1"),
    (CloudParams, "near_stride_px", 0, "CloudParams.near_stride_px must be an integer >= 1, got 0"),
    (DebuggerOptions, "images", "png", "DebuggerOptions.images must be one of ['video', 'jpeg', 'raw'], got 'png'"),
    (DebuggerOptions, "right_step", 3, "DebuggerOptions.right_step must be one of [1, 2], got 3"),
    (VideoParams, "codec", "vp9", "VideoParams.codec must be one of ['av1', 'h264'], got 'vp9'"),
    (VideoParams, "crf", 64, "VideoParams.crf must be None or an integer in [0, 63], got 64"),
    (VideoParams, "keyframe_interval_s", 0, "VideoParams.keyframe_interval_s must be a finite number > 0, got 0"),
    (TipParams, "tip_band_px", -0.5, "TipParams.tip_band_px must be a finite number >= 0, got -0.5"),
    (DiagnosticParams, "mask_area_jump", 0, "DiagnosticParams.mask_area_jump must be a finite number in (0, 1], got 0"),
    (DiagnosticParams, "max_hole_fraction", 1.5,
     "DiagnosticParams.max_hole_fraction must be a finite number in [0, 1], got 1.5"),
    (DiagnosticParams, "tool_diameter_mm", 0, "DiagnosticParams.tool_diameter_mm must be a finite number > 0, got 0"),
    (DebuggerOptions, "end", -1, "DebuggerOptions.end must be None or an integer >= 0, got -1"),
    (DebuggerOptions, "jpeg_quality", 101, "DebuggerOptions.jpeg_quality must be an integer in [1, 100], got 101"),
    (DebuggerOptions, "color_reduction", True, "DebuggerOptions.color_reduction must be one of [1, 2, 4, 8], got True"),
    (HMMParams, "var_floor", None, "HMMParams.var_floor must be a finite number > 0, got None"),
]


@pytest.mark.parametrize("cls, name, value, message", BAD, ids=[f"{c.__name__}.{n}={v!r}" for c, n, v, _ in BAD])
def test_a_bad_field_is_one_message_naming_it_and_what_was_expected(cls, name, value, message):
    with pytest.raises(ValueError) as info:
        cls(**{name: value})
    assert str(info.value) == message


def test_cross_field_rules_still_apply():
    with pytest.raises(ValueError, match=r"band_min_px <= band_max_px"):
        PatchParams(band_min_px=5.0, band_max_px=4.0)
    with pytest.raises(ValueError, match=r"p1_factor < p2_factor, got 40 and 32"):
        SGBMParams(p1_factor=40, p2_factor=32)
    with pytest.raises(ValueError, match=r"tau_patch=290 exceeds the 17x17 window"):
        PatchParams(tau_patch=17 * 17 + 1)


def test_json_round_trip_keeps_values_as_given():
    # An integer given for a float field stays an integer, so the saved JSON and the cache keys
    # made from it are what they were before the checks were shared.
    data = {"erosion_px": 2, "ring_px": 3, "n2": 15}
    params = from_dict(PatchParams, data)
    assert params.erosion_px == 2 and type(params.erosion_px) is int
    text = json.dumps(to_dict(params))
    assert '"erosion_px": 2,' in text and '"ring_px": 3,' in text
    assert from_dict(PatchParams, json.loads(text)) == params
    for cls in (PatchParams, LabelParams, SGBMParams, CloudParams, TipParams, DiagnosticParams, HMMParams,
                VideoParams):
        assert from_dict(cls, json.loads(json.dumps(to_dict(cls())))) == cls()


def test_pairs_from_json_lists_are_stored_as_float_tuples():
    @dataclass(frozen=True)
    class Ranges:
        gap_m: tuple[float, float] = checked((0.002, 0.01), gt=0, le=1, pair=True)  # a range, m
        count: int | None = checked(None, ge=2)  # optional, count

        def __post_init__(self) -> None:
            check_fields(self)

    assert Ranges(gap_m=[1, 1]).gap_m == (1.0, 1.0) and type(Ranges(gap_m=[1, 1]).gap_m[0]) is float
    assert Ranges(count=2).count == 2
    with pytest.raises(ValueError) as info:
        Ranges(gap_m=(0.5, 0.1))
    assert str(info.value) == "Ranges.gap_m must be a (lo, hi) pair of numbers with 0 < lo <= hi <= 1, got (0.5, 0.1)"
    with pytest.raises(ValueError, match=r"Ranges.gap_m must be a \(lo, hi\) pair"):
        Ranges(gap_m=(0.1, 0.2, 0.3))
    with pytest.raises(ValueError, match=r"Ranges.count must be None or an integer >= 2, got 1"):
        Ranges(count=1)
