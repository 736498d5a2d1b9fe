"""The moments of xi by simulation: a synthetic likelihood with the paper's estimator as summary.

The paper's estimator (eq. sample-mean: the moments of xi_{k|k} over the window) is biased: the EnKF's
filtered means are shrunk toward its random walk, and its covariance mixes the spread of xi with the
filter's own. Its bias depends on the plant, the input, the window and the noise, so no fixed correction
removes it. But rdsexp can run the same identification on the model at any law of xi. So:

1. the summary s of the identification run (`s_obs`): the paper estimator's mean (p) and std (p), and any
   other statistic the caller computes the same way on every run (rdsexp adds the outputs' and the
   innovations' log mean squares and the outputs' lag-1 and cross correlations);
2. theta = (mean of xi (p), std of every component that is not two-point, the partial correlations of each pair
   (`correlation_root`)) drawn uniformly from a box around the paper estimator's moments (`prior_box`), one law per
   replicate path (`path_laws`, `distributions.PathLaws`) of those moments, its shape at random (`random_shapes`:
   theta does not state it, so what the summary reads of it belongs in the regression's residual, not its mean);
3. the same identification (input, feedback, EnKF, window) of the model on each replicate, batched over
   paths: its summary s_r;
4. a regression of s on theta over the replicates (`emulator`: the summary's expectation at any law in the box,
   and the covariance of its residual), and the posterior of theta given s_obs under the box prior with that
   Gaussian likelihood of s given theta (`synthetic_posterior`: Wood 2010), drawn by importance sampling.

The likelihood models the summary given the law, so the posterior's mass sits where the law's expected summary
is the observed one, and its spread contains the data's noise and the regression's own error; where s says
little about a component (an output that barely sees it) the posterior stays as wide as the box. A two-point
component (a Bernoulli dropout: `EnKF.two_point`) has its std fixed by its mean.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.optimize import minimize
from scipy.stats import chi2

from .distributions import SHAPES, PathLaws

WEAK = 0.8      # `narrowed` above this: the data hardly narrowed the prior box, the component is weakly identified
PARTIAL = 0.95  # the prior box of each partial correlation: [-PARTIAL, PARTIAL] (any point of it a valid correlation)


def prior_box(s_obs: np.ndarray, ends: np.ndarray, low: np.ndarray, high: np.ndarray, width: float):
    """(lo, hi) (d,): the uniform prior of theta = (mean (p), std of the components not in `ends`, partial
    correlation of each pair (p (p - 1) / 2, `correlation_root`)).

    s_obs (2p,): the paper estimator's mean and std of xi; mean_i in s_obs mean_i +- width s_obs std_i (a
    two-point component: inside its ends low_i < high_i, off each end by 1e-3 of the box), std_i in
    [0, width s_obs std_i], each partial correlation in [-PARTIAL, PARTIAL]. ends (p,) bool; low, high (p,) the
    two-point components' ends."""
    p = ends.size
    mean, std = s_obs[:p], np.maximum(s_obs[p:], 1e-6)
    lo_m, hi_m = mean - width * std, mean + width * std
    if ends.any():
        eps = 1e-3 * (high - low)
        lo_m, hi_m = np.where(ends, low + eps, lo_m), np.where(ends, high - eps, hi_m)
    free, pairs = ~ends, np.full(p * (p - 1) // 2, PARTIAL)
    return np.concatenate([lo_m, np.zeros(free.sum()), -pairs]), np.concatenate([hi_m, width * std[free], pairs])


def correlation_columns(ends: np.ndarray) -> slice:
    """theta's partial correlations (`prior_box`'s layout)."""
    p, free = ends.size, int((~ends).sum())
    return slice(p + free, p + free + p * (p - 1) // 2)


def quadratic_replicates(d: int) -> int:
    """The replicates the `emulator`'s quadratic fit in d components of theta takes: 5 per coefficient."""
    return (d + 1) * (d + 2) // 2 * 5


def correlation_root(partial: np.ndarray, p: int) -> np.ndarray:
    """(..., p, p): the lower-triangular root L of a correlation matrix L L^T from the partial correlations (..., p (p -
    1) / 2) of each pair (i, j), i > j, in np.tril_indices(p, -1)'s order, of xi_i and xi_j given xi_0..xi_{j-1}
    (the C-vine of Lewandowski, Kurowicka & Joe 2009): L[i, j] = partial_ij sqrt(1 - sum_{k<j} L[i, k]^2), L[i, i]
    what is left of row i's unit length. Every point of (-1, 1)^{p (p - 1) / 2} gives a valid correlation, and
    elementwise arithmetic gives the same bytes on every CPU (no factorization)."""
    L = np.zeros(partial.shape[:-1] + (p, p))
    L[..., 0, 0] = 1.0
    for k, (i, j) in enumerate(zip(*np.tril_indices(p, -1))):     # row by row, left to right
        L[..., i, j] = partial[..., k] * np.sqrt(np.clip(1 - (L[..., i, :j] ** 2).sum(axis=-1), 0, None))
        if j == i - 1:
            L[..., i, i] = np.sqrt(np.clip(1 - (L[..., i, :i] ** 2).sum(axis=-1), 0, None))
    return L


def uniform_draws(lo: np.ndarray, hi: np.ndarray, count: int, seed) -> np.ndarray:
    """(count, d): theta uniform in the box [lo, hi] (d,), from default_rng(seed)."""
    return lo + (hi - lo) * np.random.default_rng(seed).random((count, lo.size))


def posterior_box(draws: np.ndarray, w: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                  margin: float = 0.25, tail: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """The box the next round draws from: the span of the weighted draws (N, d) between their `tail` and 1 - `tail`
    weighted quantiles, widened by `margin` of it on each side, within [lo, hi]. The posterior under the first box
    lies inside (up to the tails and the margin), so the same prior restricted to it gives the same posterior,
    resolved by more replicates where it has its mass."""
    span = np.array([weighted_quantiles(column, w, [tail, 1 - tail]) for column in draws.T]).reshape(-1, 2)
    pad = margin * (span[:, 1] - span[:, 0])
    new_lo, new_hi = np.maximum(lo, span[:, 0] - pad), np.minimum(hi, span[:, 1] + pad)
    return new_lo, np.maximum(new_hi, new_lo)


def partial_correlations(corr: np.ndarray) -> np.ndarray:
    """(p (p - 1) / 2,): the partial correlations of a positive definite correlation matrix corr (p, p), as
    `correlation_root` takes them (its inverse, through corr's Cholesky factor)."""
    L = np.linalg.cholesky(corr)
    i, j = np.tril_indices(len(corr), -1)
    left = 1 - np.array([(L[a, :b] ** 2).sum() for a, b in zip(i, j)])
    return L[i, j] / np.sqrt(left)


def moments_of(theta: np.ndarray, ends: np.ndarray, low: np.ndarray, high: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """theta (..., d) -> mean (..., p) and covariance (..., p, p) of xi: the stds of theta, a two-point
    component's sqrt((mean - low)(high - mean)), and the correlation of theta's partial correlations."""
    mean, std, root = law_of(theta, ends, low, high)
    corr = np.einsum("...ik,...jk->...ij", root, root)
    return mean, std[..., :, None] * corr * std[..., None, :]


def law_of(theta: np.ndarray, ends: np.ndarray, low: np.ndarray, high: np.ndarray):
    """theta (..., d) -> mean (..., p), std (..., p) and the correlation's root (..., p, p) (`correlation_root`)."""
    p = ends.size
    free = int((~ends).sum())
    mean = theta[..., :p]
    std = np.zeros(theta.shape[:-1] + (p,))
    std[..., ~ends] = np.abs(theta[..., p:p + free])
    if ends.any():
        std[..., ends] = np.sqrt(np.clip((mean[..., ends] - low[ends]) * (high[ends] - mean[..., ends]), 0, None))
    return mean, std, correlation_root(theta[..., p + free:p + free + p * (p - 1) // 2], p)


def posterior_moments(draws: np.ndarray, w: np.ndarray, ends: np.ndarray, low: np.ndarray, high: np.ndarray,
                      correlated: bool = True):
    """The model of the weighted draws (N, d) of theta: the posterior mean of xi's mean (p,) and of each std, with
    the posterior mean of the correlation (p, p) between them (a mean of correlations: one); correlated=False (the
    draws' correlations are the prior's): I, the prior's mean correlation (its box is symmetric about 0)."""
    mean, std, root = law_of(draws, ends, low, high)
    corr = np.einsum("n,nik,njk->ij", w, root, root) / w.sum() if correlated else np.eye(ends.size)
    std = w @ std / w.sum()
    return w @ mean / w.sum(), std[:, None] * corr * std[None, :]


@dataclasses.dataclass(frozen=True)
class Shapes:
    """The replicates' laws beyond theta's moments, one per replicate: the shape of each of its p independent
    standardized factors (`distributions.PathLaws`), shape (R, p) codes into `distributions.SHAPES`, high_prob (R, p)
    a two-point factor's probability of its high point."""

    shape: np.ndarray
    high_prob: np.ndarray

    def take(self, rows) -> Shapes:
        """The replicates `rows` (an index array or slice)."""
        return Shapes(self.shape[rows], self.high_prob[rows])


def random_shapes(count: int, p: int, seed) -> Shapes:
    """`count` laws' shapes at any moments (default_rng(seed)): each factor normal, uniform or two-point with equal
    probability, a two-point's high point with probability uniform in (0.1, 0.9) (skewness up to 2.7). The model
    states xi's means, stds and correlations; a replicate drawn from one such law makes the regression's residual
    hold what the summary reads of the rest of the law (tails, atoms, skew), which no moment fixes."""
    rng = np.random.default_rng(seed)
    return Shapes(rng.integers(0, len(SHAPES), (count, p)), rng.uniform(0.1, 0.9, (count, p)))


def path_laws(theta: np.ndarray, ends: np.ndarray, low: np.ndarray, high: np.ndarray,
              shapes: Shapes | None = None) -> PathLaws:
    """The replicates' laws: path r draws xi from theta[r] (R, d) (`law_of`: mean + std L e, e of p independent
    standardized factors), with shapes[r] (`random_shapes`; None: normal factors)."""
    mean, std, root = law_of(theta, ends, low, high)
    two = ends if ends.any() else None
    if shapes is None:
        return PathLaws(mean, std[..., None] * root, two, low, high)
    return PathLaws(mean, std[..., None] * root, two, low, high, shapes.shape, shapes.high_prob)


def weighted_quantiles(values: np.ndarray, w: np.ndarray, q) -> np.ndarray:
    """The quantiles q of values (N,) weighted by w (N,) (the weighted empirical distribution, interpolated)."""
    order = np.argsort(values, kind="stable")
    cdf = (np.cumsum(w[order]) - 0.5 * w[order]) / w.sum()
    return np.interp(q, cdf, values[order])


def edge_share(draws: np.ndarray, w: np.ndarray, lo: np.ndarray, hi: np.ndarray, low: np.ndarray,
               high: np.ndarray) -> np.ndarray:
    """(d,): the share of the weight w (N,) of the draws (N, d) within 1% of the box [lo, hi] of its low end (where
    low (d,) is True) or of its high end (where high is)."""
    margin = 0.01 * (hi - lo)
    near = ((draws <= lo + margin) & low) | ((draws >= hi - margin) & high)
    return w @ near / w.sum()


def at_the_edge(draws: np.ndarray, w: np.ndarray, lo: np.ndarray, hi: np.ndarray, ends: np.ndarray,
                share: float = 0.05) -> np.ndarray:
    """(d,) bool: the components of theta whose posterior puts more than `share` of its weight within 1% of the
    prior box [lo, hi] at an edge that is not the law's own: either end of a mean that is not two-point, the
    upper end of a std (a std of 0 and a two-point component's ends are laws the box rightly holds). There the
    box, not the data, stops the posterior: its interval may be cut short."""
    stds = np.zeros(lo.size - ends.size, dtype=bool)
    return edge_share(draws, w, lo, hi, np.concatenate([~ends, stds]), np.concatenate([~ends, ~stds])) > share


def pressed(draws: np.ndarray, w: np.ndarray, lo: np.ndarray, hi: np.ndarray, prior_lo: np.ndarray,
            prior_hi: np.ndarray, share: float = 0.05) -> np.ndarray:
    """(d,) bool: the components whose posterior draws (N, d), weighted by w (N,), put more than `share` of their
    weight within 1% of an edge of the box [lo, hi] they were drawn under that lies inside the prior box
    [prior_lo, prior_hi] (by more than 1% of the box): a box placed by an earlier round, not the prior, cuts the
    posterior there."""
    margin = 0.01 * (hi - lo)
    return edge_share(draws, w, lo, hi, lo > prior_lo + margin, hi < prior_hi - margin) > share


def narrowed(draws: np.ndarray, w: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(d,): each component's posterior sd over the prior box's, (hi - lo) / sqrt(12): near 1 where the data
    did not narrow the box (the outputs do not tell that component), small where they pinned it down."""
    mean = w @ draws / w.sum()
    return np.sqrt(w @ (draws - mean) ** 2 / w.sum()) / np.maximum((hi - lo) / np.sqrt(12), 1e-300)


def weighted_draws(draws: np.ndarray, w: np.ndarray, count: int, seed) -> np.ndarray:
    """(count, d): draws from the weighted draws (N, d) (multinomial by weight, default_rng(seed))."""
    pick = np.random.default_rng(seed).choice(len(w), size=count, p=w / w.sum())
    return draws[pick]


def emulator(theta: np.ndarray, s: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """The regression of the summary on the law over a round's replicates: s_r = mu(theta_r) + e_r with mu
    quadratic in theta where there are at least 5 replicates per coefficient, else linear, and e_r of one
    covariance Sigma. theta (R, d) drawn in the box [lo, hi] (d,), s (R, ds), finite. Replicates whose residual is
    beyond the 0.999 quantile of its chi-square (an estimate near divergence) are left out of the fit, twice.
    Returns mu and h (theta (M, d) -> (M, ds), (M,): the fitted mean and its leverage, the fit's variance at theta
    in units of Sigma) and Sigma's whitening W (ds, k), k its numerical rank: W^T Sigma W = I_k."""
    centre, half = (hi + lo) / 2, np.where(hi > lo, (hi - lo) / 2, 1.0)
    pairs = np.triu_indices(theta.shape[1])
    quadratic = quadratic_replicates(theta.shape[1]) <= len(theta)

    def features(t):
        t = (t - centre) / half
        return np.concatenate([np.ones((len(t), 1)), t] + ([t[:, pairs[0]] * t[:, pairs[1]]] if quadratic else []),
                              axis=1)
    X, keep = features(theta), np.ones(len(theta), dtype=bool)
    for _ in range(3):                      # fit, leave out the outlying replicates, fit again (twice)
        beta = np.linalg.lstsq(X[keep], s[keep], rcond=None)[0]
        e = s - X @ beta
        dof = max(int(keep.sum()) - X.shape[1], 1)
        lam, U = np.linalg.eigh(e[keep].T @ e[keep] / dof)
        rank = lam > 1e-12 * max(lam.max(), 1e-300)
        W = U[:, rank] / np.sqrt(lam[rank])
        d2 = ((e @ W) ** 2).sum(axis=1)
        keep = d2 <= chi2.ppf(0.999, rank.sum())
    G = np.linalg.pinv(X[keep].T @ X[keep])
    mu = lambda t: features(t) @ beta
    h = lambda t: np.einsum("mk,kl,ml->m", features(t), G, features(t))
    return mu, h, W


def synthetic_posterior(theta: np.ndarray, s: np.ndarray, s_obs: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                        ratio: float, count: int = 10000, seed=0, squared=None
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Draws of theta given s_obs under the uniform prior on the box [lo, hi] (d,), by a Gaussian synthetic
    likelihood (Wood 2010) whose mean and covariance are the `emulator`'s regression on a round's replicates
    theta (R, d), s (R, ds) (rows with a non-finite s left out: their identification failed), in theta's
    components or, where squared (d,) bool says, their squares (of components >= 0): s_obs ~ N(mu(theta),
    (ratio + h(theta)) Sigma), ratio = the observed summary's covariance over a replicate's (its paths are
    averaged over more or fewer runs), h the regression's own error at theta. The likelihood of the summary given
    the law, not of the law given the summary, so that its maximum is where the law's expected summary is s_obs,
    whatever the box.

    Importance sampling, `count` draws from default_rng(seed), in three steps from half the box's uniform and half
    a normal: first about the likelihood's maximum (bounded quasi-Newton from the best of `count` uniform draws)
    with twice the sds of its Gauss-Newton curvature (plus the box's own, where the summary is flat), then about
    the previous step's weighted mean with twice its weighted covariance. A posterior far narrower than the box
    (many recorded paths) is found and resolved alike. Returns the last step's draws (count, d), their weights
    (count,), and s_obs's place among the summaries of the posterior mean's law ((s_obs - mu) / sd per component,
    of order 1 where the model reproduces the data)."""
    ok = np.all(np.isfinite(s), axis=1)
    g = (lambda t: t) if squared is None else (lambda t: np.where(squared, t * t, t))
    mu_g, h_g, W = emulator(g(theta[ok]), s[ok], g(lo), g(hi))
    mu, h = lambda t: mu_g(g(t)), lambda t: h_g(g(t))
    k, free = W.shape[1], hi > lo
    span = np.where(free, hi - lo, 0.0)

    def log_likelihood(t):
        spread = ratio + h(t)
        return -0.5 * (((s_obs - mu(t)) @ W) ** 2).sum(axis=1) / spread - 0.5 * k * np.log(spread)
    rng = np.random.default_rng(seed)
    draws = lo + span * rng.random((count, lo.size))
    start = draws[np.argmax(log_likelihood(draws))]
    centre = minimize(lambda t: -log_likelihood(t[None])[0], start, method="L-BFGS-B",
                      bounds=list(zip(lo, hi))).x
    step = 1e-4 * np.where(free, span, 1.0)
    J = (mu(centre + np.diag(step)) - mu(centre[None])) / step[:, None] @ W        # (d, k): whitened d mu / d theta
    box_precision = np.where(free, 12 / np.where(free, span, 1.0) ** 2, 1.0)
    cov = np.linalg.inv(J @ J.T / (ratio + h(centre[None])[0]) + np.diag(box_precision))
    for _ in range(3):
        cov = cov[np.ix_(free, free)] + np.diag((1e-3 * span[free]) ** 2)
        root = np.linalg.cholesky(4 * cov)                      # the normal: twice the sds
        draws = lo + span * rng.random((count, lo.size))
        half = count // 2
        draws[half:, free] = centre[free] + rng.standard_normal((count - half, free.sum())) @ root.T
        z = np.linalg.solve(root, (draws[:, free] - centre[free]).T)
        log_n = -0.5 * (z ** 2).sum(axis=0) - np.log(np.diag(root)).sum() - 0.5 * free.sum() * np.log(2 * np.pi)
        log_q = np.logaddexp(-np.log(span[free]).sum(), log_n) - np.log(2)
        inside = np.all((draws >= lo) & (draws <= hi), axis=1)
        log_w = np.where(inside, log_likelihood(draws) - log_q, -np.inf)
        w = np.exp(log_w - log_w.max())
        centre = w @ draws / w.sum()
        dev = draws - centre
        cov = (w[:, None] * dev).T @ dev / w.sum()
    mean = centre[None]
    sd = np.sqrt(np.clip(np.diag(np.linalg.pinv(W @ W.T)), 0, None) * (ratio + h(mean)[0]))
    # a summary no replicate varies (beyond Sigma's numerical rank: its sd is round-off) has no misfit to read
    varied = sd > 1e-6 * sd.max()
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(varied, (s_obs - mu(mean)[0]) / sd, 0.0)
    return draws, w, z
