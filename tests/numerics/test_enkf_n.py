"""The finite-size EnKF (enkf_n; Bocquet 2011, dual form of Bocquet, Raanes & Hannart 2015) against a
direct computation of its analysis, its large-ensemble limit (the ETKF), and adaptive inflation
(Miyoshi 2011's innovation estimate, smoothed in time) on a case whose correct inflation is known."""
import numpy as np
import pytest
from conftest import linear_gaussian
from hydra import compose, initialize_config_module
from scipy.optimize import brentq

import rdsexp as rx
from rdsexp.errors import ConfigError
from rdsexp.experiment.config import build
from rdsexp.numerics.enkf import AdaptiveInflation, EnKF, component_major, enkf_n_zeta
from rdsexp.numerics.simulation import simulate

paper = rx.paper
ARRAYS = ("q", "y", "u", "psi_pred_mean", "psi_pred_std", "psi_filt_mean", "psi_filt_std", "failed_at")


def direct_enkf_n(psi, z, y, R):
    """EnKF-N analysis of one path from its definition, with M x M matrices: psi (M, d) forecast
    members, z (M, ny) their outputs. zeta_a: the global minimum of the dual cost
    D(zeta) = 1/2 delta^T (R + Y Y^T / zeta)^-1 delta + eps zeta / 2 + N/2 ln(N / zeta) - N/2 on a fine grid
    of (0, N / eps], then the root of D' in the grid cells beside it (brentq); then
    w = (Y^T R^-1 Y + zeta I)^-1 Y^T R^-1 delta, mean + X w and sqrt(N-1) X (Y^T R^-1 Y + zeta I)^(-1/2).
    Returns (members (M, d), zeta_a)."""
    N = psi.shape[0]
    eps, Rinv = 1 + 1 / N, np.linalg.inv(R)
    X, Y = (psi - psi.mean(0)).T, (z - z.mean(0)).T
    delta = y - z.mean(0)

    def D(zeta):
        return 0.5 * delta @ np.linalg.solve(R + Y @ Y.T / zeta, delta) + 0.5 * eps * zeta \
            + 0.5 * N * np.log(N / zeta) - 0.5 * N

    def dD(zeta):
        a = np.linalg.solve(R + Y @ Y.T / zeta, delta)
        return 0.5 * a @ Y @ Y.T @ a / zeta ** 2 + 0.5 * eps - 0.5 * N / zeta

    top = N / eps
    grid = top * np.logspace(-9, 0, 9001)
    j = int(np.argmin([D(g) for g in grid]))
    lo, hi = grid[max(j - 1, 0)], grid[min(j + 1, len(grid) - 1)]
    zeta = top if dD(hi) <= 0 else brentq(dD, lo, hi, xtol=1e-300, rtol=1e-15)
    H = Y.T @ Rinv @ Y + zeta * np.eye(N)
    w = np.linalg.solve(H, Y.T @ Rinv @ delta)
    lam, V = np.linalg.eigh(H)
    T = np.sqrt(N - 1) * (V / np.sqrt(lam)) @ V.T
    return (psi.mean(0) + X @ w)[None, :] + (X @ T).T, zeta


CASES = [(seed, M, ny) for seed in (0, 1, 2) for M, ny in ((3, 1), (5, 2), (12, 2), (8, 3))]


@pytest.mark.parametrize("seed, M, ny", CASES)
def test_enkf_n_equals_its_direct_computation(seed, M, ny):
    """Four paths at once (one with y = z_mean, where zeta_a = N / eps_N, and one whose innovation
    is far outside the forecast spread): members, mean, inflation factor and zeta_a agree with the
    direct M x M computation to 1e-8."""
    system, C, R, rng = linear_gaussian(seed, ny=ny)
    P = 4
    psi = rng.normal(size=(P, M, 3)) @ rng.normal(size=(3, 3)) + rng.normal(size=(P, 1, 3))
    y = rng.normal(size=(P, ny))
    y[1] = psi[1].mean(0) @ C.T                                     # no innovation
    y[2] *= 30                                                       # the forecast spread is far too small
    a = EnKF(system, 0.0, R, variant="enkf_n").update(psi, np.zeros((P, 1)), y, None)
    for j in range(P):
        members, zeta = direct_enkf_n(psi[j], psi[j] @ C.T, y[j], R)
        scale = 1 + np.abs(members).max()
        np.testing.assert_allclose(a.psi[j], members, rtol=0, atol=1e-8 * scale)
        np.testing.assert_allclose(a.filt_mean[j], members.mean(0), rtol=0, atol=1e-8 * scale)
        np.testing.assert_allclose(a.inflation[j], np.sqrt((M - 1) / zeta), rtol=1e-8)
    assert a.inflation[1] == pytest.approx(np.sqrt((M - 1) * (M + 1)) / M, rel=1e-12)   # zeta_a = N / eps_N
    assert a.inflation[2] > 2


