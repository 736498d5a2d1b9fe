"""Monte Carlo of the plant with the EnKF as observer (paper Sec. IV, Fig. wcontroller), batched over paths.

One step k, for all P paths at once (estimate="predicted", the paper):
    u_k = F x_{k|k-1} + d_k                  control input decision, eq. (sf-enkf), plus external input
    y_k = C(s_k) q_k + D(s_k) u_k            plant output
    psi_{k|k} = filter(psi_{k|k-1}, u_k, y_k)        output prediction + filtering
    q_{k+1} = A(s_k) q_k + B(s_k) u_k,  psi_{k+1|k} = predict(psi_{k|k}, u_k)
With estimate="filtered" (plant and model without D, so that y_k does not depend on u_k) the output
is filtered first and u_k = F x_{k|k} + d_k: the "current estimator" of digital control. The paper
uses x_{k|k-1} because with D the output depends on u_k; without D, x_{k|k-1} carries the error of
the unknown xi_{k-1} (A(xi_{k-1}) - E A) x_{k-1} into u_k, which feeds back multiplicatively.
F = 0 gives the open loop (and, with an M-sequence as d, the identification run).
F may be one gain (m, n) or one per path (P, m, n); a `controller` (e.g. the online, learning-type
controller of `online.py`) may change the per-path gains between steps k and k+1 from psi_{k|k}.

Randomness: path j of a run with root SeedSequence `seed` draws its plant coefficients from
SeedSequence(entropy, spawn_key=seed.spawn_key + (PLANT, j)), its EnKF noise from (..., (ENKF, j)) and,
where the plant has additive noise (`PlantNoise`), that noise from (..., (NOISE, j)). Results therefore do not
depend on how paths are batched or chunked.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from threadpoolctl import threadpool_limits

from .distributions import sample_paths
from .enkf import EnKF, check_covariance, component_major, ensemble_mean, sqrtm_psd
from .systems import AffineRandomSystem, _finite_array

PLANT, ENKF, NOISE = 0, 1, 2     # SeedSequence spawn-key slots per purpose
ESTIMATES = ("predicted", "filtered")   # the state estimate the feedback uses: x_{k|k-1} or x_{k|k}
DIVERGENCE_BOUND = 1e6        # |q| (or |ensemble mean|) beyond this marks a path (or its filter) diverged


def path_generators(seed, purpose: int, paths) -> list[np.random.Generator]:
    """One independent Generator per path index in `paths` for `purpose` (PLANT or ENKF)."""
    root = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    return [np.random.default_rng(np.random.SeedSequence(root.entropy, spawn_key=root.spawn_key + (purpose, int(j))))
            for j in paths]


@dataclass
class Trajectories:
    """Monte Carlo result; arrays are (K+1, P, dim) over steps k = 0..K and paths.

    q: plant state, y: output, u: input applied to the plant (F x_{k|k-1} + d_k, or F x_{k|k} + d_k),
    psi_pred_* / psi_filt_*: ensemble mean and spread (std over members, ddof 1) of psi_{k|k-1}
    and psi_{k|k}; split with `x(...)`/`xi(...)`. failed_at (P,): first step whose values are
    not kept (-1 if none); failure (P,): "" / "diverged" (the plant state) / "filter_diverged" (the
    EnKF mean only) / "singular_innovation". Values of a
    failed path from failed_at on are NaN. members: filtered ensembles (K+1, P, M, n+p) if kept;
    xi_filt_cov: the ensemble covariance (ddof 1) of the filtered xi, (K+1, P, p, p), if kept.
    s: the plant's coefficients (K+1, P, p_plant), s_k moving q_k to q_{k+1} (all steps drawn).
    gain_index (K+1, P): with a controller, how many gains path j had adopted before step k (0: the
    initial gain) -- the gain in use at k is that path's gain_index-th adopted one; None without.
    y_forecast: with keep_forecast, every member's predicted output z_k^(i) from psi_{k|k-1} without output
    noise (`EnKF.outputs`), (K+1, P, M, ny): the one-step-ahead predictive ensemble of y_k.
    d_filt_mean, d_filt_std: with the EnKF's disturbance estimate (EnKF.disturbance), the filtered
    ensemble's mean and spread of the unknown input disturbance d, (K+1, P, m); None without.
    """

    q: np.ndarray
    y: np.ndarray
    u: np.ndarray
    psi_pred_mean: np.ndarray
    psi_pred_std: np.ndarray
    psi_filt_mean: np.ndarray
    psi_filt_std: np.ndarray
    failed_at: np.ndarray
    failure: np.ndarray
    n: int
    members: np.ndarray | None = None
    xi_filt_cov: np.ndarray | None = None
    s: np.ndarray | None = None
    gain_index: np.ndarray | None = None
    d_filt_mean: np.ndarray | None = None
    d_filt_std: np.ndarray | None = None
    y_forecast: np.ndarray | None = None      # (K+1, P, M, ny) members' predicted outputs (keep_forecast)

    @property
    def status(self) -> str:
        """"ok", "partially_failed" or "failed" (every path)."""
        bad = self.failed_at >= 0
        return "ok" if not bad.any() else ("failed" if bad.all() else "partially_failed")

    def x(self, a: np.ndarray) -> np.ndarray:
        return a[..., :self.n]

    def xi(self, a: np.ndarray) -> np.ndarray:
        return a[..., self.n:]


class GainController(Protocol):
    """What `simulate` asks of a controller that changes the per-path gains during the loop."""

    needs_xi_cov: bool      # whether update wants the filtered xi covariance (else it gets None)

    def update(self, k: int, psi_filt_mean: np.ndarray, alive: np.ndarray,
               xi_filt_cov: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """After filtering at step k: psi_{k|k} means (P, n+p) (the xi part: `EnKF.xi_estimate`, smoothed with a
        lag), alive (P,) and that xi's filtered covariance (P, p, p) -> None (no change) or (paths (U,) int,
        gains (U, m, n)): the gains those paths use from step k+1 on. Optionally observer_prior() -> None or
        per-path moments the EnKF's prediction draws xi from (`EnKF._predict(path_prior=...)`), and
        excitation(k) -> None or a known input (m,) or (P, m) added to u_k (the EnKF is told it)."""


@dataclass(frozen=True)
class Recorded:
    """Recorded inputs and outputs of P paths over steps k = 0..K: u (K+1, P, m), y (K+1, P, ny).

    In place of the plant in `simulate` (recorded=...): the EnKF is told u_k and filters y_k, exactly
    as it is told and filters a simulated plant's, so a run replayed from its own record gives the same
    estimates bit for bit (same per-path EnKF streams and initial ensemble)."""

    u: np.ndarray
    y: np.ndarray

    def __post_init__(self):
        u, y = np.asarray(self.u, dtype=float), np.asarray(self.y, dtype=float)
        if u.ndim != 3 or y.ndim != 3 or u.shape[:2] != y.shape[:2]:
            raise ValueError(f"recorded: u {u.shape} and y {y.shape}, expected (K+1, P, m) and (K+1, P, ny)")
        if not (np.all(np.isfinite(u)) and np.all(np.isfinite(y))):
            raise ValueError("recorded: u and y must be finite")
        object.__setattr__(self, "u", u)
        object.__setattr__(self, "y", y)

    @property
    def steps(self) -> int:
        return self.u.shape[0]

    @property
    def paths(self) -> int:
        return self.u.shape[1]

    def select(self, paths) -> Recorded:
        """The recorded paths `paths` (indices or a slice), in that order."""
        return Recorded(self.u[:, paths], self.y[:, paths])


@dataclass(frozen=True)
class PlantNoise:
    """Additive noise on a simulated plant: q_{k+1} = A q_k + B u_k + w_k, y_k = C q_k + D u_k + v_k with
    w_k ~ N(0, W), v_k ~ N(0, V), i.i.d. in k. W (n, n) and V (ny, ny), or one per path (P, n, n), (P, ny, ny).
    rdsexp's plants are noise-free; recorded data are not, and the simulated estimator's replicates of a data run
    carry the noise the EnKF assumes, scaled per path (`pipeline.identification`)."""

    W: np.ndarray
    V: np.ndarray

    def draws(self, rngs: list, steps: int) -> tuple[np.ndarray, np.ndarray]:
        """(w (steps, P, n), v (steps, P, ny)): path j's noise from rngs[j] (NOISE streams), with elementwise
        products summed per row: each path's numbers whatever the other paths in the batch."""
        n = self.W.shape[-1]
        z = np.stack([g.standard_normal((steps, n + self.V.shape[-1])) for g in rngs], axis=1)
        # a factor (n, n) or one per path (P, n, n) broadcasts against z's (steps, P, 1, n) alike
        w = (sqrtm_psd(self.W) * z[..., None, :n]).sum(axis=-1)
        v = (sqrtm_psd(self.V) * z[..., None, n:]).sum(axis=-1)
        return w, v


