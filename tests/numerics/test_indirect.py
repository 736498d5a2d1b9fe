"""The simulated estimator's parts (`numerics.indirect`, `distributions.PathLaws`): per-path laws drawn exactly and
independently of the batch, and a posterior whose 95% interval covers at its level where the truth is known."""
import numpy as np
import pytest
from scipy.stats import binom

from rdsexp.numerics import indirect
from rdsexp.numerics.distributions import PathLaws, sample_paths, two_point_draw
from rdsexp.numerics.simulation import PLANT, path_generators


def test_each_path_draws_its_own_law_whatever_the_batch():
    rng = np.random.default_rng(0)
    P, p, K = 5, 3, 40
    mean = rng.normal(size=(P, p))
    mean[:, 0] = rng.uniform(0.1, 0.9, P)                     # component 0 two-point on {0, 1}
    sqrt = rng.normal(size=(P, p, p))
    ends, low, high = np.array([True, False, False]), np.zeros(p), np.ones(p)
    laws = PathLaws(mean, sqrt, ends, low, high)
    rngs = path_generators(np.random.SeedSequence(3), PLANT, range(P))
    xi = sample_paths(laws, rngs, K)                            # (K, P, p)
    for j in range(P):                                          # an independent computation, path by path
        z = path_generators(np.random.SeedSequence(3), PLANT, [j])[0].standard_normal((K, p))
        np.testing.assert_allclose(xi[:, j, 1:], (mean[j] + z @ sqrt[j].T)[:, 1:], rtol=1e-13, atol=1e-13)
        np.testing.assert_array_equal(xi[:, j, 0], two_point_draw(z[:, 0], mean[j, 0], 0.0, 1.0))
    # a chunk of the paths draws exactly those paths' coefficients
    part = PathLaws(mean[2:], sqrt[2:], ends, low, high)
    np.testing.assert_array_equal(sample_paths(part, path_generators(np.random.SeedSequence(3), PLANT, range(2, P)), K),
                                  xi[:, 2:])
    with pytest.raises(ValueError, match="rngs: 2 paths"):
        sample_paths(laws, rngs[:2], K)


def test_moments_of_a_two_point_component_follow_its_mean():
    theta = np.array([[0.3, 0.8, 2.0], [0.9, -0.1, 0.5]])      # means of 2 components, the std of the second
    ends, low, high = np.array([True, False]), np.array([0.0, 0.0]), np.array([1.0, 1.0])
    mean, cov = indirect.moments_of(theta, ends, low, high, corr=np.array([[1.0, 0.5], [0.5, 1.0]]))
    np.testing.assert_array_equal(mean, theta[:, :2])
    std = np.stack([np.sqrt(theta[:, 0] * (1 - theta[:, 0])), theta[:, 2]], axis=1)
    np.testing.assert_allclose(np.sqrt(np.einsum("rii->ri", cov)), std, rtol=1e-15)
    np.testing.assert_allclose(cov[:, 0, 1], 0.5 * std[:, 0] * std[:, 1], rtol=1e-15)


def interval(adjusted, w, level=0.95):
    """Weighted (1 - level) / 2 and (1 + level) / 2 quantiles of each column."""
    out = []
    for column in adjusted.T:
        order = np.argsort(column)
        cdf = np.cumsum(w[order]) / w.sum()
        out.append(np.interp([(1 - level) / 2, (1 + level) / 2], cdf, column[order]))
    return np.array(out)


def test_the_posterior_interval_covers_at_its_level_and_stays_wide_where_nothing_is_seen():
    """theta = (a, b) in the box [-3, 3]^2; the summary sees a with noise 0.3 and a nonlinear bias, b not at all.
    Over many truths the 95% interval of a covers at its level (tolerance: 3 binomial sds), and b's interval
    spans most of the box."""
    lo, hi, noise, R, runs = np.full(2, -3.0), np.full(2, 3.0), 0.3, 4000, 200
    summary = lambda theta, e: np.stack([0.6 * theta[..., 0] + 0.1 * theta[..., 0] ** 2 + noise * e[..., 0],
                                         e[..., 1]], axis=-1)
    covered, widths = 0, []
    for seed in range(runs):
        rng = np.random.default_rng(seed)
        truth = rng.uniform(-2, 2, 2)
        s_obs = summary(truth, rng.standard_normal(2))
        theta = lo + (hi - lo) * rng.random((R, 2))
        adjusted, w = indirect.adjusted_posterior(theta, summary(theta, rng.standard_normal((R, 2))), s_obs,
                                                  lo, hi, accept=0.1)
        bounds = interval(adjusted, w)
        covered += bounds[0, 0] <= truth[0] <= bounds[0, 1]
        widths.append(bounds[1, 1] - bounds[1, 0])
    low_count = binom.ppf(0.0015, runs, 0.95)              # 3 sd below the nominal count
    assert covered >= low_count, f"{covered} of {runs} intervals hold a (nominal 95%)"
    assert covered <= runs - binom.ppf(0.0015, runs, 0.05)
    assert np.median(widths) > 0.85 * 0.95 * (hi - lo)[1]


