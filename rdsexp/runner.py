"""`python -m rdsexp`: the paper's experiment from a Hydra config, recorded in a run directory.

Stages (DESIGN.md): identification -> modeling -> synthesis -> closed loop (and open loop) ->
metrics; `run_experiment` computes them into tables without touching the file system, `record`
writes the run directory. Seeds: the identification run uses SeedSequence(seed, spawn_key=(0,)),
the closed and open loops SeedSequence(seed, spawn_key=(1,)) (the same plant samples, as in the
paper's Figs. decay_proposed and decay_open); inside each, path j has its own plant and EnKF streams.
"""
from __future__ import annotations

import datetime as dt
import logging
import os
import shutil
import sys
import time
import traceback
import uuid
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import hydra
import numpy as np
import pandas as pd
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from . import paper, tracking
from .analysis import empirical_rate, ms_rate, second_moments
from .config import ConfigError, Experiment, build
from .modeling import model_distribution
from .simulation import Trajectories, simulate
from .synthesis import METHODS, SynthesisResult, synthesize

log = logging.getLogger("rdsexp")
CONF_DIR = str(tracking.REPO / "conf")
SPAWN_KEYS = {"identification": (0,), "closed_loop": (1,), "open_loop": (1,)}
TABLES = ("trajectories", "identification", "paths", "model", "gains", "metrics", "exact")

if not OmegaConf.has_resolver("uid"):
    # unique run directories even for runs started in the same microsecond; cached so that every
    # job of one sweep resolves the same sweep directory
    OmegaConf.register_new_resolver("uid", lambda: uuid.uuid4().hex[:8], use_cache=True)


@dataclass
class Outcome:
    """What a run computed: tables by name, a flat summary of key numbers, seconds per stage."""

    tables: dict[str, pd.DataFrame]
    summary: dict
    timings: dict = field(default_factory=dict)
    members: pd.DataFrame | None = None


@contextmanager
def _timed(timings: dict, stage: str):
    start = time.perf_counter()
    yield
    timings[stage] = round(time.perf_counter() - start, 4)


def _progress(desc: str, total: int):
    """A tqdm bar (silent when not on a terminal) and its per-step callback."""
    bar = tqdm(total=total, desc=desc, disable=None, leave=False, file=sys.stderr)
    return bar, lambda k: bar.update(1)


def run_experiment(exp: Experiment) -> Outcome:
    """Compute every stage of the experiment; numerical failures become statuses in the tables."""
    timings, summary = {}, {}
    root = lambda stage: np.random.SeedSequence(exp.seed, spawn_key=SPAWN_KEYS[stage])
    sim = dict(q0=exp.q0, psi0=exp.psi0, P0=exp.P0, ensemble_size=exp.ensemble_size)
    keep = exp.tracking == "full"

    with _timed(timings, "identification"):
        ident = simulate(exp.plant, exp.enkf, d=exp.identification_input, paths=1, seed=root("identification"),
                         filter_sees_d=True, keep_members=keep, **sim)
    with _timed(timings, "modeling"):
        xi = ident.xi(ident.psi_filt_mean)[:, 0]
        if ident.status != "ok" or not np.all(np.isfinite(xi[exp.K0:exp.K0 + exp.K1 + 1])):
            dist = None
            summary["modeling_status"] = f"identification {ident.failure[0]} at k = {ident.failed_at[0]}"
        else:
            dist = model_distribution(xi, exp.K0, exp.K1)
            summary["modeling_status"] = "ok"
    with _timed(timings, "synthesis"):
        # every method on the identified moments (the selected one with its configured options) and,
        # when the config gives them, on the moments a paper reports
        designs = {}
        for source, moments in (("identified", dist), ("reported", exp.reported)):
            for method in METHODS if moments is not None else ():
                options = exp.gain_options if method == exp.gain_method else {}
                designs[source, method] = (moments, synthesize(exp.model, moments, method, **options))
        chosen = designs.get(("identified", exp.gain_method), (None, None))[1]

    loops = {}
    if chosen is not None and chosen.F is not None:
        settings = dict(d=exp.disturbance, paths=exp.paths, filter_sees_d=exp.filter_sees_disturbance,
                        keep_members=keep, **sim)
        runs = [("closed_loop", chosen.F)] + ([("open_loop", None)] if exp.open_loop else [])
        for name, F in runs:
            with _timed(timings, name):
                bar, step = _progress(name.replace("_", " "), exp.disturbance.shape[0])
                with bar, logging_redirect_tqdm():
                    loops[name] = simulate(exp.plant, exp.enkf, F=F, seed=root(name), progress=step, **settings)

    with _timed(timings, "metrics"):
        tables = {
            "trajectories": pd.concat([trajectory_table(name, tr) for name, tr in loops.items()],
                                      ignore_index=True) if loops else trajectory_table("closed_loop", None, exp),
            "identification": trajectory_table("identification", ident),
            "paths": path_table({"identification": ident, **loops}),
            "model": model_table(exp, dist),
            "gains": gains_table(exp, designs),
            "metrics": metrics_table(exp, loops),
            "exact": exact_table(exp, chosen),
        }
    summary.update(_summary(exp, dist, chosen, tables["metrics"]))
    timings["synthesis_by_method"] = {f"{source}/{method}": round(res.seconds, 4)
                                      for (source, method), (_, res) in designs.items()}
    members = None
    if keep:
        members = pd.concat([members_table(name, tr, exp) for name, tr in {"identification": ident, **loops}.items()],
                            ignore_index=True)
    return Outcome(tables=tables, summary=summary, timings=timings, members=members)


