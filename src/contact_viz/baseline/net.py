"""The EfficientNet model, the device, the input batch and the augmentation (torch, kornia; imported
when called)."""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from contact_viz.baseline.params import (
    BaselineParams, BaselineWarning, CONTACT, IMAGENET_MEAN, IMAGENET_STD, NO_CONTACT, N_CLASSES, PIXEL_MAX,
)

if TYPE_CHECKING:  # torch is imported lazily: importing this module stays cheap
    import torch


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
