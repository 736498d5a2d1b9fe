"""Mean-square LQ (ms_lqr), robust box design (robust_box), exact LQ cost and H2 norm.

Every property is checked against an independent computation: the DARE (scipy), the generalized
Riccati equation written with E[[1; xi][1; xi]^T] instead of Gbar, dense vertex LMIs built here,
and a Monte Carlo of the random closed loop written here.
"""
import itertools

import numpy as np
import pytest
import scipy.linalg

import rdsexp as rx
from rdsexp.numerics.analysis import cost_matrix, h2_norm, lq_cost
from rdsexp.numerics.synthesis import robust
from rdsexp.numerics.synthesis.robust import box_vertices


def random_system(rng, n, m, p, cov_scale=0.5, a_scale=1.0):
    """Random affine system and moments (cov_scale 0: deterministic xi)."""
    A = [a_scale * rng.normal(size=(n, n)) / np.sqrt(n)] + [0.4 * rng.normal(size=(n, n)) / np.sqrt(n)
                                                             for _ in range(p)]
    B = [rng.normal(size=(n, m))] + [0.3 * rng.normal(size=(n, m)) for _ in range(p)]
    L = rng.normal(size=(p, p)) * cov_scale
    return rx.AffineRandomSystem(A=A, B=B), rx.MomentModel(mean=rng.normal(size=p) * 0.3, cov=L @ L.T)


def expect(M, N, P, W):
    """E[M(xi)^T P N(xi)] = sum_ij W_ij M_i^T P N_j, W = E[[1; xi][1; xi]^T] (not through Gbar)."""
    return np.einsum("ij,iba,bc,jcd->ad", W, M, P, N)


def dense_cost_matrix(system, dist, F, Q, R):
    """P = Q + F'RF + E[Acl' P Acl] by a dense Kronecker solve (column-major vec), for comparison."""
    W, n = dist.augmented_second_moment, system.n
    Acl = system.A + system.B @ F
    L = sum(W[i, j] * np.kron(Acl[j].T, Acl[i].T) for i in range(len(W)) for j in range(len(W)))
    return np.linalg.solve(np.eye(n * n) - L, (Q + F.T @ R @ F).ravel(order="F")).reshape(n, n, order="F")


# ------------------------------------------------------------------------------------------- ms_lqr
@pytest.mark.parametrize("seed", range(5))
def test_ms_lqr_is_the_dare_gain_without_covariance(seed):
    rng = np.random.default_rng(seed)
    n, m = int(rng.integers(1, 5)), int(rng.integers(1, 3))
    system, dist = random_system(rng, n, m, p=2, a_scale=1.5)       # open loops often unstable
    dist = rx.MomentModel.deterministic(dist.mean)
    Q = np.eye(n) + (G := rng.normal(size=(n, n))) @ G.T if seed % 2 else 2.0
    res = rx.synthesize(system, dist, "ms_lqr", state_weight=Q, input_weight=0.5)
    A, B, _, _ = system.at(dist.mean)
    Qm = Q * np.eye(n) if np.isscalar(Q) else Q
    P = scipy.linalg.solve_discrete_are(A, B, Qm, 0.5 * np.eye(m))
    F = -np.linalg.solve(0.5 * np.eye(m) + B.T @ P @ B, B.T @ P @ A)
    assert res.status == "optimal"
    np.testing.assert_allclose(res.F, F, rtol=1e-8, atol=1e-9)
    assert res.lam == pytest.approx(np.abs(np.linalg.eigvals(A + B @ res.F)).max(), abs=1e-9)
    assert res.info["cost_trace"] == pytest.approx(np.trace(P), rel=1e-9)


