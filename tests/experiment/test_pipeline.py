"""The stage pipeline: stages computed once per process for identical inputs, the same tables."""
import copy
import dataclasses

import numpy as np
import pandas as pd
import pytest
from conftest import SMALL, rdsexp, undocumented
from hydra import compose, initialize_config_module

from rdsexp.errors import ConfigError
from rdsexp.experiment import pipeline
from rdsexp.experiment.config import build
from rdsexp.experiment.montecarlo import Simulation
from rdsexp.experiment.pipeline import design, identification, loops, online, record
from rdsexp.experiment.store import stages


def experiment(*extra):
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        return build(compose("config", overrides=[*SMALL, "tracking=off", "gain.designs=all", *extra]))


@pytest.mark.slow
def test_identical_stages_are_reused_within_a_process_with_the_same_tables():
    """With this process's stage cache (StageCache.in_process), a second run of the same identification
    takes identification and designs from memory (designs report seconds 0) and gives the same tables as a
    fresh computation; another seed (other identified moments) designs those again, and the reported
    moments, the same in both, are reused. Without a cache (verify) everything is computed."""
    stages._MEMORY.clear()
    cache = lambda: stages.StageCache.in_process()
    first = pipeline.run_experiment(experiment("seed=3"), cache=cache())
    assert all(s > 0 for name, s in first.timings["synthesis_by_method"].items()
               if not name.endswith("pole_placement"))
    again_cache = cache()
    again = pipeline.run_experiment(experiment("seed=3", "closed_loop.paths=2"), cache=again_cache)  # only the loop
    assert set(again.timings["synthesis_by_method"].values()) == {0.0}
    assert "modeling" not in again.timings                       # identification with modeling from memory
    assert "identification" in again_cache.keys and not again_cache.reused     # (no store: no run to name)
    for name in ("gains", "identification", "model"):
        pd.testing.assert_frame_equal(again.tables[name], first.tables[name], check_exact=True)
    other = pipeline.run_experiment(experiment("seed=4"), cache=cache())
    seconds = other.timings["synthesis_by_method"]
    assert all(seconds[f"reported/{m}"] == 0.0 for m in ("proposed", "policy_iteration", "robust_box"))
    assert all(seconds[f"identified/{m}"] > 0 for m in ("proposed", "policy_iteration", "robust_box"))
    fresh = pipeline.run_experiment(experiment("seed=4"))
    assert all(s > 0 for name, s in fresh.timings["synthesis_by_method"].items()
               if not name.endswith("pole_placement"))
    for name in ("gains", "identification", "model", "metrics"):
        pd.testing.assert_frame_equal(fresh.tables[name], other.tables[name], check_exact=True)


def test_memory_keeps_at_most_its_bound_and_copies(monkeypatch):
    """The process's memory drops its oldest entries beyond MEMORY_KEPT and hands out copies: a caller
    that changes what it got (a reused design's seconds) does not change the kept value."""
    monkeypatch.setattr(stages, "MEMORY_KEPT", 3)
    stages._MEMORY.clear()
    cache = stages.StageCache.in_process()
    keys = [cache.key("synthesis", i=i) for i in range(5)]
    for i, key in enumerate(keys):
        cache.save("synthesis", key, {"seconds": float(i)})
    assert len(stages._MEMORY) == 3
    assert cache.load("synthesis", keys[0]) is None and cache.load("synthesis", keys[1]) is None
    got = cache.load("synthesis", keys[4])
    got["seconds"] = 0.0
    assert cache.load("synthesis", keys[4]) == {"seconds": 4.0}


def test_a_run_designs_its_method_and_the_designs_it_asks_for():
    """gain.designs: the loop's method plus the listed comparison designs, on the identified and the
    reported moments; the summary and the gains table name exactly those."""
    out = pipeline.run_experiment(experiment("gain=lqr_mean", "gain.designs=[robust_box]"))
    gains = out.tables["gains"]
    for source in ("identified", "reported"):
        assert list(gains[gains["distribution"] == source]["method"]) == ["lqr_mean", "robust_box"]
    assert set(out.summary["designs"]) == {"lqr_mean", "robust_box"}
    assert set(out.timings["synthesis_by_method"]) == {f"{s}/{m}" for s in ("identified", "reported")
                                                        for m in ("lqr_mean", "robust_box")}


