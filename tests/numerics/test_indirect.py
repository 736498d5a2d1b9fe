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
        # the two-point component from its correlated normal, standardized
        np.testing.assert_array_equal(xi[:, j, 0], two_point_draw((z @ sqrt[j, 0]) / np.linalg.norm(sqrt[j, 0]),
                                                                 mean[j, 0], 0.0, 1.0))
    # a chunk of the paths draws exactly those paths' coefficients
    part = PathLaws(mean[2:], sqrt[2:], ends, low, high)
    np.testing.assert_array_equal(sample_paths(part, path_generators(np.random.SeedSequence(3), PLANT, range(2, P)), K),
                                  xi[:, 2:])
    with pytest.raises(ValueError, match="rngs: 2 paths"):
        sample_paths(laws, rngs[:2], K)


def test_random_shapes_keep_each_replicates_moments_and_draw_its_shape():
    """A replicate's law under `indirect.random_shapes` keeps theta's means, stds and correlations (within 4 Monte
    Carlo sds over K steps, whatever the shapes), its first component (the first factor alone) takes the factor's
    shape (uniform within mean +- sqrt(3) std, two-point on two values with its high one at frequency high_prob),
    and a replicate draws the same numbers whatever the chunk."""
    P, p, K = 12, 3, 20000
    rng = np.random.default_rng(1)
    theta = np.concatenate([rng.normal(size=(P, p)), rng.uniform(0.2, 2.0, (P, p)), rng.uniform(-0.9, 0.9, (P, 3))],
                           axis=1)
    ends, low, high = np.zeros(p, dtype=bool), np.zeros(p), np.ones(p)
    shapes = indirect.random_shapes(P, p, 7)
    assert set(np.unique(shapes.shape)) == {0, 1, 2}
    rngs = lambda paths: path_generators(np.random.SeedSequence(5), PLANT, paths)
    xi = sample_paths(indirect.path_laws(theta, ends, low, high, shapes), rngs(range(P)), K)     # (K, P, p)
    mean, cov = indirect.moments_of(theta, ends, low, high)
    std = np.sqrt(np.einsum("rii->ri", cov))
    np.testing.assert_allclose(std, theta[:, p:2 * p], rtol=1e-14)
    np.testing.assert_array_less(np.abs(xi.mean(axis=0) - mean), 4 * std / np.sqrt(K))
    # the sd of a sample std is std sqrt((kurtosis - 1) / (4 K)), of a sample correlation about sqrt(kurtosis / K);
    # the factors' kurtosis is below 9 here (a two-point of high_prob 0.1), a mixture's below its factors'
    np.testing.assert_array_less(np.abs(xi.std(axis=0) / std - 1), 4 * np.sqrt(8 / (4 * K)))
    sample = np.einsum("krp,krq->rpq", xi - mean, xi - mean) / K / std[:, :, None] / std[:, None, :]
    np.testing.assert_array_less(np.abs(sample - cov / std[:, :, None] / std[:, None, :]), 4 * np.sqrt(9 / K))
    first = shapes.shape[:, 0]
    for r in np.flatnonzero(first == 1):
        assert np.all(np.abs(xi[:, r, 0] - mean[r, 0]) <= np.sqrt(3) * std[r, 0] * (1 + 1e-12))
    for r in np.flatnonzero(first == 2):
        values = np.unique(xi[:, r, 0])
        q = shapes.high_prob[r, 0]
        assert values.size == 2 and abs(np.mean(xi[:, r, 0] == values[1]) - q) < 4 * np.sqrt(q * (1 - q) / K)
    part = indirect.path_laws(theta[4:], ends, low, high, shapes.take(slice(4, None)))
    np.testing.assert_array_equal(sample_paths(part, rngs(range(4, P)), K), xi[:, 4:])


