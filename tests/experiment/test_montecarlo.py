"""Chunked Monte Carlo: tables and metrics do not depend on the chunk size or the workers,
streamed tables are hashed as whole ones, the recording keeps a bounded sample of paths."""
import json

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from conftest import SMALL, rdsexp
from hydra import compose, initialize_config_module

from rdsexp.errors import ConfigError
from rdsexp.experiment.config import build
from rdsexp.experiment.montecarlo import Simulation
from rdsexp.experiment.pipeline import run_experiment
from rdsexp.experiment.store import files

# 7 paths so that chunks of 3 leave a remainder; tracking full to stream the members table too
OVERRIDES = [o for o in SMALL if not o.startswith("closed_loop.paths")] + ["closed_loop.paths=7",
                                                                           "tracking=full"]


def experiment(*extra):
    with initialize_config_module(config_module="rdsexp.conf", version_base="1.3"):
        return build(compose("config", overrides=[*OVERRIDES, *extra]))


@pytest.fixture(scope="module")
def whole():
    return run_experiment(experiment("closed_loop.chunk_paths=7"))


@pytest.mark.parametrize("extra", [["closed_loop.chunk_paths=3"], ["closed_loop.chunk_paths=1"],
                                   ["closed_loop.chunk_paths=2", "closed_loop.workers=2"]])
@pytest.mark.slow
def test_tables_do_not_depend_on_chunks_or_workers(whole, extra):
    chunked = run_experiment(experiment(*extra))
    assert set(chunked.tables) == set(whole.tables) >= {"trajectories", "members", "metrics", "paths"}
    for name, table in whole.tables.items():
        pd.testing.assert_frame_equal(chunked.tables[name], table, check_exact=True, obj=name)
    assert chunked.summary == whole.summary


def test_rows_are_path_major_and_every_path_is_there(whole):
    traj = whole.tables["trajectories"]
    for _, rows in traj.groupby("experiment", sort=False):
        assert rows["path"].is_monotonic_increasing
        assert sorted(rows["path"].unique()) == list(range(7))
        assert (rows.groupby("path")["k"].apply(lambda k: list(k) == list(range(31)))).all()


def test_recording_keeps_a_bounded_sample():
    out = run_experiment(experiment("tracking.recorded_paths=2"))
    loops = out.recorded[out.recorded["experiment"] != "identification"]
    assert set(loops["path"]) == {0, 1} and set(loops["experiment"]) == {"closed_loop", "open_loop"}
    assert set(out.recorded_members["path"]) == {0, 1}
    assert out.tables["trajectories"]["path"].nunique() == 7


def test_chunk_size_from_the_memory_budget():
    loop = lambda *extra: Simulation.of(exp := experiment(*extra), exp.filter.enkf, None, 0)
    chunks = loop("closed_loop.paths=100000", "tracking=summary").chunks()
    assert 1 <= chunks[0][1] < 100000 and sum(count for _, count in chunks) == 100000
    assert [first for first, _ in chunks] == list(np.cumsum([0] + [count for _, count in chunks[:-1]]))
    assert loop("closed_loop.paths=12", "closed_loop.chunk_paths=5", "tracking=full").chunks() == [(0, 5), (5, 5), (10, 2)]


