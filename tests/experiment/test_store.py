"""Fault injection on the run store: a damaged record never spreads.

One tiny sweep (3 seeds) is stored once; each test copies that store, injects one fault and checks
what must happen: no traceback, the message, the exit code, and that every undamaged record is
still listed (`rdsexp-runs list`), reused (the reuse lookup of a resumed sweep), reported
(`rdsexp.report.load_runs`) and passes `rdsexp-runs check`. Faults that need a running process
(read-only store, a write failing midway, concurrent resumes, a kill during the summary write, a
sweep outside the store) run the CLI.
"""
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import REPO, SERIAL, SMALL, rdsexp

from rdsexp import report
from rdsexp.errors import warnings_as_lines
from rdsexp.experiment import catalog, store

TINY = [*SMALL, "model.reported=null", "tracking.recording=false"]
SWEEP = ["+sweep=seeds", "seed=range(0,3)", *TINY, SERIAL]
DAMAGED = 1                                  # the job a fault damages (when it damages one)


@dataclass
class Store:
    root: Path
    sweep: Path
    jobs: list[Path]
    infos: list[dict]

    def key(self, j: int) -> tuple[str, str]:
        return self.infos[j]["config_hash"], self.infos[j]["code"]["version"]


@pytest.fixture(autouse=True)
def record_warnings_as_lines():
    """The store's readers warn (RecordWarning); here printed as the command line prints them, one
    line each on stderr, whether a test calls the command line or the library."""
    with warnings_as_lines():
        yield


@pytest.fixture(scope="session")
def pristine(tmp_path_factory) -> Path:
    """A store holding one complete sweep of 3 tiny jobs (tracking summary, no recording)."""
    cwd = tmp_path_factory.mktemp("pristine")
    rdsexp(*SWEEP, f"store={cwd / 'outputs'}", cwd=cwd)
    return cwd / "outputs"


def copy_store(pristine: Path, root: Path) -> Store:
    shutil.copytree(pristine, root)
    (sweep,) = (root / "sweeps").iterdir()
    jobs = [sweep / str(j) for j in range(3)]
    return Store(root, sweep, jobs, [json.loads((d / "run.json").read_text()) for d in jobs])


@pytest.fixture
def st(pristine, tmp_path) -> Store:
    return copy_store(pristine, tmp_path / "outputs")


def overwrite(path: Path, data: bytes) -> None:
    if path.exists():
        path.chmod(0o644)                    # stored read-only: an edit is deliberate
    path.write_bytes(data)


def dead_pid() -> int:
    proc = subprocess.Popen(["true"])
    proc.wait()
    return proc.pid


def set_field(path: Path, **fields) -> None:
    info = json.loads(path.read_text())
    info.update(fields)
    overwrite(path, json.dumps(info).encode())


# --- the faults: each injects into a copied store and returns nothing; the table says what must happen

def truncated_run_json(s):
    overwrite(s.jobs[1] / "run.json", (s.jobs[1] / "run.json").read_bytes()[:300])


def empty_run_json(s):
    overwrite(s.jobs[1] / "run.json", b"")


def binary_run_json(s):
    overwrite(s.jobs[1] / "run.json", bytes(range(256)))


def wrong_field_type(s):
    set_field(s.jobs[1] / "run.json", summary=[1, 2])