def test_lmi_designs_above_the_size_limit_are_not_applicable_and_the_loop_falls_back():
    """gain.lmi_max_n: an LMI design on a larger system is not_applicable at once (no SDP solved), the
    SDP-free designs run, and the loop uses gain.fallback (policy iteration) and says so; without a
    fallback the run still completes with its statuses and no loop."""
    out = pipeline.run_experiment(experiment("gain.lmi_max_n=5", "gain.designs=[nominal_lmi]"))
    gains = out.tables["gains"].set_index(["distribution", "method"])
    for method in ("proposed", "nominal_lmi"):                       # the paper's model has n = 6 > 5
        assert gains.loc[("identified", method), "status"] == "not_applicable"
        assert out.timings["synthesis_by_method"][f"identified/{method}"] < 0.01
    assert gains.loc[("identified", "policy_iteration"), "selected"]
    assert out.summary["gain_fallback"] == {"method": "policy_iteration", "instead_of": "proposed", "because":
                                            "n = 6 > gain.lmi_max_n = 5: an SDP of this size runs for hours; "
                                            "policy_iteration and ms_lqr need none"}
    assert out.summary["gain_method"] == "policy_iteration" and "closed_loop_status" in out.summary
    assert undocumented(out.summary) == []
    bare = pipeline.run_experiment(experiment("gain.lmi_max_n=5", "gain.fallback=null"))
    assert bare.summary["synthesis_status"] == "not_applicable" and "closed_loop_status" not in bare.summary


@pytest.mark.parametrize("extra, key", [([], "reference"), (["controller=online"], "online_rate"),
                                        (["plant=cart_pole", "model=plant"], "gain_choice")],
                         ids=["paper", "online", "user_plant"])
def test_every_summary_key_is_in_the_data_dictionary(extra, key):
    """A summary number a stage adds is documented (schema.RUN_SUMMARY_KEYS, docs/data_dictionary.md): the paper's run,
    the online controller (online_*), a user plant (identification passes, the gain choice)."""
    summary = pipeline.run_experiment(experiment(*extra)).summary
    assert key in summary and undocumented(summary) == []


@pytest.mark.slow
def test_modeled_covariance_is_total_for_a_user_plant_and_the_papers_for_the_paper():
    """identification.covariance: a library plant defaults to total (eq. sample-mean's covariance plus the
    mean filtered covariance: same mean, every variance at least as large, and larger somewhere); the
    paper's plant file keeps eq. (sample-mean). (The paper's estimator, whose covariance this is.)"""
    out = {c: pipeline.run_experiment(experiment("plant=dropout", f"identification.covariance={c}",
                                                 "identification.xi_model=random_walk",
                                                 "identification.estimator=paper")).summary
           for c in ("sample", "total")}
    assert pipeline.run_experiment(experiment("plant=dropout")).summary["modeling_covariance"] == "total"
    assert out["sample"]["xi_mean"] == out["total"]["xi_mean"]
    sample, total = (np.array(out[c]["xi_std"]) for c in ("sample", "total"))
    assert np.all(total >= sample) and np.any(total > sample * 1.01)
    assert pipeline.run_experiment(experiment()).summary["modeling_covariance"] == "sample"


@pytest.mark.slow
def test_iterated_identification_models_from_its_last_pass_and_stops_at_a_fixed_point():
    """identification.xi_model = iterated (a library plant's default): the model is eq. (sample-mean) of
    the identification table's xi_{k|k}, the last pass's; the summary counts the passes. A pass that
    reproduces its prior stops the iteration (converged), and a failing pass keeps the last model. The
    paper's plant file keeps the random walk (no passes)."""
    out = pipeline.run_experiment(experiment("plant=dropout", "identification.covariance=sample",
                                             "identification.passes=2", "identification.estimator=paper"))
    info = out.summary["identification_passes"]
    assert info["first"] == "random_walk" and 1 <= info["passes"] <= 2
    ident = out.tables["identification"]
    window = ident[(ident["k"] >= 5) & (ident["k"] <= 25)]
    xi = window[[c for c in window.columns if c.startswith("xi_filt_mean")]].to_numpy()
    model = out.tables["model"]
    mean = model[model["quantity"] == "mean"].sort_values("row")["value"].to_numpy()
    np.testing.assert_allclose(mean, xi.mean(axis=0), rtol=1e-12)
    assert "identification_passes" not in pipeline.run_experiment(experiment()).summary

    exp = experiment("plant=dropout")
    first = Simulation.of(exp, exp.filter.enkf, None, 1, d=exp.identification.input, paths=1,
                          filter_sees_d=True).run(keep_xi_cov=True)
    dist, failure = identification.identified_moments(exp, first)
    assert failure == ""
    _, same, _, info = identification.iterate_identification(exp, lambda enkf: first, first, dist, "")
    assert info == {"first": "random_walk", "passes": 1, "converged": True, "last_change": 0.0,
                    "tolerance": identification.PASS_TOL}
    np.testing.assert_array_equal(same.mean, dist.mean)
    failing = copy.copy(first)
    failing.failed_at = np.array([7])
    failing.failure = np.array(["filter_diverged"], dtype=object)
    kept, model, why, info = identification.iterate_identification(exp, lambda enkf: failing, first, dist, "")
    assert kept is first and model is dist and why == "" and info["passes"] == 0
    assert info["failed"] == "identification failed at k = 7: the EnKF estimate diverged"


