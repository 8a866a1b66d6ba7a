"""Measure the diagnostics: inject each failure into synthetic sessions and count what `check` flags.

:func:`inject_and_check` puts one failure of a kind into a session twice, once while the tool
approaches and once while it is in contact (windows of random length and position, severity drawn
from :data:`SEVERITY`, all from ``seed``), runs :func:`contact_viz.pipeline.check.check_session` on
the copy and returns per phase the injected frames and those flagged by any check.
:func:`detection_table` pools the outcomes per kind and phase. Used by
tests/test_failure_injection.py and benchmarks/bench_diagnostics.py.
"""

from __future__ import annotations

import csv
import shutil
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from contact_viz.checks.params import DiagnosticParams
from contact_viz.pipeline.check import CheckReport, check_session
from contact_viz.synth.faults import ALL_FAULT_KINDS, MULTI_FAULT_KINDS, inject_fault, read_mask_ids

__all__ = ["Injection", "InjectionOutcome", "SEVERITY", "decisions", "detection_table", "flagged_frames", "inject",
           "inject_and_check", "inject_and_check_job", "instruments_visible", "make_session_job", "outcome",
           "plan_pair_windows", "plan_windows", "read_truth_contact"]

# Severity drawn per injection (see contact_viz.synth.faults), for a 320 px wide image: lengths scale with width.
SEVERITY: dict[str, tuple] = {
    "mask_dropout": ("fixed", 0.0),
    "mask_drift": ("px", 4.0, 9.0),  # mask shifted by 4-9 px at 320 px width (a lagging mask)
    "mask_bleed": ("px", 5.0, 9.0),  # lobe radius
    "second_object": ("px", 4.0, 8.0),  # blob radius
    "depth_holes": ("uniform", 0.5, 0.9),  # share of tool + band invalid
    "edge_bleeding": ("px", 3.0, 6.0),  # tool depth smeared this far onto tissue
    "depth_scale": ("choice", 0.7, 0.8, 1.25, 1.4, 0.0),  # factor; 0 = disparity read as depth
    "depth_misregistration": ("px", 4.0, 8.0),  # depth shifted
    "force_offset": ("frames", 4, 8),  # +- frames
    "frozen_depth": ("fixed", 0.0),
    "id_swap": ("fixed", 0.0),  # ids 1 and 2 exchanged (two-instrument sessions)
    "tools_merged": ("fixed", 0.0),  # one id takes in the other (which one: from the seed)
}
MIN_VISIBLE_PX = 30  # an instrument counts as in view with at least this many mask pixels (at 320 px width), px
REFERENCE_WIDTH_PX = 320  # SEVERITY lengths are for this image width, px


@dataclass(frozen=True)
class InjectionOutcome:
    """One injected session: per phase ("approach", "contact") the injected and the flagged frames."""

    kind: str
    session: str
    severity: float
    injected: dict[str, tuple[int, ...]]
    flagged: dict[str, tuple[int, ...]]  # injected frames on which any check fired
    checks: dict[str, int]  # check code -> injected frames it fired on
    report: CheckReport


def read_truth_contact(session_dir: str | Path) -> np.ndarray:
    """truth.csv's contact column (0/1 per frame) of a synthetic session."""
    with (Path(session_dir) / "truth.csv").open(newline="") as handle:
        return np.array([int(row["contact"]) for row in csv.DictReader(handle)], dtype=np.int8)


