"""identification.estimator = simulated (the default beside the paper's plant): the moments of xi by simulation
(`numerics.indirect`), blind, with an interval that holds the law the plant is simulated from, the same numbers
whatever the chunks, and the paper's estimator where the paper's plant asks for it."""
import sys

import numpy as np
import pytest
import yaml
from conftest import SMALL
from hydra import compose, initialize_config_module
from scipy.stats import binom

from rdsexp.errors import ConfigError
from rdsexp.experiment.config import build
from rdsexp.experiment.pipeline import identification
from rdsexp.experiment.pipeline.identification import identify_and_model, moment_uncertainty
from rdsexp.experiment.pipeline.loops import root_seed
from rdsexp.experiment.pipeline.stage import Stages
from rdsexp.numerics import indirect
from rdsexp.numerics.modeling import correlation_z

# open-loop unstable, identified under nominal feedback: a Bernoulli(0.8) actuator link and a normal gain on A
PLANT = {"name": "link", "A": [[[1.05, 0.2], [0.0, 0.95]], [[0, 0], [0, 0]], [[0.3, 0], [0, 0]]],
         "B": [[[0], [0.2]], [[0], [1]], [[0], [0]]], "C": [[[1, 0]]], "nominal": [1.0, 0.0],
         "xi": {"family": "independent", "components": [{"family": "bernoulli", "prob": 0.8},
                                                         {"family": "normal", "mean": [0.5], "cov": [[0.09]]}]}}
TRUE_MEAN, TRUE_STD = np.array([0.8, 0.5]), np.array([0.4, 0.3])


def experiment(tmp_path, *extra):
    (tmp_path / "plant").mkdir(exist_ok=True)
    (tmp_path / "plant" / "link.yaml").write_text(yaml.safe_dump(PLANT))
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        return build(compose("config", overrides=[f"hydra.searchpath=[file://{tmp_path}]", "plant=link",
                                                  "model=plant", *SMALL, "tracking=off", "identification.horizon=60",
                                                  "identification.K1=50", "identification.replicates=200", *extra]))


def modeled(exp):
    identified = identify_and_model(exp, Stages(cache=None), root_seed(exp, "identification"))
    return identified, moment_uncertainty(exp, identified)


def test_the_stated_interval_holds_the_law(tmp_path):
    """Over seeds, modeled +- 1.96 stated sd holds the true mean and std of both components at about the
    nominal 95% (at least the count 3 binomial sds below it), where the paper's estimator misses."""
    hits, paper_hits, count = 0, 0, 0
    for seed in range(10):
        identified, posterior = modeled(experiment(tmp_path, f"seed={seed}"))
        assert identified.status in ("ok", "weakly_identified") and min(identified.estimator["usable"]) >= 100
        summary = posterior.summary()["modeling_uncertainty"]
        mean, std = identified.moments.mean, np.sqrt(np.diag(identified.moments.cov))
        hits += np.sum(np.abs(mean - TRUE_MEAN) <= 1.96 * np.asarray(summary["xi_mean_sd"]))
        hits += np.sum(np.abs(std - TRUE_STD) <= 1.96 * np.asarray(summary["xi_std_sd"]))
        paper = identified.estimator
        paper_hits += np.sum(np.abs(np.array(paper["summary_mean"]) - TRUE_MEAN) <= 1.96 * np.asarray(summary["xi_mean_sd"]))
        count += 4
    assert hits >= binom.ppf(0.0015, count, 0.95), f"{hits} of {count} intervals hold the truth"
    assert paper_hits < hits


def chunks_of_seven_paths(monkeypatch) -> None:
    """The identification's replicates and recorded paths simulated 7 paths a chunk: a replicate of 3 paths then
    falls into two chunks now and then, and the chunks end inside a round."""
    monkeypatch.setattr(identification, "bytes_per_path", lambda *args, **kwargs: 1)
    monkeypatch.setattr(identification, "MEMORY_BUDGET", 3 * 7)