def test_xi_crps_scores_the_modeled_marginals_against_the_plant_file():
    """summary xi_crps: the expected CRPS of the modeled N(mean, std^2) against the plant file's xi, here a
    Bernoulli(gamma) dropout, whose expectation is exact: gamma CRPS(1) + (1 - gamma) CRPS(0). The summary's
    estimate from its fixed draws agrees within 4 Monte Carlo standard errors."""
    from scipy.stats import norm
    exp = experiment("plant=dropout")
    s = pipeline.run_experiment(exp).summary
    (gamma,), (m,), (sd,) = exp.plant.xi_dist.prob, s["xi_mean"], s["xi_std"]

    def crps(y):
        z = (y - m) / sd
        return sd * (z * (2 * norm.cdf(z) - 1) + 2 * norm.pdf(z) - 1 / np.sqrt(np.pi))

    exact = gamma * crps(1.0) + (1 - gamma) * crps(0.0)
    error = abs(crps(1.0) - crps(0.0)) * np.sqrt(gamma * (1 - gamma) / record.CRPS_DRAWS)
    assert abs(s["xi_crps"] - exact) <= 4 * error


@pytest.mark.parametrize("override, message", [
    ("enkf.disturbance=0", "enkf.disturbance: 0 is not allowed, expected null (off) or a nonzero scale of I_m, "
                           "m diagonal entries or an (m, m) matrix"),
    ("enkf.disturbance=[1,2]", "enkf.disturbance: shape (2,) is not allowed, expected a scalar, 1 diagonal entries "
                               "or (1, 1)"),
])
def test_bad_disturbance_scale_is_a_one_line_error(override, message):
    with pytest.raises(ConfigError) as err:
        experiment(override)
    assert str(err.value) == message


def test_disturbance_estimate_is_the_loops_not_identifications():
    """enkf.disturbance: the loops' EnKF carries d (width n + p + m), identification's does not; the
    tables keep the paper's columns (x and xi of n + p)."""
    exp = experiment("enkf.disturbance=0.5", "closed_loop.filter_sees_disturbance=false")
    assert exp.filter.enkf.disturbance is None and exp.filter.enkf.width == exp.filter.enkf.dim
    observer = loops.loop_observer(exp, None)
    np.testing.assert_array_equal(observer.disturbance, 0.5 * np.eye(exp.model.m))
    assert observer.width == observer.dim + exp.model.m
    tables = pipeline.run_experiment(exp).tables
    columns = tables["trajectories"].columns
    assert sum(c.startswith("x_filt_mean[") for c in columns) == exp.model.n
    assert sum(c.startswith("xi_filt_mean[") for c in columns) == exp.model.p
    # the estimate of d is in the loops' rows, finite wherever the path is, and not in identification's table
    d = [c for c in columns if c.startswith("d_filt_")]
    assert sorted(d) == sorted(f"d_filt_{s}[{i}]" for s in ("mean", "std") for i in range(exp.model.m))
    rows = tables["trajectories"]
    alive = rows["q[0]"].notna()
    assert set(rows["experiment"]) == {"closed_loop", "open_loop"} and rows.loc[alive, d].notna().all().all()
    assert not any(c.startswith("d_filt_") for c in tables["identification"].columns)


def test_disturbance_columns_in_a_stored_run_with_the_online_loop(tmp_path):
    """One trajectories.parquet, one set of columns: with enkf.disturbance and the online controller, the
    online loop's EnKF carries d too (its rows the estimate, as the offline loop's, finite where the path
    is, and not the offline loop's numbers: its own gains); the columns are described in the table's
    schema metadata."""
    rdsexp(*SMALL, "controller=online", "enkf.disturbance=0.5", "closed_loop.filter_sees_disturbance=false",
           "tracking.recording=false", cwd=tmp_path)
    (run,) = (tmp_path / "outputs" / "runs").iterdir()
    rows = pd.read_parquet(run / "trajectories.parquet")
    assert rows.attrs["rdsexp"]["columns"]["d_filt_mean[0]"]["unit"] == "input"
    online, offline = rows[rows["experiment"] == "online"], rows[rows["experiment"] == "closed_loop"]
    for loop in (online, offline):
        assert len(loop) and loop.loc[loop["q[0]"].notna(), ["d_filt_mean[0]", "d_filt_std[0]"]].notna().all().all()
    assert (online.loc[online["q[0]"].notna(), "d_filt_std[0]"] > 0).all()
    assert not np.array_equal(online["d_filt_mean[0]"].to_numpy(), offline["d_filt_mean[0]"].to_numpy())


UNST3 = {"name": "unst3",
         "A": [[[1.05, 0.2, 0.0], [0.0, 0.95, 0.1], [0.0, 0.0, 0.9]], [[0, 0, 0]] * 3,
               [[0.3, 0, 0], [0, 0, 0], [0, 0, 0]]],
         "B": [[[0], [0], [0]], [[0], [0], [1]], [[0], [0], [0]]],
         "C": [[[1, 0, 0]]],
         "xi": {"family": "independent", "components": [{"family": "bernoulli", "prob": 0.8},
                                                         {"family": "uniform", "low": -1.0, "high": 1.0}]},
         "nominal": [1.0, 0.0]}                        # the actuator link delivers (B_0 = 0: no input at xi = 0)


