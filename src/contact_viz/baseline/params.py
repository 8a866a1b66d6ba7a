"""The baseline's settings (``BaselineParams``), its shared constants and its warning class."""

from __future__ import annotations

import re
from dataclasses import dataclass

from contact_viz.params import check_fields, checked


IMAGENET_MEAN = (0.485, 0.456, 0.406)  # per-channel mean of ImageNet RGB in [0, 1], -
IMAGENET_STD = (0.229, 0.224, 0.225)  # per-channel standard deviation of ImageNet RGB in [0, 1], -
N_CLASSES = 2  # no contact, contact
CONTACT, NO_CONTACT, UNKNOWN_LABEL = 1, 0, -1
CHECKPOINT_FORMAT = 1  # version of the fold checkpoint layout
ENSEMBLE_FILE = "ensemble.json"  # name of the ensemble description in the checkpoint directory
PIXEL_MAX = 255.0  # uint8 full scale
_MODEL_NAME = re.compile(r"efficientnet-b[0-8]")  # architectures efficientnet-pytorch builds by name


class BaselineWarning(UserWarning):
    """Something about the baseline run the user should know (e.g. training from scratch)."""


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