# ------------------------------------------------------------------------------------ tables
def _columns(name: str, values: np.ndarray) -> dict:
    """{"name[i]": values[..., i].ravel()} for the last axis of values."""
    return {f"{name}[{i}]": values[..., i].ravel() for i in range(values.shape[-1])}


def trajectory_table(experiment: str, tr: Trajectories | None, exp: Experiment | None = None) -> pd.DataFrame:
    """One row per (k, path): plant q, y, u and EnKF mean/spread of x and xi before/after filtering."""
    if tr is None:                       # no gain to simulate: an empty table with the usual columns
        n, p, ny, m = exp.model.n, exp.model.p, exp.model.ny, exp.model.m
        shape = lambda d: np.zeros((0, 0, d))
        tr = Trajectories(q=shape(n), y=shape(ny), u=shape(m), psi_pred_mean=shape(n + p),
                          psi_pred_std=shape(n + p), psi_filt_mean=shape(n + p), psi_filt_std=shape(n + p),
                          failed_at=np.zeros(0, int), failure=np.zeros(0, object), n=n)
    steps, P = tr.q.shape[:2]
    cols = {"experiment": np.full(steps * P, experiment), "k": np.repeat(np.arange(steps), P),
            "path": np.tile(np.arange(P), steps)}
    cols.update(_columns("q", tr.q) | _columns("y", tr.y) | _columns("u", tr.u))
    for stage in ("pred", "filt"):
        for stat in ("mean", "std"):
            psi = getattr(tr, f"psi_{stage}_{stat}")
            cols.update(_columns(f"x_{stage}_{stat}", tr.x(psi)) | _columns(f"xi_{stage}_{stat}", tr.xi(psi)))
    return pd.DataFrame(cols)


def members_table(experiment: str, tr: Trajectories, exp: Experiment) -> pd.DataFrame:
    """Every filtered ensemble member: one row per (k, path, member) (tracking level `full`)."""
    steps, P, M, _ = tr.members.shape
    cols = {"experiment": np.full(steps * P * M, experiment), "k": np.repeat(np.arange(steps), P * M),
            "path": np.tile(np.repeat(np.arange(P), M), steps), "member": np.tile(np.arange(M), steps * P)}
    cols.update(_columns("x_filt", tr.x(tr.members)) | _columns("xi_filt", tr.xi(tr.members)))
    return pd.DataFrame(cols)


def path_table(runs: dict[str, Trajectories]) -> pd.DataFrame:
    """Per path: the step it failed at (-1: never) and why."""
    return pd.DataFrame([{"experiment": name, "path": j, "failed_at": int(tr.failed_at[j]),
                          "failure": str(tr.failure[j])}
                         for name, tr in runs.items() for j in range(tr.failed_at.size)])


def model_table(exp: Experiment, dist) -> pd.DataFrame:
    """The modeled distribution: mean, cov, second moment and Gbar as (quantity, row, col, value)."""
    rows = []
    if dist is not None:
        for name, value in (("mean", dist.mean[:, None]), ("cov", dist.cov), ("second_moment", dist.second_moment),
                            ("Gbar", exp.model.Gbar(dist))):
            rows += [{"quantity": name, "row": i, "col": j, "value": float(v)}
                     for (i, j), v in np.ndenumerate(value)]
    return pd.DataFrame(rows, columns=["quantity", "row", "col", "value"])