def test_the_loop_keeps_the_identification_gain_where_the_designed_one_is_worse(tmp_path):
    """An open-loop unstable plant identified under its nominal gain F_id: a designed gain whose exact rate's 95%
    quantile over the moments' draws is above 1 and above F_id's is replaced by F_id (status `kept`, its exact rate
    on the identified moments); the quantiles are those of an independent ms_rate at every draw; a designed gain
    that stabilizes 95% of the draws stays, whatever its worst, and so does one no worse than F_id."""
    import yaml

    from rdsexp.numerics.analysis import ms_rate
    from rdsexp.numerics.synthesis import SynthesisResult
    from rdsexp.numerics.systems import MomentModel
    (tmp_path / "plant").mkdir()
    (tmp_path / "plant" / "unst3.yaml").write_text(yaml.safe_dump(UNST3))
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        exp = build(compose("config", overrides=[f"hydra.searchpath=[file://{tmp_path}]", "plant=unst3", "model=plant",
                                                 *SMALL, "identification.resamples=20", "tracking=off"]))
    identified = identification.identify_and_model(exp, pipeline.Stages(), np.random.SeedSequence(0, spawn_key=(0,)))
    dist, uncertainty = identified.moments, identification.moment_uncertainty(exp, identified)
    summary = identified.summary() | uncertainty.summary()
    draws = uncertainty.draws
    assert draws[0].shape == (20, 2) and len(summary["modeling_uncertainty"]["xi_mean_sd"]) == 2
    assert summary["identification_feedback"]["used"] == "nominal"
    F_id = np.array(summary["identification_feedback"]["F"])
    np.testing.assert_array_equal(F_id, identification.identification_feedback(exp)[0])     # the gain it ran under
    at_draws = lambda F: np.sort([ms_rate(exp.model, MomentModel(mean=m, cov=c), F) for m, c in zip(*draws)])
    zero = np.zeros((1, 3))                                        # no feedback: the plant grows
    designed = SynthesisResult("ms_lqr", zero, ms_rate(exp.model, dist, zero), "optimal", nbar=3)
    choice, kept = design.safer_gain(exp, dist, designed, draws, F_id)
    assert kept is not None and kept.status == "kept" and kept.method == design.KEPT_GAIN
    np.testing.assert_array_equal(kept.F, F_id)
    assert kept.lam == pytest.approx(ms_rate(exp.model, dist, F_id), rel=1e-12)
    assert choice["kept"] == "identification" and choice["draws"] == 20
    # the 95% quantile of 20 draws is the 19th smallest (inverted cdf): an exact rate of one draw
    assert choice["designed_quantile"] == pytest.approx(at_draws(zero)[18], rel=1e-9) and choice["designed_quantile"] > 1
    assert choice["identification_quantile"] == pytest.approx(at_draws(F_id)[18], rel=1e-9)
    assert choice["identification_quantile"] < choice["designed_quantile"]
    assert choice["designed_worst"] == pytest.approx(at_draws(zero)[-1], rel=1e-9)
    same = SynthesisResult("ms_lqr", F_id.copy(), ms_rate(exp.model, dist, F_id), "optimal", nbar=3)
    summary["gain_choice"], kept = design.safer_gain(exp, dist, same, draws, F_id)
    assert kept is None and summary["gain_choice"]["kept"] == "designed"       # a tie keeps the design
    from rdsexp.experiment.recording import report_markdown
    tables = {"gains": pd.DataFrame(columns=["distribution", "method", "status", "lam", "rate_plant", "selected"]),
              "metrics": pd.DataFrame(columns=list(pipeline.METRIC_COLUMNS))}
    report = report_markdown(tables, summary)          # the recording's summary document says both
    assert "spread over 20 draws of their posterior" in report and "gain choice: **designed**" in report


@pytest.mark.parametrize("unstable_draws, kept", [(1, "designed"), (2, "identification")])
def test_the_gain_choice_reads_the_95_percent_quantile_of_the_draws_not_their_worst(unstable_draws, kept):
    """x+ = 1.2 x + (1 + xi) u, xi ~ (0, s^2) at each draw: the gain F has the exact rate
    sqrt((1.2 + F)^2 + F^2 s^2). The designed F = -1.2 (rate 1.2 s) beats F_id = -0.6 (0.6 sqrt(1 + s^2)) at
    s = 0.5 and is unstable at s = 0.9, where F_id is not. Of 20 draws, one at 0.9: the designed gain stabilizes
    95% of them and stays, though its worst (1.08) is above F_id's (0.81); two: its 95% quantile is 1.08 and the
    loop keeps F_id."""
    from types import SimpleNamespace

    from rdsexp.numerics.synthesis import SynthesisResult
    from rdsexp.numerics.systems import AffineRandomSystem, MomentModel
    system = AffineRandomSystem(A=[[[1.2]], [[0.0]]], B=[[[1.0]], [[1.0]]])
    s = np.array([0.5] * (20 - unstable_draws) + [0.9] * unstable_draws)
    draws = (np.zeros((20, 1)), s[:, None, None] ** 2)
    rate = lambda F, s: np.sqrt((1.2 + F) ** 2 + F ** 2 * s ** 2)
    F_d, F_id = np.array([[-1.2]]), np.array([[-0.6]])
    dist = MomentModel(mean=np.zeros(1), cov=np.full((1, 1), 0.25))
    choice, gain = design.safer_gain(SimpleNamespace(model=system), dist,
                                     SynthesisResult("ms_lqr", F_d, rate(-1.2, 0.5), "optimal", nbar=2), draws, F_id)
    assert choice["kept"] == kept and (gain is None) == (kept == "designed")
    assert choice["designed_quantile"] == pytest.approx(rate(-1.2, np.sort(s)[18]), rel=1e-12)
    assert choice["identification_quantile"] == pytest.approx(rate(-0.6, np.sort(s)[18]), rel=1e-12)
    assert choice["designed_worst"] == pytest.approx(rate(-1.2, 0.9), rel=1e-12)
    assert choice["designed_worst"] > 1 > choice["identification_worst"]


