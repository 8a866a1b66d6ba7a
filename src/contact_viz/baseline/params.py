"""The baseline's settings (``BaselineParams``), its shared constants and its warning class."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any




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
    width_coefficient: float | None = None  # channel-width multiplier override (None = the architecture's), -
    depth_coefficient: float | None = None  # layer-count multiplier override (None = the architecture's), -
    # batch-norm running-statistics update weight per step, torch convention (None = efficientnet-pytorch's 0.01), -
    bn_momentum: float | None = None
    crop_px: int = 234  # side of the square input crop centred on the tool tip, px
    dropout: float = 0.3  # dropout probability before the two-class linear layer, -
    lr: float = 1e-4  # Adam learning rate, -
    weight_decay: float = 1e-4  # Adam weight decay (L2 penalty), -
    epochs: int = 10  # passes over each fold's training frames (not reported by Yang et al.), count
    batch_size: int = 16  # training batch, frames
    eval_batch_size: int = 32  # inference batch, frames
    rotation_deg: float = 20.0  # random rotation drawn from U(-rotation_deg, rotation_deg), deg
    hflip_p: float = 0.5  # probability of a horizontal flip, -
    color_jitter: float = 0.5  # brightness, contrast and saturation jitter factor, -
    hue_jitter: float = 0.0  # hue jitter, fraction of the hue circle (<= 0.5), -
    erasing_p: float = 0.5  # probability of random erasing, -
    erasing_scale: tuple[float, float] = (0.02, 0.33)  # erased area range, fraction of the crop
    seed: int = 0  # seed of weight init, shuffling, dropout and augmentation, -

    def __post_init__(self) -> None:
        object.__setattr__(self, "erasing_scale", tuple(float(v) for v in self.erasing_scale))
        if not isinstance(self.model_name, str) or not _MODEL_NAME.fullmatch(self.model_name):
            raise ValueError(
                f"BaselineParams.model_name must be efficientnet-b0 .. efficientnet-b8, got {self.model_name!r}"
            )
        for name in ("width_coefficient", "depth_coefficient"):
            value = getattr(self, name)
            if value is not None and not (_is_number(value) and value > 0):
                raise ValueError(f"BaselineParams.{name} must be None or a number > 0, got {value!r}")
        for name in ("crop_px", "epochs", "batch_size", "eval_batch_size"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"BaselineParams.{name} must be a positive integer, got {value!r}")
        if self.bn_momentum is not None and not (_is_number(self.bn_momentum) and 0 < self.bn_momentum <= 1):
            raise ValueError(f"BaselineParams.bn_momentum must be None or in (0, 1], got {self.bn_momentum!r}")
        for name in ("dropout", "hflip_p", "erasing_p"):
            value = getattr(self, name)
            if not (_is_number(value) and 0 <= value <= 1):
                raise ValueError(f"BaselineParams.{name} must be a probability in [0, 1], got {value!r}")
        for name in ("lr", "weight_decay", "rotation_deg", "color_jitter"):
            value = getattr(self, name)
            if not (_is_number(value) and value >= 0):
                raise ValueError(f"BaselineParams.{name} must be a finite number >= 0, got {value!r}")
        if not self.lr > 0:
            raise ValueError(f"BaselineParams.lr must be > 0, got {self.lr!r}")
        if not (_is_number(self.hue_jitter) and 0 <= self.hue_jitter <= 0.5):
            raise ValueError(f"BaselineParams.hue_jitter must be in [0, 0.5], got {self.hue_jitter!r}")
        lo, hi = self.erasing_scale if len(self.erasing_scale) == 2 else (math.nan, math.nan)
        if not (0 < lo <= hi <= 1):
            raise ValueError(
                f"BaselineParams.erasing_scale must be (lo, hi) with 0 < lo <= hi <= 1, got {self.erasing_scale!r}"
            )
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"BaselineParams.seed must be an integer >= 0, got {self.seed!r}")


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
