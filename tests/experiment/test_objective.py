"""`objective=METRIC`: the job returns one float for an optimizing sweeper, and +sweep=tune_enkf runs Optuna (rdsexp's
Hydra sweeper, hydra_plugins/rdsexp_optuna)."""
import io
import json
import math

import numpy as np
import pandas as pd
import pytest
import yaml
from conftest import SMALL, rdsexp
from hydra import compose, initialize_config_module

from rdsexp.experiment.config import ConfigError, build
from rdsexp.experiment.runner import job_config, objective_value
from rdsexp.experiment.store import provenance


@pytest.fixture(autouse=True)
def hydra_context():
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        yield


def info(status="complete", rate=0.9, failed=None, **summary):
    s = {"closed_loop_status": "ok", "closed_loop_rate": [rate, rate - 0.01, rate + 0.01], "lam": 0.8} | summary
    if failed is not None:
        s["closed_loop_failed"] = {"fraction": failed}
    return {"id": "run", "status": status, "summary": s, "seconds": 4.0}


@pytest.mark.parametrize("record, name, penalty, expected", [
    (info(), "closed_loop_rate", 1.0, 0.9),                      # a rate's point estimate
    (info(failed=0.25), "closed_loop_rate", 2.0, 0.9 + 2.0 * 0.25),   # failed paths add penalty x fraction
    (info(failed=0.25), "closed_loop_failed_fraction", 2.0, 0.25),    # ... but not to the fraction itself
    (info(rate=float("nan"), failed=1.0), "closed_loop_rate", 1.0, math.inf),   # no rate measured
    (info(status="error"), "lam", 1.0, math.inf),               # a run that did not complete
    (info(), "xi_mean_error", 1.0, math.inf),                   # no such number in this run
    (info(xi_mean_error=0.03), "xi_mean_error", 1.0, 0.03),
    (info(), "seconds", 0.0, 4.0),
])
def test_objective_value(record, name, penalty, expected):
    assert objective_value(record, name, penalty) == pytest.approx(expected)


def test_objective_is_checked_and_left_out_of_the_config_hash():
    with pytest.raises(ConfigError, match="objective: 'rate' is not allowed, expected null or one of lam"):
        build(compose("config", overrides=["objective=rate"]))
    with pytest.raises(ConfigError, match="objective_penalty: -1"):
        build(compose("config", overrides=["objective=lam", "objective_penalty=-1"]))
    with pytest.raises(ConfigError, match="objective_seeds: 0 is not allowed, expected a whole number >= 1"):
        build(compose("config", overrides=["objective=lam", "objective_seeds=0"]))
    plain = compose("config")
    tuned = compose("config", overrides=["objective=lam", "objective_penalty=3", "objective_seeds=5"])
    assert provenance.config_hash(job_config(plain)) == provenance.config_hash(job_config(tuned))


