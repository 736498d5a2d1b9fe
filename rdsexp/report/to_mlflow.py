"""Stored rdsexp runs on an MLflow tracking server: `rdsexp-runs export --mlflow URI SWEEP|--where ...`.

    from rdsexp.experiment.catalog import search
    from rdsexp.report import to_mlflow
    to_mlflow.export(search("outputs", "enkf.q_scale >= 1"), "http://127.0.0.1:5000")
    to_mlflow.export("my_sweep", "http://127.0.0.1:5000", experiment="tuning")   # a sweep by name

Each stored run (one row of `rdsexp.runs.search`, one per computation) becomes an MLflow run of the
experiment (default "rdsexp"), written with `MlflowClient` (explicit run ids, no active run):

    params     the resolved config (run.json `params`, the search table's params.*), values as text;
               MLflow's limits: a key of at most 250 characters, a value of at most 6000 (longer values
               are cut and named in the tag rdsexp.truncated_params)
    metrics    the summary's numbers (the search table's numeric metrics.*; NaN, a number the run does
               not have, is left out) at step 0, and the RMS curves sqrt(E||q_k||^2) at step k:
               rms/<loop> over the paths of the trajectories table, rms/<loop>_exact of the ideal
               loop (exact table); names as MLflow allows them: xi_mean[0] is xi_mean.0
    tags       rdsexp.run_id, rdsexp.code, rdsexp.config_hash, rdsexp.plant_hash (a data run: rdsexp.data_sha256,
               its data file's), rdsexp.status, rdsexp.plant, rdsexp.sweep,
               rdsexp.seed, ... (the identity columns), summary.<name> for the summary's words
               (verdicts, statuses), rdsexp.recording: the path of recording.rrd (a link, not a copy,
               also in the run's note)
    artifacts  run.json, config.yaml (the composed config) and the stored tables (<name>.parquet)

A sweep (sweep_id) is a parent run with its jobs as nested runs (tag mlflow.parentRunId); a run
outside a sweep is a top-level run. Every MLflow run is keyed by a tag (rdsexp.run_id; a sweep's
parent by rdsexp.sweep_id) that is looked up before anything is created: exporting again adds
nothing, and a run whose export was interrupted (no tag rdsexp.export = complete) is completed with
what it lacks. Runs still being computed (status incomplete) and damaged records are left out.
"""
from __future__ import annotations

import datetime as dt
import hashlib
import math
import numbers
import os
import re
import tempfile
import urllib.error
import urllib.request
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import DamagedRecord, one_line
from ..experiment import metrics as registry
from ..experiment.catalog import DEFAULT_ROOT, locate, locate_sweep, query, search
from ..experiment.store import Run, layout
from ..experiment.store.table import changed_params, run_params
from ..numerics.analysis import rms_band

DEFAULT_EXPERIMENT = "rdsexp"
MAX_KEY, MAX_PARAM, MAX_TAG = 250, 6000, 8000      # MLflow's limits (mlflow.utils.validation)
RUN_KEY, SWEEP_KEY, DONE = "rdsexp.run_id", "rdsexp.sweep_id", "rdsexp.export"
STATUS = {"complete": "FINISHED", "interrupted": "KILLED"}     # any other final status: FAILED
TRUNCATED = "...[truncated]"


@dataclass
class Report:
    """What `export` did: rdsexp run ids exported now, already there, completed (an interrupted
    export finished) and left out ({id: reason}); {rdsexp id or sweep id: MLflow run id}."""

    experiment: str
    experiment_id: str
    uri: str
    exported: list[str] = field(default_factory=list)
    already: list[str] = field(default_factory=list)
    completed: list[str] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)
    runs: dict[str, str] = field(default_factory=dict)
    parents: dict[str, str] = field(default_factory=dict)
    copies: list[str] = field(default_factory=list)      # reused copies, each tagged on its original's run

    @property
    def url(self) -> str | None:
        """The experiment's page in the MLflow UI (an http(s) tracking URI only)."""
        if not self.uri.startswith(("http://", "https://")):
            return None
        return f"{self.uri.rstrip('/')}/#/experiments/{self.experiment_id}/runs"       # the runs table

    def lines(self) -> list[str]:
        counts = f"exported {len(self.exported)}, already there {len(self.already)}"
        counts += f", completed {len(self.completed)}" if self.completed else ""
        counts += f", copies {len(self.copies)} (on their originals' runs)" if self.copies else ""
        counts += f", left out {len(self.skipped)}" if self.skipped else ""
        where = f"experiment {self.experiment!r} (id {self.experiment_id}) at {self.uri}"
        return [*(f"left out {run}: {reason}" for run, reason in self.skipped.items()), f"{counts}: {where}",
                *([self.url] if self.url else [])]


