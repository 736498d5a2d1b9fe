"""Gain synthesis against the paper's numbers, and the LMI against the SDP-free policy iteration."""
import numpy as np
import pytest

import rdsexp as rx

paper = rx.paper


@pytest.fixture(scope="module")
def model():
    return paper.model(), paper.modeled_distribution()


def test_pole_placement_reproduces_paper_gain_and_fails(model):
    system, dist = model
    res = rx.synthesize(system, dist, "pole_placement", poles=paper.poles)
    np.testing.assert_allclose(res.F, paper.F_pole_placement, atol=1e-3)
    assert rx.ms_rate(system, dist, res.F) > 1          # not mean-square stable on the random model
    assert res.lam == pytest.approx(0.9, abs=1e-6)      # but it is, by design, on the LTI mean model


def test_proposed_reproduces_paper(model):
    system, dist = model
    res = rx.synthesize(system, dist, "proposed")
    assert (res.status, res.nbar) == ("optimal", 4)
    assert res.lam == pytest.approx(paper.lam_proposed, abs=2e-3)
    assert rx.ms_rate(system, dist, res.F) == pytest.approx(res.lam, abs=1e-4)
    assert res.lam_lower <= res.lam and res.lam - res.lam_lower < 1e-6
    # the paper's printed gain (4 digits) is within rounding of optimal on the same model
    assert rx.ms_rate(system, dist, paper.F_proposed) == pytest.approx(res.lam, abs=2e-3)


def test_nominal_lmi_fails_on_random_model(model):
    system, dist = model
    res = rx.synthesize(system, dist, "nominal_lmi")
    assert res.status == "infimum_not_attained_on_mean_model" and res.nbar == 1
    assert res.lam < 0.5                                 # the LTI model's infimum is 0 (dead beat)
    assert rx.ms_rate(system, dist, res.F) > 1


def test_lqr_mean_solves_the_riccati_equation(model):
    system, dist = model
    res = rx.synthesize(system, dist, "lqr_mean")
    A, B, _, _ = system.at(dist.mean)
    assert np.abs(np.linalg.eigvals(A + B @ res.F)).max() == pytest.approx(res.lam, abs=1e-12)
    assert res.lam < 1


def random_model(rng, n, m, p):
    scale = rng.uniform(0.2, 0.6)
    A = [rng.normal(size=(n, n)) / np.sqrt(n)] + [scale * rng.normal(size=(n, n)) / np.sqrt(n) for _ in range(p)]
    B = [rng.normal(size=(n, m))] + [0.3 * rng.normal(size=(n, m)) for _ in range(p)]
    L = rng.normal(size=(p, p)) * 0.5
    return rx.AffineRandomSystem(A=A, B=B), rx.MomentModel(mean=rng.normal(size=p) * 0.3, cov=L @ L.T)


@pytest.mark.parametrize("seed", range(6))
def test_policy_iteration_agrees_with_lmi(seed):
    rng = np.random.default_rng(seed)
    system, dist = random_model(rng, n=int(rng.integers(2, 5)), m=int(rng.integers(1, 3)), p=2)
    lmi = rx.synthesize(system, dist, "proposed")
    pi = rx.synthesize(system, dist, "policy_iteration")
    assert lmi.status in ("optimal", "not_ms_stabilizable")
    assert pi.lam == pytest.approx(lmi.lam, abs=1e-6)
    assert pi.status == lmi.status


def test_not_ms_stabilizable_is_a_status():
    """x+ = (1.1 + xi) x + 0 u cannot be stabilised: rate sqrt(1.21 + var) whatever F."""
    system = rx.AffineRandomSystem(A=[[[1.1]], [[1.0]]], B=[[[0.0]]])
    dist = rx.MomentModel(mean=[0.0], cov=[[0.25]])
    for method in ("proposed", "policy_iteration"):
        res = rx.synthesize(system, dist, method)
        assert res.status == "not_ms_stabilizable"
        assert res.lam == pytest.approx(np.sqrt(1.21 + 0.25), abs=1e-6)


