"""The split file of a study: reading, checking and writing."""

from __future__ import annotations

import pytest

from contact_viz.paper.study import CATEGORIES, HeldOutEntry, Split, read_split, write_split


def test_split_round_trip(tmp_path):
    split = Split(train=("cup_1", "cup_2"), test=(HeldOutEntry("kidney_1", CATEGORIES[1]),
                                                  HeldOutEntry("glove_1", CATEGORIES[2])))
    path = tmp_path / "split.json"
    write_split(path, split)
    assert read_split(path) == split
    assert not list(tmp_path.glob("*.tmp"))


@pytest.mark.parametrize(("text", "message"), [
    ('{"train": ["a"], "test": [{"session": "b", "category": "new phantom"}]}', "at least 2"),
    ('{"train": ["a", "b"], "test": [{"session": "c", "category": "other"}]}', "category 'other'"),
    ('{"train": ["a", "b"], "test": [{"session": "a", "category": "new phantom"}]}', "repeated: \\['a'\\]"),
    ('{"train": ["a", "b"], "test": []}', "non-empty list"),
    ('{"train": ["a", "b"], "test": ["c"]}', "test\\[0\\]"),
    ('{"train": ["a", "b"]}', "expected JSON"),
    ("not json", "expected JSON"),
])
def test_split_file_errors_name_the_file_and_the_expectation(tmp_path, text, message):
    path = tmp_path / "split.json"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as info:
        read_split(path)
    assert str(info.value).startswith(str(path))


def test_missing_split_file(tmp_path):
    with pytest.raises(ValueError, match="split file not found"):
        read_split(tmp_path / "missing.json")
