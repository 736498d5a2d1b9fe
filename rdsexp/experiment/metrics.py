"""The metric registry: every number or word of a run that the catalog shows, declared once.

A run's key results are run.json's `summary` (written by the pipeline; its keys and meanings are
`schema.RUN_SUMMARY_KEYS`). The catalog flattens it into columns `metrics.NAME` (`flatten`), and
every view of those columns reads this registry instead of a list of its own:

    flatten          the runs table's metrics.* columns (`RunRecord.metrics`, `store.table.runs_table`)
    listed()         the default metric columns of `rdsexp-runs list` (and with --changed)
    per_job()        a sweep's table per job (`rdsexp-runs show SWEEP`, the sweep's recording)
    plotted()        the metrics a sweep's recording draws against the swept values, first
    mlflow_first()   the metrics logged first to MLflow (its compare view draws the first)
    objectives()     the metrics a tuning study may take as its objective (config `objective`)
    exact_counterpart(name)   the exact number a Monte Carlo estimate estimates a function of
    markdown()       the metric table of docs/data_dictionary.md

Adding a metric is one `Metric` below (and the stage that writes it into the summary). A summary
entry that no `Metric` declares is still flattened into columns by its shape (a number: one column;
a list: NAME[i]; a record: NAME_FIELD), so every number a run wrote can be searched; declaring it
gives it a label, a kind and its places in the views.

No numerics, pandas or Hydra here: the command line imports it at start.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

RATE, FRACTION, COUNT, NUMBER, VERDICT, TEXT = "rate", "fraction", "count", "number", "verdict", "text"
KINDS = (RATE, FRACTION, COUNT, NUMBER, VERDICT, TEXT)
NUMERIC = (RATE, FRACTION, COUNT, NUMBER)
MINIMIZE, MAXIMIZE = "minimize", "maximize"
SUMMARY, OBJECTIVE, RUN = "summary", "objective", "run"       # where in run.json a metric's value is

# the run's headline number: MLflow's compare view (parallel coordinates) draws the first metric logged
HEADLINE = "closed_loop_rate"


@dataclass(frozen=True)
class Metric:
    """One catalog metric, column `metrics.NAME`.

    name: the column's name after `metrics.`, and (source summary) the summary key it is read from.
    label: a few words for a table header or a legend. kind: rate, fraction, count, number (a value with
    a unit), verdict (a word decided by evidence) or text. unit: as the data dictionary writes it.
    source: where run.json holds it: its `summary`, a tuning trial's `objective` (mean, se, seeds), or the
    run itself (seconds).
    interval: the summary holds [value, low, high] (a 95% interval): columns NAME, NAME_low, NAME_high.
    zero_if: the summary key (a loop's status) whose presence, without this metric, means 0 (a loop that
    ran with no failed path writes no {loop}_failed record).
    listed: a default column of `rdsexp-runs list`. per_job: a column of a sweep's table per job.
    plotted: drawn first against the swept values in a sweep's recording.
    objective: a tuning objective (config `objective`) in this direction (minimize or maximize).
    exact: the metric's exact counterpart, a number it estimates a function of (closed_loop_rate, a
    Monte Carlo estimate: rate_plant, the gain's exact rate on the true plant).
    """

    name: str
    label: str
    kind: str
    unit: str | None = None
    source: str = SUMMARY
    interval: bool = False
    zero_if: str | None = None
    listed: bool = False
    per_job: bool = False
    plotted: bool = False
    objective: str | None = None
    exact: str | None = None

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"metric {self.name}: kind {self.kind!r} is not one of {', '.join(KINDS)}")
        if self.objective not in (None, MINIMIZE, MAXIMIZE):
            raise ValueError(f"metric {self.name}: objective {self.objective!r} is not minimize or maximize")
        if self.source not in (SUMMARY, OBJECTIVE, RUN):
            raise ValueError(f"metric {self.name}: source {self.source!r} is not summary, objective or run")

    @property
    def column(self) -> str:
        """The runs table's column, `metrics.NAME`."""
        return f"metrics.{self.name}"

    @property
    def numeric(self) -> bool:
        return self.kind in NUMERIC


