"""The online (learning-type) controller: per-path gains in the Monte Carlo, re-design, safeguard, config."""
import numpy as np
import pandas as pd
import pytest
from conftest import REPO, SMALL, rdsexp
from hydra import compose, initialize_config_module

import rdsexp as rx
from rdsexp import runs
from rdsexp.errors import ConfigError
from rdsexp.experiment.config import build
from rdsexp.experiment.recording import read_series
from rdsexp.numerics.distributions import from_spec
from rdsexp.numerics.enkf import EnKF
from rdsexp.numerics.online import (
    OnlineController,
    OnlineSettings,
    moment_factors,
    policy_iteration_batch,
    rates,
    two_point_moments,
    weighted_moments,
)
from rdsexp.numerics.simulation import simulate

paper = rx.paper
ARRAYS = ("q", "y", "u", "psi_pred_mean", "psi_pred_std", "psi_filt_mean", "psi_filt_std", "failed_at")


def kron_rate(system, mean, cov, F):
    """Independent exact rate: E[Acl (x) Acl] = sum_il W_il Acl_i (x) Acl_l with W = E[[1; xi][1; xi]^T]."""
    W = np.block([[np.ones((1, 1)), mean[None]], [mean[:, None], cov + np.outer(mean, mean)]])
    Acl = system.A + system.B @ F
    L = sum(W[i, j] * np.kron(Acl[i], Acl[j]) for i in range(len(W)) for j in range(len(W)))
    return np.sqrt(np.abs(np.linalg.eigvals(L)).max())


def random_system(rng, n, m, p, degenerate=False):
    A = [rng.normal(size=(n, n)) / np.sqrt(n)] + [0.3 * rng.normal(size=(n, n)) / np.sqrt(n) for _ in range(p)]
    B = [rng.normal(size=(n, m))] + [(0.0 if degenerate else 0.3) * rng.normal(size=(n, m)) for _ in range(p)]
    L = 0.5 * rng.normal(size=(p, p))
    if degenerate:
        L[:, 0] = 0.0                                  # a singular covariance: xi_1 deterministic
    xi = from_spec({"family": "normal", "mean": (0.3 * rng.normal(size=p)).tolist(),
                                     "cov": (L @ L.T).tolist()})
    return rx.AffineRandomSystem(A=A, B=B, xi_dist=xi)


def test_batched_rates_and_policy_iteration_match_the_single_path_ones():
    """`rates` against a dense Kronecker eigenvalue, `policy_iteration_batch` against `policy_iteration`,
    over random and degenerate systems, with and without covariance."""
    for seed in range(8):
        rng = np.random.default_rng(seed)
        n, m, p = int(rng.integers(2, 5)), int(rng.integers(1, 3)), int(rng.integers(1, 4))
        system = random_system(rng, n, m, p, degenerate=seed % 2 == 1)
        P = 4
        mean = 0.3 * rng.normal(size=(P, p))
        L = 0.4 * rng.normal(size=(P, p, p))
        cov = L @ L.transpose(0, 2, 1)
        cov[0] = np.outer(L[0, 0], L[0, 0])                    # a singular covariance (rank one)
        Abar, Bbar = moment_factors(system, mean, cov)
        F = rng.normal(size=(P, m, n))
        for j, r in enumerate(rates(Abar, Bbar, F)):
            assert r == pytest.approx(kron_rate(system, mean[j], cov[j], F[j]), rel=1e-9)
        Fb = policy_iteration_batch(Abar, Bbar, np.zeros((P, m, n)))
        for j in range(P):
            single = rx.synthesize(system, rx.MomentModel(mean=mean[j], cov=cov[j]), "policy_iteration")
            assert kron_rate(system, mean[j], cov[j], Fb[j]) == pytest.approx(single.lam, rel=1e-8, abs=1e-12)


def test_batched_policy_iteration_returns_its_best_gain_where_a_step_raises_the_rate():
    """With B certain and m = n, the optimum is dead beat at the mean: Acl = sum_i (xi_i - mean_i) A_i, whose
    rate sqrt(rho(sum_il cov_il A_i (x) A_l)) no gain beats (an independent computation). The Perron vector
    there is singular and the minimum-norm step moves away from it (the rate can rise): from any start, the
    batched policy iteration returns the optimum and never a gain worse than its start."""
    nonzero = 0
    for seed in range(12):
        rng = np.random.default_rng(100 + seed)
        n, p = int(rng.integers(2, 4)), int(rng.integers(1, 3))
        system = random_system(rng, n, n, p, degenerate=True)     # B_i = 0 for i >= 1: B(xi) = B_0
        P = 3
        mean = 0.5 * rng.normal(size=(P, p))
        L = 0.5 * rng.normal(size=(P, p, p))
        cov = L @ L.transpose(0, 2, 1)
        Abar, Bbar = moment_factors(system, mean, cov)
        F0 = np.stack([np.zeros((n, n)), rng.normal(size=(n, n)),
                       -np.linalg.solve(system.B[0], system.A[0] + np.tensordot(mean[2], system.A[1:], 1))])
        F = policy_iteration_batch(Abar, Bbar, F0)
        for j in range(P):
            Ai = system.A[1:]
            optimum = np.sqrt(np.abs(np.linalg.eigvals(sum(cov[j][i, q] * np.kron(Ai[i], Ai[q])
                                                           for i in range(p) for q in range(p)))).max())
            assert kron_rate(system, mean[j], cov[j], F[j]) == pytest.approx(optimum, rel=1e-7, abs=1e-12)
            assert kron_rate(system, mean[j], cov[j], F[j]) <= kron_rate(system, mean[j], cov[j], F0[j]) + 1e-12
            nonzero += kron_rate(system, mean[j], cov[j], F[j]) > 1e-9
    assert nonzero > 0         # not every optimum is zero (cov != 0): the check is not vacuous


def test_weighted_moments_are_the_sample_moments_with_equal_weights():
    xi = np.random.default_rng(0).normal(size=(30, 3, 2))
    mean, cov = weighted_moments(xi, np.ones(30))
    for j in range(3):
        ref = rx.MomentModel.from_samples(xi[:, j])
        np.testing.assert_allclose(mean[j], ref.mean, rtol=1e-13)
        np.testing.assert_allclose(cov[j], ref.cov, rtol=1e-12, atol=1e-15)


def test_weighted_moments_of_a_path_are_the_same_bits_in_any_batch():
    """A path's moments (and its bootstrap resamples') do not depend on which other paths share the batch: alone
    in a contiguous array (a chunk of one path) they are the bits they are among five, with filtered
    covariances too, for p = 1 to 3 (a reduction whose order follows the layout differed in the last bits)."""
    rng = np.random.default_rng(3)
    for p in (1, 2, 3):
        T, U = 17, 5
        xi, xi_cov = rng.uniform(size=(T, U, p)), rng.normal(size=(T, U, p, p))
        w, steps = 0.9 ** np.arange(T)[::-1], rng.integers(0, T, size=(7, T))
        together = weighted_moments(xi, w, xi_cov), weighted_moments(xi[steps], w[steps])
        for j in range(U):
            alone = np.ascontiguousarray(xi[:, j:j + 1])
            for a, b in zip(weighted_moments(alone, w, np.ascontiguousarray(xi_cov[:, j:j + 1])), together[0]):
                np.testing.assert_array_equal(a[0], b[j])
            for a, b in zip(weighted_moments(alone[steps], w[steps]), together[1]):
                np.testing.assert_array_equal(a[:, 0], b[:, j])


