"""Classical designs on the mean (LTI) model that the paper compares with (Sec. V-B)."""
from __future__ import annotations

import numpy as np
import scipy.signal

from ..systems import AffineRandomSystem
from .base import SynthesisResult, designed, mean_model


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


def pole_placement(system, dist, *, poles=None):
    """Place the eigenvalues of A(mean) + B(mean) F at `poles` (n,) (complex poles in conjugate pairs).

    No poles, no design: status `not_applicable` (the paper's poles are `rdsexp.paper.poles`)."""
    if poles is None:
        return SynthesisResult("pole_placement", None, float("nan"), "not_applicable", nbar=1,
                               info={"reason": "no poles given"})
    poles = check_poles(poles, system)
    A, B = mean_model(system, dist)
    placed = scipy.signal.place_poles(A, B, poles.real if np.all(poles.imag == 0) else poles)
    return designed("pole_placement", system, dist, -placed.gain_matrix, poles=poles.tolist())


def random_pole_sets(rng: np.random.Generator, n: int, count: int) -> np.ndarray:
    """`count` random pole sets of size n strictly inside the unit disc, closed under conjugation: (count, n) complex.

    Each set draws its number c of conjugate pairs uniformly from 0..n//2; the pairs are
    r e^{+-i theta} with (r, theta) uniform in area on the open upper half disc (r = sqrt(U), theta ~
    U(0, pi)), the n - 2c real poles uniform on (-1, 1). Sorted by decreasing modulus within a set.
    With continuous draws every pole is simple, so any m >= 1 can place them.
    """
    if count < 0 or n < 1:
        raise ValueError(f"random_pole_sets: n = {n}, count = {count}; expected n >= 1, count >= 0")
    pairs = rng.integers(0, n // 2 + 1, size=count)                        # (count,)
    r = np.sqrt(rng.uniform(0.0, 1.0, size=(count, n // 2)))
    theta = rng.uniform(0.0, np.pi, size=(count, n // 2))
    real = rng.uniform(-1.0, 1.0, size=(count, n))
    out = np.empty((count, n), dtype=complex)
    for s in range(count):                     # a set's layout depends on its own number of pairs
        c = pairs[s]
        z = r[s, :c] * np.exp(1j * theta[s, :c])
        poles = np.concatenate([z, z.conj(), real[s, :n - 2 * c]])
        out[s] = poles[np.argsort(-np.abs(poles), kind="stable")]
    return out
