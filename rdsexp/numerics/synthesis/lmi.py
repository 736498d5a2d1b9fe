"""Theorem 2's LMI designs (paper Sec. II-B, V-B).

- `proposed`: bisection on lambda under LMI (lmi-syn) with the modeled moments of xi: the
  mean-square optimal decay rate.
- `nominal_lmi`: the same with xi fixed to its mean (covariance discarded).
"""
from __future__ import annotations

import warnings
from collections.abc import Callable

import cvxpy as cp
import numpy as np

from ..systems import AffineRandomSystem, MomentModel
from .bisection import Trial, certified_bisection
from .riccati import BRACKET_TOL, policy_iteration

T_PROOF = 1e-8       # the margin t must be below -T_PROOF to prove infeasibility: above Clarabel's accuracy


def _lmi_problem(n: int, m: int, nbar: int):
    """Theorem 2's LMI at a given lambda^2, compiled (lambda^2, Abar, Bbar parameters): once per design, whose
    bisection solves it at every lambda (`lmi_solver` owns it; a compile takes a fraction of a design).

    Rows of the off-diagonal block are reordered (a congruence by a permutation) so that
    X (x) I_nbar becomes I_nbar (x) X = blockdiag(X, ..., X); the margin t on the (1,1) block
    is maximised with trace(X) = 1 fixing the scale of the homogeneous LMI:
        max t  s.t.  [[lam2 X - t I, *], [Abar_r X + Bbar_r Y (r = 1..nbar), I_nbar (x) X]] >= 0.
    (lmi-syn) holds with X > 0 iff t* >= 0; the solve always has a solution, so a gain
    F = Y X^-1 comes back at every lambda, feasible or not, and its exact rate decides.
    """
    lam2, Abar, Bbar, X, Y, t = lmi_variables(n, m, nbar)
    H = cp.vstack([Abar[r] @ X + Bbar[r] @ Y for r in range(nbar)])           # (nbar n, n)
    Z = np.zeros((n, n))
    diag = cp.bmat([[X if i == j else Z for j in range(nbar)] for i in range(nbar)])
    lmi = cp.bmat([[lam2 * X - t * np.eye(n), H.T], [H, diag]])
    problem = cp.Problem(cp.Maximize(t), [lmi >> 0, cp.trace(X) == 1])
    # compile now: cvxpy's first solve canonicalises with the parameter values in place, later ones
    # go through the cached parametrised program, and the two differ in the last bits; compiling
    # here (get_problem_data builds and caches the parametrised program without solving) sends every
    # real solve through the same path; every solve also builds a fresh Clarabel solver
    # (warm_start=False) instead of updating the previous one's data in place, which differs in the last
    # bits. Together, results do not depend on call history.
    compile_problem(problem, lam2, Abar, Bbar)
    return problem, lam2, Abar, Bbar, X, Y, t


def lmi_variables(n: int, m: int, count: int):
    """The parameters and variables of a decay-rate LMI: lambda^2, `count` pairs of parameters A_r (n, n),
    B_r (n, m), and the variables X (n, n) symmetric, Y (m, n) (the gain is Y X^-1) and the margin t."""
    lam2 = cp.Parameter(nonneg=True)
    A = [cp.Parameter((n, n)) for _ in range(count)]
    B = [cp.Parameter((n, m)) for _ in range(count)]
    return lam2, A, B, cp.Variable((n, n), symmetric=True), cp.Variable((m, n)), cp.Variable()


def compile_problem(problem: cp.Problem, lam2, A: list, B: list) -> None:
    """Compile the parametrised program now, without a solve (at lambda = 1, A_r = I, B_r = 0): see
    `_lmi_problem`, why every solve must go through the same path."""
    lam2.value = 1.0
    for a, b in zip(A, B, strict=True):
        a.value, b.value = np.eye(a.shape[0]), np.zeros(b.shape)
    problem.get_problem_data(cp.CLARABEL)