def plan_windows(contact: np.ndarray, rng: np.random.Generator, visible: np.ndarray | None = None
                 ) -> dict[str, tuple[int, ...]]:
    """An approach window (4-10 frames, no contact, ending >= 3 frames before the first contact) and a
    contact window (3-8 frames inside the longest contact run), at random positions.

    ``visible`` (bool per frame, default all): the tool is in view; the approach window starts at least
    2 frames after it first is (a failure while no tool is in view is no failure)."""
    contact = np.asarray(contact, dtype=bool)
    first = int(np.argmax(contact)) if contact.any() else contact.size
    seen = 0 if visible is None or not np.any(visible) else int(np.argmax(np.asarray(visible, dtype=bool)))
    length = int(rng.integers(4, 11))
    last_start = first - 3 - length
    if last_start < seen + 2:
        raise ValueError("session too short before its first contact for an approach window")
    a0 = int(rng.integers(seen + 2, last_start + 1))
    runs = _runs(contact)
    if not runs:
        raise ValueError("session has no contact frames")
    r0, r1 = max(runs, key=lambda r: r[1] - r[0])
    c_len = int(rng.integers(3, max(4, min(9, r1 - r0))))
    c_len = min(c_len, r1 - r0)
    c0 = int(rng.integers(r0, r1 - c_len + 1))
    return {"approach": tuple(range(a0, a0 + length)), "contact": tuple(range(c0, c0 + c_len))}


def _runs(flags) -> list[tuple[int, int]]:
    """(start, stop) of every run of True in ``flags``, half-open, in order."""
    runs, start = [], None
    for i, flag in enumerate(np.append(np.asarray(flags, dtype=bool), False)):
        if flag and start is None:
            start = i
        elif not flag and start is not None:
            runs.append((start, i))
            start = None
    return runs


def plan_pair_windows(contact: np.ndarray, rng: np.random.Generator, both: np.ndarray) -> dict[str, tuple[int, ...]]:
    """Windows for a failure between two instruments (:data:`MULTI_FAULT_KINDS`): like :func:`plan_windows`
    an "approach" window of 4-10 frames without contact (here: no instrument in contact within 3 frames; the
    second instrument often touches first) and a contact window of 3-8 frames in a contact run, but only
    over frames where both instruments are in view (``both``, bool per frame), as is the frame before each
    window; each in the longest such run, shorter (down to 2 frames) where the runs are short. Raises
    ValueError when there is no such place."""
    contact = np.asarray(contact, dtype=bool)
    both = np.asarray(both, dtype=bool)
    ok = both & np.concatenate([[False], both[:-1]])  # this frame and the one before show both

    def place(allowed: np.ndarray, lo: int, hi: int) -> tuple[int, ...]:
        runs = _runs(allowed)
        if not runs:
            raise ValueError("no frames with both instruments in view for a window")
        r0, r1 = max(runs, key=lambda r: r[1] - r[0])
        length = min(int(rng.integers(lo, hi + 1)), r1 - r0)
        if length < 2:
            raise ValueError("both instruments are in view for too short a time for a window")
        a0 = int(rng.integers(r0, r1 - length + 1))
        return tuple(range(a0, a0 + length))

    near_contact = np.convolve(contact.astype(int), np.ones(7, int), mode="same") > 0  # within 3 frames of one
    before = ok & ~near_contact  # approaching (or retracting): no instrument in contact nearby
    before[:2] = False
    during = ok & contact
    if not during.any():
        raise ValueError("no contact frames with both instruments in view")
    runs, start = [], None
    for i, c in enumerate(np.append(contact, False)):
        if c and start is None:
            start = i
        elif not c and start is not None:
            runs.append((start, i))
            start = None
    r0, r1 = max(runs, key=lambda r: int(during[r[0]:r[1]].sum()))
    in_run = np.zeros_like(during)
    in_run[r0:r1] = during[r0:r1]
    return {"approach": place(before, 4, 10), "contact": place(in_run, 3, 8)}


def instruments_visible(session_dir: str | Path, min_px: int = MIN_VISIBLE_PX) -> np.ndarray:
    """(frames, 2) bool: instruments 1 and 2 in view (mask pixels of that object id, at least ``min_px`` at
    320 px width, scaled by the area), masks/ in frame order."""
    paths = sorted((p for p in (Path(session_dir) / "masks").iterdir() if not p.name.startswith(".")),
                   key=lambda p: int(p.stem))
    out = []
    for path in paths:
        ids, _ = read_mask_ids(path)
        limit = min_px * (ids.shape[1] / REFERENCE_WIDTH_PX) ** 2
        out.append((np.count_nonzero(ids == 1) >= limit, np.count_nonzero(ids == 2) >= limit))
    return np.array(out, dtype=bool).reshape(-1, 2)


