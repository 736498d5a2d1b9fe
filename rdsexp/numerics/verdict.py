"""A loop's verdict from its Monte Carlo: stable, unstable, undetermined or failed.

The empirical rate of a loop, (E||q_{k_to}||^2 / E||q_{k_from}||^2)^(1/(2 (k_to - k_from))) with its
95% interval (`rate_interval`), says whether the loop decays only where the decay is
measurable:
- after the disturbance d_k has ended (the paper's window k = 60..80 starts 10 steps after its
  d_k ends at k = 50);
- above the loop's noise floor. The plant has no noise, but the loop u_k = F x_{k|k-1} feeds the
  EnKF's own noise (its Q, R and finite ensemble) back into the plant, so E||q_k||^2 stops decaying
  at a floor. Over a window at the floor the paths do not decay whatever the gain: a rate near 1
  there says nothing about the loop. The floor is measured, not guessed: E||q_k||^2 of the same
  loop started at rest (q_0 = 0, no disturbance), averaged over the second half of its horizon
(`Floor`). The floor only pulls the plain rate towards 1; where that keeps its interval from
deciding, the floor's mean square is subtracted from the loop's (the EnKF's noise adds to the
transient), with the floor's own uncertainty, so a loop that decays from far above the floor to it
has a rate; the window is then cut where the loop reaches the floor ("at rest from k = ..."). A run
at rest that grows, or whose paths diverge, is no floor: the loop grows.

The interval must hold when the mean square is carried by a few paths (multiplicative noise makes
||q_k||^2 a product of random factors, nearly lognormal with a spread that grows with k; a sample
of P paths then misses the paths that carry the mean, and the sample mean is low). It is the hull
of two bootstrap intervals over paths of the same log ratio: the bias-corrected and accelerated
(BCa) bootstrap of the sample means (valid where the central limit theorem holds; unlike a
studentised bootstrap, its ends do not explode when one path carries most of the mean square and
the resamples that miss it have almost no spread) and a percentile bootstrap of the
lognormal means exp(mu + sigma^2 / 2) (valid for products of many random factors, where the
sample mean is not; mu and sigma from the median and the upper half of log ||q||^2, so that states
near 0 do not widen it). `experiments/coverage.py` measures its coverage against exact rates.

`place_window` derives the window from the exact curve sqrt(E||x_k||^2) of the ideal loop (state
feedback on the true plant, `analysis.second_moments`): from the end of the disturbance to the last
step at which that curve is still ABOVE_FLOOR times the floor. `judge_loop` then reads the
evidence in a fixed order: failed paths (in the open loop, whose observer does not act on the plant,
a diverged plant state is growth), a run at rest that diverged or grows, no measurable window, the
plain interval over the window against 1 and, where it does not decide, the one with the floor
subtracted over the window cut where the loop is at rest; last the exact rate of the ideal loop over
the same steps: a loop is never called stable where that exact rate is >= 1.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr, ndtri
from scipy.stats import binom

VERDICTS = ("stable", "unstable", "undetermined", "failed")
ABOVE_FLOOR = 10.0    # a placed window ends where the ideal loop's RMS is still 10 floors (one decade) up
AT_REST = 2.0         # a loop whose mean square is below 2 floors' (its transient below the floor) is at rest
AT_FLOOR = 3.0        # an automatic window ends where the loop's own RMS comes within 2 AT_FLOOR floors
LEVEL = 0.95          # of every rate interval
PAIRED_LEVEL = 0.05   # `paired_losses`: a loop loses more paths than another where p < this
RESAMPLES = 999       # bootstrap resamples of the paths
UPPER_SIGMA = 0.8413447460685429    # the standard normal's cdf at 1: its quantile of log v is mu + sigma
BOOTSTRAP_SEED = 7    # one fixed stream: an interval is a function of its paths alone (the same bytes for any
                      # chunk size, worker count or rerun)
# a path's failure reason (Trajectories.failure) in words
FAILURES = {"diverged": "the plant state diverged", "filter_diverged": "the EnKF estimate diverged",
            "singular_innovation": "the EnKF innovation covariance was singular"}


HEAVY_TAIL = 0.7      # `tail_index` above this: a few paths carry the mean square (PSIS's threshold for a mean)


def tail_index(values: np.ndarray) -> float:
    """The Pareto shape k-hat of the upper tail of values (P,) > 0 (the paths' ||q_k||^2 at one step), as Pareto
    smoothed importance sampling computes it (Vehtari, Simpson, Gelman, Yao & Gabry): a generalized Pareto fit
    to the largest min(P / 5, 3 sqrt(P)) values over the next one, by Zhang & Stephens' (2009) estimator with its
    weakly informative shrinkage toward 0.5. Above HEAVY_TAIL (0.7) the sample mean is carried by a few values and
    converges too slowly to trust at this P; the tail has no finite variance above 0.5. NaN below 20 finite
    values or where a quarter of the tail ties with its threshold."""
    x = np.sort(np.asarray(values, dtype=float)[np.isfinite(values)])
    if x.size < 20:
        return float("nan")
    tail = int(np.ceil(min(0.2 * x.size, 3 * np.sqrt(x.size))))
    excess = x[-tail:] - x[-tail - 1]
    if excess[int(excess.size / 4 + 0.5) - 1] <= 0:      # a quarter of the tail tied with its threshold: no
        return float("nan")                              # continuous tail to fit (values of a discrete law)
    n = excess.size
    # Zhang & Stephens: a grid of the profile parameter theta = -k / sigma, weighted by its profile likelihood
    grid = 30 + int(np.sqrt(n))
    theta = 1 / excess[-1] + (1 - np.sqrt(grid / (np.arange(1, grid + 1) - 0.5))) / (3 * excess[int(n / 4 + 0.5) - 1])
    with np.errstate(all="ignore"):
        k = np.log1p(-theta[:, None] * excess).mean(axis=1)
        profile = n * (np.log(-theta / k) - k - 1)
        weights = 1 / np.exp(profile - profile[:, None]).sum(axis=1)
    theta_hat = np.sum(theta * weights / weights.sum())
    k_hat = np.log1p(-theta_hat * excess).mean()
    return float((n * k_hat + 10 * 0.5) / (n + 10))           # the prior's shrinkage, as PSIS has it


def look_level(looks: int, level: float = LEVEL) -> float:
    """The level of every look's intervals where a run may stop at any of `looks` looks (closed_loop.paths auto):
    1 - (1 - level) / looks (Bonferroni). Whichever look it stops at, the chance that an interval it reports
    misses is at most the chance that any look's does, at most 1 - level: optional stopping keeps the level."""
    return 1 - (1 - level) / looks


def asks_for_paths(word: str, paths_needed: float, tail_khat: float, fed_back: bool) -> bool:
    """Whether more paths could change a verdict or firm it up: undetermined by an interval that holds 1 (with the
    paths it would need, `Verdict.needs`: finite), or, in a loop whose estimate is fed back (closed, online),
    decisive while a few paths carry the mean square at the window's end (`tail_index` above HEAVY_TAIL: there
    the closed loops' intervals held a near-truth for 81-83% against 98-100%, docs/verdicts.md). A failed loop,
    or one without a window or below its floor, says the same at any path count."""
    if word == "undetermined":
        return bool(np.isfinite(paths_needed))
    return fed_back and word in ("stable", "unstable") and bool(tail_khat > HEAVY_TAIL)


def judge_at_looks(sq: np.ndarray, looks: tuple[int, ...], fed_back: bool, **judge) -> tuple[Verdict, int]:
    """closed_loop.paths auto's rule on paths simulated beforehand, sq (K+1, >= looks[-1]): `judge_loop` on the
    first P paths of each look at `look_level`, up to the first whose verdict does not `asks_for_paths` (the
    pipeline simulates each look's paths only when it gets there). judge: judge_loop's other arguments, failed_at
    and failure for every path. Returns the verdict and the paths it was judged on."""
    failed_at, failure = judge.pop("failed_at"), judge.pop("failure")
    for P in looks:
        v = judge_loop(sq[:, :P], failed_at=failed_at[:P], failure=failure[:P], level=look_level(len(looks)), **judge)
        window = judge.get("window")
        khat = tail_index(sq[window[1], :P]) if window is not None else np.nan
        if not asks_for_paths(v.word, np.nan if v.needs is None else v.needs, khat, fed_back):
            break
    return v, P


def window_start(d: np.ndarray, n: int) -> int:
    """First step of an automatic window: the first step after the disturbance d (K+1, m) has ended
    for good, and at least n (the EnKF has seen n outputs, enough to observe x)."""
    active = np.flatnonzero(np.any(d != 0, axis=1))
    return max(int(active[-1]) + 1 if active.size else 0, n)


def place_window(exact_rms: np.ndarray, start: int, floor_rms: float, empirical_rms: np.ndarray | None = None,
                 above: float = ABOVE_FLOOR) -> tuple[int, int] | None:
    """[start, k_to] with k_to the last step such that the ideal loop's RMS exact_rms (K+1,) stays
    above `above` * floor_rms on every step from start to k_to (the horizon K when it never drops
    there), and the loop's own RMS empirical_rms (K+1,), when given, above 2 AT_FLOOR floors (a loop
    that decays faster than the ideal one reaches the floor earlier); None when not even
    [start, start + 1] qualifies (the ideal loop starts at the floor or at 0, or start >= K).
    floor_rms NaN (not measured) counts as 0; inf (the loop at rest diverged) leaves no window."""
    K = exact_rms.size - 1
    if start >= K:
        return None
    floor = 0.0 if np.isnan(floor_rms) else float(floor_rms)
    above_floor = exact_rms[start:] > above * floor
    if empirical_rms is not None:
        above_floor &= ~(empirical_rms[start:] <= 2 * AT_FLOOR * floor)       # NaN (failed paths): not judged here
    if not (above_floor[0] and above_floor[1]):
        return None
    k_to = start + (above_floor.size - 1 if above_floor.all() else int(np.argmin(above_floor)) - 1)
    return start, k_to


@dataclass(frozen=True)
class Verdict:
    """word: one of VERDICTS; reason: what it means, in words, from the evidence beside it; rate, low,
    high: the rate and its interval the word was decided on, over [k_from, k_end] (k_end < the window's
    k_to when the loop reached its floor earlier; NaN without a rate); window_rate: the plain rate
    (rate_interval without the floor) over the whole window, computed on the way."""

    word: str
    reason: str
    rate: float = float("nan")
    low: float = float("nan")
    high: float = float("nan")
    k_end: int = -1
    window_rate: tuple[float, float, float] = (float("nan"),) * 3     # plain, over the whole window (NaN: none)
    needs: int | None = None     # undetermined by an interval that contains 1: the paths that would separate it


@dataclass(frozen=True)
class Floor:
    """The loop started at rest (q_0 = 0, no disturbance): samples (P_f,), each path's mean of ||q_k||^2
    over the second half of the horizon; growth (rate, low, high) from the mean over its third quarter
    to the mean over its last quarter, per path; failed: the fraction of its paths that failed."""

    samples: np.ndarray
    growth: tuple[float, float, float]
    failed: float

    @classmethod
    def of(cls, sq: np.ndarray, failed_at: np.ndarray) -> Floor:
        """From ||q_k||^2 (K+1, P_f) of the run at rest and the step each path failed at (-1: never)."""
        K = sq.shape[0] - 1
        ok = failed_at < 0
        half, quarter = sq[K // 2:, ok], sq[(3 * K) // 4:, ok]
        third = sq[K // 2:(3 * K) // 4, ok]
        growth = rate_interval(third.mean(axis=0), quarter.mean(axis=0), max((3 * K) // 4 - K // 2, 1)) \
            if ok.sum() > 1 and third.size else (float("nan"),) * 3
        return cls(samples=half.mean(axis=0), growth=growth, failed=float(np.mean(~ok)))

    @property
    def rms(self) -> float:
        """sqrt of the floor's mean square (inf when a path of the run at rest failed)."""
        return float("inf") if self.failed > 0 else float(np.sqrt(np.mean(self.samples)))

    @property
    def holds(self) -> bool:
        """Whether the run at rest keeps a floor: no path failed and its growth is not above 1 at 95% (else
        `judge_loop` calls the loop itself unstable or failed)."""
        return self.failed == 0 and not self.growth[1] > 1


def rate_interval(b: np.ndarray, a: np.ndarray, span: int, floor: np.ndarray | None = None,
                  level: float = LEVEL) -> tuple[float, float, float]:
    """(rate, low, high): rate = ((mean a - f) / (mean b - f))^(1/(2 span)) from per-path ||q_{k_from}||^2
    = b (P,) and ||q_{k_to}||^2 = a (P,), f the mean of `floor` (P_f,) (0 without), and its `level`
    interval: the hull of the BCa bootstrap of the log ratio and the percentile bootstrap of its
    lognormal counterpart (module docstring), paths (and floor paths) resampled together, RESAMPLES
    times from one fixed stream. NaN when a value is not finite, a transient is not positive, or P < 2.
    A resample whose transient at k_to (k_from) is not positive has log ratio -inf (+inf): the bound
    it decides is open (low 0, high inf) rather than guessed."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    f = np.zeros(1) if floor is None else np.asarray(floor, dtype=float)
    P = a.size
    if P < 2 or not (np.all(np.isfinite(a)) and np.all(np.isfinite(b)) and np.all(np.isfinite(f))):
        return (float("nan"),) * 3
    point = _log_ratio(a[None], b[None], f[None])[0]
    if not np.isfinite(point):
        return (float("nan"),) * 3
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    means, lognormal = [], []
    block = max(1, 2_000_000 // max(P, 1))                  # blocks of resamples: bounded memory
    for start in range(0, RESAMPLES, block):
        count = min(RESAMPLES - start, block)
        i = rng.integers(P, size=(count, P))
        j = rng.integers(f.size, size=(count, f.size)) if floor is not None else np.zeros((count, 1), int)
        ai, bi, fi = a[i], b[i], f[j]
        means.append(_log_ratio(ai, bi, fi))
        if np.all(a > 0) and np.all(b > 0):
            lognormal.append(_log_ratio(ai, bi, fi, lognormal=True))
    tail = (1 - level) / 2
    quantile = lambda v, q: np.quantile(v, q, method="inverted_cdf")       # no interpolation between infinities
    means = np.nan_to_num(np.concatenate(means), nan=np.inf, posinf=np.inf, neginf=-np.inf)
    low, high = quantile(means, _bca_levels(means, point, _jackknife(a, b, f, floor is not None), tail))
    if lognormal:
        lognormal = np.nan_to_num(np.concatenate(lognormal), nan=-np.inf, posinf=np.inf, neginf=-np.inf)
        low, high = min(low, quantile(lognormal, tail)), max(high, quantile(lognormal, 1 - tail))
    with np.errstate(all="ignore"):
        return tuple(float(np.exp(v / (2.0 * span))) for v in (point, low, high))


def _bca_levels(replicates: np.ndarray, point: float, jackknife: np.ndarray, tail: float) -> np.ndarray:
    """The bias-corrected and accelerated percentile levels (Efron 1987) of a `2 tail` interval, from the
    bootstrap replicates (R,) of a statistic, its value `point` and its jackknife values (J,): the bias
    z0 from the replicates' share below the point (ties count half), the acceleration from the jackknife's
    skewness. A skewed statistic (a ratio of means carried by a few paths) moves both ends the way of its
    skew, where a studentised bootstrap's would explode with the resamples that miss those paths."""
    below = (np.sum(replicates < point) + 0.5 * np.sum(replicates == point)) / replicates.size
    z0 = ndtri(np.clip(below, 0.5 / replicates.size, 1 - 0.5 / replicates.size))
    d = jackknife.mean() - jackknife
    spread = np.sum(d ** 2)
    accel = np.sum(d ** 3) / (6 * spread ** 1.5) if spread > 0 else 0.0
    z = ndtri(np.array([tail, 1 - tail]))
    with np.errstate(all="ignore"):
        levels = ndtr(z0 + (z0 + z) / (1 - accel * (z0 + z)))
    return np.nan_to_num(levels, nan=0.5)


def _jackknife(a, b, f, with_floor: bool) -> np.ndarray:
    """Leave-one-out log ratios (P + P_f,) of `_log_ratio`: one loop path left out, then (with_floor) one
    floor path; leaves whose transient is not positive are dropped (they carry no finite influence)."""
    P, Pf = a.size, f.size
    fm = np.full(P, f.mean())
    tops, bottoms = [(a.sum() - a) / (P - 1) - fm], [(b.sum() - b) / (P - 1) - fm]
    if with_floor and Pf > 1:
        fl = (f.sum() - f) / (Pf - 1)
        tops.append(a.mean() - fl)
        bottoms.append(b.mean() - fl)
    top, bottom = np.concatenate(tops), np.concatenate(bottoms)
    with np.errstate(all="ignore"):
        values = np.log(top) - np.log(bottom)
    return values[np.isfinite(values)]


def _log_ratio(a, b, f, lognormal: bool = False) -> np.ndarray:
    """log((m(a) - f) / (m(b) - f)) per row of a, b (R, P) and f (R, P_f) (its mean): m the sample mean, or
    the lognormal mean exp(mu + sigma^2 / 2) with mu the median of log v and sigma the spread of its upper
    half (84th percentile - median): the right tail carries the mean, while a left tail of states near 0
    would inflate the variance of log v without changing the mean. +-inf where one transient is not
    positive, NaN where neither is."""
    if lognormal:
        def m(v):
            mu, upper = np.quantile(np.log(v), [0.5, UPPER_SIGMA], axis=1)
            return np.exp(mu + (upper - mu) ** 2 / 2)
    else:
        m = lambda v: v.mean(axis=1)
    fm = f.mean(axis=1)
    top, bottom = m(a) - fm, m(b) - fm
    with np.errstate(all="ignore"):
        return np.log(np.clip(top, 0, None)) - np.log(np.clip(bottom, 0, None))   # +-inf, NaN if neither > 0


def at_rest_from(sq: np.ndarray, k_from: int, k_to: int, floor: Floor | None) -> int | None:
    """The first step in (k_from, k_to] at which the loop's mean square E||q_k||^2 (sq (K+1, P)) is below
    AT_REST times the floor's (its transient, the mean square less the floor's, below the floor itself);
    None when it stays above until k_to. A point estimate on purpose: the transient's uncertainty is the
    rate interval's (a resample whose transient is not positive opens its bound), and a significance
    test here would cut the window early wherever a few paths carry the mean square."""
    if floor is None:
        return None
    below = sq[k_from + 1:k_to + 1].mean(axis=1) < AT_REST * np.mean(floor.samples)
    return k_from + 1 + int(np.argmax(below)) if below.any() else None


def _decisive(interval: tuple[float, float, float]) -> bool:
    """An interval (rate, low, high) that lies below or above 1."""
    return interval[2] < 1 or interval[1] > 1


def paths_needed(rate: float, low: float, high: float, paths: int) -> int | None:
    """Paths at which an interval [low, high] around `rate` that contains 1 would shrink (as 1 / sqrt(P),
    about the rate) to exclude it, if the rate stayed: the side of the interval towards 1 decides (the
    interval need not be symmetric); None when the rate is 1 or not finite."""
    if not (np.isfinite(rate) and np.isfinite(low) and np.isfinite(high)) or rate == 1:
        return None
    distance = abs(np.log(rate))
    reach = np.log(high) - np.log(rate) if rate < 1 else np.log(rate) - np.log(low)     # towards 1: >= distance
    return int(np.ceil(paths * (reach / distance) ** 2))


def paired_losses(lost_a: np.ndarray, lost_b: np.ndarray) -> tuple[int, int, float]:
    """Whether loop a loses more paths than loop b, run on the same plant samples (path j of both draws
    the same coefficients), as an exact test, not a comparison of two counts.

    lost_a, lost_b (P,) bool. Returns (only_a, only_b, p): the paths lost by a alone and by b alone, and
    the one-sided p-value of the exact sign (McNemar) test, P(Bin(only_a + only_b, 1/2) >= only_a). Under
    "a loses a path no more often than b" each discordant path is a's with probability at most 1/2; paths
    both lose or both keep say nothing. p = 1 when no path is discordant. A path lost now and then by
    either loop makes the bare counts differ by chance (measured: docs/online.md); p says by how much.
    """
    lost_a, lost_b = np.asarray(lost_a, bool), np.asarray(lost_b, bool)
    if lost_a.shape != lost_b.shape or lost_a.ndim != 1:
        raise ValueError(f"paired_losses: lost_a {lost_a.shape} and lost_b {lost_b.shape}, expected two (P,) arrays")
    only_a, only_b = int(np.sum(lost_a & ~lost_b)), int(np.sum(lost_b & ~lost_a))
    return only_a, only_b, sign_test(only_a, only_b)


def sign_test(only_a: int, only_b: int) -> float:
    """`paired_losses`'s p from the discordant counts, P(Bin(only_a + only_b, 1/2) >= only_a) (1 if only_a = 0);
    the counts of independent runs (seeds) add up."""
    return float(binom.sf(only_a - 1, only_a + only_b, 0.5)) if only_a else 1.0


def judge_loop(sq: np.ndarray, *, failed_at: np.ndarray, failure: np.ndarray, window: tuple[int, int] | None,
               exact_rms: np.ndarray | None, floor: Floor | None, open_loop: bool = False,
               level: float = LEVEL) -> Verdict:
    """The verdict of one loop, from its paths' ||q_k||^2 sq (K+1, P) (NaN after a path failed).

    failed_at (P,) the step each path failed at (-1: never), failure (P,) why; window: the rate
    window (None: no window above the floor could be placed); exact_rms (K+1,): sqrt(E||x_k||^2) of the
    ideal loop (state feedback on the true plant; None: unknown); floor: the loop at rest (None: no floor,
    as for the open loop, whose observer does not act on the plant, or not measured); open_loop: a
    diverged plant state is then the plant's growth; level: of the rate intervals (the looks of
    closed_loop.paths auto share the 5% between them, `experiment.pipeline.loops.run_loops`)."""
    bad = failed_at >= 0
    if bad.any():
        reasons = {r: int(np.sum(failure[bad] == r)) for r in dict.fromkeys(failure[bad])}
        words = ", ".join(f"{FAILURES.get(r, r)} on {c}" for r, c in reasons.items())
        when = f"first at k = {failed_at[bad].min()}, median k = {np.median(failed_at[bad]):g}"
        if open_loop and "diverged" in reasons:
            # the open loop's observer does not act on the plant: an EnKF estimate that diverged beside plant
            # states that did is the EnKF tracking that growth, not a failure of the loop
            grown = failure[bad] == "diverged"
            also = "" if grown.all() else f"; the EnKF estimate failed on {100 * np.mean(~grown) * bad.mean():.3g}% " \
                                          f"({words}), its observer does not act on the plant"
            return Verdict("unstable", f"the uncontrolled plant grows: its state diverged on "
                                       f"{100 * grown.mean() * bad.mean():.3g}% of paths ({when}){also}")
        return Verdict("failed", f"{100 * bad.mean():.3g}% of paths failed ({when}): {words}")
    if floor is not None and floor.failed > 0:
        return Verdict("failed", f"the same loop started at rest (no disturbance) diverged on "
                                 f"{100 * floor.failed:.3g}% of its paths: it has no noise floor, the EnKF's noise "
                                 f"alone drives it away")
    if floor is not None and floor.growth[1] > 1:
        g = floor.growth
        return Verdict("unstable", f"the same loop started at rest (no disturbance) grows: its mean square's rate "
                                   f"over the second half of its horizon is {g[0]:.4f} [{g[1]:.4f}, {g[2]:.4f}] > 1, "
                                   f"so it has no noise floor and the loop grows", *g)
    if window is None:
        floor_rms = "not measured" if floor is None else f"{floor.rms:.3g}"
        return Verdict("undetermined", f"no window to measure a decay: after the disturbance, the ideal loop "
                                       f"({ABOVE_FLOOR:g} floors) and this loop ({2 * AT_FLOOR:g} floors) are not both "
                                       f"above the noise floor ({floor_rms}) for a step before the horizon")
    k_from, k_to = window
    # the plain rate over the window first: the floor adds relatively more to the smaller of the two mean
    # squares, so it only pulls the rate towards 1, and an interval that clears 1 without subtracting it is
    # evidence as it stands. Where it does not, the floor's mean square is subtracted and the window cut
    # where the loop is at rest (a loop that decayed onto its floor has decayed).
    plain = rate_interval(sq[k_from], sq[k_to], k_to - k_from, level=level)
    evidence = [(k_to, plain, f"k = {k_from}..{k_to}")]
    if floor is not None and not _decisive(plain):
        rest = at_rest_from(sq, k_from, k_to, floor)
        k_end = k_to if rest is None else rest - 1
        if k_end <= k_from:
            return Verdict("undetermined", f"the loop is at its noise floor ({floor.rms:.3g}) from k = {k_from + 1}: "
                                           f"no decay above it to measure", k_end=k_from, window_rate=plain)
        at_rest = "" if rest is None else f", at rest from k = {rest} (its mean square within {AT_REST:g} floors')"
        evidence.append((k_end, rate_interval(sq[k_from], sq[k_end], k_end - k_from, floor.samples, level),
                         f"k = {k_from}..{k_end}{at_rest}, the floor's mean square subtracted"))
    # the evidence that decides; where none does, the plain interval (the subtracted one is the wider)
    k_end, (rate, low, high), over = next((e for e in evidence if _decisive(e[1])), evidence[0])
    shown, percent = f"{rate:.4f} [{low:.4f}, {high:.4f}]", f"{100 * level:g}%"
    if not np.isfinite(rate):
        return Verdict("undetermined", "no rate: the state is 0 or not finite in the window", k_end=k_end,
                       window_rate=plain)
    exact = np.nan                         # the ideal loop over the verdict's steps and over the whole window
    if exact_rms is not None:
        with np.errstate(all="ignore"):
            exact = max((exact_rms[k] / exact_rms[k_from]) ** (1 / (k - k_from)) for k in (k_end, k_to))
    if high < 1:
        if exact >= 1:
            steps = f"k = {k_from}..{k_to}" if k_end == k_to else f"k = {k_from}..{k_end} or {k_from}..{k_to}"
            return Verdict("undetermined", f"these paths decay ({shown}, {over}) but the ideal loop's exact rate over "
                                           f"{steps} is {exact:.4f} >= 1: its mean square is carried by paths this "
                                           f"sample does not have", rate, low, high, k_end, plain)
        return Verdict("stable", f"the loop decays: the rate's {percent} interval [{low:.4f}, {high:.4f}] lies "
                                 f"below 1 ({over})", rate, low, high, k_end, plain)
    if low > 1:
        return Verdict("unstable", f"the loop grows: the rate's {percent} interval [{low:.4f}, {high:.4f}] lies "
                                   f"above 1 ({over})", rate, low, high, k_end, plain)
    need = paths_needed(rate, low, high, sq.shape[1])
    hint = f"; about {need} paths would separate this rate from 1" if need else ""
    return Verdict("undetermined", f"the rate's {percent} interval [{low:.4f}, {high:.4f}] contains 1 ({over}): "
                                   f"these paths show neither decay nor growth at {percent}{hint}", rate, low, high,
                   k_end, plain, need)