def export(table_or_selection=None, uri: str = "", experiment: str = DEFAULT_EXPERIMENT, *,
           where: str | None = None, root=DEFAULT_ROOT, tables: bool = True, client=None) -> Report:
    """Write stored runs to the MLflow tracking server at `uri` (any tracking URI MlflowClient takes:
    http://host:port, sqlite:///file.db; MLflow refuses a plain directory); returns a `Report`.

    table_or_selection: a `search` table (its rows, then `where`), a sweep (directory or name) or a
    run (directory or id) under root, or None: the runs under root that `where` selects.
    tables: also the stored tables as artifacts (run.json and config.yaml always)."""
    try:
        from mlflow import MlflowClient
    except ImportError:
        raise ValueError("export: MLflow is not installed (pip install 'rdsexp[mlflow]')") from None
    table = select(table_or_selection, where, root)
    if not uri:
        raise ValueError("export: give the MLflow tracking URI (--mlflow URI)")
    reachable(uri)
    from mlflow.exceptions import MlflowException
    with _quiet():
        try:
            return _export(table, client or MlflowClient(tracking_uri=uri), uri, experiment, tables)
        except MlflowException as err:      # e.g. a backend MLflow no longer writes (a file store): one line
            raise ValueError(f"export: MLflow at {uri}: {one_line(err)}") from None


def _export(table: pd.DataFrame, client, uri: str, experiment: str, tables: bool) -> Report:
    found = client.get_experiment_by_name(experiment)
    if found is not None and found.lifecycle_stage != "active":
        raise ValueError(f"export: MLflow experiment {experiment!r} is deleted at {uri}; restore it or name another")
    experiment_id = found.experiment_id if found is not None else client.create_experiment(experiment)
    report = Report(experiment, experiment_id, uri)
    rows = [row for _, row in table.iterrows()]
    # a reused copy (a relaunched sweep's job, a command run twice) is no computation of its own: it is its
    # original's MLflow run, which names it in a tag, and adds no run (nor a parent for a sweep of copies)
    copies = [r for r in rows if isinstance(r.get("reused_from"), str)]
    rows = [r for r in rows if not isinstance(r.get("reused_from"), str)]
    for sweep_id in dict.fromkeys(r["sweep_id"] for r in rows if isinstance(r["sweep_id"], str)):
        jobs = [r for r in rows if r["sweep_id"] == sweep_id]
        existing, swept = _existing(client, experiment_id, SWEEP_KEY, sweep_id), _swept(jobs)
        parent = _parent(client, experiment_id, sweep_id, jobs, swept, existing)
        report.parents[sweep_id] = parent
        for row in jobs:
            name = f"{row['job']} " + " ".join(f"{k}={_text(row.get(f'params.{k}'))}" for k in swept)
            _one(client, experiment_id, row, report, existing, parent, name.strip(), tables)
    for row in (r for r in rows if not isinstance(r["sweep_id"], str)):
        _one(client, experiment_id, row, report, _existing(client, experiment_id, RUN_KEY, row["id"]), None,
             str(row["id"]), tables)
    for copy in copies:
        _copy(client, experiment_id, copy, report, tables)
    return report


def _copy(client, experiment_id: str, copy: pd.Series, report: Report, tables: bool) -> None:
    """A reused copy: its original's MLflow run (exported first, as a top-level run, when it is not there),
    tagged rdsexp.copy.<copy id> = the copy's directory; report.runs maps the copy to that run."""
    original = str(copy["reused_from"])
    there = _existing(client, experiment_id, RUN_KEY, original).get(original)
    if there is None or there.data.tags.get(DONE) != "complete":
        copy_dir = Path(copy["dir"]).resolve()
        root = copy_dir.parents[2] if "/" in str(copy["id"]) else copy_dir.parents[1]   # sweeps/<id>/<job>, runs/<id>
        try:
            original_dir = locate(original, root)
        except LookupError:
            report.skipped[str(copy["id"])] = f"a copy of {original}, which is not in the store"
            return
        row = search(original_dir.parent, copies=True).pipe(lambda t: t[t["dir"] == str(original_dir)])
        if not len(row):
            report.skipped[str(copy["id"])] = f"a copy of {original}, which the store does not list"
            return
        _one(client, experiment_id, row.iloc[0], report, {} if there is None else {original: there}, None,
             original, tables)
        there = _existing(client, experiment_id, RUN_KEY, original).get(original)
        if there is None:
            return
    client.set_tag(there.info.run_id, mlflow_key(f"rdsexp.copy.{copy['id']}"), str(Path(copy["dir"]).resolve()))
    report.runs[str(copy["id"])] = there.info.run_id
    report.copies.append(str(copy["id"]))


