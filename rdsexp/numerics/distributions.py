"""Families of distributions of a plant's random parameters xi (Assumption 1: xi_k i.i.d.).

A plant draws its coefficients from a family; everything that needs moments (Gbar, nbar, exact
mean-square rates, synthesis) uses the family's exact mean and covariance as a `MomentModel`
(Theorem 2 depends on E[[1; xi][1; xi]^T] only), while the Monte Carlo samples the family itself.

- `MomentModel` (family `normal`): Gaussian with the given mean (p,) and covariance (p, p);
- `Uniform`: independent components uniform on [low_j, high_j];
- `Bernoulli`: independent 0/1 components, P(xi_j = 1) = prob_j (packet dropouts);
- `Discrete`: one of finitely many vectors values[i] (N, p) with probability probs[i];
- `Independent`: xi = [xi^(1); ...; xi^(c)], independent blocks each drawn from its own family
  (any of these, nested `independent` included), e.g. a bernoulli dropout beside a uniform gain.

Every family has `p`, `mean`, `cov`, `moments` (a MomentModel), `sample(rng, size)` -> size + (p,)
and `support` -> (low (p,), high (p,)), the smallest box containing the support (+-inf if unbounded);
`two_point` says which components take only that box's two ends.
`expected_crps` scores a modeled Gaussian against draws of the true distribution (a proper score).
`PathLaws` gives every simulated path a law of its own (the replicates of `numerics.indirect`); `sample_paths`
draws any family's coefficients path by path.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from .systems import MomentModel, _finite_array

FAMILIES = ("normal", "uniform", "bernoulli", "discrete", "independent")


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
    support = property(lambda self: (self.low.copy(), self.high.copy()))

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
    # [0, 1] whatever prob: the box is the family's, so it does not jump when prob reaches 0 or 1
    support = property(lambda self: (np.zeros(self.p), np.ones(self.p)))

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
    support = property(lambda self: (self.values.min(axis=0), self.values.max(axis=0)))

    @property
    def cov(self) -> np.ndarray:
        dev = self.values - self.mean
        return (dev.T * self.probs) @ dev

    def sample(self, rng: np.random.Generator, size: tuple[int, ...]) -> np.ndarray:
        """Draws of shape size + (p,)."""
        return self.values[rng.choice(self.probs.size, size=tuple(size), p=self.probs)]


@dataclass(frozen=True, eq=False)
class Independent(_Family):
    """xi = [xi^(1); ...; xi^(c)] with independent blocks xi^(i) (p_i,), each from its own family.

    components: a non-empty sequence of families (Independent included); p = sum of p_i."""

    components: tuple

    def __post_init__(self):
        if not isinstance(self.components, (list, tuple)):
            raise ValueError(f"components: expected a list of families, got {self.components!r}")
        if not self.components:
            raise ValueError("components: an empty list is not allowed, expected at least one family")
        for i, c in enumerate(self.components):
            if not all(hasattr(c, name) for name in ("p", "mean", "cov", "sample", "support")):
                raise ValueError(f"components[{i}]: expected a distribution family, got {type(c).__name__}")
        object.__setattr__(self, "components", tuple(self.components))

    mean = property(lambda self: np.concatenate([c.mean for c in self.components]))

    @property
    def support(self) -> tuple[np.ndarray, np.ndarray]:
        """(low (p,), high (p,)): the components' boxes stacked (the product of boxes is a box)."""
        lows, highs = zip(*(c.support for c in self.components))
        return np.concatenate(lows), np.concatenate(highs)

    @property
    def cov(self) -> np.ndarray:
        """Block diagonal (p, p): independent blocks are uncorrelated."""
        ends = np.cumsum([c.p for c in self.components])
        cov = np.zeros((ends[-1], ends[-1]))
        for c, end in zip(self.components, ends):
            cov[end - c.p:end, end - c.p:end] = c.cov
        return cov

    def sample(self, rng: np.random.Generator, size: tuple[int, ...]) -> np.ndarray:
        """Draws of shape size + (p,), the components' in turn from the same generator (deterministic)."""
        return np.concatenate([c.sample(rng, size) for c in self.components], axis=-1)


