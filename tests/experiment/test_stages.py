"""The stage cache (store/stages.py): stages loaded from it give the tables computed without it, bit for
bit; keys follow what each stage is computed from; verify ignores it; a damaged entry is recomputed."""
import json
import os
from pathlib import Path

import numpy as np
import pytest
from conftest import SMALL, rdsexp

from rdsexp.experiment import catalog
from rdsexp.experiment.store import layout
from rdsexp.experiment.store import stages as stage_cache
from rdsexp.experiment.store.stages import StageCache, digest, pack, unpack

# two designs x two seeds of the `paper` sweep, at the small size (open loop on, recording off)
PAPER = ["+sweep=paper", "gain=proposed,pole_placement", "seed=0,1", *SMALL, "tracking.recording=false"]


def sweep(cwd: Path, *args) -> dict:
    """Run a sweep in cwd's store; {(gain, seed): run.json} of its jobs."""
    before = set((cwd / "outputs" / "sweeps").glob("*")) if (cwd / "outputs" / "sweeps").exists() else set()
    rdsexp(*args, cwd=cwd)
    (new,) = set((cwd / "outputs" / "sweeps").glob("*")) - before
    jobs = {}
    for path in new.glob("*/run.json"):
        info = json.loads(path.read_text())
        assert info["status"] == "complete", info.get("error")
        point = dict(o.split("=", 1) for o in info["overrides"] if o.split("=")[0] in ("gain", "seed"))
        jobs[point["gain"], point["seed"]] = info
    return jobs


def hashes(jobs: dict) -> dict:
    """{job: {table: content sha256}} (file bytes differ between any two runs: the run id is in the schema)."""
    return {job: {name: t["sha256"] for name, t in info["tables"].items()}
            for job, info in jobs.items()}


@pytest.fixture(scope="module")
def plain(tmp_path_factory):
    """The sweep computed without the cache."""
    cwd = tmp_path_factory.mktemp("plain")
    return sweep(cwd, *PAPER, "cache=false")


@pytest.fixture(scope="module")
def cached(tmp_path_factory):
    """The sweep with the cache, twice in one store (the second computes again: reuse=false)."""
    cwd = tmp_path_factory.mktemp("cached")
    first = sweep(cwd, *PAPER)
    second = sweep(cwd, *PAPER, "reuse=false")
    return cwd, first, second


@pytest.mark.slow
def test_tables_with_the_cache_are_those_without_bit_for_bit(plain, cached):
    _, first, second = cached
    assert hashes(first) == hashes(plain) and hashes(second) == hashes(plain)
    assert not any(info.get("stages_reused") for info in plain.values())
    for (gain, _), info in second.items():      # every stage it could take from the store, it took
        reused = info["stages_reused"]
        assert {"identification", "open_loop", f"synthesis/identified/{gain}"} <= set(reused)
        assert all(entry["run"] in {i["id"] for i in first.values()} for entry in reused.values())
        assert set(info["stage_keys"]) >= set(reused)
    # within the first sweep, the second design of a seed took identification and open loop from the first
    for seed in ("0", "1"):
        later = first["pole_placement", seed]["stages_reused"]
        assert later["identification"]["run"] == first["proposed", seed]["id"]
        assert later["open_loop"]["run"] == first["proposed", seed]["id"]


@pytest.mark.slow
def test_changed_paths_reuse_identification_and_designs_and_recompute_the_loops(cached, plain):
    cwd, first, _ = cached
    more = sweep(cwd, *PAPER, "closed_loop.paths=5")
    for (gain, seed), info in more.items():
        reused = info["stages_reused"]
        designs = [label for label in info["stage_keys"] if label.startswith("synthesis/")]
        assert "identification" in reused and designs and all(label in reused for label in designs)
        # the open loop of 5 paths: computed by this sweep's first job of the seed, reused by the next
        assert "open_loop" in info["stage_keys"]
        assert reused.get("open_loop", {}).get("run") in (None, *(i["id"] for i in more.values()))
        assert ("open_loop" in reused) == (gain == "pole_placement")
        for table in ("identification", "model"):
            assert info["tables"][table]["sha256"] == first[gain, seed]["tables"][table]["sha256"]
    # the fresh loops equal a computation without the cache
    again = sweep(cwd, *PAPER, "closed_loop.paths=5", "cache=false", "reuse=false")
    assert hashes(again) == hashes(more)


