"""`RunStore`: the runs under a root directory, read safely, indexed, summarized and checked."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from . import layout
from .check import Finding, check, quarantine
from .index import find_reusable, index_add, rebuild_index
from .layout import DEFAULT_ROOT
from .record import sweep_name
from .run import Run, intact_runs, read_runs
from .table import runs_table, write_sweep_summary

if TYPE_CHECKING:
    import pandas as pd


class RunStore:
    """The runs under `root`: a store (runs/, sweeps/, index/, quarantine/) or any directory of runs."""

    def __init__(self, root: Path | str = DEFAULT_ROOT):
        self.root = Path(root)

    def __repr__(self) -> str:
        return f"RunStore({str(self.root)!r})"

    # --- reading
    def runs(self, warn: bool = True) -> list[Run]:
        """Every readable run, oldest first; each damaged run.json named in one warning line."""
        return [Run(d, info) for d, info in read_runs(self.root, warn_damaged=warn)[0]]

    def intact(self) -> list[Run]:
        """The runs whose run.json and (when complete) files are intact; the others named in one
        warning line each."""
        return [Run(d, info) for d, info in intact_runs(self.root)]

    def table(self, params: bool = False) -> pd.DataFrame:
        """The runs table: one row per readable run (`table.runs_table`)."""
        return runs_table(read_runs(self.root)[0], params=params)

    def locate(self, run: str) -> Path:
        """A run directory from its path or its id (a directory name under the store, SWEEP/JOB for a
        sweep job); LookupError with one line if there is none. Its run.json is not read."""
        path = Path(run)
        if layout.is_run(path):
            return path
        matches = [r.dir for r in self.runs() if r.id == run or r.dir.name == run]
        if len(matches) != 1:
            raise LookupError(f"{'no' if not matches else 'more than one'} run {run!r} under {self.root}")
        return matches[0]

    def run(self, run: str) -> Run:
        """The `Run` of a path or an id (`locate`); DamagedRecord if its run.json cannot be read."""
        return Run(self.locate(run))

    def locate_sweep(self, sweep: str) -> Path | None:
        """A sweep directory from its path, its directory name, or its config name (the latest sweep of
        that name); None if `sweep` names no sweep."""
        if layout.is_sweep(Path(sweep)):
            return Path(sweep)
        runs = self.runs()
        dirs = [r.dir.parent for r in runs if str(r.id).startswith(f"{sweep}/")]
        if not dirs:            # by name: `+sweep=NAME`'s, or a `-m` sweep's overrides (the name `list` shows)
            names = {}
            for r in runs:
                if isinstance(r._info.get("sweep"), dict) and r.dir.parent not in names:
                    names[r.dir.parent] = r._info["sweep"].get("name") or sweep_name(r.dir.parent)
            dirs = [d for d, name in names.items() if name == sweep]
        return dirs[-1] if dirs else None

    # --- the reuse index
    def find_reusable(self, config_hash: str, version: str) -> Path | None:
        """The intact complete run of this config hash and code version the index names, or None."""
        return find_reusable(self.root, config_hash, version)

    def index(self, run_dir: Path, info: dict) -> None:
        """Index a complete run for reuse (runs outside the store are not indexed)."""
        index_add(self.root, run_dir, info)

    def rebuild_index(self) -> int:
        return rebuild_index(self.root)

    # --- sweeps and maintenance
    @staticmethod
    def write_sweep_summary(sweep_dir: Path) -> Path:
        return write_sweep_summary(sweep_dir)

    def check(self) -> list[Finding]:
        """Every damaged or inconsistent record (`check.check`)."""
        return check(self.root)

    def quarantine(self, findings: list[Finding]):
        """Move the damaged records of `findings` to quarantine/, rebuild summaries and index."""
        return quarantine(self.root, findings)