@pytest.mark.parametrize("method, options, message", [
    ("magic", {}, "method: unknown 'magic'"),
    ("proposed", {"tolerance": 1}, "proposed: unknown option"),
    ("pole_placement", {"poles": (0.9, 0.8)}, "poles: 2 given"),
    ("pole_placement", {"poles": (1.2, 0.8, 0.7, 0.6, 0.5, 0.4)}, "inside the unit disc"),
    ("pole_placement", {"poles": (0.5, 0.5, 0.7, 0.6, 0.5, 0.4)}, "multiplicity 3 exceeds"),
    ("lqr_mean", {"input_weight": 0}, "input_weight: 0 is not allowed"),
])
def test_bad_synthesis_arguments(model, method, options, message):
    with pytest.raises(ValueError, match=message):
        rx.synthesize(*model, method, **options)


def test_pole_placement_without_poles_is_not_applicable(model):
    """No hidden default poles: the paper's poles are configured (rdsexp.paper.poles), never assumed."""
    res = rx.synthesize(*model, "pole_placement")
    assert res.status == "not_applicable" and res.F is None and res.info["reason"] == "no poles given"
    assert rx.synthesize(*model, "pole_placement", poles=paper.poles).status == "designed"


@pytest.mark.parametrize("seed", range(4))
def test_seeded_lmi_matches_full_bisection(seed):
    """Seeded by policy iteration's bracket: same status and lambda within tol, in fewer solves."""
    rng = np.random.default_rng(50 + seed)
    system, dist = random_model(rng, n=int(rng.integers(2, 6)), m=int(rng.integers(1, 3)), p=int(rng.integers(1, 4)))
    seeded = rx.synthesize(system, dist, "proposed")
    full = rx.synthesize(system, dist, "proposed", seed=False)
    assert seeded.status == full.status
    assert seeded.lam == pytest.approx(full.lam, abs=1e-7)
    assert seeded.lam == pytest.approx(rx.ms_rate(system, dist, seeded.F), rel=1e-12)
    assert seeded.lam_lower <= full.lam and full.lam_lower <= seeded.lam
    if seeded.status == "optimal":
        assert seeded.info["seeded"] and seeded.info["solves"] <= full.info["solves"]
        assert seeded.lam - seeded.lam_lower <= 1e-7


@pytest.mark.parametrize("seed", range(3))
def test_seeded_lmi_on_a_system_no_gain_stabilizes(seed):
    """A closed bracket above 1 from policy iteration seeds the LMI too: one solve, the same status
    and lambda as the full bisection, and a proven lower end >= 1."""
    rng = np.random.default_rng(70 + seed)
    system, dist = random_model(rng, n=int(rng.integers(2, 6)), m=1, p=int(rng.integers(1, 4)))
    system = rx.AffineRandomSystem(A=2.5 * system.A, B=0.01 * system.B)
    seeded = rx.synthesize(system, dist, "proposed")
    full = rx.synthesize(system, dist, "proposed", seed=False)
    assert seeded.status == full.status == "not_ms_stabilizable"
    assert seeded.info["seeded"] and seeded.info["solves"] == 1 < full.info["solves"]
    assert seeded.lam == pytest.approx(full.lam, abs=1e-7) and seeded.lam_lower >= 1


def test_lmi_results_do_not_depend_on_call_history():
    """A design of the same size in between changes nothing: the same design again agrees bit for bit."""
    rng = np.random.default_rng(7)
    system, dist = random_model(rng, n=3, m=1, p=2)
    other, other_dist = random_model(rng, n=3, m=1, p=2)
    first = rx.synthesize(system, dist, "proposed", seed=False)
    rx.synthesize(other, other_dist, "proposed", seed=False)
    again = rx.synthesize(system, dist, "proposed", seed=False)
    assert np.array_equal(first.F, again.F) and first.lam == again.lam and first.info == again.info
