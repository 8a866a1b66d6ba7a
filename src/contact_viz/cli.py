"""The `contact-viz` command line: thin wrappers over the library.

Heavy modules (open3d for `synth`, rerun for the viewer, torch for the baseline) are imported
inside the commands that use them, so `contact-viz extract` never pays for them at start-up.
"""

from __future__ import annotations

import signal
import sys
import threading
from multiprocessing import parent_process

# A stop signal (SIGINT, SIGTERM, SIGHUP) while the command starts up, before main() installs the console's
# handlers, is noted here and answered with its line by main(): without this, a signal in the first ~0.1-0.5 s
# (imports; longer on a loaded machine) killed the command silently. Only when this module runs the command.
_EARLY_STOP: list[int] = []
if ((__name__ == "__main__" or sys.argv[0].endswith("contact-viz")) and parent_process() is None  # not a worker
        and threading.current_thread() is threading.main_thread()):
    for _signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(_signum, lambda signum, frame: _EARLY_STOP.append(int(signum)))

import warnings  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Annotated, Optional  # noqa: E402

import typer  # noqa: E402

from contact_viz.cli_common import (
    CacheDir,
    ContactForce,
    ObjectId,
    ParamsFile,
    _LazyProgress,
    _fail,
    _inside,
    _load_features,
    _model_and_features,
    _parse_size,
    _print_report,
    _progress,
    _resolve_params,
    _write_evaluation,
)
from contact_viz.cli_edge import EdgeGroup
from contact_viz.model.kinds import FIT_DEFAULT_KIND

app = typer.Typer(
    cls=EdgeGroup,  # bad input: one error line and exit 2 (contact_viz.cli_edge)
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,  # plain help: no defaults cut at 80 columns, "[default: ...]" is text, not markup
    help="Visual debugger for tool-tissue contact detection from stereo depth.\n\n"
         "`contact-viz SESSION [OPTIONS]` is short for `contact-viz view SESSION [OPTIONS]`.",
)


def _version(value: bool) -> None:
    if value:
        from contact_viz import __version__

        typer.echo(f"contact-viz {__version__}")
        raise typer.Exit()


@app.callback()
def _main_options(
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Show tracebacks and the log lines of OpenCV "
                       "and Rerun (may also follow the command).")] = False,
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                       help="Print the version and exit.")] = False,
) -> None:
    """Visual debugger for tool-tissue contact detection from stereo depth."""
    from contact_viz import console

    console.quiet_libraries(verbose or console.VERBOSE)


@app.command()
def extract(
    session_dir: Annotated[Path, typer.Argument(help="Session directory (docs/session.md).")],
    output: Annotated[Optional[Path], typer.Option("-o", "--output", help="features CSV to write "
                      "[default: results/<session name>/features.csv]")] = None,
    object_ids: ObjectId = None,
    contact_force: ContactForce = 2.0,
    params_file: ParamsFile = None,
    cache_dir: CacheDir = None,
    processes: Annotated[Optional[int], typer.Option(
        min=1, help="Processes to spread the frames over, this one included [default: the number of cores, "
        "at most 8].")] = None,
) -> None:
    """Compute the minimum-distance patch of every frame and write one row per frame and instrument."""
    from contact_viz.console import FrameReport, check_output_file
    from contact_viz.pipeline.allocator import keep_freed_memory
    from contact_viz.pipeline.parallel import DEFAULT_PROCESSES, ProcessPool, WorkerError

    keep_freed_memory()
    # The workers start first, so that they import NumPy, OpenCV and the patch while this
    # process does the same and opens the session.
    with ProcessPool(processes or DEFAULT_PROCESSES, initializer=keep_freed_memory,
                     preload=("contact_viz.pipeline.extract",)) as pool:
        from contact_viz.errors import SessionError
        from contact_viz.pipeline.extract import BadFrameWarning, extract_features, run_config, write_features
        from contact_viz.io.session import open_session

        params, label_params = _resolve_params(params_file, contact_force)
        try:
            session = open_session(session_dir, object_ids=object_ids, label_params=label_params, cache_dir=cache_dir)
        except SessionError as exc:
            _fail(str(exc))
        typer.echo(session.depth_note, err=True)
        output = output or Path("results") / session.name / "features.csv"
        check_output_file(output, "-o/--output", session_root=session.root, example="features.csv")
        check_output_file(output.with_name(output.name + ".json"), "-o/--output (its .json)")
        with warnings.catch_warnings(record=True) as caught, _progress() as progress:
            warnings.simplefilter("always", BadFrameWarning)  # the rows carry the same; reported below
            task = progress.add_task(f"extract {session.name}", total=len(session))
            try:
                rows = extract_features(session, params, progress=lambda done: progress.update(task, completed=done),
                                        pool=pool)
            except WorkerError as exc:
                _fail(str(exc))
    from contact_viz.io.depth_cache import CacheWarning

    for w in caught:  # a depth cache that filled up during the run: its one warning line
        if issubclass(w.category, CacheWarning):
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    report = FrameReport.from_rows(rows, lambda layer, stem: session.layer_file(layer, stem))
    _print_report(report)
    bad = sum(1 for r in rows if r["reason"] == "bad_frame")
    if bad == len(rows):
        _fail(f"{session.root}: no frame could be read ({report.summary()}); nothing written")
    write_features(rows, output, run_config(session, patch_params=params, label_params=label_params))
    found = sum(1 for r in rows if r["distance_m"] != "")
    tools = sorted({r["tool"] for r in rows if r["tool"] != ""})
    if tools in ([], [1]):
        typer.echo(f"{output}: {len(rows)} frames, patch found on {found}, {bad} unreadable")
    else:
        typer.echo(f"{output}: {len(session)} frames, {len(rows)} rows (instruments "
                   f"{', '.join(map(str, tools))}), patch found on {found}, {bad} unreadable")