@contextmanager
def _quiet():
    """Without MLflow's "View run ... at" lines on stdout (MlflowClient.set_terminated prints them)."""
    name = "MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT"
    saved = os.environ.get(name)
    os.environ[name] = "true"
    try:
        yield
    finally:
        if saved is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = saved


def select(selection, where: str | None, root) -> pd.DataFrame:
    """The runs table to export (see `export`)."""
    root = Path(root)
    if isinstance(selection, pd.DataFrame):
        return query(selection, where) if where else selection
    if selection is None:
        if where is None:
            raise ValueError("export: name a SWEEP or RUN, or give --where")
        table = search(root, where)
    else:
        text = str(selection)
        directory = locate_sweep(text, root) if not layout.is_run(Path(text)) else None
        table = search(directory if directory is not None else locate(text, root), where)
    if not len(table):
        raise ValueError(f"export: no runs{f' of {selection}' if selection is not None else ''}"
                         f"{f' with {where}' if where else ''}")
    return table


def reachable(uri: str) -> None:
    """An http(s) tracking URI must answer (any HTTP status will do) before the client's retries
    would wait minutes for it; ValueError in one line otherwise."""
    if not uri.startswith(("http://", "https://")):
        return
    try:
        urllib.request.urlopen(uri.rstrip("/") + "/health", timeout=10).close()
    except urllib.error.HTTPError:
        pass
    except (urllib.error.URLError, OSError) as err:
        reason = getattr(err, "reason", err)
        raise ValueError(f"export: no MLflow tracking server answers at {uri} ({reason})") from None


# ---------------------------------------------------------------- one run


def _one(client, experiment_id: str, row: pd.Series, report: Report, existing: dict, parent: str | None,
         name: str, tables: bool) -> None:
    """Export one run unless it is there (complete), or complete an interrupted export of it."""
    from mlflow.entities import Metric, Param, RunTag
    run_id, run_dir = str(row["id"]), Path(row["dir"]).resolve()
    there = existing.get(run_id)
    if there is not None and there.data.tags.get(DONE) == "complete":
        report.already.append(run_id)
        report.runs[run_id] = there.info.run_id
        return
    status = row.get("status")
    if status == "incomplete":
        report.skipped[run_id] = "incomplete (still running, or its process died)"
        return
    try:
        run = Run(run_dir)        # its files (tables, recording) and what the row has no column for
    except DamagedRecord as err:
        report.skipped[run_id] = f"damaged ({err})"
        return
    record = run.record
    damage = run.damage() if status == "complete" else []
    if damage:
        report.skipped[run_id] = "damaged: " + "; ".join(damage)
        return
    # params from the record: the table's params.* columns are shared by all its runs (a key one run lacks makes
    # the column float for every run, and 40 would read 40.0)
    params, truncated = _params(run_params(run_dir, record.params))
    stamp = _millis(record.finished or record.created) or int(dt.datetime.now(dt.UTC).timestamp() * 1000)
    metrics, words = _scalars({k: v for k, v in row.items() if str(k).startswith("metrics.")})
    tags = _tags(row, run, parent, name) | words
    if truncated:
        tags["rdsexp.truncated_params"] = ", ".join(truncated)[:MAX_TAG]
    curves = _curves(run)
    start = _millis(record.created)
    if there is None:
        mlflow_id = client.create_run(experiment_id, start_time=start, tags=_tag_values(tags)).info.run_id
        have_params, have_metrics, have_files = {}, {}, set()
    else:
        mlflow_id = there.info.run_id
        have_params, have_metrics = there.data.params, there.data.metrics
        have_files = {f.path for f in client.list_artifacts(mlflow_id)}
    client.log_batch(mlflow_id, metrics=[Metric(k, v, stamp, 0) for k, v in metrics.items() if k not in have_metrics],
                     params=[Param(k, v) for k, v in params.items() if k not in have_params],
                     tags=[RunTag(k, v) for k, v in _tag_values(tags).items()])
    points = []
    for key, curve in curves.items():
        steps = {m.step for m in client.get_metric_history(mlflow_id, key)} if key in have_metrics else set()
        points += [Metric(key, v, stamp, k) for k, v in curve.items() if k not in steps]
    client.log_batch(mlflow_id, metrics=points)
    for source, artifact in _artifacts(run, tables):
        if artifact not in have_files:
            client.log_artifact(mlflow_id, str(source))
    plant = _plant_file(run_dir)
    if plant is not None and PLANT_FILE not in have_files:       # the system itself, beside its hash
        with tempfile.TemporaryDirectory() as tmp:
            (Path(tmp) / PLANT_FILE).write_text(plant)
            client.log_artifact(mlflow_id, str(Path(tmp) / PLANT_FILE))
    end = _millis(record.finished) or (start + int(1000 * (record.seconds or 0)) if start else None)
    client.set_terminated(mlflow_id, STATUS.get(status, "FAILED"), end_time=end)
    client.set_tag(mlflow_id, DONE, "complete")
    (report.exported if there is None else report.completed).append(run_id)
    report.runs[run_id] = mlflow_id


