"""The run store: one capability that owns where runs live and how they are written and read.

`RunStore(root)` is a store (the config key `store`, default `outputs/`; any directory of runs,
such as one sweep, can be read as one): its runs as `Run` handles, the runs table, the reuse index,
sweep summaries, `check` and quarantine. `RunWriter` writes one run directory. Every file and
folder name is in `layout`; the command line, sweeps, recordings and the report are clients.

    layout      every name: runs/, sweeps/, index/, quarantine/, run.json, tables, recording
    files       atomic writes, read-only stored files, content hashes, streamed parquet tables
    provenance  code version, environment, process and time of a run
    record      run.json as typed values (`RunRecord`, `RunSummary`), older records made current
    run         reading run.json and a run's files safely; the `Run` handle
    writer      writing one run directory (`RunWriter`)
    table       the runs table (catalog, search, sweep summaries)
    index       the reuse index
    stages      the stage cache (identification, designs, open loop by the hash of their inputs)
    check       checking a store, quarantine, settling the runs a Ctrl-C stopped
    runstore    `RunStore`, the one entry to all of the above

Names are imported on first use (`layout` alone needs no pandas: the command line starts fast).
"""
import importlib

from . import layout
from .layout import DEFAULT_ROOT, INDEX, QUARANTINE

_NAMES = {"RunStore": "runstore", "Run": "run", "RunWriter": "writer", "Finding": "check", "check": "check",
          "quarantine": "check", "settle_interrupted": "check", "find_reusable": "index", "index_add": "index",
          "index_key": "index",
          "rebuild_index": "index", "read_run": "run", "read_runs": "run", "read_table": "run",
          "run_damage": "run", "intact_runs": "run", "runs_table": "table", "write_sweep_summary": "table",
          "StageCache": "stages", "RunRecord": "record", "RunSummary": "record", "SweepRef": "record",
          "status_of": "run"}


def __getattr__(name: str):
    if name not in _NAMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{_NAMES[name]}", __name__), name)
    globals()[name] = value
    return value


__all__ = ["DEFAULT_ROOT", "INDEX", "QUARANTINE", "layout", *_NAMES]
