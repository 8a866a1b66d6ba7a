"""The not_rectified check's measurement on rectified pairs, pairs with a vertical offset shifted in, and real
da Vinci pairs rectified with their published calibration; the threshold's margins.

    python benchmarks/bench_rectification.py                 # every source found on this machine
    python benchmarks/bench_rectification.py --frames 24 --seeds 3,5

Per source it prints the vertical offset (right y - left y) that contact_viz.checks.rectification
measures: the median over every kept match of the sampled frames, the spread of the per-frame medians,
the matches kept; then the same with the right images shifted down by 1, 2 and 4 px
(contact_viz.synth.faults.shift_rows; in synthetic sessions through the ``vertical_offset`` fault kind)
and whether the check fires at DiagnosticParams.max_vertical_offset_px. Sources:

* synthetic sessions (`contact-viz synth`, rectified by construction): four phantoms at 640x360, two at
  1280x720, measured as `contact-viz check` does (contact_viz.pipeline.check.rectification_offset);
* Middlebury's motorcycle pair (skimage.data.stereo_motorcycle(), rectified);
* the SCARED keyframe of mli0603/stereo-transformer's sample data (rectified), when its mirror is here;
* the 30 da Vinci pairs of LauraCruciani/DaVinci_project in /tmp/dv (1280x960 crops [20:980, 310:1590]
  of 1080p frames, raw), rectified with cv2.stereoRectify on the 1080p geometry (the published
  CalibrationParameters.xml, its R replaced by the nearest rotation) and remapped into the crop
  (principal points shifted by -310, -20): all 30 pairs, and as `contact-viz check` reads a session of them
  (a calibration.xml for the crop, rectified on load). Skipped with one line when /tmp/dv is missing.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from contact_viz.checks.frame import shrink_grey  # noqa: E402
from contact_viz.checks.params import DiagnosticParams  # noqa: E402
from contact_viz.checks.rectification import sample_frames, vertical_offset  # noqa: E402
from contact_viz.io.calibration import rotation_deviation  # noqa: E402
from contact_viz.io.session import open_session  # noqa: E402
from contact_viz.pipeline.check import rectification_offset  # noqa: E402
from contact_viz.synth.faults import inject_fault, shift_rows  # noqa: E402

SHIFTS_PX = (1.0, 2.0, 4.0)  # vertical offsets shifted into the right images, px
DV = Path("/tmp/dv")  # the da Vinci pairs and their calibration (local only: no licence to redistribute)
DV_FRAMES = DV / "Offline" / "frame_decenti" / "frame"
CROP_X0, CROP_Y0, CROP_W, CROP_H = 310, 20, 1280, 960  # the crop [20:980, 310:1590] of 1920x1080, px
FULL_SIZE = (1920, 1080)  # the calibration's image size (width, height), px
SCARED_GIT = Path("/work/.mirror/mli0603+stereo-transformer/repo")  # bare mirror holding the SCARED keyframe
SCARED_PATH = "sample_data/SCARED/training/img_{side}/dataset_1_keyframe_1.png"


def offsets_of_pairs(pairs, params: DiagnosticParams, shift_px: float = 0.0):
    """vertical_offset over (index, left grey, right grey) at full size, shrunk as `check` shrinks them, the
    right images shifted down by ``shift_px`` first."""
    shrunk = []
    for index, left, right in pairs:
        step = max(1, -(-left.shape[1] // params.rectification_width_px))
        right = shift_rows(right, shift_px) if shift_px else right
        shrunk.append((index, shrink_grey(left, step), shrink_grey(right, step)))
    return vertical_offset(shrunk, params, scale_px=pairs[0][1].shape[0] / shrunk[0][1].shape[0])


def row(name: str, size: str, clean, shifted: list, seconds: float) -> dict:
    """Print one source's line; return its figures."""
    def cell(m) -> str:
        return "   n/a" if m is None else f"{m.offset_px:+6.2f}"

    lo, hi = clean.spread_px if clean is not None else (math.nan, math.nan)
    shifts = "  ".join(f"{cell(m)} {'fires' if m is not None and m.fired else 'quiet'}" for m in shifted)
    print(f"{name:24s} {size:>9s}  {len(clean.frames) if clean else 0:3d} {clean.matches if clean else 0:7,d}  "
          f"{cell(clean)}  [{lo:+5.2f}, {hi:+5.2f}]  {'fires' if clean is not None and clean.fired else 'quiet'}  "
          f"{shifts}  {seconds:5.1f}")
    return {"name": name, "clean": clean, "shifted": shifted}