def gains_table(exp: Experiment, designs: dict) -> pd.DataFrame:
    """Per (distribution, method): status, lam (design), bracket, nbar, exact rates on the design
    moments and on the true plant, F. designs: {(source, method): (moments, SynthesisResult)}.

    Only reproducible numbers go into tables; synthesis times are in run.json's timings."""
    rows = []
    for (source, method), (moments, res) in designs.items():
        found = res.F is not None
        F = res.F if found else np.full((exp.model.m, exp.model.n), np.nan)
        rows.append({"distribution": source, "method": method,
                     "selected": source == "identified" and method == exp.gain_method,
                     "status": res.status, "lam": res.lam, "lam_lower": res.lam_lower,
                     "lower_certified": res.lower_certified, "nbar": res.nbar,
                     "rate_model": ms_rate(exp.model, moments, F) if found else np.nan,
                     "rate_plant": ms_rate(exp.plant, None, F) if found else np.nan,
                     **{f"F[{i}]": v for i, v in enumerate(F.ravel())}})
    return pd.DataFrame(rows)


def metrics_table(exp: Experiment, loops: dict[str, Trajectories]) -> pd.DataFrame:
    """Per loop: empirical rate over rate_window with its 95% interval, failures, estimation error."""
    k_from, k_to = exp.rate_window
    rows = []
    for name, tr in loops.items():
        rate, low, high = empirical_rate(tr.q, k_from, k_to)
        err = tr.x(tr.psi_pred_mean) - tr.q
        rows.append({"experiment": name, "status": tr.status, "rate": rate, "rate_low": low, "rate_high": high,
                     "k_from": k_from, "k_to": k_to, "paths": tr.q.shape[1],
                     "failed_fraction": float(np.mean(tr.failed_at >= 0)),
                     "x_error_rms": float(np.sqrt(np.nanmean(np.sum(err ** 2, axis=-1)))),
                     "q_rms_final": float(np.sqrt(np.mean(np.sum(tr.q[-1] ** 2, axis=-1))))})
    return pd.DataFrame(rows, columns=["experiment", "status", "rate", "rate_low", "rate_high", "k_from", "k_to",
                                       "paths", "failed_fraction", "x_error_rms", "q_rms_final"])


def exact_table(exp: Experiment, chosen: SynthesisResult | None) -> pd.DataFrame:
    """sqrt(E||q_k||^2) of the ideal loops (state feedback, true plant distribution), exactly."""
    frames = []
    gains = ([("closed_loop", chosen.F)] if chosen is not None and chosen.F is not None else []) + \
        [("open_loop", np.zeros((exp.plant.m, exp.plant.n)))]
    for name, F in gains:
        with np.errstate(all="ignore"):
            _, second = second_moments(exp.plant, None, F, exp.q0, exp.disturbance)
        frames.append(pd.DataFrame({"experiment": name, "k": np.arange(second.shape[0]),
                                    "rms": np.sqrt(np.trace(second, axis1=1, axis2=2))}))
    return pd.concat(frames, ignore_index=True)


def _summary(exp: Experiment, dist, chosen, metrics: pd.DataFrame) -> dict:
    s = {"gain_method": exp.gain_method}
    if dist is not None:
        s.update(nbar=int(exp.model.Gbar(dist).shape[0]), xi_mean=dist.mean.tolist())
    if chosen is not None:
        s.update(synthesis_status=chosen.status, lam=chosen.lam,
                 rate_plant=ms_rate(exp.plant, None, chosen.F) if chosen.F is not None else None)
    for row in metrics.itertuples():
        s[f"{row.experiment}_status"] = row.status
        s[f"{row.experiment}_rate"] = [row.rate, row.rate_low, row.rate_high]
    return s


# ------------------------------------------------------------------------------------ recording
def record(run_dir: Path, outcome: Outcome, exp: Experiment, info: dict) -> dict:
    """Write tables, recording and the final run.json into run_dir; returns the run.json content."""
    timings = dict(outcome.timings)
    with _timed(timings, "tables"):
        frames = dict(outcome.tables) | ({"members": outcome.members} if outcome.members is not None else {})
        hashes = {name: {"file": f"{name}.parquet", "rows": len(table),
                         "sha256": tracking.write_table(run_dir / f"{name}.parquet", table)}
                  for name, table in frames.items()}
    with _timed(timings, "recording"):
        if exp.recording:
            from .recording import write_recording      # rerun is imported only when recording
            tmp = run_dir / ".recording.rrd.tmp"
            trajectories = pd.concat([outcome.tables["identification"], outcome.tables["trajectories"]],
                                     ignore_index=True)
            write_recording(tmp, trajectories, recording_id=info["id"], members=outcome.members)
            tmp.replace(run_dir / "recording.rrd")
    info.update(status="complete", finished=_now(), summary=outcome.summary, tables=hashes, timings=timings,
                seconds=round(sum(v for v in timings.values() if isinstance(v, float)), 3))
    tracking.write_json(run_dir / "run.json", info)
    return info


