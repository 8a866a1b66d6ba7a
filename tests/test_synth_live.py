"""Tests of the live synthetic session writer (contact_viz.synth.live, `contact-viz synth --live`).

No assertion depends on how fast the machine is: the writer never writes a frame before its time,
so only lower bounds on times are checked; everything else is order and content (checked from the
writer's own ``on_frame`` callback, which runs between frames, or by a reader thread that polls).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from contact_viz.synth import SynthParams, generate_session, write_live
from contact_viz.synth import live as live_module

TINY = {"width": 160, "height": 90}
FRAMES = 20
FPS = 60.0
LAYERS = (("right", ".jpg"), ("masks", ".png"), ("depth", ".npy"), ("left", ".jpg"))  # the order they appear in


def tree(root: Path) -> dict[str, str]:
    """Every file under ``root`` (hidden ones too): relative path -> sha256."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def no_staging_beside(out: Path) -> list[str]:
    return [p.name for p in out.parent.iterdir() if p.name.startswith(".")]


def completeness(path: Path, data: bytes) -> str | None:
    """Why ``data`` is not a complete file of its kind (None: complete)."""
    name = path.name
    if name.endswith(".jpg"):
        return None if data[:2] == b"\xff\xd8" and data[-2:] == b"\xff\xd9" else "JPEG without its end marker"
    if name.endswith(".png"):
        return None if data[:8] == b"\x89PNG\r\n\x1a\n" and data[-12:] == b"\x00\x00\x00\x00IEND\xaeB`\x82" \
            else "PNG without its IEND chunk"
    if name.endswith(".npy"):
        buffer = io.BytesIO(data)
        try:
            version = np.lib.format.read_magic(buffer)
            read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, _, dtype = read(buffer)
        except (ValueError, SyntaxError, EOFError):
            return "npy with a partial header"
        if len(data) != buffer.tell() + int(np.prod(shape)) * dtype.itemsize:
            return f"npy of {len(data)} bytes, short of its data"
        return None
    if name.endswith(".csv"):
        return None if data.endswith(b"\n") else "CSV ending in a partial line"
    if name == "session.json":
        try:
            json.loads(data)
        except ValueError:
            return "partial JSON"
        return None
    if name == "K.txt":
        return None if data.endswith(b"\n") and data.count(b"\n") == 2 else "partial K.txt"
    return "an unexpected file"


class Reader(threading.Thread):
    """Polls the session as a follower would: notes when each visible file is first seen and every
    visible file that is not complete when read."""

    def __init__(self, out: Path) -> None:
        super().__init__(daemon=True)
        self.out, self.halt = out, threading.Event()
        self.first_seen: dict[str, int] = {}  # relative path -> poll number
        self.partial: list[tuple[str, str]] = []
        self.hidden_seen = 0
        self.polls = 0

    def run(self) -> None:
        while not self.halt.is_set():
            self.poll()

    def poll(self) -> None:
        """One look at every folder, in the reverse of the writing order (left/, depth/, masks/, right/, the
        session's own files), so that a file seen in a poll implies those written before it are seen too."""
        self.polls += 1
        folders = [self.out / sub for sub, _ in reversed(LAYERS)] + [self.out]
        for folder in folders:
            try:
                entries = sorted(os.scandir(folder), key=lambda e: e.name)
            except FileNotFoundError:
                continue
            for entry in entries:
                if entry.is_dir():
                    continue
                if entry.name.startswith("."):
                    self.hidden_seen += 1
                    continue
                path = Path(entry.path)
                try:
                    data = path.read_bytes()
                except FileNotFoundError:
                    continue
                why = completeness(path, data)
                if why is not None:
                    self.partial.append((str(path.relative_to(self.out)), why))
                self.first_seen.setdefault(str(path.relative_to(self.out)), self.polls)

    def stop(self) -> None:
        self.halt.set()
        self.join()
        self.poll()


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> tuple[Path, SynthParams]:
    """``generate_session`` of the params the live runs use (out dir named ``s``, as theirs)."""
    params = SynthParams(phantom="cup", frames=FRAMES, seed=3, **TINY)
    return generate_session(tmp_path_factory.mktemp("reference") / "s", params), params