@pytest.mark.parametrize("seed", range(6))
def test_ms_lqr_solves_generalized_riccati_and_is_minimal(seed):
    rng = np.random.default_rng(100 + seed)
    n, m, p = int(rng.integers(2, 5)), int(rng.integers(1, 3)), int(rng.integers(1, 4))
    system, dist = random_system(rng, n, m, p, a_scale=1.3)
    Q, R = np.eye(n), np.eye(m)
    res = rx.synthesize(system, dist, "ms_lqr")
    if res.status == "not_ms_stabilizable":
        assert res.F is None and rx.synthesize(system, dist, "policy_iteration").lam >= 1 - 1e-9
        return
    assert res.status == "optimal" and res.lam < 1
    assert res.lam == pytest.approx(rx.ms_rate(system, dist, res.F), abs=1e-15)
    W = dist.augmented_second_moment
    P = dense_cost_matrix(system, dist, res.F, Q, R)
    A, B = system.A, system.B
    residual = Q + expect(A, A, P, W) - expect(A, B, P, W) @ np.linalg.solve(R + expect(B, B, P, W),
                                                                             expect(B, A, P, W)) - P
    assert np.abs(residual).max() <= 1e-9 * np.abs(P).max()
    best = lq_cost(system, dist, res.F)
    assert best == pytest.approx(np.trace(P), rel=1e-9)
    for scale in (1e-4, 1e-2, 1e-1):
        for _ in range(10):
            assert lq_cost(system, dist, res.F + scale * rng.normal(size=res.F.shape)) >= best * (1 - 1e-12)


def test_ms_lqr_not_ms_stabilizable_is_a_status():
    """x+ = (1.1 + xi) x + 0 u: no gain has a finite cost."""
    system = rx.AffineRandomSystem(A=[[[1.1]], [[1.0]]], B=[[[0.0]]])
    res = rx.synthesize(system, rx.MomentModel(mean=[0.0], cov=[[0.25]]), "ms_lqr")
    assert (res.status, res.F) == ("not_ms_stabilizable", None)


# ------------------------------------------------------------------------------ exact cost and H2 norm
def test_cost_scalar_closed_form_and_instability():
    """x+ = (a0 + xi) x + (b0 + xi) u: J = (q + r f^2) x0^2 / (1 - E[acl^2]); inf when E[acl^2] >= 1."""
    system = rx.AffineRandomSystem(A=[[[0.9]], [[1.0]]], B=[[[0.5]], [[1.0]]])
    dist = rx.MomentModel(mean=[0.0], cov=[[0.09]])
    f = -0.7
    s = (0.9 + 0.5 * f) ** 2 + (1 + f) ** 2 * 0.09
    assert lq_cost(system, dist, [[f]], [2.0], state_weight=3.0, input_weight=0.5) == \
        pytest.approx(4 * (3 + 0.5 * f ** 2) / (1 - s), rel=1e-13)
    assert h2_norm(system, dist, [[f]]) == pytest.approx(np.sqrt((1 + f ** 2) * (0.25 + 0.09) / (1 - s)), rel=1e-13)
    assert lq_cost(system, dist, [[1.0]]) == np.inf and h2_norm(system, dist, [[1.0]]) == np.inf


@pytest.mark.parametrize("seed", range(4))
def test_cost_matrix_matches_dense_kronecker(seed):
    rng = np.random.default_rng(200 + seed)
    system, dist = random_system(rng, int(rng.integers(1, 5)), 2, int(rng.integers(0, 3)), a_scale=0.6)
    F = 0.1 * rng.normal(size=(2, system.n))
    if rx.ms_rate(system, dist, F) >= 1:
        assert np.all(cost_matrix(system, dist, F) == np.inf)
        return
    Q = np.diag(rng.uniform(0.5, 2, system.n))
    np.testing.assert_allclose(cost_matrix(system, dist, F, state_weight=Q, input_weight=3.0),
                               dense_cost_matrix(system, dist, F, Q, 3 * np.eye(2)), rtol=1e-10, atol=1e-12)


def monte_carlo_cost(system, dist, F, x0, steps, rng):
    """Per-path sum_{k<steps} x'x + u'u of x+ = A(xi) x + B(xi) F x, x0 (P, n), written independently."""
    x, total = x0.copy(), np.zeros(len(x0))
    for _ in range(steps):
        u = x @ F.T
        total += np.sum(x ** 2, axis=1) + np.sum(u ** 2, axis=1)
        A, B, _, _ = system.at(dist.sample(rng, (len(x),)))
        x = np.einsum("pij,pj->pi", A, x) + np.einsum("pij,pj->pi", B, u)
    return total


