"""Empirical Bayes shrinkage toward a trend (geocoder.quality.shrinkage), against known spreads."""

import numpy as np

from geocoder.quality.shrinkage import random_effects, shrink


def test_spread_about_a_trend_is_recovered_and_estimates_are_shrunk_by_it():
    rng = np.random.default_rng(5)
    n = 4000
    v = np.linspace(-1, 1, n)
    design = np.stack([np.ones(n), v, v * v], axis=1)
    var = rng.uniform(0.5, 2.0, n) ** 2 * 1e-4  # each estimate's own noise, 0.005-0.02
    trend = 0.3 - 0.2 * v + 0.1 * v * v
    for tau in (0.0, 0.01, 0.05):
        truth = trend + tau * rng.standard_normal(n)
        values = truth + np.sqrt(var) * rng.standard_normal(n)
        fitted, fitted_var, tau2 = random_effects(values, var, design)
        assert abs(np.sqrt(tau2) - tau) <= 0.1 * tau + 0.002
        assert np.sqrt(np.mean((fitted - trend) ** 2)) < 3 * np.sqrt(np.mean(fitted_var))
        post, post_var = shrink(values, var, design)
        own, pooled = np.sqrt(np.mean((values - truth) ** 2)), np.sqrt(np.mean((post - truth) ** 2))
        assert pooled <= own  # never worse than each estimate alone
        ratio = pooled / np.sqrt(np.mean(post_var))
        print(tau, np.sqrt(tau2), own, pooled, ratio)
        if tau > 0:  # the posterior variance says how far the shrunk values are from the truth
            assert 0.85 <= ratio <= 1.15
        else:  # they come back on the trend, known to all of them together; a tau2 of sampling
            # noise alone is counted as a possible spread (pessimistic, never optimistic)
            assert pooled < 0.1 * own and ratio <= 1.15


def test_a_common_mean_is_a_column_of_ones():
    values = np.array([1.0, 1.2, 0.8, 1.1])
    var = np.full(4, 1.0)  # noise far beyond the spread: all come back on the mean
    post, post_var = shrink(values, var, np.ones((4, 1)))
    np.testing.assert_allclose(post, np.mean(values))
    np.testing.assert_allclose(post_var, 0.25)  # the mean of four, each of variance 1


def test_a_spread_must_pass_its_test_to_be_taken():
    # estimates that share a trend and differ only by their noise, correlated over 5 neighbours:
    # the moment estimate of their spread, floored at 0, is positive on a third of such sets
    # (measured 68 of 200), with z = 2 and the correlation counted on none. A real spread of one
    # noise passes every time.
    n = 400
    v = np.linspace(-1, 1, n)
    design = np.stack([np.ones(n), v, v * v], axis=1)
    var = np.full(n, 1e-4)
    trend = 0.3 - 0.2 * v
    spurious = {0.0: 0, 2.0: 0}
    for seed in range(200):
        rng = np.random.default_rng(seed)
        # neighbours share their errors over 5 estimates (a moving sum of white noise)
        errors = np.convolve(rng.standard_normal(n + 4), np.ones(5), mode="valid") / np.sqrt(5)
        values = trend + 0.01 * errors
        for z in spurious:
            spurious[z] += random_effects(values, var, design, significance=z, correlation=5)[2] > 0
        real = trend + 0.01 * rng.standard_normal(n) + 0.01 * errors
        assert random_effects(real, var, design, significance=2.0, correlation=5)[2] > 0
    assert spurious[0.0] > 60 and spurious[2.0] <= 10, spurious
