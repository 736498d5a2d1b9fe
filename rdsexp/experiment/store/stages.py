"""The stage cache: content-addressed results of pipeline stages, shared by the runs of a store.

    <store>/stages/<stage>/<key>/     one entry: meta.json, then parts 0000.json + 0000.npz, ...

A key is the sha256 of the stage's name, the code version the run records and a canonical digest
(`digest`) of exactly the values the stage computes from (the pipeline names them: numerics
objects, arrays, seeds); equal keys mean equal results, so a run whose stage has the key of a
stored entry loads that entry instead of computing it. meta.json names the stage, the key, the code
version, the run that computed it, the digest of every named input and the sha256 of every part's
files. A part is one Python value (`pack`): its structure in JSON (floats exactly, NaN and inf
included) and its arrays in an uncompressed .npz read without pickle; dataclasses are rebuilt only
from rdsexp's own modules.

In front of the store's entries, this process keeps its own copies of single-value entries (at most
MEMORY_KEPT, the oldest dropped first), by stage and inputs: the jobs of a sweep that run in one process
share their identifications and designs without reading them back from disk, and a cache without a
store (`StageCache.in_process()`: tracking off, tests) has only these.

An entry is written into a temporary directory and renamed into place, so a reader sees a complete
entry or none; when several processes write the same key, the first rename wins and the others
discard theirs (the contents are equal). An entry whose files are missing, unreadable or do not match
meta.json's hashes is never used: the stage is computed again (one warning line) and the entry
replaced. The cache is derived data: a write that fails is a warning, never the end of a run.
"""
from __future__ import annotations

import copy
import dataclasses
import hashlib
import importlib
import io
import json
import logging
import os
import shutil
from collections import OrderedDict
from pathlib import Path

import numpy as np

from .files import file_hash
from .layout import STAGES, stage_entry

log = logging.getLogger("rdsexp")
META = "meta.json"
FORMAT = 1
MEMORY_KEPT = 256
# this process's single-value entries: (stage, digest of the inputs) -> (value, origin), origin the
# (stage cache directory, run) that stored the value there or loaded it from there, None without a store
_MEMORY: OrderedDict[tuple[str, str], tuple[object, tuple[str, str] | None]] = OrderedDict()


# ---------------------------------------------------------------------------------- keys
def digest(value) -> str:
    """sha256 of a canonical encoding of `value`: None, bools, ints, floats (exactly, by their hex
    form), strings, numpy arrays (dtype, shape and bytes; object arrays item by item), dataclasses
    (type and fields), dicts (by sorted keys), lists and tuples, SeedSequences (entropy, spawn key,
    pool size). Anything else raises TypeError: a key never depends on a repr."""
    h = hashlib.sha256()
    _feed(h, value)
    return h.hexdigest()


def _feed(h, value) -> None:
    if value is None:
        h.update(b"N;")
    elif isinstance(value, (bool, np.bool_)):
        h.update(b"B1;" if value else b"B0;")
    elif isinstance(value, (int, np.integer)):
        h.update(f"I{int(value)};".encode())
    elif isinstance(value, (float, np.floating)):
        h.update(f"F{float(value).hex()};".encode())
    elif isinstance(value, (complex, np.complexfloating)):
        h.update(f"C{complex(value).real.hex()},{complex(value).imag.hex()};".encode())
    elif isinstance(value, str):
        data = value.encode()
        h.update(f"S{len(data)}:".encode() + data)
    elif isinstance(value, np.ndarray):
        h.update(f"A{value.dtype.str}{value.shape}:".encode())
        if value.dtype.hasobject:
            for item in value.ravel():
                _feed(h, item)
        else:
            h.update(np.ascontiguousarray(value).tobytes())
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        h.update(f"D{type(value).__module__}.{type(value).__qualname__}:".encode())
        for f in dataclasses.fields(value):
            _feed(h, f.name)
            _feed(h, getattr(value, f.name))
    elif isinstance(value, dict):
        h.update(f"M{len(value)}:".encode())
        for k in sorted(value, key=str):
            _feed(h, str(k))
            _feed(h, value[k])
    elif isinstance(value, (list, tuple)):
        h.update(f"L{len(value)}:".encode())
        for item in value:
            _feed(h, item)
    elif isinstance(value, np.random.SeedSequence):
        h.update(b"Q")
        _feed(h, [value.entropy, list(value.spawn_key), value.pool_size])
    else:
        raise TypeError(f"stage key: cannot digest a {type(value).__module__}.{type(value).__qualname__}")