@pytest.mark.parametrize("case", ["paper", "random"])
def test_exact_costs_match_monte_carlo(case):
    """x0^T P x0, trace(P) (x0 ~ N(0, I)) and the H2 norm (impulse on the input) against 4000 paths:
    within 4.5 standard errors; the horizon makes the neglected tail < 1e-9 of the cost."""
    rng = np.random.default_rng(7)
    if case == "paper":
        system, dist = rx.paper.plant(), rx.paper.plant().xi_dist
        F = rx.synthesize(rx.paper.model(), rx.paper.modeled_distribution(), "ms_lqr").F
        x0 = np.asarray(rx.paper.q0, dtype=float)
    else:
        system, dist = random_system(np.random.default_rng(3), 3, 2, 2, a_scale=0.8)
        F = rx.synthesize(system, dist, "ms_lqr").F
        x0 = np.array([1.0, -2.0, 0.5])
    lam = rx.ms_rate(system, dist, F)
    steps = int(np.ceil(np.log(1e-9) / (2 * np.log(lam)))) + 1
    P = 4000
    checks = [(lq_cost(system, dist, F, x0), np.broadcast_to(x0, (P, system.n))),
              (lq_cost(system, dist, F), rng.standard_normal((P, system.n)))]
    for exact, start in checks:
        sample = monte_carlo_cost(system, dist, F, start, steps, rng)
        assert abs(sample.mean() - exact) <= 4.5 * sample.std(ddof=1) / np.sqrt(P)
    # H2: a unit impulse in input channel i at k = 0 gives x_1 = B(xi_0) e_i; the norm^2 sums over i
    h2sq = var = 0.0
    for i in range(system.m):
        _, B, _, _ = system.at(dist.sample(rng, (P,)))
        sample = monte_carlo_cost(system, dist, F, B[:, :, i], steps, rng)
        h2sq, var = h2sq + sample.mean(), var + sample.var(ddof=1) / P
    assert abs(h2sq - h2_norm(system, dist, F) ** 2) <= 4.5 * np.sqrt(var)


# ---------------------------------------------------------------------------------------- robust_box
def vertex_lmi_min_eig(system, dist, width, F, X, lam):
    """Smallest eigenvalue over the box vertices of [[lam^2 X, (A X + B Y)^T], [A X + B Y, X]], Y = F X,
    with the vertices and A(v), B(v) built here from the basis matrices."""
    std = np.sqrt(np.diag(dist.cov))
    worst = np.inf
    for signs in itertools.product((-1.0, 1.0), repeat=dist.p):
        v = dist.mean + width * np.array(signs) * std
        A = system.A[0] + np.tensordot(v, system.A[1:], axes=1)
        B = system.B[0] + np.tensordot(v, system.B[1:], axes=1)
        H = A @ X + B @ (F @ X)
        M = np.block([[lam ** 2 * X, H.T], [H, X]])
        worst = min(worst, np.linalg.eigvalsh((M + M.T) / 2).min())
    return worst


@pytest.mark.parametrize("seed", range(4))
def test_robust_box_gain_satisfies_the_lmi_at_every_vertex_and_widening_never_helps(seed):
    rng = np.random.default_rng(300 + seed)
    system, dist = random_system(rng, int(rng.integers(2, 4)), 1, 2, a_scale=1.0)
    previous = None
    for width in (0.0, 0.5, 1.0, 2.0):
        res = rx.synthesize(system, dist, "robust_box", width=width)
        lam_box = res.info["lam_box"]
        if res.F is None:                                 # proven infeasible, or undecided at lambda = 1
            assert res.status in ("infeasible", "not_converged") and lam_box >= 1
            assert (res.info["lam_box_lower"] >= 1) == (res.status == "infeasible")
        else:
            assert res.status in ("box_optimal", "infimum_not_attained", "not_converged")
            X = res.info["X"]
            assert np.linalg.eigvalsh(X).min() > 0
            assert vertex_lmi_min_eig(system, dist, width, res.F, X, lam_box) >= -1e-9 * np.abs(X).max()
            assert res.lam == pytest.approx(rx.ms_rate(system, dist, res.F), abs=1e-15)
            assert (res.status == "box_optimal") == (lam_box - res.info["lam_box_lower"] <= 1e-4)
        assert res.info["lam_box_lower"] <= res.info["lam_box_bisection_lower"] <= lam_box
        if previous is not None:                          # box(previous) is inside box(width): proven ends grow
            assert lam_box >= previous.info["lam_box_lower"] - 1e-9
            if previous.status == "infeasible":
                assert res.status == "infeasible"
        previous = res