def _severity(kind: str, rng: np.random.Generator, width: int) -> float:
    spec = SEVERITY[kind]
    if spec[0] == "fixed":
        return float(spec[1])
    if spec[0] == "px":
        return float(rng.uniform(spec[1], spec[2]) * width / REFERENCE_WIDTH_PX)
    if spec[0] == "uniform":
        return float(rng.uniform(spec[1], spec[2]))
    if spec[0] == "choice":
        return float(rng.choice(spec[1:]))
    if spec[0] == "frames":
        return float(rng.integers(spec[1], spec[2] + 1) * rng.choice([-1, 1]))
    raise ValueError(spec)


def flagged_frames(report: CheckReport, ignore: Iterable[str] = ()) -> set[int]:
    """Frames on which any check of ``report`` fired (except those in ``ignore``)."""
    out: set[int] = set()
    for code, ranges in report.fired.items():
        if code in ignore:
            continue
        for a, b in ranges:
            out.update(range(a, b + 1))
    return out


@dataclass(frozen=True)
class Injection:
    """A copy of a session with one failure injected (:func:`inject`), before it is checked."""

    kind: str
    session: str  # the clean session's name
    path: Path  # the copy
    severity: float
    windows: dict[str, tuple[int, ...]]  # per phase ("approach", "contact") the injected frames


def inject(session_dir: str | Path, work_dir: str | Path, kind: str, seed: int) -> Injection:
    """Inject ``kind`` into a copy of ``session_dir`` (in ``work_dir``) in an approach and a contact window."""
    session_dir = Path(session_dir)
    rng = np.random.default_rng(seed)
    if kind in MULTI_FAULT_KINDS:
        windows = plan_pair_windows(read_truth_contact(session_dir), rng, instruments_visible(session_dir).all(axis=1))
    else:
        windows = plan_windows(read_truth_contact(session_dir), rng, _tool_visible(session_dir))
    severity = _severity(kind, rng, _image_width(session_dir))
    dst = Path(work_dir) / f"{session_dir.name}_{kind}_{seed}"
    if dst.exists():
        shutil.rmtree(dst)
    fault = inject_fault(session_dir, dst, kind, windows["approach"] + windows["contact"], severity, seed=seed)
    if kind == "force_offset":  # the whole session is shifted: every frame of each phase is injected
        contact = read_truth_contact(session_dir).astype(bool)
        windows = {"approach": tuple(int(i) for i in np.nonzero(~contact)[0]),
                   "contact": tuple(int(i) for i in np.nonzero(contact)[0])}
    return Injection(kind, session_dir.name, dst, fault.severity, windows)


def outcome(injection: Injection, report: CheckReport) -> InjectionOutcome:
    """What ``report`` (`check` on the injected copy) flagged of the injected frames."""
    # a frame failure counts only where a frame check fired (a session check firing on every frame would
    # flag them all); the force offset only where the session check did
    from contact_viz.checks.rules import SESSION_CHECKS

    windows = injection.windows
    if injection.kind != "force_offset":
        flagged = flagged_frames(report, ignore=SESSION_CHECKS)
    else:
        flagged = flagged_frames(report, ignore=[c for c in report.fired if c != "force_lag"])
    injected_all = set(windows["approach"]) | set(windows["contact"])
    checks = {}
    for code, ranges in report.fired.items():
        hit = sum(1 for a, b in ranges for i in range(a, b + 1) if i in injected_all)
        if hit:
            checks[code] = hit
    return InjectionOutcome(injection.kind, injection.session, injection.severity, windows,
                            {phase: tuple(i for i in idx if i in flagged) for phase, idx in windows.items()},
                            checks, report)


