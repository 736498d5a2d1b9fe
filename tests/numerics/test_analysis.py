"""Exact mean-square analysis: closed forms and agreement with Monte Carlo."""
import numpy as np
import pytest

import rdsexp as rx
from rdsexp.numerics.analysis import empirical_rate, second_moments
from rdsexp.numerics.simulation import simulate_state_feedback


def test_ms_rate_scalar_closed_form():
    """x+ = (a0 + xi + (b0 + xi) f) x: E[acl^2] = (a0 + b0 f)^2 + (1 + f)^2 var."""
    system = rx.AffineRandomSystem(A=[[[0.9]], [[1.0]]], B=[[[0.5]], [[1.0]]])
    dist = rx.MomentModel(mean=[0.0], cov=[[0.09]])
    f = -0.7
    assert rx.ms_rate(system, dist, [[f]]) == pytest.approx(np.sqrt((0.9 + 0.5 * f) ** 2 + (1 + f) ** 2 * 0.09), abs=1e-14)


def test_open_loop_plant_is_mean_square_stable():
    assert rx.ms_rate(rx.paper.plant(), None, np.zeros((1, 6))) < 1


def test_exact_second_moments_match_monte_carlo():
    """E||q_k||^2 of the ideal closed loop with the paper's F and d_k: exact vs 4000 paths, per-step z-scores."""
    plant, d = rx.paper.plant(), rx.paper.disturbance()
    mean, second = second_moments(plant, None, rx.paper.F_proposed, rx.paper.q0, d)
    x = simulate_state_feedback(plant, rx.paper.F_proposed, d=d, x0=rx.paper.q0, paths=4000, seed=7)
    sq = np.sum(x ** 2, axis=-1)                                      # (K+1, P)
    exact = np.trace(second, axis1=1, axis2=2)
    # 100 steps, correlated: 4.5 standard errors raise no false alarm; components that are still
    # deterministic at small k have zero spread and must then agree to rounding
    se = sq.std(1, ddof=1) / np.sqrt(sq.shape[1])
    assert np.all(np.abs(sq.mean(1) - exact) <= 4.5 * se + 1e-9 * exact)
    se_mean = x.std(1, ddof=1) / np.sqrt(x.shape[1])
    assert np.all(np.abs(x.mean(1) - mean) <= 4.5 * se_mean + 1e-9 * np.abs(mean))

def test_empirical_rate_interval_covers_truth():
    """On the ideal closed loop the k=60..80 rate's 95% interval covers the exact rate in most seeds."""
    plant, d = rx.paper.plant(), rx.paper.disturbance()
    _, second = second_moments(plant, None, rx.paper.F_proposed, rx.paper.q0, d)
    e = np.trace(second, axis1=1, axis2=2)
    truth = (e[80] / e[60]) ** (1 / 40)
    covered = 0
    for seed in range(20):
        x = simulate_state_feedback(plant, rx.paper.F_proposed, d=d, x0=rx.paper.q0, paths=200, seed=seed)
        rate, lo, hi = empirical_rate(x, 60, 80)
        covered += lo <= truth <= hi
    assert covered >= 15                                 # P(fewer than 15 of 20 | 95%) < 0.3%
