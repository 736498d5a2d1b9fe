"""Robust (deterministic-uncertainty) design the paper argues against in Sec. V-B: quadratic stabilization
with decay rate lambda for every xi in a box (or a polytope), not in distribution.

For the vertices v of the set (the box mean +- width * std has 2^p of them),
    (A(v) X + B(v) Y)^T X^-1 (A(v) X + B(v) Y) <= lambda^2 X,  X > 0,   F = Y X^-1,
which by Schur complement is the LMI [[lambda^2 X, *], [A(v) X + B(v) Y, X]] >= 0 at every vertex.
It is affine in (A, B), so it holds on the convex hull: ||x_{k+1}||_P <= lambda ||x_k||_P with
P = X^-1 for every xi in the set. Bisection on lambda gives the smallest such lambda (`lam_box`).

The bisection's upper end is the box rate certified by the gain and X in hand, checked independently
of the solver (`box_rate`). Its lower end is proven in two SDP-free ways, never by the solver's margin
alone: policy iteration's bound for distributions on the vertices (`vertex_floor`), and the
solver's dual matrices where they pass an independent check (`infeasibility_proven`). Below the
optimum the vertex LMIs are often only weakly infeasible (singular X reach margin 0 to within the
solver's accuracy), and then nothing proves the bisection's lower end.
As for every method, the result's `lam` is the exact mean-square rate of the gain on the modeled
distribution (`ms_rate`); the box's decay rate is info["lam_box"].
"""
from __future__ import annotations

import itertools
from functools import cache

import cvxpy as cp
import numpy as np

from ..analysis import ms_rate, perron
from ..systems import AffineRandomSystem, MomentModel
from .base import SynthesisResult
from .lmi import compile_problem, lmi_variables, solve_fresh
from .riccati import policy_iteration

MAX_VERTICES = 1024
MAX_WIDTH = 1024.0          # find_max_width stops doubling here
FLOOR_STEPS = 8             # weights tried by vertex_floor (the bound rises most in the first few)
FLOOR_STEP_SIZE = 2.0       # of its exponentiated-gradient ascent


def box_vertices(dist: MomentModel, width: float) -> np.ndarray:
    """Vertices (V, p) of the box mean +- width * std(xi), duplicates (zero spread) removed."""
    std = np.sqrt(np.clip(np.diag(dist.cov), 0.0, None))
    signs = np.array(list(itertools.product((-1.0, 1.0), repeat=dist.p)), float).reshape(2 ** dist.p, dist.p)
    return np.unique(dist.mean + width * signs * std, axis=0)


def box_rate(system: AffineRandomSystem, vertices: np.ndarray, F, X) -> float:
    """max_v ||X^-1/2 (A(v) + B(v) F) X^1/2||_2: the decay rate that (F, X) certifies on the hull of vertices.

    It is the smallest lambda with (A(v) X + B(v) F X)^T X^-1 (...) <= lambda^2 X at every vertex;
    inf if X is not positive definite.
    """
    w, U = np.linalg.eigh((X + X.T) / 2)
    if w.min() <= 0:
        return float("inf")
    half, inv_half = (U * np.sqrt(w)) @ U.T, (U / np.sqrt(w)) @ U.T
    A, B, _, _ = system.at(vertices)
    return float(np.linalg.norm(inv_half @ (A + B @ F) @ half, ord=2, axis=(1, 2)).max())


def _box_problem(n: int, m: int, V: int):
    """The vertex LMIs at a given lambda^2, compiled once per solver (`_solver` owns it; parameters lambda^2,
    A(v), B(v)).

    As in Theorem 2's problem (lmi.py): the margin t on the (1,1) blocks is maximised with
    trace(X) = 1 fixing the scale; the LMIs hold with X > 0 iff t* >= 0 and a gain comes back at
    every lambda, whose certified box rate then decides.
    """
    lam2, A, B, X, Y, t = lmi_variables(n, m, V)
    lmis = []
    for v in range(V):
        H = A[v] @ X + B[v] @ Y
        lmis.append(cp.bmat([[lam2 * X - t * np.eye(n), H.T], [H, X]]) >> 0)
    problem = cp.Problem(cp.Maximize(t), lmis + [cp.trace(X) == 1])
    compile_problem(problem, lam2, A, B)
    return problem, lam2, A, B, X, Y, t