def test_failed_replicates_are_left_out():
    rng = np.random.default_rng(1)
    theta = rng.random((200, 1))
    s = theta + 0.01 * rng.standard_normal((200, 1))
    s[::4] = np.nan                                             # their identification failed
    adjusted, w = indirect.adjusted_posterior(theta, s, np.array([0.5]), np.zeros(1), np.ones(1), accept=0.5)
    assert np.all(np.isfinite(adjusted)) and len(w) <= 150 and np.all(w > 0)
    assert abs(w @ adjusted[:, 0] / w.sum() - 0.5) < 0.01


def test_a_posterior_stopped_by_the_box_is_told_apart_from_a_law_at_its_own_edge():
    """theta = (mean 1 two-point, mean 2, std 2): weight at mean 2's edge or std 2's upper edge flags the box;
    a std of 0 or a two-point mean at its end is a law the box rightly holds."""
    lo, hi, ends = np.array([0.001, -1.0, 0.0]), np.array([0.999, 1.0, 2.0]), np.array([True, False])
    inside = np.array([0.5, 0.0, 1.0])
    w = np.ones(100)
    for column, value, flagged in [(1, 1.0, True), (1, -1.0, True), (2, 2.0, True), (2, 0.0, False),
                                   (0, 0.999, False), (0, 0.001, False)]:
        draws = np.tile(inside, (100, 1))
        draws[:10, column] = value                              # 10% of the weight at that edge
        expect = np.zeros(3, dtype=bool)
        expect[column] = flagged
        np.testing.assert_array_equal(indirect.at_the_edge(draws, w, lo, hi, ends), expect)
    draws = np.tile(inside, (100, 1))
    draws[:4, 1] = 1.0                                          # 4%: below the share
    assert not indirect.at_the_edge(draws, w, lo, hi, ends).any()


def test_a_boundary_truth_keeps_its_posterior_inside_the_box_and_spread():
    """A std near 0 that the summary reads with noise: the regression on the logit keeps every adjusted draw inside
    the box and spread (no pile at the edge), and the 95% interval holds the truth at about its level."""
    lo, hi, R, runs, covered = np.zeros(1), np.ones(1), 2000, 200, 0
    for seed in range(runs):
        rng = np.random.default_rng(seed)
        truth = rng.uniform(0.0, 0.1)
        s_obs = np.array([truth + 0.05 * rng.standard_normal()])
        theta = rng.random((R, 1))
        adjusted, w = indirect.adjusted_posterior(theta, theta + 0.05 * rng.standard_normal((R, 1)), s_obs, lo, hi,
                                                  accept=0.1)
        assert np.all((adjusted > 0) & (adjusted < 1)) and np.unique(adjusted).size == adjusted.size
        bounds = interval(adjusted, w)[0]
        covered += bounds[0] <= truth <= bounds[1]
    assert binom.ppf(0.0015, runs, 0.95) <= covered <= runs - binom.ppf(0.0015, runs, 0.05), covered


def test_summaries_of_one_path_made_those_of_a_mean_of_many():
    """s = 1 + 2 theta + theta^2 + e, e ~ N(0, 0.5^2): `averaged` keeps the regression and divides the residual's
    sd by sqrt(paths) (to within the Monte Carlo error of 4000 replicates: 5%); failed rows stay NaN."""
    rng = np.random.default_rng(0)
    theta = rng.uniform(-1, 1, (4000, 1))
    mean = 1 + 2 * theta + theta ** 2
    s = mean + 0.5 * rng.standard_normal(theta.shape)
    s[7] = np.nan
    out = indirect.averaged(theta, s, paths=25)
    assert np.isnan(out[7]).all() and np.isfinite(np.delete(out, 7, axis=0)).all()
    residual = np.delete(out - mean, 7, axis=0)
    assert abs(residual.std() / (0.5 / 5) - 1) < 0.05 and abs(residual.mean()) < 3 * 0.1 / np.sqrt(4000)


def test_weighted_quantiles_are_the_weighted_distributions():
    """Equal weights: numpy's (Hazen) quantiles; integer weights: within a draw's spacing of the repeated sample's."""
    rng = np.random.default_rng(2)
    values, q = rng.standard_normal(500), [0.025, 0.5, 0.975]
    np.testing.assert_allclose(indirect.weighted_quantiles(values, np.ones(500), q),
                               np.quantile(values, q, method="hazen"))
    counts = rng.integers(1, 4, 500)
    repeated = np.quantile(np.repeat(values, counts), q, method="hazen")
    assert np.all(np.abs(indirect.weighted_quantiles(values, counts.astype(float), q) - repeated) < 0.05)


def test_a_summary_no_law_reaches_is_a_misfit():
    """s = (theta, theta^2 + e): an observed summary some law makes lies among the nearest replicates (|z| of order
    1 in every component over many truths); one whose second component no theta in the box reaches is many sds off."""
    rng = np.random.default_rng(3)
    theta = rng.uniform(-1, 1, (2000, 1))
    s = np.column_stack([theta[:, 0] + 0.1 * rng.standard_normal(2000), theta[:, 0] ** 2 + 0.1 * rng.standard_normal(2000)])
    worst = [np.abs(indirect.misfit(s, np.array([t + 0.1 * rng.standard_normal(), t ** 2 + 0.1 * rng.standard_normal()]),
                                    0.5)).max() for t in rng.uniform(-0.9, 0.9, 100)]
    assert np.quantile(worst, 0.95) < 3
    z = indirect.misfit(s, np.array([0.5, -1.0]), 0.5)        # theta^2 >= 0: no law gives -1
    assert z[1] < -4 and abs(z[0]) < 3
