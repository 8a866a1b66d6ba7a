"""Tests of the RGB baseline: crops, model, augmentation, Platt scaling, LOSO training and resume.

Everything runs a tiny network (EfficientNet-B0 at a quarter of its width and depth, 64 px crops,
one or two epochs) on three short synthetic sessions, so the whole file takes seconds on a CPU.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.optimize import minimize
from sklearn.utils.class_weight import compute_class_weight

from contact_viz.baseline import (
    ENSEMBLE_FILE,
    IMAGE_CENTER,
    TIP_FOUND,
    BaselineEnsemble,
    BaselineParams,
    BaselineWarning,
    PlattScaling,
    SessionCrops,
    build_model,
    extract_crops,
    fit_loso,
    fit_platt,
    make_augmentation,
    prepare_batch,
    raw_scores,
)
from contact_viz.baseline.loso import _class_weights
from contact_viz.model.hmm import select_f1_threshold
from contact_viz.io.session import open_session
from contact_viz.synth import SynthParams, generate_session
from contact_viz.geometry.tooltip import crop_centered, tool_tip_xy

CROP_PX = 64  # px
N_FRAMES = 24
TINY = BaselineParams(
    model_name="efficientnet-b0",
    width_coefficient=0.25,
    depth_coefficient=0.25,
    bn_momentum=0.5,
    crop_px=CROP_PX,
    epochs=1,
    batch_size=8,
    eval_batch_size=16,
)
CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def session_dirs(tmp_path_factory) -> list[Path]:
    root = tmp_path_factory.mktemp("baseline_sessions")
    return [
        generate_session(
            root / f"cup{seed}", SynthParams(phantom="cup", frames=N_FRAMES, seed=seed, width=160, height=96, fps=10)
        )
        for seed in range(3)
    ]


@pytest.fixture(scope="module")
def crops(session_dirs) -> list[SessionCrops]:
    return [extract_crops(open_session(d), CROP_PX) for d in session_dirs]


@pytest.fixture(scope="module")
def fitted(crops, tmp_path_factory):
    """A 2-fold LOSO fit on the first two sessions: (ensemble, checkpoint dir, progress events)."""
    directory = tmp_path_factory.mktemp("ckpt")
    events = []
    with pytest.warns(BaselineWarning, match="trains from scratch"):
        ensemble = fit_loso(crops[:2], TINY, directory, device=CPU, progress=events.append)
    return ensemble, directory, events


def quiet_model(params: BaselineParams = TINY, weights=None) -> torch.nn.Module:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BaselineWarning)
        return build_model(params, weights)


# ---- crops ----


def test_crops_are_centred_on_the_tool_tip(session_dirs, crops):
    session = open_session(session_dirs[0])
    sc = crops[0]
    assert sc.crops.shape == (N_FRAMES, CROP_PX, CROP_PX, 3) and sc.crops.dtype == np.uint8
    np.testing.assert_array_equal(sc.labels, session.labels)
    assert sc.readable.all()
    for frame in session.iter_frames(layers=("mask", "left"), indices=[0, 11, 23]):
        tip = tool_tip_xy(frame.tool_mask)
        assert tip is not None and sc.center_source[frame.index] == TIP_FOUND
        np.testing.assert_allclose(sc.center_xy[frame.index], tip)
        np.testing.assert_array_equal(sc.crops[frame.index], crop_centered(frame.left_rgb, tip, CROP_PX))


def test_frames_without_a_tip_use_the_last_tip_or_the_image_centre(session_dirs, tmp_path):
    import shutil

    from PIL import Image

    work = tmp_path / "s"
    shutil.copytree(session_dirs[0], work)
    masks = sorted((work / "masks").glob("*.png"))
    for i in (0, 5):  # frame 0: no tip yet -> image centre; frame 5: last tip (frame 4's)
        with Image.open(masks[i]) as image:
            blank = Image.new(image.mode, image.size)
            if image.mode == "P":
                blank.putpalette(image.getpalette())
        blank.save(masks[i])
    (work / "left" / "000007.jpg").write_bytes(b"not a jpeg")  # unreadable left image
    sc = extract_crops(open_session(work), CROP_PX)
    assert sc.center_source[0] == IMAGE_CENTER
    np.testing.assert_allclose(sc.center_xy[0], ((160 - 1) / 2, (96 - 1) / 2))
    np.testing.assert_allclose(sc.center_xy[5], sc.center_xy[4])
    assert not sc.readable[7] and sc.readable[[6, 8]].all()
    np.testing.assert_array_equal(sc.crops[7], sc.crops[6])  # held from the previous frame
    assert not sc.trainable[7]


def test_crop_cache_is_a_memory_map_read_back_without_decoding(session_dirs, crops, tmp_path):
    session = open_session(session_dirs[1])
    first = extract_crops(session, CROP_PX, cache_dir=tmp_path)
    assert isinstance(first.crops, np.memmap)
    np.testing.assert_array_equal(first.crops, crops[1].crops)

    def no_decoding(*args, **kwargs):
        raise AssertionError("the cached crops should be read back, not recomputed")

    session.iter_frames = no_decoding
    again = extract_crops(session, CROP_PX, cache_dir=tmp_path)
    np.testing.assert_array_equal(again.crops, crops[1].crops)
    np.testing.assert_array_equal(again.center_xy, crops[1].center_xy)
    assert not list(tmp_path.rglob("*.tmp*"))


# ---- model, input, augmentation ----


def test_model_outputs_two_logits_per_crop():
    model = quiet_model().eval()
    x = prepare_batch(np.zeros((3, CROP_PX, CROP_PX, 3), dtype=np.uint8), CPU)
    assert x.shape == (3, 3, CROP_PX, CROP_PX) and x.dtype == torch.float32
    with torch.no_grad():
        assert model(x).shape == (3, 2)


def test_default_head_is_one_dropout_and_a_two_class_linear_layer():
    with pytest.warns(BaselineWarning, match="from scratch"):
        model = build_model(BaselineParams())
    dropouts = [m for m in model.modules() if isinstance(m, torch.nn.Dropout)]
    assert len(dropouts) == 1 and dropouts[0].p == pytest.approx(0.3)
    assert model._fc.out_features == 2 and model._fc.in_features == 1536  # EfficientNet-B3 features


def test_normalisation_is_imagenet_mean_and_std():
    crops = np.full((1, 4, 4, 3), 255, dtype=np.uint8)
    x = prepare_batch(crops, CPU)
    expected = [(1.0 - m) / s for m, s in zip((0.485, 0.456, 0.406), (0.229, 0.224, 0.225))]
    np.testing.assert_allclose(x[0, :, 0, 0].numpy(), expected, rtol=1e-6)


def test_augmentation_keeps_shape_and_is_seeded():
    aug = make_augmentation(TINY)
    x = torch.rand(4, 3, CROP_PX, CROP_PX, generator=torch.Generator().manual_seed(0))
    torch.manual_seed(3)
    a = aug(x)
    torch.manual_seed(3)
    b = aug(x)
    torch.manual_seed(4)
    c = aug(x)
    assert a.shape == x.shape and a.dtype == torch.float32
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_augmentation_with_everything_off_is_the_plain_normalisation():
    off = BaselineParams(crop_px=CROP_PX, rotation_deg=0.0, hflip_p=0.0, color_jitter=0.0, erasing_p=0.0)
    crops = np.random.default_rng(0).integers(0, 256, (2, CROP_PX, CROP_PX, 3), dtype=np.uint8)
    augmented = prepare_batch(crops, CPU, make_augmentation(off))
    # atol: a 0-deg rotation still resamples bilinearly (1e-4 is under 1 % of one grey level)
    np.testing.assert_allclose(augmented.numpy(), prepare_batch(crops, CPU).numpy(), atol=1e-4)


def test_imagenet_weights_load_into_the_backbone(tmp_path):
    from efficientnet_pytorch import EfficientNet

    torch.manual_seed(1)
    imagenet = EfficientNet.from_name(
        "efficientnet-b0", width_coefficient=0.25, depth_coefficient=0.25, image_size=CROP_PX
    )
    path = tmp_path / "weights.pth"
    torch.save(imagenet.state_dict(), path)  # 1000-class _fc, as the released files
    model = build_model(TINY, path)
    own = model.state_dict()
    for key, value in imagenet.state_dict().items():
        if key.startswith("_fc."):
            assert own[key].shape[0] == 2
        else:
            assert torch.equal(own[key], value), key

    with pytest.raises(FileNotFoundError, match="missing.pth: missing: expected an efficientnet-pytorch"):
        build_model(TINY, tmp_path / "missing.pth")
    other = tmp_path / "b0_full_width.pth"
    torch.save(EfficientNet.from_name("efficientnet-b0").state_dict(), other)
    with pytest.raises(ValueError, match="b0_full_width.pth: expected an efficientnet-pytorch.*another shape"):
        build_model(TINY, other)


# ---- Platt scaling ----


def smoothed_log_loss(w, s, y):
    """Platt's objective, written out independently of the module."""
    n_pos, n_neg = (y == 1).sum(), (y == 0).sum()
    t = np.where(y == 1, (n_pos + 1) / (n_pos + 2), 1 / (n_neg + 2))
    z = w[0] * s + w[1]
    return np.sum(np.logaddexp(0, z) - t * z)


