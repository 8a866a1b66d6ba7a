"""The study's figures: the timelines of both methods against ground truth and the pipeline figure
of one frame (``viz.figures`` draws them)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from contact_viz.io.session import BadFrame, Session
from contact_viz.paper.protocol import MethodResult, Study
from contact_viz.params import PatchParams
from contact_viz.pipeline.features import Features


def pick_figure_frame(features: Features) -> int:
    """The frame of the smallest |distance| among frames with a patch (the tool at the tissue), else 0
    (several instruments: the smallest of any instrument's, the rows of a frame being consecutive)."""
    position = {stem: i for i, stem in enumerate(features.frames)}
    distance = np.full(len(features.frames), np.inf)
    for r in features.rows:
        if r["distance_m"] != "":
            i = position[str(r["frame"])]
            distance[i] = min(distance[i], abs(float(r["distance_m"])))
    return int(np.argmin(distance)) if np.isfinite(distance).any() else 0


def figure_frame(study: Study, spec: str | None, test_features: list[Features]) -> tuple[Session, int]:
    """The session and frame index of the pipeline figure (``SESSION:INDEX``, or the default)."""
    if spec is None:
        return study.test[0], pick_figure_frame(test_features[0])
    name, _, index = spec.rpartition(":")
    by_name = {s.name: s for s in study.train + study.test}
    if name not in by_name or not index.isdigit() or int(index) >= len(by_name[name]):
        raise ValueError(f"--figure-frame {spec!r}: expected SESSION:INDEX with SESSION one of {sorted(by_name)} "
                         "and INDEX a frame number of that session")
    return by_name[name], int(index)


def write_figures(out: Path, study: Study, hmm: MethodResult, rgb: MethodResult, title: str | None,
                  frame_session: Session, frame_index: int, params: PatchParams) -> tuple[list[Path], dict]:
    """timelines.png/.pdf and pipeline.png/.pdf; returns the files and a description of the figure frame."""
    from contact_viz.geometry.patch import compute_patch
    from contact_viz.viz.figures import TimelineSession, pipeline_figure, save_figure, timelines_figure

    timeline = [TimelineSession(s.name, study.categories[s.name], np.asarray(s.timestamps_s), np.asarray(s.labels),
                                hmm.posteriors[i], hmm.threshold, rgb.posteriors[i], rgb.threshold)
                for i, s in enumerate(study.test)]
    files = save_figure(timelines_figure(timeline, method_names=(hmm.name, rgb.name), title=title), out / "timelines")
    frame = next(iter(frame_session.iter_frames(layers=("mask", "depth", "left"), indices=[frame_index])))
    if isinstance(frame, BadFrame):
        raise ValueError(f"pipeline figure: frame {frame_index} of {frame_session.name} is unreadable: {frame.reason}")
    patch = compute_patch(frame.depth_m, frame.tool_mask, params)
    files += save_figure(pipeline_figure(frame.left_rgb, frame.tool_mask, frame.depth_m, patch), out / "pipeline")
    described = {"session": frame_session.name, "index": frame_index, "stem": frame.stem,
                 "distance_m": patch.distance_m if patch.found else None, "no_patch_reason": patch.reason}
    return files, described