def test_partial_correlations_give_the_correlation_whose_partial_correlations_they_are():
    """`correlation_root` of random partial correlations (and of +-0.999) is a lower-triangular root of a
    correlation matrix (unit diagonal, positive definite) whose partial correlation of (i, j) given components
    0..j-1, read from the inverse of its block (an independent computation), is the one given, and which
    `partial_correlations` reads back; p = 2 gives rho."""
    rng = np.random.default_rng(2)
    p = 4
    i, j = np.tril_indices(p, -1)
    partial = np.concatenate([rng.uniform(-1, 1, (50, 6)), np.full((1, 6), 0.999), np.full((1, 6), -0.999)])
    L = indirect.correlation_root(partial, p)
    np.testing.assert_array_equal(np.triu(L, 1), 0)
    C = L @ np.swapaxes(L, 1, 2)
    np.testing.assert_allclose(np.einsum("rii->ri", C), 1.0, rtol=1e-14)
    assert np.all(np.linalg.eigvalsh(C)[:, 0] > 0)
    for r in range(len(partial)):
        for k, (a, b) in enumerate(zip(i, j)):
            keep = [*range(b), b, a]
            inv = np.linalg.inv(C[r][np.ix_(keep, keep)])
            np.testing.assert_allclose(-inv[-1, -2] / np.sqrt(inv[-1, -1] * inv[-2, -2]), partial[r, k], atol=1e-9)
        np.testing.assert_allclose(indirect.partial_correlations(C[r]), partial[r], atol=1e-9)
    np.testing.assert_allclose(indirect.correlation_root(np.array([0.3]), 2) @ indirect.correlation_root(
        np.array([0.3]), 2).T, [[1.0, 0.3], [0.3, 1.0]], rtol=1e-15)


def test_moments_of_a_two_point_component_follow_its_mean():
    theta = np.array([[0.3, 0.8, 2.0, 0.5], [0.9, -0.1, 0.5, 0.5]])   # means, the std of the second, a correlation
    ends, low, high = np.array([True, False]), np.array([0.0, 0.0]), np.array([1.0, 1.0])
    mean, cov = indirect.moments_of(theta, ends, low, high)
    np.testing.assert_array_equal(mean, theta[:, :2])
    std = np.stack([np.sqrt(theta[:, 0] * (1 - theta[:, 0])), theta[:, 2]], axis=1)
    np.testing.assert_allclose(np.sqrt(np.einsum("rii->ri", cov)), std, rtol=1e-15)
    np.testing.assert_allclose(cov[:, 0, 1], 0.5 * std[:, 0] * std[:, 1], rtol=1e-15)


def test_the_posterior_moments_are_the_mean_law_of_the_draws():
    """The model of weighted draws: the weighted mean of the means and of the stds, with the weighted mean of the
    correlations (a correlation matrix: unit diagonal, positive semidefinite)."""
    rng = np.random.default_rng(3)
    draws = np.concatenate([rng.normal(size=(200, 3)), rng.uniform(0.1, 1, (200, 3)), rng.uniform(-1, 1, (200, 3))],
                           axis=1)
    w = rng.random(200)
    ends, low, high = np.zeros(3, dtype=bool), np.zeros(3), np.ones(3)
    mean, cov = indirect.posterior_moments(draws, w, ends, low, high)
    np.testing.assert_allclose(mean, w @ draws[:, :3] / w.sum(), rtol=1e-14)
    std = w @ draws[:, 3:6] / w.sum()
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), std, rtol=1e-14)
    corr = sum(wi * (c / np.sqrt(np.outer(np.diag(c), np.diag(c))))
               for wi, c in zip(w, indirect.moments_of(draws, ends, low, high)[1])) / w.sum()
    np.testing.assert_allclose(cov / np.outer(std, std), corr, rtol=1e-12)
    assert np.linalg.eigvalsh(corr)[0] > -1e-12


def interval(draws, w, level=0.95):
    """Weighted (1 - level) / 2 and (1 + level) / 2 quantiles of each column."""
    return np.array([indirect.weighted_quantiles(column, w, [(1 - level) / 2, (1 + level) / 2]) for column in draws.T])


def covers_at_its_level(covered: int, runs: int) -> bool:
    """The count of 95% intervals that hold the truth within 3 binomial sds of the nominal count."""
    return binom.ppf(0.0015, runs, 0.95) <= covered <= runs - binom.ppf(0.0015, runs, 0.05)


