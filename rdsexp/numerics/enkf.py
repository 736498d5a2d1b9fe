"""Ensemble Kalman filter on the augmented state psi = [x; xi] (paper Sec. III-A, III-B).

Simulation model (eqs. f-A-B, h-C-D): psi_k = [A(xi) x + B(xi) u; xi] + w_k, z_k = C(xi) x + D(xi) u + v_k,
w ~ N(0, Q), v ~ N(0, R). `predict` is eq. (state-pred2), `update` eqs. (output-pred2), (filtering)-(kalman-v).
Ensembles are arrays (..., M, width) with any leading batch axes (paths), width = n+p plus the optional parts
below (`EnKF.width`); every step is a few batched matrix products, never a loop over members. Noise comes in
as standard normal draws, so that the caller owns the random streams (one per path), and the filter keeps
nothing between calls: what one step hands to the next (the ensemble, the adaptive inflation's rho_{k-1}) is
passed in and returned.

Variants (`EnKF.variant`), batched the same way:
- "stochastic": the paper's, perturbed outputs (eq. output-pred2), K = U V^-1 (eqs. kalman-u, kalman-v);
- "etkf": the ensemble transform Kalman filter (Hunt, Kostelich & Szunyogh 2007), symmetric square root, no
  output perturbations, computed in the ny x ny eigenbasis of R^(-1/2) V_z R^(-1/2) (`_transform`);
- "enkf_n": the finite-size EnKF (Bocquet 2011; dual form of Bocquet, Raanes & Hannart 2015), the ETKF with the
  forecast anomalies scaled by lambda = sqrt((N-1) / zeta_a), one scalar problem per path (`enkf_n_zeta`):
  no inflation to tune.
Options, each for what a small ensemble or the random dynamics need:
- `inflation`: rho >= 1 on the forecast anomalies, or adaptive (`AdaptiveInflation`, Miyoshi 2011's innovation
  estimate smoothed in time); `relaxation`: RTPS (Whitaker & Hamill 2012);
- `xi_bounds`: analysed xi projected onto its box, as a coefficient outside its support is a plant that cannot
  occur and can make the estimate diverge;
- `xi_prior`: xi_k drawn i.i.d. from known moments (Assumption 1) instead of the paper's random walk;
- `disturbance`: an unknown input disturbance d estimated in psi = [x; xi; d], not read as a wrong xi;
- `lag`: a fixed-lag smoother keeping past draws, for components of xi that reach an output only later;
- `static_mean`: the online controller's start, xi_k drawn about a static mean mu in psi that the outputs learn.
docs/enkf.md derives each (equations and why) and tells how the start's defaults were found.

Ensembles returned by `predict` and `update` are stored component-major: (..., M, width) views of
(width, ..., M) arrays, so each component of all paths and members is one contiguous block and the
elementwise work runs as single long loops instead of short strided ones over the numbers of each member.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .distributions import two_point, two_point_draw
from .systems import AffineRandomSystem, MomentModel, _finite_array, affine_apply

# an innovation covariance V with condition number above this is singular to working precision
# (1 / (45 eps)); a merely large spread of the outputs stays well below it
V_COND_LIMIT = 1e14
VARIANTS = ("stochastic", "etkf", "enkf_n")


def check_covariance(name: str, value, dim: int) -> np.ndarray:
    """A symmetric positive semidefinite (dim, dim) matrix from a scalar (times I), a diagonal of
    dim entries or a matrix; a one-line ValueError otherwise."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = arr * np.eye(dim)
    elif arr.ndim == 1 and arr.size == dim:
        arr = np.diag(arr)
    if arr.shape != (dim, dim):
        raise ValueError(f"{name}: shape {arr.shape} is not allowed, expected a scalar, {dim} diagonal entries "
                         f"or ({dim}, {dim})")
    arr = _finite_array(name, arr, 2)
    if not np.allclose(arr, arr.T, rtol=1e-9, atol=1e-12):
        raise ValueError(f"{name}: must be symmetric")
    if np.linalg.eigvalsh(arr).min() < -1e-10 * max(1.0, np.abs(arr).max()):
        raise ValueError(f"{name}: must be positive semidefinite")
    return (arr + arr.T) / 2


def sqrtm_psd(S: np.ndarray) -> np.ndarray:
    """Symmetric square root of PSD matrices S (..., n, n) (valid when S is singular)."""
    w, V = np.linalg.eigh(S)
    return (V * np.sqrt(np.clip(w, 0.0, None))[..., None, :]) @ V.swapaxes(-1, -2)


@dataclass(frozen=True)
class AdaptiveInflation:
    """Settings of the adaptive multiplicative inflation (docs/enkf.md): Miyoshi 2011's estimate of the
    covariance inflation from the innovation d = y - z_mean, Delta^o_k = (d^T d - tr R) / tr(V_z) (V_z the
    predicted outputs' sample covariance), smoothed as Delta_k = smoothing Delta_{k-1} + (1 - smoothing)
    Delta^o_k per path, rho_k = sqrt(Delta_k) kept in [low, high]. smoothing in [0, 1] (0: each step's own
    estimate; 1: rho stays at its start, 1 clipped to [low, high]); 0 < low <= high."""

    smoothing: float = 0.95
    low: float = 1.0
    high: float = 2.0

    def __post_init__(self):
        if not (_real(self.smoothing) and 0 <= self.smoothing <= 1):
            raise ValueError(f"smoothing: {self.smoothing!r} is not allowed, expected a number in [0, 1]")
        if not (_real(self.low) and self.low > 0):
            raise ValueError(f"low: {self.low!r} is not allowed, expected a finite number > 0")
        if not (_real(self.high) and self.high >= self.low):
            raise ValueError(f"high: {self.high!r} is not allowed, expected a finite number >= low = {self.low}")


class TwoPointLaws(NamedTuple):
    """The components an EnKF draws from their two-point law (`EnKF.xi_ends`), (p,) each: which (those with two
    distinct ends), their ends low and high (0 and 1 elsewhere), which of them the static-mean start draws so
    (start: those the next output sees, whose walk step is not 0) and that step's standard deviation sd."""

    which: np.ndarray
    low: np.ndarray
    high: np.ndarray
    start: np.ndarray
    sd: np.ndarray


