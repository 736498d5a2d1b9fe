"""Checking a store and quarantining what is damaged (no record is ever deleted), and settling the runs a
Ctrl-C stopped."""
from __future__ import annotations

import json
import os
import shutil
import socket
import time
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from ...errors import DamagedRecord, one_line
from . import provenance
from .files import TMP_SUFFIX
from .index import _version, index_key, rebuild_index
from .layout import INDEX, MULTIRUN, QUARANTINE, STAGES, SUMMARY
from .run import read_run, read_runs, run_damage
from .table import write_sweep_summary


@dataclass
class Finding:
    """One damaged or inconsistent thing in a store: what (kind), where (path), why (reason), and
    the record it belongs to (moved to quarantine), or None (repaired by rebuilding instead)."""

    kind: str          # damaged | stuck | summary | index | temporary
    path: Path
    reason: str
    record: Path | None = None

    def line(self) -> str:
        return f"{self.kind:9s} {self.path}: {self.reason}"


def process_alive(process) -> bool | None:
    """Whether the process recorded in run.json still runs; None when that cannot be known here
    (another host, or no process recorded)."""
    if not isinstance(process, dict) or process.get("host") != socket.gethostname() \
            or not isinstance(process.get("pid"), int):
        return None
    try:
        os.kill(process["pid"], 0)
    except ProcessLookupError:
        return False
    except PermissionError:             # exists, owned by someone else
        pass
    start = provenance.start_time(process["pid"])
    return start is None or process.get("start") is None or start == process["start"]


def _tmp_pid(name: str) -> int | None:
    parts = name.split(".")
    return int(parts[-2]) if len(parts) >= 4 and parts[-1] == "tmp" and parts[-2].isdigit() else None


INTERRUPTED = "interrupted by Ctrl-C (SIGINT) before it completed"


def settle_interrupted(directory: Path, wait: float = 10.0) -> list[Path]:
    """After a Ctrl-C: every run under `directory` (a run or a sweep) whose run.json still says
    "incomplete" gets status "interrupted" once its process has ended (a sweep's workers are waited for
    up to `wait` seconds; a run whose process still runs after that is left as it is), the temporary
    files (`files.tmp_name`, never a complete record) of this process and of ended ones are removed, with
    the stage cache's temporary entries in the same store, and a sweep's summary is rebuilt so that it
    agrees with its jobs. Returns the runs marked."""
    from .writer import RunWriter
    directory = Path(directory)
    deadline = time.monotonic() + wait
    pending = [d for d, info in read_runs(directory, warn_damaged=False)[0] if info.get("status") == "incomplete"]
    marked = []
    while pending:
        states = {d: _state(d) for d in pending}
        for run_dir in [d for d, state in states.items() if state == "ended"]:
            RunWriter(run_dir).fail("interrupted", INTERRUPTED)
            marked.append(run_dir)
        pending = [d for d, state in states.items() if state == "running"]
        if not pending or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    # the run's or sweep's own files, and the stage cache's entries being written (directories) in the store
    # it belongs to: a worker stopped mid-write leaves its temporary entry there, outside the sweep
    root = _store_root(directory)
    stage_entries = (root / STAGES).glob(f"*/.*{TMP_SUFFIX}") if root is not None else ()
    for tmp in [*directory.rglob(f"*{TMP_SUFFIX}"), *stage_entries]:
        pid = _tmp_pid(tmp.name)
        if pid == os.getpid() or (pid is not None and not process_alive({"pid": pid, "host": socket.gethostname()})):
            if tmp.is_dir():
                shutil.rmtree(tmp, ignore_errors=True)
            else:
                tmp.unlink(missing_ok=True)
    if directory.is_dir() and ((directory / SUMMARY).exists() or (directory / MULTIRUN).exists()):
        write_sweep_summary(directory)
    return marked


def _store_root(directory: Path) -> Path | None:
    """The store a run, a sweep or a sweep's job lies in (the nearest of it and its three parents that holds
    the stage cache), or None."""
    return next((d for d in [directory, *list(directory.parents)[:3]] if (d / STAGES).is_dir()), None)


def _state(run_dir: Path) -> str:
    """"ended": run.json says "incomplete" and the process writing it has ended (this process counts as
    ended: it is handling the Ctrl-C); "running": its process may still write it; "done": run.json is
    no longer "incomplete" (or unreadable): not this function's to change."""
    try:
        info = read_run(run_dir)
    except DamagedRecord:
        return "done"
    if info.get("status") != "incomplete":
        return "done"
    process = info.get("process") or {}
    mine = process.get("pid") == os.getpid() and process.get("host") == socket.gethostname()
    return "ended" if mine or process_alive(process) is False else "running"