@pytest.mark.slow
def test_a_changed_identification_setting_misses(cached):
    cwd, first, _ = cached
    other = sweep(cwd, *PAPER, "identification.K1=15")
    earlier = {i["id"] for i in first.values()}
    for info in other.values():          # (a job may reuse what this sweep's previous job of its seed computed)
        reused = info["stages_reused"]
        assert reused.get("identification", {}).get("run") not in earlier
        assert not any(entry["run"] in earlier for label, entry in reused.items()
                       if label.startswith("synthesis/identified/"))                     # other moments
        assert all(reused[label]["run"] in earlier for label in info["stage_keys"]
                   if label.startswith("synthesis/reported/"))                           # the same reported ones
    assert {i["stage_keys"]["identification"] for i in other.values()}.isdisjoint(
        {i["stage_keys"]["identification"] for i in first.values()})


@pytest.mark.slow
def test_verify_computes_everything(cached, monkeypatch):
    _, _, second = cached
    info = second["pole_placement", "1"]
    assert info["stages_reused"]
    run_dir = Path(info["sweep"]["dir"]) / str(info["sweep"]["job"])
    def refuse(*args, **kwargs):
        raise AssertionError("verify read the stage cache")
    monkeypatch.setattr(StageCache, "key", refuse)
    monkeypatch.setattr(StageCache, "load_parts", refuse)
    ok, lines = catalog.verify(run_dir)
    assert ok, lines


def single(cwd: Path, *args) -> dict:
    before = set((cwd / "outputs" / "runs").glob("*")) if (cwd / "outputs" / "runs").exists() else set()
    rdsexp(*SMALL, "tracking.recording=false", "reuse=false", *args, cwd=cwd)     # the stages, not the run, reused
    (new,) = set((cwd / "outputs" / "runs").glob("*")) - before
    return json.loads((new / "run.json").read_text())


@pytest.mark.slow
def test_a_damaged_or_partial_entry_is_recomputed_not_a_traceback(tmp_path):
    first = single(tmp_path)
    stages = tmp_path / "outputs" / layout.STAGES
    (ident,) = (stages / "identification").iterdir()
    (loop,) = (stages / "open_loop").iterdir()
    npz = next(ident.glob("*.npz"))
    os.chmod(npz, 0o644)
    npz.write_bytes(npz.read_bytes()[:100])                    # truncated
    (loop / "meta.json").unlink()                              # partial: no meta.json
    (stages / "open_loop" / f".{loop.name}.999999.tmp").mkdir()   # a writer that never finished
    stage_cache._MEMORY.clear()                                # a later process: only the store's entries
    second = single(tmp_path)
    assert "identification" not in second["stages_reused"] and "open_loop" not in second["stages_reused"]
    assert {k: v["sha256"] for k, v in second["tables"].items()} == {k: v["sha256"] for k, v in first["tables"].items()}
    log = (tmp_path / "outputs" / "runs" / second["id"] / layout.LOG).read_text()
    assert "ignoring the damaged entry" in log
    stage_cache._MEMORY.clear()
    third = single(tmp_path)                                   # the damaged entry was replaced by a good one
    assert "identification" in third["stages_reused"]
    assert {k: v["sha256"] for k, v in third["tables"].items()} == {k: v["sha256"] for k, v in first["tables"].items()}


def test_pack_round_trips_and_digest_is_exact():
    from rdsexp.numerics.systems import MomentModel
    value = {"m": MomentModel(np.array([0.1, 0.2]), np.eye(2)), "x": [1, 2.5, float("nan"), 1 + 2j, np.float64(3.0)],
             "t": (None, True, "s"), "o": np.array(["", "diverged"], dtype=object)}
    arrays = {}
    back = unpack(json.loads(json.dumps(pack(value, arrays))), arrays)
    assert digest(back) == digest(value)
    assert digest(np.float64(0.1)) != digest(np.nextafter(0.1, 1.0))
    with pytest.raises(TypeError):
        digest(object())


