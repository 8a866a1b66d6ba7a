"""`contact-viz import` and `contact-viz depth` from the command line, then `extract` on the result."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from contact_viz.io.session import open_session
from contact_viz.synth import SynthParams, generate_session

sys.path.insert(0, str(Path(__file__).parent))
from test_importers import listing, make_dvrk  # noqa: E402  (the importer tests' layout builder)

CLI = [sys.executable, "-m", "contact_viz.cli"]


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *args], capture_output=True, text=True)


def test_import_dvrk_then_the_reader_says_what_is_missing(tmp_path):
    src = tmp_path / "recording"
    make_dvrk(src)
    before = listing(src)
    out = tmp_path / "session"
    done = run("import", "dvrk", str(src), str(out))
    assert done.returncode == 0, done.stderr
    assert "masks" in done.stdout  # says which folders are still to be filled
    assert listing(src) == before  # the source is untouched
    assert (out / "frames.csv").exists() and (out / "force.csv").exists()
    done = run("extract", str(out), "-o", str(tmp_path / "f.csv"))
    assert done.returncode == 2
    assert "masks" in done.stderr and "Traceback" not in done.stderr


def test_import_rejects_an_unknown_kind(tmp_path):
    done = run("import", "nonsense", str(tmp_path), str(tmp_path / "out"))
    assert done.returncode == 2 and "dvrk" in done.stderr


@pytest.fixture(scope="module")
def stereo_only(tmp_path_factory) -> Path:
    """A synthetic session with its depth/ removed: only the stereo pair is left."""
    root = tmp_path_factory.mktemp("stereo")
    full = root / "full"
    generate_session(full, SynthParams(phantom="cup", frames=6, seed=5, width=320, height=180))
    pair = root / "pair"
    shutil.copytree(full, pair)
    shutil.rmtree(pair / "depth")
    return pair


def test_depth_command_precomputes_sgbm_outside_the_session(stereo_only, tmp_path):
    before = listing(stereo_only)
    cache = tmp_path / "cache"
    out = tmp_path / "depth_out"
    done = run("depth", str(stereo_only), "--cache-dir", str(cache), "-o", str(out))
    assert done.returncode == 0, done.stderr
    assert listing(stereo_only) == before
    files = sorted(out.glob("*.npy"))
    assert len(files) == 6
    # Against the generator's true depth: SGBM on the synthetic pair is within a few mm where valid.
    truth = np.load(stereo_only.parent / "full" / "depth" / files[0].name)
    sgbm = np.load(files[0])
    both = (truth > 0) & np.isfinite(sgbm) & (sgbm > 0)
    assert both.mean() > 0.5
    assert np.median(np.abs(sgbm[both] - truth[both])) < 0.003
    # extract then reads the cached depth (the session says where its depth came from).
    session = open_session(stereo_only, cache_dir=cache)
    assert session.depth_source == "sgbm"
    done = run("extract", str(stereo_only), "--cache-dir", str(cache), "-o", str(tmp_path / "f.csv"))
    assert done.returncode == 0, done.stderr
    assert "sgbm" in done.stderr.lower()