PLANT_FILE = "plant.yaml"


def _plant_file(run_dir: Path) -> str | None:
    """The plant node of the run's composed config as YAML (the plant file as the run read it); None without one."""
    import yaml
    try:
        config = yaml.safe_load((run_dir / layout.HYDRA_CONFIG).read_text()) or {}
    except (OSError, yaml.YAMLError):
        return None
    plant = config.get("plant") if isinstance(config, dict) else None
    return yaml.safe_dump(plant, sort_keys=False, default_flow_style=None) if isinstance(plant, dict) else None


def _params(params: dict) -> tuple[dict[str, str], list[str]]:
    """{MLflow key: value as text} and the keys whose values were cut to MLflow's length."""
    out, truncated = {}, []
    for name, value in params.items():
        key, text = mlflow_key(name.removeprefix("params."), out), _text(value)
        if len(text) > MAX_PARAM:
            text = text[:MAX_PARAM - len(TRUNCATED)] + TRUNCATED
            truncated.append(key)
        out[key] = text
    return out, truncated


def _scalars(metrics: dict) -> tuple[dict[str, float], dict[str, str]]:
    """The row's metrics.* (the summary's numbers and words) as {MLflow metric key: value} (NaN: no value, left
    out), the registry's `mlflow_first` first, and its words (verdicts, statuses) as tags summary.<name>."""
    numbers_, words = {}, {}
    first = [m.column for m in registry.mlflow_first() if m.column in metrics]
    for name in [*first, *(m for m in metrics if m not in first)]:
        value, name = metrics[name], name.removeprefix("metrics.")
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Number):
            if value is not None and value is not pd.NA:
                words[mlflow_key(f"summary.{name}", words)] = str(value)[:MAX_TAG]
        elif not math.isnan(value):
            numbers_[mlflow_key(name, numbers_)] = float(value)
    return numbers_, words