@pytest.fixture(scope="module")
def glove_reference(tmp_path_factory) -> tuple[Path, SynthParams]:
    params = SynthParams(phantom="glove", frames=12, seed=1, **TINY)
    return generate_session(tmp_path_factory.mktemp("glove") / "s", params), params


def rows(path: Path) -> list[str]:
    return path.read_text().splitlines()[1:]


# -- rename (the default): the final session, order, no visible partial file ---------------------


def test_live_session_is_the_same_files_appearing_in_order_at_the_rate(reference, tmp_path):
    ref, params = reference
    out = tmp_path / "s"
    reader = Reader(out)
    started: list[float] = []
    seen: list[tuple[int, float]] = []
    problems: list[str] = []

    def on_start() -> None:
        started.append(time.monotonic())
        reader.start()

    def on_frame(k: int, late_s: float) -> None:  # runs in the writer between frames: exact state
        seen.append((k, time.monotonic()))
        stems = {sub: sorted(p.name for p in (out / sub).iterdir() if not p.name.startswith("."))
                 for sub, _ in LAYERS}
        for sub, suffix in LAYERS:
            if stems[sub] != [f"{j:06d}{suffix}" for j in range(k + 1)]:
                problems.append(f"after frame {k}: {sub}/ holds {stems[sub]}")
        for name in ("force.csv", "truth.csv"):
            if [r.split(",")[0] for r in rows(out / name)] != [str(j) for j in range(k + 1)]:
                problems.append(f"after frame {k}: {name} rows {rows(out / name)}")
        if late_s < 0:
            problems.append(f"frame {k}: lateness {late_s}")

    stats = write_live(out, params, FPS, on_start=on_start, on_frame=on_frame, workers=1)
    reader.stop()

    assert tree(out) == tree(ref)  # byte-identical, and no file more (a .tmp left behind) or less
    assert no_staging_beside(out) == []
    assert problems == []
    assert reader.partial == []  # under its own name a file is always complete
    # order as a reader saw it: the session-wide files first, then per frame right, mask, depth, left
    first = reader.first_seen
    for name in ("K.txt", "force.csv", "truth.csv", "session.json"):
        assert first[name] <= first["left/000000.jpg"]
    for k in range(FRAMES):
        stems = [f"{sub}/{k:06d}{suffix}" for sub, suffix in LAYERS]
        assert [first[s] for s in stems] == sorted(first[s] for s in stems), stems
        if k:
            assert first[f"left/{k - 1:06d}.jpg"] <= first[f"left/{k:06d}.jpg"]
    # the rate: frame k is never written before its time, one interval after the session-wide files
    assert [k for k, _ in seen] == list(range(FRAMES))
    for k, at in seen:
        assert at - started[0] >= (k + 1) / FPS - 0.002, (k, at - started[0])
    assert stats.frames == stats.total == FRAMES and not stats.stopped
    assert stats.fps == FPS and stats.achieved_fps is not None and stats.max_late_s >= 0
    assert "20 frames written at" in stats.line(out)


def test_glove_live_in_place_with_late_force_rows_is_the_same_session(glove_reference, tmp_path):
    """--no-rename with force rows 3 frames late: the same files in the end (labels.csv too); a reader
    sees half-written files (what the mode is for); force rows come 3 frames after their frames."""
    ref, params = glove_reference
    out = tmp_path / "s"
    reader = Reader(out)
    counts: list[tuple[int, int, int]] = []

    def on_frame(k: int, late_s: float) -> None:
        counts.append((k, len(rows(out / "force.csv")), len(rows(out / "labels.csv"))))

    # at 15 frames/s each frame's files are written in pieces over 50 ms
    write_live(out, params, 15.0, rename=False, force_delay_frames=3, on_start=reader.start, on_frame=on_frame,
               workers=2)  # two workers render frames out of order: still the same files
    reader.stop()
    assert tree(out) == tree(ref)
    assert no_staging_beside(out) == []
    assert counts == [(k, max(0, k - 2), k + 1) for k in range(params.frames)]
    assert [p for p in reader.partial if p[0].split("/")[0] in {sub for sub, _ in LAYERS}], reader.partial[:5]


