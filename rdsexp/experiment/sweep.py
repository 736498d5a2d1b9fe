"""The sweep callback: every job's config validated before the first runs, a progress bar over the
jobs, and the sweep's summary table written once all have returned."""
from __future__ import annotations

import json
import logging
import os
import sys
import threading
from pathlib import Path

import numpy as np
import pandas as pd
import yaml
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from ..errors import ConfigError, Exit, RunExit, WriteError
from .config import build, check_overrides
from .store import RunStore, layout, status_of, write_sweep_summary
from .store.files import atomic_write_bytes
from .store.layout import HYDRA_CONFIG, MULTIRUN, RESUMES, SUMMARY_CSV
from .store.record import Objective, RunRecord
from .store.table import as_text, sweep_results


class SweepProgress:
    """The sweep's progress bar (jobs done out of total, time left), in the process that launched it.

    A job that runs in this process (the basic launcher) counts when its `on_job_end` callback
    returns; jobs in other processes (joblib workers, Ray, Slurm), whose callbacks this process never
    sees, count when their run.json leaves "incomplete", looked for every `poll` seconds in the sweep
    directory (only the jobs not yet counted are read). A job counts once whichever way it is seen."""

    def __init__(self, total, sweep_dir: Path, poll: float = 1.0, file=None, disable: bool | None = None):
        # disable=None: shown on a terminal only
        self.bar = tqdm(total=total, desc="sweep", unit="job", disable=disable, file=file or sys.stderr)
        self.sweep_dir, self.poll = Path(sweep_dir), poll
        self.done: set[str] = set()
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.thread = None
        if not self.bar.disable:
            self.thread = threading.Thread(target=self._watch, name="rdsexp-sweep-progress", daemon=True)
            self.thread.start()

    def finished(self, job: str) -> None:
        """Count job `job` (its subdirectory's name) as done, once."""
        with self.lock:
            if job not in self.done and not self.stop.is_set():
                self.done.add(job)
                self.bar.update(1)

    def _watch(self) -> None:
        while not self.stop.wait(self.poll):
            self._scan()

    def _scan(self) -> None:
        try:
            jobs = [d for d in self.sweep_dir.iterdir() if d.name not in self.done and d.is_dir()]
        except OSError:                   # the sweep directory is not made yet
            return
        for job in jobs:
            if not layout.is_job(job):               # a trial's other seed, a held-out run
                continue
            status = status_of(job)                  # None: not started, or being written
            if status not in (None, "incomplete"):
                self.finished(job.name)

    def close(self) -> None:
        """Count the jobs that ended since the last look, stop looking, end the bar's line."""
        if self.thread is not None:
            self.stop.set()
            self.thread.join()
            self.stop.clear()
            self._scan()
        with self.lock:
            self.stop.set()
        self.bar.close()


_SWEEP_BARS: dict[int, SweepProgress] = {}      # the sweep's progress bar, in the process that launched it