@app.command()
def synth(
    out_dir: Annotated[Path, typer.Argument(help="Directory to create the session in (must be new or empty).")],
    phantom: Annotated[str, typer.Option(help="Tissue shape: cup, kidney, liver or glove (pulling task).")] = "cup",
    frames: Annotated[int, typer.Option(min=1, help="Number of frames.")] = 120,
    seed: Annotated[int, typer.Option(help="Random seed (same seed and options = same files).")] = 0,
    size: Annotated[str, typer.Option(help="Image size WIDTHxHEIGHT.")] = "1920x1080",
    tools: Annotated[int, typer.Option(min=1, max=2, help="Instruments in the scene: 1, or 2 (the second one "
                                       "presses while the first hovers, passes within a few px of it and "
                                       "crosses in front of it; mask id 2).")] = 1,
    shaft_elevation_deg: Annotated[Optional[float], typer.Option(
        help="Angle of the shafts above the tissue base plane, deg (e.g. 8: lying nearly flat); "
             "default: drawn around the phantom's usual axis (about 35-40 deg).")] = None,
    camera: Annotated[str, typer.Option(
        help="Stereo endoscope: default (80 deg horizontal field of view, 5 mm baseline, tissue at 90 mm), "
             "davinci (measured from a da Vinci calibration: fx 1103.4 px at 1920 px wide = 82.05 deg, "
             "4.11 mm baseline, 50 mm working distance) or close (the davinci endoscope at 30 mm). A camera "
             "that sees less of the tissue than the default (nearer, or narrower) sees the phantom shrunk to "
             "fill the same part of the image, and the gaps too when it sees less than the default's field at "
             "50 mm; the instruments keep their size.")] = "default",
    fov_deg: Annotated[Optional[float], typer.Option(
        help="Horizontal field of view, deg (30-120) [default: the camera's].")] = None,
    baseline_mm: Annotated[Optional[float], typer.Option(
        help="Stereo baseline, mm [default: the camera's].")] = None,
    working_distance_mm: Annotated[Optional[float], typer.Option(
        help="Distance from the camera to the tissue base plane along the optical axis, mm "
             "[default: the camera's].")] = None,
    overwrite: Annotated[bool, typer.Option(help="Replace the files of an existing session there.")] = False,
    live: Annotated[bool, typer.Option(help="Write the session frame by frame at --fps, as a recorder does "
                                       "(the same files in the end; for `contact-viz SESSION --follow`).")] = False,
    fps: Annotated[Optional[float], typer.Option(min=0.001, help="With --live: frames written per second "
                                                 "[default: the session's 30].")] = None,
    rename: Annotated[bool, typer.Option(help="With --live: write each file under a hidden .tmp name and rename "
                                         "it into place; --no-rename: write it in place, slowly, in pieces "
                                         "(readers see half-written files).")] = True,
    prerender: Annotated[bool, typer.Option(help="With --live: render every frame before writing the first "
                                            "(no rendering during the writing).")] = False,
) -> None:
    """Make a synthetic session with known truth (stereo renders, masks, depth, force, truth.csv)."""
    from contact_viz.synth import PHANTOMS, SynthParams, generate_session
    from contact_viz.synth.camera import camera_fields

    if phantom not in PHANTOMS:
        _fail(f"--phantom must be one of {', '.join(PHANTOMS)}; got {phantom!r}")
    if not live and (fps is not None or not rename or prerender):
        _fail("--fps, --no-rename and --prerender go with --live")
    for option, value in (("--baseline-mm", baseline_mm), ("--working-distance-mm", working_distance_mm)):
        if value is not None and not value > 0:
            _fail(f"{option} must be a number > 0, got {value:g}")
    width, height = _parse_size(size)
    try:
        geometry = camera_fields(camera, fov_deg=fov_deg, baseline_mm=baseline_mm,
                                 working_distance_mm=working_distance_mm)
    except ValueError as exc:
        _fail(str(exc))
    try:
        params = SynthParams(phantom=phantom, frames=frames, seed=seed, width=width, height=height, tools=tools,
                             shaft_elevation_deg=shaft_elevation_deg, **geometry)
    except ValueError as exc:
        _fail(str(exc).replace("SynthParams.", "--").replace("_", "-"))
    if live:
        _synth_live(out_dir, params, fps, rename, prerender, overwrite)
        return
    with _LazyProgress(f"synth {phantom}", frames) as progress:  # no bar before the target is accepted
        try:
            path = generate_session(out_dir, params, overwrite=overwrite,
                                    progress=lambda done, total: progress.update(completed=done))
        except (FileExistsError, ValueError, RuntimeError) as exc:
            _fail(str(exc).replace("pass overwrite=True", "pass --overwrite"))
    instruments = "" if tools == 1 else f" with {tools} instruments"
    lens = "" if geometry == camera_fields() else (
        f", camera {params.fov_deg:.2f} deg, baseline {params.baseline_m * 1e3:.2f} mm, "
        f"tissue at {params.tissue_distance_m * 1e3:.0f} mm")
    typer.echo(f"{path}: {frames} frames of the {phantom} phantom at {width}x{height}{instruments}{lens}")


