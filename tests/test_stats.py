"""The comparison statistics on tiny hand-computed cases."""

import numpy as np
import pytest
from scipy.stats import trim_mean

from agent.metrics import normalized_auc
from sweeper.stats import (
    bootstrap_ci,
    iqm,
    probability_of_improvement,
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
