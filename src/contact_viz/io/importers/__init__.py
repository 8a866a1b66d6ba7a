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
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

from contact_viz.io.importers.common import ImportResult
from contact_viz.io.importers.dvrk import import_dvrk
from contact_viz.io.importers.yang2024 import import_yang2024

__all__ = ["IMPORTERS", "ImportResult", "import_dvrk", "import_yang2024"]

# --------------------------------------------------------------------------------------------
# Kinds
# --------------------------------------------------------------------------------------------

IMPORTERS: dict[str, Callable[..., ImportResult]] = {"dvrk": import_dvrk, "yang2024": import_yang2024}


def run_import_command(
    kind: str,
    src: str | Path,
    out: str | Path,
    *,
    force_topic: str | None = None,
    video: str | None = None,
    calibration: Sequence[str | Path] = (),
    copy: bool = False,
) -> list[str]:
    """`contact-viz import KIND SRC OUT_SESSION`: returns the lines to print.

    Raises ValueError (bad arguments) or SessionError (malformed source) with the message to show.
    """
    if kind not in IMPORTERS:
        raise ValueError(f"KIND must be one of {', '.join(IMPORTERS)}, got {kind!r}")
    if kind == "yang2024":
        unused = [name for name, value in (("--force-topic", force_topic), ("--video", video)) if value is not None]
        if unused:
            raise ValueError(f"{', '.join(unused)} only apply to dvrk imports")
        result = import_yang2024(src, out, calibration=calibration, copy=copy)
    else:
        result = import_dvrk(src, out, force_topic=force_topic, video=video, calibration=calibration, copy=copy)
    return result.lines()
