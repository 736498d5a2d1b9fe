"""Experiment layer: Hydra config -> validated Experiment -> stage pipeline -> run directory.

From the bottom up (each module imports only those before it; tests/test_package.py checks it):
store (the run store: layout, writing and reading runs, the runs table, reuse index, check),
schema (table metadata), config (one validated object per config group), montecarlo (chunks of
paths, workers), pipeline (stages -> tables, no I/O), summary (a run in words), recording (Rerun),
runner (one run computed and recorded), failures (an exception -> status and exit code), runs
(`rdsexp-runs`: query, diff, verify), sweep (Hydra callback), cli (entry point).
The only layer that knows about Hydra, Rerun, parquet and provenance.
"""