def test_platt_recovers_a_known_logistic_relationship():
    rng = np.random.default_rng(7)
    slope, intercept = 1.5, -0.7
    s = rng.normal(0.3, 2.0, 20000)
    y = (rng.random(s.size) < 1 / (1 + np.exp(-(slope * s + intercept)))).astype(np.int64)
    y[::97] = -1  # unknown frames are ignored
    platt = fit_platt(s, y)
    assert platt.slope == pytest.approx(slope, abs=0.08)
    assert platt.intercept == pytest.approx(intercept, abs=0.08)
    keep = y >= 0
    reference = minimize(smoothed_log_loss, x0=[0.0, 0.0], args=(s[keep], y[keep]), method="BFGS", tol=1e-10).x
    np.testing.assert_allclose([platt.slope, platt.intercept], reference, atol=1e-4)
    z = platt.slope * np.array([0.0, 1.0]) + platt.intercept
    np.testing.assert_allclose(platt(np.array([0.0, 1.0])), 1 / (1 + np.exp(-z)))


def test_platt_stays_finite_on_separated_and_constant_scores():
    s = np.array([-3.0, -2.0, -1.0, 1.0, 2.0, 3.0])
    y = np.array([0, 0, 0, 1, 1, 1])
    platt = fit_platt(s, y)
    assert math.isfinite(platt.slope) and platt.slope > 0
    reference = minimize(smoothed_log_loss, x0=[0.0, 0.0], args=(s, y), method="BFGS", tol=1e-12).x
    np.testing.assert_allclose([platt.slope, platt.intercept], reference, atol=1e-4)
    flat = fit_platt(np.zeros(4), np.array([0, 1, 1, 1]))  # targets 1/3, 4/5, 4/5, 4/5 -> mean 41/60
    assert flat.slope == 0.0 and flat.intercept == pytest.approx(math.log(41 / 19))
    with pytest.raises(ValueError, match="both classes"):
        fit_platt(np.arange(3.0), np.array([1, 1, -1]))


