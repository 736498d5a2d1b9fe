"""The run store: reading it safely, checking it, quarantining damage, and the reuse index.

A store is the directory named by the config key `store` (default `outputs/`): run directories
`runs/<id>/` and `sweeps/<id>/<job>/` (see `records`), each sweep's `summary.parquet`, the reuse
index `index/` and `quarantine/`. Stores live for months on shared file systems where partial
files, full disks and copies from other machines happen, so every reader of a store

- turns a run.json it cannot read, or a table that is missing, unreadable or not what run.json
  hashed, into a `DamagedRecord` (path and reason, one line),
- skips that record with one warning line on stderr and goes on with the rest.

The reuse index (`index/<key>.json`, key from the config hash and code version) names one complete
run per (config hash, code version): a sweep job finds a run to reuse by reading one small file and
checking that run's files, whatever the number of stored runs. It is derived data: an entry that
is unreadable or names a damaged run is ignored (the job runs again and overwrites it), and
`rdsexp-runs check --quarantine` rebuilds it from the runs on disk.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import socket
import sys
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from . import records

INDEX = "index"
QUARANTINE = "quarantine"
INDEX_BUILT = ".built"              # marker: the index was built from a full scan of the store
REQUIRED = ("id", "status")          # what every run.json of every rdsexp version has
# fields readers use, with the type they expect (older records may lack them, not change their type)
FIELDS = {"summary": dict, "tables": dict, "code": dict, "seed": dict, "sweep": (dict, type(None)),
          "overrides": list, "recording": (dict, type(None))}


class DamagedRecord(Exception):
    """A stored record that cannot be read as written (one line: path and reason)."""

    def __init__(self, path: Path, reason: str):
        super().__init__(f"{path}: {reason}")
        self.path, self.reason = Path(path), reason


def warn(err: DamagedRecord, action: str = "skipped", then: str = "") -> None:
    """The one warning line a reader of the store prints for a record it skips."""
    print(f"rdsexp: warning: {action} {err.path}: {err.reason}{then}", file=sys.stderr)


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0] if text else ''}".rstrip(": ")


# --- reading records

def read_run(run_dir: Path) -> dict:
    """The run.json of run_dir; DamagedRecord if it is missing, unreadable, partial or not an rdsexp
    run record (no id or status, or a field readers use of another type)."""
    path = Path(run_dir) / "run.json"
    try:
        text = path.read_bytes()
    except FileNotFoundError:
        raise DamagedRecord(path, "missing") from None
    except OSError as err:
        raise DamagedRecord(path, f"unreadable ({err.strerror or err})") from None
    if not text.strip():
        raise DamagedRecord(path, "empty")
    try:
        info = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise DamagedRecord(path, f"truncated or not JSON ({err})") from None
    if not isinstance(info, dict) or any(k not in info for k in REQUIRED):
        raise DamagedRecord(path, f"not an rdsexp run record (no {' or '.join(REQUIRED)})")
    for key, kind in FIELDS.items():
        if key in info and not isinstance(info[key], kind):
            raise DamagedRecord(path, f"not an rdsexp run record ({key} is a {type(info[key]).__name__})")
    return info


def _entries(info: dict) -> list:
    """run.json's file entries: every table, and the recording when it has one."""
    return list((info.get("tables") or {}).values()) + ([info["recording"]] if info.get("recording") else [])


def run_damage(run_dir: Path, info: dict) -> list[str]:
    """What is wrong with the files of a complete run, one line each (file: reason): missing,
    unreadable or modified tables and recording, missing .hydra/config.yaml; [] when intact.

    A file recorded with its bytes' sha256 is checked by hashing the bytes; older records (content
    hash only) by reading the parquet table and hashing its content."""
    import pyarrow as pa
    run_dir = Path(run_dir)
    problems = []
    for meta in _entries(info):
        if not isinstance(meta, dict) or not isinstance(meta.get("file"), str):
            problems.append(f"run.json: malformed file entry {meta!r}"[:200])
            continue
        path = run_dir / meta["file"]
        try:
            if meta.get("file_sha256"):
                if records.file_hash(path) == meta["file_sha256"]:
                    continue
                if path.suffix == ".parquet":
                    pd.read_parquet(path)           # unreadable (truncated), or readable but modified?
                problems.append(f"{meta['file']}: modified after the run (does not match the hash in run.json)")
            elif path.suffix == ".parquet" and records.table_hash(pd.read_parquet(path)) != meta.get("sha256"):
                problems.append(f"{meta['file']}: modified after the run (does not match the hash in run.json)")
        except FileNotFoundError:
            problems.append(f"{meta['file']}: missing")
        except (OSError, pa.ArrowException, ValueError) as err:
            problems.append(f"{meta['file']}: unreadable ({_one_line(err)})")
    if not (run_dir / ".hydra" / "config.yaml").is_file():
        problems.append(".hydra/config.yaml: missing")
    return problems