def closed_loop(F, paths=4, M=20, horizon=30, controller=None, **kw):
    return simulate(paper.plant(), EnKF(paper.model(), paper.Q, paper.R), F=F, d=paper.disturbance(horizon),
                    q0=paper.q0, psi0=paper.psi0, ensemble_size=M, paths=paths, seed=3, filter_sees_d=False,
                    controller=controller, **kw)


def test_total_covariance_adds_the_mean_filtered_covariance_of_the_window():
    """covariance = total: each decision's modeled covariance is eq. (sample-mean)'s over the window plus
    the weighted mean of the EnKF's filtered xi covariances there (both from simulate's own record), the
    mean unchanged; weighted_moments adds exactly the weighted mean of the given covariances."""
    settings = OnlineSettings(warmup=3, period=6, memory="exponential", forgetting=0.8, safeguard=False,
                              covariance="total")
    ctrl = OnlineController(paper.model(), settings, np.zeros((1, 6)), paths=3, horizon=30)
    tr = closed_loop(np.zeros((1, 6)), paths=3, controller=ctrl, keep_xi_cov=True)
    xi, d = tr.xi(tr.psi_filt_mean), ctrl.decisions()
    assert len(d.k) > 0
    for i in range(len(d.k)):
        first, w = ctrl.weights(d.k[i])
        window, p = slice(first, d.k[i] + 1), w / w.sum()
        samples = xi[window, d.path[i]]
        mean = p @ samples
        cov = (samples - mean).T @ np.diag(p) @ (samples - mean) + np.einsum("t,tab->ab", p, tr.xi_filt_cov[window, d.path[i]])
        np.testing.assert_allclose(d.mean[i], mean, rtol=1e-12)
        np.testing.assert_allclose(d.cov[i], cov, rtol=1e-10, atol=1e-15)
    samples, covs = np.random.default_rng(1).normal(size=(2, 7, 3, 2)), np.random.default_rng(2).normal(size=(7, 3, 2, 2))
    w = np.arange(1.0, 8.0)
    plain_mean, plain_cov = weighted_moments(samples[0], w)
    mean, cov = weighted_moments(samples[0], w, covs)
    np.testing.assert_array_equal(mean, plain_mean)
    np.testing.assert_allclose(cov, plain_cov + np.einsum("t,tjab->jab", w / w.sum(), covs), rtol=1e-12)


def test_model_observer_draws_from_each_paths_latest_model_adopted_or_not():
    """observer = model: no prior before the first re-design (the random walk); after each, every path with finite
    moments has its latest decision's moments as the EnKF's prior, also where the candidate was not adopted."""
    settings = OnlineSettings(warmup=4, period=6, memory="all", observer="model")
    priors = []

    class Kept(OnlineController):
        def update(self, k, *args, **kw):
            change = super().update(k, *args, **kw)
            prior = self.observer_prior()
            priors.append((k, None if prior is None else tuple(np.array(a) for a in prior)))
            return change

    ctrl = Kept(paper.model(), settings, np.zeros((1, 6)), paths=4, horizon=30)
    closed_loop(np.zeros((1, 6)), paths=4, horizon=30, controller=ctrl)
    dec = ctrl.decisions()
    assert all(prior is None for k, prior in priors if k < 10) and (~dec.adopted).any()
    for k, (mean, root, has) in priors[10:]:
        last = dec.k == max(j for j in set(dec.k) if j <= k)
        assert has[dec.path[last]].all() and has.sum() == last.sum()
        np.testing.assert_array_equal(mean[dec.path[last]], dec.mean[last])
        np.testing.assert_allclose(root[dec.path[last]] @ root[dec.path[last]], dec.cov[last], rtol=1e-9,
                                   atol=1e-12 * np.abs(dec.cov[last]).max())


def test_period_beyond_the_horizon_is_the_fixed_gain_closed_loop_bit_for_bit():
    fixed = closed_loop(paper.F_proposed)
    ctrl = OnlineController(paper.model(), OnlineSettings(warmup=0, period=31, window=10), paper.F_proposed,
                            paths=4, horizon=30)
    online = closed_loop(paper.F_proposed, controller=ctrl)
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(online, name), getattr(fixed, name), err_msg=name)
    assert np.all(online.gain_index == 0) and len(ctrl.decisions().k) == 0
    # per-path gains without a controller, all equal: the same loop too
    same = closed_loop(np.broadcast_to(paper.F_proposed, (4, 1, 6)))
    np.testing.assert_array_equal(same.q, fixed.q)


