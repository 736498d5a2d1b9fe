"""The one wrapper every stage of a run goes through: timing, the stage cache, errors and progress.

`Stages.timed(name)` times a block into `timings[name]` and rdsexp.log and turns an unexpected exception
into a StageError naming the stage; `cached` and `streamed` take a stage's value from the stage cache
(store.stages.StageCache) when it holds a value computed from the same inputs; `progress` is the stage's bar.
"""
from __future__ import annotations

import logging
import sys
import time
from contextlib import contextmanager

import pandas as pd
from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from ...errors import ConfigError, StageError, WriteError

log = logging.getLogger("rdsexp")
_ANNOUNCE = {"on": False}       # `announce_stages`: the command line's stage lines


def announce_stages(on: bool) -> None:
    """Print a line per stage of a run (`Stages.timed`'s outermost ones) with its seconds on stderr: what the command
    line does where stderr is no terminal (a log file, a CI job, a sweep's worker), which has no progress bar."""
    _ANNOUNCE["on"] = on


@contextmanager
def timed(timings: dict, stage: str):
    """Time the block into timings[stage] (added to a previous block of the same stage: the loops of each look) and
    log the stage with its seconds (rdsexp.log); an unexpected exception inside becomes a StageError naming the
    innermost stage."""
    start = time.perf_counter()
    log.info("%s ...", stage)
    try:
        yield
    except (StageError, WriteError, ConfigError):   # named by an inner stage, or not a stage's failure
        raise
    except Exception as err:
        raise StageError(stage, err) from err
    seconds = time.perf_counter() - start
    timings[stage] = round(timings.get(stage, 0.0) + seconds, 4)      # a stage of every look adds up
    log.info("%s done in %.3f s", stage, seconds)


class Stages:
    """The one wrapper every stage of a run goes through (docs/design.md: the two levels of reuse).

    `timed(name)`: the stage's seconds into `timings[name]` and rdsexp.log; an unexpected exception
    inside becomes a StageError naming the innermost stage. `cached(name, compute, **inputs)`: a
    stage computed from exactly `inputs` (numerics objects, arrays, seeds: their digest is the key)
    is taken from the stage cache when it holds that key (this process's memory, then the store's
    entries), else computed and stored there; `streamed` is the same for a stage whose value is a
    sequence of parts (a loop's chunks), stored part by part as they are computed.

    cache: a store.stages.StageCache (a store's, or `StageCache.in_process()`), or None: every stage
    is computed (`rdsexp-runs verify`)."""

    def __init__(self, cache=None):
        self.cache = cache
        self.timings: dict = {}
        self._open = 0                  # stages open now (a stage inside another is not announced)

    @contextmanager
    def timed(self, name: str):
        start, self._open = time.perf_counter(), self._open + 1
        try:
            with timed(self.timings, name):
                yield
        finally:
            self._open -= 1
        if _ANNOUNCE["on"] and not self._open:
            print(f"rdsexp: {name.replace('_', ' ')} done in {time.perf_counter() - start:.1f} s", file=sys.stderr,
                  flush=True)

    @staticmethod
    @contextmanager
    def progress(desc: str, total: int):
        """A progress bar of `total` steps (silent when not on a terminal), yielding its update(steps, more=0):
        `more` steps not counted in `total` (work the stage finds it must do) are added to it. Console log lines go
        through the bar (`console_to_tqdm`) rather than breaking it."""
        with tqdm(total=total, desc=desc, disable=None, leave=False, file=sys.stderr) as bar, console_to_tqdm():
            def update(steps: int, more: int = 0):
                if more:
                    bar.total += more
                    bar.refresh()
                bar.update(steps)
            yield update

    def cached(self, name: str, compute, *, label: str | None = None, **inputs) -> tuple[object, bool]:
        """(the stage's value, whether it was reused rather than computed in this run)."""
        key, value = self._stored(name, label, inputs, parts=False)
        if value is not None:
            return value, True
        value = compute()
        if key is not None:
            self.cache.save(name, key, value)
        return value, False

    def streamed(self, name: str, compute, *, label: str | None = None, **inputs):
        """(an iterator of the stage's parts, whether they are reused); computed parts are stored as they
        are consumed, the entry committed when the last one is, dropped if the consumer stops early."""
        key, stored = self._stored(name, label, inputs, parts=True)
        if stored is not None:
            return stored, True
        return (compute() if key is None else self._storing(self.cache.writer(name, key), compute())), False

    def _stored(self, name: str, label: str | None, inputs: dict, parts: bool) -> tuple[str | None, object]:
        """(the stage's key, its stored value or parts, None where the cache has none); (None, None) without a
        cache."""
        if self.cache is None:
            return None, None
        key = self.cache.key(name, **inputs)
        load = self.cache.load_parts if parts else self.cache.load
        return key, load(name, key, label or name)

    @staticmethod
    def _storing(writer, parts):
        try:
            for part in parts:
                writer.add(part)
                yield part
        except BaseException:         # an error, Ctrl-C or a consumer that closed the iterator
            writer.abort()
            raise
        writer.commit()


@contextmanager
def console_to_tqdm():
    """Console log records through tqdm.write (they do not break a progress bar), at the console
    handler's own level: tqdm's handler takes every level, which would put INFO lines on the terminal."""
    console = [h for h in logging.root.handlers
               if isinstance(h, logging.StreamHandler) and not isinstance(h, logging.FileHandler)]
    before = list(logging.root.handlers)
    with logging_redirect_tqdm():
        for handler in logging.root.handlers:
            if handler not in before and console:
                handler.setLevel(console[0].level)
        yield


class MemorySink:
    """Collects the streamed tables' rows in memory; `tables()` gives them whole (tests, tracking off)."""

    def __init__(self):
        self.parts: dict[str, list[pd.DataFrame]] = {}

    def append(self, name: str, rows: pd.DataFrame) -> None:
        self.parts.setdefault(name, []).append(rows)

    def tables(self) -> dict[str, pd.DataFrame]:
        return {name: pd.concat(parts, ignore_index=True) for name, parts in self.parts.items()}
