"""What every importer shares: the result, staging OUT in a hidden folder, placing files, small CSV/JSON writers."""

from __future__ import annotations

import csv
import json
import math
import os
import re
import shutil
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from contact_viz.io.atomic import reported_as, staging_path, sweep_stale
from contact_viz.io.calibration import CALIBRATION_FILES
from contact_viz.errors import SessionError


STEM_DIGITS = 6  # stems are frame numbers zero-padded to at least this many digits
NS_PER_S = 10**9  # nanoseconds per second
FORCE_COLUMNS = (("wrench.force.x", "wrench.force.y", "wrench.force.z"), ("force.x", "force.y", "force.z"))
YANG_LABELS = "labels_30hz.txt"
YANG_FORCE_COLUMNS = (1, 2, 3)  # 0-based columns of Fx, Fy, Fz in labels_30hz.txt (column 0 = time)
_DVRK_FRAME = re.compile(r"^(?P<video>.+)_(?P<side>left|right)_(?P<t>\d+(?:\.\d+)?)\.(?P<ext>png|jpe?g)$", re.I)
_YANG_FRAME = re.compile(r"^img_(?P<n>\d+)\.(?P<ext>jpe?g|png)$", re.I)
_CAMERA_INFO_FIELDS = {  # ROS 2 / ROS 1 flattened CameraInfo field prefixes -> YAML key, shape
    "camera_matrix": (("k", "K"), (3, 3)),
    "distortion_coefficients": (("d", "D"), None),
    "rectification_matrix": (("r", "R"), (3, 3)),
    "projection_matrix": (("p", "P"), (3, 4)),
}


# --------------------------------------------------------------------------------------------
# Result
# --------------------------------------------------------------------------------------------


@dataclass
class ImportResult:
    """What an import produced."""

    kind: str  # importer name
    source: Path  # SRC as resolved
    out: Path  # the new session directory
    frames: int  # frames imported
    placed: dict[str, int]  # how image files got into OUT: {"hardlink": n, "symlink": n, "copy": n}
    force_samples: int  # rows in force.csv (0 = no force.csv)
    notes: list[str] = field(default_factory=list)  # things the user should know (skipped files, ...)
    to_fill: list[str] = field(default_factory=list)  # what the session still lacks (missing_inputs)

    def lines(self) -> list[str]:
        """Human-readable report, one line each."""
        verbs = {"hardlink": "hardlinked", "symlink": "symlinked", "copy": "copied"}
        how = ", ".join(f"{n} {verbs.get(way, way)}" for way, n in self.placed.items() if n)
        out = [f"{self.out}: {self.frames} frames imported from {self.source} ({self.kind}; images {how or 'none'})"]
        out.append(f"force.csv: {self.force_samples} samples" if self.force_samples else "no force.csv written")
        out.extend(f"note: {note}" for note in self.notes)
        if self.to_fill:
            out.append("still to fill before `contact-viz extract`:")
            out.extend(f"  - {line}" for line in self.to_fill)
        return out


# --------------------------------------------------------------------------------------------
# File operations
# --------------------------------------------------------------------------------------------


def _place(src: Path, dst: Path, copy: bool) -> str:
    """Put ``src`` at ``dst`` by hard link, else symbolic link, else copy; returns which was used."""
    if not copy:
        try:
            os.link(src, dst)
            return "hardlink"
        except OSError:
            pass
        try:
            os.symlink(src.resolve(), dst)
            return "symlink"
        except OSError:
            pass
    shutil.copy2(src, dst)
    return "copy"


@contextmanager
def _staging(src: Path, out: Path) -> Iterator[Path]:
    """A hidden folder beside ``out`` to build the session in; renamed to ``out`` on success."""
    src = src.resolve()
    out = out.expanduser().resolve()
    if out == src or src in out.parents:
        raise ValueError(f"{out}: the new session must not be inside the source folder {src} (it is never modified)")
    if out in src.parents:
        raise ValueError(f"{out}: the new session must not contain the source folder {src}")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"{out}: expected a new or empty folder for the imported session")
    with reported_as(out):  # a read-only or full place: the error names OUT, not the staging folder
        out.parent.mkdir(parents=True, exist_ok=True)
        sweep_stale(out)  # the staging folder of a killed import
        tmp = staging_path(out, "import")
        tmp.mkdir()
    try:
        with reported_as(out, tmp):  # errors about the source files pass as they are
            yield tmp
            if out.exists():
                out.rmdir()
            os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence[object]]) -> None:
    with open(path, "w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        writer.writerows(rows)


def _write_session_json(path: Path, name: str, kind: str, src: Path, times_s: Sequence[float], extra: dict) -> None:
    data = {"name": name, "import": {"kind": kind, "source": str(src), **extra}}
    if len(times_s) > 1:
        gap = float(np.median(np.diff(np.asarray(times_s, dtype=np.float64))))
        if math.isfinite(gap) and gap > 0:
            data["fps"] = round(1.0 / gap, 3)
    path.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")


def _place_calibration(files: Sequence[str | Path], tmp: Path, copy: bool) -> list[str]:
    """Link/copy user-given calibration files into the new session under their own names."""
    names = []
    for given in files:
        path = Path(given).expanduser()
        if path.name not in CALIBRATION_FILES:
            raise ValueError(
                f"{path}: a calibration file must be named one of {', '.join(CALIBRATION_FILES)} "
                "(see the README: calibration)"
            )
        if not path.is_file():
            raise SessionError(path, "missing: expected a calibration file")
        if (tmp / path.name).exists():
            raise ValueError(f"{path}: two calibration files named {path.name}")
        _place(path, tmp / path.name, copy)
        names.append(path.name)
    return names


def _stem_width(count: int) -> int:
    return max(STEM_DIGITS, len(str(max(count - 1, 0))))


