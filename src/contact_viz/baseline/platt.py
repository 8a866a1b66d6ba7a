"""Platt scaling of raw scores: p = sigmoid(a z + b), fitted by Newton's method on the log-loss with
Platt's smoothed targets."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from contact_viz.baseline.params import CONTACT, NO_CONTACT, UNKNOWN_LABEL
from contact_viz.model.hmm import sigmoid as _sigmoid


_PLATT_MAX_ITER = 100  # Newton iterations of the Platt fit, count
_PLATT_GRAD_TOL = 1e-10  # stop when the mean log-loss gradient is below this, -
_PLATT_MAX_HALVINGS = 60  # step halvings of one Newton line search, count


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
    (N+ + 1)/(N+ + 2) for contact and 1/(N- + 2) for no contact, by Newton's method with step
    halving, on standardised scores (then mapped back). Both classes must be present.
    """
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
    u = (s - center) / scale
    design = np.stack([u, np.ones_like(u)], axis=1)  # (n, 2)

    def loss(w: np.ndarray) -> float:
        z = design @ w
        return float(np.sum(np.logaddexp(0.0, z) - target * z))

    w = np.array([0.0, math.log(target.mean() / (1.0 - target.mean()))])
    current = loss(w)
    for _ in range(_PLATT_MAX_ITER):
        p = _sigmoid(design @ w)
        grad = design.T @ (p - target)
        if np.max(np.abs(grad)) < _PLATT_GRAD_TOL * len(u):
            break
        hess = (design * (p * (1.0 - p))[:, None]).T @ design
        step = np.linalg.lstsq(hess, grad, rcond=None)[0]
        for _ in range(_PLATT_MAX_HALVINGS):
            trial = w - step
            trial_loss = loss(trial)
            if trial_loss <= current:
                break
            step = step / 2.0
        else:
            break  # no decrease possible: at the minimum to machine precision
        w, current = trial, trial_loss
    slope = w[0] / scale
    return PlattScaling(slope=float(slope), intercept=float(w[1] - slope * center))
