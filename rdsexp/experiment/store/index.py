"""The reuse index: one small file per (config hash, code version) naming one complete run.

A sweep job finds a run to reuse by reading one index entry and checking that run's files, whatever
the number of stored runs. The index is derived data: an entry that is unreadable or names a
damaged run is ignored (the job runs again and overwrites it), and `rdsexp-runs check --quarantine`
rebuilds it from the runs on disk.
"""
from __future__ import annotations

import hashlib
import json
import warnings
from pathlib import Path

from ...errors import DamagedRecord, RecordWarning, WriteError, one_line
from . import files
from .layout import INDEX, INDEX_BUILT
from .run import read_run, read_runs, run_damage, warn


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
    files.write_json(store / INDEX / f"{index_key(info['config_hash'], _version(info))}.json",
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
    files.atomic_write_bytes(index / INDEX_BUILT, f"{len(entries)}\n".encode())
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
            warn(DamagedRecord(path, f"unusable index entry ({one_line(err)})"), "ignored",
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
    except (OSError, WriteError) as err:
        warnings.warn(f"cannot index the run store {store}: {err}", RecordWarning, stacklevel=3)
        return False