def box_systems():
    """Random and degenerate (system, vertices): B = 0, a single vertex, two equal inputs (B stacked of
    rank 1), large A, p = 1, an unstabilizable box."""
    rng = np.random.default_rng(77)
    out = []
    for k in range(4):
        system, dist = random_system(rng, int(rng.integers(2, 4)), int(rng.integers(1, 3)), 2, a_scale=1.2)
        out.append((system, box_vertices(dist, 0.5 + 0.5 * k)))
    system, dist = random_system(rng, 3, 1, 2, a_scale=0.9)
    out.append((rx.AffineRandomSystem(A=system.A, B=np.zeros_like(system.B)), box_vertices(dist, 1.0)))
    out.append((system, dist.mean[None, :]))
    b = rng.normal(size=(3, 3, 1))
    out.append((rx.AffineRandomSystem(A=system.A, B=np.concatenate([b, b], axis=2)), box_vertices(dist, 1.0)))
    out.append((rx.AffineRandomSystem(A=100 * system.A, B=system.B), box_vertices(dist, 1.0)))
    system, dist = random_system(rng, 2, 1, 1, a_scale=1.5)
    out.append((system, box_vertices(dist, 1.0)))
    out.append((system, box_vertices(dist, 8.0)))
    return out


@pytest.mark.parametrize("case", range(10))
def test_box_lower_ends_are_never_above_a_certified_box_rate(case):
    """Soundness of the two proofs of robust_box's lower end, against certificates checked independently.

    The vertex LMIs are solved over a grid of lambda; every (F, X) that comes back certifies its own
    box rate (`box_rate`, no solver). Every lambda the dual check proves infeasible, the vertex floor
    and robust_box's lam_box_lower stay below the smallest such rate. At a lambda certified feasible,
    no dual matrix passes the check: not the solver's from any trial lambda, nor random PSD ones."""
    system, vertices = box_systems()[case]
    A, B, _, _ = system.at(vertices)
    solve = robust._solver(system, vertices)
    grid = np.linspace(0.05, 1.6, 12)
    trials = [(lam, *solve(lam)) for lam in grid]
    rates = [robust.box_rate(system, vertices, F, X) for _, F, X, _ in trials if F is not None]
    res = rx.synthesize(system, rx.MomentModel(mean=vertices.mean(0), cov=np.eye(system.p)), "robust_box",
                        vertices=vertices)
    best = min(rates + [res.info["lam_box"]])
    assert res.info["lam_box_lower"] <= best and robust.vertex_floor(system, vertices) <= best
    duals = [Z for *_, Z in trials if Z is not None]
    rng = np.random.default_rng(case)
    duals += [G @ G.transpose(0, 2, 1) for G in rng.normal(size=(5, len(vertices), 2 * system.n, 2 * system.n))]
    proven = [lam for lam, _, _, Z in trials if Z is not None and robust.infeasibility_proven(A, B, lam, Z)]
    assert all(lam < best for lam in proven)
    for lam in grid[grid >= best]:
        assert not any(robust.infeasibility_proven(A, B, lam, Z) for Z in duals), lam


def test_box_proofs_where_they_apply():
    """On a random box the dual check proves the lower end (box_optimal, bracket <= tol); on a box too
    wide for any gain it proves infeasibility; where even uniform xi on the vertices is not mean-square
    stabilizable the floor proves it without a solve; the paper's boxes are weakly infeasible below
    their optimum (the margin reaches -2e-9 with singular X), so nothing proves the lower end there."""
    rng = np.random.default_rng(5)
    systems = [random_system(rng, 4, int(rng.integers(1, 4)), int(rng.integers(1, 5))) for _ in range(3)]
    statuses = [rx.synthesize(s, d, "robust_box", width=1.0) for s, d in systems]
    assert statuses[0].status == "infeasible" and statuses[0].info["solves"] == 0          # the floor
    assert statuses[1].status == "infeasible" and statuses[1].info["solves"] == 1          # the dual check
    assert statuses[1].info["lam_box_lower"] == 1 > robust.vertex_floor(systems[1][0], box_vertices(systems[1][1], 1))
    assert statuses[2].status == "box_optimal"
    paper = rx.synthesize(rx.paper.model(), rx.paper.modeled_distribution(), "robust_box", width=1.0)
    assert paper.status == "not_converged" and paper.info["lam_box_lower"] < paper.info["lam_box"] - 0.01
    uniform = robust.vertex_floor(rx.paper.model(), box_vertices(rx.paper.modeled_distribution(), 1.0), steps=1)
    assert paper.info["lam_box_lower"] > uniform + 0.03           # the ascent over vertex weights tightens it


