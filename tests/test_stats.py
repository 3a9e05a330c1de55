"""The comparison statistics and their intervals on tiny hand-computed cases, and against
rliable's aggregates and scipy's percentile bootstrap on the same data."""

import zlib

import numpy as np
import pytest
import scipy.stats
from scipy.stats import trim_mean

from agent.metrics import normalized_auc
from sweeper.results import _stats as stats
from sweeper.results._stats import (
    Group,
    bootstrap_ci,
    bootstrap_indices,
    iqm,
    mean,
    median,
    normalize,
    optimality_gap,
    probability_of_improvement,
    profile_statistic,
    score_profile,
    several,
    stratified_bootstrap,
    stratified_bootstrap_ci,
)


def test_normalized_auc_hand_computed():
    # trapezoids: 1 * (0 + 1) / 2 + 2 * (1 + 1) / 2 = 2.5 over a range of 3
    assert normalized_auc([0, 1, 3], [0.0, 1.0, 1.0]) == pytest.approx(2.5 / 3)
    assert normalized_auc([0, 100, 200], [0.4, 0.4, 0.4]) == pytest.approx(0.4)
    assert normalized_auc([0, 10], [0.0, 1.0]) == pytest.approx(0.5)


@pytest.mark.parametrize(
    ("steps", "values", "message"),
    [
        ([0], [1.0], "two evaluation points"),
        ([0, 2, 1], [0.0, 0.0, 0.0], "strictly increasing"),
        ([0, 1], [0.0], "aligned"),
        ([0, 1], [0.0, float("nan")], "finite"),
    ],
)
def test_normalized_auc_rejects_bad_curves(steps, values, message):
    with pytest.raises(ValueError, match=message):
        normalized_auc(steps, values)


def test_iqm_hand_computed():
    assert iqm([4, 1, 3, 2]) == pytest.approx(2.5)  # drops 1 and 4
    assert iqm([1, 2, 3]) == pytest.approx(2.0)  # n < 4: nothing dropped
    assert iqm([100, 0, 0, 0, 1, 2, 3, 4]) == pytest.approx(1.5)  # middle: 0, 1, 2, 3
    assert iqm([7.0]) == 7.0
    batch = iqm(np.array([[4, 1, 3, 2], [1, 1, 1, 9]]))
    np.testing.assert_allclose(batch, [2.5, 1.0])


def test_iqm_is_scipy_trim_mean_quarter():
    rng = np.random.default_rng(0)
    for n in range(1, 30):
        x = rng.normal(size=n)
        assert iqm(x) == pytest.approx(trim_mean(x, 0.25))


def test_bootstrap_of_two_values_hand_computed():
    # Resampled means of [0, 1]: 0, 0.5, 1 with probabilities 1/4, 1/2, 1/4.
    rng = np.random.default_rng(0)
    assert bootstrap_ci([0.0, 1.0], np.mean, rng=rng, resamples=4000) == (0.0, 1.0)
    # The 30 % and 70 % quantiles both fall on the atom 0.5.
    low, high = bootstrap_ci([0.0, 1.0], np.mean, confidence=0.4, rng=rng, resamples=4000)
    assert (low, high) == (0.5, 0.5)
    # A constant sample has a zero-width interval.
    assert bootstrap_ci([3.0] * 5, rng=rng) == (3.0, 3.0)


def test_bootstrap_ci_narrows_with_more_data_and_covers_the_iqm():
    rng = np.random.default_rng(1)
    small, large = rng.normal(size=10), rng.normal(size=400)
    w_small = np.subtract(*bootstrap_ci(small, rng=rng)[::-1])
    w_large = np.subtract(*bootstrap_ci(large, rng=rng)[::-1])
    assert w_large < w_small / 3
    low, high = bootstrap_ci(large, rng=rng)
    assert low < iqm(large) < high


def test_stratified_bootstrap_is_seeded_per_stratum():
    a, b = [0.1, 0.5, 0.3, 0.9, 0.2], [0.6, 0.7, 0.65, 0.8]
    both = stratified_bootstrap_ci({"a": a, "b": b}, seed=3)
    assert stratified_bootstrap_ci({"a": a}, seed=3)["a"] == both["a"]  # b does not matter
    assert stratified_bootstrap_ci({"b": b, "a": a}, seed=3) == both  # nor the order
    wide = {"c": np.random.default_rng(0).normal(size=50)}
    assert stratified_bootstrap_ci(wide, seed=3) != stratified_bootstrap_ci(wide, seed=4)
    assert both["a"][0] <= iqm(a) <= both["a"][1]


def test_bootstrap_rejects_bad_arguments():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="non-empty"):
        bootstrap_ci([], rng=rng)
    with pytest.raises(ValueError, match="confidence"):
        bootstrap_ci([1.0, 2.0], confidence=1.0, rng=rng)
    with pytest.raises(ValueError, match="finite"):
        bootstrap_ci([1.0, float("nan")], rng=rng)


