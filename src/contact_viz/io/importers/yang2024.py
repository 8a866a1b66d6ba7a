"""Yang et al. (2024): ``img_<n>.jpg`` frames, ``right_img/``, ``labels_30hz.txt`` (see the package docstring)."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from contact_viz.io.calibration import read_calibration
from contact_viz.errors import SessionError
from contact_viz.io.session_files import check_times_increase

from contact_viz.io.decoders import read_image_size
from contact_viz.io.importers.common import ImportResult, YANG_FORCE_COLUMNS, YANG_LABELS, _YANG_FRAME, _place, _place_calibration, _staging, _stem_width, _write_csv, _write_session_json

# --------------------------------------------------------------------------------------------
# Yang et al. 2024
# --------------------------------------------------------------------------------------------


def _read_yang_labels(path: Path) -> list[list[str]]:
    """Rows of labels_30hz.txt as lists of number strings (at least 4 columns, all numeric)."""
    if not path.is_file():
        raise SessionError(
            path, "missing: expected the header-less labels_30hz.txt (column 1 time in s, columns 2-4 Fx, Fy, Fz in N)"
        )
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SessionError(path, f"expected a readable text file ({exc})") from exc
    rows = []
    for line_no, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        cells = [c.strip() for c in re.split(r"[,\s]+", line.strip()) if c.strip()]
        if len(cells) < 1 + len(YANG_FORCE_COLUMNS):
            raise SessionError(path, f"line {line_no}: expected at least 4 comma-separated numbers "
                                     f"(time, Fx, Fy, Fz), found {len(cells)}")
        for cell in cells[: 1 + len(YANG_FORCE_COLUMNS)]:
            try:
                value = float(cell)
            except ValueError:
                raise SessionError(path, f"line {line_no}: expected a number, found {cell!r}") from None
            if not math.isfinite(value):
                raise SessionError(path, f"line {line_no}: expected a finite number, found {cell!r}")
        rows.append(cells)
    if not rows:
        raise SessionError(path, "expected one row per left frame (time, Fx, Fy, Fz, ...), found an empty file")
    return rows


def import_yang2024(
    src: str | Path,
    out: str | Path,
    *,
    calibration: Sequence[str | Path] = (),
    copy: bool = False,
) -> ImportResult:
    """Import one recording of Yang et al. (2024) (``img_<n>.jpg``, ``right_img/``, ``labels_30hz.txt``).

    Row n of labels_30hz.txt belongs to img_<n>.jpg: its time (column 1) goes to frames.csv and
    its force (columns 2-4) to force.csv, indexed by frame. ``calibration`` and ``copy`` as in
    :func:`import_dvrk`.
    """
    from contact_viz.io.session import missing_inputs

    src = Path(src).expanduser()
    if not src.is_dir():
        raise SessionError(src, "missing: expected a Yang et al. 2024 recording folder (img_<n>.jpg, labels_30hz.txt)")
    src = src.resolve()
    rows = _read_yang_labels(src / YANG_LABELS)
    left = {int(m["n"]): p for p in src.iterdir() if p.is_file() and (m := _YANG_FRAME.match(p.name))}
    right_dir = src / "right_img"
    right = ({int(m["n"]): p for p in right_dir.iterdir() if p.is_file() and (m := _YANG_FRAME.match(p.name))}
             if right_dir.is_dir() else {})
    if not left:
        raise SessionError(src, "expected left frames img_<n>.jpg, found none")
    numbers = sorted(left)
    beyond = [n for n in numbers if n >= len(rows)]
    if beyond:
        raise SessionError(
            src / YANG_LABELS, f"expected a row for every left frame: {len(rows)} rows, but img_{beyond[0]} needs "
            f"row {beyond[0] + 1} ({len(beyond)} frame(s) without a row)"
        )
    notes = []
    if len(rows) > len(numbers):
        notes.append(f"{len(rows) - len(numbers)} row(s) of {YANG_LABELS} have no left image and were skipped")
    no_right = [n for n in numbers if n not in right]
    if no_right:
        notes.append(f"{len(no_right)} frame(s) have no right_img/ image (no SGBM depth for them)")
    orphans = sorted(set(right) - set(left))
    if orphans:
        notes.append(f"{len(orphans)} right_img/ image(s) without a left image were skipped")
    times = [float(rows[n][0]) for n in numbers]
    # the reader refuses a frames.csv whose times do not increase; say so now, naming the rows
    check_times_increase(src / YANG_LABELS, [f"img_{n}" for n in numbers], np.asarray(times),
                         {k: n + 1 for k, n in enumerate(numbers)})
    notes.append("force is the sensor's latest value at each left frame (the recorder wrote zeros before the "
                 "first sensor message)")
    width = _stem_width(numbers[-1] + 1)
    placed = {"hardlink": 0, "symlink": 0, "copy": 0}
    out_path = Path(out)
    with _staging(src, out_path) as tmp:
        (tmp / "left").mkdir()
        if right:
            (tmp / "right").mkdir()
        frame_rows, force_rows = [], []
        for n in numbers:
            stem = f"{n:0{width}d}"
            placed[_place(left[n], tmp / "left" / f"{stem}{left[n].suffix.lower()}", copy)] += 1
            if n in right:
                placed[_place(right[n], tmp / "right" / f"{stem}{right[n].suffix.lower()}", copy)] += 1
            frame_rows.append((stem, rows[n][0]))
            force_rows.append((stem, *(rows[n][c] for c in YANG_FORCE_COLUMNS)))
        _write_csv(tmp / "frames.csv", ("frame", "timestamp"), frame_rows)
        _write_csv(tmp / "force.csv", ("frame", "fx", "fy", "fz"), force_rows)
        if _place_calibration(calibration, tmp, copy):
            read_calibration(tmp, read_image_size(left[numbers[0]]))
        _write_session_json(tmp / "session.json", out_path.name, "yang2024", src, times, {})
    out_path = out_path.expanduser().resolve()
    return ImportResult(
        "yang2024", src, out_path, len(numbers), placed, len(force_rows), notes, missing_inputs(out_path)
    )


