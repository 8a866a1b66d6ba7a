"""Bad input and user mistakes, as a new user meets them: broken copies of one valid synthetic
session and the usual command-line slips.

Each case asserts the exit status, the one line naming the file or option, that no traceback
was printed, that the session directory is byte-for-byte untouched, that a failing command left
nothing under its output name, and for a per-frame fault that every other frame's row equals
the clean run's. Commands run in-process (typer's CliRunner, through the same error edge as
the console script) except where the exit path itself is under test (subprocess).
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from contact_viz.cli import app
from contact_viz.synth import SynthParams, generate_session

H, W, N_FRAMES = 80, 128, 8  # small enough to be quick, large enough for a patch on every frame
BAD = 3  # the frame broken by per-frame faults
STEM = f"{BAD:06d}"


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("base") / "cup"
    generate_session(out, SynthParams(phantom="cup", frames=N_FRAMES, seed=1, width=W, height=H))
    return out


@pytest.fixture(scope="module")
def clean_rows(base, tmp_path_factory) -> list[dict]:
    out = tmp_path_factory.mktemp("clean") / "features.csv"
    result = cli(["extract", str(base), "-o", str(out), "--processes", "1"])
    assert result.exit_code == 0, result.output
    rows = read_rows(out)
    assert len(rows) == N_FRAMES and all(r["distance_m"] for r in rows)  # a patch on every frame
    return rows


@pytest.fixture
def session(base, tmp_path) -> Path:
    copy = tmp_path / "session"
    shutil.copytree(base, copy, symlinks=True)
    return copy


def cli(args: list[str]):
    return CliRunner().invoke(app, args, catch_exceptions=True)


def read_rows(path: Path) -> list[dict]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def tree_hash(root: Path) -> dict[str, str]:
    """Every entry under ``root``: file bytes hashed, links by their target (never followed), modes."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in sorted(dirnames + filenames):
            path = Path(dirpath) / name
            rel = str(path.relative_to(root))
            st = path.lstat()
            if path.is_symlink():
                out[rel] = f"link:{os.readlink(path)}"
            elif path.is_file():
                out[rel] = f"{st.st_mode:o}:" + hashlib.sha256(path.read_bytes()).hexdigest()
            else:
                out[rel] = f"dir:{st.st_mode:o}"
    return out


def assert_one_error_line(result, pattern: str) -> str:
    """Exit 2, no traceback, exactly one ``error:`` line matching ``pattern`` (regex)."""
    import re

    err = result.stderr
    assert result.exit_code == 2, (result.exit_code, result.output, result.exception)
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    assert "Traceback" not in result.output
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1, err
    assert re.search(pattern, lines[0]), (pattern, lines[0])
    return lines[0]


def depth_file(session: Path, stem: str = STEM) -> Path:
    return session / "depth" / f"{stem}.npy"


def mask_file(session: Path, stem: str = STEM) -> Path:
    return session / "masks" / f"{stem}.png"


def all_depth(session: Path, change) -> None:
    for path in sorted((session / "depth").glob("*.npy")):
        change(path)


def all_masks(session: Path, change) -> None:
    for path in sorted((session / "masks").glob("*.png")):
        change(path)


def write(path: Path, text: str) -> None:
    path.write_text(text)


