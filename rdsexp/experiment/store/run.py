"""Reading a store safely: run.json, a run's files, and the `Run` handle.

Stores live for months on shared file systems where partial files, full disks and copies from
other machines happen, so every reader

- turns a run.json it cannot read, or a table that is missing, unreadable or not what run.json
  hashed, into a `DamagedRecord` (path and reason, one line),
- skips that record with one warning line on stderr and goes on with the rest.
"""
from __future__ import annotations

import copy
import json
import os
import re
import warnings
from functools import cached_property
from pathlib import Path

import pandas as pd

from ...errors import DamagedRecord, RecordWarning, one_line
from . import files
from .layout import HYDRA_CONFIG, INDEX, QUARANTINE, RUN_JSON, STAGES, table_file
from .record import RunRecord

REQUIRED = ("id", "status")          # what every run.json of every rdsexp version has
# fields readers use, with the type they expect (older records may lack them, not change their type)
FIELDS = {"summary": dict, "tables": dict, "code": dict, "seed": dict, "sweep": (dict, type(None)),
          "overrides": list, "recording": (dict, type(None))}


def warn(err: DamagedRecord, action: str = "skipped", then: str = "") -> None:
    """The one RecordWarning a reader of the store gives for a record it skips."""
    warnings.warn(f"{action} {err.path}: {err.reason}{then}", RecordWarning, stacklevel=3)


# --- reading records

def read_run(run_dir: Path) -> dict:
    """The run.json of run_dir; DamagedRecord if it is missing, unreadable, partial or not an rdsexp
    run record (no id or status, or a field readers use of another type)."""
    path = Path(run_dir) / RUN_JSON
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


def status_of(run_dir: Path) -> str | None:
    """run.json's status in run_dir (a run being written, a job of a sweep being watched); None when there
    is no readable run.json."""
    try:
        return read_run(run_dir)["status"]
    except DamagedRecord:
        return None


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
                if files.stored_file_hash(path) == meta["file_sha256"]:
                    continue
                if path.suffix == ".parquet":
                    pd.read_parquet(path)           # unreadable (truncated), or readable but modified?
                problems.append(f"{meta['file']}: modified after the run (does not match the hash in run.json)")
            elif path.suffix == ".parquet" and files.table_hash(pd.read_parquet(path)) != meta.get("sha256"):
                problems.append(f"{meta['file']}: modified after the run (does not match the hash in run.json)")
        except FileNotFoundError:
            problems.append(f"{meta['file']}: missing")
        except (OSError, pa.ArrowException, ValueError) as err:
            problems.append(f"{meta['file']}: unreadable ({one_line(err)})")
    if not (run_dir / HYDRA_CONFIG).is_file():
        problems.append(f"{HYDRA_CONFIG}: missing")
    return problems


def read_table(run_dir: Path, info: dict, name: str, check_hash: bool = True) -> pd.DataFrame:
    """A stored table, checked against run.json's content hash; DamagedRecord (file, reason) if it
    is missing, unreadable or (with `check_hash`) modified after the run."""
    import pyarrow as pa
    meta = (info.get("tables") or {}).get(name)
    if not isinstance(meta, dict) or not isinstance(meta.get("file"), str):
        raise DamagedRecord(Path(run_dir) / table_file(name), "not in run.json")
    path = Path(run_dir) / meta["file"]
    try:
        table = pd.read_parquet(path)
    except FileNotFoundError:
        raise DamagedRecord(path, "missing") from None
    except (OSError, pa.ArrowException, ValueError) as err:
        raise DamagedRecord(path, f"unreadable ({one_line(err)})") from None
    if not check_hash or not meta.get("sha256"):
        return table
    # the file's bytes as recorded (hashed once per process and file: a report's `run_damage` check of the
    # runs it selects hashed them already) are its content as recorded; else the content hash decides (a
    # record without the file's hash). Either matching is an intact table, as before: a record written
    # before NaNs were hashed as one can disagree on the content of an intact file
    if not (meta.get("file_sha256") and files.stored_file_hash(path) == meta["file_sha256"]) \
            and files.table_hash(table) != meta["sha256"]:
        raise DamagedRecord(path, "modified after the run (does not match the hash in run.json)")
    return table


def run_json_paths(root: Path) -> list[Path]:
    """Every run.json under root, except under the store's quarantine/, index/ and stages/."""
    root = Path(root)
    found = []
    for top, dirs, names in os.walk(root):
        if Path(top) == root:
            dirs[:] = [d for d in dirs if d not in (QUARANTINE, INDEX, STAGES)]
        dirs.sort()
        if RUN_JSON in names or RUN_JSON in dirs:
            found.append(Path(top) / RUN_JSON)
            dirs[:] = [d for d in dirs if d != RUN_JSON]
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