def from_spec(spec: dict):
    """A family from {family: NAME, ...parameters}; family absent means `normal` {mean, cov}.

    `independent` takes {components: [spec, ...]}, each component parsed by from_spec itself.
    One-line ValueError for an unknown family, missing or extra parameters or bad values; errors
    inside a component name it, e.g. "components[1]: family uniform takes {low, high}, got {low}"."""
    if not isinstance(spec, dict):
        raise ValueError(f"{spec!r} is not allowed, expected a mapping {{family: ..., parameters}}")
    spec = dict(spec)
    family = spec.pop("family", "normal")
    params = {"normal": ("mean", "cov"), "uniform": ("low", "high"), "bernoulli": ("prob",),
              "discrete": ("values", "probs"), "independent": ("components",)}
    if family not in params:
        raise ValueError(f"family: {family!r} is not allowed, expected one of {', '.join(FAMILIES)}")
    if set(spec) != set(params[family]):
        raise ValueError(f"family {family} takes {{{', '.join(params[family])}}}, got {{{', '.join(spec)}}}")
    if family == "independent":
        return _independent(spec["components"])
    cls = {"normal": MomentModel, "uniform": Uniform, "bernoulli": Bernoulli, "discrete": Discrete}[family]
    return cls(**spec)


def _independent(specs) -> Independent:
    """`independent` from its list of component specs, each parsed by from_spec (errors name its index)."""
    if not isinstance(specs, (list, tuple)):
        raise ValueError(f"components: expected a list of family specs, got {specs!r}")
    parsed = []
    for i, spec in enumerate(specs):
        try:
            parsed.append(from_spec(spec))
        except ValueError as err:
            raise ValueError(f"components[{i}]: {err}") from None
    return Independent(parsed)          # an empty list is rejected there


SHAPES = ("normal", "uniform", "two_point")   # `PathLaws.shape`: a factor's law at mean 0 and variance 1


@dataclass(frozen=True, eq=False)
class PathLaws:
    """One law of xi per simulated path: path j draws xi_k = mean[j] + sqrt[j] z_k, z_k ~ N(0, I_q) from its own
    stream, except the components `ends` (p,) bool, which take the two-point law on {low, high} with that mean
    (`two_point_draw` of the same z, standardized). mean (P, p), sqrt (P, p, q); low, high (p,) (None: no such
    component). With `shape` (P, q), codes into SHAPES, each factor of z takes that law at mean 0 and variance 1
    (normal; uniform on +- sqrt(3); two-point, its high point with probability high_prob (P, q): a skewed law) from
    its normal draw, so the mean and covariance sqrt sqrt^T stay, and the laws of the components are the factors'
    mixtures (a component of `ends` still from the normal z). A plant with these laws simulates P paths exactly
    (`sample_paths`), not one path more."""

    mean: np.ndarray
    sqrt: np.ndarray
    ends: np.ndarray | None = None
    low: np.ndarray | None = None
    high: np.ndarray | None = None
    shape: np.ndarray | None = None
    high_prob: np.ndarray | None = None

    p = property(lambda self: self.mean.shape[1])

    def sample_paths(self, rngs: list, steps: int) -> np.ndarray:
        """(steps, P, p): path j's coefficients from rngs[j] (P generators, one per path)."""
        if len(rngs) != self.mean.shape[0]:
            raise ValueError(f"rngs: {len(rngs)} paths, these laws are of {self.mean.shape[0]}")
        z = np.stack([g.standard_normal((steps, self.sqrt.shape[2])) for g in rngs], axis=1)      # (steps, P, q)
        # elementwise products summed per row: each path's numbers whatever the other paths in the batch
        mix = lambda factors: (self.sqrt * factors[..., None, :]).sum(axis=-1)
        dev = mix(z)
        xi = self.mean + dev
        if self.shape is not None:
            u, q = ndtr(z), self.high_prob
            two_point = np.where(u < q, np.sqrt((1 - q) / q), -np.sqrt(q / (1 - q)))
            factors = np.select([self.shape == SHAPES.index("uniform"), self.shape == SHAPES.index("two_point")],
                                [np.sqrt(3) * (2 * u - 1), two_point], z)
            xi = self.mean + mix(factors)
        if self.ends is not None and self.ends.any():
            std = np.sqrt((self.sqrt ** 2).sum(axis=-1))                                   # (P, p)
            xi = np.where(self.ends, two_point_draw(dev / np.where(std > 0, std, 1.0), self.mean, self.low, self.high),
                          xi)
        return xi