def test_the_posterior_interval_covers_at_its_level_and_stays_wide_where_nothing_is_seen():
    """theta = (a, b) in the box [-3, 3]^2; the summary sees a with noise 0.3 and a nonlinear bias, b not at all.
    Over many truths the 95% interval of a covers at its level (tolerance: 3 binomial sds), and b's interval
    spans most of the box."""
    lo, hi, noise, R, runs = np.full(2, -3.0), np.full(2, 3.0), 0.3, 1000, 200
    summary = lambda theta, e: np.stack([0.6 * theta[..., 0] + 0.1 * theta[..., 0] ** 2 + noise * e[..., 0],
                                         e[..., 1]], axis=-1)
    covered, widths = 0, []
    for seed in range(runs):
        rng = np.random.default_rng(seed)
        truth = rng.uniform(-2, 2, 2)
        s_obs = summary(truth, rng.standard_normal(2))
        theta = lo + (hi - lo) * rng.random((R, 2))
        draws, w, _ = indirect.synthetic_posterior(theta, summary(theta, rng.standard_normal((R, 2))), s_obs,
                                                   lo, hi, ratio=1.0, count=2000, seed=seed)
        bounds = interval(draws, w)
        covered += bounds[0, 0] <= truth[0] <= bounds[0, 1]
        widths.append(bounds[1, 1] - bounds[1, 0])
    assert covers_at_its_level(covered, runs), f"{covered} of {runs} intervals hold a (nominal 95%)"
    assert np.median(widths) > 0.85 * 0.95 * (hi - lo)[1]


def test_a_linear_summary_gives_the_exact_posterior():
    """s = a + B theta + e, e ~ N(0, Sigma) of 3 correlated components, theta in a box far wider than the
    posterior: the posterior is normal, mean the generalized least squares estimate and covariance
    ratio (B^T Sigma^-1 B)^-1 (ratio: the observed summary averages 1 / ratio replicates' runs). Its mean agrees
    within 3 sds of the regression's error (its 6 coefficients fitted on R replicates move the mean by about
    sqrt(6 / (R ratio)) posterior sds), its sds and correlation within the sampling's error."""
    rng = np.random.default_rng(4)
    B = np.array([[1.0, 0.5], [0.2, -1.0], [0.7, 0.7]])
    L = np.array([[0.3, 0, 0], [0.1, 0.2, 0], [-0.1, 0.05, 0.25]])
    lo, hi, R, ratio = np.full(2, -4.0), np.full(2, 4.0), 4000, 0.25
    theta = lo + (hi - lo) * rng.random((R, 2))
    s = 1.0 + theta @ B.T + rng.standard_normal((R, 3)) @ L.T
    truth = np.array([0.3, -0.5])
    s_obs = 1.0 + B @ truth + np.sqrt(ratio) * L @ rng.standard_normal(3)
    draws, w, z = indirect.synthetic_posterior(theta, s, s_obs, lo, hi, ratio=ratio, count=8000, seed=1)
    info = B.T @ np.linalg.inv(L @ L.T) @ B
    exact_cov = ratio * np.linalg.inv(info)
    exact_mean = np.linalg.solve(info, B.T @ np.linalg.inv(L @ L.T) @ (s_obs - 1.0))
    mean = w @ draws / w.sum()
    cov = (w[:, None] * (draws - mean)).T @ (draws - mean) / w.sum()
    sd = np.sqrt(np.diag(exact_cov))
    assert np.all(np.abs(mean - exact_mean) < 3 * np.sqrt(6 / (R * ratio)) * sd), (mean, exact_mean, sd)
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), sd, rtol=0.08)
    assert abs(cov[0, 1] / np.sqrt(cov[0, 0] * cov[1, 1]) - exact_cov[0, 1] / sd.prod()) < 0.05
    assert np.all(np.abs(z) < 4)


