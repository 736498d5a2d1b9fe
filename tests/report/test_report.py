"""Report scripts on small stored sweeps made here: figures with finite data, a row per reference
number, lineage hashes that match the tables, identical re-runs, and the code-version check."""
import json
import math
import sys
from pathlib import Path
from subprocess import CompletedProcess

import numpy as np
import pandas as pd
import pytest
from conftest import REPO, SMALL, rdsexp, rdsexp_each

import rdsexp as rx
from rdsexp import report
from rdsexp.errors import DamagedRecord
from rdsexp.experiment.store import files

sys.path.insert(0, str(REPO / "experiments"))
import fig_decay  # noqa: E402
import fig_estimation  # noqa: E402
import fig_gains  # noqa: E402
import fig_sweeps  # noqa: E402
import identification_input  # noqa: E402
import paper  # noqa: E402
import pole_sets  # noqa: E402
import reproduction_table  # noqa: E402

# Small sizes: every run designs all gain methods (a few CPU seconds), so the number of runs is the
# cost. The paper sweep keeps the methods the reproduction rows read (proposed, nominal_lmi,
# pole_placement) and one that reaches the proposed gain's rate (the figure's overlap note).
METHODS = ("proposed", "nominal_lmi", "pole_placement", "policy_iteration")
SWEEPS = {"paper": [f"gain={','.join(METHODS)}", "seed=0,1"], "ensemble_size": ["enkf.ensemble_size=10,20", "seed=0"],
          "noise": ["enkf.q_scale=0.5,1.0", "enkf.r_scale=1.0,2.0", "seed=0"],
          "window": ["identification.K1=10,20", "seed=0"],
          # every key the sweep files vary is overridden, so each small sweep is exactly this grid
          "identification_input": ["identification.input.levels=bipolar,unipolar", "identification.input.amplitude=10",
                                   "identification.input.hold=1", "seed=0,1,2"],
          "closed_loop_rate": ["gain.source=identified,reported,fixed", "closed_loop.filter_sees_disturbance=false,true",
                               "seed=0,1"]}


@pytest.fixture(scope="module", autouse=True)
def fewer_pole_sets():
    """paper.py's pole_sets study on 40 seeded pole sets per plant instead of 200: the same code, plants,
    outputs and lineage (exact rates, no runs behind them); the sample's size only scales its time, which
    was a third of each report written here."""
    main = pole_sets.main
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(pole_sets, "main", lambda argv=None: main([*(argv or []), "--count", "40"]))
        yield


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    """outputs/ with small versions of the six sweeps the report needs (paper.SWEEPS): the report
    then runs none itself (at full size the identification_input sweep alone takes minutes)."""
    assert set(SWEEPS) == set(paper.SWEEPS)
    cwd = tmp_path_factory.mktemp("report")
    # two sweeps at a time, the ones of most jobs first
    order = sorted(SWEEPS, key=lambda sweep: -math.prod(len(o.split(",")) for o in SWEEPS[sweep]))
    rdsexp_each([((f"+sweep={sweep}", *SMALL, "tracking.recording=false", *SWEEPS[sweep]), {"cwd": cwd})
                 for sweep in order])
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


@pytest.mark.slow
def test_each_figure_script_draws_finite_data(root):
    runs = report.load_runs(root, "paper")
    proposed = report.select(runs, gain__method="proposed")
    assert finite_axes(fig_estimation.draw(report.first_seed(runs)))
    for experiment in ("closed_loop", "open_loop"):
        assert finite_axes(fig_decay.draw(report.first_seed(runs), experiment, proposed))
    summary = fig_gains.table(runs)
    assert list(summary["method"]) == [m for m in fig_gains.ORDER if m in METHODS]
    assert list(summary["label"]) == [fig_gains.label(m) for m in summary["method"]]
    assert finite_axes(fig_gains.draw(runs, summary))
    assert finite_axes(fig_sweeps.draw({name: report.load_runs(root, name) for name in SWEEPS if name != "paper"}))


