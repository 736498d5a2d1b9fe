"""Report scripts on small stored sweeps made here: figures with finite data, a row per reference
number, lineage hashes that match the tables, identical re-runs, and the code-version check."""
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import REPO, SMALL, rdsexp

from rdsexp import report
from rdsexp.experiment import records

sys.path.insert(0, str(REPO / "experiments"))
import fig_decay  # noqa: E402
import fig_estimation  # noqa: E402
import fig_gains  # noqa: E402
import fig_sweeps  # noqa: E402
import paper  # noqa: E402
import reproduction_table  # noqa: E402

SWEEPS = {"paper": ["seed=0,1"], "ensemble_size": ["enkf.ensemble_size=10,20", "seed=0,1"],
          "noise": ["enkf.q_scale=0.5,1.0", "enkf.r_scale=1.0,2.0", "seed=0"],
          "window": ["identification.K1=10,20", "seed=0,1"]}


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    """outputs/ with small versions of the four sweeps the report needs."""
    cwd = tmp_path_factory.mktemp("report")
    for sweep, overrides in SWEEPS.items():
        rdsexp(f"+sweep={sweep}", *SMALL, "tracking.recording=false", *overrides, cwd=cwd)
    return cwd / "outputs"


@pytest.fixture(scope="module")
def written(root):
    out = root / "report"
    paper.main(["--root", str(root), "--out", str(out)])
    return out


def finite_axes(fig):
    """Every axes of the figure has some line with finite data."""
    for ax in fig.axes:
        data = [np.asarray(line.get_ydata(), float) for line in ax.get_lines()]
        assert any(np.isfinite(d).any() for d in data), ax.get_title()
    return True


def test_each_figure_script_draws_finite_data(root):
    runs = report.load_runs(root, "paper")
    proposed = report.select(runs, gain__method="proposed")
    assert finite_axes(fig_estimation.draw(report.first_seed(runs)))
    for experiment in ("closed_loop", "open_loop"):
        assert finite_axes(fig_decay.draw(report.first_seed(runs), experiment, proposed))
    summary = fig_gains.table(runs)
    assert set(summary["method"]) == set(fig_gains.STYLES)
    assert finite_axes(fig_gains.draw(runs, summary))
    assert finite_axes(fig_sweeps.draw({name: report.load_runs(root, name) for name in SWEEPS if name != "paper"}))


def test_reproduction_table_has_a_row_per_reference_number(written):
    table = pd.read_csv(written / "reproduction.csv")
    expected = [key for key, _ in reproduction_table.flatten("", report.reference())]
    assert list(table["number"]) == expected and len(expected) > 60
    assert set(table["verdict"]) <= {"reproduced", "within Monte Carlo error", "differs"}
    assert not table["reason"].fillna("").str.contains("no rule").any()
    rows = table.set_index("number")
    assert rows.loc["synthesis_proposed.nbar", "verdict"] == "reproduced"
    assert rows.loc["pole_placement.F[4]", "verdict"] == "reproduced"
    assert rows.loc["nominal_lmi.lambda", "verdict"] == "differs"       # the infimum is 0


def test_lineage_hashes_match_the_tables(written):
    outputs = sorted(written.glob("*.json"))
    assert {p.stem for p in outputs} == {"estimation", "decay_proposed", "decay_open", "gain_comparison",
                                         "sweeps", "reproduction"}
    for path in outputs:
        lineage = json.loads(path.read_text())
        assert lineage["runs"] and lineage["script"].endswith(".py")
        for run in lineage["runs"]:
            assert run["tables"]
            for name, sha in run["tables"].items():
                assert records.table_hash(pd.read_parquet(Path(run["dir"]) / f"{name}.parquet")) == sha


def test_rerun_rewrites_identical_files_without_simulating(root, written, tmp_path):
    before = {p.name: p.read_bytes() for p in written.iterdir()}
    runs_before = sorted(p for p in root.rglob("run.json"))
    again = tmp_path / "again"
    paper.main(["--root", str(root), "--out", str(again)])
    assert sorted(p for p in root.rglob("run.json")) == runs_before
    for name, data in before.items():
        assert (again / name).read_bytes() == data, name


def test_missing_sweep_is_run_first_and_announced(tmp_path, monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(paper.subprocess, "run", lambda cmd, **kw: calls.append(cmd))
    paper.ensure_sweeps(tmp_path / "outputs")
    assert [c[3] for c in calls] == [f"+sweep={s}" for s in paper.SWEEPS]
    assert "running python -m rdsexp +sweep=paper" in capsys.readouterr().out


def test_report_refuses_mixed_code_versions(root, tmp_path):
    runs = report.load_runs(root, "paper")
    runs[0].info["code"]["version"] = "another"
    with pytest.raises(report.LineageError, match="2 code versions"):
        report.check_versions(runs)
    assert report.check_versions(runs, allow_mixed=True).startswith("mixed:")


def test_tampered_table_is_refused(root, tmp_path):
    import shutil
    run = report.load_runs(root, "paper")[0]
    copy = tmp_path / "copy"
    shutil.copytree(run.dir, copy)
    frame = pd.read_parquet(copy / "metrics.parquet")
    frame.loc[0, "rate"] = 0.5
    (copy / "metrics.parquet").chmod(0o644)               # stored read-only: an edit is deliberate
    frame.to_parquet(copy / "metrics.parquet", index=False)
    with pytest.raises(report.LineageError, match="does not match the hash"):
        report.Run(copy).table("metrics")
