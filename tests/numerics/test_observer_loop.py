"""The loop through the outputs: exact rate of the plant with a linear observer-based controller."""
import numpy as np
import pytest

from rdsexp.numerics import distributions as D
from rdsexp.numerics.observer_loop import _parts, _rate_and_gradient, best_observer, observer_loop_rate
from rdsexp.numerics.systems import AffineRandomSystem, MomentModel


def step_matrix(A, B, Abar, Bbar, C, F, L, estimate):
    """z_{k+1} = M z_k for z = [x; x_{k|k-1}], from the loop's equations applied to basis vectors: an
    independent construction (other coordinates, no block algebra)."""
    n = A.shape[0]
    M = np.zeros((2 * n, 2 * n))
    for i, z in enumerate(np.eye(2 * n)):
        x, x_pred = z[:n], z[n:]
        x_filt = x_pred + L @ (C @ x - C @ x_pred)
        u = F @ (x_filt if estimate == "filtered" else x_pred)
        M[:n, i] = A @ x + B @ u
        M[n:, i] = Abar @ x_filt + Bbar @ u
    return M


def random_case(rng):
    n, m, ny, p = (int(v) for v in rng.integers(1, 4, size=4))
    values, probs = rng.standard_normal((4, p)) + 0.5, rng.dirichlet(np.ones(4))
    dist = D.Discrete(values.tolist(), probs.tolist())
    A, B = 0.5 * rng.standard_normal((p + 1, n, n)), 0.5 * rng.standard_normal((p + 1, n, m))
    system = AffineRandomSystem(A=A, B=B, C=[rng.standard_normal((ny, n))], xi_dist=dist)
    return system, 0.3 * rng.standard_normal((m, n)), 0.3 * rng.standard_normal((n, ny)), values, probs


@pytest.mark.parametrize("estimate", ["filtered", "predicted"])
def test_rate_is_the_exact_rate_of_the_loop(estimate):
    # E[M (x) M] over the values of a discrete xi, M built from the loop's equations: the same rate
    rng = np.random.default_rng(0)
    for _ in range(25):
        system, F, L, values, probs = random_case(rng)
        mean = system.xi_dist.mean
        Abar, Bbar = system.at(mean)[:2]
        T = sum(pr * np.kron(M, M) for pr, M in
                ((pr, step_matrix(*system.at(v)[:2], Abar, Bbar, system.C[0], F, L, estimate))
                 for pr, v in zip(probs, values)))
        expected = np.sqrt(np.abs(np.linalg.eigvals(T)).max())
        assert observer_loop_rate(system, None, F, L, estimate=estimate) == pytest.approx(expected, rel=1e-10)


def test_deterministic_plant_separates():
    # no randomness: the loop's eigenvalues are those of A + B F and of the observer, A (I - L C)
    rng = np.random.default_rng(1)
    for _ in range(10):
        n, m, ny = 3, 2, 1
        A, B, C = rng.standard_normal((n, n)), rng.standard_normal((n, m)), rng.standard_normal((ny, n))
        system = AffineRandomSystem(A=[A], B=[B], C=[C])
        F, L = 0.3 * rng.standard_normal((m, n)), 0.3 * rng.standard_normal((n, ny))
        radius = lambda M: np.abs(np.linalg.eigvals(M)).max()
        expected = max(radius(A + B @ F), radius(A @ (np.eye(n) - L @ C)))
        got = observer_loop_rate(system, MomentModel.deterministic(np.zeros(0)), F, L)
        assert got == pytest.approx(expected, rel=1e-10)


@pytest.mark.parametrize("estimate", ["filtered", "predicted"])
def test_gradient_matches_finite_differences(estimate):
    rng = np.random.default_rng(2)
    for _ in range(10):
        system, F, L, _, _ = random_case(rng)
        parts = _parts(system, system.check_distribution(None), F, estimate)
        _, grad = _rate_and_gradient(parts, L)
        h, fd = 1e-6, np.zeros_like(L)
        for idx in np.ndindex(L.shape):
            step = np.zeros_like(L)
            step[idx] = h
            fd[idx] = (_rate_and_gradient(parts, L + step)[0] - _rate_and_gradient(parts, L - step)[0]) / (2 * h)
        np.testing.assert_allclose(grad, fd, atol=1e-7)


def test_best_observer_reports_the_rate_of_what_it_returns():
    rng = np.random.default_rng(3)
    for _ in range(10):
        system, F, _, _, _ = random_case(rng)
        found = best_observer(system, None, F)
        assert found.rate == observer_loop_rate(system, None, F, found.L)          # recomputed, exactly
        assert found.rate <= found.kalman_rate + 1e-12                               # never worse than its start


def test_stopping_below_one_answers_the_same_side_of_one_as_the_full_search():
    """stop_below=1 follows the full search's path up to its first observer below 1: the same side of 1
    on every system, the same result where none is found, never more iterations, and an exact rate."""
    rng = np.random.default_rng(12)
    sides, stopped_midway = set(), 0
    for _ in range(12):
        system, F, _, _, _ = random_case(rng)
        full = best_observer(system, None, F, max_iter=20)
        early = best_observer(system, None, F, max_iter=20, stop_below=1.0)
        assert (early.rate < 1) == (full.rate < 1) and early.iterations <= full.iterations
        assert early.rate == observer_loop_rate(system, None, F, early.L)
        if full.rate >= 1:
            assert early.rate == full.rate and np.array_equal(early.L, full.L)
        sides.add(bool(full.rate < 1))
        stopped_midway += early.kalman_rate >= 1 > early.rate
    assert sides == {True, False} and stopped_midway    # both answers, and a stop inside the BFGS search


def test_outputs_that_depend_on_xi_are_refused_in_one_line():
    system = AffineRandomSystem(A=[[[0.5]], [[0.1]]], B=[[[1.0]]], C=[[[1.0]], [[0.2]]],
                                xi_dist=D.Discrete([[0.0], [1.0]], [0.5, 0.5]))
    with pytest.raises(ValueError, match="random C") as err:
        observer_loop_rate(system, None, [[0.1]], [[0.5]])
    assert "\n" not in str(err.value)
