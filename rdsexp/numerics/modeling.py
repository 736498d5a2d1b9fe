"""Distribution modeling of xi from an identification run (paper Sec. III-B, eq. sample-mean).

The plant is driven by a maximal-length sequence, the EnKF filters it, and the filtered ensemble
means xi_{k|k}, k = K0..K0+K1, are taken as samples of xi: their moments give the system model's
distribution (mean, covariance, second moment, Gbar, nbar).
"""
from __future__ import annotations

import numpy as np
import scipy.signal

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