def test_the_online_observer_draws_a_dropout_from_its_two_point_law():
    """`pipeline.online.online_observer` marks the dropout plant's Bernoulli xi (`EnKF.xi_ends`, its box [0, 1]) for its
    static-mean start and its paths' models, and nothing on the paper's plant (a normal xi); with the walk as
    the start it keeps the mark for the paths' models only."""
    observer = online.online_observer(experiment("plant=dropout", "controller=online"))
    assert observer.static_mean and observer.xi_ends.tolist() == [True]
    assert observer.xi_bounds[0].tolist() == [0.0] and observer.xi_bounds[1].tolist() == [1.0]
    assert online.online_observer(experiment("controller=online")).xi_ends is None
    walk = online.online_observer(experiment("plant=dropout", "controller=online", "controller.start=random_walk"))
    assert not walk.static_mean and walk.xi_ends.tolist() == [True]


@pytest.mark.slow
def test_the_online_controller_models_a_dropout_with_the_variance_its_mean_fixes():
    """The online loop's controller gets the observer's two-point components (`EnKF.two_point`): on the dropout
    plant every modeled variance of its Bernoulli xi is mu (1 - mu) (`online.two_point_moments`), and on the
    paper's plant (normal xi) the window's sample variance is left as it is."""
    out = pipeline.run_experiment(experiment("plant=dropout", "controller=online", "closed_loop.horizon=50",
                                             "closed_loop.open_loop=false"))
    c = out.tables["controller"]
    c = c[c["k"] >= 0]
    assert (c["cov[0,0]"] > 0.05).any()
    mu = c["mean[0]"].clip(0, 1)
    np.testing.assert_allclose(c["cov[0,0]"], mu * (1 - mu), rtol=1e-12, atol=1e-15)
    paper = pipeline.run_experiment(experiment("controller=online", "closed_loop.horizon=50",
                                               "closed_loop.open_loop=false")).tables["controller"]
    paper = paper[paper["k"] >= 0]
    assert len(paper) > 0 and not np.allclose(paper["cov[0,0]"], paper["mean[0]"] * (1 - paper["mean[0]"]))


def test_the_online_loops_nominal_gain_is_designed_on_the_law_its_enkf_starts_from():
    """controller.initial=nominal is the mean-square LQR at the guess with the spread xi has in the online loop's
    EnKF at its start (`pipeline.online.online_nominal`). On the dropout plant that law is the two-point law at the
    guess mu (variance mu (1 - mu)): the gain in use before any re-design is that design, recomputed here, and its
    rate on the law (recorded) is its exact rate on the plant (the controller table's) where the guess is the
    plant's probability."""
    from rdsexp.numerics.synthesis import synthesize
    from rdsexp.numerics.systems import MomentModel
    exp = experiment("plant=dropout", "controller=online", "controller.initial=nominal", "closed_loop.horizon=20",
                     "closed_loop.open_loop=false", "identification.xi_guess=[0.8]")
    out = pipeline.run_experiment(exp)
    info = out.summary["online_initial"]
    assert (info["nominal_law"], info["method"]) == ("start", "ms_lqr") and info["rate_on_law"] < 1
    mu = float(exp.identification.xi_guess[0])
    assert mu == float(np.asarray(exp.plant.xi_dist.mean).ravel()[0])
    F = synthesize(exp.model, MomentModel(mean=np.array([mu]), cov=np.array([[mu * (1 - mu)]])), "ms_lqr").F
    first = out.tables["controller"].query("k < 0")
    np.testing.assert_allclose(first[[f"F[0,{j}]" for j in range(exp.model.n)]].to_numpy(), np.repeat(F, len(first), 0),
                               rtol=1e-12)
    np.testing.assert_allclose(first["rate_plant"], info["rate_on_law"], rtol=1e-9)
    det = synthesize(exp.model, MomentModel.deterministic([mu]), "lqr_mean").F
    assert not np.allclose(F, det, rtol=1e-3)                       # not the deterministic design at the guess