# ---------------------------------------------------------------------------------- values
def pack(value, arrays: dict):
    """`value` as a JSON tree, its numeric arrays moved to `arrays` (named a0, a1, ...)."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int) and not isinstance(value, bool):
        return value
    if isinstance(value, float):
        return value
    if isinstance(value, complex):
        return {"__complex__": [value.real, value.imag]}
    if isinstance(value, np.generic):
        return {"__scalar__": value.dtype.str, "value": pack(value.item(), arrays)}
    if isinstance(value, np.ndarray):
        if value.dtype.hasobject:
            return {"__objects__": [pack(v, arrays) for v in value.ravel()], "shape": list(value.shape)}
        name = f"a{len(arrays)}"
        arrays[name] = value
        return {"__array__": name}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        cls = type(value)
        return {"__dataclass__": f"{cls.__module__}:{cls.__qualname__}",
                "fields": {f.name: pack(getattr(value, f.name), arrays) for f in dataclasses.fields(value)}}
    if isinstance(value, dict):
        if not all(isinstance(k, str) for k in value):
            raise TypeError("stage cache: dict keys must be strings")
        return {"__dict__": {k: pack(v, arrays) for k, v in value.items()}}
    if isinstance(value, tuple):
        return {"__tuple__": [pack(v, arrays) for v in value]}
    if isinstance(value, list):
        return [pack(v, arrays) for v in value]
    raise TypeError(f"stage cache: cannot store a {type(value).__module__}.{type(value).__qualname__}")


def unpack(tree, arrays):
    """The value `pack` stored (arrays: the part's loaded .npz)."""
    if isinstance(tree, list):
        return [unpack(v, arrays) for v in tree]
    if not isinstance(tree, dict):
        return tree
    if "__array__" in tree:
        return arrays[tree["__array__"]]
    if "__complex__" in tree:
        return complex(*tree["__complex__"])
    if "__scalar__" in tree:
        return np.dtype(tree["__scalar__"]).type(unpack(tree["value"], arrays))
    if "__objects__" in tree:
        out = np.empty(len(tree["__objects__"]), dtype=object)
        out[:] = [unpack(v, arrays) for v in tree["__objects__"]]
        return out.reshape(tree["shape"])
    if "__dataclass__" in tree:
        module, name = tree["__dataclass__"].split(":")
        if module != "rdsexp" and not module.startswith("rdsexp."):
            raise ValueError(f"not an rdsexp type: {tree['__dataclass__']}")
        cls = importlib.import_module(module)
        for part in name.split("."):
            cls = getattr(cls, part)
        if not dataclasses.is_dataclass(cls):
            raise ValueError(f"not a dataclass: {tree['__dataclass__']}")
        fields = {k: unpack(v, arrays) for k, v in tree["fields"].items()}
        init = {f.name for f in dataclasses.fields(cls) if f.init}
        obj = cls(**{k: v for k, v in fields.items() if k in init})
        for k, v in fields.items():          # fields the constructor does not take (none so far)
            if k not in init:
                object.__setattr__(obj, k, v)
        return obj
    if "__tuple__" in tree:
        return tuple(unpack(v, arrays) for v in tree["__tuple__"])
    if "__dict__" in tree:
        return {k: unpack(v, arrays) for k, v in tree["__dict__"].items()}
    raise ValueError(f"unknown node {sorted(tree)}")


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


# ---------------------------------------------------------------------------------- the cache
class StageCache:
    """The stage cache as one run uses it: `key` a stage's inputs, `load` an entry (None on a miss or a
    damaged entry), `save` or `writer` a computed one. root: the store whose `<root>/stages/` holds the
    entries, or None (`in_process`: this process's memory only).

    `reused` ({label: {"stage", "key", "run"}}: what this run loaded and from which run) and `keys`
    ({label: key}: every stage it looked up) go into run.json (`stages_reused`, `stage_keys`)."""

    def __init__(self, root: Path | None, code: str, run: str | None):
        self.dir = Path(root) / STAGES if root is not None else None
        self.code, self.run = str(code), None if run is None else str(run)
        self.reused: dict[str, dict] = {}
        self.keys: dict[str, str] = {}
        self._inputs: dict[str, dict] = {}
        self._memory: dict[str, str] = {}       # key -> the digest of its inputs without the code version

    @classmethod
    def in_process(cls) -> StageCache:
        """A cache of this process's memory only (no store: nothing is written)."""
        return cls(None, "", None)

    def __repr__(self) -> str:
        return f"StageCache({str(self.dir) if self.dir is not None else 'in process'!r})"

    def key(self, stage: str, **inputs) -> str:
        """The key of `stage` computed from `inputs` (each digested; the names are part of the key)."""
        parts = {name: digest(value) for name, value in inputs.items()}
        key = digest({"stage": stage, "code": self.code, "inputs": parts})
        self._inputs[key] = parts
        self._memory[key] = digest({"stage": stage, "inputs": parts})     # one process: one code version
        return key

    def note(self, label: str, stage: str, key: str, run: str | None) -> None:
        """Record a stage `label` looked up under `key`, reused from `run` (None: computed here)."""
        self.keys[label] = key
        if run is not None:
            self.reused[label] = {"stage": stage, "key": key, "run": run}

    def _origin(self, run: str | None) -> tuple[str, str] | None:
        return (str(self.dir), str(run)) if self.dir is not None else None

    def _remember(self, stage: str, key: str, value, run: str | None) -> None:
        """Keep a copy of a single-value entry in this process's memory, the oldest dropped beyond MEMORY_KEPT."""
        slot = (stage, self._memory[key])
        _MEMORY.pop(slot, None)
        if len(_MEMORY) >= MEMORY_KEPT:
            _MEMORY.popitem(last=False)
        _MEMORY[slot] = (copy.deepcopy(value), self._origin(run))

    def _recall(self, stage: str, key: str, label: str):
        """A copy of the entry from this process's memory (None: not there). One that came from this store
        is noted as reused from its run; one computed without this store (or whose entry there is gone) is
        stored in it now."""
        found = _MEMORY.get((stage, self._memory[key]))
        if found is None:
            return None
        value, origin = copy.deepcopy(found[0]), found[1]
        stored = self.dir is not None and (stage_entry(self.dir.parent, stage, key) / META).exists()
        if stored and origin is not None and origin[0] == str(self.dir):
            self.note(label, stage, key, origin[1] if origin[1] != self.run else None)
        else:
            self.note(label, stage, key, None)
            if self.dir is not None:
                self._store(stage, key, value)
                self._remember(stage, key, value, self.run)
        log.info("%s: reused from this process's memory", label)
        return value

    # --- reading
    def load_parts(self, stage: str, key: str, label: str | None = None):
        """The parts of the entry (a list of lazily decoded values: an iterator), or None when there
        is no intact entry. Every file is checked against meta.json before the first value is given."""
        label = label or stage
        entry = stage_entry(self.dir.parent, stage, key) if self.dir is not None else None
        if entry is None or not (entry / META).exists():
            self.note(label, stage, key, None)
            return None
        try:
            meta = json.loads((entry / META).read_text())
            if meta.get("key") != key or meta.get("stage") != stage or meta.get("format") != FORMAT:
                raise ValueError("meta.json names another entry")
            for part in meta["parts"]:          # every file intact before the first value is used
                for suffix in ("json", "npz"):
                    if file_hash(entry / part[suffix]) != part[f"{suffix}_sha256"]:
                        raise ValueError(f"{part[suffix]} does not match its hash in meta.json")
        except (OSError, ValueError, KeyError, TypeError) as err:
            log.warning("stage cache: ignoring the damaged entry %s (%s); computing %s", entry, err, label)
            self._discard(entry)
            self.note(label, stage, key, None)
            return None
        self.note(label, stage, key, str(meta.get("run")))
        log.info("%s: reused from run %s (stage cache %s/%s)", label, meta.get("run"), stage, key[:12])
        return (self._decode(entry, part) for part in meta["parts"])     # one part in memory at a time

    def load(self, stage: str, key: str, label: str | None = None):
        """The value of a single-part entry: from this process's memory, else from the store (then kept
        in memory); None on a miss or a damaged entry."""
        label = label or stage
        value = self._recall(stage, key, label)
        if value is not None or self.dir is None:
            if value is None:
                self.note(label, stage, key, None)
            return value
        parts = self.load_parts(stage, key, label)
        if parts is None:
            return None
        try:
            values = list(parts)
        except (OSError, ValueError, KeyError, TypeError, AttributeError, ImportError) as err:
            log.warning("stage cache: cannot read %s/%s (%s); computing %s", stage, key, err, label)
            self.reused.pop(label, None)
            return None
        if len(values) != 1:
            return None
        self._remember(stage, key, values[0], self.reused[label]["run"])
        return values[0]

    @staticmethod
    def _decode(entry: Path, part: dict):
        blobs = {suffix: (entry / part[suffix]).read_bytes() for suffix in ("json", "npz")}
        for suffix, raw in blobs.items():
            if _sha(raw) != part[f"{suffix}_sha256"]:
                raise ValueError(f"{entry / part[suffix]} changed after it was checked")
        with np.load(io.BytesIO(blobs["npz"]), allow_pickle=False) as npz:
            arrays = {name: npz[name] for name in npz.files}
        return unpack(json.loads(blobs["json"]), arrays)

    # --- writing
    def save(self, stage: str, key: str, value) -> None:
        """Store a single-part entry, in this process's memory and in the store (a failed write: a warning)."""
        self._store(stage, key, value)
        self._remember(stage, key, value, self.run)

    def _store(self, stage: str, key: str, value) -> None:
        if self.dir is not None:
            writer = self.writer(stage, key)
            try:
                writer.add(value)
                writer.commit()
            except BaseException:        # Ctrl-C mid-write (a sweep's worker): no temporary entry left behind
                writer.abort()
                raise

    def writer(self, stage: str, key: str) -> EntryWriter:
        """A writer of the entry's parts, one `add` at a time (a loop's chunks), then `commit` (without a
        store: one that writes nothing; multi-part entries are not kept in memory)."""
        return EntryWriter(self, stage, key)

    def _discard(self, entry: Path) -> None:
        """Remove a damaged entry (derived data), renamed aside first so no reader sees it half gone."""
        aside = entry.with_name(f".{entry.name}.{os.getpid()}.damaged")
        try:
            os.replace(entry, aside)
            shutil.rmtree(aside, ignore_errors=True)
        except OSError:
            pass


class EntryWriter:
    """Writes one entry's parts into a temporary directory; `commit` renames it into place,
    `abort` (or a failed write: a warning) drops it. The directory is made by the first write, inside the
    caller's guard, so that a Ctrl-C between making the writer and using it leaves nothing behind."""

    def __init__(self, cache: StageCache, stage: str, key: str):
        self.cache, self.stage, self.key = cache, stage, key
        self.parts: list[dict] = []
        self.ok = cache.dir is not None
        if not self.ok:
            return
        self.final = stage_entry(cache.dir.parent, stage, key)
        self.tmp = self.final.with_name(f".{key}.{os.getpid()}.tmp")
        self._made = False

    def _make(self) -> None:
        """The temporary directory, made once (OSError to the caller)."""
        if not self._made:
            shutil.rmtree(self.tmp, ignore_errors=True)
            self.tmp.mkdir(parents=True)
            self._made = True

    def _fail(self, err) -> None:
        log.warning("stage cache: %s/%s not stored (%s)", self.stage, self.key[:12], err)
        self.abort()

    def add(self, value) -> None:
        if not self.ok:
            return
        try:
            self._make()
            arrays: dict = {}
            tree = json.dumps(pack(value, arrays), allow_nan=True).encode()
            buffer = io.BytesIO()
            np.savez(buffer, **arrays)
            name = f"{len(self.parts):04d}"
            part = {"json": f"{name}.json", "npz": f"{name}.npz"}
            for suffix, data in (("json", tree), ("npz", buffer.getvalue())):
                (self.tmp / part[suffix]).write_bytes(data)
                part[f"{suffix}_sha256"] = _sha(data)
            self.parts.append(part)
        except (OSError, TypeError, ValueError) as err:
            self._fail(err)

    def commit(self) -> None:
        """Rename the complete entry into place; if another process stored the key first, keep its."""
        if not self.ok:
            return
        meta = {"format": FORMAT, "stage": self.stage, "key": self.key, "code": self.cache.code,
                "run": self.cache.run, "inputs": self.cache._inputs.get(self.key, {}), "parts": self.parts}
        try:
            self._make()
            (self.tmp / META).write_text(json.dumps(meta, indent=1) + "\n")
            os.rename(self.tmp, self.final)
        except OSError as err:
            if self.final.is_dir():              # stored meanwhile by another process: equal content
                self.abort()
                return
            self._fail(err)
            return
        self.ok = False

    def abort(self) -> None:
        if self.cache.dir is not None:
            shutil.rmtree(self.tmp, ignore_errors=True)
        self.ok = False
