"""EnKF variants (stochastic, etkf), inflation and relaxation: the Kalman update they approximate,
the square-root transform against its M x M definition, and the config settings (enkf_n and
adaptive inflation: test_enkf_n.py)."""
import numpy as np
import pytest
from conftest import linear_gaussian
from hydra import compose, initialize_config_module

import rdsexp as rx
from rdsexp.errors import ConfigError
from rdsexp.experiment.config import build
from rdsexp.numerics.enkf import EnKF, truth_map
from rdsexp.numerics.simulation import simulate

paper = rx.paper
ARRAYS = ("q", "y", "u", "psi_pred_mean", "psi_pred_std", "psi_filt_mean", "psi_filt_std", "failed_at")


def kalman(m, P, C, R, y):
    """Exact Kalman analysis mean (..., n) and covariance (..., n, n) from forecast moments."""
    G = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
    return m + ((y - m @ C.T)[..., None, :] @ G.swapaxes(-1, -2))[..., 0, :], P - G @ C @ P


def moments(ens):
    """Sample mean (..., n) and covariance (ddof 1) (..., n, n) of an ensemble (..., M, n)."""
    mean = ens.mean(-2)
    dev = ens - mean[..., None, :]
    return mean, dev.swapaxes(-1, -2) @ dev / (ens.shape[-2] - 1)


@pytest.mark.parametrize("M", [2, 3, 5, 40])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_etkf_equals_kalman_update_of_the_forecast_moments(M, seed):
    """For any M (also M - 1 < n: a rank-deficient forecast covariance) the ETKF's analysis sample
    mean and covariance are the Kalman update of the forecast ensemble's sample moments."""
    system, C, R, rng = linear_gaussian(seed)
    enkf = EnKF(system, 0.0, R, variant="etkf")
    ens = rng.normal(size=(4, M, 3)) @ rng.normal(size=(3, 3)) + rng.normal(size=(4, 1, 3))
    y = rng.normal(size=(4, 2))
    a = enkf.update(ens, np.zeros((4, 1)), y, None)
    m_kf, P_kf = kalman(*moments(ens), C, R, y)
    m_a, P_a = moments(a.psi)
    np.testing.assert_allclose(m_a, m_kf, rtol=0, atol=1e-10 * (1 + np.abs(m_kf).max()))
    np.testing.assert_allclose(P_a, P_kf, rtol=0, atol=1e-10 * (1 + np.abs(P_kf).max()))
    np.testing.assert_allclose(a.filt_mean, m_kf, atol=1e-10 * (1 + np.abs(m_kf).max()))
    np.testing.assert_allclose(a.filt_std, np.sqrt(np.clip(np.diagonal(P_kf, axis1=-2, axis2=-1), 0, None)),
                               atol=1e-7)
    assert a.ok.all()


@pytest.mark.parametrize("seed", [0, 1])
def test_etkf_transform_equals_its_M_by_M_definition_on_the_paper_model(seed):
    """Bilinear outputs (the paper's model, p = 3): the ny x ny form used equals
    psi_a = mean + K (y - z_mean) + X (I + S^T S)^(-1/2) with S = R^(-1/2) Y / sqrt(M-1),
    computed here per path with an M x M eigendecomposition; the transform keeps the mean."""
    rng = np.random.default_rng(seed)
    P, M = 3, 12
    model = paper.model()
    enkf = EnKF(model, paper.Q, paper.R, variant="etkf")
    psi = rng.normal(size=(P, M, 9))
    u, y = rng.normal(size=(P, 1)), rng.normal(size=(P, 3))
    a = enkf.update(psi, u, y, None)
    Rh_inv = np.linalg.inv(np.linalg.cholesky(paper.R))            # any square root of R^-1 gives the same S^T S
    for j in range(P):
        z = np.stack([model.at(p[6:])[2] @ p[:6] for p in psi[j]])  # (M, ny), D = 0
        X, Y = (psi[j] - psi[j].mean(0)).T, (z - z.mean(0)).T
        S = Rh_inv @ Y / np.sqrt(M - 1)
        w, V = np.linalg.eigh(np.eye(M) + S.T @ S)
        T = (V / np.sqrt(w)) @ V.T
        K = (X @ Y.T) @ np.linalg.inv(Y @ Y.T + (M - 1) * paper.R)
        ref = psi[j].mean(0) + K @ (y[j] - z.mean(0)) + (X @ T).T
        np.testing.assert_allclose(a.psi[j], ref, atol=1e-11)
        np.testing.assert_allclose(a.psi[j].mean(0), a.filt_mean[j], atol=1e-12)


