"""Classical designs on the mean (LTI) model that the paper compares with (Sec. V-B)."""
from __future__ import annotations

import numpy as np
import scipy.signal

from ..systems import AffineRandomSystem
from .base import designed, mean_model


def check_poles(poles, system: AffineRandomSystem) -> np.ndarray:
    """Poles as a complex (n,) array: strictly inside the unit disc, multiplicity at most m."""
    try:
        poles = np.asarray(poles, dtype=complex).ravel()
    except (TypeError, ValueError):
        raise ValueError(f"poles: {poles!r} is not a list of numbers") from None
    if poles.shape != (system.n,) or not np.all(np.isfinite(poles)):
        raise ValueError(f"poles: {poles.size} given, the system has n = {system.n} (finite values)")
    if np.any(np.abs(poles) >= 1):
        raise ValueError(f"poles: {np.round(poles.real, 6).tolist()} must lie strictly inside the unit disc")
    _, counts = np.unique(np.round(poles, 12), return_counts=True)
    if counts.max() > system.m:
        raise ValueError(f"poles: multiplicity {counts.max()} exceeds the number of inputs m = {system.m}")
    return poles


def pole_placement(system, dist, *, poles=(0.9, 0.8, 0.7, 0.6, 0.5, 0.4)):
    """Place the eigenvalues of A(mean) + B(mean) F at `poles` (complex poles in conjugate pairs)."""
    poles = check_poles(poles, system)
    A, B = mean_model(system, dist)
    placed = scipy.signal.place_poles(A, B, poles.real if np.all(poles.imag == 0) else poles)
    return designed("pole_placement", system, dist, -placed.gain_matrix, poles=poles.tolist())