class _PlantSource:
    """The simulated plant of `simulate`: coefficients s_k drawn per path (PLANT streams), state q_k, and the
    plant's additive noise (NOISE streams) if it has any."""

    def __init__(self, plant: AffineRandomSystem, q0, rngs, K: int, noise: PlantNoise | None = None,
                 noise_rngs: list | None = None):
        self.s = sample_paths(plant.xi_dist, rngs, K + 1)                              # (K+1, P, p_plant)
        self.A, self.B, self.C, self.D = plant.at(self.s)
        self.q = np.broadcast_to(q0, (len(rngs), plant.n)).copy()
        self.w = self.v = None
        if noise is not None:
            self.w, self.v = noise.draws(noise_rngs, K + 1)

    def stop(self, dead):
        self.q[dead] = 0.0                     # no overflow on failed paths

    def input(self, k, u):
        return u                                 # the decided input is applied

    def output(self, k, u=None):
        y = (self.C[k] @ self.q[..., None])[..., 0]
        y = y if u is None else y + (self.D[k] @ u[..., None])[..., 0]
        return y if self.v is None else y + self.v[k]

    def advance(self, k, u):
        self.q = (self.A[k] @ self.q[..., None])[..., 0] + (self.B[k] @ u[..., None])[..., 0]
        if self.w is not None:
            self.q += self.w[k]