def _curves(run: Run) -> dict[str, dict[int, float]]:
    """{rms/<loop>: {k: sqrt(E||q_k||^2)}} over the paths of the trajectories table (the mean over the
    paths where q_k is finite, `analysis.rms_band`) and {rms/<loop>_exact: {k: rms}} of the exact table;
    a table the run lacks (a run that failed) gives no curve."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    curves = {}
    try:        # a complete run's bytes were checked against run.json (run_damage)
        path = run.file("trajectories")
        columns = [c for c in pq.read_schema(path).names if re.fullmatch(r"q\[\d+\]", c)]
        frame = pd.read_parquet(path, columns=["experiment", "k", "path", *columns])
        frame["sq"] = np.sum(frame[columns].to_numpy(dtype=float) ** 2, axis=1)
        for loop, rows in frame.groupby("experiment", sort=False):
            sq = rows.set_index(["k", "path"])["sq"].unstack("path").sort_index()      # (K+1, P)
            mean = rms_band(sq.to_numpy())[0]
            curves[f"rms/{loop}"] = {int(k): float(v) for k, v in zip(sq.index, mean) if np.isfinite(v)}
    except (OSError, KeyError, TypeError, ValueError, pa.ArrowException):
        pass
    try:
        exact = pd.read_parquet(run.file("exact"))
        for loop, rows in exact.groupby("experiment", sort=False):
            curves[f"rms/{loop}_exact"] = {int(k): float(v) for k, v in zip(rows["k"], rows["rms"]) if np.isfinite(v)}
    except (OSError, KeyError, TypeError, ValueError, pa.ArrowException):
        pass
    return {mlflow_key(k, {}): v for k, v in curves.items() if v}


def _tags(row: pd.Series, run: Run, parent: str | None, name: str) -> dict:
    """The run's tags: its identity from the row, from its record what the row has no column for (the whole
    plant hash, the data file's hash, the error, the rate window, the commit)."""
    record, run_dir = run.record, run.dir.resolve()
    window = record.summary.rate_window
    tags = {RUN_KEY: row["id"], "rdsexp.kind": "run", "rdsexp.code": row.get("code"),
            "rdsexp.config_hash": row.get("config_hash"), "rdsexp.plant_hash": record.plant_hash,
            "rdsexp.data_sha256": (record.data or {}).get("sha256"),
            "rdsexp.status": row.get("status"),
            "rdsexp.plant": row.get("plant"), "rdsexp.model": row.get("model"), "rdsexp.method": row.get("method"),
            "rdsexp.sweep": row.get("sweep"), SWEEP_KEY: row.get("sweep_id"), "rdsexp.job": row.get("job"),
            "rdsexp.seed": row.get("seed"), "rdsexp.overrides": row.get("overrides") or None,
            "rdsexp.reused_from": row.get("reused_from"), "rdsexp.created": row.get("created"),
            "rdsexp.dir": str(run_dir), "rdsexp.error": record.error,
            "rdsexp.rate_window": ",".join(map(str, window)) if window else None,
            "mlflow.runName": name, "mlflow.parentRunId": parent, "mlflow.source.git.commit": record.code_commit}
    recording = run.recording_file
    if recording is not None and recording.exists():
        tags["rdsexp.recording"] = str(recording.resolve())
    tags["mlflow.note.content"] = _note(row, record.command, run_dir, tags.get("rdsexp.recording"))
    return tags


def _note(row: pd.Series, command: str | None, run_dir: Path, recording: str | None) -> str:
    lines = [f"rdsexp run `{row['id']}`: status {row.get('status')}, code `{row.get('code')}`",
             "", f"- directory: `{run_dir}`"]
    if command:
        lines.append(f"- command: `{command}`")
    if recording:
        lines.append(f"- recording (not copied): `{recording}`; open it with `rdsexp-runs view {run_dir}` "
                     f"or `rerun {recording}`")
    return "\n".join(lines)


def _artifacts(run: Run, tables: bool) -> list[tuple[Path, str]]:
    """(file, its name among the run's artifacts): run.json, config.yaml and the stored tables."""
    run_dir = run.dir.resolve()
    files = [(run_dir / run.record_file.name, run.record_file.name), (run_dir / layout.HYDRA_CONFIG, "config.yaml")]
    if tables:
        files += [(run_dir / stored.file, Path(stored.file).name) for stored in run.record.tables.values()]
    return [(source, name) for source, name in files if source.is_file()]


# ---------------------------------------------------------------- sweeps


def _parent(client, experiment_id: str, sweep_id: str, jobs: list[pd.Series], swept: list[str],
            existing: dict) -> str:
    """The MLflow run of the sweep (created on first export, completed if that was interrupted); its run id."""
    from mlflow.entities import RunTag
    there = existing.get(sweep_id)
    if there is not None and there.data.tags.get(DONE) == "complete":
        return there.info.run_id
    sweep_dir = Path(jobs[0]["dir"]).resolve().parent
    name = next((j["sweep"] for j in jobs if isinstance(j.get("sweep"), str)), None) or sweep_id
    tags = {SWEEP_KEY: sweep_id, "rdsexp.kind": "sweep", "rdsexp.sweep": name, "rdsexp.dir": str(sweep_dir),
            "rdsexp.swept": ", ".join(swept) or None, "mlflow.runName": name}
    overrides = _overrides(sweep_dir)
    if overrides:
        tags["rdsexp.overrides"] = " ".join(overrides)
    summary = sweep_dir / layout.SUMMARY_RECORDING
    if summary.exists():
        tags["rdsexp.recording"] = str(summary)
    tags["mlflow.note.content"] = (f"rdsexp sweep `{sweep_id}` ({name})\n\n- directory: `{sweep_dir}`"
                                   + (f"\n- recording (not copied): `{summary}`" if summary.exists() else ""))
    created = [_millis(j.get("created")) for j in jobs]
    if there is None:
        run_id = client.create_run(experiment_id, start_time=min((c for c in created if c), default=None),
                                   tags=_tag_values(tags)).info.run_id
    else:
        run_id = there.info.run_id
        client.log_batch(run_id, tags=[RunTag(k, v) for k, v in _tag_values(tags).items()])
    have = {f.path for f in client.list_artifacts(run_id)} if there is not None else set()
    if (sweep_dir / layout.MULTIRUN).is_file() and layout.MULTIRUN not in have:
        client.log_artifact(run_id, str(sweep_dir / layout.MULTIRUN))
    finished = [_finished(Path(j["dir"])) for j in jobs]
    client.set_terminated(run_id, "FINISHED", end_time=max((f for f in finished if f), default=None))   # its jobs' end
    client.set_tag(run_id, DONE, "complete")
    return run_id


