"""Loop verdicts, rate intervals and the automatic rate window on constructed cases with known truth
(numerics/verdict.py)."""
import numpy as np
import pytest
from scipy.stats import binom

from rdsexp.numerics.verdict import (
    ABOVE_FLOOR,
    AT_FLOOR,
    AT_REST,
    HEAVY_TAIL,
    LEVEL,
    PAIRED_LEVEL,
    VERDICTS,
    Floor,
    asks_for_paths,
    at_rest_from,
    judge_at_looks,
    judge_loop,
    look_level,
    paired_losses,
    paths_needed,
    place_window,
    rate_interval,
    tail_index,
    window_start,
)

OK = dict(failed_at=np.full(400, -1), failure=np.full(400, "", dtype=object))


def paths(rate: float, K: int = 40, P: int = 400, floor: float = 0.0, seed: int = 0) -> np.ndarray:
    """||q_k||^2 (K+1, P) of paths decaying (or growing) at `rate` per step in RMS, with a lognormal
    spread across paths, plus a floor of mean square floor^2."""
    rng = np.random.default_rng(seed)
    scale = rng.lognormal(0, 0.3, P)
    k = np.arange(K + 1)[:, None]
    return scale * rate ** (2 * k) + floor ** 2 * rng.exponential(1.0, (K + 1, P))


def at_rest(floor: float, K: int = 40, P: int = 200, growth: float = 1.0, seed: int = 1) -> Floor:
    """The run at rest of a loop whose floor has mean square floor^2 (growing by `growth` per step in RMS)."""
    sq = floor ** 2 * np.random.default_rng(seed).exponential(1.0, (K + 1, P)) * growth ** (2 * np.arange(K + 1))[:, None]
    return Floor.of(sq, np.full(P, -1))


def judge(sq, window, floor=None, exact=None, **kw):
    P = sq.shape[1]
    settings = dict(failed_at=np.full(P, -1), failure=np.full(P, "", dtype=object)) | kw
    return judge_loop(sq, window=window, exact_rms=exact, floor=floor, **settings)


@pytest.mark.parametrize("rate, word", [(0.8, "stable"), (1.1, "unstable"), (1.0, "undetermined")])
def test_interval_decides_above_the_floor(rate, word):
    v = judge(paths(rate), (5, 15))
    assert v.word == word, v.reason
    assert ("below 1" in v.reason) == (word == "stable") and ("above 1" in v.reason) == (word == "unstable")
    assert v.k_end == 15 and v.low <= v.rate <= v.high


def scalar_paths(a_draws: np.ndarray, K: int) -> np.ndarray:
    """||x_k||^2 (K+1, P) of x_{k+1} = a_k x_k, x_0 = 1, from the draws a (K, P)."""
    return np.r_[np.ones((1, a_draws.shape[1])), np.cumprod(a_draws ** 2, axis=0)]


@pytest.mark.parametrize("law, P", [("student", 30), ("student", 200), ("bernoulli", 30), ("uniform", 100)])
@pytest.mark.slow
def test_interval_covers_the_exact_rate_of_a_heavy_tailed_scalar_system(law, P):
    """x_{k+1} = a_k x_k: exact mean-square rate sqrt(E a^2) over any window. a = 0.9 + 0.3 t_5 (heavy
    tails: t with 5 degrees of freedom, E a^2 = 0.81 + 0.09 * 5/3), a lossy actuator (1.25 w.p. 0.7, else
    0.3), a uniform on [0, 1.9]. Over 200 seeds the 95% interval must cover as often as a binomial(200,
    0.95) allows at its 0.1% quantile (the Monte Carlo error of the coverage itself)."""
    K, k_from, k_to, seeds = 30, 10, 30, 200
    draw = {"student": lambda g, s: 0.9 + 0.3 * g.standard_t(5, s),
            "bernoulli": lambda g, s: np.where(g.random(s) < 0.7, 1.25, 0.3),
            "uniform": lambda g, s: g.uniform(0.0, 1.9, s)}[law]
    exact = {"student": np.sqrt(0.81 + 0.09 * 5 / 3), "bernoulli": np.sqrt(1.25 ** 2 * 0.7 + 0.3 ** 2 * 0.3),
             "uniform": np.sqrt(1.9 ** 2 / 3)}[law]
    covered = 0
    for seed in range(seeds):
        sq = scalar_paths(draw(np.random.default_rng(seed), (K, P)), K)
        _, low, high = rate_interval(sq[k_from], sq[k_to], k_to - k_from)
        covered += low <= exact <= high
    assert covered >= binom.ppf(0.001, seeds, LEVEL), f"{covered} of {seeds}"