@pytest.mark.parametrize("seed", range(3))
def test_robust_box_width_zero_equals_nominal_lmi(seed):
    """An uncontrollable mode at 0.7 (hidden by a random similarity) makes the LTI optimum 0.7 and attained."""
    rng = np.random.default_rng(400 + seed)
    Ac, Bc = rng.normal(size=(2, 2)), rng.normal(size=(2, 1))
    A0 = np.block([[Ac, rng.normal(size=(2, 1))], [np.zeros((1, 2)), np.array([[0.7]])]])
    T = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    system = rx.AffineRandomSystem(A=[T @ A0 @ T.T, 0.3 * rng.normal(size=(3, 3))],
                                   B=[T @ np.vstack([Bc, [[0.0]]]), np.zeros((3, 1))])
    dist = rx.MomentModel(mean=[0.0], cov=[[0.04]])                 # A(mean) = T A0 T^T
    box = rx.synthesize(system, dist, "robust_box", width=0.0, tol=1e-7)
    nominal = rx.synthesize(system, dist, "nominal_lmi")
    assert box.status == "box_optimal" and nominal.status == "optimal_on_mean_model"
    assert box.info["lam_box"] == pytest.approx(nominal.lam, abs=1e-4)
    assert box.info["lam_box"] == pytest.approx(0.7, abs=1e-4) and box.info["lam_box"] >= 0.7 - 1e-9
    A, B, _, _ = system.at(dist.mean)
    assert np.abs(np.linalg.eigvals(A + B @ box.F)).max() <= box.info["lam_box"] + 1e-12


def test_robust_box_on_paper_model_width_zero_is_the_nominal_case():
    """On the paper's controllable mean model both designs approach dead beat (infimum 0, not attained)."""
    system, dist = rx.paper.model(), rx.paper.modeled_distribution()
    box = rx.synthesize(system, dist, "robust_box", width=0.0)
    nominal = rx.synthesize(system, dist, "nominal_lmi")
    assert box.status == "infimum_not_attained" and nominal.status == "infimum_not_attained_on_mean_model"
    assert box.info["vertices"] == 1
    assert rx.ms_rate(system, dist, box.F) > 1 and rx.ms_rate(system, dist, nominal.F) > 1


@pytest.mark.slow
def test_max_width_brackets_both_boundaries_on_the_paper_model():
    """Between the certified and the proven boundary lie widths that nothing decides (the paper's box
    LMIs are weakly infeasible), so the proven one is searched beyond the first width not certified."""
    system, dist = rx.paper.model(), rx.paper.modeled_distribution()
    lo, hi = robust.max_feasible_width(system, dist)
    assert 0 < lo < hi < np.inf
    assert rx.synthesize(system, dist, "robust_box", width=lo).F is not None
    between = rx.synthesize(system, dist, "robust_box", width=(lo + hi) / 2)
    assert between.status == "not_converged" and between.F is None
    assert rx.synthesize(system, dist, "robust_box", width=hi).status == "infeasible"


def test_robust_box_polytope_and_max_width():
    rng = np.random.default_rng(11)
    system, dist = random_system(rng, 2, 1, 2, a_scale=1.2)
    box = rx.synthesize(system, dist, "robust_box", width=0.5, find_max_width=True)
    std = np.sqrt(np.diag(dist.cov))
    corners = [dist.mean + 0.5 * np.array(s) * std for s in itertools.product((-1, 1), repeat=2)]
    poly = rx.synthesize(system, dist, "robust_box", vertices=[list(c) for c in corners])
    assert poly.info["lam_box"] == pytest.approx(box.info["lam_box"], abs=2e-4)
    lo, hi = box.info["max_width"], box.info["min_infeasible_width"]
    assert 0 < lo < hi < np.inf and hi - lo <= 2e-3 * max(lo, 1)
    assert rx.synthesize(system, dist, "robust_box", width=lo).status != "infeasible"
    assert rx.synthesize(system, dist, "robust_box", width=hi).status == "infeasible"