class _RecordedSource:
    """Recorded (u_k, y_k) in place of the plant: no state (q is empty: nothing to diverge), the
    recorded input replaces the decided one."""

    s = None

    def __init__(self, recorded: Recorded):
        self.rec = recorded
        self.q = np.zeros((recorded.paths, 0))

    def stop(self, dead):
        pass

    def input(self, k, u):
        return self.rec.u[k]

    def output(self, k, u=None):
        return self.rec.y[k]

    def advance(self, k, u):
        pass


def check_estimate(plant: AffineRandomSystem | None, model: AffineRandomSystem, estimate: str) -> None:
    """One-line ValueError unless `estimate` (ESTIMATES) applies: "filtered" needs D = 0 in plant and model
    (plant None: recorded data, the model alone)."""
    if estimate not in ESTIMATES:
        raise ValueError(f"estimate: {estimate!r} is not allowed, expected one of {', '.join(ESTIMATES)}")
    if estimate == "filtered" and ((plant is not None and plant.D.any()) or model.D.any()):
        raise ValueError("estimate: 'filtered' needs D = 0 in the plant and the model (with D, y_k depends on "
                         "u_k, which would depend on y_k); use 'predicted'")


def check_settings(plant: AffineRandomSystem | None, enkf: EnKF, F, d, q0, psi0, P0, paths: int = 1,
                   estimate: str = "predicted", recorded: Recorded | None = None) -> tuple:
    """Validate and convert the simulation inputs; one-line ValueError naming the argument.

    recorded: the recorded (u, y) that replace the plant (plant None, F None, len(d) = recorded steps)."""
    model = enkf.model
    check_estimate(plant, model, estimate)
    if recorded is not None:
        if plant is not None or F is not None:
            raise ValueError("recorded: replaces the plant and its input: plant and F must be None")
        if recorded.paths != paths or recorded.steps != len(d):
            raise ValueError(f"recorded: {recorded.paths} paths x {recorded.steps} steps, expected paths = {paths} "
                             f"x len(d) = {len(d)}")
        if recorded.u.shape[2] != model.m or recorded.y.shape[2] != model.ny:
            raise ValueError(f"recorded: u has {recorded.u.shape[2]} and y {recorded.y.shape[2]} columns, the "
                             f"EnKF model's (m, ny) = {(model.m, model.ny)}")
        plant = model                     # the state's size only (q0), no coefficients are drawn
    elif plant is None:
        raise ValueError("plant: None is only allowed with recorded data")
    elif plant.xi_dist is None:
        raise ValueError("plant: needs xi_dist, the distribution its coefficients are drawn from")
    if (plant.n, plant.m, plant.ny) != (model.n, model.m, model.ny):
        raise ValueError(f"plant: (n, m, ny) = {(plant.n, plant.m, plant.ny)} does not match the "
                         f"EnKF model's {(model.n, model.m, model.ny)}")
    if F is not None and np.ndim(F) == 3:            # one gain per path
        F = _finite_array("F", F, 3)
        if F.shape != (paths, model.m, model.n):
            raise ValueError(f"F: shape {F.shape}, expected (m, n) = {(model.m, model.n)} or (paths, m, n) = "
                             f"{(paths, model.m, model.n)}")
    else:
        F = np.zeros((model.m, model.n)) if F is None else model.check_gain(F)
    d = np.asarray(d, dtype=float)
    if d.ndim == 3:                                  # one input sequence per path
        d = _finite_array("d", d, 3)
        if d.shape[1:] != (paths, model.m) or d.shape[0] < 1:
            raise ValueError(f"d: shape {d.shape}, expected (K+1, m = {model.m}) or (K+1, paths = {paths}, m)")
    else:
        d = _finite_array("d", d.reshape(len(d), -1), 2)
        if d.shape[1] != model.m or d.shape[0] < 1:
            raise ValueError(f"d: shape {d.shape}, expected (K+1, m = {model.m})")
    q0 = _finite_array("q0", q0, 1)
    if q0.shape != (plant.n,):
        raise ValueError(f"q0: length {q0.size}, expected n = {plant.n}")
    psi0 = _finite_array("psi0", psi0, 1)
    if psi0.shape != (enkf.dim,):
        raise ValueError(f"psi0: length {psi0.size}, expected n + p = {enkf.dim}")
    P0 = check_covariance("P0", 0.0 if P0 is None else P0, enkf.dim)
    return F, d, q0, psi0, P0