# In this order: the order of every view (list, per job, plotted rates then fractions, objectives).
_DECLARED = (
    Metric("lam", "design's decay rate lambda", RATE, "1/step", listed=True, per_job=True, plotted=True,
           objective=MINIMIZE),
    Metric("rate_plant", "gain's exact rate on the plant", RATE, "1/step", listed=True, per_job=True, plotted=True,
           objective=MINIMIZE),
    Metric("closed_loop_rate", "closed loop's rate", RATE, "1/step", interval=True, listed=True, per_job=True,
           plotted=True, objective=MINIMIZE, exact="rate_plant"),
    Metric("closed_loop_verdict", "closed loop's verdict", VERDICT, listed=True, per_job=True),
    Metric("closed_loop_paths", "closed loop's paths (closed_loop.paths auto: the last look's)", COUNT, listed=True,
           per_job=True),
    Metric("closed_loop_failed_fraction", "closed loop's failed paths", FRACTION, zero_if="closed_loop_status",
           per_job=True, plotted=True, objective=MINIMIZE),
    Metric("open_loop_rate", "open loop's rate", RATE, "1/step", interval=True, per_job=True, plotted=True,
           objective=MINIMIZE, exact="open_loop_exact_rate"),
    Metric("online_rate", "online loop's rate", RATE, "1/step", interval=True, objective=MINIMIZE,
           exact="rate_plant"),
    Metric("closed_loop_exact_rate", "ideal closed loop's exact rate", RATE, "1/step", plotted=True,
           objective=MINIMIZE),
    Metric("open_loop_exact_rate", "ideal open loop's exact rate", RATE, "1/step", plotted=True),
    Metric("open_loop_failed_fraction", "open loop's failed paths", FRACTION, zero_if="open_loop_status",
           plotted=True),
    Metric("open_loop_verdict", "open loop's verdict", VERDICT),
    Metric("online_verdict", "online loop's verdict", VERDICT),
    Metric("closed_loop_status", "closed loop's paths: ok, partially_failed or failed", TEXT),
    Metric("modeling_status", "modeling status", TEXT, listed=True),
    Metric("synthesis_status", "design status of the loop's gain", TEXT),
    Metric("xi_mean_error", "RMS error of the modeled mean of xi", NUMBER, "xi", objective=MINIMIZE),
    Metric("xi_std_error", "RMS error of the modeled std of xi", NUMBER, "xi", objective=MINIMIZE),
    Metric("xi_crps", "CRPS of the modeled law of xi", NUMBER, "xi", objective=MINIMIZE),
    Metric("rate_model", "gain's exact rate on the identified model (data run)", RATE, "1/step"),
    Metric("cost_ratio_plant", "LQ gain's exact cost on the plant over the optimum for its law", NUMBER,
           objective=MINIMIZE),
    Metric("rate_excess_plant", "rate gain's exact rate on the plant minus the optimal rate", RATE, "1/step",
           objective=MINIMIZE),
    Metric("seconds", "compute time of the run", NUMBER, "s", source=RUN, objective=MINIMIZE),
    Metric("objective_mean", "tuning trial's objective, mean over its seeds", NUMBER, source=OBJECTIVE, listed=True),
    Metric("objective_se", "standard error of objective_mean", NUMBER, source=OBJECTIVE, listed=True),
    Metric("objective_seeds", "seeds the objective is averaged over", COUNT, source=OBJECTIVE),
)
# name -> Metric, in declaration order; `register` adds to it
REGISTRY: dict[str, Metric] = {m.name: m for m in _DECLARED}

# summary entries that are settings or nested records rather than numbers of the run: not flattened
SETTINGS = ("plant", "model", "gain_method", "rate_window", "reference", "designs", "identification_feedback",
            "data", "no_plant", "design_rates")


def register(metric: Metric) -> Metric:
    """Declare a metric (ValueError if its name is taken); returns it. The views read REGISTRY when they
    are drawn, so a metric registered before that is in all of them."""
    if metric.name in REGISTRY:
        raise ValueError(f"metric {metric.name}: already registered")
    REGISTRY[metric.name] = metric
    return metric


def unregister(name: str) -> None:
    """Remove a registered metric (what `register` added)."""
    REGISTRY.pop(name)


# ------------------------------------------------------------------ views

def listed() -> list[Metric]:
    """The default metric columns of `rdsexp-runs list`, in order."""
    return [m for m in REGISTRY.values() if m.listed]


def per_job() -> list[Metric]:
    """The metric columns of a sweep's table per job, in order."""
    return [m for m in REGISTRY.values() if m.per_job]


def plotted() -> list[Metric]:
    """The metrics a sweep's recording draws first, in order."""
    return [m for m in REGISTRY.values() if m.plotted]


