"""Experiment layer: Hydra config -> validated Experiment -> stage pipeline -> run directory.

config (validation), pipeline (stages -> tables, no I/O), records (run.json, provenance, atomic
writes), recording (Rerun), runs (catalog, verify, check), store (safe reading of the run store, check
and quarantine, reuse index), sweep (Hydra callback), cli (entry point).
The only layer that knows about Hydra, Rerun, parquet and provenance.
"""