def test_probability_of_improvement_hand_computed():
    x, y = [1, 2, 3, 4], [0, 2, 5, 1]  # win, tie, loss, win -> (1 + 0.5 + 0 + 1) / 4
    assert probability_of_improvement(x, y) == pytest.approx(0.625)
    assert probability_of_improvement(y, x) == pytest.approx(0.375)
    assert probability_of_improvement([1, 1], [1, 1]) == 0.5
    assert probability_of_improvement([2], [1]) == 1.0


def test_probability_of_improvement_needs_pairs():
    with pytest.raises(ValueError, match="paired"):
        probability_of_improvement([1, 2], [1])


def test_mean_median_optimality_gap_hand_computed():
    x = [0.2, 1.4, 0.6, 0.0]
    assert mean(x) == pytest.approx(0.55)
    assert median(x) == pytest.approx(0.4)  # (0.2 + 0.6) / 2
    # shortfalls below 1: 0.8, 0 (1.4 overshoots, counts as 1), 0.4, 1.0 -> 2.2 / 4
    assert optimality_gap(x) == pytest.approx(0.55)
    assert optimality_gap(x, threshold=0.5) == pytest.approx((0.3 + 0 + 0 + 0.5) / 4)
    np.testing.assert_allclose(optimality_gap(np.array([[1.0, 1.0], [0.0, 0.5]])), [0.0, 0.75])


def test_score_profile_hand_computed():
    taus = [0.0, 0.5, 1.0]
    np.testing.assert_allclose(score_profile([0.2, 0.6], taus), [1.0, 0.5, 0.0])
    # strictly above: a score equal to tau does not count, a zero score is above no tau
    np.testing.assert_allclose(score_profile([0.0, 0.5, 0.5, 1.0], taus), [0.75, 0.25, 0.0])
    batch = score_profile(np.array([[0.2, 0.6], [0.7, 0.9]]), taus)
    np.testing.assert_allclose(batch, [[1.0, 0.5, 0.0], [1.0, 1.0, 0.0]])
    with pytest.raises(ValueError, match="increasing"):
        score_profile([0.1], [0.5, 0.5])


def test_score_profile_is_rliables_score_distribution():
    # rliable.library.run_score_deviation: np.mean(scores > tau), vectorised over the taus
    rng = np.random.default_rng(2)
    scores = rng.choice(np.linspace(0, 1, 11), size=(7, 40))  # many ties with the taus
    taus = np.linspace(0, 1, 21)
    expected = np.array([[np.mean(row > tau) for tau in taus] for row in scores])
    np.testing.assert_allclose(score_profile(scores, taus), expected)
    np.testing.assert_allclose(score_profile(scores.T, taus, axis=0), expected)


def test_statistics_match_rliable():
    """rliable's aggregates over a (runs x tasks) matrix; a method's trials as one row of
    tasks makes its median and mean plain ones (rliable averages runs per task first)."""
    from rliable import metrics

    rng = np.random.default_rng(3)
    for n in (1, 2, 5, 8, 33, 200):
        x = rng.beta(2, 3, size=n).round(2)  # rounded: ties, as AUCs on a coarse grid have
        y = np.clip(x + rng.normal(0, 0.1, n).round(2), 0, 1)
        row = x[None, :]
        assert iqm(x) == pytest.approx(metrics.aggregate_iqm(row))
        assert mean(x) == pytest.approx(metrics.aggregate_mean(row))
        assert median(x) == pytest.approx(metrics.aggregate_median(row))
        assert optimality_gap(x) == pytest.approx(metrics.aggregate_optimality_gap(row))
        # paired: every (SAC configuration, seed) pair is a task with one run of each
        assert probability_of_improvement(x, y) == pytest.approx(
            metrics.probability_of_improvement(x[None, :], y[None, :])
        )


def test_stratified_bootstrap_is_scipys_percentile_bootstrap():
    """One stratum: the same draws and the same percentile interval as scipy's bootstrap,
    for a one-sample statistic and for the paired probability of improvement."""
    rng = np.random.default_rng(4)
    x, y = rng.random(13), rng.random(13)
    ours = stratified_bootstrap(iqm, {"a": x}, reps=999, seed=0)["a"]
    theirs = scipy.stats.bootstrap(
        (x,),
        iqm,
        n_resamples=999,
        method="percentile",
        rng=np.random.default_rng([0, zlib.crc32(b"a")]),
    ).confidence_interval
    assert (ours.low, ours.high) == pytest.approx((theirs.low, theirs.high), rel=1e-12)
    assert ours.point == pytest.approx(iqm(x))
    ours = stratified_bootstrap(probability_of_improvement, {"a>b": Group((x, y))}, seed=1)
    theirs = scipy.stats.bootstrap(
        (x, y),
        probability_of_improvement,
        paired=True,
        n_resamples=2000,
        method="percentile",
        rng=np.random.default_rng([1, zlib.crc32(b"a>b")]),
    ).confidence_interval
    assert (ours["a>b"].low, ours["a>b"].high) == pytest.approx((theirs.low, theirs.high))