def test_the_same_numbers_whatever_the_chunks(tmp_path, monkeypatch):
    """Replicates of several identification paths each (identification.paths) give the same bytes in chunks of 7
    paths, where a replicate's paths fall in different chunks."""
    exp = experiment(tmp_path, "seed=3", "identification.paths=3", "identification.replicates=60")
    whole, whole_draws = modeled(exp)
    assert whole.estimator["replicate_paths"] == 3 and "fallback" not in whole.estimator
    chunks_of_seven_paths(monkeypatch)
    parts, parts_draws = modeled(exp)
    np.testing.assert_array_equal(whole.moments.mean, parts.moments.mean)
    np.testing.assert_array_equal(whole.moments.cov, parts.moments.cov)
    np.testing.assert_array_equal(whole_draws.mean, parts_draws.mean)


def test_too_few_identified_replicates_keep_the_paper_moments_and_say_so(tmp_path, monkeypatch):
    exp = experiment(tmp_path, "seed=0")
    width = len(identification.summary_names(exp.model))
    monkeypatch.setattr(identification, "replicate_summaries",
                        lambda exp, enkf, F, theta, *rest: np.full((len(theta), width), np.nan))
    identified, uncertainty = modeled(exp)
    assert identified.status == "unsettled" and "0 of 200 replicates" in identified.estimator["fallback"]
    np.testing.assert_array_equal(identified.moments.mean, identified.estimator["summary_mean"])
    # their uncertainty is the prior box's (no posterior): a uniform's sd, width / sqrt(12), within 4 Monte Carlo sds
    # of 200 draws (a uniform sample's sd varies by sqrt((kurtosis 1.8 - 1) / (4 x 200)) = 0.032 of it)
    assert uncertainty.over == "the prior box"
    lo, hi = indirect.prior_box(np.concatenate([identified.estimator["summary_mean"],
                                                identified.estimator["summary_std"]]),
                                *identification.two_point_ends(exp), exp.identification.prior_width)
    sd = uncertainty.summary()["modeling_uncertainty"]["xi_mean_sd"]
    np.testing.assert_allclose(sd, (hi - lo)[:exp.model.p] / np.sqrt(12), rtol=4 * 0.032)


def test_the_paper_plant_keeps_the_paper_estimator(tmp_path):
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        assert build(compose("config", overrides=SMALL)).identification.estimator == "paper"
        with pytest.raises(ConfigError, match="identification.estimator: 'bogus' is not allowed"):
            build(compose("config", overrides=[*SMALL, "identification.estimator=bogus"]))
        assert build(compose("config", overrides=SMALL)).identification.replicate_laws == "random_shapes"
        with pytest.raises(ConfigError, match="identification.replicate_laws: 'gaussian' is not allowed, expected auto "
                                              "or one of random_shapes, normal"):
            build(compose("config", overrides=[*SMALL, "identification.replicate_laws=gaussian"]))
    assert experiment(tmp_path).identification.estimator == "simulated"


def data_experiment(tmp_path, seed, *extra, model=None, paths=40, steps=101):
    """A data run's Experiment on a new data set of `experiments/user_data.py` (a simulator rdsexp does not know):
    `paths` x `steps`, noise sd 0.01 (the EnKF assumes 0.1 unless told), the model file's structure (or `model`)."""
    from tests.conftest import REPO
    sys.path.insert(0, str(REPO / "experiments"))
    import user_data
    name = user_data.write_config(tmp_path)
    if model is not None:
        (tmp_path / "model" / f"{name}.yaml").write_text(yaml.safe_dump(model))
    data = user_data.write(tmp_path / f"d{seed}.csv", seed, paths=paths, steps=steps)
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        return build(compose("config", overrides=[
            f"hydra.searchpath=[file://{tmp_path}]", f"data.file={data}", f"model={name}", "plant=recorded",
            "tracking=off", "identification.replicates=200", f"seed={seed}", *extra])), user_data


def data_run(tmp_path, seed, *extra, **data):
    from rdsexp.experiment.pipeline.run import run_on_data
    exp, user_data = data_experiment(tmp_path, seed, *extra, **data)
    return exp, run_on_data(exp).summary, user_data


