"""One run: a composed config validated, computed through the stage pipeline and recorded in its
run directory (run.json "incomplete" first, then the tables, the recording and the final run.json).

A library function: it returns run.json's content or raises (see `failures`); the command line
(`cli`) prints and chooses the exit code.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import shlex
from pathlib import Path

import numpy as np
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from ..errors import WriteError, one_line
from .config import Experiment, build, check_overrides
from .metrics import MAXIMIZE, REGISTRY, exact_counterpart
from .pipeline import SPAWN_KEYS, TABLES, Outcome, run_experiment, timed
from .schema import attach
from .store import RunRecord, RunStore, RunWriter, StageCache, layout, provenance
from .store.table import flat_params

log = logging.getLogger("rdsexp")


def record(writer: RunWriter, outcome: Outcome, exp: Experiment, info: dict, streamed: dict,
           index=None, amend=None) -> dict:
    """Write the remaining tables, the recording and the final run.json of the run; `streamed`:
    the tables the pipeline already wrote through a ParquetSink; `index(info)` is called with the
    complete content just before run.json says so, so that a process killed in between leaves no
    complete run that the reuse index does not know (an entry naming a run not yet complete is
    never reused). Returns the run.json content."""
    timings = dict(outcome.timings)
    with timed(timings, "tables"):
        hashes = writer.store_tables({name: attach(name, table, info["id"])       # attach: schema metadata
                                      for name, table in outcome.tables.items()})
        hashes = dict(sorted((hashes | streamed).items(), key=lambda item: _table_order(item[0])))
    with timed(timings, "recording"):
        if exp.tracking.recording:
            from .recording import write_recording  # rerun is imported only when recording
            entry = writer.store_recording(lambda tmp: write_recording(
                tmp, outcome.recorded, recording_id=info["id"], members=outcome.recorded_members,
                tables=outcome.tables, summary=outcome.summary, squares=outcome.squares,
                window=(exp.identification.K0, exp.identification.K0 + exp.identification.K1), **true_xi(exp)))
            if entry is not None:
                info["recording"] = entry
            else:                                   # RERUN=off in the environment: rerun wrote nothing
                log.info("no recording: Rerun is disabled (RERUN=off)")
    if exp.tracking.figure:
        with timed(timings, "figure"):
            from .figure import draw  # matplotlib is imported only when drawing
            try:
                info["figure"] = writer.store_recording(lambda tmp: bool(draw(
                    tmp, outcome.squares, outcome.tables["metrics"], outcome.tables["exact"], outcome.summary)),
                    name=layout.FIGURE)
            except WriteError:
                raise
            except Exception as err:    # a view of the results, not a result: the run stays complete without it
                log.warning("figure not drawn: %s", one_line(err))
    info.update(status="complete", finished=provenance.now(), summary=outcome.summary, tables=hashes,
                timings=timings, seconds=round(sum(v for v in timings.values() if isinstance(v, float)), 3))
    if amend is not None:
        amend(info)
    if index is not None:
        index(info)
    return writer.finish(info)


class _Described:
    """The pipeline's sink for the streamed tables, each chunk with the table's schema metadata."""

    def __init__(self, sink, run: str):
        self.sink, self.run = sink, run

    def append(self, name: str, rows) -> None:
        self.sink.append(name, attach(name, rows, self.run))


def true_xi(exp: Experiment) -> dict:
    """The plant's xi in the model's terms, T s + t (`truth_map`): {"xi_true": mean (p,), "xi_true_std":
    standard deviations (p,)}, empty if there is no such map."""
    from ..numerics.enkf import truth_map
    if exp.plant is None:                   # a data run: no true xi
        return {}
    truth = truth_map(exp.model, exp.plant)
    if truth is None:
        return {}
    T, t = truth
    dist = exp.plant.check_distribution(None)
    return {"xi_true": T @ dist.mean + t, "xi_true_std": np.sqrt(np.maximum(np.diag(T @ dist.cov @ T.T), 0.0))}


def _table_order(name: str) -> int:
    return TABLES.index(name) if name in TABLES else len(TABLES)


def hydra_context(run_dir: Path) -> dict:
    """What run.json records of the command that started a run: id, command, overrides and sweep, from
    Hydra's job (a single run when Hydra is not running one)."""
    hc = HydraConfig.get() if HydraConfig.initialized() else None
    multirun = hc is not None and hc.mode == RunMode.MULTIRUN
    return {
        "id": run_dir.name if not multirun else f"{Path(hc.sweep.dir).name}/{run_dir.name}",
        "command": " ".join(["python -m rdsexp", *config_dirs(hc), *(hc.overrides.task if hc else [])]),
        "overrides": list(hc.overrides.task) if hc else [],
        "sweep": {"dir": str(Path(hc.sweep.dir).resolve()), "job": int(hc.job.num),
                  "name": hc.runtime.choices.get("sweep"), "resumes": resumes(Path(hc.sweep.dir))}
        if multirun else None,
    }