def _synth_live(out_dir: Path, params, fps: float | None, rename: bool, prerender: bool, overwrite: bool) -> None:
    """`synth --live`: one line at the start, one at the end (also when stopped by Ctrl-C or SIGTERM)."""
    from contact_viz.synth import write_live

    rate = params.fps if fps is None else fps
    written = 0

    def count(k: int, late_s: float) -> None:
        nonlocal written
        written = k + 1

    typer.echo(f"writing {out_dir} live at {rate:g} frames/s: {params.frames} frames")
    try:
        stats = write_live(out_dir, params, rate, rename=rename, prerender=prerender, overwrite=overwrite,
                           on_frame=count)
    except (FileExistsError, ValueError, RuntimeError) as exc:
        _fail(str(exc).replace("pass overwrite=True", "pass --overwrite"))
    except KeyboardInterrupt:
        if written:
            typer.echo(f"{out_dir}: stopped after {written} of {params.frames} frames (a session of those frames)")
        else:
            typer.echo(f"{out_dir}: stopped before the first frame")
        raise
    typer.echo(stats.line(out_dir))


@app.command()
def fit(
    train_sessions: Annotated[list[Path], typer.Argument(help="Labelled training session directories (at least 2).")],
    output: Annotated[Path, typer.Option("-o", "--output", help="model.json to write.")] = Path("model.json"),
    params_file: ParamsFile = None,
    contact_force: ContactForce = 2.0,
    object_ids: ObjectId = None,
    cache_dir: CacheDir = None,
    model_kind: Annotated[str, typer.Option(
        help="The HMM's emission (docs/method.md): clip (the paper's Gaussians on the signal clipped to the training range and the rising side of their ratio: a nearer tool is never less evidence of contact), paper (the paper's six-parameter HMM, exact: its contact Gaussian is the narrower, so a tool nearer than the contact mean reads as less in contact), tied (one variance for both states), flat (the paper's with the contact density held flat above its mean and the no-contact one below its mean) or isotonic (a calibrated monotone likelihood ratio)")] = FIT_DEFAULT_KIND,
) -> None:
    """Fit the leave-one-session-out HMM ensemble and its threshold on training sessions.

    Several instruments: each instrument's signal is a sequence of its own; in a frame labelled
    contact the instrument nearest the tissue gets contact and the others none (unless labels.csv
    labels each instrument: frame,tool,contact); the threshold is chosen on the scene posterior."""
    from contact_viz.console import check_output_file, session_training_problem
    from contact_viz.model.hmm import HMMParams
    from contact_viz.model.kinds import MODEL_KINDS
    from contact_viz.model.model_file import ContactModel, save_model
    from contact_viz.pipeline.features import fit_loso

    if model_kind not in MODEL_KINDS:
        _fail(f"--model-kind must be one of {', '.join(MODEL_KINDS)}; got {model_kind!r}")
    params, label_params = _resolve_params(params_file, contact_force)
    if len(train_sessions) < 2:
        _fail(f"fit needs at least 2 training sessions for leave-one-session-out, got {len(train_sessions)}")
    check_output_file(output, "-o/--output", example="model.json")
    features = _load_features(train_sessions, params, label_params, object_ids, cache_dir)
    problem = session_training_problem([f.name for f in features], [f.labels for f in features],
                                       [f.signal for f in features])
    if problem:
        _fail(problem)
    try:
        ensemble = fit_loso(features, HMMParams(model_kind=model_kind))
    except ValueError as exc:
        _fail(str(exc))
    model = ContactModel(
        ensemble=ensemble, patch_params=params, label_params=label_params,
        training_sessions=tuple(f.training_entry(str(p.resolve())) for f, p in zip(features, train_sessions)),
    )
    save_model(model, output)
    typer.echo(f"{output}: {len(features)} LOSO models ({model_kind}), threshold {model.threshold:.4f}")
    for hmm, name in zip(ensemble.models_, ensemble.session_names_):
        m, v, a = hmm.means_, hmm.vars_, hmm.transmat_
        tied = f" (tied {hmm.emission_.var_ ** 0.5:.3f})" if model_kind == "tied" else ""
        typer.echo(f"  without {name}: means {m[0]:.3f} / {m[1]:.3f}, sd {v[0] ** 0.5:.3f} / {v[1] ** 0.5:.3f}"
                   f"{tied}, stay {a[0, 0]:.3f} / {a[1, 1]:.3f}")