def simulate(plant: AffineRandomSystem | None, enkf: EnKF, *, F=None, d, q0, psi0, P0=None, ensemble_size: int,
             paths: int, seed, first_path: int = 0, filter_sees_d: bool = True, keep_members: bool = False,
             keep_xi_cov: bool = False, block: int = 16, bound: float = DIVERGENCE_BOUND, progress=None,
             controller: GainController | None = None, estimate: str = "predicted",
             recorded: Recorded | None = None, keep_forecast: bool = False,
             plant_noise: PlantNoise | None = None) -> Trajectories:
    """Closed loop (open loop when F is None) of `plant` observed by `enkf`, P = `paths` sample paths.

    d: (K+1, m) external input added on u_k, or one per path (K+1, P, m) (horizon K = len(d) - 1); q0: (n,)
    plant initial state; psi0, P0: mean (n+p,) and covariance of the initial ensemble psi_{0|-1} (P0 = 0: every member
    at psi0, as in the paper); with the EnKF's disturbance estimate, its d part starts N(0, Q_d), one step
    of its random walk from 0. first_path: index of the first of the P paths, so that a run split into
    chunks of paths (first_path = 0, P1, P1 + P2, ...) gives exactly the paths of one batch.
    filter_sees_d: the EnKF is told the applied input u_k (True) or only F x_{k|k-1} (False).
    keep_members / keep_xi_cov: keep the filtered ensembles / the filtered xi's covariance per step.
    estimate: the feedback's state estimate, "predicted" x_{k|k-1} (eq. sf-enkf) or "filtered" x_{k|k}
    (needs D = 0 in plant and model; see the module docstring).
    block: steps of noise drawn per generator call (does not change results).
    progress: optional callable(k) called once per step (a progress bar's update).
    F: None (open loop), one gain (m, n) or one per path (P, m, n). controller: changes per-path
    gains between steps (`GainController.update`, called after filtering at every step k < K);
    then F is each path's initial gain and out.gain_index counts the adopted gains.
    recorded: recorded inputs and outputs (`Recorded`, P paths x len(d) steps) in place of the plant
    (plant None, F None, filter_sees_d True): the EnKF is told the recorded u_k and filters the recorded
    y_k; q, s stay NaN/None. The same EnKF streams and initial ensemble as a simulated run of `seed`.
    keep_forecast: keep every member's predicted output (Trajectories.y_forecast).
    plant_noise: additive process and output noise on the plant (`PlantNoise`; None: noise-free).
    """
    F, d, q0, psi0, P0 = check_settings(plant, enkf, F, d, q0, psi0, P0, paths, estimate, recorded)
    _check_counts(ensemble_size, paths, first_path, block, recorded, filter_sees_d)
    M, P, K = int(ensemble_size), int(paths), d.shape[0] - 1
    model, ny, width = enkf.model, enkf.model.ny, enkf.width
    psi0, P0 = _augmented_start(enkf, psi0, P0)

    # the plant (its coefficients from the PLANT streams) or the recorded data: what gives (u_k, y_k)
    paths_here = range(first_path, first_path + P)
    source = _RecordedSource(recorded) if recorded is not None else \
        _PlantSource(plant, q0, path_generators(seed, PLANT, paths_here), K, plant_noise,
                     path_generators(seed, NOISE, paths_here) if plant_noise is not None else None)
    enkf_rngs = path_generators(seed, ENKF, paths_here)
    n_q = model.n if recorded is not None else plant.n
    # ensembles psi_{k|k-1}, psi_{k|k} and the EnKF's scratch, reused at every step (see EnKF._predict)
    psi, filtered, work = (component_major((P, M, c)) for c in (width, width, width + ny + 1))
    # the adaptive inflation rho_{k-1} (P,) this run carries from one update to the next (None: every path
    # starts at 1, clipped to [low, high]); this loop holds it, so that each run and chunk has its own
    inflation = None
    psi[...] = psi0 + np.stack([g.standard_normal((M, width)) for g in enkf_rngs]) @ sqrtm_psd(P0)

    out = _empty_trajectories(enkf, K, P, M, n_q, source.s, keep_members=keep_members, keep_xi_cov=keep_xi_cov,
                              keep_forecast=keep_forecast)
    alive = np.ones(P, dtype=bool)
    if controller is not None:
        # per-path gains (P, m, n): the same product per path as one shared (m, n) gain, bit for bit
        F = np.broadcast_to(F, (P, model.m, model.n)).copy()
        out.gain_index = np.zeros((K + 1, P), dtype=np.int64)
        adopted = np.zeros(P, dtype=np.int64)
    nv = enkf.output_noise_dim
    draw = _noise_blocks(enkf_rngs, K, M, nv + width, block)

    def fail(mask, k, reason):
        new = mask & alive
        out.failed_at[new], out.failure[new] = k, reason
        alive[new] = False

    # BLAS on one thread: the products here are small (9 x 300 per path), and a second BLAS thread
    # only competes with the noise-drawing thread for the other core
    with np.errstate(all="ignore"), ThreadPoolExecutor(max_workers=1) as drawer, \
            threadpool_limits(limits=1, user_api="blas"):
        pending = drawer.submit(draw, 0)
        for k in range(K + 1):
            if k % block == 0:
                noise = pending.result()
                if k + block <= K:
                    pending = drawer.submit(draw, k + block)
            e_v, e_w = noise[:, k % block, :, :nv], noise[:, k % block, :, nv:]
            mean_pred = ensemble_mean(psi)                                          # eq. (state-pred1)
            # a path whose state or ensemble left the bound (or is not finite) stops here; the
            # reason says which: the plant ("diverged") or only the EnKF's estimate
            fail(~np.all(np.abs(source.q) <= bound, axis=1), k, "diverged")
            fail(~np.all(np.abs(mean_pred) <= bound, axis=1), k, "filter_diverged")
            source.stop(~alive)
            psi[~alive], mean_pred[~alive] = 0.0, 0.0                    # no overflow on failed paths
            if estimate == "filtered":              # D = 0: y_k first, then u_k = F x_{k|k} + d_k
                y = source.output(k)
                a = enkf._update(psi, None, y, e_v, mean_pred, out=filtered, work=work,   # D = 0: no u
                                  inflation=inflation)
                x_hat = a.filt_mean
            else:
                x_hat = mean_pred
            # eq. (sf-enkf) + d_k, one product per path: the rounding of a single (P, n) @ (n, m)
            # product depends on P
            u = (F @ x_hat[:, :model.n, None])[..., 0] + d[k]
            probe = controller.excitation(k) if controller is not None and hasattr(controller, "excitation") else None
            u = source.input(k, u if probe is None else u + probe)      # a controller's known excitation
            u_filter = u if filter_sees_d else u - d[k]
            if estimate == "predicted":
                y = source.output(k, u)
                a = enkf._update(psi, u_filter, y, e_v, mean_pred, out=filtered, work=work, inflation=inflation)
            inflation = a.inflation                 # rho_k (adaptive inflation; enkf_n's lambda is not read back)
            fail(~a.ok, k, "singular_innovation")
            keep = alive[:, None]
            if keep_forecast:                       # psi still holds psi_{k|k-1} (the update wrote `filtered`)
                out.y_forecast[k] = np.where(keep[:, :, None], enkf.outputs(psi, u_filter), np.nan)
            q = source.q if recorded is None else np.full((P, n_q), np.nan)
            xi_cov = _store_step(out, k, enkf, a, keep, q, y, u)
            if controller is not None and controller.needs_xi_cov:
                xi_cov = _xi_cov(a, enkf.xi_estimate, keep) if enkf.lag or xi_cov is None else xi_cov
            if progress is not None:
                progress(k)
            if k == K:
                if controller is not None:
                    out.gain_index[k] = adopted
                break
            if controller is not None:
                out.gain_index[k] = adopted
                _adopt(controller, k, enkf, a, keep, alive, xi_cov, F, adopted)
            source.advance(k, u)
            prior = controller.observer_prior() if controller is not None and hasattr(controller, "observer_prior") \
                else None
            enkf._predict(filtered, u_filter, e_w, out=psi, path_prior=prior)
    return out