def test_a_start_law_no_gain_keeps_mean_square_stable_is_halved_until_one_does(tmp_path):
    """x_{k+1} = (0.5 + xi_k) x_k + u_k, y = x: under N(mu, v) the best gain's mean-square rate is sqrt(v) (u = -0.5 x
    cancels the mean), so a law is stabilizable exactly when v < 1. With enkf.Q's xi block 0.25, start_spread 2 and
    mean_spread 0.3, the online loop's start law has v = (0.09 + 4) 0.25 = 1.0225: no gain is mean-square stable
    there, and the start keeps half of it (`pipeline.online.stabilizable_start`), v = 0.511, where the nominal gain is the
    mean-square LQR (recomputed here); with Q's xi block 0.2 (v = 0.818) nothing is narrowed."""
    import yaml

    from rdsexp.experiment.summary import initial_gain
    from rdsexp.numerics.synthesis import synthesize
    from rdsexp.numerics.systems import MomentModel
    (tmp_path / "plant").mkdir()
    plant = {"name": "scalar", "A": [[[0.5]], [[1.0]]], "B": [[[1.0]], [[0.0]]], "C": [[[1.0]], [[0.0]]],
             "xi": {"family": "normal", "mean": [0.0], "cov": [[0.04]]}}
    (tmp_path / "plant" / "scalar.yaml").write_text(yaml.safe_dump(plant))

    def run(q_xi):
        with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
            exp = build(compose("config", overrides=[
                f"hydra.searchpath=[file://{tmp_path}]", "plant=scalar", "model=plant", *SMALL, "tracking=off",
                "controller=online", "closed_loop.observer_xi=model", "controller.start_spread=2",
                "controller.mean_spread=0.3", f"enkf.Q.xi={q_xi}", "closed_loop.open_loop=false"]))
        return exp, pipeline.run_experiment(exp)

    exp, out = run(0.25)
    info = out.summary["online_initial"]
    assert info["start_scale"] == 0.5 and (info["nominal_law"], info["method"]) == ("start", "ms_lqr")
    v = 0.5 * (0.09 + 4) * 0.25
    F = synthesize(exp.model, MomentModel(mean=np.zeros(1), cov=np.array([[v]])), "ms_lqr").F
    first = out.tables["controller"].query("k < 0")
    np.testing.assert_allclose(first["F[0,0]"], F[0, 0], rtol=1e-12)
    np.testing.assert_allclose(info["rate_on_law"], np.sqrt((0.5 + F[0, 0]) ** 2 + v), rtol=1e-9)
    assert "(its spread x 0.5: none is mean-square stable at the full one)" in initial_gain(info)
    _, wide = run(0.2)
    assert wide.summary["online_initial"]["start_scale"] == 1.0


# seed 0's plant 9 of experiments/random_plants.py: a Bernoulli dropout on B, two Gaussian components on A
RP9 = {"name": "rp9",
       "A": [[[2.18394, 1.74588, 1.76272], [0.664008, -0.911092, -0.829603], [-1.14159, -0.331597, 0.253575]],
             [[0.0, 0.348009, 0.0186337], [0.119678, 1.09308, 0.0], [0.0960303, 0.0, 0.631105]],
             [[0.0, -1.5404, -0.302973], [0.0, -0.201918, 0.0], [1.75852, -1.23318, 0.0]],
             [[-1.76868, -0.251144, -0.928984], [-1.42891, 0.750081, 0.891767], [-0.638366, 1.50206, -0.433374]]],
       "B": [[[0.0, 0.0], [-1.09914, 0.31072], [0.0, 0.315335]],
             [[0.434499, 0.0266773], [0.246123, -1.13077], [1.10395, 0.434411]],
             [[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]], [[0.0, 0.0], [1.63817, -0.4631], [0.0, -0.469978]]],
       "C": [[[-0.407152, -0.248498, -0.878906], [0.669734, 0.0881912, -0.737345]]],
       "xi": {"family": "independent", "components": [
           {"family": "bernoulli", "prob": [0.825327]},
           {"family": "normal", "mean": [0.651176, 0.670957], "cov": [[0.077627, 0.00842031], [0.00842031, 0.066362]]}]}}