@app.command()
def evaluate(
    model_path: Annotated[Path, typer.Argument(metavar="MODEL", help="model.json from `contact-viz fit`.")],
    test_sessions: Annotated[list[Path], typer.Argument(help="Labelled test session directories or features CSVs.")],
    per_frame: Annotated[Optional[Path], typer.Option(help="CSV of session, frame, signal, posterior, "
                         "predicted, label for every frame.")] = None,
    json_out: Annotated[Optional[Path], typer.Option("--json", help="Metrics as JSON.")] = None,
    markdown: Annotated[bool, typer.Option(help="Also print the table as Markdown.")] = False,
    latex: Annotated[bool, typer.Option(help="Also print the table as LaTeX (booktabs).")] = False,
    object_ids: ObjectId = None,
    cache_dir: CacheDir = None,
) -> None:
    """Score held-out sessions: the Table-1 metrics per session and their macro mean.

    Several instruments: a session is scored on its scene posterior (the max over the instruments in
    the frame); where labels.csv labels each instrument, a row "SESSION tool ID" per instrument too."""
    from contact_viz.console import check_output_file
    from contact_viz.model.evaluation import metrics_table
    from contact_viz.model.metrics import format_table
    from contact_viz.pipeline.features import score_features

    for path, option in ((per_frame, "--per-frame"), (json_out, "--json")):
        if path is not None:
            check_output_file(path, option, example="metrics.json" if option == "--json" else "per_frame.csv")
    model, features = _model_and_features(model_path, test_sessions, object_ids, cache_dir)
    try:
        scores = [score_features(model.predict_proba, model.threshold, f) for f in features]
        table = metrics_table(scores, model.threshold)
    except ValueError as exc:
        _fail(str(exc))
    from contact_viz.io.atomic import all_or_nothing

    with all_or_nothing():  # both outputs or neither (e.g. a full disk under --json)
        _write_evaluation(per_frame, json_out, scores, table, model, model_path)  # before anything is printed
    typer.echo(format_table(table, style="text"))
    for note in [n for row in table.values() for n in row.get("notes", [])]:
        typer.echo(f"note: {note}")
    if markdown:
        typer.echo("\n" + format_table(table, style="markdown"))
    if latex:
        typer.echo("\n" + format_table(table, style="latex"))


@app.command()
def predict(
    model_path: Annotated[Path, typer.Argument(metavar="MODEL", help="model.json from `contact-viz fit`.")],
    session_dir: Annotated[Path, typer.Argument(help="Session directory (labels not needed).")],
    output: Annotated[Path, typer.Option("-o", "--output", help="CSV to write.")] = Path("predictions.csv"),
    object_ids: ObjectId = None,
    cache_dir: CacheDir = None,
) -> None:
    """Contact posteriors for a session, with or without labels (several instruments: the scene's, and
    each instrument's in posterior_tool_ID columns)."""
    from contact_viz.console import check_output_file
    from contact_viz.model.evaluation import per_frame_columns, per_frame_rows
    from contact_viz.paper.tables import write_per_frame
    from contact_viz.pipeline.features import score_features

    check_output_file(output, "-o/--output", example="predictions.csv")
    model, (features,) = _model_and_features(model_path, [session_dir], object_ids, cache_dir)
    scores = score_features(model.predict_proba, model.threshold, features)
    write_per_frame(output, per_frame_columns([scores]), per_frame_rows([scores]))
    typer.echo(f"{output}: {len(scores.frames)} frames, {int(scores.predicted.sum())} predicted contact "
               f"(threshold {model.threshold:.4f})")