def read_table(run_dir: Path, info: dict, name: str, check_hash: bool = True) -> pd.DataFrame:
    """A stored table, checked against run.json's content hash; DamagedRecord (file, reason) if it
    is missing, unreadable or (with `check_hash`) modified after the run."""
    import pyarrow as pa
    meta = (info.get("tables") or {}).get(name)
    if not isinstance(meta, dict) or not isinstance(meta.get("file"), str):
        raise DamagedRecord(Path(run_dir) / f"{name}.parquet", "not in run.json")
    path = Path(run_dir) / meta["file"]
    try:
        table = pd.read_parquet(path)
    except FileNotFoundError:
        raise DamagedRecord(path, "missing") from None
    except (OSError, pa.ArrowException, ValueError) as err:
        raise DamagedRecord(path, f"unreadable ({_one_line(err)})") from None
    if check_hash and meta.get("sha256") and records.table_hash(table) != meta["sha256"]:
        raise DamagedRecord(path, "modified after the run (does not match the hash in run.json)")
    return table


def run_json_paths(root: Path) -> list[Path]:
    """Every run.json under root, except under the store's quarantine/ and index/."""
    root = Path(root)
    found = []
    for top, dirs, files in os.walk(root):
        if Path(top) == root:
            dirs[:] = [d for d in dirs if d not in (QUARANTINE, INDEX)]
        dirs.sort()
        if "run.json" in files or "run.json" in dirs:
            found.append(Path(top) / "run.json")
            dirs[:] = [d for d in dirs if d != "run.json"]
    return found


def read_runs(root: Path, warn_damaged: bool = True) -> tuple[list[tuple[Path, dict]], list[DamagedRecord]]:
    """(run directory, run.json) of every readable run under root, oldest first, and the damaged
    run.json files (each named in one warning line unless warn_damaged is False)."""
    runs, damaged = [], []
    for path in run_json_paths(root):
        try:
            runs.append((path.parent, read_run(path.parent)))
        except DamagedRecord as err:
            damaged.append(err)
            if warn_damaged:
                warn(err)
    runs.sort(key=lambda run: str(run[1].get("created") or ""))
    return runs, damaged


def intact_runs(root: Path) -> list[tuple[Path, dict]]:
    """Complete runs under root whose run.json and files are intact (the report reads these);
    every other damaged record is named in one warning line."""
    runs = []
    for run_dir, info in read_runs(root)[0]:
        if info.get("status") == "complete":
            problems = run_damage(run_dir, info)
            if problems:
                warn(DamagedRecord(run_dir, "; ".join(problems)))
                continue
        runs.append((run_dir, info))
    return runs


# --- the reuse index

def _version(info: dict) -> str | None:
    return (info.get("code") or {}).get("version")


def index_key(config_hash: str, version: str) -> str:
    return hashlib.sha256(f"{config_hash}\n{version}".encode()).hexdigest()[:32]


def _reusable(info: dict) -> bool:
    return info.get("status") == "complete" and not info.get("reused_from") and bool(info.get("config_hash")) \
        and bool(_version(info))


def index_add(store: Path, run_dir: Path, info: dict) -> None:
    """Point the index entry of this run's config hash and code version at run_dir (a complete,
    not reused run inside the store; runs outside the store are not indexed)."""
    store, run_dir = Path(store).resolve(), Path(run_dir).resolve()
    if not run_dir.is_relative_to(store) or not _reusable(info):
        return
    (store / INDEX).mkdir(parents=True, exist_ok=True)
    records.write_json(store / INDEX / f"{index_key(info['config_hash'], _version(info))}.json",
                       {"dir": run_dir.relative_to(store).as_posix(), "id": info.get("id"),
                        "config_hash": info["config_hash"], "version": _version(info)})


def rebuild_index(store: Path) -> int:
    """Rebuild the index from every intact, complete, not reused run in the store (the oldest run
    of each config hash and code version wins); returns the number of entries."""
    store = Path(store)
    entries = {}
    for run_dir, info in read_runs(store, warn_damaged=False)[0]:
        key = index_key(info.get("config_hash"), _version(info)) if _reusable(info) else None
        if key is not None and key not in entries and not run_damage(run_dir, info):
            entries[key] = (run_dir, info)
    index = store / INDEX
    index.mkdir(parents=True, exist_ok=True)
    for path in index.glob("*.json"):
        if path.stem not in entries:
            path.unlink(missing_ok=True)
    for run_dir, info in entries.values():
        index_add(store, run_dir, info)
    records.atomic_write_bytes(index / INDEX_BUILT, f"{len(entries)}\n".encode())
    return len(entries)


