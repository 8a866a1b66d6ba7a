"""Small JSON files: one error naming the file, atomic writes."""

from __future__ import annotations

import pytest

from contact_viz.io.jsonfile import read_json, write_json


def test_round_trip_with_final_newline_and_no_temp_file(tmp_path):
    path = tmp_path / "sub" / "a.json"
    write_json(path, {"b": [1, 2.5, None]}, indent=1)
    assert path.read_text().endswith("}\n")
    assert read_json(path, "expected x") == {"b": [1, 2.5, None]}
    assert [p.name for p in path.parent.iterdir()] == ["a.json"]


def test_errors_name_the_file(tmp_path):
    missing = tmp_path / "missing.json"
    with pytest.raises(ValueError, match=r"missing\.json: expected x \(.*No such file"):
        read_json(missing, "expected x")
    with pytest.raises(ValueError) as info:
        read_json(missing, "expected x", missing="not found; make one")
    assert str(info.value) == f"{missing}: not found; make one"
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match=r"bad\.json: expected x \(Expecting"):
        read_json(bad, "expected x", missing="unused")
    binary = tmp_path / "binary.json"
    binary.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(ValueError, match=r"binary\.json: expected x"):
        read_json(binary, "expected x")