def test_stochastic_update_approaches_kalman_within_sampling_error():
    """The perturbed-output update of a fixed forecast ensemble: its analysis mean and covariance
    differ from the Kalman update by sampling error ~ 1/sqrt(M). With the same forecast moments, over 40 independent draws of the
    perturbations, the RMS error at M = 4000 is about 1/4 of that at M = 250, and every draw at
    M = 4000 lies within 5 of the standard errors predicted from the M = 250 draws."""
    system, C, R, rng = linear_gaussian(7)
    enkf = EnKF(system, 0.0, R)
    paths, y = 40, rng.normal(size=2)
    m_f, L_f = rng.normal(size=3), rng.normal(size=(3, 3))
    err = {}
    for M in (250, 4000):
        E = rng.normal(size=(M, 3))                                # whitened: the same forecast moments
        E -= E.mean(0)                                             # (mean m_f, covariance L_f L_f^T) for both M
        E = E @ np.linalg.inv(np.linalg.cholesky(E.T @ E / (M - 1))).T
        ens = m_f + E @ L_f.T
        ens = np.broadcast_to(ens, (paths, M, 3))                  # one forecast, independent perturbations
        a = enkf.update(ens, np.zeros((paths, 1)), np.broadcast_to(y, (paths, 2)), rng.normal(size=(paths, M, 2)))
        m_kf, P_kf = kalman(*moments(ens[:1]), C, R, y[None])
        m_a, P_a = moments(a.psi)
        err[M] = (m_a - m_kf, (P_a - P_kf).reshape(paths, -1))
    for i, name in enumerate(("mean", "cov")):
        small, large = err[250][i], err[4000][i]
        ratio = np.sqrt(np.mean(large ** 2) / np.mean(small ** 2))
        assert 0.15 < ratio < 0.4, (name, ratio)                    # 1/4 expected
        predicted = np.sqrt(np.mean(small ** 2, axis=0) * 250 / 4000)
        assert np.all(np.abs(large) < 5 * predicted + 1e-12), name


def test_inflation_scales_the_forecast_anomalies_and_one_changes_nothing():
    rng = np.random.default_rng(3)
    psi, u, e_w = rng.normal(size=(2, 6, 9)), rng.normal(size=(2, 1)), rng.normal(size=(2, 6, 9))
    base = EnKF(paper.model(), paper.Q, paper.R).predict(psi, u, e_w)
    inflated = EnKF(paper.model(), paper.Q, paper.R, inflation=1.3).predict(psi, u, e_w)
    mean = base.mean(-2, keepdims=True)
    np.testing.assert_allclose(inflated.mean(-2, keepdims=True), mean, atol=1e-13)
    np.testing.assert_allclose(inflated - mean, 1.3 * (base - mean), atol=1e-12)
    # inflation 1 and relaxation 0 given explicitly: bit-identical closed loops
    runs = [simulate(paper.plant(), EnKF(paper.model(), paper.Q, paper.R, **kw), F=paper.F_proposed,
                     d=paper.disturbance(20), q0=paper.q0, psi0=paper.psi0, ensemble_size=15, paths=3, seed=5)
            for kw in ({}, {"variant": "stochastic", "inflation": 1.0, "relaxation": 0.0})]
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(runs[0], name), getattr(runs[1], name), err_msg=name)