def test_a_data_run_of_a_users_own_simulator_holds_the_law_and_estimates_its_noise(tmp_path):
    """Recorded data of a simulator rdsexp does not know, with noise the EnKF does not assume (1e-4 against its
    1e-2): the replicates replay each recorded path's inputs, their noise scale is estimated, and over seeds the
    stated 95% intervals of both components' mean and std hold the law at about the nominal level (at least the
    count 3 binomial sds below it), and so do the noise scale's intervals hold the data's, 1e-2, each of them
    below 1: the data are less noisy than the EnKF assumes."""
    hits, count, noise = 0, 0, []
    for seed in range(6):
        exp, s, user_data = data_run(tmp_path, seed)
        assert exp.identification.estimator == "simulated" and s["modeling_status"] in ("ok", "weakly_identified")
        assert s["modeling_estimator"]["replicate_laws"] == "normal"      # auto, for a data run
        sd = s["modeling_uncertainty"]
        assert sd["over"] == "simulated replicates"
        hits += np.sum(np.abs(np.array(s["xi_mean"]) - user_data.TRUE_MEAN) <= 1.96 * np.array(sd["xi_mean_sd"]))
        hits += np.sum(np.abs(np.array(s["xi_std"]) - user_data.TRUE_STD) <= 1.96 * np.array(sd["xi_std_sd"]))
        count += 4
        noise.append(s["modeling_estimator"]["noise_scale"])
    assert hits >= binom.ppf(0.0015, count, 0.95), f"{hits} of {count} intervals hold the truth"
    held = sum(n["low"] <= 1e-2 <= n["high"] for n in noise)
    assert held >= binom.ppf(0.0015, len(noise), 0.95), f"{held} of {len(noise)} noise intervals hold 1e-2"
    assert all(n["low"] <= n["median"] <= n["high"] < 1 for n in noise), noise


def test_a_data_runs_replicates_are_the_same_whatever_the_chunks(tmp_path, monkeypatch):
    small = ("identification.replicates=80", "identification.horizon=50",
             "identification.K0=10", "identification.K1=40")
    _, whole, _ = data_run(tmp_path, 1, *small, paths=12, steps=51)
    chunks_of_seven_paths(monkeypatch)
    _, parts, _ = data_run(tmp_path, 1, *small, paths=12, steps=51)
    assert whole["xi_mean"] == parts["xi_mean"] and whole["xi_std"] == parts["xi_std"]
    assert whole["modeling_estimator"]["noise_scale"] == parts["modeling_estimator"]["noise_scale"]


SCALAR = {"name": "scalar", "A": [[[0.0]], [[1.0]]], "B": [[[1.0]], [[0.0]]], "C": [[[1.0]]], "nominal": [0.0],
          "xi": {"family": "normal", "mean": [0.5], "cov": [[0.04]]}}


# two states, each its own random gain, the gains correlated 0.8: only the outputs' joint spread shows the correlation
PAIR = {"name": "pair", "A": [[[0, 0], [0, 0]], [[1, 0], [0, 0]], [[0, 0], [0, 1]]],
        "B": [[[1, 0], [0, 1]], [[0, 0], [0, 0]], [[0, 0], [0, 0]]], "C": [[[1, 0], [0, 1]]], "nominal": [0.4, 0.4],
        "xi": {"family": "normal", "mean": [0.5, 0.3], "cov": [[0.04, 0.032], [0.032, 0.04]]}}


