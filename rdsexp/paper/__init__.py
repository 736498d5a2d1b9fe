"""The paper's numerical example (Sec. V): true plant, system model, EnKF settings, reported numbers.

Plant (eqs. co-state, co-output): three second-order subsystems G1-G3 in a ring, state
q = [x'_1; x'_2; x'_3] in R^6, random coefficients s = [s1, s2] with s1 ~ N(0.8, 0.2^2),
s2 ~ N(0.2, 0.3^2) i.i.d. System model (eq. sysmodel-coef): the same structure with the unknown
entries replaced by xi = [xi1, xi2, xi3], standing for [0.7 s1, s2, 0.6].
"""
from __future__ import annotations

import numpy as np

from ..numerics.systems import AffineRandomSystem, MomentModel

n, m, ny = 6, 1, 3


def _E(i: int, j: int) -> np.ndarray:
    """Matrix unit with a one at the paper's (1-based) entry (i, j)."""
    M = np.zeros((n, n))
    M[i - 1, j - 1] = 1.0
    return M


# A(xi) of eq. (sysmodel-coef) without its unknown entries
_A_KNOWN = np.array([
    [0, -0.4, 0, 0, 0, 0],
    [1, 1.3, 0, 0, 0, 0.4],
    [0, 0, 0, 0, 0, 0],
    [0, 0.4, 1, 0, 0, 0],
    [0, 0, 0, 0, 0, -0.8],
    [0, 0, 0, 0, 1, 0],
], dtype=float)
_B = np.array([[0], [0.4], [0], [0], [0], [0]], dtype=float)
_C = np.array([[0, 1, 0, 0, 0, 0], [0, 0, 0, 1, 0, 0], [0, 0, 0, 0, 0, 1]], dtype=float)


def model() -> AffineRandomSystem:
    """System model of eq. (sysmodel-coef): xi1 at (4,4), xi2 at (6,4) and (6,6), -xi3 at (3,4)."""
    return AffineRandomSystem(A=[_A_KNOWN, _E(4, 4), _E(6, 4) + _E(6, 6), -_E(3, 4)], B=[_B], C=[_C])


def plant() -> AffineRandomSystem:
    """True plant of eqs. (co-state), (co-output) in s = [s1, s2], with xi_dist the law of s.

    A2 = [[0, -0.6], [1, 0.7 s1]], A3 = [[0, -0.8], [1, s2]], B3 C2 = [[0, 0], [0, s2]]:
    the model with xi = [0.7 s1, s2, 0.6].
    """
    A0 = _A_KNOWN - 0.6 * _E(3, 4)
    s = MomentModel(mean=[0.8, 0.2], cov=np.diag([0.04, 0.09]))             # 0.2^2, 0.3^2
    return AffineRandomSystem(A=[A0, 0.7 * _E(4, 4), _E(6, 4) + _E(6, 6)], B=[_B], C=[_C], xi_dist=s)


# ------------------------------------------------------------------ settings of Sec. V-A and V-B
q0 = np.ones(n)                                   # plant initial state
psi0 = np.zeros(n + 3)                            # EnKF initial value [x0; xi0]
ensemble_size = 300                               # M
R = 0.01 * np.eye(ny)
Q = 0.01 * np.diag([1, 1, 1, 1, 1, 1, 2, 2, 2])
horizon = 100                                     # k = 0..100
K0, K1 = 20, 80                                   # modeling window k = K0..K0+K1
paths = 200


def disturbance(horizon: int = horizon, amplitude: float = 10.0, until: int = 50) -> np.ndarray:
    """d_k = amplitude for 0 <= k < until, 0 after; shape (horizon+1, m), added on u_k."""
    d = np.zeros((horizon + 1, m))
    d[:until] = amplitude
    return d


# ------------------------------------------------------------------ numbers the paper reports
xi_mean = np.array([0.4403, 0.1739, 0.5003])      # eq. (ex-mean)
xi_cov = np.array([[0.0192, -0.0039, 0.0081],     # eq. (ex-covar)
                   [-0.0039, 0.0750, -0.0006],
                   [0.0081, -0.0006, 0.0205]])
lam_proposed, nbar_proposed = 0.8432, 4
F_proposed = np.array([[-2.4986, -4.8035, -3.8835, 2.2159, 5.2592, 4.6178]])
poles = (0.9, 0.8, 0.7, 0.6, 0.5, 0.4)
F_pole_placement = np.array([[-1.5556, 4.9645, 12.1698, -16.8991, -71.3356, 24.6177]])
lam_nominal_lmi = 0.1143
rate_k60_k80 = 0.8473


def modeled_distribution() -> MomentModel:
    """The paper's modeled distribution of xi, eqs. (ex-mean), (ex-covar)."""
    return MomentModel(mean=xi_mean, cov=xi_cov)
