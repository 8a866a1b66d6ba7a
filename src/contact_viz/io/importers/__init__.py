"""Convert what a recorder wrote into a native session (``contact-viz import KIND SRC OUT``).

Importers never modify SRC: images are hard-linked into OUT where the file system allows it,
else symbolic-linked, else copied; CSV and JSON files are written new. OUT is built in a hidden
folder beside it and renamed into place at the end, so a failed import leaves nothing behind.
Masks and depth are not part of the recorders' layouts: the result lists what the user still
has to fill (:func:`contact_viz.io.session.missing_inputs`, the same text the reader's errors use).

Kinds:

``dvrk``
    The layout of the JHU dVRK ``data_collection`` extractor (``extract -a -f png|jpg -S``):
    stereo frames ``<video>_left_<t>.png|jpg`` and ``<video>_right_<t>.png|jpg`` (t = epoch
    seconds), and one CSV per ROS topic, each starting with ``# Topic: ...`` and ``# Type: ...``
    lines, then a header whose first column ``timestamp`` is in nanoseconds followed by the
    flattened message fields. SRC is that folder (or a recording folder holding exactly one
    ``extracted/<target>/``). Frames get stems 000000, 000001, ... in time order and frames.csv
    their timestamps; force.csv keeps the force topic's own samples and times (s). The force
    topic is the CSV with ``wrench.force.x|y|z`` or ``force.x|y|z`` columns (chosen with
    ``force_topic`` when there are several). ``sensor_msgs/CameraInfo`` topics whose names
    contain "left" and "right" become left.yaml + right.yaml.
``yang2024``
    The data of Yang et al. (2024), "Vision-based force estimation for minimally invasive
    telesurgery through contact detection and local stiffness models": ``img_<n>.jpg`` left
    frames, ``right_img/img_<n>.jpg`` right frames and a header-less comma-separated
    ``labels_30hz.txt`` with one row per left frame: column 1 = time (s), columns 2-4 = force
    Fx, Fy, Fz (N). Stems are n zero-padded to 6 digits; force.csv is indexed by frame.
    With ``labels`` (their ``labels/MTurk_Labels_with_keypoints.csv``: ``GT, MTurk_Label, dataset,
    image, x, y``, every 45th frame of each recording) the recording's rows become labels.csv (GT),
    crowd_labels.csv (the crowd workers' label) and tool_tips.csv (the keypoint, px).
``bag``
    A ROS 1 ``.bag`` file, a ROS 2 bag folder (sqlite3 ``.db3`` or ``.mcap``) or a bare ``.mcap``
    file, read with ``rosbags`` (see ``bag.py``): left/right ``sensor_msgs/Image`` or
    ``CompressedImage`` paired by header stamp, CameraInfo -> left.yaml + right.yaml,
    ``WrenchStamped`` -> force.csv (own rate), ``PoseStamped`` / ``TransformStamped`` ->
    kinematics.csv (``contact_viz.io.kinematics``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

from contact_viz.io.importers.bag import import_bag
from contact_viz.io.importers.common import ImportResult
from contact_viz.io.importers.dvrk import import_dvrk
from contact_viz.io.importers.yang2024 import import_yang2024

__all__ = ["IMPORTERS", "ImportResult", "import_bag", "import_dvrk", "import_yang2024"]

# --------------------------------------------------------------------------------------------
# Kinds
# --------------------------------------------------------------------------------------------

IMPORTERS: dict[str, Callable[..., ImportResult]] = {"dvrk": import_dvrk, "yang2024": import_yang2024,
                                                     "bag": import_bag}


def run_import_command(
    kind: str,
    src: str | Path,
    out: str | Path,
    *,
    force_topic: str | None = None,
    video: str | None = None,
    calibration: Sequence[str | Path] = (),
    copy: bool = False,
    labels: str | Path | None = None,
    dataset: str | None = None,
    bag_topics: dict[str, str | None] | None = None,
    pair_tolerance_s: float | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> list[str]:
    """`contact-viz import KIND SRC OUT_SESSION`: returns the lines to print.

    Raises ValueError (bad arguments) or SessionError (malformed source) with the message to show.
    """
    if kind not in IMPORTERS:
        raise ValueError(f"KIND must be one of {', '.join(IMPORTERS)}, got {kind!r}")
    topics = {k: v for k, v in (bag_topics or {}).items() if v is not None}
    if kind != "bag" and (topics or pair_tolerance_s is not None):
        given = [f"--{k.replace('_', '-')}" for k in topics] + (["--pair-tolerance-ms"] if pair_tolerance_s else [])
        raise ValueError(f"{', '.join(given)} only apply to bag imports")
    if kind != "yang2024" and (labels is not None or dataset is not None):
        raise ValueError("--labels and --dataset only apply to yang2024 imports")
    if kind == "bag":
        if video is not None:
            raise ValueError("--video only applies to dvrk imports")
        if force_topic is not None:
            topics["force"] = force_topic
        result = import_bag(src, out, **topics, pair_tolerance_s=pair_tolerance_s, calibration=calibration,
                            progress=progress)
    elif kind == "yang2024":
        unused = [name for name, value in (("--force-topic", force_topic), ("--video", video)) if value is not None]
        if unused:
            raise ValueError(f"{', '.join(unused)} only apply to dvrk imports")
        result = import_yang2024(src, out, calibration=calibration, copy=copy, labels=labels, dataset=dataset)
    else:
        result = import_dvrk(src, out, force_topic=force_topic, video=video, calibration=calibration, copy=copy)
    return result.lines()