def test_the_modeled_correlation_holds_the_laws(tmp_path):
    """A law of correlated components (0.8): over seeds the modeled correlation's stated 95% interval holds it at
    about its level (at least the count 3 binomial sds below it), the data narrow it far inside the prior (a
    correlation's sd under the uniform partial-correlation box is about 0.55), and its error is a fraction of what
    independent components would make (0.8)."""
    (tmp_path / "plant").mkdir()
    (tmp_path / "plant" / "pair.yaml").write_text(yaml.safe_dump(PAIR))
    hits, errors, sds = 0, [], []
    for seed in range(8):
        with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
            exp = build(compose("config", overrides=[
                f"hydra.searchpath=[file://{tmp_path}]", "plant=pair", "model=plant", *SMALL, "tracking=off",
                "identification.horizon=60", "identification.K0=10", "identification.K1=50",
                "identification.replicates=250", f"seed={seed}"]))
        identified, posterior = modeled(exp)
        assert identified.status in ("ok", "weakly_identified") and "correlations" not in identified.estimator
        cov = identified.moments.cov
        error = cov[1, 0] / np.sqrt(cov[0, 0] * cov[1, 1]) - 0.8
        sd = posterior.summary()["modeling_uncertainty"]["xi_corr_sd"][0]
        hits += abs(error) <= 1.96 * sd
        errors.append(error)
        sds.append(sd)
    assert hits >= binom.ppf(0.0015, 8, 0.95), f"{hits} of 8 intervals hold the correlation"
    assert np.median(sds) < 0.2 and np.median(np.abs(errors)) < 0.15, (sds, errors)


@pytest.mark.slow
def test_the_error_shrinks_with_paths_on_a_fully_observed_scalar_system(tmp_path):
    """x+ = xi_k x + u_k, y = x, xi_k ~ N(0.5, 0.2^2): four times the identification paths (identification.paths,
    each replicate run as many times) roughly halves the modeled mean's and std's RMS error over seeds (asserted: by
    a factor above 1.4, where sqrt(4) = 2 is expected and 12 seeds estimate each RMS within about 20%), and the
    stated interval holds the truth at about its level at both."""
    (tmp_path / "plant").mkdir()
    (tmp_path / "plant" / "scalar.yaml").write_text(yaml.safe_dump(SCALAR))
    rms, hits = {}, 0
    for paths in (1, 4):
        errors = []
        for seed in range(12):
            with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
                exp = build(compose("config", overrides=[
                    f"hydra.searchpath=[file://{tmp_path}]", "plant=scalar", "model=plant", *SMALL, "tracking=off",
                    "identification.horizon=60", "identification.K0=10", "identification.K1=50",
                    f"identification.paths={paths}", "identification.replicates=200", f"seed={seed}"]))
            identified, posterior = modeled(exp)
            assert identified.trajectories.failed_at.size == paths
            assert identified.estimator.get("replicate_paths", 1) == paths
            sd = posterior.summary()["modeling_uncertainty"]
            error = np.array([identified.moments.mean[0] - 0.5, np.sqrt(identified.moments.cov[0, 0]) - 0.2])
            errors.append(error)
            hits += np.sum(np.abs(error) <= 1.96 * np.array([sd["xi_mean_sd"][0], sd["xi_std_sd"][0]]))
        rms[paths] = np.sqrt(np.mean(np.square(errors), axis=0))
    assert np.all(rms[1] / rms[4] > 1.4), rms
    assert hits >= binom.ppf(0.0015, 48, 0.95), f"{hits} of 48 intervals hold the truth"


def test_the_progress_bar_counts_every_round_it_runs(tmp_path, monkeypatch):
    """The modeling bar's total ends equal to the replicate paths run, where a pressed box adds a round beyond the
    planned ones (forced here) and the later rounds run identification.paths paths per replicate."""
    from contextlib import contextmanager

    from rdsexp.numerics import indirect
    bars = []

    class Counted(Stages):
        @staticmethod
        @contextmanager
        def progress(desc, total):
            bar = {"total": total, "done": 0}
            bars.append(bar)
            def update(steps, more=0):
                bar["total"] += more
                bar["done"] += steps
            yield update
    monkeypatch.setattr(indirect, "pressed", lambda draws, *rest: np.ones(draws.shape[1], dtype=bool))
    exp = experiment(tmp_path, "seed=1", "identification.paths=2", "identification.replicates=100")
    identified = identify_and_model(exp, Counted(cache=None), root_seed(exp, "identification"))
    rounds = len(identified.estimator["usable"])
    assert rounds == identification.POSTERIOR_ROUNDS[0] + 1           # one beyond the planned rounds
    assert bars == [{"total": 100 * (1 + 2 * (rounds - 1)), "done": 100 * (1 + 2 * (rounds - 1))}]