def test_interval_is_deterministic_and_needs_two_paths():
    sq = paths(0.9, P=50)
    assert rate_interval(sq[5], sq[15], 10) == rate_interval(sq[5].copy(), sq[15].copy(), 10)
    assert all(np.isnan(rate_interval(sq[5, :1], sq[15, :1], 10)))
    bad = sq[15].copy()
    bad[3] = np.inf
    assert all(np.isnan(rate_interval(sq[5], bad, 10)))


def test_a_loop_that_decays_to_its_floor_is_stable():
    """A fast loop (rate 0.3) reaches the floor 1e-3 within ~6 steps: over k = 0..30 it has decayed (the floor
    only pulls the plain rate towards 1, so its interval below 1 decides), where the previous rule called
    a window ending within 3 floors undetermined; a window that starts at the floor has nothing to measure."""
    sq = paths(0.3, floor=1e-3)
    v = judge(sq, (0, 30), at_rest(1e-3))
    assert v.word == "stable" and v.k_end == 30 and v.high < 1, v.reason
    assert v.window_rate == rate_interval(sq[0], sq[30], 30)
    v = judge(sq, (20, 30), at_rest(1e-3))
    assert v.word == "undetermined" and "noise floor" in v.reason and v.k_end == 20


def test_floor_is_subtracted_with_its_uncertainty():
    """Paths decaying at 0.9 onto a floor: the rate with the floor's mean square subtracted is near 0.9, while
    the plain ratio is pulled towards 1; the window is cut where the loop is at rest (mean square below
    AT_REST floors')."""
    sq = paths(0.9, K=40, P=2000, floor=0.05)
    floor = at_rest(0.05, P=2000)
    subtracted = rate_interval(sq[0], sq[25], 25, floor.samples)
    plain = rate_interval(sq[0], sq[25], 25)
    assert abs(subtracted[0] - 0.9) < abs(plain[0] - 0.9) and subtracted[1] < 0.9 < subtracted[2]
    rest = at_rest_from(sq, 0, 40, floor)
    f = np.mean(floor.samples)
    assert sq[rest].mean() < AT_REST * f <= sq[rest - 1].mean() and np.all(sq[1:rest].mean(axis=1) >= AT_REST * f)
    assert at_rest_from(sq, 0, 5, floor) is None and at_rest_from(sq, 0, 40, None) is None


def test_a_floor_that_grows_or_diverges_is_no_floor():
    sq = paths(0.8)
    grows = judge(sq, (5, 15), at_rest(0.01, growth=1.05))
    assert grows.word == "unstable" and "at rest" in grows.reason and grows.low > 1
    steady = at_rest(0.01)
    assert steady.growth[1] <= 1 <= steady.growth[2]
    diverged = Floor(samples=np.ones(10), growth=(1.0, 0.9, 1.1), failed=0.2)
    v = judge(sq, (5, 15), diverged)
    assert v.word == "failed" and "diverged on 20% of its paths" in v.reason and diverged.rms == np.inf
    # `holds` is what judge_loop reads as a floor: neither of these is one, a steady run at rest is
    assert steady.holds and not at_rest(0.01, growth=1.05).holds and not diverged.holds


def test_never_stable_beside_an_exact_rate_at_or_above_1():
    """Paths that decay while the ideal loop's exact curve grows over the same steps: undetermined."""
    sq = paths(0.8)
    K = sq.shape[0] - 1
    growing = 1.02 ** np.arange(K + 1)
    v = judge(sq, (5, 15), exact=growing)
    assert v.word == "undetermined" and "exact rate" in v.reason and "1.0200 >= 1" in v.reason
    assert judge(sq, (5, 15), exact=0.9 ** np.arange(K + 1)).word == "stable"
    assert judge(paths(1.1), (5, 15), exact=growing).word == "unstable"


def test_failed_paths_give_failed_with_fraction_time_and_cause():
    failed_at = np.full(10, -1)
    failed_at[[2, 5, 7]] = [30, 12, 40]
    failure = np.full(10, "", dtype=object)
    failure[[2, 5, 7]] = ["diverged", "filter_diverged", "filter_diverged"]
    v = judge(paths(0.5, P=10), (5, 10), failed_at=failed_at, failure=failure)
    assert v.word == "failed"
    assert v.reason == ("30% of paths failed (first at k = 12, median k = 30): the plant state diverged on 1, "
                        "the EnKF estimate diverged on 2")