@pytest.mark.parametrize("method, options, message", [
    ("robust_box", {"width": -1}, "width: -1 is not allowed"),
    ("robust_box", {"vertices": [[0.0]]}, "vertices: .* length p = 3"),
    ("robust_box", {"vertices": [[0.0, 0.0, 0.0]], "width": 1}, "either vertices or width"),
    ("robust_box", {"find_max_width": "yes"}, "find_max_width"),
    ("ms_lqr", {"state_weight": -1}, "state_weight: must be symmetric positive definite"),
    ("ms_lqr", {"state_weight": np.eye(5)}, r"state_weight: shape \(5, 5\)"),
    ("ms_lqr", {"input_weight": [[0.0]]}, "input_weight: must be symmetric positive definite"),
])
def test_bad_design_options(method, options, message):
    with pytest.raises(ValueError, match=message):
        rx.synthesize(rx.paper.model(), rx.paper.modeled_distribution(), method, **options)


# ----------------------------------------------------------------------------- pole sets, costs, table
def test_random_pole_sets_lie_in_the_disc_closed_under_conjugation_and_are_placed():
    from rdsexp.numerics.synthesis.classical import random_pole_sets
    rng = np.random.default_rng(3)
    sets = random_pole_sets(rng, 5, 300)
    assert sets.shape == (300, 5) and np.all(np.abs(sets) < 1)
    for poles in sets:                                        # the conjugates are the same multiset
        np.testing.assert_allclose(np.sort_complex(poles), np.sort_complex(poles.conj()), atol=0)
    pairs = (np.abs(sets.imag) > 0).sum(axis=1) // 2
    assert set(pairs) == {0, 1, 2}                            # every number of pairs occurs
    np.testing.assert_array_equal(sets, random_pole_sets(np.random.default_rng(3), 5, 300))
    assert random_pole_sets(rng, 1, 4).imag.max() == 0        # n = 1: real poles only
    for poles in sets[:20]:                                   # pole placement puts the mean loop there
        system, dist = random_system(rng, 5, 2, 2)
        res = rx.synthesize(system, dist, "pole_placement", poles=poles)
        A, B, _, _ = system.at(dist.mean)
        np.testing.assert_allclose(np.sort_complex(np.linalg.eigvals(A + B @ res.F)), np.sort_complex(poles),
                                   atol=1e-6)


@pytest.mark.parametrize("seed", range(3))
def test_exact_costs_equal_the_single_cost_functions(seed):
    from rdsexp.numerics.analysis import exact_costs
    rng = np.random.default_rng(300 + seed)
    system, dist = random_system(rng, 3, 2, 2, a_scale=0.5 + seed)    # seed 2: often not ms stable
    F = 0.2 * rng.normal(size=(2, 3))
    x0, Bw = rng.normal(size=3), rng.normal(size=(3, 2))
    got = exact_costs(system, dist, F, x0, state_weight=2.0, input_weight=0.5)
    assert got["lq_cost_x0"] == lq_cost(system, dist, F, x0, state_weight=2.0, input_weight=0.5)
    assert got["lq_cost"] == lq_cost(system, dist, F, state_weight=2.0, input_weight=0.5)
    assert got["h2"] == h2_norm(system, dist, F, state_weight=2.0, input_weight=0.5)
    assert exact_costs(system, dist, F, disturbance=Bw)["h2"] == h2_norm(system, dist, F, disturbance=Bw)
    assert np.isnan(exact_costs(system, dist, F)["lq_cost_x0"])


def test_gains_table_reports_the_box_width_bracket():
    from types import SimpleNamespace

    from rdsexp.experiment.pipeline.results import DesignSet
    from rdsexp.experiment.pipeline.tables import gains_table
    rng = np.random.default_rng(7)
    system, dist = random_system(rng, 2, 1, 1)
    plant = rx.AffineRandomSystem(A=system.A, B=system.B, xi_dist=dist)
    exp = SimpleNamespace(model=system, plant=plant, q0=np.ones(2))
    designs = {("identified", m): (dist, rx.synthesize(system, dist, m, **opts))
               for m, opts in (("robust_box", {"width": 0.5, "find_max_width": True}), ("ms_lqr", {}))}
    table = gains_table(exp, DesignSet(designs, ("identified", "robust_box"))).set_index("method")
    box = designs[("identified", "robust_box")][1]
    assert table.loc["robust_box", "max_width"] == box.info["max_width"]
    assert table.loc["robust_box", "min_infeasible_width"] == box.info["min_infeasible_width"]
    assert box.info["max_width"] <= box.info["min_infeasible_width"]
    assert np.isnan(table.loc["ms_lqr", "max_width"]) and np.isnan(table.loc["ms_lqr", "lam_box"])
