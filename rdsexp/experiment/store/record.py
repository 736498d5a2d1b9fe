"""run.json as typed values: `RunRecord` (one run's record) and `RunSummary` (its key numbers).

A run.json is parsed once, here, at the store's boundary (`Run.record`, `RunStore`); what older
rdsexp versions wrote differently is made current here and nowhere else:

- `seed` was the root seed itself before it became {"root", "spawn_keys", "per_path"};
- `sweep` had no `name` (a `-m` run's name is then the overrides that sweep, from multirun.yaml) and
  no `resumes`;
- `plant_hash`, `command`, `finished`, `reused_from` and `error` may be missing (None).

Callers read fields (`record.summary.rate()`, `record.objective.mean`, `record.tables`), never run.json's
keys; `RunRecord.raw`, the whole run.json as read, is for the store's own modules (the writer's format
stays the dict it wrote). The catalog's metrics of a record are `RunRecord.metrics` (the registry's
flattening, `rdsexp.experiment.metrics`).
"""
from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import yaml

from ..metrics import flatten
from .layout import MULTIRUN

NAN = float("nan")


@dataclass(frozen=True)
class SweepRef:
    """The sweep a run is a job of: its directory, job number, name (`+sweep=NAME`, or the overrides of a
    `-m` run that sweep), the interrupted sweep it resumes (None: a first launch) and the name run.json
    records (`+sweep=NAME`'s; None for a `-m` run)."""

    dir: Path
    job: int | None
    name: str | None
    resumes: str | None = None
    recorded_name: str | None = field(default=None, compare=False)    # `+sweep=NAME`'s NAME, None without one

    @property
    def id(self) -> str:
        """The sweep's id: its directory's name."""
        return self.dir.name

    def as_recorded(self, job: int | None) -> dict:
        """run.json's `sweep` of a run of this sweep with job number `job` (a held-out re-run's: None)."""
        return {"dir": str(self.dir), "job": job, "name": self.recorded_name, "resumes": self.resumes}


@dataclass(frozen=True)
class RunSummary(Mapping):
    """run.json's `summary` (keys and meanings: `schema.RUN_SUMMARY_KEYS`, docs/data_dictionary.md): a read-only
    mapping, with the key numbers a catalog reads as typed accessors."""

    values: dict = field(default_factory=dict)

    def __getitem__(self, key: str):
        return self.values[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self.values)

    def __len__(self) -> int:
        return len(self.values)

    @property
    def plant(self) -> str | None:
        return self.values.get("plant")

    @property
    def model(self) -> str | None:
        return self.values.get("model")

    @property
    def gain_method(self) -> str | None:
        return self.values.get("gain_method")

    @property
    def modeling_status(self) -> str | None:
        """ok, unsettled, at_prior_edge, weakly_identified (moments were modeled), or why no model was made."""
        return self.values.get("modeling_status")

    @property
    def synthesis_status(self) -> str | None:
        """The loop's design status (data dictionary of gains)."""
        return self.values.get("synthesis_status")

    @property
    def lam(self) -> float:
        """The loop's design's decay rate lambda on its moments (NaN without one)."""
        return _number(self.values.get("lam"))

    @property
    def rate_plant(self) -> float:
        """The exact mean-square rate of the loop's gain on the true plant (NaN without one: a data run)."""
        return _number(self.values.get("rate_plant"))

    @property
    def xi_mean(self) -> tuple[float, ...]:
        """The modeled mean of xi, shape (p,); () without a model."""
        return tuple(_number(v) for v in self.values.get("xi_mean") or ())

    @property
    def xi_std(self) -> tuple[float, ...]:
        """The modeled standard deviation of xi, shape (p,); () without a model."""
        return tuple(_number(v) for v in self.values.get("xi_std") or ())

    @property
    def xi_crps(self) -> float:
        """CRPS of the modeled marginals against the plant's xi (NaN without a plant)."""
        return _number(self.values.get("xi_crps"))

    @property
    def rate_window(self) -> tuple | None:
        """(k_from, k_to) of the closed loop's rate window in steps as the run resolved it, None without one."""
        window = self.values.get("rate_window")
        return tuple(window) if isinstance(window, list) and window else None

    @property
    def identification_feedback(self) -> Mapping:
        """The identification run's loop: mode, the rule that chose it (`used`), F and its exact rates; {} for
        older records."""
        return self.values.get("identification_feedback") or {}

    @property
    def fed_back(self) -> str:
        """The estimate the closed loop feeds back (filtered x_{k|k}, the default, or predicted x_{k|k-1})."""
        return (self.values.get("loop") or {}).get("estimate", "filtered")

    def status(self, loop: str = "closed_loop") -> str | None:
        """ok, partially_failed or failed (every path), None without that loop."""
        return self.values.get(f"{loop}_status")

    def verdict(self, loop: str = "closed_loop") -> str | None:
        """The loop's verdict word (stable, unstable, undetermined, failed), None without that loop."""
        return self.values.get(f"{loop}_verdict")

    def verdict_reason(self, loop: str = "closed_loop") -> str | None:
        """The loop's verdict in words, with its evidence; None without that loop."""
        return self.values.get(f"{loop}_verdict_reason")

    def rate(self, loop: str = "closed_loop") -> tuple[float, float, float]:
        """(rate, low, high) of the loop's plain rate over its window; NaNs without one."""
        value = self.values.get(f"{loop}_rate")
        return tuple(NAN if v is None else float(v) for v in value) if isinstance(value, list) and len(value) == 3 \
            else (NAN, NAN, NAN)

    def failed_fraction(self, loop: str = "closed_loop") -> float:
        """The fraction of the loop's paths that failed (0 when none did)."""
        return float((self.values.get(f"{loop}_failed") or {}).get("fraction", 0.0))