def find_reusable(store: Path, config_hash: str, version: str) -> Path | None:
    """The complete, intact run of this config hash and code version the store's index names, or
    None (then the job runs). Reads one index entry and that run: the cost does not grow with the
    number of stored runs. A store without an index (written before rdsexp kept one), or with an
    unusable entry, is indexed again from its runs. A damaged run is never returned: it is named
    in one warning line and the job runs again."""
    store = Path(store)
    if not store.is_dir():
        return None
    if not (store / INDEX / INDEX_BUILT).exists():
        _rebuild_or_warn(store)
    for attempt in range(2):
        path = store / INDEX / f"{index_key(config_hash, version)}.json"
        try:
            entry = json.loads(path.read_bytes())
            run_dir = (store / entry["dir"]).resolve()
            if not run_dir.is_relative_to(store.resolve()):
                raise ValueError(f"names {run_dir}, outside the store")
            break
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, TypeError) as err:
            warn(DamagedRecord(path, f"unusable index entry ({_one_line(err)})"), "ignored",
                 "; indexing the store again" if attempt == 0 else "")
            if attempt == 1 or not _rebuild_or_warn(store):
                return None
    try:
        info = read_run(run_dir)
        if not (_reusable(info) and info.get("config_hash") == config_hash and _version(info) == version):
            return None                                   # stale entry: the job runs and replaces it
        problems = run_damage(run_dir, info)
        if problems:
            raise DamagedRecord(run_dir, "; ".join(problems))
    except DamagedRecord as err:
        warn(err, "not reusing", "; the job runs again")
        return None
    return run_dir


def _rebuild_or_warn(store: Path) -> bool:
    try:
        rebuild_index(store)
        return True
    except (OSError, records.WriteError) as err:
        print(f"rdsexp: warning: cannot index the run store {store}: {err}", file=sys.stderr)
        return False


# --- the check walk and quarantine

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
    start = records.start_time(process["pid"])
    return start is None or process.get("start") is None or start == process["start"]


def _tmp_pid(name: str) -> int | None:
    parts = name.split(".")
    return int(parts[-2]) if len(parts) >= 4 and parts[-1] == "tmp" and parts[-2].isdigit() else None


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
        if "summary.parquet" in files or "multirun.yaml" in files:
            findings += _check_summary(Path(top), [(d, i) for d, i in runs if d.parent == Path(top)],
                                       [e for e in damaged if e.path.parent.parent == Path(top)])
    if (root / INDEX).is_dir():
        findings += _check_index(root)
    return findings


def _check_summary(sweep_dir: Path, jobs: list[tuple[Path, dict]], damaged: list) -> list[Finding]:
    """A sweep's summary against its jobs' run.json files (id and status of each)."""
    import pyarrow as pa
    path = sweep_dir / "summary.parquet"
    want = {(str(info.get("id")), str(info.get("status"))) for _, info in jobs}
    try:
        table = pd.read_parquet(path, columns=["id", "status"])
    except FileNotFoundError:
        return [Finding("summary", path, "missing", None)] if jobs or damaged else []
    except (OSError, pa.ArrowException, ValueError, KeyError) as err:
        return [Finding("summary", path, f"unreadable ({_one_line(err)})")]
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
            findings.append(Finding("index", path, f"unusable index entry ({_one_line(err)})"))
    return findings


def quarantine(root: Path, findings: list[Finding]) -> tuple[list[tuple[Path, Path]], list[Path]]:
    """Move every damaged record (run directory, or a leftover temporary file) into
    `<root>/quarantine/`, keeping its path below root (nothing is deleted); rebuild the summaries of
    the sweeps concerned and the reuse index. Returns the moves and the rebuilt summaries."""
    from .runs import write_sweep_summary
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
        if (source.parent / "summary.parquet").exists() or (source.parent / "multirun.yaml").exists():
            sweeps.add(source.parent)
    sweeps |= {f.path.parent for f in findings if f.kind == "summary"}
    rebuilt = [write_sweep_summary(s) for s in sorted(sweeps) if s.is_dir()]
    if (root / INDEX).is_dir() or any(f.kind == "index" for f in findings):
        rebuild_index(root)
    return moves, rebuilt
