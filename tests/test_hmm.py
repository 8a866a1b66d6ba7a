"""Tests of the supervised two-state HMM, its forward filter, the F1 threshold and the LOSO ensemble."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from sklearn.metrics import f1_score

from contact_viz.model.hmm import (
    HMMParams,
    LosoEnsemble,
    NotFittedError,
    StreamingFilter,
    SupervisedGaussianHMM,
    forward_filter,
    select_f1_threshold,
    stationary_distribution,
)

TRUE_MEANS = np.array([0.5, 2.5])  # dec
TRUE_VARS = np.array([0.30, 0.15])  # dec^2
TRUE_TRANSMAT = np.array([[0.95, 0.05], [0.10, 0.90]])


def sample_session(rng: np.random.Generator, n_frames: int, nan_frac: float = 0.05, unknown_frac: float = 0.03):
    """(signal, labels, true_states) of one session drawn from the known HMM above."""
    states = np.empty(n_frames, dtype=np.int64)
    states[0] = rng.integers(2)
    for t in range(1, n_frames):
        states[t] = rng.choice(2, p=TRUE_TRANSMAT[states[t - 1]])
    signal = rng.normal(TRUE_MEANS[states], np.sqrt(TRUE_VARS[states]))
    signal[rng.random(n_frames) < nan_frac] = np.nan
    labels = states.copy()
    labels[rng.random(n_frames) < unknown_frac] = -1
    return signal, labels, states


def slow_fit(signals, labels):
    """Literal maximum-likelihood estimate with Python loops: means, vars (ddof=0), counts, transmat."""
    sums, sq, n = [0.0, 0.0], [0.0, 0.0], [0, 0]
    for x, y in zip(signals, labels):
        for xt, yt in zip(x.tolist(), y.tolist()):
            if yt in (0, 1) and xt == xt:  # xt == xt is False for NaN
                sums[yt] += xt
                n[yt] += 1
    means = [sums[s] / n[s] for s in (0, 1)]
    for x, y in zip(signals, labels):
        for xt, yt in zip(x.tolist(), y.tolist()):
            if yt in (0, 1) and xt == xt:
                sq[yt] += (xt - means[yt]) ** 2
    variances = [sq[s] / n[s] for s in (0, 1)]
    counts = [[0, 0], [0, 0]]
    for y in labels:
        for t in range(1, len(y)):
            if y[t - 1] != -1 and y[t] != -1:
                counts[y[t - 1]][y[t]] += 1
    transmat = [[counts[i][j] / (counts[i][0] + counts[i][1]) for j in (0, 1)] for i in (0, 1)]
    return np.array(means), np.array(variances), np.array(counts), np.array(transmat)


@pytest.fixture(scope="module")
def sessions():
    rng = np.random.default_rng(12345)
    out = [sample_session(rng, n) for n in (700, 500, 600)]
    return [s for s, _, _ in out], [y for _, y, _ in out]


# ------------------------------------------------------------------ forward filter


def test_forward_filter_hand_worked_example():
    # means (0, 1), equal variances 1: the emission ratio e1(x)/e0(x) = exp(x - 1/2)
    # (the normalising constants cancel). A = [[0.9, 0.1], [0.2, 0.8]];
    # pi = stationary = (2/3, 1/3)  (check: 2/3 * 0.1 = 1/3 * 0.2).
    transmat = np.array([[0.9, 0.1], [0.2, 0.8]])
    startprob = np.array([2 / 3, 1 / 3])
    signal = np.array([0.5 + np.log(3.0), 0.5, 0.5 - np.log(2.0), np.nan])  # ratios 3, 1, 1/2, (missing)
    # t=0: alpha ∝ (2/3 * 1, 1/3 * 3) = (2/3, 1)          -> P(contact) = 1 / (5/3) = 3/5 = 0.6
    # t=1: predict 0.4*0.1 + 0.6*0.8 = 0.52; ratio 1      -> 0.52
    # t=2: predict 0.48*0.1 + 0.52*0.8 = 0.464; ratio 1/2 -> 0.232 / (0.232 + 0.536) = 29/96
    # t=3: NaN, prediction only: (67/96)*0.1 + (29/96)*0.8 = 29.9/96 = 299/960
    expected = np.array([0.6, 0.52, 29 / 96, 299 / 960])
    got = forward_filter(signal, [0.0, 1.0], [1.0, 1.0], transmat, startprob)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)


def test_forward_filter_matches_hmmlearn():
    hmm = pytest.importorskip("hmmlearn.hmm")
    means, variances = np.array([0.3, 2.1]), np.array([0.4, 0.09])
    transmat = np.array([[0.93, 0.07], [0.12, 0.88]])
    startprob = np.array([0.7, 0.3])  # deliberately not stationary: the filter takes any pi
    rng = np.random.default_rng(7)
    signal = rng.normal(1.2, 1.0, 40)

    ref = hmm.GaussianHMM(n_components=2, covariance_type="diag", init_params="", params="")
    ref.startprob_ = startprob
    ref.transmat_ = transmat
    ref.means_ = means[:, None]
    ref.covars_ = variances[:, None]
    # hmmlearn exposes only smoothed posteriors; at the last frame of a prefix the smoothed
    # posterior equals the filtered one, so P(contact | x_1..x_t) = last row on the prefix 0..t.
    expected = np.array([ref.predict_proba(signal[: t + 1, None])[-1, 1] for t in range(signal.size)])
    got = forward_filter(signal, means, variances, transmat, startprob)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-10)


def test_forward_filter_is_causal_exactly():
    rng = np.random.default_rng(3)
    signal = rng.normal(1.5, 1.2, 200)
    args = ([0.5, 2.5], [0.3, 0.15], TRUE_TRANSMAT, [2 / 3, 1 / 3])
    before = forward_filter(signal, *args)
    changed = signal.copy()
    changed[120:] = rng.normal(0.0, 5.0, 80)
    changed[150] = np.nan
    after = forward_filter(changed, *args)
    assert np.array_equal(before[:120], after[:120])
    assert not np.array_equal(before[120:], after[120:])


def test_forward_filter_range_and_extremes_without_warnings():
    rng = np.random.default_rng(4)
    signal = np.concatenate([rng.normal(1.5, 3.0, 500), [1e6, -1e6, 4.0, -1e3, 1e3]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        post = forward_filter(signal, [0.5, 2.5], [1e-6, 0.15], TRUE_TRANSMAT, [2 / 3, 1 / 3])
    assert np.isfinite(post).all()
    assert (post >= 0).all() and (post <= 1).all()


def test_nan_frame_is_one_step_prediction():
    rng = np.random.default_rng(5)
    signal = rng.normal(1.5, 1.0, 30)
    nan_at = [0, 7, 8, 20]
    signal[nan_at] = np.nan
    transmat = TRUE_TRANSMAT
    startprob = np.array([0.6, 0.4])
    post = forward_filter(signal, [0.5, 2.5], [0.3, 0.15], transmat, startprob)
    assert post[0] == pytest.approx(startprob[1], abs=1e-12)  # no evidence at t=0: the prior
    for t in nan_at[1:]:
        predicted = (1 - post[t - 1]) * transmat[0, 1] + post[t - 1] * transmat[1, 1]
        assert post[t] == pytest.approx(predicted, abs=1e-12)


def test_forward_filter_bad_input():  # its speed: benchmarks/bench_hmm.py
    with pytest.raises(ValueError, match="signal"):
        forward_filter(np.array([0.0, np.inf]), [0.5, 2.5], [0.3, 0.15], TRUE_TRANSMAT, [0.5, 0.5])
    with pytest.raises(ValueError, match="vars"):
        forward_filter(np.zeros(3), [0.5, 2.5], [0.0, 0.15], TRUE_TRANSMAT, [0.5, 0.5])
    with pytest.raises(ValueError, match="transmat"):
        forward_filter(np.zeros(3), [0.5, 2.5], [0.3, 0.15], [[0.5, 0.6], [0.1, 0.9]], [0.5, 0.5])


# ------------------------------------------------------------------ stationary distribution


def test_stationary_distribution():
    for transmat in (TRUE_TRANSMAT, np.array([[0.2, 0.8], [0.6, 0.4]]), np.array([[0.0, 1.0], [1.0, 0.0]])):
        pi = stationary_distribution(transmat)
        np.testing.assert_allclose(pi @ transmat, pi, rtol=0, atol=1e-12)
        assert pi.sum() == pytest.approx(1.0, abs=1e-12)
    # closed form for two states: pi = (a10, a01) / (a01 + a10)
    np.testing.assert_allclose(stationary_distribution(TRUE_TRANSMAT), [0.10 / 0.15, 0.05 / 0.15], atol=1e-12)
    # one absorbing state: reducible but unique
    np.testing.assert_allclose(stationary_distribution([[0.9, 0.1], [0.0, 1.0]]), [0.0, 1.0], atol=1e-12)
    with pytest.raises(ValueError, match="no unique stationary"):
        stationary_distribution(np.eye(2))
    # counts 80/1 and 1/17 (a fitted fold of a synthetic study): row sums off by round-off only
    fitted = np.array([[80 / 81, 1 / 81], [1 / 18, 17 / 18]])
    np.testing.assert_allclose(stationary_distribution(fitted), [(1 / 18) / (1 / 81 + 1 / 18), (1 / 81) / (1 / 81 + 1 / 18)],
                               atol=1e-12)


# ------------------------------------------------------------------ fitting


def test_fit_matches_slow_count_and_recovers_truth(sessions):
    signals, labels = sessions
    model = SupervisedGaussianHMM().fit(signals, labels)
    means, variances, counts, transmat = slow_fit(signals, labels)
    np.testing.assert_allclose(model.means_, means, rtol=0, atol=1e-12)
    np.testing.assert_allclose(model.vars_, variances, rtol=0, atol=1e-12)
    assert np.array_equal(model.transition_counts_, counts)
    np.testing.assert_allclose(model.transmat_, transmat, rtol=0, atol=1e-15)
    np.testing.assert_allclose(model.startprob_ @ model.transmat_, model.startprob_, atol=1e-12)
    # ~1800 frames: sampling error on these is a few hundredths
    np.testing.assert_allclose(model.means_, TRUE_MEANS, atol=0.08)
    np.testing.assert_allclose(model.vars_, TRUE_VARS, atol=0.06)
    np.testing.assert_allclose(model.transmat_, TRUE_TRANSMAT, atol=0.04)


def test_transitions_not_counted_across_sessions():
    a = (np.array([0.1, 2.0, 2.1, 0.2]), np.array([0, 1, 1, 0]))  # 0->1, 1->1, 1->0
    b = (np.array([2.2, 0.3, 0.1]), np.array([1, 0, 0]))  # 1->0, 0->0
    c = (np.array([0.4, 2.3]), np.array([0, 1]))  # 0->1
    model = SupervisedGaussianHMM().fit([a[0], b[0], c[0]], [a[1], b[1], c[1]])
    separate = np.array([[1, 2], [2, 1]])
    # concatenated would also count a->b (0 -> 1) and b->c (0 -> 0)
    concatenated = np.array([[2, 3], [2, 1]])
    assert np.array_equal(model.transition_counts_, separate)
    np.testing.assert_allclose(model.transmat_, [[1 / 3, 2 / 3], [2 / 3, 1 / 3]], rtol=0, atol=1e-15)
    joined = SupervisedGaussianHMM().fit([np.concatenate([a[0], b[0], c[0]])], [np.concatenate([a[1], b[1], c[1]])])
    assert np.array_equal(joined.transition_counts_, concatenated)


def test_unknown_labels_and_nan_frames():
    x = np.array([0.1, np.nan, 2.0, 2.2, 0.3, 2.6, 2.4, 0.1])
    y = np.array([0, 0, 1, -1, 0, 1, 1, 0])
    model = SupervisedGaussianHMM().fit([x], [y])
    # pairs: (0,0) (0,1) [(1,-1) skipped] [(-1,0) skipped] (0,1) (1,1) (1,0); the NaN frame still has a label
    assert np.array_equal(model.transition_counts_, [[1, 2], [1, 1]])
    # emissions: state 0 uses 0.1, 0.3, 0.1 (NaN frame dropped); state 1 uses 2.0, 2.6, 2.4 (2.2 is unknown)
    assert np.array_equal(model.n_frames_, [3, 3])
    np.testing.assert_allclose(model.means_, [0.5 / 3, 7.0 / 3], rtol=0, atol=1e-15)
    var0 = ((0.1 - 0.5 / 3) ** 2 * 2 + (0.3 - 0.5 / 3) ** 2) / 3
    var1 = ((2.0 - 7 / 3) ** 2 + (2.6 - 7 / 3) ** 2 + (2.4 - 7 / 3) ** 2) / 3
    np.testing.assert_allclose(model.vars_, [var0, var1], rtol=0, atol=1e-15)


def test_degenerate_data_errors_and_floor():
    x = np.array([0.1, 0.2, 2.0, 2.1, 0.3])
    # contact frames all without a finite signal
    with pytest.raises(ValueError, match=r"state 1 \(contact\).*no contact=3, contact=0"):
        SupervisedGaussianHMM().fit([np.array([0.1, 0.2, np.nan, np.nan, 0.3])], [np.array([0, 0, 1, 1, 0])])
    # no transition from contact back to no contact
    with pytest.raises(ValueError, match="no transition contact -> no contact"):
        SupervisedGaussianHMM().fit([x[:4]], [np.array([0, 0, 1, 1])])
    # zero variance -> floor
    params = HMMParams(var_floor=1e-4)
    model = SupervisedGaussianHMM(params).fit([np.array([0.2, 0.2, 2.0, 2.1, 0.2])], [np.array([0, 0, 1, 1, 0])])
    assert model.vars_[0] == 1e-4
    assert model.vars_[1] == pytest.approx(0.0025, abs=1e-15)
    assert np.isfinite(model.predict_proba(x)).all()
    # malformed input
    with pytest.raises(ValueError, match="labels of session 0"):
        SupervisedGaussianHMM().fit([x], [np.array([0, 0, 1, 2, 0])])
    with pytest.raises(ValueError, match="labels of session 0.*5 labels"):
        SupervisedGaussianHMM().fit([x], [np.array([0, 1, 0])])
    with pytest.raises(ValueError, match="signal of session 0"):
        SupervisedGaussianHMM().fit([np.array([0.1, np.inf, 2.0, 2.1, 0.3])], [np.array([0, 0, 1, 1, 0])])
    with pytest.raises(ValueError, match="var_floor"):
        HMMParams(var_floor=0.0)
    with pytest.raises(NotFittedError):
        SupervisedGaussianHMM().predict_proba(x)


def test_model_round_trip(sessions):
    signals, labels = sessions
    model = SupervisedGaussianHMM().fit(signals, labels)
    data = json.loads(json.dumps(model.to_dict()))
    back = SupervisedGaussianHMM.from_dict(data)
    assert np.array_equal(back.predict_proba(signals[0]), model.predict_proba(signals[0]))
    assert back.params == model.params
    with pytest.raises(ValueError, match="unknown"):
        SupervisedGaussianHMM.from_dict({**data, "extra": 1})


# ------------------------------------------------------------------ threshold


def brute_force_threshold(scores, labels):
    keep = labels != -1
    s, y = scores[keep], labels[keep]
    candidates = sorted(set(s.tolist()))
    f1s = [f1_score(y, (s >= c).astype(int), zero_division=0) for c in candidates]
    best = max(f1s)
    return min(c for c, f in zip(candidates, f1s) if f >= best - 1e-12), best


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_select_f1_threshold_vs_brute_force(seed):
    rng = np.random.default_rng(seed)
    n = 300
    labels = rng.integers(-1, 2, n)
    # rounded scores -> many ties among candidates
    scores = np.round(np.clip(rng.normal(0.35 + 0.3 * (labels == 1), 0.25), 0, 1), 2)
    expected, best_f1 = brute_force_threshold(scores, labels)
    got = select_f1_threshold(scores, labels)
    assert got == expected
    keep = labels != -1
    assert f1_score(labels[keep], (scores[keep] >= got).astype(int)) == pytest.approx(best_f1, abs=1e-12)


def test_select_f1_threshold_tie_takes_smallest_and_errors():
    # thresholds 0.2 and 0.8 both give F1 = 2/3 (0.8: TP=1,FP=0,FN=1; 0.2: TP=2,FP=2,FN=0);
    # 0.5 gives TP=1,FP=1,FN=1 -> 1/2
    scores = np.array([0.8, 0.5, 0.2, 0.2, 0.2])
    labels = np.array([1, 0, 1, 0, -1])
    assert select_f1_threshold(scores, labels) == pytest.approx(0.2)
    assert select_f1_threshold(np.array([0.8, 0.5, 0.2, 0.2]), np.array([1, 0, 1, 0])) == 0.2
    with pytest.raises(ValueError, match="no frame labelled contact"):
        select_f1_threshold(np.array([0.1, 0.2]), np.array([0, -1]))
    with pytest.raises(ValueError, match="scores"):
        select_f1_threshold(np.array([0.1, np.nan]), np.array([0, 1]))


# ------------------------------------------------------------------ LOSO ensemble


def test_loso_ensemble(sessions):
    signals, labels = sessions
    names = ["cup_a", "cup_b", "cup_c"]
    ens = LosoEnsemble().fit(signals, labels, names)
    assert ens.session_names_ == names
    assert len(ens.models_) == 3
    for k in range(3):
        rest = [i for i in range(3) if i != k]
        ref = SupervisedGaussianHMM().fit([signals[i] for i in rest], [labels[i] for i in rest])
        np.testing.assert_array_equal(ens.models_[k].means_, ref.means_)
        np.testing.assert_array_equal(ens.oof_posteriors_[k], ref.predict_proba(signals[k]))
    pooled_scores = np.concatenate(ens.oof_posteriors_)
    pooled_labels = np.concatenate(labels)
    expected, _ = brute_force_threshold(pooled_scores, pooled_labels)
    assert ens.threshold_ == expected

    test_signal = signals[1][:250]
    per_model = [forward_filter(test_signal, m.means_, m.vars_, m.transmat_, m.startprob_) for m in ens.models_]
    mean_post = np.mean(per_model, axis=0)
    np.testing.assert_allclose(ens.predict_proba(test_signal), mean_post, rtol=0, atol=1e-15)
    assert np.array_equal(ens.predict(test_signal), ens.predict_proba(test_signal) >= ens.threshold_)

    back = LosoEnsemble.from_dict(json.loads(json.dumps(ens.to_dict())))
    assert np.array_equal(back.predict_proba(test_signal), ens.predict_proba(test_signal))
    assert np.array_equal(back.predict(test_signal), ens.predict(test_signal))
    assert back.threshold_ == ens.threshold_ and back.session_names_ == names
    for a, b in zip(back.oof_posteriors_, ens.oof_posteriors_):
        assert np.array_equal(a, b)


def test_loso_errors(sessions):
    signals, labels = sessions
    with pytest.raises(ValueError, match="at least 2"):
        LosoEnsemble().fit(signals[:1], labels[:1])
    with pytest.raises(ValueError, match="distinct names"):
        LosoEnsemble().fit(signals[:2], labels[:2], ["a", "a"])
    # a fold whose training sessions have no contact frame names the left-out session
    no_contact = np.zeros(50, dtype=np.int64)
    with pytest.raises(ValueError, match="fold leaving out s2"):
        LosoEnsemble().fit(
            [signals[0][:50], signals[1][:50], signals[2]], [no_contact, no_contact, labels[2]], ["s0", "s1", "s2"]
        )
    with pytest.raises(NotFittedError):
        LosoEnsemble().predict(signals[0])


# ------------------------------------------------------------------ streaming filter


def test_streaming_filter_equals_forward_filter_bit_for_bit(sessions):
    signals, labels = sessions
    rng = np.random.default_rng(11)
    signal = rng.normal(1.5, 1.5, 400)
    signal[rng.random(400) < 0.1] = np.nan
    signal[0] = np.nan  # a missing first frame: the prior
    signal[50:60] = np.nan  # a run of missing frames: repeated predictions
    signal[100] = 40.0  # extreme values saturate the log-odds
    signal[101] = -40.0

    model = SupervisedGaussianHMM().fit(signals, labels)
    stream = StreamingFilter(model)
    got = np.array([stream.update(x) for x in signal])
    assert np.array_equal(got, model.predict_proba(signal))
    assert stream.frames == 400

    # ensembles of several sizes (the mean over models must add up in the same order as np.mean)
    many = [signals[0][:200], signals[1][:200], signals[2][:200], signals[0][200:400], signals[1][200:400],
            signals[2][200:400], signals[0][400:600], signals[2][400:600], signals[0][600:], signals[1][400:]]
    many_labels = [labels[0][:200], labels[1][:200], labels[2][:200], labels[0][200:400], labels[1][200:400],
                   labels[2][200:400], labels[0][400:600], labels[2][400:600], labels[0][600:], labels[1][400:]]
    for k in (2, 3, 6, 10):
        ens = LosoEnsemble().fit(many[:k], many_labels[:k])
        stream = StreamingFilter(ens)
        got = np.array([stream.update(x) for x in signal])
        assert np.array_equal(got, ens.predict_proba(signal)), k
        # causal: a prefix gives the same values, and reset starts over
        stream.reset()
        assert np.array_equal([stream.update(x) for x in signal[:30]], ens.predict_proba(signal[:30]))


def test_streaming_filter_errors():
    with pytest.raises(NotFittedError):
        StreamingFilter(LosoEnsemble())
    with pytest.raises(TypeError, match="SupervisedGaussianHMM or LosoEnsemble"):
        StreamingFilter("model.json")
    model = SupervisedGaussianHMM().fit([np.array([0.1, 0.2, 2.0, 2.1, 0.3])], [np.array([0, 0, 1, 1, 0])])
    with pytest.raises(ValueError, match="finite"):
        StreamingFilter(model).update(np.inf)
