"""A synthetic session is what it was: the same seed and options make the same session, within what
another processor changes (docs/session.md, "What --seed promises").

The tables (force.csv, truth.csv, labels.csv, K.txt) come from this package's own arithmetic on
seeded random numbers: every number must equal the reference to 1e-9 relative (they print the same
on every processor measured). The rendered layers come from the ray caster (open3d's Embree), OpenCV
and NumPy, whose last bits depend on the processor's vector instructions; they are compared with
stated tolerances, measured between this AVX-512 machine and an emulated AVX2-only processor
(``qemu-x86_64 -cpu Haswell-v4``) and with NumPy's and OpenCV's wider paths switched off:

* depth: equally valid on all but ``MAX_FLIPPED`` of the pixels, within ``DEPTH_REL`` relative where
  both are valid (measured: 3e-7, a few float32 ulps);
* left and right images (decoded): within 1 grey level on all but ``MAX_OFF_1`` of the pixels and
  within 8 on all but ``MAX_OFF_8`` (measured: 2 grey levels on 0.002%);
* masks: the same object id on all but ``MAX_FLIPPED`` of the pixels (measured: identical).

The reference holds, for three sessions of the generator's defaults, the tables and session.json
whole and two frames (middle, last) sampled on a grid: depth and images every 4th pixel, masks
whole. ``python tests/test_synth_reference.py --write`` makes it again (after a deliberate
change of the generator: say so in the commit). ``scripts/test.sh`` runs this module a second time
with NumPy's and OpenCV's wider vector paths switched off, and once more on an emulated AVX2-only
processor where qemu-user is installed (the ray caster's paths cannot be switched any other way).
"""

from __future__ import annotations

import csv
import io
import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from contact_viz.synth import SynthParams, generate_session
from contact_viz.synth.faults import read_mask_ids

REFERENCE = Path(__file__).resolve().parent / "data" / "synth_reference.npz"
# name -> phantom, seed, frames, width, height (contact-viz synth NAME --phantom P --seed S --frames N --size WxH)
SESSIONS = {
    "ref-cup": ("cup", 5, 20, 320, 180),
    "ref-glove": ("glove", 5, 20, 320, 180),
    "ref-kidney": ("kidney", 2, 12, 240, 136),
}
TABLES = ("K.txt", "force.csv", "truth.csv", "labels.csv")
DEPTH_STEP, IMAGE_STEP = 4, 4  # the reference samples depth and images every n-th pixel, px
DEPTH_REL = 1e-5  # depth where both are valid: relative error at most this, -
MAX_FLIPPED = 0.001  # share of pixels whose depth validity or mask id may differ, -
MAX_OFF_1, MAX_OFF_8 = 0.005, 0.001  # share of image pixels more than 1 / 8 grey levels off, -
TABLE_REL = 1e-9  # numbers of the tables: relative error at most this, -