def test_a_summary_quadratic_in_a_components_square_gives_its_exact_posterior():
    """s = (1 + t^2)^2 + e, t in [0, 3]: flat at t = 0, then quartic, as a data run's summary in its noise's sd.
    Regressed on t^2 (squared), the emulator holds it exactly, and the posterior's quantiles are those of the
    exact posterior, uniform prior times N(s_obs; (1 + t^2)^2, ratio sigma^2), on a grid, within the importance
    sampling's and the regression's error; regressed on t, the quartic bends it (its median is off by more)."""
    rng = np.random.default_rng(7)
    lo, hi, R, ratio, sigma = np.zeros(1), np.full(1, 3.0), 2000, 1 / 16, 0.5
    theta = lo + (hi - lo) * rng.random((R, 1))
    response = lambda t: (1 + t ** 2) ** 2
    s = response(theta) + sigma * rng.standard_normal((R, 1))
    s_obs = np.array([response(1.0) + np.sqrt(ratio) * sigma * 0.3])
    grid = np.linspace(0, 3, 30001)
    density = np.exp(-0.5 * (s_obs[0] - response(grid)) ** 2 / (ratio * sigma ** 2))
    cdf = np.cumsum(density) / density.sum()
    exact = grid[np.searchsorted(cdf, [0.025, 0.5, 0.975])]
    def q(squared):
        draws, w, _ = indirect.synthetic_posterior(theta, s, s_obs, lo, hi, ratio=ratio, count=8000, seed=2,
                                                   squared=squared)
        return indirect.weighted_quantiles(draws[:, 0], w, [0.025, 0.5, 0.975])
    width = exact[2] - exact[0]
    np.testing.assert_allclose(q(np.array([True])), exact, atol=0.05 * width)
    assert abs(q(None)[1] - exact[1]) > 0.05 * width


def test_failed_and_outlying_replicates_are_left_out():
    """Replicates whose summary is not finite (their identification failed) or far off the regression (an estimate
    near divergence) do not move the posterior."""
    rng = np.random.default_rng(1)
    theta = rng.random((400, 1))
    s = theta + 0.01 * rng.standard_normal((400, 1))
    s[::4] = np.nan
    clean = indirect.synthetic_posterior(theta, s, np.array([0.5]), np.zeros(1), np.ones(1), ratio=1.0)
    s[1::20] = 1e6                                              # 5%: far off
    draws, w, _ = indirect.synthetic_posterior(theta, s, np.array([0.5]), np.zeros(1), np.ones(1), ratio=1.0)
    assert np.all(np.isfinite(draws)) and np.all(np.isfinite(w)) and w.sum() > 0
    mean = lambda d, w: w @ d[:, 0] / w.sum()
    assert abs(mean(draws, w) - 0.5) < 0.003 and abs(mean(draws, w) - mean(*clean[:2])) < 0.002


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


def test_a_posterior_cut_by_a_placed_box_is_told_apart_from_one_cut_by_the_prior():
    """Draws piling at an edge of a round's box that lies inside the prior box are pressed (a later round must reach
    past it); at an edge the round's box shares with the prior, or well inside, they are not."""
    prior_lo, prior_hi = np.array([0.0, 0.0]), np.array([10.0, 10.0])
    lo, hi = np.array([2.0, 0.0]), np.array([4.0, 3.0])        # component 0 placed inside; 1 shares the prior's lower edge
    w = np.ones(100)
    for column, value, flagged in [(0, 2.0, True), (0, 4.0, True), (1, 0.0, False), (1, 3.0, True), (0, 3.0, False)]:
        draws = np.tile([3.0, 1.5], (100, 1))
        draws[:10, column] = value
        expect = np.zeros(2, dtype=bool)
        expect[column] = flagged
        np.testing.assert_array_equal(indirect.pressed(draws, w, lo, hi, prior_lo, prior_hi), expect)


def test_a_boundary_truth_keeps_its_posterior_inside_the_box():
    """A std near 0 that the summary reads with noise: every draw stays inside the box and the 95% interval holds
    the truth at about its level."""
    lo, hi, R, runs, covered = np.zeros(1), np.ones(1), 1000, 200, 0
    for seed in range(runs):
        rng = np.random.default_rng(seed)
        truth = rng.uniform(0.0, 0.1)
        s_obs = np.array([truth + 0.05 * rng.standard_normal()])
        theta = rng.random((R, 1))
        draws, w, _ = indirect.synthetic_posterior(theta, theta + 0.05 * rng.standard_normal((R, 1)), s_obs, lo, hi,
                                                   ratio=1.0, count=2000, seed=seed)
        assert np.all((draws[w > 0] >= 0) & (draws[w > 0] <= 1))
        bounds = interval(draws, w)[0]
        covered += bounds[0] <= truth <= bounds[1]
    assert covers_at_its_level(covered, runs), covered


