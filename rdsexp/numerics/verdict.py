"""A loop's verdict from its Monte Carlo: stable, unstable, undetermined or failed.

The empirical rate of a loop, (E||q_{k_to}||^2 / E||q_{k_from}||^2)^(1/(2 (k_to - k_from))) with its
95% interval (`analysis.empirical_rate_sq`), says whether the loop decays only where the decay is
measurable:
- after the disturbance d_k has ended (the paper's window k = 60..80 starts 10 steps after its
  d_k ends at k = 50);
- above the loop's noise floor. The plant has no noise, but the loop u_k = F x_{k|k-1} feeds the
  EnKF's own noise (its Q, R and finite ensemble) back into the plant, so E||q_k||^2 stops decaying
  at a floor. Over a window at the floor the paths do not decay whatever the gain: a rate near 1
  there says nothing about the loop. The floor is measured, not guessed: E||q_k||^2 of the same
  loop started at rest (q_0 = 0, no disturbance), averaged over the second half of its horizon.

`place_window` derives the window from the exact curve sqrt(E||x_k||^2) of the ideal loop (state
feedback on the true plant, `analysis.second_moments`): from the end of the disturbance to the last
step at which that curve is still ABOVE_FLOOR times the floor. `loop_verdict` then reads the
evidence in a fixed order: failed paths, no measurable window, a window ending at the floor, the
interval against 1.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

VERDICTS = ("stable", "unstable", "undetermined", "failed")
ABOVE_FLOOR = 10.0    # a placed window ends where the ideal loop's RMS is still 10 floors (one decade) up
AT_FLOOR = 3.0        # a window whose empirical RMS at k_to is below 3 floors (the floor then makes
                      # more than 1/9 of E||q||^2) measures the floor, not the loop
# a path's failure reason (Trajectories.failure) in words
FAILURES = {"diverged": "the plant state diverged", "filter_diverged": "the EnKF estimate diverged",
            "singular_innovation": "the EnKF innovation covariance was singular"}


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
    """word: one of VERDICTS; reason: what it means, in words, from the evidence beside it."""

    word: str
    reason: str


def loop_verdict(interval: tuple[float, float, float], *, failed_at: np.ndarray, failure: np.ndarray,
                 window: tuple[int, int] | None, end_rms: float, floor_rms: float) -> Verdict:
    """The verdict of one loop.

    interval: (rate, low, high) over the window; failed_at (P,) the step each path failed at (-1:
    never) and failure (P,) why; window: the rate window (None: no window above the floor could be
    placed); end_rms: sqrt(E||q_{k_to}||^2) of the loop; floor_rms: the loop's noise floor (NaN: not
    measured, 0: none, as for the open loop, whose observer does not act on the plant; inf: the loop
    at rest diverged)."""
    bad = failed_at >= 0
    if bad.any():
        reasons = {r: int(np.sum(failure[bad] == r)) for r in dict.fromkeys(failure[bad])}
        words = ", ".join(f"{FAILURES.get(r, r)} on {c}" for r, c in reasons.items())
        return Verdict("failed", f"{100 * bad.mean():.0f}% of paths failed (first at k = {failed_at[bad].min()}, "
                                 f"median k = {np.median(failed_at[bad]):g}): {words}")
    if np.isinf(floor_rms):
        return Verdict("undetermined", "the same loop started at rest (no disturbance) diverged: it has no noise "
                                       "floor, and these paths' decay is not evidence that it is stable")
    if window is None:
        return Verdict("undetermined", f"no window to measure a decay: after the disturbance, the ideal loop "
                                       f"({ABOVE_FLOOR:g} floors) and this loop ({2 * AT_FLOOR:g} floors) are not both "
                                       f"above the noise floor ({floor_rms:.3g}) for a step before the horizon")
    rate, low, high = interval
    if np.isfinite(floor_rms) and floor_rms > 0 and not end_rms > AT_FLOOR * floor_rms:
        return Verdict("undetermined", f"the window ends at the noise floor: RMS {end_rms:.3g} at k = {window[1]} "
                                       f"is within {AT_FLOOR:g} times the floor {floor_rms:.3g} (the loop at rest), "
                                       f"so its rate there measures the EnKF's noise, not the loop")
    if not (np.isfinite(low) and np.isfinite(high)):
        return Verdict("undetermined", "no rate: the state is 0 or not finite in the window")
    if high < 1:
        return Verdict("stable", f"the loop decays: the rate's 95% interval [{low:.4f}, {high:.4f}] lies below 1")
    if low > 1:
        return Verdict("unstable", f"the loop grows: the rate's 95% interval [{low:.4f}, {high:.4f}] lies above 1")
    return Verdict("undetermined", f"the rate's 95% interval [{low:.4f}, {high:.4f}] contains 1: these paths "
                                   f"show neither decay nor growth at 95%")
