"""`contact-viz batch`: the chosen steps over every session of a dataset, on local cores or Ray.

For each session, in this order: ``depth`` (SGBM depth into the cache, for sessions with neither
depth/ nor disparity/), ``extract`` (``OUT/<name>/features.csv`` and its ``.json``), ``check``
(``OUT/<name>/check.json``), ``view`` (``OUT/<name>/view.rrd``); then, over the dataset, ``fit``
(``OUT/model.json``: the leave-one-session-out HMM ensemble) and ``evaluate`` (``OUT/metrics.json``
and ``OUT/per_frame.csv``: each session scored by the ensemble member that did not see it, or by
``--model``). ``OUT/summary.json`` sums it up.

Each step of each session is one task, except depth and extract, which are split into chunks of
``chunk_frames`` frames so that long sessions spread over the cores or the cluster; the chunks'
rows, concatenated, equal the whole session's. The driver writes every file, atomically, and
records in ``OUT/<name>/batch.json`` the key of each finished step (the session's files, the
parameters, the package version: :func:`contact_viz.io.cache.cache_key`); a re-run skips the
steps whose key is unchanged, so an interrupted run resumes where it stopped. A session that fails
is reported and the others go on.
"""

from __future__ import annotations

import csv
import io
import os
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from contact_viz import __version__
from contact_viz.errors import SessionError
from contact_viz.io.atomic import all_or_nothing, atomic_write
from contact_viz.io.cache import cache_key
from contact_viz.io.jsonfile import read_json, write_json
from contact_viz.params import LabelParams, PatchParams, to_dict
from contact_viz.pipeline.batch_steps import SessionJob, check_task, depth_task, extract_task, view_task

__all__ = ["SESSION_STEPS", "STEPS", "BatchOptions", "BatchSummary", "find_sessions", "run_batch", "summary_lines"]

SESSION_STEPS = ("depth", "extract", "check", "view")  # steps run per session, in this order
DATASET_STEPS = ("fit", "evaluate")  # steps run once over the dataset, after the session steps
STEPS = SESSION_STEPS + DATASET_STEPS


@dataclass(frozen=True)
class BatchOptions:
    """What `contact-viz batch` runs and how."""

    steps: tuple[str, ...] = ("depth", "extract", "check")  # steps to run (subset of STEPS)
    params: PatchParams = PatchParams()  # patch parameters of extract and view
    label_params: LabelParams = LabelParams()  # label threshold (force, N)
    object_ids: tuple[int, ...] | None = None  # object ids of palettized masks to run on (None = every instrument)
    cache_dir: str | None = None  # cache of features and SGBM depth (None = the default cache)
    chunk_frames: int = 256  # frames per depth/extract task, frames
    model_path: str | None = None  # model.json for view/evaluate (evaluate without fit needs it)

    def __post_init__(self) -> None:
        unknown = [s for s in self.steps if s not in STEPS]
        if unknown or not self.steps:
            raise ValueError(f"--steps: expected a comma-separated subset of {','.join(STEPS)}, got "
                             f"{','.join(self.steps) or 'nothing'}")
        if self.chunk_frames < 1:
            raise ValueError(f"--chunk-frames: expected a whole number >= 1, got {self.chunk_frames}")
        if "evaluate" in self.steps and "fit" not in self.steps and self.model_path is None:
            raise ValueError("--steps evaluate: give --model MODEL.json, or add fit to the steps")


@dataclass
class SessionOutcome:
    """What happened to one session."""

    name: str
    path: str
    frames: int = 0
    steps: dict[str, str] = field(default_factory=dict)  # step -> "done", "reused", "skipped: why" or "failed"
    seconds: dict[str, float] = field(default_factory=dict)  # step -> task time summed over chunks, s
    skipped_frames: dict[str, int] = field(default_factory=dict)  # why -> frames skipped (unreadable)
    no_patch: dict[str, int] = field(default_factory=dict)  # reason -> frames without a patch
    checks_fired: dict[str, int] = field(default_factory=dict)  # check -> frames flagged
    error: str | None = None  # the first failure, one line


