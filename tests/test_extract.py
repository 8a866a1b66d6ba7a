"""`extract` on synthetic sessions: the distance tracks the generator's true gap."""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from contact_viz.pipeline.extract import (FEATURE_COLUMNS, REASON_BAD_FRAME, TOOL_COLUMN, BadFrameWarning, extract_features,
                                 iter_frame_results, write_features)
from contact_viz.params import PatchParams, to_dict
from contact_viz.geometry.patch import compute_patch
from contact_viz.io.session import open_session
from contact_viz.synth import SynthParams, generate_session

CLI = [sys.executable, "-m", "contact_viz.cli"]


@pytest.fixture(scope="module")
def cup_session(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("sessions") / "cup"
    generate_session(out, SynthParams(phantom="cup", frames=90, seed=3, width=480, height=270))
    return out


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def listing(root: Path) -> list[tuple[str, int, int]]:
    return sorted((str(p.relative_to(root)), p.stat().st_size, p.stat().st_mtime_ns)
                  for p in root.rglob("*"))


def test_distance_tracks_true_gap(cup_session):
    session = open_session(cup_session)
    rows = extract_features(session)
    truth = read_csv(cup_session / "truth.csv")
    assert [int(r["frame"]) for r in rows] == [int(t["frame"]) for t in truth]
    distance = np.array([float(r["distance_m"]) if r["distance_m"] else np.nan for r in rows])
    gap = np.array([float(t["gap_m"]) for t in truth])
    assert np.isfinite(distance).mean() > 0.9
    in_contact = gap == 0
    hovering = gap > 0.004
    assert in_contact.sum() >= 5 and hovering.sum() >= 5
    ok = np.isfinite(distance)
    # In contact the distance is near 0: what remains is the depth offset between the visible top
    # of the tool's jaws and the tissue beside them, about a jaw radius (a few mm).
    contact_distance = np.abs(distance[in_contact & ok])
    assert np.median(contact_distance) < 0.0035
    # Hovering, it follows the gap: the depth difference is measured along the viewing ray, which
    # meets the tissue behind the tip obliquely, so it exceeds the Euclidean gap by a bounded factor.
    hover_ratio = distance[hovering & ok] / gap[hovering & ok]
    assert 0.8 < np.median(hover_ratio) < 3.0
    assert np.max(contact_distance) < np.min(distance[hovering & ok])
    rank = lambda v: np.argsort(np.argsort(v))
    assert np.corrcoef(rank(distance[ok]), rank(gap[ok]))[0, 1] > 0.9  # Spearman
    # The signal separates contact from hovering.
    signal = np.array([float(r["signal"]) if r["signal"] else np.nan for r in rows])
    assert np.nanmin(signal[in_contact]) > np.nanmax(signal[hovering])


def test_rows_agree_with_compute_patch(cup_session):
    session = open_session(cup_session)
    params = PatchParams()
    rows = extract_features(session, params, indices=[0, 10, 20])
    for row, frame in zip(rows, session.iter_frames(layers=("mask", "depth"), indices=[0, 10, 20])):
        direct = compute_patch(frame.depth_m, frame.tool_mask, params)
        assert row["frame"] == frame.stem
        assert set(row) == {*FEATURE_COLUMNS, TOOL_COLUMN}
        if direct.found:
            assert float(row["distance_m"]) == direct.distance_m
            assert (int(row["patch_x"]), int(row["patch_y"])) == direct.center_xy
            assert float(row["signal"]) == pytest.approx(-math.log10(max(abs(direct.distance_m), 1e-4)))
        assert int(row["tool_area_px"]) == int(frame.tool_mask.sum())
        assert float(row["force_n"]) == pytest.approx(float(session.force_n[frame.index]))


def test_bad_frame_is_skipped_with_warning_and_run_goes_on(cup_session, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(cup_session, broken)
    stems = sorted(p.stem for p in (broken / "left").iterdir())
    (broken / "depth" / f"{stems[5]}.npy").unlink()
    (broken / "masks" / f"{stems[7]}.png").write_bytes(b"not a png at all")
    session = open_session(broken)
    with pytest.warns(UserWarning) as record:
        results = list(iter_frame_results(session, indices=range(4, 10)))
    messages = [str(w.message) for w in record]
    assert any(stems[5] in m and "depth" in m for m in messages)
    assert any(stems[7] in m and "mask" in m for m in messages)
    assert [r.patch is None for r in results] == [False, True, False, True, False, False]
    with pytest.warns(BadFrameWarning):
        rows = extract_features(session, indices=range(4, 10))
    assert [r["reason"] == REASON_BAD_FRAME for r in rows] == [False, True, False, True, False, False]
    assert stems[5] in rows[1]["detail"]


def test_cli_extract_writes_features_and_config(cup_session, tmp_path):
    before = listing(cup_session)
    out = tmp_path / "out" / "features.csv"
    done = subprocess.run([*CLI, "extract", str(cup_session), "-o", str(out)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    rows = read_csv(out)
    assert len(rows) == 90 and list(rows[0]) == list(FEATURE_COLUMNS)
    config = json.loads(out.with_name("features.csv.json").read_text())
    assert config["patch_params"]["n1"] == 31 and config["label_params"]["contact_force_n"] == 2.0
    assert listing(cup_session) == before  # the session directory is untouched
    assert not [p for p in out.parent.iterdir() if p.name.endswith(".tmp")]
    # Labels follow the force threshold.
    for r in rows:
        if r["force_n"]:
            assert int(r["label"]) == int(float(r["force_n"]) >= 2.0)


def test_cli_extract_refuses_to_write_into_the_session(cup_session):
    done = subprocess.run([*CLI, "extract", str(cup_session), "-o", str(cup_session / "f.csv")],
                          capture_output=True, text=True)
    assert done.returncode == 2
    assert "inside the session directory" in done.stderr
    assert not (cup_session / "f.csv").exists()


def test_cli_extract_reports_a_malformed_session_in_one_line(tmp_path):
    done = subprocess.run([*CLI, "extract", str(tmp_path / "nowhere")], capture_output=True, text=True)
    assert done.returncode == 2
    assert "nowhere" in done.stderr and "Traceback" not in done.stderr


def test_extract_does_not_import_heavy_modules(cup_session, tmp_path):
    code = (
        "import sys\n"
        "from contact_viz.cli import app\n"
        f"sys.argv = ['contact-viz', 'extract', {str(cup_session)!r}, '-o', {str(tmp_path / 'f.csv')!r}]\n"
        "try:\n    app()\nexcept SystemExit as e:\n    assert not e.code, e.code\n"
        "heavy = sorted(m for m in ('open3d', 'rerun', 'torch', 'sklearn', 'matplotlib') if m in sys.modules)\n"
        "print('HEAVY', heavy)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env={**os.environ, "COLUMNS": "100"})
    assert done.returncode == 0, done.stderr
    assert "HEAVY []" in done.stdout


def test_read_features_config_round_trip_and_errors(tmp_path):
    from contact_viz.pipeline.extract import read_features_config

    params = PatchParams(n2=15, tau_tool=20)
    path = tmp_path / "features.csv"
    config = {"session": {"name": "cup-1"}, "patch_params": to_dict(params)}
    write_features([], path, config)
    assert read_features_config(path) == (params, "cup-1")
    (tmp_path / "features.csv.json").write_text('{"patch_params": {}}')
    with pytest.raises(ValueError, match=r"features.csv.json: expected the session's name"):
        read_features_config(path)
    (tmp_path / "features.csv.json").unlink()
    with pytest.raises(ValueError, match=r"features.csv.json: missing"):
        read_features_config(path)


def test_processes_give_the_same_rows_and_warnings(cup_session, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(cup_session, broken)
    stems = sorted(p.stem for p in (broken / "left").iterdir())
    (broken / "depth" / f"{stems[30]}.npy").unlink()
    session = open_session(broken)
    with pytest.warns(BadFrameWarning) as serial_warnings:
        serial = extract_features(session)
    # A slow progress callback keeps the caller busy, so that the spawned worker takes chunks too.
    done = []
    with pytest.warns(BadFrameWarning) as shared_warnings:
        shared = extract_features(session, processes=2, progress=lambda n: (done.append(n), time.sleep(0.05)))
    assert shared == serial
    assert [str(w.message) for w in shared_warnings] == [str(w.message) for w in serial_warnings]
    assert done[-1] == len(session)
    with pytest.warns(BadFrameWarning):
        subset = extract_features(session, indices=[40, 3, 30], processes=2)
    assert [r["frame"] for r in subset] == [stems[40], stems[3], stems[30]]
    assert subset == [serial[40], serial[3], serial[30]]
    with pytest.raises(IndexError, match="out of range"):
        extract_features(session, indices=[0, 90], processes=2)


def test_cli_extract_processes_option(cup_session, tmp_path):
    outputs = []
    for processes in ("1", "2"):
        out = tmp_path / f"p{processes}.csv"
        done = subprocess.run([*CLI, "extract", str(cup_session), "-o", str(out), "--processes", processes],
                              capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        outputs.append(out.read_text())
    assert outputs[0] == outputs[1]
    done = subprocess.run([*CLI, "extract", str(cup_session), "-o", str(tmp_path / "x.csv"), "--processes", "0"],
                          capture_output=True, text=True)
    assert done.returncode == 2 and "processes" in done.stderr


def test_rows_from_depth_rows_equal_rows_from_whole_frames(tmp_path):
    """extract's tasks read each depth map only in the rows around the tool; their rows equal
    those computed on whole frames (empty masks, tools at the borders, odd rows, PNG depth,
    unreadable files included)."""
    import cv2

    from contact_viz.pipeline.extract import FeatureRows, result_rows

    root, height, width = tmp_path / "s", 97, 131
    rng = np.random.default_rng(7)
    for sub in ("left", "masks", "depth"):
        (root / sub).mkdir(parents=True)
    (root / "K.txt").write_text("100 0 65 0 100 48 0 0 1\n0.005\n")
    (root / "force.csv").write_text("frame,fx,fy,fz\n" + "".join(f"{i},0,0,{i % 4}\n" for i in range(12)))
    yy, xx = np.mgrid[0:height, 0:width]
    for i in range(12):
        tool = np.zeros((height, width), np.uint8)
        if i == 0:
            pass  # empty mask
        elif i == 1:
            tool[: 20 + i] = 1  # touches the top border across the image
        elif i == 2:
            cv2.circle(tool, (60, height - 5), 25, 1, -1)  # touches the bottom border
        else:
            cv2.line(tool, (int(rng.integers(0, width)), int(rng.integers(0, height))),
                     (int(rng.integers(0, width)), int(rng.integers(0, height))), 1, int(rng.integers(5, 25)))
        cv2.imwrite(str(root / "masks" / f"{i}.png"), tool * 255)
        depth = (0.08 + 0.005 * np.sin(xx / 9) + rng.normal(0, 0.0005, (height, width))).astype(np.float32)
        depth[tool == 1] -= rng.uniform(0, 0.01)
        depth[rng.random((height, width)) < 0.05] = np.nan
        if i == 4:
            cv2.imwrite(str(root / "depth" / f"{i}.png"), np.nan_to_num(depth * 1000).astype(np.uint16))
        elif i != 9:  # frame 9 has no depth file
            np.save(root / "depth" / f"{i}.npy", depth)
        cv2.imwrite(str(root / "left" / f"{i}.png"), np.zeros((height, width, 3), np.uint8))
    (root / "masks" / "6.png").write_bytes(b"broken")
    session = open_session(root)
    small = PatchParams(n1=11, n2=5, tau_tool=5, tau_patch=3, erosion_px=1.0, ring_px=1.0, band_min_px=1.0, band_max_px=2.0)
    for params in (PatchParams(), small):
        task = FeatureRows(session, params, tuple(range(len(session))))
        with pytest.warns(BadFrameWarning):
            whole = [row for r in iter_frame_results(session, params) for row in result_rows(session, r)]
        assert [row for rows in task(0, len(session)) for row in rows] == whole
        assert [r["reason"] for r in whole][:3] == ["empty_mask", whole[1]["reason"], whole[2]["reason"]]
        assert whole[6]["reason"] == whole[9]["reason"] == REASON_BAD_FRAME
        assert sum(r["distance_m"] != "" for r in whole) >= 5


def _long_session(tmp_path: Path, n: int = 6000) -> Path:
    """A 960x540 session of the same frame linked ``n`` times: an extract of several seconds."""
    import cv2

    root, height, width = tmp_path / "long", 540, 960
    for sub in ("left", "masks", "depth"):
        (root / sub).mkdir(parents=True)
    (root / "K.txt").write_text("500 0 480 0 500 270 0 0 1\n0.005\n")
    tool = np.zeros((height, width), np.uint8)
    cv2.line(tool, (0, 100), (500, 300), 1, 60)
    cv2.imwrite(str(tmp_path / "mask.png"), tool * 255)
    np.save(tmp_path / "depth.npy", np.full((height, width), 0.08, np.float32))
    cv2.imwrite(str(tmp_path / "left.png"), np.zeros((height, width, 3), np.uint8))
    for i in range(n):
        for sub, name in (("masks", "mask.png"), ("depth", "depth.npy"), ("left", "left.png")):
            (root / sub / f"{i}{Path(name).suffix}").symlink_to(tmp_path / name)
    (root / "force.csv").write_text("frame,fx,fy,fz\n" + "".join(f"{i},0,0,1\n" for i in range(n)))
    return root


def test_ctrl_c_stops_every_process_and_writes_nothing(tmp_path):
    """Ctrl-C in a terminal reaches the command and its workers: all stop, no features file."""
    import signal

    root = _long_session(tmp_path)
    out = tmp_path / "out" / "features.csv"
    # SIGINT as a terminal leaves it: a test run started in the background (`cmd &` in a script)
    # inherits SIGINT ignored, and an ignored signal stays ignored across exec
    run = subprocess.Popen([*CLI, "extract", str(root), "-o", str(out), "--processes", "2"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True,
                           preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    time.sleep(2.0)  # started, workers running
    assert run.poll() is None, run.communicate()
    os.killpg(run.pid, signal.SIGINT)  # what a terminal does: the whole process group
    run.communicate(timeout=30)
    assert run.returncode == 130  # click exits with 128 + SIGINT on Ctrl-C
    assert not out.exists() and not out.with_name("features.csv.json").exists()
    time.sleep(0.5)
    running = [p for p in Path("/proc").iterdir() if p.name.isdigit() and _running_in_group(p, run.pid)]
    assert running == []


def test_a_killed_worker_is_one_error_line(tmp_path):
    """A worker killed mid-run (e.g. by the out-of-memory killer): one line, no file, no process left."""
    import signal

    root = _long_session(tmp_path)
    out = tmp_path / "out" / "features.csv"
    run = subprocess.Popen([*CLI, "extract", str(root), "-o", str(out), "--processes", "2"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    time.sleep(3.0)  # started, workers running
    assert run.poll() is None, run.communicate()
    workers = [int(p.name) for p in Path("/proc").iterdir() if p.name.isdigit() and _running_in_group(p, run.pid)
               and b"spawn_main" in (p / "cmdline").read_bytes()]
    assert workers
    os.kill(workers[0], signal.SIGKILL)
    _, stderr = run.communicate(timeout=60)
    assert run.returncode == 2, stderr
    assert "error: a worker process died" in stderr and "Traceback" not in stderr
    assert not out.exists() and not out.with_name("features.csv.json").exists()
    time.sleep(0.5)
    assert [p for p in Path("/proc").iterdir() if p.name.isdigit() and _running_in_group(p, run.pid)] == []


def _running_in_group(proc: Path, group: int) -> bool:
    """Whether /proc/PID ``proc`` is a process of process group ``group`` that has not exited
    (an exited one waiting to be reaped by init, a zombie, does not count)."""
    try:
        state, _, pgrp = (proc / "stat").read_text().rsplit(")", 1)[1].split()[:3]
    except (OSError, ValueError):
        return False
    return int(pgrp) == group and state != "Z"


def test_processes_with_sgbm_depth(tmp_path):
    """A session whose depth SGBM computes (no depth/) is shared by processes too: the session,
    its matcher settings and cache travel to the workers, and the rows are the same."""
    generate_session(tmp_path / "s", SynthParams(phantom="cup", frames=6, seed=1, width=320, height=180))
    shutil.rmtree(tmp_path / "s" / "depth")
    session = open_session(tmp_path / "s", cache_dir=tmp_path / "cache")
    assert session.depth_source == "sgbm"
    shared = extract_features(session, processes=2)
    assert shared == extract_features(session)
    assert sum(r["distance_m"] != "" for r in shared) >= 4