def test_two_writers_of_one_key_leave_one_entry(tmp_path):
    a, b = StageCache(tmp_path, "v", "run-a"), StageCache(tmp_path, "v", "run-b")
    key = a.key("open_loop", x=np.arange(3))
    wa, wb = a.writer("open_loop", key), b.writer("open_loop", key)
    for w in (wa, wb):
        w.add({"first": 0, "values": np.arange(4.0)})
        w.add({"first": 4, "values": np.arange(2.0)})
    wa.commit()
    wb.commit()                                                # the key is stored: b's copy is dropped
    entries = list((tmp_path / layout.STAGES / "open_loop").iterdir())
    assert [e.name for e in entries] == [key]
    parts = list(StageCache(tmp_path, "v", "run-c").load_parts("open_loop", key))
    assert [p["first"] for p in parts] == [0, 4] and np.array_equal(parts[1]["values"], np.arange(2.0))


def test_a_save_interrupted_mid_write_leaves_no_temporary_entry(tmp_path, monkeypatch):
    """A Ctrl-C while a single-part entry is written (`StageCache.save`, e.g. a sweep's worker storing its
    synthesis) drops the temporary directory and stores nothing; the next save stores the entry."""
    cache = StageCache(tmp_path, "v", "run-a")
    key = cache.key("synthesis", x=1)
    def interrupted(self):
        raise KeyboardInterrupt
    with monkeypatch.context() as patch:
        patch.setattr(stage_cache.EntryWriter, "commit", interrupted)
        with pytest.raises(KeyboardInterrupt):
            cache.save("synthesis", key, {"F": np.eye(2)})
    assert not list((tmp_path / layout.STAGES).rglob("*"))[1:], list((tmp_path / layout.STAGES).rglob("*"))
    cache.save("synthesis", key, {"F": np.eye(2)})
    assert [e.name for e in (tmp_path / layout.STAGES / "synthesis").iterdir()] == [key]


@pytest.mark.slow
def test_a_reused_stage_is_said_in_the_summary_and_the_log_not_on_the_terminal(tmp_path):
    # the open loop is loaded under its progress bar, where console logging goes through tqdm: the
    # console handler's level (warnings) still holds there
    args = (*SMALL, "tracking.recording=false", "reuse=false")       # the stages, not the whole run, reused
    rdsexp(*args, cwd=tmp_path)
    proc = rdsexp(*args, cwd=tmp_path)
    assert "reused from the stage cache" in proc.stdout and "open loop" in proc.stdout
    assert "INFO" not in proc.stderr, proc.stderr
    (run,) = sorted((tmp_path / "outputs" / "runs").iterdir())[-1:]
    assert "open_loop: reused from run" in (run / "rdsexp.log").read_text()


def test_a_streamed_stage_is_stored_only_when_consumed_whole(tmp_path):
    """`Stages.streamed` stores a loop's parts as they are consumed: a consumer that stops early (an error,
    Ctrl-C), or before its first read, leaves neither an entry nor a temporary directory; one that reads
    every part commits the entry, and the next lookup replays the same parts."""
    from contextlib import closing

    from rdsexp.experiment.pipeline import Stages
    computed = []
    def parts():
        for first in (0, 3, 6):
            computed.append(first)
            yield {"first": first, "values": np.arange(first, first + 3.0)}
    stages = Stages(StageCache(tmp_path, "v", "run-a"))
    never, _ = stages.streamed("open_loop", parts, x=1)          # a Ctrl-C before its consumer's first read
    never.close()
    assert not list((tmp_path / layout.STAGES).rglob("*")) and not computed
    chunks, reused = stages.streamed("open_loop", parts, x=1)
    with closing(chunks):
        assert next(chunks)["first"] == 0 and not reused
    assert not any((tmp_path / layout.STAGES / "open_loop").iterdir())
    chunks, reused = stages.streamed("open_loop", parts, x=1)
    assert [p["first"] for p in chunks] == [0, 3, 6] and not reused
    computed.clear()
    chunks, reused = Stages(StageCache(tmp_path, "v", "run-b")).streamed("open_loop", parts, x=1)
    replayed = list(chunks)
    assert reused and not computed and np.array_equal(replayed[2]["values"], np.arange(6.0, 9.0))
