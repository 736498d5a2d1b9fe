"""The metric registry (rdsexp/experiment/metrics.py): one declaration per metric drives the catalog's columns,
`list`, a sweep's table per job, its recording, the MLflow export, the tuning objectives and the data dictionary."""
import math

import pandas as pd
import pytest
from conftest import REPO
from omegaconf import OmegaConf

from rdsexp.experiment import catalog, config, metrics, schema
from rdsexp.experiment.config import ConfigError
from rdsexp.experiment.runner import objective_value
from rdsexp.experiment.store import RunRecord
from rdsexp.experiment.store.table import sweep_results
from rdsexp.report import to_mlflow


def record(summary: dict, **more) -> RunRecord:
    return RunRecord.parse({"id": "r", "status": "complete", "seconds": 3.0, "summary": summary, **more})


@pytest.fixture
def settle_rate():
    """A metric a stage might add: the settling loop's rate with its interval, shown everywhere, an objective."""
    metric = metrics.register(metrics.Metric("settle_rate", "settling loop's rate", metrics.RATE, "1/step",
                                             interval=True, listed=True, per_job=True, plotted=True,
                                             objective=metrics.MINIMIZE, exact="rate_plant"))
    yield metric
    metrics.unregister(metric.name)


def test_the_views_are_todays_lists():
    """What list, show SWEEP, the sweep recording, MLflow and the tuning objectives read from the registry."""
    names = lambda ms: [m.name for m in ms]                      # noqa: E731
    assert names(metrics.listed()) == ["lam", "rate_plant", "closed_loop_rate", "closed_loop_verdict",
                                       "closed_loop_paths", "modeling_status", "objective_mean", "objective_se"]
    assert names(metrics.per_job()) == ["lam", "rate_plant", "closed_loop_rate", "closed_loop_verdict",
                                        "closed_loop_paths", "closed_loop_failed_fraction", "open_loop_rate"]
    assert names(metrics.plotted()) == ["lam", "rate_plant", "closed_loop_rate", "closed_loop_failed_fraction",
                                        "open_loop_rate", "closed_loop_exact_rate", "open_loop_exact_rate",
                                        "open_loop_failed_fraction"]
    assert names(metrics.mlflow_first()) == ["closed_loop_rate", "lam", "rate_plant", "closed_loop_paths",
                                             "closed_loop_failed_fraction", "open_loop_rate"]
    assert set(metrics.objectives()) == {"lam", "rate_plant", "closed_loop_rate", "open_loop_rate", "online_rate",
                                         "closed_loop_exact_rate", "xi_mean_error", "xi_std_error", "xi_crps",
                                         "closed_loop_failed_fraction", "seconds", "cost_ratio_plant", "rate_excess_plant"}
    assert {n: metrics.exact_counterpart(n) for n in ("closed_loop_rate", "online_rate", "open_loop_rate", "lam")} \
        == {"closed_loop_rate": "rate_plant", "online_rate": "rate_plant", "open_loop_rate": "open_loop_exact_rate",
            "lam": None}


def test_flattening():
    """Intervals by the registry, other lists by component, records by field, a loop's failed fraction 0 where it
    ran and no path failed, settings left out, None as NaN."""
    flat = record({"plant": "paper", "closed_loop_status": "ok", "closed_loop_rate": [0.9, 0.8, 1.0],
                   "open_loop_status": "partially_failed", "open_loop_failed": {"fraction": 0.5, "first_k": 3},
                   "xi_mean": [0.5, 0.7], "lam": None, "validation": {"modeled": {"crps": 0.1, "levels": [1]}}},
                  objective={"role": "trial", "mean": 0.9, "se": 0.01, "seeds": [0, 1]}).metrics
    assert list(flat) == ["metrics.closed_loop_status", "metrics.closed_loop_rate", "metrics.closed_loop_rate_low",
                          "metrics.closed_loop_rate_high", "metrics.open_loop_status",
                          "metrics.open_loop_failed_fraction", "metrics.open_loop_failed_first_k",
                          "metrics.xi_mean[0]", "metrics.xi_mean[1]", "metrics.lam", "metrics.validation_modeled_crps",
                          "metrics.closed_loop_failed_fraction", "metrics.objective_mean", "metrics.objective_se",
                          "metrics.objective_seeds", "metrics.seconds"]
    assert flat["metrics.closed_loop_failed_fraction"] == 0.0 and flat["metrics.open_loop_failed_fraction"] == 0.5
    assert math.isnan(flat["metrics.lam"]) and flat["metrics.objective_seeds"] == 2 and flat["metrics.seconds"] == 3.0


def test_a_registered_metric_is_in_every_view(settle_rate):
    """Adding a metric is its declaration: the flattening, `list`, show SWEEP, the sweep recording, MLflow, the
    objectives (checked and computed), its exact counterpart and the data dictionary all follow."""
    run = record({"settle_rate": [0.7, 0.6, 0.8], "rate_plant": 0.65, "closed_loop_status": "ok",
                  "closed_loop_failed": {"fraction": 0.1}})
    assert run.metric("settle_rate") == 0.7 and run.metrics["metrics.settle_rate_high"] == 0.8
    assert "metrics.settle_rate[0]" not in run.metrics                   # an interval, not three components
    table = pd.DataFrame([{"id": "r", "job": 0, "status": "complete", "reused_from": None, **run.metrics}])
    assert "metrics.settle_rate" in catalog.listed_columns(table)
    assert "metrics.settle_rate" in sweep_results(table).columns
    numbers, _ = to_mlflow._scalars(run.metrics)                        # logged first: the per-job numbers
    assert list(numbers)[:3] == ["rate_plant", "closed_loop_failed_fraction", "settle_rate"]
    from rdsexp.experiment.recording import _sweep_metrics
    assert _sweep_metrics(table) == (["metrics.rate_plant", "metrics.settle_rate"],
                                     ["metrics.closed_loop_failed_fraction"])
    config.check_objective(OmegaConf.create({"objective": "settle_rate"}))
    assert objective_value(run, "settle_rate", penalty=2.0) == pytest.approx(0.7 + 2.0 * 0.1)
    assert metrics.exact_counterpart("settle_rate") == "rate_plant"
    assert "| `metrics.settle_rate` (`_low`, `_high`) | settling loop's rate | rate |" in schema.markdown()
    assert schema.summary_entry("settle_rate") == ("settling loop's rate", "1/step")      # documented


def test_an_objective_not_registered_is_refused():
    with pytest.raises(ConfigError, match="objective: 'settle_rate' is not allowed, expected null or one of lam, "):
        config.check_objective(OmegaConf.create({"objective": "settle_rate"}))


def test_a_maximized_objective_is_negated():
    metric = metrics.register(metrics.Metric("coverage", "coverage", metrics.FRACTION, objective=metrics.MAXIMIZE))
    try:
        assert objective_value(record({"coverage": 0.9}), "coverage", 1.0) == -0.9
    finally:
        metrics.unregister(metric.name)


def test_declarations_are_checked():
    with pytest.raises(ValueError, match="metric x: kind 'speed' is not one of rate"):
        metrics.Metric("x", "x", "speed")
    with pytest.raises(ValueError, match="metric lam: already registered"):
        metrics.register(metrics.Metric("lam", "lam", metrics.RATE))


def test_data_dictionary_lists_every_registered_metric():
    """docs/data_dictionary.md's metric table is the registry's (the whole page: test_runs)."""
    page = (REPO / "docs" / "data_dictionary.md").read_text()
    assert "\n".join(metrics.markdown()) in page
    for metric in metrics.REGISTRY.values():
        assert f"| `{metric.column}`" in page, metric.name