@dataclass(frozen=True, eq=False)
class EnKF:
    """EnKF for `model`, process noise Q (n+p, n+p), output noise R (ny, ny) (docs/enkf.md).

    Q and R may be given as scalars (times I) or diagonals. variant: "stochastic" (the paper's,
    perturbed outputs), "etkf" or "enkf_n" (both need R positive definite); inflation: rho >= 1 of the
    forecast anomalies (1: none), or "adaptive" / an AdaptiveInflation (estimated per path); enkf_n
    estimates its own and takes none (1 only); relaxation alpha in [0, 1] to the prior spread (0: none);
    xi_bounds: None or (low, high) (p,) each, the box the xi part of analysed members is projected onto
    (+-inf: free); xi_prior: None (the random walk) or a MomentModel the predicted xi is drawn from i.i.d.;
    disturbance: None (off) or Q_d, the covariance (m, m) (a scalar times I, or m diagonal entries; not 0)
    of the random-walk increment of an unknown input disturbance estimated in psi = [x; xi; d];
    lag: steps each xi stays in the ensemble after its own, updated by later outputs (the fixed-lag
    smoother; 0: none); static_mean: paths without a per-path prior draw xi about a static mean in psi (the
    online loop's start; docs/enkf.md) rather than walk; start_spread: those draws are mu + start_spread w,
    w the xi part of the process noise (covariance start_spread^2 times Q's xi block); mean_spread: mu_0 ~
    N(initial xi, mean_spread^2 Q's xi block); start_scale: with static_mean, Q's xi block as the start uses it
    (mu_0's spread, the draws, the walked components' step) is start_scale times Q's; xi_ends: None or (p,)
    bool, the components whose law takes only the two ends of xi_bounds (`xi_ends(model, plant)`), which that
    start, and a path's own model, draw from their two-point law at the mean instead.
    """

    model: AffineRandomSystem
    Q: np.ndarray
    R: np.ndarray
    variant: str = "stochastic"
    inflation: float | str | AdaptiveInflation = 1.0
    relaxation: float = 0.0
    xi_bounds: tuple[np.ndarray, np.ndarray] | None = None
    xi_prior: MomentModel | None = None
    disturbance: np.ndarray | None = None
    lag: int = 0
    static_mean: bool = False
    start_spread: float = 1.0
    mean_spread: float = 1.0
    start_scale: float = 1.0
    xi_ends: np.ndarray | None = None

    def __post_init__(self):
        if self.xi_prior is not None:
            if self.xi_prior.p != self.model.p:
                raise ValueError(f"xi_prior: p = {self.xi_prior.p} does not match the model's p = {self.model.p}")
            object.__setattr__(self, "_xi_prior_sqrt", sqrtm_psd(self.xi_prior.cov))
        if self.xi_bounds is not None:
            low, high = (_finite_or_inf(name, b, self.model.p) for name, b in zip(("low", "high"), self.xi_bounds))
            if np.any(low > high):
                raise ValueError(f"xi_bounds: low {low.tolist()} must be <= high {high.tolist()} componentwise")
            object.__setattr__(self, "xi_bounds", None if np.all(np.isinf(low) & np.isinf(high)) else (low, high))
        object.__setattr__(self, "Q", check_covariance("Q", self.Q, self.dim))
        object.__setattr__(self, "R", check_covariance("R", self.R, self.model.ny))
        Q_full = self.Q
        if self.disturbance is not None:
            Q_d = check_covariance("disturbance", self.disturbance, self.model.m)
            if not Q_d.any():
                raise ValueError("disturbance: 0 is not allowed (a disturbance estimate that never moves from 0); "
                                 "expected a nonzero covariance, or None for no disturbance estimate")
            object.__setattr__(self, "disturbance", Q_d)
            Q_full = np.block([[self.Q, np.zeros((self.dim, self.model.m))],
                               [np.zeros((self.model.m, self.dim)), Q_d]])      # w = [w_x; w_xi; w_d]
        if not (isinstance(self.lag, (int, np.integer)) and not isinstance(self.lag, bool) and self.lag >= 0):
            raise ValueError(f"lag: {self.lag!r} is not allowed, expected an integer >= 0")
        if not isinstance(self.static_mean, (bool, np.bool_)):
            raise ValueError(f"static_mean: {self.static_mean!r} is not allowed, expected true or false")
        for name in ("start_spread", "mean_spread"):
            if not (_real(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{name}: {getattr(self, name)!r} is not allowed, expected a finite number > 0")
        if not (_real(self.start_scale) and 0 < self.start_scale <= 1):
            raise ValueError(f"start_scale: {self.start_scale!r} is not allowed, expected a number in (0, 1]")
        # components on the walk in the static-mean start: those the next output does not see
        object.__setattr__(self, "_walked", output_delay(self.model) > 0 if self.static_mean else None)
        # the start's w_xi scaled (p,): the walk's step on the walked components, start_spread on the drawn ones
        step = None if not self.static_mean else \
            np.sqrt(self.start_scale) * np.where(self._walked, 1.0, self.start_spread)
        object.__setattr__(self, "_start_step", step)
        object.__setattr__(self, "_ends", self._check_ends())
        lags = self.width - Q_full.shape[0]                            # mu and the past draws: no noise
        Q_full = np.block([[Q_full, np.zeros((len(Q_full), lags))], [np.zeros((lags, len(Q_full) + lags))]])
        object.__setattr__(self, "_Q_sqrt", sqrtm_psd(Q_full))
        object.__setattr__(self, "_R_sqrt", sqrtm_psd(self.R))
        if self.variant not in VARIANTS:
            raise ValueError(f"variant: {self.variant!r} is not allowed, expected one of {', '.join(VARIANTS)}")
        if isinstance(self.inflation, str) and self.inflation == "adaptive":
            object.__setattr__(self, "inflation", AdaptiveInflation())
        adaptive = isinstance(self.inflation, AdaptiveInflation)
        if not (adaptive or _real(self.inflation) and self.inflation >= 1):
            raise ValueError(f"inflation: {self.inflation!r} is not allowed, expected a finite number >= 1 or "
                             f"'adaptive'")
        if self.variant == "enkf_n" and (adaptive or self.inflation != 1):
            raise ValueError(f"inflation: {self.inflation!r} is not allowed with variant enkf_n, which estimates "
                             f"the prior's scale itself (Bocquet 2011); expected 1")
        object.__setattr__(self, "_rho", 1.0 if adaptive else self.inflation)   # of `_predict`
        if not (_real(self.relaxation) and 0 <= self.relaxation <= 1):
            raise ValueError(f"relaxation: {self.relaxation!r} is not allowed, expected a number in [0, 1]")
        if self.variant in ("etkf", "enkf_n"):
            w, E = np.linalg.eigh(self.R)
            if w.min() <= 1e-12 * max(w.max(), 1e-300):
                raise ValueError(f"R: must be positive definite for the {self.variant} variant (its transform "
                                 f"uses R^-1)")
            object.__setattr__(self, "_R_isqrt", (E / np.sqrt(w)) @ E.T)              # R^(-1/2), symmetric

    @property
    def output_noise_dim(self) -> int:
        """Standard normals per member and step for the output perturbations: ny (stochastic), 0 (etkf, enkf_n)."""
        return self.model.ny if self.variant == "stochastic" else 0

    @property
    def dim(self) -> int:
        """Dimension n + p of psi = [x; xi] (the paper's)."""
        return self.model.n + self.model.p

    @property
    def width(self) -> int:
        """The ensembles' last axis: n + p, plus m with the disturbance estimate [x; xi; d], plus p with the
        static mean [x; xi; d; mu], plus lag p with the smoother's past draws [...; xi_{k-1}; ...; xi_{k-lag}]."""
        return self.mu_slice.stop + self.lag * self.model.p

    @property
    def d_slice(self) -> slice:
        """Where psi holds the disturbance estimate d (empty without it)."""
        return slice(self.dim, self.dim + (self.model.m if self.disturbance is not None else 0))

    @property
    def mu_slice(self) -> slice:
        """Where psi holds the static mean mu of the start (empty without it)."""
        return slice(self.d_slice.stop, self.d_slice.stop + (self.model.p if self.static_mean else 0))

    @property
    def xi_estimate(self) -> slice:
        """Where psi holds the estimate of xi the online controller models from: xi itself, or with a lag the
        oldest past draw, xi_{k-1-lag} given y up to k (the fixed-lag smoother's estimate)."""
        p = self.model.p
        return slice(self.model.n, self.dim) if self.lag == 0 else slice(self.width - p, self.width)

    def split(self, psi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(x, xi) parts of psi (..., width), eqs. (psi-x-xi), (psi-x-xi-i)."""
        return psi[..., :self.model.n], psi[..., self.model.n:self.dim]

    def inputs(self, psi: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The input each member's model sees: u (..., m) as (..., 1, m), or u + d^(i) (..., M, m) with
        the disturbance estimate (psi (..., M, width))."""
        u = np.asarray(u)[..., None, :]
        return u if self.disturbance is None else u + psi[..., self.d_slice]

    def outputs(self, psi: np.ndarray, u: np.ndarray | None) -> np.ndarray:
        """Each member's predicted output without noise, z^(i) = C(xi) x + D(xi) (u + d), eq. (output-pred2)
        without v: psi (..., M, width), u (..., m) (None: D = 0) -> (..., M, ny), a new array."""
        x, xi = self.split(psi)
        z = np.array(affine_apply(self.model.C, xi, x))
        if self.model.D.any() and u is not None:
            z += affine_apply(self.model.D, xi, self.inputs(psi, u))
        return z

    def predict(self, psi: np.ndarray, u: np.ndarray, e_w: np.ndarray) -> np.ndarray:
        """State prediction, eq. (state-pred2): psi_{k|k-1}^(i) = f(psi_{k-1|k-1}^(i), u_{k-1}) + w_k^(i).

        psi: (..., M, width) filtered ensemble, u: (..., m) input applied at k-1 (same for all members),
        e_w: (..., M, width) standard normal draws (w = Q^(1/2) e_w). Returns (..., M, width), component-major,
        its anomalies scaled by `inflation`.
        """
        return self._predict(psi, u, e_w, out=component_major(e_w.shape))

    def update(self, psi: np.ndarray, u: np.ndarray, y: np.ndarray, e_v: np.ndarray,
               psi_mean: np.ndarray | None = None, inflation: np.ndarray | None = None) -> Analysis:
        """Output prediction and filtering, eqs. (output-pred2), (filtering)-(kalman-v).

        psi: (..., M, width) predicted ensemble psi_{k|k-1}, u: (..., m) input at k, y: (..., ny)
        measured output, e_v: (..., M, ny) standard normal draws (v = R^(1/2) e_v; the etkf and enkf_n
        variants draw none: pass None), psi_mean: the ensemble mean (eq. state-pred1) if already computed.
        inflation: with adaptive inflation, rho_{k-1} (...,) of the previous update (its
        `Analysis.inflation`); None starts at 1 (clipped to [low, high]).
        Where the innovation covariance V_k is singular, `ok` is False and the ensemble is returned
        unfiltered (K_k = 0). The filtered ensemble is component-major.
        """
        work = component_major(psi.shape[:-1] + (self.width + self.model.ny + 1,))
        return self._update(psi, u, y, e_v, psi_mean, out=component_major(psi.shape), work=work, inflation=inflation)

    # `simulate` calls the two steps below with buffers it reuses at every step: allocating the
    # large arrays afresh costs a page fault per 4 kB once the allocator has returned them to the OS.

    def _predict(self, psi: np.ndarray, u: np.ndarray, e_w: np.ndarray, out: np.ndarray,
                 path_prior: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """`predict` into `out` (..., M, width), component-major, which must not overlap psi; returns out.

        path_prior: None, or per-path moments the predicted xi is drawn from i.i.d. (as `xi_prior` does for
        every path): (mean (P, p), square root of the covariance (P, p, p), active (P,) bool) for psi of
        shape (P, M, width); paths not active keep the EnKF's own model of xi (`_start`). The online
        controller's paths, each with its latest modeled moments (`OnlineController.observer_prior`)."""
        n, dim = self.model.n, self.dim
        x, xi = self.split(psi)
        np.matmul(self._Q_sqrt.T, e_w.swapaxes(-1, -2), out=out.swapaxes(-1, -2))    # w = Q^(1/2) e_w
        psi_next = components(out)
        walk = self.xi_prior is None and self.model.p > 0
        rest = slice(None)                      # the paths without a model of xi: all, unless path_prior has some
        if walk and path_prior is not None and path_prior[2].any():
            mean, sqrt, active = path_prior
            e = components(e_w)[n:dim][:, active]                                      # (p, A, M)
            draws = np.einsum("jil,ljm->ijm", sqrt[active], e) + mean[active].T[..., None]
            if self._ends is not None:
                # a component whose law its mean fixes (`xi_ends`): that two-point law at the modeled mean, from
                # the same e (xi = high if Phi(e) < P(high)), not a Gaussian of the modeled variance
                ends, low, high = (a.reshape(-1, 1, 1) for a in self.two_point)
                draws = np.where(ends, two_point_draw(e, mean[active].T[..., None], low, high), draws)
            if self.xi_bounds is not None:
                self._clip_xi(draws)
            psi_next[n:dim][:, active] = draws
            rest = ~active
        elif self.xi_prior is not None and self.model.p:        # Assumption 1 with the known moments:
            # xi_k drawn i.i.d. moves x_k to x_{k+1} and stays in the ensemble, so that the update with
            # y_{k+1} estimates the coefficient of the step that produced it
            np.matmul(self._xi_prior_sqrt, components(e_w)[n:dim].reshape(self.model.p, -1),
                      out=psi_next[n:dim].reshape(self.model.p, -1))     # a contiguous block: a view
            psi_next[n:dim] += self.xi_prior.mean.reshape((-1,) + (1,) * (psi_next.ndim - 1))
            if self._ends is not None:          # (`xi_ends`) the two-point law at the prior's mean, as above
                ends, low, high = (a.reshape((-1,) + (1,) * (psi_next.ndim - 1)) for a in self.two_point)
                mean = self.xi_prior.mean.reshape(ends.shape)
                psi_next[n:dim] = np.where(ends, two_point_draw(components(e_w)[n:dim], mean, low, high),
                                           psi_next[n:dim])
            if self.xi_bounds is not None:       # a Gaussian draw of moments also leaves the support
                self._clip_xi(psi_next[n:dim])
            xi = out[..., n:dim]
        if walk:
            moved = self._start(psi, psi_next, rest)
            xi = moved if isinstance(rest, slice) else np.where(rest[:, None, None], moved, out[..., n:dim])
        psi_next[:n] += components(affine_apply(self.model.A, xi, x))                 # eq. (f-A-B)
        psi_next[:n] += components(affine_apply(self.model.B, xi, self.inputs(psi, u)))   # B(xi) (u + d)
        if self.disturbance is not None:
            psi_next[self.d_slice] += components(psi[..., self.d_slice])               # d: random walk
        if self.static_mean:
            psi_next[self.mu_slice] = components(psi[..., self.mu_slice])             # mu: static
        if self.lag:                    # the smoother's past draws move down one slot, the latest enters
            p, first = self.model.p, self.mu_slice.stop
            psi_next[first:first + p] = components(psi[..., n:dim])
            psi_next[first + p:] = components(psi[..., first:self.width - p])
        if self._rho != 1:                          # rho (psi - mean) + mean; skipped at 1 (bit-identical)
            mean = components(ensemble_mean(out))[..., None]
            psi_next -= mean
            psi_next *= self._rho
            psi_next += mean
        return out

    def start_cov(self, P0_xi: np.ndarray) -> np.ndarray:
        """(p, p): the covariance of the first xi the start draws, xi_1 before any output, for an initial
        ensemble whose xi has covariance P0_xi (p, p) (docs/enkf.md). With the static mean, Q_xi scaled by
        c = start_scale: mu_0 ~ N(., c mean_spread^2 Q_xi) and the draw mu + sqrt(c) start_spread w_xi, so
        c (mean_spread^2 + start_spread^2) Q_xi; on the walk (every component without the static mean, those the
        next output does not see with it): xi_0 + sqrt(c) w_xi, so P0_xi + c Q_xi (c = 1 without the static mean).
        A two-point component gets its Gaussian stand-in here; its law's variance is fixed by its mean (`two_point`)."""
        Q = self.Q[self.model.n:self.dim, self.model.n:self.dim]
        if not self.static_mean:
            return Q + P0_xi
        walked, step = self._walked, self._start_step
        mean = self.start_scale * self.mean_spread ** 2 * np.outer(~walked, ~walked) * Q      # mu_0's spread
        return step[:, None] * Q * step[None, :] + mean + np.outer(walked, walked) * P0_xi

    @property
    def two_point(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(which (p,) bool, low (p,), high (p,)): the components drawn from their two-point law (`xi_ends` with
        two distinct ends) and those ends; None where there are none. The online controller models them so."""
        return None if self._ends is None else (self._ends.which, self._ends.low, self._ends.high)

    def _check_ends(self) -> TwoPointLaws | None:
        """`xi_ends` validated (one-line ValueError): None where no component is drawn from its two-point law."""
        if self.xi_ends is None:
            return None
        ends = np.asarray(self.xi_ends)
        if ends.shape != (self.model.p,) or ends.dtype != bool:
            raise ValueError(f"xi_ends: {self.xi_ends!r} is not allowed, expected p = {self.model.p} booleans")
        bounded = np.zeros(self.model.p, bool) if self.xi_bounds is None else \
            np.isfinite(self.xi_bounds[0]) & np.isfinite(self.xi_bounds[1])
        if np.any(ends & ~bounded):
            raise ValueError(f"xi_ends: component {int(np.flatnonzero(ends & ~bounded)[0])} has no finite xi_bounds, "
                             f"whose two ends its law would take")
        if not ends.any():
            return None
        low, high = self.xi_bounds
        ends = ends & (high > low)                                        # (a point: the box keeps it)
        sd = np.sqrt(np.diag(self.Q)[self.model.n:self.dim])
        start = ends & (sd > 0) & (~self._walked if self.static_mean else False)
        # elsewhere any finite numbers: the Gaussian draw is kept there
        return TwoPointLaws(ends, np.where(ends, low, 0.0), np.where(ends, high, 1.0), start, np.where(start, sd, 1.0))

    def _start(self, psi: np.ndarray, psi_next: np.ndarray, rest) -> np.ndarray:
        """The predicted xi of paths `rest` (a slice, or (P,) bool) that have no model of xi yet, added into
        psi_next's xi rows (p, ..., M) (components), which hold w: the random walk xi_{k|k} + w, or with the
        static mean xi_k = mu + w for the components the next output sees (docs/enkf.md). Returns the xi
        (..., M, p) that moves x: xi_{k|k} on the walk, the new draw about mu."""
        n, dim = self.model.n, self.dim
        xi = psi[..., n:dim]
        if not self.static_mean:
            psi_next[n:dim][:, rest] += components(xi)[:, rest]
            return xi
        shape = (-1,) + (1,) * (psi_next.ndim - 1)
        walked = self._walked.reshape(shape)
        w = draws = psi_next[n:dim][:, rest]
        if np.any(self._start_step != 1):                           # skipped at 1 (bit-identical): the draws'
            draws = draws * self._start_step.reshape(shape)                       # spread, not the walk's step
        about = components(np.where(self._walked, xi, psi[..., self.mu_slice]))[:, rest]
        draws = draws + about
        if self._ends is not None and self._ends.start.any():
            # a component whose law its mean fixes (`xi_ends`) is drawn from that two-point law about mu, from the
            # same w through its normal CDF (no other random numbers): xi = high if Phi(w / sd) < P(high)
            _, low, high, start, sd = (a.reshape(shape) for a in self._ends)
            draws = np.where(start, two_point_draw(w / sd, about, low, high), draws)
        if self.xi_bounds is not None:                  # draws about mu, like those of a model, stay in the box
            draws = np.where(walked, draws, self._clip_xi(draws.copy()))
        psi_next[n:dim][:, rest] = draws
        return np.where(self._walked, xi, np.moveaxis(psi_next[n:dim], 0, -1))

    def _update(self, psi: np.ndarray, u: np.ndarray, y: np.ndarray, e_v: np.ndarray,
                psi_mean: np.ndarray | None, out: np.ndarray, work: np.ndarray,
                inflation: np.ndarray | None = None) -> Analysis:
        """`update` with the filtered ensemble written into `out` (..., M, width) and `work`
        (..., M, width+ny+1) as scratch, both component-major; neither may overlap psi. inflation: as in
        `update`, rho_{k-1} (...,) that the caller carries from the previous update (None: the start)."""
        d, ny, M = self.width, self.model.ny, psi.shape[-2]
        x, xi = self.split(psi)
        # the forecast anomalies are scaled per path before the analysis: by the EnKF-N's lambda or
        # the adaptive rho_k, both computed from the outputs without perturbations
        scaled = self.variant == "enkf_n" or isinstance(self.inflation, AdaptiveInflation)
        # rows [psi - psi_mean; z - z_mean; 1] of all members, as X (d+ny+1, ..., M) for the
        # elementwise work and as Xb (..., d+ny+1, M), a matrix per path, for the products: the
        # Gram matrix of Xb holds U and V, and one more product with it filters every member
        X = components(work)
        Xb = np.moveaxis(X, 0, -2)
        dpsi, dz = X[:d], X[d:-1]
        if self.variant == "stochastic" and not scaled:
            np.matmul(self._R_sqrt.T, e_v.swapaxes(-1, -2), out=Xb[..., d:-1, :])    # v = R^(1/2) e_v
            dz += components(affine_apply(self.model.C, xi, x))                        # eq. (output-pred2)
        else:
            dz[...] = components(affine_apply(self.model.C, xi, x))                    # no perturbation (yet)
        if self.model.D.any():
            dz += components(affine_apply(self.model.D, xi, self.inputs(psi, u)))     # D(xi) (u + d)
        psi_mean = ensemble_mean(psi) if psi_mean is None else psi_mean              # eq. (state-pred1)
        z_mean = ensemble_mean(np.moveaxis(dz, 0, -1))                                # eq. (output-pred1)
        dz -= components(z_mean)[..., None]
        np.subtract(components(psi), components(psi_mean)[..., None], out=dpsi)
        factor = None
        if scaled:
            factor = self._forecast_inflation(Xb[..., d:-1, :], y - z_mean, inflation)
            X[:-1] *= factor[..., None]
            if self.variant == "stochastic":     # z^(i) = h(psi^(i)) + v^(i) of the inflated members
                v = self._R_sqrt.T @ e_v.swapaxes(-1, -2)                              # (..., ny, M)
                v_mean = v.mean(axis=-1)
                Xb[..., d:-1, :] += v - v_mean[..., None]
                z_mean = z_mean + v_mean
        X[-1] = 1.0
        S = Xb[..., :-1, :] @ Xb[..., :-1, :].swapaxes(-1, -2) / (M - 1)   # sample covariance of [psi; z]
        cov_pred, U, V = S[..., :d, :d], S[..., :d, d:], S[..., d:, d:]    # eqs. (kalman-u), (kalman-v)
        if self.variant == "stochastic":
            lam = np.linalg.eigvalsh(V)                                    # V is symmetric PSD:
            ok = lam[..., 0] * V_COND_LIMIT > lam[..., -1]                 # cond(V) = lam_max / lam_min
            V = np.where(ok[..., None, None], V, np.eye(ny))
            K = np.linalg.solve(V, U.swapaxes(-1, -2)).swapaxes(-1, -2) * ok[..., None, None]   # eq. (kalman-gain)
            # eq. (filtering) for all members: psi + K (y - z) = psi + [-K, K (y - z_mean)] [dz; 1]
            coefficients = -K
        else:
            K, coefficients, ok = self._transform(U, V)
        correction = (K @ (y - z_mean)[..., None])[..., 0]                 # of the mean
        np.matmul(np.concatenate([coefficients, correction[..., None]], axis=-1), Xb[..., d:, :],
                  out=out.swapaxes(-1, -2))
        filtered = components(out)
        if scaled:                                   # mean + factor (psi - mean), the anomalies held in dpsi
            filtered += dpsi
            filtered += components(psi_mean)[..., None]
        else:
            filtered += components(psi)
        # moments of psi_{k|k} from the same products: psi_{k|k} - mean = dpsi - K dz, so its sample
        # covariance is Cov(psi_{k|k-1}) - U K^T (exactly, for the sample moments; for the etkf
        # Cov(psi_{k|k-1}) - U (V_z + R)^-1 U^T, the same expression with its K)
        var_pred = np.diagonal(cov_pred, axis1=-2, axis2=-1)
        pred_std = np.sqrt(np.clip(var_pred, 0, None))
        filt_mean = psi_mean + correction
        filt_std = np.sqrt(np.clip(var_pred - np.sum(U * K, axis=-1), 0, None))
        if self.relaxation:
            filt_std = self._relax(filtered, filt_mean, pred_std, filt_std)
        if self.xi_bounds is not None:
            filt_mean, filt_std = self._project(filtered, filt_mean, filt_std)
        return Analysis(psi=out, ok=ok, pred_mean=psi_mean, pred_std=pred_std, filt_mean=filt_mean, filt_std=filt_std,
                        inflation=factor)

    def _forecast_inflation(self, Y: np.ndarray, delta: np.ndarray, previous: np.ndarray | None) -> np.ndarray:
        """The factor (...,) on this update's forecast anomalies (docs/enkf.md): the EnKF-N's
        lambda = sqrt((N-1) / zeta_a) or the adaptive rho_k. Y: (..., ny, M) output anomalies without
        perturbations, delta = y - z_mean (..., ny); previous: rho_{k-1} (...,), or None at the start (1,
        clipped to [low, high]). Non-finite moments give 1 (enkf_n) or rho_{k-1} (adaptive)."""
        M = Y.shape[-1]
        finite = np.all(np.isfinite(Y), axis=(-2, -1)) & np.all(np.isfinite(delta), axis=-1)
        Y, delta = np.where(finite[..., None, None], Y, 0.0), np.where(finite[..., None], delta, 0.0)
        if self.variant == "enkf_n":
            mu, E = np.linalg.eigh(self._R_isqrt @ (Y @ Y.swapaxes(-1, -2)) @ self._R_isqrt)
            b = (E.swapaxes(-1, -2) @ (self._R_isqrt @ delta[..., None]))[..., 0]     # E^T R^(-1/2) delta
            zeta = enkf_n_zeta(np.clip(mu, 0.0, None), b * b, M)
            return np.where(finite, np.sqrt((M - 1) / zeta), 1.0)
        settings = self.inflation
        start = min(max(1.0, settings.low), settings.high)
        previous = np.broadcast_to(start if previous is None else previous, finite.shape)
        spread = path_sum(Y * Y, 2) / (M - 1)                                          # tr(V_z)
        with np.errstate(divide="ignore", invalid="ignore"):
            estimate = (path_sum(delta * delta, 1) - np.trace(self.R)) / spread        # Delta^o_k (Miyoshi 2011)
        a = settings.smoothing
        smoothed = a * previous ** 2 + (1 - a) * estimate
        keep = ~(finite & (spread > 0) & np.isfinite(smoothed))
        return np.sqrt(np.clip(np.where(keep, previous ** 2, smoothed), settings.low ** 2, settings.high ** 2))

    def _transform(self, U: np.ndarray, V_z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """ETKF: (K, L, ok) with K = U (V_z + R)^-1 (..., n+p, ny) for the mean and L (..., n+p, ny)
        with analysis anomalies dpsi + L dz = X (I + S^T S)^(-1/2) (docs/enkf.md), from the
        eigenpairs of S S^T = R^(-1/2) V_z R^(-1/2) (..., ny, ny). V_z + R is positive definite, so
        only non-finite moments make ok False (K = L = 0, the ensemble unfiltered)."""
        ok = np.all(np.isfinite(V_z), axis=(-2, -1)) & np.all(np.isfinite(U), axis=(-2, -1))
        V_z = np.where(ok[..., None, None], V_z, 0.0)
        lam, E = np.linalg.eigh(self._R_isqrt @ V_z @ self._R_isqrt)
        lam = np.clip(lam, 0.0, None)                                    # S S^T is PSD
        W = np.where(ok[..., None, None], U, 0.0) @ self._R_isqrt @ E   # U R^(-1/2) E
        Et = E.swapaxes(-1, -2) @ self._R_isqrt                          # E^T R^(-1/2)
        root = np.sqrt(1.0 + lam)[..., None, :]
        K = (W / (root * root)) @ Et
        L = (W * (-1.0 / (root * (1.0 + root)))) @ Et
        return K, L, ok

    def _relax(self, filtered: np.ndarray, mean: np.ndarray, pred_std: np.ndarray, filt_std: np.ndarray) -> np.ndarray:
        """RTPS in place on `filtered` (n+p, ..., M) (components) about its mean (..., n+p): anomalies
        scaled by (alpha sigma_f + (1 - alpha) sigma_a) / sigma_a per component; returns the new spread.
        A component without analysis spread stays as it is."""
        a = self.relaxation
        relaxed = a * pred_std + (1 - a) * filt_std
        scale = np.divide(relaxed, filt_std, out=np.ones_like(filt_std), where=filt_std > 0)
        centre = components(mean)[..., None]
        filtered -= centre
        filtered *= components(scale)[..., None]
        filtered += centre
        return np.where(filt_std > 0, relaxed, filt_std)


    def _clip_xi(self, xi: np.ndarray) -> np.ndarray:
        """Clip xi rows (p, ...) (components) onto xi_bounds in place; returns them."""
        shape = (-1,) + (1,) * (xi.ndim - 1)
        return np.clip(xi, self.xi_bounds[0].reshape(shape), self.xi_bounds[1].reshape(shape), out=xi)

    def _project(self, filtered: np.ndarray, mean: np.ndarray, std: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Clip the xi rows of `filtered` (width, ..., M) (components) onto xi_bounds in place, and the static
        mean's and the smoother's past draws; returns the filtered mean and spread (..., width) with those
        parts recomputed from the projected members."""
        p, first = self.model.p, self.mu_slice.stop
        mean, std = mean.copy(), std.copy()
        past = [slice(first + j * p, first + (j + 1) * p) for j in range(self.lag)]
        for rows in [slice(self.model.n, self.dim)] + [self.mu_slice] * self.static_mean + past:
            xi = self._clip_xi(filtered[rows])
            mean[..., rows] = np.moveaxis(xi.mean(axis=-1), 0, -1)
            std[..., rows] = np.moveaxis(xi.std(axis=-1, ddof=1), 0, -1)
        return mean, std


class Analysis(NamedTuple):
    """Result of one EnKF update: filtered ensemble (..., M, width), ok (...,), and the ensemble
    mean and spread (std over members, ddof 1) before (pred_*) and after (filt_*) filtering, (..., width)
    (width = n+p, plus m with the disturbance estimate, plus lag p with the smoother: EnKF.width).
    inflation: the factor (...,) this update scaled the forecast anomalies by (enkf_n: lambda;
    adaptive inflation: rho_k), None otherwise; pred_std is the spread after the scaling."""

    psi: np.ndarray
    ok: np.ndarray
    pred_mean: np.ndarray
    pred_std: np.ndarray
    filt_mean: np.ndarray
    filt_std: np.ndarray
    inflation: np.ndarray | None = None


def enkf_n_zeta(mu: np.ndarray, b2: np.ndarray, N: int, grid: int = 32, iterations: int = 40) -> np.ndarray:
    """zeta_a (...,) minimising the EnKF-N's dual cost D(zeta) over 0 < zeta <= N / eps_N (docs/enkf.md;
    Bocquet, Raanes & Hannart 2015), for N members, the eigenvalues mu (..., ny) >= 0 of
    R^(-1/2) Y Y^T R^(-1/2) and b2 (..., ny), the squares of b = E^T R^(-1/2) delta.

    In t = ln zeta, 2 dD/dt = g(t) = sum_i b_i^2 mu_i zeta / (zeta + mu_i)^2 + eps_N zeta - N. As
    mu zeta / (zeta + mu)^2 <= min(zeta / mu, 1/4), g < 0 below zeta_lo = max(N / (eps_N + sum b^2 / mu),
    (N - sum b^2 / 4) / eps_N), and g(N / eps_N) >= 0: every minimum lies in [zeta_lo, N / eps_N]. D is
    not always convex (two minima when the innovation is far outside the forecast spread), so it is
    evaluated on a log grid of `grid` points there, and the two lowest local minima of the grid are
    refined: Newton steps on g(t) within the neighbouring grid points, bisecting whenever a step leaves
    that bracket (at most `iterations`, all paths at once, each candidate until its own step is below
    1e-14 in t, then left as it is); the lower of the two is zeta_a."""
    eps = 1.0 + 1.0 / N
    top = N / eps
    mu, b2 = mu[..., None, :], b2[..., None, :]                                     # (..., 1, ny)
    ratio = np.divide(b2, mu, out=np.zeros_like(mu), where=mu > 0).sum(axis=-1)
    with np.errstate(over="ignore"):
        low = np.maximum(N / (eps + ratio), (N - b2.sum(axis=-1) / 4) / eps)
    low = np.clip(low, top * 1e-30, top)
    cost = lambda t: 0.5 * np.sum(np.exp(t)[..., None] * b2 / (np.exp(t)[..., None] + mu), axis=-1) \
        + 0.5 * eps * np.exp(t) - 0.5 * N * t                                                # D + const
    ts = np.linspace(np.log(low), np.full_like(low, np.log(top)), grid, axis=-1)[..., 0, :]   # (..., grid)
    values = cost(ts)
    padded = np.concatenate([values[..., :1] + 1, values, values[..., -1:] + 1], axis=-1)
    local = (values <= padded[..., :-2]) & (values <= padded[..., 2:])            # a grid point below its neighbours
    order = np.argsort(np.where(local, values, np.inf), axis=-1)
    j = order[..., :2]                                                                 # (..., 2) candidates
    j[..., 1] = np.where(local.sum(axis=-1) > 1, j[..., 1], j[..., 0])                 # one minimum: twice
    left = np.take_along_axis(ts, np.maximum(j - 1, 0), axis=-1)
    right = np.take_along_axis(ts, np.minimum(j + 1, grid - 1), axis=-1)
    t = np.take_along_axis(ts, j, axis=-1)
    # each candidate stops at its own convergence and is frozen there: a path's zeta never depends on
    # how many steps the other paths of its batch needed (the same bytes for any batch or chunk)
    active = np.ones(t.shape, dtype=bool)
    for _ in range(iterations):
        z = np.exp(t)
        q = z[..., None] + mu
        terms = b2 * mu * z[..., None] / (q * q)
        g = np.sum(terms, axis=-1) + eps * z - N
        slope = np.sum(terms * (mu - z[..., None]) / q, axis=-1) + eps * z
        below = g < 0
        left, right = np.where(below, t, left), np.where(below, right, t)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = t - g / slope
        step = np.where((slope > 0) & (step >= left) & (step <= right), step, 0.5 * (left + right))
        converged = np.abs(step - t) <= 1e-14 * np.maximum(1.0, np.abs(t))
        t = np.where(active, step, t)
        active &= ~converged
        if not active.any():
            break
    best = np.argmin(cost(t), axis=-1)[..., None]
    return np.exp(np.take_along_axis(t, best, axis=-1)[..., 0])


def path_sum(a: np.ndarray, axes: int) -> np.ndarray:
    """Sum of a (..., *last `axes` axes*) over its last `axes` axes -> (...), in one order for every
    batch: numpy's order follows the memory layout (a batch of one path is contiguous and summed
    pairwise, a strided batch row by row), so the summands are first laid out contiguously per path."""
    return np.ascontiguousarray(a).reshape(a.shape[:a.ndim - axes] + (-1,)).sum(axis=-1)


def components(a: np.ndarray) -> np.ndarray:
    """View (c, ...) of an array (..., c): elementwise work in this orientation runs in the memory
    order of component-major arrays (numpy picks a slower one when an operand is broadcast)."""
    return np.moveaxis(a, -1, 0)


def component_major(shape: tuple[int, ...]) -> np.ndarray:
    """An uninitialised array of `shape` (..., M, d), stored component-major: a view of a (d, ..., M) array."""
    return np.moveaxis(np.empty(shape[-1:] + shape[:-1]), 0, -1)


def ensemble_mean(a: np.ndarray) -> np.ndarray:
    """Mean over the member axis: (..., M, d) -> (..., d), as one batched matrix-vector product."""
    M = a.shape[-2]
    return (np.full((1, M), 1.0 / M) @ a)[..., 0, :]


def truth_map(model: AffineRandomSystem, plant: AffineRandomSystem, rtol: float = 1e-9):
    """The affine map xi = T s + t under which `model` equals `plant` for every plant parameter s,
    as (T (p, p_plant), t (p,)), or None when there is none or it is not unique.

    Solves model_0 + sum_i t_i model_i = plant_0 and sum_i T_ij model_i = plant_j for the stacked
    basis matrices [A; B; C; D] (least squares, then checked to hold to rtol). For the paper's plant
    and model it gives xi = [0.7 s1, s2, 0.6] (eq. sysmodel-coef); for a model that is the plant, T = I."""
    if (model.n, model.m, model.ny) != (plant.n, plant.m, plant.ny):
        return None
    stack = lambda sys: np.concatenate([M.reshape(sys.p + 1, -1) for M in (sys.A, sys.B, sys.C, sys.D)], axis=1)
    G, H = stack(model), stack(plant)                                  # (p+1, N), (p_plant+1, N)
    rhs = np.concatenate([(H[0] - G[0])[:, None], H[1:].T], axis=1)    # (N, 1 + p_plant)
    basis = G[1:].T                                                    # (N, p)
    if model.p and np.linalg.matrix_rank(basis) < model.p:
        return None                                                    # xi not determined by the matrices
    sol = np.linalg.lstsq(basis, rhs, rcond=None)[0] if model.p else np.zeros((0, rhs.shape[1]))
    if not np.allclose(basis @ sol, rhs, rtol=0, atol=rtol * max(1.0, np.abs(rhs).max(), np.abs(G).max())):
        return None
    return sol[:, 1:], sol[:, 0]


def xi_support(model: AffineRandomSystem, plant: AffineRandomSystem) -> tuple[np.ndarray, np.ndarray] | None:
    """The box (low, high) (p,) of the model's xi implied by the support of the plant's family
    (`plant.xi_dist.support`), for EnKF.xi_bounds; None without a family or a map xi = T s + t.

    A component xi_i = t_i + T_ij s_j of a single plant parameter lies in t_i + T_ij [low_j, high_j];
    a component of several parameters, or of none (a constant the model does not know is one, as
    the paper's xi3 = 0.6), is left free (+-inf): only what the plant file states bounds the filter."""
    truth = _one_parameter(model, plant)
    if truth is None:
        return None
    t, T, single, j = truth
    low_s, high_s = plant.xi_dist.support
    low, high = np.full(model.p, -np.inf), np.full(model.p, np.inf)
    for i in np.flatnonzero(single):
        ends = t[i] + T[i, j[i]] * np.array([low_s[j[i]], high_s[j[i]]])
        with np.errstate(invalid="ignore"):
            low[i], high[i] = np.nanmin(ends), np.nanmax(ends)
    return low, high


def xi_ends(model: AffineRandomSystem, plant: AffineRandomSystem) -> np.ndarray | None:
    """(p,) bool: the model's xi components whose law takes only the two ends of their `xi_support` box (one
    plant parameter each, of a Bernoulli or two-valued family: `distributions.two_point`), for EnKF.xi_ends;
    None where `xi_support` is None."""
    truth = _one_parameter(model, plant)
    if truth is None:
        return None
    _, _, single, j = truth
    ends = np.zeros(model.p, dtype=bool)
    ends[single] = two_point(plant.xi_dist)[j[single]]
    return ends


def _one_parameter(model: AffineRandomSystem, plant: AffineRandomSystem):
    """(t (p,), T (p, p_s), single (p,) bool, j (p,) int) of the map xi = T s + t (`truth_map`): the model's
    components that are one plant parameter each, s_j; None without a family or a map."""
    truth = truth_map(model, plant)
    if truth is None or plant.xi_dist is None:
        return None
    T, t = truth
    T = np.where(np.abs(T) > 1e-12 * max(np.abs(T).max(initial=0.0), 1e-300), T, 0.0)    # least-squares dust
    j = np.argmax(T != 0, axis=1) if T.size else np.zeros(len(T), dtype=int)
    return t, T, np.count_nonzero(T, axis=1) == 1, j


def output_delay(model: AffineRandomSystem) -> np.ndarray:
    """(p,) int: the steps j >= 0 after which xi_i, drawn at k, first reaches an output, y_{k+1+j}; -1 if never.

    xi_k moves x_{k+1} = A(xi_k) x_k + B(xi_k) u_k in the states where A_i or B_i has a nonzero row, and
    y_{k+1} = C(xi_k) x_{k+1} + D(xi_k) u_{k+1} directly with C_i or D_i nonzero (j = 0). Otherwise it reaches
    y_{k+1+j} where the states it moved reach a measured state in j steps of the dynamics (structurally:
    the nonzero pattern of A_0, ..., A_p; the inputs, which the filter is told, carry nothing of it). An EnKF
    that keeps xi_k `lag` more steps (EnKF.lag) learns it only if j <= lag."""
    n, p = model.n, model.p
    reach = np.any(model.A != 0, axis=0)                                    # (n, n): x_a at k+1 <- x_b at k
    measured = np.any(model.C != 0, axis=(0, 1))                            # (n,)
    out = np.full(p, -1)
    for i in range(p):
        moved = np.any(model.A[1 + i] != 0, axis=1) | np.any(model.B[1 + i] != 0, axis=1)
        if model.C[1 + i].any() or model.D[1 + i].any():
            out[i] = 0
            continue
        for j in range(n):
            if np.any(moved & measured):
                out[i] = j
                break
            moved = np.any(reach[:, moved], axis=1)
    return out


def _finite_or_inf(name: str, value, p: int) -> np.ndarray:
    """A (p,) float vector of finite numbers or +-inf (a scalar is broadcast); one-line ValueError otherwise."""
    arr = np.broadcast_to(np.asarray(value, dtype=float), (p,)).copy() if np.ndim(value) == 0 else \
        np.asarray(value, dtype=float)
    if arr.shape != (p,) or np.any(np.isnan(arr)):
        raise ValueError(f"xi_bounds: {name} {np.asarray(value).tolist()} is not allowed, expected p = {p} numbers "
                         f"(or +-inf)")
    return arr


def _real(value) -> bool:
    """A finite real number (not a bool)."""
    return isinstance(value, (int, float, np.floating, np.integer)) and not isinstance(value, bool) \
        and bool(np.isfinite(value))