MATRIX = "<not a scalar>"           # stands for a nested list while a config is resolved
_CONFIGS: dict[tuple, dict] = {}    # scalar_config by (path, size, mtime): a stored config never changes


def scalar_config(run_dir: Path) -> dict:
    """The run's composed config (.hydra/config.yaml), resolved, with every list that is not a flat
    list of at most 8 scalars replaced by MATRIX; {} without the file.

    The YAML is parsed as OmegaConf parses it (on libyaml), its matrices replaced before OmegaConf
    resolves the interpolations: building OmegaConf nodes for every matrix entry would take most of
    the time of `rdsexp-runs list` and of a report. Cached per file."""
    import yaml
    from omegaconf import OmegaConf
    path = Path(run_dir) / HYDRA_CONFIG
    try:
        stat = path.stat()
    except FileNotFoundError:
        return {}
    key = (str(path.resolve()), stat.st_size, stat.st_mtime_ns)
    if key not in _CONFIGS:
        text = path.read_text()
        node = scalars_only(yaml.load(text, Loader=_yaml_loader()) or {})
        if "${" in text and not _resolve_selects(node):
            cfg = OmegaConf.create(node)
            try:
                node = OmegaConf.to_container(cfg, resolve=True)
            except Exception:     # noqa: BLE001 -- an interpolation this version cannot resolve: the raw values
                node = OmegaConf.to_container(cfg, resolve=False)
        _CONFIGS[key] = node
    return _CONFIGS[key]


_SELECT = re.compile(r"\$\{oc\.select:([A-Za-z_][\w.]*),\s*([\w.+-]+|\[\])\s*\}")
_INT = re.compile(r"[+-]?\d+")
_FLOAT = re.compile(r"[+-]?(\d+\.\d*|\.\d+|\d+)([eE][+-]?\d+)?")
_WORD = re.compile(r"[A-Za-z_]\w*")
_UNKNOWN = object()
_ABSENT = object()


def _default(text: str):
    """An `oc.select` default as OmegaConf's grammar reads it: [], an int, a float, true/false/null in
    any case, a word; _UNKNOWN for anything else."""
    if text == "[]":
        return []
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    if text.lower() == "null":
        return None
    if _INT.fullmatch(text):
        return int(text)
    if _FLOAT.fullmatch(text):
        return float(text)
    return text if _WORD.fullmatch(text) else _UNKNOWN


def _resolve_selects(config: dict) -> bool:
    """Resolve in place the interpolations of a composed config when each is a whole value
    `${oc.select:KEY,DEFAULT}` (what rdsexp's configs use) whose KEY holds no interpolation: the value at
    KEY (absolute), or DEFAULT where KEY is absent or ??? -- as OmegaConf resolves them, in a
    fraction of the time (building OmegaConf nodes is most of reading a config). False, config untouched,
    when any interpolation is of another kind: the caller then resolves through OmegaConf."""
    found: list[tuple[dict, str, str, str]] = []

    def walk(node) -> bool:
        for k, v in node.items():
            if isinstance(v, dict):
                if not walk(v):
                    return False
            elif isinstance(v, str) and "${" in v:
                match = _SELECT.fullmatch(v)
                if match is None:
                    return False
                found.append((node, k, match.group(1), match.group(2)))
            elif isinstance(v, list) and any(isinstance(x, str) and "${" in x for x in v):
                return False
        return True
    if not walk(config):
        return False
    values = []
    for _, _, key, default in found:
        node = config
        for part in key.split("."):
            node = node.get(part, _ABSENT) if isinstance(node, dict) else _ABSENT
        if isinstance(node, str) and "${" in node or (isinstance(node, (dict, list)) and "${" in repr(node)):
            return False                   # a chain of interpolations: OmegaConf's
        value = _default(default) if node is _ABSENT or node == "???" else copy.deepcopy(node)
        if value is _UNKNOWN:
            return False
        values.append(value)
    for (parent, k, _, _), value in zip(found, values):
        parent[k] = value
    return True



def _yaml_loader():
    """OmegaConf's YAML loader (its float and timestamp rules), on libyaml's parser where available."""
    import yaml
    from omegaconf._utils import get_yaml_loader
    reference = get_yaml_loader()
    if not getattr(yaml, "__with_libyaml__", False):
        return reference
    loader = type("Loader", (yaml.CSafeLoader,), {})
    loader.yaml_implicit_resolvers = reference.yaml_implicit_resolvers
    return loader


