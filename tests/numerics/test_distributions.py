"""xi families: the `independent` family's exact moments, samples and parsing; every family's support box."""
import numpy as np
import pytest
from scipy.linalg import block_diag

from rdsexp.numerics import distributions as D
from rdsexp.numerics.systems import MomentModel

# one of each family, multi-dimensional where the family allows it, with correlated blocks
PARTS = [D.Bernoulli([0.9]), D.Uniform([-0.2, 1.0], [0.2, 3.0]), MomentModel([1.0, -2.0], [[1.0, 0.6], [0.6, 0.5]]),
         D.Discrete([[0, 1], [2, -1], [1, 1]], [0.2, 0.5, 0.3])]
SPECS = [{"family": "bernoulli", "prob": 0.9}, {"family": "uniform", "low": [-0.2, 1], "high": [0.2, 3]},
         {"mean": [1, -2], "cov": [[1, 0.6], [0.6, 0.5]]},
         {"family": "discrete", "values": [[0, 1], [2, -1], [1, 1]], "probs": [0.2, 0.5, 0.3]}]
IND = D.Independent(PARTS)


def test_independent_moments_are_the_components_block_diagonal():
    """mean = the components' means stacked, cov = their covariances block-diagonally, exactly."""
    dist = D.from_spec({"family": "independent", "components": SPECS})
    assert dist.p == 7 and [c.p for c in dist.components] == [1, 2, 2, 2]
    for d in (dist, IND):
        np.testing.assert_array_equal(d.mean, np.concatenate([c.mean for c in PARTS]))
        np.testing.assert_array_equal(d.cov, block_diag(*(c.cov for c in PARTS)))
        np.testing.assert_array_equal(d.moments.augmented_second_moment,
                                      MomentModel(d.mean, d.cov).augmented_second_moment)


def test_independent_moments_match_monte_carlo():
    """Sample mean and covariance within 4 Monte Carlo standard errors of the exact ones (zero across blocks)."""
    N = 100_000
    x = IND.sample(np.random.default_rng(3), (N,))
    dev = x - x.mean(axis=0)
    prods = dev[:, :, None] * dev[:, None, :]                          # (N, p, p): cov's summands
    se_mean = np.sqrt(np.diag(IND.cov) / N)
    se_cov = prods.std(axis=0) / np.sqrt(N)
    assert np.all(np.abs(x.mean(axis=0) - IND.mean) < 4 * se_mean)
    assert np.all(np.abs(prods.mean(axis=0) - IND.cov) < 4 * se_cov + 1e-12)


@pytest.mark.parametrize("size", [(), (7,), (3, 5)])
def test_independent_sample_shape_and_determinism(size):
    x = IND.sample(np.random.default_rng(0), size)
    assert x.shape == size + (IND.p,)
    np.testing.assert_array_equal(x, IND.sample(np.random.default_rng(0), size))


NESTED = D.from_spec({"family": "independent", "components": [
    {"family": "independent", "components": SPECS[:2]}, {"family": "bernoulli", "prob": [0.0, 1.0]}]})
FAMILY_SUPPORTS = [
    (MomentModel([0.0, 1.0], np.eye(2)), [-np.inf, -np.inf], [np.inf, np.inf]),
    (D.Uniform([-1, 0.5], [2, 0.5]), [-1, 0.5], [2, 0.5]),
    (D.Bernoulli([0.9, 0.0, 1.0]), [0, 0, 0], [1, 1, 1]),                # prob 0 or 1: still the box [0, 1]
    (D.Discrete([[0, 1], [2, -1], [1, 1]], [0.2, 0.5, 0.3]), [0, -1], [2, 1]),
    (D.Discrete([3, -4], [0.5, 0.5]), [-4], [3]),                         # p = 1 given as a plain list
    (IND, [0, -0.2, 1, -np.inf, -np.inf, 0, -1], [1, 0.2, 3, np.inf, np.inf, 2, 1]),
    (NESTED, [0, -0.2, 1, 0, 0], [1, 0.2, 3, 1, 1]),
]


@pytest.mark.parametrize("dist, low, high", FAMILY_SUPPORTS)
def test_support_is_the_exact_box(dist, low, high):
    lo, hi = dist.support
    assert lo.shape == hi.shape == (dist.p,) and lo.dtype == hi.dtype == float
    np.testing.assert_array_equal(lo, low)
    np.testing.assert_array_equal(hi, high)


@pytest.mark.parametrize("dist", [d for d, _, _ in FAMILY_SUPPORTS])
def test_samples_lie_in_the_support(dist):
    x = dist.sample(np.random.default_rng(5), (2000,))
    lo, hi = dist.support
    assert x.shape == (2000, dist.p) and np.all((lo <= x) & (x <= hi))


def test_support_is_a_copy():
    """Writing into a returned box does not change the (frozen) family."""
    dist = D.Uniform([0.0], [1.0])
    dist.support[0][0] = 5
    assert dist.support[0][0] == 0 and dist.low[0] == 0


