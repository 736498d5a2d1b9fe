"""`rdsexp` / `python -m rdsexp`: the Hydra entry point and the run directory it records into.

One run: validate the config (exit 2 on a bad value, no run directory), write run.json as
"incomplete", compute the stage pipeline, write tables, recording and the final run.json.
In a sweep a job that fails is recorded with its status and the sweep goes on.
"""
from __future__ import annotations

import dataclasses
import logging
import shutil
import signal
import sys
import traceback
import uuid
from pathlib import Path

import hydra
import numpy as np
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from ..numerics.modeling import one_line
from . import records, store
from .config import ConfigError, Experiment, build, check_overrides
from .pipeline import FAILURES, SPAWN_KEYS, TABLES, Outcome, run_experiment, timed
from .schema import attach

log = logging.getLogger("rdsexp")
CONF_PACKAGE = "pkg://rdsexp.conf"        # conf/ of the repository, shipped as the package rdsexp.conf

if not OmegaConf.has_resolver("uid"):
    # unique run directories even for runs started in the same microsecond; cached so that every
    # job of one sweep resolves the same sweep directory
    OmegaConf.register_new_resolver("uid", lambda: uuid.uuid4().hex[:8], use_cache=True)


def record(run_dir: Path, outcome: Outcome, exp: Experiment, info: dict, streamed: dict) -> dict:
    """Write the remaining tables, the recording and the final run.json into run_dir; `streamed`:
    the tables the pipeline already wrote through a ParquetSink. Returns the run.json content."""
    timings = dict(outcome.timings)
    with timed(timings, "tables"):
        hashes = {name: records.store_table(run_dir / f"{name}.parquet", attach(name, table, info["id"]))
                  for name, table in outcome.tables.items()}                   # attach: schema metadata
        hashes = dict(sorted((hashes | streamed).items(), key=lambda item: _table_order(item[0])))
    with timed(timings, "recording"):
        if exp.recording:
            from .recording import write_recording  # rerun is imported only when recording
            tmp = records.tmp_name(run_dir / "recording.rrd")
            try:
                written = write_recording(tmp, outcome.recorded, recording_id=info["id"],
                                          members=outcome.recorded_members, tables=outcome.tables,
                                          summary=outcome.summary, squares=outcome.squares,
                                          window=(exp.K0, exp.K0 + exp.K1), **true_xi(exp))
            except OSError as err:
                tmp.unlink(missing_ok=True)
                raise records.WriteError(run_dir / "recording.rrd", err) from err
            if written:
                info["recording"] = records.store_file(tmp, run_dir / "recording.rrd")
            else:                                   # RERUN=off in the environment: rerun wrote nothing
                log.info("no recording: Rerun is disabled (RERUN=off)")
    info.update(status="complete", finished=records.now(), summary=outcome.summary, tables=hashes, timings=timings,
                seconds=round(sum(v for v in timings.values() if isinstance(v, float)), 3))
    records.write_json(run_dir / "run.json", info)
    return info


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
    truth = truth_map(exp.model, exp.plant)
    if truth is None:
        return {}
    T, t = truth
    dist = exp.plant.check_distribution(None)
    return {"xi_true": T @ dist.mean + t, "xi_true_std": np.sqrt(np.maximum(np.diag(T @ dist.cov @ T.T), 0.0))}


def _table_order(name: str) -> int:
    return TABLES.index(name) if name in TABLES else len(TABLES)


def run_info(run_dir: Path, job_config: dict, seed: int) -> tuple[dict, str]:
    """The provenance part of run.json, known before any compute, and the uncommitted diff."""
    code = records.code_version()
    hc = HydraConfig.get() if HydraConfig.initialized() else None
    multirun = hc is not None and hc.mode == RunMode.MULTIRUN
    return {
        "id": run_dir.name if not multirun else f"{Path(hc.sweep.dir).name}/{run_dir.name}",
        "status": "incomplete", "created": records.now(),
        "command": " ".join(["python -m rdsexp", *(hc.overrides.task if hc else [])]),
        "overrides": list(hc.overrides.task) if hc else [],
        "sweep": {"dir": str(Path(hc.sweep.dir).resolve()), "job": int(hc.job.num),
                  "name": hc.runtime.choices.get("sweep")} if multirun else None,
        "config_hash": records.config_hash(job_config),
        "code": {k: v for k, v in code.items() if k != "diff"}
        | {"diff_file": "uncommitted.diff" if code["dirty"] else None},
        "seed": {"root": seed, "spawn_keys": {k: list(v) for k, v in SPAWN_KEYS.items()},
                 "per_path": "SeedSequence(seed, spawn_key=(*spawn_key, purpose, path)), purpose 0 plant, 1 EnKF"},
        "environment": records.environment(),
        "process": records.process_info(),     # tells a run whose process died from a running one
    }, code["diff"]