def _solver(system: AffineRandomSystem, vertices: np.ndarray):
    """solve(lam) -> (F, X, Z) for the vertex LMIs at lam: the gain Y X^-1 (m, n) and X (n, n) of the
    solve (None if nothing usable), and its dual matrices Z (V, 2n, 2n) (None if none) for
    `infeasibility_proven`."""
    problem, lam2, pA, pB, X, Y, _ = _box_problem(system.n, system.m, len(vertices))
    A, B, _, _ = system.at(vertices)
    for v in range(len(vertices)):
        pA[v].value, pB[v].value = A[v], B[v]

    def solve(lam: float):
        lam2.value = lam ** 2
        status = solve_fresh(problem)
        if X.value is None or status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
            return None, None, None
        try:
            F = np.linalg.solve(X.value.T, Y.value.T).T                  # Y X^-1
        except np.linalg.LinAlgError:
            F = None
        duals = [c.dual_value for c in problem.constraints[:len(vertices)]]
        return F, X.value, None if any(d is None for d in duals) else np.array(duals, dtype=float)

    return solve


def infeasibility_proven(A: np.ndarray, B: np.ndarray, lam: float, Z: np.ndarray) -> bool:
    """Whether Z (V, 2n, 2n) proves that no X >= 0, X != 0, and Y satisfy the vertex LMIs at lam.

    A (V, n, n), B (V, n, m) at the vertices; M_v = [[lam^2 X, H_v^T], [H_v, X]], H_v = A_v X + B_v Y.
    For Z_v = [[P_v, Q_v^T], [Q_v, R_v]] >= 0 and any feasible (X, Y) scaled to tr X = 1,
        0 <= sum_v <Z_v, M_v> = <G_X, X> + <G_Y, Y>,
        G_X = sum_v lam^2 P_v + R_v + A_v^T Q_v + Q_v^T A_v,   G_Y = 2 sum_v B_v^T Q_v,
    with <G_X, X> <= lambda_max(G_X). Feasibility bounds ||H_v||_2 <= lam ||X||_2 <= lam, so the part of Y
    the LMIs see (its projection on the row space of B stacked, which alone matters) has
    ||Y||_F <= sqrt(rank) sqrt(V) (lam + max_v ||A_v||_2) / sigma_min+(B stacked). If lambda_max(G_X)
    plus that bound times ||G_Y||_F is negative, no feasible point exists. Z (the solver's duals) is
    first made PSD (eigenvalues clipped, then shifted by its rounding), and the floating-point error
    of the sums is added: the check is independent of the solver, which only proposes Z.
    """
    eps = np.finfo(float).eps
    V, n, m = B.shape
    w, U = np.linalg.eigh((Z + Z.transpose(0, 2, 1)) / 2)
    Z = (U * np.clip(w, 0.0, None)[:, None, :]) @ U.transpose(0, 2, 1)
    size = np.abs(w).max(axis=1)
    shift = np.clip(-np.linalg.eigvalsh(Z).min(axis=1), 0.0, None) + 32 * n * eps * size   # Z_v + shift_v I >= 0
    P, Q, R = Z[:, :n, :n], Z[:, n:, :n], Z[:, n:, n:]
    AQ = A.transpose(0, 2, 1) @ Q
    G_X = (lam ** 2 * P + R + AQ + AQ.transpose(0, 2, 1)).sum(axis=0)
    G_Y = 2 * (B.transpose(0, 2, 1) @ Q).sum(axis=0)
    a = np.linalg.norm(A, ord=2, axis=(1, 2))
    rounding = 32 * n * eps * float(np.sum(size * (lam ** 2 + 1 + 2 * a)) + np.abs(G_X).sum())
    sigma = np.linalg.svd(B.reshape(V * n, m), compute_uv=False)
    seen = sigma > 1e-12 * sigma.max(initial=0.0)
    y_bound = np.sqrt(seen.sum() * V) * (lam + a.max()) / sigma[seen].min() if seen.any() else 0.0
    total = (np.linalg.eigvalsh(G_X).max() + shift.sum() * (lam ** 2 + 1) + rounding
             + (np.linalg.norm(G_Y) + 32 * n * eps * float(np.sum(size * np.linalg.norm(B, axis=(1, 2))))) * y_bound)
    return bool(np.isfinite(total) and total < 0)


