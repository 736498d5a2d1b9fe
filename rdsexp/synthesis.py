"""State-feedback gain synthesis u = F x, selected by method name (paper Sec. II-B, V-B).

- `proposed`: Theorem 2, bisection on lambda^2 under LMI (lmi-syn), certified by the exact rate.
- `nominal_lmi`: the same with xi fixed to its mean (covariance discarded).
- `pole_placement`, `lqr_mean`: classical designs on the mean (LTI) model.
- `policy_iteration`: SDP-free optimal mean-square decay rate, used to cross-check the LMI.

Every method returns a `SynthesisResult`; numerical outcomes (not stabilizable, solver failure)
are statuses, bad arguments raise ValueError before any work.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from functools import lru_cache

import cvxpy as cp
import numpy as np
import scipy.linalg
import scipy.signal

from .analysis import ms_rate
from .systems import AffineRandomSystem, MomentModel

STATUSES = ("optimal", "not_ms_stabilizable", "infimum_not_attained", "solver_failed", "designed")


@dataclass
class SynthesisResult:
    """A gain and how it was obtained.

    F: (m, n) gain for u = F x, or None if no gain was found. lam: the exact mean-square rate of F
    on the design distribution (so lam is certified: it is achieved). lam_lower: a lower bound on
    the optimal rate where the method gives one (LMI infeasibility), else NaN. nbar: rank of Gbar.
    """

    method: str
    F: np.ndarray | None
    lam: float
    status: str
    nbar: int
    lam_lower: float = float("nan")
    lower_certified: bool = True
    seconds: float = 0.0
    info: dict = field(default_factory=dict)


def synthesize(system: AffineRandomSystem, dist: MomentModel | None, method: str = "proposed",
               **options) -> SynthesisResult:
    """Design F for `system` with xi ~ `dist` by `method` (see METHODS); options go to the method."""
    check_options(method, options, system)
    dist = system.check_distribution(dist)
    design = METHODS[method]
    start = time.perf_counter()
    res = design(system, dist, **options)
    res.seconds = time.perf_counter() - start
    return res


def check_options(method: str, options: dict, system: AffineRandomSystem) -> None:
    """One-line ValueError for an unknown method, an unknown option or a bad pole set."""
    if method not in METHODS:
        raise ValueError(f"method: unknown {method!r}, allowed: {', '.join(METHODS)}")
    code = METHODS[method].__code__
    allowed = set(code.co_varnames[code.co_argcount:code.co_argcount + code.co_kwonlyargcount])
    unknown = set(options) - allowed
    if unknown:
        raise ValueError(f"{method}: unknown option(s) {sorted(unknown)}, allowed: {sorted(allowed) or 'none'}")
    for name, value in options.items():
        if name == "poles":
            check_poles(value, system)
        elif name in POSITIVE_OPTIONS and not (isinstance(value, (int, float)) and not isinstance(value, bool)
                                               and np.isfinite(value) and value > 0):
            raise ValueError(f"{name}: {value!r} is not allowed, expected a number > 0")


POSITIVE_OPTIONS = ("tol", "max_iter", "x_cond_limit", "state_weight", "input_weight")


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


# --------------------------------------------------------------------------------------- LMI
@lru_cache(maxsize=8)
def _lmi_problem(n: int, m: int, nbar: int):
    """Theorem 2's LMI at a given lambda^2, compiled once per size (lambda^2, Abar, Bbar parameters).

    Rows of the off-diagonal block are reordered (a congruence by a permutation) so that
    X (x) I_nbar becomes I_nbar (x) X = blockdiag(X, ..., X); the margin t on the (1,1) block
    is maximised with trace(X) = 1 fixing the scale of the homogeneous LMI:
        max t  s.t.  [[lam2 X - t I, *], [Abar_r X + Bbar_r Y (r = 1..nbar), I_nbar (x) X]] >= 0.
    (lmi-syn) holds with X > 0 iff t* >= 0; the solve always has a solution, so a gain
    F = Y X^-1 comes back at every lambda, feasible or not, and its exact rate decides.
    """
    lam2 = cp.Parameter(nonneg=True)
    Abar = [cp.Parameter((n, n)) for _ in range(nbar)]
    Bbar = [cp.Parameter((n, m)) for _ in range(nbar)]
    X = cp.Variable((n, n), symmetric=True)
    Y = cp.Variable((m, n))
    t = cp.Variable()
    H = cp.vstack([Abar[r] @ X + Bbar[r] @ Y for r in range(nbar)])           # (nbar n, n)
    Z = np.zeros((n, n))
    diag = cp.bmat([[X if i == j else Z for j in range(nbar)] for i in range(nbar)])
    lmi = cp.bmat([[lam2 * X - t * np.eye(n), H.T], [H, diag]])
    problem = cp.Problem(cp.Maximize(t), [lmi >> 0, cp.trace(X) == 1])
    # compile now: cvxpy's first solve canonicalises with the parameter values in place, later ones
    # go through the cached parametrised program, and the two differ in the last bits; compiling
    # here sends every real solve through the same path, so results do not depend on call history
    lam2.value = 1.0
    for r in range(nbar):
        Abar[r].value, Bbar[r].value = np.eye(n), np.zeros((n, m))
    problem.solve(solver=cp.CLARABEL)
    return problem, lam2, Abar, Bbar, X, Y, t


def _lmi_bisection(system, dist, *, tol: float = 1e-7, max_iter: int = 60,
                   x_cond_limit: float = 1e6, method: str) -> SynthesisResult:
    """Minimise lambda over (lmi-syn) by bisection on lambda^2 with a certified upper end.

    The upper end `lam` is always the exact rate (`ms_rate`) of a gain in hand: F = 0 (the open
    loop) to start, then F = Y X^-1 from a solve whose exact rate confirms the trial lambda. Such a
    solve slightly above the optimum returns a nearly optimal gain, so after each confirmed trial
    the next one probes just below the new upper end (lam - tol); otherwise the interval is halved
    in lambda^2. A trial whose gain does not confirm it raises the lower end; that lower end is
    certified when the solver's margin t* < 0 proves (lmi-syn) infeasible there.
    """
    Abar, Bbar = system.moment_factors(dist)
    nbar = Abar.shape[0]
    problem, lam2, pA, pB, X, Y, t = _lmi_problem(system.n, system.m, nbar)
    for r in range(nbar):
        pA[r].value, pB[r].value = Abar[r], Bbar[r]
    best_F = np.zeros((system.m, system.n))
    lam = ms_rate(system, dist, best_F)
    lo, certified, best_X, solves, confirmed = 0.0, True, None, 0, True
    while lam - lo > tol and solves < max_iter:
        trial = max(lam - tol / 2, 0.0) if confirmed else np.sqrt((lo ** 2 + lam ** 2) / 2)
        lam2.value = trial ** 2
        solves += 1
        try:
            with warnings.catch_warnings():                              # inaccuracy is a status here
                warnings.simplefilter("ignore")
                problem.solve(solver=cp.CLARABEL)
            status = problem.status
        except cp.error.SolverError:
            status = "solver_error"
        confirmed = False
        if X.value is not None and status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
            F = Y.value @ np.linalg.inv(X.value)
            rate = ms_rate(system, dist, F)
            confirmed = rate <= trial
            if rate < lam:                                               # any gain certifies its rate
                lam, best_F, best_X = rate, F, X.value
        if not confirmed:
            lo = min(trial, lam)
            certified = status == cp.OPTIMAL and t.value < 0
    info = {"solves": solves}
    if best_X is not None:
        info["cond_X"] = float(np.linalg.cond(best_X))
    if lam >= 1.0:
        status = "not_ms_stabilizable"
    elif best_X is None:
        status = "solver_failed"
    elif lo <= tol or (not certified and info["cond_X"] > x_cond_limit):
        # the certificate X degenerates towards the infimum, which no gain attains
        # (e.g. a deterministic model, where the infimum is the dead-beat rate 0)
        status = "infimum_not_attained"
    else:
        status = "optimal"
    return SynthesisResult(method, best_F, lam, status, nbar, lam_lower=lo, lower_certified=certified,
                           info=info)


def proposed(system, dist, *, tol: float = 1e-7, max_iter: int = 60, x_cond_limit: float = 1e6):
    """Theorem 2 with the modeled moments of xi: the mean-square optimal decay rate.

    Only E[[1; xi][1; xi]^T] enters (through Gbar), so the covariance normalisation matters:
    `MomentModel.from_samples` uses 1/N, which makes Gbar^T Gbar the paper's eq. (sample-mean)
    exactly. On the paper's printed moments (eqs. ex-mean, ex-covar) taken as the covariance,
    lam = 0.844183 (paper: 0.8432); if the printed matrix is a 1/(N-1) covariance of N = 81
    samples, the 1/N one is 80/81 of it and lam = 0.843610. Both within 2e-3 of the paper.
    """
    return _lmi_bisection(system, dist, tol=tol, max_iter=max_iter, x_cond_limit=x_cond_limit,
                          method="proposed")


def nominal_lmi(system, dist, *, tol: float = 1e-7, max_iter: int = 60, x_cond_limit: float = 1e6):
    """Theorem 2 on the LTI model with xi fixed to its mean; lam is the rate on that LTI model."""
    return _lmi_bisection(system, MomentModel.deterministic(dist.mean), tol=tol, max_iter=max_iter,
                          x_cond_limit=x_cond_limit, method="nominal_lmi")


# --------------------------------------------------------------------------------------- classical
def _mean_model(system, dist):
    A, B, _, _ = system.at(dist.mean)
    return A, B


def _designed(method, system, dist, F, **info) -> SynthesisResult:
    """A classical design: lam is its exact rate on the LTI mean model (what it was designed for)."""
    lam = ms_rate(system, MomentModel.deterministic(dist.mean), F)
    return SynthesisResult(method, F, lam, "designed", nbar=1, info=info)


def pole_placement(system, dist, *, poles=(0.9, 0.8, 0.7, 0.6, 0.5, 0.4)):
    """Place the eigenvalues of A(mean) + B(mean) F at `poles` (complex poles in conjugate pairs)."""
    poles = check_poles(poles, system)
    A, B = _mean_model(system, dist)
    placed = scipy.signal.place_poles(A, B, poles.real if np.all(poles.imag == 0) else poles)
    return _designed("pole_placement", system, dist, -placed.gain_matrix, poles=poles.tolist())


def lqr_mean(system, dist, *, state_weight: float = 1.0, input_weight: float = 1.0):
    """Discrete LQR on the mean model with weights state_weight I_n, input_weight I_m (F = -K)."""
    A, B = _mean_model(system, dist)
    Rw = input_weight * np.eye(system.m)
    P = scipy.linalg.solve_discrete_are(A, B, state_weight * np.eye(system.n), Rw)
    F = -np.linalg.solve(Rw + B.T @ P @ B, B.T @ P @ A)
    return _designed("lqr_mean", system, dist, F)


# --------------------------------------------------------------------------------------- SDP-free
def policy_iteration(system, dist, *, max_iter: int = 200, tol: float = 1e-13, F0=None):
    """Optimal mean-square rate without an SDP.

    Alternate (i) P = Perron eigenvector of the positive map P -> E[Acl^T P Acl] for the current F,
    (ii) F = argmin_F E[(A + B F)^T P (A + B F)] = -E[B^T P B]^{-1} E[B^T P A].
    Since E[Acl_new^T P Acl_new] <= E[Acl^T P Acl] = lam^2 P with P > 0, the rate never increases.
    """
    Abar, Bbar = system.moment_factors(dist)
    n, m = system.n, system.m
    F = np.zeros((m, n)) if F0 is None else system.check_gain(F0)
    lam, history = np.inf, []
    for it in range(max_iter):
        Acl = Abar + Bbar @ F
        # row-major vec(A^T P A) = (A^T (x) A^T) vec(P)
        L = np.einsum("rji,rlk->ikjl", Acl, Acl).reshape(n * n, n * n)
        w, V = np.linalg.eig(L)
        i = np.argmax(w.real)
        new_lam = float(np.sqrt(max(w[i].real, 0.0)))
        P = V[:, i].real.reshape(n, n)
        P = (P + P.T) / 2
        P *= np.sign(np.trace(P)) / np.abs(P).max()
        history.append(new_lam)
        if lam - new_lam <= tol * max(new_lam, 1e-300) and it > 0:
            lam = min(lam, new_lam)
            break
        lam = new_lam
        BPB = np.einsum("rji,jk,rkl->il", Bbar, P, Bbar)
        BPA = np.einsum("rji,jk,rkl->il", Bbar, P, Abar)
        F = -np.linalg.lstsq(BPB, BPA, rcond=None)[0]          # minimum-norm minimiser if singular
    lam = ms_rate(system, dist, F)
    status = "optimal" if lam < 1 else "not_ms_stabilizable"
    return SynthesisResult("policy_iteration", F, lam, status, Abar.shape[0],
                           info={"iterations": len(history)})


METHODS = {
    "proposed": proposed,
    "nominal_lmi": nominal_lmi,
    "pole_placement": pole_placement,
    "lqr_mean": lqr_mean,
    "policy_iteration": policy_iteration,
}