def truncate(path: Path, keep: float = 0.5) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def resize_mask(path: Path) -> None:
    mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(path), cv2.resize(mask, (W // 2, H // 2), interpolation=cv2.INTER_NEAREST))


def frames_csv(session: Path, times: list[float]) -> None:
    write(session / "frames.csv", "frame,timestamp\n" + "".join(f"{i:06d},{t}\n" for i, t in enumerate(times)))


# --------------------------------------------------------------------------------------------
# Session faults: the whole session is refused with one line naming the file
# --------------------------------------------------------------------------------------------

def _u8_depth_png(path: Path) -> None:
    depth = np.load(path)
    cv2.imwrite(str(path.with_suffix(".png")), np.clip(depth * 1000, 0, 255).astype(np.uint8))
    path.unlink()


def _rgb16_depth_png(path: Path) -> None:
    depth = (np.nan_to_num(np.load(path)) * 1000).astype(np.uint16)
    cv2.imwrite(str(path.with_suffix(".png")), np.dstack([depth] * 3))
    path.unlink()


def _to_disparity_wrong_shape(session: Path) -> None:
    (session / "disparity").mkdir()
    for path in sorted((session / "depth").glob("*.npy")):
        np.save(session / "disparity" / path.name, np.ones((H // 2, W), np.float32))
    shutil.rmtree(session / "depth")


def _link_loop(session: Path) -> None:
    (session / "left" / "loop.png").symlink_to("loop2.png")
    (session / "left" / "loop2.png").symlink_to("loop.png")


SESSION_FAULTS = {
    # calibration
    "no calibration": (lambda s: (s / "K.txt").unlink(), r"K\.txt|calibration"),
    "K.txt 8 numbers": (lambda s: write(s / "K.txt", "1 0 64 0 1 40 0 0\n0.005\n"), r"K\.txt"),
    "K.txt zero baseline": (lambda s: write(s / "K.txt", "76 0 63.5 0 76 39.5 0 0 1\n0\n"), r"K\.txt.*baseline"),
    "K.txt words": (lambda s: write(s / "K.txt", "fx fy cx cy\n"), r"K\.txt"),
    "K.txt empty": (lambda s: write(s / "K.txt", ""), r"K\.txt"),
    # session.json
    "session.json not JSON": (lambda s: write(s / "session.json", "{name: cup"), r"session\.json: expected valid JSON"),
    "session.json a list": (lambda s: write(s / "session.json", "[1, 2]"), r"session\.json: expected a JSON object"),
    "session.json fps -1": (lambda s: write(s / "session.json", '{"fps": -1}'), r"session\.json: .*\"fps\""),
    "session.json name 3": (lambda s: write(s / "session.json", '{"name": 3}'), r"session\.json: .*\"name\""),
    # frames.csv
    "frames.csv no timestamp column": (lambda s: write(s / "frames.csv", "frame,time\n0,0\n"),
                                       r"frames\.csv: expected columns frame, timestamp"),
    "frames.csv times go back": (lambda s: frames_csv(s, [0, 0.1, 0.2, 0.15, 0.4, 0.5, 0.6, 0.7]),
                                 r"frames\.csv: line 5: .*000003.*goes back.*000002.*line 4"),
    "frames.csv time repeats": (lambda s: frames_csv(s, [0, 0.1, 0.1, 0.3, 0.4, 0.5, 0.6, 0.7]),
                                r"frames\.csv: line 4: .*repeats"),
    "frames.csv frame missing": (lambda s: frames_csv(s, [0, 0.1, 0.2]), r"frames\.csv: expected a timestamp for every"),
    "frames.csv nan time": (lambda s: frames_csv(s, [0, 0.1, "nan", 0.3, 0.4, 0.5, 0.6, 0.7]), r"frames\.csv: line 4"),
    # force.csv / labels.csv
    "force.csv no fz": (lambda s: write(s / "force.csv", "frame,fx,fy\n0,1,1\n"), r"force\.csv: .*missing fz"),
    "force.csv word": (lambda s: write(s / "force.csv", "frame,fx,fy,fz\n0,1,x,1\n"), r"force\.csv: line 2"),
    "force.csv row twice": (lambda s: write(s / "force.csv", "frame,fx,fy,fz\n1,1,1,1\n1,2,2,2\n"),
                            r"force\.csv: expected one row per frame"),
    "force.csv ragged": (lambda s: write(s / "force.csv", "frame,fx,fy,fz\n1,1,1\n"), r"force\.csv: line 2"),
    "force.csv binary": (lambda s: (s / "force.csv").write_bytes(b"\xff\xfe\x00garbage\x80\x81"), r"force\.csv"),
    "force by time, no frames.csv": (lambda s: write(s / "force.csv", "timestamp,fx,fy,fz\n0,1,1,1\n"),
                                     r"frames\.csv: missing"),
    "labels.csv contact 2": (lambda s: write(s / "labels.csv", "frame,contact\n1,2\n"), r"labels\.csv: line 2"),
    "labels.csv no contact column": (lambda s: write(s / "labels.csv", "frame,label\n1,1\n"), r"labels\.csv"),
    # folders and links
    "no left/": (lambda s: shutil.rmtree(s / "left"), r"left: missing"),
    "empty left/": (lambda s: [p.unlink() for p in (s / "left").iterdir()], r"left: expected .* found none"),
    "no masks/": (lambda s: shutil.rmtree(s / "masks"), r"masks: missing: masks/<stem>\.png"),
    "two files one stem": (lambda s: shutil.copy(s / "left" / "000001.jpg", s / "left" / "000001.png"),
                           r"left: expected one file per frame"),
    "first left image garbage": (lambda s: (s / "left" / "000000.jpg").write_bytes(b"not an image"),
                                 r"left/000000\.jpg: expected a readable PNG/JPEG"),
    "symlink loop in left/": (_link_loop, r"left/loop2?\.png: .*symbolic links"),
    # a format fault every frame shares (shape, dtype, bit depth, channels)
    "masks all half size": (lambda s: all_masks(s, resize_mask), r"masks/000000\.png: expected a tool mask of 80x128"),
    "depth all half size": (lambda s: all_depth(s, lambda p: np.save(p, np.ones((H // 2, W // 2), np.float32))),
                            r"depth/000000\.npy: expected a depth map of 80x128"),
    "depth all int16": (lambda s: all_depth(s, lambda p: np.save(p, np.ones((H, W), np.int16))),
                        r"depth/000000\.npy: expected a 2-D float32 .*int16"),
    "depth all 3-D": (lambda s: all_depth(s, lambda p: np.save(p, np.ones((H, W, 1), np.float32))),
                      r"depth/000000\.npy: expected a 2-D float32"),
    "depth all uint8 PNG": (lambda s: all_depth(s, _u8_depth_png), r"depth/000000\.png: expected a 16-bit .* 8-bit"),
    "depth all RGB PNG": (lambda s: all_depth(s, _rgb16_depth_png), r"depth/000000\.png: expected a 16-bit single"),
    "disparity all wrong shape": (_to_disparity_wrong_shape, r"disparity/000000\.npy: expected a disparity map of 80x128"),
}


@pytest.mark.parametrize("name", list(SESSION_FAULTS))
def test_session_fault_stops_every_command_with_one_line(name, session, tmp_path):
    change, pattern = SESSION_FAULTS[name]
    change(session)
    before = tree_hash(session)
    out = tmp_path / "results" / "features.csv"
    line = assert_one_error_line(cli(["extract", str(session), "-o", str(out), "--processes", "1"]), pattern)
    assert not out.exists() and not out.with_name("features.csv.json").exists()
    rrd = tmp_path / "results" / "view.rrd"
    view_line = assert_one_error_line(cli(["view", str(session), "--save", str(rrd)]), pattern)
    assert view_line == line  # the debugger refuses the same files with the same message
    assert not rrd.exists()
    assert tree_hash(session) == before


def test_object_id_on_rgb_masks_is_a_session_error(session, tmp_path):
    """--object-id needs palettized or single-channel masks: RGB masks on every frame stop the run."""
    all_masks(session, lambda p: cv2.imwrite(str(p), np.dstack([cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)] * 3)))
    out = tmp_path / "f.csv"
    assert_one_error_line(cli(["extract", str(session), "-o", str(out), "--object-id", "1", "--processes", "1"]),
                          r"masks/000000\.png: .*--object-id 1, found 3 channels")
    assert not out.exists()


# --------------------------------------------------------------------------------------------
# Per-frame faults: that frame is skipped with one warning line, the rest is unchanged
# --------------------------------------------------------------------------------------------

def _dangling(path: Path) -> None:
    path.unlink()
    path.symlink_to(path.with_name("nowhere.npy"))


def _dir_instead(path: Path) -> None:
    path.unlink()
    path.mkdir()


FRAME_FAULTS = {
    "mask missing": (lambda s: mask_file(s).unlink(), r"masks/000003\.png: missing", "missing mask"),
    "mask truncated": (lambda s: truncate(mask_file(s)), r"masks/000003\.png: expected a tool mask PNG",
                       "unreadable mask"),
    "mask not a PNG": (lambda s: mask_file(s).write_bytes(b"GIF89a garbage"), r"masks/000003\.png: expected a tool mask",
                       "unreadable mask"),
    "mask empty file": (lambda s: mask_file(s).write_bytes(b""), r"masks/000003\.png: .*empty file", "unreadable mask"),
    "mask is a directory": (lambda s: _dir_instead(mask_file(s)), r"masks/000003\.png: missing", "missing mask"),
    "mask of one frame half size": (lambda s: resize_mask(mask_file(s)), r"masks/000003\.png: expected a tool mask of 80x128",
                                    "unreadable mask"),
    "depth missing": (lambda s: depth_file(s).unlink(), r"depth/000003\.npy: missing", "missing depth"),
    "depth truncated": (lambda s: truncate(depth_file(s)), r"depth/000003\.npy: .*truncated file", "unreadable depth"),
    "depth header cut": (lambda s: truncate(depth_file(s), 0.001), r"depth/000003\.npy: expected a 2-D float32",
                         "unreadable depth"),
    "depth not npy": (lambda s: depth_file(s).write_bytes(b"0.1 0.2 0.3\n" * 50), r"depth/000003\.npy: .*NUMPY magic",
                      "unreadable depth"),
    "depth dangling link": (lambda s: _dangling(depth_file(s)), r"depth/000003\.npy: missing", "missing depth"),
    "depth of one frame wrong shape": (lambda s: np.save(depth_file(s), np.ones((H, W + 1), np.float32)),
                                       r"depth/000003\.npy: expected a depth map of 80x128", "unreadable depth"),
    "depth pickled object": (lambda s: np.save(depth_file(s), np.array([{"a": 1}], dtype=object), allow_pickle=True),
                             r"depth/000003\.npy: expected a 2-D float32", "unreadable depth"),
}


def _check_per_frame(session, tmp_path, clean_rows, warning_pattern, kind, bad_reason="bad_frame"):
    import re

    before = tree_hash(session)
    out = tmp_path / "f.csv"
    result = cli(["extract", str(session), "-o", str(out), "--processes", "1"])
    assert result.exit_code == 0, result.output
    assert "Traceback" not in result.output
    warnings = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and warnings[0].startswith(f"warning: frame {STEM} ")
    assert re.search(warning_pattern, warnings[0]), (warning_pattern, warnings[0])
    assert f"1 frame skipped: 1 {kind}" in result.stderr.splitlines()
    rows = read_rows(out)
    assert rows[BAD]["reason"] == bad_reason
    assert [r for i, r in enumerate(rows) if i != BAD] == [r for i, r in enumerate(clean_rows) if i != BAD]
    assert tree_hash(session) == before


@pytest.mark.parametrize("name", list(FRAME_FAULTS))
def test_per_frame_fault_skips_that_frame_only(name, session, tmp_path, clean_rows):
    change, pattern, kind = FRAME_FAULTS[name]
    change(session)
    _check_per_frame(session, tmp_path, clean_rows, pattern, kind)


@pytest.mark.parametrize("name, change, pattern, kind, reason", [
    ("depth all zero", lambda s: np.save(depth_file(s), np.zeros((H, W), np.float32)),
     r"depth/000003\.npy: no valid depth around the tool", "empty depth", "too_few_tool_pixels"),
    ("depth all NaN", lambda s: np.save(depth_file(s), np.full((H, W), np.nan, np.float32)),
     r"depth/000003\.npy: no valid depth around the tool", "empty depth", "too_few_tool_pixels"),
    ("mask covers the image", lambda s: cv2.imwrite(str(mask_file(s)), np.full((H, W), 255, np.uint8)),
     r"masks/000003\.png: the mask leaves no background", "mask without background", "no_band"),
])
def test_frame_without_measurable_input_is_named(name, change, pattern, kind, reason, session, tmp_path, clean_rows):
    change(session)
    _check_per_frame(session, tmp_path, clean_rows, pattern, kind, bad_reason=reason)


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads files whatever their mode; an unreadable file is "
                    "covered by the truncated and garbage cases")
def test_unreadable_mask_permissions(session, tmp_path, clean_rows):
    mask_file(session).chmod(0)
    try:
        _check_per_frame(session, tmp_path, clean_rows, r"masks/000003\.png: .*could not read", "unreadable mask")
    finally:
        mask_file(session).chmod(0o644)


# --------------------------------------------------------------------------------------------
# Valid stored forms are read alike by every reader
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name, change", [
    ("Fortran-order depth", lambda s: all_depth(s, lambda p: np.save(p, np.asfortranarray(np.load(p))))),
    ("float64 depth", lambda s: all_depth(s, lambda p: np.save(p, np.load(p).astype(np.float64)))),
    ("big-endian depth", lambda s: all_depth(s, lambda p: np.save(p, np.load(p).astype(">f4")))),
])
def test_valid_depth_forms_give_the_clean_rows(name, change, session, tmp_path, clean_rows):
    change(session)
    out = tmp_path / "f.csv"
    result = cli(["extract", str(session), "-o", str(out), "--processes", "1"])
    assert result.exit_code == 0 and "warning" not in result.stderr, result.output
    assert read_rows(out) == clean_rows


def test_uint16_depth_png_and_disparity_are_accepted(session, tmp_path):
    """The other stored forms: disparity/ instead of depth/, and uint16 mm PNGs."""
    fx, baseline_m = float((session / "K.txt").read_text().split()[0]), 0.005
    (session / "disparity").mkdir()
    with np.errstate(divide="ignore"):  # depth 0 (invalid) -> disparity inf (invalid)
        all_depth(session, lambda p: np.save(session / "disparity" / p.name, fx * baseline_m / np.load(p)))
    depth = tmp_path / "depth"
    (session / "depth").rename(depth)
    result = cli(["extract", str(session), "-o", str(tmp_path / "disparity.csv"), "--processes", "1"])
    assert result.exit_code == 0 and "warning" not in result.stderr, result.output
    assert "depth from disparity/" in result.stderr
    assert all(r["distance_m"] for r in read_rows(tmp_path / "disparity.csv"))
    shutil.rmtree(session / "disparity")
    depth.rename(session / "depth")
    all_depth(session, lambda p: (cv2.imwrite(str(p.with_suffix(".png")),
                                              np.round(np.nan_to_num(np.load(p)) * 1000).astype(np.uint16)),
                                  p.unlink()))
    result = cli(["extract", str(session), "-o", str(tmp_path / "png.csv"), "--processes", "1"])
    assert result.exit_code == 0 and "warning" not in result.stderr, result.output
    assert all(r["distance_m"] for r in read_rows(tmp_path / "png.csv"))


def test_fortran_and_truncated_depth_agree_between_extract_and_view(session, tmp_path):
    """The two depth readers (the row reader of extract, the whole-map reader of the debugger) take
    the same files and refuse the same ones with the same message."""
    from contact_viz.io.decoders import read_depth_m, read_depth_rows_m
    from contact_viz.errors import SessionError

    path = depth_file(session)
    np.save(path, np.asfortranarray(np.load(path)))
    np.testing.assert_array_equal(read_depth_rows_m(path, 10, 30, (H, W)), read_depth_m(path)[10:30])
    truncate(path)
    messages = []
    for read in (lambda: read_depth_m(path), lambda: read_depth_rows_m(path, 0, 5, (H, W))):
        with pytest.raises(SessionError) as info:
            read()
        messages.append(str(info.value))
    assert messages[0] == messages[1] and "truncated" in messages[0]


def test_view_warnings_look_like_extract_warnings(session, tmp_path):
    """The debugger's skipped frames: the same one-line warning and summary as extract, no raw
    Python warning, no OpenCV log line (subprocess: the console as the user sees it)."""
    tool = cv2.imread(str(mask_file(session)), cv2.IMREAD_GRAYSCALE)  # palettized: decoded by PIL
    cv2.imwrite(str(mask_file(session)), np.where(tool > 0, 255, 0).astype(np.uint8))  # 8-bit: by OpenCV
    truncate(mask_file(session))
    rrd = tmp_path / "v.rrd"
    env = {key: value for key, value in os.environ.items() if key not in ("OPENCV_LOG_LEVEL", "RUST_LOG")}
    command = [sys.executable, "-m", "contact_viz.cli", "view", str(session), "--save", str(rrd)]
    loud = subprocess.run([*command, "--verbose"], capture_output=True, text=True, env=env, timeout=300)
    assert loud.returncode == 0 and "[ WARN" in loud.stderr  # OpenCV does complain about this file
    proc = subprocess.run(command, capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stderr.splitlines()
    assert [line for line in lines if line.startswith("warning:")] == [
        next(line for line in lines if line.startswith(f"warning: frame {STEM} skipped: "))]
    assert "1 frame skipped: 1 unreadable mask" in lines
    assert "BadFrameWarning" not in proc.stderr and "[ WARN" not in proc.stderr and "Traceback" not in proc.stderr
    assert rrd.exists()


@pytest.mark.parametrize("command", [["view", "--images", "video"], ["view", "--images", "jpeg"], ["check"]])
def test_truncated_jpeg_is_named_not_grey_filled(session, tmp_path, command):
    """A left JPEG cut short: libjpeg would decode it with grey rows and print "Premature end of JPEG
    file". The viewer and `check` name the file in one warning line and go on (subprocess: the console
    as the user sees it); nothing in the session changes."""
    path = session / "left" / f"{STEM}.jpg"
    truncate(path)
    before = tree_hash(session)
    args = [*command, str(session)] + (["--save", str(tmp_path / "v.rrd")] if command[0] == "view" else [])
    proc = subprocess.run([sys.executable, "-m", "contact_viz.cli", *args], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    output = proc.stdout + proc.stderr
    named = [line for line in output.splitlines() if "left/000003.jpg" in line]
    assert len(named) == 1 and "warning:" in named[0] and "cut short" in named[0], output
    assert "Premature end" not in output and "Traceback" not in output
    assert tree_hash(session) == before


def test_jpeg_completeness_test():
    """A JPEG is whole when its end-of-image marker is within the last KiB: files that PIL writes pass,
    with or without padding after the marker; the same files cut anywhere after the header do not."""
    from io import BytesIO

    from PIL import Image

    from contact_viz.errors import SessionError
    from contact_viz.io.decoders import check_jpeg_complete

    rng = np.random.default_rng(0)
    buffer = BytesIO()
    Image.fromarray(rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)).save(buffer, "JPEG", quality=90)
    data = buffer.getvalue()
    assert data.endswith(b"\xff\xd9")
    for whole in (data, data + b"\0" * 100):
        check_jpeg_complete(Path("x.jpg"), whole, "a JPEG")
    for keep in (0.3, 0.6, 0.9, 0.999):
        with pytest.raises(SessionError, match=r"x\.jpg: expected a JPEG, found a JPEG cut short"):
            check_jpeg_complete(Path("x.jpg"), data[: int(len(data) * keep)], "a JPEG")
    check_jpeg_complete(Path("x.png"), b"\x89PNG\r\n\x1a\n" + bytes(50), "a PNG")  # not a JPEG: not its business


# --------------------------------------------------------------------------------------------
# Command-line slips
# --------------------------------------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


SLIPS = {
    "extract -o a directory": (lambda s, t: ["extract", str(s), "-o", str(t)], r": -o/--output: is a directory"),
    "extract -o /proc": (lambda s, t: ["extract", str(s), "-o", "/proc/x.csv"], r"/proc/x\.csv: -o/--output: cannot write"),
    "extract -o in the session": (lambda s, t: ["extract", str(s), "-o", str(s / "f.csv")], r"inside the session directory"),
    "extract -o under a file": (lambda s, t: ["extract", str(s), "-o", str(s / "K.txt" / "f.csv")],
                                r"K\.txt/f\.csv: -o/--output"),
    "--contact-force -1": (lambda s, t: ["extract", str(s), "--contact-force", "-1", "-o", str(t / "f.csv")],
                           r"^error: --contact-force: expected a force > 0 N, got -1$"),
    "--params missing": (lambda s, t: ["extract", str(s), "--params", str(t / "p.json"), "-o", str(t / "f.csv")],
                         r"p\.json"),
    "--params not JSON": (lambda s, t: [(t / "p.json").write_text("{n1: 3"), "extract", str(s), "--params",
                                        str(t / "p.json"), "-o", str(t / "f.csv")][1:], r"p\.json"),
    "--params bad field": (lambda s, t: [(t / "p.json").write_text('{"n1": -4}'), "extract", str(s), "--params",
                                         str(t / "p.json"), "-o", str(t / "f.csv")][1:], r"p\.json"),
    "session missing": (lambda s, t: ["extract", str(t / "nope"), "-o", str(t / "f.csv")],
                        r"nope: missing: expected a session directory \(left/, masks/ and K\.txt; depth/ optional"),
    "session is a file": (lambda s, t: ["extract", str(s / "K.txt"), "-o", str(t / "f.csv")],
                          r"K\.txt: expected a session directory .*found a file"),
    "view --connect not a URL": (lambda s, t: ["view", str(s), "--connect", "notaurl"],
                                 r"--connect: expected a Rerun viewer URL like rerun\+http://"),
    "view --connect no viewer": (lambda s, t: ["view", str(s), "--connect", f"rerun+http://127.0.0.1:{_free_port()}/proxy"],
                                 r"--connect .*: no Rerun viewer is listening"),
    "view --save /proc": (lambda s, t: ["view", str(s), "--save", "/proc/a.rrd"], r"/proc/a\.rrd: --save: cannot write"),
    "view --save a directory": (lambda s, t: ["view", str(s), "--save", str(t)], r"--save: is a directory"),
    "view --start past the end": (lambda s, t: ["view", str(s), "--save", str(t / "a.rrd"), "--start", "99"],
                                  r"--start: frame 99 is past the last frame"),
    "view --save not .rrd": (lambda s, t: ["view", str(s), "--save", str(t / "a.txt")], r"expected a path ending in \.rrd"),
    "synth over a session": (lambda s, t: ["synth", str(s), "--frames", "2", "--size", "64x64"], r"pass --overwrite"),
    "synth --size tiny": (lambda s, t: ["synth", str(t / "n"), "--size", "10x10"], r"--size must be at least 32x32"),
    "fit one session": (lambda s, t: ["fit", str(s), "-o", str(t / "m.json")], r"at least 2 training sessions"),
    "fit SESSION/K.txt": (lambda s, t: ["fit", str(s / "K.txt"), str(s), "-o", str(t / "m.json")],
                          r"K\.txt: expected a session directory or a features CSV"),
    "fit -o a directory": (lambda s, t: ["fit", str(s), str(s), "-o", str(t)], r"-o/--output: is a directory"),
    "depth -o /proc": (lambda s, t: ["depth", str(s), "-o", "/proc/dd"], r"/proc/dd: -o/--output: cannot make a directory"),
    "depth -o a file": (lambda s, t: ["depth", str(s), "-o", str(s / "K.txt")], r"K\.txt: -o/--output: is a file"),
    "import unknown kind": (lambda s, t: ["import", "foo", str(s), str(t / "new")], r"KIND must be one of dvrk, yang2024"),
    "import missing source": (lambda s, t: ["import", "dvrk", str(t / "nope"), str(t / "new")], r"nope: missing"),
    "predict -o a directory": (lambda s, t: ["predict", str(t / "m.json"), str(s), "-o", str(t)],
                               r"-o/--output: is a directory; expected a file name, e.g. .*predictions\.csv"),
    "view --model a directory": (lambda s, t: ["view", str(s), "--model", str(t), "--save", str(t / "v.rrd")],
                                 r"(?i:is a directory)"),
    "predict no model": (lambda s, t: ["predict", str(t / "m.json"), str(s), "-o", str(t / "p.csv")], r"m\.json"),
    "evaluate --json a directory": (lambda s, t: ["evaluate", str(t / "m.json"), str(s), "--json", str(t)],
                                    r"--json: is a directory"),
    "evaluate --per-frame /proc": (lambda s, t: ["evaluate", str(t / "m.json"), str(s), "--per-frame", "/proc/p.csv"],
                                   r"/proc/p\.csv: --per-frame: cannot write"),
}


@pytest.mark.parametrize("name", list(SLIPS))
def test_command_line_slip_is_one_line(name, session, tmp_path):
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    before = tree_hash(session)
    result = cli(SLIPS[name][0](session, out_dir))
    assert_one_error_line(result, SLIPS[name][1])
    assert result.stdout == ""  # nothing that looks like a result was printed before failing
    assert sorted(p.name for p in out_dir.iterdir()) == [n for n in ("p.json",) if (out_dir / n).exists()]
    assert tree_hash(session) == before


def test_fit_without_an_ending_contact_names_the_sessions(session, tmp_path):
    """Short sessions without a contact episode that ends: the advice names them and what is needed."""
    other = tmp_path / "other"
    shutil.copytree(session, other)
    (other / "session.json").write_text(json.dumps({"name": "other"}))
    write(session / "labels.csv", "frame,contact\n" + "".join(f"{i},{int(i >= 5)}\n" for i in range(N_FRAMES)))
    before = tree_hash(session)
    result = cli(["fit", str(session), str(other), "-o", str(tmp_path / "m.json"),
                  "--cache-dir", str(tmp_path / "cache")])
    assert_one_error_line(result, r"fit: leaving out .*, the other training sessions \(.*8 frames.*\) have no .*"
                                  r"contact episode that ends.*expected every training session to hold")
    assert not (tmp_path / "m.json").exists()
    assert tree_hash(session) == before


def test_misspelled_command_is_not_a_session_path(session):
    proc = subprocess.run([sys.executable, "-m", "contact_viz.cli", "extrat", str(session)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.startswith("error: no such command 'extrat' (did you mean 'extract'?)")
    assert "Traceback" not in proc.stderr and "view --help" not in proc.stderr


def test_session_fault_in_a_real_process_writes_nothing(session, tmp_path):
    """The console script's exit path: a format fault of every frame stops before any output."""
    all_masks(session, resize_mask)
    out = tmp_path / "r" / "f.csv"
    proc = subprocess.run([sys.executable, "-m", "contact_viz.cli", "extract", str(session), "-o", str(out)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1].startswith(f"error: {session / 'masks' / '000000.png'}: expected")
    assert "Traceback" not in proc.stderr and "warning" not in proc.stderr
    assert not out.exists() and not out.with_name("f.csv.json").exists()


def test_help_at_80_columns():
    import re

    env = {**os.environ, "COLUMNS": "80"}
    top = subprocess.run([sys.executable, "-m", "contact_viz.cli", "--help"], capture_output=True, text=True,
                         env=env, timeout=60)
    assert top.returncode == 0 and "contact-viz SESSION" in top.stdout and "--version" in top.stdout
    commands = top.stdout.split("Commands:")[1]
    assert not any(line.rstrip().endswith("...") for line in commands.splitlines())  # whole first lines
    assert "Yang et al. 2024, ROS bag / MCAP) into a session." in " ".join(commands.split())
    for command in ("extract", "view", "fit", "evaluate", "synth"):
        text = subprocess.run([sys.executable, "-m", "contact_viz.cli", command, "--help"], capture_output=True,
                              text=True, env=env, timeout=60).stdout
        assert max(len(line) for line in text.splitlines()) <= 80
        assert not re.search(r"\s\.(\s|$)", text) and "…" not in text  # no stray space before a full stop
        flat = " ".join(text.split())
        if command in ("extract", "view"):
            assert "[default: ~/.cache/contact-viz]" in flat
    version = subprocess.run([sys.executable, "-m", "contact_viz.cli", "--version"], capture_output=True, text=True,
                             timeout=60)
    assert version.returncode == 0 and version.stdout.startswith("contact-viz ")


def _tiny_model(path: Path) -> Path:
    """A model.json fitted on made-up signals (the model's numbers do not matter here)."""
    from contact_viz.model.hmm import LosoEnsemble
    from contact_viz.model.model_file import ContactModel, save_model
    from contact_viz.params import LabelParams, PatchParams

    rng = np.random.default_rng(0)
    labels = [np.tile(np.repeat([0, 1], 10), 3).astype(np.int8) for _ in range(3)]
    signals = [y * 1.0 + rng.normal(0, 0.3, y.size) for y in labels]
    ensemble = LosoEnsemble().fit(signals, labels, session_names=["a", "b", "c"])
    return save_model(ContactModel(ensemble=ensemble, patch_params=PatchParams(), label_params=LabelParams(),
                                   training_sessions=()), path)


def test_view_params_that_differ_from_the_model_say_what_to_do(session, tmp_path):
    model = _tiny_model(tmp_path / "m.json")
    (tmp_path / "p.json").write_text('{"n1": 41}')
    rrd = tmp_path / "v.rrd"
    result = cli(["view", str(session), "--model", str(model), "--params", str(tmp_path / "p.json"),
                  "--save", str(rrd)])
    assert_one_error_line(result, r"^error: --params .*p\.json: differs from the patch parameters .*m\.json was "
                                  r"fitted with \(.*n1.*\); drop --params .* or fit a model with these parameters$")
    assert not rrd.exists() and result.stdout == ""


def test_view_serve_on_a_busy_port_is_one_line(session):
    with socket.socket() as busy:
        busy.bind(("0.0.0.0", 0))
        busy.listen()
        port = busy.getsockname()[1]
        proc = subprocess.run([sys.executable, "-m", "contact_viz.cli", "view", str(session), "--serve",
                               "--grpc-port", str(_free_port()), "--web-port", str(port)],
                              capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "Address already in use" in errors[0] and "--web-port" in errors[0]
    assert "Traceback" not in proc.stderr