def synth_rows(work: Path, frames: int, seeds: list[int], params: DiagnosticParams) -> list[dict]:
    from contact_viz.synth import SynthParams, generate_session

    out = []
    plans = [(phantom, 640, 360, seeds[0]) for phantom in ("cup", "kidney", "liver", "glove")]
    plans += [(phantom, 1280, 720, seeds[-1]) for phantom in ("cup", "kidney")]
    for phantom, width, height, seed in plans:
        src = work / f"{phantom}_{width}_{seed}"
        generate_session(src, SynthParams(phantom=phantom, frames=frames, seed=seed, width=width, height=height))
        t0 = time.perf_counter()
        clean = rectification_offset(open_session(src, require_masks=False), params)
        shifted = []
        for shift in SHIFTS_PX:
            dst = work / f"{src.name}_down{shift:g}"
            inject_fault(src, dst, "vertical_offset", range(frames), shift)
            shifted.append(rectification_offset(open_session(dst, require_masks=False), params))
        out.append(row(f"synth {phantom} seed {seed}", f"{width}x{height}", clean, shifted,
                       (time.perf_counter() - t0) / 4))
    return out


def grey(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def pair_rows(name: str, pairs, params: DiagnosticParams) -> dict:
    t0 = time.perf_counter()
    clean = offsets_of_pairs(pairs, params)
    shifted = [offsets_of_pairs(pairs, params, s) for s in SHIFTS_PX]
    h, w = pairs[0][1].shape
    return row(name, f"{w}x{h}", clean, shifted, (time.perf_counter() - t0) / 4)


def scared_pair():
    """The SCARED keyframe's (left, right) grey images from the mirror, or None."""
    if not SCARED_GIT.is_dir():
        return None
    images = []
    for side in ("left", "right"):
        done = subprocess.run(["git", "--git-dir", str(SCARED_GIT), "show", f"HEAD:{SCARED_PATH.format(side=side)}"],
                              capture_output=True)
        if done.returncode != 0:
            return None
        images.append(cv2.imdecode(np.frombuffer(done.stdout, np.uint8), cv2.IMREAD_GRAYSCALE))
    return tuple(images)


def dv_calibration():
    """(M_l, M_r, D_l, D_r, R, T mm) of the published 1080p calibration, R as read (not yet corrected)."""
    storage = cv2.FileStorage(str(DV / "CalibrationParameters.xml"), cv2.FILE_STORAGE_READ)
    return tuple(storage.getNode(k).mat().astype(np.float64) for k in ("M_l", "M_r", "D_l", "D_r", "R", "T"))


def dv_files() -> list[tuple[str, Path, Path]]:
    """(stem, left, right) of the 30 pairs (one right file is named <stem>_r.jpg)."""
    out = []
    for left in sorted((DV_FRAMES / "left").glob("*.jpg")):
        right = DV_FRAMES / "right" / left.name
        out.append((left.stem, left, right if right.is_file() else right.with_name(f"{left.stem}_r.jpg")))
    return out


def dv_rectified_pairs():
    """Every pair rectified on the 1080p geometry and remapped into the crop: [(index, left, right)]."""
    M1, M2, D1, D2, R, T = dv_calibration()
    Q, _ = rotation_deviation(R)
    R1, R2, P1, P2, *_ = cv2.stereoRectify(M1, D1, M2, D2, FULL_SIZE, Q, T, flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
    crop = np.array([[1.0, 0, -CROP_X0], [0, 1, -CROP_Y0], [0, 0, 1]])  # full-frame px -> crop px
    maps = [cv2.initUndistortRectifyMap(crop @ M, D, Rk, crop @ P[:, :3], (CROP_W, CROP_H), cv2.CV_32FC1)
            for M, D, Rk, P in ((M1, D1, R1, P1), (M2, D2, R2, P2))]
    pairs = []
    for k, (_, left, right) in enumerate(dv_files()):
        images = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in (left, right)]
        pairs.append((k, *(cv2.remap(im, mx, my, cv2.INTER_LINEAR) for im, (mx, my) in zip(images, maps))))
    return pairs


def dv_session(work: Path) -> Path:
    """A session of the 30 pairs as a user makes one: the crops linked, a calibration.xml for the crop (principal
    points shifted, T in mm), rectified on load."""
    root = work / "davinci"
    for side in ("left", "right"):
        (root / side).mkdir(parents=True)
    for stem, left, right in dv_files():
        os.symlink(left, root / "left" / f"{stem}.jpg")
        os.symlink(right, root / "right" / f"{stem}.jpg")
    M1, M2, D1, D2, R, T = dv_calibration()
    storage = cv2.FileStorage(str(root / "calibration.xml"), cv2.FILE_STORAGE_WRITE)
    for name, value in (("M_l", M1), ("M_r", M2), ("D_l", D1), ("D_r", D2), ("R", R), ("T", T)):
        if name in ("M_l", "M_r"):
            value = value.copy()
            value[0, 2] -= CROP_X0
            value[1, 2] -= CROP_Y0
        storage.write(name, value)
    storage.write("translation_unit", "mm")
    storage.write("image_width", CROP_W)
    storage.write("image_height", CROP_H)
    storage.release()
    return root


def dv_rows(work: Path, params: DiagnosticParams) -> list[dict]:
    out = []
    pairs = dv_rectified_pairs()
    every = params.__class__(**{**params.to_dict(), "rectification_frames": len(pairs)})
    t0 = time.perf_counter()
    out.append(row("da Vinci, all 30 pairs", f"{CROP_W}x{CROP_H}", offsets_of_pairs(pairs, every), [],
                   time.perf_counter() - t0))
    sampled = [pairs[i] for i in sample_frames(range(len(pairs)), params.rectification_frames)]
    out.append(pair_rows("da Vinci, 8 sampled", sampled, params))
    raw = [(k, *(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in (left, right)))
           for k, (_, left, right) in enumerate(dv_files())]
    t0 = time.perf_counter()
    out.append(row("da Vinci, raw (no rectif.)", f"{CROP_W}x{CROP_H}", offsets_of_pairs(raw, every), [],
                   time.perf_counter() - t0))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the published R's one warning
        session = open_session(dv_session(work), require_masks=False)
    t0 = time.perf_counter()
    out.append(row("da Vinci, as check reads", f"{CROP_W}x{CROP_H}", rectification_offset(session, params), [],
                   time.perf_counter() - t0))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=24, help="frames of each synthetic session")
    parser.add_argument("--seeds", default="3,5", help="seed of the 640x360 sessions, of the 1280x720 ones")
    args = parser.parse_args()
    params = DiagnosticParams()
    seeds = [int(s) for s in args.seeds.split(",")]
    print(f"threshold {params.max_vertical_offset_px:g} px; {params.rectification_frames} frames sampled, matched at "
          f"<= {params.rectification_width_px} px wide; offsets in px of each source's images (> 0: right lower)")
    shifts = "  ".join(f"{f'+{s:g} px':>6s} fires?" for s in SHIFTS_PX)
    print(f"{'source':24s} {'size':>9s}  {'frm':>3s} {'matches':>7s}  {'offset':>6s}  {'per-frame range':16s}  "
          f"fires  {shifts}  {'s/run':>5s}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-rectification-") as tmp:
        work = Path(tmp)
        rows += synth_rows(work, args.frames, seeds, params)
        from skimage.data import stereo_motorcycle

        left, right, _ = stereo_motorcycle()
        rows.append(pair_rows("Middlebury motorcycle", [(0, grey(left), grey(right))], params))
        scared = scared_pair()
        if scared is None:
            print(f"SCARED keyframe: skipped ({SCARED_GIT} not found)")
        else:
            rows.append(pair_rows("SCARED keyframe", [(0, *scared)], params))
        if not (DV / "CalibrationParameters.xml").is_file():
            print(f"da Vinci pairs: skipped ({DV} not found)")
        else:
            rows += dv_rows(work, params)
    threshold = params.max_vertical_offset_px
    rectified = [r for r in rows if r["shifted"] and not r["name"].startswith("da Vinci") and r["clean"] is not None]
    worst = max(rectified, key=lambda r: abs(r["clean"].offset_px))
    weakest = min(((r, m) for r in rectified for m in r["shifted"][:1] if m is not None),
                  key=lambda rm: abs(rm[1].offset_px))
    detected = {s: sum(1 for r in rectified if r["shifted"][k] is not None and r["shifted"][k].fired)
                for k, s in enumerate(SHIFTS_PX)}
    print(f"\nthreshold {threshold:g} px: largest rectified offset {abs(worst['clean'].offset_px):.2f} px "
          f"({worst['name']}; {threshold / max(abs(worst['clean'].offset_px), 1e-9):.1f}x below the threshold); "
          f"weakest 1 px shift measured {abs(weakest[1].offset_px):.2f} px ({weakest[0]['name']}; "
          f"{abs(weakest[1].offset_px) / threshold:.2f}x the threshold)")
    print("shifts detected: " + ", ".join(f"+{s:g} px on {n} of {len(rectified)} rectified sources"
                                          for s, n in detected.items()))
    false = [r["name"] for r in rectified if r["clean"].fired]
    print(f"false alarms on rectified sources: {len(false)}" + (f" ({', '.join(false)})" if false else ""))


if __name__ == "__main__":
    main()