def solve_fresh(problem: cp.Problem) -> str:
    """Solve a compiled problem with a fresh Clarabel solver (see `_lmi_problem`); its status, or
    "solver_error". Inaccuracy is a status here, so the solver's warnings are silenced."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            problem.solve(solver=cp.CLARABEL, warm_start=False)
        return problem.status
    except cp.error.SolverError:
        return "solver_error"


def lmi_solver(system: AffineRandomSystem, dist: MomentModel) -> Callable[[float], Trial]:
    """solve(lam) -> Trial: Theorem 2's LMI (lmi-syn) at a fixed lambda with the moments of `dist`.

    The gain F = Y X^-1 (m, n) comes back at every lambda the solver returns something usable for,
    feasible or not; infeasible only where the margin t < -T_PROOF (the solver's evidence, which
    `certified_bisection` checks before it reports a lower end)."""
    Abar, Bbar = system.moment_factors(dist)
    problem, lam2, pA, pB, X, Y, t = _lmi_problem(system.n, system.m, Abar.shape[0])
    for r in range(Abar.shape[0]):
        pA[r].value, pB[r].value = Abar[r], Bbar[r]

    def solve(lam: float) -> Trial:
        lam2.value = lam ** 2
        status = solve_fresh(problem)
        usable = X.value is not None and status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE)
        return Trial(F=Y.value @ np.linalg.inv(X.value) if usable else None, X=X.value if usable else None,
                     infeasible=status == cp.OPTIMAL and t.value < -T_PROOF)

    return solve


def _theorem2(system: AffineRandomSystem, dist: MomentModel, method: str, seed: bool = True, **settings):
    """Bisection over (lmi-syn) with the moments of `dist`; settings go to `certified_bisection`."""
    bracket = None
    if seed:                    # policy iteration's certified bracket (no SDP) seeds the bisection
        pi = policy_iteration(system, dist)
        if np.isfinite(pi.lam) and pi.lam - pi.lam_lower <= BRACKET_TOL * pi.lam:   # closed: optimal, or
            bracket = (pi.lam_lower, pi.lam)                                       # proven not ms-stabilizable
    res = certified_bisection(system, dist, lmi_solver(system, dist), method=method,
                              nbar=system.Gbar(dist).shape[0], bracket=bracket, **settings)
    res.info["seeded"] = bracket is not None
    return res


def proposed(system, dist, *, tol: float = 1e-7, max_iter: int = 60, x_cond_limit: float = 1e6, seed: bool = True):
    """Theorem 2 with the modeled moments of xi: the mean-square optimal decay rate.

    Only E[[1; xi][1; xi]^T] enters (through Gbar), so the covariance normalisation matters:
    `MomentModel.from_samples` uses 1/N, which makes Gbar^T Gbar the paper's eq. (sample-mean)
    exactly. seed: start from policy iteration's certified bracket when it is closed, below 1 or
    above (one solve, the lower end proven by policy iteration's SDP-free bound; see
    `certified_bisection`, which gives the statuses, lam_lower and info); False runs the plain
    bisection. info also has seeded.
    """
    return _theorem2(system, dist, "proposed", seed=seed, tol=tol, max_iter=max_iter, x_cond_limit=x_cond_limit)


def nominal_lmi(system, dist, *, tol: float = 1e-7, max_iter: int = 60, x_cond_limit: float = 1e6):
    """Theorem 2 on the LTI model with xi fixed to its mean; lam is the rate on that LTI model.

    What it certifies is the mean model, not the random system, so every status carries the suffix
    `_on_mean_model` (e.g. `optimal_on_mean_model`); the gains table shows the gain's rate on the
    distribution beside it."""
    res = _theorem2(system, MomentModel.deterministic(dist.mean), "nominal_lmi", tol=tol, max_iter=max_iter,
                    x_cond_limit=x_cond_limit)
    res.status += "_on_mean_model"
    return res
