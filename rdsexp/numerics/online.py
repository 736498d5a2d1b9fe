"""The online, learning-type controller the paper's Conclusions point to.

During feedback control the EnKF keeps estimating xi (eq. psi-x-xi-i), so each path's controller
can model the distribution of xi from its own filtered estimates xi_{k|k} and re-design its gain:

    u_k = F_k x_{k|k-1}                      eq. (sf-enkf) with a gain that changes over time
    at k = warmup + j * period (j >= 1):     moments of xi from xi_{k'|k'}, warmup < k' <= k
                                             (the last `window` of them, all, or weighted by
                                             forgetting^(k - k')), eq. (sample-mean) per path
                                             F_new = design(model, moments) by `method`
                                             adopted from k+1 on if the evidence carries it

The evidence (`resamples` > 0, the default): a candidate is adopted only if its exact rate is below 1 and
below the gain in use's on the window's moments, and also at its worst over B moving-block bootstrap draws of
the window (`modeling.block_bootstrap_steps`; blocks of `block` estimates, which are correlated in k):
max_b lam_b(F_new) < 1 and max_b lam_b(F_new) < max_b lam_b(F_k), else `not_robust`. A window of fewer than
`min_blocks` blocks has too few distinct resamples to measure its uncertainty: a candidate that passes
`waits` there, unless the gain in use is unstable at every draw and at the prior guess (`at_guess`), two
independent sources agreeing that waiting lets the path grow. A candidate not certified below 1 is never
adopted: the model of a growing loop is biased. A component whose law its mean fixes (`EnKF.two_point`) is
modeled with that law's variance (`two_point_moments`), which the shrunk estimates understate. The probe
(`probe` > 0, off by default) adds a known white excitation probe * s_k, s_k in {-1, 1}^m, until
`probe_until`, which keeps the state and the outputs moving under feedback. docs/online.md states each rule
with the measurements behind it, docs/online-rounds.md how the defaults were found.

No identification run. `OnlineController` is what `simulation.simulate(controller=...)` calls after
filtering; every decision (adopted or not, and why) is kept in `decisions()`. The default method, policy
iteration, is run batched over paths (stacked eigenproblems, warm-started from the gain in use); any other
method of `synthesis.METHODS` is called path by path.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import one_line
from .analysis import DENSE_MAX_N, perron
from .enkf import sqrtm_psd
from .modeling import COVARIANCES, block_bootstrap_steps
from .synthesis import METHODS, check_options, synthesize
from .synthesis.riccati import greedy_gain
from .systems import AffineRandomSystem, MomentModel

MEMORIES = ("window", "all", "exponential")
OBSERVERS = ("random_walk", "model")
STARTS = ("random_walk", "static_mean")
REASONS = ("adopted", "adopted_unchecked", "not_stabilizing", "no_improvement", "not_robust", "waiting", "failed")


@dataclass(frozen=True)
class OnlineSettings:
    """When and how the online controller re-designs (see the module docstring).

    warmup: estimates xi_{k|k} with k <= warmup are not used (the EnKF has not converged yet);
    period: steps between re-designs; memory: "window" (the last `window` estimates), "all"
    (every estimate since warm-up) or "exponential" (all, weighted forgetting^(k - k'));
    method / options: a `synthesis.METHODS` design; safeguard: adopt only certified improvements;
    resamples: 0 (the window's model only) or B moving-block bootstrap resamples of the window (blocks
    of `block` consecutive estimates: xi_{k|k} are correlated in k), over which the candidate's worst
    rate must be < 1 and below the worst rate of the gain in use (else `not_robust`); min_blocks: below
    this many blocks in the window a passing candidate waits (`waiting`); covariance: "sample" (eq.
    sample-mean of the estimates) or "total" (plus their mean filtered covariance); observer: "random_walk"
    (the loop's EnKF keeps its own model of xi) or "model" (from a path's first re-design on, its EnKF draws
    xi i.i.d. from the path's latest modeled moments, adopted or not, as the offline loop's observer draws
    from the identified ones: `observer_prior`; `start` before); start: with observer "model", the loop's
    EnKF before a path's first model: "random_walk" or "static_mean" (xi drawn about a mean the EnKF learns,
    `EnKF.static_mean`); start_spread: with static_mean, the draws about that mean are mu + start_spread w_xi
    (`EnKF.start_spread`); mean_spread: that mean starts at guess + mean_spread w_xi (`EnKF.mean_spread`);
    lag: the smoothing lag of the loop's EnKF (`EnKF.lag`); all set where that EnKF is built. The estimates
    modeled at k are then xi_{k-1-lag} given y up to k. probe: the amplitude of the known excitation added to u_k
    on every input (0: off), for k < probe_until (None: to the end).
    """

    warmup: int = 20
    period: int = 10
    memory: str = "window"
    window: int = 30
    forgetting: float = 0.95
    method: str = "policy_iteration"
    options: dict = field(default_factory=dict)
    safeguard: bool = True
    resamples: int = 50
    block: int = 5
    min_blocks: int = 4
    covariance: str = "sample"
    observer: str = "random_walk"
    start: str = "random_walk"
    start_spread: float = 1.0
    mean_spread: float = 1.0
    lag: int = 0
    probe: float = 0.0
    probe_until: int | None = None

    def check(self, system: AffineRandomSystem, horizon: int | None = None) -> OnlineSettings:
        """One-line ValueError naming the setting; returns self."""
        for name, low in (("warmup", 0), ("period", 1), ("window", 2), ("resamples", 0), ("block", 1),
                          ("min_blocks", 1), ("lag", 0)):
            value = getattr(self, name)
            if not (isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= low):
                raise ValueError(f"{name}: {value!r} is not allowed, expected an integer >= {low}")
        if self.memory not in MEMORIES:
            raise ValueError(f"memory: {self.memory!r} is not allowed, expected one of {', '.join(MEMORIES)}")
        if not (isinstance(self.forgetting, (int, float)) and 0 < self.forgetting < 1):
            raise ValueError(f"forgetting: {self.forgetting!r} is not allowed, expected a number in (0, 1)")
        if horizon is not None and self.memory == "window" and self.window > horizon:
            raise ValueError(f"window: {self.window} is not allowed, longer than the horizon {horizon}")
        if self.observer not in OBSERVERS:
            raise ValueError(f"observer: {self.observer!r} is not allowed, expected one of {', '.join(OBSERVERS)}")
        if self.start not in STARTS:
            raise ValueError(f"start: {self.start!r} is not allowed, expected one of {', '.join(STARTS)}")
        for name in ("start_spread", "mean_spread"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value)
                    and value > 0):
                raise ValueError(f"{name}: {value!r} is not allowed, expected a finite number > 0")
        if not (isinstance(self.probe, (int, float)) and not isinstance(self.probe, bool) and np.isfinite(self.probe)
                and self.probe >= 0):
            raise ValueError(f"probe: {self.probe!r} is not allowed, expected a finite number >= 0")
        until = self.probe_until
        if not (until is None or isinstance(until, (int, np.integer)) and not isinstance(until, bool) and until >= 0):
            raise ValueError(f"probe_until: {until!r} is not allowed, expected None or a step >= 0")
        if not isinstance(self.safeguard, bool):
            raise ValueError(f"safeguard: {self.safeguard!r} is not allowed, expected true or false")
        if self.covariance not in COVARIANCES:
            raise ValueError(f"covariance: {self.covariance!r} is not allowed, expected one of "
                             f"{', '.join(COVARIANCES)}")
        check_options(self.method, dict(self.options), system)       # unknown method / option
        return self

    def updates(self, horizon: int) -> np.ndarray:
        """The steps k < horizon after whose filtering a re-design happens."""
        return np.arange(self.warmup + self.period, horizon, self.period)

    def probe_signs(self, k: int, m: int) -> np.ndarray:
        """(m,) signs +-1 of the probe at step k, from a generator seeded by [7, k]: the same on every path and
        in every chunk, so the controller stays deterministic."""
        return np.where(np.random.default_rng([7, k]).random(m) < 0.5, -1.0, 1.0)


# ------------------------------------------------------------------ batched moments and rates
def weighted_moments(xi: np.ndarray, w: np.ndarray, xi_cov: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-path weighted mean (..., P, p) and covariance (..., P, p, p) of samples xi (..., N, P, p),
    weights w (..., N) (leading axes: batches, e.g. bootstrap resamples).

    With equal weights this is eq. (sample-mean), the 1/N covariance of `MomentModel.from_samples`;
    with xi_cov (..., N, P, p, p), the EnKF's filtered covariances of the samples, their weighted mean
    is added (the law of total variance, `modeling.model_distribution`). The sums run over the samples
    in order, one elementwise step each, so a path's moments are the same bits whatever other paths share
    its batch (a chunk of one path, or of many); a reduction's order would follow the arrays' layout."""
    w = w / w.sum(axis=-1, keepdims=True)
    samples = range(xi.shape[-3])
    mean = np.zeros(xi.shape[:-3] + xi.shape[-2:])
    for t in samples:
        mean += w[..., t, None, None] * xi[..., t, :, :]
    cov = np.zeros(mean.shape + mean.shape[-1:])
    for t in samples:
        dev = xi[..., t, :, :] - mean
        cov += w[..., t, None, None, None] * dev[..., :, None] * dev[..., None, :]
    if xi_cov is not None:
        for t in samples:
            cov += w[..., t, None, None, None] * xi_cov[..., t, :, :, :]
    return mean, cov


def two_point_moments(mean: np.ndarray, cov: np.ndarray, two_point, estimates=None) -> tuple[np.ndarray, np.ndarray]:
    """mean (..., p) and cov (..., p, p) with the variance of each two-point component the one its mean fixes.

    two_point: None (returned as they are) or (which (p,) bool, low (p,), high (p,)), `EnKF.two_point`. A
    component on {low, high} with mean mu has variance (mu - low) (high - mu), mu clipped into [low, high];
    its correlations with the other components are kept (its row and column rescaled), so cov stays PSD.
    The window's sample variance of xi_{k|k} understates it (each estimate is shrunk toward the filter's prior),
    and so does a design on it (docs/online.md, "And modeled as a dropout").

    estimates: None, or the number N of estimates the moments come from (a scalar, or an array broadcasting
    against mean.shape[:-1]): the mean of such a component is then kept (high - low) / (2 (N + 1)) inside its
    ends, the add-half estimate of N equal outcomes. N estimates cannot tell a probability below that from 0,
    and a model at an end is deterministic there: its design can lean on an input that the end switches off
    (gain entries of 1e16 where the input matrix has a rounding-level entry), and the EnKF that draws from it
    never draws the other end again (docs/online.md, "Never at an end")."""
    if two_point is None:
        return mean, cov
    which, low, high = two_point
    var = np.diagonal(cov, axis1=-2, axis2=-1)
    if estimates is None:
        mu = np.clip(mean, low, high)
    else:
        margin = np.where(which, high - low, 0.0) / (2.0 * (np.asarray(estimates, dtype=float)[..., None] + 1.0))
        mu = np.clip(mean, low + margin, high - margin)
        mean = np.where(which, mu, mean)
    fixed = np.where(which, (mu - low) * (high - mu), var)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(which, np.where(var > 0, np.sqrt(fixed / var), 0.0), 1.0)
    cov = cov * scale[..., :, None] * scale[..., None, :]
    diagonal = np.arange(cov.shape[-1])
    cov[..., diagonal, diagonal] = fixed
    return mean, cov


def moment_factors(system: AffineRandomSystem, mean: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Abar (P, p+1, n, n), Bbar (P, p+1, n, m)) with sum_r Abar_r (x) Abar_r = E[A(xi) (x) A(xi)] etc.

    The batched `AffineRandomSystem.moment_factors`: rows diag(sqrt(w)) V^T of W = E[[1; xi][1; xi]^T]
    per path, with every row kept (a zero eigenvalue gives a zero row, which adds nothing)."""
    P, p = mean.shape
    W = np.empty((P, p + 1, p + 1))
    W[:, 0, 0], W[:, 0, 1:], W[:, 1:, 0] = 1.0, mean, mean
    W[:, 1:, 1:] = cov + mean[:, :, None] * mean[:, None, :]
    G = np.full_like(W, np.nan)                    # paths whose moments overflowed stay NaN (a status later)
    ok = np.all(np.isfinite(W), axis=(1, 2))
    w, V = np.linalg.eigh(W[ok])
    G[ok] = np.sqrt(np.clip(w, 0.0, None))[:, :, None] * V.transpose(0, 2, 1)   # (P, p+1, p+1)
    return np.einsum("jri,inl->jrnl", G, system.A), np.einsum("jri,inl->jrnl", G, system.B)


def symmetric_part(L: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The operators L (U, n^2, n^2) on row-major vec(X), restricted to symmetric X: (U, d, d), d = n(n+1)/2,
    in the coordinates X_ij, i <= j, and the (d, n^2) map back to vec(X).

    For T(X) = sum_r Acl_r X Acl_r^T (and its adjoint), Sym is invariant and holds the PSD Perron
    eigenvector, so the restriction has the same spectral radius; its eigenproblem is (d / n^2)^3 ~ 1/5
    of the cost for n >= 4."""
    i, j = np.triu_indices(n)
    rows, cols_ij, cols_ji = i * n + j, i * n + j, j * n + i
    Lr = L[:, rows]
    out = Lr[:, :, cols_ij] + np.where(i != j, 1.0, 0.0) * Lr[:, :, cols_ji]
    back = np.zeros((i.size, n * n))
    back[np.arange(i.size), cols_ij] = 1.0
    back[np.arange(i.size), cols_ji] = 1.0
    return out, back


def rates(Abar: np.ndarray, Bbar: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Exact mean-square rates sqrt(rho(sum_r Acl_r (x) Acl_r)) of per-path gains F (P, m, n).

    Abar (P, r, n, n) / Bbar (P, r, n, m), or one (r, n, n) / (r, n, m) for every path. Dense stacked
    eigenvalues up to n = DENSE_MAX_N (what `analysis.ms_rate` computes, batched), `perron` beyond."""
    F = np.asarray(F, dtype=float)
    Acl = Abar + Bbar @ F[:, None] if Abar.ndim == 4 else Abar[None] + Bbar[None] @ F[:, None]
    P, _, n, _ = Acl.shape
    out = np.full(P, np.inf)
    ok = np.all(np.isfinite(Acl), axis=(1, 2, 3))
    if n <= DENSE_MAX_N:
        L = np.einsum("jrab,jrcd->jacbd", Acl[ok], Acl[ok]).reshape(-1, n * n, n * n)
        out[ok] = np.sqrt(np.abs(np.linalg.eigvals(symmetric_part(L, n)[0])).max(axis=1)) if len(L) else []
    else:
        out[ok] = [np.sqrt(perron(a)[0]) for a in Acl[ok]]
    return out


def _perron_symmetric(S: np.ndarray, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Largest real eigenvalue (U,) and an eigenvector (U, d) of each S (U, d, d).

    The eigenvalues alone, then two steps of inverse iteration from `start` (vec(I), which is not
    orthogonal to the PSD Perron eigenvector), cheaper than all eigenvectors of the stack. Where
    the shifted system is singular to working precision (e.g. rho = 0), all eigenvectors instead."""
    rho = np.linalg.eigvals(S).real.max(axis=1)
    scale = np.abs(S).max(axis=(1, 2))
    shifted = S - (rho + 1e-9 * np.maximum(np.abs(rho), scale) + 1e-300)[:, None, None] * np.eye(S.shape[1])
    v = np.broadcast_to(start, (S.shape[0], S.shape[1]))
    try:
        for _ in range(2):
            v = np.linalg.solve(shifted, v[..., None])[..., 0]
            v = v / np.abs(v).max(axis=1, keepdims=True)
        if np.all(np.isfinite(v)):
            return rho, v
    except np.linalg.LinAlgError:
        pass
    w, V = np.linalg.eig(S)
    i = np.argmax(w.real, axis=1)
    return w.real[np.arange(len(S)), i], V[np.arange(len(S)), :, i].real


def policy_iteration_batch(Abar: np.ndarray, Bbar: np.ndarray, F0: np.ndarray, *, max_iter: int = 200,
                           tol: float = 1e-13) -> np.ndarray:
    """`synthesis.riccati.policy_iteration` for P models at once: gains (P, m, n) from F0 (P, m, n).

    Per path: P_j = Perron eigenvector of X -> sum_r Acl_r^T X Acl_r, then F = `greedy_gain` of P_j; a path
    stops when its rate no longer decreases by tol (relative). As the single-path one, it returns each
    path's gain with the smallest rate seen, never worse than F0: with a singular P_j the step can raise
    the rate (a random plant whose B is certain: 0.93 at the optimum, 2.2 one step later)."""
    F = np.array(F0, dtype=float)
    best = F.copy()
    Pn, _, n, m = Bbar.shape
    lam = np.full(Pn, np.inf)
    active = np.ones(Pn, dtype=bool)
    for it in range(max_iter):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        Acl = Abar[idx] + Bbar[idx] @ F[idx, None]
        L = np.einsum("jrab,jrcd->jbdac", Acl, Acl).reshape(-1, n * n, n * n)   # vec(Acl^T X Acl), row-major
        # Perron root from the eigenvalues only, its eigenvector by two steps of inverse iteration
        # from vec(I) (which is not orthogonal to it), cheaper than eigenvectors of the whole stack,
        # on symmetric X only (`symmetric_part`)
        S, back = symmetric_part(L, n)
        rho, v = _perron_symmetric(S, np.eye(n)[np.triu_indices(n)])
        new = np.sqrt(np.clip(rho, 0.0, None))
        X = (v @ back).reshape(-1, n, n)
        X = (X + X.transpose(0, 2, 1)) / 2
        X *= (np.sign(np.trace(X, axis1=1, axis2=2)) / np.abs(X).max(axis=(1, 2)))[:, None, None]
        better = new < lam[idx]
        best[idx[better]] = F[idx[better]]
        done = (lam[idx] - new <= tol * np.maximum(new, 1e-300)) & (it > 0)
        lam[idx] = np.minimum(lam[idx], new)
        active[idx[done]] = False
        go = ~done
        if not go.any():
            break
        F[idx[go]] = greedy_gain(Abar[idx[go]], Bbar[idx[go]], X[go])
    return best


# ------------------------------------------------------------------------------ the controller
@dataclass
class Decisions:
    """Every re-design, one row per (update step, path): arrays over U rows.

    k: the step after whose filtering it happened (the gain acts from k+1); mean (U, p), cov (U, p, p):
    the modeled moments; F (U, m, n): the designed gain (NaN if none); rate_model: its exact rate on
    the modeled moments; rate_current: the exact rate of the gain in use on the same moments;
    rate_worst / rate_current_worst: their maxima over the bootstrap resamples, rate_current_best the
    minimum of the gain in use's (NaN without resamples); rate_current_guess: the gain in use's rate on the
    system at the prior guess (NaN without one); estimates: how many xi_{k|k} the window holds; adopted and
    reason (REASONS; "failed: ..." with the method's error)."""

    k: np.ndarray
    path: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    F: np.ndarray
    rate_model: np.ndarray
    rate_current: np.ndarray
    rate_worst: np.ndarray
    rate_current_worst: np.ndarray
    rate_current_best: np.ndarray
    rate_current_guess: np.ndarray
    estimates: np.ndarray
    adopted: np.ndarray
    reason: np.ndarray


class OnlineController:
    """Per-path online re-design (the module docstring); pass it to `simulate(controller=...)`.

    system: the model the EnKF and the designs use (n, m, its xi of dimension p); F0: (m, n) or
    (P, m, n) initial gains; horizon: K, the last step; at_guess: None, or the system at the prior guess
    (A (n, n), B (n, m)), on which a gain in use that every resample of a thin window calls unstable must
    be unstable too for that window to act (module docstring); two_point: None or `EnKF.two_point`, the
    components modeled with the variance their mean fixes (`two_point_moments`). Deterministic (draws no
    random numbers).
    """

    def __init__(self, system: AffineRandomSystem, settings: OnlineSettings, F0, *, paths: int, horizon: int,
                 at_guess: tuple[np.ndarray, np.ndarray] | None = None, two_point=None):
        self.system, self.settings = system, settings.check(system, horizon)
        n, m = system.n, system.m
        # (1, n, n), (1, n, m): one term of `rates`' sum, the deterministic system at the guess
        self.at_guess = None if at_guess is None else (np.reshape(np.asarray(at_guess[0], float), (1, n, n)),
                                                       np.reshape(np.asarray(at_guess[1], float), (1, n, m)))
        self.two_point = None if two_point is None else tuple(np.asarray(a).reshape(system.p) for a in two_point)
        self.P, self.K = int(paths), int(horizon)
        self.F = np.broadcast_to(np.asarray(F0, dtype=float), (self.P, m, n)).copy()   # gains in use
        self.F0 = self.F.copy()
        self.xi = np.full((self.K + 1, self.P, system.p), np.nan)                  # xi_{k|k}, k = 0..K
        # their filtered covariances, with covariance = "total" (simulate passes them when asked)
        self.needs_xi_cov = settings.covariance == "total"
        self.xi_cov = np.full((self.K + 1, self.P, system.p, system.p), np.nan) if self.needs_xi_cov else None
        self._rows: list[dict] = []
        self._updates = set(settings.updates(self.K).tolist())
        # with observer = "model": per path, the moments of its latest model, for the EnKF's prediction
        self._prior = (np.zeros((self.P, system.p)), np.zeros((self.P, system.p, system.p)), np.zeros(self.P, bool))

    def excitation(self, k: int) -> np.ndarray | None:
        """The probe added to u_k on every path, (m,), or None (`OnlineSettings.probe`)."""
        s = self.settings
        if s.probe == 0 or (s.probe_until is not None and k >= s.probe_until):
            return None
        return s.probe * s.probe_signs(k, self.system.m)

    def observer_prior(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """What `simulate` passes to the EnKF's prediction (`EnKF._predict(path_prior=...)`): per path the mean
        (P, p) and covariance square root (P, p, p) of its latest model, and whether it has one (P,); None with
        observer = "random_walk" or before any path's first re-design."""
        return self._prior if self.settings.observer == "model" and self._prior[2].any() else None

    def weights(self, k: int) -> tuple[int, np.ndarray]:
        """(first step, weights (k - first + 1,)) of the estimates the model at step k uses."""
        s = self.settings
        first = s.warmup + 1
        if s.memory == "window":
            first = max(first, k - s.window + 1)
        t = np.arange(first, k + 1)
        w = s.forgetting ** (k - t) if s.memory == "exponential" else np.ones(t.size)
        return first, w

    def update(self, k: int, psi_filt_mean: np.ndarray, alive: np.ndarray, xi_filt_cov: np.ndarray | None = None):
        """Store xi_{k|k} (P, n+p -> the last p) and, with covariance = "total", its filtered covariance
        (P, p, p); at a re-design step return (paths, new gains)."""
        self.xi[k] = psi_filt_mean[:, self.system.n:]
        if self.needs_xi_cov:
            self.xi_cov[k] = xi_filt_cov
        if k not in self._updates:
            return None
        first, w = self.weights(k)
        samples = self.xi[first:k + 1]
        covs = self.xi_cov[first:k + 1] if self.needs_xi_cov else None
        idx = np.flatnonzero(alive & np.all(np.isfinite(samples), axis=(0, 2)))
        if idx.size == 0:
            return None
        with np.errstate(all="ignore"):
            mean, cov = self._moments(samples[:, idx], w, None if covs is None else covs[:, idx])
            Abar, Bbar = moment_factors(self.system, mean, cov)
        F_new, failed = self._design(idx, mean, cov, Abar, Bbar)
        with np.errstate(all="ignore"):
            rate_new = rates(Abar, Bbar, np.nan_to_num(F_new))
            rate_new[failed != ""] = np.nan
            rate_cur = rates(Abar, Bbar, self.F[idx])
            guess_cur = np.full(idx.size, np.nan) if self.at_guess is None else rates(*self.at_guess, self.F[idx])
        worst_new = worst_cur = best_cur = np.full(idx.size, np.nan)
        s = self.settings
        if s.safeguard and s.resamples:
            worst_new, worst_cur, best_cur = self._draw_rates(
                k, samples[:, idx], w, None if covs is None else covs[:, idx], np.nan_to_num(F_new), self.F[idx])
            worst_new[failed != ""] = np.nan
        if s.safeguard:
            # every candidate must be certified: exact rate < 1 and below the gain in use's on the window's model
            # and at the worst bootstrap draw (the model of a loop that grows is biased: a candidate the model
            # does not call stabilizing can be worse on the plant than the gain in use, and is never adopted)
            model_ok = (failed == "") & (rate_new < 1) & (rate_new < rate_cur)
            robust = model_ok & (worst_new < 1) & (worst_new < worst_cur) if s.resamples else model_ok
            # with fewer than min_blocks blocks the draws' spread says too little to act on, unless they all
            # call the gain in use unstable and so does the prior guess (the draws alone misfire: docstring)
            enough = samples.shape[0] >= s.min_blocks * s.block or not s.resamples
            adopt = robust & (enough | (best_cur >= 1) & (guess_cur >= 1))
            reason = np.where(failed != "", failed, np.where(
                adopt, "adopted", np.where(~(rate_new < 1), "not_stabilizing", np.where(
                    ~model_ok, "no_improvement", np.where(robust, "waiting", "not_robust")))))
        else:
            adopt = failed == ""
            reason = np.where(adopt, "adopted_unchecked", failed)
        self._rows.append(dict(k=np.full(idx.size, k), path=idx, mean=mean, cov=cov, F=F_new, rate_model=rate_new,
                               rate_current=rate_cur, rate_worst=worst_new, rate_current_worst=worst_cur,
                               rate_current_best=best_cur, rate_current_guess=guess_cur,
                               estimates=np.full(idx.size, samples.shape[0]),
                               adopted=adopt, reason=reason.astype(object)))
        if self.settings.observer == "model":
            # the path's latest model, its gain adopted or not: a random walk left running in a loop whose state
            # decays drifts (y carries less and less of xi) until the filter diverges, whatever the gain
            modeled = np.all(np.isfinite(mean), axis=1) & np.all(np.isfinite(cov), axis=(1, 2))
            self._prior[0][idx[modeled]] = mean[modeled]
            self._prior[1][idx[modeled]] = sqrtm_psd(cov[modeled])
            self._prior[2][idx[modeled]] = True
        if not adopt.any():
            return None
        self.F[idx[adopt]] = F_new[adopt]
        return idx[adopt], F_new[adopt]

    def resample_steps(self, k: int, T: int) -> np.ndarray:
        """(B, T) moving-block bootstrap indices into a window of T estimates (`modeling.block_bootstrap_steps`),
        from a generator seeded by (k, T), the same for every path, so the controller stays deterministic."""
        return block_bootstrap_steps(T, self.settings.resamples, self.settings.block, [k, T])

    def _moments(self, samples: np.ndarray, w: np.ndarray, covs: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The modeled moments, mean (..., U, p) and cov (..., U, p, p), of samples (..., T, U, p) with weights
        w (..., T) and filtered covariances covs or None (`weighted_moments`, `two_point_moments` with the
        window's effective number of estimates, (sum w)^2 / sum w^2: T with equal weights)."""
        n_eff = w.sum(axis=-1) ** 2 / (w ** 2).sum(axis=-1)
        return two_point_moments(*weighted_moments(samples, w, covs), self.two_point, np.asarray(n_eff)[..., None])

    def _draw_rates(self, k: int, samples: np.ndarray, w: np.ndarray, covs: np.ndarray | None, F_new: np.ndarray,
                    F_cur: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The largest exact rates of F_new and F_cur (U, m, n) and the smallest of F_cur over B moving-block
        bootstrap resamples of the window samples (T, U, p) with weights w (T,) and filtered covariances covs
        (T, U, p, p) or None (`resample_steps`): (U,) each."""
        steps = self.resample_steps(k, samples.shape[0])
        with np.errstate(all="ignore"):
            mean, cov = self._moments(samples[steps], w[steps], None if covs is None else covs[steps])
            B, U, p = mean.shape
            Abar, Bbar = moment_factors(self.system, mean.reshape(B * U, p), cov.reshape(B * U, p, p))
            new, cur = (rates(Abar, Bbar, np.tile(F, (B, 1, 1))).reshape(B, U) for F in (F_new, F_cur))
        return new.max(axis=0), cur.max(axis=0), cur.min(axis=0)

    def _design(self, idx, mean, cov, Abar, Bbar) -> tuple[np.ndarray, np.ndarray]:
        """Gains (U, m, n) for the paths idx and a failure text per path ("" if designed)."""
        s, m, n = self.settings, self.system.m, self.system.n
        failed = np.full(idx.size, "", dtype=object)
        finite = np.all(np.isfinite(Abar), axis=(1, 2, 3)) & np.all(np.isfinite(Bbar), axis=(1, 2, 3))
        failed[~finite] = "failed: the modeled moments are not finite"
        F = np.full((idx.size, m, n), np.nan)
        batched = s.method == "policy_iteration" and set(s.options) <= {"max_iter", "tol"}
        if batched and finite.any():
            try:
                with np.errstate(all="ignore"):
                    F[finite] = policy_iteration_batch(Abar[finite], Bbar[finite], self.F[idx[finite]], **s.options)
            except (np.linalg.LinAlgError, ValueError):     # e.g. an eigensolver that did not converge:
                batched = False                              # path by path below, failures as statuses
        if not batched:
            for u in np.flatnonzero(finite):
                try:
                    with np.errstate(all="ignore"):
                        res = synthesize(self.system, MomentModel(mean=mean[u], cov=cov[u]), s.method, **s.options)
                    if res.F is None:
                        failed[u] = f"failed: {res.status}"
                    else:
                        F[u] = res.F
                except Exception as err:       # noqa: BLE001 -- one path's failed design is its status
                    failed[u] = f"failed: {one_line(err)}"
        bad = (failed == "") & ~np.all(np.isfinite(F), axis=(1, 2))
        failed[bad] = "failed: the gain is not finite"
        return F, failed

    def decisions(self) -> Decisions:
        """Every decision so far, in order of (k, path)."""
        p, m, n = self.system.p, self.system.m, self.system.n
        if not self._rows:
            empty = {"mean": (0, p), "cov": (0, p, p), "F": (0, m, n)}
            return Decisions(k=np.zeros(0, int), path=np.zeros(0, int), **{a: np.zeros(s) for a, s in empty.items()},
                             rate_model=np.zeros(0), rate_current=np.zeros(0), rate_worst=np.zeros(0),
                             rate_current_worst=np.zeros(0), rate_current_best=np.zeros(0),
                             rate_current_guess=np.zeros(0),
                             estimates=np.zeros(0, int), adopted=np.zeros(0, bool),
                             reason=np.zeros(0, object))
        return Decisions(**{name: np.concatenate([r[name] for r in self._rows]) for name in self._rows[0]})

    def gain_history(self) -> list[np.ndarray]:
        """Per path j: its gains in order of adoption, (1 + adoptions, m, n); row i is the gain in use
        where `Trajectories.gain_index` is i."""
        d = self.decisions()
        return [np.concatenate([self.F0[j][None], d.F[(d.path == j) & d.adopted]]) for j in range(self.P)]


__all__ = ["Decisions", "MEMORIES", "METHODS", "OBSERVERS", "OnlineController", "OnlineSettings", "STARTS",
           "moment_factors", "policy_iteration_batch", "rates", "two_point_moments", "weighted_moments"]