@app.command()
def view(
    session_dir: Annotated[Path, typer.Argument(help="Session directory.")],
    model_path: Annotated[Optional[Path], typer.Option("--model", help="model.json: adds the HMM posterior, "
                          "threshold and predicted contact.")] = None,
    save: Annotated[Optional[Path], typer.Option("--save", "-o", help="Write the recording to this .rrd file.")] = None,
    serve: Annotated[bool, typer.Option(help="Serve the web viewer on localhost (Ctrl-C to stop).")] = False,
    connect: Annotated[Optional[str], typer.Option(help="Stream to a running viewer, e.g. "
                       "rerun+http://127.0.0.1:9876/proxy.")] = None,
    spawn: Annotated[Optional[bool], typer.Option("--spawn/--no-spawn", help="Open the native viewer "
                     "[default: when a display exists and no other sink is chosen].")] = None,
    start: Annotated[int, typer.Option(min=0, help="First frame index.")] = 0,
    end: Annotated[Optional[int], typer.Option(help="Stop before this frame index.")] = None,
    stride: Annotated[int, typer.Option(min=1, help="Show every n-th frame.")] = 1,
    images: Annotated[str, typer.Option(help="How the images are logged: video (AV1 stream, smallest), jpeg "
                      "(JPEG files as they are) or raw (decoded RGB, exact, large).")] = "video",
    video_codec: Annotated[str, typer.Option(help="--images video: av1 (the native viewer decodes it itself) or "
                           "h264 (faster to encode; the native viewer needs FFmpeg on PATH).")] = "av1",
    video_crf: Annotated[Optional[int], typer.Option(help="--images video: quality, lower = better and larger "
                         "[default: 30 for AV1 (0-63), 23 for H.264 (0-51)].")] = None,
    jpeg_quality: Annotated[int, typer.Option(min=1, max=100, help="--images jpeg: quality of re-encoded "
                            "images.")] = 85,
    right: Annotated[bool, typer.Option("--right/--no-right", help="Log the right image.")] = True,
    right_step: Annotated[int, typer.Option(min=1, max=2, help="--images video: log the right image at 1/n of its "
                          "size (2: half, the size its pane shows; 1: full).")] = 2,
    depth_step: Annotated[int, typer.Option(min=1, help="Log every n-th depth pixel (1 = full resolution).")] = 6,
    points: Annotated[bool, typer.Option("--points/--no-points", help="Log the RGB point cloud.")] = True,
    point_stride: Annotated[Optional[int], typer.Option(min=0, help="Point cloud: every n-th pixel away from the "
                            "patch (0 = none) [default: image width / 120, 16 at 1080p].")] = None,
    voxel_mm: Annotated[float, typer.Option(min=0, help="Point cloud: voxel size away from the patch, mm.")] = 4.0,
    near_radius_px: Annotated[int, typer.Option(min=0, help="Point cloud: the RGB points within this of each "
                              "patch centre, px.")] = 40,
    near_stride: Annotated[int, typer.Option(min=1, help="Point cloud: every n-th pixel near the patches "
                           "(1 = all).")] = 4,
    grpc_port: Annotated[int, typer.Option(help="gRPC port for --serve/--spawn.")] = 9876,
    web_port: Annotated[int, typer.Option(help="Web viewer port for --serve.")] = 9090,
    hand_eye: Annotated[Optional[Path], typer.Option(help="4x4 camera_T_base (text or .npy, m): draw the "
                        "kinematics.csv tool tip and its distance to the mask's tip.")] = None,
    object_ids: ObjectId = None,
    contact_force: ContactForce = 2.0,
    params_file: ParamsFile = None,
    cache_dir: CacheDir = None,
    tool_diameter_mm: Annotated[float, typer.Option(min=0.1, help="The instrument's shaft diameter, mm, for the "
                                "tool-width check (docs/diagnostics.md).")] = 8.0,
    follow: Annotated[bool, typer.Option("--follow", help="Follow a session being recorded: log each new frame "
                      "as soon as its files are complete (docs/live.md).")] = False,
    from_start: Annotated[bool, typer.Option("--from-start", help="--follow: replay the frames already there "
                          "first, each shown whole (default: start after them).")] = False,
    idle_timeout: Annotated[Optional[float], typer.Option(min=0.001, help="--follow: stop after this many seconds "
                            "without a new frame [default: never; Ctrl-C stops].")] = None,
    frame_timeout: Annotated[float, typer.Option(min=0.001, help="--follow: skip a frame whose mask, depth or "
                             "right image is not complete this many seconds after its left image.")] = 5.0,
) -> None:
    """Run the pipeline frame by frame and log everything to one Rerun timeline.

    With --model the model's patch parameters are used (--params is then an error if it differs)."""
    from contact_viz.checks.params import DiagnosticParams
    from contact_viz.geometry.pointcloud import CloudParams
    from contact_viz.io.live import FollowParams
    from contact_viz.viz.debugger import IMAGE_MODES, DebuggerOptions
    from contact_viz.viz.video import CODECS, VideoParams
    from contact_viz.viz.view_command import ViewRequest, run_view

    params, label_params = _resolve_params(params_file, contact_force)
    if images not in IMAGE_MODES:
        _fail(f"--images: expected one of {', '.join(IMAGE_MODES)}, got {images!r}")
    if video_codec not in CODECS:
        _fail(f"--video-codec: expected one of {', '.join(CODECS)}, got {video_codec!r}")
    options = DebuggerOptions(
        start=start, end=end, stride=stride, jpeg_quality=jpeg_quality, images=images,
        video=VideoParams(codec=video_codec, crf=video_crf), with_right=right, right_step=right_step,
        depth_step=depth_step, points=points, diagnostics=DiagnosticParams(tool_diameter_mm=tool_diameter_mm),
        cloud=CloudParams(near_radius_px=near_radius_px, near_stride_px=near_stride, stride_px=point_stride,
                          voxel_m=voxel_mm / 1000))
    request = ViewRequest(
        session_dir=session_dir, options=options, model_path=model_path, params=params, params_file=params_file,
        label_params=label_params, object_ids=None if object_ids is None else tuple(object_ids), cache_dir=cache_dir,
        hand_eye=hand_eye, save=save, serve=serve, connect=connect, spawn=spawn, grpc_port=grpc_port,
        web_port=web_port, follow=FollowParams(from_start=from_start, idle_timeout_s=idle_timeout,
                                               frame_timeout_s=frame_timeout) if follow else None)
    with _LazyProgress(f"view {session_dir.name}", None) as bar:
        outcome = run_view(request, lambda line, err: typer.echo(line, err=err),
                           progress=lambda done, total: bar.update(completed=done, total=total))
    _print_report(outcome.report)
    for line in outcome.lines:
        typer.echo(line)
    if outcome.serve is not None:
        outcome.serve()
    raise typer.Exit(code=outcome.status)


