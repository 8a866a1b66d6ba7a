"""The public API (contact_viz.__all__, docs/api.md): each name, the README's Python example and every recipe of
docs/api.md run; the debugger's recording is the same logged through log_session into a caller's stream, under a
root or not, as the CLI's; the numbers are those of the CLI's commands (computed by them, independently)."""

from __future__ import annotations

import csv
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import contact_viz as cv

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-c", "import sys; from contact_viz.cli import main; sys.exit(main())"]


def python_blocks(text: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


@pytest.fixture(scope="module")
def session_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("api") / "s"
    return cv.make_synthetic_session(out, phantom="cup", frames=24, width=640, height=360, seed=4)


def test_every_public_name_imports_and_has_a_docstring():
    import subprocess

    names = [n for n in cv.__all__ if n != "__version__"]
    for name in names:
        value = getattr(cv, name)
        assert (value.__doc__ or "").strip(), name
    # importing the package stays cheap: none of the heavy libraries come with it
    done = subprocess.run([sys.executable, "-c", "import sys, contact_viz; print(sorted(m for m in "
                           "('rerun', 'torch', 'open3d', 'cv2', 'numpy') if m in sys.modules))"],
                          capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]"
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        cv.nope  # noqa: B018


def test_api_md_names_exactly_all():
    text = (ROOT / "docs" / "api.md").read_text()
    documented = set()
    for heading in re.findall(r"^### (.+)$", text, flags=re.M):
        documented |= set(re.findall(r"`(\w+)", heading))
    assert documented == set(cv.__all__) - {"__version__"}


def test_run_frame_and_run_session_are_extracts_numbers(session_dir, tmp_path):
    out = tmp_path / "f.csv"
    subprocess.run([*CLI, "extract", str(session_dir), "-o", str(out), "--cache-dir", str(tmp_path / "c1")],
                   check=True, capture_output=True)
    with out.open() as f:
        rows = list(csv.DictReader(f))
    session = cv.open_session(session_dir, cache_dir=tmp_path / "c2")
    table = cv.run_session(session, cache_dir=tmp_path / "c2")
    assert table.column_names == list(rows[0].keys())
    assert table.num_rows == len(rows)
    extracted = np.array([float(r["distance_m"]) if r["distance_m"] else np.nan for r in rows])
    np.testing.assert_array_equal(table.column("distance_m").to_numpy(zero_copy_only=False), extracted)
    assert table.column("frame").to_pylist() == [r["frame"] for r in rows]
    frame = cv.run_frame(session, 12)
    assert frame.stem == rows[12]["frame"] and frame.distance_m == extracted[12]
    assert frame.signal == pytest.approx(-np.log10(max(abs(frame.distance_m), 1e-4)), abs=1e-12)
    x, y = frame.patch_center_xy
    assert (x, y) == (int(rows[12]["patch_x"]), int(rows[12]["patch_y"]))
    assert frame.patch[y, x] and frame.band[y, x] and not (frame.interior & frame.band).any()
    assert not (frame.ring & frame.band).any() and frame.interior.any()


def test_fit_and_evaluate_are_the_commands(tmp_path):
    paths = [cv.make_synthetic_session(tmp_path / f"cup_{s}", frames=150, width=320, height=180, seed=s)
             for s in (1, 2, 3)]
    cache = tmp_path / "cache"
    subprocess.run([*CLI, "fit", *map(str, paths[:2]), "-o", str(tmp_path / "m.json"), "--cache-dir", str(cache)],
                   check=True, capture_output=True)
    done = subprocess.run([*CLI, "evaluate", str(tmp_path / "m.json"), str(paths[2]), "--json", str(tmp_path / "e.json"),
                           "--cache-dir", str(cache)], check=True, capture_output=True, text=True)
    import json

    expected = json.loads((tmp_path / "e.json").read_text())["metrics"]
    sessions = [cv.open_session(p, cache_dir=cache) for p in paths]
    model = cv.fit(sessions[:2], cache_dir=cache)
    assert model.threshold == cv.load_model(tmp_path / "m.json").threshold
    table = cv.evaluate(model, sessions[2:], cache_dir=cache).to_pylist()
    assert [r["session"] for r in table] == ["cup_3", "Macro"]
    for row in table:
        for key in ("accuracy", "f1", "auprc"):
            assert row[key] == expected[row["session"]][key], (row["session"], key, done.stdout)
    paper = cv.fit(sessions[:2], model_kind="paper", cache_dir=cache)
    assert paper.model_kind == "paper" and model.model_kind != "paper"


def test_check_is_the_commands(session_dir, tmp_path):
    import json

    subprocess.run([*CLI, "check", str(session_dir), "--json", str(tmp_path / "c.json"), "--cache-dir",
                    str(tmp_path / "c")], check=True, capture_output=True)
    expected = json.loads((tmp_path / "c.json").read_text())["sessions"][0]
    report = cv.check(session_dir, cache_dir=tmp_path / "c")
    assert report.flagged_frames == expected["flagged_frames"]
    assert {k: v["frames"] for k, v in report.to_dict()["checks"].items()} == \
        {k: v["frames"] for k, v in expected["checks"].items()}


def outline(path: Path, root: str = "") -> tuple[dict[str, set[str]], set[int]]:
    """{entity path (without ``root``): its component columns} of a recording's data, and its frame times."""
    from rerun.chunk import RrdReader

    entities: dict[str, set[str]] = {}
    frames: set[int] = set()
    prefix = f"/{root}" if root else ""
    for chunk in RrdReader(path).stream():
        entity = str(chunk.entity_path)
        if entity.startswith("/__") or not entity.startswith(prefix):
            continue
        batch = chunk.to_record_batch()
        columns = {f.name for f in batch.schema if f.name not in chunk.timeline_names and not f.name.startswith("rerun.")
                   and f.name != "frame" and f.name != "time" and "RowId" not in f.name}
        entities.setdefault(entity[len(prefix):] or "/", set()).update(columns)
        if "frame" in chunk.timeline_names:
            frames.update(int(v) for v in batch.column("frame").to_pylist() if v is not None)
    return entities, frames


def test_log_session_is_the_debuggers_recording_under_any_root(session_dir, tmp_path):
    import rerun as rr

    cli = tmp_path / "cli.rrd"
    subprocess.run([*CLI, str(session_dir), "--save", str(cli), "--cache-dir", str(tmp_path / "c")],
                   check=True, capture_output=True)
    session = cv.open_session(session_dir, cache_dir=tmp_path / "c")
    outlines = {}
    for root in ("", "contact_viz", "a/b"):
        path = tmp_path / f"api_{root.replace('/', '_') or 'none'}.rrd"
        rec = rr.RecordingStream("mine")
        rec.save(path)
        if root:
            rec.set_time("frame", sequence=0)
            rec.log("robot/joint", rr.Scalars(1.0))  # the caller's own data beside ours
        summary = cv.log_session(rec, session, root=root or None)
        rec.flush(timeout_sec=60)
        rec.disconnect()
        assert summary.frames == len(session)
        outlines[root] = outline(path, root)
        if root:
            everything, _ = outline(path)
            assert "/robot/joint" in everything
            assert all(e.startswith(f"/{root}/") or e == "/robot/joint" for e in everything)
    expected_entities, expected_frames = outline(cli)
    assert expected_frames == set(range(len(session)))
    assert len(expected_entities) > 30
    for root, (entities, frames) in outlines.items():
        assert entities == expected_entities, root
        assert frames == expected_frames, root
    # log_frame: that frame's data only
    rec = rr.RecordingStream("mine")
    rec.save(tmp_path / "one.rrd")
    cv.log_frame(rec, session, 7, root="x")
    rec.flush(timeout_sec=60)
    rec.disconnect()
    _, frames = outline(tmp_path / "one.rrd", "x")
    assert frames == {7}


def test_log_session_touches_no_global_recording(session_dir, tmp_path):
    import rerun as rr

    assert rr.get_global_data_recording() is None
    rec = rr.RecordingStream("mine")
    rec.save(tmp_path / "r.rrd")
    cv.log_session(rec, cv.open_session(session_dir, cache_dir=tmp_path / "c"),
                   options=cv.DebuggerOptions(end=3))
    assert rr.get_global_data_recording() is None


def test_readme_python_example_runs(tmp_path):
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## From Python"):]
    (block,) = python_blocks(section[:section.index("\n## ", 3)])
    assert len(block.strip().splitlines()) == 5
    done = subprocess.run([sys.executable, "-c", block], cwd=tmp_path, capture_output=True, text=True,
                          env={**os.environ, "CONTACT_VIZ_CACHE": str(tmp_path / "cache")})
    assert done.returncode == 0, done.stderr
    rows = eval(done.stdout.strip())  # noqa: S307 (the example prints a list of dicts)
    assert [r["frame"] for r in rows] == ["000020", "000021", "000022"]
    assert all(abs(r["signal"] + np.log10(max(abs(r["distance_m"]), 1e-4))) < 1e-12 for r in rows)


def test_every_recipe_in_api_md_runs(tmp_path):
    blocks = python_blocks((ROOT / "docs" / "api.md").read_text())
    assert len(blocks) == 4
    script = "\n\n".join(blocks)
    done = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True,
                          env={**os.environ, "CONTACT_VIZ_CACHE": str(tmp_path / "cache")})
    assert done.returncode == 0, done.stderr
    change = float(re.search(r"median distance change: ([-+0-9.]+) mm", done.stdout).group(1))
    assert abs(change) < 0.05  # depth 0.5 mm further everywhere, tissue and tool alike: their difference stays
    assert (tmp_path / "s1_distance.png").stat().st_size > 10_000
    assert (tmp_path / "my_robot.rrd").stat().st_size > 100_000
    entities, _ = outline(tmp_path / "my_robot.rrd")
    assert "/robot/joint_0" in entities and "/contact_viz/series/distance" in entities
    assert not list((tmp_path / "s1").rglob("*.tmp"))