def _number(value) -> float:
    return float("nan") if value is None else float(value)


@dataclass(frozen=True)
class StoredFile:
    """A file of a run as run.json records it: its path relative to the run directory and its content hash."""

    file: str
    sha256: str | None = None


@dataclass(frozen=True)
class Objective:
    """run.json's `objective`: a tuning trial's (role "trial"), one of its other seeds' ("seed": `trial` names
    the trial) or a held-out re-run's ("heldout": `of` names the best trial). A trial and the last held-out
    run carry the metric, penalty, seeds, each seed's value, their mean and standard error, and `exact`:
    the metric's exact counterpart in the same runs ({metric, values, mean}), where it has one."""

    role: str | None
    metric: str | None = None
    penalty: float | None = None
    seeds: tuple[int, ...] = ()
    values: tuple[float, ...] = ()
    mean: float | None = None
    se: float | None = None
    exact: Mapping | None = None
    trial: str | None = None
    of: str | None = None

    @classmethod
    def parse(cls, value: dict) -> Objective:
        return cls(role=value.get("role"), metric=value.get("metric"), penalty=value.get("penalty"),
                   seeds=tuple(value.get("seeds") or ()), values=tuple(value.get("values") or ()),
                   mean=value.get("mean"), se=value.get("se"), exact=value.get("exact"), trial=value.get("trial"),
                   of=value.get("of"))


