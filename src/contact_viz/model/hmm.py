"""The minimal supervised two-state Gaussian HMM of the paper (Sec. 2.2) and its LOSO ensemble.

Observation per frame: the scalar signal ``x_t = -log10(max(|d_t|, eps))`` (unit: decades of
metres, written "dec" below; NaN where a frame had no patch). Hidden states: 0 = no contact,
1 = contact, each with a Gaussian emission. The six learned parameters are the two means, the
two variances and the two free transition probabilities; the start distribution is not learned
but set to the stationary distribution of the fitted transition matrix.

Conventions follow hmmlearn: fitted attributes carry a trailing underscore (``means_``,
``vars_``, ``transmat_``, ``startprob_``). Unlike hmmlearn, ``predict_proba`` returns the
*causally filtered* posterior P(contact | x_1..x_t), shape (T,), not the smoothed (T, 2) one.

Model kinds (``HMMParams.model_kind``, :mod:`contact_viz.model.emission`): the paper's Gaussian
emissions (``"paper"``, the default here, exact) or a kind whose emission log-likelihood ratio never
falls as the signal rises; every kind shares the transitions, the start distribution and the forward
filter (:func:`forward_filter_llr`). The monotone kinds need a persistent chain,
P(contact | contact) >= P(contact | no contact), which ``fit`` and ``from_dict`` enforce.

Several instruments (one signal sequence each, see :mod:`contact_viz.model.instruments`):
``LosoEnsemble.fit`` takes a session's instrument sequences and chooses the threshold on its scene
posterior; :class:`SceneStreamingFilter` filters them frame by frame.

Everything here is pure computation on arrays: no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from contact_viz.model.emission import EMISSIONS, MODEL_KINDS, PAPER_KIND, emission_log_likelihood_ratio
from contact_viz.model.instruments import scene_posterior
from contact_viz.params import check_fields, checked
from contact_viz.params import from_dict as _params_from_dict
from contact_viz.params import to_dict as _params_to_dict

N_STATES = 2
NO_CONTACT = 0
CONTACT = 1
UNKNOWN_LABEL = -1
STATE_NAMES = ("no contact", "contact")
STATIONARY_RANK_TOL = 1e-9  # singular values below this count as zero when testing A^T - I for rank n-1


@dataclass(frozen=True)
class HMMParams:
    """Fixed (not learned) settings of the supervised HMM."""

    # lower bound on each state's emission variance, dec^2 (signal units squared)
    var_floor: float = checked(1e-6, gt=0)
    # the emission of contact_viz.model.emission: "paper" (Gaussians, the paper's HMM) or a monotone kind
    model_kind: str = checked(PAPER_KIND, choices=MODEL_KINDS)
    # model kind "isotonic": P(contact | signal) kept within [this, 1 - this], probability
    calibration_min_prob: float = checked(0.01, gt=0, lt=0.5)

    def __post_init__(self) -> None:
        check_fields(self)


class NotFittedError(ValueError):
    """A model was used before ``fit`` (or ``from_dict``)."""


# --------------------------------------------------------------------------------------------
# Input validation
# --------------------------------------------------------------------------------------------


def _check_signal(signal: Any, name: str) -> np.ndarray:
    """``signal`` as a 1-D float64 array whose values are finite or NaN."""
    arr = np.asarray(signal)
    if arr.ndim != 1 or not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise ValueError(f"{name}: expected a 1-D float array (T,), got shape {arr.shape} dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if np.isinf(arr).any():
        raise ValueError(f"{name}: expected finite values or NaN, found {int(np.isinf(arr).sum())} infinite value(s)")
    return arr


def _check_labels(labels: Any, name: str, length: int) -> np.ndarray:
    """``labels`` as a 1-D int64 array of values in {-1, 0, 1} with ``length`` entries."""
    arr = np.asarray(labels)
    if arr.ndim != 1 or not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name}: expected a 1-D integer array (T,), got shape {arr.shape} dtype {arr.dtype}")
    if arr.shape[0] != length:
        raise ValueError(f"{name}: expected {length} labels (one per signal frame), got {arr.shape[0]}")
    bad = ~np.isin(arr, (UNKNOWN_LABEL, NO_CONTACT, CONTACT))
    if bad.any():
        raise ValueError(f"{name}: expected values in {{-1, 0, 1}}, found {sorted(set(arr[bad].tolist()))[:5]}")
    return arr.astype(np.int64, copy=False)


def _check_model(means: Any, vars: Any, transmat: Any, startprob: Any) -> tuple[np.ndarray, ...]:
    """Validated float64 copies of the four parameter arrays of a two-state model."""
    means_a = np.asarray(means, dtype=np.float64)
    vars_a = np.asarray(vars, dtype=np.float64)
    if means_a.shape != (N_STATES,) or not np.isfinite(means_a).all():
        raise ValueError(f"means: expected 2 finite values (dec), got {means_a.tolist()}")
    if vars_a.shape != (N_STATES,) or not (np.isfinite(vars_a).all() and (vars_a > 0).all()):
        raise ValueError(f"vars: expected 2 finite values > 0 (dec^2), got {vars_a.tolist()}")
    return (means_a, vars_a, *_check_chain(transmat, startprob))


def _check_chain(transmat: Any, startprob: Any) -> tuple[np.ndarray, np.ndarray]:
    """Validated float64 copies of a two-state transition matrix and start distribution."""
    trans_a = np.asarray(transmat, dtype=np.float64)
    start_a = np.asarray(startprob, dtype=np.float64)
    if (
        trans_a.shape != (N_STATES, N_STATES)
        or not np.isfinite(trans_a).all()
        or (trans_a < 0).any()
        or not np.allclose(trans_a.sum(axis=1), 1.0, rtol=0, atol=1e-9)
    ):
        raise ValueError(f"transmat: expected a 2x2 row-stochastic matrix, got {trans_a.tolist()}")
    if (
        start_a.shape != (N_STATES,)
        or not np.isfinite(start_a).all()
        or (start_a < 0).any()
        or not math.isclose(float(start_a.sum()), 1.0, rel_tol=0, abs_tol=1e-9)
    ):
        raise ValueError(f"startprob: expected 2 probabilities summing to 1, got {start_a.tolist()}")
    return trans_a, start_a


# --------------------------------------------------------------------------------------------
# Pure model functions
# --------------------------------------------------------------------------------------------


def stationary_distribution(transmat: Any) -> np.ndarray:
    """The stationary distribution pi (pi A = pi, sum 1) of a row-stochastic matrix A, shape (n,).

    Solved as the linear system (A^T - I) pi = 0 with one equation replaced by sum(pi) = 1.
    A reducible chain with a single closed class (e.g. one absorbing state) still has a unique
    stationary distribution and gets it; a chain with several closed classes (e.g. A = I, no
    transition between states ever) has none unique, which is a ValueError.
    """
    a = np.asarray(transmat, dtype=np.float64)
    if a.ndim != 2 or a.shape[0] != a.shape[1] or not np.isfinite(a).all():
        raise ValueError(f"transmat: expected a finite square matrix, got shape {a.shape}")
    n = a.shape[0]
    system = a.T - np.eye(n)
    # the null space of (A^T - I) is one-dimensional exactly when the distribution is unique
    # (round-off in the row sums leaves a singular value of ~1e-17 where the exact one is 0, so
    # the rank needs a tolerance well above machine precision)
    if np.linalg.matrix_rank(system, tol=STATIONARY_RANK_TOL) != n - 1:
        raise ValueError(
            f"transmat {a.tolist()} has no unique stationary distribution (the chain has more than one "
            "closed class, e.g. no transition between the states was ever observed)"
        )
    system[-1, :] = 1.0
    rhs = np.zeros(n)
    rhs[-1] = 1.0
    pi = np.linalg.solve(system, rhs)
    pi = np.clip(pi, 0.0, None)  # round-off may leave -1e-17 where the exact value is 0
    return pi / pi.sum()


def _log_or_minus_inf(value: float) -> float:
    return math.log(value) if value > 0.0 else -math.inf


def _transitions(transmat: np.ndarray) -> tuple[float, float, float, float]:
    """(a00, a01, a10, a11) of a 2x2 transition matrix, as Python floats."""
    return float(transmat[0, 0]), float(transmat[0, 1]), float(transmat[1, 0]), float(transmat[1, 1])


def _prior_log_odds(startprob: np.ndarray) -> float:
    """log pi_1 - log pi_0: the log-odds of contact before the first observation."""
    return _log_or_minus_inf(float(startprob[1])) - _log_or_minus_inf(float(startprob[0]))


def _filter_step(z: float, transitions: tuple[float, float, float, float], llr: float) -> float:
    """The filtered log-odds at frame t from those at t-1 (``z``) and frame t's emission log-likelihood ratio.

    The one step of :func:`forward_filter` and :class:`StreamingFilter`, so the two agree bit for bit.
    """
    a00, a01, a10, a11 = transitions
    # filtered (p0, p1) at t-1 from the log-odds, each side computed without cancellation
    e = math.exp(-abs(z))
    if z >= 0:
        p1, p0 = 1.0 / (1.0 + e), e / (1.0 + e)
    else:
        p1, p0 = e / (1.0 + e), 1.0 / (1.0 + e)
    # prediction A^T p, then the emission update in log-odds
    q1 = p0 * a01 + p1 * a11
    q0 = p0 * a00 + p1 * a10
    return _log_or_minus_inf(q1) - _log_or_minus_inf(q0) + llr


def sigmoid(z: np.ndarray) -> np.ndarray:
    """1 / (1 + exp(-z)) without overflow; exact 0 / 1 at -inf / +inf."""
    e = np.exp(-np.abs(z))
    return np.where(z >= 0, 1.0 / (1.0 + e), e / (1.0 + e))


def check_persistent(transmat: Any, kind: str) -> None:
    """ValueError unless P(contact | contact) >= P(contact | no contact): the condition under which a larger
    posterior at frame t-1 predicts a larger one at frame t, so that a monotone emission gives a monotone
    filter (the model kinds other than the paper's require it)."""
    a = np.asarray(transmat, dtype=np.float64)
    if a[1, 1] < a[0, 1]:
        raise ValueError(
            f"model kind {kind!r}: P(contact | contact) = {a[1, 1]:.4g} is below P(contact | no contact) = "
            f"{a[0, 1]:.4g} (the labels leave contact more often than they stay in it); the posterior would "
            "then fall after frames that read nearer")


def forward_filter_llr(signal: Any, llr: Any, transmat: Any, startprob: Any) -> np.ndarray:
    """The forward filter with any emission: P(contact | x_1..x_t) for every frame t.

    Args:
        signal: (T,) float, the per-frame signal (dec); NaN = no observation at that frame.
        llr: the emission log-likelihood ratio, a function (T,) signal -> (T,) log p(x | contact) -
            log p(x | no contact) (NaN where the signal is NaN), e.g. an emission's
            ``log_likelihood_ratio`` (:mod:`contact_viz.model.emission`).
        transmat: (2, 2) row-stochastic, transmat[i, j] = P(s_t = j | s_{t-1} = i).
        startprob: (2,) distribution of s_0.

    Returns:
        (T,) float64 in [0, 1]: z_0 = log pi_1 - log pi_0 + llr(x_0), then
        z_t = log (A^T p_{t-1})_1 - log (A^T p_{t-1})_0 + llr(x_t) (a NaN frame adds 0: the one-step
        prediction), and sigmoid(z_t). See :func:`forward_filter` for the paper's Gaussian emission.
    """
    x = _check_signal(signal, "signal")
    trans_a, start_a = _check_chain(transmat, startprob)
    n_frames = x.shape[0]
    if n_frames == 0:
        return np.zeros(0, dtype=np.float64)
    evidence = np.asarray(llr(x), dtype=np.float64)
    if evidence.shape != x.shape:
        raise ValueError(f"llr: expected {x.shape[0]} values (one per frame), got shape {evidence.shape}")
    evidence = np.where(np.isnan(evidence), 0.0, evidence).tolist()  # a missing observation adds no evidence

    transitions = _transitions(trans_a)
    log_odds = [0.0] * n_frames
    z = log_odds[0] = _prior_log_odds(start_a) + evidence[0]
    for t in range(1, n_frames):
        z = log_odds[t] = _filter_step(z, transitions, evidence[t])
    return sigmoid(np.asarray(log_odds, dtype=np.float64))


def forward_filter(signal: Any, means: Any, vars: Any, transmat: Any, startprob: Any) -> np.ndarray:
    """Causal forward filtering with the paper's Gaussian emissions: P(contact | x_1..x_t) for every frame t.

    Args:
        signal: (T,) float, the per-frame signal (dec); NaN = no observation at that frame.
        means: (2,) emission means of states (no contact, contact), dec.
        vars: (2,) emission variances, dec^2, > 0.
        transmat: (2, 2) row-stochastic, transmat[i, j] = P(s_t = j | s_{t-1} = i).
        startprob: (2,) distribution of s_0.

    Returns:
        (T,) float64 in [0, 1]. alpha_0 is proportional to pi * e(x_0) and alpha_t to
        e(x_t) * (A^T alpha_{t-1}), normalised at every step; a NaN frame skips the emission term,
        so its value is the one-step prediction. The recursion runs on the log-odds
        z_t = log alpha_t[1] - log alpha_t[0], carrying both p and 1 - p, so extreme
        observations saturate at exactly 0 or 1 instead of underflowing to NaN. The output at
        frame t depends on frames 0..t only. It is :func:`forward_filter_llr` with
        ``emission_log_likelihood_ratio``.
    """
    means_a, vars_a, _, _ = _check_model(means, vars, transmat, startprob)
    return forward_filter_llr(signal, lambda x: emission_log_likelihood_ratio(x, means_a, vars_a),
                              transmat, startprob)


def select_f1_threshold(scores: Any, labels: Any) -> float:
    """The threshold c maximising F1 of ``scores >= c`` against ``labels``.

    Args:
        scores: (n,) finite float scores (e.g. pooled out-of-fold posteriors).
        labels: (n,) int in {-1, 0, 1}; frames labelled -1 (unknown) are excluded.

    Returns:
        The chosen threshold, one of the distinct scores of the labelled frames. Ties in F1 go to
        the smallest such threshold (the one predicting contact on the most frames).
        F1 = 2 TP / (2 TP + FP + FN), computed for every candidate at once from counts sorted by
        score (O(n log n)). At least one frame must be labelled contact.
    """
    s = np.asarray(scores)
    if s.ndim != 1 or not np.issubdtype(s.dtype, np.number):
        raise ValueError(f"scores: expected a 1-D numeric array, got shape {s.shape} dtype {s.dtype}")
    s = s.astype(np.float64, copy=False)
    y = _check_labels(labels, "labels", s.shape[0])
    keep = y != UNKNOWN_LABEL
    s, y = s[keep], y[keep]
    if not np.isfinite(s).all():
        n_bad = int((~np.isfinite(s)).sum())
        raise ValueError(f"scores: expected finite values on labelled frames, found {n_bad} non-finite")
    n_pos = int((y == CONTACT).sum())
    if n_pos == 0:
        raise ValueError(f"labels: no frame labelled contact among {y.shape[0]} labelled frames; F1 is undefined")
    candidates, inverse = np.unique(s, return_inverse=True)  # ascending distinct values
    pos_at = np.bincount(inverse, weights=(y == CONTACT).astype(np.float64), minlength=candidates.shape[0])
    all_at = np.bincount(inverse, minlength=candidates.shape[0]).astype(np.float64)
    # frames with score >= candidates[j]: suffix sums
    tp = np.cumsum(pos_at[::-1])[::-1]
    predicted = np.cumsum(all_at[::-1])[::-1]
    f1 = 2.0 * tp / (n_pos + predicted)  # 2TP / (2TP + FP + FN) with FP + TP = predicted, FN + TP = n_pos
    return float(candidates[int(np.argmax(f1))])  # argmax takes the first = smallest threshold


# --------------------------------------------------------------------------------------------
# The supervised HMM
# --------------------------------------------------------------------------------------------


def _check_keys(data: dict[str, Any], expected: set[str], where: str) -> None:
    """ValueError naming ``where`` unless ``data`` has exactly the keys ``expected``."""
    if set(data) != expected:
        raise ValueError(
            f"{where}: expected keys {sorted(expected)}, "
            f"missing {sorted(expected - set(data))}, unknown {sorted(set(data) - expected)}"
        )


def _check_session_lists(signals: Sequence[Any], labels: Sequence[Any]) -> None:
    """Per-session sequences of signals and labels, one label array per session, at least one session."""
    if isinstance(signals, np.ndarray) or isinstance(labels, np.ndarray):
        raise ValueError("signals, labels: expected sequences (e.g. lists) of per-session 1-D arrays, got an array")
    if len(signals) != len(labels):
        raise ValueError(f"signals, labels: expected one label array per session, got {len(signals)} and {len(labels)}")
    if len(signals) == 0:
        raise ValueError("signals: expected at least one session, got none")


def _check_sessions(
    signals: Sequence[Any], labels: Sequence[Any], names: Sequence[str]
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Validated (signal, labels) pairs, one per session; errors name the session."""
    _check_session_lists(signals, labels)
    out = []
    for name, sig, lab in zip(names, signals, labels):
        x = _check_signal(sig, f"signal of {name}")
        out.append((x, _check_labels(lab, f"labels of {name}", x.shape[0])))
    return out


def _check_scene_sessions(
    signals: Sequence[Any], labels: Sequence[Any], names: Sequence[str],
    scene_labels: Sequence[Any] | None, present: Sequence[Any] | None,
) -> list[tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray, np.ndarray | None]]:
    """Per session of ``LosoEnsemble.fit``: (its (signal, labels) sequences, its scene labels, where each
    instrument is present (None for a session of one sequence)); errors name the session."""
    _check_session_lists(signals, labels)
    for what, given in (("scene_labels", scene_labels), ("present", present)):
        if given is not None and len(given) != len(signals):
            raise ValueError(f"{what}: expected one entry per session ({len(signals)}), got {len(given)}")
    out = []
    for k, (name, sig, lab) in enumerate(zip(names, signals, labels)):
        if np.ndim(sig) != 2:
            x = _check_signal(sig, f"signal of {name}")
            y = _check_labels(lab, f"labels of {name}", x.shape[0])
            out.append(([(x, y)], y, None))
            continue
        rows = np.asarray(sig)
        lab_rows = np.asarray(lab)
        if rows.shape[0] == 0 or lab_rows.shape != rows.shape:
            raise ValueError(f"labels of {name}: expected one label row per instrument signal, shape {rows.shape}, "
                             f"got {lab_rows.shape}")
        sequences = []
        for i in range(rows.shape[0]):
            x = _check_signal(rows[i], f"signal of {name}, instrument row {i}")
            sequences.append((x, _check_labels(lab_rows[i], f"labels of {name}, instrument row {i}", x.shape[0])))
        scene = None if scene_labels is None else scene_labels[k]
        if scene is None:
            raise ValueError(f"scene_labels of {name}: required for a session of several instrument sequences")
        scene = _check_labels(scene, f"scene labels of {name}", rows.shape[1])
        here = None if present is None else present[k]
        here = np.ones(rows.shape, dtype=bool) if here is None else np.asarray(here, dtype=bool)
        if here.shape != rows.shape:
            raise ValueError(f"present of {name}: expected shape {rows.shape}, got {here.shape}")
        out.append((sequences, scene, here))
    return out


class SupervisedGaussianHMM:
    """Two-state HMM fitted by maximum likelihood on fully labelled sessions, with the emission of
    ``params.model_kind`` (the paper's Gaussians by default).

    Fitted attributes (after ``fit`` or ``from_dict``):
        means_: (2,) float64, emission mean per state (0 = no contact, 1 = contact), dec.
        vars_: (2,) float64, emission variance per state (ddof=0, floored at params.var_floor), dec^2.
        transmat_: (2, 2) float64, transmat_[i, j] = n_ij / sum_j n_ij.
        startprob_: (2,) float64, the stationary distribution of transmat_ (not learned).
        n_frames_: (2,) int, frames with a finite signal per state used for means_/vars_.
        transition_counts_: (2, 2) int, n_ij: consecutive labelled pairs (i -> j) within sessions.
        emission_: the fitted emission of the model kind (contact_viz.model.emission), whose
            ``log_likelihood_ratio`` is the per-frame evidence the filter adds.
    """

    def __init__(self, params: HMMParams | None = None) -> None:
        self.params = params if params is not None else HMMParams()

    def fit(self, signals: Sequence[Any], labels: Sequence[Any]) -> SupervisedGaussianHMM:
        """Fit on sessions: ``signals[k]`` (T_k,) float (NaN allowed), ``labels[k]`` (T_k,) int in {-1,0,1}.

        Means and variances use the frames of each state with a finite signal; transitions count
        consecutive label pairs inside each session (never across sessions), skipping pairs with
        an unknown label. Raises ValueError when a state has no finite frame, or when a state was
        never left or never entered (a zero off-diagonal count would make it absorbing, which the
        maximum-likelihood estimate cannot tell apart from missing data).
        """
        sessions = _check_sessions(signals, labels, [f"session {k}" for k in range(len(signals))])
        x_all = np.concatenate([x for x, _ in sessions])
        y_all = np.concatenate([y for _, y in sessions])
        finite = np.isfinite(x_all)
        n_frames = np.array([int(((y_all == s) & finite).sum()) for s in range(N_STATES)])
        counts_text = ", ".join(f"{STATE_NAMES[s]}={n_frames[s]}" for s in range(N_STATES))
        for s in range(N_STATES):
            if n_frames[s] == 0:
                raise ValueError(
                    f"SupervisedGaussianHMM.fit: state {s} ({STATE_NAMES[s]}) has no frame with a finite signal; "
                    f"frames with a finite signal per state: {counts_text}"
                )
        means = np.array([x_all[(y_all == s) & finite].mean() for s in range(N_STATES)])
        raw_vars = np.array([x_all[(y_all == s) & finite].var(ddof=0) for s in range(N_STATES)])
        vars_ = np.maximum(raw_vars, self.params.var_floor)

        counts = np.zeros((N_STATES, N_STATES), dtype=np.int64)
        for _, y in sessions:
            prev, nxt = y[:-1], y[1:]
            both = (prev != UNKNOWN_LABEL) & (nxt != UNKNOWN_LABEL)
            np.add.at(counts, (prev[both], nxt[both]), 1)
        for i in range(N_STATES):
            j = 1 - i
            if counts[i, j] == 0:
                raise ValueError(
                    f"SupervisedGaussianHMM.fit: no transition {STATE_NAMES[i]} -> {STATE_NAMES[j]} in the "
                    f"training labels (transition counts [[n00, n01], [n10, n11]] = {counts.tolist()}); the "
                    f"maximum-likelihood transition matrix would make state {i} ({STATE_NAMES[i]}) "
                    f"{'absorbing' if counts[i].sum() else 'unobserved'}"
                )
        transmat = counts / counts.sum(axis=1, keepdims=True)

        kind = self.params.model_kind
        if kind != PAPER_KIND:
            check_persistent(transmat, kind)
        labelled = finite & (y_all != UNKNOWN_LABEL)
        emission = EMISSIONS[kind]().fit(x_all[labelled], y_all[labelled], means, vars_,
                                         min_prob=self.params.calibration_min_prob)

        self.means_ = means
        self.vars_ = vars_
        self.transmat_ = transmat
        self.startprob_ = stationary_distribution(transmat)
        self.n_frames_ = n_frames
        self.transition_counts_ = counts
        self.emission_ = emission
        return self

    def _check_fitted(self) -> None:
        if not hasattr(self, "transmat_"):
            raise NotFittedError("SupervisedGaussianHMM is not fitted: call fit() or from_dict() first")

    def log_likelihood_ratio(self, signal: Any) -> np.ndarray:
        """The per-frame evidence log p(x | contact) - log p(x | no contact), shape (T,), NaN where x is NaN."""
        self._check_fitted()
        return self.emission_.log_likelihood_ratio(signal)

    def predict_proba(self, signal: Any) -> np.ndarray:
        """Filtered P(contact | x_1..x_t), shape (T,), float64; see ``forward_filter_llr`` (the paper's
        kind: exactly ``forward_filter``)."""
        self._check_fitted()
        return forward_filter_llr(signal, self.emission_.log_likelihood_ratio, self.transmat_, self.startprob_)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (plain floats, ints and lists) of params and fitted attributes (a kind other than
        the paper's adds its emission's under "emission")."""
        self._check_fitted()
        extra = {} if self.params.model_kind == PAPER_KIND else {"emission": self.emission_.to_dict()}
        return {
            "params": _params_to_dict(self.params),
            "means": [float(v) for v in self.means_],
            "vars": [float(v) for v in self.vars_],
            "transmat": [[float(v) for v in row] for row in self.transmat_],
            "startprob": [float(v) for v in self.startprob_],
            "n_frames": [int(v) for v in self.n_frames_],
            "transition_counts": [[int(v) for v in row] for row in self.transition_counts_],
            **extra,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SupervisedGaussianHMM:
        """Rebuild a fitted model from ``to_dict`` output; missing or unknown keys are an error."""
        model = cls(_params_from_dict(HMMParams, data["params"]))
        kind = model.params.model_kind
        keys = {"params", "means", "vars", "transmat", "startprob", "n_frames", "transition_counts"}
        _check_keys(data, keys if kind == PAPER_KIND else keys | {"emission"}, "SupervisedGaussianHMM.from_dict")
        means, vars_, transmat, startprob = _check_model(
            data["means"], data["vars"], data["transmat"], data["startprob"]
        )
        if kind != PAPER_KIND:
            check_persistent(transmat, kind)
        emission = EMISSIONS[kind].from_dict(data.get("emission", {}), means, vars_)
        model.means_, model.vars_, model.transmat_, model.startprob_ = means, vars_, transmat, startprob
        model.emission_ = emission
        model.n_frames_ = np.asarray(data["n_frames"], dtype=np.int64)
        model.transition_counts_ = np.asarray(data["transition_counts"], dtype=np.int64)
        return model


# --------------------------------------------------------------------------------------------
# Leave-one-session-out ensemble
# --------------------------------------------------------------------------------------------


class LosoEnsemble:
    """K supervised HMMs, model k fitted on all training sessions but session k (paper, Sec. 2.2).

    Fitted attributes:
        models_: list of K fitted SupervisedGaussianHMM.
        session_names_: list of K str, the training sessions in fit order.
        oof_posteriors_: list of K (T_k,) float64, session k filtered by models_[k] (out of fold); for a
            session of several instruments, its scene posterior (see ``fit``).
        threshold_: float, ``select_f1_threshold`` on the pooled out-of-fold posteriors.
    """

    def __init__(self, params: HMMParams | None = None) -> None:
        self.params = params if params is not None else HMMParams()

    def fit(
        self,
        signals: Sequence[Any],
        labels: Sequence[Any],
        session_names: Sequence[str] | None = None,
        *,
        scene_labels: Sequence[Any] | None = None,
        present: Sequence[Any] | None = None,
    ) -> LosoEnsemble:
        """Fit on K >= 2 sessions (same inputs as ``SupervisedGaussianHMM.fit``), names default to "session k".

        A session with several instruments gives instead their signals ``signals[k]`` (N_k, T_k), one
        row per instrument (NaN where it is absent or has no patch), with ``labels[k]`` (N_k, T_k) the
        instruments' training labels (:func:`contact_viz.model.instruments.training_labels`),
        ``scene_labels[k]`` (T_k,) the scene's labels and ``present[k]`` (N_k, T_k) bool where each
        instrument is in the frame (None: everywhere); ``scene_labels`` and ``present`` hold None for
        the sessions given as one sequence. Each fold model is then fitted on every instrument
        sequence of the other sessions (transitions counted within a sequence); the held-out
        session's out-of-fold posterior is its scene posterior
        (:func:`contact_viz.model.instruments.scene_posterior` of its instruments' posteriors), and
        the threshold is chosen on the pooled scene posteriors against the scene labels: the
        quantity it is applied to. Sessions of one sequence are fitted and scored exactly as before.
        """
        n_sessions = len(signals)
        if session_names is None:
            names = [f"session {k}" for k in range(n_sessions)]
        else:
            names = [str(n) for n in session_names]
        if len(names) != n_sessions or len(set(names)) != n_sessions:
            raise ValueError(f"session_names: expected {n_sessions} distinct names, got {list(names)}")
        sessions = _check_scene_sessions(signals, labels, names, scene_labels, present)
        if n_sessions < 2:
            raise ValueError(f"LosoEnsemble.fit: expected at least 2 training sessions, got {n_sessions}")
        models, oof = [], []
        for k in range(n_sessions):
            rest = [seq for i in range(n_sessions) if i != k for seq in sessions[i][0]]
            try:
                model = SupervisedGaussianHMM(self.params).fit([x for x, _ in rest], [y for _, y in rest])
            except ValueError as exc:
                raise ValueError(f"LosoEnsemble.fit, fold leaving out {names[k]}: {exc}") from exc
            models.append(model)
            sequences, _, here = sessions[k]
            if here is None:  # one sequence: its posterior
                oof.append(model.predict_proba(sequences[0][0]))
            else:
                oof.append(scene_posterior(np.stack([model.predict_proba(x) for x, _ in sequences]), here))
        pooled_labels = np.concatenate([scene for _, scene, _ in sessions])
        try:
            threshold = select_f1_threshold(np.concatenate(oof), pooled_labels)
        except ValueError as exc:
            raise ValueError(f"LosoEnsemble.fit, threshold on pooled out-of-fold posteriors: {exc}") from exc
        self.models_ = models
        self.session_names_ = names
        self.oof_posteriors_ = oof
        self.threshold_ = threshold
        return self

    def _check_fitted(self) -> None:
        if not hasattr(self, "models_"):
            raise NotFittedError("LosoEnsemble is not fitted: call fit() or from_dict() first")

    def predict_proba(self, signal: Any) -> np.ndarray:
        """Mean over the K models of the filtered P(contact | x_1..x_t), shape (T,), float64."""
        self._check_fitted()
        return np.mean(np.stack([m.predict_proba(signal) for m in self.models_]), axis=0)

    def log_likelihood_ratio(self, signal: Any) -> np.ndarray:
        """Mean over the K models of the per-frame evidence (emission log-likelihood ratio), (T,), NaN where x is NaN."""
        self._check_fitted()
        return np.mean(np.stack([m.log_likelihood_ratio(signal) for m in self.models_]), axis=0)

    def predict(self, signal: Any) -> np.ndarray:
        """Contact decision per frame, (T,) bool: ``predict_proba(signal) >= threshold_``."""
        return self.predict_proba(signal) >= self.threshold_

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict: params, session names, per-fold models, threshold and out-of-fold posteriors."""
        self._check_fitted()
        return {
            "params": _params_to_dict(self.params),
            "session_names": list(self.session_names_),
            "models": [m.to_dict() for m in self.models_],
            "threshold": float(self.threshold_),
            "oof_posteriors": [[float(v) for v in p] for p in self.oof_posteriors_],
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LosoEnsemble:
        """Rebuild a fitted ensemble from ``to_dict`` output; missing or unknown keys are an error."""
        _check_keys(data, {"params", "session_names", "models", "threshold", "oof_posteriors"},
                    "LosoEnsemble.from_dict")
        n = len(data["session_names"])
        if len(data["models"]) != n or len(data["oof_posteriors"]) != n or n < 2:
            raise ValueError(
                f"LosoEnsemble.from_dict: expected K >= 2 session names, models and out-of-fold posteriors, "
                f"got {n}, {len(data['models'])}, {len(data['oof_posteriors'])}"
            )
        ens = cls(_params_from_dict(HMMParams, data["params"]))
        ens.models_ = [SupervisedGaussianHMM.from_dict(m) for m in data["models"]]
        kinds = sorted({m.params.model_kind for m in ens.models_})
        if kinds != [ens.params.model_kind]:
            raise ValueError(f"LosoEnsemble.from_dict: the ensemble's model kind is {ens.params.model_kind!r}, "
                             f"its models' {kinds}")
        ens.session_names_ = [str(s) for s in data["session_names"]]
        ens.oof_posteriors_ = [np.asarray(p, dtype=np.float64) for p in data["oof_posteriors"]]
        ens.threshold_ = float(data["threshold"])
        return ens


# --------------------------------------------------------------------------------------------
# Streaming (frame-by-frame) causal filter
# --------------------------------------------------------------------------------------------


class StreamingFilter:
    """``forward_filter`` fed one observation at a time, for one model or the mean of an ensemble.

    ``update(x)`` returns P(contact | x_1..x_t) for the frame just given (NaN x = no observation:
    the one-step prediction), equal to ``predict_proba`` on the whole sequence so far, bit for bit:
    the recursion performs the same floating-point operations in the same order, with each model's
    emission. With an ensemble the value is the mean over its K models, as
    ``LosoEnsemble.predict_proba`` computes it. After an update, ``evidence`` is that frame's emission
    log-likelihood ratio (the mean over the K models, as ``LosoEnsemble.log_likelihood_ratio``; NaN
    for no observation). Memory is O(K), whatever the sequence length.
    """

    def __init__(self, model: SupervisedGaussianHMM | LosoEnsemble) -> None:
        if isinstance(model, LosoEnsemble):
            model._check_fitted()
            models = list(model.models_)
        elif isinstance(model, SupervisedGaussianHMM):
            model._check_fitted()
            models = [model]
        else:
            raise TypeError(
                f"model: expected a fitted SupervisedGaussianHMM or LosoEnsemble, got {type(model).__name__}"
            )
        self._params = [(m.emission_.log_likelihood_ratio, *_check_chain(m.transmat_, m.startprob_)) for m in models]
        self._log_odds: list[float] | None = None  # per model, after the last update; None before the first
        self.frames = 0
        self.evidence = math.nan  # the last frame's emission log-likelihood ratio (NaN: none yet, or no observation)

    def reset(self) -> None:
        """Forget every observation (the next update is frame 0 again)."""
        self._log_odds = None
        self.frames = 0
        self.evidence = math.nan

    def update(self, x: float) -> float:
        """Add the next frame's signal ``x`` (dec; NaN = missing) and return the filtered P(contact)."""
        x = float(x)
        if math.isinf(x):
            raise ValueError(f"x: expected a finite signal value or NaN, got {x!r}")
        new, evidence = [], []
        for k, (log_likelihood_ratio, trans, start) in enumerate(self._params):
            llr = float(log_likelihood_ratio(np.array([x]))[0])
            evidence.append(llr)
            if math.isnan(llr):
                llr = 0.0
            if self._log_odds is None:
                z = _prior_log_odds(start) + llr
            else:
                z = _filter_step(self._log_odds[k], _transitions(trans), llr)
            new.append(z)
        self._log_odds = new
        self.evidence = float(np.mean(evidence))
        self.frames += 1
        posteriors = sigmoid(np.asarray(new, dtype=np.float64))
        total = posteriors[0]
        for value in posteriors[1:]:  # the same order of additions as np.mean(..., axis=0) over the stack
            total = total + value
        return float(total / len(new))


class SceneStreamingFilter:
    """:class:`StreamingFilter` per instrument and the scene posterior, fed one frame at a time.

    ``update({object id: signal})`` takes the instruments in the frame (NaN signal = in the frame
    without a patch) and returns (the scene's P(contact), {object id: P(contact)} of every
    instrument seen so far). Each instrument's filter runs over every frame (a NaN observation
    where it is absent; one that first appears at frame t is caught up on t missing frames), and
    the scene posterior is :func:`contact_viz.model.instruments.scene_posterior`'s max over the
    instruments in the frame (over all of them in a frame without one), so the values equal
    ``pipeline.features.score_features`` on the whole session, bit for bit, whatever the number
    of instruments. Before any instrument was seen it is the prediction of a filter without
    observations (a session's frames without any instrument give exactly that).
    """

    def __init__(self, model: SupervisedGaussianHMM | LosoEnsemble) -> None:
        self._model = model
        self._blank = StreamingFilter(model)  # fed NaN on every frame: a new instrument's history
        self._filters: dict[int, StreamingFilter] = {}
        self.frames = 0

    def reset(self) -> None:
        """Forget every frame and instrument."""
        self._blank.reset()
        self._filters.clear()
        self.frames = 0

    def update(self, signals: dict[int, float]) -> tuple[float, dict[int, float]]:
        """Add the next frame's instruments {object id: signal, dec (NaN = no patch)}; returns (scene, each one's)."""
        for tool in sorted(signals):
            if tool not in self._filters:
                caught_up = StreamingFilter(self._model)
                for _ in range(self.frames):
                    caught_up.update(math.nan)
                self._filters[tool] = caught_up
        blank = self._blank.update(math.nan)
        each = {tool: f.update(signals.get(tool, math.nan)) for tool, f in sorted(self._filters.items())}
        self.frames += 1
        if len(each) == 1:  # one instrument: its posterior, present or not
            return next(iter(each.values())), each
        here = [each[tool] for tool in signals]
        return (max(here) if here else max(each.values(), default=blank)), each