def test_enkf_n_on_the_paper_model_equals_its_direct_computation():
    """Bilinear outputs (the paper's model, p = 3, ny = 3): Y is the spread of the members' outputs."""
    rng = np.random.default_rng(5)
    P, M = 3, 10
    model = paper.model()
    psi = rng.normal(size=(P, M, 9))
    u, y = rng.normal(size=(P, 1)), rng.normal(size=(P, 3))
    a = EnKF(model, paper.Q, paper.R, variant="enkf_n").update(psi, u, y, None)
    for j in range(P):
        z = np.stack([model.at(p[6:])[2] @ p[:6] for p in psi[j]])              # (M, ny), D = 0
        members, _ = direct_enkf_n(psi[j], z, y[j], paper.R)
        np.testing.assert_allclose(a.psi[j], members, rtol=0, atol=1e-8 * (1 + np.abs(members).max()))


@pytest.mark.parametrize("N", [2, 5, 20, 300])
def test_enkf_n_zeta_finds_the_global_minimum_of_the_dual_cost(N):
    """Random spectra over 12 decades (some with two minima, some mu = 0): zeta_a is the lowest point
    of D on a fine grid (to rounding), and never above N / eps_N."""
    rng = np.random.default_rng(N)
    mu = rng.uniform(size=(2000, 3)) * 10.0 ** rng.uniform(-6, 6, size=(2000, 3))
    b2 = rng.uniform(size=(2000, 3)) * 10.0 ** rng.uniform(-6, 6, size=(2000, 3))
    mu[rng.uniform(size=mu.shape) < 0.1] = 0.0
    zeta = enkf_n_zeta(mu, b2, N)
    eps = 1 + 1 / N

    def D(z):
        return 0.5 * np.sum(z[..., None] * b2[:, None] / (z[..., None] + mu[:, None]), -1) + 0.5 * eps * z \
            - 0.5 * N * np.log(z)
    best = D(N / eps * np.logspace(-14, 0, 2000)[None, :] * np.ones((len(mu), 1))).min(1)
    assert np.all(D(zeta[:, None])[:, 0] <= best + 1e-12 * np.maximum(1, np.abs(best)))
    assert np.all(zeta <= N / eps * (1 + 1e-15))


def test_enkf_n_approaches_the_etkf_for_a_large_ensemble():
    """The prior's scale is then well determined: with the same innovation (of the forecast spread's
    size) at every M, lambda^2 - 1 = O(1/M) (here M (lambda^2 - 1) ~ 0.5 and ~ 0.005 on the two paths),
    and the analysis members differ from the ETKF's by O(1/M) relative to the forecast spread."""
    system, C, R, rng = linear_gaussian(11)
    L, e = rng.normal(size=(3, 3)), rng.normal(size=(2, 3))
    diff = {}
    for M in (50, 500, 5000):
        psi = rng.normal(size=(2, M, 3)) @ L.T
        y = (psi.mean(1) + e @ L.T) @ C.T
        n_ = EnKF(system, 0.0, R, variant="enkf_n").update(psi, np.zeros((2, 1)), y, None)
        e_ = EnKF(system, 0.0, R, variant="etkf").update(psi, np.zeros((2, 1)), y, None)
        assert np.all(np.abs(n_.inflation ** 2 - 1) < 2 / M), (M, n_.inflation)
        diff[M] = np.abs(n_.psi - e_.psi).max() / psi.std(1, ddof=1).max()
        assert diff[M] < 2 / M, (M, diff[M])
    assert diff[5000] < diff[50] / 20


