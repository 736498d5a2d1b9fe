"""Exact mean-square analysis of the ideal closed loop and empirical rates from Monte Carlo.

The ideal closed loop is x_{k+1} = Acl(xi_k) x_k + B(xi_k) d_k with Acl = A + B F (eq. closed-loop)
and full state feedback; its second moments depend on the distribution of xi only through Gbar.
"""
from __future__ import annotations

import numpy as np
from scipy import stats

from .systems import AffineRandomSystem, MomentModel


def second_moment_operator(system: AffineRandomSystem, dist: MomentModel | None, F) -> np.ndarray:
    """E[Acl (x) Acl], shape (n^2, n^2): row-major vec(X_{k+1}) = this @ vec(X_k) for d = 0."""
    Abar, Bbar = system.moment_factors(dist)
    Acl = Abar + Bbar @ system.check_gain(F)                 # (nbar, n, n)
    n = system.n
    return np.einsum("rij,rkl->ikjl", Acl, Acl).reshape(n * n, n * n)


def ms_rate(system: AffineRandomSystem, dist: MomentModel | None, F) -> float:
    """Exact mean-square decay rate sqrt(rho(E[Acl (x) Acl])) of the ideal closed loop.

    This is the smallest lambda of eq. (exp-def) for the gain F (>= 1: not mean-square stable).
    `dist` None uses the system's own xi_dist.
    """
    return float(np.sqrt(np.abs(np.linalg.eigvals(second_moment_operator(system, dist, F))).max()))


def second_moments(system: AffineRandomSystem, dist: MomentModel | None, F, x0, d) -> tuple[np.ndarray, np.ndarray]:
    """Exact E[x_k] (K+1, n) and E[x_k x_k^T] (K+1, n, n) of the ideal closed loop with input d.

    x_{k+1} = (A(xi_k) + B(xi_k) F) x_k + B(xi_k) d_k, x_0 deterministic, d: (K+1, m) deterministic
    (the last row is unused). Since xi_k is independent of x_k,
        X_{k+1} = sum_r T_r [[X_k, m_k], [m_k^T, 1]] T_r^T,  T_r = [Abar_r + Bbar_r F, Bbar_r d_k].
    """
    dist = system.check_distribution(dist)
    F = system.check_gain(F)
    x0 = np.asarray(x0, dtype=float)
    d = np.atleast_2d(np.asarray(d, dtype=float))
    if x0.shape != (system.n,):
        raise ValueError(f"x0: shape {x0.shape}, expected ({system.n},)")
    if d.ndim != 2 or d.shape[1] != system.m:
        raise ValueError(f"d: shape {d.shape}, expected (K+1, m = {system.m})")
    Abar, Bbar = system.moment_factors(dist)
    Acl_bar = Abar + Bbar @ F
    A_mu, B_mu, _, _ = system.at(dist.mean)
    Acl_mu = A_mu + B_mu @ F
    K = d.shape[0] - 1
    mean = np.empty((K + 1, system.n))
    second = np.empty((K + 1, system.n, system.n))
    mean[0], second[0] = x0, np.outer(x0, x0)
    for k in range(K):                                          # a recursion in time, not over samples
        T = np.concatenate([Acl_bar, (Bbar @ d[k])[:, :, None]], axis=2)       # (nbar, n, n+1)
        Z = np.block([[second[k], mean[k][:, None]], [mean[k][None, :], np.ones((1, 1))]])
        second[k + 1] = np.einsum("rij,jl,rkl->ik", T, Z, T)
        mean[k + 1] = Acl_mu @ mean[k] + B_mu @ d[k]
    return mean, second


def empirical_rate(q: np.ndarray, k_from: int, k_to: int, level: float = 0.95) -> tuple[float, float, float]:
    """Rate (sqrt(E||q_to||^2) / sqrt(E||q_from||^2))^(1/(k_to-k_from)) from sample paths, with a CI.

    q: (K+1, P, n) trajectories. The expectation is the sample mean over the P paths (as in the
    paper, which used k = 60 -> 80); the interval is the delta-method interval for the log ratio of
    the two correlated means. Returns (rate, low, high); NaN when a path is not finite at either step.
    """
    a = np.sum(q[k_to] ** 2, axis=-1)
    b = np.sum(q[k_from] ** 2, axis=-1)
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))) or a.mean() <= 0 or b.mean() <= 0:
        return float("nan"), float("nan"), float("nan")
    P, span = a.size, 2.0 * (k_to - k_from)
    log_ratio = np.log(a.mean()) - np.log(b.mean())
    # gradient of log(mean a) - log(mean b) applied to the per-path pairs
    g = a / a.mean() - b / b.mean()
    se = np.std(g, ddof=1) / np.sqrt(P) if P > 1 else np.inf
    z = stats.norm.ppf(0.5 + level / 2)
    return tuple(float(np.exp(v / span)) for v in (log_ratio, log_ratio - z * se, log_ratio + z * se))


