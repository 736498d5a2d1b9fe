"""Systems, moment models, Gbar: deterministic checks against the paper's equations."""
import numpy as np
import pytest

import rdsexp as rx


def test_plant_is_the_model_at_xi_of_s():
    """eq. (co-state) equals eq. (sysmodel-coef) with xi = [0.7 s1, s2, 0.6], for any s."""
    s = np.random.default_rng(0).normal(size=(5, 2))
    xi = np.column_stack([0.7 * s[:, 0], s[:, 1], np.full(5, 0.6)])
    for a, b in zip(rx.paper.plant().at(s), rx.paper.model().at(xi)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-15)


def test_plant_networked_structure():
    """The 6x6 block structure [[A1, 0, B1 C3], [B2 C1, A2, 0], [0, B3 C2, A3]] at s = (s1, s2)."""
    s1, s2 = 0.9, -0.3
    A, B, C, D = rx.paper.plant().at(np.array([s1, s2]))
    A1, A2, A3 = (np.array(M) for M in ([[0, -0.4], [1, 1.3]], [[0, -0.6], [1, 0.7 * s1]], [[0, -0.8], [1, s2]]))
    b1, b2, b3, c = np.array([[0], [0.4]]), np.array([[0], [0.4]]), np.array([[0], [s2]]), np.array([[0, 1]])
    Z = np.zeros((2, 2))
    expected = np.block([[A1, Z, b1 @ c], [b2 @ c, A2, Z], [Z, b3 @ c, A3]])
    np.testing.assert_array_equal(A, expected)
    np.testing.assert_array_equal(B, np.vstack([b1, np.zeros((4, 1))]))
    np.testing.assert_array_equal(C, np.kron(np.eye(3), c))
    np.testing.assert_array_equal(D, np.zeros((3, 1)))


def test_gbar_factorises_the_second_moment_of_g():
    """Gbar^T Gbar = E[g^T g] (eq. equiv-rep-decom-syn), here by exact expansion over the basis."""
    system, dist = rx.paper.model(), rx.paper.modeled_distribution()
    G = system.Gbar(dist)
    n, m = system.n, system.m
    Gamma = np.concatenate([system.A.reshape(4, n * n), system.B.reshape(4, n * m)], axis=1)
    W = np.block([[np.ones((1, 1)), dist.mean[None]], [dist.mean[:, None], dist.second_moment]])
    np.testing.assert_allclose(G.T @ G, Gamma.T @ W @ Gamma, atol=1e-13)
    assert G.shape == (4, (n + m) * n)                      # nbar = 4 as in the paper
    assert system.Gbar(rx.MomentModel.deterministic(dist.mean)).shape[0] == 1


def test_from_samples_matches_sample_mean_equation():
    """Second moment of from_samples = average of xi xi^T, as eq. (sample-mean) needs (1/N normalisation)."""
    xis = np.random.default_rng(1).normal(size=(81, 3))
    d = rx.MomentModel.from_samples(xis)
    np.testing.assert_allclose(d.second_moment, xis.T @ xis / 81, atol=1e-14)
    np.testing.assert_allclose(d.cov, np.cov(xis.T, ddof=0), atol=1e-14)


def test_gaussian_sampling_moments():
    """MomentModel.sample is Gaussian with the given moments (singular covariance allowed)."""
    d = rx.MomentModel(mean=[0.5, 0.6], cov=[[0.04, 0.0], [0.0, 0.0]])
    x = d.sample(np.random.default_rng(2), (40000,))
    se = 0.2 / np.sqrt(40000)
    assert abs(x[:, 0].mean() - 0.5) < 4 * se and np.all(x[:, 1] == 0.6)
    assert abs(x[:, 0].var() - 0.04) < 4 * 0.04 * np.sqrt(2 / 40000)


@pytest.mark.parametrize("kwargs, message", [
    (dict(A=[[[1, 0], [0]]], B=[np.ones((2, 1))]), "A: expected a list of numeric matrices"),
    (dict(A=[np.eye(2), np.eye(3)], B=[np.ones((2, 1))]), "A: basis matrices have different shapes"),
    (dict(A=[np.ones((2, 3))], B=[np.ones((2, 1))]), "A: basis matrices must be square"),
    (dict(A=[np.eye(2)], B=[np.ones((3, 1))]), "B: basis matrices have shape"),
    (dict(A=[np.eye(2) * np.nan], B=[np.ones((2, 1))]), "A: contains NaN or inf"),
    (dict(A=np.eye(2), B=[np.ones((2, 1))]), "A: expected a list"),
    (dict(A=[np.eye(2)], B=[np.ones((2, 1))], C=[np.ones((1, 3))]), "C: basis matrices have shape"),
])
def test_bad_systems_fail_with_one_line(kwargs, message):
    with pytest.raises(ValueError, match=message):
        rx.AffineRandomSystem(**kwargs)


@pytest.mark.parametrize("mean, cov, message", [
    ([0.0, 1.0], [[1.0]], "cov: shape"),
    ([0.0], [[-1.0]], "positive semidefinite"),
    ([0.0, 0.0], [[1.0, 0.5], [0.0, 1.0]], "symmetric"),
    ([np.inf], [[1.0]], "mean: contains NaN or inf"),
])
def test_bad_moment_models(mean, cov, message):
    with pytest.raises(ValueError, match=message):
        rx.MomentModel(mean=mean, cov=cov)