def sweep_points(config: DictConfig) -> list[list[str]]:
    """The overrides of every job of a multirun: the sweeper's params, overridden key by key on the
    command line (as Hydra's basic sweeper combines them)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser
    params = {k: f"{k}={v}" for k, v in (OmegaConf.select(config, "hydra.sweeper.params") or {}).items()}
    parser = OverridesParser.create()
    for override in parser.parse_overrides(list(config.hydra.overrides.task)):
        params[override.get_key_element()] = override.input_line
    return BasicSweeper.split_arguments(parser.parse_overrides(list(params.values())), max_batch_size=None)[0]


def enumerable(config: DictConfig) -> bool:
    """Whether the sweep's jobs are known before it starts (Hydra's basic sweeper), not proposed trial by
    trial (an optimizing sweeper such as Optuna's)."""
    target = str(OmegaConf.select(config, "hydra.sweeper._target_") or "")
    return target.endswith("BasicSweeper")


def compose_points(points: list[list[str]], reuse: bool = False):
    """Yield (overrides, composed config) for every job, composing once per choice of config groups.

    Hydra composes the defaults (the group choices) first and applies the value overrides last, so
    a composition of the group choices alone with each job's value overrides applied on top is the
    job's config (tests/experiment/test_cli.py checks it against a full compose); a sweep of 200
    points over `enkf.*` values then composes once instead of 200 times.

    reuse: points that set the same keys (plain key=value) share one working copy, each point's
    values overwriting the previous point's, instead of a copy per point (the copy of a config with
    matrices is most of the time); a yielded config is then valid only until the next one."""
    from hydra import compose
    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import OverrideType
    loader, parser = GlobalHydra.instance().config_loader(), OverridesParser.create()
    is_group: dict[str, bool] = {}
    composed: dict[tuple, DictConfig] = {}
    working: dict[tuple, DictConfig] = {}
    for overrides in points:
        parsed = parser.parse_overrides(list(overrides))
        for o in parsed:
            if o.key_or_group not in is_group:
                is_group[o.key_or_group] = bool(loader.get_group_options(o.key_or_group))
        groups = tuple(o.input_line for o in parsed if is_group[o.key_or_group])
        values = [o for o in parsed if not (is_group[o.key_or_group] or o.key_or_group.startswith("hydra."))]
        if groups not in composed:
            composed[groups] = compose(config_name="config", overrides=list(groups))
        keys = (groups, tuple(sorted(o.key_or_group for o in values)))
        if reuse and all(o.type == OverrideType.CHANGE for o in values):
            if keys not in working:
                working[keys] = composed[groups].copy()
            cfg = working[keys]
        else:
            cfg = composed[groups].copy()
        ConfigLoaderImpl._apply_overrides_to_config(values, cfg)
        yield overrides, cfg


def validate_sweep(points: list[list[str]]) -> None:
    """Compose and validate every job's config before the first job runs; exit 2 on the first bad one."""
    try:
        for overrides, cfg in compose_points(points, reuse=True):
            check_overrides(cfg, overrides)
            build(cfg)
    except ConfigError as err:
        print(f"rdsexp: config error in sweep job {' '.join(overrides)}: {err}", file=sys.stderr)
        raise RunExit(Exit.CONFIG) from None


_VALIDATED: set[int] = set()      # processes whose running sweep's jobs validate_sweep composed and checked


def skip_hydra_validation() -> None:
    """Let Hydra's basic sweeper skip its own check that every job composes (`validate_batch_is_legal`,
    a full composition per job, ~0.6 s each, in the launching process before any job starts: 2.5
    minutes of the report's 234 jobs with every worker idle) for the sweep this process runs:
    `validate_sweep` has composed and validated each job already (once per choice of config groups)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    _VALIDATED.add(os.getpid())
    if getattr(BasicSweeper.validate_batch_is_legal, "rdsexp", False):
        return
    original = BasicSweeper.validate_batch_is_legal

    def validate_batch_is_legal(self, batch) -> None:
        if os.getpid() not in _VALIDATED:
            original(self, batch)
    validate_batch_is_legal.rdsexp = True
    BasicSweeper.validate_batch_is_legal = validate_batch_is_legal


RESULT_ROWS = 40          # rows of the results table a sweep prints at its end (all are in summary.csv)


class SweepSummary(Callback):
    """Hydra callback: validates every job's config before the first runs, shows a progress bar over
    the jobs and writes the summary table once all have returned.

    Each job also rebuilds the summary when it ends, so a sweep that is killed still has one.
    A run or sweep whose directory cannot be written stops before any work with one line (exit 1);
    a sweep in which a job did not complete exits 1 after its summary, with one line."""

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        writable_or_exit(Path(config.hydra.run.dir))

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        if enumerable(config):
            points = sweep_points(config)
        else:                             # an optimizing sweeper proposes its points as it goes: the
            points = [list(config.hydra.overrides.task)]     # command line is checked, each trial by its job
        validate_sweep(points)            # a config error leaves nothing behind, not even the sweep dir
        if enumerable(config):            # every job composed and validated: the basic sweeper need not again
            skip_hydra_validation()
        writable_or_exit(Path(config.hydra.sweep.dir))
        resumes = resumed_sweep(config)
        if resumes is not None:           # read by every job's run.json (`runner.run_info`): the link
            atomic_write_bytes(Path(config.hydra.sweep.dir) / RESUMES, json.dumps({"resumes": resumes}).encode())
            print(f"resuming sweep {resumes} (interrupted): its completed jobs are reused")
        total = len(points) if enumerable(config) else OmegaConf.select(config, "hydra.sweeper.n_trials")
        _SWEEP_BARS[os.getpid()] = SweepProgress(total, Path(config.hydra.sweep.dir))

    def on_job_end(self, config: DictConfig, job_return, **kwargs) -> None:
        bar = _SWEEP_BARS.get(os.getpid())      # None in launcher worker processes
        if bar is not None:
            bar.finished(str(config.hydra.sweep.subdir))

    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        _VALIDATED.discard(os.getpid())
        bar = _SWEEP_BARS.pop(os.getpid(), None)
        if bar is not None:
            bar.close()
        try:
            path = write_sweep_summary(Path(config.hydra.sweep.dir))
        except WriteError as err:
            print(f"rdsexp: {err}", file=sys.stderr)
            raise RunExit(Exit.FAILED) from None
        if not enumerable(config) and config.get("objective"):
            for line in held_out(config, path.parent):     # the best trial again, on fresh seeds
                print(line)
            path = write_sweep_summary(path.parent)
        print(f"sweep summary: {path}")
        jobs = RunStore(path.parent).runs()
        if not jobs:                       # tracking=off: the jobs recorded nothing to draw
            print("sweep recording: none (no job recorded a run: tracking.level=off)")
        else:                              # the sweep's own recording: metrics against the swept params
            try:
                from .recording import write_sweep_recording
                print(f"sweep recording: {write_sweep_recording(path.parent) or 'none (Rerun disabled: RERUN=off)'}")
            except Exception as err:      # noqa: BLE001 -- a view, never the end of a sweep
                print(f"rdsexp: no sweep recording ({type(err).__name__}: {err})", file=sys.stderr)
        table = RunStore(path.parent).table(params=True)
        if len(table):                    # what was swept against what came out, as `rdsexp-runs show SWEEP`
            print(as_text(sweep_results(table), max_rows=RESULT_ROWS))
            print(f"reused {int(table['reused_from'].notna().sum())} of {len(table)} jobs (same config hash and "
                  f"code version as a stored run)")
            note = stage_cache_note([job.record for job in jobs])
            if note:
                print(note)
        status = table["status"] if "status" in table else pd.Series([], dtype=object)
        failed = status[status != "complete"].value_counts()
        if len(failed):
            counts = ", ".join(f"{n} {s}" for s, n in failed.items())
            print(f"rdsexp: sweep {path.parent}: {failed.sum()} of {len(status)} jobs did not complete ({counts}); "
                  f"see {path.with_name(SUMMARY_CSV)}", file=sys.stderr)
            raise RunExit(Exit.FAILED)


HELD_OUT = "heldout.json"


def held_out(config: DictConfig, sweep_dir: Path) -> list[str]:
    """At the end of a tuning study (an optimizing sweep with `objective`): its best trial (least mean
    objective) re-run on as many fresh seeds as a trial averages (after every seed the study used), each a
    run in the sweep directory (heldout.seed<s>, run.json `objective.role` heldout, the last one with their
    mean and standard error), the result in <sweep>/heldout.json; the lines that say it, which trials are
    within each other's standard error of the best, and the objective's exact counterpart."""
    from .runner import at_seed, command_with, execute, objective_over
    trials = [run for run in RunStore(sweep_dir).runs(warn=False)
              if run.record.objective is not None and run.record.objective.role == "trial"]
    if not trials:
        return []
    of = lambda run: run.record.objective                          # noqa: E731
    best = min(trials, key=lambda run: of(run).mean)
    name, penalty, n = of(best).metric, of(best).penalty, len(of(best).seeds)
    used = [seed for run in trials for seed in of(run).seeds]
    seeds = list(range(max(used) + 1, max(used) + 1 + n))
    cfg = OmegaConf.load(best.dir / HYDRA_CONFIG)
    runs = []
    for i, seed in enumerate(seeds):
        other = at_seed(cfg, seed)
        run_dir = sweep_dir / f"heldout.seed{seed}"
        overrides = [o for o in best.record.overrides if not o.startswith("seed=")] + [f"seed={seed}"]
        sweep = best.record.sweep
        context = {"id": f"{sweep_dir.name}/{run_dir.name}", "command": command_with(best.record.command, overrides),
                   "overrides": overrides, "sweep": sweep.as_recorded(job=None) if sweep is not None else {"job": None},
                   "objective": {"role": "heldout", "of": best.id}}
        last = i == len(seeds) - 1
        amend = (lambda info: info.update(objective=objective_over(
            name, penalty, [*runs, info], seeds, "heldout", of=best.id))) if last else None
        logging.disable(logging.INFO)        # the stages' progress lines: the jobs' go to their logs, not here
        try:
            runs.append(execute(other, run_dir, context, amend))
        finally:
            logging.disable(logging.NOTSET)
    result = runs[-1].get("objective") or objective_over(name, penalty, runs, seeds, "heldout", of=best.id)
    atomic_write_bytes(sweep_dir / HELD_OUT, json.dumps(result, indent=1).encode())
    best_, held = of(best), Objective.parse(result)
    lines = [f"tuning: best trial {best.id}: {name} {best_.mean:.4f} +- {best_.se:.4f} (standard error over "
             f"seeds {list(best_.seeds)}); held out on fresh seeds {seeds}: {held.mean:.4f} +- {held.se:.4f}"]
    close = [run.id for run in trials if run is not best
             and abs(of(run).mean - best_.mean) <= np.nan_to_num(of(run).se) + np.nan_to_num(best_.se)]
    lines.append(f"tuning: {len(close)} other trial(s) within one standard error of the best ({', '.join(close)}): the "
                 f"study cannot tell them apart" if close else "tuning: no other trial is within one standard "
                 "error of the best")
    exact = best_.exact
    if exact:
        spread = [of(run).exact["mean"] for run in trials]
        lines.append(f"tuning: {name} is a Monte Carlo estimate of a rate; its exact counterpart {exact['metric']} "
                     f"(the gain's exact rate on the true plant): best trial {exact['mean']:.4f}, held out "
                     f"{held.exact['mean']:.4f}, over the trials {min(spread):.4f} to {max(spread):.4f}")
    return lines


def stage_cache_note(records: list[RunRecord]) -> str:
    """How many of the jobs that computed loaded each stage from the stage cache (run.json
    `stages_reused`), e.g. "stage cache: identification reused in 60 of 70 jobs, designs 400 of 420,
    open loop 60 of 70"; "" when no job looked a stage up."""
    computed = [record for record in records if not record.reused_from and record.stage_keys]
    if not computed:
        return ""
    counts: dict[str, list[int]] = {}
    for record in computed:
        reused = record.stages_reused
        for label in record.stage_keys:
            stage = "designs" if label.startswith("synthesis") else label.replace("_", " ")
            hits = counts.setdefault(stage, [0, 0])
            hits[0] += label in reused
            hits[1] += 1
    words = [f"{stage} {hit} of {total}" for stage, (hit, total) in counts.items()]
    return f"stage cache (jobs that computed: {len(computed)}): reused " + ", ".join(words)


def resumed_sweep(config: DictConfig) -> str | None:
    """The id of the sweep this one resumes: the latest earlier sweep of the same store launched with the
    same command line (multirun.yaml's hydra.overrides.task), if it did not complete (a job not
    "complete", or fewer jobs than its points); None otherwise (a first launch, or a rerun of a complete
    sweep)."""
    sweep_dir = Path(config.hydra.sweep.dir)
    task = [str(o) for o in config.hydra.overrides.task]
    for other in sorted((d for d in sweep_dir.parent.iterdir() if d.is_dir() and d != sweep_dir), reverse=True):
        try:
            old = OmegaConf.load(other / MULTIRUN)
        except (OSError, ValueError, yaml.YAMLError):
            continue
        if [str(o) for o in (OmegaConf.select(old, "hydra.overrides.task") or [])] != task:
            continue
        statuses = [job.record.status for job in RunStore(other).runs(warn=False)]
        total = len(sweep_points(old)) if enumerable(old) else len(statuses)
        return other.name if len(statuses) < total or any(st != "complete" for st in statuses) else None
    return None


def writable_or_exit(directory: Path) -> None:
    """Create `directory` and write a file into it, or exit 1 with one line (a read-only or full
    file system, no permission) before Hydra or any job starts writing."""
    try:
        directory.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(directory / ".write_test", b"")
        (directory / ".write_test").unlink()
    except (OSError, WriteError) as err:
        reason = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
        print(f"rdsexp: cannot write {directory}: {reason}" if isinstance(err, OSError) else f"rdsexp: {err}",
              file=sys.stderr)
        raise RunExit(Exit.FAILED) from None
