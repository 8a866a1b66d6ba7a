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