def job_config(cfg: DictConfig) -> dict:
    """The resolved job config without the hydra node (what the run computes from; `store`, where
    it is recorded, is not part of it)."""
    return {k: v for k, v in OmegaConf.to_container(cfg, resolve=True).items() if k != "store"}


def store_root(cfg: DictConfig) -> Path:
    """The run store (config key `store`, relative to the directory rdsexp was started in)."""
    from hydra.utils import to_absolute_path
    return Path(to_absolute_path(str(cfg.get("store") or "outputs")))


def execute(cfg: DictConfig, run_dir: Path) -> dict:
    """Validate, compute and record one run into run_dir; returns run.json's content.

    With tracking level "off" nothing is written (Hydra's .hydra/ aside) and the same content
    is only returned."""
    if HydraConfig.initialized():
        check_overrides(cfg, HydraConfig.get().overrides.task)   # `+enkf.ensemble_sze=50`: a typo, not a key
    exp = build(cfg)                                    # ConfigError before any compute
    if OmegaConf.select(cfg, "plant.name") is None and HydraConfig.initialized():
        # a plant file without `name:` is named by its file (plant=NAME)
        exp = dataclasses.replace(exp, plant_name=HydraConfig.get().runtime.choices.get("plant") or "plant")
    if exp.tracking == "off":
        outcome = run_experiment(exp)
        return {"id": run_dir.name, "status": "complete", "summary": outcome.summary, "timings": outcome.timings}
    timings = {}
    with timed(timings, "provenance"):
        info, diff = run_info(run_dir, job_config(cfg), exp.seed)
        previous = reusable_run(cfg, info)
        if previous is not None:
            return reuse(previous, run_dir, info)
        if diff:
            records.atomic_write_bytes(run_dir / "uncommitted.diff", diff.encode())
        records.write_json(run_dir / "run.json", info)     # "incomplete" until the end
    sink = records.ParquetSink(run_dir)
    try:
        outcome = run_experiment(exp, _Described(sink, info["id"]))
    except BaseException:                   # no partial table left behind (run.json says what happened)
        sink.abort()
        raise
    outcome.timings |= timings
    with timed(outcome.timings, "streamed_tables"):
        streamed = sink.close()
    info = record(run_dir, outcome, exp, info, streamed)
    try:                                    # the index is derived data: a run is complete without it
        store.index_add(store_root(cfg), run_dir, info)
    except records.WriteError as err:
        log.warning("run %s not indexed for reuse: %s", info["id"], err)
    return info


def reusable_run(cfg: DictConfig, info: dict) -> Path | None:
    """In a sweep with `reuse: true`, an intact complete run of the same config hash and code version
    in the run store (config key `store`, found through its index; never anything outside it), so
    that a relaunched sweep skips the jobs a killed one completed."""
    if not cfg.get("reuse") or info["sweep"] is None:
        return None
    return store.find_reusable(store_root(cfg), info["config_hash"], info["code"]["version"])


def reuse(previous: Path, run_dir: Path, info: dict) -> dict:
    """Record run_dir as a copy of a complete previous run (files hard-linked where possible)."""
    old = store.read_run(previous)
    for name in [meta["file"] for meta in old["tables"].values()] + ["recording.rrd", "uncommitted.diff"]:
        if (previous / name).exists() and not (run_dir / name).exists():
            records.link_or_copy(previous / name, run_dir / name)
    log.info("reused the complete run %s (same config hash and code version)", old["id"])
    info.update(status="complete", finished=records.now(), reused_from=old["id"],
                **{k: old[k] for k in ("summary", "tables", "recording", "timings", "seconds") if k in old})
    records.write_json(run_dir / "run.json", info)
    return info


