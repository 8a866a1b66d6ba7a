"""`contact-viz import yang2024 --labels`: Yang et al.'s MTurk_Labels_with_keypoints.csv, and the baseline's tip file."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from contact_viz.errors import SessionError
from contact_viz.io.importers import run_import_command
from contact_viz.io.session import open_session


def make_yang(root: Path, n: int, rows: int) -> None:
    """A Yang et al. recording: img_<n>.jpg, right_img/img_<n>.jpg, labels_30hz.txt (time, Fx, Fy, Fz, ...)."""
    from PIL import Image

    (root / "right_img").mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(n):
        Image.fromarray(rng.integers(0, 256, (24, 40, 3), dtype=np.uint8)).save(root / f"img_{i}.jpg")
        Image.fromarray(rng.integers(0, 256, (24, 40, 3), dtype=np.uint8)).save(root / "right_img" / f"img_{i}.jpg")
    data = rng.normal(0, 1, (rows, 8))
    data[:, 0] = np.arange(rows) / 30.0
    np.savetxt(root / "labels_30hz.txt", data, delimiter=",")

# Rows in the layout of the real file (labels/MTurk_Labels_with_keypoints.csv of
# enhanced-telerobotics/Surgical-Tool-Vision-based-Contact-Detection): header, then
# GT, MTurk_Label, dataset, image (every 45th frame), x, y in px as float32 printed in full.
MTURK = """GT,MTurk_Label,dataset,image,x,y
0,0,C_M1_T1_4,img_0.jpg,485.4918212890625,256.2578430175781
0,0,C_M1_T1_4,img_45.jpg,465.9356384277344,266.6451110839844
1,0,C_M1_T1_4,img_90.jpg,431.01123046875,292.1478881835937
1,1,C_M1_T1_4,img_135.jpg,437.2000427246094,238.63137817382807
0,0,C_M1_T1_7,img_0.jpg,487.6212158203125,249.16702270507807
1,1,C_M1_T1_7,img_45.jpg,483.7730407714844,261.1504211425781
"""


def test_labels_become_manual_labels_crowd_labels_and_tool_tips(tmp_path):
    src = tmp_path / "C_M1_T1_4"
    make_yang(src, n=100, rows=100)  # frames 0..99: img_135 is not in the recording
    labels = tmp_path / "MTurk_Labels_with_keypoints.csv"
    labels.write_text(MTURK)
    k_txt = tmp_path / "K.txt"
    k_txt.write_text("60 0 20 0 60 12 0 0 1\n0.005\n")
    lines = run_import_command("yang2024", src, tmp_path / "s", calibration=[k_txt], labels=labels)
    text = "\n".join(lines)
    assert "3 labelled frames of C_M1_T1_4" in text and "crowd agrees on 2" in text
    assert "1 row(s) of MTurk_Labels_with_keypoints.csv for C_M1_T1_4 name images that are not in the recording" in text
    out = tmp_path / "s"
    assert (out / "labels.csv").read_text().splitlines() == ["frame,contact", "000000,0", "000045,0", "000090,1"]
    assert (out / "crowd_labels.csv").read_text().splitlines() == ["frame,contact", "000000,0", "000045,0",
                                                                   "000090,0"]
    session = open_session(out, require_masks=False, cache_dir=tmp_path / "cache")
    assert session.labels[[0, 45, 90]].tolist() == [0, 0, 1]
    assert (session.label_source[[0, 45, 90]] == "manual").all()
    assert session.tool_tips_xy is not None
    np.testing.assert_array_equal(session.tool_tips_xy[[0, 45, 90]],
                                  [[485.4918212890625, 256.2578430175781], [465.9356384277344, 266.6451110839844],
                                   [431.01123046875, 292.1478881835937]])
    assert np.isnan(np.delete(session.tool_tips_xy, [0, 45, 90], axis=0)).all()


def test_labels_errors(tmp_path):
    src = tmp_path / "R1_M1_T1_1"
    make_yang(src, n=4, rows=4)
    labels = tmp_path / "labels.csv"
    labels.write_text(MTURK)
    with pytest.raises(SessionError, match=r"labels.csv: expected rows of dataset 'R1_M1_T1_1' \(choose with "
                                           r"--dataset\), found datasets C_M1_T1_4, C_M1_T1_7"):
        run_import_command("yang2024", src, tmp_path / "s", labels=labels)
    result = run_import_command("yang2024", src, tmp_path / "s", labels=labels, dataset="C_M1_T1_7")
    assert (tmp_path / "s" / "labels.csv").read_text().splitlines() == ["frame,contact", "000000,0"]
    labels.write_text("GT,dataset,image,x,y\n0,C_M1_T1_4,img_0.jpg,1,2\n")
    with pytest.raises(SessionError, match=r"labels.csv: expected Yang et al.'s .* missing columns mturk_label"):
        run_import_command("yang2024", src, tmp_path / "t", labels=labels)
    labels.write_text("GT,MTurk_Label,dataset,image,x,y\n2,0,R1_M1_T1_1,img_0.jpg,1,2\n")
    with pytest.raises(SessionError, match=r"labels.csv: line 2: expected gt 0 or 1, found '2'"):
        run_import_command("yang2024", src, tmp_path / "t", labels=labels)
    assert not (tmp_path / "t").exists()
    with pytest.raises(ValueError, match="only apply to yang2024"):
        run_import_command("dvrk", src, tmp_path / "t", labels=labels)
    assert result


def test_baseline_crops_prefer_the_tool_tips_file(tmp_path):
    pytest.importorskip("torch")
    from contact_viz.baseline import TIP_FILE, TIP_FOUND, extract_crops
    from contact_viz.geometry.tooltip import crop_centered
    from contact_viz.synth import SynthParams, generate_session

    root = tmp_path / "s"
    generate_session(root, SynthParams(phantom="cup", frames=6, seed=2, width=96, height=64))
    work = tmp_path / "with_tips"
    shutil.copytree(root, work)
    (work / "tool_tips.csv").write_text("frame,x_px,y_px\n000002,20.0,30.0\n000004,70.5,10.25\n")
    plain = extract_crops(open_session(root), 32)
    tipped = extract_crops(open_session(work), 32)
    for i in (2, 4):
        assert tipped.center_source[i] == TIP_FILE
        session = open_session(work)
        left = session.load_frame(i, ("left",)).left_rgb
        np.testing.assert_array_equal(tipped.crops[i], crop_centered(left, tuple(session.tool_tips_xy[i]), 32))
    for i in (0, 1, 3, 5):  # no keypoint: the mask's tip, as without the file
        assert tipped.center_source[i] == plain.center_source[i] == TIP_FOUND
        np.testing.assert_array_equal(tipped.center_xy[i], plain.center_xy[i])


def test_score_crowd_recipe_worked_example(tmp_path):
    import subprocess
    import sys

    session = tmp_path / "C_M1_T1_4"
    session.mkdir()
    # truth 0 0 1 1, crowd 0 1 0 1: one each of TN, FP, FN, TP
    (session / "labels.csv").write_text("frame,contact\n000000,0\n000045,0\n000090,1\n000135,1\n")
    (session / "crowd_labels.csv").write_text("frame,contact\n000000,0\n000045,1\n000090,0\n000135,1\n")
    recipe = Path(__file__).resolve().parents[1] / "recipes" / "score_crowd.py"
    proc = subprocess.run([sys.executable, str(recipe), str(session)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    row = next(line.split() for line in proc.stdout.splitlines() if line.startswith("C_M1_T1_4"))
    # accuracy 2/4, precision 1/2, recall 1/2, F1 1/2, AUROC (TPR + TNR) / 2 = 1/2, AP 0.5 * 0.5 + 0.5 * 0.5
    assert row[1:] == ["0.500"] * 6
