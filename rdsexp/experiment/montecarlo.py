"""A loop's Monte Carlo in chunks of paths: bounded memory, rows streamed out, optional worker processes.

A loop of P paths (a `Simulation`: one typed object with everything `simulate` reads) runs as chunks of at most
`chunk_paths` paths (`simulate(first_path=...)`). Each
chunk's table rows go to a sink as soon as the chunk is done, and what the metrics need is reduced
to a few numbers per path (`LoopSummary`), so memory is bounded by the chunk, not by P. Every path
has its own random streams, so the rows and the metrics do not depend on the chunk size or on the
number of worker processes (tests/experiment/test_montecarlo.py).
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from ..numerics.enkf import EnKF, truth_map
from ..numerics.simulation import Trajectories, bytes_per_path, simulate
from ..numerics.systems import AffineRandomSystem
from .config import FilterSettings

MEMORY_BUDGET = 256 * 2 ** 20       # bytes of simulation arrays per chunk when chunk_paths is not set


@dataclass(frozen=True)
class Simulation:
    """One simulation of a loop (or of an identification run), everything `simulate` reads, each field owned by
    the part of the experiment that sets it: the plant (None: recorded data) and its initial state q0 (n,); the
    observer (the EnKF) and its start (`config.FilterSettings`: ensemble size M, initial ensemble psi0 (n+p,),
    P0 (n+p, n+p)); the loop: gain F (m, n) (None: open loop), input d (K+1, m), whether the EnKF is told it,
    the estimate fed back, paths P and the chunks they run in; the root seed."""

    plant: AffineRandomSystem | None
    observer: EnKF
    filter: FilterSettings
    q0: np.ndarray
    F: np.ndarray | None
    d: np.ndarray
    seed: np.random.SeedSequence
    paths: int
    filter_sees_d: bool = True
    estimate: str = "predicted"
    keep_members: bool = False
    chunk_paths: int | None = None
    first_path: int = 0         # a later look of closed_loop.paths auto adds paths first_path.. to the earlier ones

    @classmethod
    def of(cls, exp, observer: EnKF, F: np.ndarray | None, seed, **changes) -> Simulation:
        """The experiment's loop (closed_loop.*) observed by `observer` with gain F; `changes` replace fields."""
        loop = exp.loop
        return cls(**{"plant": exp.plant, "observer": observer, "filter": exp.filter, "q0": exp.q0, "F": F,
                      "d": loop.disturbance, "seed": seed, "paths": loop.paths,
                      "filter_sees_d": loop.filter_sees_disturbance, "estimate": loop.estimate,
                      "keep_members": exp.tracking.level == "full", "chunk_paths": loop.chunk_paths, **changes})

    def run(self, first: int = 0, count: int | None = None, *, controller=None, progress=None,
            **keep) -> Trajectories:
        """`simulate` of paths first..first+count-1 (every path by default); keep: keep_xi_cov, keep_forecast,
        recorded (`numerics.simulation.simulate`)."""
        f = self.filter
        return simulate(self.plant, self.observer, F=self.F, d=self.d, q0=self.q0, psi0=f.psi0, P0=f.P0,
                        ensemble_size=f.ensemble_size, paths=self.paths if count is None else count,
                        first_path=first, seed=self.seed, filter_sees_d=self.filter_sees_d,
                        keep_members=self.keep_members, estimate=self.estimate, controller=controller,
                        progress=progress, **keep)

    def chunks(self) -> list[tuple[int, int]]:
        """The paths first_path..paths - 1 in chunks as (first path, number of paths), in path order: chunk_paths
        each, else as many as fit the memory budget (at least 1)."""
        count = self.paths - self.first_path
        if self.chunk_paths is not None:
            size = min(self.chunk_paths, count)
        else:
            per_path = bytes_per_path(self.plant, self.filter.enkf, ensemble_size=self.filter.ensemble_size,
                                      horizon=self.d.shape[0] - 1, keep_members=self.keep_members)
            # the chunk's table rows and the worker's copy roughly double what simulate holds
            size = int(min(count, max(1, MEMORY_BUDGET // (3 * per_path))))
        return [(j, min(size, self.paths - j)) for j in range(self.first_path, self.paths, size)]


def _simulate_chunk(sim: Simulation, first: int, count: int, controller=None, progress=None):
    """One chunk of paths; `controller(paths=count)` makes the chunk's gain controller (None: fixed
    gains). Returns the trajectories and the controller with its decisions."""
    controller = controller(paths=count) if controller is not None else None
    return sim.run(first, count, controller=controller, progress=progress), controller


def run_chunks(sim: Simulation, *, workers: int = 1, progress: Callable[[int], None] | None = None,
               controller: Callable | None = None) -> Iterator[tuple[int, Trajectories, object]]:
    """(first_path, Trajectories of that chunk, its controller) in path order. controller: None (fixed
    gains), or a picklable factory of the chunk's gain controller called as controller(paths=count) (the
    online controller: a path's decisions depend on its own estimates only, so one controller per chunk
    gives the same results).

    workers > 1: the chunks run in joblib (loky) worker processes, results still yielded in path
    order, at most 2 * workers chunks in flight. progress(steps) is called with the number of
    path-steps done."""
    starts = sim.chunks()
    steps = sim.d.shape[0]
    if workers <= 1 or len(starts) == 1:
        for first, count in starts:
            step = (lambda k, c=count: progress(c)) if progress is not None else None
            yield first, *_simulate_chunk(sim, first, count, controller, step)
        return
    from joblib import Parallel, delayed
    parallel = Parallel(n_jobs=workers, backend="loky", return_as="generator", pre_dispatch="2*n_jobs")
    results = parallel(delayed(_simulate_chunk)(sim, first, count, controller) for first, count in starts)
    for (first, count), (tr, chunk_controller) in zip(starts, results, strict=True):
        if progress is not None:
            progress(count * steps)
        yield first, tr, chunk_controller


@dataclass
class LoopSummary:
    """A loop reduced to what its metrics need, for all P paths: O(P (K+1)) numbers, no state vectors.

    sq: ||q_k||^2 (K+1, P); failed_at (P,), failure (P,); sums (P, 2) of (sum over steps, count of
    finite steps) for the squared errors and spreads of the estimates:
    x_pred_err ||x_{k|k-1} - q_k||^2 (k >= 0); x_err ||x_{k|k} - q_k||^2 and x_var sum std^2 (k >= 1);
    xi_err, xi_var the same for xi against the true xi (NaN rows when the model's xi has no truth).
    """

    sq: np.ndarray
    failed_at: np.ndarray
    failure: np.ndarray
    sums: dict

    @property
    def status(self) -> str:
        """"ok", "partially_failed" or "failed" (every path), as Trajectories.status."""
        bad = self.failed_at >= 0
        return "ok" if not bad.any() else ("failed" if bad.all() else "partially_failed")

    @staticmethod
    def of(tr: Trajectories, exp) -> LoopSummary:
        """The summary of one chunk (or a whole loop) of trajectories."""
        def per_path(values):                             # (steps, P, d) -> (P, 2): sum of ||.||^2, count
            # summed along a contiguous path-major copy: numpy's summation order then depends on the
            # number of steps only, not on how many paths the chunk has
            sq = np.ascontiguousarray(np.sum(values ** 2, axis=-1).T)
            finite = np.isfinite(sq)
            return np.stack([np.where(finite, sq, 0.0).sum(axis=1), finite.sum(axis=1)], axis=1)
        sums = {"x_pred_err": per_path(tr.x(tr.psi_pred_mean) - tr.q)}
        with np.errstate(all="ignore"):
            sums["x_err"] = per_path(tr.x(tr.psi_filt_mean)[1:] - tr.q[1:])
            sums["x_var"] = per_path(tr.x(tr.psi_filt_std)[1:])
            truth = truth_map(exp.model, exp.plant) if tr.s is not None else None
            if truth is not None:
                T, t = truth
                # the true xi at k is T s_{k-1} + t: the coefficients that moved the plant into q_k
                sums["xi_err"] = per_path(tr.xi(tr.psi_filt_mean)[1:] - (tr.s[:-1] @ T.T + t))
                sums["xi_var"] = per_path(tr.xi(tr.psi_filt_std)[1:])
            else:
                sums["xi_err"] = sums["xi_var"] = np.full((tr.q.shape[1], 2), np.nan)
        return LoopSummary(np.sum(tr.q ** 2, axis=-1), tr.failed_at, tr.failure, sums)

    @staticmethod
    def concat(parts: list[LoopSummary]) -> LoopSummary:
        """The summaries of consecutive chunks as one, in path order."""
        return LoopSummary(np.concatenate([p.sq for p in parts], axis=1),
                           np.concatenate([p.failed_at for p in parts]),
                           np.concatenate([p.failure for p in parts]),
                           {name: np.concatenate([p.sums[name] for p in parts]) for name in parts[0].sums})

    def rms_of(self, name: str) -> float:
        """sqrt(mean) of a summed squared quantity over every finite (step, path) of the loop."""
        total, count = (np.ascontiguousarray(column).sum() for column in self.sums[name].T)
        return float(np.sqrt(total / count)) if count > 0 else float("nan")