@pytest.mark.slow
def test_reproduction_tables_split_inputs_from_results(written):
    """Every reference number is in exactly one of the two tables, in the reference's order; configured
    inputs carry no verdict, computed results do, and the summary counts results only."""
    inputs, table = pd.read_csv(written / "reproduction_inputs.csv"), pd.read_csv(written / "reproduction.csv")
    expected = [key for key, _ in reproduction_table.flatten("", report.reference())]
    assert len(expected) > 60
    assert [k for k in expected if k in set(inputs["number"])] == list(inputs["number"])
    assert [k for k in expected if reproduction_table.is_input(k)] == list(inputs["number"])
    computed = [k for k in expected if not reproduction_table.is_input(k)]
    assert list(table["number"])[:len(computed)] == computed
    assert "verdict" not in inputs.columns and set(inputs["as_the_paper_says"]) <= {"yes", "no"}
    assert {"plant.q0[0]", "enkf.M", "pole_placement.poles[0]"} <= set(inputs["number"])
    assert set(table["verdict"]) <= {"reproduced", "within Monte Carlo error", "differs"}
    assert not table["reason"].fillna("").str.contains("no rule").any()
    rows = table.set_index("number")
    assert rows.loc["synthesis_proposed.nbar", "verdict"] == "reproduced"
    assert rows.loc["pole_placement.F[4]", "verdict"] == "reproduced"
    assert rows.loc["nominal_lmi.lambda", "verdict"] == "differs"       # the infimum is 0
    counts = reproduction_table.verdict_counts(table)
    assert counts.sum() == len(table)
    page = (written / "index.md").read_text()
    assert "Verdicts of the computed results: " + ", ".join(f"{v} {n}" for v, n in counts.items()) in page


@pytest.mark.slow
def test_new_reproduction_rows_on_small_runs(root, written):
    """The rows not in the reference: the identification input consistent with the paper's moments
    (one per sweep, the verdict follows identification_input's table) and the closed-loop rate with
    the paper's moments and the paper's F, EnKF told d_k and not, each with its bootstrap interval."""
    table = pd.read_csv(written / "reproduction.csv").set_index("number")
    ident = pd.read_csv(written / "identification_input.csv")
    assert list(ident["setting"]) == ["bipolar, amplitude 10, hold 1, register 7",
                                      "unipolar, amplitude 10, hold 1, register 7"]
    assert (ident["seeds"] == 3).all() and set(ident["consistent"]) <= {True, False}
    z = ident[[c for c in ident.columns if c.startswith("z ")]].abs().max(axis=1)
    assert np.allclose(z, ident["max_abs_z"], atol=0.01)
    assert list(ident["consistent"]) == list(ident["max_abs_z"] <= ident["z_bound"])
    row = table.loc["modeling.identification_input_consistent"]
    consistent = list(ident[ident["consistent"]]["setting"])
    configured = identification_input.setting(report.first_seed(report.load_runs(root, "paper")))
    assert row["verdict"] == ("within Monte Carlo error" if configured in consistent else "differs")
    rate = pd.read_csv(written / "closed_loop_rate.csv")
    assert sorted(zip(rate["source"], rate["filter_sees_d"])) == sorted(
        (s, t) for s in ("identified", "reported", "fixed") for t in (False, True))
    assert (rate["seeds"] == 2).all() and (rate["paths"] == 4).all()
    assert ((rate["pooled_low"] <= rate["pooled_rate"]) & (rate["pooled_rate"] <= rate["pooled_high"])).all()
    assert ((rate["largest_path_share_median"] >= 0.25) & (rate["largest_path_share_max"] <= 1)).all()
    # the fixed gain is the paper's F in every seed: its exact rate on the true plant is one number
    fixed = rate[rate["source"] == "fixed"]
    assert fixed["exact_rate_true_plant"].nunique() == 1
    assert fixed["exact_rate_true_plant"].iloc[0] == pytest.approx(rx.ms_rate(rx.paper.plant(), None,
                                                                              rx.paper.F_proposed), abs=1e-4)
    for source in ("reported", "fixed"):
        for told in (False, True):
            number = [n for n in table.index if n.startswith("closed_loop.rate_k60_k80 (")
                      and reproduction_table.RATE_ROW[source] in n and ("not told" in n) != told]
            assert len(number) == 1, (source, told, list(table.index))
            r = rate[(rate["source"] == source) & (rate["filter_sees_d"] == told)].iloc[0]
            inside = r["pooled_low"] <= 0.8473 <= r["pooled_high"]
            assert table.loc[number[0], "verdict"] == ("within Monte Carlo error" if inside else "differs")


