"""The tasks of `contact-viz batch`: module-level functions an engine runs in any process or node.

Each task opens its session itself (from a :class:`SessionJob`, which pickles small), computes, and
returns plain data; the driver (:mod:`contact_viz.pipeline.batch`) writes every output file. Frame
chunks of one session give, concatenated, the same rows as the whole session in one call.
"""

from __future__ import annotations

import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

from contact_viz.params import LabelParams, PatchParams

__all__ = ["SessionJob", "check_task", "depth_task", "extract_task", "view_task"]


@dataclass(frozen=True)
class SessionJob:
    """What a task needs to open one session the way the batch opened it."""

    path: str  # session directory, absolute (the same path on every node)
    name: str  # the session's name (its result folder under OUT)
    params: PatchParams  # patch parameters
    label_params: LabelParams  # label threshold
    object_ids: tuple[int, ...] | None  # object ids of palettized masks to run on (None = every instrument)
    cache_dir: str | None  # cache of features and SGBM depth (None = the default cache)

    def open(self):
        from contact_viz.io.session import open_session

        if not Path(self.path).is_dir():
            import platform

            raise FileNotFoundError(f"{self.path}: session folder not found on node {platform.node()} "
                                    "(on a cluster every node must see the sessions at the same path)")
        return open_session(self.path, object_ids=self.object_ids, label_params=self.label_params,
                            cache_dir=self.cache_dir)


def depth_task(job: SessionJob, lo: int, hi: int) -> dict:
    """Compute (or find cached) the SGBM depth of frames ``lo .. hi-1`` into the depth cache."""
    from contact_viz.io.session import BadFrame

    start = time.perf_counter()
    session = job.open()
    failed = []
    for index in range(lo, hi):
        result = session.load_depth(index, with_origin=True)
        if isinstance(result, BadFrame):
            failed.append(f"{result.stem}: {result.reason}")
    return {"frames": hi - lo, "failed": failed, "seconds": time.perf_counter() - start}


def extract_task(job: SessionJob, lo: int, hi: int) -> dict:
    """The features rows of frames ``lo .. hi-1`` (as `contact-viz extract` writes them)."""
    from contact_viz.pipeline.extract import BadFrameWarning, extract_features

    start = time.perf_counter()
    session = job.open()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BadFrameWarning)  # bad frames are in the rows' reason/detail
        rows = extract_features(session, job.params, indices=range(lo, hi))
    return {"rows": [{k: str(v) for k, v in row.items()} for row in rows], "seconds": time.perf_counter() - start}


def check_task(job: SessionJob) -> dict:
    """The report of `contact-viz check` on the session, as a JSON-ready dict."""
    from contact_viz.pipeline.check import check_session

    start = time.perf_counter()
    report = check_session(Path(job.path), cache_dir=job.cache_dir, patch_params=job.params, object_ids=job.object_ids)
    return {"report": report.to_dict(), "seconds": time.perf_counter() - start}


def view_task(job: SessionJob, model_path: str | None) -> dict:
    """The debugger's recording of the session (the bytes of a .rrd file) and its summary lines."""
    from contact_viz.viz.debugger import DebuggerOptions, log_session
    from contact_viz.viz.rerun_log import default_blueprint, open_recording

    start = time.perf_counter()
    session = job.open()
    model = None
    if model_path is not None:
        from contact_viz.model.model_file import load_model

        model = load_model(model_path)
    with tempfile.TemporaryDirectory(prefix="contact-viz-view-") as tmp:
        path = Path(tmp) / "view.rrd"
        opened = open_recording(save=path, recording_id=f"contact-viz-batch-{job.name}",
                                blueprint=default_blueprint(with_right=session.has_right,
                                                            with_model=model is not None))
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # bad frames are counted in the summary
                # a signal stops the whole batch (in this process it is the caller's), not only this recording
                summary = log_session(opened.rec, session, options=DebuggerOptions(patch_params=job.params),
                                      model=model, keep_partial=False)
        except BaseException:
            opened.close(keep=False)
            raise
        opened.close()
        data = path.read_bytes()
    return {"rrd": data, "lines": summary.lines(), "seconds": time.perf_counter() - start}
