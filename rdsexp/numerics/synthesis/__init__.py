"""State-feedback gain synthesis u = F x, selected by method name (paper Sec. II-B, V-B).

One module per family of methods:
- `lmi`: `proposed` (Theorem 2, the mean-square optimal decay rate) and `nominal_lmi` (xi at its
  mean), both through the certified bisection of `bisection`;
- `riccati`: `policy_iteration` (SDP-free optimal rate, cross-checks the LMI) and `lqr_mean`;
- `classical`: `pole_placement` on the mean model;
- `robust`: `robust_box`, quadratic stabilization on a box / polytope of xi (what Sec. V-B argues against);
- `lq`: `ms_lqr`, the mean-square LQ optimal gain (generalized Riccati equation).

Every method returns a `SynthesisResult`; numerical outcomes (not stabilizable, solver failure)
are statuses, bad arguments raise ValueError before any work.
"""
from __future__ import annotations

import time

import numpy as np

from ..systems import AffineRandomSystem, MomentModel
from .base import STATUSES, SynthesisResult, status_meaning
from .classical import check_poles, pole_placement
from .lmi import nominal_lmi, proposed
from .lq import ms_lqr
from .riccati import lqr_mean, policy_iteration
from .robust import robust_box

METHODS = {
    "proposed": proposed,
    "nominal_lmi": nominal_lmi,
    "pole_placement": pole_placement,
    "lqr_mean": lqr_mean,
    "policy_iteration": policy_iteration,
    "robust_box": robust_box,
    "ms_lqr": ms_lqr,
}
# what a design may raise on a system it cannot handle numerically (LinAlgError, ArpackError and
# cvxpy's SolverError derive from these); a failure becomes the status `failed: <reason>`
NUMERICAL_FAILURES = (np.linalg.LinAlgError, ArithmeticError, RuntimeError)
POSITIVE_OPTIONS = ("tol", "max_iter", "x_cond_limit", "state_weight", "input_weight")

__all__ = ["METHODS", "STATUSES", "SynthesisResult", "check_options", "check_poles", "status_meaning", "synthesize"]


def synthesize(system: AffineRandomSystem, dist: MomentModel | None, method: str = "proposed",
               **options) -> SynthesisResult:
    """Design F for `system` with xi ~ `dist` by `method` (see METHODS); options go to the method."""
    check_options(method, options, system)
    dist = system.check_distribution(dist)
    design = METHODS[method]
    start = time.perf_counter()
    try:
        res = design(system, dist, **options)
    except NUMERICAL_FAILURES as err:           # arguments were checked above: this is the system's numerics
        text = str(err).strip().splitlines()
        res = SynthesisResult(method, None, float("nan"), f"failed: {type(err).__name__}: {text[0] if text else ''}",
                              nbar=system.Gbar(dist).shape[0])
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
    if hasattr(METHODS[method], "check_options"):          # a method with structured options checks them itself
        return METHODS[method].check_options(options, system)
    for name, value in options.items():
        if name == "poles" and value is not None:
            check_poles(value, system)
        elif name == "seed" and not isinstance(value, bool):
            raise ValueError(f"seed: {value!r} is not allowed, expected true or false")
        elif name in POSITIVE_OPTIONS and not (isinstance(value, (int, float)) and not isinstance(value, bool)
                                               and np.isfinite(value) and value > 0):
            raise ValueError(f"{name}: {value!r} is not allowed, expected a number > 0")
