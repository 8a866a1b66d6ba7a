"""Yang et al. (2024): ``img_<n>.jpg`` frames, ``right_img/``, ``labels_30hz.txt`` (see the package docstring)."""

from __future__ import annotations

import csv
import math
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from contact_viz.io.calibration import read_calibration
from contact_viz.errors import SessionError
from contact_viz.io.kinematics import TOOL_TIPS_COLUMNS, TOOL_TIPS_FILE
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


MTURK_COLUMNS = ("gt", "mturk_label", "dataset", "image", "x", "y")  # labels/MTurk_Labels_with_keypoints.csv


def _read_mturk_labels(path: Path, dataset: str) -> tuple[list[tuple[int, str, str, float, float]], list[str]]:
    """Rows of Yang et al.'s MTurk_Labels_with_keypoints.csv for ``dataset``: [(n of img_<n>, GT, crowd, x, y)].

    Also returns every dataset name in the file (for the error when ``dataset`` has no rows).
    """
    what = ("Yang et al.'s MTurk_Labels_with_keypoints.csv (header GT, MTurk_Label, dataset, image, x, y; "
            "labels 0/1, image img_<n>.jpg, x and y in px)")
    if not path.is_file():
        raise SessionError(path, f"missing: expected {what}")
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:
            table = list(csv.reader(handle))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise SessionError(path, f"expected {what}, could not read it ({exc})") from exc
    header = [c.strip().lower() for c in table[0]] if table else []
    missing = [c for c in MTURK_COLUMNS if c not in header]
    if missing:
        raise SessionError(path, f"expected {what}; missing columns {', '.join(missing)}")
    col = {name: header.index(name) for name in MTURK_COLUMNS}
    rows, names = [], []
    for line_no, cells in enumerate(table[1:], start=2):
        if not any(c.strip() for c in cells):
            continue
        if len(cells) != len(header):
            raise SessionError(path, f"line {line_no}: expected {len(header)} values, found {len(cells)}")
        cells = [c.strip() for c in cells]
        name = cells[col["dataset"]]
        if name not in names:
            names.append(name)
        if name != dataset:
            continue
        for key in ("gt", "mturk_label"):
            if cells[col[key]] not in ("0", "1"):
                raise SessionError(path, f"line {line_no}: expected {key} 0 or 1, found {cells[col[key]]!r}")
        match = _YANG_FRAME.match(cells[col["image"]])
        if match is None:
            raise SessionError(path, f"line {line_no}: expected an image name img_<n>.jpg, found "
                                     f"{cells[col['image']]!r}")
        try:
            x, y = float(cells[col["x"]]), float(cells[col["y"]])
        except ValueError:
            raise SessionError(path, f"line {line_no}: expected x and y in px, found {cells[col['x']]!r}, "
                                     f"{cells[col['y']]!r}") from None
        if not (math.isfinite(x) and math.isfinite(y)):
            raise SessionError(path, f"line {line_no}: expected finite x and y in px, found {x!r}, {y!r}")
        rows.append((int(match["n"]), cells[col["gt"]], cells[col["mturk_label"]], x, y))
    return rows, names


def _write_mturk_files(tmp: Path, rows, stem_of: dict[int, str], labels_path: Path, dataset: str,
                       notes: list[str]) -> None:
    """labels.csv (GT), crowd_labels.csv (MTurk_Label) and tool_tips.csv (x, y) for the rows with a left frame."""
    kept = [r for r in rows if r[0] in stem_of]
    if len(kept) < len(rows):
        notes.append(f"{len(rows) - len(kept)} row(s) of {labels_path.name} for {dataset} name images that are not "
                     "in the recording and were skipped")
    kept.sort(key=lambda r: r[0])
    seen = set()
    for n, *_ in kept:
        if n in seen:
            raise SessionError(labels_path, f"expected one row per image of {dataset}, found img_{n}.jpg twice")
        seen.add(n)
    _write_csv(tmp / "labels.csv", ("frame", "contact"), [(stem_of[n], gt) for n, gt, _, _, _ in kept])
    _write_csv(tmp / "crowd_labels.csv", ("frame", "contact"), [(stem_of[n], crowd) for n, _, crowd, _, _ in kept])
    _write_csv(tmp / TOOL_TIPS_FILE, TOOL_TIPS_COLUMNS, [(stem_of[n], repr(x), repr(y)) for n, _, _, x, y in kept])
    agree = sum(gt == crowd for _, gt, crowd, _, _ in kept)
    notes.append(f"{len(kept)} labelled frames of {dataset} from {labels_path.name}: labels.csv (GT), "
                 f"crowd_labels.csv (crowd agrees on {agree}), {TOOL_TIPS_FILE} (keypoints)")


def import_yang2024(
    src: str | Path,
    out: str | Path,
    *,
    calibration: Sequence[str | Path] = (),
    copy: bool = False,
    labels: str | Path | None = None,
    dataset: str | None = None,
) -> ImportResult:
    """Import one recording of Yang et al. (2024) (``img_<n>.jpg``, ``right_img/``, ``labels_30hz.txt``).

    Row n of labels_30hz.txt belongs to img_<n>.jpg: its time (column 1) goes to frames.csv and
    its force (columns 2-4) to force.csv, indexed by frame. ``calibration`` and ``copy`` as in
    :func:`import_dvrk`. ``labels``: Yang et al.'s MTurk_Labels_with_keypoints.csv; the rows of
    ``dataset`` (default: the name of ``src``) become labels.csv (GT, sparse manual labels),
    crowd_labels.csv (MTurk_Label) and tool_tips.csv (keypoint x, y in px).
    """
    from contact_viz.io.session import missing_inputs

    src = Path(src).expanduser()
    if not src.is_dir():
        raise SessionError(src, "missing: expected a Yang et al. 2024 recording folder (img_<n>.jpg, labels_30hz.txt)")
    src = src.resolve()
    rows = _read_yang_labels(src / YANG_LABELS)
    mturk = None
    if labels is not None:
        labels = Path(labels).expanduser()
        dataset = dataset or src.name
        mturk, names = _read_mturk_labels(labels, dataset)
        if not mturk:
            raise SessionError(labels, f"expected rows of dataset {dataset!r} (choose with --dataset), found datasets "
                                       f"{', '.join(names) or 'none'}")
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
        if mturk is not None:
            _write_mturk_files(tmp, mturk, {n: f"{n:0{width}d}" for n in numbers}, labels, dataset, notes)
        if _place_calibration(calibration, tmp, copy):
            read_calibration(tmp, read_image_size(left[numbers[0]]))
        _write_session_json(tmp / "session.json", out_path.name, "yang2024", src, times,
                            {} if mturk is None else {"labels": str(labels.resolve()), "dataset": dataset})
    out_path = out_path.expanduser().resolve()
    return ImportResult(
        "yang2024", src, out_path, len(numbers), placed, len(force_rows), notes, missing_inputs(out_path)
    )


