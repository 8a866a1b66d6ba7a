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
``contact-viz import yang2024 --labels``). Frames whose mask gives no tip are cropped at the session's
last known tip, or the image centre before
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

from contact_viz.baseline.crops import IMAGE_CENTER, LAST_TIP, TIP_FILE, TIP_FOUND, SessionCrops, extract_crops
from contact_viz.baseline.ensemble import BaselineEnsemble
from contact_viz.baseline.loso import FoldEvent, fit_loso
from contact_viz.baseline.net import build_model, make_augmentation, prepare_batch, raw_scores, resolve_device
from contact_viz.baseline.params import ENSEMBLE_FILE, BaselineParams, BaselineWarning
from contact_viz.baseline.platt import PlattScaling, fit_platt

__all__ = [
    "ENSEMBLE_FILE",
    "IMAGE_CENTER",
    "LAST_TIP",
    "TIP_FILE",
    "TIP_FOUND",
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
