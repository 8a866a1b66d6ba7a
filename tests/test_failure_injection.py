"""Failure injection: each of the ten failures, put into small synthetic sessions of every phantom while
the tool approaches and while it is in contact, is flagged at the injected frames by the check that
names it; the clean sessions raise (almost) no flags. The two failures only masks of several
instruments have (an id swap, two instruments merged into one id) likewise, in two-instrument sessions.

Sessions: `contact-viz synth` at 320x180, 84 frames (one whole contact), seed 7 (the thresholds were chosen on seed 0);
two-instrument sessions (`--tools 2`) of 100 frames. Severity and timing vary per phantom
(contact_viz.synth.fault_study.SEVERITY, plan_windows, plan_pair_windows).
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest

from contact_viz.synth import PHANTOMS
from contact_viz.synth.fault_study import detected, flagged_frames, inject_and_check_job, make_session_job
from contact_viz.synth.faults import FAULT_KINDS, MULTI_FAULT_KINDS, inject_fault, read_mask_ids, read_truth_phases

SEED = 7
FRAMES = 84

# The checks that name each failure (one of them must fire on the injected frames).
NAMED_BY = {
    "mask_dropout": {"mask_dropout"},
    "mask_drift": {"mask_image_edges", "mask_on_tissue", "tool_depth_outside"},
    "mask_bleed": {"mask_on_tissue", "mask_image_edges"},
    "second_object": {"extra_blob"},
    "depth_holes": {"depth_holes"},
    "edge_bleeding": {"tool_depth_outside"},
    "depth_scale": {"stereo_residual", "tool_width"},
    "depth_misregistration": {"mask_on_tissue", "tool_depth_outside", "stereo_residual"},
    "force_offset": {"force_lag"},
    "frozen_depth": {"frozen_depth"},
    "id_swap": {"id_swap"},
    "tools_merged": {"tools_merged"},
}
TWO_TOOL_PHANTOMS = ("cup", "glove")
TWO_TOOL_FRAMES = 100


def _pool():
    return ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn"))


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    root = tmp_path_factory.mktemp("injection")
    with _pool() as pool:
        jobs = [(root / f"{p}_{SEED}", p, SEED, FRAMES, 320, 180) for p in PHANTOMS]
        return dict(zip(PHANTOMS, pool.map(make_session_job, jobs)))


@pytest.fixture(scope="module")
def outcomes(sessions, tmp_path_factory):
    work = tmp_path_factory.mktemp("injected")
    jobs = [(sessions[p], work, kind, 1000 * k + 10 * i) for i, p in enumerate(PHANTOMS)
            for k, kind in enumerate(FAULT_KINDS)]
    with _pool() as pool:
        return list(pool.map(inject_and_check_job, jobs))


@pytest.mark.parametrize("kind", FAULT_KINDS)
def test_each_failure_is_flagged_in_approach_and_contact_by_its_check(outcomes, kind):
    mine = [o for o in outcomes if o.kind == kind]
    assert len(mine) == len(PHANTOMS)
    for o in mine:
        for phase in ("approach", "contact"):
            assert o.injected[phase], (o.session, phase)
            if (kind, phase) == ("mask_bleed", "contact"):
                continue  # the known weak spot: checked pooled below (and reported in the README table)
            if kind == "force_offset" and abs(o.severity) < 5:
                continue  # 4 frames (0.13 s) is at the lag estimate's resolution: see the next test
            assert detected(o, phase), (f"{kind} in {o.session} ({phase}, severity {o.severity:g}): flagged "
                                        f"{o.flagged[phase]} of {o.injected[phase]}; fired {o.report.fired}")
        if not (kind == "force_offset" and abs(o.severity) < 5):
            assert NAMED_BY[kind] & set(o.checks), (kind, o.session, o.checks)
    injected = sum(len(o.injected[ph]) for o in mine for ph in ("approach", "contact"))
    flagged = sum(len(o.flagged[ph]) for o in mine for ph in ("approach", "contact"))
    # pooled frame share: the target is per injection (above); mask bleed in contact is the weakest
    # (a lobe on tissue right at the tool's depth shows neither a depth step nor always an image edge)
    assert flagged >= 0.6 * injected, (kind, flagged, injected)
    if kind == "mask_bleed":
        injected = sum(len(o.injected["contact"]) for o in mine)
        flagged = sum(len(o.flagged["contact"]) for o in mine)
        assert flagged >= 0.5 * injected and sum(detected(o, "contact") for o in mine) >= 3, (flagged, injected)


def test_force_offset_lag_has_the_injected_sign(outcomes):
    # the lag is estimated within 2 frames (on/off edges of contact); from 5 frames (0.17 s) on it always fires
    for o in (o for o in outcomes if o.kind == "force_offset"):
        lag = o.report.force_lag
        assert lag.lag_frames * o.severity > 0 and abs(lag.lag_frames - o.severity) <= 2, (o.session, o.severity, lag)
        assert lag.fired or abs(o.severity) < 5, (o.session, o.severity, lag)


def test_clean_sessions_raise_few_flags(outcomes, sessions):
    from contact_viz.pipeline.check import check_session

    total = flagged = 0
    for session in sessions.values():
        report = check_session(session)
        total += report.n_frames
        flagged += len(flagged_frames(report))
    assert flagged < 0.02 * total, flagged


def test_injection_changes_only_the_injected_files(sessions, tmp_path):
    src = sessions["cup"]
    before = {p.relative_to(src): p.read_bytes() for p in src.rglob("*") if p.is_file()}
    fault = inject_fault(src, tmp_path / "x", "edge_bleeding", [20, 21], severity=4)
    after = {p.relative_to(src): p.read_bytes() for p in src.rglob("*") if p.is_file()}
    assert before == after  # the source is untouched (hard links are replaced, never written through)
    stems = sorted(p.stem for p in (src / "left").iterdir())
    changed = {p.relative_to(tmp_path / "x") for p in (tmp_path / "x").rglob("*") if p.is_file()
               and before.get(p.relative_to(tmp_path / "x")) != p.read_bytes()}
    assert {str(c) for c in changed} == {f"depth/{stems[20]}.npy", f"depth/{stems[21]}.npy"}
    assert fault.frames == (20, 21)
    assert len(read_truth_phases(src)) == FRAMES


@pytest.fixture(scope="module")
def two_tool_sessions(tmp_path_factory):
    root = tmp_path_factory.mktemp("two_tools")
    with _pool() as pool:
        jobs = [(root / f"{p}_{SEED}_two", p, SEED, TWO_TOOL_FRAMES, 320, 180, 2) for p in TWO_TOOL_PHANTOMS]
        return dict(zip(TWO_TOOL_PHANTOMS, pool.map(make_session_job, jobs)))


@pytest.fixture(scope="module")
def multi_outcomes(two_tool_sessions, tmp_path_factory):
    work = tmp_path_factory.mktemp("injected_two")
    jobs = [(two_tool_sessions[p], work, kind, 1000 * (k + 20) + 10 * i + seed) for i, p in enumerate(TWO_TOOL_PHANTOMS)
            for k, kind in enumerate(MULTI_FAULT_KINDS) for seed in (0, 1)]
    with _pool() as pool:
        return list(pool.map(inject_and_check_job, jobs))


@pytest.mark.parametrize("kind", MULTI_FAULT_KINDS)
def test_an_id_swap_or_a_merge_is_flagged_on_every_injected_frame_by_its_check(multi_outcomes, kind):
    mine = [o for o in multi_outcomes if o.kind == kind]
    assert len(mine) == 2 * len(TWO_TOOL_PHANTOMS)
    (code,) = NAMED_BY[kind]
    for o in mine:
        named = {i for a, b in o.report.fired.get(code, []) for i in range(a, b + 1)}
        for phase in ("approach", "contact"):
            assert len(o.injected[phase]) >= 2, (o.session, phase)
            assert set(o.injected[phase]) <= named, (f"{kind} in {o.session} ({phase}): {code} on "
                                                     f"{sorted(named)}, injected {o.injected[phase]}")
            assert detected(o, phase)
        # it names the instruments: both ids for a swap, the one that took in the other for a merge
        tools = set(o.report.tool_fired[code])
        assert tools == ({1, 2} if kind == "id_swap" else {int(o.severity)}), (o.session, tools)
        # and fires nowhere else (after the ids are restored / the instruments apart again, it stops)
        assert named <= set(o.injected["approach"]) | set(o.injected["contact"]), (o.session, sorted(named))


def test_injected_ids_are_what_the_segmenter_would_write(two_tool_sessions, sessions, tmp_path):
    src = two_tool_sessions["cup"]
    stems = sorted(p.stem for p in (src / "masks").iterdir())
    frame = next(i for i, stem in enumerate(stems)
                 if {1, 2} <= set(read_mask_ids(src / "masks" / f"{stem}.png")[0].ravel()))
    before, _ = read_mask_ids(src / "masks" / f"{stems[frame]}.png")
    inject_fault(src, tmp_path / "swap", "id_swap", [frame])
    swapped, image = read_mask_ids(tmp_path / "swap" / "masks" / f"{stems[frame]}.png")
    assert image.mode == "P" and np.array_equal(swapped == 1, before == 2) and np.array_equal(swapped == 2, before == 1)
    fault = inject_fault(src, tmp_path / "merge", "tools_merged", [frame], seed=3)
    merged, _ = read_mask_ids(tmp_path / "merge" / "masks" / f"{stems[frame]}.png")
    keep = int(fault.severity)
    assert np.array_equal(merged == keep, before > 0) and not (merged == 3 - keep).any()
    with pytest.raises(ValueError, match="instruments 1 and 2"):
        inject_fault(sessions["cup"], tmp_path / "one", "id_swap", [20])


def test_clean_two_instrument_sessions_raise_few_flags_and_no_swap_or_merge(two_tool_sessions):
    from contact_viz.pipeline.check import check_session

    total = flagged = 0
    for session in two_tool_sessions.values():
        report = check_session(session)
        assert report.instruments == (1, 2)
        assert not {"id_swap", "tools_merged"} & set(report.fired), report.fired
        total += report.n_frames
        flagged += len(flagged_frames(report))
    assert flagged < 0.03 * total, flagged