def test_controller_models_xi_from_the_smoothed_estimate():
    """With EnKF.lag the controller gets the oldest past draw, xi_{k-1-lag} given y up to k, and its covariance.
    An EnKF whose model outputs see nothing (C = 0) never updates, so with lag 1 that is exactly the filtered
    xi of the step before, as `simulate` records it."""
    m = paper.model()
    blind = rx.AffineRandomSystem(A=m.A, B=m.B, C=np.zeros_like(m.C), D=m.D)
    ctrl = OnlineController(blind, OnlineSettings(warmup=0, period=31, covariance="total"), paper.F_proposed,
                            paths=3, horizon=30)
    tr = simulate(paper.plant(), EnKF(blind, paper.Q, paper.R, variant="etkf", lag=1), F=paper.F_proposed,
                  d=paper.disturbance(30), q0=paper.q0, psi0=paper.psi0 + 0.1, P0=0.01, ensemble_size=20, paths=3,
                  seed=3, filter_sees_d=False, controller=ctrl, keep_xi_cov=True)
    assert np.all(np.diff(tr.xi(tr.psi_filt_mean), axis=0) != 0)              # xi moves: the walk's noise
    np.testing.assert_allclose(ctrl.xi[1:30], tr.xi(tr.psi_filt_mean)[:29], rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(ctrl.xi_cov[1:30], tr.xi_filt_cov[:29], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(ctrl.xi[0], np.broadcast_to(paper.psi0[6:] + 0.1, (3, 3)), rtol=1e-15)  # the start


def test_adopted_gains_act_from_the_next_step_on():
    """With updates, u_k = F_k x_{k|k-1} holds with each path's gain in use at k (from gain_index)."""
    ctrl = OnlineController(paper.model(), OnlineSettings(warmup=5, period=5, memory="all", safeguard=False),
                            np.zeros((1, 6)), paths=3, horizon=30)
    tr = closed_loop(np.zeros((1, 6)), paths=3, controller=ctrl)
    history = ctrl.gain_history()
    assert tr.gain_index.max() > 0
    d = paper.disturbance(30)
    for j in range(3):
        F = history[j][tr.gain_index[:, j]]                                  # (K+1, m, n)
        u = (F @ tr.x(tr.psi_pred_mean)[:, j, :, None])[..., 0] + d
        np.testing.assert_allclose(tr.u[:, j], u, rtol=1e-12, atol=1e-12)
    first = ctrl.decisions().k.min()
    assert np.all(tr.gain_index[:first + 1] == 0)


def feed(system, settings, K, paths, seed, F0=None):
    """Run the controller on samples of the true xi in place of the EnKF's xi_{k|k}."""
    rng = np.random.default_rng(seed)
    ctrl = OnlineController(system, settings, np.zeros((system.m, system.n)) if F0 is None else F0,
                            paths=paths, horizon=K)
    for k in range(K):
        xi = system.xi_dist.sample(rng, (paths,))
        ctrl.update(k, np.concatenate([np.zeros((paths, system.n)), xi], axis=1), np.ones(paths, bool))
    return ctrl


@pytest.mark.parametrize("seed", range(4))
def test_converges_to_the_true_optimum_on_true_samples(seed):
    """Fed the true distribution's samples, the final gain's exact rate on the true plant is within
    1e-3 of the optimal mean-square rate (policy iteration on the true distribution)."""
    rng = np.random.default_rng(100 + seed)
    systems = [paper.plant()] if seed == 0 else []
    while not systems:
        s = random_system(rng, 3, 1 + seed % 2, 2, degenerate=seed == 3)
        if rx.synthesize(s, None, "policy_iteration").lam < 0.98:    # stabilizable in mean square
            systems.append(s)
    system = systems[0]
    optimum = rx.synthesize(system, None, "policy_iteration").lam
    ctrl = feed(system, OnlineSettings(warmup=10, period=400, memory="all"), K=3000, paths=3, seed=seed)
    for F in (h[-1] for h in ctrl.gain_history()):
        assert rx.ms_rate(system, None, F) == pytest.approx(optimum, abs=1e-3)


@pytest.mark.parametrize("memory", ["window", "exponential"])
def test_safeguard_never_adopts_a_gain_not_certified_on_the_current_model(memory):
    """Few noisy samples (models far from the truth, often not stabilizable): every adopted gain has an
    exact rate (checked independently) < 1 and below the gain in use; without the safeguard all are taken."""
    rng = np.random.default_rng(7)
    checked = 0
    for trial in range(6):
        system = random_system(rng, 3, 1, 2, degenerate=trial % 3 == 2)
        system = rx.AffineRandomSystem(A=system.A * 1.3, B=system.B, xi_dist=system.xi_dist)  # often unstable
        settings = OnlineSettings(warmup=2, period=3, memory=memory, window=4, forgetting=0.7, resamples=0)
        ctrl = feed(system, settings, K=40, paths=5, seed=trial)
        d = ctrl.decisions()
        assert set(d.reason) <= {"adopted", "not_stabilizing", "no_improvement"}
        current = {j: ctrl.F0[j] for j in range(5)}
        for i in range(len(d.k)):
            j = d.path[i]
            exact_new = kron_rate(system, d.mean[i], d.cov[i], d.F[i])
            exact_cur = kron_rate(system, d.mean[i], d.cov[i], current[j])
            assert d.rate_model[i] == pytest.approx(exact_new, rel=1e-8)
            assert d.rate_current[i] == pytest.approx(exact_cur, rel=1e-8)
            if d.adopted[i]:
                assert exact_new < 1 and exact_new < exact_cur
                current[j] = d.F[i]
                checked += 1
            else:
                assert exact_new >= 1 or exact_new >= exact_cur * (1 - 1e-12)
        unchecked = feed(system, OnlineSettings(**{**settings.__dict__, "safeguard": False}), K=40, paths=5,
                         seed=trial).decisions()
        assert unchecked.adopted.all() and set(unchecked.reason) == {"adopted_unchecked"}
    assert checked > 0


def test_bootstrap_safeguard_reports_the_worst_rates_and_adopts_only_what_passes_them():
    """With resamples: rate_worst / rate_current_worst are the largest exact rates (checked independently)
    over the moving-block resamples of the window; a gain is adopted only when it passes on the model and
    on the worst resample, `not_robust` when only the model passes, `waiting` when both pass on fewer than
    min_blocks blocks (rate_current_best, the gain in use's best draw, checked too); at the first re-design
    the adopted paths are a subset of those the model-only safeguard adopts; the decisions repeat exactly."""
    rng = np.random.default_rng(11)
    checked = robust_refusals = waits = 0
    for trial in range(4):
        system = random_system(rng, 3, 1, 2, degenerate=trial == 3)
        system = rx.AffineRandomSystem(A=system.A * 1.2, B=system.B, xi_dist=system.xi_dist)
        settings = OnlineSettings(warmup=2, period=4, memory="window", window=8, resamples=6, block=3, min_blocks=2)
        ctrl = feed(system, settings, K=30, paths=4, seed=trial)
        d = ctrl.decisions()
        again = feed(system, settings, K=30, paths=4, seed=trial).decisions()
        for name in ("rate_worst", "rate_current_worst", "adopted"):
            np.testing.assert_array_equal(getattr(d, name), getattr(again, name))
        current = {j: ctrl.F0[j] for j in range(4)}
        for i in range(len(d.k)):
            k, j = d.k[i], d.path[i]
            first, w = ctrl.weights(k)
            steps = ctrl.resample_steps(k, k + 1 - first)
            assert steps.shape == (6, k + 1 - first) and np.all(np.diff(steps[:, :3], axis=1) == 1)
            at = [[kron_rate(system, *moments(ctrl.xi[first:k + 1, j][s], w[s]), F) for s in steps]
                  for F in (d.F[i], current[j])]
            worst = [max(r) for r in at]
            if np.all(np.isfinite(d.F[i])):
                assert d.rate_worst[i] == pytest.approx(worst[0], rel=1e-8)
            assert d.rate_current_worst[i] == pytest.approx(worst[1], rel=1e-8)
            assert d.rate_current_best[i] == pytest.approx(min(at[1]), rel=1e-8)
            model_ok = d.rate_model[i] < 1 and d.rate_model[i] < d.rate_current[i]
            passes = worst[0] < 1 and worst[0] < worst[1]
            enough = k + 1 - first >= settings.min_blocks * settings.block
            assert d.adopted[i] == (model_ok and passes and enough)
            assert d.reason[i] == ("adopted" if d.adopted[i] else "waiting" if model_ok and passes
                                   else "not_robust" if model_ok else d.reason[i])
            waits += d.reason[i] == "waiting"
            robust_refusals += d.reason[i] == "not_robust"
            if d.adopted[i]:
                current[j] = d.F[i]
                checked += 1
        plain = feed(system, OnlineSettings(**{**settings.__dict__, "resamples": 0}), K=30, paths=4,
                     seed=trial).decisions()
        at_first = d.k == d.k.min()
        assert set(d.path[at_first & d.adopted]) <= set(plain.path[(plain.k == plain.k.min()) & plain.adopted])
        assert np.isnan(plain.rate_worst).all()
    assert checked > 0 and robust_refusals > 0 and waits > 0


def scalar_plant():
    """x+ = (1.2 + xi) x + u, xi ~ N(0.5, 0.25): open-loop unstable in mean square from F = 0."""
    return rx.AffineRandomSystem(A=[np.array([[1.2]]), np.array([[1.0]])], B=[np.array([[1.0]]), np.zeros((1, 1))],
                                 xi_dist=from_spec({"family": "normal", "mean": [0.5], "cov": [[0.25]]}))


def first_decision(system, xi, at_guess=None, two_point=None, **kw):
    """The one decision of a controller from F = 0 fed the ten estimates xi (10,) (window 10, re-design at
    k = 10), with the system at the prior guess `at_guess`, `two_point` and settings kw."""
    ctrl = OnlineController(system, OnlineSettings(warmup=0, period=10, memory="window", window=10, **kw),
                            np.zeros((1, 1)), paths=1, horizon=20, at_guess=at_guess, two_point=two_point)
    for k in range(11):
        ctrl.update(k, np.array([[0.0, xi[k - 1] if k else 0.0]]), np.ones(1, bool))
    d = ctrl.decisions()
    assert len(d.k) == 1 and d.k[0] == 10 and d.estimates[0] == 10
    return d


def ten_estimates(mean, spread):
    z = np.random.default_rng(0).normal(size=10)
    return mean + spread * (z - z.mean()) / z.std()


def test_first_candidate_unstable_on_the_true_plant_is_rejected_on_the_bootstrap_evidence():
    """Constructed: x+ = (1.2 + xi) x + u, xi ~ N(0.5, 0.25); ten estimates xi_{k|k} biased to mean -0.6 with
    spread 0.85 (a biased EnKF). The first candidate, designed on their model, has model rate 0.85 < 1, below
    the gain in use's (F = 0), and passes the model-only safeguard, but its exact rate on the true plant is
    1.21: with the default bootstrap evidence it is rejected (not_robust: its worst draw is >= 1)."""
    system, xi = scalar_plant(), ten_estimates(-0.6, 0.85)
    d = first_decision(system, xi)                                          # the defaults: resamples 50
    assert d.rate_model[0] == pytest.approx(0.85, rel=1e-9) and d.rate_model[0] < d.rate_current[0]
    assert rx.ms_rate(system, None, d.F[0]) >= 1.2                          # unstable on the true plant
    assert not d.adopted[0] and d.reason[0] == "not_robust" and d.rate_worst[0] >= 1
    assert d.rate_current_best[0] <= d.rate_current_worst[0]
    plain = first_decision(system, xi, resamples=0)                         # the model alone would take it
    assert plain.adopted[0] and plain.reason[0] == "adopted"
    np.testing.assert_array_equal(plain.F, d.F)


def test_two_point_moments_give_a_two_point_component_the_variance_its_mean_fixes():
    """Over batches of random moments: a marked component's variance is (mu - low)(high - mu) at mu clipped into
    [low, high] (0 outside), its correlations with the rest are kept (0 where its variance was 0), every other
    entry and the mean are unchanged and the covariance stays PSD; None changes nothing."""
    rng = np.random.default_rng(5)
    which, low, high = np.array([True, False, True]), np.array([0.0, -np.inf, -1.0]), np.array([1.0, np.inf, 2.0])
    mean = rng.uniform(-1.5, 2.5, size=(40, 7, 3))
    L = rng.normal(size=(40, 7, 3, 3)) * 0.4
    cov = L @ L.swapaxes(-1, -2)
    cov[0, 0, 0, :] = cov[0, 0, :, 0] = 0.0                           # a component whose estimates never moved
    mean[0, 0, 0] = 0.3
    new_mean, new = two_point_moments(mean, cov.copy(), (which, low, high))
    assert new_mean is mean and two_point_moments(mean, cov, None)[1] is cov
    for b, u in np.ndindex(40, 7):
        mu, c, d = mean[b, u], cov[b, u], new[b, u]
        for j in range(3):
            expected = (min(max(mu[j], low[j]), high[j]) - low[j]) * (high[j] - min(max(mu[j], low[j]), high[j]))
            assert d[j, j] == pytest.approx(expected if which[j] else c[j, j], rel=1e-12, abs=1e-15)
        assert d[1, 1] == c[1, 1]
        for i, j in ((0, 1), (0, 2), (1, 2)):
            before = c[i, j] / np.sqrt(c[i, i] * c[j, j]) if c[i, i] * c[j, j] > 0 else 0.0
            after = d[i, j] / np.sqrt(d[i, i] * d[j, j]) if d[i, i] * d[j, j] > 0 else 0.0
            assert after == pytest.approx(before, abs=1e-12) or d[i, i] * d[j, j] == 0 and d[i, j] == 0
            assert d[j, i] == pytest.approx(d[i, j], rel=1e-14)
        assert np.linalg.eigvalsh(d).min() >= -1e-12
    assert new[0, 0, 0, 0] > 0 and np.all(new[0, 0, 0, 1:] == 0)
    outside = (mean[..., 0] < 0) | (mean[..., 0] > 1)
    assert outside.any() and np.all(new[outside][:, 0, :] == 0)


def dropout_plant():
    """x+ = 1.5 x + xi u, xi ~ Bernoulli(0.75): the input arrives with probability 0.75."""
    return rx.AffineRandomSystem(A=[np.array([[1.5]]), np.zeros((1, 1))], B=[np.zeros((1, 1)), np.array([[1.0]])],
                                 xi_dist=from_spec({"family": "bernoulli", "prob": [0.75]}))


def test_a_dropout_is_modeled_with_the_variance_its_mean_fixes_so_its_rate_is_the_plants():
    """Constructed: x+ = 1.5 x + xi u, xi ~ Bernoulli(0.75); ten estimates with the right mean 0.75 but the shrunk
    spread of filtered estimates (0.1, variance 0.01). Modeled as they are, the candidate's rate is 0.20 on its
    model and 0.85 on the plant. With the component marked two-point on [0, 1], the model's variance is 0.1875
    (the plant's): the candidate is the plant's optimum, its model rate its exact rate 0.75 (both independent),
    and the bootstrap draws are modeled the same way (their worst rate, recomputed)."""
    system, xi = dropout_plant(), ten_estimates(0.75, 0.1)
    plain = first_decision(system, xi)
    assert plain.cov[0, 0, 0] == pytest.approx(0.01, rel=1e-9) and plain.rate_model[0] < 0.21
    assert rx.ms_rate(system, None, plain.F[0]) > 0.85                     # the model's 0.20 is not the plant's
    marked = (np.array([True]), np.array([0.0]), np.array([1.0]))
    d = first_decision(system, xi, two_point=marked)
    assert d.cov[0, 0, 0] == pytest.approx(0.1875, rel=1e-12) and d.mean[0, 0] == pytest.approx(0.75, rel=1e-12)
    assert d.F[0, 0, 0] == pytest.approx(-1.5 * 0.75 / 0.75, rel=1e-6)      # -a mu / E[xi^2], the plant's optimum
    assert d.rate_model[0] == pytest.approx(0.75, rel=1e-6)
    assert rx.ms_rate(system, None, d.F[0]) == pytest.approx(d.rate_model[0], rel=1e-6)
    assert kron_rate(system, d.mean[0], d.cov[0], d.F[0]) == pytest.approx(d.rate_model[0], rel=1e-9)
    ctrl = OnlineController(system, OnlineSettings(warmup=0, period=10, memory="window", window=10), np.zeros((1, 1)),
                            paths=1, horizon=20, two_point=marked)
    steps = ctrl.resample_steps(10, 10)
    draws = [xi[s].mean() for s in steps]
    worst = max(kron_rate(system, np.array([mu]), np.array([[min(max(mu, 0), 1) * (1 - min(max(mu, 0), 1))]]), d.F[0])
                for mu in draws)
    assert d.rate_worst[0] == pytest.approx(worst, rel=1e-9)


def test_two_point_means_stay_the_add_half_estimate_inside_their_ends():
    """With the number of estimates N (scalar or per batch), a two-point component's mean is clipped into
    [low + h, high - h], h = (high - low) / (2 (N + 1)), and its variance is the one that mean fixes; a mean
    inside stays the same bits, and other components are untouched."""
    rng = np.random.default_rng(11)
    which, low, high = np.array([True, False, True]), np.array([0.0, -np.inf, -1.0]), np.array([1.0, np.inf, 2.0])
    mean = rng.uniform(-1.5, 2.5, size=(6, 5, 3))
    mean[0, 0] = [0.0, 0.0, 2.0]                                        # every estimate at an end
    L = rng.normal(size=(6, 5, 3, 3)) * 0.4
    cov = L @ L.swapaxes(-1, -2)
    N = rng.integers(1, 60, size=6).astype(float)
    new_mean, new = two_point_moments(mean, cov.copy(), (which, low, high), N[:, None])
    for b, u in np.ndindex(6, 5):
        for j in (0, 2):
            h = (high[j] - low[j]) / (2 * (N[b] + 1))
            mu = min(max(mean[b, u, j], low[j] + h), high[j] - h)
            assert new_mean[b, u, j] == mu and new[b, u, j, j] == pytest.approx((mu - low[j]) * (high[j] - mu), rel=1e-12)
        assert new_mean[b, u, 1] == mean[b, u, 1] and new[b, u, 1, 1] == cov[b, u, 1, 1]
    assert new_mean[0, 0, 0] == 1 / (2 * (N[0] + 1)) and new_mean[0, 0, 2] == 2 - 3 / (2 * (N[0] + 1))
    scalar_mean, scalar = two_point_moments(mean[1], cov[1].copy(), (which, low, high), N[1])
    np.testing.assert_array_equal(scalar_mean, new_mean[1])
    np.testing.assert_array_equal(scalar, new[1])


def test_a_window_at_a_dropouts_end_certifies_no_gain_that_leans_on_the_switched_off_input():
    """Constructed: x+ = 1.5 x + (1e-12 + xi) u, xi ~ Bernoulli(0.75), and ten estimates all at xi = 0 (an EnKF
    that collapsed onto the end of the box). Modeled at the end, the law is deterministic with an input gain of
    1e-12, and its design is a gain of about -1.5e12 with model rate ~0, unstable beyond 1e11 on the plant. Kept
    the add-half estimate inside the end, the mean is 1/22 with the variance it fixes: the model rate is the exact
    rate at that law (independent), >= 1 for every gain (no gain stabilises so rare an input), and nothing is
    adopted."""
    system = rx.AffineRandomSystem(A=[np.array([[1.5]]), np.zeros((1, 1))], B=[np.array([[1e-12]]), np.array([[1.0]])],
                                   xi_dist=from_spec({"family": "bernoulli", "prob": [0.75]}))
    at_end = first_decision(system, np.zeros(10), resamples=0)                    # unmarked: the law at the end
    assert at_end.cov[0, 0, 0] == 0 and at_end.rate_model[0] < 1e-3 and abs(at_end.F[0, 0, 0]) > 1e11
    assert rx.ms_rate(system, None, at_end.F[0]) > 1e11
    marked = (np.array([True]), np.array([0.0]), np.array([1.0]))
    d = first_decision(system, np.zeros(10), two_point=marked)
    mu = 1 / 22
    assert d.mean[0, 0] == mu and d.cov[0, 0, 0] == pytest.approx(mu * (1 - mu), rel=1e-12)
    assert d.rate_model[0] == pytest.approx(kron_rate(system, d.mean[0], d.cov[0], d.F[0]), rel=1e-9)
    assert d.rate_model[0] >= np.sqrt(2.25 * (1 - mu)) - 1e-9                  # the optimum at that law
    assert not d.adopted[0] and d.reason[0] == "not_stabilizing"


def test_a_weighted_window_keeps_a_dropout_inside_its_ends_by_its_effective_number_of_estimates():
    """With exponential memory (forgetting 0.8) ten estimates at a dropout's end count as (sum w)^2 / sum w^2 of
    them, w = 0.8^(10 - t): the modeled mean is 1 / (2 (that + 1)), recomputed here from the weights."""
    marked = (np.array([True]), np.array([0.0]), np.array([1.0]))
    ctrl = OnlineController(dropout_plant(), OnlineSettings(warmup=0, period=10, memory="exponential", forgetting=0.8),
                            np.zeros((1, 1)), paths=1, horizon=20, two_point=marked)
    for k in range(11):
        ctrl.update(k, np.array([[0.0, 1.0 if k else 0.5]]), np.ones(1, bool))
    d = ctrl.decisions()
    w = 0.8 ** (10 - np.arange(1, 11))
    n_eff = w.sum() ** 2 / (w ** 2).sum()
    assert 7 < n_eff < 8 and d.estimates[0] == 10
    assert d.mean[0, 0] == pytest.approx(1 - 1 / (2 * (n_eff + 1)), rel=1e-12)


def test_a_thin_window_acts_only_where_the_prior_guess_also_calls_the_gain_in_use_unstable():
    """x+ = (1.2 + xi) x + u from F = 0, ten estimates about the true law N(0.5, 0.25): every resample calls F = 0
    unstable and the candidate passes the model and every resample, but ten estimates are two blocks. With
    min_blocks 4 (the default) it waits, unless the system at the prior guess calls F = 0 unstable too (the
    guess xi = 0.5: rate 1.7); a guess at which F = 0 is stable (xi = -0.5: rate 0.7), or none, leaves it
    waiting. With min_blocks 2 the window is enough and the candidate is adopted whatever the guess."""
    system, xi = scalar_plant(), ten_estimates(0.5, 0.5)
    at = {guess: tuple(M[0] for M in system.at([guess])[:2]) for guess in (0.5, -0.5)}
    reasons = {}
    for min_blocks in (4, 2):
        for guess in (None, 0.5, -0.5):
            d = first_decision(system, xi, None if guess is None else at[guess], min_blocks=min_blocks)
            assert d.rate_current_best[0] >= 1 and d.rate_worst[0] < 1 and d.rate_model[0] < 1
            expected = np.nan if guess is None else abs(1.2 + guess)
            np.testing.assert_allclose(d.rate_current_guess[0], expected, rtol=1e-12)
            reasons[min_blocks, guess] = d.reason[0]
    assert reasons == {(4, None): "waiting", (4, 0.5): "adopted", (4, -0.5): "waiting",
                       (2, None): "adopted", (2, 0.5): "adopted", (2, -0.5): "adopted"}


def moments(xi, w):
    """Weighted mean (p,) and 1/sum(w) covariance (p, p) of samples xi (T, p), computed directly."""
    w = w / w.sum()
    mean = w @ xi
    return mean, (xi - mean).T @ np.diag(w) @ (xi - mean)


@pytest.mark.parametrize("method", ["lqr_mean", "proposed"])
def test_other_methods_path_by_path(method):
    """Methods without a batched form design path by path; the recorded rate is the gain's exact rate on
    the path's model, and `proposed` reaches the model's optimum (policy iteration's, within 1e-6)."""
    ctrl = feed(paper.plant(), OnlineSettings(warmup=5, period=20, memory="all", method=method), K=30,
                paths=2, seed=0)
    d = ctrl.decisions()
    assert len(d.k) == 2 and np.all(np.isfinite(d.F))
    for i in range(2):
        assert d.rate_model[i] == pytest.approx(kron_rate(paper.plant(), d.mean[i], d.cov[i], d.F[i]), rel=1e-8)
        if method == "proposed":
            optimum = rx.synthesize(paper.plant(), rx.MomentModel(d.mean[i], d.cov[i]), "policy_iteration").lam
            assert d.rate_model[i] == pytest.approx(optimum, abs=1e-6)


# ------------------------------------------------------------------------------ config and runner
@pytest.fixture
def hydra_context():
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        yield


@pytest.mark.parametrize("overrides, message", [
    ("controller=online controller.period=0", "controller.period: 0 is not allowed, expected an integer >= 1"),
    ("controller=online controller.memory=window controller.window=101",
     "controller.window: 101 is not allowed, longer than closed_loop.horizon = 100"),
    ("controller=online controller.method=magic", "controller.method: 'magic' is not allowed, expected one of"),
    ("controller=online controller.memory=forever", "controller.memory: 'forever' is not allowed"),
    ("controller=online controller.initial=random", "controller.initial: 'random' is not allowed"),
    ("controller=online controller.forgetting=1.0", "controller.forgetting: 1 is not allowed"),
    ("controller=online controller.safeguard=maybe", "controller.safeguard: 'maybe' is not allowed"),
    ("controller=online controller.covariance=full", "controller.covariance: 'full' is not allowed"),
    ("controller=online controller.resamples=-1", "controller.resamples: -1 is not allowed"),
    ("controller=online controller.lag=-1", "controller.lag: -1 is not allowed"),
    ("controller=online controller.lag=1.5", "controller.lag: 1.5 is not allowed"),
    ("controller=online controller.start=flat", "controller.start: 'flat' is not allowed, expected one of"),
    ("controller=online controller.start_spread=0", "controller.start_spread: 0 is not allowed, expected a finite "
                                                    "number > 0"),
    ("controller=online controller.mean_spread=-0.5", "controller.mean_spread: -0.5 is not allowed, expected a finite "
                                                       "number > 0"),
    ("controller=online controller.probe=-1", "controller.probe: -1 is not allowed, expected a finite number >= 0"),
    ("controller=online controller.probe_until=soon", "controller.probe_until: 'soon' is not allowed, expected "
                                                      "auto, null or a step >= 0"),
    ("controller=online +controller.options.max_iter=-1", "controller.options: max_iter: -1 is not allowed"),
    ("controller.type=hybrid", "controller.type: 'hybrid' is not allowed"),
    ("+controller.period=5", "controller.period: not read by controller=offline"),
    ("controller=online +controller.perod=5", "controller: ['perod'] is not allowed"),
])
def test_bad_controller_config_is_one_line(hydra_context, overrides, message):
    with pytest.raises(ConfigError) as err:
        build(compose("config", overrides=overrides.split()))
    assert str(err.value).startswith(message), str(err.value)
    assert "\n" not in str(err.value)


def test_lag_auto_reaches_every_component(tmp_path):
    """controller.lag=auto (the default): one step, or as many as the slowest xi needs to reach an output
    (`output_delay`). The multiplicative plant measures x1 and x3: xi_2 on a23 moves x2, seen one step later;
    measuring x1 alone, xi_3 (a31) and xi_4 (the input gain) move x3, two steps from x1."""
    import yaml
    spec = yaml.safe_load((REPO / "conf" / "plant" / "multiplicative.yaml").read_text())
    (tmp_path / "plant").mkdir()
    (tmp_path / "plant" / "x1_only.yaml").write_text(yaml.safe_dump(dict(spec, name="x1_only", C=[[[1, 0, 0]]])))
    lags = {}
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        for plant, extra in (("paper", []), ("multiplicative", []), ("x1_only", []), ("x1_only", ["controller.lag=0"])):
            exp = build(compose("config", overrides=[f"hydra.searchpath=[file://{tmp_path}]", f"plant={plant}",
                                                     "controller=online", *extra]))
            lags[plant, bool(extra)] = exp.controller.online.lag
    assert lags == {("paper", False): 1, ("multiplicative", False): 1, ("x1_only", False): 2, ("x1_only", True): 0}


@pytest.mark.slow
def test_static_mean_start_acts_with_the_model_observer_only(hydra_context):
    """controller.start is the loop's EnKF before a path's first model, which only observer=model draws from:
    on the paper's plant (observer random_walk, the walk throughout) both starts give the same bytes and the
    summary records the walk; on multiplicative (observer model) the static mean is the default, recorded,
    and changes the loop."""
    from rdsexp.experiment.pipeline import run_experiment
    small = [o for o in SMALL if not o.startswith("closed_loop.horizon")] + [
        "closed_loop.horizon=40", "controller=online", "controller.warmup=5", "controller.period=10",
        "closed_loop.open_loop=false"]
    out = {(plant, start): run_experiment(build(compose("config", overrides=small + [f"plant={plant}", *start])))
           for plant in ("paper", "multiplicative") for start in ((), ("controller.start=random_walk",))}
    assert [o.summary["online_initial"]["start"] for o in out.values()] == ["random_walk", "random_walk",
                                                                             "static_mean", "random_walk"]
    for name in ("controller", "trajectories", "paths"):
        pd.testing.assert_frame_equal(out["paper", ()].tables[name], out["paper", ("controller.start=random_walk",)]
                                      .tables[name], check_exact=True, obj=name)
    online = [o.tables["trajectories"].query("experiment == 'online'") for o in out.values()]
    assert not np.array_equal(online[2]["u[0]"], online[3]["u[0]"])       # the estimates x_{k|k-1} fed back


def test_a_thin_window_acts_from_zero_on_an_open_loop_unstable_plant_and_waits_from_nominal(hydra_context):
    """cart_pole is open-loop unstable at its guess (the plant file's mean). From F = 0 its first re-design
    (k = 10: five estimates, one block) records rate_current_guess = the spectral radius of A(xi_guess),
    computed here independently, and adopts where every resample also calls F = 0 unstable; from the nominal
    gain, stable at the guess by design, the same thin window records a rate below 1 and waits."""
    from rdsexp.experiment.pipeline import run_experiment
    small = [o for o in SMALL if not o.startswith("closed_loop.horizon")] + [
        "closed_loop.horizon=30", "plant=cart_pole", "controller=online", "controller.warmup=5",
        "controller.period=5", "closed_loop.open_loop=false", "closed_loop.paths=6"]
    first = {}
    for start in ("zero", "nominal"):
        exp = build(compose("config", overrides=small + [f"controller.initial={start}"]))
        ctl = run_experiment(exp).tables["controller"]
        first[start] = ctl[ctl["k"] == 10]
        assert (first[start]["estimates"] == 5).all() and len(first[start]) == 6
    A, _, _, _ = exp.plant.at(exp.identification.xi_guess)
    zero, nominal = first["zero"], first["nominal"]
    np.testing.assert_allclose(zero["rate_current_guess"], np.abs(np.linalg.eigvals(A)).max(), rtol=1e-9)
    assert (zero["rate_current_guess"] > 1).all() and (nominal["rate_current_guess"] < 1).all()
    urgent = (zero["rate_current_best"] >= 1) & zero["reason"].isin(["adopted", "waiting"])
    assert urgent.any() and (zero["adopted"] == urgent).all(), zero[["reason", "rate_current_best"]]
    assert not nominal["adopted"].any()


def test_offline_is_the_default_and_online_builds(hydra_context):
    assert build(compose("config")).controller.kind == "offline"
    exp = build(compose("config", overrides=["controller=online"]))
    assert exp.controller.kind == "online" and exp.controller.online.method == "policy_iteration" and exp.controller.online.safeguard


def test_cli_period_zero_exits_2(tmp_path):
    proc = rdsexp("controller=online", "controller.period=0", cwd=tmp_path, check=False)
    assert proc.returncode == 2
    assert proc.stderr.strip() == ("rdsexp: config error: controller.period: 0 is not allowed, "
                                   "expected an integer >= 1")


def test_online_run_records_the_controller_table(tmp_path):
    small = [o for o in SMALL if not o.startswith("closed_loop.horizon")] + ["closed_loop.horizon=40"]
    rdsexp(*small, "controller=online", "controller.warmup=5", "controller.period=10", cwd=tmp_path)
    (run,) = (tmp_path / "outputs" / "runs").iterdir()
    table = pd.read_parquet(run / "controller.parquet")
    traj = pd.read_parquet(run / "trajectories.parquet")
    metrics = pd.read_parquet(run / "metrics.parquet").set_index("experiment")
    assert set(table["k"]) == {-1, 15, 25, 35}                      # initial gain, then warmup + j period
    initial = table[table["k"] == -1]                                # the default start: the nominal gain
    assert len(initial) == 4 and (initial.filter(like="F[").nunique() == 1).all() and (initial["F[0,0]"] != 0).all()
    assert set(initial["reason"]) == {"initial"} and (initial["rate_plant"] < 1).all()
    # the gain in use in the trajectories is the path's adopted gain from the step after its update
    online = traj[traj["experiment"] == "online"]
    adopted = table[table["adopted"] & (table["k"] >= 0)]
    for path, k, F0 in zip(adopted["path"], adopted["k"], adopted["F[0,0]"]):
        assert online[(online["path"] == path) & (online["k"] == k + 1)]["F[0,0]"].item() == F0
    assert {"closed_loop", "open_loop", "online"} <= set(metrics.index)
    assert 0 < metrics.loc["online", "optimal_rate_plant"] <= metrics.loc["online", "offline_rate_plant"]
    # the recording holds the gain in use (row i of F as F<i>), the long form too
    ks, gain = read_series(run / "recording.rrd", "/online/F0/1")          # (k, path) order
    in_use = online.pivot(index="k", columns="path", values="F[0,1]")
    assert np.array_equal(gain, in_use.loc[np.unique(ks)].to_numpy().ravel())
    # the online tab: median over paths of the true rate of the gain in use from each step on, and
    # of the modeled mean at each update step, recomputed here path by path
    ks, median = read_series(run / "recording.rrd", "/summary/online/rate_plant/online/median")
    assert list(ks) == [0, 16, 26, 36]
    for step, value in zip(ks, median):
        held = [adopted_rows[adopted_rows["k"] < step]["rate_plant"].iloc[-1]
                for _, adopted_rows in table[table["adopted"]].groupby("path")]
        assert value == pytest.approx(np.median(held), rel=1e-12)
    ks, median = read_series(run / "recording.rrd", "/summary/online/xi_mean/xi1/median")
    decisions = table[table["k"] >= 0]
    np.testing.assert_allclose(median, [np.median(decisions[decisions["k"] == k]["mean[1]"]) for k in ks], rtol=1e-12)
    long = runs.load(run, "trajectories", long=True)
    assert set(long[long["quantity"] == "F0"]["index"]) == set(range(6))
    for frame in (table, traj, pd.read_parquet(run / "metrics.parquet")):     # every column described
        assert all(d["description"] for d in frame.attrs["rdsexp"]["columns"].values()), frame.attrs["rdsexp"]


@pytest.mark.parametrize("plant", ["paper", "multiplicative", "dropout"])
@pytest.mark.slow
def test_online_loop_does_not_depend_on_chunks_of_paths_or_workers(hydra_context, plant):
    """One controller per chunk of paths, chunks (3 paths and 1) in worker processes as the offline loops' are: the
    decisions, rows and metrics equal those of one batch, bit for bit; with the random walk (paper) and with
    the static-mean start and draws from each path's model (multiplicative: observer model), and with a
    two-point component drawn and modeled as one (dropout)."""
    from rdsexp.experiment.pipeline import run_experiment
    small = [o for o in SMALL if not o.startswith("closed_loop.horizon")] + ["closed_loop.horizon=40",
                                                                              f"plant={plant}"]
    tables = [run_experiment(build(compose("config", overrides=small + [
        "controller=online", "controller.warmup=5", "controller.period=10", "closed_loop.open_loop=false", *chunk])))
        .tables for chunk in (["closed_loop.chunk_paths=4"], ["closed_loop.chunk_paths=3", "closed_loop.workers=2"])]
    for other in tables[1:]:
        for name in ("controller", "trajectories", "metrics", "paths"):
            pd.testing.assert_frame_equal(tables[0][name], other[name], check_exact=True, obj=name)
    assert (tables[0]["controller"]["k"] >= 0).any()


@pytest.mark.slow
def test_report_tables_the_controllers_sweep_per_plant(tmp_path):
    """fig_online: per plant, a figure and a table whose numbers are the runs' metrics (means over
    seeds), and a verdict that names exactly the settings meeting its criterion."""
    import sys

    from conftest import REPO
    sys.path.insert(0, str(REPO / "experiments"))
    import fig_online

    from rdsexp import report
    small = [o for o in SMALL if not o.startswith("closed_loop.horizon")] + ["closed_loop.horizon=40"]
    rdsexp(*small, "+sweep=controllers", "seed=0,1", "controller.warmup=5",
           "controller.period=10", "tracking.recording=false", cwd=tmp_path)
    out = tmp_path / "report"
    fig_online.main(["--root", str(tmp_path / "outputs"), "--out", str(out)])
    table = pd.read_csv(out / "online_paper.csv")
    metrics = [r.table("metrics").set_index("experiment") for r in report.load_runs(tmp_path / "outputs")]
    assert table["seeds"].item() == 2 and (out / "online_paper.png").exists()
    for column, (experiment, metric) in {"offline_diverged": ("closed_loop", "failed_fraction"),
                                         "final_true_rate_median": ("online", "final_rate_plant_median"),
                                         "offline_true_rate": ("online", "offline_rate_plant")}.items():
        expected = np.mean([m.loc[experiment, metric] for m in metrics])
        assert table[column].item() == pytest.approx(expected, abs=5e-5), column
    assert "Plant paper" in (out / "online_paper.caption.md").read_text()

    settings = pd.DataFrame({"period": [5, 10, 25, 50, 100],
                             "final_true_rate_median": [0.86, 0.845, 0.844, 0.844, 0.80],
                             "offline_true_rate": [0.844] * 5,
                             "online_rate_not_diverged": [0.80, 0.86, 0.85, 0.90, 0.95],
                             "offline_rate": [0.85] * 4 + [np.nan],
                             "online_diverged": [0.0, 0.0, 0.03, 0.0, 0.1], "offline_diverged": [0.0] * 4 + [0.5],
                             "time_online_over_offline": [2.0, 1.5, 1.2, 1.1, 1.05]})
    # 5: gains 0.016 worse; 10: within both tolerances; 25: 3% more diverged; 50: loop rate 0.05 worse;
    # 100: offline has no loop rate (a path diverged) and lost more paths: the fractions decide
    assert list(fig_online.matching(settings, 0.005, 0.02)) == [False, True, False, False, True]
    text = fig_online.verdict(settings.assign(matches=fig_online.matching(settings, 0.005, 0.02)), ["period"],
                              0.005, 0.02)
    assert "at 2 of 5 settings: period 100 (" in text and text.index("period 100") < text.index("period 10 (")
    assert not any(f"period {p} " in text for p in (5, 25, 50))
    text = fig_online.verdict(settings.assign(matches=False), ["period"], 0.005, 0.02)
    assert "at none of 5 settings; closest in the final gains: period 100" in text
    assert "closest in the loop rate: period 5" in text


def test_online_bound_models_are_unbiased_and_exact_draws_reach_the_optimum():
    """experiments/online_bound.py: the per-path covariance of samples with noise r I, before its projection,
    averages to the true covariance (to 4 standard errors over paths); from many exact draws (r = 0) the
    per-path gains' median exact rate is the optimum (policy iteration on the true law) to 1e-3, and from few
    noisy ones it is above it."""
    import sys
    sys.path.insert(0, str(REPO / "experiments"))
    import online_bound

    rng = np.random.default_rng(3)
    system = random_system(rng, 3, 1, 2)
    while rx.synthesize(system, None, "policy_iteration").lam >= 0.98:      # stabilizable with a margin
        system = random_system(rng, 3, 1, 2)
    dist, r = system.xi_dist, 0.3
    samples = dist.sample(rng, (2000, 40)) + np.sqrt(r) * rng.normal(size=(2000, 40, 2))
    mean = samples.mean(axis=1)
    dev = samples - mean[:, None]
    raw = np.einsum("ptj,ptk->pjk", dev, dev) / 39 - r * np.eye(2)                 # before the projection
    se = raw.std(axis=0) / np.sqrt(2000)
    assert np.all(np.abs(raw.mean(axis=0) - dist.cov) <= 4 * se)
    _, projected = online_bound.path_models(samples, r)
    psd = np.linalg.eigvalsh(raw).min(axis=1) >= 0
    assert psd.any() and (~psd).any() and np.linalg.eigvalsh(projected).min() >= -1e-12
    np.testing.assert_allclose(projected[psd], raw[psd], atol=1e-12, rtol=0)      # a PSD one is kept as it is
    optimum = rx.synthesize(system, None, "policy_iteration").lam
    exact = online_bound.median_rate(system, dist, np.random.default_rng(0), 20, 4000, 0.0)
    assert exact == pytest.approx(optimum, abs=1e-3)
    assert online_bound.median_rate(system, dist, np.random.default_rng(0), 20, 10, 1.0) > optimum + 1e-3


def test_probe_adds_its_signs_to_u_until_its_step_and_auto_ends_where_the_rate_window_may_start(hydra_context):
    """controller.probe: u_k = F_k x_{k|k-1} + d_k + probe * s_k (s_k in {-1, 1}^m, `probe_signs`, white and the same
    on every path) for k < probe_until, nothing after; probe_until: auto is the configured rate window's first step,
    else the first step after the disturbance (`window_start`), null never stops."""
    d = paper.disturbance(30)
    for until in (None, 12):
        ctrl = OnlineController(paper.model(), OnlineSettings(warmup=0, period=31, probe=2.0, probe_until=until),
                                paper.F_proposed, paths=3, horizon=30)
        tr = closed_loop(paper.F_proposed, paths=3, controller=ctrl)
        probe = tr.u - (paper.F_proposed @ tr.x(tr.psi_pred_mean)[..., None])[..., 0] - d[:, None]   # (K+1, P, m)
        signs = np.array([ctrl.settings.probe_signs(k, 1) for k in range(31)])                       # (K+1, m)
        on = (np.arange(31) < (31 if until is None else until))[:, None, None]
        np.testing.assert_allclose(probe, np.broadcast_to(2.0 * on * signs[:, None], probe.shape), atol=1e-9)
    assert set(signs.ravel()) == {-1.0, 1.0} and abs(signs.mean()) < 0.5
    assert np.mean(signs[1:] == signs[:-1]) < 0.8                        # white: not a held level
    # the config: auto, a step, null; the probe is off by default
    online = ["controller=online", "controller.probe=10"]
    assert build(compose("config", overrides=online)).controller.online.probe_until == 60     # paper: [0.6, 0.8]
    auto = build(compose("config", overrides=online + ["closed_loop.rate_window=auto"])).controller.online
    assert auto.probe_until == 50                                  # d_k = 10 for k < 50
    for value, expected in (("30", 30), ("null", None)):
        settings = build(compose("config", overrides=online + [f"controller.probe_until={value}"])).controller.online
        assert settings.probe_until == expected and settings.probe == 10
    assert build(compose("config", overrides=["controller=online"])).controller.online.probe == 0


@pytest.mark.slow
def test_the_summary_says_whether_the_probe_reaches_into_the_rate_window(tmp_path):
    """With controller.probe the run's summary names it, and says so where it runs into the rate window (the
    online loop's empirical rate then measures the probed loop); without the probe it says nothing."""
    small = [*SMALL, "controller=online", "controller.warmup=5", "controller.period=5", "tracking=off"]
    for until, inside in (("null", True), ("15", True), ("10", False)):
        (tmp_path / until).mkdir()
        out = rdsexp(*small, "controller.probe=3", f"controller.probe_until={until}", cwd=tmp_path / until).stdout
        line = next(x for x in out.splitlines() if x.strip().startswith("online probe:"))
        assert line.strip().startswith(f"online probe: +-3 on u until {'the end' if until == 'null' else 'k=' + until}")
        assert ("measures the probed loop" in line) == inside, line
    (tmp_path / "off").mkdir()
    assert "online probe" not in rdsexp(*small, cwd=tmp_path / "off").stdout


def test_nominal_gain_with_a_spread_is_the_mean_square_design_that_spread_does_not_destabilise():
    """x+ = 1.5 x + xi u about the guess xi = 1. The deterministic LQR (unit weights) is F = -1.5 P / (1 + P),
    P = (2.25 + sqrt(2.25^2 + 4)) / 2 (the scalar Riccati equation), whose mean-square rate at N(1, v) is
    sqrt((1.5 + F)^2 + v F^2) by hand: 1.028 at v = 0.75. With that spread, nominal_gain returns the mean-square
    LQR, stable at that law (rate < 1, its rate the exact one, independently recomputed); where no gain
    stabilizes the spread (v = 1.2: min over F of (1.5 + F)^2 + v F^2 = 2.25 v / (1 + v) > 1) it falls back to
    the deterministic design, as without one."""
    from rdsexp.numerics.modeling import nominal_gain
    system = rx.AffineRandomSystem(A=[np.array([[1.5]]), np.zeros((1, 1))], B=[np.zeros((1, 1)), np.array([[1.0]])])
    P = (2.25 + np.sqrt(2.25 ** 2 + 4)) / 2
    F_det = -1.5 * P / (1 + P)
    plain = nominal_gain(system, [1.0])
    assert plain.method == "lqr_mean" and plain.F[0, 0] == pytest.approx(F_det, rel=1e-9)
    v = 0.75
    assert np.sqrt((1.5 + F_det) ** 2 + v * F_det ** 2) > 1.02
    spread = nominal_gain(system, [1.0], cov=[[v]])
    F = spread.F[0, 0]
    exact = np.sqrt((1.5 + F) ** 2 + v * F ** 2)
    assert spread.method == "ms_lqr" and exact < 1
    assert spread.lam == pytest.approx(exact, rel=1e-9)
    assert kron_rate(system, np.array([1.0]), np.array([[v]]), spread.F) == pytest.approx(exact, rel=1e-9)
    assert np.sqrt(2.25 * 1.2 / 2.2) > 1
    wide = nominal_gain(system, [1.0], cov=[[1.2]])
    assert wide.method == "lqr_mean" and wide.F[0, 0] == pytest.approx(F_det, rel=1e-9)


def test_nominal_gain_reports_the_exact_rate_of_what_it_returns_on_random_and_degenerate_systems():
    """Over 24 random systems (every other one with a rank-deficient spread and xi-free inputs), spreads from
    narrow to wide: nominal_gain returns `ms_lqr` only when its gain is mean-square stable at N(guess, cov), and
    its lam is then that gain's exact rate there (an independent Kronecker sum); otherwise the deterministic
    design, whose lam is the spectral radius of the closed loop at the guess (or a status without a gain)."""
    from rdsexp.numerics.modeling import nominal_gain
    seen = set()
    for seed in range(24):
        rng = np.random.default_rng(100 + seed)
        n, m, p = int(rng.integers(2, 5)), int(rng.integers(1, 3)), int(rng.integers(1, 4))
        system = random_system(rng, n, m, p, degenerate=seed % 2 == 1)
        guess = 0.3 * rng.normal(size=p)
        L = rng.normal(size=(p, p)) * [0.05, 0.5, 2.0][seed % 3]
        if seed % 2:
            L[:, 0] = 0.0                                                # rank-deficient spread
        cov = L @ L.T
        res = nominal_gain(system, guess, cov=cov)
        seen.add(res.method)
        if res.method == "ms_lqr":
            assert res.lam < 1
            assert kron_rate(system, guess, cov, res.F) == pytest.approx(res.lam, rel=1e-7, abs=1e-9)
        elif res.F is not None and np.all(np.isfinite(res.F)):
            A, B, _, _ = system.at(guess[None])
            radius = np.abs(np.linalg.eigvals(A[0] + B[0] @ res.F)).max()
            assert res.lam == pytest.approx(radius, rel=1e-7, abs=1e-9)
            assert not kron_rate(system, guess, cov, res.F) < res.lam - 1e-9     # the spread only adds
    assert "ms_lqr" in seen and seen - {"ms_lqr"}                        # both branches taken