@pytest.mark.slow
def test_lineage_hashes_match_the_tables(written):
    outputs = sorted(written.glob("*.json"))
    assert {p.stem for p in outputs} >= {"estimation", "decay_proposed", "decay_open", "gain_comparison",
                                         "sweeps", "reproduction", "reproduction_inputs", "identification_input",
                                         "closed_loop_rate"}
    for path in outputs:
        lineage = json.loads(path.read_text())
        # pole_sets is exact (plant configs, a seed and a count): no run behind it
        assert (lineage["runs"] or {"seed", "count", "plants"} <= set(lineage)) and lineage["script"].endswith(".py")
        for run in lineage["runs"]:
            assert run["tables"]
            for name, sha in run["tables"].items():
                assert files.table_hash(pd.read_parquet(Path(run["dir"]) / f"{name}.parquet")) == sha


@pytest.mark.slow
def test_rerun_rewrites_identical_files_without_simulating(root, written, tmp_path):
    before = {p.name: p.read_bytes() for p in written.iterdir()}
    runs_before = sorted(p for p in root.rglob("run.json"))
    again = tmp_path / "again"
    paper.main(["--root", str(root), "--out", str(again)])
    assert sorted(p for p in root.rglob("run.json")) == runs_before
    for name, data in before.items():
        assert (again / name).read_bytes() == data, name


@pytest.mark.slow
def test_second_call_on_the_same_output_renders_no_figure(root, written, tmp_path, monkeypatch):
    """Every figure's lineage (shared with its table of the same name) is found up to date: nothing is
    rendered again (rendering was most of a second call), and every file stays the same."""
    import shutil

    from matplotlib.figure import Figure
    same = tmp_path / "same"
    shutil.copytree(written, same)
    rendered = []
    monkeypatch.setattr(Figure, "savefig", lambda self, path, **kw: rendered.append(Path(path).name))
    paper.main(["--root", str(root), "--out", str(same)])
    assert rendered == []
    for path in written.iterdir():
        assert (same / path.name).read_bytes() == path.read_bytes(), path.name


