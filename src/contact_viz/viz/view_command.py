"""`contact-viz view`: a session (finished, or followed while it is recorded) into a Rerun recording.

The command line fills a :class:`ViewRequest`; :func:`run_view` checks it, opens the model, the
session and the sinks, runs :func:`contact_viz.viz.debugger.log_session` or
:func:`contact_viz.viz.follow.follow_session`, closes the recording (the .rrd appears under its
name only then) and returns the lines to print and the exit status. Bad input raises ValueError or
SessionError with the one line to show; a failing sink a SinkError.
"""

from __future__ import annotations

import os
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from contact_viz.console import FrameReport, check_connect_url, check_output_file
from contact_viz.io.live import FollowParams
from contact_viz.io.session import open_session
from contact_viz.params import LabelParams, PatchParams, to_dict
from contact_viz.viz.blueprint import default_blueprint
from contact_viz.viz.debugger import DebuggerOptions, log_session, select_frames
from contact_viz.viz.sinks import DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT, SinkError, open_recording


@dataclass(frozen=True)
class ViewRequest:
    """Everything `contact-viz view` was asked for (the command line's options, typed)."""

    session_dir: Path
    options: DebuggerOptions = DebuggerOptions()  # what is shown and how densely
    model_path: Path | None = None  # model.json: the HMM posterior (its patch parameters win)
    params: PatchParams = PatchParams()  # the patch parameters (--params, or the defaults)
    params_file: Path | None = None  # where ``params`` came from (to refuse one that differs from the model's)
    label_params: LabelParams = LabelParams()  # contact labels from force (--contact-force)
    object_ids: tuple[int, ...] | None = None  # the instruments shown (None: every one in the masks)
    cache_dir: Path | None = None  # SGBM depth cache (None: the package cache)
    hand_eye: Path | None = None  # 4x4 camera_T_base file: the kinematic tool tip
    save: Path | None = None  # the .rrd to write
    serve: bool = False  # host the web viewer
    connect: str | None = None  # a running viewer's gRPC URL
    spawn: bool | None = None  # start the native viewer (None: when there is a display and no other sink)
    grpc_port: int = DEFAULT_GRPC_PORT
    web_port: int = DEFAULT_WEB_PORT
    follow: FollowParams | None = None  # follow the session while it is recorded (None: a finished session)


@dataclass
class ViewOutcome:
    """What `view` did: lines for stdout, the frame report (warnings, for stderr), the exit status, and
    with --serve what to run once they are printed (serve until Ctrl-C, then close the recording)."""

    lines: list[str]
    report: FrameReport
    status: int = 0
    serve: Callable[[], None] | None = None