def test_paired_bootstrap_resamples_pairs_together():
    # x beats y on every pair: every resample of pairs keeps P = 1 (independent resampling
    # of x and y would not, the samples overlap)
    x, y = np.array([0.3, 0.5, 0.9, 0.4]), np.array([0.2, 0.4, 0.8, 0.3])
    assert stratified_bootstrap(probability_of_improvement, {"x>y": Group((x, y))})["x>y"] == (
        1.0,
        1.0,
        1.0,
    )
    # one win, one loss: resampled P is 0, 0.5 or 1 with probabilities 1/4, 1/2, 1/4
    group = {"p": Group((np.array([1.0, 0.0]), np.array([0.0, 1.0])))}
    assert stratified_bootstrap(probability_of_improvement, group, reps=4000)["p"] == (
        0.5,
        0.0,
        1.0,
    )
    narrow = stratified_bootstrap(probability_of_improvement, group, reps=4000, confidence=0.4)
    assert narrow["p"] == (0.5, 0.5, 0.5)


def test_strata_are_resampled_within_themselves():
    # two strata, constant inside: every resample keeps two of each, so the mean is fixed
    values = np.array([0.0, 0.0, 1.0, 1.0])
    strata = np.array([0, 0, 1, 1])
    fixed = stratified_bootstrap(mean, {"m": Group((values,), strata)})["m"]
    assert fixed == (0.5, 0.5, 0.5)
    loose = stratified_bootstrap(mean, {"m": values})["m"]
    assert loose.low < 0.5 < loose.high
    indices = bootstrap_indices(np.array([2, 7, 2, 7, 7]), 300, np.random.default_rng(0))
    assert set(np.unique(indices[:, [0, 2]])) == {0, 2}
    assert set(np.unique(indices[:, [1, 3, 4]])) == {1, 3, 4}


def test_several_statistics_share_one_resample():
    x = np.random.default_rng(5).random(30)
    together = stratified_bootstrap(several(iqm, mean, median, optimality_gap), {"a": x})["a"]
    for column, statistic in enumerate((iqm, mean, median, optimality_gap)):
        alone = stratified_bootstrap(statistic, {"a": x})["a"]
        assert together.point[column] == pytest.approx(alone.point)
        assert together.low[column] == pytest.approx(alone.low)
        assert together.high[column] == pytest.approx(alone.high)


def test_curves_and_profiles_are_resampled_by_whole_units(monkeypatch):
    """A unit can be a whole curve (trials x steps): the interval is per step; chunking the
    replicates to bound memory changes nothing."""
    rng = np.random.default_rng(6)
    curves = np.cumsum(rng.random((9, 5)), axis=1) / 5
    whole = stratified_bootstrap(iqm, {"m": curves}, reps=500)["m"]
    np.testing.assert_allclose(whole.point, iqm(curves, axis=0))
    assert whole.low.shape == whole.high.shape == (5,)
    assert np.all(whole.low <= whole.point) and np.all(whole.point <= whole.high)
    monkeypatch.setattr(stats, "CHUNK_ELEMENTS", 7 * curves.size)  # 7 replicates a chunk
    chunked = stratified_bootstrap(iqm, {"m": curves}, reps=500)["m"]
    np.testing.assert_array_equal(chunked.low, whole.low)
    np.testing.assert_array_equal(chunked.high, whole.high)
    taus = np.linspace(0, 1, 11)
    profile = stratified_bootstrap(profile_statistic(taus), {"m": curves[:, -1]})["m"]
    np.testing.assert_allclose(profile.point, score_profile(curves[:, -1], taus))
    assert profile.low.shape == (11,) and np.all(np.diff(profile.high) <= 0)


def test_groups_are_checked():
    with pytest.raises(ValueError, match="non-empty"):
        stratified_bootstrap(mean, {"a": []})
    with pytest.raises(ValueError, match="aligned"):
        stratified_bootstrap(probability_of_improvement, {"a": Group((np.ones(3), np.ones(2)))})
    with pytest.raises(ValueError, match="finite"):
        stratified_bootstrap(mean, {"a": [1.0, np.inf]})
    with pytest.raises(ValueError, match="strata"):
        stratified_bootstrap(mean, {"a": Group((np.ones(3),), np.zeros(2))})


def test_normalize_hand_computed():
    # random agent 0.2 -> 0, control 0.6 -> 1; halfway 0.4 -> 0.5; worse than random < 0
    np.testing.assert_allclose(
        normalize([0.2, 0.6, 0.4, 0.0, 0.8], 0.2, 0.6), [0, 1, 0.5, -0.5, 1.5]
    )
    # affine: the IQM of normalised scores is the normalised IQM
    x = np.random.default_rng(0).uniform(size=13)
    assert iqm(normalize(x, 0.1, 0.7)) == pytest.approx((iqm(x) - 0.1) / 0.6)
    for zero, one in [(0.5, 0.5), (0.6, 0.2), (0.0, float("nan"))]:
        with pytest.raises(ValueError, match="one > zero"):
            normalize([0.3], zero, one)