@pytest.mark.parametrize("variant", ["stochastic", "etkf"])
def test_relaxation_sets_the_analysis_spread_between_posterior_and_prior(variant):
    rng = np.random.default_rng(4)
    psi, u, y = rng.normal(size=(3, 30, 9)), rng.normal(size=(3, 1)), rng.normal(size=(3, 3))
    e_v = rng.normal(size=(3, 30, 3)) if variant == "stochastic" else None
    plain = EnKF(paper.model(), paper.Q, paper.R, variant=variant).update(psi, u, y, e_v)
    relaxed = EnKF(paper.model(), paper.Q, paper.R, variant=variant, relaxation=0.25).update(psi, u, y, e_v)
    want = 0.25 * plain.pred_std + 0.75 * plain.filt_std
    np.testing.assert_allclose(relaxed.filt_std, want, rtol=1e-10)
    np.testing.assert_allclose(relaxed.psi.std(-2, ddof=1), want, rtol=1e-10)
    np.testing.assert_allclose(relaxed.psi.mean(-2), plain.psi.mean(-2), atol=1e-12)


def test_etkf_streams_are_per_path_and_draw_no_output_noise():
    """3 paths alone equal the first 3 of 5 with another block size; the ETKF's loop differs from
    the stochastic one (it filters without output perturbations)."""
    def run(paths, block, variant="etkf"):
        return simulate(paper.plant(), EnKF(paper.model(), paper.Q, paper.R, variant=variant), F=paper.F_proposed,
                        d=paper.disturbance(25), q0=paper.q0, psi0=paper.psi0, ensemble_size=20, paths=paths,
                        seed=2, block=block)
    a, b = run(5, 16), run(3, 7)
    for name in ARRAYS:
        x = getattr(a, name)
        np.testing.assert_array_equal(x[..., :3, :] if x.ndim > 1 else x[:3], getattr(b, name), err_msg=name)
    assert not np.allclose(run(3, 7, "stochastic").psi_filt_mean[5:], b.psi_filt_mean[5:])


def test_truth_map_of_the_paper_and_of_a_model_that_is_the_plant():
    T, t = truth_map(paper.model(), paper.plant())
    np.testing.assert_allclose(T, [[0.7, 0], [0, 1], [0, 0]], atol=1e-12)
    np.testing.assert_allclose(t, [0, 0, 0.6], atol=1e-12)
    s = np.random.default_rng(0).normal(size=(5, 2))                # independent check: the matrices agree
    for M_model, M_plant in zip(paper.model().at(s @ T.T + t), paper.plant().at(s)):
        np.testing.assert_allclose(M_model, M_plant, atol=1e-12)
    T, t = truth_map(paper.plant(), paper.plant())
    np.testing.assert_allclose(T, np.eye(2), atol=1e-12)
    assert truth_map(paper.plant(), paper.model()) is None          # s does not determine xi3's entry


BAD = [
    ("enkf.variant=enkf_x", "enkf.variant: 'enkf_x' is not allowed, expected one of stochastic, etkf, enkf_n"),
    ("enkf.inflation=0.9", "enkf.inflation: 0.9 is not allowed, expected a finite number >= 1"),
    ("enkf.inflation=inf", "enkf.inflation: inf is not allowed, expected a finite number >= 1"),
    ("enkf.inflation=nan", "enkf.inflation: nan is not allowed, expected a finite number >= 1"),
    ("enkf.relaxation=1.5", "enkf.relaxation: 1.5 is not allowed, expected a finite number >= 0 and <= 1"),
    ("enkf=etkf enkf.R=0", "enkf.R: must be positive definite with enkf.variant=etkf"),
]


@pytest.mark.parametrize("overrides, message", BAD, ids=[b[0] for b in BAD])
def test_bad_enkf_settings_are_one_line_config_errors(overrides, message):
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        with pytest.raises(ConfigError) as err:
            build(compose("config", overrides=overrides.split()))
    assert str(err.value).startswith(message), str(err.value)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("kwargs, message", [({"variant": "sqrt"}, "variant: 'sqrt' is not allowed"),
                                             ({"inflation": 0.5}, "inflation: 0.5 is not allowed"),
                                             ({"relaxation": -0.1}, "relaxation: -0.1 is not allowed")])
def test_python_api_rejects_bad_settings(kwargs, message):
    with pytest.raises(ValueError, match=message):
        EnKF(paper.model(), paper.Q, paper.R, **kwargs)


