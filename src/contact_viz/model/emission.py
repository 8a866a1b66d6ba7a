"""The contact model's kinds: how a frame's signal becomes evidence for contact.

Every kind is a two-state HMM with the same transitions (counted from the labels) and the same
forward filter; the kinds differ only in the per-frame **emission log-likelihood ratio**
``llr(x) = log p(x | contact) - log p(x | no contact)`` of the signal ``x = -log10(max(|d|, eps))``
(dec; larger = nearer). The filter adds ``llr(x_t)`` to the predicted log-odds of frame t.

* ``paper``: a Gaussian per state (the paper's six-parameter HMM). With the contact state's variance
  the smaller, ``llr`` is a downward parabola: past its vertex a *nearer* tool is *less* evidence of
  contact (the demo's model: +2.1 at 0.2 mm, -0.96 at 0.1 mm, the cap).
* ``flat``: the paper's Gaussians with the contact state's density held at its peak above its mean
  and the no-contact state's held at its peak below its mean (``x`` nearer than the contact mean reads
  as the contact mean for the contact state; farther than the no-contact mean as that mean for the
  no-contact state). Nondecreasing for any parameters; unbounded above (quadratic).
* ``tied``: one variance for both states (the frames' pooled within-state variance): ``llr`` is a
  line of slope ``(m1 - m0) / v``; needs ``m1 >= m0``.
* ``isotonic``: ``P(contact | x)`` fitted on the training frames by isotonic (nondecreasing)
  regression, kept within ``[min_prob, 1 - min_prob]``; at each of its steps'
  ends ``llr = logit P(contact | x) - logit(prior)``, the prior being the training frames' contact
  share (Bayes' rule turns a posterior into a likelihood ratio); linear between them, constant
  beyond the training range.
* ``clip``: the paper's ``llr`` of the signal clipped to the training range and to the rising side of
  the parabola's vertex (a range alone does not do: the demo's vertex, 3.17 dec, is inside it);
  needs ``m1 >= m0``.

Each kind's ``llr`` of every kind but ``paper`` is nondecreasing in ``x``, exactly in floating point
(each is written as a chain of operations that are each monotone under rounding). With a persistent
chain (``P(c|c) >= P(c|n)``, enforced by :mod:`contact_viz.model.hmm` for these kinds) the causal
posterior then never decreases when any frame's signal rises (tests/test_monotone.py).

Classes follow hmmlearn's conventions: ``fit`` sets the attributes with a trailing underscore. They
are fitted on the training frames with a finite signal and a known label, given the HMM's per-state
means and (floored) variances. Pure computation on arrays: no I/O.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from contact_viz.model.kinds import FIT_DEFAULT_KIND, MODEL_KINDS, MONOTONE_KINDS, PAPER_KIND

__all__ = ["EMISSIONS", "FIT_DEFAULT_KIND", "MODEL_KINDS", "MONOTONE_KINDS", "PAPER_KIND", "ClippedEmission",
           "FlatTailEmission", "GaussianEmission", "IsotonicEmission", "TiedEmission", "emission_log_likelihood_ratio",
           "isotonic_fit", "monotone_interp"]


def _pair(values: Any) -> tuple[float, float]:
    return float(values[0]), float(values[1])


def emission_log_likelihood_ratio(signal: np.ndarray, means: np.ndarray, vars: np.ndarray) -> np.ndarray:
    """log N(x; m1, v1) - log N(x; m0, v0) per frame, shape (T,), float64; NaN where x is NaN."""
    x = np.asarray(signal, dtype=np.float64)
    m0, m1 = float(means[0]), float(means[1])
    v0, v1 = float(vars[0]), float(vars[1])
    return -0.5 * math.log(v1 / v0) - (x - m1) ** 2 / (2.0 * v1) + (x - m0) ** 2 / (2.0 * v0)


def _require_ordered_means(means: Any, kind: str) -> None:
    m0, m1 = _pair(means)
    if m1 < m0:
        raise ValueError(
            f"model kind {kind!r}: the contact state's mean signal {m1:.4g} dec is below the no-contact state's "
            f"{m0:.4g} dec (the signal does not rise toward contact in these sessions); its evidence would "
            "fall as the tool nears the tissue")


def _check_finite(data: dict[str, Any], keys: tuple[str, ...], where: str) -> None:
    for key in keys:
        value = data.get(key)
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
            raise ValueError(f"{where}: expected a finite number for {key!r}, got {value!r}")


class GaussianEmission:
    """The paper's emission: a Gaussian per state. Not monotone (see the module docstring)."""

    kind = PAPER_KIND
    monotone = False

    def fit(self, signal: np.ndarray, labels: np.ndarray, means: Any, vars: Any,
            min_prob: float = 0.0) -> GaussianEmission:
        """Nothing beyond the HMM's means and variances."""
        self.means_, self.vars_ = np.asarray(means, np.float64), np.asarray(vars, np.float64)
        return self

    @classmethod
    def _with_gaussians(cls, means: Any, vars: Any) -> GaussianEmission:
        """An unfitted instance holding the HMM's means and variances only: what each from_dict builds on."""
        return GaussianEmission.fit(cls(), np.zeros(0), np.zeros(0, np.int64), means, vars)

    def log_likelihood_ratio(self, signal: Any) -> np.ndarray:
        return emission_log_likelihood_ratio(signal, self.means_, self.vars_)

    def to_dict(self) -> dict[str, Any]:
        return {}

    @classmethod
    def from_dict(cls, data: dict[str, Any], means: Any, vars: Any) -> GaussianEmission:
        return cls._with_gaussians(means, vars)


