"""Rate estimators of the closed-loop rate table (experiments/closed_loop_rate.py): the bootstrap
interval's coverage of a simulated ideal loop's true rate, the largest-path share, the robust rate."""
import numpy as np
import pytest
from scipy import stats

import rdsexp as rx
from rdsexp.numerics.analysis import bootstrap_rate, largest_path_share, robust_rate, second_moments
from rdsexp.numerics.simulation import simulate_state_feedback


def ideal_loop(seed: int):
    """A random 3-state, 2-parameter affine system with Gaussian xi, its gain F = 0 and x0 (seeded)."""
    rng = np.random.default_rng(seed)
    n, p = 3, 2
    A = rng.standard_normal((p + 1, n, n)) * [[[0.3]], [[0.15]], [[0.15]]]
    A[0] += 0.6 * np.eye(n)
    dist = rx.MomentModel(mean=rng.uniform(-0.5, 0.5, p), cov=np.diag(rng.uniform(0.2, 0.5, p)))
    system = rx.AffineRandomSystem(A=A, B=[np.zeros((n, 1))], xi_dist=dist)
    return system, np.zeros((1, n)), rng.standard_normal(n)


@pytest.mark.parametrize("seeds, paths", [(1, 200), (4, 50)])
@pytest.mark.slow
def test_bootstrap_interval_covers_the_true_rate_at_its_nominal_level(seeds, paths):
    """Over R repetitions (independent paths of one ideal loop), the 95% interval of the two-point
    rate k = 10..20 covers the exact ratio of the second moments in a fraction of repetitions within
    3 binomial standard errors of 0.95. Exact truth: the second-moment recursion (`second_moments`)."""
    system, F, x0 = ideal_loop(3)
    k_from, k_to, R = 10, 20, 300
    _, second = second_moments(system, None, F, x0, np.zeros((k_to + 1, 1)))
    e = np.trace(second, axis1=1, axis2=2)
    truth = (e[k_to] / e[k_from]) ** (1 / (2 * (k_to - k_from)))
    x = simulate_state_feedback(system, F, d=np.zeros((k_to + 1, 1)), x0=x0, paths=R * seeds * paths, seed=11)
    sq = np.sum(x[[k_from, k_to]] ** 2, axis=-1).reshape(2, R, seeds, paths)
    covered = []
    for r in range(R):
        rate, low, high = bootstrap_rate(sq[0, r], sq[1, r], k_to - k_from, replicates=1000, seed=r)
        assert low <= rate <= high
        covered.append(low <= truth <= high)
    se = np.sqrt(0.95 * 0.05 / R)
    assert abs(np.mean(covered) - 0.95) <= 3 * se, (np.mean(covered), truth)


def test_bootstrap_rate_is_the_pooled_two_point_ratio():
    """The point estimate is (sum sq_to / sum sq_from)^(1/(2 span)) over all seeds' paths; NaN on
    non-finite data; shapes are checked."""
    rng = np.random.default_rng(0)
    a, b = rng.exponential(size=(3, 20)), rng.exponential(size=(3, 20)) * 0.3
    rate, low, high = bootstrap_rate(a, b, 5, replicates=200)
    assert rate == pytest.approx((b.sum() / a.sum()) ** 0.1, rel=1e-14) and low < rate < high
    b[1, 2] = np.inf
    assert np.isnan(bootstrap_rate(a, b, 5)).all()
    with pytest.raises(ValueError, match="must match"):
        bootstrap_rate(a, b[:2], 5)


def test_largest_path_share_and_robust_rate():
    """Exact geometric decay: robust_rate returns the decay exactly; one heavy path makes the share
    large and moves the two-point ratio but not the robust rate (the median over groups)."""
    k = np.arange(31)
    q = (0.9 ** k)[:, None, None] * np.ones((1, 40, 2))                 # (K+1, P, n), rate 0.9 per step
    assert robust_rate(q, 10, 30, groups=10) == pytest.approx(0.9, rel=1e-12)
    assert largest_path_share(q, 30) == pytest.approx(1 / 40, rel=1e-12)
    heavy = q.copy()
    heavy[:, 0] *= (1.05 ** k)[:, None] * 30                             # one path grows, far above the rest
    assert largest_path_share(heavy, 30) > 0.9
    two_point = np.sqrt((np.sum(heavy[30] ** 2) / np.sum(heavy[10] ** 2)) ** (1 / 20))
    assert two_point > 0.93 and robust_rate(heavy, 10, 30, groups=10) == pytest.approx(0.9, rel=1e-12)
    with pytest.raises(ValueError, match="groups"):
        robust_rate(q, 10, 30, groups=41)


def test_binomial_tolerance_is_what_the_coverage_test_allows():
    """3 binomial standard errors at R = 300 is a two-sided false-alarm rate below 0.5%."""
    R = 300
    lo, hi = 0.95 - 3 * np.sqrt(0.95 * 0.05 / R), 0.95 + 3 * np.sqrt(0.95 * 0.05 / R)
    false_alarm = stats.binom.cdf(np.ceil(lo * R) - 1, R, 0.95) + stats.binom.sf(np.floor(hi * R), R, 0.95)
    assert false_alarm < 0.005
