"""A nearer tool never looks less in contact (issue 34): the monotone model kinds, property-tested.

For random parameter draws of every kind claimed monotone (contact_viz.model.emission.MONOTONE_KINDS)
and random signal sequences (NaN frames, the cap 4.0, values far beyond any training range), raising
the signal at any frame never lowers the causal posterior at that frame or any later one, and leaves
the earlier frames exactly as they were. The paper's kind fails the same check (the test can fail), and
so does a monotone emission with a chain that is not persistent (the condition the model enforces).
hypothesis is not installed here: the draws are NumPy's, many of them, from fixed seeds.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import norm
from sklearn.isotonic import IsotonicRegression

from contact_viz.model.emission import (
    EMISSIONS,
    FIT_DEFAULT_KIND,
    MODEL_KINDS,
    MONOTONE_KINDS,
    emission_log_likelihood_ratio,
    isotonic_fit,
    monotone_interp,
)
from contact_viz.model.hmm import (
    HMMParams,
    LosoEnsemble,
    StreamingFilter,
    SupervisedGaussianHMM,
    forward_filter,
    forward_filter_llr,
    stationary_distribution,
)
from contact_viz.model.instruments import scene_posterior

CAP = 4.0  # the signal of |d| <= eps_m = 0.1 mm
ROUNDING = 1e-12  # a posterior may lose this much to rounding in log/exp of the filter step (it never did)
DRAWS = 300  # parameter draws per kind


def random_chain(rng: np.random.Generator) -> np.ndarray:
    """A persistent 2x2 transition matrix: P(c | c) >= P(c | n), sometimes equal (frames independent)."""
    a01 = rng.uniform(0.001, 0.6)
    a11 = a01 if rng.random() < 0.1 else rng.uniform(a01, 0.999)
    return np.array([[1.0 - a01, a01], [1.0 - a11, a11]])


def random_model(kind: str, rng: np.random.Generator) -> SupervisedGaussianHMM:
    """A model of ``kind`` with random parameters, built through from_dict (the path of a model file)."""
    m0 = rng.uniform(0.0, 3.5)
    ordered = kind in ("tied", "clip")  # these need m1 >= m0; the others take any order
    m1 = m0 + rng.uniform(0.0, 2.0) if ordered else rng.uniform(0.0, 4.0)
    v0, v1 = 10.0 ** rng.uniform(-4, 0, size=2)
    if rng.random() < 0.05:
        v1 = v0
    transmat = random_chain(rng)
    data = {"params": {"var_floor": 1e-6, "model_kind": kind, "calibration_min_prob": 0.01},
            "means": [m0, m1], "vars": [v0, v1], "transmat": transmat.tolist(),
            "startprob": stationary_distribution(transmat).tolist(), "n_frames": [10, 10],
            "transition_counts": [[5, 1], [1, 5]]}
    if kind == "tied":
        data["emission"] = {"var": float(10.0 ** rng.uniform(-4, 0))}
    elif kind == "clip":
        vertex = math.nan if v0 == v1 else (m1 * v0 - m0 * v1) / (v0 - v1)
        low, high = np.sort(rng.uniform(-1.0, 5.0, size=2))
        if v1 < v0:
            high = min(high, vertex)
            low = min(low, high)
        elif v1 > v0:
            low = max(low, vertex)
            high = max(low, high)
        data["emission"] = {"low": float(low), "high": float(high)}
    elif kind == "isotonic":
        k = int(rng.integers(1, 12))
        knots = np.sort(rng.uniform(0.0, 4.0, size=k))
        knots = np.unique(knots)
        llr = np.sort(rng.normal(0.0, 4.0, size=knots.shape[0]))
        if knots.shape[0] > 2:
            llr[1] = llr[2]  # a flat step
        data["emission"] = {"knots": knots.tolist(), "llr": llr.tolist(), "prior": float(rng.uniform(0.05, 0.9))}
    elif kind != "paper":
        data["emission"] = {}
    return SupervisedGaussianHMM.from_dict(data)


def random_signal(rng: np.random.Generator) -> np.ndarray:
    """1-40 frames: uniform over [-1, 5] dec (beyond any training range at both ends), the cap 4.0
    often, NaN (no patch) sometimes."""
    n = int(rng.integers(1, 41))
    x = rng.uniform(-1.0, 5.0, size=n)
    x[rng.random(n) < 0.2] = CAP
    x[rng.random(n) < 0.1] = np.nan
    return x


def raised(rng: np.random.Generator, x: np.ndarray) -> tuple[np.ndarray, int] | None:
    """``x`` with one finite frame's signal raised (to the cap, past it, or by a random step); None if
    no frame is finite."""
    finite = np.flatnonzero(np.isfinite(x))
    if finite.size == 0:
        return None
    t = int(rng.choice(finite))
    y = x.copy()
    choice = rng.random()
    y[t] = max(x[t], CAP) if choice < 0.3 else x[t] + 10.0 if choice < 0.4 else x[t] + rng.exponential(0.5)
    return y, t


def violations(predict, rng: np.random.Generator, sequences: int) -> list[tuple]:
    """(t, before, after) of every raise that lowered the posterior at frame t or later by more than
    ROUNDING; also asserts that the frames before t did not change at all (causality)."""
    out = []
    for _ in range(sequences):
        x = random_signal(rng)
        change = raised(rng, x)
        if change is None:
            continue
        y, t = change
        before, after = predict(x), predict(y)
        np.testing.assert_array_equal(after[:t], before[:t])
        worst = int(np.argmin(after[t:] - before[t:]))
        if after[t + worst] < before[t + worst] - ROUNDING:
            out.append((t, x.tolist(), y.tolist(), before[t + worst], after[t + worst]))
    return out


# ------------------------------------------------------------------ the property


@pytest.mark.parametrize("kind", MONOTONE_KINDS)
def test_raising_the_signal_never_lowers_the_posterior_random_draws(kind):
    rng = np.random.default_rng(3400 + MODEL_KINDS.index(kind))
    found = []
    for _ in range(DRAWS):
        model = random_model(kind, rng)
        found += violations(model.predict_proba, rng, sequences=8)
    assert found == [], f"{kind}: {len(found)} raises lowered the posterior, e.g. {found[0]}"


@pytest.mark.parametrize("kind", MONOTONE_KINDS)
def test_the_emission_evidence_never_falls_as_the_signal_rises(kind):
    rng = np.random.default_rng(77 + MODEL_KINDS.index(kind))
    grid = np.concatenate([np.linspace(-3.0, 8.0, 4001), [CAP]])
    grid.sort()
    for _ in range(DRAWS):
        llr = random_model(kind, rng).log_likelihood_ratio(grid)
        assert np.isfinite(llr).all()
        assert (np.diff(llr) >= 0).all(), kind  # exactly, in floating point


def test_the_default_kind_is_claimed_monotone():
    assert FIT_DEFAULT_KIND in MONOTONE_KINDS


@pytest.mark.parametrize("kind", MONOTONE_KINDS)
def test_fitted_ensembles_and_the_scene_posterior_are_monotone(kind):
    """Models fitted on random labelled sessions (the LOSO ensemble's mean of K posteriors), and the scene
    posterior (the max over two instruments' posteriors)."""
    rng = np.random.default_rng(11 + MODEL_KINDS.index(kind))
    for _ in range(6):
        signals, labels = [], []
        for _ in range(3):
            states = np.repeat(rng.integers(0, 2, size=12), rng.integers(3, 15, size=12))
            states[:3], states[-3:] = 0, 1  # both states, both transitions, in every session
            states[4] = 1
            x = rng.normal(np.where(states == 1, rng.uniform(2.4, 3.2), rng.uniform(1.2, 2.0)),
                           np.where(states == 1, rng.uniform(0.05, 0.3), rng.uniform(0.2, 0.6)))
            x[rng.random(x.shape[0]) < 0.05] = np.nan
            signals.append(x)
            labels.append(states.astype(np.int64))
        ensemble = LosoEnsemble(HMMParams(model_kind=kind)).fit(signals, labels)
        assert violations(ensemble.predict_proba, rng, sequences=60) == []
        other = random_signal(rng)

        def scene(x, other=other):
            n = min(x.shape[0], other.shape[0])
            both = np.stack([ensemble.predict_proba(x[:n]), ensemble.predict_proba(other[:n])])
            return np.concatenate([scene_posterior(both), ensemble.predict_proba(x)[n:]])

        assert violations(scene, rng, sequences=60) == []


def test_the_paper_kind_is_not_monotone_the_demos_model():
    """The demo's model (issue 34, its parameters rounded): 1 mm is strong evidence of contact, 0.1 mm (the
    cap) evidence against it, so a tool that comes nearer lowers the posterior; the same raise with the
    flat kind raises it."""
    means, variances = np.array([1.78, 2.81]), np.array([0.197, 0.051])
    transmat = np.array([[0.984, 0.016], [0.049, 0.951]])
    start = stationary_distribution(transmat)
    llr = emission_log_likelihood_ratio(np.array([3.0, 3.7, CAP]), means, variances)
    by_hand = [-0.5 * math.log(variances[1] / variances[0]) - (x - means[1]) ** 2 / (2 * variances[1])
               + (x - means[0]) ** 2 / (2 * variances[0]) for x in (3.0, 3.7, CAP)]
    np.testing.assert_allclose(llr, by_hand, rtol=1e-12)
    assert llr[0] > 4.0 and 2.0 < llr[1] < 2.5 and llr[2] < -0.5  # 1 mm, 0.2 mm, 0.1 mm
    x = np.array([1.5, 2.8, 2.8, 3.0, 2.9])
    y = x.copy()
    y[3] = CAP
    paper = [forward_filter(s, means, variances, transmat, start) for s in (x, y)]
    assert paper[1][3] < paper[0][3] - 0.1  # 0.998 -> 0.784
    flat = EMISSIONS["flat"]().fit(np.zeros(0), np.zeros(0, np.int64), means, variances)
    after = [forward_filter_llr(s, flat.log_likelihood_ratio, transmat, start) for s in (x, y)]
    assert (after[1][3:] >= after[0][3:]).all() and after[1][3] > after[0][3]


def test_the_paper_kind_fails_the_property_test():
    rng = np.random.default_rng(5)
    found = []
    for _ in range(60):
        found += violations(random_model("paper", rng).predict_proba, rng, sequences=8)
    assert len(found) > 20


# ------------------------------------------------------------------ the chain's condition


def flickering_sessions():
    """Labels that leave contact more often than they stay: P(c | c) < P(c | n)."""
    labels = np.array([0, 1, 0, 0, 1, 1, 0, 1, 0, 1, 0, 0, 1, 0] * 4, dtype=np.int64)
    x = np.where(labels == 1, 3.0, 1.5) + np.linspace(-0.1, 0.1, labels.shape[0])
    return [x, x[::-1].copy()], [labels, labels[::-1].copy()]


def test_a_chain_that_is_not_persistent_breaks_monotonicity():
    """Why the condition: with P(c | c) < P(c | n), a nearer frame t (more contact at t) predicts less
    contact at t + 1, so even a monotone emission gives a posterior that falls there."""
    means, variances = np.array([1.5, 3.0]), np.array([0.2, 0.05])
    transmat = np.array([[0.5, 0.5], [0.9, 0.1]])
    flat = EMISSIONS["flat"]().fit(np.zeros(0), np.zeros(0, np.int64), means, variances)
    start = stationary_distribution(transmat)
    x, y = np.array([1.5, 2.0, 2.0]), np.array([1.5, 3.0, 2.0])
    before, after = (forward_filter_llr(s, flat.log_likelihood_ratio, transmat, start) for s in (x, y))
    assert after[1] > before[1] and after[2] < before[2]


@pytest.mark.parametrize("kind", MONOTONE_KINDS)
def test_fit_and_from_dict_refuse_a_chain_that_is_not_persistent(kind):
    signals, labels = flickering_sessions()
    SupervisedGaussianHMM().fit(signals, labels)  # the paper's kind fits it, as the paper would
    pairs = [(int(a), int(b)) for y in labels for a, b in zip(y[:-1], y[1:])]
    stay = pairs.count((1, 1)) / (pairs.count((1, 1)) + pairs.count((1, 0)))
    enter = pairs.count((0, 1)) / (pairs.count((0, 1)) + pairs.count((0, 0)))
    assert stay < enter
    with pytest.raises(ValueError, match=rf"P\(contact \| contact\) = {stay:.4g} is below P\(contact \| no "
                                         rf"contact\) = {enter:.4g}"):
        SupervisedGaussianHMM(HMMParams(model_kind=kind)).fit(signals, labels)
    rng = np.random.default_rng(2)
    data = random_model(kind, rng).to_dict()
    data["transmat"] = [[0.5, 0.5], [0.9, 0.1]]
    data["startprob"] = stationary_distribution(np.array(data["transmat"])).tolist()
    with pytest.raises(ValueError, match=r"P\(contact \| contact\)"):
        SupervisedGaussianHMM.from_dict(data)


@pytest.mark.parametrize("kind", ["tied", "clip"])
def test_kinds_that_need_ordered_means_refuse_others(kind):
    x = np.array([3.0, 3.1, 2.9, 1.0, 1.1, 0.9, 3.0, 1.0])
    y = np.array([0, 0, 0, 1, 1, 1, 0, 1], dtype=np.int64)
    with pytest.raises(ValueError, match="mean signal .* below the no-contact"):
        SupervisedGaussianHMM(HMMParams(model_kind=kind)).fit([x, x.copy()], [y, y.copy()])


# ------------------------------------------------------------------ the generalised forward pass


def test_forward_filter_llr_worked_example():
    """llr(x) = 2x - 1, A = [[0.9, 0.1], [0.2, 0.8]], pi = (2/3, 1/3), signal (1, NaN, 0), by hand in
    probability space: alpha_0 ~ pi * (1, e^1); frame 1 the prediction A^T alpha_0; frame 2 the prediction
    times (1, e^-1)."""
    transmat = np.array([[0.9, 0.1], [0.2, 0.8]])
    start = np.array([2 / 3, 1 / 3])
    got = forward_filter_llr(np.array([1.0, np.nan, 0.0]), lambda x: 2.0 * x - 1.0, transmat, start)
    e = math.e
    p0 = (1 / 3 * e) / (2 / 3 + 1 / 3 * e)  # = 0.5e / (1 + 0.5e) = 0.576...
    p1 = (1 - p0) * 0.1 + p0 * 0.8  # no observation: the one-step prediction
    c = (1 - p1) * 0.1 + p1 * 0.8  # predicted contact at frame 2
    p2 = c / e / (c / e + (1 - p1) * 0.9 + p1 * 0.2)
    np.testing.assert_allclose(got, [p0, p1, p2], rtol=0, atol=1e-14)
    assert round(p0, 4) == 0.5761 and round(p1, 4) == 0.5033 and round(p2, 4) == 0.2330


def test_forward_filter_llr_with_the_paper_emission_is_forward_filter_bit_for_bit():
    rng = np.random.default_rng(8)
    for _ in range(50):
        model = random_model("paper", rng)
        x = random_signal(rng)
        a = forward_filter(x, model.means_, model.vars_, model.transmat_, model.startprob_)
        b = forward_filter_llr(x, lambda s: emission_log_likelihood_ratio(s, model.means_, model.vars_),
                               model.transmat_, model.startprob_)
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, model.predict_proba(x))


def test_forward_filter_llr_refuses_a_function_of_another_length():
    with pytest.raises(ValueError, match="llr: expected 3 values"):
        forward_filter_llr(np.zeros(3), lambda x: np.zeros(2), np.eye(2) * 0.5 + 0.25, [0.5, 0.5])


# ------------------------------------------------------------------ each kind against its definition


def runs(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n,) labels in runs of 5-25 frames, alternating, starting with no contact: a persistent chain."""
    lengths = rng.integers(5, 26, size=n)
    return (np.repeat(np.arange(n) % 2, lengths)[:n]).astype(np.int64)


def test_flat_tails_are_the_paper_between_the_means_and_flat_densities_outside():
    means, variances = np.array([1.7, 2.9]), np.array([0.2, 0.05])
    flat = EMISSIONS["flat"]().fit(np.zeros(0), np.zeros(0, np.int64), means, variances)
    x = np.linspace(-1.0, 6.0, 701)
    contact = norm.logpdf(np.minimum(x, means[1]), means[1], math.sqrt(variances[1]))  # held at its peak above
    none = norm.logpdf(np.maximum(x, means[0]), means[0], math.sqrt(variances[0]))  # held at its peak below
    np.testing.assert_allclose(flat.log_likelihood_ratio(x), contact - none, rtol=1e-12, atol=1e-9)
    between = (x >= means[0]) & (x <= means[1])
    np.testing.assert_allclose(flat.log_likelihood_ratio(x[between]),
                               emission_log_likelihood_ratio(x[between], means, variances), atol=1e-12)
    assert np.isnan(flat.log_likelihood_ratio(np.array([np.nan])))[0]


def test_tied_is_the_gaussian_ratio_with_the_pooled_variance():
    rng = np.random.default_rng(1)
    y = runs(rng, 500)
    x = np.where(y == 1, rng.normal(2.9, 0.2, 500), rng.normal(1.7, 0.45, 500))
    model = SupervisedGaussianHMM(HMMParams(model_kind="tied")).fit([x[:250], x[250:]], [y[:250], y[250:]])
    pooled = (((x[y == 0] - x[y == 0].mean()) ** 2).sum() + ((x[y == 1] - x[y == 1].mean()) ** 2).sum()) / 500
    assert model.emission_.var_ == pytest.approx(pooled, rel=1e-12)
    grid = np.linspace(-1, 6, 71)
    sd = math.sqrt(pooled)
    expected = norm.logpdf(grid, x[y == 1].mean(), sd) - norm.logpdf(grid, x[y == 0].mean(), sd)
    np.testing.assert_allclose(model.log_likelihood_ratio(grid), expected, rtol=1e-9, atol=1e-9)


def test_isotonic_fit_worked_example():
    """Pool-adjacent-violators by hand: y = 0, 1, 0, 1 at x = 1..4 pools the middle pair to 0.5; the fit is
    linear between its knots and constant beyond them."""
    knots, values = isotonic_fit(np.array([1.0, 2.0, 3.0, 4.0]), np.array([0.0, 1.0, 0.0, 1.0]))
    query = np.array([0.0, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 9.0])
    np.testing.assert_allclose(monotone_interp(query, knots, values),
                               [0.0, 0.0, 0.25, 0.5, 0.5, 0.5, 0.75, 1.0, 1.0], rtol=0, atol=1e-12)


def test_isotonic_evidence_is_the_calibrated_posterior_against_the_prior():
    rng = np.random.default_rng(6)
    y = runs(rng, 800)
    x = np.where(y == 1, rng.normal(2.8, 0.3, 800), rng.normal(1.8, 0.5, 800))
    model = SupervisedGaussianHMM(HMMParams(model_kind="isotonic", calibration_min_prob=0.02)).fit(
        [x[:400], x[400:]], [y[:400], y[400:]])
    query = np.linspace(-1, 6, 141)
    reference = IsotonicRegression(out_of_bounds="clip").fit(x, y)  # its steps, then the llr linear between them
    p = np.clip(reference.y_thresholds_, 0.02, 0.98)
    prior = y.mean()
    expected = np.interp(query, reference.X_thresholds_, np.log(p / (1 - p)) - math.log(prior / (1 - prior)))
    np.testing.assert_allclose(model.log_likelihood_ratio(query), expected, rtol=0, atol=1e-9)


def test_clip_is_the_paper_ratio_of_the_clipped_signal_on_the_rising_side():
    rng = np.random.default_rng(9)
    y = runs(rng, 600)
    x = np.where(y == 1, rng.normal(2.8, 0.15, 600), rng.normal(1.7, 0.45, 600))
    model = SupervisedGaussianHMM(HMMParams(model_kind="clip")).fit([x[:300], x[300:]], [y[:300], y[300:]])
    (m0, m1), (v0, v1) = model.means_, model.vars_
    vertex = (m1 * v0 - m0 * v1) / (v0 - v1)
    assert model.emission_.low_ == x.min() and model.emission_.high_ == min(x.max(), vertex)
    grid = np.linspace(-1, 6, 141)
    expected = emission_log_likelihood_ratio(np.clip(grid, x.min(), min(x.max(), vertex)), model.means_, model.vars_)
    np.testing.assert_allclose(model.log_likelihood_ratio(grid), expected, rtol=1e-12, atol=1e-9)


# ------------------------------------------------------------------ files and the streaming filter


@pytest.mark.parametrize("kind", MODEL_KINDS)
def test_every_kind_round_trips_and_streams_bit_for_bit(kind):
    rng = np.random.default_rng(21)
    y = np.repeat(rng.integers(0, 2, 30), rng.integers(2, 9, 30)).astype(np.int64)
    y[:2], y[-2:] = 0, 1
    x = np.where(y == 1, rng.normal(2.8, 0.2, y.shape[0]), rng.normal(1.7, 0.4, y.shape[0]))
    ensemble = LosoEnsemble(HMMParams(model_kind=kind)).fit([x[:100], x[100:], x[::-1].copy()],
                                                             [y[:100], y[100:], y[::-1].copy()])
    again = LosoEnsemble.from_dict(ensemble.to_dict())
    test = random_signal(np.random.default_rng(3))
    np.testing.assert_array_equal(again.predict_proba(test), ensemble.predict_proba(test))
    assert again.params.model_kind == kind
    stream = StreamingFilter(again)
    values, evidence = [], []
    for v in test:
        values.append(stream.update(v))
        evidence.append(stream.evidence)
    np.testing.assert_array_equal(values, ensemble.predict_proba(test))
    np.testing.assert_allclose(evidence, ensemble.log_likelihood_ratio(test), rtol=1e-12, atol=1e-12)