def test_prerender_renders_every_frame_before_writing_one(reference, tmp_path):
    """From a test thread: every frame is in the hidden stage beside the session before the first file."""
    ref, params = reference
    out = tmp_path / "s"
    staged_at_start: list[int] = []
    result: list = []
    stop = threading.Event()

    def on_start() -> None:
        stage = [p for p in tmp_path.iterdir() if p.name.startswith(".s.") and p.name.endswith(".live")]
        staged_at_start.append(len(list((stage[0] / "left").iterdir())) if len(stage) == 1 else -1)

    worker = threading.Thread(target=lambda: result.append(
        write_live(out, params, 120.0, prerender=True, on_start=on_start, stop=stop, workers=2)))
    worker.start()
    worker.join(120)
    if worker.is_alive():
        stop.set()
        worker.join(30)
        pytest.fail("prerender did not start writing within 120 s")
    assert staged_at_start == [FRAMES]
    assert result and result[0].frames == FRAMES and not result[0].stopped
    assert tree(out) == tree(ref)
    assert no_staging_beside(out) == []


# -- stopping -----------------------------------------------------------------------------------


def test_stop_event_leaves_a_session_of_the_frames_written(reference, tmp_path):
    from contact_viz.io.session import open_session

    ref, params = reference
    out = tmp_path / "s"
    stop = threading.Event()

    def on_frame(k: int, late_s: float) -> None:
        if k == 5:
            stop.set()

    stats = write_live(out, params, FPS, stop=stop, on_frame=on_frame, force_delay_frames=4, workers=1)
    assert stats.stopped and stats.frames == 6 and stats.total == FRAMES
    session = open_session(out)
    assert session.stems == [f"{k:06d}" for k in range(6)]
    assert not np.isnan(session.force_xyz_n).any()  # the force rows still owed were written
    reference_files = tree(ref)
    for rel, digest in tree(out).items():  # every file is the finished session's, or its beginning
        if rel.endswith(".csv"):
            full = (ref / rel).read_bytes()
            assert full.startswith((out / rel).read_bytes()) and (out / rel).read_bytes().count(b"\n") == 7, rel
        else:
            assert digest == reference_files[rel], rel
    assert no_staging_beside(out) == []


def test_interrupt_mid_frame_removes_that_frame(reference, tmp_path, monkeypatch):
    """Ctrl-C while frame 4's depth is written: frames 0-3 stay, nothing of frame 4 nor a .tmp."""
    from contact_viz.io.session import open_session

    _, params = reference
    out = tmp_path / "s"
    real = live_module._write_renamed

    def write(path: Path, data: bytes) -> None:
        if path.name == "000004.npy":
            raise KeyboardInterrupt
        real(path, data)

    monkeypatch.setattr(live_module, "_write_renamed", write)
    with pytest.raises(KeyboardInterrupt):
        write_live(out, params, FPS, force_delay_frames=2, workers=1)
    assert sorted(p.name for p in out.rglob("*") if p.name.startswith(".")) == []
    for sub, suffix in LAYERS:
        assert sorted(p.name for p in (out / sub).iterdir()) == [f"{k:06d}{suffix}" for k in range(4)], sub
    assert [r.split(",")[0] for r in rows(out / "force.csv")] == ["0", "1", "2", "3"]
    assert len(open_session(out)) == 4
    assert no_staging_beside(out) == []


def test_stopped_before_the_first_frame_leaves_nothing(reference, tmp_path):
    _, params = reference
    stop = threading.Event()
    stop.set()
    stats = write_live(tmp_path / "new" / "s", params, FPS, stop=stop, workers=1)
    assert stats.stopped and stats.frames == 0
    assert sorted(p.name for p in (tmp_path / "new").iterdir()) == []  # neither the session nor the stage