@hydra.main(config_path=CONF_PACKAGE, config_name="config", version_base="1.3")
def hydra_main(cfg: DictConfig) -> dict | None:
    STATE["started"] = True
    hc = HydraConfig.get()
    run_dir = Path(hc.runtime.output_dir)
    multirun = hc.mode == RunMode.MULTIRUN
    try:
        info = execute(cfg, run_dir)
    except records.WriteError as err:                     # disk full, permission denied, read-only
        info = _failed(run_dir, cfg, "write_error", str(err))
        if not multirun:
            print(f"rdsexp: {err}", file=sys.stderr)
            sys.exit(1)
        log.error("job %s: %s", hc.job.num, err)
    except ConfigError as err:
        if not multirun:                                  # nothing that could pass for a result
            shutil.rmtree(run_dir, ignore_errors=True)
            print(f"rdsexp: config error: {err}", file=sys.stderr)
            sys.exit(2)
        info = _failed(run_dir, cfg, "config_error", str(err))
    except Exception as err:                              # a sweep goes on; a single run reports and fails
        stage = getattr(err, "rdsexp_stage", "run")
        message = f"stage {stage}: {one_line(err)}"
        trace = traceback.format_exc()
        log.error("%s failed: %s", "run" if not multirun else f"job {hc.job.num}", message)
        log.info("traceback:\n%s", trace)                # rdsexp.log only (the terminal gets warnings and up)
        info = _failed(run_dir, cfg, "error", message, trace)
        if not multirun:                                  # the status, plainly; the traceback is in run.json
            print_summary(info, run_dir)
            sys.exit(1)
    if multirun:
        from .runs import write_sweep_summary
        try:
            write_sweep_summary(Path(hc.sweep.dir))
        except records.WriteError as err:                 # the sweep's end writes it again, and fails loudly
            log.error("job %s: %s", hc.job.num, err)
    else:
        print_summary(info, run_dir)
    return info


def main() -> None:
    """Console entry point `rdsexp` (and `python -m rdsexp`)."""
    # Ctrl-C stops a run or sweep even when the launching process ignored SIGINT (a child inherits
    # an ignored SIGINT): Python's default handler raises KeyboardInterrupt, which ends the run
    # with run.json still "incomplete" and every finished file complete
    signal.signal(signal.SIGINT, signal.default_int_handler)
    for arg in sys.argv[1:]:
        # enkf.Q's default is the mapping {x, xi, matrix}: Hydra cannot merge a list into it and
        # would end with a stack of merge errors; say in one line where a matrix goes
        name, _, value = arg.partition("=")
        if name.lstrip("+") == "enkf.Q" and value.lstrip().startswith("["):
            print(f"rdsexp: config error: enkf.Q: {value} is not allowed, expected the scales enkf.Q.x=, "
                  f"enkf.Q.xi= or a matrix as enkf.Q.matrix={value} (a scalar, n+p diagonal entries or "
                  f"a full (n+p)x(n+p) matrix)", file=sys.stderr)
            sys.exit(2)
    try:
        hydra_main()
    except SystemExit as exit_:
        # Hydra reports its own errors (a bad override, a missing config option, a key `+` cannot
        # add) and exits 1; before the run or sweep has started that is a config error: exit 2
        if exit_.code == 1 and not STATE["started"]:
            print("rdsexp: config error (reported by Hydra above)", file=sys.stderr)
            sys.exit(2)
        raise


# set by the task function and the sweep callback once the run or sweep has started: `main` tells
# Hydra's config errors (exit 2) from errors of the run (exit 1)
STATE = {"started": False}


def _failed(run_dir: Path, cfg: DictConfig, status: str, message: str, trace: str | None = None) -> dict:
    """Record a run that could not finish (keeps whatever provenance run.json already had), where
    run.json can still be written."""
    path = run_dir / "run.json"
    try:
        info = store.read_run(run_dir)
    except store.DamagedRecord:
        info = {"id": run_dir.name, "created": records.now(), "config_hash": records.config_hash(job_config(cfg))}
    info.update(status=status, error=message, traceback=trace, finished=records.now())
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        records.write_json(path, info)
    except (OSError, records.WriteError) as err:
        log.error("cannot record status %s in %s: %s", status, path, err)
    return info


