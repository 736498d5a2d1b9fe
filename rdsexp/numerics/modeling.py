"""Distribution modeling of xi from an identification run (paper Sec. III-B, eq. sample-mean).

The plant is driven by a maximal-length sequence, the EnKF filters it, and the filtered ensemble
means xi_{k|k}, k = K0..K0+K1, are taken as samples of xi: their moments give the system model's
distribution (mean, covariance, second moment, Gbar, nbar).
"""
from __future__ import annotations

import numpy as np
import scipy.signal

from .synthesis.base import SynthesisResult
from .systems import MomentModel


def mls_input(horizon: int, m: int = 1, register_length: int = 7, amplitude: float = 1.0) -> np.ndarray:
    """Maximal-length sequence input, +-amplitude, shape (horizon+1, m).

    Period 2^register_length - 1; input channel j uses the sequence shifted by j * period / m so
    that the channels are uncorrelated over a period.
    """
    if not 2 <= register_length <= 32:
        raise ValueError(f"register_length: {register_length}, allowed 2..32")
    if not (np.isfinite(amplitude) and amplitude > 0):
        raise ValueError(f"amplitude: {amplitude}, must be a positive number")
    seq = scipy.signal.max_len_seq(register_length)[0].astype(float) * 2 - 1
    period = seq.size
    k = np.arange(horizon + 1)
    return amplitude * np.stack([seq[(k + j * period // m) % period] for j in range(m)], axis=1)


def window_samples(xi_filt_mean: np.ndarray, K0: int, K1: int) -> np.ndarray:
    """xi_{k|k} for k = K0..K0+K1: (K+1, ..., p) -> (K1+1, ..., p)."""
    K = xi_filt_mean.shape[0] - 1
    if K0 < 0 or K1 < 0 or K0 + K1 > K:
        raise ValueError(f"K0, K1: window {K0}..{K0 + K1} must lie within the horizon 0..{K}")
    return xi_filt_mean[K0:K0 + K1 + 1]


def model_distribution(xi_filt_mean: np.ndarray, K0: int, K1: int) -> MomentModel:
    """The modeled distribution of xi from one path's xi_{k|k} (K+1, p), eq. (sample-mean)."""
    return MomentModel.from_samples(window_samples(xi_filt_mean, K0, K1))


def nominal_gain(model, xi_guess) -> SynthesisResult:
    """A stabilizing gain for the model at the nominal guess xi = xi_guess (p,) (prior knowledge).

    Used to identify an open-loop unstable plant under feedback, u_k = F x_{k|k-1} + d_k. The guess
    says nothing about the spread of xi, so the design wants a stability margin rather than the
    fastest rate at the guess (Theorem 2 on a deterministic model is often near dead-beat, which a
    small deviation of xi destabilises): LQR with unit weights on A(xi_guess), B(xi_guess) first,
    Theorem 2 at the guess if the Riccati equation has no solution. Returns the first design whose
    exact rate at the guess is < 1, else the last one tried (status says why); never raises.
    """
    from .synthesis import synthesize  # synthesis imports systems only; no cycle
    guess = MomentModel.deterministic(xi_guess)
    result = None
    for method in ("lqr_mean", "proposed"):
        try:
            result = synthesize(model, guess, method)
        except (ValueError, np.linalg.LinAlgError) as err:
            result = SynthesisResult(method, None, float("nan"), f"failed: {one_line(err)}", nbar=0)
            continue
        if result.F is not None and np.all(np.isfinite(result.F)) and result.lam < 1:
            return result
    return result


def one_line(err: BaseException) -> str:
    """An exception as one line: its type and the first line of its message."""
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0] if text else ''}".rstrip(": ")