class FlatTailEmission(GaussianEmission):
    """The paper's Gaussians, the contact one held flat above its mean, the no-contact one below its mean.

    llr(x) = -log(v1 / v0) / 2 - min(x - m1, 0)^2 / (2 v1) + max(x - m0, 0)^2 / (2 v0): the first square
    shrinks and the second grows as x rises, for any means and variances."""

    kind = "flat"
    monotone = True

    def log_likelihood_ratio(self, signal: Any) -> np.ndarray:
        x = np.asarray(signal, dtype=np.float64)
        m0, m1 = _pair(self.means_)
        v0, v1 = _pair(self.vars_)
        below_contact = np.minimum(x - m1, 0.0)  # NaN stays NaN
        above_none = np.maximum(x - m0, 0.0)
        return -0.5 * math.log(v1 / v0) - below_contact ** 2 / (2.0 * v1) + above_none ** 2 / (2.0 * v0)


class TiedEmission(GaussianEmission):
    """Gaussians with one variance: the training frames' pooled within-state variance.

    Fitted attribute: ``var_`` (dec^2), sum over states of n_s v_s / (n0 + n1), at least the smaller
    of the two (floored) variances' floor. llr(x) = (m1 - m0) / v_ * (x - (m0 + m1) / 2)."""

    kind = "tied"
    monotone = True

    def fit(self, signal: np.ndarray, labels: np.ndarray, means: Any, vars: Any,
            min_prob: float = 0.0) -> TiedEmission:
        super().fit(signal, labels, means, vars)
        _require_ordered_means(self.means_, self.kind)
        counts = np.array([np.count_nonzero(labels == s) for s in (0, 1)], dtype=np.float64)
        self.var_ = float((counts * self.vars_).sum() / counts.sum())
        return self

    def log_likelihood_ratio(self, signal: Any) -> np.ndarray:
        x = np.asarray(signal, dtype=np.float64)
        m0, m1 = _pair(self.means_)
        return ((m1 - m0) / self.var_) * (x - 0.5 * (m0 + m1))

    def to_dict(self) -> dict[str, Any]:
        return {"var": float(self.var_)}

    @classmethod
    def from_dict(cls, data: dict[str, Any], means: Any, vars: Any) -> TiedEmission:
        _check_finite(data, ("var",), "tied emission")
        if not data["var"] > 0:
            raise ValueError(f"tied emission: expected var > 0 (dec^2), got {data['var']!r}")
        model = cls._with_gaussians(means, vars)
        _require_ordered_means(model.means_, cls.kind)
        model.var_ = float(data["var"])
        return model


