"""The RGB contact classifier of Yang et al. (2024) as a baseline (paper, Sec. 3.3).

Model: EfficientNet (``efficientnet-pytorch``, default B3) whose classifier is dropout 0.3 and a
two-class linear layer. (In efficientnet-pytorch the head is ``_dropout`` then ``_fc``; we build
the net with ``dropout_rate=params.dropout`` and ``num_classes=2``, which is exactly one
Dropout(0.3) followed by Linear(features, 2), as torchvision's EfficientNet-B3 classifier with its
last layer replaced.) ``image_size`` is set to the crop size so the "same" padding of the
convolutions is computed for the real input size.

Input: a ``crop_px`` (234) square RGB crop centred on the tool tip estimated from the tool mask
(``contact_viz.geometry.tooltip``: the mask pixel farthest from where the tool enters the image), or
on the session's ``tool_tips.csv`` keypoint where it has one (Yang et al.'s labelled keypoints,
``contact-viz import yang2024 --labels``). Frames whose mask gives no tip are cropped at the session's last known tip, or the image centre before
any tip was found (causal: only earlier frames are used). Frames whose left image cannot be read
reuse the previous readable frame's crop (zeros before the first one) and are never trained on.
Pixels are scaled to [0, 1] and normalised with the ImageNet mean and standard deviation.

Training (per fold): Adam(lr 1e-4, weight decay 1e-4); cross-entropy weighted by class, weight of
class c = N / (2 N_c) over the fold's training frames (sklearn's "balanced"); frames labelled -1
are skipped. Augmentation on the device with kornia, in this order: rotation by U(-20, 20) deg
(always, zeros outside), horizontal flip (p 0.5), colour jitter (brightness, contrast, saturation
0.5; hue ``hue_jitter``, default 0), ImageNet normalisation, random erasing (p 0.5, 2-33 % of the
area, value 0 = the mean colour after normalisation; as torchvision's RandomErasing after
Normalize).

Protocol: K-fold leave-one-session-out over the training sessions; fold k trains on every session
but k and scores session k (out of fold). The raw score of a frame is the logit difference
z = logit(contact) - logit(no contact) (= log-odds of the softmax). Platt scaling,
p = sigmoid(a z + b), is fitted on the pooled out-of-fold raw scores of the labelled frames by
Newton's method on the log-loss with Platt's (1999) smoothed targets (N+ + 1)/(N+ + 2) and
1/(N- + 2), which keep (a, b) finite when the scores separate the classes. The decision threshold
is ``select_f1_threshold`` on the calibrated pooled out-of-fold probabilities. The ensemble scores
a frame with the mean of the K models' raw scores and applies the same Platt map: averaging in
logit space keeps the scale on which the map was fitted, one model's out-of-fold score.

Checkpoints: ``fold_k.pt`` in the checkpoint directory, written atomically after every epoch
(model, optimizer and random states), and finally with the out-of-fold scores. A rerun loads
completed folds (``torch.load(weights_only=True)``) instead of training them and resumes an
interrupted fold at its last finished epoch, reproducing the uninterrupted run. ``ensemble.json``
holds the params, the Platt map, the threshold and the out-of-fold scores; the weights stay in
the ``.pt`` files.

Without ``weights`` (a local efficientnet-pytorch ImageNet state dict) the network trains from
scratch and a :class:`BaselineWarning` says so. The device is CUDA when available, else the CPU.
"""

from __future__ import annotations

import json
import math
import os
import re
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from contact_viz.io.atomic import atomic_write
from contact_viz.model.hmm import select_f1_threshold
from contact_viz.model.hmm import sigmoid as _sigmoid
from contact_viz.params import check_fields, checked
from contact_viz.params import from_dict as _params_from_dict
from contact_viz.params import to_dict as _params_to_dict
from contact_viz.geometry.tooltip import TipParams, crop_centered, tool_tip_xy

if TYPE_CHECKING:  # torch is imported lazily: importing this module stays cheap
    import torch

__all__ = [
    "BaselineEnsemble",
    "BaselineParams",
    "BaselineWarning",
    "FoldEvent",
    "PlattScaling",
    "SessionCrops",
    "build_model",
    "extract_crops",
    "fit_loso",
    "fit_platt",
    "make_augmentation",
    "prepare_batch",
    "raw_scores",
    "resolve_device",
]

IMAGENET_MEAN = (0.485, 0.456, 0.406)  # per-channel mean of ImageNet RGB in [0, 1], -
IMAGENET_STD = (0.229, 0.224, 0.225)  # per-channel standard deviation of ImageNet RGB in [0, 1], -
N_CLASSES = 2  # no contact, contact
CONTACT, NO_CONTACT, UNKNOWN_LABEL = 1, 0, -1
CHECKPOINT_FORMAT = 1  # version of the fold checkpoint layout
ENSEMBLE_FILE = "ensemble.json"  # name of the ensemble description in the checkpoint directory
PIXEL_MAX = 255.0  # uint8 full scale
_MODEL_NAME = re.compile(r"efficientnet-b[0-8]")  # architectures efficientnet-pytorch builds by name
_PLATT_TOL = 1e-10  # scikit-learn's lbfgs stopping tolerance of the Platt fit (gradient), -
_PLATT_MAX_ITER = 1000  # lbfgs iterations of the Platt fit, count