def mlflow_first() -> list[Metric]:
    """The metrics logged first to MLflow: the headline, then the numeric metrics per job."""
    return [REGISTRY[HEADLINE], *(m for m in per_job() if m.numeric and m.name != HEADLINE)]


def objectives() -> tuple[str, ...]:
    """The metrics a tuning study may take as its objective (config `objective`)."""
    return tuple(m.name for m in REGISTRY.values() if m.objective)


def exact_counterpart(name: str) -> str | None:
    """The exact number metric `name` estimates a function of (closed_loop_rate: rate_plant); None without one."""
    metric = REGISTRY.get(name)
    return metric.exact if metric is not None else None


def kind_of(name: str) -> str | None:
    """The kind of a catalog column (with or without `metrics.`): a registered metric's; else, by its name,
    a fraction (..._fraction) or a rate (lam, or a name with a `rate` word that is no interval bound
    _low/_high nor quantile _q10/_q90, e.g. online_final_rate_plant_median); None otherwise."""
    name = name.removeprefix("metrics.")
    if name in REGISTRY:
        return REGISTRY[name].kind
    if name.endswith("_fraction"):
        return FRACTION
    if name == "lam" or ("rate" in name.split("_") and not name.endswith(("_low", "_high", "_q10", "_q90"))):
        return RATE
    return None


# ------------------------------------------------------------------ the flattening

def flatten(summary: Mapping, objective: Mapping | None = None, seconds: float | None = None) -> dict:
    """{"metrics.NAME": value}: run.json's summary flattened into catalog columns, a tuning trial's
    objective (objective_mean, _se, _seeds) and the run's seconds; None is NaN.

    An interval metric [value, low, high] gives NAME, NAME_low, NAME_high; any other list NAME[i]; a
    record NAME_FIELD (its lists NAME_FIELD[i]; a record in it, NAME_FIELD_SUB for its scalars: a data
    run's validation by law); a number or word one column. SETTINGS are left out."""
    out = {}
    for name, value in summary.items():
        if name in SETTINGS:
            continue
        metric = REGISTRY.get(name)
        if metric is not None and metric.interval and isinstance(value, list) and len(value) == 3:
            out[name], out[f"{name}_low"], out[f"{name}_high"] = value
        elif isinstance(value, dict):
            for k, v in value.items():
                if isinstance(v, dict):
                    out |= {f"{name}_{k}_{kk}": vv for kk, vv in v.items() if not isinstance(vv, (list, dict))}
                else:
                    out |= {f"{name}_{k}[{i}]": x for i, x in enumerate(v)} if isinstance(v, list) else \
                        {f"{name}_{k}": v}
        elif isinstance(value, list):
            out |= {f"{name}[{i}]": v for i, v in enumerate(value)}
        else:
            out[name] = value
    for metric in REGISTRY.values():
        if metric.zero_if is not None and metric.zero_if in summary:
            out.setdefault(metric.name, 0.0)
    objective = objective or {}
    if "mean" in objective:
        out |= {"objective_mean": objective["mean"], "objective_se": objective["se"],
                "objective_seeds": len(objective.get("seeds") or [])}
    out["seconds"] = seconds
    return {f"metrics.{k}": (math.nan if v is None else v) for k, v in out.items()}


# ------------------------------------------------------------------ the data dictionary

def markdown() -> list[str]:
    """The data dictionary's table of catalog metrics (lines of docs/data_dictionary.md)."""
    def mark(flag) -> str:
        return "yes" if flag else ""
    lines = ["## Catalog metrics", "",
             "The metrics the catalog declares (`rdsexp/experiment/metrics.py`): their column in `rdsexp.runs.search`",
             "and `rdsexp-runs list`, kind and unit, whether `list` shows them by default, a sweep's table shows them",
             "per job and its recording plots them, whether a tuning study may take them as `objective`, and their",
             "exact counterpart. Every other entry of the summary is a column too, flattened by its shape.", "",
             "| column | label | kind | unit | list | per job | plotted | objective | exact counterpart |",
             "|---|---|---|---|---|---|---|---|---|"]
    for m in REGISTRY.values():
        column = f"`{m.column}`" + (" (`_low`, `_high`)" if m.interval else "")
        lines.append(f"| {column} | {m.label} | {m.kind} | {m.unit or ''} | {mark(m.listed)} | {mark(m.per_job)} | "
                     f"{mark(m.plotted)} | {m.objective or ''} | {f'`{m.exact}`' if m.exact else ''} |")
    return [*lines, ""]