def truncated_parquet(s):
    path = s.jobs[1] / "metrics.parquet"
    overwrite(path, path.read_bytes()[: path.stat().st_size // 2])


def missing_table(s):
    (s.jobs[1] / "paths.parquet").unlink()


def tampered_table(s):
    path = s.jobs[1] / "metrics.parquet"
    table = pd.read_parquet(path)
    table.loc[0, "rate"] += 1e-9
    path.chmod(0o644)
    table.to_parquet(path, index=False)


def missing_hydra(s):
    shutil.rmtree(s.jobs[1] / ".hydra")


def other_code_version(s):
    old = s.root / "runs" / "from_another_version"
    shutil.copytree(s.jobs[1], old)
    info = json.loads((old / "run.json").read_text())
    info["code"]["version"] = "0" * 40
    info["id"], info["sweep"], info["added_by_a_later_version"] = old.name, None, {"x": 1}
    for meta in info["tables"].values():
        meta.pop("file_sha256")               # an older record: content hashes only
    overwrite(old / "run.json", json.dumps(info).encode())


def foreign_files(s):
    (s.root / "notes.txt").write_text("not a run")
    (s.root / "sweeps" / "README").write_text("not a run")
    (s.root / "runs").mkdir(exist_ok=True)
    (s.root / "runs" / "stray.parquet").write_bytes(b"PAR1 garbage")


def foreign_directory(s):
    other = s.root / "other_project"
    (other / "sub").mkdir(parents=True)
    (other / "run.json").write_text(json.dumps([{"epoch": 1, "loss": 0.5}]))
    (other / "data.parquet").write_bytes(b"garbage")
    (other / "sub" / "x.txt").write_text("x")


def stuck_incomplete(s):
    set_field(s.jobs[1] / "run.json", status="incomplete",
              process={"pid": dead_pid(), "host": os.uname().nodename, "start": None})


def summary_disagrees(s):
    path = s.sweep / "summary.parquet"
    table = pd.read_parquet(path)
    overwrite(path, b"")
    table[table["job"] != 2].to_parquet(path, index=False)


def truncated_summary(s):
    path = s.sweep / "summary.parquet"
    overwrite(path, path.read_bytes()[:100])


def leftover_temporary(s):
    (s.jobs[1] / f".metrics.parquet.{dead_pid()}.tmp").write_bytes(b"PAR1 partial")


def unreadable_index_entry(s):
    overwrite(s.root / store.INDEX / f"{store.index_key(*s.key(1))}.json", b'{"dir": ')


def index_entry_outside_store(s):
    outside = s.root.parent / "elsewhere" / "1"
    shutil.copytree(s.jobs[1], outside)
    overwrite(s.root / store.INDEX / f"{store.index_key(*s.key(1))}.json",
              json.dumps({"dir": "../elsewhere/1"}).encode())


# fault, message (in the warnings of list/report/reuse and in check), check's exit code, whether the
# list warns, the job that must not be reused (None: every job is reused), whether report skips it
FAULTS = [
    (truncated_run_json, "truncated or not JSON", 1, True, DAMAGED),
    (empty_run_json, "run.json: empty", 1, True, DAMAGED),
    (binary_run_json, "truncated or not JSON", 1, True, DAMAGED),
    (wrong_field_type, "not an rdsexp run record (summary is a list)", 1, True, DAMAGED),
    (truncated_parquet, "metrics.parquet: unreadable", 1, False, DAMAGED),
    (missing_table, "paths.parquet: missing", 1, False, DAMAGED),
    (tampered_table, "metrics.parquet: modified after the run", 1, False, DAMAGED),
    (missing_hydra, ".hydra/config.yaml: missing", 1, False, DAMAGED),
    (other_code_version, None, 0, False, None),
    (foreign_files, None, 0, False, None),
    (foreign_directory, "other_project/run.json: not an rdsexp run record", 1, True, None),
    (stuck_incomplete, "incomplete and its process", 1, False, DAMAGED),
    (summary_disagrees, "summary.parquet: disagrees with its jobs", 1, False, None),
    (truncated_summary, "summary.parquet: unreadable", 1, False, None),
    (leftover_temporary, "left by a write that did not finish", 1, False, None),
    (unreadable_index_entry, "unusable index entry", 1, False, None),
    (index_entry_outside_store, "outside the store", 1, False, None),
]


def call(capsys, *argv) -> tuple[int, str, str]:
    rc = catalog.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err
    return rc, out, err


def files(root: Path) -> set[Path]:
    """Every record file under root (wherever quarantine moved it), without derived data."""
    return {Path(*p.relative_to(root).parts[1:]) if p.relative_to(root).parts[0] == store.QUARANTINE
            else p.relative_to(root) for p in root.rglob("*") if p.is_file()
            and store.INDEX not in p.relative_to(root).parts[:1] and not p.name.startswith("summary.")}


def assert_undamaged_still_served(s: Store, capsys, skip: int | None):
    """Listed, reused and reported: every job but `skip`."""
    rc, out, err = call(capsys, "list", s.root)
    assert rc == 0
    for j, info in enumerate(s.infos):
        if j != skip:
            assert info["id"] in out
    for j in range(3):
        found = store.find_reusable(s.root, *s.key(j))
        assert found == (None if j == skip else s.jobs[j].resolve()), j
    loaded = {run.dir.resolve(): run for run in report.load_runs(s.root)}
    for j in range(3):
        if j != skip:
            assert loaded[s.jobs[j].resolve()].table("metrics").shape[0] > 0
    capsys.readouterr()


@pytest.mark.parametrize("inject, message, check_rc, list_warns, unreusable", FAULTS,
                         ids=[f[0].__name__ for f in FAULTS])
def test_fault(st, capsys, inject, message, check_rc, list_warns, unreusable):
    inject(st)
    before = files(st.root)
    # check: the message and the exit code, nothing about an undamaged job
    rc, out, err = call(capsys, "check", st.root)
    assert rc == check_rc, out
    if message:
        assert message in out
    for j in (0, 2):
        assert not [line for line in out.splitlines() if line.startswith("damaged") and str(st.jobs[j]) + "/" in line]
    rc, out, err = call(capsys, "list", st.root)
    assert rc == 0
    warnings = [line for line in err.splitlines() if line.startswith("rdsexp: warning:")]
    assert len(warnings) == (1 if list_warns else 0), err
    if list_warns:
        assert message in warnings[0]

    # the reuse lookup: a damaged record is named once and never reused; the others are
    for j in range(3):
        found = store.find_reusable(st.root, *st.key(j))
        assert found == (None if j == unreusable else st.jobs[j].resolve()), j
    out, err = capsys.readouterr()
    if message and unreusable is not None and not list_warns and "incomplete" not in message:
        assert message in err

    # the report: damaged runs are left out with a warning, the others read
    loaded = {run.dir.resolve() for run in report.load_runs(st.root)}
    for j in range(3):
        assert (st.jobs[j].resolve() in loaded) == (j != unreusable), j      # complete, intact runs only
    capsys.readouterr()

    # show on the damaged run: the damage named, no traceback
    if unreusable is not None:
        rc, out, err = call(capsys, "show", st.jobs[DAMAGED])
        assert (message if inject is not stuck_incomplete else "status: incomplete") in out + err
        assert rc == (1 if list_warns else 0)

    # quarantine repairs what the readers above did not (the reuse lookup re-indexes by itself)
    if call(capsys, "check", st.root)[0]:
        rc, out, err = call(capsys, "check", st.root, "--quarantine")
        assert rc == 0 and "moved to quarantine" in out
        rc, out, err = call(capsys, "check", st.root)
        assert rc == 0, out
        assert files(st.root) == before                  # nothing deleted, only moved
        summary = pd.read_parquet(st.sweep / "summary.parquet")
        assert set(summary["id"]) == {info["id"] for j, info in enumerate(st.infos) if j != unreusable}
    assert_undamaged_still_served(st, capsys, skip=unreusable)


def test_verify_names_damaged_tables(st, capsys):
    truncated_parquet(st)
    missing_table(st)
    rc, out, err = call(capsys, "verify", st.jobs[1])
    assert rc == 1
    assert f"damaged: {st.jobs[1] / 'metrics.parquet'}: unreadable" in out
    assert f"damaged: {st.jobs[1] / 'paths.parquet'}: missing" in out
    assert "metrics         DAMAGED" in out and "gains           identical" in out
    truncated_run_json(st)
    rc, out, err = call(capsys, "verify", st.jobs[1])
    assert rc == 1 and f"damaged: {st.jobs[1] / 'run.json'}: truncated or not JSON" in err


# --- faults that need the CLI running

@pytest.mark.slow
def test_resumed_sweep_reruns_only_the_damaged_job(st, tmp_path):
    """A half-written run.json. A resumed sweep names it in one warning, runs that
    job again, reuses the others (read-only files, shared only where modes protect them) and
    exits 0; an edit of a reused table is caught and does not change the original."""
    truncated_run_json(st)
    proc = rdsexp(*SWEEP, f"store={st.root}", cwd=tmp_path)
    warnings = [line for line in proc.stderr.splitlines() if "warning" in line]
    assert "Traceback" not in proc.stderr and len(warnings) == 1
    assert f"not reusing {st.jobs[1] / 'run.json'}: truncated or not JSON" in warnings[0]
    (new,) = set((st.root / "sweeps").iterdir()) - {st.sweep}
    infos = [json.loads((new / str(j) / "run.json").read_text()) for j in range(3)]
    assert [i["status"] for i in infos] == ["complete"] * 3
    assert [i.get("reused_from") for i in infos] == [st.infos[0]["id"], None, st.infos[2]["id"]]
    # the sweep's end: its results table (a row per job, the run it reused) and the count of reused jobs
    lines = proc.stdout.splitlines()
    assert "reused 2 of 3 jobs (same config hash and code version as a stored run)" in lines
    header = next(i for i, line in enumerate(lines) if line.split()[:1] == ["job"])
    assert [line.split()[0] for line in lines[header + 1:header + 4]] == ["0", "1", "2"]
    assert lines[header + 1].split()[-1] == st.infos[0]["id"] and lines[header + 2].split()[-1] == "-"
    summary = pd.read_parquet(new / "summary.parquet")
    assert list(summary["status"]) == ["complete"] * 3
    old, reused = st.jobs[0] / "metrics.parquet", new / "0" / "metrics.parquet"
    assert not reused.stat().st_mode & 0o222 and not old.stat().st_mode & 0o222
    assert os.path.samefile(old, reused) == (os.geteuid() != 0)         # root is not stopped by modes: copy
    table = pd.read_parquet(reused)                                    # a deliberate edit of the reused copy
    table.loc[0, "rate"] += 1e-9
    if os.geteuid() == 0:
        reused.chmod(0o644)
        table.to_parquet(reused, index=False)
        assert store.run_damage(new / "0", infos[0]) == [
            "metrics.parquet: modified after the run (does not match the hash in run.json)"]
    else:
        with pytest.raises(PermissionError):
            table.to_parquet(reused, index=False)
    assert not store.run_damage(st.jobs[0], st.infos[0])               # the original is unchanged
    # the rerun job 1 is now the indexed one: the next resume reuses it
    assert store.find_reusable(st.root, *st.key(1)) == (new / "1").resolve()


@pytest.mark.slow
def test_sweep_outside_the_store_reads_and_reuses_nothing_there(pristine, tmp_path):
    """hydra.sweep.dir=SOMEWHERE/x: the reuse lookup searches the configured store only, never
    SOMEWHERE (which here holds complete runs of the same configs and a damaged record)."""
    somewhere = tmp_path / "somewhere"
    shutil.copytree(pristine, somewhere)
    (somewhere / "junk").mkdir()
    (somewhere / "junk" / "run.json").write_text('{"id": ')
    index_before = {p.name: p.read_bytes() for p in (somewhere / store.INDEX).iterdir()}
    empty = tmp_path / "store"
    proc = rdsexp("+sweep=seeds", "seed=range(0,1)", *TINY, f"store={empty}",
                  f"hydra.sweep.dir={somewhere / 'x'}", cwd=tmp_path)
    assert "warning" not in proc.stderr and "Traceback" not in proc.stderr
    info = json.loads((somewhere / "x" / "0" / "run.json").read_text())
    assert info["status"] == "complete" and "reused_from" not in info
    assert {p.name: p.read_bytes() for p in (somewhere / store.INDEX).iterdir()} == index_before
    assert not list((empty / store.INDEX).glob("*.json"))        # a run outside the store is not indexed


@pytest.mark.slow
def test_read_only_store_fails_before_any_work_with_one_line(st, tmp_path):
    """A read-only store (simulated as EROFS, which root cannot bypass): a run and a sweep each
    exit 1 with one line and write nothing; everything stored is still listed and reused."""
    before = sorted(st.root.rglob("*"))
    for args in ([*TINY], SWEEP):
        proc = subprocess.run([sys.executable, str(REPO / "tests" / "faulty_rdsexp.py"), f"erofs:{st.root}",
                               *args, f"store={st.root}"], cwd=tmp_path, capture_output=True, text=True)
        assert proc.returncode == 1, proc.stderr
        (line,) = proc.stderr.strip().splitlines()
        assert line.startswith(f"rdsexp: cannot write {st.root}/") and line.endswith("Read-only file system")
    assert sorted(st.root.rglob("*")) == before


@pytest.mark.slow
def test_write_failing_midway_leaves_nothing_that_looks_complete(st, tmp_path, capsys):
    """A file size limit (as a full disk) hits the tables: exit 1 with one line, run.json says
    write_error, no partial file under a final name, no temporary file left."""
    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (16_000, 16_000))
    env = dict(os.environ, PYTHONWARNINGS="ignore::DeprecationWarning", PYTHONDONTWRITEBYTECODE="1")
    proc = subprocess.run([sys.executable, "-m", "rdsexp", *TINY, f"store={st.root}"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, preexec_fn=limit)
    assert proc.returncode == 1
    (line,) = proc.stderr.strip().splitlines()
    assert line.startswith(f"rdsexp: cannot write {st.root / 'runs'}/") and ".parquet: " in line
    assert line.endswith("File too large")
    (run_dir,) = (st.root / "runs").iterdir()
    info = json.loads((run_dir / "run.json").read_text())
    assert info["status"] == "write_error" and "File too large" in info["error"]
    assert Path(line.split()[3].rstrip(":")).name not in os.listdir(run_dir)
    assert not [p for p in run_dir.iterdir() if p.name.endswith(".tmp")]
    for table in run_dir.glob("*.parquet"):
        pd.read_parquet(table)
    rc, out, _ = call(capsys, "list", st.root)
    assert "write_error" in out
    assert call(capsys, "check", st.root)[0] == 0
    assert_undamaged_still_served(st, capsys, skip=None)


@pytest.mark.slow
def test_two_processes_resuming_the_same_sweep(st, tmp_path, capsys):
    cmd = [sys.executable, "-m", "rdsexp", *SWEEP, f"store={st.root}"]
    procs = [subprocess.Popen(cmd, cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    for p in procs:
        assert p.wait(timeout=300) == 0
        assert "Traceback" not in p.stderr.read()
    for sweep in set((st.root / "sweeps").iterdir()) - {st.sweep}:
        summary = pd.read_parquet(sweep / "summary.parquet")
        assert list(summary["status"]) == ["complete"] * 3
        assert [json.loads((sweep / str(j) / "run.json").read_text())["reused_from"] for j in range(3)] \
            == [i["id"] for i in st.infos]
    assert call(capsys, "check", st.root)[0] == 0
    assert_undamaged_still_served(st, capsys, skip=None)


@pytest.mark.slow
def test_sweep_killed_during_its_summary_write(st, tmp_path, capsys):
    proc = subprocess.run([sys.executable, str(REPO / "tests" / "faulty_rdsexp.py"), "kill:summary.parquet",
                           *SWEEP, f"store={st.root}"], cwd=tmp_path, capture_output=True, text=True)
    assert proc.returncode == -signal.SIGKILL
    (new,) = set((st.root / "sweeps").iterdir()) - {st.sweep}
    assert not (new / "summary.parquet").exists()
    rc, out, err = call(capsys, "list", st.root, "--all")        # its jobs reused the stored ones: copies
    assert rc == 0 and "warning" not in err and f"{new.name}/0" in out
    rc, out, _ = call(capsys, "check", st.root)
    assert rc == 1 and "left by a write that did not finish" in out and "summary.parquet: missing" in out
    rc, out, _ = call(capsys, "check", st.root, "--quarantine")
    assert rc == 0
    assert list(pd.read_parquet(new / "summary.parquet")["id"]) == [f"{new.name}/0"]
    assert call(capsys, "check", st.root)[0] == 0
    assert_undamaged_still_served(st, capsys, skip=None)


@pytest.mark.parametrize("text, fast", [
    ("a: {b: 2, s: x, n: null}\nc: ${oc.select:a.b,3}\nd: ${oc.select:a.zz,auto}\ne: ${oc.select:q,[]}\n"
     "f: ${oc.select:q,True}\ng: ${oc.select:a.n,1}\nh: ${oc.select:a, 0.5}\ni: ${oc.select:q,-1e-3}\nj: '???'\n"
     "k: ${oc.select:j,null}\nm: [[1, 2], [3, 4]]\nn: ${oc.select:m,none}\n", True),
    ("a: 1\nb: ${a}\n", False),                                  # other interpolations: OmegaConf's
    ("a: 1\nb: x_${oc.select:a,0}\n", False),
    ("a: ${oc.select:c,1}\nb: ${oc.select:a,0}\n", False),       # a chain
    ("a: 1\nb: ${oc.select:a,'q r'}\n", False),
])
def test_scalar_config_resolves_selects_as_omegaconf_does(tmp_path, text, fast):
    """A stored config's `${oc.select:KEY,DEFAULT}` values are resolved without building OmegaConf nodes
    (most of a report's time reading configs), to exactly what OmegaConf resolves; any other
    interpolation goes through OmegaConf."""
    import yaml
    from omegaconf import OmegaConf

    from rdsexp.experiment.store import run as stored
    (tmp_path / ".hydra").mkdir()
    (tmp_path / ".hydra" / "config.yaml").write_text(text)
    node = stored.scalars_only(yaml.load(text, Loader=stored._yaml_loader()))
    expected = OmegaConf.to_container(OmegaConf.create(node), resolve=True)
    assert stored._resolve_selects(stored.scalars_only(yaml.load(text, Loader=stored._yaml_loader()))) is fast
    got = stored.scalar_config(tmp_path)
    assert got == expected and repr(got) == repr(expected)


def test_run_metrics_flattens_lists_inside_summary_dicts():
    """A summary number is a scalar column: lists one level down (the moments' spread) by component."""
    from rdsexp.experiment.store import RunRecord
    row = RunRecord.parse({"id": "r", "status": "complete", "seconds": 1.0, "summary": {
        "modeling_uncertainty": {"resamples": 200, "xi_mean_sd": [0.1, 0.2]}, "closed_loop_rate": [0.9, 0.8, 1.0],
        "xi_mean": [0.5]}}).metrics
    assert row == {"metrics.modeling_uncertainty_resamples": 200, "metrics.modeling_uncertainty_xi_mean_sd[0]": 0.1,
                   "metrics.modeling_uncertainty_xi_mean_sd[1]": 0.2, "metrics.closed_loop_rate": 0.9,
                   "metrics.closed_loop_rate_low": 0.8, "metrics.closed_loop_rate_high": 1.0,
                   "metrics.xi_mean[0]": 0.5, "metrics.seconds": 1.0}


def test_run_record_types_run_json_and_makes_older_records_current(tmp_path):
    """RunRecord.parse: the typed view of run.json; an older record (seed as an int, a sweep without a name or
    `resumes`, no plant_hash) reads as a current one, and the catalog's identity comes from it."""
    from rdsexp.experiment.store import RunRecord
    from rdsexp.experiment.store.table import identity
    sweep = tmp_path / "S"
    sweep.mkdir()
    (sweep / "multirun.yaml").write_text("hydra:\n  overrides:\n    task: [\"seed=0,1\", closed_loop.paths=4]\n")
    old = {"id": "S/1", "status": "complete", "seed": 1, "sweep": {"dir": str(sweep), "job": 1},
           "overrides": ["seed=1", "closed_loop.paths=4"], "code": {"version": "abc"},
           "summary": {"plant": "paper", "closed_loop_verdict": "stable", "closed_loop_rate": [0.85, 0.8, None],
                       "closed_loop_failed": {"fraction": 0.25}}}
    record = RunRecord.parse(old)
    assert (record.seed, record.sweep.job, record.sweep.id, record.sweep.resumes) == (1, 1, "S", None)
    assert record.sweep.name == "seed=0,1" and record.plant_hash is None and record.code_version == "abc"
    assert record.summary.verdict() == "stable" and record.summary.plant == "paper"
    assert record.summary.rate()[:2] == (0.85, 0.8) and np.isnan(record.summary.rate()[2])
    assert record.summary.failed_fraction() == 0.25 and np.isnan(record.summary.rate("open_loop")[0])
    assert dict(record.summary) == old["summary"] and record.raw is old
    current = dict(old, seed={"root": 1}, sweep={"dir": str(sweep), "job": 1, "name": "seed=0,1", "resumes": None})
    assert RunRecord.parse(current).seed == 1 and RunRecord.parse(current).sweep == record.sweep
    row = identity(sweep / "1", record)
    assert (row["sweep"], row["sweep_id"], row["job"], row["seed"], row["plant"]) == ("seed=0,1", "S", 1, 1, "paper")


def test_settling_an_interrupt_removes_the_temporary_entries_of_ended_processes_only(tmp_path):
    """After a Ctrl-C, `settle_interrupted` on a sweep also removes the stage cache's temporary entries
    (directories ".<key>.<pid>.tmp", where a worker stopped mid-write leaves its entry) of this process and of
    ended ones in the sweep's store, and keeps those of a process still running and complete entries."""
    ended = subprocess.Popen([sys.executable, "-c", "pass"])
    ended.wait()
    stages = tmp_path / "outputs" / "stages" / "open_loop"
    entries = {who: stages / f".{'ab' * 32}.{pid}.tmp" for who, pid in
               (("ended", ended.pid), ("mine", os.getpid()), ("running", os.getppid()))}
    complete = stages / ("cd" * 32)
    for entry in [*entries.values(), complete]:
        entry.mkdir(parents=True)
        (entry / "0000.npz").write_bytes(b"part")
    sweep = tmp_path / "outputs" / "sweeps" / "s"
    sweep.mkdir(parents=True)
    leftover = sweep / f".summary.parquet.{ended.pid}.tmp"               # a file of an ended process: removed too
    leftover.write_bytes(b"")
    assert store.settle_interrupted(sweep, wait=0) == []
    assert not entries["ended"].exists() and not entries["mine"].exists()
    assert entries["running"].is_dir() and (complete / "0000.npz").read_bytes() == b"part"
    assert not leftover.exists()
