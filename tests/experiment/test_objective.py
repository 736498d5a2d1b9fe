"""`objective=METRIC`: the job returns one float for an optimizing sweeper, and +sweep=tune_enkf runs Optuna."""
import json
import math

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
    return {"status": status, "summary": s, "seconds": 4.0}


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
    plain, tuned = compose("config"), compose("config", overrides=["objective=lam", "objective_penalty=3"])
    assert provenance.config_hash(job_config(plain)) == provenance.config_hash(job_config(tuned))


def test_tune_enkf_runs_optuna_trials_as_stored_runs(tmp_path):
    """Three Optuna trials on a small paper plant: each a complete run in the store, the study and its best
    trial in the sweep directory, the best value the smallest objective of the stored runs."""
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper")
    rdsexp("+sweep=tune_enkf", "hydra.sweeper.n_trials=3", "tracking.recording=false", *SMALL, cwd=tmp_path,
           timeout=600)
    (sweep,) = (tmp_path / "outputs" / "sweeps").iterdir()
    runs = [json.loads(p.read_text()) for p in sorted(sweep.glob("*/run.json"))]
    assert len(runs) == 3 and all(r["status"] == "complete" for r in runs)
    assert len({(r["params"]["enkf.q_scale"], r["params"]["enkf.r_scale"]) for r in runs}) == 3   # 3 proposals
    assert (sweep / "study.db").stat().st_size > 0
    best = yaml.safe_load((sweep / "optimization_results.yaml").read_text())
    values = [objective_value(r, "closed_loop_rate", 1.0) for r in runs]
    assert best["best_value"] == pytest.approx(min(values))