def scalars_only(node):
    """The config with every list that is not a flat list of at most 8 scalars replaced by MATRIX."""
    if isinstance(node, dict):
        return {k: scalars_only(v) for k, v in node.items()}
    if isinstance(node, list):
        flat = len(node) <= 8 and all(v is None or isinstance(v, (bool, int, float, str)) for v in node)
        return node if flat else MATRIX
    return node


def _has_matrix(node) -> bool:
    return node == MATRIX if not isinstance(node, dict) else any(_has_matrix(v) for v in node.values())


class Run:
    """A stored run directory: its run.json (read safely on construction: DamagedRecord if it cannot be;
    typed as `record`), its composed config and its tables, each checked against run.json's hash on
    first use. `used` collects {table name: sha256} of the tables read, for a figure's lineage.

    The raw run.json is private to the store (`_info`): every other module reads `record`'s fields."""

    def __init__(self, directory: Path, info: dict | None = None):
        self.dir = Path(directory)
        self._info = read_run(self.dir) if info is None else info
        self.used: dict[str, str] = {}

    def __repr__(self) -> str:
        return f"Run({str(self.dir)!r})"

    @cached_property
    def config(self):
        """The composed config (.hydra/config.yaml) as a read-only OmegaConf node, parsed once per Run."""
        from omegaconf import OmegaConf
        cfg = OmegaConf.load(self.dir / HYDRA_CONFIG)
        OmegaConf.set_readonly(cfg, True)
        return cfg

    @cached_property
    def record(self) -> RunRecord:
        """run.json, typed (`record.RunRecord`: older records made current)."""
        return RunRecord.parse(self._info)

    @property
    def id(self) -> str:
        return self._info["id"]

    @property
    def record_file(self) -> Path:
        """The run's run.json (an artifact, a lineage's hash)."""
        return self.dir / RUN_JSON

    @property
    def code(self) -> str | None:
        """The code version the run was made with."""
        return (self._info.get("code") or {}).get("version")

    def get(self, key: str):
        """Config value at a dotted key (None where the config has none); scalars from the cached
        `scalar_config`, matrices from the full config."""
        node = scalar_config(self.dir)
        for part in key.split("."):
            node = node.get(part) if isinstance(node, dict) else None
        if _has_matrix(node):
            from omegaconf import OmegaConf
            node = OmegaConf.select(self.config, key)
            node = OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node
        return node

    @property
    def rate_window(self) -> tuple[int, int]:
        """The closed-loop rate window (k_from, k_to) in steps, as the run resolved it (the config may
        give fractions of the horizon)."""
        k_from, k_to = self._info["summary"]["rate_window"]
        return int(k_from), int(k_to)

    def table(self, name: str, columns: list[str] | None = None, check_hash: bool = True,
              described: bool = False) -> pd.DataFrame:
        """A stored table (optionally some columns). The first read of each table reads it whole and
        checks it against run.json's hash; DamagedRecord if it is missing, unreadable or modified.
        described: with its schema metadata in attrs (the data dictionary's descriptions)."""
        if name in self.used:
            table = pd.read_parquet(self.dir / self._info["tables"][name]["file"], columns=columns)
        else:
            table = read_table(self.dir, self._info, name, check_hash=check_hash)
            if check_hash:
                self.used[name] = self._info["tables"][name].get("sha256")
            table = table if columns is None else table[columns]
        # the schema metadata stays in the file: in attrs, pandas deep-copies it into every derived frame
        # (seconds of every report call)
        if not described:
            table.attrs = {}
        return table

    def file(self, name: str) -> Path | None:
        """The stored file of table `name` (as run.json records it), None when the run has no such table;
        for a reader that takes some columns of a file whose bytes `damage` checked (a table is read with
        `table`)."""
        stored = self.record.tables.get(name)
        return self.dir / stored.file if stored is not None else None

    @property
    def recording_file(self) -> Path | None:
        """The run's recording (.rrd) as run.json records it; None without one."""
        return self.dir / self.record.recording.file if self.record.recording is not None else None

    def shown(self) -> dict:
        """run.json as `rdsexp-runs show` prints it: every entry but the environment, the traceback and the
        params (the config, shown by `diff` and `list --columns`)."""
        return {k: v for k, v in self._info.items() if k not in ("environment", "traceback", "params")}

    def damage(self) -> list[str]:
        """What is wrong with the run's files, one line each; [] when intact (see `run_damage`)."""
        return run_damage(self.dir, self._info)