def print_summary(info: dict, run_dir: Path) -> None:
    """A few lines: the plant and model, the key numbers (beside the reference numbers when the
    config carries them), plainly what failed, the run directory and how to view it."""
    s = info.get("summary", {})
    ref = s.get("reference") or {}
    fmt = lambda v: "n/a" if v is None else (f"{v:.4f}" if isinstance(v, float) else str(v))
    interval = lambda r: (f"{r[0]:.4f} [{r[1]:.4f}, {r[2]:.4f}]" if r and np.all(np.isfinite(r))
                          else "n/a (not every path reached the window)")
    beside = lambda name: f" ({ref.get('source', 'paper')} {ref[name]})" if name in ref else ""
    unstable = lambda rate: rate is not None and not rate < 1          # NaN too: not shown to be stable
    k_from, k_to = s.get("rate_window") or (None, None)
    lines = [f"rdsexp run {info.get('id')}: {info.get('status')}"]
    if s.get("plant"):                    # a run that failed before its summary has none
        lines.append(f"  plant {s['plant']}, model {s.get('model')}")
    if info.get("error"):
        lines.append(f"  failed: {info['error']} (traceback in run.json and rdsexp.log)")
    ident = s.get("identification_feedback") or {}
    if ident.get("mode", "none") != "none":
        line = f"  identification feedback {ident['mode']}: {ident.get('used')}"
        if "open_loop_rate_at_guess" in ident:
            line += f" (open-loop rate at xi_guess {fmt(ident['open_loop_rate_at_guess'])})"
        if ident.get("used", "").startswith("nominal"):
            line += f", gain {ident.get('method')} with rate {fmt(ident.get('rate_plant'))} on the true plant"
            if unstable(ident.get("rate_plant")):
                line += " (it does not stabilize the true plant in mean square)"
        lines.append(line)
    if s.get("modeling_status") == "ok":
        lines.append(f"  modeling ok: xi mean {np.round(s.get('xi_mean', []), 4).tolist()}{beside('xi_mean')}, "
                     f"nbar {s.get('nbar')}{beside('nbar')}")
    elif s.get("modeling_status") is not None:
        lines.append(f"  no model: {s.get('modeling_status')}" +
                     ("; no gain designed, no closed loop" if s.get("synthesis_status") is None else ""))
    if s.get("synthesis_status") is not None:
        lines.append(f"  gain {s.get('gain_method')}: {s.get('synthesis_status')}, lambda {fmt(s.get('lam'))}"
                     f"{beside('lam')}, exact rate on the true plant {fmt(s.get('rate_plant'))}")
        if s.get("rate_plant") is None:
            lines.append(f"  no stabilizing gain: {s.get('gain_method')} returned none "
                         f"({s.get('synthesis_status')}); no closed loop")
        elif s.get("synthesis_status") == "not_ms_stabilizable":
            lines.append(f"  no stabilizing gain: not_ms_stabilizable, the best rate found on the model is "
                         f"{fmt(s.get('lam'))}")
        elif unstable(s.get("rate_plant")):
            lines.append(f"  the gain does not stabilize the true plant: its exact rate there is "
                         f"{fmt(s.get('rate_plant'))} >= 1")
    others = {m: st for m, st in (s.get("designs") or {}).items()
              if m != s.get("gain_method") and st not in ("optimal", "designed")}
    if others:
        lines.append("  other designs: " + ", ".join(f"{m} {st}" for m, st in others.items()))
    for loop, label in (("closed_loop", "closed loop"), ("open_loop", "open loop  "), ("online", "online     ")):
        if f"{loop}_status" not in s:
            continue
        line = f"  {label} rate k={k_from}..{k_to}: {interval(s.get(f'{loop}_rate'))}"
        if loop == "closed_loop":
            line += beside("closed_loop_rate")
        line += f", {s.get(f'{loop}_status')}"
        failed = s.get(f"{loop}_failed")
        if failed:
            line += (f"; {100 * failed['fraction']:.0f}% of paths failed (first at k = {failed['first_k']}, "
                     f"median k = {failed['median_k']:g})")
            reasons = failed.get("reasons") or {}
            if reasons:
                line += ": " + ", ".join(f"{FAILURES.get(r, r)} on {c}" for r, c in reasons.items())
        lines.append(line)
    if s.get("online"):                                   # controller=online (issue 9)
        o = s["online"]
        fmt = lambda v: "nan" if v is None else f"{v:.4f}"
        lines.append(f"  online final gains: exact rate on the true plant median {fmt(o['final_rate_plant_median'])} "
                     f"(10-90% {fmt(o['final_rate_plant_q10'])}-{fmt(o['final_rate_plant_q90'])}), "
                     f"{100 * o['final_stable_fraction']:.0f}% stable, {o['adoptions_per_path']:.1f} adoptions per "
                     f"path; offline gain {fmt(o['offline_rate_plant'])}, optimum {fmt(o['optimal_rate_plant'])}")
    lines.append(f"  run directory: {run_dir}")
    if (run_dir / "recording.rrd").exists():
        lines.append(f"  view: rerun {run_dir / 'recording.rrd'}")
    print("\n".join(lines))
