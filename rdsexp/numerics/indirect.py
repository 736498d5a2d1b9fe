"""The moments of xi by simulation: approximate Bayesian computation with the paper's estimator as summary.

The paper's estimator (eq. sample-mean: the moments of xi_{k|k} over the window) is biased: the EnKF's
filtered means are shrunk toward its random walk, and its covariance mixes the spread of xi with the
filter's own. Its bias depends on the plant, the input, the window and the noise, so no fixed correction
removes it. But rdsexp can run the same identification on the model at any law of xi. So:

1. the summary s of the identification run (`s_obs`): the paper estimator's mean (p) and std (p), and any
   other statistic the caller computes the same way on every run (rdsexp adds the outputs' and the
   innovations' log mean squares);
2. theta = (mean of xi (p), std of every component that is not two-point) drawn uniformly from a box
   around the paper estimator's moments (`prior_box`), one law per replicate path (`path_laws`,
   `distributions.PathLaws`);
3. the same identification (input, feedback, EnKF, window) of the model on each replicate, batched over
   paths: its summary s_r;
4. the replicates nearest s_obs weighted (Epanechnikov kernel), and theta_r moved along a weighted linear
   regression of theta on s to s = s_obs (`adjusted_posterior`: Beaumont, Zhang & Balding 2002).

The weighted adjusted thetas are draws of the posterior of theta given s_obs under the box prior. Their
mean is the modeled law, their spread its uncertainty: it contains the estimator's bias and its noise, and
where s says little about a component (an output that barely sees it) the posterior stays as wide as the
box. A two-point component (a Bernoulli dropout: `EnKF.two_point`) has its std fixed by its mean.
"""
from __future__ import annotations

import numpy as np
from scipy.special import expit

from .distributions import PathLaws

WEAK = 0.8      # `narrowed` above this: the data hardly narrowed the prior box, the component is weakly identified


def prior_box(s_obs: np.ndarray, ends: np.ndarray, low: np.ndarray, high: np.ndarray, width: float):
    """(lo, hi) (d,): the uniform prior of theta = (mean (p), std of the components not in `ends`).

    s_obs (2p,): the paper estimator's mean and std of xi; mean_i in s_obs mean_i +- width s_obs std_i (a
    two-point component: inside its ends low_i < high_i, off each end by 1e-3 of the box), std_i in
    [0, width s_obs std_i]. ends (p,) bool; low, high (p,) the two-point components' ends."""
    p = ends.size
    mean, std = s_obs[:p], np.maximum(s_obs[p:], 1e-6)
    lo_m, hi_m = mean - width * std, mean + width * std
    if ends.any():
        eps = 1e-3 * (high - low)
        lo_m, hi_m = np.where(ends, low + eps, lo_m), np.where(ends, high - eps, hi_m)
    free = ~ends
    return np.concatenate([lo_m, np.zeros(free.sum())]), np.concatenate([hi_m, width * std[free]])


def uniform_draws(lo: np.ndarray, hi: np.ndarray, count: int, seed) -> np.ndarray:
    """(count, d): theta uniform in the box [lo, hi] (d,), from default_rng(seed)."""
    return lo + (hi - lo) * np.random.default_rng(seed).random((count, lo.size))


