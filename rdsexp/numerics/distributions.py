"""Families of distributions of a plant's random parameters xi (Assumption 1: xi_k i.i.d.).

A plant draws its coefficients from a family; everything that needs moments (Gbar, nbar, exact
mean-square rates, synthesis) uses the family's exact mean and covariance as a `MomentModel`
(Theorem 2 depends on E[[1; xi][1; xi]^T] only), while the Monte Carlo samples the family itself.

- `MomentModel` (family `normal`): Gaussian with the given mean (p,) and covariance (p, p);
- `Uniform`: independent components uniform on [low_j, high_j];
- `Bernoulli`: independent 0/1 components, P(xi_j = 1) = prob_j (packet dropouts);
- `Discrete`: one of finitely many vectors values[i] (N, p) with probability probs[i].

Every family has `p`, `mean`, `cov`, `moments` (a MomentModel) and `sample(rng, size)` -> size + (p,).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .systems import MomentModel, _finite_array

FAMILIES = ("normal", "uniform", "bernoulli", "discrete")


def _vector(name: str, value) -> np.ndarray:
    """A finite float vector (a scalar counts as length 1), or a one-line ValueError."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a list of numbers, got {value!r}") from None
    return _finite_array(name, np.atleast_1d(arr), 1)


class _Family:
    """Moments from the family's exact mean and covariance."""

    @property
    def p(self) -> int:
        return self.mean.size

    @property
    def moments(self) -> MomentModel:
        """The exact first two moments as a MomentModel (what synthesis and analysis use)."""
        return MomentModel(mean=self.mean, cov=self.cov)

    # MomentModel's derived moments, so a family can stand wherever moments are read
    second_moment = property(lambda self: self.moments.second_moment)
    augmented_second_moment = property(lambda self: self.moments.augmented_second_moment)


@dataclass(frozen=True, eq=False)
class Uniform(_Family):
    """Independent xi_j ~ U[low_j, high_j]; low, high (p,) with low <= high."""

    low: np.ndarray
    high: np.ndarray

    def __post_init__(self):
        low, high = _vector("low", self.low), _vector("high", self.high)
        if low.shape != high.shape:
            raise ValueError(f"high: length {high.size} does not match low of length {low.size}")
        if np.any(low > high):
            raise ValueError(f"low, high: low {low.tolist()} must be <= high {high.tolist()} componentwise")
        object.__setattr__(self, "low", low)
        object.__setattr__(self, "high", high)

    mean = property(lambda self: (self.low + self.high) / 2)
    cov = property(lambda self: np.diag((self.high - self.low) ** 2 / 12))

    def sample(self, rng: np.random.Generator, size: tuple[int, ...]) -> np.ndarray:
        """Draws of shape size + (p,)."""
        return self.low + (self.high - self.low) * rng.random(tuple(size) + (self.p,))


@dataclass(frozen=True, eq=False)
class Bernoulli(_Family):
    """Independent xi_j in {0, 1} with P(xi_j = 1) = prob_j, prob (p,) in [0, 1]."""

    prob: np.ndarray

    def __post_init__(self):
        prob = _vector("prob", self.prob)
        if np.any((prob < 0) | (prob > 1)):
            raise ValueError(f"prob: {prob.tolist()} must lie in [0, 1]")
        object.__setattr__(self, "prob", prob)

    mean = property(lambda self: self.prob.copy())
    cov = property(lambda self: np.diag(self.prob * (1 - self.prob)))

    def sample(self, rng: np.random.Generator, size: tuple[int, ...]) -> np.ndarray:
        """Draws of shape size + (p,)."""
        return (rng.random(tuple(size) + (self.p,)) < self.prob).astype(float)


@dataclass(frozen=True, eq=False)
class Discrete(_Family):
    """xi = values[i] with probability probs[i]; values (N, p), probs (N,) >= 0 summing to 1."""

    values: np.ndarray
    probs: np.ndarray

    def __post_init__(self):
        try:
            values = np.asarray(self.values, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"values: expected a list of equal-length vectors, got {self.values!r}") from None
        values = _finite_array("values", values[:, None] if values.ndim == 1 else values, 2)   # p = 1: a list
        probs = _vector("probs", self.probs)
        if probs.shape != (values.shape[0],):
            raise ValueError(f"probs: length {probs.size}, expected one per row of values ({values.shape[0]})")
        if np.any(probs < 0) or not np.isclose(probs.sum(), 1.0, rtol=0, atol=1e-9):
            raise ValueError(f"probs: {probs.tolist()} must be >= 0 and sum to 1")
        object.__setattr__(self, "values", values)
        object.__setattr__(self, "probs", probs / probs.sum())

    mean = property(lambda self: self.probs @ self.values)

    @property
    def cov(self) -> np.ndarray:
        dev = self.values - self.mean
        return (dev.T * self.probs) @ dev

    def sample(self, rng: np.random.Generator, size: tuple[int, ...]) -> np.ndarray:
        """Draws of shape size + (p,)."""
        return self.values[rng.choice(self.probs.size, size=tuple(size), p=self.probs)]


def from_spec(spec: dict):
    """A family from {family: NAME, ...parameters}; family absent means `normal` {mean, cov}.

    One-line ValueError for an unknown family, missing or extra parameters or bad values."""
    if not isinstance(spec, dict):
        raise ValueError(f"{spec!r} is not allowed, expected a mapping {{family: ..., parameters}}")
    spec = dict(spec)
    family = spec.pop("family", "normal")
    params = {"normal": ("mean", "cov"), "uniform": ("low", "high"), "bernoulli": ("prob",),
              "discrete": ("values", "probs")}
    if family not in params:
        raise ValueError(f"family: {family!r} is not allowed, expected one of {', '.join(FAMILIES)}")
    if set(spec) != set(params[family]):
        raise ValueError(f"family {family} takes {{{', '.join(params[family])}}}, got {{{', '.join(spec)}}}")
    cls = {"normal": MomentModel, "uniform": Uniform, "bernoulli": Bernoulli, "discrete": Discrete}[family]
    return cls(**spec)
