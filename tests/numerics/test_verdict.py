"""Loop verdicts and the automatic rate window on constructed cases (numerics/verdict.py)."""
import numpy as np
import pytest

from rdsexp.numerics.analysis import empirical_rate_sq
from rdsexp.numerics.verdict import ABOVE_FLOOR, AT_FLOOR, VERDICTS, loop_verdict, place_window, window_start

OK = dict(failed_at=np.full(400, -1), failure=np.full(400, "", dtype=object))


def paths(rate: float, K: int = 40, P: int = 400, floor: float = 0.0, seed: int = 0) -> np.ndarray:
    """||q_k||^2 (K+1, P) of paths decaying (or growing) at `rate` per step in RMS, with a lognormal
    spread across paths, plus a floor of mean square floor^2."""
    rng = np.random.default_rng(seed)
    scale = rng.lognormal(0, 0.3, P)
    k = np.arange(K + 1)[:, None]
    return scale * rate ** (2 * k) + floor ** 2 * rng.exponential(1.0, (K + 1, P))


def verdict_of(sq, window, floor):
    k_from, k_to = window
    interval = empirical_rate_sq(sq[k_from], sq[k_to], k_to - k_from)
    return loop_verdict(interval, **OK, window=window, end_rms=float(np.sqrt(sq[k_to].mean())), floor_rms=floor)


@pytest.mark.parametrize("rate, word", [(0.8, "stable"), (1.1, "unstable"), (1.0, "undetermined")])
def test_interval_decides_above_the_floor(rate, word):
    v = verdict_of(paths(rate), (5, 15), 0.0)
    assert v.word == word, v.reason
    assert ("below 1" in v.reason) == (word == "stable") and ("above 1" in v.reason) == (word == "unstable")


def test_a_window_at_the_noise_floor_is_undetermined():
    # a fast loop (rate 0.3) reaches the floor 1e-3 within ~6 steps: over k = 20..30 the paths sit at
    # the floor and their rate is ~1, which says nothing about the loop
    sq = paths(0.3, floor=1e-3)
    v = verdict_of(sq, (20, 30), 1e-3)
    assert v.word == "undetermined" and "noise floor" in v.reason
    # the same paths over a window above the floor: stable
    assert verdict_of(sq, (0, 3), 1e-3).word == "stable"
    # the floor check is a comparison with AT_FLOOR floors at k_to
    end = float(np.sqrt(sq[30].mean()))
    assert "noise floor" not in verdict_of(sq, (20, 30), end / (AT_FLOOR * 1.01)).reason
    assert "noise floor" in verdict_of(sq, (20, 30), end / (AT_FLOOR * 0.99)).reason


def test_failed_paths_give_failed_with_fraction_time_and_cause():
    failed_at = np.full(10, -1)
    failed_at[[2, 5, 7]] = [30, 12, 40]
    failure = np.full(10, "", dtype=object)
    failure[[2, 5, 7]] = ["diverged", "filter_diverged", "filter_diverged"]
    v = loop_verdict((0.5, 0.4, 0.6), failed_at=failed_at, failure=failure, window=(5, 10), end_rms=1.0,
                     floor_rms=0.0)
    assert v.word == "failed"
    assert v.reason == ("30% of paths failed (first at k = 12, median k = 30): the plant state diverged on 1, "
                        "the EnKF estimate diverged on 2")


def test_no_window_is_undetermined():
    v = loop_verdict((0.5, 0.4, 0.6), **OK, window=None, end_rms=1.0, floor_rms=0.1)
    assert v.word == "undetermined" and "no window" in v.reason
    # the loop at rest diverged (floor inf): whatever these paths did, undetermined, and no window placed
    v = loop_verdict((0.5, 0.4, 0.6), **OK, window=(5, 10), end_rms=1.0, floor_rms=float("inf"))
    assert v.word == "undetermined" and "at rest (no disturbance) diverged" in v.reason
    assert place_window(np.ones(20), 3, float("inf")) is None
    assert {"stable", "unstable", "undetermined", "failed"} == set(VERDICTS)


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
