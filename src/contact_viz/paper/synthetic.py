"""The synthetic study of scripts/demo.sh: ``cup`` training sessions (seeds 0..K-1) and one test
session per phantom (seed 100 + the phantom's index in ``synth.PHANTOMS``), with its split file."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

from contact_viz.paper.profiles import StudyProfile
from contact_viz.paper.study import CATEGORIES, HeldOutEntry, Split, write_split
from contact_viz.params import to_dict

log = logging.getLogger(__name__)
PHANTOM_CATEGORY = {"cup": CATEGORIES[0], "kidney": CATEGORIES[1], "liver": CATEGORIES[1], "glove": CATEGORIES[2]}
TEST_SEED_BASE = 100  # synthetic test seeds: 100 + index of the phantom in synth.PHANTOMS (training: 0..K-1)
SPLIT_FILE = "split.json"  # name of the split file written beside a generated synthetic study


def synthetic_study(directory: Path, profile: StudyProfile) -> tuple[Path, Path, list[dict]]:
    """Generate (or reuse) the synthetic study; returns (sessions folder, split file, session specs).

    Sessions already in ``directory/sessions`` with the same generator settings are reused."""
    from contact_viz.synth import PHANTOMS, SynthParams, generate_session

    sessions_dir = directory / "sessions"
    specs = [{"session": f"cup_train_{k}", "phantom": "cup", "seed": k} for k in range(profile.n_train)]
    specs += [{"session": f"{phantom}_test", "phantom": phantom, "seed": TEST_SEED_BASE + PHANTOMS.index(phantom),
               "category": PHANTOM_CATEGORY[phantom]} for phantom in profile.test_phantoms]
    for spec in specs:
        params = SynthParams(phantom=spec["phantom"], frames=profile.synth_frames, seed=spec["seed"],
                             width=profile.synth_width, height=profile.synth_height, fps=profile.synth_fps)
        spec["synth_params"] = to_dict(params)
        out = sessions_dir / spec["session"]
        marker = out / "session.json"  # written last by generate_session: the completion marker
        wanted = json.loads(json.dumps(spec["synth_params"]))  # tuples as JSON lists, as session.json holds them
        if marker.is_file() and json.loads(marker.read_text()).get("generator") == wanted:
            continue
        start = time.perf_counter()
        generate_session(out, params, overwrite=True)
        log.info(f"  generated {out} ({profile.synth_frames} frames, {time.perf_counter() - start:.1f} s)")
    split = Split(train=tuple(s["session"] for s in specs if "category" not in s),
                  test=tuple(HeldOutEntry(s["session"], s["category"]) for s in specs if "category" in s))
    split_path = directory / SPLIT_FILE
    write_split(split_path, split)
    return sessions_dir, split_path, specs