def rms(q: np.ndarray) -> np.ndarray:
    """sqrt(E||q_k||^2) over paths: q (K+1, P, n) -> (K+1,)."""
    return np.sqrt(np.mean(np.sum(q ** 2, axis=-1), axis=1))


# ----------------------------------------------------------- rate estimators beside empirical_rate
def bootstrap_rate(sq_from: np.ndarray, sq_to: np.ndarray, span: int, *, replicates: int = 2000,
                   level: float = 0.95, seed=0) -> tuple[float, float, float]:
    """Two-point mean-square rate with a percentile bootstrap interval, resampling seeds then paths.

    sq_from, sq_to: (S, P) values of ||q_{k_from}||^2 and ||q_{k_to}||^2 per seed (independent run)
    and path; span = k_to - k_from. The rate is (sum sq_to / sum sq_from)^(1/(2 span)), the paper's
    ratio of sample means pooled over all S*P paths. Each replicate draws S seeds with replacement
    and, within each, P paths with replacement (S = 1: the bootstrap over paths of one run), so the
    interval carries the spread between seeds as well as within. NaN if any value is not finite.
    Returns (rate, low, high).
    """
    a, b = np.atleast_2d(np.asarray(sq_to, float)), np.atleast_2d(np.asarray(sq_from, float))
    if a.shape != b.shape or span < 1:
        raise ValueError(f"sq_from, sq_to: shapes {b.shape}, {a.shape} must match (S, P); span {span} must be >= 1")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))) or b.sum() <= 0 or a.sum() <= 0:
        return float("nan"), float("nan"), float("nan")
    S, P = a.shape
    rng = np.random.default_rng(seed)
    s = rng.integers(S, size=(replicates, S, 1))
    p = rng.integers(P, size=(replicates, S, P))
    ratio = a[s, p].sum(axis=(1, 2)) / b[s, p].sum(axis=(1, 2))          # (replicates,)
    with np.errstate(divide="ignore"):
        boot = ratio ** (1 / (2 * span))
    low, high = np.quantile(boot, [0.5 - level / 2, 0.5 + level / 2])
    return float((a.sum() / b.sum()) ** (1 / (2 * span))), float(low), float(high)


def largest_path_share(q: np.ndarray, k: int) -> float:
    """Share of the largest path in the sample mean of ||q_k||^2: q (K+1, P, n) -> in [1/P, 1]."""
    sq = np.sum(q[k] ** 2, axis=-1)
    return float(sq.max() / sq.sum()) if np.all(np.isfinite(sq)) and sq.sum() > 0 else float("nan")


def robust_rate(q: np.ndarray, k_from: int, k_to: int, groups: int = 10) -> float:
    """Median-of-means rate: a rate estimate that no single path can dominate.

    The P paths are split into `groups` interleaved groups (path j in group j mod groups); in each,
    log of the group's mean ||q_k||^2 is fitted by least squares against k = k_from..k_to (every
    step of the window, not only its two ends), the slope halved; the median over groups is
    returned as exp(.). One heavy path moves one group, not the median. It estimates the same
    mean-square rate as the two-point ratio when groups are large enough that each group mean is
    close to its expectation. q: (K+1, P, n). NaN if a path is not finite in the window.
    """
    P = q.shape[1]
    if not 1 <= groups <= P or not 0 <= k_from < k_to < q.shape[0]:
        raise ValueError(f"groups {groups} must be in 1..P = {P}; window {k_from}..{k_to} within 0..{q.shape[0] - 1}")
    sq = np.sum(q[k_from:k_to + 1] ** 2, axis=-1)                            # (W, P)
    if not np.all(np.isfinite(sq)):
        return float("nan")
    member = np.arange(P) % groups
    means = np.stack([sq[:, member == g].mean(axis=1) for g in range(groups)], axis=1)   # (W, groups)
    if np.any(means <= 0):
        return float("nan")
    k = np.arange(k_from, k_to + 1) - (k_from + k_to) / 2
    slopes = k @ np.log(means) / (k @ k)                                   # least-squares slope per group
    return float(np.exp(np.median(slopes) / 2))