# center_source codes of SessionCrops
TIP_FOUND, LAST_TIP, IMAGE_CENTER, TIP_FILE = 0, 1, 2, 3


class BaselineWarning(UserWarning):
    """Something about the baseline run the user should know (e.g. training from scratch)."""


# --------------------------------------------------------------------------------------------
# Parameters
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BaselineParams:
    """Settings of the RGB baseline; defaults reproduce Yang et al. as described in the paper."""

    model_name: str = "efficientnet-b3"  # efficientnet-pytorch architecture, efficientnet-b0..b8
    # channel-width multiplier override (None = the architecture's), -
    width_coefficient: float | None = checked(None, gt=0)
    # layer-count multiplier override (None = the architecture's), -
    depth_coefficient: float | None = checked(None, gt=0)
    # batch-norm running-statistics update weight per step, torch convention (None = efficientnet-pytorch's 0.01), -
    bn_momentum: float | None = checked(None, gt=0, le=1)
    crop_px: int = checked(234, ge=1)  # side of the square input crop centred on the tool tip, px
    dropout: float = checked(0.3, ge=0, le=1)  # dropout probability before the two-class linear layer, -
    lr: float = checked(1e-4, gt=0)  # Adam learning rate, -
    weight_decay: float = checked(1e-4, ge=0)  # Adam weight decay (L2 penalty), -
    epochs: int = checked(10, ge=1)  # passes over each fold's training frames (not reported by Yang et al.), count
    batch_size: int = checked(16, ge=1)  # training batch, frames
    eval_batch_size: int = checked(32, ge=1)  # inference batch, frames
    rotation_deg: float = checked(20.0, ge=0)  # random rotation drawn from U(-rotation_deg, rotation_deg), deg
    hflip_p: float = checked(0.5, ge=0, le=1)  # probability of a horizontal flip, -
    color_jitter: float = checked(0.5, ge=0)  # brightness, contrast and saturation jitter factor, -
    hue_jitter: float = checked(0.0, ge=0, le=0.5)  # hue jitter, fraction of the hue circle (<= 0.5), -
    erasing_p: float = checked(0.5, ge=0, le=1)  # probability of random erasing, -
    # erased area range, fraction of the crop
    erasing_scale: tuple[float, float] = checked((0.02, 0.33), gt=0, le=1, pair=True)
    seed: int = checked(0, ge=0)  # seed of weight init, shuffling, dropout and augmentation, -

    def __post_init__(self) -> None:
        check_fields(self)
        if not _MODEL_NAME.fullmatch(self.model_name):
            raise ValueError(
                f"BaselineParams.model_name must be efficientnet-b0 .. efficientnet-b8, got {self.model_name!r}"
            )


# --------------------------------------------------------------------------------------------
# Crops
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SessionCrops:
    """The tool-tip crops of one session (T frames), ready for training or prediction."""

    name: str  # session name (unique within a LOSO run)
    crops: np.ndarray  # (T, S, S, 3) uint8 RGB crops (in memory or a read-only memory map)
    labels: np.ndarray  # (T,) int8 1 = contact, 0 = no contact, -1 = unknown
    center_xy: np.ndarray  # (T, 2) float64 crop centre (x = column, y = row) in the left image, px
    center_source: np.ndarray  # (T,) uint8 TIP_FOUND (0) / LAST_TIP (1) / IMAGE_CENTER (2) / TIP_FILE (3)
    readable: np.ndarray  # (T,) bool, False where the left image could not be read (never trained on)

    def __post_init__(self) -> None:
        crops = self.crops
        if crops.ndim != 4 or crops.shape[3] != 3 or crops.shape[1] != crops.shape[2] or crops.dtype != np.uint8:
            raise ValueError(
                f"SessionCrops {self.name!r}: crops: expected (T, S, S, 3) uint8, "
                f"got shape {crops.shape} dtype {crops.dtype}"
            )
        n = crops.shape[0]
        for attr, shape in (("labels", (n,)), ("center_xy", (n, 2)), ("center_source", (n,)), ("readable", (n,))):
            value = getattr(self, attr)
            if value.shape != shape:
                raise ValueError(f"SessionCrops {self.name!r}: {attr}: expected shape {shape}, got {value.shape}")
        if not np.isin(self.labels, (UNKNOWN_LABEL, NO_CONTACT, CONTACT)).all():
            raise ValueError(f"SessionCrops {self.name!r}: labels: expected values in {{-1, 0, 1}}")

    def __len__(self) -> int:
        return int(self.crops.shape[0])

    @property
    def trainable(self) -> np.ndarray:
        """(T,) bool: frames labelled 0 or 1 whose left image was read."""
        return (self.labels != UNKNOWN_LABEL) & self.readable