def vertex_floor(system: AffineRandomSystem, vertices: np.ndarray, steps: int = FLOOR_STEPS) -> float:
    """A proven lower bound on the box rate of every gain (SDP-free): the largest of policy iteration's
    lam_lower for xi distributed on the vertices (V, p) with weights w, over the weights tried.

    A box certificate (F, X) at lambda gives Acl(v)^T X^-1 Acl(v) <= lambda^2 X^-1 at every vertex, so
    E_w[Acl^T P Acl] <= lambda^2 P (P = X^-1) for every w: lambda is at least that distribution's
    mean-square rate of F, hence at least its optimal one. Any w gives a bound, so the weights are only
    ascended, from uniform, by exponentiated gradient: E_w[Acl (x) Acl] = sum_v w_v Acl_v (x) Acl_v is
    linear in w, and at the optimal loop of w the Perron root rho = lam^2 has d rho / d w_v =
    <X, Acl_v^T P Acl_v> / <X, P> (P, X its left and right Perron vectors). steps: weight vectors
    tried; the ascent stops early once the bound reaches 1 or the gradient is not finite."""
    A, B, _, _ = system.at(vertices)
    w = np.full(len(vertices), 1.0 / len(vertices))
    best = 0.0
    for _ in range(steps):
        mean = w @ vertices
        dev = vertices - mean
        res = policy_iteration(system, MomentModel(mean=mean, cov=(dev.T * w) @ dev))
        best = max(best, res.lam_lower)                  # policy iteration's lam_lower is finite, >= 0
        if best >= 1:
            break
        Acl = A + B @ res.F                                                  # (V, n, n)
        factors = np.sqrt(w)[:, None, None] * Acl
        rho, P = perron(factors, adjoint=True)
        _, X = perron(factors)
        overlap = float(np.sum(X * P))
        if not (rho > 0 and overlap > 0 and np.all(np.isfinite(P)) and np.all(np.isfinite(X))):
            break
        grad = np.einsum("ij,vij->v", X, Acl.transpose(0, 2, 1) @ P @ Acl) / overlap
        step = np.clip(FLOOR_STEP_SIZE * (grad / rho - 1), -30.0, 30.0)  # sum_v w_v grad_v = rho
        if not np.all(np.isfinite(step)):
            break
        w = w * np.exp(step)
        w /= w.sum()
    return float(best)


def box_bisection(system: AffineRandomSystem, vertices: np.ndarray, *, tol: float, max_iter: int) -> dict:
    """Smallest certified box rate over the vertex LMIs, by bisection on lambda^2.

    Starts at lambda = 1 (quadratic stabilizability) with the proven `vertex_floor` as lower end (no
    solve when it is >= 1), then halves [lo, hi] in lambda^2. Upper end hi: the certified `box_rate` of
    the best (F, X) in hand (often below the trial that produced it). A trial whose (F, X) does not
    certify it moves the bisection's lower end lo there, and the proven lower end `proven` too where
    `infeasibility_proven` holds. Unlike `certified_bisection` no probe just below hi: the
    margin-maximising solve returns gains whose box rate is only slightly below the trial, so such
    probes creep. Returns {F, X, hi, lo, proven, solves}; F None when no gain certifies any rate.
    """
    solve, (A, B, _, _) = _solver(system, vertices), system.at(vertices)
    F_best = X_best = None
    proven = vertex_floor(system, vertices)
    hi, lo, trial, solves = np.inf, proven, 1.0, 0
    while solves < max_iter and lo < 1:
        F, X, Z = solve(trial)
        solves += 1
        rate = box_rate(system, vertices, F, X) if F is not None else np.inf
        if rate < hi:                                          # any (F, X) certifies its own rate
            hi, F_best, X_best = rate, F, X
        if rate > trial:
            lo = min(trial, hi)
            if Z is not None and infeasibility_proven(A, B, trial, Z):
                proven = max(proven, trial)
        lo = min(lo, hi)                                       # a gain beat an unproven lower end
        if hi - lo <= tol or lo >= 1:                          # bracketed, or no box rate below 1
            break
        trial = float(np.sqrt((lo ** 2 + hi ** 2) / 2))
    return {"F": F_best, "X": X_best, "hi": hi, "lo": lo, "proven": min(proven, hi), "solves": solves}


def max_feasible_width(system: AffineRandomSystem, dist: MomentModel, *, rel_tol: float = 1e-3) -> tuple[float, float]:
    """(largest width certified quadratically stabilizable, smallest width proven not), the box mean +- width * std.

    Nested boxes: certified feasibility at lambda = 1 and proven infeasibility are both monotone in
    the width, so doubling then bisection brackets each boundary (to rel_tol); the proven one is
    searched from the first width not certified, since between the two lie widths that neither a
    gain certifies nor a proof excludes. Second value inf when nothing up to MAX_WIDTH is proven
    infeasible (first value NaN when even width 0 is not certified).
    """
    @cache
    def status(width: float) -> str:
        pts = box_vertices(dist, width)
        if vertex_floor(system, pts) >= 1:
            return "infeasible"
        F, X, Z = _solver(system, pts)(1.0)
        if F is not None and box_rate(system, pts, F, X) < 1:
            return "feasible"
        A, B, _, _ = system.at(pts)
        return "infeasible" if Z is not None and infeasibility_proven(A, B, 1.0, Z) else "unknown"

    def crossing(turned, start: float, below: float) -> tuple[float, float]:
        """(below, above) around the width where turned(width) becomes true: doubling from start,
        then bisection; above inf when it stays false up to MAX_WIDTH."""
        width = start
        while not turned(width):
            below, width = width, 2 * width
            if width > MAX_WIDTH:
                return below, np.inf
        above = width
        while above - below > rel_tol * max(below, 1.0):
            mid = (below + above) / 2
            below, above = (below, mid) if turned(mid) else (mid, above)
        return below, above

    first = status(0.0)
    if first != "feasible":
        return float("nan"), 0.0 if first == "infeasible" else float("nan")
    lo, upper = crossing(lambda w: status(w) != "feasible", 1.0, 0.0)
    if not np.isfinite(upper):
        return float(lo), float("inf")
    return float(lo), float(crossing(lambda w: status(w) == "infeasible", upper, lo)[1])


