"""The split file of a study: which sessions train the models and which are held out, in what category.

The paper's protocol (Sec. 3) trains on some sessions (leave-one-session-out) and tests on others
ordered by domain shift. A split file says which is which, with session paths relative to a
sessions folder, test sessions in table order:

    {"train": ["cup_1", "cup_2", "cup_3", "cup_4", "cup_5", "cup_6"],
     "test": [{"session": "cup_7",    "category": "same phantom and task"},
              {"session": "kidney_1", "category": "new phantom"},
              {"session": "liver_1",  "category": "new phantom"},
              {"session": "glove_1",  "category": "new phantom and task"}]}

"train" needs at least two sessions; "category" is one of CATEGORIES.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from contact_viz.io.jsonfile import read_json, write_json

CATEGORIES = ("same phantom and task", "new phantom", "new phantom and task")  # test session categories, paper order


@dataclass(frozen=True)
class HeldOutEntry:
    """One held-out session of the split."""

    session: str  # path relative to the sessions folder
    category: str  # one of CATEGORIES


@dataclass(frozen=True)
class Split:
    """Which sessions train and which test, as read from a split file."""

    train: tuple[str, ...]  # training session paths, relative to the sessions folder
    test: tuple[HeldOutEntry, ...]  # held-out sessions in table order


def read_split(path: Path) -> Split:
    """Read and check a split file; any problem is one ValueError naming the file and what was expected."""
    expected = ('expected JSON {"train": [session, ...], "test": [{"session": ..., "category": ...}, ...]}')
    data = read_json(path, expected, missing=f"split file not found; {expected}")
    if not isinstance(data, dict) or set(data) != {"train", "test"}:
        found = sorted(data) if isinstance(data, dict) else type(data).__name__
        raise ValueError(f"{path}: {expected}; found {found}")
    train, test = data["train"], data["test"]
    if not isinstance(train, list) or len(train) < 2 or not all(isinstance(s, str) and s for s in train):
        raise ValueError(f"{path}: \"train\": expected a list of at least 2 session names (leave-one-session-out)")
    if not isinstance(test, list) or not test:
        raise ValueError(f"{path}: \"test\": expected a non-empty list of {{\"session\", \"category\"}} objects")
    entries = []
    for i, item in enumerate(test):
        if not isinstance(item, dict) or set(item) != {"session", "category"} or not isinstance(item["session"], str):
            raise ValueError(f"{path}: test[{i}]: expected {{\"session\": name, \"category\": one of "
                             f"{list(CATEGORIES)}}}")
        if item["category"] not in CATEGORIES:
            raise ValueError(f"{path}: test[{i}] ({item['session']}): category {item['category']!r}: "
                             f"expected one of {list(CATEGORIES)}")
        entries.append(HeldOutEntry(item["session"], item["category"]))
    names = list(train) + [e.session for e in entries]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(f"{path}: every session must appear once in the split, repeated: {repeated}")
    return Split(tuple(train), tuple(entries))


def write_split(path: Path, split: Split) -> None:
    """Write ``split`` as a split file (atomically), in the form :func:`read_split` reads."""
    data = {"train": list(split.train), "test": [{"session": e.session, "category": e.category} for e in split.test]}
    write_json(path, data)