def test_parquet_sink_hash_equals_whole_table_hash(tmp_path, whole):
    table = whole.tables["trajectories"]
    sink = files.ParquetSink(tmp_path)
    for start in range(0, len(table), 50):
        sink.append("trajectories", table.iloc[start:start + 50].reset_index(drop=True))
    assert not (tmp_path / "trajectories.parquet").exists()          # nothing under the final name yet
    meta = sink.close()["trajectories"]
    assert meta["rows"] == len(table) and meta["sha256"] == files.table_hash(table)
    assert pq.ParquetFile(tmp_path / "trajectories.parquet").num_row_groups == -(-len(table) // 50)
    assert [p.name for p in tmp_path.iterdir()] == ["trajectories.parquet"]


def test_a_stored_table_with_any_nan_reads_back_with_its_hash(tmp_path):
    # inf - inf is a NaN with the sign bit set; parquet stores every NaN as null and reads back np.nan,
    # so the content hash counts every NaN as one (a failed loop's rates are such NaNs)
    from rdsexp.experiment.store.run import read_table
    with np.errstate(invalid="ignore"):
        rates = np.array([0.5, np.inf, np.nan]) - np.array([0.0, np.inf, 0.0])
    assert np.signbit(rates[1]) and np.isnan(rates[1:]).all()
    table = pd.DataFrame({"rate": rates, "k": [1, 2, 3]})
    meta = files.store_table(tmp_path / "metrics.parquet", table)
    assert meta["sha256"] == files.table_hash(pd.read_parquet(tmp_path / "metrics.parquet"))
    pd.testing.assert_frame_equal(read_table(tmp_path, {"tables": {"metrics": meta}}, "metrics"), table)
    # a record whose content hash took the NaN bits (written before): the intact file's own hash decides
    old = dict(meta, sha256="0" * 64)
    read_table(tmp_path, {"tables": {"metrics": old}}, "metrics")
    with pytest.raises(Exception, match="modified after the run"):
        read_table(tmp_path, {"tables": {"metrics": dict(old, file_sha256="1" * 64)}}, "metrics")


@pytest.mark.parametrize("override, message", [
    ("closed_loop.chunk_paths=0", "closed_loop.chunk_paths: 0 is not allowed, expected an integer >= 1"),
    ("closed_loop.workers=0", "closed_loop.workers: 0 is not allowed, expected an integer >= 1"),
    ("tracking.recorded_paths=-1", "tracking.recorded_paths: -1 is not allowed, expected an integer >= 0"),
])
def test_bad_scale_settings_are_one_line_errors(override, message):
    with pytest.raises(ConfigError) as err:
        experiment(override)
    assert str(err.value) == message


@pytest.mark.slow
def test_cli_streams_tables_and_verify_passes(tmp_path):
    rdsexp(*SMALL, "closed_loop.paths=5", "closed_loop.chunk_paths=2", cwd=tmp_path)
    (run,) = (tmp_path / "outputs" / "runs").iterdir()
    info = json.loads((run / "run.json").read_text())
    assert info["tables"]["trajectories"]["rows"] == 2 * 5 * 31
    assert pq.ParquetFile(run / "trajectories.parquet").num_row_groups == 2 * 3   # two loops, three chunks
    assert files.stored_table_hash(run / "trajectories.parquet") == info["tables"]["trajectories"]["sha256"]
    assert not [p for p in run.iterdir() if p.name.endswith(".tmp")]
    proc = rdsexp("verify", str(run), cwd=tmp_path, module="rdsexp.runs")
    assert "verify: identical" in proc.stdout
    np.testing.assert_equal(pd.read_parquet(run / "trajectories.parquet")["path"].unique(), np.arange(5))


def test_a_table_checked_once_is_checked_again_when_its_file_changes(tmp_path):
    # read_table remembers the files it verified (by size and mtime): a file rewritten later is checked again
    import os

    from rdsexp.errors import DamagedRecord
    from rdsexp.experiment.store.run import read_table
    path = tmp_path / "metrics.parquet"
    info = {"tables": {"metrics": files.store_table(path, pd.DataFrame({"rate": [0.5, 0.7]}))}}
    read_table(tmp_path, info, "metrics")
    os.chmod(path, 0o644)
    pd.DataFrame({"rate": [0.5, 0.8]}).to_parquet(path, index=False)
    os.utime(path, ns=(path.stat().st_atime_ns, path.stat().st_mtime_ns + 1_000_000))
    with pytest.raises(DamagedRecord, match="modified after the run"):
        read_table(tmp_path, info, "metrics")
