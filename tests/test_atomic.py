"""atomic_write: all or nothing under the final name."""

from __future__ import annotations

import os
import stat

import pytest

from contact_viz.io.atomic import atomic_write


def test_replaces_only_on_success(tmp_path):
    target = tmp_path / "out.csv"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_write(target) as handle:
            handle.write("half of the new conte")
            raise RuntimeError("interrupted")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.csv"]  # no temporary left behind
    with atomic_write(target) as handle:
        handle.write("new")
    assert target.read_text() == "new"


def test_creates_parent_and_uses_normal_permissions(tmp_path):
    target = tmp_path / "a" / "b" / "out.json"
    with atomic_write(target) as handle:
        handle.write("{}")
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~umask


def test_a_zombie_writer_counts_as_gone(tmp_path):
    """A killed writer not yet reaped (a zombie: in a container whose init does not reap) writes nothing more:
    its staging file is swept, while a live process's is kept."""
    import subprocess
    import time

    from contact_viz.io.atomic import sweep_stale

    out = tmp_path / "features.csv"
    zombie = subprocess.Popen(["true"])
    live = subprocess.Popen(["sleep", "30"])
    try:
        time.sleep(0.3)  # `true` has exited; not waited for, it stays a zombie
        dead_file = tmp_path / f".features.csv.{zombie.pid}-1.tmp"
        live_file = tmp_path / f".features.csv.{live.pid}-2.tmp"
        dead_file.write_text("x")
        live_file.write_text("y")
        assert sweep_stale(out) == [dead_file]
        assert live_file.exists() and not dead_file.exists()
    finally:
        live.kill()
        live.wait()
        zombie.wait()