def _noise_blocks(enkf_rngs: list, K: int, M: int, width: int, block: int):
    """draw(k0): the EnKF noise of steps k0..k0+block-1 (P, block, M, width), from each path's own stream.

    A helper thread draws into one of two buffers while the loop filters with the other (numpy's generators
    release the GIL); each stream is still consumed in order, so results do not depend on the threading (the
    etkf variant draws no output perturbations: only e_w per member and step)."""
    buffers = np.empty((2, len(enkf_rngs), min(block, K + 1), M, width))

    def draw(k0: int) -> np.ndarray:
        noise = buffers[(k0 // block) % 2]
        for g, buffer in zip(enkf_rngs, noise):
            g.standard_normal(out=buffer[:K + 1 - k0])
        return noise
    return draw


def _adopt(controller: GainController, k: int, enkf: EnKF, a, keep: np.ndarray, alive: np.ndarray, xi_cov,
           F: np.ndarray, adopted: np.ndarray) -> None:
    """The controller's decision after step k's filter, from x_{k|k} and the xi estimate it models from (with
    the EnKF's lag: smoothed): the paths it re-designs get their new gains in F (P, m, n), acting from step k+1
    on, and their count of adopted gains (P,) goes up."""
    modeled = np.concatenate([a.filt_mean[:, :enkf.model.n], a.filt_mean[:, enkf.xi_estimate]], axis=1)
    change = controller.update(k, np.where(keep, modeled, np.nan), alive.copy(), xi_cov)
    if change is not None:
        idx, gains = change
        F[idx] = gains
        adopted[idx] += 1


def _check_counts(ensemble_size: int, paths: int, first_path: int, block: int, recorded, filter_sees_d: bool):
    """`simulate`'s counts and the recorded data's input, each a one-line ValueError naming the argument."""
    if recorded is not None and not filter_sees_d:
        raise ValueError("filter_sees_d: must be True with recorded data (the EnKF is told the recorded input)")
    if int(ensemble_size) < 2:
        raise ValueError(f"ensemble_size: {int(ensemble_size)}, must be >= 2 (the EnKF needs a sample covariance)")
    if int(paths) < 1:
        raise ValueError(f"paths: {int(paths)}, must be >= 1")
    if first_path < 0:
        raise ValueError(f"first_path: {first_path}, must be >= 0")
    if block < 1:
        raise ValueError(f"block: {block}, must be >= 1")


def _augmented_start(enkf: EnKF, psi0: np.ndarray, P0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The initial ensemble's mean (width,) and covariance (width, width) over the EnKF's whole state: psi0, P0
    of [x; xi], then the unknown input's d_{0|-1} ~ N(0, Q_d), the static mean's mu_0 ~ N(xi_{0|-1} mean,
    c mean_spread^2 Q_xi) (the guess's doubt) and the smoother's past draws, fixed at the initial xi."""
    model, dim, width = enkf.model, enkf.dim, enkf.width
    md = enkf.d_slice.stop - dim
    if md:                                           # [x; xi; d]: d_{0|-1} ~ N(0, Q_d)
        psi0 = np.concatenate([psi0, np.zeros(md)])
        P0 = np.block([[P0, np.zeros((dim, md))], [np.zeros((md, dim)), enkf.disturbance]])
    if enkf.static_mean:
        xi_rows = slice(model.n, dim)
        psi0 = np.concatenate([psi0, psi0[xi_rows]])
        P0_mu = enkf.start_scale * enkf.mean_spread ** 2 * enkf.Q[xi_rows, xi_rows]
        P0 = np.block([[P0, np.zeros((len(P0), model.p))], [np.zeros((model.p, len(P0))), P0_mu]])
    if enkf.lag:
        psi0 = np.concatenate([psi0, np.tile(psi0[model.n:dim], enkf.lag)])
        P0 = np.block([[P0, np.zeros((len(P0), width - len(P0)))], [np.zeros((width - len(P0), width))]])
    return psi0, P0


def _empty_trajectories(enkf: EnKF, K: int, P: int, M: int, n_q: int, s, *, keep_members: bool, keep_xi_cov: bool,
                        keep_forecast: bool) -> Trajectories:
    """The result arrays (K+1, P, ...), NaN until a step stores its values (`_store_step`)."""
    model, dim, ny = enkf.model, enkf.dim, enkf.model.ny
    md = enkf.d_slice.stop - dim
    nan = lambda *shape: np.full((K + 1, P) + shape, np.nan)
    return Trajectories(q=nan(n_q), y=nan(ny), u=nan(model.m), psi_pred_mean=nan(dim),
                        psi_pred_std=nan(dim), psi_filt_mean=nan(dim), psi_filt_std=nan(dim),
                        failed_at=np.full(P, -1), failure=np.full(P, "", dtype=object), n=model.n,
                        members=nan(M, dim) if keep_members else None,
                        xi_filt_cov=nan(model.p, model.p) if keep_xi_cov else None, s=s,
                        d_filt_mean=nan(md) if md else None, d_filt_std=nan(md) if md else None,
                        y_forecast=nan(M, ny) if keep_forecast else None)


def _store_step(out: Trajectories, k: int, enkf: EnKF, a, keep: np.ndarray, q, y, u) -> np.ndarray | None:
    """Step k's plant, output, input and the EnKF's analysis `a` into `out` (NaN on paths not kept (P, 1));
    returns the filtered xi's covariance (P, p, p) where it is kept, else None."""
    dim = enkf.dim
    for name, value in (("q", q), ("y", y), ("u", u), ("psi_pred_mean", a.pred_mean[:, :dim]),
                        ("psi_pred_std", a.pred_std[:, :dim]), ("psi_filt_mean", a.filt_mean[:, :dim]),
                        ("psi_filt_std", a.filt_std[:, :dim])):
        getattr(out, name)[k] = np.where(keep, value, np.nan)
    if out.d_filt_mean is not None:
        out.d_filt_mean[k] = np.where(keep, a.filt_mean[:, enkf.d_slice], np.nan)
        out.d_filt_std[k] = np.where(keep, a.filt_std[:, enkf.d_slice], np.nan)
    if out.members is not None:
        out.members[k] = np.where(keep[:, :, None], a.psi[..., :dim], np.nan)
    if out.xi_filt_cov is None:
        return None
    out.xi_filt_cov[k] = xi_cov = _xi_cov(a, slice(enkf.model.n, dim), keep)
    return xi_cov


def _xi_cov(a, rows: slice, keep: np.ndarray) -> np.ndarray:
    """The filtered members' sample covariance (P, p, p) of psi's rows `rows` (NaN on paths not kept (P, 1))."""
    dev = a.psi[..., rows] - a.filt_mean[:, None, rows]                                     # (P, M, p)
    return np.where(keep[:, :, None], np.einsum("jip,jiq->jpq", dev, dev) / (dev.shape[1] - 1), np.nan)


def bytes_per_path(plant: AffineRandomSystem, enkf: EnKF, *, ensemble_size: int, horizon: int,
                   keep_members: bool = False, block: int = 16) -> int:
    """Bytes `simulate` holds per path (the arrays above, float64), to size chunks of paths.

    Plant coefficients and matrices per step, the result arrays (K+1 steps), the ensembles and
    their scratch, and the two noise buffers of `block` steps; members (K+1, M, n+p) if kept.
    """
    M, K1, model, dim, width = int(ensemble_size), int(horizon) + 1, enkf.model, enkf.dim, enkf.width
    n, m, ny = model.n, model.m, model.ny
    per_step = plant.xi_dist.p if plant.xi_dist is not None else 0
    per_step += n * n + n * m + ny * n + ny * m + n + ny + m + 4 * dim + 2 * (enkf.d_slice.stop - dim) \
        + (M * dim if keep_members else 0)
    ensembles = M * (3 * width + ny + 1)
    noise = 2 * min(block, K1) * M * (enkf.output_noise_dim + width)
    return 8 * (K1 * per_step + ensembles + noise)


def simulate_state_feedback(system: AffineRandomSystem, F, *, d, x0, paths: int, seed) -> np.ndarray:
    """Ideal closed loop x_{k+1} = (A(xi_k) + B(xi_k) F) x_k + B(xi_k) d_k with xi ~ system.xi_dist.

    d: (K+1, m); returns x (K+1, P, n). Per-path streams as in `simulate` (PLANT slot).
    """
    F = system.check_gain(F)
    system.check_distribution(None)
    dist = system.xi_dist                                   # the family itself samples, not its moments
    d = np.asarray(d, dtype=float).reshape(len(d), -1)
    if d.shape[1] != system.m or paths < 1:
        raise ValueError(f"d: shape {d.shape}, expected (K+1, m = {system.m}); paths: {paths}, must be >= 1")
    K = d.shape[0] - 1
    xi = np.stack([dist.sample(g, (K + 1,)) for g in path_generators(seed, PLANT, range(paths))], axis=1)
    A, B, _, _ = system.at(xi)
    x = np.empty((K + 1, paths, system.n))
    x[0] = x0
    with np.errstate(all="ignore"):
        for k in range(K):
            x[k + 1] = ((A[k] + B[k] @ F) @ x[k][..., None])[..., 0] + (B[k] @ d[k])
    return x