def test_open_loop_paths_whose_plant_diverged_are_growth():
    failed_at = np.full(10, -1)
    failed_at[[1, 4]] = [60, 70]
    failure = np.full(10, "", dtype=object)
    failure[[1, 4]] = "diverged"
    v = judge(paths(1.1, P=10), (5, 10), failed_at=failed_at, failure=failure, open_loop=True)
    assert v.word == "unstable" and "diverged on 20% of paths" in v.reason
    failure[4] = "filter_diverged"          # the EnKF, which does not act on this loop's plant, failed first there
    v = judge(paths(1.1, P=10), (5, 10), failed_at=failed_at, failure=failure, open_loop=True)
    assert v.word == "unstable" and "diverged on 10% of paths" in v.reason and "EnKF estimate failed on 10%" in v.reason


def test_no_window_is_undetermined():
    v = judge(paths(0.5), None, at_rest(0.1))
    assert v.word == "undetermined" and "no window" in v.reason
    assert place_window(np.ones(20), 3, float("inf")) is None
    assert {"stable", "unstable", "undetermined", "failed"} == set(VERDICTS)


def test_undetermined_says_how_many_paths_would_decide():
    sq = paths(0.998, P=100, seed=3) * np.random.default_rng(4).lognormal(0, 0.3, (41, 100))
    v = judge(sq, (5, 15))
    assert v.word == "undetermined" and "paths would separate" in v.reason
    need = paths_needed(v.rate, v.low, v.high, 100)
    assert need > 100
    # the interval shrinks as 1/sqrt(P): at the paths it names, its side towards 1 reaches 1
    reach = np.log(v.high / v.rate) if v.rate < 1 else np.log(v.rate / v.low)
    assert abs(reach * np.sqrt(100 / need) - abs(np.log(v.rate))) < 1e-2 * reach
    # an asymmetric interval: the side towards 1 decides, never fewer paths than there are
    assert paths_needed(0.95, 0.5, 1.01, 100) > 100 and paths_needed(1.05, 0.99, 2.0, 100) > 100


def test_window_placed_after_the_disturbance_above_the_floor():
    K = 100
    exact = np.r_[np.full(50, 10.0), 10.0 * 0.8 ** np.arange(1, K - 48)]     # (K+1,): flat until k = 49
    d = np.zeros((K + 1, 2))
    d[:50] = 1.0
    start = window_start(d, n=3)
    assert start == 50
    floor = 1e-3
    k_from, k_to = place_window(exact, start, floor)
    assert k_from == 50
    # k_to: the last step with exact > ABOVE_FLOOR * floor, every step before it too
    assert exact[k_to] > ABOVE_FLOOR * floor >= exact[k_to + 1]
    # no floor measured: the whole rest of the horizon
    assert place_window(exact, start, float("nan")) == (50, K)
    # a floor above the curve at the start: no window; a disturbance until the horizon: none either
    assert place_window(exact, start, 1.0) is None
    assert place_window(exact, K, 0.0) is None
    # without a disturbance the window starts after n steps
    assert window_start(np.zeros((K + 1, 2)), n=3) == 3
    # the loop's own RMS ends the window where it comes within 2 AT_FLOOR floors, if earlier
    empirical = np.r_[np.full(50, 10.0), 10.0 * 0.6 ** np.arange(1, K - 48)]
    k_to_loop = place_window(exact, start, floor, empirical)[1]
    assert k_to_loop < k_to and empirical[k_to_loop] > 2 * AT_FLOOR * floor >= empirical[k_to_loop + 1]
    # a curve that is 0 (nothing excited) has no window
    assert place_window(np.zeros(K + 1), 3, 0.0) is None