def posterior_box(adjusted: np.ndarray, w: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                  margin: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """The box the next round draws from: the span of the weighted draws (N, d), widened by `margin` of it on
    each side, within [lo, hi]. The posterior under the first box lies inside (up to the margin), so the same
    prior restricted to it gives the same posterior, resolved by more replicates where it has its mass."""
    kept = adjusted[w > 0]
    low, high = kept.min(axis=0), kept.max(axis=0)
    pad = margin * (high - low)
    new_lo, new_hi = np.maximum(lo, low - pad), np.minimum(hi, high + pad)
    return new_lo, np.maximum(new_hi, new_lo)


def moments_of(theta: np.ndarray, ends: np.ndarray, low: np.ndarray, high: np.ndarray,
               corr: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """theta (..., d) -> mean (..., p) and covariance (..., p, p) of xi: the stds of theta, a two-point
    component's sqrt((mean - low)(high - mean)), with correlation `corr` (p, p) (None: independent)."""
    p = ends.size
    mean = theta[..., :p]
    std = np.zeros(theta.shape[:-1] + (p,))
    std[..., ~ends] = np.abs(theta[..., p:])
    if ends.any():
        std[..., ends] = np.sqrt(np.clip((mean[..., ends] - low[ends]) * (high[ends] - mean[..., ends]), 0, None))
    corr = np.eye(p) if corr is None else corr
    return mean, std[..., :, None] * corr * std[..., None, :]


def path_laws(theta: np.ndarray, ends: np.ndarray, low: np.ndarray, high: np.ndarray) -> PathLaws:
    """The replicates' laws: path r draws xi from theta[r] (R, d), independent components (`moments_of`)."""
    mean, cov = moments_of(theta, ends, low, high)
    sqrt = np.sqrt(np.einsum("rii->ri", cov))[..., None] * np.eye(ends.size)
    return PathLaws(mean, sqrt, ends if ends.any() else None, low, high)


def adjusted_posterior(theta: np.ndarray, s: np.ndarray, s_obs: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                       accept: float) -> tuple[np.ndarray, np.ndarray]:
    """Draws of theta given s_obs: the local-linear regression adjustment (Beaumont, Zhang & Balding 2002).

    theta (R, d) drawn from the box prior [lo, hi], s (R, ds) their summaries (rows with a non-finite s are
    left out: the replicate's identification failed), s_obs (ds,). The fraction `accept` of the replicates
    nearest s_obs (distance scaled by s's spread over the replicates) get Epanechnikov weights; theta is
    regressed on s by weighted least squares and moved to s = s_obs, then kept in the box.
    Returns the adjusted draws (N, d) and their weights (N,), N > 0 the weighted replicates."""
    ok = np.all(np.isfinite(s), axis=1)
    theta, s = theta[ok], s[ok]
    dev = s - s_obs
    scale = s.std(axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    dist = np.sqrt(((dev / scale) ** 2).sum(axis=1))
    h = np.quantile(dist, accept)
    w = np.clip(1 - (dist / h) ** 2, 0, None) if h > 0 else (dist == 0).astype(float)
    keep = w > 0
    theta, dev, w = theta[keep], dev[keep], w[keep]
    X = np.concatenate([np.ones((len(w), 1)), dev / scale], axis=1)
    # the regression on the logit of theta's place in the box, so that the adjusted draws stay inside it without
    # piling up on an edge where the regression extrapolates (a std of 0, a probability of 1)
    span = np.where(hi > lo, hi - lo, 1.0)
    place = np.clip((theta - lo) / span, 1e-9, 1 - 1e-9)
    logit = np.log(place) - np.log1p(-place)
    # weighted least squares, a minimum-norm solution where the kept summaries are collinear
    beta = np.linalg.lstsq(X * np.sqrt(w)[:, None], logit * np.sqrt(w)[:, None], rcond=None)[0]
    adjusted = lo + span * expit(logit - (dev / scale) @ beta[1:])
    return np.where(hi > lo, adjusted, lo), w


def misfit(s: np.ndarray, s_obs: np.ndarray, accept: float) -> np.ndarray:
    """(ds,): where s_obs lies among the replicates' summaries s (R, ds) nearest to it (the fraction `accept`, as
    `adjusted_posterior` weights them): (s_obs - their mean) / their sd per component. Where the model reproduces
    the data these are of order 1; a component many sds off is a summary no law in the box reaches, and the
    regression adjustment would extrapolate to it."""
    s = s[np.all(np.isfinite(s), axis=1)]
    scale = s.std(axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    dist = np.sqrt((((s - s_obs) / scale) ** 2).sum(axis=1))
    near = s[dist <= np.quantile(dist, accept)]
    spread = near.std(axis=0)
    return (s_obs - near.mean(axis=0)) / np.where(spread > 0, spread, scale)


def averaged(theta: np.ndarray, s: np.ndarray, paths: int) -> np.ndarray:
    """(R, ds): summaries of one path per replicate made those of the mean over `paths` paths, as the observed
    summary of several recorded paths is: the regression of s on theta (R, d) (quadratic in theta where there are
    at least 5 replicates per coefficient, else linear) plus the residual over sqrt(paths). The mean of `paths`
    i.i.d. summaries has the regression of one and 1/paths of its covariance. Rows with a non-finite s stay NaN."""
    ok = np.all(np.isfinite(s), axis=1)
    t = theta[ok]
    t = (t - t.mean(axis=0)) / np.where(t.std(axis=0) > 0, t.std(axis=0), 1.0)
    pairs = np.triu_indices(t.shape[1])
    quadratic = (t.shape[1] + 1) * (t.shape[1] + 2) // 2 * 5 <= len(t)
    X = np.concatenate([np.ones((len(t), 1)), t] + ([t[:, pairs[0]] * t[:, pairs[1]]] if quadratic else []), axis=1)
    fit = X @ np.linalg.lstsq(X, s[ok], rcond=None)[0]
    out = np.full(s.shape, np.nan)
    out[ok] = fit + (s[ok] - fit) / np.sqrt(paths)
    return out


def weighted_quantiles(values: np.ndarray, w: np.ndarray, q) -> np.ndarray:
    """The quantiles q of values (N,) weighted by w (N,) (the weighted empirical distribution, interpolated)."""
    order = np.argsort(values, kind="stable")
    cdf = (np.cumsum(w[order]) - 0.5 * w[order]) / w.sum()
    return np.interp(q, cdf, values[order])


def at_the_edge(adjusted: np.ndarray, w: np.ndarray, lo: np.ndarray, hi: np.ndarray, ends: np.ndarray,
                share: float = 0.05) -> np.ndarray:
    """(d,) bool: the components of theta whose posterior puts more than `share` of its weight within 1% of the
    prior box [lo, hi] at an edge that is not the law's own: either end of a mean that is not two-point, the
    upper end of a std (a std of 0 and a two-point component's ends are laws the box rightly holds). There the
    box, not the data, stops the posterior: its interval may be cut short."""
    p = ends.size
    near_lo = adjusted <= lo + 0.01 * (hi - lo)
    near_hi = adjusted >= hi - 0.01 * (hi - lo)
    check_lo = np.concatenate([~ends, np.zeros(lo.size - p, dtype=bool)])
    check_hi = np.concatenate([~ends, np.ones(lo.size - p, dtype=bool)])
    edge = (near_lo & check_lo) | (near_hi & check_hi)
    return w @ edge / w.sum() > share


def narrowed(adjusted: np.ndarray, w: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(d,): each component's posterior sd over the prior box's, (hi - lo) / sqrt(12): near 1 where the data
    did not narrow the box (the outputs do not tell that component), small where they pinned it down."""
    mean = w @ adjusted / w.sum()
    return np.sqrt(w @ (adjusted - mean) ** 2 / w.sum()) / np.maximum((hi - lo) / np.sqrt(12), 1e-300)


def weighted_draws(adjusted: np.ndarray, w: np.ndarray, count: int, seed) -> np.ndarray:
    """(count, d): draws from the weighted adjusted thetas (multinomial by weight, default_rng(seed))."""
    pick = np.random.default_rng(seed).choice(len(w), size=count, p=w / w.sum())
    return adjusted[pick]