def _finished(run_dir: Path) -> int | None:
    """When a run ended (run.json's `finished`, ms), None when it has no readable record of it."""
    try:
        return _millis(Run(run_dir).record.finished)
    except (DamagedRecord, OSError):
        return None


def _swept(jobs: list[pd.Series]) -> list[str]:
    """The config keys whose values differ between the sweep's jobs (those of the whole sweep on
    disk where it is there, else those of the jobs exported)."""
    sweep_dir = Path(jobs[0]["dir"]).resolve().parent
    table = search(sweep_dir, copies=True) if layout.is_sweep(sweep_dir) else pd.DataFrame(jobs)
    if not len(table):
        table = pd.DataFrame(jobs)
    return [c.removeprefix("params.") for c in changed_params(table)]


def _overrides(sweep_dir: Path) -> list[str]:
    import yaml
    try:
        config = yaml.safe_load((sweep_dir / layout.MULTIRUN).read_text())
        return [str(o) for o in ((config or {}).get("hydra") or {}).get("overrides", {}).get("task") or []]
    except (OSError, yaml.YAMLError, AttributeError):
        return []


def _existing(client, experiment_id: str, key: str, value: str) -> dict:
    """{rdsexp run id or sweep id: MLflow run} of the active runs tagged key=value: a sweep's parent
    and its jobs (key rdsexp.sweep_id), or one run (rdsexp.run_id)."""
    found, token = {}, None
    while True:
        page = client.search_runs([experiment_id], filter_string=f"tags.`{key}` = '{value}'", max_results=1000,
                                  page_token=token)
        for run in page:
            tags = run.data.tags
            ident = tags.get(RUN_KEY) if tags.get("rdsexp.kind") == "run" else tags.get(SWEEP_KEY)
            if ident is not None:
                found.setdefault(ident, run)
        token = page.token
        if not token:
            return found


# ---------------------------------------------------------------- names and values


def mlflow_key(name: str, taken: dict | None = None) -> str:
    """`name` as MLflow allows a param, metric or tag key: xi_mean[0] -> xi_mean.0, other characters
    than letters, digits, _ - . space : / -> _, at most 250 characters (a longer one ends in a hash of
    the name); a key already in `taken` gets ~2, ~3, ..."""
    key = re.sub(r"\[([^\]]*)\]", lambda m: "." + re.sub(r"\s*,\s*", ".", m.group(1)), name)
    key = re.sub(r"[^\w.\- :/]", "_", key)
    key = re.sub(r"/+", "/", key).strip("/") or "_"
    if len(key) > MAX_KEY:
        key = key[:MAX_KEY - 9] + "~" + hashlib.sha1(name.encode()).hexdigest()[:8]
    base, n = key, 1
    while taken and key in taken:
        n += 1
        key = f"{base[:MAX_KEY - len(str(n)) - 1]}~{n}"
    return key


def _text(value) -> str:
    """A param's value as MLflow stores it (text, as MlflowClient.log_param would: str)."""
    return str(value.item() if isinstance(value, np.generic) else value)


def _tag_values(tags: dict) -> dict[str, str]:
    """Tags with a value, as text of at most MLflow's length."""
    out = {}
    for key, value in tags.items():
        if value is None or (isinstance(value, float) and math.isnan(value)) or value is pd.NA:
            continue
        out[key] = _text(value)[:MAX_TAG]
    return out


def _millis(stamp) -> int | None:
    """Milliseconds since the epoch of an ISO time (run.json's created, finished); None without one."""
    if not isinstance(stamp, str):
        return None
    try:
        when = dt.datetime.fromisoformat(stamp)
    except ValueError:
        return None
    when = when if when.tzinfo else when.replace(tzinfo=dt.UTC)
    return int(when.timestamp() * 1000)