class ClippedEmission(GaussianEmission):
    """The paper's llr of the signal clipped to [``low_``, ``high_``]: the training range, cut at the
    parabola's vertex on the side where the llr falls (v1 < v0: above it; v1 > v0: below it).

    Written around the vertex x* = (m1 v0 - m0 v1) / (v0 - v1) as llr(x*) - a (x - x*)^2 with
    a = (1/v1 - 1/v0) / 2, so that it rises exactly in floating point on the clipped range."""

    kind = "clip"
    monotone = True

    def fit(self, signal: np.ndarray, labels: np.ndarray, means: Any, vars: Any,
            min_prob: float = 0.0) -> ClippedEmission:
        super().fit(signal, labels, means, vars)
        _require_ordered_means(self.means_, self.kind)
        low, high = float(np.min(signal)), float(np.max(signal))
        vertex = self._vertex()
        v0, v1 = _pair(self.vars_)
        if v1 < v0:
            high = min(high, vertex)
        elif v1 > v0:
            low = max(low, vertex)
        self.low_, self.high_ = low, max(low, high)
        return self

    def _vertex(self) -> float:
        m0, m1 = _pair(self.means_)
        v0, v1 = _pair(self.vars_)
        return math.nan if v0 == v1 else (m1 * v0 - m0 * v1) / (v0 - v1)

    def log_likelihood_ratio(self, signal: Any) -> np.ndarray:
        x = np.clip(np.asarray(signal, dtype=np.float64), self.low_, self.high_)  # NaN stays NaN
        m0, m1 = _pair(self.means_)
        v0, v1 = _pair(self.vars_)
        if v0 == v1:  # a line of slope (m1 - m0) / v >= 0
            return ((m1 - m0) / v0) * (x - 0.5 * (m0 + m1))
        vertex = self._vertex()
        top = float(emission_log_likelihood_ratio(np.array([vertex]), self.means_, self.vars_)[0])
        curvature = 0.5 * (1.0 / v1 - 1.0 / v0)  # > 0: a maximum at the vertex (x <= it); < 0: a minimum (x >= it)
        return top - curvature * (x - vertex) ** 2

    def to_dict(self) -> dict[str, Any]:
        return {"low": float(self.low_), "high": float(self.high_)}

    @classmethod
    def from_dict(cls, data: dict[str, Any], means: Any, vars: Any) -> ClippedEmission:
        _check_finite(data, ("low", "high"), "clip emission")
        model = cls._with_gaussians(means, vars)
        _require_ordered_means(model.means_, cls.kind)
        low, high, vertex = float(data["low"]), float(data["high"]), model._vertex()
        v0, v1 = _pair(model.vars_)
        if not (low <= high and (v1 >= v0 or high <= vertex) and (v1 <= v0 or low >= vertex)):
            raise ValueError(f"clip emission: expected low <= high on the rising side of the vertex {vertex:.4g} "
                             f"dec, got low {low!r}, high {high!r}")
        model.low_, model.high_ = low, high
        return model