def test_a_failed_random_walk_is_read_again_with_an_iid_xi_and_so_are_the_replicates(tmp_path, monkeypatch):
    """Where the random-walk run fails, the summary comes from a run whose EnKF draws xi i.i.d. about the prior guess
    (enkf.Q's xi block), the replicates run that same EnKF, and the summary says so."""
    exp = experiment(tmp_path, "seed=0")
    real, calls, filters = identification.identified_moments, [], []
    def first_fails(exp, ident):
        calls.append(ident)
        return (None, "identification failed at k = 3: the EnKF estimate diverged") if len(calls) == 1 else \
            real(exp, ident)
    replicate = identification.replicate_summaries
    def spy(exp, enkf, *rest):
        filters.append(enkf)
        return replicate(exp, enkf, *rest)
    monkeypatch.setattr(identification, "identified_moments", first_fails)
    monkeypatch.setattr(identification, "replicate_summaries", spy)
    identified, _ = modeled(exp)
    assert identified.moments is not None and len(calls) == 2 and calls[0] is not calls[1]
    assert identified.estimator["summary_filter"].startswith("i.i.d. about the prior guess (the random walk's "
                                                            "identification failed at k = 3")
    n = exp.model.n
    for enkf in filters:
        np.testing.assert_array_equal(enkf.xi_prior.mean, exp.filter.psi0[n:])
        np.testing.assert_array_equal(enkf.xi_prior.cov, exp.filter.enkf.Q[n:, n:])


def test_the_held_out_validation_tells_the_law_from_a_wrong_one(tmp_path):
    """With the EnKF told the data's noise, the true law's one-step-ahead predictive covers the held-out outputs
    within the slack of 50% and 90% (measured 0.47-0.49 / 0.88-0.89), and a wrong law, the Bernoulli link at its
    mean (a model file that states no two-point link), is flagged on every seed (measured 0.01 / 0.04)."""
    from rdsexp.experiment.pipeline.data import validate_holdout
    from rdsexp.numerics.systems import MomentModel
    for seed in range(3):
        exp, user_data = data_experiment(tmp_path / str(seed), seed, "data.holdout=0.5", "enkf.Q.x=1e-4", "enkf.R=1e-4")
        law = MomentModel(mean=user_data.TRUE_MEAN, cov=np.diag(user_data.TRUE_STD ** 2))
        truth = validate_holdout(exp, law).summary
        assert truth["calibrated"], truth["modeled"]
        no_link = user_data.model()
        no_link["xi"]["components"][1] = {"family": "uniform", "low": [0.0], "high": [1.0]}
        exp, _ = data_experiment(tmp_path / str(seed), seed, "data.holdout=0.5", "enkf.Q.x=1e-4", "enkf.R=1e-4",
                                 model=no_link)
        wrong = validate_holdout(exp, MomentModel(mean=user_data.TRUE_MEAN, cov=np.zeros((2, 2)))).summary
        assert not wrong["calibrated"] and wrong["modeled"]["coverage_90"] < 0.9 - wrong["coverage_slack"][1]


def test_outputs_identically_zero_keep_the_window_moments_and_say_why(tmp_path):
    """A degenerate record (every output 0: no log mean square to match) runs no replicates and warns nothing: the
    window's moments, status unsettled, the reason in the summary."""
    import warnings

    import pandas as pd

    from rdsexp.experiment.pipeline.run import run_on_data
    exp, _ = data_experiment(tmp_path, 0)
    zeros = pd.read_csv(exp.data.data.file).assign(**{"y[0]": 0.0, "y[1]": 0.0})
    zeros.to_csv(tmp_path / "zeros.csv", index=False)
    exp, _ = data_experiment(tmp_path, 0, f"data.file={tmp_path / 'zeros.csv'}")
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        s = run_on_data(exp).summary
    estimator = s["modeling_estimator"]
    assert s["modeling_status"] == "unsettled" and estimator["usable"] == [] and "no path's summary" in \
        estimator["fallback"] and s["xi_mean"] == estimator["summary_mean"]