def _now() -> str:
    return dt.datetime.now(dt.timezone.utc).isoformat(timespec="milliseconds")


def run_info(run_dir: Path, job_config: dict, seed: int) -> tuple[dict, str]:
    """The provenance part of run.json, known before any compute, and the uncommitted diff."""
    code = tracking.code_version()
    hc = HydraConfig.get() if HydraConfig.initialized() else None
    multirun = hc is not None and hc.mode == RunMode.MULTIRUN
    return {
        "id": run_dir.name if not multirun else f"{Path(hc.sweep.dir).name}/{run_dir.name}",
        "status": "incomplete", "created": _now(),
        "command": " ".join(["python -m rdsexp", *(hc.overrides.task if hc else [])]),
        "overrides": list(hc.overrides.task) if hc else [],
        "sweep": {"dir": str(Path(hc.sweep.dir).resolve()), "job": int(hc.job.num),
                  "name": hc.runtime.choices.get("sweep")} if multirun else None,
        "config_hash": tracking.config_hash(job_config),
        "code": {k: v for k, v in code.items() if k != "diff"} | {"diff_file": "uncommitted.diff" if code["dirty"] else None},
        "seed": {"root": seed, "spawn_keys": {k: list(v) for k, v in SPAWN_KEYS.items()},
                 "per_path": "SeedSequence(seed, spawn_key=(*spawn_key, purpose, path)), purpose 0 plant, 1 EnKF"},
        "environment": tracking.environment(),
    }, code["diff"]


# ------------------------------------------------------------------------------------ entry point
def job_config(cfg: DictConfig) -> dict:
    """The resolved job config without the hydra node (what the run computes from)."""
    return OmegaConf.to_container(cfg, resolve=True)


def execute(cfg: DictConfig, run_dir: Path) -> dict:
    """Validate, compute and record one run into run_dir; returns run.json's content.

    With tracking level "off" nothing is written (Hydra's .hydra/ aside) and the same content
    is only returned."""
    exp = build(cfg)                                    # ConfigError before any compute
    if exp.tracking == "off":
        outcome = run_experiment(exp)
        return {"id": run_dir.name, "status": "complete", "summary": outcome.summary, "timings": outcome.timings}
    timings = {}
    with _timed(timings, "provenance"):
        info, diff = run_info(run_dir, job_config(cfg), exp.seed)
        previous = reusable_run(cfg, info)
        if previous is not None:
            return reuse(previous, run_dir, info)
        if diff:
            tracking.atomic_write_bytes(run_dir / "uncommitted.diff", diff.encode())
        tracking.write_json(run_dir / "run.json", info)     # "incomplete" until the end
    outcome = run_experiment(exp)
    outcome.timings |= timings
    return record(run_dir, outcome, exp, info)


def reusable_run(cfg: DictConfig, info: dict) -> Path | None:
    """In a sweep with `reuse: true`, a complete run of the same config hash and code version under
    the sweeps' root (a relaunched sweep skips the jobs a killed one completed)."""
    if not cfg.get("reuse") or info["sweep"] is None:
        return None
    from .runs import find_complete
    return find_complete(Path(info["sweep"]["dir"]).parent, info["config_hash"], info["code"]["version"])


def reuse(previous: Path, run_dir: Path, info: dict) -> dict:
    """Record run_dir as a copy of a complete previous run (files hard-linked where possible)."""
    old = tracking.read_json(previous / "run.json")
    for name in [meta["file"] for meta in old["tables"].values()] + ["recording.rrd", "uncommitted.diff"]:
        if (previous / name).exists() and not (run_dir / name).exists():
            try:
                os.link(previous / name, run_dir / name)
            except OSError:
                shutil.copy2(previous / name, run_dir / name)
    info.update(status="complete", finished=_now(), reused_from=old["id"],
                **{k: old[k] for k in ("summary", "tables", "timings", "seconds") if k in old})
    tracking.write_json(run_dir / "run.json", info)
    return info