@pytest.mark.slow
def test_tune_enkf_averages_each_trial_over_seeds_and_holds_out_the_best(tmp_path):
    """Three Optuna trials of two seeds each on a small paper plant: every seed a complete run in the study's
    directory; each trial's stored mean and standard error recomputed from its stored runs; Optuna minimized
    those means; the best trial re-run on two fresh seeds, recorded, found by the catalog and reported."""
    proc = rdsexp("+sweep=tune_enkf", "hydra.sweeper.n_trials=3", "objective_seeds=2", "tracking.recording=false",
                  *SMALL, cwd=tmp_path, timeout=600)
    (sweep,) = (tmp_path / "outputs" / "sweeps").iterdir()
    runs = {p.parent.name: json.loads(p.read_text()) for p in sorted(sweep.glob("*/run.json"))}
    assert sorted(runs) == ["0", "0.seed1", "1", "1.seed1", "2", "2.seed1", "heldout.seed2", "heldout.seed3"]
    assert all(r["status"] == "complete" for r in runs.values())
    assert len({(runs[j]["params"]["enkf.q_scale"], runs[j]["params"]["enkf.r_scale"]) for j in "012"}) == 3
    means = {}
    for job in "012":
        trial, other = runs[job], runs[f"{job}.seed1"]
        assert other["params"] == {**trial["params"], "seed": 1} and other["objective"]["trial"] == trial["id"]
        values = [objective_value(r, "closed_loop_rate", 1.0) for r in (trial, other)]
        recorded = trial["objective"]
        assert recorded["values"] == values and recorded["seeds"] == [0, 1]
        assert recorded["mean"] == pytest.approx(np.mean(values), rel=1e-12)
        assert recorded["se"] == pytest.approx(abs(values[0] - values[1]) / 2, rel=1e-9)   # std(ddof=1) / sqrt(2)
        means[trial["id"]] = recorded["mean"]
    best = yaml.safe_load((sweep / "optimization_results.yaml").read_text())
    assert best["best_value"] == pytest.approx(min(means.values()))
    # the study's storage, as optuna-dashboard opens it: three complete trials, their values the trials' means
    import optuna
    study = optuna.load_study(study_name="tune_enkf", storage=f"sqlite:///{sweep / 'study.db'}")
    assert [t.state for t in study.trials] == [optuna.trial.TrialState.COMPLETE] * 3
    assert sorted(t.value for t in study.trials) == pytest.approx(sorted(means.values()), rel=1e-12)
    assert study.best_params == best["best_params"]
    best_id = min(means, key=means.get)
    held = runs["heldout.seed3"]["objective"]
    assert held["role"] == "heldout" and held["of"] == best_id and held["seeds"] == [2, 3]
    values = [objective_value(runs[f"heldout.seed{s}"], "closed_loop_rate", 1.0) for s in (2, 3)]
    assert held["mean"] == pytest.approx(np.mean(values), rel=1e-12)
    assert json.loads((sweep / "heldout.json").read_text())["mean"] == held["mean"]
    for s in (2, 3):
        assert runs[f"heldout.seed{s}"]["params"] == {**runs[best_id.split("/")[1]]["params"], "seed": s}
    from rdsexp.runs import search
    found = search(sweep, "objective_role == 'heldout'")
    assert sorted(found["seed"]) == [2, 3] and found["metrics.objective_mean"].dropna().tolist() == [held["mean"]]
    listed = rdsexp("list", sweep, "--csv", module="rdsexp.runs", cwd=tmp_path).stdout      # the catalog's view
    shown = pd.read_csv(io.StringIO(listed)).set_index("id")
    assert shown.loc[best_id, "metrics.objective_mean"] == pytest.approx(means[best_id], rel=1e-9)
    assert shown.loc[best_id, "metrics.objective_se"] == pytest.approx(runs[best_id.split("/")[1]]["objective"]["se"], rel=1e-9)
    assert shown.loc[runs["heldout.seed3"]["id"], "metrics.objective_mean"] == pytest.approx(held["mean"], rel=1e-9)
    assert f"tuning: best trial {best_id}: closed_loop_rate {means[best_id]:.4f}" in proc.stdout
    assert "held out on fresh seeds [2, 3]" in proc.stdout and "exact counterpart rate_plant" in proc.stdout


def test_a_bad_sweeper_setting_is_one_line_before_any_trial(tmp_path):
    """rdsexp's Optuna sweeper checks its settings (and that Optuna is installed) before any trial: one config-error
    line, exit 2, nothing written (Hydra has made the sweep's directory, empty)."""
    proc = rdsexp("+sweep=tune_enkf", "hydra.sweeper.direction=up", *SMALL, cwd=tmp_path, check=False)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1] == ("rdsexp: config error: hydra.sweeper.direction: 'up' is not allowed, "
                                                    "expected minimize or maximize")
    assert not [p for p in (tmp_path / "outputs").rglob("*") if p.is_file()]