def test_a_narrowed_start_whose_gain_holds_the_whole_law_worse_than_the_guess_design_is_refused(tmp_path):
    """With the guess one standard deviation off the plant's mean (the dropout at 0.446 for 0.825), the start's law
    admits a mean-square stabilizing gain at 2^-8 of its spread (none above), where the Gaussian components are nearly
    certain beside the dropout, whose spread its mean fixes: that gain's exact rate at the whole law is worse than
    the deterministic design's (recomputed here), so the start is not narrowed (`pipeline.online.stabilizable_start`)
    and the nominal gain is the design at the guess."""
    import yaml

    from rdsexp.numerics.analysis import ms_rate
    from rdsexp.numerics.synthesis import synthesize
    from rdsexp.numerics.systems import MomentModel
    (tmp_path / "plant").mkdir()
    (tmp_path / "plant" / "rp9.yaml").write_text(yaml.safe_dump(RP9))
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        exp = build(compose("config", overrides=[f"hydra.searchpath=[file://{tmp_path}]", "plant=rp9", "model=plant",
                                                 *SMALL, "tracking=off", "controller=online",
                                                 "identification.xi_guess=[0.44564,0.92979,0.41335]"]))
    enkf = online.online_observer(exp)
    assert enkf.static_mean and enkf.start_scale == 1.0
    assert online.online_nominal(exp, enkf)[1] == "guess"
    whole = MomentModel(*online.start_law(exp, enkf))
    narrow = MomentModel(*online.start_law(exp, dataclasses.replace(enkf, start_scale=2.0 ** -8)))
    stabilizing = synthesize(exp.model, narrow, "ms_lqr")
    assert stabilizing.F is not None and ms_rate(exp.model, narrow, stabilizing.F) < 1
    at_guess = synthesize(exp.model, MomentModel.deterministic(whole.mean), "lqr_mean")
    assert ms_rate(exp.model, whole, stabilizing.F) > ms_rate(exp.model, whole, at_guess.F) > 1


@pytest.mark.slow
def test_the_online_loop_borrows_the_fixed_gain_loops_floor_only_where_it_holds(monkeypatch):
    """The fixed-gain loop's run at rest is replaced by one that keeps a floor, then by one that grows: the online
    row's floor_rms is that floor where it holds and NaN where it does not, and only the fixed-gain loop is called
    unstable for a growth at rest that is its own (the online loop's gains and EnKF are not its)."""
    from rdsexp.numerics.verdict import Floor
    rng = np.random.default_rng(0)
    K = 60
    runs = {"holds": Floor.of(1e-4 * rng.exponential(1.0, (K + 1, 20)), np.full(20, -1)),
            "grows": Floor.of(1e-4 * rng.exponential(1.0, (K + 1, 20)) * 1.1 ** (2 * np.arange(K + 1))[:, None],
                              np.full(20, -1))}
    assert runs["holds"].holds and not runs["grows"].holds
    exp = experiment("controller=online", "closed_loop.paths=8", "closed_loop.open_loop=false")
    for name, floor in runs.items():
        monkeypatch.setattr(pipeline.loops, "noise_floor", lambda *args, floor=floor: floor)
        metrics = pipeline.run_experiment(exp).tables["metrics"].set_index("experiment")
        closed, online = metrics.loc["closed_loop"], metrics.loc["online"]
        assert closed["floor_rms"] == floor.rms
        if name == "holds":
            assert online["floor_rms"] == floor.rms
        else:
            assert np.isnan(online["floor_rms"]) and "at rest" not in online["verdict_reason"]
            assert closed["verdict"] == "unstable" and "at rest" in closed["verdict_reason"]


def test_paths_the_online_loop_loses_alone_are_counted_path_by_path_and_tested_against_chance():
    """A destabilising initial gain (u = 100 x_2 on the paper's plant: x_2 grows about 41-fold a step) loses every
    online path before its first re-design, while the offline loop of the same plant samples keeps its own. The
    online metrics count the paths each loop lost alone from the paths table, path by path, and the exact paired
    test (`verdict.paired_losses`) gives p = 2^-P: more than chance explains."""
    exp = experiment("controller=online", "controller.initial=[[0,100,0,0,0,0]]", "closed_loop.paths=8",
                     "closed_loop.open_loop=false")
    out = pipeline.run_experiment(exp)
    paths = out.tables["paths"]
    lost = {e: paths[paths["experiment"] == e].sort_values("path")["failed_at"].to_numpy() >= 0
            for e in ("online", "closed_loop")}
    o = out.summary["online"]
    assert lost["online"].all() and not lost["closed_loop"].any()
    assert (o["lost_online_only"], o["lost_offline_only"]) == (8, 0) and o["lost_more_p"] == 2.0 ** -8
    metrics = out.tables["metrics"].set_index("experiment").loc["online"]
    assert (metrics["lost_online_only"], metrics["lost_more_p"]) == (8, 2.0 ** -8)
    # every lost path held the initial gain, unstable on the true plant: its exact rate, computed independently
    from rdsexp.numerics.analysis import ms_rate
    F0 = np.array([[0.0, 100.0, 0.0, 0.0, 0.0, 0.0]])
    assert o["lost_held_unstable"] == 8 and o["lost_held_rate_max"] == pytest.approx(
        ms_rate(exp.plant, None, F0), rel=1e-9)
    assert not undocumented(out.summary)