@dataclass
class BatchSummary:
    """The dataset summary (``OUT/summary.json``)."""

    engine: str
    sessions: list[SessionOutcome]
    wall_s: dict[str, float]  # step -> wall time, s
    dataset: dict[str, str] = field(default_factory=dict)  # fit/evaluate -> outcome
    metrics: dict | None = None  # evaluate's table

    @property
    def failed(self) -> list[SessionOutcome]:
        return [s for s in self.sessions if s.error is not None]

    def to_dict(self) -> dict:
        return {"contact_viz_version": __version__, "engine": self.engine, "wall_s": self.wall_s,
                "sessions": [vars(s) for s in self.sessions], "dataset": self.dataset, "metrics": self.metrics,
                "failed": [s.name for s in self.failed]}


def find_sessions(source: str | Path) -> list[Path]:
    """The sessions of ``source``: a session folder, a folder of session folders, or a text file
    listing session folders (one per line, relative to the file's folder; ``#`` starts a comment)."""
    from contact_viz.io.session_files import natural_key

    source = Path(source).expanduser()
    if source.is_file():
        paths = []
        for number, line in enumerate(source.read_text().splitlines(), start=1):
            line = line.split("#", 1)[0].strip()
            if line:
                path = Path(line).expanduser()
                paths.append(path if path.is_absolute() else source.parent / path)
        if not paths:
            raise SessionError(source, "expected a list of session folders, one per line; found none")
        return [p.resolve() for p in paths]
    if not source.is_dir():
        raise SessionError(source, "expected a session folder, a folder of sessions or a list file")
    if (source / "left").is_dir():
        return [source.resolve()]
    found = sorted((p for p in source.iterdir() if p.is_dir() and (p / "left").is_dir()),
                   key=lambda p: natural_key(p.name))
    if not found:
        raise SessionError(source, "expected session folders (each with a left/ folder) in it; found none")
    return [p.resolve() for p in found]


class _State:
    """``OUT/<name>/batch.json``: the key of every finished step of one session."""

    def __init__(self, folder: Path) -> None:
        self.path = folder / "batch.json"
        self.steps: dict = (read_json(self.path, "expected the state file of contact-viz batch").get("steps", {})
                            if self.path.exists() else {})

    def is_done(self, step: str, key: str, outputs: Sequence[Path]) -> bool:
        return self.steps.get(step) == key and all(p.exists() for p in outputs)

    def mark(self, step: str, key: str) -> None:
        self.steps[step] = key
        write_json(self.path, {"contact_viz_version": __version__, "steps": self.steps})


def _chunks(n: int, size: int) -> list[tuple[int, int]]:
    return [(lo, min(lo + size, n)) for lo in range(0, n, size)]


def _step_key(job: SessionJob, step: str, depth_config: object, extra: object = None) -> str:
    return cache_key(job.path, f"batch-{step}", {"patch_params": to_dict(job.params),
                                                  "label_params": to_dict(job.label_params),
                                                  "object_ids": job.object_ids, "depth": depth_config,
                                                  "extra": extra})