def isotonic_fit(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Isotonic (nondecreasing) least-squares regression of ``y`` on ``x`` (scikit-learn's
    IsotonicRegression): (knots, values), the fit at each knot, linear between knots and constant beyond
    them. ``x`` finite (n,), ``y`` (n,) float, n >= 1."""
    from sklearn.isotonic import IsotonicRegression  # only when fitting: loading a model does not need it

    fitted = IsotonicRegression(out_of_bounds="clip").fit(x, y)
    return np.asarray(fitted.X_thresholds_, np.float64), np.asarray(fitted.y_thresholds_, np.float64)


def monotone_interp(x: np.ndarray, knots: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Piecewise-linear interpolation through (knots, values) (knots increasing, values nondecreasing),
    constant beyond the ends, NaN for NaN; each segment's value is kept within its end values, so the
    result is nondecreasing in x exactly in floating point (np.interp may overshoot a knot by one ulp)."""
    x = np.asarray(x, dtype=np.float64)
    if knots.shape[0] == 1:
        return np.where(np.isnan(x), np.nan, values[0])
    j = np.clip(np.searchsorted(knots, x, side="right") - 1, 0, knots.shape[0] - 2)
    lo, hi = values[j], values[j + 1]
    t = np.clip((x - knots[j]) / (knots[j + 1] - knots[j]), 0.0, 1.0)
    return np.minimum(np.maximum(lo + t * (hi - lo), lo), hi)  # NaN x -> NaN t -> NaN


def _logit(p: np.ndarray | float) -> np.ndarray:
    return np.log(p) - np.log1p(-np.asarray(p))


class IsotonicEmission(GaussianEmission):
    """llr(x) = logit P(contact | x) - logit(prior), P(contact | x) by isotonic regression on the training frames.

    Fitted attributes: ``knots_`` (k,) dec increasing (each step's first and last signal), ``llr_`` (k,)
    nondecreasing: the llr at each knot (linear between, constant beyond); ``prior_``: the training frames' contact share. ``min_prob`` keeps
    P(contact | x) within [min_prob, 1 - min_prob] (a block of frames all in contact is not certainty)."""

    kind = "isotonic"
    monotone = True

    def fit(self, signal: np.ndarray, labels: np.ndarray, means: Any, vars: Any,
            min_prob: float = 0.01) -> IsotonicEmission:
        super().fit(signal, labels, means, vars)
        x = np.asarray(signal, dtype=np.float64)
        y = (np.asarray(labels) == 1).astype(np.float64)
        knots, probs = isotonic_fit(x, y)
        self.prior_ = float(y.mean())
        self.knots_ = knots
        self.llr_ = _logit(np.clip(probs, min_prob, 1.0 - min_prob)) - float(_logit(self.prior_))
        self.llr_ = np.maximum.accumulate(self.llr_)  # nondecreasing also after rounding
        return self

    def log_likelihood_ratio(self, signal: Any) -> np.ndarray:
        return monotone_interp(np.asarray(signal, dtype=np.float64), self.knots_, self.llr_)

    def to_dict(self) -> dict[str, Any]:
        return {"knots": [float(v) for v in self.knots_], "llr": [float(v) for v in self.llr_],
                "prior": float(self.prior_)}

    @classmethod
    def from_dict(cls, data: dict[str, Any], means: Any, vars: Any) -> IsotonicEmission:
        _check_finite(data, ("prior",), "isotonic emission")
        knots = np.asarray(data.get("knots", []), dtype=np.float64)
        llr = np.asarray(data.get("llr", []), dtype=np.float64)
        if (knots.ndim != 1 or knots.shape != llr.shape or knots.shape[0] == 0 or not np.isfinite(knots).all()
                or not np.isfinite(llr).all() or (np.diff(knots) <= 0).any() or (np.diff(llr) < 0).any()):
            raise ValueError("isotonic emission: expected knots (increasing) and llr (nondecreasing) of one "
                             "length >= 1, finite")
        model = cls._with_gaussians(means, vars)
        model.knots_, model.llr_, model.prior_ = knots, llr, float(data["prior"])
        return model


EMISSIONS: dict[str, type[GaussianEmission]] = {
    cls.kind: cls for cls in (GaussianEmission, FlatTailEmission, TiedEmission, IsotonicEmission, ClippedEmission)}
assert tuple(EMISSIONS) == MODEL_KINDS and MONOTONE_KINDS == tuple(k for k, c in EMISSIONS.items() if c.monotone)