def test_class_weights_are_sklearns_balanced():
    labels = np.array([0] * 7 + [1] * 3)
    expected = compute_class_weight("balanced", classes=np.array([0, 1]), y=labels)
    np.testing.assert_allclose(_class_weights(labels, "f"), expected)
    with pytest.raises(ValueError, match="both classes"):
        _class_weights(np.zeros(4, dtype=np.int8), "fold 0")


# ---- LOSO training ----


def test_fit_loso_end_to_end(crops, fitted):
    ensemble, directory, events = fitted
    assert [(e.fold, e.stage) for e in events] == [(0, "epoch"), (0, "done"), (1, "epoch"), (1, "done")]
    assert ensemble.session_names_ == ["cup0", "cup1"] and len(ensemble.models_) == 2
    assert [len(o) for o in ensemble.oof_scores_] == [N_FRAMES, N_FRAMES]
    # Out-of-fold scores are model k on session k; calibration and threshold follow from them.
    for k in range(2):
        np.testing.assert_array_equal(ensemble.oof_scores_[k], raw_scores(ensemble.models_[k], crops[k].crops, 16, CPU))
    pooled = np.concatenate(ensemble.oof_scores_)
    labels = np.concatenate([c.labels for c in crops[:2]])
    assert ensemble.platt_ == fit_platt(pooled, labels)
    assert ensemble.threshold_ == select_f1_threshold(ensemble.platt_(pooled), labels)
    # The ensemble averages raw scores, then calibrates.
    test = crops[2]
    batch = TINY.eval_batch_size
    mean_raw = np.mean([raw_scores(m, test.crops, batch, CPU) for m in ensemble.models_], axis=0)
    proba = ensemble.predict_proba(test)
    assert proba.shape == (N_FRAMES,) and ((proba >= 0) & (proba <= 1)).all()
    np.testing.assert_allclose(proba, ensemble.platt_(mean_raw), rtol=1e-12)
    np.testing.assert_array_equal(ensemble.predict(test.crops), proba >= ensemble.threshold_)
    saved = json.loads((directory / ENSEMBLE_FILE).read_text())
    assert saved["threshold"] == ensemble.threshold_ and saved["checkpoints"] == ["fold_0.pt", "fold_1.pt"]