def sampled_frames(n: int) -> tuple[int, ...]:
    return (n // 2, n - 1)


def generate(name: str, out: Path) -> Path:
    phantom, seed, frames, width, height = SESSIONS[name]
    return generate_session(out / name, SynthParams(phantom=phantom, seed=seed, frames=frames, width=width,
                                                    height=height))


def _image(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image is not None, path
    return image


def snapshot(session: Path, name: str) -> dict[str, np.ndarray]:
    """What the reference keeps of a session: tables, generator options, sampled frames."""
    out = {}
    for table in TABLES:
        if (session / table).exists():
            out[f"{name}/{table}"] = np.frombuffer((session / table).read_bytes(), np.uint8)
    generator = json.loads((session / "session.json").read_text())["generator"]
    out[f"{name}/generator"] = np.frombuffer(json.dumps(generator).encode(), np.uint8)
    stems = sorted((p.stem for p in (session / "left").iterdir()), key=int)
    for i in sampled_frames(len(stems)):
        stem = stems[i]
        out[f"{name}/depth/{stem}"] = np.load(session / "depth" / f"{stem}.npy")[::DEPTH_STEP, ::DEPTH_STEP]
        for side in ("left", "right"):
            out[f"{name}/{side}/{stem}"] = _image(next((session / side).glob(f"{stem}.*")))[::IMAGE_STEP, ::IMAGE_STEP]
        out[f"{name}/masks/{stem}"] = read_mask_ids(session / "masks" / f"{stem}.png")[0]
    return out


def _numbers(text: str) -> list[list[str]]:
    return [row for row in csv.reader(io.StringIO(text.replace(" ", ",")))]


def tables_differ(reference: str, now: str) -> str | None:
    """Where two tables (CSV, or K.txt's space-separated lines) differ beyond TABLE_REL; None if they do not."""
    a, b = _numbers(reference), _numbers(now)
    if len(a) != len(b):
        return f"{len(a)} rows, now {len(b)}"
    for r, (ra, rb) in enumerate(zip(a, b)):
        if len(ra) != len(rb):
            return f"row {r}: {len(ra)} cells, now {len(rb)}"
        for x, y in zip(ra, rb):
            if x == y:
                continue
            try:
                fx, fy = float(x), float(y)
            except ValueError:
                return f"row {r}: {x!r}, now {y!r}"
            if not math.isclose(fx, fy, rel_tol=TABLE_REL, abs_tol=1e-12):
                return f"row {r}: {x}, now {y}"
    return None


@pytest.fixture(scope="module")
def reference() -> dict[str, np.ndarray]:
    with np.load(REFERENCE) as data:
        return {key: data[key] for key in data.files}


@pytest.mark.generated_data
@pytest.mark.parametrize("name", list(SESSIONS))
def test_a_synthetic_session_is_its_reference_within_the_stated_tolerances(name, reference, tmp_path):
    now = snapshot(generate(name, tmp_path), name)
    mine = {key for key in reference if key.startswith(f"{name}/")}
    assert set(now) == mine, sorted(set(now) ^ mine)
    for table in TABLES:
        key = f"{name}/{table}"
        if key in mine:
            problem = tables_differ(reference[key].tobytes().decode(), now[key].tobytes().decode())
            assert problem is None, f"{table}: {problem}"
    generator = json.loads(now[f"{name}/generator"].tobytes())
    for option, value in json.loads(reference[f"{name}/generator"].tobytes()).items():
        assert generator[option] == value, option  # options added since keep their defaults out of this
    for key in sorted(mine):
        kind = key.split("/")[1]
        ref, got = reference[key], now[key]
        assert ref.shape == got.shape, key
        if kind == "depth":
            valid_ref, valid_now = ref > 0, got > 0
            assert (valid_ref != valid_now).mean() <= MAX_FLIPPED, key
            both = valid_ref & valid_now
            rel = np.abs(got[both].astype(np.float64) - ref[both]) / ref[both]
            assert rel.max(initial=0.0) <= DEPTH_REL, f"{key}: relative error {rel.max():.2g}"
        elif kind == "masks":
            assert (ref != got).mean() <= MAX_FLIPPED, key
        elif kind in ("left", "right"):
            off = np.abs(got.astype(np.int16) - ref).max(axis=-1)
            assert (off > 1).mean() <= MAX_OFF_1 and (off > 8).mean() <= MAX_OFF_8, \
                f"{key}: {(off > 1).mean():.3%} of the pixels more than 1 grey level off, {(off > 8).mean():.3%} more than 8"


def test_the_tolerances_catch_a_change():
    """Each comparison fails on a change one step beyond its tolerance (the test above can fail)."""
    assert tables_differ("a,b\n1,0.5\n", "a,b\n1,0.5000000000001\n") is None
    assert tables_differ("a,b\n1,0.5\n", "a,b\n1,0.50001\n") == "row 1: 0.5, now 0.50001"
    assert tables_differ("0.1 0 1\n", "0.1 0 1\n0.005\n") == "1 rows, now 2"
    depth = np.full((10, 10), 0.09, np.float32)
    changed = depth * np.float32(1 + 3 * DEPTH_REL)
    assert (np.abs(changed.astype(np.float64) - depth) / depth).max() > DEPTH_REL


if __name__ == "__main__" and "--write" in sys.argv:
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        arrays = {}
        for session_name in SESSIONS:
            arrays.update(snapshot(generate(session_name, Path(tmp)), session_name))
    REFERENCE.parent.mkdir(exist_ok=True)
    np.savez_compressed(REFERENCE, **arrays)
    print(f"{REFERENCE}: {len(arrays)} arrays, {REFERENCE.stat().st_size / 1e3:.0f} kB")