def test_enkf_n_takes_no_inflation():
    with pytest.raises(ValueError, match=r"^inflation: 1.2 is not allowed with variant enkf_n, .*expected 1$"):
        EnKF(paper.model(), paper.Q, paper.R, variant="enkf_n", inflation=1.2)
    with pytest.raises(ValueError, match="^inflation: AdaptiveInflation.* is not allowed with variant enkf_n"):
        EnKF(paper.model(), paper.Q, paper.R, variant="enkf_n", inflation="adaptive")
    EnKF(paper.model(), paper.Q, paper.R, variant="enkf_n", inflation=1.0)       # 1: no inflation, allowed


def _whitened(rng, shape):
    """Standard normal draws (..., M, d) made exactly centred and white over the members (axis -2)."""
    e = rng.normal(size=shape)
    e -= e.mean(-2, keepdims=True)
    cov = e.swapaxes(-1, -2) @ e / (shape[-2] - 1)
    return e @ np.linalg.inv(np.linalg.cholesky(cov)).swapaxes(-1, -2)


@pytest.mark.parametrize("variant", ["etkf", "stochastic"])
def test_adaptive_inflation_converges_to_a_known_deflation(variant):
    """x_{k+1} = w_k (A = 0, p = 0), y = C x + v: the truth's process noise is Q, the filter assumes
    Q / c^2, and its members' noise is whitened, so every forecast ensemble has mean 0 and covariance
    exactly Q / c^2 and the correct covariance inflation is exactly c^2: E[Delta^o_k] = c^2 with
    var(Delta^o_k) = 2 tr(S^2) / tr(C Q C^T / c^2)^2, S = C Q C^T + R, independently over steps and
    paths. After K steps (the start's weight a^K is ~1e-9) the smoothed estimate rho_K^2 of each path has
    variance var(Delta^o) (1 - a) / (1 + a); their mean over P paths must lie within 4.5 standard
    errors of c^2, and so must the mean of rho_k^2 over the last K/2 steps and all paths
    (variance ~ var(Delta^o) / (P K/2)). The update into reused buffers (as `simulate` makes it) equals
    `update`'s into fresh arrays, each carrying its own rho_{k-1}."""
    rng = np.random.default_rng(1 if variant == "etkf" else 2)
    n, ny, M, P, K, c, a = 3, 2, 30, 200, 400, 1.5, 0.95
    C, L = rng.normal(size=(ny, n)), rng.normal(size=(n, n))
    Q, R = L @ L.T, 0.3 * np.eye(ny)
    system = rx.AffineRandomSystem(A=[np.zeros((n, n))], B=[np.zeros((n, 1))], C=[C])
    settings = AdaptiveInflation(smoothing=a, low=0.1, high=10.0)
    enkf = EnKF(system, Q / c ** 2, R, variant=variant, inflation=settings)
    u = np.zeros((P, 1))
    filtered, work = component_major((P, M, n)), component_major((P, M, n + ny + 1))
    psi = np.zeros((P, M, n))
    rho = np.empty((K, P))
    carried = explicit = None
    for k in range(K):
        psi = enkf.predict(psi, u, _whitened(rng, (P, M, n)))
        y = (rng.normal(size=(P, n)) @ np.linalg.cholesky(Q).T) @ C.T + rng.normal(size=(P, ny)) @ np.sqrt(R)
        e_v = rng.normal(size=(P, M, ny)) if variant == "stochastic" else None
        analysis = enkf._update(psi, u, y, e_v, None, out=filtered, work=work, inflation=carried)
        same = enkf.update(psi, u, y, e_v, inflation=explicit)
        np.testing.assert_array_equal(same.inflation, analysis.inflation)
        np.testing.assert_array_equal(same.psi, analysis.psi)
        explicit, carried, rho[k], psi = same.inflation, analysis.inflation, analysis.inflation, analysis.psi.copy()
    HQH = C @ Q @ C.T
    S = HQH + R
    var = 2 * np.trace(S @ S) / (np.trace(HQH) / c ** 2) ** 2
    final = rho[-1] ** 2
    assert abs(final.mean() - c ** 2) < 4.5 * np.sqrt(var * (1 - a) / (1 + a) / P), final.mean()
    assert abs(np.mean(rho[K // 2:] ** 2) - c ** 2) < 4.5 * np.sqrt(var / (P * K / 2)), np.mean(rho[K // 2:] ** 2)
    assert np.all((rho > 0.1) & (rho < 10))                          # the bounds never acted


def _adaptive_run(enkf, seed, steps, P, M, work=None, filtered=None):
    """A filtering loop of the adaptive EnKF on the paper's model as a generator: one (rho_k (P,), filtered
    ensemble (P, M, 9)) per step, rho_{k-1} held here (the caller's state, as in `simulate`); scratch and
    output buffers `work`, `filtered` (component-major) shared with whoever passes the same ones."""
    rng = np.random.default_rng(seed)
    width, ny = enkf.width, enkf.model.ny
    work = component_major((P, M, width + ny + 1)) if work is None else work
    filtered = component_major((P, M, width)) if filtered is None else filtered
    psi, u, rho = rng.normal(size=(P, M, width)), np.zeros((P, enkf.model.m)), None
    for _ in range(steps):
        y = 3 * rng.normal(size=(P, ny))                 # outputs far from the forecast: rho moves
        e_v = rng.normal(size=(P, M, ny)) if enkf.variant == "stochastic" else None
        a = enkf._update(psi, u, y, e_v, None, out=filtered, work=work, inflation=rho)
        rho, members = a.inflation, a.psi.copy()           # a.psi is `filtered`, which the other run reuses
        yield rho.copy(), members
        psi = enkf.predict(members, u, rng.normal(size=(P, M, width)))


@pytest.mark.parametrize("variant", ["etkf", "stochastic"])
def test_adaptive_inflation_is_the_callers_state(variant):
    """Two runs stepped in turn through one EnKF and the same scratch buffers each carry their own rho_{k-1}:
    every step of each equals that of the run alone, exactly, and the two runs' rho differ (so a state shared
    between them would show). The EnKF keeps nothing between updates."""
    enkf = EnKF(paper.model(), paper.Q, paper.R, variant=variant, inflation=AdaptiveInflation(0.8, 1.0, 3.0))
    steps, P, M = 12, 3, 8
    before = dict(vars(enkf))
    alone = [list(_adaptive_run(enkf, seed, steps, P, M)) for seed in (5, 6)]
    work, filtered = component_major((P, M, enkf.width + enkf.model.ny + 1)), component_major((P, M, enkf.width))
    shared = [_adaptive_run(enkf, seed, steps, P, M, work, filtered) for seed in (5, 6)]
    for k, (first, second) in enumerate(zip(*shared)):
        for run, (rho, psi) in enumerate((first, second)):
            np.testing.assert_array_equal(rho, alone[run][k][0], err_msg=f"run {run} step {k}")
            np.testing.assert_array_equal(psi, alone[run][k][1], err_msg=f"run {run} step {k}")
    rho_first, rho_second = (np.array([r for r, _ in run]) for run in alone)
    assert not np.allclose(rho_first, rho_second)
    assert np.ptp(rho_first) > 0.1                                  # rho moved from its start
    assert vars(enkf).keys() == before.keys() and all(vars(enkf)[key] is value for key, value in before.items())


def test_adaptive_inflation_scales_the_forecast_anomalies_and_keeps_the_bounds():
    """One update from rho_{k-1}: pred_std is the forecast spread times rho_k, rho_k within [low, high],
    and the etkf analysis of the inflated forecast equals that of an ensemble inflated beforehand."""
    rng = np.random.default_rng(3)
    psi, u, y = rng.normal(size=(4, 12, 9)), rng.normal(size=(4, 1)), 10 * rng.normal(size=(4, 3))
    enkf = EnKF(paper.model(), paper.Q, paper.R, variant="etkf", inflation=AdaptiveInflation(0.5, 1.0, 1.6))
    a = enkf.update(psi, u, y, None, inflation=np.array([1.0, 1.2, 1.6, 1.4]))
    assert np.all((a.inflation >= 1) & (a.inflation <= 1.6))
    np.testing.assert_allclose(a.pred_std, psi.std(1, ddof=1) * a.inflation[:, None], rtol=1e-12)
    mean = psi.mean(1, keepdims=True)
    inflated = mean + a.inflation[:, None, None] * (psi - mean)
    plain = EnKF(paper.model(), paper.Q, paper.R, variant="etkf").update(inflated, u, y, None)
    np.testing.assert_allclose(a.psi, plain.psi, rtol=0, atol=1e-12)


@pytest.mark.parametrize("kw", [{"variant": "enkf_n"}, {"variant": "etkf", "inflation": "adaptive"},
                                {"variant": "stochastic", "inflation": "adaptive"}], ids=["enkf_n", "etkf", "stoch"])
def test_enkf_n_and_adaptive_loops_are_per_path(kw):
    """3 paths alone equal the first 3 of 5 with another block size, and a second run of the same
    loop repeats the first (the adaptive estimate starts afresh with every run); the spread differs
    from the same loop's without the inflation (etkf for enkf_n)."""
    def run(paths, block):
        return simulate(paper.plant(), EnKF(paper.model(), paper.Q, paper.R, **kw), F=paper.F_proposed,
                        d=paper.disturbance(30), q0=paper.q0, psi0=paper.psi0, ensemble_size=10, paths=paths,
                        seed=4, block=block)
    a, b, again = run(5, 16), run(3, 7), run(5, 16)
    for name in ARRAYS:
        x = getattr(a, name)
        np.testing.assert_array_equal(x[..., :3, :] if x.ndim > 1 else x[:3], getattr(b, name), err_msg=name)
        np.testing.assert_array_equal(x, getattr(again, name), err_msg=name)
    base = EnKF(paper.model(), paper.Q, paper.R, variant="etkf" if kw["variant"] == "enkf_n" else kw["variant"])
    plain = simulate(paper.plant(), base, F=paper.F_proposed, d=paper.disturbance(30), q0=paper.q0, psi0=paper.psi0,
                     ensemble_size=10, paths=3, seed=4)
    assert not np.allclose(plain.psi_pred_std[5:], b.psi_pred_std[5:])     # the inflation acted


def _build(overrides):
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        return build(compose("config", overrides=overrides))


def test_config_builds_enkf_n_and_adaptive_inflation():
    assert _build(["enkf.variant=enkf_n"]).filter.enkf.variant == "enkf_n"
    enkf = _build(["enkf=etkf", "enkf.inflation=adaptive", "enkf.adaptive.smoothing=0.9",
                   "enkf.adaptive.high=3"]).filter.enkf
    assert enkf.inflation == AdaptiveInflation(smoothing=0.9, low=1.0, high=3.0)


BAD = [
    ("enkf.inflation=fast", "enkf.inflation: 'fast' is not allowed, expected a finite number >= 1 or adaptive"),
    ("enkf.inflation=0.9", "enkf.inflation: 0.9 is not allowed, expected a finite number >= 1 or adaptive"),
    ("enkf.variant=enkf_n enkf.inflation=1.1",
     "enkf.inflation: 1.1 is not allowed with enkf.variant=enkf_n, which estimates the inflation itself"),
    ("enkf.variant=enkf_n enkf.inflation=adaptive",
     "enkf.inflation: 'adaptive' is not allowed with enkf.variant=enkf_n"),
    ("enkf.inflation=adaptive enkf.adaptive.smoothing=1.5",
     "enkf.adaptive.smoothing: 1.5 is not allowed, expected a finite number >= 0 and <= 1"),
    ("enkf.inflation=adaptive enkf.adaptive.high=0.5", "enkf.adaptive.high: 0.5 is not allowed, expected a finite "
                                                       "number >= 1.0"),
    ("enkf.variant=enkf_n enkf.R=0", "enkf.R: must be positive definite with enkf.variant=enkf_n"),
]


@pytest.mark.parametrize("overrides, message", BAD, ids=[b[0] for b in BAD])
def test_bad_enkf_n_and_adaptive_settings_are_one_line_config_errors(overrides, message):
    with pytest.raises(ConfigError) as err:
        _build(overrides.split())
    assert str(err.value).startswith(message), str(err.value)
    assert "\n" not in str(err.value)
