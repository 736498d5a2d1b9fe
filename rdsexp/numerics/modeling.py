"""Distribution modeling of xi from an identification run (paper Sec. III-B, eq. sample-mean).

The plant is driven by a maximal-length sequence, the EnKF filters it, and the filtered ensemble
means xi_{k|k}, k = K0..K0+K1, are taken as samples of xi: their moments give the system model's
distribution (mean, covariance, second moment, Gbar, nbar).
"""
from __future__ import annotations

import numpy as np
import scipy.signal

from ..errors import one_line
from .synthesis.base import SynthesisResult
from .systems import MomentModel

LEVELS = ("bipolar", "unipolar")


def mls_input(horizon: int, m: int = 1, register_length: int = 7, amplitude: float = 1.0, *,
              levels: str = "bipolar", hold: int = 1, taps=None, state=None, seed=None) -> np.ndarray:
    """Maximal-length sequence input (paper Sec. V-A), shape (horizon+1, m).

    levels "bipolar": bits {0, 1} -> {-amplitude, +amplitude}; "unipolar": -> {0, amplitude} (a
    non-zero mean input). Each bit is held for `hold` steps. The shift register has
    `register_length` bits, feedback `taps` (None: scipy's default maximal taps; given taps are
    checked to produce a maximal sequence, period 2^register_length - 1) and initial `state`
    (register_length bits, not all 0; None: all ones). `seed` (int or SeedSequence) instead draws
    the initial state at random: a random phase of the same sequence, from its own stream.
    Input channel j uses the sequence shifted by j * period / m so that the channels are
    uncorrelated over a period.
    """
    if not 2 <= register_length <= 32:
        raise ValueError(f"register_length: {register_length}, allowed 2..32")
    if not (np.isfinite(amplitude) and amplitude > 0):
        raise ValueError(f"amplitude: {amplitude}, must be a positive number")
    if levels not in LEVELS:
        raise ValueError(f"levels: {levels!r}, allowed {', '.join(LEVELS)}")
    if not (isinstance(hold, (int, np.integer)) and hold >= 1):
        raise ValueError(f"hold: {hold!r}, must be an integer >= 1")
    if state is not None and seed is not None:
        raise ValueError("state, seed: give an initial register state or a seed to draw it, not both")
    if state is not None:
        state = np.asarray(state)
        if state.shape != (register_length,) or not np.all(np.isin(state, (0, 1))) or not state.any():
            raise ValueError(f"state: {state.tolist()}, expected {register_length} bits 0/1, not all 0")
    if seed is not None:
        rng = np.random.default_rng(seed)
        state = np.zeros(register_length, dtype=int)
        while not state.any():                      # the all-zero register is the one invalid state
            state = rng.integers(0, 2, register_length)
    period = 2 ** register_length - 1
    if taps is not None:
        taps = [int(t) for t in np.atleast_1d(taps)]
        if register_length > 20 or not all(0 < t < register_length for t in taps):
            raise ValueError(f"taps: {taps}, expected integers in 1..register_length-1 "
                             f"(custom taps for register_length <= 20)")
        full = scipy.signal.max_len_seq(register_length, state=state, taps=taps)[0].astype(float) * 2 - 1
        # an m-sequence is exactly the binary sequence whose circular autocorrelation is -1 at every lag != 0
        corr = np.fft.irfft(np.abs(np.fft.rfft(full)) ** 2, n=period)[1:]
        if not np.allclose(corr, -1, atol=1e-6):
            raise ValueError(f"taps: {taps} do not give a maximal-length sequence for register_length "
                             f"{register_length}")
    # one channel reads only the first bits (the register may be long); m > 1 shifts over a period
    length = period if m > 1 else min(period, horizon // hold + 1)
    seq = scipy.signal.max_len_seq(register_length, state=state, taps=taps, length=length)[0].astype(float)
    seq = seq * 2 - 1 if levels == "bipolar" else seq
    k = np.arange(horizon + 1) // hold                                  # bit index of step k
    return amplitude * np.stack([seq[(k + j * period // m) % seq.size] for j in range(m)], axis=1)


COVARIANCES = ("sample", "total")   # the modeled covariance: eq. (sample-mean), or plus the mean filtered covariance


def window_samples(xi_filt_mean: np.ndarray, K0: int, K1: int) -> np.ndarray:
    """xi_{k|k} for k = K0..K0+K1: (K+1, ..., p) -> (K1+1, ..., p)."""
    K = xi_filt_mean.shape[0] - 1
    if K0 < 0 or K1 < 0 or K0 + K1 > K:
        raise ValueError(f"K0, K1: window {K0}..{K0 + K1} must lie within the horizon 0..{K}")
    return xi_filt_mean[K0:K0 + K1 + 1]


def model_distribution(xi_filt_mean: np.ndarray, K0: int, K1: int,
                       xi_filt_cov: np.ndarray | None = None) -> MomentModel:
    """The modeled distribution of xi from one path's xi_{k|k} (K+1, p), eq. (sample-mean).

    With xi_filt_cov (K+1, p, p), the EnKF's filtered covariance of xi at each k, the covariance is
    the law of total variance, Cov(xi) = Cov_k(E[xi_k | Y_k]) + E_k[Cov(xi_k | Y_k)]: eq. (sample-mean)'s
    covariance of the filtered means plus the mean filtered covariance over the window. The filtered
    mean of a per-step xi is shrunk toward its prediction wherever the outputs tell little about
    xi_k (one output, several xi), so the first term alone underestimates the spread.

    Several paths, xi_filt_mean (K+1, P, p) (and xi_filt_cov (K+1, P, p, p)): the window's estimates of
    every path pooled (paths of one law of xi); P = 1 gives the one path's moments bit for bit."""
    xi = window_samples(xi_filt_mean, K0, K1)
    p, samples = xi.shape[-1], int(np.prod(xi.shape[:-1]))     # (not -1: p = 0, a model without xi, is allowed)
    model = MomentModel.from_samples(xi.reshape(samples, p))
    if xi_filt_cov is None:
        return model
    cov = window_samples(xi_filt_cov, K0, K1).reshape(samples, p, p)
    return MomentModel(mean=model.mean, cov=model.cov + cov.mean(axis=0))


def path_moments(xi_filt_mean: np.ndarray, K0: int, K1: int,
                 xi_filt_cov: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each path's own `model_distribution`: xi_filt_mean (K+1, P, p) (and xi_filt_cov (K+1, P, p, p)) ->
    means (P, p) and covariances (P, p, p) over the path's window K0..K0+K1 (1/N, plus the mean filtered
    covariance with xi_filt_cov). NaN where a path's window is not finite (its estimate failed)."""
    xi = window_samples(xi_filt_mean, K0, K1)                            # (T, P, p)
    mean = time_mean(xi)
    dev = xi - mean
    cov = time_mean(dev[..., :, None] * dev[..., None, :])
    if xi_filt_cov is not None:
        cov += time_mean(window_samples(xi_filt_cov, K0, K1))
    return mean, cov


def time_mean(a: np.ndarray) -> np.ndarray:
    """The mean over axis 0 (steps) of a (T, ...) array, each element's sum in the same order whatever the other
    axes' sizes: numpy sums a contiguous axis pairwise and a strided one in sequence, so a plain mean over steps
    rounds differently for one path than for many."""
    return np.ascontiguousarray(np.moveaxis(a, 0, -1)).mean(axis=-1)


def correlations(cov: np.ndarray) -> np.ndarray:
    """(..., p (p - 1) / 2): the correlation of each pair (i, j), i > j, in np.tril_indices(p, -1)'s order, of the
    covariances (..., p, p); 0 beside a component of no spread."""
    i, j = np.tril_indices(cov.shape[-1], -1)
    std = np.sqrt(np.clip(np.diagonal(cov, axis1=-2, axis2=-1), 0, None))
    scale = std[..., i] * std[..., j]
    return np.where(scale > 0, cov[..., i, j] / np.where(scale > 0, scale, 1.0), 0.0)


def correlation_z(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P,): Fisher's z, artanh r, of the uncentered correlation r of a and b, each (T, P), over the steps: nearer
    normal than r, as the synthetic likelihood assumes. As 0.5 log(|a^ + b^|^2 / |a^ - b^|^2) (a^ = a / |a|), so
    that an r near 1 (a slow output's lag-1 correlation, 1 - r down to 1e-15) keeps its digits; within +-20 (r = 1 in
    floating point), NaN where a or b is identically 0."""
    with np.errstate(divide="ignore", invalid="ignore"):
        a, b = a / np.sqrt(time_mean(a ** 2)), b / np.sqrt(time_mean(b ** 2))
        return np.clip(0.5 * np.log(time_mean((a + b) ** 2) / time_mean((a - b) ** 2)), -20.0, 20.0)


def block_bootstrap_steps(T: int, resamples: int, block: int, seed) -> np.ndarray:
    """(resamples, T) indices into a window of T estimates: each row a moving-block bootstrap resample,
    ceil(T / L) blocks of L = min(block, T) consecutive indices with uniform starts, cut to T (xi_{k|k}
    are correlated in k, so single steps would understate the spread). From default_rng(seed)."""
    L = min(block, T)
    starts = np.random.default_rng(seed).integers(0, T - L + 1, size=(resamples, -(-T // L)))
    return (starts[..., None] + np.arange(L)).reshape(resamples, -1)[:, :T]


def moment_draws(xi_filt_mean: np.ndarray, K0: int, K1: int, xi_filt_cov: np.ndarray | None = None, *,
                 resamples: int, block: int, seed=0) -> tuple[np.ndarray, np.ndarray]:
    """The modeled moments' uncertainty: `model_distribution` of `resamples` moving-block bootstrap
    resamples of the window K0..K0+K1 (`block_bootstrap_steps`), as means (B, p) and covariances
    (B, p, p) (1/N, plus the resampled mean filtered covariance with xi_filt_cov (K+1, p, p))."""
    xi = window_samples(xi_filt_mean, K0, K1)                            # (T, p)
    steps = block_bootstrap_steps(xi.shape[0], resamples, block, seed)
    draws = xi[steps]                                                    # (B, T, p)
    mean = draws.mean(axis=1)
    dev = draws - mean[:, None]
    cov = np.einsum("btp,btq->bpq", dev, dev) / xi.shape[0]
    if xi_filt_cov is not None:
        cov += window_samples(xi_filt_cov, K0, K1)[steps].mean(axis=1)
    return mean, cov


def nominal_gain(model, xi_guess, cov=None) -> SynthesisResult:
    """A stabilizing gain for the model at the nominal guess xi = xi_guess (p,) (prior knowledge).

    Used to identify an open-loop unstable plant under feedback, u_k = F x_{k|k-1} + d_k, and as the
    online loop's first gain. The guess says nothing about the spread of xi, so the design wants a
    stability margin rather than the fastest rate at the guess (Theorem 2 on a deterministic model is
    often near dead-beat, which a small deviation of xi destabilises): LQR with unit weights on
    A(xi_guess), B(xi_guess) first, Theorem 2 at the guess if the Riccati equation has no solution.
    With cov (p, p), a spread about the guess (the online loop's start, `EnKF.start_cov`), the
    mean-square LQR at N(xi_guess, cov) comes before them: a gain that spread does not destabilise,
    where one exists. Returns the first design whose exact rate on its law (the guess, or N(xi_guess,
    cov)) is < 1, else the last one tried (status says why); never raises.
    """
    from .synthesis import synthesize  # synthesis imports systems only; no cycle
    guess = MomentModel.deterministic(xi_guess)
    designs = [(guess, "lqr_mean"), (guess, "proposed")]
    if cov is not None:
        spread = MomentModel(mean=np.asarray(xi_guess, dtype=float), cov=np.asarray(cov, dtype=float))
        designs.insert(0, (spread, "ms_lqr"))
    result = None
    for law, method in designs:
        try:
            result = synthesize(model, law, method)
        except (ValueError, np.linalg.LinAlgError) as err:
            result = SynthesisResult(method, None, float("nan"), f"failed: {one_line(err)}", nbar=0)
            continue
        if result.F is not None and np.all(np.isfinite(result.F)) and result.lam < 1:
            return result
    return result


def path_moment_draws(xi_filt_mean: np.ndarray, K0: int, K1: int, xi_filt_cov: np.ndarray | None = None, *,
                      resamples: int, seed=0) -> tuple[np.ndarray, np.ndarray]:
    """The modeled moments' uncertainty over P independent paths: `resamples` bootstrap resamples of
    the paths (P drawn with replacement, each with its whole window K0..K0+K1), each modeled as in
    `model_distribution` (pooled, 1/N), as means (B, p) and covariances (B, p, p).

    xi_filt_mean (K+1, P, p); xi_filt_cov (K+1, P, p, p) or None. Paths are independent, so resampling
    them keeps each path's correlation in k (no block length to choose). From default_rng(seed)."""
    xi = window_samples(xi_filt_mean, K0, K1)                            # (T, P, p)
    T, P, p = xi.shape
    picks = np.random.default_rng(seed).integers(0, P, size=(resamples, P))
    draws = xi[:, picks].transpose(1, 0, 2, 3).reshape(resamples, T * P, p)    # (B, T P, p)
    mean = draws.mean(axis=1)
    dev = draws - mean[:, None]
    cov = np.einsum("btp,btq->bpq", dev, dev) / (T * P)
    if xi_filt_cov is not None:
        cov += window_samples(xi_filt_cov, K0, K1)[:, picks].mean(axis=(0, 2))
    return mean, cov