def check(root: Path) -> list[Finding]:
    """Walk a store and list every damaged or inconsistent record: unreadable or partial run.json,
    missing or unreadable tables, tables that do not match run.json's hashes, runs stuck
    "incomplete" whose process is gone, temporary files of dead writers, sweep summaries that
    disagree with their jobs, index entries naming no intact run."""
    root = Path(root)
    findings = []
    runs, damaged = read_runs(root, warn_damaged=False)
    findings += [Finding("damaged", err.path, err.reason, err.path.parent) for err in damaged]
    for run_dir, info in runs:
        if info.get("status") == "complete":
            findings += [Finding("damaged", run_dir / p.split(":")[0], p.split(": ", 1)[-1], run_dir)
                         for p in run_damage(run_dir, info)]
        elif info.get("status") == "incomplete" and process_alive(info.get("process")) is False:
            findings.append(Finding("stuck", run_dir, f"incomplete and its process {info['process']['pid']} "
                                                      "is gone (killed)", run_dir))
    quarantined = root / QUARANTINE
    for top, dirs, files in os.walk(root):
        if Path(top) == quarantined:
            dirs[:] = []
            continue
        for name in files:
            pid = _tmp_pid(name)
            if pid is not None and process_alive({"pid": pid, "host": socket.gethostname()}) is False:
                findings.append(Finding("temporary", Path(top) / name, "left by a write that did not finish"))
        if SUMMARY in files or MULTIRUN in files:
            findings += _check_summary(Path(top), [(d, i) for d, i in runs if d.parent == Path(top)],
                                       [e for e in damaged if e.path.parent.parent == Path(top)])
    if (root / INDEX).is_dir():
        findings += _check_index(root)
    return findings


def _check_summary(sweep_dir: Path, jobs: list[tuple[Path, dict]], damaged: list) -> list[Finding]:
    """A sweep's summary against its jobs' run.json files (id and status of each)."""
    import pyarrow as pa
    path = sweep_dir / SUMMARY
    want = {(str(info.get("id")), str(info.get("status"))) for _, info in jobs}
    try:
        table = pd.read_parquet(path, columns=["id", "status"])
    except FileNotFoundError:
        return [Finding("summary", path, "missing", None)] if jobs or damaged else []
    except (OSError, pa.ArrowException, ValueError, KeyError) as err:
        return [Finding("summary", path, f"unreadable ({one_line(err)})")]
    have = {(str(i), str(s)) for i, s in zip(table["id"], table["status"], strict=True)}
    if have == want:
        return []
    missing, extra = sorted(want - have), sorted(have - want)
    reason = "disagrees with its jobs" + (f": missing {[i for i, _ in missing]}" if missing else "") \
        + (f", not in the jobs' run.json {[i for i, _ in extra]}" if extra else "")
    return [Finding("summary", path, reason)]


def _check_index(root: Path) -> list[Finding]:
    findings = []
    for path in sorted((root / INDEX).glob("*.json")):
        try:
            entry = json.loads(path.read_bytes())
            run_dir = (root / entry["dir"]).resolve()
            if not run_dir.is_relative_to(root.resolve()):
                raise ValueError("names a directory outside the store")
            info = read_run(run_dir)
            if index_key(info.get("config_hash"), _version(info)) != path.stem or run_damage(run_dir, info):
                raise ValueError(f"names {entry['dir']}, not an intact run of its config hash and code version")
        except DamagedRecord as err:
            findings.append(Finding("index", path, f"names a damaged run ({err})"))
        except (OSError, ValueError, KeyError, TypeError) as err:
            findings.append(Finding("index", path, f"unusable index entry ({one_line(err)})"))
    return findings


def quarantine(root: Path, findings: list[Finding]) -> tuple[list[tuple[Path, Path]], list[Path]]:
    """Move every damaged record (run directory, or a leftover temporary file) into
    `<root>/quarantine/`, keeping its path below root (nothing is deleted); rebuild the summaries of
    the sweeps concerned and the reuse index. Returns the moves and the rebuilt summaries."""
    root = Path(root)
    moves, sweeps = [], set()
    targets = {f.record for f in findings if f.record is not None} \
        | {f.path for f in findings if f.kind == "temporary"}
    for source in sorted(targets):
        if not source.exists() or source == root:
            continue
        target = root / QUARANTINE / source.relative_to(root)
        n = 1
        while target.exists():                           # quarantined before: keep both
            target, n = target.with_name(f"{source.name}.{n}"), n + 1
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(str(source), str(target))
        moves.append((source, target))
        if (source.parent / SUMMARY).exists() or (source.parent / MULTIRUN).exists():
            sweeps.add(source.parent)
    sweeps |= {f.path.parent for f in findings if f.kind == "summary"}
    rebuilt = [write_sweep_summary(s) for s in sorted(sweeps) if s.is_dir()]
    if (root / INDEX).is_dir() or any(f.kind == "index" for f in findings):
        rebuild_index(root)
    return moves, rebuilt