def _features_csv(rows: list[dict[str, str]]) -> str:
    """features.csv as `contact-viz extract` writes it (a tool column only with instruments other than id 1)."""
    from contact_viz.pipeline.extract import feature_columns

    handle = io.StringIO()
    writer = csv.DictWriter(handle, fieldnames=feature_columns(rows), lineterminator="\n", extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    return handle.getvalue()


def _count_rows(outcome: SessionOutcome, rows: list[dict[str, str]]) -> None:
    from contact_viz.pipeline.extract import REASON_BAD_FRAME

    skipped, no_patch = Counter(), Counter()
    for row in rows:
        if row["reason"] == REASON_BAD_FRAME:
            folder = Path(row["detail"].split(": ", 1)[0]).parent.name or "frame"
            skipped[f"unreadable {folder}"] += 1
        elif row["reason"]:
            no_patch[row["reason"]] += 1
    outcome.skipped_frames, outcome.no_patch = dict(skipped), dict(no_patch)


def _count_checks(outcome: SessionOutcome, report: dict) -> None:
    outcome.checks_fired = {code: check["frames"] for code, check in report["checks"].items() if check["frames"]}


def run_batch(
    source: str | Path,
    out: str | Path,
    options: BatchOptions,
    engine,
    progress: Callable[[int, int, str], None] | None = None,
) -> BatchSummary:
    """Run ``options.steps`` over every session of ``source`` into ``out`` on ``engine``.

    Stopped by an error (a full disk: an OSError naming the file) or interrupted, the files of the
    steps already finished stay (each complete, written atomically; a re-run reuses them) and the
    folders this run made that hold nothing are removed, ``out`` too if it is empty and was new."""
    out = Path(out).expanduser().resolve()
    before = _folders(out)
    try:
        return _run_batch(source, out, options, engine, progress)
    except BaseException:
        _remove_new_empty_folders(out, before)
        raise


def _folders(top: Path) -> set[str]:
    """``top`` and every folder under it (empty when ``top`` does not exist)."""
    return {dirpath for dirpath, _, _ in os.walk(top)} if top.is_dir() else set()


def _remove_new_empty_folders(top: Path, before: set[str]) -> None:
    """In ``top`` and every folder under it, deepest first: remove the staging files of processes that are gone
    (a worker stopped mid-write leaves its own), then the folder itself if it is empty and not in ``before``."""
    from contact_viz.io.atomic import sweep_stale_in

    for dirpath, _, _ in os.walk(top, topdown=False):
        sweep_stale_in(dirpath)
        if dirpath not in before:
            try:
                os.rmdir(dirpath)  # only succeeds when empty
            except OSError:
                pass


def _run_batch(source: str | Path, out: Path, options: BatchOptions, engine,
               progress: Callable[[int, int, str], None] | None) -> BatchSummary:
    from contact_viz.io.session import open_session

    paths = find_sessions(source)
    for path in paths:
        if out == path or path in out.parents:
            raise ValueError(f"-o {out}: refusing to write inside the session directory {path}")
    outcomes, jobs, sessions = [], {}, {}
    for path in paths:
        outcome = SessionOutcome(name=path.name, path=str(path))
        outcomes.append(outcome)
        try:
            session = open_session(path, object_ids=options.object_ids, label_params=options.label_params,
                                   cache_dir=options.cache_dir)
        except SessionError as exc:
            outcome.error = str(exc)
            continue
        outcome.name, outcome.frames = session.name, len(session)
        sessions[session.name] = session
        jobs[session.name] = SessionJob(str(path), session.name, options.params, options.label_params,
                                        options.object_ids, options.cache_dir)
    names = [o.name for o in outcomes]
    duplicated = sorted({n for n in names if names.count(n) > 1})
    if duplicated:
        raise ValueError(f"session names must be distinct (set \"name\" in session.json); repeated: {duplicated}")
    by_name = {o.name: o for o in outcomes}
    states = {name: _State(out / name) for name in jobs}

    # Plan: which (session, step) are still to do.
    todo: dict[str, list[str]] = {}
    keys: dict[tuple[str, str], str] = {}
    for name, job in jobs.items():
        session = sessions[name]
        for step in (s for s in SESSION_STEPS if s in options.steps):
            if step == "depth" and session.depth_source != "sgbm":
                by_name[name].steps[step] = f"skipped: depth from {session.depth_source}/"
                continue
            extra = None
            if step == "view" and options.model_path is not None:
                model = Path(options.model_path).resolve()
                extra = [str(model), model.stat().st_mtime_ns]
            keys[name, step] = _step_key(job, step, session.depth_config, extra)
            outputs = {"depth": [], "extract": [out / name / "features.csv"], "check": [out / name / "check.json"],
                       "view": [out / name / "view.rrd"]}[step]
            if states[name].is_done(step, keys[name, step], outputs):
                by_name[name].steps[step] = "reused"
            else:
                todo.setdefault(step, []).append(name)
    total = sum(len(_chunks(len(sessions[n]), options.chunk_frames)) if s in ("depth", "extract") else 1
                for s, names_ in todo.items() for n in names_)
    total += sum(1 for s in DATASET_STEPS if s in options.steps)
    done = 0
    wall: dict[str, float] = {}

    def tick(step: str) -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, total, step)

    def fail(name: str, step: str, exc: BaseException) -> None:
        outcome = by_name[name]
        outcome.steps[step] = "failed"
        if outcome.error is None:
            outcome.error = f"{step}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}"

    for step in SESSION_STEPS:
        names_ = [n for n in todo.get(step, []) if by_name[n].error is None]
        if not names_:
            continue
        start = time.perf_counter()
        calls, owners = [], []
        for name in names_:
            job = jobs[name]
            if step in ("depth", "extract"):
                for lo, hi in _chunks(len(sessions[name]), options.chunk_frames):
                    calls.append((depth_task if step == "depth" else extract_task, (job, lo, hi)))
                    owners.append((name, lo))
            else:
                calls.append((check_task, (job,)) if step == "check" else (view_task, (job, options.model_path)))
                owners.append((name, 0))
        results: dict[str, dict[int, dict]] = {}
        base = done

        def step_progress(finished: int, step: str = step, base: int = base) -> None:
            nonlocal done
            done = base + finished
            if progress is not None:
                progress(done, total, step)

        for position, result in engine.run(calls, progress=step_progress):
            name, lo = owners[position]
            if isinstance(result, BaseException):
                fail(name, step, result)
                continue
            results.setdefault(name, {})[lo] = result
            by_name[name].seconds[step] = by_name[name].seconds.get(step, 0.0) + result["seconds"]
        for name in names_:
            outcome = by_name[name]
            if outcome.steps.get(step) == "failed":
                continue
            parts = [results[name][lo] for lo in sorted(results[name])]
            folder = out / name
            if step == "depth":
                failed = [f for part in parts for f in part["failed"]]
                outcome.steps[step] = "done" + (f" ({len(failed)} frames unreadable)" if failed else "")
            elif step == "extract":
                from contact_viz.pipeline.extract import run_config

                rows = [row for part in parts for row in part["rows"]]
                _count_rows(outcome, rows)
                with all_or_nothing():  # the .json first, the CSV last, or neither
                    write_json(folder / "features.csv.json", run_config(
                        sessions[name], patch_params=options.params, label_params=options.label_params))
                    with atomic_write(folder / "features.csv", newline="") as handle:
                        handle.write(_features_csv(rows))
                outcome.steps[step] = "done"
            elif step == "check":
                _count_checks(outcome, parts[0]["report"])
                write_json(folder / "check.json", parts[0]["report"])
                outcome.steps[step] = "done"
            else:
                with atomic_write(folder / "view.rrd", "wb") as handle:
                    handle.write(parts[0]["rrd"])
                outcome.steps[step] = "done"
            states[name].mark(step, keys[name, step])
        wall[step] = time.perf_counter() - start
    # Counts of reused steps come from the files already there.
    for name in jobs:
        outcome = by_name[name]
        if outcome.steps.get("extract") == "reused":
            from contact_viz.pipeline.extract import read_features

            _count_rows(outcome, read_features(out / name / "features.csv"))
        if outcome.steps.get("check") == "reused":
            _count_checks(outcome, read_json(out / name / "check.json", "expected a check report"))
    summary = BatchSummary(engine=engine.describe(), sessions=outcomes, wall_s=wall)
    if any(s in options.steps for s in DATASET_STEPS):
        from contact_viz.pipeline.batch_model import run_dataset_steps

        start = time.perf_counter()
        ready = [n for n in jobs if by_name[n].error is None]
        run_dataset_steps(summary, out, ready, options, tick, sessions)
        wall["dataset"] = time.perf_counter() - start
    write_json(out / "summary.json", summary.to_dict())
    return summary


