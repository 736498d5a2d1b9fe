"""The stage pipeline: a validated Experiment computed into tables and a summary, without touching the file system.

Stages (docs/design.md), one module each, every one through the wrapper `stage.Stages` (timing, the stage
cache, errors, progress) and returning a typed result (`results`):

    identification -> modeling -> uncertainty   identification.py   -> Identified, Uncertainty
    synthesis (designs, fallback, gain choice)  design.py           -> DesignSet
    closed / open loop, noise floor, verdicts   loops.py            -> LoopSummary per loop, JudgedLoops
    online loop                                 online.py           -> OnlineResult
    a data run's validation and loops on model  data.py             -> Validation
    tables, summary                             tables.py, record.py
    the orchestration of both kinds of run      run.py              -> Outcome

Seeds: the identification run uses SeedSequence(seed, spawn_key=(0,)), the closed and open loops SeedSequence(seed,
spawn_key=(1,)) (the same plant samples, as in the paper's Figs. decay_proposed and decay_open), the loop at rest
(2,), the moments' bootstrap [seed, 3], a data run's held-out paths (4,); inside each, path j has its own plant and
EnKF streams.
"""
from .loops import METRIC_COLUMNS, SPAWN_KEYS
from .run import STREAMED, TABLES, Outcome, run_experiment
from .stage import MemorySink, Stages, timed

__all__ = ["METRIC_COLUMNS", "SPAWN_KEYS", "STREAMED", "TABLES", "MemorySink", "Outcome", "Stages", "run_experiment",
           "timed"]