def run_info(run_dir: Path, job_config: dict, seed: int, context: dict | None = None) -> tuple[dict, str]:
    """The provenance part of run.json, known before any compute, and the uncommitted diff. context: id,
    command, overrides, sweep (and any other entry, e.g. `objective`) of a run that Hydra's job did not
    start itself (a tuning trial's other seeds, a study's held-out re-run); default `hydra_context`."""
    code = provenance.code_version()
    context = hydra_context(run_dir) if context is None else context
    return {
        "id": context["id"], "status": "incomplete", "created": provenance.now(),
        **{k: v for k, v in context.items() if k != "id"},
        "config_hash": provenance.config_hash(job_config),
        "code": {k: v for k, v in code.items() if k != "diff"}
        | {"diff_file": layout.DIFF if code["dirty"] else None},
        "seed": {"root": seed, "spawn_keys": {k: list(v) for k, v in SPAWN_KEYS.items()},
                 "per_path": "SeedSequence(seed, spawn_key=(*spawn_key, purpose, path)), purpose 0 plant, 1 EnKF"},
        "environment": provenance.environment(),
        "process": provenance.process_info(),     # tells a run whose process died from a running one
    }, code["diff"]


def resumes(sweep_dir: Path) -> str | None:
    """The id of the interrupted sweep that the sweep in sweep_dir resumes (`sweep.resumed_sweep`), or None."""
    try:
        return json.loads((sweep_dir / layout.RESUMES).read_text())["resumes"]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def config_dirs(hc) -> list[str]:
    """`--config-dir DIR` of the command line (Hydra's command-line config source), as absolute paths, so that
    run.json's command can be pasted back from anywhere."""
    if hc is None:
        return []
    return [f"--config-dir {shlex.quote(str(Path(source.path).resolve()))}" for source in hc.runtime.config_sources
            if source.provider == "command-line" and source.schema == "file"]


# config keys that do not change what a run computes
NOT_COMPUTED = ("store", "objective", "objective_penalty", "objective_seeds", "cache")


def job_config(cfg: DictConfig, exp: Experiment | None = None) -> dict:
    """The resolved job config without the hydra node (what the run computes from; `store`, where
    it is recorded, and what the job returns to a sweeper are not part of it). A data run's data file
    enters by its content: data.sha256 (a changed file has another config hash, never reused)."""
    config = {k: v for k, v in OmegaConf.to_container(cfg, resolve=True).items() if k not in NOT_COMPUTED}
    if exp is not None and exp.data is not None:
        config["data"] = dict(config.get("data") or {}, sha256=exp.data.data.sha256)
    return config


def write_config(run_dir: Path, cfg: DictConfig) -> None:
    """The composed config of a run that Hydra did not start as a job (run_dir/.hydra/config.yaml, as Hydra
    writes it for its jobs: what `verify` re-runs)."""
    path = Path(run_dir) / layout.HYDRA_CONFIG
    path.parent.mkdir(parents=True, exist_ok=True)
    OmegaConf.save({k: v for k, v in OmegaConf.to_container(cfg, resolve=False).items() if k != "hydra"}, path)


