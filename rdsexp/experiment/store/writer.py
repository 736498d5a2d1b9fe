"""Writing one run directory: run.json from "incomplete" to its final status, tables, recording.

run.json says "incomplete" (with the process that writes it) from before the first compute until
every table and the recording are in place, so that a killed run can be told apart; every file is
written atomically and stored read-only with its hashes (`files`).
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import pandas as pd

from ...errors import DamagedRecord, WriteError
from . import files, provenance
from .layout import DIFF, RECORDING, RUN_JSON, table_file
from .run import read_run

log = logging.getLogger("rdsexp")


class RunWriter:
    """The writer of the run directory `dir` (created by Hydra before the run starts)."""

    def __init__(self, directory: Path):
        self.dir = Path(directory)

    def start(self, info: dict, diff: str = "") -> None:
        """The uncommitted diff (when the working tree was dirty) and run.json as "incomplete"."""
        if diff:
            files.atomic_write_bytes(self.dir / DIFF, diff.encode())
        files.write_json(self.dir / RUN_JSON, info)

    def sink(self) -> files.ParquetSink:
        """A sink that streams tables chunk by chunk into the run directory."""
        return files.ParquetSink(self.dir)

    def store_tables(self, tables: dict[str, pd.DataFrame]) -> dict:
        """Store whole tables read-only; {name: run.json entry}."""
        return {name: files.store_table(self.dir / table_file(name), table) for name, table in tables.items()}

    def store_recording(self, write: Callable[[Path], bool], name: str = RECORDING) -> dict | None:
        """The recording (or another file of the run, `name`: its figure): `write(tmp)` writes it at a temporary
        path and says whether it did (Rerun may be disabled); it is then stored read-only. Returns its run.json
        entry, or None."""
        tmp = files.tmp_name(self.dir / name)
        try:
            written = write(tmp)
        except OSError as err:
            tmp.unlink(missing_ok=True)
            raise WriteError(self.dir / name, err) from err
        return files.store_file(tmp, self.dir / name) if written else None

    def finish(self, info: dict) -> dict:
        """The final run.json."""
        files.write_json(self.dir / RUN_JSON, info)
        return info

    def reuse(self, previous: Path, info: dict, amend=None) -> dict:
        """Record this run as a copy of the complete run `previous` (files hard-linked where possible);
        amend(info) adds to its run.json before it is written."""
        previous = Path(previous)
        old = read_run(previous)
        for name in [meta["file"] for meta in old["tables"].values()] + [RECORDING, DIFF]:
            if (previous / name).exists() and not (self.dir / name).exists():
                files.link_or_copy(previous / name, self.dir / name)
        log.info("reused the complete run %s (same config hash and code version)", old["id"])
        info.update(status="complete", finished=provenance.now(), reused_from=old["id"],
                    **{k: old[k] for k in ("summary", "tables", "recording", "timings", "seconds") if k in old})
        if amend is not None:
            amend(info)
        return self.finish(info)

    def fail(self, status: str, message: str, trace: str | None = None, fallback: dict | None = None) -> dict:
        """Record a run that could not finish, keeping whatever provenance run.json already had
        (else `fallback`), where run.json can still be written; returns the run.json content."""
        try:
            info = read_run(self.dir)
        except DamagedRecord:
            info = {"id": self.dir.name, "created": provenance.now(), **(fallback or {})}
        info.update(status=status, error=message, traceback=trace, finished=provenance.now())
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            files.write_json(self.dir / RUN_JSON, info)
        except (OSError, WriteError) as err:
            log.error("cannot record status %s in %s: %s", status, self.dir / RUN_JSON, err)
        return info