@dataclass(frozen=True)
class RunRecord:
    """One run.json, typed (`parse`): identity, provenance and outcome; `raw` is the dict as read."""

    id: str
    status: str
    created: str | None
    finished: str | None
    command: str | None
    overrides: tuple[str, ...]
    sweep: SweepRef | None
    config_hash: str | None
    plant_hash: str | None
    data: dict | None                 # a data run's data file: name, sha256, rows, columns (no plant)
    code_version: str | None
    seed: int | None
    reused_from: str | None
    error: str | None
    seconds: float | None
    summary: RunSummary
    raw: dict
    code_commit: str | None = None
    params: dict | None = None        # every resolved scalar of the config (dotted keys); None in older records
    objective: Objective | None = None
    timings: dict = field(default_factory=dict)            # {stage: seconds}
    tables: dict = field(default_factory=dict)             # {table name: StoredFile}
    recording: StoredFile | None = None
    stage_keys: dict = field(default_factory=dict)         # {stage label: its cache key}
    stages_reused: dict = field(default_factory=dict)      # the stages loaded from the stage cache

    @classmethod
    def parse(cls, info: dict) -> RunRecord:
        """From run.json's content (as `read_run` checked it: id and status present, fields of the types
        readers expect), older records made current (module docstring)."""
        seed = info.get("seed")
        sweep = info.get("sweep")
        return cls(
            id=str(info["id"]), status=str(info["status"]), created=info.get("created"),
            finished=info.get("finished"), command=info.get("command"),
            overrides=tuple(str(o) for o in info.get("overrides") or ()),
            sweep=_sweep(sweep) if isinstance(sweep, dict) and sweep.get("dir") else None,
            config_hash=info.get("config_hash"), plant_hash=info.get("plant_hash") or None,
            data=info.get("data") if isinstance(info.get("data"), dict) else None,
            code_version=(info.get("code") or {}).get("version"),
            seed=seed.get("root") if isinstance(seed, dict) else seed,
            reused_from=info.get("reused_from"), error=info.get("error"), seconds=info.get("seconds"),
            summary=RunSummary(dict(info.get("summary") or {})), raw=info,
            code_commit=(info.get("code") or {}).get("commit"),
            params=info.get("params") if isinstance(info.get("params"), dict) else None,
            objective=Objective.parse(info["objective"]) if isinstance(info.get("objective"), dict) else None,
            timings=dict(info.get("timings") or {}),
            tables={name: StoredFile(meta["file"], meta.get("sha256"))
                    for name, meta in (info.get("tables") or {}).items()
                    if isinstance(meta, dict) and isinstance(meta.get("file"), str)},
            recording=StoredFile(info["recording"]["file"], info["recording"].get("sha256"))
            if isinstance(info.get("recording"), dict) and isinstance(info["recording"].get("file"), str) else None,
            stage_keys=dict(info.get("stage_keys") or {}), stages_reused=dict(info.get("stages_reused") or {}))

    @property
    def complete(self) -> bool:
        return self.status == "complete"

    @cached_property
    def metrics(self) -> dict:
        """{"metrics.NAME": value}: the catalog's metrics of this run (`metrics.flatten`, as in the runs table)."""
        return flatten(self.summary, self.raw.get("objective"), self.seconds)

    def metric(self, name: str):
        """The catalog metric `name` of this run (a rate's point estimate; closed_loop_failed_fraction 0 where the
        loop ran and no path failed); NaN where the run has none."""
        return self.metrics.get(f"metrics.{name}", float("nan"))


def _sweep(sweep: dict) -> SweepRef:
    job = sweep.get("job")
    return SweepRef(dir=Path(sweep["dir"]), job=job if isinstance(job, int) else None,
                    name=sweep.get("name") or sweep_name(sweep["dir"]), resumes=sweep.get("resumes"),
                    recorded_name=sweep.get("name"))


def sweep_name(sweep_dir: str | None) -> str | None:
    """The name of a sweep launched without `+sweep=NAME`: the overrides of its command line that sweep
    (`enkf.ensemble_size=50,100 seed=range(3)`; all of them if none does), as Hydra wrote them into
    <sweep>/multirun.yaml; None without that file."""
    if not sweep_dir:
        return None
    try:
        config = yaml.safe_load((Path(sweep_dir) / MULTIRUN).read_text())
        task = [str(o) for o in ((config or {}).get("hydra") or {}).get("overrides", {}).get("task") or []
                if not str(o).startswith("+sweep=")]
    except (OSError, yaml.YAMLError, AttributeError):
        return None
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException
    try:
        swept = [o.input_line for o in OverridesParser.create().parse_overrides(task) if o.is_sweep_override()]
    except HydraException:
        swept = []
    return " ".join(swept or task) or None