def inject_and_check(session_dir: str | Path, work_dir: str | Path, kind: str, seed: int,
                     params: DiagnosticParams | None = None, keep: bool = False) -> InjectionOutcome:
    """Inject ``kind`` into ``session_dir`` in an approach and a contact window, check the copy."""
    injection = inject(session_dir, work_dir, kind, seed)
    try:
        report = check_session(injection.path, params=params)
    finally:
        if not keep:
            shutil.rmtree(injection.path, ignore_errors=True)
    return outcome(injection, report)


def decisions(report: CheckReport) -> set[tuple[str, int | None, int]]:
    """Every decision to fire in ``report``: (check, instrument or None, frame)."""
    out = {(code, None, i) for code, ranges in report.fired.items() for a, b in ranges for i in range(a, b + 1)}
    out |= {(code, tool, i) for code, tools in report.tool_fired.items() for tool, ranges in tools.items()
            for a, b in ranges for i in range(a, b + 1)}
    return out


def _tool_visible(session_dir: Path) -> np.ndarray:
    """Per frame: the tool mask has pixels (masks/ in frame order)."""
    from PIL import Image

    masks = sorted((p for p in (session_dir / "masks").iterdir() if not p.name.startswith(".")),
                   key=lambda p: int(p.stem))
    out = []
    for path in masks:
        with Image.open(path) as image:
            out.append(bool(np.asarray(image).any()))
    return np.array(out, dtype=bool)


def _image_width(session_dir: Path) -> int:
    from PIL import Image

    left = sorted(p for p in (session_dir / "left").iterdir() if not p.name.startswith("."))[0]
    with Image.open(left) as image:
        return image.size[0]


def detected(outcome: InjectionOutcome, phase: str, min_share: float = 0.9, onset_frames: int = 2) -> bool:
    """The target per injection and phase: flagged on >= ``min_share`` of the injected frames, or a
    flag within ``onset_frames`` of the window's first frame."""
    injected, flagged = outcome.injected[phase], outcome.flagged[phase]
    if not injected:
        return True
    if len(flagged) >= min_share * len(injected):
        return True
    return any(i - injected[0] <= onset_frames for i in flagged) if outcome.kind != "force_offset" else False


def detection_table(outcomes: list[InjectionOutcome]) -> list[dict]:
    """Per kind: flagged / injected frames and injections meeting the target, in approach and in contact."""
    rows = []
    for kind in ALL_FAULT_KINDS:
        mine = [o for o in outcomes if o.kind == kind]
        if not mine:
            continue
        row = {"kind": kind, "injections": len(mine)}
        for phase in ("approach", "contact"):
            row[f"{phase}_flagged"] = sum(len(o.flagged[phase]) for o in mine)
            row[f"{phase}_injected"] = sum(len(o.injected[phase]) for o in mine)
            row[f"{phase}_detected"] = sum(detected(o, phase) for o in mine)
        checks: dict[str, int] = {}
        for o in mine:
            for code, n in o.checks.items():
                checks[code] = checks.get(code, 0) + n
        row["checks"] = ", ".join(f"{c} {n}" for c, n in sorted(checks.items(), key=lambda kv: -kv[1])[:3])
        rows.append(row)
    return rows


def make_session_job(args) -> Path:
    """``generate_session(out, SynthParams(phantom, frames, seed, width, height[, tools[, shaft_elevation_deg]]))``
    from one tuple (for process pools)."""
    from contact_viz.synth import SynthParams, generate_session

    out, phantom, seed, frames, width, height, *more = args
    extra = dict(zip(("tools", "shaft_elevation_deg"), more))
    return generate_session(out, SynthParams(phantom=phantom, frames=frames, seed=seed, width=width, height=height,
                                             **extra))


def inject_and_check_job(args) -> InjectionOutcome:
    """:func:`inject_and_check` from one (session_dir, work_dir, kind, seed) tuple (for process pools)."""
    return inject_and_check(*args)