@app.command()
def check(
    session_dirs: Annotated[list[Path], typer.Argument(help="Session directories.")],
    json_path: Annotated[Optional[Path], typer.Option("--json", help="Also write every session's checks "
                         "(frame ranges, counts, force lag, thresholds) to this JSON file.")] = None,
    strict: Annotated[bool, typer.Option(help="Exit with status 1 when any check fired.")] = False,
    tool_diameter_mm: Annotated[float, typer.Option(min=0.1, help="The instrument's shaft diameter, mm "
                                "(docs/diagnostics.md).")] = 8.0,
    object_ids: ObjectId = None,
    cache_dir: CacheDir = None,
    processes: Annotated[int, typer.Option(min=1, help="Processes per session, this one included.")] = 1,
) -> None:
    """Run the debugger's diagnostics on whole sessions, without Rerun: a table of checks per session."""
    from contact_viz.checks.params import DiagnosticParams
    from contact_viz.pipeline.check import report_table, run_check

    if json_path is not None and json_path.exists() and json_path.is_dir():
        _fail(f"--json {json_path}: is a directory; expected a file name")
    for session_dir in session_dirs:
        if json_path is not None and _inside(json_path, session_dir):
            _fail(f"--json {json_path}: refusing to write inside the session directory {session_dir}")
    try:
        params = DiagnosticParams(tool_diameter_mm=tool_diameter_mm)
    except ValueError as exc:
        _fail(str(exc))

    def report(r) -> None:
        for line in report_table(r):
            typer.echo(line)

    reports, errors = run_check(session_dirs, params=params, cache_dir=cache_dir, processes=processes,
                                json_path=json_path, on_report=report, object_ids=object_ids,
                                on_error=lambda m: typer.secho(f"error: {m}", fg=typer.colors.RED, err=True))
    if json_path is not None:
        typer.echo(f"{json_path}: {len(reports)} session(s)")
    if errors:
        raise typer.Exit(code=2)
    if strict and any(r.counts for r in reports):
        raise typer.Exit(code=1)


@app.command()
def depth(
    session_dir: Annotated[Path, typer.Argument(help="Session directory (left/ + right/ + calibration).")],
    method: Annotated[str, typer.Option(help="Depth method: sgbm (OpenCV semi-global matching).")] = "sgbm",
    output: Annotated[Optional[Path], typer.Option("-o", "--output", help="Also write <stem>.npy depth "
                      "(float32 m, rectified left view) into this new folder outside the session.")] = None,
    cache_dir: CacheDir = None,
    workers: Annotated[int, typer.Option(min=1, help="Frames computed in parallel.")] = 2,
    full_frame: Annotated[bool, typer.Option("--full-frame", help="Match every frame whole at the matching "
                          "resolution, not only around the instruments (slower; frames without an instrument "
                          "always are). Cached apart from the default: keep it with -o.")] = False,
    min_depth_mm: Annotated[Optional[float], typer.Option("--min-depth-mm", help="The nearest depth in the scene, "
                            "mm: the disparity search reaches it [default: 15, an endoscope's]. Cached apart from "
                            "the default: keep it with -o.")] = None,
) -> None:
    """Precompute the depth of a session that has no depth/ or disparity/ (SGBM, cached outside it)."""
    import math

    from contact_viz.console import check_output_dir
    from contact_viz.errors import SessionError
    from contact_viz.geometry.stereo import SGBMParams
    from contact_viz.pipeline.depth import run_depth_command

    if output is not None:
        check_output_dir(output, "-o/--output")
    if min_depth_mm is not None and not (math.isfinite(min_depth_mm) and min_depth_mm > 0):
        _fail(f"--min-depth-mm: expected a depth > 0 mm, got {min_depth_mm:g}")
    fields = ({"region": False} if full_frame else {}) | (
        {"min_depth_m": min_depth_mm / 1000} if min_depth_mm is not None else {})
    params = SGBMParams(**fields) if fields else None
    with _progress() as progress:
        task = progress.add_task(f"depth {session_dir.name}", total=None)
        try:
            lines = run_depth_command(session_dir, method=method, output=output, cache_dir=cache_dir, workers=workers,
                                      params=params,
                                      progress=lambda done, total: progress.update(task, completed=done, total=total))
        except (SessionError, ValueError) as exc:
            _fail(str(exc))
    for line in lines:
        typer.echo(line)


