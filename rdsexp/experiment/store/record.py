"""run.json as typed values: `RunRecord` (one run's record) and `RunSummary` (its key numbers).

A run.json is parsed once, here, at the store's boundary (`Run.record`, `RunStore`); what older
rdsexp versions wrote differently is made current here and nowhere else:

- `seed` was the root seed itself before it became {"root", "spawn_keys", "per_path"};
- `sweep` had no `name` (a `-m` run's name is then the overrides that sweep, from multirun.yaml) and
  no `resumes`;
- `plant_hash`, `command`, `finished`, `reused_from` and `error` may be missing (None).

`RunRecord.raw` keeps the whole run.json as read (the writer's format stays the dict it wrote).
"""
from __future__ import annotations

import functools
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from .layout import MULTIRUN

NAN = float("nan")


@dataclass(frozen=True)
class SweepRef:
    """The sweep a run is a job of: its directory, job number, name (`+sweep=NAME`, or the overrides of a
    `-m` run that sweep) and the interrupted sweep it resumes (None: a first launch)."""

    dir: Path
    job: int | None
    name: str | None
    resumes: str | None = None

    @property
    def id(self) -> str:
        """The sweep's id: its directory's name."""
        return self.dir.name


@dataclass(frozen=True)
class RunSummary(Mapping):
    """run.json's `summary` (keys and meanings: `schema.SUMMARY`, docs/data_dictionary.md): a read-only
    mapping, with the key numbers a catalog reads as typed accessors."""

    values: dict = field(default_factory=dict)

    def __getitem__(self, key: str):
        return self.values[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self.values)

    def __len__(self) -> int:
        return len(self.values)

    @property
    def plant(self) -> str | None:
        return self.values.get("plant")

    @property
    def model(self) -> str | None:
        return self.values.get("model")

    @property
    def gain_method(self) -> str | None:
        return self.values.get("gain_method")

    def verdict(self, loop: str = "closed_loop") -> str | None:
        """The loop's verdict word (stable, unstable, undetermined, failed), None without that loop."""
        return self.values.get(f"{loop}_verdict")

    def rate(self, loop: str = "closed_loop") -> tuple[float, float, float]:
        """(rate, low, high) of the loop's plain rate over its window; NaNs without one."""
        value = self.values.get(f"{loop}_rate")
        return tuple(NAN if v is None else float(v) for v in value) if isinstance(value, list) and len(value) == 3 \
            else (NAN, NAN, NAN)

    def failed_fraction(self, loop: str = "closed_loop") -> float:
        """The fraction of the loop's paths that failed (0 when none did)."""
        return float((self.values.get(f"{loop}_failed") or {}).get("fraction", 0.0))


@dataclass(frozen=True)
class RunRecord:
    """One run.json, typed (`parse`): identity, provenance and outcome; `raw` is the dict as read."""

    id: str
    status: str
    created: str | None
    finished: str | None
    command: str | None
    overrides: tuple[str, ...]
    sweep: SweepRef | None
    config_hash: str | None
    plant_hash: str | None
    data: dict | None                 # a data run's data file: name, sha256, rows, columns (no plant)
    code_version: str | None
    seed: int | None
    reused_from: str | None
    error: str | None
    seconds: float | None
    summary: RunSummary
    raw: dict

    @classmethod
    def parse(cls, info: dict) -> RunRecord:
        """From run.json's content (as `read_run` checked it: id and status present, fields of the types
        readers expect), older records made current (module docstring)."""
        seed = info.get("seed")
        sweep = info.get("sweep")
        return cls(
            id=str(info["id"]), status=str(info["status"]), created=info.get("created"),
            finished=info.get("finished"), command=info.get("command"),
            overrides=tuple(str(o) for o in info.get("overrides") or ()),
            sweep=_sweep(sweep) if isinstance(sweep, dict) and sweep.get("dir") else None,
            config_hash=info.get("config_hash"), plant_hash=info.get("plant_hash") or None,
            data=info.get("data") if isinstance(info.get("data"), dict) else None,
            code_version=(info.get("code") or {}).get("version"),
            seed=seed.get("root") if isinstance(seed, dict) else seed,
            reused_from=info.get("reused_from"), error=info.get("error"), seconds=info.get("seconds"),
            summary=RunSummary(dict(info.get("summary") or {})), raw=info)

    @property
    def complete(self) -> bool:
        return self.status == "complete"


def _sweep(sweep: dict) -> SweepRef:
    job = sweep.get("job")
    return SweepRef(dir=Path(sweep["dir"]), job=job if isinstance(job, int) else None,
                    name=sweep.get("name") or sweep_name(sweep["dir"]), resumes=sweep.get("resumes"))


@functools.lru_cache(maxsize=256)
def sweep_name(sweep_dir: str | None) -> str | None:
    """The name of a sweep launched without `+sweep=NAME`: the overrides of its command line that sweep
    (`enkf.ensemble_size=50,100 seed=range(3)`; all of them if none does), as Hydra wrote them into
    <sweep>/multirun.yaml; None without that file."""
    if not sweep_dir:
        return None
    try:
        config = yaml.safe_load((Path(sweep_dir) / MULTIRUN).read_text())
        task = [str(o) for o in ((config or {}).get("hydra") or {}).get("overrides", {}).get("task") or []
                if not str(o).startswith("+sweep=")]
    except (OSError, yaml.YAMLError, AttributeError):
        return None
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException
    try:
        swept = [o.input_line for o in OverridesParser.create().parse_overrides(task) if o.is_sweep_override()]
    except HydraException:
        swept = []
    return " ".join(swept or task) or None