def command_with(command: str, overrides: list[str]) -> str:
    """A run's command line (`python -m rdsexp [--config-dir DIR ...] OVERRIDES`) with other overrides: the
    command that repeats a tuning trial's other seed or a held-out re-run by itself: a single run, without
    `+sweep=NAME`, which would start the study again. It is exact where the sweep config sets only the study
    (objective, sweeper), as tune_enkf does; the run's .hydra/config.yaml, which `verify` re-runs, always is."""
    words, kept = shlex.split(command or "python -m rdsexp"), []
    for i, word in enumerate(words[3:], start=3):
        if word in ("--config-dir", "-cd") or (i > 3 and words[i - 1] in ("--config-dir", "-cd")):
            kept.append(shlex.quote(word))
    return " ".join(["python -m rdsexp", *kept, *(o for o in overrides if not o.startswith("+sweep="))])


def at_seed(cfg: DictConfig, seed: int) -> DictConfig:
    """A copy of a job's config with another root seed."""
    other = cfg.copy()
    other.seed = seed
    return other


def objective_seeds(cfg: DictConfig) -> list[int]:
    """The seeds a tuning trial averages its objective over: the job's seed and the objective_seeds - 1
    after it."""
    return [int(cfg.seed) + i for i in range(max(1, int(cfg.get("objective_seeds") or 1)))]


def objective_over(name: str, penalty: float, runs: list[dict], seeds: list[int], role: str, **more) -> dict:
    """run.json's `objective` of a trial (role "trial") or a held-out re-run ("heldout"): the metric of each
    run (`objective_value`), their mean and its standard error (std / sqrt(n); NaN for one seed, and for
    a run that did not give a finite value, whose value is inf), and the metric's exact counterpart
    (`metrics.exact_counterpart`) in the same runs. runs: their run.json contents."""
    records = [RunRecord.parse(info) for info in runs]
    values = [objective_value(record, name, penalty) for record in records]
    finite = np.all(np.isfinite(values))
    mean = float(np.mean(values)) if finite else float("inf")
    se = float(np.std(values, ddof=1) / np.sqrt(len(values))) if finite and len(values) > 1 else float("nan")
    out = {"role": role, "metric": name, "penalty": penalty, "seeds": list(seeds), "values": values, "mean": mean,
           "se": se, **more}
    exact = exact_counterpart(name)
    if exact is not None:
        numbers = [float(record.metric(exact)) for record in records]
        out["exact"] = {"metric": exact, "values": numbers, "mean": float(np.mean(numbers))}
    return out


def trial_seeds(cfg: DictConfig, run_dir: Path, failed) -> list[dict]:
    """A tuning trial's runs at its other seeds (`objective_seeds` after the first), each recorded beside
    the job's run (<job>.seed<s>, a run like any other, its command the single run that repeats it);
    their run.json contents. failed(err, seed_dir): the run.json content of a seed whose run raised."""
    context, runs = hydra_context(run_dir), []
    for seed in objective_seeds(cfg)[1:]:
        other = at_seed(cfg, seed)
        seed_dir = run_dir.with_name(f"{run_dir.name}.seed{seed}")
        overrides = [o for o in context["overrides"] if not o.startswith("seed=")] + [f"seed={seed}"]
        try:
            runs.append(execute(other, seed_dir, context | {
                "id": f"{Path(context['id']).parent}/{seed_dir.name}" if context["sweep"] else seed_dir.name,
                "overrides": overrides, "command": command_with(context["command"], overrides),
                "objective": {"role": "seed", "trial": context["id"]}}))
        except Exception as err:          # noqa: BLE001 -- a status in its run.json; the trial's mean is inf
            runs.append(failed(err, seed_dir))
    return runs


def objective_value(record: RunRecord | dict, name: str, penalty: float = 1.0) -> float:
    """The job's objective (config `objective`, minimized): the catalog metric `name` of the run
    (`RunRecord.metric`: a rate's point estimate; negated for a metric the registry maximizes), plus
    penalty x the closed loop's failed fraction of paths (not added to that fraction itself); inf when
    the run did not complete or the metric is not finite (e.g. a rate that no path window could measure).
    record: the run's typed record, or its run.json content."""
    record = record if isinstance(record, RunRecord) else RunRecord.parse(record)
    if not record.complete:
        return float("inf")
    value = record.metric(name)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        return float("inf")
    value = -float(value) if REGISTRY[name].objective == MAXIMIZE else float(value)
    if name == "closed_loop_failed_fraction":
        return value
    return value + penalty * record.summary.failed_fraction()