def test_missing_sweep_is_run_first_and_announced(tmp_path, monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(paper.subprocess, "run", lambda cmd, **kw: calls.append(cmd) or CompletedProcess(cmd, 0))
    paper.ensure_sweeps(tmp_path / "outputs")
    assert [c[3] for c in calls] == [f"+sweep={s}" for s in paper.SWEEPS]
    assert "running python -m rdsexp +sweep=paper" in capsys.readouterr().out


def test_a_sweep_that_fails_ends_the_report_with_one_line_saying_how_to_resume(tmp_path, monkeypatch):
    """A sweep subprocess that exits non-zero (a job's write error, a full disk) stops paper.py before
    any figure with one line naming the sweep and the command that resumes it, not a traceback."""
    calls = []
    monkeypatch.setattr(paper.subprocess, "run", lambda cmd, **kw: calls.append(cmd) or CompletedProcess(
        cmd, 1 if len(calls) == 2 else 0))
    with pytest.raises(SystemExit) as exit_:
        report.script(lambda: paper.main(["--root", str(tmp_path), "--out", str(tmp_path / "report"), "--jobs", "1"]))
    message = exit_.value.code
    second = list(paper.SWEEPS)[1]
    assert len(calls) == 2 and isinstance(message, str) and "\n" not in message, message
    assert f"sweep {second!r} ended with exit code 1" in message and f"+sweep={second}" in message
    assert not (tmp_path / "report").exists()


@pytest.mark.slow
def test_report_refuses_mixed_code_versions(root, tmp_path):
    from rdsexp.experiment.store import Run
    runs = report.load_runs(root, "paper")
    other = json.loads(runs[0].record_file.read_text())
    other["code"]["version"] = "another"
    runs[0] = Run(runs[0].dir, other)
    with pytest.raises(report.LineageError, match="2 code versions"):
        report.check_versions(runs)
    assert report.check_versions(runs, allow_mixed=True).startswith("mixed:")


@pytest.mark.parametrize("change", [
    {"overrides": ["plant=dropout"], "summary": {"plant": "dropout", "model": "plant's own structure"}},
    {"overrides": ["enkf.q_scale=4"], "summary": {}},                  # changes what the figure shows
])
@pytest.mark.slow
def test_a_users_sweep_of_the_same_name_is_not_the_papers(root, tmp_path, change):
    """The report takes the shipped sweep's runs on the paper's plant, not the latest sweep of that name: a
    newer `+sweep=ensemble_size` of another plant, or with an override the sweep does not vary, is left out."""
    import shutil
    papers = report.load_runs(root, "ensemble_size")
    sweep = papers[0].dir.parent
    store = tmp_path / "outputs" / "sweeps"
    shutil.copytree(sweep, store / sweep.name)
    users = store / "9999-12-31_user"                       # newer than the paper's
    shutil.copytree(sweep, users)
    for run_json in users.glob("*/run.json"):
        info = json.loads(run_json.read_text())
        info["sweep"]["dir"] = str(users)
        info["overrides"] = info["overrides"] + change["overrides"]
        info["summary"] |= change["summary"]
        run_json.chmod(0o644)
        files.write_json(run_json, info)
    chosen = report.load_runs(tmp_path / "outputs", "ensemble_size")
    assert sorted(r.dir.name for r in chosen) == sorted(r.dir.name for r in papers)
    assert {r.dir.parent.name for r in chosen} == {sweep.name}
    assert len(report.load_runs(tmp_path / "outputs")) == 2 * len(papers)     # both stored, only one is the paper's


@pytest.mark.slow
def test_tampered_table_is_refused(root, tmp_path):
    import shutil
    run = report.load_runs(root, "paper")[0]
    copy = tmp_path / "copy"
    shutil.copytree(run.dir, copy)
    frame = pd.read_parquet(copy / "metrics.parquet")
    frame.loc[0, "rate"] = 0.5
    (copy / "metrics.parquet").chmod(0o644)               # stored read-only: an edit is deliberate
    frame.to_parquet(copy / "metrics.parquet", index=False)
    with pytest.raises(DamagedRecord, match="does not match the hash"):
        report.Run(copy).table("metrics")


@pytest.mark.slow
def test_figures_meet_the_print_requirements(root, written):
    """decay_*: one y-range, numbers in captions not titles, the lambda line names its lambda;
    gain_comparison: human labels in a legend outside the axes, the seed stated; sweeps: a diverged
    fraction under every panel; index.md: every figure and table, in the paper's order."""
    runs = report.load_runs(root, "paper")
    proposed = report.select(runs, gain__method="proposed")
    first = report.first_seed(runs)
    ylim = fig_decay.shared_ylim(first)
    figs = [fig_decay.draw(first, e, proposed, ylim) for e in ("closed_loop", "open_loop")]
    assert figs[0].axes[0].get_ylim() == figs[1].axes[0].get_ylim() == ylim
    for fig in figs:
        assert not any(ch.isdigit() for ch in fig.axes[0].get_title())
    lam = first.table("gains").query("selected")["lam"].iloc[0]
    assert any(f"= {lam:.4f}" in t.get_text() for t in figs[0].axes[0].get_legend().get_texts())
    for name in ("decay_proposed", "decay_open", "gain_comparison", "sweeps", "estimation"):
        assert (written / f"{name}.caption.md").read_text().strip(), name
    assert "0.8473" in (written / "decay_proposed.caption.md").read_text()
    summary = fig_gains.table(runs)
    fig = fig_gains.draw(runs, summary)
    legend = fig.legends[0] if fig.legends else fig.axes[0].get_legend()
    labels = [t.get_text() for t in legend.get_texts()]
    assert all(fig_gains.label(m) in labels for m in METHODS) and not any("_" in t for t in labels)
    fig.canvas.draw()
    for ax in fig.axes:                                            # every legend outside the data
        assert not ax.get_legend().get_window_extent().overlaps(ax.get_window_extent())
    assert "seed 0" in fig_gains.caption(runs, summary)
    sweeps = fig_sweeps.draw({name: report.load_runs(root, name) for name in ("ensemble_size", "noise", "window")})
    bottom = sweeps.axes[3:]
    assert len(bottom) == 3 and all(ax.get_lines() for ax in bottom)
    for ax in bottom:
        fractions = np.concatenate([line.get_ydata() for line in ax.get_lines()])
        assert np.all((fractions >= 0) & (fractions <= 1))
    page = (written / "index.md").read_text()
    drawn = [(kind, name) for kind, name, _ in paper.PAGE   # robust_width: only when its sweep is stored
             if (written / f"{name}.{'png' if kind == 'figure' else 'md'}").exists()]
    assert {name for kind, name, _ in paper.PAGE} - {name for _, name in drawn} == {"robust_width"}
    order = [f"![{name}]({name}.png)" if kind == "figure" else (written / f"{name}.md").read_text().strip()
             for kind, name in drawn]
    positions = [page.index(item) for item in order]
    assert positions == sorted(positions)


def test_report_uses_the_rate_window_the_run_resolved(tmp_path):
    """The config may give the window as fractions of the horizon (the default): the report reads
    the steps the run used, never the config's fractions."""
    small = [o for o in SMALL if not o.startswith("closed_loop.rate_window")]
    rdsexp(*small, "closed_loop.rate_window=[0.5,0.8]", "tracking.recording=false", cwd=tmp_path)
    (run,) = report.load_runs(tmp_path / "outputs")
    assert run.get("closed_loop.rate_window") == [0.5, 0.8] and run.rate_window == (15, 24)


SCRIPTS = ("closed_loop_rate", "fig_decay", "fig_estimation", "fig_filters", "fig_gains", "fig_online", "fig_sweeps",
           "identification_input", "reproduction_table", "robust_width")


@pytest.mark.slow
def test_report_scripts_without_stored_runs_end_with_one_line(tmp_path, capsys):
    """Every report script (paper.py runs missing sweeps; pole_sets needs none) on an empty store:
    exit code 1 and one line naming what is missing, never a traceback. Each script's main runs
    in this process through `report.script`, as its `__main__` does; one also as a script."""
    import importlib
    import subprocess
    argv = ["--root", str(tmp_path), "--out", str(tmp_path / "report")]
    for name in SCRIPTS:
        main = importlib.import_module(name).main
        with pytest.raises(SystemExit) as exit_:
            report.script(lambda main=main: main(argv))
        message = exit_.value.code
        assert isinstance(message, str) and "\n" not in message and "no stored" in message, (name, message)
        assert not capsys.readouterr().err, name
    proc = subprocess.run([sys.executable, str(REPO / "experiments" / f"{SCRIPTS[0]}.py"), *argv],
                          capture_output=True, text=True, timeout=120)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 1 and len(lines) == 1 and "no stored" in lines[0], proc.stderr
    assert not (tmp_path / "report").exists()


def test_stage_totals_count_each_computation_once():
    """paper.py's per-stage seconds: summed over the runs that computed; a reused copy (its original's
    timings) and the per-method breakdown of synthesis are not added."""
    from rdsexp.experiment.store import Run
    infos = [{"timings": {"synthesis": 2.0, "closed_loop": 1.0, "synthesis_by_method": {"a": 2.0}}, "seconds": 3.5},
             {"timings": {"synthesis": 0.5, "closed_loop": 3.0}, "seconds": 4.0},
             {"timings": {"synthesis": 2.0, "closed_loop": 1.0}, "seconds": 3.5, "reused_from": "x"}]
    totals = paper.stage_totals([Run(Path(f"/nowhere/{i}"), {"id": str(i), "status": "complete", **info})
                                 for i, info in enumerate(infos)])
    assert totals.to_dict() == {"closed_loop": 4.0, "synthesis": 2.5, "total": 7.5}


def test_a_report_refuses_to_pool_plant_contents_or_path_counts(tmp_path):
    """Runs of one plant name pooled as seeds must be one experiment: one plant content (plant_hash) and one
    path count, unless the figure varies the path count."""
    from rdsexp.errors import LineageError
    from rdsexp.experiment.store import Run

    def run(job, plant_hash, paths):
        d = tmp_path / f"r{job}"
        (d / ".hydra").mkdir(parents=True)
        (d / ".hydra" / "config.yaml").write_text(f"closed_loop:\n  paths: {paths}\nseed: {job}\n")
        return Run(d, {"id": d.name, "status": "complete", "summary": {"plant": "paper"}, "plant_hash": plant_hash})
    same = [run(0, "a" * 64, 40), run(1, "a" * 64, 40)]
    report.check_pooling(same)
    with pytest.raises(LineageError, match="plant paper with 2 different contents"):
        report.check_pooling([*same, run(2, "b" * 64, 40)])
    mixed = [*same, run(3, "a" * 64, 100)]
    with pytest.raises(LineageError, match=r"different path counts \(closed_loop.paths 100, 40\)"):
        report.check_pooling(mixed)
    report.check_pooling(mixed, keys=("closed_loop.paths", "seed"))