def test_the_summarys_correlations_are_fishers_z_to_the_last_digits():
    """`modeling.correlation_z` is artanh of the uncentered correlation, to round-off where r is moderate, and
    keeps its digits for two slow outputs whose r is 1 - 1e-15 to 1 - 1e-13 (the long-double reference within
    1e-3; r itself keeps one or two digits of 1 - r there); +-20 at r = +-1, NaN for an output identically 0."""
    rng = np.random.default_rng(5)
    a = rng.standard_normal((80, 6))
    b = 0.4 * a + rng.standard_normal((80, 6))
    r = (a * b).sum(axis=0) / np.sqrt((a * a).sum(axis=0) * (b * b).sum(axis=0))
    np.testing.assert_allclose(correlation_z(a, b), np.arctanh(r), rtol=0, atol=1e-13)
    ramp = 1 + np.linspace(0, 1, 101)[:, None] * np.ones((1, 4))
    for scale in (1e-7, 1e-6):
        slow = ramp + scale * rng.standard_normal(ramp.shape)
        x, y = slow.astype(np.longdouble), ramp.astype(np.longdouble)
        unit = lambda v: v / np.sqrt((v * v).sum(axis=0))
        exact = 0.5 * np.log(((unit(x) + unit(y)) ** 2).sum(axis=0) / ((unit(x) - unit(y)) ** 2).sum(axis=0))
        z = correlation_z(slow, ramp)
        assert np.all(np.isfinite(z)) and np.all(z < 20)
        np.testing.assert_allclose(z, exact.astype(float), rtol=0, atol=1e-3)
    flat = np.ones((10, 1))
    assert correlation_z(flat, flat)[0] == 20 and correlation_z(flat, -flat)[0] == -20
    assert np.isnan(correlation_z(np.zeros((10, 1)), flat)[0])


def test_correlations_are_fitted_where_the_replicates_afford_the_quadratic_fit():
    """theta's partial correlations join the regression where 10 replicates per coefficient of its quadratic fit
    remain (2 components of xi: 5 in theta, 210 replicates), else they keep their prior box (3 components: 9, 550;
    4: 14, 1200), and the model is then independent."""
    for p, replicates, fit_them in [(2, 400, True), (2, 200, False), (3, 400, False), (3, 600, True), (4, 600, False)]:
        ends = np.zeros(p, dtype=bool)
        box = indirect.prior_box(np.ones(2 * p), ends, np.zeros(p), np.ones(p), 2.5)
        fit = identification.fitted(box, ends, replicates)
        columns = indirect.correlation_columns(ends)
        assert fit[:2 * p].all() and np.all(fit[columns] == fit_them) and fit.size == 2 * p + p * (p - 1) // 2
    draws = np.concatenate([np.zeros((50, 4)), np.full((50, 4), 0.5), np.full((50, 6), 0.9)], axis=1)
    _, cov = indirect.posterior_moments(draws, np.ones(50), np.zeros(4, dtype=bool), np.zeros(4), np.ones(4),
                                        correlated=False)
    np.testing.assert_array_equal(cov, 0.25 * np.eye(4))


def test_the_misfit_bound_holds_its_level_over_the_whole_summary():
    """The misfit bound is 4 sds for a short summary and grows with the components read, so that k standard normal
    components all read within it at least 1 - 1e-3 of the time whatever k (exactly: 1 - (1 - 2 Phi(-b))^k)."""
    from scipy.stats import norm
    bounds = [identification.misfit_bound(k) for k in range(1, 200)]
    assert bounds[0] == 4.0 and np.all(np.diff(bounds) >= 0) and bounds[-1] > 4.4
    for k, b in zip(range(1, 200), bounds):
        assert 1 - (1 - 2 * norm.sf(b)) ** k <= 1e-3 + 1e-12