def _crop_cache_paths(session: Any, crop_px: int, tip_params: TipParams, cache_dir: Path) -> tuple[Path, Path]:
    from contact_viz.io.cache import cache_path

    key_params = {"crop_px": crop_px, "tip": _params_to_dict(tip_params)}
    crops_path = cache_path(session.root, "baseline-crops", key_params, ".npy", cache_dir)
    return crops_path, crops_path.with_suffix(".meta.npz")


def extract_crops(
    session: Any,
    crop_px: int,
    tip_params: TipParams = TipParams(),
    cache_dir: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> SessionCrops:
    """The tool-tip crops of every frame of an opened ``session`` (``contact_viz.io.session.Session``).

    Decodes the mask and left image of each frame once. Crop centres follow the module docstring
    (tip, else last known tip, else image centre). With ``cache_dir`` the crops are written to a
    ``.npy`` file there (keyed by the session's files, ``crop_px`` and ``tip_params``, see
    ``contact_viz.io.cache``) and returned as a read-only memory map; a later call with unchanged
    inputs reads it back without decoding anything. Without it they are held in memory
    (crop_px**2 * 3 bytes per frame: 164 kB at 234 px). ``progress(done, total)`` after each frame.
    """
    n_frames = len(session)
    height, width = session.image_size
    labels = np.array(session.labels, dtype=np.int8)
    if cache_dir is not None:
        crops_path, meta_path = _crop_cache_paths(session, crop_px, tip_params, Path(cache_dir))
        if crops_path.is_file() and meta_path.is_file():
            crops = np.load(crops_path, mmap_mode="r")
            with np.load(meta_path) as meta:
                return SessionCrops(
                    name=session.name,
                    crops=crops,
                    labels=labels,
                    center_xy=meta["center_xy"],
                    center_source=meta["center_source"],
                    readable=meta["readable"],
                )
        crops_path.parent.mkdir(parents=True, exist_ok=True)
        tmp_path = crops_path.with_name(f".{crops_path.name}.{os.getpid()}.tmp.npy")
        crops = np.lib.format.open_memmap(tmp_path, mode="w+", dtype=np.uint8, shape=(n_frames, crop_px, crop_px, 3))
    else:
        crops = np.zeros((n_frames, crop_px, crop_px, 3), dtype=np.uint8)
    center_xy = np.empty((n_frames, 2), dtype=np.float64)
    center_source = np.empty(n_frames, dtype=np.uint8)
    readable = np.ones(n_frames, dtype=bool)
    last_tip: tuple[float, float] | None = None
    file_tips = getattr(session, "tool_tips_xy", None)  # (T, 2) px from tool_tips.csv, NaN where absent
    image_center = ((width - 1) / 2.0, (height - 1) / 2.0)
    try:
        for frame in session.iter_frames(layers=("mask", "left")):
            i = frame.index
            tool_mask = getattr(frame, "tool_mask", None)
            left_rgb = getattr(frame, "left_rgb", None)
            if left_rgb is None:  # a BadFrame: the mask or the image is unreadable; try each alone
                tool_mask = getattr(session.load_frame(i, ("mask",)), "tool_mask", None)
                left_rgb = getattr(session.load_frame(i, ("left",)), "left_rgb", None)
            file_tip = None if file_tips is None or not np.isfinite(file_tips[i]).all() else file_tips[i]
            tip = tool_tip_xy(tool_mask, tip_params) if tool_mask is not None and file_tip is None else None
            if file_tip is not None:  # the session's tool_tips.csv (e.g. Yang et al.'s keypoints) wins
                last_tip, center_source[i] = (float(file_tip[0]), float(file_tip[1])), TIP_FILE
            elif tip is not None:
                last_tip, center_source[i] = tip, TIP_FOUND
            else:
                center_source[i] = LAST_TIP if last_tip is not None else IMAGE_CENTER
            center_xy[i] = last_tip if last_tip is not None else image_center
            if left_rgb is not None:
                crops[i] = crop_centered(left_rgb, center_xy[i], crop_px)
            else:
                readable[i] = False
                if i > 0:
                    crops[i] = crops[i - 1]  # hold the previous crop (zeros before the first readable frame)
            if progress is not None:
                progress(i + 1, n_frames)
        if cache_dir is not None:
            crops.flush()
            del crops
            with atomic_write(meta_path, "wb") as handle:
                np.savez(handle, center_xy=center_xy, center_source=center_source, readable=readable)
            os.replace(tmp_path, crops_path)  # the crops file appears last: both present = complete
            crops = np.load(crops_path, mmap_mode="r")
    except BaseException:
        if cache_dir is not None:
            tmp_path.unlink(missing_ok=True)
        raise
    return SessionCrops(
        name=session.name,
        crops=crops,
        labels=labels,
        center_xy=center_xy,
        center_source=center_source,
        readable=readable,
    )


# --------------------------------------------------------------------------------------------
# Model, device, input and augmentation
# --------------------------------------------------------------------------------------------


def resolve_device(device: str | torch.device | None = None) -> torch.device:
    """``device`` as a torch.device; None = CUDA when available, else the CPU."""
    import torch

    if device is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def build_model(params: BaselineParams, weights: str | Path | None = None) -> torch.nn.Module:
    """EfficientNet ``params.model_name`` with a Dropout(params.dropout) + Linear(features, 2) head.

    ``weights``: a local efficientnet-pytorch ImageNet state dict (e.g. efficientnet-b3-5fb5a3c3.pth),
    loaded with ``torch.load(weights_only=True)``; every backbone tensor must match (strict), the
    1000-class ``_fc`` is ignored and the new head keeps its random init. Without weights, a
    BaselineWarning says the network trains from scratch. Returns the model on the CPU, train mode.
    """
    import torch
    from efficientnet_pytorch import EfficientNet

    overrides: dict[str, Any] = {"image_size": params.crop_px, "dropout_rate": params.dropout, "num_classes": N_CLASSES}
    if params.width_coefficient is not None:
        overrides["width_coefficient"] = float(params.width_coefficient)
    if params.depth_coefficient is not None:
        overrides["depth_coefficient"] = float(params.depth_coefficient)
    if params.bn_momentum is not None:  # efficientnet-pytorch takes the TensorFlow convention, 1 - momentum
        overrides["batch_norm_momentum"] = 1.0 - float(params.bn_momentum)
    model = EfficientNet.from_name(params.model_name, **overrides)
    if weights is None:
        warnings.warn(
            f"no ImageNet weights given (--weights): {params.model_name} trains from scratch",
            BaselineWarning,
            stacklevel=2,
        )
        return model
    path = Path(weights).expanduser()
    what = f"an efficientnet-pytorch ImageNet state dict (.pth) for {params.model_name}"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing: expected {what}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # unpickling / format errors of many kinds
        raise ValueError(f"{path}: expected {what}, readable by torch.load(weights_only=True) "
                         f"({type(exc).__name__}: {exc})") from exc
    if not isinstance(state, Mapping) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise ValueError(f"{path}: expected {what}: a mapping of parameter names to tensors")
    own = {k: v for k, v in model.state_dict().items() if not k.startswith("_fc.")}
    given = {k: v for k, v in state.items() if not k.startswith("_fc.")}
    missing, unexpected = sorted(own.keys() - given.keys()), sorted(given.keys() - own.keys())
    wrong_shape = sorted(k for k in own.keys() & given.keys() if tuple(own[k].shape) != tuple(given[k].shape))
    if missing or unexpected or wrong_shape:
        raise ValueError(
            f"{path}: expected {what}; {len(missing)} backbone tensor(s) missing {missing[:3]}, "
            f"{len(unexpected)} unexpected {unexpected[:3]}, {len(wrong_shape)} of another shape {wrong_shape[:3]}"
        )
    model.load_state_dict(given, strict=False)  # strict over the backbone (checked above); the head stays
    return model


def prepare_batch(crops: np.ndarray, device: torch.device, augmentation: torch.nn.Module | None = None) -> torch.Tensor:
    """(B, S, S, 3) uint8 crops -> (B, 3, S, S) float32 network input on ``device``.

    Without ``augmentation``: scaled to [0, 1] and ImageNet-normalised. With it (``make_augmentation``),
    the augmentation receives the [0, 1] batch and does the normalisation itself.
    """
    import torch

    batch = torch.from_numpy(np.array(crops)).to(device)  # a writable copy (crops may be a read-only memmap)
    x = batch.permute(0, 3, 1, 2).float().div_(PIXEL_MAX)
    if augmentation is not None:
        return augmentation(x)
    mean = torch.tensor(IMAGENET_MEAN, device=device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, device=device).view(1, 3, 1, 1)
    return (x - mean) / std


def make_augmentation(params: BaselineParams) -> torch.nn.Module:
    """The training augmentation (kornia): (B, 3, S, S) float in [0, 1] -> augmented, normalised, same shape.

    Rotation U(-rotation_deg, rotation_deg) (always), horizontal flip (hflip_p), colour jitter
    (always), ImageNet normalisation, random erasing (erasing_p). Random draws come from torch's
    global generator: the same ``torch.manual_seed`` gives the same output.
    """
    import kornia.augmentation as K

    jitter = params.color_jitter
    return K.AugmentationSequential(
        K.RandomRotation(degrees=params.rotation_deg, p=1.0),
        K.RandomHorizontalFlip(p=params.hflip_p),
        K.ColorJitter(brightness=jitter, contrast=jitter, saturation=jitter, hue=params.hue_jitter, p=1.0),
        K.Normalize(mean=IMAGENET_MEAN, std=IMAGENET_STD),
        K.RandomErasing(scale=params.erasing_scale, p=params.erasing_p),
    )


def raw_scores(model: torch.nn.Module, crops: np.ndarray, batch_size: int, device: torch.device) -> np.ndarray:
    """Logit difference z = logit(contact) - logit(no contact) per crop, (T,) float64; eval mode, no grad."""
    import torch

    model.eval()
    out = np.empty(len(crops), dtype=np.float64)
    with torch.inference_mode():
        for start in range(0, len(crops), batch_size):
            logits = model(prepare_batch(crops[start : start + batch_size], device)).double()
            out[start : start + batch_size] = (logits[:, CONTACT] - logits[:, NO_CONTACT]).cpu().numpy()
    return out


# --------------------------------------------------------------------------------------------
# Platt scaling
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PlattScaling:
    """p = sigmoid(slope * score + intercept)."""

    slope: float  # per unit of raw score (logit difference), -
    intercept: float  # -

    def __call__(self, scores: Any) -> np.ndarray:
        """Calibrated P(contact) of ``scores`` (any shape), float64."""
        return _sigmoid(self.slope * np.asarray(scores, dtype=np.float64) + self.intercept)


def fit_platt(scores: Any, labels: Any) -> PlattScaling:
    """Platt scaling fitted on (n,) finite ``scores`` and (n,) ``labels`` in {-1, 0, 1} (-1 excluded).

    Minimises the log-loss of sigmoid(a s + b) against Platt's smoothed targets
    (N+ + 1)/(N+ + 2) for contact and 1/(N- + 2) for no contact: scikit-learn's unpenalised
    logistic regression, each frame once as contact with weight t and once as no contact with
    weight 1 - t (the same loss), on standardised scores (then mapped back). Both classes must
    be present.
    """
    from sklearn.linear_model import LogisticRegression

    s = np.asarray(scores, dtype=np.float64)
    y = np.asarray(labels)
    if s.ndim != 1 or y.shape != s.shape:
        raise ValueError(f"fit_platt: expected scores and labels of one shape (n,), got {s.shape} and {y.shape}")
    keep = y != UNKNOWN_LABEL
    s, y = s[keep], y[keep]
    if not np.isfinite(s).all():
        raise ValueError("fit_platt: scores must be finite on labelled frames")
    n_pos, n_neg = int((y == CONTACT).sum()), int((y == NO_CONTACT).sum())
    if n_pos == 0 or n_neg == 0:
        raise ValueError(
            f"fit_platt: expected both classes among the labelled frames, got {n_pos} contact, {n_neg} no contact"
        )
    target = np.where(y == CONTACT, (n_pos + 1.0) / (n_pos + 2.0), 1.0 / (n_neg + 2.0))
    center, scale = float(s.mean()), float(s.std())
    if scale == 0.0:  # every score equal: only the intercept is identifiable
        t = float(target.mean())
        return PlattScaling(slope=0.0, intercept=math.log(t / (1.0 - t)))
    u = ((s - center) / scale)[:, None]
    fit = LogisticRegression(C=np.inf, tol=_PLATT_TOL, max_iter=_PLATT_MAX_ITER).fit(
        np.concatenate([u, u]), np.r_[np.ones(len(u)), np.zeros(len(u))], sample_weight=np.r_[target, 1.0 - target])
    slope = float(fit.coef_[0, 0]) / scale
    return PlattScaling(slope=slope, intercept=float(fit.intercept_[0]) - slope * center)


# --------------------------------------------------------------------------------------------
# Leave-one-session-out training
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FoldEvent:
    """Progress report of ``fit_loso``."""

    fold: int  # fold index k, 0-based
    held_out: str  # name of the session left out of fold k
    stage: str  # "loaded" (complete checkpoint reused), "resumed" (partial checkpoint), "epoch", "done"
    epoch: int  # epochs finished in this fold, count
    loss: float | None = None  # mean weighted cross-entropy of the epoch just finished ("epoch"), -


def _fold_seeds(seed: int, fold: int) -> tuple[int, int]:
    """(torch global seed, shuffle seed) of one fold, independent streams."""
    a, b = np.random.SeedSequence([seed, fold]).generate_state(2)
    return int(a), int(b)


def _init_tag(weights: str | Path | None) -> str:
    return "scratch" if weights is None else f"imagenet:{Path(weights).name}"


def _check_crops(sessions: Sequence[SessionCrops], params: BaselineParams) -> list[str]:
    if len(sessions) < 2:
        raise ValueError(f"fit_loso: expected at least 2 training sessions, got {len(sessions)}")
    names = [s.name for s in sessions]
    if len(set(names)) != len(names):
        raise ValueError(f"fit_loso: expected distinct session names, got {names}")
    for s in sessions:
        if not isinstance(s, SessionCrops):
            raise TypeError(f"fit_loso: expected SessionCrops, got {type(s).__name__}")
        if s.crops.shape[1] != params.crop_px:
            raise ValueError(
                f"fit_loso: session {s.name!r} has {s.crops.shape[1]} px crops, params.crop_px is {params.crop_px}"
            )
        if not s.trainable.any():
            raise ValueError(
                f"fit_loso: session {s.name!r} has no labelled frame with a readable image (labels all -1?); "
                "it can be neither trained on nor used for calibration"
            )
    return names


def _fold_info(k: int, names: list[str], sessions: Sequence[SessionCrops], init: str) -> dict[str, Any]:
    return {
        "fold": k,
        "held_out": names[k],
        "train_sessions": [n for i, n in enumerate(names) if i != k],
        "n_frames": [len(s) for s in sessions],
        "init": init,
    }


def _class_weights(labels: np.ndarray, fold_name: str) -> np.ndarray:
    counts = np.array([(labels == NO_CONTACT).sum(), (labels == CONTACT).sum()], dtype=np.float64)
    if (counts == 0).any():
        raise ValueError(
            f"fit_loso, {fold_name}: the training frames hold {int(counts[0])} no-contact and "
            f"{int(counts[1])} contact frames; both classes are needed"
        )
    return counts.sum() / (N_CLASSES * counts)


def _save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    import torch

    with atomic_write(path, "wb") as handle:
        torch.save(payload, handle)


def _load_checkpoint(path: Path) -> dict[str, Any]:
    import torch

    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise ValueError(
            f"{path}: expected a contact-viz baseline fold checkpoint ({type(exc).__name__}: {exc})"
        ) from exc
    if not isinstance(data, dict) or data.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: expected a contact-viz baseline fold checkpoint of format {CHECKPOINT_FORMAT}")
    return data


def _is_complete(path: Path) -> bool:
    """Whether ``path`` holds a completed fold checkpoint (unreadable counts as not complete)."""
    if not path.is_file():
        return False
    try:
        return bool(_load_checkpoint(path).get("complete"))
    except ValueError:
        return False


def _check_checkpoint(path: Path, data: dict[str, Any], params: BaselineParams, info: dict[str, Any]) -> None:
    stored_params, current = data.get("params"), _params_to_dict(params)
    if stored_params != current:
        diff = sorted(k for k in current if not isinstance(stored_params, dict) or stored_params.get(k) != current[k])
        raise ValueError(
            f"{path}: this checkpoint was made with other BaselineParams (differing: {diff}); "
            "use another checkpoint directory or delete it"
        )
    if data.get("fold_info") != info:
        raise ValueError(
            f"{path}: this checkpoint belongs to another run (stored {data.get('fold_info')}, expected {info}); "
            "use another checkpoint directory or delete it"
        )


def _gather(sessions: Sequence[SessionCrops], refs: np.ndarray) -> np.ndarray:
    """Crops of (session, frame) pairs ``refs`` (B, 2) as (B, S, S, 3) uint8."""
    return np.stack([sessions[s].crops[i] for s, i in refs])


def _train_fold(
    k: int,
    sessions: Sequence[SessionCrops],
    names: list[str],
    params: BaselineParams,
    weights: str | Path | None,
    device: torch.device,
    path: Path,
    progress: Callable[[FoldEvent], None] | None,
) -> tuple[torch.nn.Module, np.ndarray]:
    """Train (or load, or resume) fold ``k``; returns (model in eval mode on ``device``, out-of-fold raw scores)."""
    import torch

    info = _fold_info(k, names, sessions, _init_tag(weights))
    data = None
    if path.is_file():
        data = _load_checkpoint(path)
        _check_checkpoint(path, data, params, info)
    torch_seed, shuffle_seed = _fold_seeds(params.seed, k)
    with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
        torch.manual_seed(torch_seed)
        with warnings.catch_warnings():  # fit_loso warns once about training from scratch
            warnings.simplefilter("ignore", BaselineWarning)
            model = build_model(params, None if data is not None else weights).to(device)
        if data is not None and data["complete"]:
            model.load_state_dict(data["model"])
            model.eval()
            if progress is not None:
                progress(FoldEvent(k, names[k], "loaded", int(data["epochs_done"])))
            return model, data["oof_scores"].numpy().astype(np.float64)

        refs = np.concatenate(
            [np.stack([np.full(int(s.trainable.sum()), i), np.flatnonzero(s.trainable)], axis=1)
             for i, s in enumerate(sessions) if i != k]
        )
        train_labels = np.concatenate([s.labels[s.trainable] for i, s in enumerate(sessions) if i != k])
        class_weights = _class_weights(train_labels, f"fold {k} (leaving out {names[k]!r})")
        criterion = torch.nn.CrossEntropyLoss(weight=torch.tensor(class_weights, dtype=torch.float32, device=device))
        optimizer = torch.optim.Adam(model.parameters(), lr=params.lr, weight_decay=params.weight_decay)
        augmentation = make_augmentation(params).to(device)
        shuffle = torch.Generator().manual_seed(shuffle_seed)
        start_epoch = 0
        if data is not None:
            model.load_state_dict(data["model"])
            optimizer.load_state_dict(data["optimizer"])
            torch.set_rng_state(data["rng_torch"])
            shuffle.set_state(data["rng_shuffle"])
            if device.type == "cuda" and "rng_cuda" in data:
                torch.cuda.set_rng_state(data["rng_cuda"], device)
            start_epoch = int(data["epochs_done"])
            if progress is not None:
                progress(FoldEvent(k, names[k], "resumed", start_epoch))
        labels_t = torch.from_numpy(train_labels.astype(np.int64))
        for epoch in range(start_epoch, params.epochs):
            model.train()
            order = torch.randperm(len(refs), generator=shuffle).numpy()
            total, seen = 0.0, 0
            for start in range(0, len(order), params.batch_size):
                batch = order[start : start + params.batch_size]
                x = prepare_batch(_gather(sessions, refs[batch]), device, augmentation)
                y = labels_t[batch].to(device)
                optimizer.zero_grad(set_to_none=True)
                loss = criterion(model(x), y)
                loss.backward()
                optimizer.step()
                total += float(loss.detach()) * len(batch)
                seen += len(batch)
            payload = {
                "format": CHECKPOINT_FORMAT,
                "params": _params_to_dict(params),
                "fold_info": info,
                "complete": False,
                "epochs_done": epoch + 1,
                "model": model.state_dict(),
                "optimizer": optimizer.state_dict(),
                "rng_torch": torch.get_rng_state(),
                "rng_shuffle": shuffle.get_state(),
            }
            if device.type == "cuda":
                payload["rng_cuda"] = torch.cuda.get_rng_state(device)
            _save_checkpoint(path, payload)
            if progress is not None:
                progress(FoldEvent(k, names[k], "epoch", epoch + 1, total / seen))
        oof = raw_scores(model, sessions[k].crops, params.eval_batch_size, device)
        _save_checkpoint(
            path,
            {
                "format": CHECKPOINT_FORMAT,
                "params": _params_to_dict(params),
                "fold_info": info,
                "complete": True,
                "epochs_done": params.epochs,
                "model": model.state_dict(),
                "oof_scores": torch.from_numpy(oof),
            },
        )
        if progress is not None:
            progress(FoldEvent(k, names[k], "done", params.epochs))
    return model, oof


def fit_loso(
    sessions: Sequence[SessionCrops],
    params: BaselineParams,
    checkpoint_dir: str | Path,
    weights: str | Path | None = None,
    device: str | torch.device | None = None,
    progress: Callable[[FoldEvent], None] | None = None,
) -> BaselineEnsemble:
    """Leave-one-session-out training of K = len(sessions) models, Platt calibration and threshold.

    Fold k trains on every session but k (frames labelled 0/1 with a readable image) and scores
    session k. Completed folds found in ``checkpoint_dir`` are loaded, an interrupted fold resumes
    (see the module docstring). A checkpoint made with other params, sessions or init is an error.
    Writes ``checkpoint_dir/ensemble.json`` and returns the fitted ensemble (models on ``device``).
    """
    names = _check_crops(sessions, params)
    directory = Path(checkpoint_dir)
    directory.mkdir(parents=True, exist_ok=True)
    dev = resolve_device(device)
    if weights is not None and not Path(weights).expanduser().is_file():
        raise FileNotFoundError(
            f"{Path(weights).expanduser()}: missing: expected an efficientnet-pytorch ImageNet state dict (.pth) "
            f"for {params.model_name}"
        )
    if weights is None and not all(_is_complete(directory / f"fold_{k}.pt") for k in range(len(sessions))):
        warnings.warn(
            f"no ImageNet weights given (--weights): {params.model_name} trains from scratch",
            BaselineWarning,
            stacklevel=2,
        )
    models, oof = [], []
    for k in range(len(sessions)):
        model, scores = _train_fold(k, sessions, names, params, weights, dev, directory / f"fold_{k}.pt", progress)
        models.append(model)
        oof.append(scores)
    pooled_scores = np.concatenate(oof)
    pooled_labels = np.concatenate([s.labels for s in sessions])
    try:
        platt = fit_platt(pooled_scores, pooled_labels)
        threshold = select_f1_threshold(platt(pooled_scores), pooled_labels)
    except ValueError as exc:
        raise ValueError(f"fit_loso, calibration on pooled out-of-fold scores: {exc}") from exc
    ensemble = BaselineEnsemble(
        params=params,
        session_names=names,
        checkpoints=[f"fold_{k}.pt" for k in range(len(sessions))],
        init=_init_tag(weights),
        platt=platt,
        threshold=threshold,
        oof_scores=oof,
        models=models,
        device=dev,
    )
    ensemble.save(directory / ENSEMBLE_FILE)
    return ensemble


# --------------------------------------------------------------------------------------------
# The ensemble
# --------------------------------------------------------------------------------------------


class BaselineEnsemble:
    """K fold models, their Platt map and decision threshold.

    Attributes:
        params: BaselineParams. session_names_: K training session names (fold k left out session k).
        checkpoints_: K checkpoint file names (relative to the directory of ensemble.json).
        init_: "scratch" or "imagenet:<weights file name>".
        platt_: PlattScaling fitted on the pooled out-of-fold raw scores.
        threshold_: float, ``select_f1_threshold`` on the calibrated pooled out-of-fold probabilities.
        oof_scores_: K (T_k,) float64 out-of-fold raw scores. models_: K torch modules (eval mode).
        device: torch.device the models run on.
    """

    def __init__(
        self,
        *,
        params: BaselineParams,
        session_names: list[str],
        checkpoints: list[str],
        init: str,
        platt: PlattScaling,
        threshold: float,
        oof_scores: list[np.ndarray],
        models: list[Any],
        device: torch.device,
    ) -> None:
        self.params = params
        self.session_names_ = list(session_names)
        self.checkpoints_ = list(checkpoints)
        self.init_ = init
        self.platt_ = platt
        self.threshold_ = float(threshold)
        self.oof_scores_ = [np.asarray(o, dtype=np.float64) for o in oof_scores]
        self.models_ = list(models)
        self.device = device

    def _check_crops(self, crops: Any) -> np.ndarray:
        arr = crops.crops if isinstance(crops, SessionCrops) else crops
        size = self.params.crop_px
        ok = isinstance(arr, np.ndarray) and arr.ndim == 4 and arr.shape[1:] == (size, size, 3)
        if not ok or arr.dtype != np.uint8:
            raise ValueError(
                f"crops: expected SessionCrops or a (T, {size}, {size}, 3) uint8 array, got "
                f"{getattr(arr, 'shape', type(arr).__name__)} {getattr(arr, 'dtype', '')}"
            )
        return arr

    def predict_raw(self, crops: SessionCrops | np.ndarray) -> np.ndarray:
        """Mean over the K models of the raw score (logit difference), (T,) float64."""
        arr = self._check_crops(crops)
        batch = self.params.eval_batch_size
        return np.mean([raw_scores(m, arr, batch, self.device) for m in self.models_], axis=0)

    def predict_proba(self, crops: SessionCrops | np.ndarray) -> np.ndarray:
        """Calibrated P(contact) per frame, (T,) float64: Platt map of ``predict_raw``."""
        return self.platt_(self.predict_raw(crops))

    def predict(self, crops: SessionCrops | np.ndarray) -> np.ndarray:
        """Contact decision per frame, (T,) bool: ``predict_proba >= threshold_``."""
        return self.predict_proba(crops) >= self.threshold_

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (everything but the weights, which stay in the checkpoints)."""
        return {
            "params": _params_to_dict(self.params),
            "session_names": list(self.session_names_),
            "checkpoints": list(self.checkpoints_),
            "init": self.init_,
            "platt": {"slope": self.platt_.slope, "intercept": self.platt_.intercept},
            "threshold": self.threshold_,
            "oof_scores": [[float(v) for v in o] for o in self.oof_scores_],
        }

    def save(self, path: str | Path) -> None:
        """Write ``to_dict`` as JSON to ``path`` atomically (keep it beside the fold checkpoints)."""
        with atomic_write(path, "w", encoding="utf-8") as handle:
            json.dump(self.to_dict(), handle, indent=1)

    @classmethod
    def load(cls, path: str | Path, device: str | torch.device | None = None) -> BaselineEnsemble:
        """Read ``ensemble.json`` and its fold checkpoints (``torch.load(weights_only=True)``)."""
        path = Path(path)
        if path.is_dir():
            path = path / ENSEMBLE_FILE
        if not path.is_file():
            raise FileNotFoundError(f"{path}: missing: expected a baseline ensemble description ({ENSEMBLE_FILE})")
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise ValueError(f"{path}: expected a JSON baseline ensemble description ({exc})") from exc
        expected = {"params", "session_names", "checkpoints", "init", "platt", "threshold", "oof_scores"}
        if not isinstance(data, dict) or set(data) != expected:
            found = sorted(data) if isinstance(data, dict) else type(data).__name__
            raise ValueError(f"{path}: expected keys {sorted(expected)}, found {found}")
        try:
            params = _params_from_dict(BaselineParams, data["params"])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: params: {exc}") from exc
        dev = resolve_device(device)
        models = []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", BaselineWarning)
            for name in data["checkpoints"]:
                ckpt_path = path.parent / name
                if not ckpt_path.is_file():
                    raise FileNotFoundError(f"{ckpt_path}: missing: expected the fold checkpoint named in {path}")
                ckpt = _load_checkpoint(ckpt_path)
                if not ckpt.get("complete") or ckpt.get("params") != _params_to_dict(params):
                    raise ValueError(f"{ckpt_path}: expected a completed fold trained with the params in {path}")
                model = build_model(params)
                model.load_state_dict(ckpt["model"])
                models.append(model.to(dev).eval())
        return cls(
            params=params,
            session_names=data["session_names"],
            checkpoints=data["checkpoints"],
            init=data["init"],
            platt=PlattScaling(float(data["platt"]["slope"]), float(data["platt"]["intercept"])),
            threshold=data["threshold"],
            oof_scores=data["oof_scores"],
            models=models,
            device=dev,
        )