@hydra.main(config_path=CONF_DIR, config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> dict | None:
    hc = HydraConfig.get()
    run_dir = Path(hc.runtime.output_dir)
    multirun = hc.mode == RunMode.MULTIRUN
    try:
        info = execute(cfg, run_dir)
    except ConfigError as err:
        if not multirun:                                  # nothing that could pass for a result
            shutil.rmtree(run_dir, ignore_errors=True)
            print(f"rdsexp: config error: {err}", file=sys.stderr)
            sys.exit(2)
        info = _failed(run_dir, cfg, "config_error", str(err))
    except Exception as err:                              # a sweep goes on; a single run reports and fails
        if not multirun:
            _failed(run_dir, cfg, "error", f"{type(err).__name__}: {err}", traceback.format_exc())
            raise
        log.exception("job %s failed", hc.job.num)
        info = _failed(run_dir, cfg, "error", f"{type(err).__name__}: {err}", traceback.format_exc())
    if multirun:
        from .runs import write_sweep_summary
        write_sweep_summary(Path(hc.sweep.dir))
    else:
        print_summary(info, run_dir)
    return info


def _failed(run_dir: Path, cfg: DictConfig, status: str, message: str, trace: str | None = None) -> dict:
    """Record a run that could not finish (keeps whatever provenance run.json already had)."""
    path = run_dir / "run.json"
    info = tracking.read_json(path) if path.exists() else {"id": run_dir.name, "created": _now(),
                                                             "config_hash": tracking.config_hash(job_config(cfg))}
    info.update(status=status, error=message, traceback=trace, finished=_now())
    tracking.write_json(path, info)
    return info


_SWEEP_BARS: dict[int, tqdm] = {}      # the sweep's progress bar, in the process that launched it


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


def validate_sweep(points: list[list[str]]) -> None:
    """Compose and validate every job's config before the first job runs; exit 2 on the first bad one."""
    from hydra import compose
    for overrides in points:
        try:
            build(compose(config_name="config", overrides=overrides))
        except ConfigError as err:
            print(f"rdsexp: config error in sweep job {' '.join(overrides)}: {err}", file=sys.stderr)
            sys.exit(2)


class SweepSummary(Callback):
    """Hydra callback: validates every job's config before the first runs, shows a progress bar over
    the jobs and writes the summary table once all have returned.

    Each job also rebuilds the summary when it ends, so a sweep that is killed still has one."""

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        points = sweep_points(config)
        validate_sweep(points)
        _SWEEP_BARS[os.getpid()] = tqdm(total=len(points), desc="sweep", unit="job", disable=None, file=sys.stderr)

    def on_job_end(self, config: DictConfig, job_return, **kwargs) -> None:
        bar = _SWEEP_BARS.get(os.getpid())      # None in launcher worker processes
        if bar is not None:
            bar.update(1)

    def on_multirun_end(self, config: DictConfig, **kwargs) -> None:
        from .runs import write_sweep_summary
        bar = _SWEEP_BARS.pop(os.getpid(), None)
        if bar is not None:
            bar.close()
        path = write_sweep_summary(Path(config.hydra.sweep.dir))
        print(f"sweep summary: {path}")


def print_summary(info: dict, run_dir: Path) -> None:
    """A few lines: the key numbers beside the paper's, the run directory and how to view it."""
    s = info.get("summary", {})
    fmt = lambda v: "n/a" if v is None else (f"{v:.4f}" if isinstance(v, float) else str(v))
    interval = lambda r: f"{r[0]:.4f} [{r[1]:.4f}, {r[2]:.4f}]" if r else "n/a"
    lines = [f"rdsexp run {info.get('id')}: {info.get('status')}",
             f"  modeling {s.get('modeling_status')}: xi mean {np.round(s.get('xi_mean', []), 4).tolist()}  "
             f"(paper {paper.xi_mean.tolist()}), nbar {s.get('nbar')} (paper {paper.nbar_proposed})",
             f"  gain {s.get('gain_method')}: {s.get('synthesis_status')}, lambda {fmt(s.get('lam'))} "
             f"(paper {paper.lam_proposed}), exact rate on the true plant {fmt(s.get('rate_plant'))}",
             f"  closed loop rate k=60..80: {interval(s.get('closed_loop_rate'))} (paper {paper.rate_k60_k80}), "
             f"{s.get('closed_loop_status')}"]
    if "open_loop_rate" in s:
        lines.append(f"  open loop rate k=60..80:   {interval(s.get('open_loop_rate'))}, {s.get('open_loop_status')}")
    lines.append(f"  run directory: {run_dir}")
    if (run_dir / "recording.rrd").exists():
        lines.append(f"  view: rerun {run_dir / 'recording.rrd'}")
    print("\n".join(lines))
