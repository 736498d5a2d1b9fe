"""ms_rate (dense for small n, Arnoldi beyond) against an independent dense Kronecker eigenvalue."""
import numpy as np
import pytest

import rdsexp as rx
from rdsexp.numerics.analysis import DENSE_MAX_N, second_moment_operator


def dense_rate(system, dist, F):
    return np.sqrt(np.abs(np.linalg.eigvals(second_moment_operator(system, dist, F))).max())


def system_of(rng, n, m, p, scale=1.0, cov=True):
    A = [rng.normal(size=(n, n)) / np.sqrt(n)] + [0.4 * rng.normal(size=(n, n)) / np.sqrt(n) for _ in range(p)]
    B = [rng.normal(size=(n, m))] + [0.3 * rng.normal(size=(n, m)) for _ in range(p)]
    L = rng.normal(size=(p, p)) * 0.5 if cov else np.zeros((p, p))
    return rx.AffineRandomSystem(A=np.array(A) * scale, B=B), rx.MomentModel(mean=rng.normal(size=p) * 0.3, cov=L @ L.T)


@pytest.mark.parametrize("seed", range(12))
def test_ms_rate_matches_dense_kronecker(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, DENSE_MAX_N + 7))          # both the dense and the Arnoldi path
    m, p = int(rng.integers(1, 4)), int(rng.integers(0, 4))
    scale = [1.0, 1e-6, 1e6][seed % 3]                # tiny and huge scales
    system, dist = system_of(rng, n, m, p, scale=scale, cov=seed % 4 != 0)      # some with zero covariance
    for F in (np.zeros((m, n)), rng.normal(size=(m, n)) * scale, rng.normal(size=(m, n)) * 10 * scale):
        assert rx.ms_rate(system, dist, F) == pytest.approx(dense_rate(system, dist, F), rel=1e-10)



def test_ms_rate_with_a_complex_pair_as_large_as_the_perron_root():
    """Rotations: T(X) = A X A^T has r^2 and r^2 e^(+-2i theta) of the same modulus (Arnoldi path)."""
    n = DENSE_MAX_N + 2
    blocks = [0.9 * np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]) for t in np.linspace(0.3, 1.2, n // 2)]
    A = np.zeros((n, n))
    for i, blk in enumerate(blocks):
        A[2 * i:2 * i + 2, 2 * i:2 * i + 2] = blk
    system = rx.AffineRandomSystem(A=[A], B=[np.zeros((n, 1))])
    dist = rx.MomentModel(mean=np.zeros(0), cov=np.zeros((0, 0)))
    assert rx.ms_rate(system, dist, np.zeros((1, n))) == pytest.approx(0.9, rel=1e-12)
    assert dense_rate(system, dist, np.zeros((1, n))) == pytest.approx(0.9, rel=1e-12)


@pytest.mark.parametrize("seed", range(6))
def test_perron_vectors_are_psd_eigenvectors(seed):
    """Both Perron vectors (of T and of its adjoint) are PSD eigenvectors to working precision, also
    for gains with large entries (the case where LAPACK's vectors were off is in test_simulation)."""
    from rdsexp.numerics.analysis import perron
    rng = np.random.default_rng(40 + seed)
    n = int(rng.integers(2, DENSE_MAX_N + 5))
    system, dist = system_of(rng, n, 1, 2)
    Abar, Bbar = system.moment_factors(dist)
    Acl = Abar + Bbar @ (rng.normal(size=(1, n)) * 5)
    for adjoint in (False, True):
        rho, X = perron(Acl, adjoint=adjoint)
        M = Acl.transpose(0, 2, 1) if adjoint else Acl
        TX = np.einsum("rij,jk,rlk->il", M, X, M)
        scale = np.einsum("rij,rij->", np.abs(M), np.abs(M))
        assert np.abs(TX - rho * X).max() <= 1e-10 * scale * np.abs(X).max()
        assert np.linalg.eigvalsh(X).min() >= -1e-8 * np.abs(X).max()
