"""Provenance of a run: code version (git commit and uncommitted diff), environment, process, time.

run.json records these so that a run can be trusted and re-run: two runs share a code version
exactly when they ran the same code, and a run whose process died is told apart from a running one.
"""
from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
import platform
import socket
import subprocess
import sys
from importlib import metadata
from pathlib import Path

from ... import __version__

PACKAGES = ("rdsexp", "numpy", "scipy", "cvxpy", "clarabel", "pandas", "pyarrow", "hydra-core",
            "omegaconf", "rerun-sdk", "matplotlib", "tqdm")
PACKAGE = Path(__file__).resolve().parents[2]
REPO = PACKAGE.parent          # the repository root when rdsexp runs from a checkout


def config_hash(job_config: dict) -> str:
    """sha256 of the resolved job config (canonical JSON), the identity of what a run computes."""
    return hashlib.sha256(json.dumps(job_config, sort_keys=True, default=str).encode()).hexdigest()


def plant_hash(matrices: dict, xi_spec) -> str:
    """sha256 of the canonical resolved plant: its basis matrices {A, B, C, D: arrays (p+1, rows, cols)} as
    built (C and D filled in where the file leaves them out) and its xi law as the file states it, every number
    as a float (1 and 1.0 are one plant), in canonical JSON: two files that describe one system share it, any
    change of a matrix entry or of the law gives another."""
    def canonical(node):
        if isinstance(node, dict):
            return {str(k): canonical(v) for k, v in node.items()}
        if isinstance(node, (list, tuple)):
            return [canonical(v) for v in node]
        if hasattr(node, "tolist"):
            return canonical(node.tolist())
        return float(node) if isinstance(node, (int, float)) and not isinstance(node, bool) else node
    content = {"matrices": canonical(matrices), "xi": canonical(xi_spec)}
    return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(REPO), *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout if out.returncode == 0 else None


def code_version() -> dict:
    """Git commit of the rdsexp source, dirty flag, the uncommitted diff and a version string.

    version = commit, plus "+" and a hash of the diff when dirty, so two runs share a version
    exactly when they ran the same code (untracked files under outputs/ are ignored by git).
    An installed copy (not a checkout, e.g. `pip install .`) has version "rdsexp==<__version__>".
    """
    top = (_git("rev-parse", "--show-toplevel") or "").strip()
    if not top or Path(top).resolve() != REPO:        # installed: the enclosing repository, if any, is not ours
        return {"commit": None, "dirty": False, "version": f"rdsexp=={__version__}", "diff": ""}
    commit = (_git("rev-parse", "HEAD") or "").strip() or None
    status = _git("status", "--porcelain", "--untracked-files=no")
    diff = _git("diff", "HEAD") or ""
    dirty = bool(status and status.strip())
    version = (commit or "unknown") + ("+" + hashlib.sha256(diff.encode()).hexdigest()[:12] if dirty else "")
    return {"commit": commit, "dirty": dirty, "version": version, "diff": diff if dirty else ""}


def environment() -> dict:
    """Python, host, package versions and BLAS threading of this process."""
    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    try:
        from threadpoolctl import threadpool_info
        blas = [{k: info.get(k) for k in ("internal_api", "num_threads", "version")} for info in threadpool_info()]
    except ImportError:
        blas = None
    threads = {v: os.environ.get(v) for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    return {"python": sys.version.split()[0], "platform": platform.platform(), "host": socket.gethostname(),
            "cpu_count": os.cpu_count(), "packages": versions, "blas": blas, "thread_env": threads}



def start_time(pid: int) -> str | None:
    """The start time of a process (Linux /proc, clock ticks since boot), None where unknown."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def process_info() -> dict:
    """This process as run.json records it: pid, host and start time (a reused pid is told apart)."""
    pid = os.getpid()
    return {"pid": pid, "host": socket.gethostname(), "start": start_time(pid)}


def now() -> str:
    """UTC time stamp of run.json, to the millisecond."""
    return dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds")