def test_frontier_is_the_smallest_M_within_tolerance_without_divergence():
    """experiments/fig_filters.py: a diverged seed or a rate off by more than 0.01 disqualifies an M."""
    import sys

    from conftest import REPO
    sys.path.insert(0, str(REPO / "experiments"))
    import fig_filters
    import pandas as pd
    rows = [("stochastic", 1.0, None, 300, 0.850, 0), ("stochastic", 1.0, None, 100, 0.855, 0),
            ("stochastic", 1.0, None, 20, 0.851, 1), ("etkf", 1.1, None, 10, 0.845, 0), ("etkf", 1.1, None, 300, 0.86, 0),
            ("etkf", 1.0, None, 20, 0.8615, 0), ("etkf", "adaptive", None, 20, 0.852, 0),
            ("stochastic", 1.0, 0.01, 300, 0.90, 0), ("etkf", 1.1, 0.01, 20, 0.852, 0), ("etkf", 1.1, 0.01, 15, 0.85, 1)]
    stats = pd.DataFrame([{"variant": v, "inflation": fig_filters.inflation(rho), "relaxation": 0.0,
                           "disturbance": fig_filters.disturbance(d), "M": M, "rate": r, "seeds_diverged": dv}
                          for v, rho, d, M, r, dv in rows])
    table, ref, sentence = fig_filters.frontier(stats)
    assert ref == 0.850                                      # the stochastic EnKF without the d estimate
    smallest = {(r.variant, r.inflation, r.disturbance): r.smallest_M for r in table.itertuples()}
    assert smallest[("stochastic", "1", "off")] == 100 and smallest[("etkf", "1.1", "off")] == 10
    assert smallest[("etkf", "adaptive", "off")] == 20      # adaptive inflation: a text among numbers
    assert pd.isna(smallest[("etkf", "1", "off")])          # 0.0115 away
    assert smallest[("etkf", "1.1", "0.01")] == 20 and pd.isna(smallest[("stochastic", "1", "0.01")])
    assert "etkf: none of M = 20" in sentence and "etkf rho=1.1: M = 10" in sentence
    assert "etkf rho=1.1 d=0.01: M = 20" in sentence


def test_best_tuned_takes_the_fewest_diverged_paths_then_the_lowest_crps():
    """experiments/fig_filters.py: each variant at each M keeps the knob with the fewest diverged paths
    and, among those, the lowest CRPS of the modeled xi."""
    import sys

    from conftest import REPO
    sys.path.insert(0, str(REPO / "experiments"))
    import fig_filters
    import pandas as pd
    rows = [("etkf", 1.0, None, 20, 0.86, 0.0, 0.10), ("etkf", 1.1, None, 20, 0.85, 0.0, 0.08),
            ("etkf", "adaptive", None, 20, 0.84, 0.1, 0.01), ("etkf", 1.0, None, 50, 0.85, 0.0, 0.05),
            ("etkf", 1.1, None, 50, 0.85, 0.0, float("nan")), ("enkf_n", 1.0, None, 20, 0.85, 0.2, 0.30),
            ("etkf", 1.1, 0.01, 50, 0.85, 0.0, 0.06), ("enkf_n", 1.0, 0.01, 20, 0.86, 0.0, 0.35)]
    stats = pd.DataFrame([{"variant": v, "inflation": fig_filters.inflation(rho), "relaxation": 0.0,
                           "disturbance": fig_filters.disturbance(d), "M": M, "rate": r, "diverged_fraction": dv,
                           "xi_crps": c} for v, rho, d, M, r, dv, c in rows])
    best = fig_filters.best_tuned(stats, ref=0.85).set_index(["variant", "M"])
    assert best.loc[("etkf", 20), "inflation"] == "1.1"          # adaptive diverged, 1.1 scores better than 1
    assert tuple(best.loc[("etkf", 50), ["inflation", "disturbance"]]) == ("1", "off")   # unscored ranks last
    assert best.loc[("enkf_n", 20), "disturbance"] == "0.01"     # the d estimate is a knob: no path lost
                                                                 # beats a lower CRPS
    assert best.loc[("enkf_n", 20), "knobs_tried"] == 2 and best.loc[("etkf", 20), "knobs_tried"] == 4
    assert abs(best.loc[("etkf", 20), "rate_minus_reference"]) < 1e-12