def test_a_mean_of_many_paths_against_replicates_of_one():
    """s = 1 + 2 theta + theta^2 + e per path, e ~ N(0, 0.5^2); the observed summary is the mean of 25 paths, each
    replicate runs one: with ratio 1 / 25 the 95% interval covers at its level, and is about a fifth of the
    width it has for one observed path (the regression's own error widens it a little)."""
    lo, hi, R, runs, covered, widths = -np.ones(1), np.ones(1), 1000, 200, 0, []
    mean = lambda theta: 1 + 2 * theta + theta ** 2
    for seed in range(runs):
        rng = np.random.default_rng(seed)
        truth = rng.uniform(-0.8, 0.8)
        s_obs = np.array([mean(truth) + 0.5 * rng.standard_normal(25).mean()])
        theta = lo + (hi - lo) * rng.random((R, 1))
        s = mean(theta) + 0.5 * rng.standard_normal((R, 1))
        draws, w, _ = indirect.synthetic_posterior(theta, s, s_obs, lo, hi, ratio=1 / 25, count=2000, seed=seed)
        bounds = interval(draws, w)[0]
        covered += bounds[0] <= truth <= bounds[1]
        widths.append((bounds[1] - bounds[0]) * (2 + 2 * truth) / (2 * 1.96 * 0.5))     # in units of one path's
    assert covers_at_its_level(covered, runs), covered
    assert 0.19 < np.median(widths) < 0.24, np.median(widths)


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
    """s = (theta, theta^2 + e): an observed summary some law makes lies among the posterior mean law's summaries
    (|z| of order 1 in every component over many truths); one whose second component no theta in the box reaches
    is many sds off."""
    rng = np.random.default_rng(3)
    lo, hi = -np.ones(1), np.ones(1)
    theta = rng.uniform(-1, 1, (2000, 1))
    s = np.column_stack([theta[:, 0] + 0.1 * rng.standard_normal(2000), theta[:, 0] ** 2 + 0.1 * rng.standard_normal(2000)])
    worst = [np.abs(indirect.synthetic_posterior(theta, s, np.array([t + 0.1 * rng.standard_normal(),
                                                                     t ** 2 + 0.1 * rng.standard_normal()]),
                                                 lo, hi, ratio=1.0, count=1000)[2]).max()
             for t in rng.uniform(-0.9, 0.9, 100)]
    assert np.quantile(worst, 0.95) < 3
    z = indirect.synthetic_posterior(theta, s, np.array([0.5, -1.0]), lo, hi, ratio=1.0)[2]    # theta^2 >= 0
    assert z[1] < -4


def test_a_summary_no_replicate_varies_reads_no_misfit():
    """A summary every replicate reads alike up to round-off (a correlation at its clip where every replicate's
    outputs grow) reads z = 0: it holds no evidence, where 1 / its round-off sd would read 1e16 sds. The other
    components still read theirs."""
    rng = np.random.default_rng(4)
    lo, hi = -np.ones(1), np.ones(1)
    theta = rng.uniform(-1, 1, (1000, 1))
    flat = np.arctanh(0.9999) + 1e-16 * rng.standard_normal(1000)
    s = np.column_stack([theta[:, 0] + 0.1 * rng.standard_normal(1000), flat])
    z = indirect.synthetic_posterior(theta, s, np.array([0.2, 1.5]), lo, hi, ratio=1.0, count=1000)[2]
    assert z[1] == 0 and abs(z[0]) < 3
    z = indirect.synthetic_posterior(theta, s, np.array([3.0, 1.5]), lo, hi, ratio=1.0, count=1000)[2]
    assert z[0] > 4 and z[1] == 0