def test_paired_losses_counts_the_discordant_paths_and_gives_the_exact_sign_test():
    """Only paths one loop alone lost count; p is the binomial tail sum P(Bin(b + c, 1/2) >= b), recomputed
    here term by term from the binomial coefficients; no discordant path (or none lost by a) is p = 1."""
    from math import comb
    rng = np.random.default_rng(3)
    for _ in range(50):
        a, b = rng.random(60) < rng.uniform(0, 0.3), rng.random(60) < rng.uniform(0, 0.3)
        only_a, only_b, p = paired_losses(a, b)
        assert (only_a, only_b) == (int(np.sum(a & ~b)), int(np.sum(b & ~a)))
        n = only_a + only_b
        expected = sum(comb(n, j) for j in range(only_a, n + 1)) / 2 ** n if only_a else 1.0
        assert p == pytest.approx(expected, rel=1e-12)
    both = np.array([True, True, False, False])
    assert paired_losses(both, both) == (0, 0, 1.0)
    assert paired_losses(np.array([1, 1, 1, 1, 1, 0], bool), np.zeros(6, bool)) == (5, 0, 1 / 32)
    with pytest.raises(ValueError, match="expected two"):
        paired_losses(np.zeros(5, bool), np.zeros(6, bool))           # not the same paths


@pytest.mark.parametrize("hazard", ["light", "heavy"])
def test_paired_losses_false_alarm_rate_and_power_measured_by_simulation(hazard):
    """Calibration of the paired test as rdsexp uses it (100 paths, a few lost): each path's plant sample sets a
    hazard shared by both loops (light: uniform; heavy: most paths safe, a few near-certain losses, as a heavy-tailed
    plant's), and each loop loses the path independently with it. With the same hazard for both loops
    ("loses no more") the test flags at most PAIRED_LEVEL of 4000 replications, up to 3 Monte Carlo standard
    errors (measured: 0.8% and 0.15%; the discrete test is conservative); where online loses one path in ten more
    (hazard + 0.1) it flags most of them (measured: 84% and 92%). The bare counts, the criterion the test
    replaces, call one loop worse than itself in about a third of the replications."""
    rng = np.random.default_rng(11)
    R, P = 4000, 100
    h = rng.uniform(0, 0.04, (R, P)) if hazard == "light" else np.where(rng.random((R, P)) < 0.03, 0.6, 0.002)
    off = rng.random((R, P)) < h
    same = rng.random((R, P)) < h
    worse = rng.random((R, P)) < np.minimum(h + 0.1, 1)
    flags = np.array([paired_losses(a, b)[2] < PAIRED_LEVEL for a, b in zip(same, off)])
    se = np.sqrt(PAIRED_LEVEL * (1 - PAIRED_LEVEL) / R)
    assert flags.mean() <= PAIRED_LEVEL + 3 * se
    assert np.mean(same.sum(1) > off.sum(1)) > 0.3                     # the bare counts' false alarms
    power = np.mean([paired_losses(a, b)[2] < PAIRED_LEVEL for a, b in zip(worse, off)])
    assert power > 0.75


def test_the_tail_index_recovers_a_pareto_shape_and_flags_a_few_paths_carrying_the_mean():
    """Generalized Pareto samples of 2,000 with shape k: the mean k-hat over 40 seeds within 3 of its standard
    errors of k (less PSIS's shrinkage toward 0.5, 10 / (n + 10) of the way); a mean square carried by 3 paths of
    200 is heavy (above HEAVY_TAIL), a lognormal of spread 0.5 is not."""
    from scipy.stats import genpareto

    from rdsexp.numerics.verdict import HEAVY_TAIL, tail_index
    for k in (0.2, 0.5, 0.9):
        est = np.array([tail_index(genpareto(c=k).rvs(size=2000, random_state=seed)) for seed in range(40)])
        n = np.ceil(3 * np.sqrt(2000))
        expected = (n * k + 10 * 0.5) / (n + 10)
        assert abs(est.mean() - expected) < 3 * est.std(ddof=1) / np.sqrt(40) + 0.02, (k, est.mean())
    rng = np.random.default_rng(0)
    few = rng.lognormal(0.0, 0.5, 200)
    few[:3] *= 1e3                                      # three paths carry most of the mean square
    assert tail_index(few) > HEAVY_TAIL > tail_index(rng.lognormal(0.0, 0.5, 200))
    assert np.isnan(tail_index(np.ones(50))) and np.isnan(tail_index(np.arange(10.0)))
    ties = np.repeat([1.0, 2.0, 40.0], [150, 45, 5])              # a discrete law's values: no tail to fit
    with np.errstate(all="raise"):
        assert np.isnan(tail_index(ties))