def test_nested_independent_equals_the_flat_one():
    flat = D.from_spec({"family": "independent", "components": [*SPECS[:2], {"family": "bernoulli", "prob": [0, 1]}]})
    np.testing.assert_array_equal(NESTED.mean, flat.mean)
    np.testing.assert_array_equal(NESTED.cov, flat.cov)


def ind(*components):
    return {"family": "independent", "components": list(components)}


@pytest.mark.parametrize("spec, message", [
    (ind(SPECS[0], {"family": "uniform", "low": [0]}), "components[1]: family uniform takes {low, high}, got {low}"),
    (ind({"family": "bernoulli", "prob": [1.2]}), "components[0]: prob: [1.2] must lie in [0, 1]"),
    (ind(SPECS[0], {"mean": [0, 0], "cov": [[1, 0]]}), "components[1]: cov: shape (1, 2) does not match mean of length 2"),
    (ind(SPECS[0], 3), "components[1]: 3 is not allowed, expected a mapping"),
    (ind(SPECS[0], ind(SPECS[1], {"family": "gamma"})), "components[1]: components[1]: family: 'gamma' is not allowed"),
    (ind(), "components: an empty list is not allowed"),
    ({"family": "independent", "components": {"family": "bernoulli"}}, "components: expected a list of family specs"),
    ({"family": "independent"}, "family independent takes {components}, got {}"),
    ({"family": "independent", "components": [SPECS[0]], "prob": 1}, "family independent takes {components}"),
])
def test_independent_errors_are_one_line_and_name_the_component(spec, message):
    with pytest.raises(ValueError) as err:
        D.from_spec(spec)
    assert str(err.value).startswith(message) and "\n" not in str(err.value)


def test_independent_constructor_errors():
    with pytest.raises(ValueError, match=r"^components\[1\]: expected a distribution family, got dict$"):
        D.Independent([D.Bernoulli([0.5]), {"family": "bernoulli", "prob": 0.5}])
    with pytest.raises(ValueError, match="^components: an empty list is not allowed"):
        D.Independent(())


def test_independent_is_a_family():
    assert "independent" in D.FAMILIES and D.FAMILIES[-1] == "independent"


def crps_by_quadrature(mu: float, s: float, y: float) -> float:
    """CRPS(N(mu, s^2), y) = integral of (Phi((x - mu) / s) - 1{y <= x})^2 dx, by adaptive quadrature."""
    from scipy.integrate import quad
    from scipy.stats import norm
    below = quad(lambda x: norm.cdf(x, mu, s) ** 2, -np.inf, y)[0]
    above = quad(lambda x: norm.sf(x, mu, s) ** 2, y, np.inf)[0]
    return below + above


@pytest.mark.parametrize("seed", range(3))
def test_expected_crps_equals_the_crps_integral_on_a_discrete_truth(seed):
    # draws listed exactly in proportion to their probabilities: the mean over them is E_Y exactly
    rng = np.random.default_rng(seed)
    values, counts = rng.normal(size=(3, 2)), np.array([1, 2, 5])
    draws = np.repeat(values, counts, axis=0)
    mean, std = rng.normal(size=2), rng.uniform(0.1, 2.0, size=2)
    expected = [np.average([crps_by_quadrature(mean[j], std[j], v) for v in values[:, j]], weights=counts)
                for j in range(2)]
    np.testing.assert_allclose(D.expected_crps(mean, std, draws), expected, rtol=1e-7, atol=1e-10)


def test_expected_crps_of_a_point_model_is_the_mean_absolute_error():
    draws = np.array([[0.0, 1.0], [2.0, 3.0]])
    np.testing.assert_allclose(D.expected_crps([1.0, 0.0], [0.0, 0.0], draws), [1.0, 2.0])


def test_expected_crps_is_proper_on_a_gaussian_truth():
    # against N(0.3, 0.5^2): the score of N(m, s^2) is E|X - Y| - s / sqrt(pi) with X - Y ~ N(m - 0.3,
    # s^2 + 0.25) in closed form; the true marginal scores lowest, and the Monte Carlo estimate of the
    # score agrees with the closed form within 4 standard errors of its mean
    from scipy.stats import norm
    y = 0.3 + 0.5 * np.random.default_rng(7).standard_normal((20_000, 1))

    def exact(m, s):
        d, t = m - 0.3, np.hypot(s, 0.5)
        return t * np.sqrt(2 / np.pi) * np.exp(-d ** 2 / (2 * t ** 2)) + d * (1 - 2 * norm.cdf(-d / t)) - s / np.sqrt(np.pi)

    for m, s in [(0.3, 0.5), (0.3, 0.25), (0.3, 1.0), (0.6, 0.5), (0.0, 0.2)]:
        z = (y - m) / s
        per_draw = s * (z * (2 * norm.cdf(z) - 1) + 2 * norm.pdf(z)) - s / np.sqrt(np.pi)
        assert abs(D.expected_crps([m], [s], y)[0] - exact(m, s)) <= 4 * per_draw.std() / np.sqrt(len(y))
        assert (m, s) == (0.3, 0.5) or exact(m, s) > exact(0.3, 0.5)