def test_overwrite_replaces_the_previous_session_and_keeps_other_files(reference, tmp_path):
    ref, params = reference
    out = generate_session(tmp_path / "s", SynthParams(phantom="glove", frames=25, seed=9, **TINY))
    (out / "notes.txt").write_text("mine")
    write_live(out, params, 120.0, overwrite=True, workers=1)
    assert (out / "notes.txt").read_text() == "mine"
    (out / "notes.txt").unlink()
    assert tree(out) == tree(ref)  # no labels.csv nor frames 20-24 of the glove session left


def test_refuses_a_non_empty_directory_and_bad_arguments(reference, tmp_path):
    _, params = reference
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "keep.txt").write_text("x")
    with pytest.raises(FileExistsError):
        write_live(tmp_path / "s", params, FPS)
    for bad in ({"fps": 0}, {"force_delay_frames": -1}, {"workers": 0}):
        with pytest.raises(ValueError):
            write_live(tmp_path / "t", params, **{"fps": FPS, **bad})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]


# -- the command --------------------------------------------------------------------------------


def _cli(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "contact_viz.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)


def _finish(proc: subprocess.Popen, timeout_s: float = 180) -> tuple[str, str]:
    try:
        return proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        pytest.fail(f"still running after {timeout_s} s:\n{out}\n{err}")


def _alive_in_group(pgid: int) -> list[int]:
    """The processes of group ``pgid`` still running (zombies excluded)."""
    alive = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[2]) == pgid and fields[0] != "Z":
                alive.append(int(entry.name))
    return alive


def test_cli_live_writes_the_session_of_cli_synth(tmp_path):
    a, b = tmp_path / "a" / "s", tmp_path / "b" / "s"
    common = ["--frames", "8", "--size", "160x90", "--seed", "4", "--phantom", "kidney"]
    out, err = _finish(_cli(["synth", str(a), *common]))
    proc = _cli(["synth", str(b), *common, "--live", "--fps", "40"])
    out, err = _finish(proc)
    assert proc.returncode == 0, err
    lines = out.splitlines()
    assert lines[0] == f"writing {b} live at 40 frames/s: 8 frames"
    assert lines[1].startswith(f"{b}: 8 frames written at ") and "largest lateness" in lines[1]
    assert len(lines) == 2 and "Traceback" not in err
    assert tree(a) == tree(b)
    assert no_staging_beside(b) == []


def test_cli_live_options_need_live(tmp_path):
    proc = _cli(["synth", str(tmp_path / "s"), "--frames", "2", "--size", "64x36", "--no-rename"])
    out, err = _finish(proc)
    assert proc.returncode == 2 and "go with --live" in err
    assert not (tmp_path / "s").exists()


def test_cli_live_stopped_by_sigterm_leaves_a_valid_session(tmp_path):
    from contact_viz.io.session import open_session

    out_dir = tmp_path / "s"
    proc = _cli(["synth", str(out_dir), "--frames", "200", "--size", "160x90", "--live", "--fps", "10"])
    deadline = time.monotonic() + 120
    while not (out_dir / "left" / "000002.jpg").exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            os.killpg(proc.pid, signal.SIGKILL)
            pytest.fail(f"no frames written: {proc.communicate()}")
        time.sleep(0.02)
    proc.send_signal(signal.SIGTERM)
    out, err = _finish(proc, 60)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "stopped by SIGTERM" in err and "Traceback" not in err
    assert "stopped after" in out
    deadline = time.monotonic() + 10
    while (left := _alive_in_group(proc.pid)) and time.monotonic() < deadline:
        time.sleep(0.05)
    if left:
        os.killpg(proc.pid, signal.SIGKILL)
    assert left == [], "render workers outlived the command"
    session = open_session(out_dir)
    n = len(session)
    assert 3 <= n < 200
    for sub, suffix in LAYERS:
        assert sorted(p.name for p in (out_dir / sub).iterdir()) == [f"{k:06d}{suffix}" for k in range(n)], sub
    assert len(rows(out_dir / "force.csv")) == len(rows(out_dir / "truth.csv")) == n
    assert no_staging_beside(out_dir) == []
