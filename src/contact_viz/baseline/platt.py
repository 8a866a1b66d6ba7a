"""Platt scaling of raw scores: p = sigmoid(a z + b), fitted on the log-loss with Platt's smoothed
targets by scikit-learn's unpenalised logistic regression with sample weights."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from contact_viz.baseline.params import CONTACT, NO_CONTACT, UNKNOWN_LABEL
from contact_viz.model.hmm import sigmoid as _sigmoid


_PLATT_TOL = 1e-10  # scikit-learn's lbfgs stopping tolerance of the Platt fit (gradient), -
_PLATT_MAX_ITER = 1000  # lbfgs iterations of the Platt fit, count


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