def robust_box(system, dist, *, width=None, vertices=None, find_max_width: bool = False, tol: float = 1e-4,
               max_iter: int = 60, x_cond_limit: float = 1e6):
    """Quadratic stabilization on the box mean +- width * std (default width 1) or the hull of `vertices` (V, p).

    Status `box_optimal` (the smallest box rate, bracketed to tol with a proven lower end: 1e-4 by
    default, since each bisection step is an SDP with 2^p blocks and the box rate is a design bound;
    lam is exact anyway), `infimum_not_attained` (the bracket closes at 0 or X degenerates, e.g. a
    controllable single point), `not_converged` (the bisection closed to tol but its lower end is not
    proven: the LMIs below are only weakly infeasible; or no gain certifies a box rate below 1 and
    infeasibility is not proven either, F None), `infeasible` (proven not quadratically stabilizable
    on the set: F None), `solver_failed`. lam: exact mean-square rate of F on `dist`; info: lam_box
    (certified by the gain and X), lam_box_lower (proven), lam_box_bisection_lower (where the
    bisection's gains stopped certifying their trials; not a proof), X, vertices, solves; with
    find_max_width, max_width (certified) and min_infeasible_width (proven).
    """
    if vertices is None:
        width = 1.0 if width is None else float(width)
        pts = box_vertices(dist, width)
    else:
        pts = np.unique(np.asarray(vertices, dtype=float).reshape(-1, system.p), axis=0)
    found = box_bisection(system, pts, tol=tol, max_iter=max_iter)
    F, X, hi, lo, proven = found["F"], found["X"], found["hi"], found["lo"], found["proven"]
    info = {"lam_box": float(hi), "lam_box_lower": float(proven), "lam_box_bisection_lower": float(lo),
            "vertices": len(pts), "solves": found["solves"]}
    if vertices is None:
        info["width"] = width
    if find_max_width:
        info["max_width"], info["min_infeasible_width"] = max_feasible_width(system, dist)
    nbar = system.Gbar(dist).shape[0]
    if hi >= 1:
        status = "infeasible" if proven >= 1 else "not_converged" if np.isfinite(hi) else "solver_failed"
        return SynthesisResult("robust_box", None, float("nan"), status, nbar, info=info)
    info["X"], info["cond_X"] = X, float(np.linalg.cond(X))
    if lo <= tol or (hi - proven > tol and info["cond_X"] > x_cond_limit):
        status = "infimum_not_attained"
    elif hi - proven <= tol:
        status = "box_optimal"
    elif hi - lo <= tol:
        status = "not_converged"
    else:
        status = "solver_failed"
    return SynthesisResult("robust_box", F, ms_rate(system, dist, F), status, nbar, info=info)


def _check(options: dict, system: AffineRandomSystem) -> None:
    """One-line ValueError for bad robust_box options (before any work)."""
    for name in ("tol", "max_iter", "x_cond_limit"):
        _positive(name, options.get(name, 1))
    if "width" in options:
        w = options["width"]
        if not (_is_number(w) and w >= 0):
            raise ValueError(f"width: {w!r} is not allowed, expected a number >= 0")
    if not isinstance(options.get("find_max_width", False), bool):
        raise ValueError(f"find_max_width: {options['find_max_width']!r} is not allowed, expected true or false")
    if options.get("vertices") is not None:
        if "width" in options or options.get("find_max_width"):
            raise ValueError("vertices: give either vertices or width/find_max_width, not both")
        try:
            pts = np.asarray(options["vertices"], dtype=float)
        except (TypeError, ValueError):
            pts = np.zeros((0,))
        if pts.ndim != 2 or pts.shape[1] != system.p or not 1 <= len(pts) <= MAX_VERTICES \
                or not np.all(np.isfinite(pts)):
            raise ValueError(f"vertices: {options['vertices']!r} is not allowed, expected 1..{MAX_VERTICES} finite "
                             f"points of length p = {system.p}")
    elif 2 ** system.p > MAX_VERTICES:
        raise ValueError(f"robust_box: the box has 2^{system.p} vertices, more than {MAX_VERTICES}; give `vertices`")


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and bool(np.isfinite(v))


def _positive(name: str, v) -> None:
    if not (_is_number(v) and v > 0):
        raise ValueError(f"{name}: {v!r} is not allowed, expected a number > 0")


robust_box.check_options = _check