def summary_lines(summary: BatchSummary) -> list[str]:
    """The dataset summary as lines to print: one row per session, then totals and failures."""
    steps = [s for s in SESSION_STEPS if any(s in o.steps for o in summary.sessions)]
    lines = [f"engine: {summary.engine}"]
    header = f"{'session':<24} {'frames':>6}  " + "  ".join(f"{s:<8}" for s in steps) + "  skipped  checks fired"
    lines.append(header)
    for o in summary.sessions:
        marks = "  ".join(f"{(o.steps.get(s, '-').split(':')[0].split(' ')[0]):<8}" for s in steps)
        skipped = sum(o.skipped_frames.values())
        fired = ", ".join(f"{k} ({v})" for k, v in sorted(o.checks_fired.items())) or "-"
        lines.append(f"{o.name:<24} {o.frames:>6}  {marks}  {skipped:>7}  {fired}")
    frames = sum(o.frames for o in summary.sessions)
    why = Counter()
    for o in summary.sessions:
        why.update(o.skipped_frames)
    skipped = sum(why.values())
    lines.append(f"{len(summary.sessions)} sessions, {frames} frames, {skipped} frames skipped"
                 + (": " + ", ".join(f"{n} {w}" for w, n in why.most_common()) if skipped else ""))
    if summary.wall_s:
        lines.append("time per step: " + ", ".join(f"{s} {t:.1f} s" for s, t in summary.wall_s.items()))
    for step, outcome in summary.dataset.items():
        lines.append(f"{step}: {outcome}")
    for o in summary.failed:
        lines.append(f"failed: {o.name}: {o.error}")
    return lines