def store_of(cfg: DictConfig) -> RunStore:
    """The run store (config key `store`, relative to the directory rdsexp was started in)."""
    from hydra.utils import to_absolute_path
    return RunStore(to_absolute_path(str(cfg.get("store") or layout.DEFAULT_ROOT)))


def execute(cfg: DictConfig, run_dir: Path, context: dict | None = None, amend=None) -> dict:
    """Validate, compute and record one run into run_dir; returns run.json's content.

    Raises ConfigError before any compute, WriteError when the store cannot be written, StageError
    when a stage fails unexpectedly (`failures` turns each into a status). With tracking level "off"
    nothing is written (Hydra's .hydra/ aside) and the same content is only returned. context: see
    `run_info` (its run directory gets the composed config, as Hydra's jobs do); amend(info): adds to the
    complete run.json before it is written (a tuning trial's objective over its seeds)."""
    if context is not None:
        write_config(run_dir, cfg)
    elif HydraConfig.initialized():
        check_overrides(cfg, HydraConfig.get().overrides.task)   # `+enkf.ensemble_sze=50`: a typo, not a key
    exp = build(cfg)                                    # ConfigError before any compute
    if exp.data is None and OmegaConf.select(cfg, "plant.name") is None and HydraConfig.initialized():
        # a plant file without `name:` is named by its file (plant=NAME)
        exp = dataclasses.replace(exp, plant_name=HydraConfig.get().runtime.choices.get("plant") or "plant")
    if exp.tracking.level == "off":
        outcome = run_experiment(exp, cache=StageCache.in_process())
        info = {"id": run_dir.name, "status": "complete", "summary": outcome.summary, "timings": outcome.timings}
        if amend is not None:
            amend(info)
        return info
    timings, writer, store = {}, RunWriter(run_dir), store_of(cfg)
    with timed(timings, "provenance"):
        info, diff = run_info(run_dir, job_config(cfg, exp), exp.seed, context)
        if exp.data is not None:        # a data run: the data file is the identity, there is no plant
            info["data"] = exp.data.data.info
            info["plant_hash"] = None
        else:
            info["plant_hash"] = provenance.plant_hash({name: getattr(exp.plant, name) for name in "ABCD"},
                                                       OmegaConf.to_container(cfg.plant.xi, resolve=True))
        info["params"] = flat_params(OmegaConf.to_container(cfg, resolve=True))   # what `rdsexp-runs list` shows
        previous = reusable_run(cfg, store, info)
        if previous is not None:
            return writer.reuse(previous, info, amend)
        writer.start(info, diff)                        # run.json "incomplete" until the end
    sink, cache = writer.sink(), stage_cache(cfg, store, info)
    try:
        outcome = run_experiment(exp, _Described(sink, info["id"]), cache=cache)
    except BaseException:                   # no partial table left behind (run.json says what happened)
        sink.abort()
        raise
    outcome.timings |= timings
    if cache.dir is not None:           # where each reused stage came from; every stage's key
        info.update(stages_reused=cache.reused, stage_keys=cache.keys)
    with timed(outcome.timings, "streamed_tables"):
        streamed = sink.close()
    def index(complete: dict) -> None:
        try:                                # the index is derived data: a run is complete without it
            store.index(run_dir, complete)
        except WriteError as err:
            log.warning("run %s not indexed for reuse: %s", complete["id"], err)
    return record(writer, outcome, exp, info, streamed, index, amend)


def stage_cache(cfg: DictConfig, store: RunStore, info: dict) -> StageCache:
    """The stage cache this run uses: the run store's (config key `cache`, default true), else this
    process's memory only."""
    if not cfg.get("cache", False):
        return StageCache.in_process()
    return StageCache(store.root, info["code"]["version"], info["id"])


def reusable_run(cfg: DictConfig, store: RunStore, info: dict) -> Path | None:
    """With `reuse: true`, an intact complete run of the same config hash and code version in the run
    store (config key `store`, found through its index; never anything outside it): a relaunched sweep
    skips the jobs a killed one completed, and the same command run twice records a copy of the first."""
    if not cfg.get("reuse"):
        return None
    return store.find_reusable(info["config_hash"], info["code"]["version"])
