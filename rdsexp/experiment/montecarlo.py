"""A loop's Monte Carlo in chunks of paths: bounded memory, rows streamed out, optional worker processes.

A loop of P paths runs as chunks of at most `chunk_paths` paths (`simulate(first_path=...)`). Each
chunk's table rows go to a sink as soon as the chunk is done, and what the metrics need is reduced
to a few numbers per path (`LoopSummary`), so memory is bounded by the chunk, not by P. Every path
has its own random streams, so the rows and the metrics do not depend on the chunk size or on the
number of worker processes (tests/experiment/test_montecarlo.py).
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from ..numerics.enkf import truth_map
from ..numerics.simulation import Trajectories, bytes_per_path, simulate

MEMORY_BUDGET = 256 * 2 ** 20       # bytes of simulation arrays per chunk when chunk_paths is not set


def chunk_size(exp, *, keep_members: bool) -> int:
    """Paths per chunk: closed_loop.chunk_paths, else as many as fit the memory budget (at least 1)."""
    if exp.loop.chunk_paths is not None:
        return min(exp.loop.chunk_paths, exp.loop.paths)
    per_path = bytes_per_path(exp.plant, exp.filter.enkf, ensemble_size=exp.filter.ensemble_size,
                              horizon=exp.loop.disturbance.shape[0] - 1, keep_members=keep_members)
    # the chunk's table rows and the worker's copy roughly double what simulate holds
    return int(min(exp.loop.paths, max(1, MEMORY_BUDGET // (3 * per_path))))


def chunk_starts(exp, *, keep_members: bool) -> list[tuple[int, int]]:
    """The loop's chunks as (first path, number of paths), in path order."""
    size = chunk_size(exp, keep_members=keep_members)
    return [(j, min(size, exp.loop.paths - j)) for j in range(0, exp.loop.paths, size)]


def _simulate_chunk(plant, enkf, first: int, count: int, settings: dict, controller=None, progress=None):
    """One chunk of paths; `controller(paths=count)` makes the chunk's gain controller (None: fixed
    gains). Returns the trajectories and the controller with its decisions."""
    controller = controller(paths=count) if controller is not None else None
    tr = simulate(plant, enkf, paths=count, first_path=first, controller=controller, progress=progress, **settings)
    return tr, controller


def run_chunks(exp, settings: dict, *, keep_members: bool, workers: int = 1,
               progress: Callable[[int], None] | None = None, controller: Callable | None = None,
               enkf=None) -> Iterator[tuple[int, Trajectories, object]]:
    """(first_path, Trajectories of that chunk, its controller) in path order; `settings` are
    simulate's other arguments. controller: None (fixed gains), or a picklable factory of the
    chunk's gain controller called as controller(paths=count) (the online controller: a path's
    decisions depend on its own estimates only, so one controller per chunk gives the same results).

    workers > 1: the chunks run in joblib (loky) worker processes, results still yielded in path
    order, at most 2 * workers chunks in flight. progress(steps) is called with the number of
    path-steps done. enkf: the loop's observer (default exp.filter.enkf)."""
    enkf = exp.filter.enkf if enkf is None else enkf
    starts = chunk_starts(exp, keep_members=keep_members)
    steps = exp.loop.disturbance.shape[0]
    settings = dict(settings, keep_members=keep_members)
    if workers <= 1 or len(starts) == 1:
        for first, count in starts:
            step = (lambda k, c=count: progress(c)) if progress is not None else None
            yield first, *_simulate_chunk(exp.plant, enkf, first, count, settings, controller, step)
        return
    from joblib import Parallel, delayed
    parallel = Parallel(n_jobs=workers, backend="loky", return_as="generator", pre_dispatch="2*n_jobs")
    results = parallel(delayed(_simulate_chunk)(exp.plant, enkf, first, count, settings, controller)
                       for first, count in starts)
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