def run_view(request: ViewRequest, echo: Callable[[str, bool], None], progress=None) -> ViewOutcome:
    """Run `contact-viz view` for ``request``; ``echo(line, err)`` prints the lines that come before the run
    (where depth comes from, on stderr; where the recording goes, the web viewer's URL); ``progress(done,
    total)`` (total None while following) is called after each frame."""
    r = request
    if r.connect is not None:
        check_connect_url(r.connect)
    model, params = _model(r)
    session = None
    if r.follow is None:
        session = open_session(r.session_dir, object_ids=r.object_ids, label_params=r.label_params,
                               cache_dir=r.cache_dir)
        echo(session.depth_note, True)
        try:  # before any sink opens
            select_frames(len(session), r.options.start, r.options.end, r.options.stride)
        except ValueError as exc:
            raise ValueError(f"--{exc}") from None
    elif r.hand_eye is not None:
        raise ValueError("--hand-eye: not available with --follow (kinematics.csv is read whole)")
    options = replace(r.options, patch_params=params, hand_eye=_hand_eye(r, session))
    save = r.save
    spawn = r.spawn if r.spawn is not None else (
        bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")) and save is None and not r.serve
        and r.connect is None)
    if not (spawn or r.serve or r.connect or save):
        name = session.name if session is not None else Path(r.session_dir).resolve().name
        save = Path("results") / name / "view.rrd"
        echo(f"no display here: saving the recording to {save} (open it with `rerun {save}`)", False)
    if save is not None:
        check_output_file(save, "--save", session_root=Path(r.session_dir), example="view.rrd")
    opened = open_recording(save=save, connect=r.connect, spawn=spawn, serve=r.serve, grpc_port=r.grpc_port,
                            web_port=r.web_port, blueprint=default_blueprint(
                                with_right=r.options.with_right and (session is None or session.has_right),
                                with_model=model is not None, with_kinematics=r.hand_eye is not None,
                                with_lag=r.follow is not None), streamed=r.follow is not None)
    if opened.web_viewer_url:
        echo(f"web viewer: {opened.web_viewer_url}", False)
    if model is None:
        echo("no --model: the HMM posterior is not shown (make one with `contact-viz fit TRAIN... -o model.json`)",
             False)
    report = FrameReport()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            summary = _run(r, session, opened, options, model, progress)
        run = getattr(summary, "run", summary)
        if run.frames and run.bad_frames == run.frames and not run.interrupted:
            raise ValueError(f"{Path(r.session_dir)}: no frame could be read (see the warnings above); "
                             "no recording written")
        if r.serve and not run.interrupted:  # the served viewer keeps the data until Ctrl-C; renamed then
            opened.flush()
        else:
            opened.close()  # the .rrd appears under its name only now, flushed and complete
    except SinkError as exc:
        error = opened.explain(exc)  # before the staging file is removed (its size tells a full disk)
        opened.close(keep=False)
        raise error from None
    except BaseException:
        opened.close(keep=False)
        raise
    report.add_warnings(caught)
    lines = summary.lines()
    if save is not None:
        lines.append(f"{save}: open it with `rerun {save}`")
    outcome = ViewOutcome(lines, report, 128 + (run.stop_signal or 2) if run.interrupted else 0)
    if r.serve and not run.interrupted:
        outcome.lines.append("serving; press Ctrl-C to stop")
        outcome.serve = lambda: _serve_until_stopped(opened.close)
    return outcome


def _serve_until_stopped(close: Callable[[], None]) -> None:
    """Keep the process (and its served viewer) alive until Ctrl-C, SIGTERM or SIGHUP, then close."""
    try:
        while True:
            time.sleep(1)
    except KeyboardInterrupt:
        pass
    close()


def _run(r: ViewRequest, session, opened, options, model, progress):
    if r.follow is None:
        return log_session(opened.rec, session, model=model, options=options, progress=progress)
    from contact_viz.viz.follow import follow_session

    return follow_session(r.session_dir, opened.rec, options, model, r.follow,
                          open_kwargs={"object_ids": r.object_ids, "label_params": r.label_params,
                                       "cache_dir": r.cache_dir},
                          progress=None if progress is None else lambda done: progress(done, None))


def _model(r: ViewRequest):
    """The model (or None) and the patch parameters the run uses (the model's, which --params must equal)."""
    if r.model_path is None:
        return None, r.params
    from contact_viz.model.model_file import load_model

    model = load_model(r.model_path)
    fitted, given = to_dict(model.patch_params), to_dict(r.params)
    diff = [f"{k}: model {fitted[k]!r}, --params {given[k]!r}" for k in fitted
            if r.params_file is not None and fitted[k] != given[k]]
    if diff:
        raise ValueError(f"--params {r.params_file}: differs from the patch parameters {r.model_path} was fitted "
                         f"with ({'; '.join(diff)}); drop --params (view then uses the model's) or fit a model "
                         "with these parameters")
    return model, model.patch_params


def _hand_eye(r: ViewRequest, session):
    """The 4x4 camera_T_base of --hand-eye as nested tuples (None without it)."""
    if r.hand_eye is None:
        return None
    from contact_viz.errors import SessionError
    from contact_viz.io.kinematics import read_hand_eye

    if session.kinematics is None:
        raise SessionError(session.root / "kinematics.csv", "missing: --hand-eye needs the robot's pose "
                           "(import a bag with a pose topic)")
    return tuple(tuple(float(v) for v in row) for row in read_hand_eye(r.hand_eye))