def two_point_draw(z: np.ndarray, mean, low, high) -> np.ndarray:
    """Draws of the law on {low, high} with the given mean from standard normal z (broadcast): high where
    Phi(z) < P(high) = (mean - low) / (high - low), else low (`EnKF.xi_ends`)."""
    return np.where(ndtr(z) < (mean - low) / (high - low), high, low)


def sample_paths(dist, rngs: list, steps: int) -> np.ndarray:
    """(steps, P, p): each path's coefficients from its own generator (rngs, P of them): `PathLaws` by path, any
    other family the same law on every path."""
    if isinstance(dist, PathLaws):
        return dist.sample_paths(rngs, steps)
    return np.stack([dist.sample(g, (steps,)) for g in rngs], axis=1)


def two_point(dist) -> np.ndarray:
    """(p,) bool: the components whose law puts all its mass on the two ends of `support` (a Bernoulli; a
    discrete component of at most two values). Given its mean mu such a law is fixed:
    P(xi_j = high_j) = (mu_j - low_j) / (high_j - low_j)."""
    if isinstance(dist, Bernoulli):
        return np.ones(dist.p, dtype=bool)
    if isinstance(dist, Discrete):
        return np.array([np.unique(column).size <= 2 for column in dist.values.T])
    if isinstance(dist, Independent):
        return np.concatenate([two_point(c) for c in dist.components])
    return np.zeros(dist.p, dtype=bool)


def expected_crps(mean, std, draws) -> np.ndarray:
    """Expected CRPS of the Gaussian marginals N(mean_j, std_j^2) against draws (N, p) of the true xi: (p,).

    E_Y CRPS(N(mu, s^2), Y) = E|X - Y| - E|X - X'| / 2 (Gneiting & Raftery 2007, eq. 21) with X, X' ~
    N(mu, s^2): E|X - X'| = 2 s / sqrt(pi) and E|X - y| = s (z (2 Phi(z) - 1) + 2 phi(z)), z = (y - mu) / s,
    or |y - mu| where s = 0; the mean over the draws estimates E_Y. A proper score in xi's units: for each
    component it is smallest when the modeled marginal equals the true one (then the true xi's own spread
    E|Y - Y'| / 2 for a Gaussian truth, not 0), and it penalizes a wrong mean and a wrong spread alike."""
    mean, std, draws = np.asarray(mean, float), np.asarray(std, float), np.asarray(draws, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (draws - mean) / std
        gauss = std * (z * (2 * ndtr(z) - 1) + 2 * np.exp(-z ** 2 / 2) / np.sqrt(2 * np.pi)) - std / np.sqrt(np.pi)
    return np.where(std > 0, gauss, np.abs(draws - mean)).mean(axis=0)


def ensemble_crps(members, y) -> np.ndarray:
    """CRPS of the ensemble's empirical law against observations: members (..., M), y (...) -> (...).

    CRPS = E|X - y| - E|X - X'| / 2 over the M members (Gneiting & Raftery 2007, eq. 21, the empirical
    law itself); E|X - X'| = 2 / M^2 sum_i (2 i - M - 1) x_(i) from the sorted members, O(M log M)."""
    x = np.sort(np.asarray(members, float), axis=-1)
    y = np.asarray(y, float)
    M = x.shape[-1]
    weights = (2 * np.arange(1, M + 1) - M - 1) / M ** 2
    return np.abs(x - y[..., None]).mean(axis=-1) - (x * weights).sum(axis=-1)


def interval_hits(members, y, level: float) -> np.ndarray:
    """Whether y (...) lies in the central `level` interval of the members (..., M) (their empirical
    quantiles (1 - level) / 2 and (1 + level) / 2, linear interpolation): bool (...)."""
    low, high = np.quantile(np.asarray(members, float), [(1 - level) / 2, (1 + level) / 2], axis=-1)
    return (low <= y) & (y <= high)