def test_rerun_loads_completed_folds_and_predicts_identically(crops, fitted):
    ensemble, directory, _ = fitted
    events = []
    with warnings.catch_warnings():
        warnings.simplefilter("error", BaselineWarning)  # nothing trains, so no "from scratch" warning
        again = fit_loso(crops[:2], TINY, directory, device=CPU, progress=events.append)
    assert [(e.fold, e.stage) for e in events] == [(0, "loaded"), (1, "loaded")]
    expected = ensemble.predict_proba(crops[2])
    np.testing.assert_array_equal(again.predict_proba(crops[2]), expected)
    loaded = BaselineEnsemble.load(directory, device="cpu")
    np.testing.assert_array_equal(loaded.predict_proba(crops[2]), expected)
    assert loaded.threshold_ == ensemble.threshold_ and loaded.params == TINY


def test_interrupted_fold_resumes_at_its_last_epoch(crops, tmp_path):
    two_epochs = BaselineParams(**{**TINY.__dict__, "epochs": 2})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BaselineWarning)
        straight = fit_loso(crops[:2], two_epochs, tmp_path / "straight", device=CPU)

        def stop_after_first_epoch(event):
            if event.stage == "epoch" and event.fold == 0 and event.epoch == 1:
                raise KeyboardInterrupt

        with pytest.raises(KeyboardInterrupt):
            fit_loso(crops[:2], two_epochs, tmp_path / "cut", device=CPU, progress=stop_after_first_epoch)
        assert (tmp_path / "cut" / "fold_0.pt").is_file() and not (tmp_path / "cut" / "fold_1.pt").exists()
        events = []
        resumed = fit_loso(crops[:2], two_epochs, tmp_path / "cut", device=CPU, progress=events.append)
    assert [(e.fold, e.stage, e.epoch) for e in events][:3] == [(0, "resumed", 1), (0, "epoch", 2), (0, "done", 2)]
    for a, b in zip(resumed.oof_scores_, straight.oof_scores_):
        np.testing.assert_array_equal(a, b)


def test_checkpoints_of_another_run_are_refused(crops, fitted):
    _, directory, _ = fitted
    other = BaselineParams(**{**TINY.__dict__, "lr": 1e-3})
    made_with = r"fold_0.pt: this checkpoint was made with other BaselineParams \(differing: \['lr'\]\)"
    with pytest.raises(ValueError, match=made_with):
        fit_loso(crops[:2], other, directory, device=CPU)
    with pytest.raises(ValueError, match="fold_0.pt: this checkpoint belongs to another run"):
        fit_loso([crops[0], crops[2]], TINY, directory, device=CPU)


def test_fit_loso_rejects_bad_input(crops, tmp_path):
    c0 = crops[0]
    def with_labels(name, labels):
        return SessionCrops(name, c0.crops, labels.astype(np.int8), c0.center_xy, c0.center_source, c0.readable)

    unlabelled = with_labels("blank", np.full(len(c0), -1))
    with pytest.raises(ValueError, match="session 'blank' has no labelled frame"):
        fit_loso([c0, unlabelled], TINY, tmp_path / "a", device=CPU)
    with pytest.raises(ValueError, match="at least 2 training sessions"):
        fit_loso([c0], TINY, tmp_path / "b", device=CPU)
    with pytest.raises(ValueError, match="64 px crops, params.crop_px is 96"):
        fit_loso(crops[:2], BaselineParams(**{**TINY.__dict__, "crop_px": 96}), tmp_path / "c", device=CPU)
    with pytest.raises(FileNotFoundError, match="nowhere.pth: missing"):
        fit_loso(crops[:2], TINY, tmp_path / "d", weights=tmp_path / "nowhere.pth", device=CPU)
    only_no_contact = with_labels("calm", np.zeros(len(c0)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BaselineWarning)
        with pytest.raises(ValueError, match=r"fold 0 \(leaving out 'cup0'\).*both classes"):
            fit_loso([c0, only_no_contact], TINY, tmp_path / "e", device=CPU)


def test_params_are_checked():
    with pytest.raises(ValueError, match="model_name"):
        BaselineParams(model_name="resnet50")
    with pytest.raises(ValueError, match="dropout"):
        BaselineParams(dropout=1.5)
    with pytest.raises(ValueError, match="crop_px"):
        BaselineParams(crop_px=0)
    assert PlattScaling(2.0, 0.0)(0.0) == pytest.approx(0.5)