@app.command("import")
def import_(
    kind: Annotated[str, typer.Argument(help="Source layout: dvrk, yang2024 or bag.")],
    src: Annotated[Path, typer.Argument(help="The recorder's folder, or for bag a .bag file, ROS 2 bag folder or "
                                        ".mcap file (never modified).")],
    out_session: Annotated[Optional[Path], typer.Argument(help="New session directory to create (new or "
                                                          "empty).")] = None,
    force_topic: Annotated[Optional[str], typer.Option("--force-topic", "--force", help="dvrk/bag: force topic "
                           "(e.g. /force_sensor/measured_cf); bag: 'none' for no force.")] = None,
    video: Annotated[Optional[str], typer.Option(help="dvrk: video name when frames of several videos are "
                     "present.")] = None,
    calibration: Annotated[Optional[list[Path]], typer.Option(help="Calibration file to put in the session "
                           "(K.txt, left.yaml + right.yaml, stereo.yaml ...); repeat for several.")] = None,
    copy: Annotated[bool, typer.Option(help="Copy the images instead of linking them.")] = False,
    list_topics: Annotated[bool, typer.Option("--list", help="bag: print the topics (type, count, rate, default "
                           "role) and stop.")] = False,
    left: Annotated[Optional[str], typer.Option(help="bag: left image topic.")] = None,
    right: Annotated[Optional[str], typer.Option(help="bag: right image topic ('none': no right images).")] = None,
    left_info: Annotated[Optional[str], typer.Option(help="bag: left CameraInfo topic.")] = None,
    right_info: Annotated[Optional[str], typer.Option(help="bag: right CameraInfo topic.")] = None,
    pose: Annotated[Optional[str], typer.Option(help="bag: tool pose topic (PoseStamped/TransformStamped, e.g. "
                    "/PSM1/measured_cp) for kinematics.csv; 'none' to skip.")] = None,
    pair_tolerance_ms: Annotated[Optional[float], typer.Option(help="bag: largest left/right stamp difference of "
                                 "a stereo pair, ms (default: a quarter of the median left frame period).")] = None,
    labels: Annotated[Optional[Path], typer.Option(help="yang2024: Yang et al.'s "
                      "MTurk_Labels_with_keypoints.csv (GT labels, crowd labels, tool-tip keypoints).")] = None,
    dataset: Annotated[Optional[str], typer.Option(help="yang2024: the recording's name in --labels "
                       "(default: the name of SRC's folder).")] = None,
) -> None:
    """Convert a recorder's output (dVRK data_collection, Yang et al. 2024, ROS bag / MCAP) into a session."""
    from contact_viz.errors import SessionError
    from contact_viz.io.importers import run_import_command

    if list_topics:
        if kind != "bag":
            _fail("--list only applies to bag imports")
        from contact_viz.io.importers.bag import list_lines

        try:
            lines = list_lines(src)
        except SessionError as exc:
            _fail(str(exc))
        for line in lines:
            typer.echo(line)
        return
    if out_session is None:
        _fail("OUT_SESSION: expected the new session directory (or --list for a bag)")
    topics = {"left": left, "right": right, "left_info": left_info, "right_info": right_info, "pose": pose}
    from contextlib import nullcontext

    try:
        with _progress() if kind == "bag" else nullcontext() as progress:  # a bag streams: show messages read
            task = progress.add_task(f"import {src.name} (messages)", total=None) if progress is not None else None
            lines = run_import_command(
                kind, src, out_session, force_topic=force_topic, video=video, calibration=calibration or (),
                copy=copy, labels=labels, dataset=dataset, bag_topics=topics,
                pair_tolerance_s=None if pair_tolerance_ms is None else pair_tolerance_ms / 1000.0,
                progress=None if progress is None else
                lambda done, total: progress.update(task, completed=done, total=total))
    except (SessionError, ValueError) as exc:
        _fail(str(exc))
    for line in lines:
        typer.echo(line)


