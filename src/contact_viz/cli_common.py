"""What the commands of `contact-viz` share: the error line, progress bars, option types, the
parameters from --params/--contact-force, and loading features for fit / evaluate / predict."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer


def _fail(message: str) -> None:
    typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
    raise typer.Exit(code=2)


def _parse_size(size: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in size.lower().split("x"))
    except ValueError:
        _fail(f"--size must look like WIDTHxHEIGHT, e.g. 1920x1080; got {size!r}")
    if width < 32 or height < 32:
        _fail(f"--size must be at least 32x32, got {size!r}")
    return width, height


def _progress():
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    class _Rate(TextColumn):
        def render(self, task):  # frames per second over the run so far
            elapsed = task.elapsed or 0.0
            return f"{task.completed / elapsed:5.1f} frames/s" if elapsed > 0 else "  --- frames/s"

    from rich.console import Console

    # on stderr, and only on a terminal: stdout holds the results (what the README quotes, what a pipe
    # reads), and a log file or a CI job gets the one-line messages without a bar's last state
    console = Console(stderr=True)
    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), _Rate(""),
                    TimeElapsedColumn(), TimeRemainingColumn(), transient=False, console=console,
                    disable=not console.is_terminal)


class _LazyProgress:
    """A progress bar that appears with the first update, so a command refused up front prints none."""

    def __init__(self, description: str, total: int | None) -> None:
        self.description, self.total, self.progress, self.task = description, total, None, None

    def update(self, **fields) -> None:
        if self.progress is None:
            self.progress = _progress()
            self.progress.start()
            self.task = self.progress.add_task(self.description, total=self.total)
        self.progress.update(self.task, **fields)

    def __enter__(self) -> "_LazyProgress":
        return self

    def __exit__(self, *exc) -> None:
        if self.progress is not None:
            self.progress.stop()


def _print_report(report) -> None:
    """The frame warnings of a run, then its summary line (contact_viz.console.FrameReport)."""
    for line in report.lines:
        typer.secho(line, fg=typer.colors.YELLOW, err=True)
    summary = report.summary()
    if summary:
        typer.secho(summary, fg=typer.colors.YELLOW, err=True)


def _inside(path: Path, directory: Path) -> bool:
    try:
        path.resolve().relative_to(directory.resolve())
        return True
    except ValueError:
        return False


ObjectId = Annotated[Optional[list[int]], typer.Option(
    "--object-id", min=1, metavar="ID", callback=lambda ids: tuple(sorted(set(ids))) or None if ids else None,
    help="Run on this instrument (object id of palettized masks) only; repeat for several. The other "
    "instruments stay excluded from the tissue. Default: every instrument.")]
ContactForce = Annotated[float, typer.Option(help="Contact label threshold on the force magnitude, N.")]
ParamsFile = Annotated[Optional[Path], typer.Option("--params", help="JSON of PatchParams fields "
                       "(e.g. from recipes/grid_search.py).")]
CacheDir = Annotated[Optional[Path], typer.Option(help="Cache of features and computed depth, outside the "
                     "sessions [default: ~/.cache/contact-viz].")]


def _resolve_params(params_file: Optional[Path], contact_force: float):
    """PatchParams from --params (defaults otherwise) and LabelParams from --contact-force; exits on error."""
    from contact_viz.params import LabelParams, PatchParams, read_patch_params

    import math

    if not (math.isfinite(contact_force) and contact_force > 0):
        _fail(f"--contact-force: expected a force > 0 N, got {contact_force:g}")
    try:
        params = PatchParams() if params_file is None else read_patch_params(params_file)
        return params, LabelParams(contact_force_n=contact_force)
    except ValueError as exc:
        _fail(str(exc))


def _load_features(sources: list[Path], params, label_params, object_ids, cache_dir) -> list:
    """Features for fit / evaluate / predict (contact_viz.pipeline.features.load_features), with a
    progress bar per session and a count of its skipped frames; exits with one line on a bad source."""
    from contact_viz.console import FrameReport
    from contact_viz.errors import SessionError
    from contact_viz.pipeline.allocator import keep_freed_memory
    from contact_viz.pipeline.features import load_features
    from contact_viz.pipeline.parallel import DEFAULT_PROCESSES

    keep_freed_memory()
    bars = []  # the progress bar of the session whose features are being computed (at most one)

    def opened(session):
        typer.echo(session.depth_note, err=True)
        bar = _progress()
        bar.start()
        task = bar.add_task(f"features {session.name}", total=len(session))
        bars.append((bar, task, session))
        return lambda frames_done: bar.update(task, completed=frames_done)

    def finished(source, features):
        if bars:  # a session directory (a features CSV has no bar)
            bar, task, session = bars.pop()
            if features.cached:
                bar.update(task, completed=len(session), description=f"features {session.name} (cached)")
            bar.stop()
        report = FrameReport.from_rows(features.rows)
        if report.n_frames:  # the warning lines are in the features; here only the count
            typer.secho(f"{features.name}: {report.summary()} (see `contact-viz extract {source}` for each)",
                        fg=typer.colors.YELLOW, err=True)

    try:
        return load_features(sources, params, label_params, object_ids=object_ids, cache_dir=cache_dir,
                             processes=DEFAULT_PROCESSES, on_open=opened, on_done=finished)
    except (SessionError, ValueError, KeyError) as exc:
        _fail(str(exc))
    finally:
        for bar, _, _ in bars:  # interrupted by an error
            bar.stop()


def _model_and_features(model_path: Path, sources: list[Path], object_ids, cache_dir):
    from contact_viz.model.model_file import load_model

    try:
        model = load_model(model_path)
    except ValueError as exc:
        _fail(str(exc))
    features = _load_features(sources, model.patch_params, model.label_params, object_ids, cache_dir)
    return model, features


def _write_evaluation(per_frame, json_out, scores, table, model, model_path) -> None:
    from contact_viz.model.evaluation import per_frame_columns, per_frame_rows
    from contact_viz.paper.tables import write_per_frame

    if per_frame is not None:
        write_per_frame(per_frame, per_frame_columns(scores), per_frame_rows(scores))
    if json_out is not None:
        from contact_viz import __version__
        from contact_viz.io.jsonfile import write_json
        from contact_viz.params import to_dict

        write_json(json_out, {"contact_viz_version": __version__, "model": str(model_path.resolve()),
                              "threshold": model.threshold, "patch_params": to_dict(model.patch_params),
                              "metrics": table})


