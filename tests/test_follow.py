"""`view --follow`: a session followed while a writer thread records it.

The writer copies a finished synthetic session frame by frame (the recorder contract: a hidden
temporary name, then a rename; or, to test the completeness rules, in place in slow chunks) and
appends frames.csv / force.csv lines. The follower's recording is compared with `extract` on the
finished session: every frame, in order, with the same distance and signal.
"""

from __future__ import annotations

import csv
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from contact_viz.cli import app
from contact_viz.io.live import FollowParams, SessionFollower, decodes_completely
from contact_viz.synth import SynthParams, generate_session
from contact_viz.viz import rerun_log
from contact_viz.viz.follow import follow_session
from contact_viz.viz.options import DebuggerOptions
from contact_viz.viz.sinks import open_recording
from test_viewer import Recording, tiny_model

N = 16


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("follow") / "cup"
    generate_session(out, SynthParams(phantom="cup", frames=N, seed=3, width=160, height=96))
    with open(out / "frames.csv", "w", newline="") as handle:  # the recorder's clock: 25 frames/s from 3.5 s
        handle.write("frame,timestamp\n" + "".join(f"{k:06d},{3.5 + k / 25:.4f}\n" for k in range(N)))
    return out


@pytest.fixture(scope="module")
def extracted(finished, tmp_path_factory) -> dict[int, dict]:
    out = tmp_path_factory.mktemp("follow-extract") / "features.csv"
    result = CliRunner().invoke(app, ["extract", str(finished), "-o", str(out), "--processes", "1"])
    assert result.exit_code == 0, result.output
    with open(out, newline="") as handle:
        return {int(row["frame"]): row for row in csv.DictReader(handle)}