@app.command()
def batch(
    sessions: Annotated[Path, typer.Argument(metavar="SESSIONS", help="A folder of session folders, one "
                        "session folder, or a text file listing session folders (one per line).")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Results folder: one folder per session, "
                      "model.json, metrics.json, summary.json.")],
    steps: Annotated[str, typer.Option(help="Comma-separated steps: depth, extract, check, view, fit, "
                     "evaluate.")] = "depth,extract,check",
    ray: Annotated[bool, typer.Option("--ray", help="Run the tasks on a local Ray started on the fly "
                   "(pip install 'contact-viz[ray]').")] = False,
    ray_address: Annotated[Optional[str], typer.Option(help="Run the tasks on an existing Ray cluster, e.g. "
                           "auto or ray://HOST:10001 (sessions must be at the same path on every node).")] = None,
    processes: Annotated[Optional[int], typer.Option(min=1, help="Local engine: processes [default: the number "
                         "of cores, at most 8].")] = None,
    chunk_frames: Annotated[int, typer.Option(min=1, help="Frames per depth/extract task.")] = 256,
    model_path: Annotated[Optional[Path], typer.Option("--model", help="model.json for view and evaluate "
                          "(evaluate without fit needs it).")] = None,
    object_ids: ObjectId = None,
    contact_force: ContactForce = 2.0,
    params_file: ParamsFile = None,
    cache_dir: CacheDir = None,
) -> None:
    """Run steps over every session of a dataset, on this machine's cores or on Ray."""
    from contact_viz.console import check_output_dir
    from contact_viz.errors import SessionError
    from contact_viz.pipeline.batch import BatchOptions, find_sessions, run_batch, summary_lines
    from contact_viz.pipeline.engines import LocalEngine, RayEngine

    params, label_params = _resolve_params(params_file, contact_force)
    check_output_dir(output, "-o/--output")
    try:
        options = BatchOptions(steps=tuple(s.strip() for s in steps.split(",") if s.strip()), params=params,
                               label_params=label_params, object_ids=object_ids,
                               cache_dir=None if cache_dir is None else str(cache_dir),
                               chunk_frames=chunk_frames,
                               model_path=None if model_path is None else str(model_path.resolve()))
        if model_path is not None and not model_path.is_file():
            raise ValueError(f"--model {model_path}: expected a model.json file")
        find_sessions(sessions)  # a wrong SESSIONS argument fails here, before any engine starts
        engine = RayEngine(address=ray_address) if (ray or ray_address) else LocalEngine(processes)
    except (SessionError, ValueError, RuntimeError) as exc:
        _fail(str(exc))
    try:
        with _progress() as progress:
            task = progress.add_task("batch", total=None)
            summary = run_batch(sessions, output, options, engine, progress=lambda done, total, step: progress.update(
                task, completed=done, total=total, description=f"batch: {step}"))
    except (SessionError, ValueError) as exc:
        _fail(str(exc))
    finally:
        engine.close()
    for line in summary_lines(summary):
        typer.echo(line)
    typer.echo(f"{output / 'summary.json'}: the dataset summary")
    if summary.failed or any(v.startswith("failed") for v in summary.dataset.values()):
        raise typer.Exit(code=1)


def _commands() -> list[str]:
    return [c.name or c.callback.__name__.rstrip("_") for c in app.registered_commands]


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point. `contact-viz SESSION_DIR [options]` means `contact-viz view SESSION_DIR`;
    a word that is neither a command nor an existing path, followed by more arguments or close to a
    command's name, is a misspelled command."""
    import difflib
    import sys

    from contact_viz import console

    args = list(sys.argv[1:] if argv is None else argv)
    if "--verbose" in args or "-v" in args[:1]:  # accepted anywhere, also after the command
        args = [a for a in args if a != "--verbose"]
        if args[:1] == ["-v"]:
            args = args[1:]
        console.VERBOSE = True
    console.quiet_libraries(console.VERBOSE)  # before OpenCV, workers or Rerun start
    console.stop_on_signals()  # SIGTERM and SIGHUP stop a command as Ctrl-C does
    if _EARLY_STOP:  # one came while the command started
        line, status = console.stop_line(console.Stopped(_EARLY_STOP[-1]))
        typer.echo(line, err=True)
        raise SystemExit(status)
    try:
        commands = _commands()
        if args and not args[0].startswith("-") and args[0] not in commands:
            word = args[0]
            close = difflib.get_close_matches(word, commands, n=1, cutoff=0.6)
            if not Path(word).exists() and "/" not in word and (close or len(args) > 1 and not args[1].startswith("-")):
                hint = f" (did you mean '{close[0]}'?)" if close else ""
                typer.secho(f"error: no such command '{word}'{hint}; commands: {', '.join(commands)}; "
                            "`contact-viz SESSION` opens the viewer on a session directory", fg=typer.colors.RED,
                            err=True)
                raise SystemExit(2)
            args.insert(0, "view")
        app(args=args, prog_name="contact-viz")
    except KeyboardInterrupt as exc:  # a stop signal before typer took over
        line, status = console.stop_line(exc)
        typer.echo(line, err=True)
        raise SystemExit(status) from None
    except SystemExit as exc:
        stopped = console.unreported_stop()  # a signal while the command line was parsed: typer says nothing
        if stopped is not None:
            typer.echo(stopped[0], err=True)
            raise SystemExit(stopped[1]) from None
        sinks = sys.modules.get("contact_viz.viz.sinks")
        if sinks is not None and sinks.exit_would_hang():  # a viewer that stopped taking data: leave now
            import os

            code = exc.code if isinstance(exc.code, int) else 1
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
        raise


if __name__ == "__main__":
    main()