@pytest.mark.slow
def test_the_sequential_interval_covers_a_heavy_tailed_scalar_rate():
    """x+ = a_k x, a_k = 0.7 + 0.2 t_4 (Student's t with 4 degrees of freedom: a^2 has no variance), exact rate
    sqrt(E a^2) = sqrt(0.49 + 0.04 * 2) over any window: judged at looks of 20, 80 and 320 paths, each at
    1 - 5% / 3, stopping where the verdict asks for no more paths, the reported intervals hold the exact rate at
    least at the nominal 95% over 120 seeds (asserted above the 0.15% quantile of Bin(decisive, 0.95)), and the
    heavy tail makes most runs look again rather than stop at the pilot."""
    K, window, looks = 20, (4, 20), (20, 80, 320)
    truth = np.sqrt(0.7 ** 2 + 0.2 ** 2 * 4 / 2)
    hits, decisive, used = 0, 0, []
    for seed in range(120):
        a = 0.7 + 0.2 * np.random.default_rng(seed).standard_t(4, size=(K, looks[-1]))
        sq = np.concatenate([np.ones((1, looks[-1])), np.cumprod(a, axis=0) ** 2])
        v, P = judge_at_looks(sq, looks, True, failed_at=np.full(looks[-1], -1), failure=np.full(looks[-1], ""),
                              window=window, exact_rms=None, floor=None)
        used.append(P)
        if v.word in ("stable", "unstable"):
            decisive += 1
            hits += v.low <= truth <= v.high
            assert f"{100 * look_level(3):g}% interval" in v.reason
    assert decisive >= 110 and hits >= binom.ppf(0.0015, decisive, 0.95), (hits, decisive)
    assert used.count(20) < 40, used


def test_a_few_paths_carrying_the_mean_square_ask_for_more_paths():
    """A closed loop whose ||q||^2 at the window's end one path in 50 carries (90% of the mean square) is decisive
    on its interval but asks for more paths (its tail k-hat above HEAVY_TAIL); the same paths in an open loop do
    not (its intervals hold heavy tails, experiments/coverage.py), nor without the path; an undetermined verdict
    asks where its interval holds 1 and says how many paths would separate it."""
    rng = np.random.default_rng(3)
    P, window = 50, (0, 10)
    end = rng.lognormal(np.log(1e-3), 0.3, P)
    end[7] = 9 * end.sum()                          # one path: 90% of the mean square
    sq = np.vstack([np.ones(P)] * 10 + [end])
    v = judge_loop(sq, failed_at=np.full(P, -1), failure=np.full(P, ""), window=window, exact_rms=None, floor=None,
                   level=look_level(4))
    khat = tail_index(sq[-1])
    assert v.word == "stable" and khat > HEAVY_TAIL
    assert asks_for_paths(v.word, np.nan, khat, fed_back=True)
    assert not asks_for_paths(v.word, np.nan, khat, fed_back=False)
    light = np.delete(sq, 7, axis=1)
    assert not asks_for_paths("stable", np.nan, tail_index(light[-1]), fed_back=True)
    near = np.vstack([np.ones(P)] * 10 + [rng.lognormal(-0.5, 1, P)])      # E = 1: rate 1
    u = judge_loop(near, failed_at=np.full(P, -1), failure=np.full(P, ""), window=window, exact_rms=None, floor=None)
    assert u.word == "undetermined" and u.needs is not None and asks_for_paths(u.word, u.needs, np.nan, True)
    assert look_level(1) == LEVEL and look_level(4) == pytest.approx(0.9875)


def test_an_open_loop_whose_plant_diverged_grows_even_where_the_enkf_estimate_failed_first():
    """The open loop's observer does not act on the plant: 32 of 40 paths whose plant state diverged and 8 whose
    EnKF estimate did (tracking that growth) read unstable, the fractions in the reason; the EnKF failing alone,
    or any failure in a closed loop, reads failed."""
    sq = np.full((11, 40), np.nan)
    sq[:5] = 1.2 ** (2 * np.arange(5))[:, None]
    failed_at = np.full(40, 5)
    failure = np.array(["diverged"] * 32 + ["filter_diverged"] * 8, dtype=object)
    judge = lambda fail, **kw: judge_loop(sq, failed_at=failed_at, failure=fail, window=(0, 10), exact_rms=None,
                                          floor=None, **kw)
    v = judge(failure, open_loop=True)
    assert v.word == "unstable" and "state diverged on 80% of paths" in v.reason
    assert "EnKF estimate failed on 20%" in v.reason
    assert judge(np.full(40, "filter_diverged", dtype=object), open_loop=True).word == "failed"
    assert judge(failure).word == "failed"