class Writer(threading.Thread):
    """Records ``src`` into ``dst`` at ``fps``: per frame right, mask, depth, then left, then its frames.csv
    line, then its force line ``force_delay`` frames later. ``rename``: the contract; else in place, in
    four chunks over ``chunk_s``. ``drop``: (folder, frame) never written."""

    def __init__(self, src: Path, dst: Path, fps: float = 20.0, *, rename: bool = True, chunk_s: float = 0.02,
                 force_delay: int = 0, drop: tuple[str, int] | None = None, frames: int = N) -> None:
        super().__init__(daemon=True)
        self.src, self.dst, self.fps, self.rename, self.chunk_s = src, dst, fps, rename, chunk_s
        self.force_delay, self.drop, self.frames = force_delay, drop, frames
        dst.mkdir()
        for name in ("K.txt", "session.json"):
            shutil.copy(src / name, dst / name)
        self.folders = [d for d in ("right", "masks", "depth", "left") if (src / d).is_dir()]
        for d in self.folders:
            (dst / d).mkdir()
        self.force = (src / "force.csv").read_text().splitlines()
        self.times = (src / "frames.csv").read_text().splitlines()
        (dst / "frames.csv").write_text(self.times[0] + "\n")
        (dst / "force.csv").write_text(self.force[0] + "\n")

    def put(self, source: Path, target: Path) -> None:
        data = source.read_bytes()
        if self.rename:
            tmp = target.with_name(f".{target.name}.tmp")
            tmp.write_bytes(data)
            os.rename(tmp, target)
            return
        with open(target, "wb") as handle:  # in place, slowly: a reader can see it half-written
            for k in range(4):
                handle.write(data[k * len(data) // 4:(k + 1) * len(data) // 4])
                handle.flush()
                time.sleep(self.chunk_s / 4)

    def append(self, name: str, line: str) -> None:
        with open(self.dst / name, "a") as handle:
            if self.rename:
                handle.write(line + "\n")
            else:  # half a line first
                handle.write(line[:3])
                handle.flush()
                time.sleep(self.chunk_s / 4)
                handle.write(line[3:] + "\n")

    def run(self) -> None:
        t0 = time.monotonic()
        for k in range(self.frames):
            time.sleep(max(0.0, t0 + k / self.fps - time.monotonic()))
            stem = f"{k:06d}"
            for folder in self.folders:
                if self.drop == (folder, k):
                    continue
                (source,) = (self.src / folder).glob(f"{stem}.*")
                self.put(source, self.dst / folder / source.name)
            self.append("frames.csv", self.times[k + 1])
            if k >= self.force_delay:
                self.append("force.csv", self.force[k - self.force_delay + 1])
        for j in range(max(self.frames - self.force_delay, 0), self.frames):
            self.append("force.csv", self.force[j + 1])


def follow(dst: Path, out: Path, params: FollowParams, model=None, **kwargs):
    opened = open_recording(save=out)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        summary = follow_session(dst, opened.rec, DebuggerOptions(**kwargs), model=model, params=params)
    opened.close()
    return summary, Recording(out), [str(w.message) for w in caught]


def distances(rec: Recording) -> dict[int, float]:
    return rec.scalars(rerun_log.ENTITY_SERIES_DISTANCE)


@pytest.mark.parametrize("rename", [True, False], ids=["rename", "in-place"])
def test_followed_frames_equal_extract_on_the_finished_session(finished, extracted, tmp_path, rename):
    dst = tmp_path / "live"
    writer = Writer(finished, dst, fps=15, rename=rename, chunk_s=0.03)
    writer.start()
    summary, rec, messages = follow(dst, tmp_path / "f.rrd", FollowParams(from_start=True, idle_timeout_s=1.5))
    writer.join()
    assert messages == []  # never a half-written file: no frame skipped, no warning
    assert summary.stop == "idle" and summary.frames_timed_out == 0
    assert summary.run.frames + summary.frames_series_only == N and summary.frames_unfiltered == 0
    got = distances(rec)
    assert sorted(got) == list(range(N))  # every frame, in order, at its index
    for k in range(N):
        assert got[k] == pytest.approx(float(extracted[k]["distance_m"]) * 1000, abs=1e-9)
    signal_series = rec.scalars(rerun_log.ENTITY_SERIES_SIGNAL)
    assert all(signal_series[k] == pytest.approx(float(extracted[k]["signal"]), abs=1e-12) for k in range(N))
    times = rec.frames(rerun_log.ENTITY_SERIES_LAG if hasattr(rerun_log, "ENTITY_SERIES_LAG") else "series/lag_ms",
                       "Scalars:scalars")
    assert times and set(times) <= set(range(N))
    p50, p95, worst = summary.latency_ms
    assert 0 <= p50 <= p95 <= worst


def test_a_reader_never_takes_a_half_written_file(finished, tmp_path):
    """The completeness rule itself: a PNG, JPEG or .npy cut anywhere is not complete."""
    for path in [next((finished / "masks").glob("*.png")), next((finished / "depth").glob("*.npy")),
                 next((finished / "left").iterdir())]:
        data = path.read_bytes()
        assert decodes_completely(path, len(data))
        for cut in (1, 10, len(data) // 2, len(data) - 1):
            part = tmp_path / f"cut{path.suffix}"
            part.write_bytes(data[:cut])
            assert not decodes_completely(part, cut), (path.name, cut)


def test_a_jpeg_cut_after_its_exif_thumbnail_is_not_complete(finished, tmp_path):
    """A camera's JPEG carries a thumbnail (a JPEG of its own, ending 0xFF 0xD9) in its EXIF segment: a
    file written in place up to the end of that thumbnail ends with an end-of-image marker too."""
    import cv2

    thumb = cv2.imencode(".jpg", np.full((8, 8, 3), 90, np.uint8))[1].tobytes()
    payload = b"Exif\x00\x00" + thumb
    app1 = b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload
    main = next((finished / "left").iterdir()).read_bytes()
    whole = main[:2] + app1 + main[2:]
    path = tmp_path / "exif.jpg"
    path.write_bytes(whole)
    assert cv2.imread(str(path)) is not None and decodes_completely(path, len(whole))
    cut = 2 + len(app1)
    assert whole[cut - 2:cut] == b"\xff\xd9"
    path.write_bytes(whole[:cut])
    assert not decodes_completely(path, cut)
    for cut in (len(whole) - 1, len(whole) // 2, 2 + len(app1) + 10):
        path.write_bytes(whole[:cut])
        assert not decodes_completely(path, cut), cut


def test_a_missing_mask_times_out_with_one_warning_naming_it(finished, extracted, tmp_path):
    dst = tmp_path / "live"
    writer = Writer(finished, dst, fps=15, drop=("masks", 5))
    writer.start()
    summary, rec, messages = follow(dst, tmp_path / "f.rrd",
                                    FollowParams(from_start=True, idle_timeout_s=2.0, frame_timeout_s=0.4))
    writer.join()
    assert messages == [f"frame 000005 skipped: {dst / 'masks' / '000005.png'} did not arrive complete within "
                        "0.4 s (--frame-timeout)"]
    assert summary.frames_timed_out == 1
    got = distances(rec)
    assert len(got) == N - 1  # the frames after it are taken, in order (indices close up)
    stems = [k for k in range(N) if k != 5]
    for index, k in enumerate(stems):
        assert got[index] == pytest.approx(float(extracted[k]["distance_m"]) * 1000, abs=1e-9)


def test_force_rows_arriving_after_their_frames_are_logged_at_their_frames(finished, tmp_path):
    dst = tmp_path / "live"
    writer = Writer(finished, dst, fps=15, force_delay=4)
    writer.start()
    _, rec, _ = follow(dst, tmp_path / "f.rrd", FollowParams(from_start=True, idle_timeout_s=1.5))
    writer.join()
    force = np.loadtxt(finished / "force.csv", delimiter=",", skiprows=1)
    got = rec.scalars("series/force/magnitude")
    assert sorted(got) == list(range(N))
    for k in range(N):
        assert got[k] == pytest.approx(float(np.linalg.norm(force[k, 1:])), abs=1e-6)


def test_idle_timeout_and_start_at_the_current_end(finished, tmp_path):
    dst = tmp_path / "live"
    writer = Writer(finished, dst, fps=200, frames=6)
    writer.run()  # six frames already there, nothing more comes
    started = time.monotonic()
    summary, rec, _ = follow(dst, tmp_path / "f.rrd", FollowParams(idle_timeout_s=0.5))
    assert summary.stop == "idle" and summary.run.frames == 0
    assert 0.5 <= time.monotonic() - started < 10


def test_ctrl_c_stops_a_follow_cleanly(finished, tmp_path):
    dst = tmp_path / "live"
    writer = Writer(finished, dst, fps=200, frames=4)
    writer.run()
    out = tmp_path / "f.rrd"
    proc = subprocess.Popen([sys.executable, "-m", "contact_viz.cli", "view", str(dst), "--follow", "--from-start",
                             "--save", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    deadline = time.monotonic() + 60
    while not list(tmp_path.glob(".f.rrd.*.part")) and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(1.0)  # the four frames are taken; it waits for more
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 130, (stdout, stderr)
    assert "interrupted (Ctrl-C): the recording is partial" in stdout and "Traceback" not in stderr
    lines = stdout.splitlines()  # the four frames were there at the start: replayed whole, no latency
    assert "replayed 4 frames there at the start (--from-start)" in lines and "4 frames in " in stdout
    assert ("latency (files complete -> logged): none (no frame arrived after the start); frames shown only in "
            "the series: 0 (0 without a distance); timed out: 0") in lines
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # --follow --save writes no footer (docs/live.md): the reader says so
        rec = Recording(out)
    assert sorted(distances(rec)) == [0, 1, 2, 3]
    assert rec.frames(rerun_log.ENTITY_DEPTH_IMAGE, "DepthImage:buffer") == [0, 1, 2, 3]  # each shown whole
    assert [p for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_the_first_frame_is_found_at_the_next_poll_not_the_next_rescan(finished, tmp_path):
    """Before its first frame the follower has no stem to probe from: it lists left/ at every poll, so a
    session started empty is not seen half a second (``rescan_s``) late."""
    dst = tmp_path / "live"
    writer = Writer(finished, dst, frames=0)
    follower = SessionFollower(dst, FollowParams(from_start=True, rescan_s=1e6, settle_s=0.0))
    assert follower.poll() == []  # the first listing: nothing yet
    writer.frames = 2
    writer.fps = 1e6
    writer.run()
    arrived = follower.poll()
    assert [index for index, _ in arrived] == [0, 1]
    assert list(follower.session.stems) == ["000000", "000001"]


def test_a_session_made_after_the_follower_started_is_followed(finished, extracted, tmp_path):
    """The recorder may make the session after the follower starts (synth --live renders ahead first)."""
    dst = tmp_path / "live"
    recorder = threading.Timer(0.5, lambda: Writer(finished, dst, fps=40).run())  # makes it 0.5 s from now
    recorder.start()
    summary, rec, messages = follow(dst, tmp_path / "f.rrd", FollowParams(from_start=True, idle_timeout_s=3.0))
    recorder.join()
    assert messages == [] and summary.stop == "idle"
    got = distances(rec)
    assert sorted(got) == list(range(N))
    assert got[N - 1] == pytest.approx(float(extracted[N - 1]["distance_m"]) * 1000, abs=1e-9)


def test_no_session_within_the_idle_timeout_stops_cleanly(tmp_path):
    result = CliRunner().invoke(app, ["view", str(tmp_path / "never"), "--follow", "--idle-timeout", "0.3",
                                      "--save", str(tmp_path / "f.rrd")])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert "0 frames in " in result.output and "stopped: no new frame within --idle-timeout" in lines
    assert "latency (files complete -> logged): none (no frame arrived after the start); frames shown only in the " \
           "series: 0 (0 without a distance); timed out: 0" in lines and "nan" not in result.output
    assert not (tmp_path / "never").exists()  # nothing made where the session was to be


def test_a_frame_is_complete_when_its_last_file_was_renamed_into_place_not_when_polled(finished, tmp_path):
    """The latency starts at the frame's last file (its change time: the rename), however late the poll."""
    dst = tmp_path / "live"
    writer = Writer(finished, dst, frames=0)
    follower = SessionFollower(dst, FollowParams(from_start=True))
    writer.frames, writer.fps = 2, 1e6
    writer.run()
    written = time.monotonic()
    time.sleep(0.3)  # the follower was busy
    arrived = follower.poll()
    polled = time.monotonic()
    assert [index for index, _ in arrived] == [0, 1]
    for _, completed in arrived:
        assert written - 0.05 <= completed <= written + 0.01 < polled - 0.25, (written, completed, polled)


def test_falling_behind_shows_the_newest_whole_and_the_filter_sees_every_frame(finished, extracted, tmp_path):
    """Frames written in a burst (far faster than they are logged): the older ones are shown in the series
    only, the newest whole; every frame has its distance, and the causal posterior is the model's on all
    of them, in order."""
    model = tiny_model(contact=(2.6, 0.3), free=(1.6, 0.3), seed=7)
    ensemble = model.ensemble
    dst = tmp_path / "live"
    recorder = threading.Timer(0.5, lambda: Writer(finished, dst, fps=1e5).run())  # every frame at once
    recorder.start()
    summary, rec, messages = follow(dst, tmp_path / "f.rrd", FollowParams(idle_timeout_s=2.0), model=model)
    recorder.join()
    assert messages == [] and summary.frames_timed_out == 0
    assert summary.frames_series_only >= 1 and summary.run.frames + summary.frames_series_only == N
    got = distances(rec)
    assert sorted(got) == list(range(N))
    for k in range(N):
        assert got[k] == pytest.approx(float(extracted[k]["distance_m"]) * 1000, abs=1e-9)
    want = ensemble.predict_proba(np.array([float(extracted[k]["signal"]) for k in range(N)]))
    posterior = rec.scalars(rerun_log.ENTITY_SERIES_POSTERIOR)
    assert sorted(posterior) == list(range(N))
    np.testing.assert_allclose([posterior[k] for k in range(N)], want, rtol=0, atol=1e-12)
    assert len(set(np.round(want, 3))) > 1  # the posterior moves
    whole = rec.frames(rerun_log.ENTITY_DEPTH_IMAGE, "DepthImage:buffer")
    assert len(whole) == summary.run.frames and (N - 1) in whole  # the newest is shown whole
    assert sorted(rec.frames(rerun_log.ENTITY_SERIES_LAG, "Scalars:scalars")) == whole


def test_stems_out_of_sequence_are_found_by_listing_once_probing_stalls(finished, tmp_path):
    """Probing finds the next three numbers; a larger gap, a stem that grows a digit or one in another
    naming is found by listing left/ once probing has found nothing for ``rescan_s``."""
    dst = tmp_path / "live"
    writer = Writer(finished, dst, frames=0)
    writer.frames, writer.fps = 3, 1e6
    writer.run()  # 000000 .. 000002, there at the start
    follower = SessionFollower(dst, FollowParams(from_start=True, rescan_s=0.2, settle_s=0.0))

    def put(k: int, stem: str) -> None:
        for folder in writer.folders:
            (source,) = (finished / folder).glob(f"{k:06d}.*")
            writer.put(source, dst / folder / f"{stem}{source.suffix}")
        writer.append("frames.csv", f"{stem},{10 + k:.1f}")

    assert [index for index, _ in follower.poll()] == [0, 1, 2]
    put(3, "000009")  # six numbers ahead: not probed
    put(4, "1000000")  # another width
    assert follower.poll() == []
    time.sleep(0.25)
    arrived = follower.poll()
    assert [follower.session.stems[index] for index, _ in arrived] == ["000009", "1000000"]
    put(5, "000004")  # before the last frame taken: never taken
    time.sleep(0.25)
    assert follower.poll() == [] and follower.poll() == []