@pytest.mark.parametrize("extra, kind", [((), "rate_excess_plant"), (("plant=dropout",), "cost_ratio_plant")])
def test_the_loops_gain_is_measured_against_the_optimum_for_the_true_law(extra, kind):
    """The end-to-end figure: a rate design's exact rate on the plant minus the optimal rate (policy iteration on
    the true law, recomputed here; >= 0 up to its certificate), an LQ design's exact LQ cost over the mean-square
    LQ optimum's for the law (>= 1), both from the summary against an independent computation."""
    from rdsexp.numerics.analysis import exact_costs, ms_rate
    from rdsexp.numerics.synthesis import synthesize
    exp = experiment(*extra)
    out = pipeline.run_experiment(exp)
    F = out.tables["gains"].query("selected")[[f"F[{i},{j}]" for i in range(exp.model.m)
                                               for j in range(exp.model.n)]].to_numpy().reshape(exp.model.m, -1)
    truth = exp.plant.check_distribution(None)
    if kind == "rate_excess_plant":
        best = synthesize(exp.plant, truth, "policy_iteration")
        assert out.summary[kind] == pytest.approx(ms_rate(exp.plant, None, F) - best.lam, abs=1e-9)
        assert out.summary[kind] >= -1e-6 and "cost_ratio_plant" not in out.summary
    else:
        best = synthesize(exp.plant, truth, "ms_lqr")
        ratio = exact_costs(exp.plant, None, F)["lq_cost"] / exact_costs(exp.plant, None, best.F)["lq_cost"]
        assert out.summary[kind] == pytest.approx(ratio, rel=1e-9) and out.summary[kind] >= 1 - 1e-9
        assert "rate_excess_plant" not in out.summary


@pytest.mark.slow
def test_auto_paths_look_again_while_a_verdict_asks_and_match_a_fixed_run_of_the_paths_they_stopped_at():
    """closed_loop.paths=auto (pilot 4, budget 64: looks at 4, 16 and 64 paths): each look but the last has a loop
    whose verdict asks for paths (`verdict.asks_for_paths`), the last has none or is the budget, and the intervals
    are at 1 - 5% / 3. The loops are those of a fixed run of the paths the looks stopped at, row for row and bit
    for bit (each path its own streams), for any chunk size; the verdicts differ only by their level."""
    from rdsexp.numerics.verdict import asks_for_paths, look_level
    auto = ["closed_loop.paths=auto", "closed_loop.pilot_paths=4", "closed_loop.max_paths=64"]
    for seed in (0, 5):
        out = pipeline.run_experiment(experiment(*auto, f"seed={seed}", "gain.designs=[]"))
        looks = out.summary["loop_looks"]
        assert [look["paths"] for look in looks] == [4, 16, 64][:len(looks)]
        asking = [[name for name, v in look.items() if isinstance(v, dict) and asks_for_paths(
            v["verdict"], np.nan if v["paths_needed"] is None else v["paths_needed"],
            np.nan if v["tail_khat"] is None else v["tail_khat"], name != "open_loop")] for look in looks]
        assert all(asking[:-1]) and (not asking[-1] or looks[-1]["paths"] == 64)
        assert out.summary["loop_paths_asking"] == (asking[-1] if looks[-1]["paths"] == 64 else [])
        metrics = out.tables["metrics"]
        assert (metrics["level"] == look_level(3)).all() and (metrics["paths"] == looks[-1]["paths"]).all()
        P = looks[-1]["paths"]
        fixed = pipeline.run_experiment(experiment(f"closed_loop.paths={P}", f"seed={seed}", "gain.designs=[]"))
        chunked = pipeline.run_experiment(experiment(*auto, f"seed={seed}", "gain.designs=[]",
                                                     "closed_loop.chunk_paths=3"))
        order = lambda t: t.sort_values(["experiment", "path", "k"], kind="stable", ignore_index=True)
        pd.testing.assert_frame_equal(order(out.tables["trajectories"]), order(fixed.tables["trajectories"]),
                                      check_exact=True)
        for name in ("trajectories", "metrics", "paths"):
            pd.testing.assert_frame_equal(chunked.tables[name], out.tables[name], check_exact=True)
        same = ["experiment", "k_from", "k_to", "exact_rate", "rms_k_to", "tail_khat", "paths", "failed_fraction",
                "x_error_rms", "q_rms_final"]
        pd.testing.assert_frame_equal(metrics[same], fixed.tables["metrics"][same], check_exact=True)


def test_auto_paths_extend_the_online_loop_with_the_others():
    """controller=online with closed_loop.paths=auto: the online loop runs the looks' paths with the closed and open
    loops, each path's decisions in the controller table once, judged on the last look's paths at its level."""
    out = pipeline.run_experiment(experiment("controller=online", "closed_loop.paths=auto", "closed_loop.pilot_paths=4",
                                             "closed_loop.max_paths=16", "seed=0", "gain.designs=[]"))
    looks = out.summary["loop_looks"]
    P = looks[-1]["paths"]
    assert all("online" in look for look in looks)
    metrics = out.tables["metrics"].set_index("experiment")
    assert metrics.loc["online", "paths"] == P == metrics.loc["closed_loop", "paths"]
    initial = out.tables["controller"].query("k == -1")
    assert sorted(initial["path"]) == list(range(P))
    assert sorted(out.tables["trajectories"].query("experiment == 'online'")["path"].unique()) == list(range(P))
